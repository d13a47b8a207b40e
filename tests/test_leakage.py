"""PSF leakage alpha (``g = c + alpha e_psf``): recovered with the right error from
synthetic shapes, and reported by ``validate`` in the sky frame of a rotated, flipped set
with a PSF varying over the field."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from pylensfit_validation.validation import psf_leakage

ALPHA = (0.12, -0.06)
C = (1e-3, -2e-3)


def _sample(rng, n=4000, sigma=0.25, heteroscedastic=False):
    """Shapes ``e_i = s_i (c_i + alpha_i e_psf,i) + noise`` at PSF ellipticities spread
    as a survey's, and the inverse-variance weights of their noise."""
    psf = rng.uniform(-0.08, 0.08, (n, 2))
    sens = rng.uniform(0.6, 0.9, (n, 2))
    sig = rng.uniform(0.1, 0.45, n) if heteroscedastic else np.full(n, sigma)
    g = np.asarray(C) + np.asarray(ALPHA) * psf
    e = sens * g + sig[:, None] * rng.standard_normal((n, 2))
    return e, sens, psf, 1.0 / sig**2


def _fit(e, sens, psf, **kw):
    return psf_leakage(e[:, 0], e[:, 1], sens[:, 0], sens[:, 1], psf[:, 0], psf[:, 1], **kw)


def test_one_sample_recovers_alpha_and_c():
    e, sens, psf, _ = _sample(np.random.default_rng(1))
    res = _fit(e, sens, psf)
    for i in (1, 2):
        assert abs(res[f"alpha{i}"] - ALPHA[i - 1]) < 3 * res[f"alpha{i}_err"]
        assert abs(res[f"c{i}"] - C[i - 1]) < 3 * res[f"c{i}_err"]
        # shape noise 0.25 over 4000 galaxies with sens ~0.75 and e_psf spread 0.046 rms:
        # sigma(alpha) ~ 0.25 / 0.75 / sqrt(4000) / 0.046 ~ 0.11
        assert 0.08 < res[f"alpha{i}_err"] < 0.15
        assert res[f"n{i}"] == 4000 and res[f"dof_{i}"] == 6
    b = res["bins"]
    assert len(b) == 16 and set(b["component"]) == {1, 2}
    for i in (1, 2):
        bi = b[b["component"] == i]
        assert bi["n"].sum() == 4000 and np.all(np.diff(bi["psf_e"]) > 0)
        assert np.all((bi["psf_e"] >= bi["lo"]) & (bi["psf_e"] <= bi["hi"]))


@pytest.mark.parametrize("weighted", [False, True])
def test_alpha_errors_are_right_over_many_samples(weighted):
    """The pulls ``(alpha - alpha_true) / alpha_err`` (and c's) over 300 samples have mean
    0 and unit spread, and the fits' chi-square its degrees of freedom: the bins' errors
    from the scatter are the errors of their means. With inverse-variance weights the
    errors are smaller than without, on heteroscedastic noise."""
    rng = np.random.default_rng(20260)
    pulls = {k: [] for k in ("alpha1", "alpha2", "c1", "c2")}
    chi2, err_w, err_u = [], [], []
    for _ in range(300):
        e, sens, psf, w = _sample(rng, n=2000, heteroscedastic=weighted)
        res = _fit(e, sens, psf, weights=w if weighted else None)
        for k in pulls:
            true = ALPHA[int(k[-1]) - 1] if k.startswith("alpha") else C[int(k[-1]) - 1]
            pulls[k].append((res[k] - true) / res[f"{k}_err"])
        chi2 += [res["chi2_1"] / res["dof_1"], res["chi2_2"] / res["dof_2"]]
        if weighted:
            err_w.append(res["alpha1_err"])
            err_u.append(_fit(e, sens, psf)["alpha1_err"])
    for k, p in pulls.items():
        p = np.asarray(p)
        # 300 pulls: the mean is known to 0.06, the spread to 0.04
        assert abs(p.mean()) < 0.2, (k, p.mean())
        assert 0.87 < p.std() < 1.13, (k, p.std())
    assert abs(np.mean(chi2) - 1.0) < 0.12  # chi2/dof on 6 dof over 600 fits: +-0.035
    if weighted:
        assert np.median(np.asarray(err_w) / np.asarray(err_u)) < 0.8


