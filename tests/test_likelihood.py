"""The likelihood engine against brute force, GalSim renderings and bad input."""

import galsim
import numpy as np
import pytest

from conftest import PSFS, N, draw, galsim_model
from pylensfit import Config, fit_stamps
from pylensfit.flags import flag_value
from pylensfit.likelihood.bank import interior
from pylensfit.likelihood.folded import CHI, folded_bank
from pylensfit.likelihood.radius_nb import _narrow_peak_factor, _run_peak_factor
from pylensfit.models import half_light_radius, model_bank, rfft_frequencies
from pylensfit.psf import psf_transform


def _phases(centres):
    """``exp(-i k.c)`` on the ``N x N`` stamp's half-plane for each centre, ``(p, N, N//2+1)``."""
    kx, ky = np.meshgrid(2 * np.pi * np.fft.rfftfreq(N), 2 * np.pi * np.fft.fftfreq(N))
    return np.exp(-1j * (kx * centres[:, 0, None, None] + ky * centres[:, 1, None, None]))


def _model_products(cfg, cols, P, centres, d, phase=None):
    """``sum m d`` and ``sum m^2`` of unit-flux models at sub-pixel positions, ``(m, p)``.

    ``m`` is the real-space image of bank column ``cols[i]`` (times the PSF transform
    ``P``) shifted to ``centres[j]``: ``irfft2(Y)``, ``Y = G P exp(-i k.c)``, on the
    ``N x N`` stamp, built independently of the engine's matrix products (no Taylor
    expansion about a re-centred origin). Both products are taken by Parseval on the
    half-plane spectrum rather than by one inverse FFT per model and position (the same
    numbers to 1e-15). ``irfft2`` keeps only the Hermitian part (in ``ky``) of the
    ``kx = 0`` and Nyquist columns of ``Y``. That leaves ``sum m d`` unchanged, since the
    data's spectrum is Hermitian there; in ``sum m^2`` the squared Hermitian part of a
    column is ``(sum |Y|^2 + Re sum_ky Y(ky) Y(-ky)) / 2``, where ``Y(ky) Y(-ky)`` carries
    the phase ``exp(-2i kx cx)``, and ``exp(-2i kx cx + 2i pi cy)`` on the Nyquist row
    (its own mirror, ``ky = -pi``).
    """
    bank = model_bank(cfg)
    nk = N // 2 + 1
    phase = _phases(centres) if phase is None else phase
    A = bank.G[:, cols].astype(float).T.reshape(len(cols), N, nk) * P
    w = np.full(nk, 2.0)  # an interior column stands for itself and its conjugate
    w[[0, -1]] = 1.0
    V = (A * np.conj(np.fft.rfft2(d)) * w).reshape(len(cols), -1)
    hh = (phase.reshape(len(centres), -1) @ V.T).real.T / N**2
    ss = (np.abs(A) ** 2 * w).sum(axis=(1, 2))[:, None]
    ny = N // 2
    mirror = (-np.arange(N)) % N
    for col, kx in ((0, 0.0), (nk - 1, np.pi)):
        a = A[:, :, col]
        pair = (a * a[:, mirror]).sum(axis=1) - a[:, ny] ** 2  # rows other than Nyquist
        rot = np.exp(-2j * kx * centres[:, 0])
        ss = ss + 0.5 * ((pair[:, None] + a[:, ny, None] ** 2 * np.exp(2j * np.pi * centres[:, 1]))
                         * rot).real - 0.5 * (np.abs(a) ** 2).sum(axis=1)[:, None]  # fmt: skip
    return hh, ss / N**2


_GL_X, _GL_W = np.polynomial.legendre.leggauss(32)


def brute_force_lnL(cfg, d, sigma, psf_img, x0, cells, amp_pow=None, amp_flux=False):
    """ln L(e) of grid cells ``cells`` by direct numerical marginalisation.

    For every model: chi-square in real space on a fine grid of sub-pixel positions,
    amplitude (> 0, uniform prior) integrated numerically, times the Gaussian position
    prior about ``x0``, integrated over position by the trapezoid rule; then summed over
    r (the point source included) with weight dr. With ``amp_pow = beta`` the amplitude
    prior is ``t^-beta dt/dA`` in the model's S/N ``t = A sqrt(sum m^2) / sigma``, for
    ``t >= 1``; with ``amp_flux`` too, it is ``A^-beta`` in the amplitude itself (for the
    same ``t >= 1``).
    """
    bank = model_bank(cfg)
    P = psf_transform(psf_img, N)
    n_r = bank.n_r
    b = cfg.position_prior_sigma
    # the peak of the cross-correlation with a near-round model of r = 2 px
    ie_round = np.argmin(np.hypot(*(bank.egrid - 0.01).T))
    ref = [ie_round * n_r + int(np.argmin(np.abs(bank.radii - 2.0)))]
    yy, xx = np.mgrid[-6:7, -6:7]
    c0 = np.column_stack([xx.ravel(), yy.ravel()]).astype(float) + N // 2
    p0 = c0[np.argmax(_model_products(cfg, ref, P, c0, d)[0][0])]
    fine = np.linspace(-0.6, 0.6, 61)
    fx, fy = np.meshgrid(fine, fine)
    cf = p0 + np.column_stack([fx.ravel(), fy.ravel()])
    hr, sr = _model_products(cfg, ref, P, cf, d)
    ll = (hr[0] ** 2 / sr[0]).reshape(61, 61)
    iy, ix = np.unravel_index(np.argmax(ll), ll.shape)
    pk = np.array([p0[0] + fine[ix], p0[1] + fine[iy]])
    ix = min(max(ix, 1), 59)
    curv = -(ll[iy, ix - 1] - 2 * ll[iy, ix] + ll[iy, ix + 1]) / (2 * sigma**2 * 0.02**2)
    sp = 1.0 / np.sqrt(max(curv, 1e-3))  # position width of the round model
    # a grid wide enough for the broadest model of the cells (elongated ones at low S/N)
    half = float(np.clip(16 * sp, 0.3, 4.0))
    g = np.linspace(-half, half, 71)
    gx, gy = np.meshgrid(g, g)
    cen = pk + np.column_stack([gx.ravel(), gy.ravel()])
    prior = np.exp(-((cen - x0) ** 2).sum(1) / (2 * b * b)) / (2 * np.pi * b * b)
    phase = _phases(cen)

    def ln_marg(cols):
        hh, ss = _model_products(cfg, cols, P, cen, d, phase)  # (m, p)
        # amplitude integral, numerically on an interval adapted to each (model, position):
        # 32-node Gauss-Legendre, within 1e-6 of a 20,001-node trapezoid (a 201-node
        # trapezoid is off by up to 0.007 where the interval is cut at its lower end)
        w = sigma / np.sqrt(ss)
        a_hat = hh / ss
        lo = np.maximum(a_hat - 10 * w, 0.0 if amp_pow is None else w)
        half_len = 0.5 * (np.maximum(a_hat, lo) + 10 * w - lo)[..., None]
        amp = lo[..., None] + half_len * (1.0 + _GL_X)
        chi = (ss[..., None] * amp**2 - 2 * hh[..., None] * amp) / (2 * sigma**2)
        if amp_pow is not None and amp_flux:  # -ln of the prior density in A
            chi = chi + amp_pow * np.log(amp)
        elif amp_pow is not None:
            t = amp / w[..., None]
            chi = chi + amp_pow * np.log(t) + np.log(w)[..., None]
        cmin = chi.min(axis=-1, keepdims=True)
        la = np.log((np.exp(-(chi - cmin)) * _GL_W * half_len).sum(axis=-1)) - cmin[..., 0]
        # position integral with the prior (trapezoid on the regular grid)
        m = la.max(axis=1, keepdims=True)
        f = (np.exp(la - m) * prior).reshape(len(cols), len(g), len(g))
        return np.log(np.trapezoid(np.trapezoid(f, g, axis=2), g, axis=1)) + m[:, 0]

    star = ln_marg([bank.n_models - 1])[0] + np.log(bank.star_weight)
    out = np.full(bank.n_e, np.nan)
    for ie in cells:
        lr = ln_marg(list(range(ie * n_r, (ie + 1) * n_r))) + np.log(bank.r_weights)
        # the engine's quadrature over r: the weighted grid sum, corrected for sub-step peaks
        k = int(np.argmax(lr))
        f = _narrow_peak_factor(*lr[k - 1 : k + 2]) if 0 < k < n_r - 1 else 1.0
        out[ie] = np.logaddexp(np.logaddexp.reduce(lr) + np.log(f), star)
    return out


def _galaxy(snr, offset, e=(0.25, -0.15), r=2.0, psf="moffat_e1", seed=3):
    rng = np.random.default_rng(seed)
    psf_obj = PSFS[psf]
    img = draw(galsim.Convolve(galsim_model("exponential", r, *e), psf_obj), offset=offset)
    flux = snr / np.sqrt((img**2).sum())  # matched-filter S/N with sigma = 1
    return img * flux + rng.normal(size=img.shape), draw(psf_obj)


