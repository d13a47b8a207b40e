"""pylensfit.joint: a galaxy fitted on all of its exposures at once."""

from __future__ import annotations

import galsim
import numpy as np
import pytest

from pylensfit.config import Config
from pylensfit.exposures import Exposure, cut_exposures
from pylensfit.flags import flag_value
from pylensfit.joint import (
    first_exposure,
    fit_exposures,
    fit_views,
    lattice_symmetries,
    sky_frequencies,
)
from pylensfit.likelihood import fit_stamps
from pylensfit.models import fourier_profile, render_models, sheared_k
from pylensfit.psf import psf_transform
from pylensfit_validation import dither
from pylensfit_validation.galaxies import PSFProfile

N = 32
SCALE = 0.2  # arcsec per pixel of the aligned exposure
#: the single fit's options that the joint fit shares: uniform amplitude prior, untruncated
#: models, second-order position expansion, one stamp size, the bank's e grid
CFG = Config().replace(model="exponential", amplitude_prior="uniform", cubic_snr=0.0,
                       truncate_models=False, max_stamp_size=0, e_refine=1,
                       n_bulge_fractions=1, dtype="float64", r_min=0.0, r_max=6.0,
                       r_step=0.25, r_rel_step=0.0, stamp_size=N)  # fmt: skip


def gaussian_psf(size: int = 25, s: float = 1.5) -> np.ndarray:
    yy, xx = np.mgrid[:size, :size] - size // 2
    return np.exp(-(xx**2 + yy**2) / (2 * s * s))


