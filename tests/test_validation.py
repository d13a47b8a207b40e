"""STEP1/STEP2-like validation sets: manifest, twins, WCS, truth conventions, star fields."""

from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS
from astropy.wcs.utils import proj_plane_pixel_scales

from pylensfit_validation.cli import simulate_main as main
from pylensfit_validation.validation import (
    STEP1_SHEARS,
    read_manifest,
    simulate_step,
)

galsim = pytest.importorskip("galsim")


@pytest.fixture(scope="module")
def step1(tmp_path_factory):
    d = simulate_step("step1", tmp_path_factory.mktemp("step1"), ngal=400, seed=3)
    return read_manifest(d)


@pytest.fixture(scope="module")
def step2(tmp_path_factory):
    d = simulate_step("step2", tmp_path_factory.mktemp("step2"), ngal=400, seed=5, n_shear=3)
    return read_manifest(d)


def _truth(path) -> Table:
    return Table.read(path, hdu="TRUTH")


def _shape_from_jac(jac: np.ndarray) -> complex:
    """e = (a - b) / (a + b) of a round profile transformed by ``jac``."""
    q = jac @ jac.T
    chi = complex(q[0, 0] - q[1, 1], 2 * q[0, 1]) / (q[0, 0] + q[1, 1])
    return chi / (1 + np.sqrt(1 - abs(chi) ** 2))


def test_step1_manifest(step1):
    man = step1
    assert man["kind"] == "step1" and len(man["psfs"]) >= 5
    shear = [f for f in man["fields"] if f["role"] == "shear"]
    prior = [f for f in man["fields"] if f["role"] == "prior"]
    assert sorted({f["g1"] for f in shear}) == sorted(STEP1_SHEARS)
    assert all(f["g2"] == 0.0 and not f["twin"] for f in shear)
    assert len(shear) == len(man["psfs"]) * len(STEP1_SHEARS)
    assert sorted(f["psf"] for f in prior) == list(range(len(man["psfs"])))
    assert all(f["g1"] == 0 and f["g2"] == 0 for f in prior)
    assert len(man["star_fields"]) == len(man["psfs"])
    assert man["star_field_size"] == man["field_size"]  # by default
    # round, elliptical along e1, along e2, larger
    p = man["psfs"]
    assert any(q["e1"] == 0 and q["e2"] == 0 for q in p)
    assert any(q["e1"] != 0 and q["e2"] == 0 for q in p)
    assert any(q["e1"] == 0 and q["e2"] != 0 for q in p)
    assert max(q["fwhm"] for q in p) > min(q["fwhm"] for q in p)
    # ngal is roughly the number of galaxies over the shear fields
    assert 0.5 * 400 < man["ngal_shear_fields"] < 2 * 400


@pytest.mark.parametrize("which,scale", [("step1", 0.206), ("step2", 0.2)])
def test_fits_wcs_and_truth(which, scale, request):
    man = request.getfixturevalue(which)
    for f, side in ([(f, man["field_size"]) for f in man["fields"][:3]]
                    + [(man["star_fields"][0], man["star_field_size"])]):  # fmt: skip
        with fits.open(f["path"]) as hdul:
            w = WCS(hdul[0].header)
            assert np.allclose(proj_plane_pixel_scales(w) * 3600, scale)
            assert hdul[0].data.shape == (side, side)
            assert "WEIGHT" in hdul and "TRUTH" in hdul


@pytest.mark.parametrize("which", ["step1", "step2"])
def test_truth_sheared_ellipticity(which, request):
    """Truth e = (e_s + g) / (1 + g* e_s), checked against GalSim's own composition."""
    man = request.getfixturevalue(which)
    f = max(man["fields"], key=lambda f: np.hypot(f["g1"], f["g2"]))
    t = _truth(f["path"])
    gal = t[~t["is_star"]]
    assert len(gal) > 0
    for row in gal[:10]:
        ei = (row["e1_int"], row["e2_int"])
        obj = galsim.Gaussian(sigma=1.0).shear(g1=ei[0], g2=ei[1]).shear(g1=f["g1"], g2=f["g2"])
        e = _shape_from_jac(obj.jac)
        assert e.real == pytest.approx(row["e1"], abs=1e-9)
        assert e.imag == pytest.approx(row["e2"], abs=1e-9)
    es = gal["e1_int"] + 1j * gal["e2_int"]
    g = complex(f["g1"], f["g2"])
    e = (es + g) / (1 + np.conj(g) * es)
    assert np.allclose(e.real, gal["e1"]) and np.allclose(e.imag, gal["e2"])


def test_step2_shears_and_twins(step2):
    man = step2
    assert man["kind"] == "step2" and len(man["psfs"]) >= 5
    assert sum(np.hypot(p["e1"], p["e2"]) >= 0.1 for p in man["psfs"]) >= 2
    shear = [f for f in man["fields"] if f["role"] == "shear"]
    prior = [f for f in man["fields"] if f["role"] == "prior"]
    assert sorted(f["psf"] for f in prior) == list(range(len(man["psfs"])))
    for f in shear:
        assert np.hypot(f["g1"], f["g2"]) <= 0.06 + 1e-12
        assert f["g1"] != 0 and f["g2"] != 0
    orig = {(f["psf"], f["shear_index"]): f for f in shear if not f["twin"]}
    twins = {(f["psf"], f["shear_index"]): f for f in shear if f["twin"]}
    assert orig.keys() == twins.keys() and len(orig) == 3 * len(man["psfs"])
    a, b = orig[(0, 0)], twins[(0, 0)]
    assert b["file"].endswith("_rot.fits") and (a["g1"], a["g2"]) == (b["g1"], b["g2"])
    ta, tb = _truth(a["path"]), _truth(b["path"])
    assert np.array_equal(ta["x"], tb["x"]) and np.array_equal(ta["y"], tb["y"])
    assert np.array_equal(ta["is_star"], tb["is_star"])
    assert np.allclose(tb["e1_int"], -ta["e1_int"]) and np.allclose(tb["e2_int"], -ta["e2_int"])
    assert np.allclose(ta["flux"], tb["flux"])
    assert set(ta["kind"][~ta["is_star"]]) <= {"sersic", "bulge+disc", "knots"}
    # the twin's galaxy really is the rotated one: shape from GalSim's transformation
    row = tb[~tb["is_star"]][0]
    e0 = (-row["e1_int"], -row["e2_int"])
    obj = (
        galsim.Gaussian(sigma=1.0)
        .shear(g1=e0[0], g2=e0[1])
        .rotate(90 * galsim.degrees)
        .shear(g1=b["g1"], g2=b["g2"])
    )
    e = _shape_from_jac(obj.jac)
    assert (e.real, e.imag) == pytest.approx((row["e1"], row["e2"]), abs=1e-9)
    # independent noise in the twins
    with fits.open(a["path"]) as ha, fits.open(b["path"]) as hb:
        assert not np.allclose(ha[0].data, hb[0].data)