@pytest.mark.xdist_group("bank_e0.025")  # one worker builds the fine grid's bank, once
@pytest.mark.parametrize(
    "snr,offset,e_step",
    [(10, (0.7, -0.4), 0.1), (30, (3.8, 1.1), 0.1), (100, (0.3, 0.2), 0.025),
     (200, (-2.6, 3.1), 0.025)],
)  # fmt: skip
def test_laplace_matches_brute_force(snr, offset, e_step):
    """ln L(e) differences within 0.05 of brute force where L > 1e-3 of its peak.

    At S/N 100-200 the likelihood is narrower than the paper's grid step, so those cases
    use a finer grid (0.025) to have a region worth the name, cut at ``|e| < 0.6`` (the
    galaxy's is 0.29): a third of the models, whose bank takes a third of the time.
    """
    e_max = 1.0 if e_step >= 0.1 else 0.6
    cfg = Config.paper(model="exponential", r_step=0.5, r_max=6.0, e_step=e_step, e_max=e_max)
    sigma = 1.0
    d, psf_img = _galaxy(snr, offset)
    x0 = np.array([N // 2, N // 2], dtype=float)  # catalogue position: the stamp centre
    fits = fit_stamps(d, psf_img, sigma, config=cfg.replace(dtype="float64"))
    eng = fits.lnL[0].astype(float)
    # up to 16 cells spread over the region where L > 1e-3 of the peak, and up to 4 deeper
    # ones down to L ~ 1e-4, always including the deepest
    order = np.argsort(eng)
    inside = order[eng[order] > np.log(1e-3)]
    outside = order[(eng[order] > -9) & (eng[order] <= np.log(1e-3))]
    pick = lambda a, k: a[np.unique(np.linspace(0, a.size - 1, min(k, a.size)).astype(int))]  # noqa: E731
    cells = np.concatenate([pick(inside, 16), pick(outside, 4)]).astype(int)
    brute = brute_force_lnL(cfg, d, sigma, psf_img, x0, cells)
    ref = np.nanargmax(brute)
    db = brute - brute[ref]
    de = eng - eng[ref]
    region = db > np.log(1e-3)
    # at S/N 200 only 4 cells of the 0.025 grid lie inside the region
    assert region.sum() >= 4
    err = np.abs(de[region] - db[region])
    assert err.max() < 0.05, f"max |d lnL| = {err.max():.3f} at S/N {snr}"
    if snr <= 30:  # the S/N-power-law amplitude prior, against its own brute force
        cs = cfg.replace(dtype="float64", amplitude_prior="snr", amplitude_prior_power=2.0)
        es = fit_stamps(d, psf_img, sigma, config=cs).lnL[0].astype(float)
        bs = brute_force_lnL(cs, d, sigma, psf_img, x0, cells, amp_pow=2.0)
        err = np.abs((es - es[ref]) - (bs - bs[ref]))[region]
        assert err.max() < 0.05, f"snr prior: max |d lnL| = {err.max():.3f} at S/N {snr}"
        if snr == 10:  # where it differs from the uniform prior by more than that (the
            # uniform prior weights every model by 1 / sqrt(sum m^2))
            assert np.max(np.abs((bs - bs[ref]) - db)[region]) > 0.1
        # the power law in the flux, the same for every model
        cf = cs.replace(amplitude_prior="flux")
        ef = fit_stamps(d, psf_img, sigma, config=cf).lnL[0].astype(float)
        bf = brute_force_lnL(cf, d, sigma, psf_img, x0, cells, amp_pow=2.0, amp_flux=True)
        err = np.abs((ef - ef[ref]) - (bf - bf[ref]))[region]
        assert err.max() < 0.05, f"flux prior: max |d lnL| = {err.max():.3f} at S/N {snr}"
        if snr == 10:  # it differs from the S/N power law by sqrt(sum m^2) per model
            assert np.max(np.abs((bf - bf[ref]) - (bs - bs[ref]))[region]) > 0.1
    # the float32 default agrees with float64 to well within that tolerance: its rounding
    # is a fixed fraction of ln L's range, S/N^2 / 2 (measured 0.0005 at S/N 30, 0.012 at
    # 200: ~6e-7 of it)
    f32 = fit_stamps(d, psf_img, sigma, config=cfg).lnL[0]
    assert np.max(np.abs(f32 - fits.lnL[0])[region]) < 1e-3 + 1e-6 * snr**2 / 2


@pytest.mark.parametrize("model", ["exponential", "devaucouleurs", "bulge+disc"])
@pytest.mark.parametrize("e", [(0.3, 0.1), (-0.2, 0.45), (0.12, -0.33)])
def test_noise_free_peak_at_input_ellipticity(model, e):
    psf = PSFS["kolmogorov_e2"]
    cfg = Config.paper(model=model)
    img = draw(galsim.Convolve(galsim_model(model, 2.5, *e), psf), offset=(0.3, -0.4)) * 1e3
    fits = fit_stamps(img, draw(psf), 1.0, config=cfg)
    peak = fits.egrid[np.argmax(fits.lnL[0])]
    assert np.all(np.abs(peak - e) <= cfg.e_step + 1e-9)
    assert np.hypot(*(peak - e)) < cfg.e_step
    assert not fits.is_star[0] and fits.flags[0] == 0
    assert fits.r_best[0] == pytest.approx(2.5, abs=0.21)
    assert fits.x[0] == pytest.approx(N // 2 + 0.3, abs=0.02)
    assert fits.y[0] == pytest.approx(N // 2 - 0.4, abs=0.02)


@pytest.mark.parametrize("model", ["exponential", "devaucouleurs", "bulge+disc"])
@pytest.mark.parametrize("e", [(0.25, -0.15), (0.05, 0.35)])
def test_flux_of_an_on_grid_galaxy(model, e):
    """With e and r on the grid the best model is the true one, and its amplitude the flux.

    The PSF image, normalised on its 32x32 stamp, misses the Kolmogorov wings beyond it
    (0.6% of the flux), so the model's unit flux stands for that fraction of the galaxy's.
    """
    psf = PSFS["kolmogorov_e2"]
    img = draw(galsim.Convolve(galsim_model(model, 2.4, *e), psf), offset=(0.3, -0.4)) * 1e3
    fits = fit_stamps(img, draw(psf), 1.0, config=Config.paper(model=model))
    assert np.allclose(fits.egrid[np.argmax(fits.lnL[0])], e)
    assert fits.r_best[0] == pytest.approx(2.4)
    assert fits.flux[0] == pytest.approx(1e3 * draw(psf).sum(), rel=2e-3)


def test_point_source_is_a_star(rng):
    psf = PSFS["moffat_e1"]
    img = draw(psf, offset=(-0.25, 0.4)) * 2e3 + rng.normal(size=(N, N))
    fits = fit_stamps(img, draw(psf), 1.0)
    assert fits.is_star[0] and fits.r_best[0] == 0.0
    assert fits.flags[0] & flag_value("STAR")


@pytest.mark.parametrize("offset", [(0.0, 0.0), (2.5, -1.5), (-5.0, 0.0), (3.0, 4.0)])
def test_catalogue_offset_does_not_move_the_peak(offset):
    """Paper Fig. 2, lower right: catalogue positions off by up to 5 px."""
    psf = PSFS["moffat_round"]
    e = (0.35, -0.25)
    img = draw(galsim.Convolve(galsim_model("exponential", 2.0, *e), psf)) * 800
    img = img + np.random.default_rng(7).normal(size=img.shape)
    centres = (np.array([N // 2 + offset[0]]), np.array([N // 2 + offset[1]]))
    cfg = Config.paper(model="exponential")
    fits = fit_stamps(img, draw(psf), 1.0, config=cfg, centres=centres)
    base = fit_stamps(img, draw(psf), 1.0, config=cfg)
    assert np.argmax(fits.lnL[0]) == np.argmax(base.lnL[0])
    assert np.hypot(*(fits.egrid[np.argmax(fits.lnL[0])] - e)) < cfg.e_step
    assert fits.x[0] == pytest.approx(base.x[0], abs=0.01)
    assert fits.y[0] == pytest.approx(base.y[0], abs=0.01)
    assert np.hypot(fits.x[0] - N // 2, fits.y[0] - N // 2) < 0.2  # S/N 60: sigma_x ~ 0.05


def test_flat_likelihood_at_very_low_snr_and_negative_correlation(rng):
    psf = PSFS["moffat_round"]
    noise = rng.normal(size=(3, N, N))
    noise[2] = -draw(galsim.Convolve(galsim.Exponential(scale_radius=2), psf)) * 300
    fits = fit_stamps(noise, draw(psf), 1.0)
    assert np.all(np.isfinite(fits.lnL))
    # pure noise: the likelihood is broad, no cell more than a few e-folds below the peak
    assert np.all(np.ptp(fits.lnL[:2], axis=1) < 15)
    # a negative galaxy: positive-flux prior keeps it finite and flat, and flags NO_PEAK
    assert fits.flags[2] & flag_value("NO_PEAK")
    assert np.ptp(fits.lnL[2]) < 15


def test_bad_stamps_are_flagged_not_raised(rng):
    psf = PSFS["moffat_round"]
    gal = draw(galsim.Convolve(galsim.Exponential(scale_radius=2), psf)) * 500
    stamps = gal[None] + rng.normal(size=(4, N, N))
    stamps[1, 3, 4] = np.nan
    sigma = np.array([1.0, 1.0, 0.0, 1.0])
    fits = fit_stamps(stamps, draw(psf), sigma)
    assert fits.flags[1] & flag_value("BAD_PIXELS")
    assert fits.flags[2] & flag_value("BAD_NOISE")
    assert np.all(np.isnan(fits.lnL[1])) and np.all(np.isnan(fits.lnL[2]))
    assert np.all(np.isfinite(fits.lnL[[0, 3]]))
    assert fits.flags[0] == 0 and fits.flags[3] == 0


def test_galaxy_partly_outside_the_stamp(rng):
    """A galaxy whose centre is 13 px from the middle of a 32 px stamp still fits."""
    psf = PSFS["moffat_round"]
    big = draw(galsim.Convolve(galsim_model("exponential", 2.0, 0.3, 0.0), psf), n=64) * 800
    big = big + rng.normal(size=big.shape)
    fits = fit_stamps(big, draw(psf), 1.0, centres=(np.array([45.0]), np.array([32.0])),
                      config=Config.paper(model="exponential"))  # fmt: skip
    assert np.all(np.isfinite(fits.lnL))
    assert fits.flags[0] == 0


def test_larger_input_stamps_are_cut_to_config_size(rng):
    psf = PSFS["moffat_round"]
    gal = galsim.Convolve(galsim_model("exponential", 2.0, -0.3, 0.2), psf)
    big = draw(gal, n=48) * 800
    small = draw(gal) * 800
    noise = rng.normal(size=(48, 48))
    cfg = Config.paper(model="exponential")
    f_big = fit_stamps(big + noise, draw(psf), 1.0, config=cfg)
    f_small = fit_stamps(small + noise[8:40, 8:40], draw(psf), 1.0, config=cfg)
    assert np.allclose(f_big.lnL, f_small.lnL, atol=1e-3)


def test_fits_do_not_depend_on_the_blas_threads(rng):
    """The products run on one BLAS thread whatever the caller allows, so the fits are
    the same bit for bit under one and two BLAS threads (a threaded float32 product sums
    in another order: ln L differed by up to 4e-4 before)."""
    from threadpoolctl import threadpool_limits

    psf = PSFS["moffat_round"]
    stamps = np.stack([draw(galsim.Convolve(galsim_model("bulge+disc", r, e1, -e1), psf)) * f
                       for r, e1, f in zip(rng.uniform(1, 3, 150), rng.uniform(-.5, .5, 150),
                                           rng.uniform(50, 400, 150), strict=True)])  # fmt: skip
    stamps += rng.normal(size=stamps.shape)
    cfg = Config.paper(model="bulge+disc", n_bulge_fractions=3)
    with threadpool_limits(1, user_api="blas"):
        one = fit_stamps(stamps, draw(psf), 1.0, config=cfg)
    with threadpool_limits(2, user_api="blas"):
        two = fit_stamps(stamps, draw(psf), 1.0, config=cfg)
    np.testing.assert_array_equal(one.lnL, two.lnL)
    np.testing.assert_array_equal(one.lnL_peak, two.lnL_peak)
    np.testing.assert_array_equal(one.x, two.x)


def test_wrong_shapes_raise():
    with pytest.raises(ValueError, match="stamps"):
        fit_stamps(np.zeros(5), np.ones((5, 5)), 1.0)
    with pytest.raises(ValueError, match="noise_sigma"):
        fit_stamps(np.zeros((3, N, N)), np.ones((5, 5)), np.ones(2))
    with pytest.raises(ValueError, match="PSF"):
        fit_stamps(np.zeros((3, N, N)), np.full((5, 5), np.nan), 1.0)


def test_stampfits_roundtrip(tmp_path, rng):
    psf = PSFS["moffat_round"]
    gal = draw(galsim.Convolve(galsim.Exponential(scale_radius=2), psf)) * 500
    fits = fit_stamps(gal[None] + rng.normal(size=(3, N, N)), draw(psf), 1.0,
                      config=Config.paper())
    path = tmp_path / "fits.fits"
    fits.write(path)
    back = type(fits).read(path)
    assert np.array_equal(back.lnL, fits.lnL)
    assert back.lnL_bulge is None and fits.lnL_bulge is None
    cfg = Config.paper(model="bulge+disc", n_bulge_fractions=3, r_max=6.0)
    fb = fit_stamps(gal[None] + rng.normal(size=(2, N, N)), draw(psf), 1.0, config=cfg)
    fb.write(tmp_path / "fb.fits")
    bb = type(fb).read(tmp_path / "fb.fits")
    assert np.array_equal(bb.lnL_bulge, fb.lnL_bulge) and bb.lnL_bulge.shape[1] == 3
    assert np.array_equal(bb.lnL_star, fb.lnL_star)
    np.testing.assert_allclose(bb.bulge_fractions, [0.0, 0.5, 1.0])
    assert np.allclose(back.egrid, fits.egrid)
    assert np.array_equal(back.flags, fits.flags)
    with pytest.raises(FileExistsError):
        fits.write(path)


@pytest.mark.parametrize("width", [0.15, 0.3, 0.6, 0.9, 1.2, 3.0])
def test_r_quadrature_exact_for_gaussian_peaks(width):
    """Grid sum x narrow-peak factor = the integral of a Gaussian, at any sub-step offset.

    The plain grid sum of a Gaussian of width 0.3 steps oscillates by ~10% with the
    peak's sub-step position (the r-grid jumps of bright galaxies' L(e)); corrected, it is
    the integral to 1e-8 for widths under one step and to 3e-9 (the trapezoid rule's
    own error) above.
    """
    j = np.arange(-40, 41)
    plain = []
    for d in np.linspace(-0.5, 0.5, 11):
        lnl = -0.5 * (j - d) ** 2 / width**2
        k = int(np.argmax(lnl))
        f = _narrow_peak_factor(lnl[k - 1], lnl[k], lnl[k + 1])
        exact = np.sqrt(2 * np.pi) * width
        assert abs(np.exp(lnl).sum() * f / exact - 1) < 1e-8
        plain.append(np.exp(lnl).sum() / exact)
    if width <= 0.3:  # the uncorrected sum is visibly wrong there
        assert np.ptp(plain) > 0.05


def test_prior_edge_is_not_read_as_a_narrow_peak():
    """At a size prior's edge ``ln(w L)`` falls by ~9 e-folds (the 1e-4 floor): the
    parabola through it reads a peak a third of a step wide and would inflate the edge
    node by ~30%. The factor there comes from ``ln L`` alone."""
    lw_floor = np.log(1e-4)
    lm, l0, lp = -0.30, -0.20, -0.25  # a broad likelihood, rising toward small sizes
    assert _narrow_peak_factor(lm + lw_floor, l0, lp) > 1.2  # the cliff read as a peak
    kink = lw_floor  # second difference of ln w over the floor, 0, 0 at the three nodes
    assert _run_peak_factor(lm + lw_floor, l0, lp, lm, l0, lp, kink) == 1.0
    # a likelihood narrower than the step that peaks at the edge node keeps its factor
    nm, n0, np_ = -4.0, 0.0, -3.0
    f = _run_peak_factor(nm + lw_floor, n0, np_, nm, n0, np_, kink)
    assert f == _narrow_peak_factor(nm, n0, np_) and f != 1.0
    # ... and one that peaks below the edge gets none
    assert _run_peak_factor(0.0 + lw_floor, -2.0, -5.0, 0.0, -2.0, -5.0, kink) == 1.0
    # a smooth prior: the factor of ln(w L), as before
    lw = (-3.0, 0.0, -2.5)
    assert _run_peak_factor(*lw, -3.1, 0.0, -2.4, 0.2) == _narrow_peak_factor(*lw)


def test_box_size_prior_edge_moves_l_e_continuously(rng):
    """A box prior's lower edge swept across one node of the size grid: ``L(e)`` of a
    faint galaxy changes smoothly (each node's share of the box is its hat's overlap),
    not in one jump when the edge crosses the node, as with the prior read at the
    nodes alone."""
    from pylensfit.prior.size import SizePrior, node_sizes

    cfg = Config.paper(model="exponential", e_step=0.2)
    bank = model_bank(cfg)
    _, _, h = node_sizes(bank, cfg)
    x = np.log(h)
    j = int(np.searchsorted(x, np.log(1.2)))
    step = x[j + 1] - x[j]
    psf = draw(PSFS["moffat_round"])
    img = draw(galsim.Convolve(galsim_model("exponential", 1.3, 0.2, 0.1),
                               PSFS["moffat_round"]))  # fmt: skip
    stamp = img * 15.0 / np.sqrt((img**2).sum()) + rng.normal(size=img.shape)
    hi = np.log(8.0)
    got = []
    for lo in x[j] + step * np.linspace(-0.45, 0.45, 7):
        kn = np.array([lo - 1e-6, lo, hi, hi + 1e-6])
        sp = SizePrior(ln_h=kn, density=np.array([0.0, 1.0, 1.0, 0.0]) / (hi - lo))
        f = fit_stamps(stamp, psf, 1.0, config=cfg, size_prior=sp)
        got.append(f.lnL[0].astype(float) + f.lnL_peak[0])
    d = np.abs(np.diff(np.array(got), axis=0)).max(axis=1)  # per 0.15 steps of the edge
    # even steps: the largest within 1.5x of the mean (a jump puts all in one step)
    assert d.max() < 1.5 * d.mean(), d
    assert d.mean() > 1e-4  # the edge does move L(e)


def test_marginal_bulge_fraction_is_the_mean_of_fixed_fraction_fits():
    """With n bulge fractions, L(e) = the mean over the fractions of the fixed-fraction L(e),
    each weighted by its half-light radius per unit r (a size prior uniform in half-light
    radius whatever the fraction).

    A bright, resolved galaxy (the point-source term negligible) so that the three
    fixed-fraction fits and the marginal one see the same models; ln L is compared in
    absolute terms (``lnL + lnL_peak``) over the region where L > 1e-3 of its peak. The
    per-fraction grids ``lnL_bulge`` are the fixed-fraction fits themselves, and
    re-mixing them with one-hot weights gives each fixed-fraction ``lnL``.
    """
    from scipy.special import logsumexp

    from pylensfit.prior import mix_bulge_fractions

    psf = PSFS["moffat_e1"]
    img = draw(galsim.Convolve(galsim_model("bulge+disc", 2.5, 0.2, -0.1, bulge_fraction=0.3),
                               psf))  # fmt: skip
    d = img * 30.0 / np.sqrt((img**2).sum()) + np.random.default_rng(2).normal(size=img.shape)
    base = Config.paper(model="bulge+disc", e_step=0.1, r_step=0.25, r_max=6.0, dtype="float64")
    marg = fit_stamps(d, draw(psf), 1.0, config=base.replace(n_bulge_fractions=3))
    fixed = [fit_stamps(d, draw(psf), 1.0, config=base.replace(bulge_fraction=b))
             for b in (0.0, 0.5, 1.0)]  # fmt: skip
    ab = np.array([f.lnL[0].astype(float) + f.lnL_peak[0] for f in fixed])
    jac = np.array([half_light_radius("bulge+disc", bulge_fraction=b) for b in (0.0, 0.5, 1.0)])
    jac /= jac[0]
    np.testing.assert_allclose(jac, [1.0, 0.6729, 0.3575], atol=2e-4)  # GalSim: 1.12935/1.678
    ab += np.log(jac)[:, None]
    total = logsumexp(ab, axis=0) - np.log(3.0)
    mine = marg.lnL[0].astype(float) + marg.lnL_peak[0]
    region = mine - mine.max() > np.log(1e-3)
    assert region.sum() >= 4
    assert np.max(np.abs(mine[region] - total[region])) < 0.01, np.abs(mine - total)[region]
    np.testing.assert_allclose(marg.bulge_fractions, [0.0, 0.5, 1.0])
    per = marg.lnL_bulge[0].astype(float) + marg.lnL_peak[0]
    for k in range(3):
        near = ab[k] - ab[k].max() > np.log(1e-3)
        assert near.sum() >= 4
        assert np.max(np.abs(per[k][near] - ab[k][near])) < 0.01
        one_hot = mix_bulge_fractions(marg.lnL_bulge, marg.lnL_star, np.eye(3)[k])[0]
        assert np.max(np.abs(one_hot[near] - fixed[k].lnL[0][near])) < 0.01
    uniform = mix_bulge_fractions(marg.lnL_bulge, marg.lnL_star)
    np.testing.assert_allclose(uniform[0][region], marg.lnL[0][region], atol=1e-4)
    # the bank: three runs of the radius grid per e cell, the fractions in order
    bank = model_bank(base.replace(n_bulge_fractions=3))
    assert bank.n_sizes * 3 == bank.n_r and bank.n_models == bank.n_e * bank.n_r + 1
    np.testing.assert_allclose(np.unique(bank.bulge), [0.0, 0.5, 1.0])
    # the best model of a disc-dominated galaxy is not the pure bulge
    assert marg.r_best[0] > 0


def test_one_profile_models_ignore_the_bulge_disc_family_settings():
    cfg = Config(model="exponential", n_bulge_fractions=3, sersic_ladder=(0.5, 2.0))
    assert cfg.n_bulge_fractions == 1 and cfg.sersic_ladder == () and len(cfg.bulge_runs) == 1


@pytest.mark.parametrize(
    "cfg",
    [Config.paper(), Config.paper(model="bulge+disc", n_bulge_fractions=3),
     Config.paper(stamp_size=33, e_step=0.2, r_max=5.0, model="exponential"),
     Config.paper(stamp_size=64, e_step=0.2, r_max=5.0, model="exponential", k_max=np.pi / 2)],
)  # fmt: skip
def test_folded_products_equal_the_direct_products(cfg):
    """The symmetry-folded products give every model's sum over frequencies exactly."""
    bank = model_bank(cfg)
    fb = folded_bank(cfg, bank)
    n = cfg.stamp_size
    kx, ky, w = rfft_frequencies(n)
    rng = np.random.default_rng(1)
    # rows of even functions of k on the rfft half-plane (the kx = 0 column even in ky)
    R = rng.normal(size=(5, *kx.shape))
    R[:, :, 0] = 0.5 * (R[:, :, 0] + R[:, (-np.arange(n)) % n, 0])
    R = R.reshape(5, -1)
    Rw = R * (w / n**2).ravel() * interior(n, cfg.k_max)
    if bank.rows is not None:  # the disc |k| <= k_max: the bank holds its frequencies only
        assert not Rw[:, np.setdiff1d(np.arange(Rw.shape[1]), bank.rows)].any()
        Rw = Rw[:, bank.rows]
    direct = Rw @ bank.G.astype(float)
    Rf = R[:, fb.idx]
    A = np.stack([
        (np.einsum("h,rhk->rk", CHI[c], Rf[:, :, fb.keep[c]]) * fb.coef[fb.keep[c]])
        @ fb.G[c].astype(float) for c in range(4)
    ])  # fmt: skip
    # the mixed bulge fractions: from the pure disc's and pure bulge's columns
    f = fb.mix_f[None, None, :]
    A = np.concatenate([A, (1 - f) * A[:, :, fb.mix_a] + f * A[:, :, fb.mix_b]], axis=2)
    assert A.shape[2] == fb.members.shape[0]
    if cfg.model == "bulge+disc" and cfg.n_bulge_fractions == 3:
        assert fb.mix_a.size == fb.members.shape[0] // 3  # a third of the columns mixed
    folded = np.full_like(direct, np.nan)
    for h in range(4):
        ok = fb.members[:, h] >= 0
        folded[:, fb.members[ok, h]] = np.einsum("c,crj->rj", CHI[:, h], A[:, :, ok])
    assert not np.isnan(folded).any()  # every model is some column's image
    assert np.abs(folded - direct).max() < 1e-6 * np.abs(direct).max()
    # a quarter of the operations: the octant's characters against the half-plane
    n_ops = sum(g.size for g in fb.G)
    assert n_ops < 0.3 * interior(n, cfg.k_max).sum() * bank.n_models


@pytest.mark.parametrize("ladder", [(), (0.5, 2.0, 4.0)])
def test_mixed_bulge_fractions_equal_their_own_products(rng, monkeypatch, ladder):
    """The kernel's mixed columns (the middle bulge fraction from the pure disc's and
    pure bulge's products; with the Sersic ladder also each half-and-half mixture from
    its two Sersic profiles') give the fits that the runs' own columns give."""
    import pylensfit.likelihood.folded as lk

    cfg = Config.paper(model="bulge+disc", n_bulge_fractions=3, e_step=0.2, sersic_ladder=ladder)
    bank = model_bank(cfg)
    n_orb = int(((bank.egrid[:, 0] > 0) & (bank.egrid[:, 1] > 0)).sum())
    n_mixed = 4 if ladder else 1  # 0.5 (of 0 and 1); Sersic 0.5+1, 1+2 and 2+4
    assert lk.folded_bank(cfg, bank).mix_a.size == n_orb * n_mixed * bank.n_sizes
    psf = draw(PSFS["moffat_e1"])
    imgs = [draw(galsim.Convolve(galsim_model("bulge+disc", r, *e, bulge_fraction=bf),
                                 PSFS["moffat_e1"]))
            for r, e, bf in ((1.5, (0.3, -0.2), 0.5), (0.8, (-0.1, 0.4), 0.2))]  # fmt: skip
    imgs.append(draw(galsim.Convolve(galsim.Sersic(n=1.5, half_light_radius=2.0).shear(
        g1=0.2, g2=0.1), PSFS["moffat_e1"])))  # fmt: skip
    stamps = np.stack([img * f for img, f in zip(imgs, (25.0, 150.0, 80.0), strict=True)])
    stamps += rng.normal(size=stamps.shape)
    mixed = fit_stamps(stamps, psf, 1.0, config=cfg)
    assert lk.folded_bank(cfg, model_bank(cfg)).mix_a.size > 0
    lk._FOLDED.clear()
    monkeypatch.setattr(lk, "mixed_columns", lambda bank, n_orb: (
        np.arange(n_orb * bank.n_r + 1), *lk.NO_MIX[:1] * 2, lk.NO_MIX[1]))  # fmt: skip
    own = fit_stamps(stamps, psf, 1.0, config=cfg)
    assert lk._FOLDED[next(iter(lk._FOLDED))][1].mix_a.size == 0
    lk._FOLDED.clear()
    # float32 products of the mixed columns against the mix of float32 products
    np.testing.assert_allclose(mixed.lnL_bulge, own.lnL_bulge, atol=2e-3)
    np.testing.assert_allclose(mixed.lnL, own.lnL, atol=2e-3)
    np.testing.assert_array_equal(mixed.r_best, own.r_best)


def test_sizes_outside_the_size_prior_are_not_evaluated(rng, monkeypatch):
    """The sizes a size prior leaves out (``size_prior_cut``) have no columns in the
    matrix products or the kernel, except the pure fractions' that feed a mixed column:
    the fits are those of the whole bank with the same weights to rounding (float64;
    a BLAS may round a column's product differently in matrices of other widths: 1e-13
    in ``ln L_star`` with numpy 2.4's OpenBLAS), and ``L(r)`` is 0 at the sizes left
    out."""
    import pylensfit.likelihood.folded as lk
    import pylensfit.likelihood.priors as priors
    from pylensfit.prior import SizePrior

    cfg = Config.paper(model="bulge+disc", n_bulge_fractions=3, e_step=0.2, dtype="float64")
    bank = model_bank(cfg)
    knots = np.linspace(np.log(0.3), np.log(6.0), 40)
    sp = SizePrior(ln_h=knots, density=np.exp(-0.5 * ((knots - np.log(1.5)) / 0.4) ** 2),
                   star=1e-4)  # fmt: skip
    w, _ = sp.node_weights(bank, cfg)
    on = w > 0
    assert 0.3 * on.size < on.sum() < 0.8 * on.size
    psf = draw(PSFS["moffat_e1"])
    imgs = [draw(galsim.Convolve(galsim_model("bulge+disc", r, *e, bulge_fraction=bf),
                                 PSFS["moffat_e1"]))
            for r, e, bf in ((1.5, (0.3, -0.2), 0.5), (0.8, (-0.1, 0.4), 0.2),
                             (3.0, (0.1, 0.1), 0.9))]  # fmt: skip
    stamps = np.stack([img * f for img, f in zip(imgs, (25.0, 150.0, 60.0), strict=True)])
    stamps += rng.normal(size=stamps.shape)
    cut = fit_stamps(stamps, psf, 1.0, config=cfg, size_prior=sp)
    fb = lk.folded_bank(cfg, bank)
    sub = lk.active_columns(fb, bank, on)
    n_on = on.reshape(3, -1)
    # the kernel's columns: the active sizes' (one per e orbit) and the point source
    n_orb = (fb.members.shape[0] - 1) // bank.n_r
    assert sub.members.shape[0] == n_orb * on.sum() + 1
    # the products: the pure fractions' active sizes and those the middle one needs
    feeds = (n_on[0] | n_on[1]).sum() + (n_on[2] | n_on[1]).sum()
    assert sub.G[0].shape[1] == n_orb * feeds + 1 < fb.G[0].shape[1]
    monkeypatch.setattr(priors, "active_columns", lambda fb, bank, active: fb)
    every = fit_stamps(stamps, psf, 1.0, config=cfg, size_prior=sp)
    for k in ("lnL", "lnL_bulge", "lnL_r", "lnL_star"):
        np.testing.assert_allclose(getattr(cut, k), getattr(every, k), rtol=1e-12, atol=1e-10)
    np.testing.assert_array_equal(cut.r_best, every.r_best)
    assert np.isneginf(cut.lnL_r[:, :-1][:, ~on]).all()
    assert np.isfinite(cut.lnL_r[:, :-1][:, on]).all()


def test_floored_sizes_on_every_third_size_leave_galaxies_in_the_prior_alone(rng):
    """``size_prior_floor_stride=3`` evaluates a third of the floored compact sizes (each
    carrying the floor of three): galaxies whose sizes the prior covers keep their
    ``L(e)`` (to 1e-3 in ln L where it is within 10 of the peak) and posterior mean; a
    bright compact galaxy far below the prior, whose size the floor's models resolve, is
    the case the coarser sum is not for: its posterior moves (by 0.002-0.015 with these
    seeds), which also shows that the comparison can tell the two apart."""
    from pylensfit.prior import SizePrior

    cfg1 = Config.paper(model="exponential", e_step=0.2, dtype="float64", size_prior_floor_stride=1)
    cfg3 = cfg1.replace(size_prior_floor_stride=3)
    lo, hi = np.log(1.5), np.log(4.0)  # a box in half-light radius, as the precision mode's
    knots = np.concatenate([[lo - 1e-4], np.linspace(lo, hi, 30), [hi + 1e-4]])
    dens = np.concatenate([[0.0], np.full(30, 1.0 / (hi - lo)), [0.0]])
    sp = SizePrior(ln_h=knots, density=dens * (1 - 1e-4), star=1e-4)
    bank = model_bank(cfg1)
    w1, w3 = sp.node_weights(bank, cfg1)[0], sp.node_weights(bank, cfg3)[0]
    assert (w3 > 0).sum() <= (w1 > 0).sum() - 10
    psf = draw(PSFS["moffat_e1"])
    gals = ((2.5, (0.2, -0.1), 30.0), (1.0, (0.1, 0.4), 12.0), (1.8, (-0.5, 0.4), 80.0),
            (0.4, (0.5, 0.3), 150.0))  # fmt: skip
    imgs = []
    for r, e, snr in gals:
        im = draw(galsim.Convolve(galsim_model("exponential", r, *e), PSFS["moffat_e1"]))
        imgs.append(im * snr / np.sqrt((im**2).sum()))
    stamps = np.stack(imgs) + rng.normal(size=(len(imgs), *imgs[0].shape))
    f1 = fit_stamps(stamps, psf, 1.0, config=cfg1, size_prior=sp)
    f3 = fit_stamps(stamps, psf, 1.0, config=cfg3, size_prior=sp)

    def mean_e(lnL):
        p = np.exp(lnL.astype(float))
        return p @ f1.egrid / p.sum()

    for i in range(3):
        a, b = f1.lnL[i].astype(float), f3.lnL[i].astype(float)
        near = a > -10
        assert np.abs(a - b)[near].max() < 1e-3, i
        np.testing.assert_allclose(mean_e(f3.lnL[i]), mean_e(f1.lnL[i]), atol=1e-5)
    d = np.abs(mean_e(f3.lnL[3]) - mean_e(f1.lnL[3]))
    assert d.max() > 3e-4


def test_size_prior_uniform_in_half_light_radius_is_the_flat_sum(rng):
    """A SizePrior of density ~ h per unit ln h reproduces the default sum over r."""
    from pylensfit.prior.size import SizePrior, node_sizes

    cfg = Config.paper(model="bulge+disc", n_bulge_fractions=3, e_step=0.2)
    bank = model_bank(cfg)
    _, _, h = node_sizes(bank, cfg)
    knots = np.linspace(np.log(h.min()) - 0.1, np.log(h.max()) + 0.1, 400)
    c = 0.37  # any constant: the prior's normalisation is a constant in ln L
    u0 = half_light_radius("bulge+disc", bulge_fraction=0.0)
    flat = SizePrior(ln_h=knots, density=c * np.exp(knots), star=c * u0 * bank.star_weight)
    psf = draw(PSFS["moffat_round"])
    gal = galsim_model("bulge+disc", 2.0, 0.3, -0.2, bulge_fraction=0.3)
    img = draw(galsim.Convolve(gal, PSFS["moffat_round"]))
    stamps = np.stack([img * f for f in (300.0, 900.0)]) + rng.normal(size=(2, N, N))
    ref = fit_stamps(stamps, psf, 1.0, config=cfg)
    got = fit_stamps(stamps, psf, 1.0, config=cfg, size_prior=flat)
    # the knots interpolate h linearly in ln h: exact to ~(0.015^2 / 8) relative; each
    # node reads the prior's mean over its hat in ln h (half-width delta <= 0.095), h_j
    # (1 + delta^2 / 12): within 8e-4 of h_j
    np.testing.assert_allclose(got.lnL, ref.lnL, atol=1e-3)
    np.testing.assert_allclose(got.lnL_bulge, ref.lnL_bulge, atol=1e-3)
    # a prior concentrated on small sizes pulls the mixture to the compact models
    small = SizePrior(ln_h=knots, density=np.exp(-0.5 * ((knots - np.log(0.3)) / 0.1) ** 2))
    sm = fit_stamps(stamps, psf, 1.0, config=cfg, size_prior=small)
    # L(r) is the data's alone: the same under any prior, up to the shift of each row,
    # at the sizes evaluated (those above the prior's mode and its tail are not)
    on = np.append(small.node_weights(bank, cfg)[0] > 0, True)
    assert (~on).sum() > 0 and on.sum() > 20 and np.isneginf(sm.lnL_r[:, ~on]).all()

    def rel(f):
        return f.lnL_r[:, on] - f.lnL_r[:, on].max(axis=1, keepdims=True)

    # (fewer columns, other float32 roundings in the matrix products: 3e-6 at ln L -539)
    np.testing.assert_allclose(rel(sm), rel(ref), atol=1e-3, rtol=1e-5)
    assert not np.allclose(sm.lnL, ref.lnL, atol=0.1)


def test_lnL_r_by_annulus_reweights_to_another_prior(rng):
    """L(r) kept per group of equal |e| sums to the ordinary L(r), and reweighted to
    another prior it is what a fit marginalised with that prior gives (the precision
    mode's calibration takes its size prior's data this way, without a second pass)."""
    from pylensfit.likelihood import e_annuli, reweight_lnL_r
    from pylensfit.prior import Prior

    cfg = Config.paper(model="bulge+disc", n_bulge_fractions=3, e_step=0.2)
    psf = draw(PSFS["moffat_round"])
    imgs = [draw(galsim.Convolve(galsim_model("bulge+disc", r, *e, bulge_fraction=0.3),
                                 PSFS["moffat_round"]))
            for r, e in ((1.0, (0.3, -0.2)), (2.5, (-0.1, 0.5)), (0.6, (0.0, 0.1)))]  # fmt: skip
    stamps = np.stack([img * f for img, f in zip(imgs, (40.0, 300.0, 15.0), strict=True)])
    stamps += rng.normal(size=stamps.shape)
    egrid = model_bank(cfg).egrid
    grp = e_annuli(egrid)
    ee = np.hypot(*egrid.T)
    assert grp.max() + 1 == np.unique(np.round(ee, 9)).size
    assert all(np.ptp(ee[grp == a]) < 1e-9 for a in range(grp.max() + 1))
    other = Prior(B=0.3, C=1.2, D=3.0)
    ref = fit_stamps(stamps, psf, 1.0, config=cfg)
    got = fit_stamps(stamps, psf, 1.0, config=cfg, lnL_r_groups=grp)
    direct = fit_stamps(stamps, psf, 1.0, config=cfg, size_marginal_prior=other)
    assert ref.lnL_r_grouped is None
    assert got.lnL_r_grouped.shape == (3, grp.max() + 1, ref.lnL_r.shape[1])
    np.testing.assert_array_equal(got.lnL, ref.lnL)  # the groups change nothing else
    np.testing.assert_allclose(got.lnL_r, ref.lnL_r, atol=2e-5)
    rw = reweight_lnL_r(got.lnL_r_grouped, egrid, grp, None, other)
    np.testing.assert_allclose(rw, direct.lnL_r, atol=2e-5)
    # the other prior moves L(r) by far more than that: the test can fail
    assert np.abs(direct.lnL_r - ref.lnL_r).max() > 0.05
    with pytest.raises(ValueError, match="not constant"):
        reweight_lnL_r(got.lnL_r_grouped, egrid, np.arange(egrid.shape[0]) % 2, None, other)


def test_amplitude_terms_match_scipy():
    """The positive-flux terms (tabulated between -20 and 7.5) against scipy's ln Phi."""
    from scipy.special import log_ndtr

    from pylensfit.likelihood.amplitude_nb import _amplitude_terms

    t = np.concatenate([np.linspace(-30, 40, 7001), np.linspace(-20.01, -19.99, 101),
                        np.linspace(7.49, 7.51, 101)])  # fmt: skip
    got = np.array([_amplitude_terms(x) for x in t])
    val = 0.5 * t * t + log_ndtr(t)
    dl = t + np.exp(-0.5 * t * t - 0.5 * np.log(2 * np.pi) - log_ndtr(t))
    e_val = np.abs(got[:, 0] - val) / np.maximum(1, np.abs(val))
    e_dl = np.abs(got[:, 1] - dl) / np.maximum(1, np.abs(dl))
    table = (t >= -20) & (t <= 7.5)
    assert e_val[table].max() < 1e-10 and e_dl[table].max() < 1e-10
    # below -20, the asymptotic series (next term 105 / t^8 = 4e-9)
    assert e_val.max() < 2e-9 and e_dl.max() < 2e-7


def test_bounded_flux_prior_mass_matches_scipy():
    """``_bounded_mass(a, b)``: ``ln(Phi(a) - Phi(b))``, the Gaussian amplitude's mass
    between a flux prior's bounds, and its derivative, against scipy's normal CDF in
    double-double-free form (``ndtr`` differences where they are precise, ``log_ndtr``
    where ``b`` is -inf) and a central difference."""
    from scipy.special import log_ndtr, ndtr

    from pylensfit.likelihood.amplitude_nb import _bounded_mass

    for a, b in [(3.0, -np.inf), (-4.0, -np.inf), (-25.0, -np.inf), (2.0, -1.0),
                 (0.5, -0.5), (-3.0, -9.0), (9.0, 1.0), (6.0, 5.5), (1.0, 0.9),
                 (40.0, 35.0), (-0.2, -30.0)]:  # fmt: skip
        got, dgot = _bounded_mass(a, b)
        if b == -np.inf:
            want = log_ndtr(a)
        elif b > 0:
            want = np.log(ndtr(-b) - ndtr(-a))
        else:
            want = np.log(ndtr(a) - ndtr(b))
        assert abs(got - want) < 1e-9 * max(1.0, abs(want)), (a, b, got, want)
        h = 1e-5
        fd = (_bounded_mass(a + h, b + h)[0] - _bounded_mass(a - h, b - h)[0]) / (2 * h)
        assert abs(dgot - fd) < 1e-5 * max(1.0, abs(fd)), (a, b, dgot, fd)


def test_power_law_amplitude_integral_matches_quadrature():
    """The amplitude integral of a bounded power-law prior, ``0.5 t^2 + ln int_lo^hi
    u^-beta phi(u - t) du``, and its ``t`` derivative (the posterior mean of ``u``)
    against scipy's adaptive quadrature, for bounds below, at and above the model's S/N.
    The Laplace form at ``t`` that it replaced, ``0.5 t^2 - beta ln t + ln(Phi(t - lo) -
    Phi(t - hi))``, is off by more than 0.1 here (measured: up to 1.9 at ``t = 4`` against
    ``lo = 10``)."""
    from scipy.integrate import quad
    from scipy.special import log_ndtr, ndtr

    from pylensfit.likelihood.amplitude_nb import amplitude_integral

    def integrand(u, power, t, m):  # scaled by the Gaussian's value at m
        return u**power * np.exp(-0.5 * (u - t) ** 2 + 0.5 * (m - t) ** 2)

    worst_old = 0.0
    for beta in (0.0, 1.5, 2.0):
        for lo, hi in [(1.0, np.inf), (5.0, np.inf), (10.0, np.inf), (10.0, 30.0),
                       (2.0, 12.0)]:  # fmt: skip
            for t in (4.0, 6.0, 8.0, 10.0, 12.0, 20.0, 60.0):
                top = min(hi, t + 40.0)
                pts = [p for p in (t, lo + 1e-9) if lo < p < top] or None
                m = min(max(t, lo), top)
                f0, f1 = (quad(integrand, lo, top, args=(k - beta, t, m), points=pts,
                               limit=400, epsabs=0, epsrel=1e-12)[0] for k in (0, 1))  # fmt: skip
                want = 0.5 * t * t - 0.5 * (m - t) ** 2 + np.log(f0) - 0.5 * np.log(2 * np.pi)
                # the flux bounds in S/N units: amp * s * iss with s = 4, iss = 1 / 2
                got, mean = amplitude_integral(t, 4.0, np.log(4.0), 0.5, beta, 0.0,
                                               lo / 2.0, hi / 2.0)  # fmt: skip
                # measured worst: 5e-4, 3.4e-3, 1.1e-2 (value); 4.9e-3, 1.5e-2, 6.4e-2 (mean)
                tol, tol_mean = {4.0: (0.015, 0.08), 6.0: (0.005, 0.02)}.get(t, (1e-3, 6e-3))
                assert abs(got - want) < tol, (beta, lo, hi, t, got - want)
                assert abs(mean - f1 / f0) < tol_mean, (beta, lo, hi, t, mean, f1 / f0)
                mass = (log_ndtr(t - lo) if hi == np.inf
                        else np.log(max(ndtr(t - lo) - ndtr(t - hi), 1e-300)))  # fmt: skip
                old = 0.5 * t * t - beta * np.log(t) + mass
                worst_old = max(worst_old, abs(old - want))
    assert worst_old > 0.1


def test_flux_prior_bounds_favour_models_of_allowed_flux():
    """A flux prior bounded below near the galaxy's own flux takes weight from the models
    that fit it with less flux, the elongated ones for a round galaxy: at S/N ~10 their
    ln L drops by ~3 against ~0.2 for the round cells, and the posterior's rms |e|
    shrinks. A bound far below the flux changes nothing."""
    psf = draw(PSFS["moffat_round"], N)
    gal = galsim.Convolve(galsim_model("exponential", 2.0), PSFS["moffat_round"])
    rng = np.random.default_rng(3)
    stamps = draw(gal, N, flux=100.0)[None] + rng.normal(0, 1.0, (1, N, N))
    base = Config.paper(model="exponential", amplitude_prior="flux")
    f0 = fit_stamps(stamps, psf, 1.0, config=base)
    assert f0.flux[0] == pytest.approx(100.0, rel=0.1) and 8 < f0.snr[0] < 11
    far = fit_stamps(stamps, psf, 1.0, config=base.replace(amplitude_prior_min=1.0))
    np.testing.assert_allclose(far.lnL, f0.lnL, atol=1e-4)
    tight = fit_stamps(stamps, psf, 1.0, config=base.replace(amplitude_prior_min=90.0))
    drop = (tight.lnL[0] - f0.lnL[0]).astype(float)
    e = np.hypot(*f0.egrid.T)
    assert drop[e > 0.7].mean() < -2.0
    assert drop[e > 0.7].mean() < drop[e < 0.2].mean() - 2.0

    def rms_e(lnl):
        w = np.exp(lnl.astype(float))
        return np.sqrt(np.sum(w * e**2) / w.sum())

    assert rms_e(tight.lnL[0]) < rms_e(f0.lnL[0]) - 0.03


# --- stamp tiers: large galaxies on larger stamps (Config.max_stamp_size) ---------------
KOLMOGOROV_4PX = galsim.Kolmogorov(fwhm=4.0)


def _ring_responses(cfg, n_render, hlr, g=0.02, n_angles=8, snr=60.0):
    """Noise-free responses ``(<e_i>(+g_i) - <e_i>(-g_i)) / 2g`` of the posterior mean
    (the STEP prior), averaged over a ring of intrinsic shapes ``|e| = 0.2``."""
    from pylensfit import Prior
    from pylensfit.shear import posterior_moments

    imgs = []
    for a in np.arange(n_angles) * np.pi / n_angles:
        z = 0.2 * np.exp(2j * a)
        for s in (g, -g, 1j * g, -1j * g):
            gal = galsim.Exponential(half_light_radius=hlr).shear(g1=z.real, g2=z.imag)
            imgs.append(draw(galsim.Convolve(gal.shear(g1=s.real, g2=s.imag), KOLMOGOROV_4PX),
                             n=n_render))  # fmt: skip
    imgs = np.array(imgs) * snr / np.sqrt(np.sum(imgs[0] ** 2))
    fits = fit_stamps(imgs, draw(KOLMOGOROV_4PX, n=n_render), 1.0, config=cfg)
    mom = posterior_moments(fits.lnL, fits.egrid, Prior())
    e1 = mom["e1"].reshape(n_angles, 4)
    e2 = mom["e2"].reshape(n_angles, 4)
    return np.mean(e1[:, 0] - e1[:, 1]) / (2 * g), np.mean(e2[:, 2] - e2[:, 3]) / (2 * g), fits


def test_stamp_tiers_remove_the_edge_anisotropy():
    """A galaxy of 2 PSF half-light radii (5 px) under a 4-pixel Kolmogorov PSF: on a
    32-pixel stamp its posterior mean responds 1.3 % more to g2 than to g1 (the pixel
    axes see the stamp's edge nearer than the diagonals); fitted on the 64-pixel tier
    (the frequencies |k| <= pi/2) the two responses agree, as they must by symmetry."""
    cfg = Config.paper(model="exponential", position_prior_sigma=0.01)
    r1, r2, _ = _ring_responses(cfg, 32, 5.0)
    assert r2 / r1 - 1 > 5e-3
    r1, r2, fits = _ring_responses(cfg.replace(max_stamp_size=96), 96, 5.0)
    assert np.all(fits.stamp == 64)
    assert abs(r2 / r1 - 1) < 1e-3


def test_stamp_tiers_route_by_size_and_keep_input_coordinates(rng):
    """Stars and small galaxies stay on the base stamp, large ones go up a tier; the
    fitted centres are in the given stamps' pixels whatever the tier."""
    psf = draw(KOLMOGOROV_4PX, n=96)
    off = (1.3, -0.7)
    objs = [galsim.Gaussian(sigma=1e-3), galsim.Exponential(half_light_radius=1.0),
            galsim.Exponential(half_light_radius=5.0),
            galsim.Exponential(half_light_radius=9.0)]  # fmt: skip
    imgs = np.array([draw(galsim.Convolve(o, KOLMOGOROV_4PX), n=96, offset=off) for o in objs])
    imgs = imgs * 200 / np.sqrt((imgs**2).sum(axis=(1, 2)))[:, None, None]
    imgs += rng.normal(size=imgs.shape) * 0.01
    cfg = Config.paper(model="exponential", max_stamp_size=96)
    fits = fit_stamps(imgs, psf, 0.01, config=cfg)
    assert list(fits.stamp) == [32, 32, 64, 96]
    assert fits.meta["stamp_sizes"] == [32, 64, 96]
    assert np.allclose(fits.x, 48 + off[0], atol=0.05)
    assert np.allclose(fits.y, 48 + off[1], atol=0.05)
    # without tiers the same stamps are fitted on the central 32 x 32 window, in the
    # same coordinates
    one = fit_stamps(imgs[:2], psf, 0.01, config=cfg.replace(max_stamp_size=0))
    assert list(one.stamp) == [32, 32]
    assert np.allclose(one.lnL, fits.lnL[:2], atol=1e-4, equal_nan=True)
    assert np.allclose(one.x, fits.x[:2], atol=1e-6)


def test_max_stamp_size_must_be_a_multiple_of_the_stamp():
    from pylensfit.config import ConfigError

    # rounded down to a whole tier; below two base stamps, one stamp for all
    assert Config.paper(max_stamp_size=40).max_stamp_size == 0
    assert Config(stamp_size=32, max_stamp_size=100).max_stamp_size == 96
    with pytest.raises(ConfigError, match="k_max"):
        Config.paper(k_max=-1.0)


@pytest.mark.parametrize("beta", [0.0, 1.0, 2.0, 2.5, 4.0])
def test_power_law_table_matches_the_direct_integral(beta):
    """Without flux bounds the power-law amplitude integral depends on the S/N ``t``
    alone; ``amplitude_tile`` reads it off a cubic Hermite table from ``t0`` up, and
    evaluates it directly below ``t0``, above the table and within ``_PT_BOUND_MARGIN``
    of a flux bound in effect. Table and direct evaluation agree on the value and on the
    amplitude's mean (which sets the position curvature) to 1e-7 (measured: 2e-8 and
    8e-8, both worst just above ``t0``); the models off the table are the direct ones
    exactly."""
    from pylensfit.likelihood.amplitude_nb import (
        _PT_BOUND_MARGIN,
        _PT_MAX,
        amplitude_tile,
        power_law_table,
    )
    from pylensfit.likelihood.tile_nb import W_DL, W_HS, W_ISS, W_ROWS, W_VAL

    t0, tab = power_law_table(beta)
    assert t0 == max(4.0, beta + 1.5)
    rng = np.random.default_rng(11)
    n = 512
    t = np.concatenate([rng.uniform(t0, _PT_MAX - 1, 400), t0 + rng.uniform(0, 0.5, 60),
                        rng.uniform(-6, t0, 40), rng.uniform(_PT_MAX, 900, 12)])  # fmt: skip
    cm = np.zeros((6, n))
    cm[0] = rng.uniform(0.5, 3.0, n)
    cm[5] = np.log(cm[0])
    W = np.zeros((W_ROWS, n))
    W[W_ISS] = rng.uniform(0.1, 1.0, n)
    W[W_HS] = t / W[W_ISS]
    direct = W.copy()
    amplitude_tile(cm, beta, beta - 1.0, 0.0, np.inf, t0, tab, W)
    amplitude_tile(cm, beta, beta - 1.0, 0.0, np.inf, 0.0, np.empty((4, 0)), direct)
    on = (t >= t0) & (t < _PT_MAX - 1)
    np.testing.assert_allclose(W[W_VAL, on], direct[W_VAL, on], rtol=0, atol=1e-7)
    np.testing.assert_allclose(W[W_DL, on] / W[W_ISS, on], direct[W_DL, on] / W[W_ISS, on],
                               rtol=0, atol=1e-7)  # fmt: skip
    np.testing.assert_array_equal(W[:, ~on], direct[:, ~on])
    # flux bounds (in S/N units ``flux S / (sigma sqrt S)``): the models within
    # _PT_BOUND_MARGIN of a bound in effect are evaluated directly; those further inside
    # read the unbounded table, which is the bounded integral there to the table's error
    for lo, hi in ((3.0, np.inf), (3.0, 150.0), (0.0, 150.0)):
        a, b = W.copy(), W.copy()
        amplitude_tile(cm, beta, beta - 1.0, lo, hi, t0, tab, a)
        amplitude_tile(cm, beta, beta - 1.0, lo, hi, 0.0, np.empty((4, 0)), b)
        lo_u, hi_u = lo * cm[0] * W[W_ISS], hi * cm[0] * W[W_ISS]
        near = ((lo_u > 1.0) & (t - lo_u < _PT_BOUND_MARGIN)) | (hi_u - t < _PT_BOUND_MARGIN)
        inside = on & ~near
        assert near.sum() > 30 and inside.sum() > 100, (near.sum(), inside.sum())
        # a lower bound in effect and the upper one far, off the table's cases: the
        # lower bound's own evaluation (the next test); else direct
        low = (lo_u > 1.0) & (hi_u - t >= _PT_BOUND_MARGIN) & (t >= t0) & ~inside
        np.testing.assert_array_equal(a[:, ~inside & ~low], b[:, ~inside & ~low])
        np.testing.assert_allclose(a[W_VAL, low], b[W_VAL, low], rtol=0, atol=1e-7)
        np.testing.assert_array_equal(a[:, inside], W[:, inside])
        np.testing.assert_allclose(a[W_VAL, inside], b[W_VAL, inside], rtol=0, atol=1e-7)
        np.testing.assert_allclose(a[W_DL, inside] / W[W_ISS, inside],
                                   b[W_DL, inside] / W[W_ISS, inside], rtol=0, atol=1e-7)
        # where a bound is near, it changes the integral: the table would be wrong there
        close = on & near & (t > lo_u) & (t < hi_u)
        assert np.abs(b[W_VAL, close] - W[W_VAL, close]).max() > 1e-3


@pytest.mark.parametrize("beta", [0.0, 1.0, 2.0, 2.5, 4.0])
def test_lower_flux_bound_evaluation_matches_the_direct_integral(beta):
    """A model within ``_PT_BOUND_MARGIN`` of the lower flux bound and far below the
    upper one: ``amplitude_tile`` evaluates the bounded integral without the upper tail,
    with the parts that depend on ``t`` alone off the table where the interior root
    ``u*`` is above the bound (``_amplitude_integral_lo`` elsewhere). Against the
    general direct evaluation, on both sides of ``u* = lo``, on and off the table: the
    value and the amplitude's mean to 1e-7 (the table's 2e-8, the upper tail's 3e-9),
    and the bound does change them there (by more than 1e-3 from the unbounded table)."""
    from pylensfit.likelihood import amplitude_nb as K
    from pylensfit.likelihood import tile_nb as T

    t0, tab = K.power_law_table(beta)
    rng = np.random.default_rng(3)
    n = 600
    t = np.concatenate([rng.uniform(t0, 40.0, 500),
                        rng.uniform(K._PT_MAX - 30, K._PT_MAX + 30, 100)])
    d = rng.uniform(-8.0, K._PT_BOUND_MARGIN, n)  # t - lo in S/N units
    lo_flux = 5.0
    cm = np.zeros((6, n))
    W = np.zeros((T.W_ROWS, n))
    W[T.W_ISS] = rng.uniform(0.1, 1.0, n)
    lo_u = np.maximum(t - d, 1.0 + 1e-3)
    cm[0] = lo_u / (lo_flux * W[T.W_ISS])  # the model's S, so that lo_flux is lo_u in S/N
    cm[5] = np.log(cm[0])
    W[T.W_HS] = t / W[T.W_ISS]
    hi = lo_flux * (K._PT_MAX + 200.0) * 10  # far above every model
    a, b, free = W.copy(), W.copy(), W.copy()
    K.amplitude_tile(cm, beta, beta - 1.0, lo_flux, hi, t0, tab, a)
    K.amplitude_tile(cm, beta, beta - 1.0, lo_flux, hi, 0.0, np.empty((4, 0)), b)
    K.amplitude_tile(cm, beta, beta - 1.0, 0.0, np.inf, t0, tab, free)
    ustar = 0.5 * (t + np.sqrt(t * t - 4.0 * beta))
    above = ustar > lo_u
    assert above.sum() > 150 and (~above).sum() > 150
    assert (t < K._PT_MAX).sum() > 400 and (t >= K._PT_MAX).sum() > 20
    np.testing.assert_allclose(a[T.W_VAL], b[T.W_VAL], rtol=0, atol=1e-7)
    np.testing.assert_allclose(a[T.W_DL] / W[T.W_ISS], b[T.W_DL] / W[T.W_ISS], rtol=0, atol=1e-7)
    assert np.abs(a[T.W_VAL] - free[T.W_VAL])[d < 2].min() > 1e-3


# --- the tiled kernel against the per-model reference ---------------------------------
@pytest.mark.parametrize("n_chi", [1, 4])
@pytest.mark.parametrize("cubic", [False, True])
@pytest.mark.parametrize("amp", [(-np.inf, 0.0, 0.0, np.inf), (2.0, 1.0, 0.0, np.inf),
                                 (1.8, 0.8, 12.0, 80.0), (-0.7, -1.7, 12.0, 80.0)])  # fmt: skip
def test_tiled_kernel_matches_per_model_laplace(n_chi, cubic, amp):
    """``laplace_grid`` evaluates the Laplace terms a tile of models at a time, without
    branches; ``laplace_lnl`` is the same arithmetic one model at a time, with them.
    Random products that take every branch (data Hessians that are not maxima, Newton
    steps beyond the cap, cubic steps that fail, S/N below 1 and negative), more columns
    than one tile, and slots without a model: every model's ln L, the best model and its
    peak must agree to rounding, except that the kernel reads a power law without flux
    bounds off a table (``power_law_table``, within 2e-8 of the direct evaluation).
    With one size per e cell the kernel's ``ln L_k(e)`` is the model's own ``ln L`` plus
    the node's log weight, so each model is checked."""
    from pylensfit.likelihood.grid_nb import (
        Amplitude,
        Columns,
        Galaxies,
        Laplace,
        Models,
        Outputs,
        Sums,
        laplace_grid,
    )
    from pylensfit.likelihood.laplace_nb import laplace_lnl
    from pylensfit.likelihood.tile_nb import TILE

    rng = np.random.default_rng(7 + n_chi + 2 * cubic)
    n_gal, n_e = 4, (2 * TILE + 37) * n_chi
    n_mod = n_e + 1  # one size per cell, and the point source
    n_cols = -(-n_mod // n_chi) + 3
    slots = rng.permutation(n_cols * n_chi)[:n_mod]
    members = np.full(n_cols * n_chi, -1, dtype=np.int64)
    members[slots] = np.arange(n_mod)
    members = members.reshape(n_cols, n_chi)
    n_q = 10 if cubic else 6
    q = np.empty((n_chi, n_q, n_gal, n_cols))
    q[:, 0] = rng.normal(40, 40, q[:, 0].shape)
    q[:, 1:3] = rng.normal(0, 15, q[:, 1:3].shape)
    q[:, 3] = -np.abs(rng.normal(25, 12, q[:, 3].shape)) * rng.choice([1, 1, 1, -1], q[:, 3].shape)
    q[:, 4] = rng.normal(0, 8, q[:, 4].shape)
    q[:, 5] = -np.abs(rng.normal(25, 12, q[:, 5].shape))
    if cubic:
        q[:, 6:] = rng.normal(0, 6, q[:, 6:].shape)
    prod = np.ascontiguousarray(q.reshape(n_chi, n_q * n_gal, n_cols), dtype=np.float32)
    s_m = rng.uniform(0.5, 2.0, n_mod)
    mxx = -rng.uniform(0.1, 0.5, n_mod)
    myy = -rng.uniform(0.1, 0.5, n_mod)
    mxy = rng.uniform(-0.05, 0.05, n_mod)
    sigma = rng.uniform(0.8, 1.5, n_gal)
    x0 = rng.normal(0, 0.3, n_gal)
    y0 = rng.normal(0, 0.3, n_gal)
    b2, max_step = 0.1, 1.2
    node_w, w_star = np.array([0.7]), 0.3
    amp_pow = amp[0]
    outs = Outputs.empty(n_gal, n_e, 1, 1, 1)
    no_mix = np.zeros(0, dtype=np.int64)
    laplace_grid(prod, Columns(members, no_mix, no_mix, np.zeros(0)), Models(s_m, mxx, mxy, myy),
                 Galaxies(sigma, x0, y0),
                 Sums(node_w, w_star, np.zeros(1), np.full(n_e, 1.0 / n_e),
                      np.zeros(n_e, dtype=np.int64), 1),
                 Amplitude(*amp), Laplace(b2, max_step, cubic), outs)  # fmt: skip
    lnlb, lnlr, best, hbest, xb, yb = outs[1:]
    lnlr = lnlr[:, 0]
    # the reference: the square's four characters folded as the kernel does (float32)
    p = prod.reshape(n_chi, n_q, n_gal, n_cols)
    if n_chi == 4:
        s02, s13, d02, d13 = p[0] + p[2], p[1] + p[3], p[0] - p[2], p[1] - p[3]
        vals = np.stack([s02 + s13, s02 - s13, d02 + d13, d02 - d13])
    else:
        vals = p
    vals = vals.astype(float)  # (member, q, galaxy, column)
    ref = np.empty((n_gal, n_mod, 4))
    branches = set()
    for g in range(n_gal):
        for c in range(n_cols):
            for hm in range(n_chi):
                j = members[c, hm]
                if j < 0:
                    continue
                v = vals[hm, :, g, c]
                t3 = v[6:] if cubic else np.zeros(4)
                sj = s_m[j]
                ref[g, j] = laplace_lnl(tuple(v[:6]), tuple(t3), cubic,
                                        (sj, np.sqrt(sj), np.log(sj), mxx[j], mxy[j], myy[j]),
                                        (sigma[g], x0[g], y0[g]), b2, max_step**2, amp)
                det = v[3] * v[5] - v[4] ** 2
                branches.add("data" if v[3] < 0 and det > 0 else "expected")
    assert branches == {"data", "expected"}
    lnl = ref[..., 0]
    # a model whose Laplace terms are not finite (S/N < 1 under the flux prior can make
    # det M negative) drops out of the sum over r: -inf, in the kernel and the reference
    # alike; it must be rare
    bad = ~np.isfinite(lnl[:, :n_e])
    assert bad.mean() < 0.05
    want = np.where(bad, -np.inf, lnl[:, :n_e])
    # the power law's table (read by the models inside any flux bounds too), or rounding
    tol = 5e-8 if np.isfinite(amp_pow) else 1e-9
    np.testing.assert_allclose(lnlb[:, :, 0] - np.log(node_w[0]), want, rtol=1e-12, atol=tol)
    np.testing.assert_allclose(lnlr[:, 1], lnl[:, n_e], rtol=1e-12, atol=tol)
    jb = np.where(np.isfinite(lnl), lnl, -np.inf).argmax(axis=1)
    np.testing.assert_array_equal(best, jb)
    np.testing.assert_allclose(hbest, ref[np.arange(n_gal), jb, 1], rtol=1e-12, atol=tol)
    np.testing.assert_allclose(xb, ref[np.arange(n_gal), jb, 2], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(yb, ref[np.arange(n_gal), jb, 3], rtol=1e-12, atol=1e-12)


def _refinement_set(rng, model, snr_range, n=10):
    psf = PSFS["moffat_e1"]
    stamps = []
    for _ in range(n):
        e1, e2 = rng.uniform(-0.45, 0.45, 2)
        img = draw(galsim.Convolve(galsim_model(model, rng.uniform(1.2, 3.0), e1, e2), psf),
                   offset=tuple(rng.uniform(-0.5, 0.5, 2)))  # fmt: skip
        img *= rng.uniform(*snr_range) / np.sqrt((img**2).sum())
        stamps.append(img + rng.normal(size=img.shape))
    return np.array(stamps), draw(psf)


@pytest.mark.xdist_group("bank_e0.05")  # one worker builds the finer grid's banks
@pytest.mark.parametrize("model, n_b", [("exponential", 1), ("bulge+disc", 3)])
def test_refined_windows_are_the_finer_grid_fit(rng, model, n_b):
    """With ``e_refine = 2`` a bright galaxy's likelihood near its peak is the one a fit on
    the grid of 0.05 gives (the same models, up to the centring pass's origin), and
    elsewhere the interpolation of its fit on the grid of 0.1, which alone is off by
    more than a unit of ln L at the peak of such a narrow likelihood."""
    from pylensfit.grid import refine_lnL

    stamps, psf = _refinement_set(rng, model, (60, 250))
    cfg = Config.paper(model=model, n_bulge_fractions=n_b)
    ref = fit_stamps(stamps, psf, 1.0, config=cfg.replace(e_refine=2))
    fine = fit_stamps(stamps, psf, 1.0, config=cfg.replace(e_step=0.05))
    coarse = fit_stamps(stamps, psf, 1.0, config=cfg)
    np.testing.assert_array_equal(ref.egrid, fine.egrid)
    assert ref.meta["e_step"] == 0.05 and ref.lnL.shape == fine.lnL.shape
    interp = refine_lnL(coarse.lnL, coarse.egrid, refine=2)[0] + coarse.lnL_peak[:, None]
    A = ref.lnL + ref.lnL_peak[:, None].astype(float)
    B = fine.lnL + fine.lnL_peak[:, None].astype(float)
    assert (np.abs(A - interp) > 1e-3).any(axis=1).all()  # every one was refined
    close = B > B.max(axis=1, keepdims=True) - 10.0  # the cells within 10 of the peak
    np.testing.assert_allclose(A[close], B[close], atol=0.05)
    assert np.abs(interp - B)[close].max() > 1.0  # the interpolation alone is not enough
    if n_b > 1:
        Ab = ref.lnL_bulge + ref.lnL_peak[:, None, None]
        Bb = fine.lnL_bulge + fine.lnL_peak[:, None, None]
        live = close[:, None, :] & (Bb > B.max(axis=1)[:, None, None] - 10.0)
        np.testing.assert_allclose(Ab[live], Bb[live], atol=0.05)


@pytest.mark.xdist_group("bank_e0.05")
def test_broad_likelihoods_are_interpolated_not_refined(rng):
    """A faint galaxy's likelihood spreads beyond ``refine_width``: it is the interpolation
    of the grid of 0.1 (the quintic of the Bayesian integrals) on every cell."""
    from pylensfit.grid import refine_lnL

    stamps, psf = _refinement_set(rng, "exponential", (8, 12))
    cfg = Config.paper(model="exponential")
    ref = fit_stamps(stamps, psf, 1.0, config=cfg.replace(e_refine=2))
    coarse = fit_stamps(stamps, psf, 1.0, config=cfg)
    interp = refine_lnL(coarse.lnL, coarse.egrid, refine=2)[0] + coarse.lnL_peak[:, None]
    A = ref.lnL + ref.lnL_peak[:, None].astype(float)
    np.testing.assert_allclose(A, interp, atol=2e-3)
    np.testing.assert_allclose(ref.lnL_r, coarse.lnL_r + (coarse.lnL_peak
                                                          - ref.lnL_peak)[:, None], atol=1e-4)


def test_refinement_settings():
    cfg = Config.paper(e_refine=2)
    assert cfg.output_e_step == 0.05 and cfg.output_refine == 2
    assert Config.paper(e_refine=2, integration_refine=1).output_refine == 1
    for bad in ({"e_refine": 0}, {"e_refine": 1.5}, {"refine_width": 0.0},
                {"refine_lnl": -1.0}):  # fmt: skip
        with pytest.raises(ValueError):
            Config.paper(**bad)


def test_two_bulge_sizes_are_the_two_families_runs(rng, tmp_path):
    """With ``bulge_size_ratio2`` the bank's runs are the one-size banks' (the disc and
    the first size's fractions, then the second size's fractions above 0; the wrap
    correction of the stamp's edge included), each run's ``ln L_k(e)`` is what the fit
    with that bulge size alone gives it, and ``ln L`` is their mixture with uniform
    weights over the five runs."""
    from pylensfit.prior import mix_bulge_fractions

    cfg = Config.paper(model="bulge+disc", n_bulge_fractions=3, e_step=0.2)
    two = cfg.replace(bulge_size_ratio2=1.2)
    assert [(run.fraction, run.size) for run in two.bulge_runs] == [
        (0.0, 0.6), (0.5, 0.6), (1.0, 0.6), (0.5, 1.2), (1.0, 1.2)]
    b1, b2, bb = model_bank(cfg), model_bank(cfg.replace(bulge_size_ratio=1.2)), model_bank(two)
    n_sub, n_e = b1.n_sizes, b1.n_e
    G = bb.G[:, :-1].reshape(-1, n_e, 5, n_sub)
    tol = 1e-6 * np.abs(b1.G).max()
    np.testing.assert_allclose(G[:, :, :3], b1.G[:, :-1].reshape(-1, n_e, 3, n_sub), atol=tol)
    np.testing.assert_allclose(G[:, :, 3:], b2.G[:, :-1].reshape(-1, n_e, 3, n_sub)[:, :, 1:],
                               atol=tol)  # fmt: skip
    np.testing.assert_array_equal(bb.bulge_size[::n_sub], [0.6, 0.6, 0.6, 1.2, 1.2])
    hlr = [half_light_radius("bulge+disc", bulge_fraction=f, bulge_size_ratio=s)
           for f, s, *_ in two.bulge_runs]  # fmt: skip
    np.testing.assert_allclose(bb.run_weights, np.array(hlr) / hlr[0])

    psf = draw(PSFS["moffat_e1"])
    gals = []
    for r, e, bf, s in ((1.5, (0.3, -0.2), 0.5, 0.5), (1.0, (-0.1, 0.35), 0.3, 0.9),
                        (2.2, (0.15, 0.1), 0.7, 0.7)):  # fmt: skip
        disc = galsim.Exponential(half_light_radius=r)
        bulge = galsim.DeVaucouleurs(half_light_radius=s * r)
        gal = ((1 - bf) * disc + bf * bulge).shear(e1=e[0], e2=e[1])
        gals.append(draw(galsim.Convolve(gal, PSFS["moffat_e1"])))
    stamps = np.stack([g * f / np.sqrt((g**2).sum()) for g, f in zip(gals, (30.0, 80.0, 50.0),
                                                                    strict=True)])  # fmt: skip
    stamps += rng.normal(size=stamps.shape)
    f2 = fit_stamps(stamps, psf, 1.0, config=two)
    f1 = fit_stamps(stamps, psf, 1.0, config=cfg)
    f1b = fit_stamps(stamps, psf, 1.0, config=cfg.replace(bulge_size_ratio=1.2))
    np.testing.assert_array_equal(f2.bulge_fractions, [0.0, 0.5, 1.0, 0.5, 1.0])
    np.testing.assert_array_equal(f2.bulge_sizes, [0.6, 0.6, 0.6, 1.2, 1.2])

    def absolute(f):
        return f.lnL_bulge + f.lnL_peak[:, None, None]

    a2, a1, a1b = absolute(f2), absolute(f1), absolute(f1b)
    live = a2 > a2.max(axis=(1, 2), keepdims=True) - 30.0
    # the same models; the fits differ only in the centring pass's origin
    np.testing.assert_allclose(a2[:, :3][live[:, :3]], a1[live[:, :3]], atol=0.01)
    np.testing.assert_allclose(a2[:, 3:][live[:, 3:]], a1b[:, 1:][live[:, 3:]], atol=0.01)
    assert np.abs(a2[:, 3:] - a2[:, 1:3])[live[:, 3:]].max() > 1.0  # the sizes do differ
    mixed = mix_bulge_fractions(f2.lnL_bulge, f2.lnL_star)
    np.testing.assert_allclose(mixed, f2.lnL, atol=1e-3)
    f2.write(tmp_path / "two.fits")
    back = type(f2).read(tmp_path / "two.fits")
    np.testing.assert_array_equal(back.bulge_sizes, f2.bulge_sizes)
    np.testing.assert_array_equal(back.bulge_fractions, f2.bulge_fractions)
    for bad in ({"bulge_size_ratio2": -1.0}, {"bulge_size_ratio2": 0.6},
                {"bulge_size_ratio2": 1.0, "n_bulge_fractions": 1}):  # fmt: skip
        with pytest.raises(ValueError, match="bulge_size_ratio2"):
            cfg.replace(**bad)
