"""Field-varying PSF models (pylensfit.psfmodel), checked against GalSim renderings.

The star field's Moffat PSF varies with survey-like gradients: ``e = 0.04 (u + i v)^2``
(``|e|`` from 0 at the centre to 0.08 in the corners) and FWHM ``3 (1 + 0.1 (u + v) / 2)``
pixels, ``u, v in [-1, 1]`` across the image.
"""

import dataclasses
import inspect
import logging
import sys

import galsim
import numpy as np
import pytest

from pylensfit.psf import REASONS, PSFError, PSFResult, StarChecks, stack_psf
from pylensfit.psf.fourier import gaussian_peak, pad_to
from pylensfit.psfmodel import (
    ConstantPSF,
    PiffNotInstalledError,
    PiffPSF,
    PolynomialPSF,
    n_terms,
    read_psf_model,
)

NF = 1536  # side of the star field
SIGMA = 1.0  # pixel noise
SIZE = 32


def true_psf(x, y, n=NF):
    """The field's PSF at 0-based pixel (x, y), without the pixel response."""
    u, v = 2.0 * x / (n - 1) - 1.0, 2.0 * y / (n - 1) - 1.0
    e = 0.04 * (u + 1j * v) ** 2
    fwhm = 3.0 * (1.0 + 0.1 * (u + v) / 2.0)
    return galsim.Moffat(beta=3.5, fwhm=fwhm).shear(g1=e.real, g2=e.imag)


def render(objects, n=NF, seed=1):
    """Draw ``(profile, x, y, flux)`` objects (with the pixel) on an ``n x n`` image plus noise.

    0-based positions, pixel centres on integers: GalSim (x, y) == numpy [y, x].
    """
    img = galsim.ImageD(n, n, scale=1.0)
    img.setOrigin(0, 0)
    for prof, x, y, flux in objects:
        b = galsim.BoundsI(int(x) - 24, int(x) + 24, int(y) - 24, int(y) + 24) & img.bounds
        prof.withFlux(flux).drawImage(
            image=img[b], add_to_image=True, center=galsim.PositionD(x, y)
        )
    return img.array + np.random.default_rng(seed + 1000).normal(0.0, SIGMA, (n, n))


def peak_flux(prof, peak_snr):
    """Total flux giving a peak pixel of ``peak_snr * SIGMA`` (object on a pixel centre)."""
    return peak_snr * SIGMA / prof.drawImage(nx=1, ny=1, scale=1.0).array[0, 0]


def make_field(n_star=300, n_gal=8, seed=1):
    """Stars (peak S/N 50-1000, log-uniform) and bright small galaxies on a jittered grid."""
    rng = np.random.default_rng(seed)
    g = np.arange(40, NF - 40, 60)
    gx, gy = np.meshgrid(g, g)
    sel = rng.choice(gx.size, n_star + n_gal, replace=False)
    xs = gx.ravel()[sel] + rng.uniform(-8, 8, sel.size)
    ys = gy.ravel()[sel] + rng.uniform(-8, 8, sel.size)
    snr = np.exp(rng.uniform(np.log(50.0), np.log(1000.0), sel.size))
    objects = []
    for i, (x, y, s) in enumerate(zip(xs, ys, snr, strict=True)):
        prof = true_psf(x, y)
        if i >= n_star:  # exponential, r_half 1.5 px, peak S/N 300-1000
            prof = galsim.Convolve(galsim.Exponential(half_light_radius=1.5), prof)
            s = 300.0 + 700.0 * (i - n_star) / max(n_gal - 1, 1)
        objects.append((prof, x, y, peak_flux(prof, s)))
    image = render(objects, seed=seed)
    return {"image": image, "x": xs[:n_star], "y": ys[:n_star], "gx": xs[n_star:],
            "gy": ys[n_star:], "snr": snr[:n_star]}  # fmt: skip


def truth_moments(x, y):
    """Adaptive moments (e1, e2, sigma) of the true pixel-convolved PSF at the positions."""
    out = []
    for xi, yi in zip(x, y, strict=True):
        img = true_psf(xi, yi).drawImage(nx=SIZE, ny=SIZE, scale=1.0, offset=(0.5, 0.5))
        m = galsim.hsm.FindAdaptiveMom(img)
        out.append((m.observed_shape.g1, m.observed_shape.g2, m.moments_sigma))
    return np.array(out).T


def rms(a):
    return float(np.sqrt(np.mean(np.square(a))))