def test_a_constant_psf_gives_only_c():
    """A PSF constant over the sample (or varying by less than ``min_spread``) measures
    no alpha: c is the mean shear. A few distinct PSFs are one bin each."""
    rng = np.random.default_rng(3)
    e, sens, psf, _ = _sample(rng, n=3000)
    flat = np.full_like(psf, 0.03) + 1e-7 * rng.standard_normal(psf.shape)
    res = _fit(e, sens, flat)
    for i in (1, 2):
        assert np.isnan(res[f"alpha{i}"]) and np.isnan(res[f"alpha{i}_err"])
        g = e[:, i - 1].sum() / sens[:, i - 1].sum()
        assert abs(res[f"c{i}"] - g) < 0.05 * res[f"c{i}_err"]
    # three PSFs: three bins per component, at their values, and alpha from them
    three = np.array([-0.05, 0.0, 0.05])[rng.integers(0, 3, psf.shape)]
    e3 = sens * (np.asarray(C) + np.asarray(ALPHA) * three) + 0.25 * rng.standard_normal(e.shape)
    res = _fit(e3, sens, three)
    b = res["bins"]
    assert len(b) == 6 and np.all(b["lo"] == b["hi"])
    np.testing.assert_allclose(b["psf_e"], np.tile([-0.05, 0.0, 0.05], 2), atol=1e-15)
    for i in (1, 2):
        assert abs(res[f"alpha{i}"] - ALPHA[i - 1]) < 3 * res[f"alpha{i}_err"]
        assert res[f"dof_{i}"] == 1


def test_bad_inputs():
    e, sens, psf, w = _sample(np.random.default_rng(4), n=100)
    with pytest.raises(ValueError, match="one value per galaxy"):
        psf_leakage(e[:, 0], e[:-1, 1], sens[:, 0], sens[:, 1], psf[:, 0], psf[:, 1])
    with pytest.raises(ValueError, match="n_bins"):
        _fit(e, sens, psf, n_bins=0)
    # rows of zero weight or non-finite values are skipped
    e[:10, 0] = np.nan
    w[10:20] = 0.0
    res = _fit(e, sens, psf, weights=w)
    assert res["n1"] == 80 and res["n2"] == 90
    empty = _fit(e[:0], sens[:0], psf[:0])
    assert np.isnan(empty["alpha1"]) and np.isnan(empty["c1"]) and len(empty["bins"]) == 0


def test_validate_in_the_sky_frame_with_a_varying_psf(tmp_path):
    """``validate`` on a set whose WCS is rotated by 35 degrees and flipped, with the
    'survey' PSF variation: the shapes from the pixel-frame lnL grids are compared with
    the sky-frame shears and truth, so m1 is the model's bias (the exponential model on
    bulge+disc galaxies: about -0.15 on the plain WCS for this seed), not the
    ``cos(70 deg) - 1 ~ -0.66`` of a frame left pixel; and the PSF leakage with the true
    PSF is that of a PSF model constant over the field, ~0.7-0.8 in both components on
    the plain WCS too."""
    pytest.importorskip("galsim")
    from pylensfit import CalibrationWarning
    from pylensfit.config import Config
    from pylensfit_validation.validation import STEP1_PSFS, simulate_step, validate

    d = simulate_step("step1", tmp_path / "s", ngal=600, seed=11, psfs=STEP1_PSFS[1:2],
                      n_shear=5, twins=True, psf_variation="survey", wcs_rotation_deg=35.0,
                      wcs_flip=True)  # fmt: skip
    with warnings.catch_warnings():  # a small zero-shear field: the priors' defaults
        warnings.simplefilter("ignore", CalibrationWarning)
        res = validate(d, config=Config.paper(model="exponential"), progress=False, bins={},
                       estimator="key2", report=tmp_path / "report.md")  # fmt: skip
    assert res.meta["mode"] == "pairs" and res["n_gal"][-1] > 500
    m1, m1_err = res["m1"][-1], res["m1_err"][-1]
    assert m1_err < 0.15 and abs(m1 + 0.15) < 3 * m1_err, (m1, m1_err)
    lk = res.meta["leakage"]
    assert list(lk["psf"]) == ["0", "all", "0", "all"]
    assert list(lk["source"]) == ["truth", "truth", "model", "model"]
    t = lk[(lk["source"] == "truth") & (lk["psf"] == "0")][0]
    for i in (1, 2):
        assert t[f"alpha{i}_err"] < 0.25 and 0.2 < t[f"alpha{i}"] < 1.5, t
    assert t["n"] > 250  # twin groups
    text = (tmp_path / "report.md").read_text()
    assert "PSF leakage (g = c + alpha e_psf, sky frame) with the true PSF" in text
    assert "with the catalogue's model PSF" in text