def test_noise_twins(tmp_path):
    """``noise_twins=True``: every shear field has a twin with the same objects and the
    same noise field negated; nothing else changes, and the seeds of the other fields are
    those of the set without them, rendered in parallel or not."""
    from pylensfit_validation.validation import STEP2_PSFS

    kw = dict(ngal=240, seed=6, n_shear=1, psfs=STEP2_PSFS[:1], field_size=200)
    d = simulate_step("step2", tmp_path / "n", noise_twins=True, jobs=2, **kw)
    d0 = simulate_step("step2", tmp_path / "o", **kw)
    man, man0 = read_manifest(d), read_manifest(d0)
    shear = {f["file"]: f for f in man["fields"] if f["role"] == "shear"}
    assert sorted(shear) == ["psf0_g0.fits", "psf0_g0_neg.fits", "psf0_g0_rot.fits",
                             "psf0_g0_rot_neg.fits"]  # fmt: skip
    seeds0 = {f["file"]: (f["seed"], f["noise_seed"]) for f in man0["fields"]}
    for f in man["fields"]:
        assert f.get("noise_twin", False) == f["file"].endswith("_neg.fits")
        src = f["file"].replace("_neg", "")
        assert (f["seed"], f["noise_seed"]) == seeds0[src]
    sky, sigma = man["fieldspec"]["sky"], man["noise_sigma"]
    for a in ("psf0_g0.fits", "psf0_g0_rot.fits"):
        b = a.replace(".fits", "_neg.fits")
        ta, tb = _truth(d / a), _truth(d / b)
        for c in ta.colnames:
            x, y = np.asarray(ta[c]), np.asarray(tb[c])
            assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), c
        with fits.open(d / a) as ha, fits.open(d / b) as hb, fits.open(d0 / a) as h0:
            pa, pb = ha[0].data.astype(float), hb[0].data.astype(float)
            # the set without them (and rendered by one process): the same
            assert np.array_equal(ha[0].data, h0[0].data)
        half_diff, mean = (pa - pb) / 2, (pa + pb) / 2 - sky
        assert np.std(half_diff) == pytest.approx(sigma, rel=0.02)  # the noise, negated
        # the mean of the two has no noise: between the objects, nothing
        yy, xx = np.mgrid[: pa.shape[0], : pa.shape[1]]
        far = np.ones(pa.shape, bool)
        for x, y in zip(ta["x"], ta["y"], strict=True):
            far &= np.hypot(xx - x, yy - y) > 15
        assert far.sum() > 1000 and np.std(mean[far]) < 0.05 * sigma


def test_step1_twins(tmp_path):
    """``twins=True`` gives step1 rotated twins: same objects and flux, e_int flipped."""
    d = simulate_step("step1", tmp_path / "s1t", ngal=300, seed=4, n_shear=2, twins=True)
    man = read_manifest(d)
    shear = [f for f in man["fields"] if f["role"] == "shear"]
    assert len(shear) == 2 * 2 * len(man["psfs"])
    orig = {(f["psf"], f["shear_index"]): f for f in shear if not f["twin"]}
    twins = {(f["psf"], f["shear_index"]): f for f in shear if f["twin"]}
    assert orig.keys() == twins.keys()
    ta, tb = _truth(d / orig[(1, 1)]["file"]), _truth(d / twins[(1, 1)]["file"])
    gal = ~np.asarray(ta["is_star"])
    assert gal.sum() > 5 and np.array_equal(ta["x"], tb["x"])
    assert np.allclose(tb["e1_int"], -ta["e1_int"]) and np.allclose(tb["e2_int"], -ta["e2_int"])
    assert np.allclose(ta["flux"], tb["flux"], rtol=1e-6)  # the flux of the unlensed galaxy
    assert not np.allclose(ta["e1"][gal], tb["e1"][gal])


def _star_shape(path) -> complex:
    """HSM shape (reduced-shear convention) of the brightest star away from the edges."""
    t = _truth(path)
    with fits.open(path) as hdul:
        img = hdul[0].data.astype(np.float64) - 50.0  # sky of FieldSpec
    n = img.shape[0]
    ok = (t["x"] > 20) & (t["x"] < n - 21) & (t["y"] > 20) & (t["y"] < n - 21)
    row = t[ok][np.argmax(t["flux"][ok])]
    ix, iy = int(round(row["x"])), int(round(row["y"]))
    cut = img[iy - 16 : iy + 16, ix - 16 : ix + 16]
    m = galsim.hsm.FindAdaptiveMom(galsim.ImageD(cut, scale=1.0)).observed_shape
    return complex(m.g1, m.g2)


@pytest.mark.parametrize("which", ["step1", "step2"])
def test_star_fields_are_the_psf(which, request):
    man = request.getfixturevalue(which)
    for sf in man["star_fields"]:
        t = _truth(sf["path"])
        assert np.all(t["is_star"]) and np.all(t["e1"] == 0)
        p = sf["psf_params"]
        psf = galsim.Moffat(beta=p["beta"], fwhm=p["fwhm"]).shear(g1=p["e1"], g2=p["e2"])
        ref = galsim.hsm.FindAdaptiveMom(psf.drawImage(nx=32, ny=32, scale=1.0)).observed_shape
        e = _star_shape(sf["path"])
        assert abs(e - complex(ref.g1, ref.g2)) < 0.01
        assert abs(e - complex(p["e1"], p["e2"])) < 0.02  # pixel dilution aside


def test_cli_main(tmp_path, capsys):
    rc = main(["step1", "--out", str(tmp_path / "s"), "--ngal", "25", "--size", "120",
               "--nshear", "2", "--star-field-size", "150"])  # fmt: skip
    assert rc == 0
    man = read_manifest(tmp_path / "s")
    assert man["field_size"] == 120 and len(man["fields"]) == 5 * 3
    assert man["star_field_size"] == 150
    assert fits.getdata(man["star_fields"][0]["path"]).shape == (150, 150)
    assert "step1" in capsys.readouterr().out


def test_bad_kind(tmp_path):
    with pytest.raises(ValueError):
        simulate_step("step3", tmp_path)


def test_pylensfit_simulate_command(tmp_path):
    from pylensfit.cli import main as cli_main

    assert cli_main(["simulate", "step1", "--out", str(tmp_path / "s1"), "--ngal", "200"]) == 0
    man = read_manifest(tmp_path / "s1")
    assert man["kind"] == "step1" and len(man["fields"]) >= 5 * 6
    # a wider lattice: the same objects per field on fields 1.5 times the side
    assert cli_main(["simulate", "step1", "--out", str(tmp_path / "s2"), "--ngal", "200",
                     "--spacing", "60", "--quiet"]) == 0  # fmt: skip
    wide = read_manifest(tmp_path / "s2")
    assert wide["fieldspec"]["spacing"] == 60.0
    assert wide["field_size"] * 2 == man["field_size"] * 3