def truth_residuals(model, probe):
    e1, e2, sig = model.shape_at(probe["x"], probe["y"])
    t1, t2, ts = probe["truth"]
    return rms(e1 - t1), rms(e2 - t2), rms(sig / ts - 1.0)


def gaussian_centre(images, sigma=2.0):
    """Offset of the Gaussian cross-correlation peak from [size//2, size//2] (pixels)."""
    from pylensfit.psfmodel.basis import phase as _phase  # a helper of the models

    images = np.atleast_3d(images).reshape(-1, *np.shape(images)[-2:])
    big = images.shape[-1] + 9
    D = np.fft.rfft2(pad_to(images, big)) * _phase(big)[None]
    z = np.zeros(len(images))
    X, Y, ok = gaussian_peak(D, sigma, z, z, 2.0)
    assert ok.all()
    return X, Y


@pytest.fixture(scope="module")
def field():
    return make_field()


@pytest.fixture(scope="module")
def probe(field):
    """50 random positions away from the stars, and the truth's moments there."""
    rng = np.random.default_rng(11)
    px, py = [], []
    while len(px) < 50:
        x, y = rng.uniform(40, NF - 40, 2)
        if np.min(np.hypot(field["x"] - x, field["y"] - y)) > 15:
            px.append(x)
            py.append(y)
    px, py = np.array(px), np.array(py)
    return {"x": px, "y": py, "truth": truth_moments(px, py)}


@pytest.fixture(scope="module")
def catalogue(field):
    """Catalogue positions good to ~0.3 px, as from a detection catalogue."""
    j = np.random.default_rng(7).normal(0.0, 0.3, (2, field["x"].size))
    return field["x"] + j[0], field["y"] + j[1]


@pytest.fixture(scope="module")
def poly(field, catalogue):
    return PolynomialPSF.fit(field["image"], *catalogue, noise_sigma=SIGMA, order=2)


# ---------------------------------------------------------------------------------------
# The polynomial model
# ---------------------------------------------------------------------------------------
def test_polynomial_matches_the_varying_psf_and_a_constant_does_not(field, catalogue, poly,
                                                                    probe):  # fmt: skip
    d = poly.diagnostics
    assert (d["order"], d["n_terms"], d["n_stars"]) == (2, 6, 300)
    assert d["n_used"] >= 297
    r1, r2, rs = truth_residuals(poly, probe)
    # measured: 6.2e-4, 9.2e-4, size 2.0e-4. Most of it is the order-2 floor (7e-4, 8e-4
    # without noise): the pixels of this pixel-convolved PSF are not exactly quadratic
    # in position (its size varies too, and the pixel dilutes e by an amount that
    # depends on the size), so the bound of 1e-3 has a thin margin.
    assert r1 < 1e-3 and r2 < 1e-3
    assert rs < 5e-3
    # the constant stack of the same stars cannot follow the pattern (measured 0.013, 0.027)
    stack = ConstantPSF(stack_psf(field["image"], *catalogue, noise_sigma=SIGMA, max_chi2=None))
    c1, c2, _ = truth_residuals(stack, probe)
    assert c1 > 3e-3 and c2 > 3e-3
    # a cubic takes the floor away (measured 2.9e-4, 1.5e-4): the residual above is the
    # polynomial's degree, not the method
    cubic = PolynomialPSF.fit(field["image"], *catalogue, noise_sigma=SIGMA, order=3, holdout=0)
    q1, q2, _ = truth_residuals(cubic, probe)
    assert q1 < 5e-4 and q2 < 5e-4


def test_draw_convention(poly, probe):
    imgs = poly.draw(probe["x"], probe["y"])
    assert imgs.shape == (50, SIZE, SIZE) and imgs.dtype == np.float64
    np.testing.assert_allclose(imgs.sum(axis=(1, 2)), 1.0, atol=1e-12)
    X, Y = gaussian_centre(imgs)
    assert np.max(np.hypot(X, Y)) < 1e-6
    one = poly.draw(probe["x"][3], probe["y"][3])
    assert one.shape == (SIZE, SIZE)
    np.testing.assert_allclose(one, imgs[3], rtol=0, atol=1e-15)
    e1, e2, sig = poly.shape_at(probe["x"][3], probe["y"][3])
    assert e1.shape == e2.shape == sig.shape == (1,)
    assert poly.draw(np.zeros(0), np.zeros(0)).shape == (0, SIZE, SIZE)
    with pytest.raises(ValueError, match="equal length"):
        poly.draw(np.zeros(2), np.zeros(3))
    # the field centre as a PSFResult, its noise from the fit's covariance
    c = poly.centre
    assert isinstance(c, PSFResult) and c.size == SIZE
    np.testing.assert_allclose(c.image, poly.draw(767.5, 767.5), atol=1e-15)
    assert 0 < c.pixel_noise < 1e-4 and c.n_used == poly.diagnostics["n_used"]
    assert abs(c.e1) < 0.005 and abs(c.e2) < 0.005  # e = 0 at the centre


