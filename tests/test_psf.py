"""PSF estimation by stacking stars (paper section 2.4), checked against GalSim renderings."""

import galsim
import numpy as np
import pytest

from conftest import N, draw, galsim_model
from pylensfit import Config, fit_stamps
from pylensfit.psf import (
    REASONS,
    PSFError,
    PSFResult,
    combine_psfs,
    psf_from_image,
    psf_transform,
    read_psf,
    stack_psf,
)

PSF = galsim.Moffat(beta=3.5, fwhm=3.0).shear(g1=0.05, g2=-0.03)
ROUND = galsim.Moffat(beta=3.5, fwhm=3.4)
SIGMA = 1.0
BRIGHT = (3e3, 3e4)  # total flux in units of SIGMA: peak S/N 220-2200
MODEST = (400.0, 1500.0)  # peak S/N 30-110, the paper's lower limit


def star_field(psf=PSF, *, n=512, n_star=30, flux=BRIGHT, seed=1, extra=()):
    """A GalSim field of ``psf`` stars (and ``extra`` objects) at random sub-pixel positions.

    Objects sit on a jittered 56-pixel grid, so that no two cutouts overlap. Returns the
    noisy image (sigma = SIGMA), positions (0-based, pixel centres at integers) and fluxes.
    """
    rng = np.random.default_rng(seed)
    img = galsim.ImageD(n, n, scale=1.0)
    img.setOrigin(0, 0)  # galsim (x, y) == numpy [y, x]
    g = np.arange(40, n - 40, 56)
    gx, gy = np.meshgrid(g, g)
    sel = rng.choice(gx.size, n_star + len(extra), replace=False)
    xs = gx.ravel()[sel] + rng.uniform(-4, 4, sel.size)
    ys = gy.ravel()[sel] + rng.uniform(-4, 4, sel.size)
    fl = np.exp(rng.uniform(np.log(flux[0]), np.log(flux[1]), sel.size))
    for i, (x, y, f) in enumerate(zip(xs, ys, fl, strict=True)):
        obj = psf if i < n_star else extra[i - n_star]
        b = galsim.BoundsI(int(x) - 32, int(x) + 32, int(y) - 32, int(y) + 32)
        obj.withFlux(f).drawImage(
            image=img[b], add_to_image=True, center=galsim.PositionD(x, y)
        )
    return img.array + rng.normal(0.0, SIGMA, img.array.shape), xs, ys, fl


def truth(psf=PSF):
    """GalSim's rendering with the pixel response on the 32x32 stamp, unit sum."""
    t = draw(psf)
    return t / t.sum()


def band_limited(psf=PSF, n=N, m=128):
    """The pixel-convolved PSF keeping only |k| < pi (from GalSim's k-space rendering).

    A stack of Fourier-shifted stars estimates this: the modes above the pixel Nyquist
    frequency alias with a phase that depends on each star's sub-pixel position and
    average away (paper section 2.4).
    """
    k = galsim.Convolve(psf, galsim.Pixel(1.0)).drawKImage(nx=m, ny=m, scale=2 * np.pi / m)
    img = np.fft.fftshift(np.fft.ifft2(np.fft.ifftshift(k.array))).real
    lo = m // 2 - n // 2
    img = img[lo : lo + n, lo : lo + n]
    return img / img.sum()


def moments(image):
    m = galsim.hsm.FindAdaptiveMom(galsim.Image(image, scale=1.0))
    return m.moments_sigma, m.observed_shape.g1, m.observed_shape.g2


@pytest.fixture(scope="module")
def bright():
    img, xs, ys, fl = star_field()
    # catalogue positions good to ~0.3 px, as from a detection catalogue
    jitter = np.random.default_rng(7).normal(0.0, 0.3, (2, xs.size))
    res = stack_psf(img, xs + jitter[0], ys + jitter[1], noise_sigma=SIGMA, source="bright")
    return res, xs, ys, fl