def test_fit_m_c_and_quality_factor():
    from pylensfit_validation.validation import fit_m_c, quality_factor

    rng = np.random.default_rng(3)
    gt = np.repeat([0.0, 0.005, 0.01, 0.05, 0.1], 40)
    err = np.full(gt.size, 2e-3)
    # exact line: recovered exactly; errors are the analytic weighted-least-squares ones
    m, m_err, c, c_err = fit_m_c(gt, gt * 1.02 + 3e-4, err)
    assert m == pytest.approx(0.02, abs=1e-12) and c == pytest.approx(3e-4, abs=1e-12)
    S, Sx, Sxx = gt.size / 4e-6, gt.sum() / 4e-6, (gt**2).sum() / 4e-6
    assert m_err == pytest.approx(np.sqrt(S / (S * Sxx - Sx**2)))
    assert c_err == pytest.approx(np.sqrt(Sxx / (S * Sxx - Sx**2)))
    # with noise, the pulls of many fits have unit spread
    pulls = []
    for _ in range(300):
        m, m_err, c, c_err = fit_m_c(gt, gt + err * rng.standard_normal(gt.size), err)
        pulls.append((m / m_err, c / c_err))
    assert np.std(pulls, axis=0) == pytest.approx([1, 1], abs=0.12)
    # only c when every true shear is the same
    m, _, c, c_err = fit_m_c(np.zeros(4), [1e-3, 3e-3, 1e-3, 3e-3], np.full(4, 1e-3))
    assert np.isnan(m) and c == pytest.approx(2e-3) and c_err == pytest.approx(5e-4)
    # Q: 1000 when the scatter is purely statistical, 250 when twice as large
    g_t = np.zeros((20000, 2))
    g_m = 1e-3 * rng.standard_normal((20000, 2))
    assert quality_factor(g_t, g_m, np.full((20000, 2), 1e-3)) == pytest.approx(1000, rel=0.03)
    assert quality_factor(g_t, 2 * g_m, np.full((20000, 2), 1e-3)) == pytest.approx(250, rel=0.03)


def test_validate_end_to_end(tmp_path):
    from pylensfit import CalibrationWarning
    from pylensfit_validation.validation import STEP1_PSFS, simulate_step, validate

    # three of the five PSFs (round, elliptical along e1 and along e2), with the fields of
    # a 1500-galaxy set
    d = simulate_step("step1", tmp_path / "s1", ngal=900, seed=4, psfs=STEP1_PSFS[:3])
    # a zero-shear field of ~30 galaxies is too few to estimate the priors from: each
    # falls back to its default with a warning, and the run goes on. This set's hold ~60
    # per PSF; it is measured with the flat size prior, to keep the test short
    tiny = simulate_step("step1", tmp_path / "s0", ngal=150, seed=5, psfs=STEP1_PSFS[:1],
                         prior_ngal=30)  # fmt: skip
    with pytest.warns(CalibrationWarning, match="falls back to its default"):
        small = validate(tiny, config=_flat(), progress=False, bins={})
    assert "fallbacks" in small.meta["priors"][0].info
    res = validate(d, config=_flat(), report=tmp_path / "report.md", progress=False)
    assert list(res["psf"]) == ["0", "1", "2", "all"]
    assert res["n_gal"][-1] > 600
    # a small set: m is known only to ~0.3, but it must be consistent with no bias
    assert abs(res["m1"][-1]) < 4 * res["m1_err"][-1]
    assert np.isnan(res["m2"][-1])  # step1 has g2 = 0: only c2 is measured
    assert abs(res["c2"][-1]) < 4 * res["c2_err"][-1]
    text = (tmp_path / "report.md").read_text()
    assert text.count("| ") > 5 and "## Diagnosis" in text
    for png in ("report.png", "report_mc.png", "report_bins.png", "report_prior.png"):
        assert (tmp_path / png).stat().st_size > 1000
        assert f"]({png})" in text
    # step1 has no twins: the fits use the single images
    assert res.meta["mode"] == "images" and res.meta["pairs"] is None
    assert res["n_gal"][-1] == res.meta["images"]["n"].sum()
    # bins of equal counts partition the galaxies (every usable galaxy has a magnitude, S/N)
    b = res.meta["bins"]
    assert "morphology" not in set(b["kind"])  # STEP1's galaxies have no kinds
    for kind in ("mag", "snr"):
        a = b[(b["kind"] == kind) & (b["psf"] == "all")]
        assert len(a) == 4 and a["n_gal"].sum() == res["n_gal"][-1]
        assert np.all(np.abs(a["n_gal"] - a["n_gal"].mean()) <= 0.05 * a["n_gal"].mean())
    # the recovered prior is compared with the truth's intrinsic ellipticities
    pc = res.meta["prior_check"]
    assert pc["n"] > 100 and np.isfinite(pc["rms_true"])
    # the stacked PSFs against GalSim's pixelised input PSFs, measured alike
    ps = res.meta["psf_check"]
    assert len(ps) == 3
    np.testing.assert_allclose(ps["fwhm_meas"], ps["fwhm_true"], rtol=0.02)
    assert np.max(np.abs(ps["e1_meas"] - ps["e1_true"])) < 0.005
    assert np.max(np.abs(ps["e2_meas"] - ps["e2_true"])) < 0.005
    assert set(res.meta["diagnosis"]) >= {"m", "sigma_c", "Q", "all_met"}
    assert res.meta["truth_control"] is False
    # the truth's shape noise taken out (the kept catalogues reused): every image's error
    # falls below two thirds of its plain one (S/N 15-150: the measurement noise is about
    # half the shape noise) and the estimates move by about their plain errors
    ctl = validate(d, config=_flat(), report=tmp_path / "ctl.md", progress=False, bins={},
                   truth_control=True)  # fmt: skip
    a, b = res.meta["images"], ctl.meta["images"]
    assert all(v["reused"] for v in ctl.meta["measured"].values())
    for i in (1, 2):
        assert np.all(b[f"g{i}_err"] < 0.67 * a[f"g{i}_err"])
        pull = (b[f"g{i}"] - a[f"g{i}"]) / a[f"g{i}_err"]
        assert np.all(np.abs(pull) < 4) and np.std(pull) > 0.3
    assert abs(ctl["m1"][-1]) < 4 * ctl["m1_err"][-1] and ctl["m1_err"][-1] < res["m1_err"][-1]
    assert ctl.meta["truth_control"] is True
    assert "truth's shape noise taken out" in (tmp_path / "ctl.md").read_text()