def test_star_table(poly, field):
    t = poly.stars
    for col in ("x", "y", "flux", "snr", "chi2", "used", "reason", "heldout", "e1_star",
                "e2_star", "e1_model", "e2_model"):  # fmt: skip
        assert col in t.colnames
    used = np.asarray(t["used"])
    assert np.all(np.asarray(t["reason"])[used] == "")
    # measured centres within 0.02 px of the truth (catalogue jitter 0.3 px)
    dx = np.asarray(t["x"])[used] - field["x"][used]
    dy = np.asarray(t["y"])[used] - field["y"][used]
    assert rms(dx) < 0.02 and rms(dy) < 0.02
    assert np.median(np.asarray(t["chi2"])[used]) == pytest.approx(1.0, abs=0.25)
    snr_true = np.asarray(t["snr"])[used] / field["snr"][used]  # matched / peak S/N
    assert np.std(snr_true) / np.mean(snr_true) < 0.15


def test_galaxies_in_the_star_list_are_rejected(field, probe):
    x = np.concatenate([field["x"], field["gx"]])
    y = np.concatenate([field["y"], field["gy"]])
    model = PolynomialPSF.fit(field["image"], x, y, noise_sigma=SIGMA, order=2)
    t = model.stars
    gal = np.arange(x.size) >= field["x"].size
    assert not np.asarray(t["used"])[gal].any()
    assert set(np.asarray(t["reason"])[gal]) <= {REASONS["chi2"], REASONS["correlation"]}
    assert np.asarray(t["used"])[~gal].sum() >= 295
    assert model.diagnostics["n_rejected"] == int((~np.asarray(t["used"])).sum())
    r1, r2, rs = truth_residuals(model, probe)
    assert r1 < 1e-3 and r2 < 1e-3 and rs < 5e-3


def test_heldout_diagnostics_agree_with_the_truth(field, catalogue, poly, probe):
    d = poly.diagnostics
    t = poly.stars
    assert d["n_heldout"] == 60 == int(np.sum(t["heldout"]))
    assert d["heldout_n"] >= 58
    # the held-out residuals are the stars' noise (expected rms 3.7e-3 per component;
    # measured rms 3.5e-3, 2.9e-3, chi2 1.29) plus the model's error (< 1e-3, above)
    assert 0.6 < d["heldout_chi2_de"] < 1.6
    truth_rms = max(truth_residuals(poly, probe)[:2])
    for k in ("heldout_excess_de1", "heldout_excess_de2"):
        assert d[k] < truth_rms + 2.5e-3
    assert abs(d["heldout_mean_de1"]) < 1.5e-3 and abs(d["heldout_mean_de2"]) < 1.5e-3
    assert d["heldout_excess_dsigma"] < 0.01
    # a constant model fails the held-out check as it fails the truth (measured: excess
    # 0.016, 0.013, chi2 15; truth 0.013, 0.026). The held-out stars are those the final model
    # accepts (so that galaxies in the list do not count), which hides the worst misfits
    # of a model that rejects most stars (here 186 of 300): the excess is a lower bound.
    const = PolynomialPSF.fit(field["image"], *catalogue, noise_sigma=SIGMA, order=0)
    c1, c2, _ = truth_residuals(const, probe)
    dc = const.diagnostics
    assert dc["heldout_chi2_de"] > 5 and dc["n_used"] < 200
    assert 5e-3 < dc["heldout_excess_de1"] < 1.5 * c1
    assert 5e-3 < dc["heldout_excess_de2"] < 1.5 * c2