def test_stack_matches_galsim_psf(bright):
    res, xs, ys, fl = bright
    t, b = truth(), band_limited()
    peak = t.max()
    assert res.image.shape == (N, N) and res.image.dtype == np.float64
    assert res.image.sum() == pytest.approx(1.0, abs=1e-12)
    assert np.unravel_index(res.image.argmax(), res.image.shape) == (N // 2, N // 2)
    assert res.n_used == 30 and res.n_rejected == 0 and np.all(res.reason == "")
    # tolerance budget: GalSim's pixel rendering differs from its band-limited part by
    # 1.3e-3 of the peak (aliasing, which no stack of pixelised stars can recover),
    # and the stack's own noise is res.pixel_noise ~ 1.3e-4 of the peak per pixel
    alias = np.abs(t - b).max() / peak
    assert 1.0e-3 < alias < 1.5e-3
    assert res.pixel_noise / peak < 2.5e-4
    assert np.all(np.abs(res.image - t) < np.abs(t - b) + 5 * res.pixel_noise)
    assert np.abs(res.image - t).max() < 2e-3 * peak  # 1.3e-3 here (1.0-1.8e-3 by seed)
    # against the band-limited PSF the residual is the noise: chi2 per pixel ~ 1
    # (30 stars also leave ~1e-4 of peak of un-averaged aliasing)
    chi2 = np.mean(((res.image - b) / res.pixel_noise) ** 2)
    assert 0.7 < chi2 < 1.4
    # diagnostics: adaptive moments of the stack vs the input shear and GalSim's rendering
    sig_t, e1_t, e2_t = moments(t)
    assert res.e1 == pytest.approx(0.05, abs=0.005) and res.e2 == pytest.approx(-0.03, abs=0.005)
    assert res.e1 == pytest.approx(e1_t, abs=3e-4) and res.e2 == pytest.approx(e2_t, abs=3e-4)
    assert res.sigma == pytest.approx(sig_t, rel=2e-3)
    fwhm_pix = galsim.Convolve(galsim.Moffat(beta=3.5, fwhm=3.0), galsim.Pixel(1.0))
    fwhm_pix = fwhm_pix.drawImage(nx=256, ny=256, scale=0.05, method="no_pixel").calculateFWHM()
    assert res.fwhm == pytest.approx(fwhm_pix, rel=0.01)  # 3.11 px (3.0 before the pixel)
    # per-star measurements
    assert np.max(np.hypot(res.x - xs, res.y - ys)) < 0.02
    np.testing.assert_allclose(res.flux, fl * draw(PSF).sum(), rtol=0.01)
    np.testing.assert_allclose(res.correlation, 1.0, atol=2e-3)


def test_noise_limited_at_modest_snr():
    """Peak S/N 30-110: the stack is unbiased, its residual consistent with pixel_noise."""
    img, xs, ys, _ = star_field(flux=MODEST, seed=2)
    res = stack_psf(img, xs, ys, noise_sigma=SIGMA)
    assert res.n_used == 30
    chi2 = np.mean(((res.image - band_limited()) / res.pixel_noise) ** 2)
    assert 0.8 < chi2 < 1.25  # 1024 pixels: chi2 per pixel is 1 +- 0.05
    # e scatters by ~2e-3 about GalSim's value here (over seeds)
    _, e1_t, e2_t = moments(truth())
    assert res.e1 == pytest.approx(e1_t, abs=0.006) and res.e2 == pytest.approx(e2_t, abs=0.006)
    r_median = stack_psf(img, xs, ys, noise_sigma=SIGMA, weighting="median")
    assert r_median.n_used == 30 and r_median.pixel_noise > res.pixel_noise
    assert np.mean(((r_median.image - band_limited()) / r_median.pixel_noise) ** 2) < 1.5


CONTAMINANTS = [
    galsim.Convolve(galsim.Exponential(half_light_radius=1.5).shear(g1=0.2, g2=0.1), PSF),
    galsim.Convolve(galsim.Exponential(half_light_radius=2.5).shear(g1=-0.1, g2=0.3), PSF),
    galsim.Convolve(galsim.DeVaucouleurs(half_light_radius=2.0).shear(g1=0.3, g2=0.0), PSF),
    # close binaries: separation 2.5, 3 and 6 px, flux ratios 0.5, 0.3 and 0.3
    galsim.Add(PSF.withFlux(2 / 3), PSF.withFlux(1 / 3).shift(2.0, 1.5)),
    galsim.Add(PSF.withFlux(1 / 1.3), PSF.withFlux(0.3 / 1.3).shift(-2.4, 1.8)),
    galsim.Add(PSF.withFlux(1 / 1.3), PSF.withFlux(0.3 / 1.3).shift(0.0, 6.0)),
]


def test_contaminants_are_rejected():
    img, xs, ys, fl = star_field(extra=CONTAMINANTS, seed=3)
    # a cosmic ray (a 100-sigma pixel) one pixel from the faintest star
    k = int(np.argmin(fl[:30]))
    img[int(round(ys[k])) + 1, int(round(xs[k]))] += 100.0
    res = stack_psf(img, xs, ys, noise_sigma=SIGMA)
    bad = np.r_[k, np.arange(30, 30 + len(CONTAMINANTS))]
    assert not res.used[bad].any()
    known = {REASONS["correlation"], REASONS["chi2"], REASONS["shift"]}
    assert set(res.reason[bad]) <= known
    assert res.n_used == 29 and np.all(res.reason[np.delete(np.arange(30), k)] == "")
    t = truth()
    assert np.abs(res.image - t).max() < 2e-3 * t.max()
    assert res.e1 == pytest.approx(0.05, abs=0.005) and res.e2 == pytest.approx(-0.03, abs=0.005)
    # the same stars without the rejection: the contaminants spoil the PSF
    naive = stack_psf(img, xs, ys, noise_sigma=SIGMA, min_correlation=-np.inf, max_chi2=None,
                      max_shift=5.0)  # fmt: skip
    assert naive.n_used == 36
    assert np.abs(naive.image - t).max() > 5e-3 * t.max()


def test_edge_and_bad_pixels_are_rejected_not_raised():
    img, xs, ys, _ = star_field(n_star=12, seed=4)
    weight = np.ones_like(img)
    img[int(round(ys[0])) + 3, int(round(xs[0]))] = np.nan
    weight[int(round(ys[1])) - 5, int(round(xs[1])) + 5] = 0.0
    x = np.r_[xs, 5.3, 509.0, -20.0, np.nan, 250.2]
    y = np.r_[ys, 250.0, 100.0, 100.0, 30.0, 506.5]
    res = stack_psf(img, x, y, noise_sigma=SIGMA, weight=weight, source="edge.fits")
    assert res.reason[0] == REASONS["nonfinite"] and res.reason[1] == REASONS["weight"]
    assert list(res.reason[12:]) == [REASONS["edge"]] * 3 + [REASONS["position"], REASONS["edge"]]
    assert np.all(np.isnan(res.x[12:])) and np.all(np.isnan(res.correlation[:2]))
    assert res.n_used == 10 and np.all(res.reason[2:12] == "")
    assert np.isfinite(res.image).all()
    # a per-star noise array; a bad value rejects that star only
    sig = np.full(x.size, SIGMA)
    sig[2] = 0.0
    res2 = stack_psf(img, x, y, noise_sigma=sig, weight=weight)
    assert res2.reason[2] == REASONS["noise"] and res2.n_used == 9


def test_no_usable_star_names_the_source():
    img, xs, ys, _ = star_field(n_star=4, seed=5)
    with pytest.raises(PSFError, match=r"starfield\.fits.*no usable PSF star.*cutout leaves"):
        stack_psf(img, [3.0, 508.5], [100.0, 7.0], noise_sigma=SIGMA, source="starfield.fits")
    # catalogue positions on empty sky: nothing above min_snr
    with pytest.raises(PSFError, match=r"sky\.fits.*signal-to-noise"):
        stack_psf(img, xs + 28.0, ys + 28.0, noise_sigma=SIGMA, source="sky.fits")
    with pytest.raises(PSFError, match="empty"):
        stack_psf(img, [], [], noise_sigma=SIGMA, source="empty")
    with pytest.raises(ValueError):
        stack_psf(img, [1.0, 2.0], [1.0], noise_sigma=SIGMA)


def test_combine_same_psf_is_the_truth(bright):
    res1 = bright[0]
    img, xs, ys, _ = star_field(n_star=12, seed=6)
    res2 = stack_psf(img, xs, ys, noise_sigma=SIGMA, source="galaxy_field")
    comb = combine_psfs([res1, res2])
    t = truth()
    assert comb.n_used == 42 and comb.source == "bright+galaxy_field"
    assert comb.image.sum() == pytest.approx(1.0)
    assert np.abs(comb.image - t).max() < 2e-3 * t.max()
    assert comb.e1 == pytest.approx(0.05, abs=0.005) and comb.e2 == pytest.approx(-0.03, abs=0.005)
    np.testing.assert_array_equal(comb.x, np.r_[res1.x, res2.x])
    np.testing.assert_allclose(combine_psfs([res1, res2], weights=[0, 1]).image, res2.image)
    with pytest.raises(PSFError):
        combine_psfs([res1, res2], weights=[0, 0])


def test_combine_different_psfs_is_the_weighted_mean(bright):
    res1 = bright[0]
    img, xs, ys, _ = star_field(ROUND, n_star=10, seed=8)
    res2 = stack_psf(img, xs, ys, noise_sigma=SIGMA)
    assert abs(res2.e1) < 2e-3 and abs(res2.e2) < 2e-3 and res2.n_used == 10
    for weights, w in ((None, np.array([30.0, 10.0])), ([1.0, 3.0], np.array([1.0, 3.0]))):
        comb = combine_psfs([res1, res2], weights=weights)
        mix = (w[0] * truth(PSF) + w[1] * truth(ROUND)) / w.sum()
        assert np.abs(comb.image - mix).max() < 2e-3 * mix.max()
        sig, e1, e2 = moments(mix)
        # diagnostics are measured on the co-added image, not averaged
        assert comb.e1 == pytest.approx(e1, abs=5e-4) and comb.e2 == pytest.approx(e2, abs=5e-4)
        assert comb.sigma == pytest.approx(sig, rel=3e-3)
    assert comb.e1 < 0.6 * res1.e1


def test_write_read_roundtrip(bright, tmp_path):
    img, xs, ys, _ = star_field(n_star=6, seed=9)
    res = stack_psf(img, np.r_[xs, 2.0], np.r_[ys, 2.0], noise_sigma=SIGMA, source="f.fits")
    path = tmp_path / "psf.fits"
    res.write(path)
    back = PSFResult.read(path)
    np.testing.assert_array_equal(back.image, res.image)
    for name in ("x_cat", "y_cat", "x", "y", "flux", "snr", "correlation", "chi2"):
        np.testing.assert_array_equal(getattr(back, name), getattr(res, name))
    np.testing.assert_array_equal(back.used, res.used)
    assert list(back.reason) == list(res.reason) and back.reason[-1] == REASONS["edge"]
    for name in ("fwhm", "sigma", "e1", "e2", "pixel_noise"):
        assert getattr(back, name) == pytest.approx(getattr(res, name), rel=1e-14)
    assert back.n_used == 6 and back.n_rejected == 1 and back.source == "f.fits"
    from astropy.io import fits

    hdr = fits.getheader(path)
    assert hdr["N_USED"] == 6 and hdr["N_REJ"] == 1 and hdr["E1"] == res.e1
    with pytest.raises(FileExistsError):
        res.write(path)
    bright[0].write(path, overwrite=True)
    assert PSFResult.read(path).n_used == 30
    # a source as long as an ordinary file path (its card would be too long with a
    # comment, a warning that pytest makes an error)
    for n in (40, 55, 68, 120):
        res.source = "/data/survey/" + "x" * n + ".fits"
        res.write(path, overwrite=True)
        assert PSFResult.read(path).source == res.source


def test_stacked_psf_gives_the_same_likelihood_peak(bright):
    """A noise-free galaxy convolved with the true PSF: same L(e) argmax with either PSF."""
    res = bright[0]
    cfg = Config.paper(model="exponential")
    for e in ((0.3, 0.1), (-0.12, -0.33)):
        gal = galsim.Convolve(galsim_model("exponential", 2.0, *e), PSF)
        stamp = draw(gal, offset=(0.3, -0.4)) * 1e3
        f_true = fit_stamps(stamp, draw(PSF), 1.0, config=cfg)
        f_stack = fit_stamps(stamp, res.image, 1.0, config=cfg)
        i = np.argmax(f_true.lnL[0])
        assert np.argmax(f_stack.lnL[0]) == i
        assert np.hypot(*(f_stack.egrid[i] - e)) < cfg.e_step
        assert f_stack.r_best[0] == pytest.approx(f_true.r_best[0], abs=0.21)


def _moffat_image(n=33, g1=0.06, g2=-0.04):
    obj = galsim.Moffat(beta=3.5, fwhm=3.0).shear(g1=g1, g2=g2)
    return obj.drawImage(nx=n, ny=n, scale=1.0, use_true_center=False).array.astype(np.float64)


def test_psf_from_image_normalises_and_measures_like_a_stack():
    img = _moffat_image()
    res = psf_from_image(7.5 * img, source="model")
    assert res.image.sum() == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(res.image, img / img.sum(), rtol=1e-12)
    # the same adaptive moments as GalSim's on the same image: the sheared Moffat's
    # shape, diluted a little by the pixel
    hsm = galsim.hsm.FindAdaptiveMom(galsim.Image(img, scale=1.0)).observed_shape
    assert (res.e1, res.e2) == pytest.approx((hsm.g1, hsm.g2), abs=1e-6)
    assert 0.05 < res.e1 < 0.06 and -0.04 < res.e2 < -0.033
    assert res.n_used == 0 and res.stars()["x"].size == 0 and res.source == "model"
    # the transform the likelihood uses is that of the image, whatever its scale
    np.testing.assert_allclose(psf_transform(res.image, 48), psf_transform(img, 48), atol=1e-12)
    # the digest keys kept results: the image's bytes, whatever array order it came in
    assert res.digest == psf_from_image(np.asfortranarray(img), source="other").digest
    assert res.digest != psf_from_image(_moffat_image(g1=0.061), source="model").digest


@pytest.mark.parametrize(
    ("image", "match"),
    [(np.ones(9), "2-D"), (np.zeros((9, 9)), "non-positive sum"),
     (np.where(np.eye(9) > 0, np.nan, 1.0), "9 non-finite pixel")],  # fmt: skip
)
def test_psf_from_image_refuses_bad_images(image, match):
    with pytest.raises(PSFError, match=f"given: .*{match}"):
        psf_from_image(image, source="given")


def test_read_psf_plain_fits_and_psf_files(bright, tmp_path):
    from astropy.io import fits
    from astropy.table import Table

    img = _moffat_image()
    plain = tmp_path / "plain.fits"  # a PSF from another code: an image in an extension
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(img.astype(np.float32))]).writeto(plain)
    res = read_psf(plain)
    np.testing.assert_allclose(res.image, img / img.sum(), rtol=1e-6)
    assert res.source == str(plain) and res.n_used == 0
    # a stacked PSF written by the pipeline comes back whole, with its stars
    psf = bright[0]
    psf.write(tmp_path / "stack.psf.fits")
    back = read_psf(tmp_path / "stack.psf.fits")
    np.testing.assert_array_equal(back.image, psf.image)
    assert back.n_used == psf.n_used > 0
    # no image, not FITS: a PSFError naming the file
    table_only = tmp_path / "table.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.table_to_hdu(Table({"a": [1.0]}))]).writeto(table_only)
    with pytest.raises(PSFError, match="table.fits: no 2-D image"):
        read_psf(table_only)
    junk = tmp_path / "junk.fits"
    junk.write_bytes(b"not a FITS file at all" * 50)
    with pytest.raises(PSFError, match="junk.fits: not a readable PSF file"):
        read_psf(junk)