# ----------------------------------------------------------------------------------------
# Twins, bins, kept catalogues, report (issue: per-bin m/c, twins, quick tier)
# ----------------------------------------------------------------------------------------
def test_twin_shear_cancels_shape_noise():
    from pylensfit_validation.validation import twin_shear

    rng = np.random.default_rng(11)
    n, g = 500, np.array([0.031, -0.017])
    e_int = 0.3 * rng.standard_normal((n, 2))
    ones = np.ones((n, 2))
    # noise-free twins: e_b = -e_a + 2 g exactly -> the exact shear, zero error
    est = twin_shear(e_int + g, -e_int + g, ones, ones)
    assert (est.g1, est.g2) == pytest.approx(tuple(g), abs=1e-15)
    assert est.g1_err < 1e-14 and est.g2_err < 1e-14 and est.n == n
    # sensitivities divide as in eq-key2: responses of 0.8 scale e and s together
    est = twin_shear(0.8 * (e_int + g), 0.8 * (-e_int + g), 0.8 * ones, 0.8 * ones)
    assert (est.g1, est.g2) == pytest.approx(tuple(g), abs=1e-15)
    # with measurement noise: the error is that of the noise alone (pulls of unit spread),
    # far below the single-image error set by the shape noise
    pulls, ratio = [], []
    for _ in range(300):
        ea = e_int + g + 0.05 * rng.standard_normal((n, 2))
        eb = -e_int + g + 0.05 * rng.standard_normal((n, 2))
        est = twin_shear(ea, eb, ones, ones)
        pulls.append(((est.g1 - g[0]) / est.g1_err, (est.g2 - g[1]) / est.g2_err))
        single = np.std(ea[:, 0], ddof=1) / np.sqrt(n)
        ratio.append(est.g1_err / single)
    assert np.std(pulls, axis=0) == pytest.approx([1, 1], abs=0.12)
    assert np.mean(pulls, axis=0) == pytest.approx([0, 0], abs=0.2)
    # sigma_pair / sigma_single = (0.05 sqrt(2) / 2) / sqrt(0.3^2 + 0.05^2) ~ 0.116
    assert np.mean(ratio) == pytest.approx(0.05 / np.sqrt(2) / np.hypot(0.3, 0.05), rel=0.05)
    # non-finite rows are skipped; bad input raises
    ea = e_int + g
    ea[0] = np.nan
    assert twin_shear(ea, -e_int + g, ones, ones).n == n - 1
    with pytest.raises(ValueError):
        twin_shear(ea[:3], ea[:4], ones[:3], ones[:3])
    with pytest.raises(ValueError):
        twin_shear(e_int, -e_int, -ones, ones)


def test_group_shear_cancels_shape_and_noise():
    """Four renderings of each galaxy (rotated twin, noise twins): a linear response
    cancels both the intrinsic shape and the noise exactly; the grouping of a table of
    measured galaxies by truth index keeps only galaxies measured in every member."""
    from astropy.table import Table

    from pylensfit_validation.validation import group_members, group_shear, shear_groups

    rng = np.random.default_rng(12)
    n, g = 400, np.array([-0.022, 0.041])
    e_int = 0.3 * rng.standard_normal((n, 2))
    noise, noise_rot = 0.2 * rng.standard_normal((2, n, 2))
    e = np.stack([e_int + g + noise, e_int + g - noise,
                  -e_int + g + noise_rot, -e_int + g - noise_rot], axis=1)
    s = np.ones_like(e)
    est = group_shear(e, s)
    assert (est.g1, est.g2) == pytest.approx(tuple(g), abs=1e-15) and est.n == n
    assert est.g1_err < 1e-14 and est.g2_err < 1e-14
    # a quadratic response to the noise (noise bias) stays in the estimate and its error
    e2 = e + 0.5 * np.concatenate([noise, noise, noise_rot, noise_rot], axis=1).reshape(
        n, 4, 2) ** 2
    est = group_shear(e2, s)
    assert est.g1 - g[0] == pytest.approx(0.5 * np.mean(noise[:, 0] ** 2 + noise_rot[:, 0] ** 2)
                                          / 2, rel=1e-12)  # fmt: skip
    assert est.g1_err > 1e-4
    # the pair estimate is the group estimate of two members
    p = twin_shear_pair = group_shear(e[:, [0, 2]], s[:, [0, 2]])
    from pylensfit_validation.validation import twin_shear

    q = twin_shear(e[:, 0], e[:, 2], s[:, 0], s[:, 2])
    assert (p.g1, p.g2, p.g1_err, p.g2_err) == (q.g1, q.g2, q.g1_err, q.g2_err)
    assert twin_shear_pair.g1_err > 5 * est.g1_err  # the noise does not cancel in a pair
    with pytest.raises(ValueError):
        group_shear(e[:, :, 0], s[:, :, 0])
    # grouping: 2 PSF/shear keys with 4 members; galaxy 3 missing in one member of key A
    fields = {}
    for psf, j in [(0, 0), (1, 0)]:
        for rot in (False, True):
            for neg in (False, True):
                name = f"psf{psf}_g{j}" + ("_rot" if rot else "") + ("_neg" if neg else "")
                fields[name] = {"file": name, "role": "shear", "psf": psf, "shear_index": j,
                                "twin": rot, "noise_twin": neg}  # fmt: skip
    fields["psf0_prior"] = {"file": "psf0_prior", "role": "prior", "psf": 0,
                            "shear_index": None, "twin": False}  # fmt: skip
    rows = [(name, t) for name in fields for t in range(5)
            if not (name == "psf0_g0_rot_neg" and t == 3)]
    rows = [rows[i] for i in rng.permutation(len(rows))]
    gal = Table(rows=rows, names=("image", "truth_index"))
    gid, base = shear_groups(gal, fields)
    img, tix = np.asarray(gal["image"]), np.asarray(gal["truth_index"])
    assert np.all(gid[img == "psf0_prior"] == -1)
    assert np.all(gid[(tix == 3) & np.char.startswith(img.astype(str), "psf0")] == -1)
    assert np.sum(gid >= 0) == 4 * 4 + 4 * 5
    mem = group_members(gid)
    assert mem.shape == (9, 4)
    for r in mem:  # one galaxy, four renderings of one key, one base
        assert len(set(tix[r])) == 1 and len(set(img[r])) == 4 and len(set(base[r])) == 1
        assert base[r[0]] == img[r[0]].split("_rot")[0].split("_neg")[0]


def test_group_error_is_the_ratio_estimators():
    """The group error is the scatter of ``e - g s``: galaxies whose summed ellipticity
    is exactly their sensitivity times the shear carry no error however much their
    sensitivities differ (``std(e)`` would give ``g std(s) sqrt(N) / sum s``)."""
    from pylensfit_validation.validation import group_shear

    rng = np.random.default_rng(5)
    n, g = 300, np.array([0.1, -0.05])
    s = rng.uniform(0.6, 1.0, (n, 4, 2))
    est = group_shear(s * g, s)
    assert (est.g1, est.g2) == pytest.approx(tuple(g), abs=1e-15)
    assert est.g1_err < 1e-14 and est.g2_err < 1e-14
    # with noise in e the error is the noise's: pulls of unit spread
    pulls = []
    for _ in range(200):
        e = s * g + 0.05 * rng.standard_normal((n, 4, 2))
        est = group_shear(e, s)
        pulls.append(((est.g1 - g[0]) / est.g1_err, (est.g2 - g[1]) / est.g2_err))
    assert np.std(pulls, axis=0) == pytest.approx([1, 1], abs=0.12)


