"""The priors in the joint fit, and the recipe and the shapes table on joint fits:
:func:`pylensfit.joint.fit_exposures` with a size prior, ``L(r)`` and an amplitude
prior; :func:`pylensfit.calibrate_exposures`; :func:`pylensfit.measure_exposure_stamps`."""

from __future__ import annotations

import galsim
import numpy as np
import pytest

import pylensfit as plf
from pylensfit.catalogue import COLUMNS
from pylensfit.config import Config
from pylensfit.exposures import ExposureStamps
from pylensfit.flags import flag_value
from pylensfit.joint import fit_exposures, pixel_cells
from pylensfit.likelihood import e_annuli, fit_stamps
from pylensfit.models import render_models
from pylensfit.prior import SizePrior
from pylensfit.skyframe import SkyFrame

N = 32
#: the single fit's options that the joint fit shares (tests/test_joint.py)
CFG = Config().replace(model="exponential", amplitude_prior="uniform", cubic_snr=0.0,
                       truncate_models=False, max_stamp_size=0, e_refine=1,
                       n_bulge_fractions=1, dtype="float64", r_min=0.0, r_max=6.0,
                       r_step=0.25, r_rel_step=0.0, stamp_size=N)  # fmt: skip
#: a size prior (pixels) narrower than the grid: its tails get weight 0 (left out)
SIZE = SizePrior(ln_h=np.log([0.8, 1.5, 2.5, 4.0, 6.0]),
                 density=np.array([0.0, 0.8, 1.0, 0.3, 0.0]), star=1e-3)  # fmt: skip


def gaussian_psf(size: int = 25, s: float = 1.5) -> np.ndarray:
    yy, xx = np.mgrid[:size, :size] - size // 2
    return np.exp(-(xx**2 + yy**2) / (2 * s * s))