# ---------------------------------------------------------------------------------------
# Order 0, too few stars
# ---------------------------------------------------------------------------------------
def test_order_zero_is_the_stack():
    psf = galsim.Moffat(beta=3.5, fwhm=3.0).shear(g1=0.05, g2=-0.03)
    rng = np.random.default_rng(5)
    g = np.arange(40, 512 - 40, 56)
    gx, gy = np.meshgrid(g, g)
    sel = rng.choice(gx.size, 40, replace=False)
    xs = gx.ravel()[sel] + rng.uniform(-4, 4, 40)
    ys = gy.ravel()[sel] + rng.uniform(-4, 4, 40)
    snr = np.exp(rng.uniform(np.log(50), np.log(500), 40))
    image = render([(psf, x, y, peak_flux(psf, s)) for x, y, s in zip(xs, ys, snr, strict=True)],
                   n=512, seed=5)  # fmt: skip
    stack = stack_psf(image, xs, ys, noise_sigma=SIGMA)
    model = PolynomialPSF.fit(image, xs, ys, noise_sigma=SIGMA, order=0)
    assert model.order == 0 and model.diagnostics["n_used"] == stack.n_used == 40
    img = model.draw(100.0, 400.0)
    np.testing.assert_allclose(model.draw(500.0, 3.0), img, atol=1e-15)  # constant
    diff = img - stack.image
    # the same inverse-variance stack (measured: 1.5e-3 of its pixel noise)
    assert np.max(np.abs(diff)) < 0.02 * stack.pixel_noise
    assert model.centre.pixel_noise == pytest.approx(stack.pixel_noise, rel=1e-3)
    e1, e2, sig = model.shape_at(100.0, 400.0)
    assert (e1[0], e2[0]) == pytest.approx((stack.e1, stack.e2), abs=1e-6)
    assert sig[0] == pytest.approx(stack.sigma, rel=1e-6)
    # the stars do not vary: a quadratic's F-test says so; the varying field's does not
    flat = PolynomialPSF.fit(image, xs, ys, noise_sigma=SIGMA, order=2).variation()
    assert flat["vary_n"] == 40 and flat["vary_pvalue"] > 1e-3
    assert model.variation()["vary_pvalue"] == 1.0  # order 0: nothing to test


def test_variation_of_the_varying_field(poly):
    var = poly.variation()
    assert var["vary_pvalue"] < 1e-10
    # the map's |e| goes as 0.04 r^2 and its size by +-10 %: the fitted rms variations
    assert 0.01 < var["vary_rms_de"] < 0.05 and 0.01 < var["vary_rms_dsigma"] < 0.06


def test_too_few_stars_lower_the_order(field, caplog):
    img, x, y = field["image"], field["x"], field["y"]
    with caplog.at_level(logging.WARNING, logger="pylensfit"):
        model = PolynomialPSF.fit(img, x[:20], y[:20], noise_sigma=SIGMA, order=2)
    assert model.order == 1 and model.diagnostics["order_requested"] == 2
    assert model.coefs.shape == (n_terms(1), SIZE, SIZE)
    assert any("order lowered to 1" in r.getMessage() and r.levelno == logging.WARNING
               for r in caplog.records)  # fmt: skip
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pylensfit"):
        # (four stars across the field disagree with a constant: no chi2 test here)
        model = PolynomialPSF.fit(img, x[:4], y[:4], noise_sigma=SIGMA, order=2, clip=None)
    assert model.order == 0 and "order lowered to 0" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pylensfit"):
        PolynomialPSF.fit(img, x[:40], y[:40], noise_sigma=SIGMA, order=2, holdout=0)
    assert "order lowered" not in caplog.text


def test_no_usable_star_and_bad_arguments(field):
    img = field["image"]
    with pytest.raises(PSFError, match="no usable PSF star among 2 candidates"):
        PolynomialPSF.fit(img, [-50.0, 3.0], [10.0, 3.0], noise_sigma=SIGMA, source="f.fits")
    with pytest.raises(ValueError, match="holdout"):
        PolynomialPSF.fit(img, field["x"], field["y"], noise_sigma=SIGMA, holdout=1.0)
    with pytest.raises(ValueError, match="order"):
        PolynomialPSF.fit(img, field["x"], field["y"], noise_sigma=SIGMA, order=-1)