def _controlled_trials(rng, n_trials, select):
    """Plain and truth-controlled key2 estimates of single images of a population with
    shape noise and measurement noise."""
    from pylensfit.shear import apply_shear
    from pylensfit_validation.validation import truth_control_variate

    n_pop, g = 3000, np.array([0.04, -0.02])
    out = []
    for _ in range(n_trials):
        mod = np.abs(rng.normal(0.0, 0.3, n_pop)).clip(max=0.9)
        phi = rng.uniform(0.0, np.pi, n_pop)
        e1, e2 = apply_shear(mod * np.cos(2 * phi), mod * np.sin(2 * phi), *g)
        e_true = np.column_stack([e1, e2])
        # a response of 0.85; the sensitivities scatter about it galaxy by galaxy
        e = 0.85 * e_true + 0.1 * rng.standard_normal((n_pop, 2))
        resp = 0.85 + 0.05 * rng.standard_normal((n_pop, 1))
        keep = select(e_true, rng)
        row = []
        for i in range(2):
            ee, ss, tt = e[keep, i], resp[keep, 0], e_true[keep, i] - g[i]
            den = ss.sum()
            gh = ee.sum() / den
            r = ee - gh * ss
            err = np.std(r, ddof=1) * np.sqrt(r.size) / den
            delta, err_c = truth_control_variate(r, tt, e_true[:, i] - g[i], 1.0 / den)
            row.append((gh, err, gh - delta, err_c))
        out.append(row)
    return np.array(out), g  # (trials, component, [plain, err, controlled, err])


def test_truth_control_variate_takes_out_the_shape_noise():
    """The control variate keeps the estimate's expectation and takes the shape noise
    out of it, with errors that match the scatter over independent images; a twin
    group at g = 0 (``t`` zero) is left as it is."""
    from pylensfit_validation.validation import truth_control_variate

    rng = np.random.default_rng(21)
    a, g = _controlled_trials(rng, 150, lambda e, rng: rng.random(len(e)) < 0.7)
    for i in range(2):
        plain, err, ctl, err_c = a[:, i].T
        # both unbiased (the sensitivities' mean is the response)
        assert abs(plain.mean() - g[i]) < 4 * plain.std() / np.sqrt(len(plain))
        assert abs(ctl.mean() - g[i]) < 4 * ctl.std() / np.sqrt(len(ctl))
        # the shape noise goes (0.85 x 0.21 per component), the measurement noise (0.1)
        # stays, and so does the unmeasured 30 %'s share of the shape noise:
        # sqrt(0.1^2 + 0.3 (0.85 x 0.21)^2) / sqrt(0.1^2 + (0.85 x 0.21)^2) = 0.68
        assert ctl.std() / plain.std() == pytest.approx(0.68, rel=0.1)
        # the errors are the scatters (the lost galaxies' share of the population included)
        assert err.mean() == pytest.approx(plain.std(), rel=0.15)
        assert err_c.mean() == pytest.approx(ctl.std(), rel=0.15)
    # nothing to take out: t = 0 (a twin pair at g = 0)
    r = rng.standard_normal(100)
    assert truth_control_variate(r, np.zeros(100), np.zeros(120), 0.01) == pytest.approx(
        (0.0, np.std(r, ddof=1) * 10 * 0.01), rel=1e-12)  # fmt: skip


def test_truth_control_variate_keeps_what_a_selection_does():
    """Galaxies elongated along +x measured half as often: the plain estimate of g1 is
    biased, and the controlled one keeps the same bias (the population's mean, not the
    measured galaxies', is what it subtracts); g2 stays unbiased in both."""
    rng = np.random.default_rng(22)

    def select(e, rng):
        return (e[:, 0] < 0.2) | (rng.random(len(e)) < 0.5)

    a, g = _controlled_trials(rng, 100, select)
    plain, _, ctl, _ = a[:, 0].T
    n = len(plain)
    bias = plain.mean() - g[0]
    assert bias < -6 * plain.std() / np.sqrt(n)  # the selection's bias, resolved
    # the controlled estimate has the same expectation: its mean differs from the plain
    # one's by their difference's noise only
    assert abs(ctl.mean() - plain.mean()) < 3 * (ctl - plain).std() / np.sqrt(n)
    assert abs(ctl.mean() - g[0] - bias) < 0.2 * abs(bias)
    plain2, _, ctl2, _ = a[:, 1].T
    assert abs(ctl2.mean() - g[1]) < 4 * ctl2.std() / np.sqrt(n)


def test_bins_partition():
    from pylensfit_validation.validation import bin_index, quantile_edges

    rng = np.random.default_rng(2)
    v = rng.normal(size=1001)
    extra = rng.normal(size=300) * 2  # the prior fields' values widen the outer edges
    edges = quantile_edges(v, 4, extra)
    assert edges.size == 5 and np.all(np.diff(edges) > 0)
    assert edges[0] <= min(v.min(), extra.min()) and edges[-1] >= max(v.max(), extra.max())
    for x in (v, extra):
        idx = bin_index(x, edges)
        assert np.all(idx >= 0) and np.all(idx < 4)  # every value in exactly one bin
        for i in range(4):
            assert np.all((x[idx == i] >= edges[i]) & (x[idx == i] <= edges[i + 1]))
    assert np.bincount(bin_index(v, edges)) == pytest.approx([250, 250, 250, 251], abs=2)
    # the convention of BinnedPrior: half-open bins, the last one closed; NaN / outside -> -1
    e = np.array([0.0, 1.0, 2.0])
    assert list(bin_index(np.array([0.0, 0.5, 1.0, 2.0, 2.1, -1, np.nan]), e)) == [
        0, 0, 1, 1, -1, -1, -1,
    ]  # fmt: skip
    with pytest.raises(ValueError):
        quantile_edges(v, [0.0, 0.0, 1.0], extra)