def rotation(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


def galaxies(ng: int, seed: int, psf: np.ndarray, flux=(60.0, 400.0)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return render_models(N, psf, 16 + rng.uniform(-0.5, 0.5, ng), 16 + rng.uniform(-0.5, 0.5, ng),
                         rng.uniform(-0.4, 0.4, ng), rng.uniform(-0.4, 0.4, ng),
                         rng.uniform(1.2, 3.0, ng), rng.uniform(*flux, ng),
                         model="exponential")  # fmt: skip


def views_of(stamps, psfs, sigma, jacobians, flags=None) -> list[ExposureStamps]:
    """:class:`ExposureStamps` of ``(K, n, N, N)`` stamps, one PSF and Jacobian per
    exposure, the galaxies at the stamps' centres (image positions ``100 + 50 i``)."""
    K, n = stamps.shape[:2]
    fl = np.zeros((K, n), np.int64) if flags is None else flags
    x = 100.0 + 50.0 * np.arange(n)
    zero = np.zeros(n)
    return [ExposureStamps(stamps=stamps[k], weights=np.full(stamps[k].shape, sigma[k] ** -2.0),
                           noise_sigma=np.full(n, float(sigma[k])),
                           psf=np.broadcast_to(psfs[k], (n, *psfs[k].shape)), x=x, y=x + 7.0,
                           x0=(x - N // 2).astype(np.int64), y0=(x + 7.0 - N // 2).astype(np.int64),
                           jacobian=np.broadcast_to(jacobians[k], (n, 2, 2)),
                           frame=SkyFrame(zero, zero.astype(bool), zero, zero, zero > -1),
                           flux_scale=1.0, flags=fl[k], exposure=k)
            for k in range(K)]  # fmt: skip


@pytest.mark.parametrize("amp, model, n_b", [("uniform", "exponential", 1),
                                             ("flux", "exponential", 1),
                                             ("flux", "bulge+disc", 3)])  # fmt: skip
def test_one_exposure_with_priors_is_the_single_fit(amp, model, n_b):
    """K = 1 with J = I (pixel scale 1), the size prior and the amplitude prior (uniform;
    the power law 1.5 in flux between bounds that cut the sample's fluxes):
    fit_stamps's ln L(e), ln L(r) per ring of |e|, most likely model and size, to
    float32 rounding. Without the size prior (or with the uniform amplitude prior under a
    power-law configuration) ln L(e) moves by far more: the check sees both."""
    cfg = CFG.replace(amplitude_prior=amp, amplitude_prior_power=1.5, model=model,
                      n_bulge_fractions=n_b, amplitude_prior_min=80.0,
                      amplitude_prior_max=350.0)  # fmt: skip
    psf = gaussian_psf()
    img = galaxies(8, 1, psf) + np.random.default_rng(2).normal(0.0, 1.0, (8, N, N))
    groups = e_annuli(plf.ellipticity_grid(cfg.e_step, emax=cfg.e_max))
    single = fit_stamps(img, psf, 1.0, config=cfg, size_prior=SIZE, lnL_r_groups=groups)
    joint = fit_exposures(img[None], psf[None], 1.0, np.eye(2)[None], config=cfg,
                          size_prior=SIZE, lnL_r_groups=groups)  # fmt: skip
    assert (joint.flags == 0).all() and (single.flags == 0).all()
    near = single.lnL > -30
    a, b = single.lnL + single.lnL_peak[:, None], joint.lnL + joint.lnL_peak[:, None]
    assert np.abs(a - b)[near].max() < 1e-4
    fin = np.isfinite(single.lnL_r_grouped) & (single.lnL_r_grouped > -30)
    np.testing.assert_array_equal(fin, np.isfinite(joint.lnL_r_grouped)
                                  & (joint.lnL_r_grouped > -30))  # fmt: skip
    assert np.abs(single.lnL_r_grouped[fin] - joint.lnL_r_grouped[fin]).max() < 1e-4
    fr = np.isfinite(single.lnL_r)
    np.testing.assert_array_equal(fr, np.isfinite(joint.lnL_r))
    np.testing.assert_allclose(joint.lnL_r[fr], single.lnL_r[fr], atol=1e-4)
    np.testing.assert_allclose(joint.snr, single.snr, rtol=1e-6)
    np.testing.assert_allclose(joint.flux, single.flux, rtol=1e-6)
    np.testing.assert_array_equal(joint.r_marginal, single.r_best)
    np.testing.assert_array_equal(joint.is_star, single.is_star)
    np.testing.assert_allclose(joint.x, single.x - N // 2, atol=1e-6)
    if n_b > 1:
        near_b = single.lnL_bulge > -30
        assert np.abs(joint.lnL_bulge - single.lnL_bulge)[near_b].max() < 1e-4
        np.testing.assert_allclose(joint.lnL_star, single.lnL_star, atol=1e-5)
    flat = fit_exposures(img[None], psf[None], 1.0, np.eye(2)[None], config=cfg)
    assert np.abs(flat.lnL - joint.lnL)[near].max() > 0.05  # the size prior matters here
    if amp == "flux":
        unif = fit_exposures(img[None], psf[None], 1.0, np.eye(2)[None], size_prior=SIZE,
                             config=cfg.replace(amplitude_prior="uniform"))  # fmt: skip
        assert np.abs(unif.lnL - joint.lnL)[near].max() > 0.05


def large_galaxies(n: int, seed: int, psf: np.ndarray, r_range) -> np.ndarray:
    """Six bright exponentials of sizes ``r_range`` (pixels) within 0.3 px of the
    centres of ``n``-pixel stamps, noise 1."""
    rng = np.random.default_rng(seed)
    c, ng = n // 2, 6
    return render_models(n, psf, c + rng.uniform(-0.3, 0.3, ng), c + rng.uniform(-0.3, 0.3, ng),
                         rng.uniform(-0.4, 0.4, ng), rng.uniform(-0.4, 0.4, ng),
                         rng.uniform(*r_range, ng), rng.uniform(600.0, 900.0, ng),
                         model="exponential") + rng.normal(0.0, 1.0, (ng, n, n))  # fmt: skip


def test_one_exposure_on_a_larger_tier_is_the_single_fits_tier():
    """K = 1, J = I, 64-pixel stamps: with ``k_max = pi / 2`` (the frequencies of the
    64-pixel stamp that a 32-pixel bank holds) fit_exposures gives fit_stamps' ln L(e)
    of galaxies it fits on its 64-pixel tier (``max_stamp_size = 64`` over
    ``stamp_size = 32``) to float32 rounding (the galaxies near the stamps' centres, so
    that the single fit's window about its first centre is the whole stamp); on every
    frequency of the stamp it does not."""
    big = 64
    psf = gaussian_psf()
    img = large_galaxies(big, 8, psf, (2.5, 5.0))
    single = fit_stamps(img, psf, 1.0, config=CFG.replace(max_stamp_size=big,
                                                          stamp_hlr_ratio=1e3))  # fmt: skip
    assert np.all(single.stamp == big)
    tier = CFG.replace(stamp_size=big, k_max=np.pi / 2)
    joint = fit_exposures(img[None], psf[None], 1.0, np.eye(2)[None], config=tier)
    full = fit_exposures(img[None], psf[None], 1.0, np.eye(2)[None],
                         config=CFG.replace(stamp_size=big))  # fmt: skip
    near = single.lnL > -30
    a = single.lnL + single.lnL_peak[:, None]
    assert np.abs(a - (joint.lnL + joint.lnL_peak[:, None]))[near].max() < 1e-4
    assert np.abs(a - (full.lnL + full.lnL_peak[:, None]))[near].max() > 0.05
    np.testing.assert_allclose(joint.flux, single.flux, rtol=1e-6)


SHAPES = ("e1", "e2", "e1_var", "e2_var", "e12_cov", "sens1", "sens2", "model_flux",
          "model_SNratio", "scalelength", "e1_best", "e2_best", "noise_sigma", "weight",
          "flags", "fitclass", "is_star", "bulge_best")  # fmt: skip


#: the priors that calibrate estimates, for bulge+disc fractions: a size prior per run,
#: the flux power law between limits, bulge weights
RUN_SIZE = SizePrior(ln_h=SIZE.ln_h, density=np.array([[0.0, 0.8, 1.0, 0.3, 0.0],
                                                       [0.0, 0.3, 1.0, 0.8, 0.0],
                                                       [0.0, 1.0, 0.5, 0.1, 0.0]]), star=1e-3)


@pytest.mark.parametrize("model", ["exponential", "bulge+disc"])
def test_one_exposure_table_is_measure_stamps(model):
    """K = 1, J = I: measure_exposure_stamps gives measure_stamps' columns under the same
    priors (a size prior, an ellipticity prior, a position prior; for bulge+disc
    fractions a size prior per run, bulge weights and the flux power law between
    limits), the same numbers (to float32 rounding of ln L), one exposure used (bit 0)."""
    psf = gaussian_psf()
    sigma = 1.5
    img = galaxies(12, 5, psf) + np.random.default_rng(6).normal(0.0, sigma, (12, N, N))
    cfg, priors = CFG, plf.Priors(ellipticity=plf.Prior(B=0.25, C=0.6, D=2.5), size=SIZE,
                                  position_sigma=0.8, info={"pixel_scale": 1.0})  # fmt: skip
    if model != "exponential":
        cfg = CFG.replace(model=model, n_bulge_fractions=3, amplitude_prior="flux")
        priors = plf.Priors(ellipticity=priors.ellipticity, size=RUN_SIZE, flux_power=1.7,
                            flux_range=(40.0, 500.0), bulge_weights=np.array([0.5, 0.3, 0.2]),
                            position_sigma=0.8, info={"pixel_scale": 1.0})  # fmt: skip
    tab = plf.measure_stamps(img, psf, sigma, priors=priors, config=cfg)
    jt = plf.measure_exposure_stamps(views_of(img[None], psf[None], [sigma], np.eye(2)[None]),
                                     priors=priors, config=cfg)  # fmt: skip
    assert len(jt) == len(tab) == 12
    assert [c for c in jt.colnames if c not in ("n_exposures", "exposures_used")] == tab.colnames
    for c in SHAPES:
        np.testing.assert_allclose(np.asarray(jt[c], float), np.asarray(tab[c], float),
                                   rtol=2e-5, atol=1e-7, err_msg=c)  # fmt: skip
        assert (jt[c].unit, jt[c].description) == (tab[c].unit, tab[c].description)
    assert (np.asarray(tab["flags"]) == 0).sum() >= 10
    np.testing.assert_allclose(jt["x"] - jt["x_detect"], tab["x"] - tab["x_detect"], atol=1e-5)
    assert (jt["n_exposures"] == 1).all() and (jt["exposures_used"] == 1).all()
    assert jt["exposures_used"].description == COLUMNS["exposures_used"][1]


def test_one_exposure_metacal_columns_are_measure_stamps():
    """K = 1, J = I, ``response="metacal"`` with the same seed: the same added noise
    fields, images and fits as :func:`pylensfit.measure_stamps`' metacalibration, so the
    same ``e1_mcal, e2_mcal, R11 ... R22`` (to float32 rounding); another seed other
    numbers."""
    psf = gaussian_psf()
    sigma = 1.5
    img = galaxies(8, 9, psf) + np.random.default_rng(10).normal(0.0, sigma, (8, N, N))
    priors = plf.Priors(ellipticity=plf.Prior(B=0.25, C=0.6, D=2.5), size=SIZE,
                        position_sigma=0.8, info={"pixel_scale": 1.0})  # fmt: skip
    kw = {"priors": priors, "config": CFG, "response": "metacal", "seed": 3}
    tab = plf.measure_stamps(img, psf, sigma, **kw)
    view = views_of(img[None], psf[None], [sigma], np.eye(2)[None])
    jt = plf.measure_exposure_stamps(view, **kw)
    mcal = ("e1_mcal", "e2_mcal", "R11", "R12", "R21", "R22")
    assert np.isfinite([jt[c] for c in mcal]).all()
    for c in mcal:
        np.testing.assert_allclose(np.asarray(jt[c]), np.asarray(tab[c]), rtol=1e-4, atol=2e-5,
                                   err_msg=c)  # fmt: skip
    other = plf.measure_exposure_stamps(view, **(kw | {"seed": 4}))
    assert np.abs(np.asarray(other["R11"]) - np.asarray(jt["R11"])).max() > 1e-3
    assert jt.meta["metacal_step"] == 0.01


def test_a_masked_exposure_leaves_the_fit_and_its_bit():
    """Three exposures (rotated, mirror image, aligned): galaxy 1 flagged in exposure 1 is
    measured from exposures 0 and 2, as the fit of those two alone (n_exposures 2, bit 1
    clear: exposures_used 0b101); galaxy 2, flagged in all three, is NOT_MEASURED with
    NaN shapes and weight 0; rows in = rows out."""
    psf = gaussian_psf()
    sig = np.array([1.0, 1.2, 0.9])
    J = np.stack([np.eye(2), rotation(40.0), np.diag([-1.0, 1.0])]) / 0.2
    clean = galaxies(4, 7, psf, flux=(250.0, 400.0))
    rng = np.random.default_rng(8)
    stamps = clean[None] + rng.normal(0.0, 1.0, (3, *clean.shape)) * sig[:, None, None, None]
    flags = np.zeros((3, 4), np.int64)
    flags[1, 1] = 8  # StampFlag.MASKED
    flags[:, 2] = 1  # StampFlag.OFF_IMAGE
    stamps[1, 1] = rng.normal(0.0, 50.0, (N, N))  # the masked view holds garbage
    psfs = np.stack([psf] * 3)
    priors = plf.Priors(info={"pixel_scale": 0.2})
    t = plf.measure_exposure_stamps(views_of(stamps, psfs, sig, J, flags), priors=priors,
                                    config=CFG)  # fmt: skip
    assert len(t) == 4
    np.testing.assert_array_equal(t["n_exposures"], [3, 2, 0, 3])
    np.testing.assert_array_equal(t["exposures_used"], [7, 5, 0, 7])
    assert t["flags"][2] & flag_value("NOT_MEASURED") and t["fitclass"][2] == -1
    assert np.isnan([t[c][2] for c in ("e1", "e2", "e1_var", "e2_var", "e12_cov")]).all()
    assert t["weight"][2] == 0, t["flags"][2]
    keep = [0, 2]
    two = plf.measure_exposure_stamps(views_of(stamps[keep][:, 1:2], psfs[keep], sig[keep],
                                               J[keep]), priors=priors, config=CFG)
    for c in ("e1", "e2", "e1_var", "sens1", "model_flux", "model_SNratio"):
        np.testing.assert_allclose(t[c][1], two[c][0], rtol=1e-9, err_msg=c)
    assert np.isfinite([t["e1"][i] for i in (0, 1, 3)]).all()
    assert (np.asarray(t["flags"])[[0, 1, 3]] == 0).all()


def _render(gal, psf_fwhm, J, noise, rng):
    wcs = galsim.JacobianWCS(*np.linalg.inv(J).ravel())
    img = galsim.Convolve(gal, galsim.Moffat(beta=3.5, fwhm=psf_fwhm)).drawImage(
        nx=N, ny=N, wcs=wcs, offset=rng.uniform(-0.5, 0.5, 2)).array  # fmt: skip
    return img + rng.normal(0.0, noise, img.shape)


def test_calibrate_exposures_is_calibrate_at_equal_depth():
    """The recipe on joint fits of 300 GalSim exponentials in K = 2 exposures (rotated by
    0.7 degrees, one a mirror image, each of noise sqrt(2) sigma) and on single fits of
    the same galaxies in one exposure of noise sigma (equal depth): finite priors, whose
    ellipticity priors' rms |e| agree to 0.03 (measured 0.171 and 0.167) and size priors'
    mean half-light radius to 10 % (measured 2.03 and 1.91 px: the two differ by the
    noise realisations and the joint fit's two samplings). A size prior read in arcsec
    rather than reference pixels (0.2") would be 5 times too small, one without the
    joint ``L(r)`` no estimate (the recipe's flat fallback, ``size`` None)."""
    rng = np.random.default_rng(11)
    n, scale, sigma = 300, 0.2, 1.0
    cfg = Config().replace(model="exponential", n_bulge_fractions=1, stamp_size=N,
                           max_stamp_size=0, e_refine=1)  # fmt: skip
    e = rng.normal(0.0, 0.25, (n, 2))
    e *= np.minimum(1.0, 0.8 / np.hypot(*e.T))[:, None]
    hlr = np.exp(rng.normal(np.log(0.35), 0.3, n))
    flux = 40.0 * rng.pareto(1.5, n) + 60.0
    gals = [galsim.Exponential(half_light_radius=h, flux=f).shear(e1=a, e2=b)
            for h, f, (a, b) in zip(hlr, flux, e, strict=True)]  # fmt: skip
    J = np.stack([rotation(0.7), np.diag([-1.0, 1.0]) @ rotation(-0.4)]) / scale
    stamps = np.array([[_render(g, 0.7, Jk, sigma * np.sqrt(2), rng) for g in gals]
                       for Jk in J])  # fmt: skip
    moffat = galsim.Moffat(beta=3.5, fwhm=0.7)
    psfs = np.stack([moffat.drawImage(nx=25, ny=25, wcs=galsim.JacobianWCS(
        *np.linalg.inv(Jk).ravel())).array for Jk in J])  # fmt: skip
    deep = np.array([_render(g, 0.7, np.eye(2) / scale, sigma, rng) for g in gals])
    psf_deep = moffat.drawImage(nx=25, ny=25, scale=scale).array
    pj = plf.calibrate_exposures(views_of(stamps, psfs, [sigma * np.sqrt(2)] * 2, J),
                                 config=cfg)  # fmt: skip
    ps = plf.calibrate(deep, psf_deep, sigma, config=cfg)
    assert pj.info["joint_fit"] and pj.info["pixel_scale"] == pytest.approx(scale)
    for p in (pj, ps):
        assert p.size is not None and np.isfinite(p.size.density).all()
        assert np.isfinite(p.ellipticity.pdf(np.array([0.1]), np.array([0.0]))).all()
    rms = [np.sqrt(_mean_e2(p.ellipticity)) for p in (pj, ps)]
    assert abs(rms[0] - rms[1]) < 0.03, rms
    hj, hs = (_mean_h(p.size) for p in (pj, ps))
    assert abs(hj / hs - 1) < 0.1, (hj, hs)


def _mean_e2(prior) -> float:
    g = np.linspace(-0.99, 0.99, 199)
    e1, e2 = np.meshgrid(g, g)
    p = prior.pdf(e1.ravel(), e2.ravel())
    return float(np.sum(p * (e1.ravel() ** 2 + e2.ravel() ** 2)) / np.sum(p))


def _mean_h(size: SizePrior) -> float:
    h = np.exp(size.ln_h)
    d = size.marginal()
    return float(np.sum(h * d) / np.sum(d))


def test_pixel_cells_are_the_models_seen_through_the_jacobian():
    """A sky-frame model through a rotated, sheared, mirror-image Jacobian
    (render_models(jacobian=)) is the pixel-frame model of pixel_cells' ellipticity and
    size, to float64 rounding."""
    J = np.diag([1.0, -1.0]) @ rotation(33.0) @ np.array([[1.03, 0.02], [0.02, 0.97]]) / 0.2
    eg = np.array([[0.3, -0.2], [-0.45, 0.1], [0.0, 0.6], [0.0, 0.0]])
    e_pix, scale = pixel_cells(eg, J)
    psf = gaussian_psf()
    n = 64
    sky = render_models(n, psf, [32.2] * 4, [31.7] * 4, eg[:, 0], eg[:, 1], [0.5] * 4, [1.0] * 4,
                        model="exponential", jacobian=J)  # fmt: skip
    pix = render_models(n, psf, [32.2] * 4, [31.7] * 4, e_pix[:, 0], e_pix[:, 1],
                        [0.5 * scale] * 4, [1.0] * 4, model="exponential")  # fmt: skip
    assert np.abs(sky - pix).max() < 1e-12
    assert np.hypot(*e_pix[3]) > 0.03  # the WCS's own shear makes a round model elliptical
    e_conf, _ = pixel_cells(eg, np.diag([1.0, -1.0]) @ rotation(33.0) / 0.2)
    assert np.abs(e_conf[3]).max() < 1e-12  # a rotation and a mirror keep it round
    # and rotate the others by twice the angle after the mirror's e2 -> -e2
    z = (eg[:3, 0] - 1j * eg[:3, 1]) * np.exp(-2j * np.radians(33.0))
    np.testing.assert_allclose(e_conf[:3, 0] + 1j * e_conf[:3, 1], z, atol=1e-12)


@pytest.mark.parametrize("flip", [False, True])
def test_truncated_models_through_a_jacobian_are_the_single_fits(flip):
    """Large galaxies whose models wrap round 32-pixel stamps, with ``truncate_models``:
    K = 1 with J = I gives fit_stamps' ln L(e) (its models cut at the stamp's edge) to
    float32 rounding; with the mirror image J = diag(1, -1) the sky frame's ln L(e1, e2)
    is the single fit's ln L(e1, -e2) of the same pixels. Without the truncation the
    joint fit is off by far more."""
    cfg = CFG.replace(truncate_models=True)
    psf = gaussian_psf()
    img = large_galaxies(N, 11, psf, (3.0, 5.5))
    single = fit_stamps(img, psf, 1.0, config=cfg)
    J = np.diag([1.0, -1.0]) if flip else np.eye(2)
    joint = fit_exposures(img[None], psf[None], 1.0, J[None], config=cfg)
    loose = fit_exposures(img[None], psf[None], 1.0, J[None], config=CFG)
    eg = single.egrid
    cell = {(round(a, 6), round(b, 6)): i for i, (a, b) in enumerate(eg)}
    order = np.array([cell[(round(a, 6), round(-b if flip else b, 6))] for a, b in eg])
    a = (single.lnL + single.lnL_peak[:, None])[:, order]
    near = single.lnL[:, order] > -30
    assert np.abs(a - (joint.lnL + joint.lnL_peak[:, None]))[near].max() < 1e-4
    assert np.abs(a - (loose.lnL + loose.lnL_peak[:, None]))[near].max() > 0.05