# ---------------------------------------------------------------------------------------
# Files
# ---------------------------------------------------------------------------------------
def test_write_read_roundtrip_and_dispatch(poly, probe, tmp_path):
    path = tmp_path / "psfmodel.fits"
    poly.write(path)
    with pytest.raises(FileExistsError):
        poly.write(path)
    back = read_psf_model(path)
    assert isinstance(back, PolynomialPSF)
    np.testing.assert_array_equal(back.draw(probe["x"], probe["y"]),
                                  poly.draw(probe["x"], probe["y"]))  # fmt: skip
    assert back.digest == poly.digest and len(poly.digest) == 40
    assert back.bounds == poly.bounds and back.order == poly.order
    assert back.diagnostics["heldout_rms_de1"] == poly.diagnostics["heldout_rms_de1"]
    for col in poly.stars.colnames:
        np.testing.assert_array_equal(np.asarray(back.stars[col]), np.asarray(poly.stars[col]))
    assert back.centre.pixel_noise == poly.centre.pixel_noise
    # the digest follows what draws the images, and only that
    other = PolynomialPSF(poly.coefs * (1 + 1e-12), poly.order, poly.bounds)
    assert other.digest != poly.digest
    assert PolynomialPSF(poly.coefs, poly.order, poly.bounds).digest == poly.digest
    # a PSFResult file, and a plain image, are constant models
    res = poly.centre
    res.write(tmp_path / "psf.fits")
    const = read_psf_model(tmp_path / "psf.fits")
    assert isinstance(const, ConstantPSF) and const.digest == res.digest
    np.testing.assert_array_equal(const.draw([1.0, 900.0], [2.0, 5.0])[1], res.image)
    const.write(tmp_path / "psf2.fits")
    assert read_psf_model(tmp_path / "psf2.fits").digest == res.digest
    with pytest.raises(PSFError, match="not a readable PSF file"):
        (tmp_path / "junk.fits").write_text("not fits")
        read_psf_model(tmp_path / "junk.fits")


def test_missing_piff_names_the_extra(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "piff", None)  # import piff raises ImportError
    (tmp_path / "model.piff").write_bytes(b"")
    with pytest.raises(PiffNotInstalledError, match=r"pip install pylensfit\[piff\]"):
        read_psf_model(tmp_path / "model.piff")
    assert issubclass(PiffNotInstalledError, ImportError)


# ---------------------------------------------------------------------------------------
# Piff
# ---------------------------------------------------------------------------------------
def piff_fit(image, x, y, path):
    """A PixelGrid model, quadratic in the position, fitted by Piff (``fit_piff``)."""
    pytest.importorskip("piff")
    from pylensfit.psfmodel import fit_piff

    fit_piff(image, x, y, path, noise_sigma=SIGMA, order=2)


def test_piff_model(field, catalogue, probe, tmp_path):
    pytest.importorskip("piff")
    path = tmp_path / "field.piff"
    piff_fit(field["image"], field["x"], field["y"], path)
    model = read_psf_model(path)
    assert isinstance(model, PiffPSF) and model.size == SIZE
    assert model.diagnostics["n_stars"] == 300
    imgs = model.draw(probe["x"], probe["y"])
    assert imgs.shape == (50, SIZE, SIZE)
    np.testing.assert_allclose(imgs.sum(axis=(1, 2)), 1.0, atol=1e-12)
    X, Y = gaussian_centre(imgs)
    assert np.max(np.hypot(X, Y)) < 1e-6  # an exact shift (0.02 px would do)
    r1, r2, rs = truth_residuals(model, probe)
    # measured: 6.2e-4, 9.1e-4, size 2.1e-4 (as the polynomial: the same order-2 floor)
    assert r1 < 2e-3 and r2 < 2e-3 and rs < 5e-3
    c = model.centre
    assert c.size == SIZE and abs(c.e1) < 0.005 and abs(c.e2) < 0.005
    # byte-for-byte copy, the same digest; the digest knows the drawing options
    model.write(tmp_path / "copy.piff")
    again = read_psf_model(tmp_path / "copy.piff")
    assert again.digest == model.digest
    np.testing.assert_array_equal(again.draw(probe["x"][:3], probe["y"][:3]), imgs[:3])
    assert read_psf_model(path, size=24).digest != model.digest
    assert read_psf_model(path, size=24).draw(500.0, 500.0).shape == (24, 24)
    (tmp_path / "junk.piff").write_text("not a Piff file")
    with pytest.raises(PSFError, match="junk.piff: not a readable Piff file"):
        read_psf_model(tmp_path / "junk.piff")


def test_star_checks_hold_the_keywords_of_the_stack_and_the_polynomial_fit():
    """StarChecks, the stars' tests shared by stack_psf and PolynomialPSF.fit, has their
    keywords' names (``clip`` for ``max_chi2`` in the fit) and defaults."""
    checks = {f.name: f.default for f in dataclasses.fields(StarChecks)}
    for fn, names in ((stack_psf, {}), (PolynomialPSF.fit, {"max_chi2": "clip"})):
        params = inspect.signature(fn).parameters
        assert {k: params[names.get(k, k)].default for k in checks} == checks
    for bad in ({"centroid_sigma": 0.0}, {"max_shift": -1.0}, {"margin": -1}):
        with pytest.raises(ValueError, match="centroid_sigma and max_shift must be positive"):
            StarChecks(**bad)