def test_diagnosis_states():
    from astropy.table import Table

    from pylensfit_validation.validate import _diagnose
    from pylensfit_validation.validation import mc_summary

    def res(m, m_err, c, c_err, q):
        rows = [(str(k), m, m_err, c[k], c_err, m, m_err, -c[k], c_err, q, 100) for k in range(3)]
        rows.append(("all", m, m_err, 0.0, c_err, m, m_err, 0.0, c_err, q, 300))
        t = Table(rows=rows, names=("psf", "m1", "m1_err", "c1", "c1_err", "m2", "m2_err",
                                    "c2", "c2_err", "Q", "n_gal"))  # fmt: skip
        t.meta.update(mc_summary(t[:-1]))
        return t

    d = _diagnose(res(0.002, 0.001, [1e-5, -1e-5, 0.0], 1e-5, 500))
    assert d["all_met"] and d["m"][0] == "met" and d["Q"][0] == "met"
    # <m> = 0.008 +- 0.01 / sqrt(6) = 0.0041: within 1 sigma of the target
    d = _diagnose(res(0.008, 0.01, [1e-5, -1e-5, 0.0], 1e-5, 500))
    assert d["m"][0] == "met within error" and d["all_met"]
    d = _diagnose(res(0.008, 0.004, [1e-5, -1e-5, 0.0], 1e-5, 500))  # 0.008 +- 0.0016
    assert d["m"][0] == "not met" and not d["all_met"]
    d = _diagnose(res(0.02, 0.002, [3e-4, -3e-4, 0.0], 1e-5, 50))
    assert d["m"][0] == "not met" and d["Q"][0] == "not met" and not d["all_met"]
    assert d["sigma_c"][0] == "not met" and "more than noise" in d["sigma_c"][1]
    d = _diagnose(res(0.0, 0.05, [3e-4, -3e-4, 0.0], 5e-4, 500))
    assert "too small" in d["m"][1] and "consistent with noise" in d["sigma_c"][1]
    assert "chi-square of c over PSFs" in d["sigma_c"][1]


def test_c_scatter_coverage():
    """The spread of c over PSFs beyond its errors: the upper limit covers the true spread
    at its confidence, the estimate converges on many PSFs, and without a spread the
    chi-square's p is uniform."""
    from pylensfit_validation.validation import c_scatter

    rng = np.random.default_rng(5)
    err = np.array([1.5e-4, 2e-4, 2e-4, 2.5e-4, 3e-4])  # five PSFs, unequal errors
    n_sim, true = 2000, 3e-4
    below, p_small = 0, 0
    for _ in range(n_sim):
        c = 4e-4 + true * rng.standard_normal(5) + err * rng.standard_normal(5)
        below += c_scatter(c, err)["sigma_upper"] < true
        c0 = -2e-4 + err * rng.standard_normal(5)
        p_small += c_scatter(c0, err)["p"] < 0.05
    # binomial sd of a 5 % rate over 2000 draws: 0.5 %
    assert 0.035 < below / n_sim < 0.065
    assert 0.035 < p_small / n_sim < 0.065
    many = np.full(2000, 2e-4)
    r = c_scatter(true * rng.standard_normal(2000) + many * rng.standard_normal(2000), many)
    assert r["sigma_hat"] == pytest.approx(true, rel=0.08) and r["dof"] == 1999
    assert r["sigma_upper"] > r["sigma_hat"]
    # no spread beyond the errors: the estimate is 0; non-finite rows are skipped
    r = c_scatter([1e-4, 1e-4, 1e-4, np.nan], [2e-4, 2e-4, 2e-4, 2e-4])
    assert r["sigma_hat"] == 0.0 and r["sigma_upper"] == 0.0 and r["dof"] == 2
    assert np.isnan(c_scatter([1e-4], [1e-4])["chi2"])


def _flat():
    """``validate``'s default with the flat size prior: the small sets' zero-shear fields
    hold too few galaxies per PSF to estimate one."""
    from pylensfit.config import Config

    return Config.paper(model="bulge+disc", n_bulge_fractions=3)


def _exponential():
    """The flat size prior and one model, one bulge fraction: the pairing, bins and kept
    catalogues work alike for any model, and this one fits three times as fast."""
    from pylensfit.config import Config

    return Config.paper(model="exponential")


def test_validate_with_the_true_psf(tmp_path):
    from pylensfit_validation.validation import STEP1_PSFS, true_psf_image, validate

    d = simulate_step("step1", tmp_path / "s1", ngal=300, seed=6, psfs=STEP1_PSFS[1:3],
                      n_shear=2)  # fmt: skip
    cfg = _exponential()
    res = validate(d, config=cfg, true_psf=True, progress=False, bins={})
    assert res.meta["psf_source"] == "true"
    mdir = Path(d) / "measured_true_psf"
    assert all(Path(v["path"]).parent == mdir for v in res.meta["measured"].values())
    # each PSF's fields were fitted with its true image (at the largest stamp's size),
    # not with a stack of its stars
    from pylensfit.pipeline import read_catalogue

    for k, p in enumerate(STEP1_PSFS[1:3]):
        cat = read_catalogue(mdir / f"psf{k}_shear.fits")
        want = true_psf_image(p, cfg.largest_stamp)
        for img in cat.meta["psf_images"]:  # kept as float32
            np.testing.assert_allclose(img, want, rtol=1e-6, atol=1e-10)
        assert not np.any(cat["psf_star"])
        assert json.loads((mdir / f"psf{k}_shear.json").read_text())["psf"]
    # so the report's PSF check compares the true PSF with itself; e along e1 for PSF 1
    # (index 0 here) and along e2 for PSF 2, diluted by the pixel
    pc = res.meta["psf_check"]
    np.testing.assert_allclose(pc["e1_meas"], pc["e1_true"], atol=2e-5)
    np.testing.assert_allclose(pc["e2_meas"], pc["e2_true"], atol=2e-5)
    assert 0.04 < pc["e1_true"][0] < 0.05 and 0.04 < pc["e2_true"][1] < 0.05
    # the star-built run keeps its own catalogues
    res_s = validate(d, config=cfg, progress=False, bins={})
    assert res_s.meta["psf_source"] == "stars" and (Path(d) / "measured").is_dir()
    assert not any(v["reused"] for v in res_s.meta["measured"].values())
    # the same galaxies, fitted with nearly the same PSF: c agrees far inside its error
    for c in ("c1", "c2"):
        assert abs(res[c][-1] - res_s[c][-1]) < 0.5 * res[c + "_err"][-1]
    # the same true images given as PSF model files: the same fits, kept apart
    from pylensfit.psf import psf_from_image

    files = {}
    for k, p in enumerate(STEP1_PSFS[1:3]):
        files[k] = tmp_path / f"psf{k}.fits"
        psf_from_image(true_psf_image(p, cfg.largest_stamp)).write(files[k])
    res_f = validate(d, config=cfg, psf_models=files, progress=False, bins={})
    assert res_f.meta["psf_source"] == "models"
    assert all(Path(v["path"]).parent == Path(d) / "measured_psf_models"
               for v in res_f.meta["measured"].values())  # fmt: skip
    for c in ("m1", "c1", "m2", "c2"):
        np.testing.assert_allclose(res_f[c], res[c], rtol=0, atol=1e-7)
    with pytest.raises(ValueError, match=r"no file for PSF \[1\]"):
        validate(d, config=cfg, psf_models={0: files[0]}, progress=False, bins={})


