"""A PSF that varies over the field: the polynomial model in the pipeline."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from pylensfit import Config, Prior, measure
from pylensfit_validation.simulate import FieldSpec, simulate_field, write_field

SPEC = FieldSpec(size=1024, spacing=36, psf_variation="survey", psf_e1=0.0, psf_e2=0.0,
                 star_fraction=0.25, snr_range=(60.0, 200.0), size_range=(1.5, 2.5),
                 star_peak_snr=(80.0, 1000.0))  # fmt: skip
CFG = Config.paper(model="exponential", r_max=6.0, r_step=0.3, min_snr=0.0)


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    d = tmp_path_factory.mktemp("varying")
    img, w, truth = simulate_field(SPEC, seed=11)
    write_field(d / "f.fits", img, w, SPEC, truth=truth)
    return d / "f.fits", truth


def _matched(cat, truth):
    gal = ~np.asarray(truth["is_star"])
    t = truth[gal]
    dist, j = cKDTree(np.column_stack([cat["x"], cat["y"]])).query(
        np.column_stack([t["x"], t["y"]]), distance_upper_bound=2.0)
    ok = np.isfinite(dist)
    j = np.where(ok, j, 0)
    use = ok & (np.asarray(cat["flags"])[j] == 0) & (np.asarray(cat["fitclass"])[j] == 0)
    return t[use], cat[j[use]]


def _leakage(t, c):
    """Slope of the galaxies' shape error against the true PSF ellipticity (both
    components stacked) and its error."""
    x = np.concatenate([t["psf_e1_obs"], t["psf_e2_obs"]])
    y = np.concatenate([c["e1"] - t["e1"], c["e2"] - t["e2"]])
    A = np.column_stack([np.ones_like(x), x])
    coef, res, *_ = np.linalg.lstsq(A, y, rcond=None)
    s2 = float(res[0]) / (x.size - 2)
    return coef[1], np.sqrt(s2 * np.linalg.inv(A.T @ A)[1, 1])


@pytest.fixture(scope="module")
def poly(field):
    return measure([field[0]], config=CFG.replace(psf_model="polynomial", psf_order=2,
                                                  psf_cells=8),
                   prior=Prior(), progress=False)  # fmt: skip


def test_each_galaxy_is_fitted_with_the_psf_at_its_position(field, poly):
    path, truth = field
    const = measure([path], config=CFG, prior=Prior(), progress=False)
    t, c = _matched(poly, truth)
    assert len(t) > 250
    # the catalogue's PSF ellipticity follows the true map: interpolated between the
    # cells' corners (the default) to 7e-4 rms, where the cells' centres (128 px apart;
    # the map changes by up to ~0.01 across a cell) give 4e-3; the constant one is one
    # number
    d = np.concatenate([c["PSF_e1"] - t["psf_e1_obs"], c["PSF_e2"] - t["psf_e2_obs"]])
    assert np.sqrt(np.mean(d**2)) < 0.0015
    tc, cc = _matched(const, truth)
    assert np.ptp(np.asarray(cc["PSF_e1"])) < 1e-5  # (the sky frame turns by ~1e-3 deg)
    # the shape errors follow the PSF's with the constant PSF, not with the model
    a_const, s_const = _leakage(tc, cc)
    a_poly, s_poly = _leakage(t, c)
    assert a_const > 5 * s_const, (a_const, s_const)  # the uncorrected PSF shows through
    assert abs(a_poly) < 3 * s_poly and abs(a_poly) < 0.3 * abs(a_const), (a_poly, s_poly)
    # the PSFS table keeps the model's held-out check; the constant PSF has none
    held = poly.meta["psfs"][0]
    assert held["psf_heldout_n"] >= 5
    rms = np.hypot(held["psf_heldout_rms_de1"], held["psf_heldout_rms_de2"])
    assert 0 < rms < 0.01 and held["psf_heldout_noise_de"] > 0
    assert np.isnan(const.meta["psfs"][0]["psf_heldout_rms_de1"])


def test_fourier_fits_each_galaxy_once_with_the_psf_at_its_position(field, poly):
    """``psf_interpolation = "fourier"``: one fit per galaxy with the corners' PSFs mixed
    at its position; every row of the bilinear blend's catalogue, the same flags, and
    shapes within a small fraction of their noise of the blend's (the two differ at
    second order in the PSF's change across a cell)."""
    cfg = CFG.replace(psf_model="polynomial", psf_order=2, psf_cells=8,
                      psf_interpolation="fourier")  # fmt: skip
    cat = measure([field[0]], config=cfg, prior=Prior(), progress=False)
    assert len(cat) == len(poly)
    np.testing.assert_allclose(cat["x"], poly["x"], atol=0.1)  # the fitted centres
    np.testing.assert_allclose(cat["PSF_e1"], poly["PSF_e1"], atol=1e-6)
    ok = (np.asarray(cat["flags"]) == 0) & (np.asarray(poly["flags"]) == 0)
    assert ok.sum() > 250 and np.mean(np.asarray(cat["flags"]) == np.asarray(poly["flags"])) > 0.99
    de = np.concatenate([cat["e1"][ok] - poly["e1"][ok], cat["e2"][ok] - poly["e2"][ok]])
    assert np.all(np.isfinite(de)) and np.sqrt(np.mean(de**2)) < 2e-3, np.sqrt(np.mean(de**2))
    t, c = _matched(cat, truth=field[1])
    a, s = _leakage(t, c)
    assert abs(a) < 3 * s, (a, s)