def rotation(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


def posterior_mean(lnL: np.ndarray, egrid: np.ndarray) -> np.ndarray:
    """``<e>`` under a flat prior on the grid, ``(n, 2)``."""
    p = np.exp(lnL.astype(float) - np.nanmax(lnL, axis=1, keepdims=True))
    return (p @ egrid) / p.sum(axis=1, keepdims=True)


@pytest.mark.parametrize("model, n_b", [("exponential", 1), ("bulge+disc", 3)])
def test_one_exposure_is_the_single_fit(model, n_b):
    """K = 1 with J = I (pixel scale 1): fit_stamps's ln L(e) (and per bulge fraction), to
    its precision; a PSF given per galaxy is the same as one for all."""
    cfg = CFG.replace(model=model, n_bulge_fractions=n_b)
    rng = np.random.default_rng(1)
    ng = 5
    psf = gaussian_psf()
    img = render_models(N, psf, 16 + rng.uniform(-0.5, 0.5, ng), 16 + rng.uniform(-0.5, 0.5, ng),
                        rng.uniform(-0.3, 0.3, ng), rng.uniform(-0.3, 0.3, ng),
                        rng.uniform(1.5, 3.0, ng), np.full(ng, 300.0), model=model,
                        bulge_fraction=0.3)  # fmt: skip
    img = img + rng.normal(0.0, 1.0, img.shape)
    single = fit_stamps(img, psf, 1.0, config=cfg)
    joint = fit_exposures(img[None], psf[None], 1.0, np.eye(2)[None], config=cfg)
    assert (joint.n_exposures == 1).all() and (joint.flags == 0).all()
    a = single.lnL + single.lnL_peak[:, None]
    b = joint.lnL + joint.lnL_peak[:, None]
    near = single.lnL > -30  # where the posterior has any weight
    # same expansion point, same formulas: equal to float32 rounding of the output (sigma
    # = 1, so not even the constant ln sigma differs)
    assert np.abs(a - b)[near].max() < 1e-4
    np.testing.assert_allclose(joint.snr, single.snr, rtol=1e-6)
    np.testing.assert_allclose(joint.x, single.x - N // 2, atol=1e-6)
    np.testing.assert_allclose(joint.y, single.y - N // 2, atol=1e-6)
    if n_b > 1:
        np.testing.assert_array_equal(joint.bulge_fractions, single.bulge_fractions)
        near_b = single.lnL_bulge > -30
        assert np.abs(joint.lnL_bulge - single.lnL_bulge)[near_b].max() < 1e-4
        np.testing.assert_allclose(joint.lnL_star, single.lnL_star, atol=1e-6)
    each = fit_exposures(img[None], np.repeat(psf[None, None], ng, 1), 1.0, np.eye(2)[None],
                         config=cfg)  # fmt: skip
    np.testing.assert_allclose(each.lnL, joint.lnL, atol=1e-5)


def test_identical_exposures_are_their_mean():
    """K identical exposures with independent noise sigma: the joint ln L(e) is that of
    their mean with sigma / sqrt(K), up to a constant (exact for Gaussian noise)."""
    rng = np.random.default_rng(2)
    K, sigma = 4, 2.0
    psf = gaussian_psf(s=1.8)
    clean = render_models(N, psf, [16.3, 15.8, 16.1], [15.9, 16.2, 16.4], [0.2, -0.1, 0.05],
                          [0.1, 0.25, -0.3], [2.0, 2.5, 1.6], [250.0, 200.0, 300.0])  # fmt: skip
    exps = clean[None] + rng.normal(0.0, sigma, (K, *clean.shape))
    J = np.eye(2) / SCALE
    joint = fit_exposures(exps, psf, sigma, np.repeat(J[None], K, 0), config=CFG)
    mean = fit_exposures(exps.mean(0)[None], psf, sigma / np.sqrt(K), J[None], config=CFG)
    near = mean.lnL > -30
    assert np.abs(joint.lnL - mean.lnL)[near].max() < 1e-4
    np.testing.assert_allclose(joint.snr, mean.snr, rtol=1e-6)
    assert (joint.n_exposures == K).all()


def galsim_exposure(J: np.ndarray, psf_prof, gal, flux_scale: float = 1.0):
    """A galaxy and its PSF drawn by GalSim through the local WCS ``J`` (GalSim's
    ``JacobianWCS`` is ``J^-1``), the galaxy at element ``[N//2, N//2]``."""
    wcs = galsim.JacobianWCS(*np.linalg.inv(J).ravel())
    img = galsim.Convolve(gal * flux_scale, psf_prof).drawImage(
        nx=N, ny=N, wcs=wcs, offset=(0.5, 0.5)).array  # fmt: skip
    psf = psf_prof.drawImage(nx=31, ny=31, wcs=wcs).array
    return img, psf


def test_model_through_jacobian_is_galsim():
    """M_pix(k) = M_sky(J^T k): a sheared exponential through a rotated, flipped and
    sheared J is GalSim's drawing through that WCS."""
    J = rotation(30.0) @ np.array([[1.05, 0.03], [0.03, 0.95]]) @ np.diag([-1.0, 1.0]) / SCALE
    gal = galsim.Exponential(scale_radius=0.3).shear(g1=0.3, g2=-0.2)
    img, psf = galsim_exposure(J, galsim.Gaussian(fwhm=0.6), gal)
    qx, qy = sky_frequencies(J, N)
    kx, ky = 2 * np.pi * np.fft.rfftfreq(N), 2 * np.pi * np.fft.fftfreq(N)
    G = fourier_profile(sheared_k(qx, qy, 0.3, -0.2) * 0.3, "exponential")
    phase = np.exp(-1j * (kx[None, :] + ky[:, None]) * (N // 2))
    ours = np.fft.irfft2(G * psf_transform(psf, N) * phase, s=(N, N))
    assert np.abs(ours - img).max() < 2e-3 * img.max()
    # the transposed Jacobian (a rotation of the wrong sense) is far from it
    qx, qy = sky_frequencies(J.T, N)
    G = fourier_profile(sheared_k(qx, qy, 0.3, -0.2) * 0.3, "exponential")
    wrong = np.fft.irfft2(G * psf_transform(psf, N) * phase, s=(N, N))
    assert np.abs(wrong - img).max() > 0.02 * img.max()


#: the exposures' Jacobians (pixels per arcsec): rotated by 30 degrees, mirror image
#: (det J < 0), sheared by the WCS
JACOBIANS = (rotation(30.0) / SCALE,
             np.diag([-1.0, 1.0]) @ rotation(-65.0) / SCALE,
             np.array([[1.06, 0.04], [0.04, 0.95]]) / SCALE)  # fmt: skip
PSFS = (galsim.Gaussian(fwhm=0.65), galsim.Moffat(beta=3.0, fwhm=0.7).shear(g1=0.05, g2=-0.03),
        galsim.Gaussian(fwhm=0.55).shear(g1=-0.04, g2=0.02))  # fmt: skip


def sky_fit(jacobians, psfs, gal, *, flux_scales=None, config=CFG):
    K = len(jacobians)
    fs = np.ones(K) if flux_scales is None else np.asarray(flux_scales)
    pairs = [galsim_exposure(J, p, gal, f) for J, p, f in zip(jacobians, psfs, fs, strict=True)]
    stamps = np.stack([s for s, _ in pairs])[:, None]
    psf = np.stack([p for _, p in pairs])
    return fit_exposures(stamps, psf, 1.0, np.stack(jacobians), flux_scale=fs, config=config,
                         pixel_scale=SCALE)  # fmt: skip


@pytest.mark.parametrize("e", [(0.3, 0.15), (-0.2, 0.35), (0.05, -0.42)])
def test_sky_frame_shape_through_rotated_flipped_sheared_exposures(e):
    """A GalSim galaxy of known sky-frame shape, drawn noise-free through three
    misaligned exposures (rotated, mirror image, sheared WCS) with their own PSFs and
    flux scales: the joint fit's posterior mean is that of the same galaxy drawn in an
    aligned exposure whose noise gives it the same S/N (the mean over a 0.1 grid depends
    on the likelihood's width: the same data fitted twice as two exposures move it by
    0.005). They then differ only by the PSFs and the pixel sampling: measured 0.001 to
    0.005; 0.01 is a tenth of the grid step. A rotation or flip taken with the wrong sense
    (``J^T`` for ``J``, ngmix #72) moves the mean by 0.2 to 0.3 and fails."""
    gal = galsim.Exponential(scale_radius=0.45, flux=400.0).shear(g1=e[0], g2=e[1])
    joint = sky_fit(list(JACOBIANS), list(PSFS), gal, flux_scales=[1.0, 0.7, 1.3])
    assert joint.n_exposures[0] == 3
    np.testing.assert_allclose(joint.flux, 400.0, rtol=0.01)
    assert np.hypot(joint.x, joint.y)[0] < 0.01  # arcsec: the galaxy is where it was drawn
    img, psf = galsim_exposure(np.eye(2) / SCALE, galsim.Gaussian(fwhm=0.6), gal)
    one = fit_exposures(img[None, None], psf[None], 1.0, np.eye(2)[None] / SCALE, config=CFG,
                        pixel_scale=SCALE)  # fmt: skip
    aligned = fit_exposures(img[None, None], psf[None], one.snr[0] / joint.snr[0],
                            np.eye(2)[None] / SCALE, config=CFG, pixel_scale=SCALE)  # fmt: skip
    e_al = posterior_mean(aligned.lnL, aligned.egrid)[0]
    e_jt = posterior_mean(joint.lnL, joint.egrid)[0]
    assert np.abs(e_jt - e_al).max() < 0.01, (e_jt, e_al)
    assert np.abs(e_al - np.array(e)).max() < 0.03  # and both near the truth
    bad = fit_exposures(*transposed_views(JACOBIANS, PSFS, gal), config=CFG, pixel_scale=SCALE)
    e_bad = posterior_mean(bad.lnL, bad.egrid)[0]
    assert np.abs(e_bad - e_al).max() > 0.1, (e_bad, e_al)


@pytest.mark.parametrize("X", [(0.5, -0.3), (0.7, 0.45)])
def test_shared_sky_offset(X):
    """A galaxy off its catalogue position by ``X`` (arcsec, (W, N); up to 4 pixels) is
    at pixel offset ``J_k X`` in each misaligned exposure: the joint fit finds ``X``
    (measured to 1e-3 arcsec, noise-free) and the shape of the centred galaxy to 0.01 (a
    tenth of the grid step; measured 0.004 at 0.58", 0.007 at 0.83", where the stamp's edge
    cuts one side of the galaxy's wings and not the other)."""
    gal = galsim.Exponential(scale_radius=0.45, flux=400.0).shear(g1=0.3, g2=0.15)
    stamps, psfs = [], []
    for J, P in zip(JACOBIANS, PSFS, strict=True):
        wcs = galsim.JacobianWCS(*np.linalg.inv(J).ravel())
        off = J @ np.asarray(X)
        stamps.append(galsim.Convolve(gal, P).drawImage(
            nx=N, ny=N, wcs=wcs, offset=(0.5 + off[0], 0.5 + off[1])).array)  # fmt: skip
        psfs.append(P.drawImage(nx=31, ny=31, wcs=wcs).array)
    cfg = CFG.replace(position_prior_sigma=10.0)  # no pull towards the catalogue position
    fits = fit_exposures(np.stack(stamps)[:, None], np.stack(psfs), 1.0, np.stack(JACOBIANS),
                         config=cfg, pixel_scale=SCALE)  # fmt: skip
    assert abs(fits.x[0] - X[0]) < 0.005 and abs(fits.y[0] - X[1]) < 0.005
    centred = sky_fit(list(JACOBIANS), list(PSFS), gal, config=cfg)
    e_off = posterior_mean(fits.lnL, fits.egrid)[0]
    np.testing.assert_allclose(e_off, posterior_mean(centred.lnL, centred.egrid)[0], atol=0.01)


@pytest.mark.parametrize("e", [(0.3, 0.15), (0.05, -0.42)])
def test_astrometric_residuals_between_exposures(e):
    """Each exposure's WCS off by 0.05" (the galaxy drawn 0.05" from where the WCS puts
    it, in a different direction in each of the three misaligned exposures): the joint
    fit's sky-frame posterior mean is that of the exactly registered exposures to 0.01, a
    tenth of the grid step (measured 0.004 and 1e-6 at e = (0.3, 0.15): the residuals
    blur the galaxy; a shape error of the offsets' order, 0.05 / 0.45 = 0.1, fails it),
    and its position is the residuals' mean to 0.01"."""
    gal = galsim.Exponential(scale_radius=0.45, flux=400.0).shear(g1=e[0], g2=e[1])
    resid = 0.05 * np.array([[np.cos(a), np.sin(a)] for a in (0.3, 2.4, 4.4)])
    stamps, psfs = [], []
    for J, P, d in zip(JACOBIANS, PSFS, resid, strict=True):
        wcs = galsim.JacobianWCS(*np.linalg.inv(J).ravel())
        off = J @ d
        stamps.append(galsim.Convolve(gal, P).drawImage(
            nx=N, ny=N, wcs=wcs, offset=(0.5 + off[0], 0.5 + off[1])).array)  # fmt: skip
        psfs.append(P.drawImage(nx=31, ny=31, wcs=wcs).array)
    fits = fit_exposures(np.stack(stamps)[:, None], np.stack(psfs), 1.0, np.stack(JACOBIANS),
                         config=CFG, pixel_scale=SCALE)  # fmt: skip
    registered = sky_fit(list(JACOBIANS), list(PSFS), gal)
    e_res = posterior_mean(fits.lnL, fits.egrid)[0]
    e_reg = posterior_mean(registered.lnL, registered.egrid)[0]
    assert np.abs(e_res - e_reg).max() < 0.01, (e_res, e_reg)
    assert np.hypot(fits.x[0] - resid[:, 0].mean(), fits.y[0] - resid[:, 1].mean()) < 0.01


def transposed_views(jacobians, psfs, gal):
    """The stamps of ``jacobians`` given to the fit with ``J^T`` in place of ``J``."""
    pairs = [galsim_exposure(J, p, gal) for J, p in zip(jacobians, psfs, strict=True)]
    return (np.stack([s for s, _ in pairs])[:, None], np.stack([p for _, p in pairs]), 1.0,
            np.stack([J.T for J in jacobians]))  # fmt: skip


def test_unusable_exposure_changes_nothing():
    """An exposure flagged unusable for a galaxy (here also holding garbage) gives the fit
    without it (the same ln L(e) rows); a galaxy with no usable exposure is NaN and flagged."""
    rng = np.random.default_rng(3)
    psf = gaussian_psf()
    clean = render_models(N, psf, [16.2, 15.7], [16.1, 16.3], [0.2, -0.3], [0.1, 0.05],
                          [2.0, 2.4], [250.0, 220.0])  # fmt: skip
    exps = clean[None] + rng.normal(0.0, 1.0, (3, *clean.shape))
    J = np.stack([np.eye(2), rotation(40.0), np.diag([-1.0, 1.0])]) / SCALE
    psfs = np.stack([psf, gaussian_psf(s=1.7), gaussian_psf(s=1.3)])
    usable = np.array([[True, True], [True, False], [True, True]])
    garbage = exps.copy()
    garbage[1, 1] = rng.normal(0.0, 50.0, (N, N))
    with_flag = fit_exposures(garbage, psfs, [1.0, 1.2, 0.9], J, flux_scale=[1.0, 0.8, 1.1],
                              usable=usable, config=CFG)  # fmt: skip
    keep = [0, 2]
    without = fit_exposures(exps[keep][:, 1:], psfs[keep], [1.0, 0.9], J[keep],
                            flux_scale=[1.0, 1.1], config=CFG)  # fmt: skip
    np.testing.assert_array_equal(with_flag.lnL[1], without.lnL[0])
    # the unshifted peak to the rounding of BLAS sums over blocks of other sizes
    np.testing.assert_allclose(with_flag.lnL_peak[1], without.lnL_peak[0], rtol=1e-13)
    np.testing.assert_array_equal(with_flag.n_exposures, [3, 2])
    none = fit_exposures(exps, psfs, 1.0, J, usable=np.zeros((3, 2), bool), config=CFG)
    assert np.isnan(none.lnL).all() and (none.n_exposures == 0).all()
    assert (none.flags & flag_value("NOT_MEASURED")).all()


def test_bad_inputs_raise():
    psf = gaussian_psf()
    stamps = np.zeros((2, 3, N, N))
    with pytest.raises(ValueError, match="jacobian"):
        fit_exposures(stamps, psf, 1.0, np.eye(2)[None], config=CFG)
    with pytest.raises(ValueError, match="noise_sigma"):
        fit_exposures(stamps, psf, np.ones(5), np.stack([np.eye(2)] * 2), config=CFG)


def test_fit_views_on_a_dithered_set(tmp_path):
    """End to end: GalSim exposures with their own WCS (rotations, a mirror image, a chip
    gap), cut by :func:`cut_exposures` and fitted by :func:`fit_views`. At S/N 300-400
    per exposure the likelihood lies within one 0.1 cell, so the posterior mean is the
    truth to about half a cell; the position to a small fraction of a pixel (0.2")."""
    spec = dither.DitherSpec(n_exposures=3, ngal=6, snr_range=(300.0, 400.0),
                             size_range=(0.24, 0.45), spacing=16.0, star_field_size=96,
                             model="exponential")  # fmt: skip
    s = dither.read_dither(dither.simulate_dither(tmp_path, spec, seed=3))
    exposures = []
    for k, e in enumerate(s.exposures):
        psf = PSFProfile("moffat", e.psf_fwhm, spec.psf_beta, e.psf_e1, e.psf_e2).galsim()
        exposures.append(Exposure.from_fits(s.path(k), reference_zero_point=spec.zero_point,
                                            psf=psf.drawImage(nx=31, ny=31, scale=1.0).array))
    views = cut_exposures(exposures, s.truth["ra"], s.truth["dec"], size=N)
    fits = fit_views(views, config=CFG.replace(dtype="float32"))
    np.testing.assert_array_equal(fits.n_exposures, sum(v.usable.astype(int) for v in views))
    assert fits.n_exposures.min() < 3 and (fits.flags == 0).all()  # a galaxy in the gap
    mean = posterior_mean(fits.lnL, fits.egrid)
    truth = np.c_[s.truth["e1"], s.truth["e2"]]
    assert np.abs(mean - truth).max() < 0.06, np.c_[mean, truth]
    assert np.hypot(fits.x, fits.y).max() < 0.02  # arcsec
    np.testing.assert_allclose(fits.flux, s.truth["flux"], rtol=0.05)


def test_lattice_symmetries():
    """A Jacobian that maps the pixel axes onto the sky's axes or diagonals keeps the
    square's four symmetries, a rotation times a scale (or its mirror image) the quarter
    turn, a sheared one none; ``e -> s e`` as the single fit's folded bank reads it."""
    flip = np.diag([-1.0, 1.0])
    for J, kept in ((np.eye(2) / SCALE, [0, 1, 2, 3]), (flip @ rotation(90.0) / SCALE,
                    [0, 1, 2, 3]), (rotation(45.0) * 3.0, [0, 1, 2, 3]),
                    (rotation(30.0) / SCALE, [0, 3]), (flip @ rotation(-65.0), [0, 3]),
                    (JACOBIANS[2], [0]), (np.diag([1.0, 2.0]), [0, 1])):  # fmt: skip
        h, s = lattice_symmetries(J)
        np.testing.assert_array_equal(h, kept)
    assert list(lattice_symmetries(rotation(45.0))[1]) == [0, 2, 1, 3]  # s1 <-> s2 on the sky


@pytest.mark.parametrize("deg", [0.0, 30.0])
def test_folded_products_are_the_unfolded_ones(deg):
    """An exposure whose Jacobian keeps symmetries (folded products) and the same Jacobian
    moved by 1e-8 (none kept: the half-plane): the same ln L(e) to the models' change."""
    rng = np.random.default_rng(4)
    psf = gaussian_psf()
    img = render_models(N, psf, [16.2, 15.7, 16.0], [16.1, 16.3, 15.8], [0.2, -0.3, 0.1],
                        [0.1, 0.05, -0.25], [2.0, 2.4, 1.5], [250.0, 220.0, 300.0])  # fmt: skip
    img = img[None] + rng.normal(0.0, 1.0, (1, *img.shape))
    J = rotation(deg) / SCALE
    moved = J @ np.array([[1.0, 1e-8], [0.0, 1.0]])
    assert lattice_symmetries(J)[0].size > 1 and lattice_symmetries(moved)[0].size == 1
    cfg = CFG.replace(n_bulge_fractions=1)
    a = fit_exposures(img, psf, 1.0, J[None], config=cfg, pixel_scale=SCALE)
    b = fit_exposures(img, psf, 1.0, moved[None], config=cfg, pixel_scale=SCALE)
    near = a.lnL > -30
    assert np.abs(a.lnL - b.lnL)[near].max() < 1e-4  # measured 2e-6: float32 output
    np.testing.assert_allclose(a.lnL_peak, b.lnL_peak, rtol=1e-7)


def test_the_bank_caches_keep_within_their_bytes():
    """``keep_last`` with a byte budget drops the oldest entries until the arrays kept fit
    (the newest always kept); a view counts as its base, once."""
    from pylensfit.likelihood.bank import array_bytes, keep_last

    cache: dict = {}
    big = np.zeros(1000)  # 8,000 bytes
    for k in range(5):
        keep_last(cache, k, (np.zeros(1000), big[:10]), 8, max_bytes=40_000)
    assert array_bytes(cache[4]) == 16_000 and list(cache) == [3, 4]
    keep_last(cache, 9, np.zeros(10_000), 8, max_bytes=40_000)
    assert list(cache) == [9]
    for k in range(12):
        keep_last(cache, k, np.zeros(1), 8)
    assert list(cache) == list(range(4, 12))


def test_first_exposure_is_the_lowest_set_bit():
    used = np.array([0, 1, 2, 6, 8, 12, 2**40 + 2**41, 2**62])
    np.testing.assert_array_equal(first_exposure(used), [-1, 0, 1, 1, 3, 2, 40, 62])
    assert first_exposure(used, none=0)[0] == 0