def test_validate_with_the_true_psf_over_the_field(tmp_path):
    from pylensfit_validation.validate import _true_psf
    from pylensfit_validation.validation import STEP1_PSFS, validate

    d = simulate_step("step1", tmp_path / "v", ngal=300, seed=8, psfs=STEP1_PSFS[1:2],
                      n_shear=1, psf_variation="survey")  # fmt: skip
    man = read_manifest(d)
    cfg = _exponential()
    model = _true_psf(man, 0, cfg.largest_stamp)
    # the PSF at each object of a shear field is the truth's (its adaptive moments)
    t = Table.read(next(f["path"] for f in man["fields"] if f["role"] == "shear"),
                   hdu="TRUTH")  # fmt: skip
    e1, e2, _ = model.shape_at(t["x"], t["y"])
    assert np.max(np.abs(e1 - t["psf_e1_obs"])) < 1e-4
    assert np.max(np.abs(e2 - t["psf_e2_obs"])) < 1e-4
    assert np.ptp(e1) > 0.05  # and it varies
    res = validate(d, config=cfg, true_psf=True, progress=False, bins={})
    assert res.meta["psf_source"] == "true"
    for name in ("psf0_prior", "psf0_shear"):
        ident = json.loads((Path(d) / "measured_true_psf" / f"{name}.json").read_text())
        assert ident["psf"] == model.digest  # the galaxies were fitted with the map


@pytest.fixture(scope="module")
def step2_validated(step2):
    import warnings

    from pylensfit import CalibrationWarning
    from pylensfit_validation.validation import validate

    # on a STEP2 set validate adds a bin per galaxy kind to these; its zero-shear fields
    # hold ~15 galaxies per PSF, too few for the recipe's priors (their defaults are used,
    # with a warning; validate's own ellipticity prior pools the PSFs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)
        return validate(step2["dir"], config=_exponential(), progress=False,
                        bins={"mag": 2, "size": 2})  # fmt: skip


@pytest.mark.xdist_group("step2_validated")  # one worker validates the set
def test_validate_step2_twins_and_bins(step2, step2_validated):
    res = step2_validated
    m = res.meta
    assert m["mode"] == "pairs" and list(res["psf"]) == ["0", "1", "2", "3", "4", "all"]
    pairs, img = m["pairs"], m["images"]
    assert m["estimates"] is pairs
    n_psf, n_shear = len(step2["psfs"]), len(step2["shears"])
    assert len(pairs) == n_psf * n_shear and len(img) == 2 * n_psf * n_shear
    assert np.all(pairs["n"] >= 2 * pairs["n_pair"]) and pairs["n_pair"].sum() > 50
    # a pair is made of galaxies measured in both images; every usable detection of the
    # two images is in the estimate, paired or not (as a survey counts them)
    n_img = {str(r["file"]): r["n"] for r in img}
    for r in pairs:
        rot = str(r["file"]).replace(".fits", "_rot.fits")
        assert r["n_pair"] <= min(n_img[str(r["file"])], n_img[rot])
        assert r["n"] == n_img[str(r["file"])] + n_img[rot]
    # shape noise cancels: the pairs' errors are well below the single images'
    assert np.median(pairs["g1_err"]) < 0.7 * np.median(img["g1_err"])
    assert np.median(pairs["g2_err"]) < 0.7 * np.median(img["g2_err"])
    assert len(m["single"]) == len(res) and res["n_gal"][-1] == pairs["n"].sum()
    # bins partition the paired galaxies; the per-PSF rows add up to the "all" rows
    b = m["bins"]
    for kind in ("mag", "size"):
        t = b[b["kind"] == kind]
        a = t[t["psf"] == "all"]
        assert list(a["bin"]) == [0, 1]
        tot = a["n_gal"].sum()
        n_paired = 2 * pairs["n_pair"].sum()  # the bins hold the paired galaxies
        assert tot <= n_paired and (kind == "size" or tot == n_paired)
        for i in (0, 1):
            assert t[(t["bin"] == i) & (t["psf"] != "all")]["n_gal"].sum() == a["n_gal"][i]
        assert np.all(a["n_prior"] > 0)
    assert m["bin_edges"]["size"][0] > 0  # r / FWHM
    # one bin per STEP2 kind (Sersic, bulge+disc, knots; drawn 40/30/30 %), the galaxies'
    # kinds from the truth: together the truth-matched galaxies, as the size bins
    t = b[(b["kind"] == "morphology") & (b["psf"] == "all")]
    assert list(t["bin"]) == [0, 1, 2]
    n_size = b[(b["kind"] == "size") & (b["psf"] == "all")]["n_gal"].sum()
    assert t["n_gal"].sum() == n_size
    frac = t["n_gal"] / n_size
    assert np.all(np.abs(frac - [0.4, 0.3, 0.3]) < 0.1), frac
    assert set(m["measured"]) == {f"psf{k}_{r}" for k in range(n_psf) for r in ("prior", "shear")}
    assert not any(v["reused"] for v in m["measured"].values())