def test_auto_fits_the_polynomial_only_where_the_stars_vary(field, poly, tmp_path):
    """``psf_model = "auto"`` (the default): on the varying field the polynomial model's
    catalogue; on a field of the map's central PSF everywhere, the stacked PSF's."""
    auto = CFG.replace(psf_model="auto", psf_order=2, psf_cells=8)
    cat = measure([field[0]], config=auto, prior=Prior(), progress=False)
    np.testing.assert_array_equal(cat["e1"], poly["e1"])
    np.testing.assert_array_equal(cat["PSF_e2"], poly["PSF_e2"])
    assert cat.meta["psfs"][0]["psf_heldout_n"] >= 5
    spec = replace(SPEC, size=512, psf_variation="none")
    img, w, truth = simulate_field(spec, seed=12)
    write_field(tmp_path / "c.fits", img, w, spec, truth=truth)
    assert int(np.sum(truth["is_star"])) >= 30  # enough for order 2
    cat = measure([tmp_path / "c.fits"], config=auto, prior=Prior(), progress=False)
    const = measure([tmp_path / "c.fits"], config=CFG, prior=Prior(), progress=False)
    np.testing.assert_array_equal(cat["e1"], const["e1"])
    assert np.isnan(cat.meta["psfs"][0]["psf_heldout_rms_de1"])  # no model over the field


def test_heldout_residuals_are_pooled_over_images():
    """validate's PSF table pools the images' distinct held-out checks as
    sqrt(sum n x^2 / sum n)."""
    from astropy.table import Table, vstack

    from pylensfit_validation.validate import _heldout_pooled

    p = Table({"psf_heldout_n": [10, 30, 0], "psf_heldout_rms_de1": [3e-3, 1e-3, np.nan],
               "psf_heldout_rms_de2": [2e-3, 2e-3, np.nan],
               "psf_heldout_noise_de": [1e-3, 1e-3, np.nan]})  # fmt: skip
    n, r1, r2, noise, x1, x2 = _heldout_pooled(p)
    assert n == 40
    assert r1 == pytest.approx(np.sqrt((10 * 9e-6 + 30 * 1e-6) / 40))
    assert r2 == pytest.approx(2e-3) and noise == pytest.approx(1e-3)
    assert x1 == pytest.approx(np.sqrt(r1**2 - 1e-6)) and x2 == pytest.approx(np.sqrt(3e-6))
    # images measured with one model repeat its check: counted once
    assert _heldout_pooled(vstack([p, p[:2], p[1:2]])) == (n, r1, r2, noise, x1, x2)
    assert _heldout_pooled(Table({"psf_n_used": [3]}))[0] == 0  # an older catalogue


def test_a_piff_model_fitted_to_the_same_stars(field, tmp_path):
    """The same with a Piff model (PixelGrid, quadratic in the position) that Piff fits
    to the field's stars, given to ``measure`` as its file."""
    pytest.importorskip("piff")
    from astropy.io import fits

    from pylensfit.psfmodel import fit_piff

    path, truth = field
    image = fits.getdata(path).astype(float) - SPEC.sky
    st = truth[np.asarray(truth["is_star"])]
    fit_piff(image, np.asarray(st["x"]), np.asarray(st["y"]), tmp_path / "field.piff",
             noise_sigma=SPEC.noise_sigma, order=2)  # fmt: skip
    cat = measure([path], psf=tmp_path / "field.piff", config=CFG, prior=Prior(),
                  progress=False)  # fmt: skip
    t, c = _matched(cat, truth)
    assert len(t) > 250
    d = np.concatenate([c["PSF_e1"] - t["psf_e1_obs"], c["PSF_e2"] - t["psf_e2_obs"]])
    assert np.sqrt(np.mean(d**2)) < 0.006
    a, s = _leakage(t, c)
    assert abs(a) < 3 * s, (a, s)