@pytest.mark.xdist_group("step2_validated")  # one worker validates the set
def test_validate_reuses_kept_catalogues(step2, step2_validated, monkeypatch):
    from pylensfit import pipeline
    from pylensfit.config import Config
    from pylensfit_validation.validation import validate

    def boom(*a, **k):
        raise AssertionError("measure called")

    monkeypatch.setattr(pipeline, "measure", boom)
    again = validate(step2["dir"], config=_exponential(), progress=False,
                     bins={"mag": 2, "size": 2})  # fmt: skip
    assert all(v["reused"] for v in again.meta["measured"].values())
    for c in ("m1", "c1", "m2", "c2", "Q", "n_gal"):
        assert np.array_equal(np.asarray(again[c]), np.asarray(step2_validated[c]), equal_nan=True)
    # a different configuration, or remeasure=True, measures again
    with pytest.raises(AssertionError, match="measure called"):
        validate(step2["dir"], progress=False, bins={},
                 config=Config.paper(model="bulge+disc", integration_refine=2))  # fmt: skip
    with pytest.raises(AssertionError, match="measure called"):
        validate(step2["dir"], config=_exponential(), progress=False, bins={}, remeasure=True)
    # so does a catalogue kept by a version of the code that measured differently
    from pylensfit_validation import estimates

    monkeypatch.setattr(estimates, "_MEASURE_VERSION", estimates._MEASURE_VERSION + 1)
    with pytest.raises(AssertionError, match="measure called"):
        validate(step2["dir"], config=_exponential(), progress=False, bins={})
    monkeypatch.undo()
    monkeypatch.setattr(pipeline, "measure", boom)
    # so does a field written again (a set simulated again with other parameters and the
    # same seeds): here a star field, whose PSF every catalogue of its PSF used
    star = Path(step2["star_fields"][0]["path"])
    st = star.stat()
    os.utime(star, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    try:
        with pytest.raises(AssertionError, match="measure called"):
            validate(step2["dir"], config=_exponential(), progress=False, bins={})
    finally:
        os.utime(star, ns=(st.st_atime_ns, st.st_mtime_ns))


def test_validate_takes_the_size_prior_from_the_zero_shear_field(tmp_path, monkeypatch):
    """With ``size_prior: estimated`` the size prior is estimated once per PSF, on the
    zero-shear field (as the ellipticity prior is), and the shear fields are measured
    with it: no second estimation pass over them, and the kept catalogues record it."""
    from pylensfit import pipeline
    from pylensfit.config import Config
    from pylensfit.prior import SizePrior
    from pylensfit_validation.validation import STEP2_PSFS, simulate_step, validate

    # two PSFs (the round one and the diagonal, highly elliptical one) with the fields of
    # a 1500-galaxy five-PSF set, about 150 galaxies each; one model, one bulge fraction:
    # the plumbing is the same for any model
    d = simulate_step("step2", tmp_path / "s2", ngal=600, seed=8, n_shear=1,
                      psfs=STEP2_PSFS[::4])  # fmt: skip
    n_psf = len(read_manifest(d)["psfs"])
    assert n_psf == 2
    calls = []
    real = pipeline.measure

    def spy(paths, **kw):
        given = kw.get("priors")
        calls.append((Path(paths[0]).name, None if given is None else given.size))
        return real(paths, **kw)

    monkeypatch.setattr(pipeline, "measure", spy)
    cfg = Config.paper(model="exponential", size_prior="estimated")
    res = validate(d, config=cfg, progress=False, bins={})
    assert len(calls) == 2 * n_psf and res["n_gal"][-1] > 100
    mdir = Path(d) / "measured"
    for k in range(n_psf):
        (prior_name, given_p), (shear_name, given_s) = calls[2 * k], calls[2 * k + 1]
        assert "prior" in prior_name and given_p is None  # estimated there
        assert "prior" not in shear_name
        sp = pipeline.read_catalogue(mdir / f"psf{k}_prior.fits").meta["size_prior"]
        assert isinstance(sp, SizePrior) and isinstance(given_s, SizePrior)
        np.testing.assert_array_equal(given_s.density, sp.density)
        kept = pipeline.read_catalogue(mdir / f"psf{k}_shear.fits").meta["size_prior"]
        np.testing.assert_array_equal(kept.density, sp.density)
        side = json.loads((mdir / f"psf{k}_shear.json").read_text())
        assert side["priors"]["size"] == sp.to_dict()
    # kept catalogues are reused, the size prior included
    calls.clear()
    validate(d, config=cfg, progress=False, bins={})
    assert calls == []


def test_validate_groups_noise_twins(tmp_path):
    """A set with noise twins: ``validate`` sums each galaxy's four renderings (image,
    rotated twin, and both with the noise negated), so that the shape noise and the
    noise's first order cancel: the group errors are a small fraction of the single
    images', and the report says how the renderings were grouped."""
    from pylensfit_validation.validation import STEP2_PSFS, validate

    d = simulate_step("step2", tmp_path / "s2n", ngal=800, seed=9, n_shear=1,
                      psfs=STEP2_PSFS[:1], noise_twins=True, jobs=2)  # fmt: skip
    res = validate(d, config=_exponential(), progress=False, bins={},
                   report=tmp_path / "report.md")  # fmt: skip
    m = res.meta
    groups, img = m["pairs"], m["images"]
    assert m["mode"] == "pairs" and len(groups) == 1 and len(img) == 4
    assert groups["n"][0] == img["n"].sum() >= 4 * groups["n_pair"][0]
    assert groups["n_pair"][0] > 50
    assert groups["n_pair"][0] <= img["n"].min()
    # a pair leaves the noise (0.7 of a single image's error at most, as above); a group
    # of four cancels its first order as well
    assert groups["g1_err"][0] < 0.3 * np.median(img["g1_err"])
    assert groups["g2_err"][0] < 0.3 * np.median(img["g2_err"])
    text = (tmp_path / "report.md").read_text()
    assert "image + rotated twin + noise twins" in text
    # the truth control on a group: the rotation left the shapes' second order only
    # (|g| <= 0.06), so it moves the estimate by a fraction of its error and the error
    # by a little
    ctl = validate(d, config=_exponential(), progress=False, bins={}, truth_control=True)
    c = ctl.meta["pairs"]
    for i in (1, 2):
        assert 0 < abs(c[f"g{i}"][0] - groups[f"g{i}"][0]) < groups[f"g{i}_err"][0]
        assert c[f"g{i}_err"][0] <= 1.001 * groups[f"g{i}_err"][0]


def test_step2_flux_does_not_follow_the_shear():
    """A STEP2 galaxy's flux is that of the unlensed galaxy: the same seed with opposite
    shears gives the same fluxes (the image differs), and the twin's too. When the flux
    came from the S/N of the lensed galaxy, galaxies sheared longer got brighter (by up
    to 0.6 % at g = 0.06: with the uniform amplitude prior, too little to move m)."""
    from pylensfit_validation.simulate import FieldSpec
    from pylensfit_validation.validation import render_step2_field

    base = FieldSpec(size=160, spacing=40.0, star_fraction=0.0)
    runs = [render_step2_field(replace(base, g1=g, g2=-g, rotate=rot), seed=7)
            for g, rot in ((0.05, False), (-0.05, False), (0.05, True))]  # fmt: skip
    (ia, _, ta), (ib, _, tb), (_, _, tc) = runs
    assert len(ta) >= 9 and not np.allclose(ia, ib)
    assert not np.allclose(ta["e1"], tb["e1"])
    np.testing.assert_allclose(tb["flux"], ta["flux"], rtol=1e-6)
    np.testing.assert_allclose(tc["flux"], ta["flux"], rtol=1e-6)


def test_truth_tables_are_read_once_per_file_version(tmp_path):
    """validate reads each field's TRUTH for the matching and the truth control: once,
    unless the file changes."""
    from pylensfit_validation import validation as V

    path = tmp_path / "f.fits"

    def write(e1):
        t = Table({"x": [1.0, 2.0], "e1": [e1, -e1]})
        fits.HDUList([fits.PrimaryHDU(), fits.table_to_hdu(t)]).writeto(path, overwrite=True)
        with fits.open(path, mode="update") as h:
            h[1].name = "TRUTH"

    write(0.1)
    a = V.read_truth(path)
    assert V.read_truth(str(path)) is a and a["e1"][0] == pytest.approx(0.1)
    write(0.25)  # a new version of the file (its size or time differs): read again
    st = os.stat(path)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    b = V.read_truth(path)
    assert b is not a and b["e1"][0] == pytest.approx(0.25)
