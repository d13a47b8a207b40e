"""The calibration recipe on galaxies whose flux counts are flat or rise with flux (a
bright selection, a cluster field), where the counts' power law ``A^-beta`` has
``beta <= 0``: the recipe runs, records what it estimated, and measures the shear."""

from __future__ import annotations

import math
import warnings

import galsim
import numpy as np
import pytest

import pylensfit as plf

#: the shear of the test population
G_TRUE = (0.04, -0.03)
#: per-pixel noise of the stamps
SIGMA = 10.0


def _pairs(n_pairs: int, counts: str, seed: int, size: int = 32):
    """``2 n_pairs`` exponential and de Vaucouleurs galaxies sheared by :data:`G_TRUE`,
    each with its 90-degree rotated twin, on ``size``-pixel stamps: fluxes ``F`` drawn
    uniformly on ``[800, 6000]`` (``counts="flat"``, S/N ~ 8-90) or with ``dN/dF ~ F``
    on it (``"rising"``, a negative power)."""
    rng = np.random.default_rng(seed)
    psf = galsim.Moffat(beta=3.5, fwhm=3.0)
    lo, hi = 800.0, 6000.0
    u = rng.uniform(size=n_pairs)
    flux = lo + (hi - lo) * (u if counts == "flat" else np.sqrt(u))
    out = np.empty((2 * n_pairs, size, size))
    for k in range(n_pairs):
        r = rng.uniform(0.8, 2.0)
        e = rng.normal(0, 0.25, 2).clip(-0.7, 0.7)
        off = rng.uniform(-0.5, 0.5, 2) + 0.5  # the profile centred on [size//2, size//2]
        gal = (galsim.Exponential(half_light_radius=r) if k % 2
               else galsim.DeVaucouleurs(half_light_radius=r, trunc=8 * r))  # fmt: skip
        gal = gal.withFlux(flux[k]).shear(g1=e[0], g2=e[1])
        for j, rot in enumerate((0.0, 90.0)):
            twin = gal.rotate(rot * galsim.degrees).shear(g1=G_TRUE[0], g2=G_TRUE[1])
            out[2 * k + j] = galsim.Convolve(twin, psf).drawImage(
                nx=size, ny=size, scale=1.0, offset=off).array
    out += rng.normal(size=out.shape) * SIGMA
    return out, psf.drawImage(nx=size, ny=size, scale=1.0, offset=(0.5, 0.5)).array


def _paired_shear(t) -> tuple[np.ndarray, np.ndarray]:
    """The shear (lensfit's ``sum <e> / sum sens``) of the pairs whose two galaxies are
    usable, and its error from the scatter of the pairs' sums: the twins' intrinsic
    shapes cancel, so this error is the measurement's own, not the shape noise."""
    ok = (np.asarray(t["flags"]) == 0) & (np.asarray(t["weight"]) > 0)
    ok = (ok[0::2] & ok[1::2]).repeat(2)
    g, err = np.empty(2), np.empty(2)
    for i in (0, 1):
        e = np.asarray(t[f"e{i + 1}"])[ok].reshape(-1, 2).sum(axis=1)
        s = np.asarray(t[f"sens{i + 1}"])[ok].reshape(-1, 2).sum(axis=1)
        g[i] = e.sum() / s.sum()
        err[i] = math.sqrt(np.sum((e - g[i] * s) ** 2)) / s.sum()
    return g, err


@pytest.mark.parametrize(("counts", "seed"), [("flat", 12), ("rising", 11)])
def test_recipe_runs_on_counts_that_do_not_fall_with_flux(counts, seed):
    """Flat counts (whose faint end the S/N cut and the flux errors thin: the power of
    their measured fluxes comes out at -1.0 +- 0.33 here) and counts rising as ``dN/dF ~
    F`` (power -1): both gave a negative power, which the configuration refused. The
    power is kept as the prior's, between the estimated flux limits, recorded with its
    error and the counts' shape in the priors (the catalogue's ``PRIORS`` HDU is
    written from them), and the shear is within three of its errors (the pairs'
    scatter) of the truth."""
    stamps, psf = _pairs(120, counts, seed=seed)
    with warnings.catch_warnings():
        warnings.simplefilter("error", plf.CalibrationWarning)  # no prior falls back
        t = plf.measure_stamps(stamps, psf, SIGMA)
    pr = t.meta["priors"]
    beta, err = pr.flux_power, pr.info["flux_power_err"]
    assert beta < 0 and 0 < err < 0.5
    assert abs(beta - (0.0 if counts == "flat" else -1.0)) < 4 * err
    assert pr.info["flux_counts"] == ("flat" if abs(beta) <= 2 * err else "rising with flux")
    assert pr.flux_range is not None and 400 < pr.flux_range[0] < pr.flux_range[1] < 7000
    assert "fallbacks" not in pr.info
    # the record round-trips through the priors' JSON (the PRIORS HDU's)
    back = plf.Priors.from_dict(pr.to_dict())
    assert back.flux_power == beta and back.info["flux_counts"] == pr.info["flux_counts"]
    assert f"flux_power={beta:.3f}" in repr(back)
    g, gerr = _paired_shear(t)
    assert np.all(gerr < 0.01)
    assert np.all(np.abs(g - G_TRUE) < 3 * gerr), (g, gerr)


def _recipe_on_fluxes(flux: np.ndarray, **kw) -> plf.Priors:
    """:func:`run_recipe` with a fitting pass that hands it ``flux`` (and flat ``ln
    L(e)``), the ellipticity prior given, no size, bulge or position prior to estimate."""
    from pylensfit.calibration import CalibrationSample, run_recipe

    n = flux.size
    cal = CalibrationSample(egrid=np.zeros((4, 2)), lnL=np.zeros((n, 4)), flux=flux,
                            flux_err=flux / 20.0, snr=np.full(n, 20.0), dx=np.zeros(n),
                            dy=np.zeros(n), group=np.zeros(n, int))  # fmt: skip
    cfg = plf.Config(size_prior="flat", bulge_prior="uniform", estimate_position_prior=False)
    return run_recipe(lambda *a: cal, cfg, prior=plf.Prior(), **kw)[0]


def test_rising_counts_without_an_upper_flux_limit_fall_back_to_the_flat_power():
    """A negative power is a proper prior only below an upper flux limit: without one
    (the limits not estimated) the power falls back to 0, with a warning, and the
    estimate is kept in the record."""
    flux = np.sqrt(np.random.default_rng(1).uniform(1e4, 1e8, 400))  # dN/dF ~ F
    with pytest.warns(plf.CalibrationWarning, match="the flux power prior falls back to "
                      "the flat power 0"):  # fmt: skip
        pr = _recipe_on_fluxes(flux, flux_bounds=False)
    assert pr.flux_power == 0.0 and pr.flux_range is None
    est, err = pr.info["flux_power_estimated"], pr.info["flux_power_err"]
    assert est < 0 and abs(est + 1.0) < 3 * err
    assert "no upper flux limit" in pr.info["fallbacks"]["flux power"]
    assert "fallbacks=['flux power']" in repr(pr)
    # with its limits estimated the same fluxes keep their negative power
    with warnings.catch_warnings():
        warnings.simplefilter("error", plf.CalibrationWarning)
        pr = _recipe_on_fluxes(flux)
    assert pr.flux_power == est and pr.flux_range is not None
    assert pr.flux_range[1] == pytest.approx(1e4, rel=0.05)


def test_fluxes_without_a_range_keep_the_configured_power():
    """Fluxes whose quantiles coincide (one flux for all) have no slope to estimate: the
    configured power is kept, with a warning and the reason recorded."""
    with pytest.warns(plf.CalibrationWarning, match="quantiles coincide"):
        pr = _recipe_on_fluxes(np.full(100, 500.0), flux_bounds=False)
    assert pr.flux_power == plf.Config().amplitude_prior_power
    assert "quantiles coincide" in pr.info["fallbacks"]["flux power"]


def test_negative_power_amplitude_integral_matches_quadrature():
    """The amplitude integral ``0.5 t^2 + ln int_lo^hi u^-beta phi(u - t) du`` of a power
    law rising with flux (``beta < 0``) and the amplitude's posterior mean, against
    scipy's quadrature: the expansion about the integrand's peak serves it as it does
    ``beta >= 0``, within 1e-3 from ``t = 8`` (measured worst: 3.4e-3 in the value and
    2.1e-2 in the mean at ``t = 4``, 5.7e-4 and 3.5e-3 from ``t = 8``)."""
    from scipy.integrate import quad

    from pylensfit.likelihood.amplitude_nb import amplitude_integral

    def integrand(u, power, t, m):  # scaled by the Gaussian's value at m
        return u**power * np.exp(-0.5 * (u - t) ** 2 + 0.5 * (m - t) ** 2)

    for beta in (-0.5, -1.0, -2.0):
        for lo, hi in [(1.0, np.inf), (5.0, np.inf), (10.0, 30.0), (2.0, 12.0)]:
            for t in (4.0, 6.0, 8.0, 12.0, 20.0, 60.0):
                top = min(hi, t + 40.0)
                pts = [p for p in (t, lo + 1e-9) if lo < p < top] or None
                m = min(max(t, lo), top)
                f0, f1 = (quad(integrand, lo, top, args=(k - beta, t, m), points=pts,
                               limit=400, epsabs=0, epsrel=1e-12)[0] for k in (0, 1))  # fmt: skip
                want = 0.5 * t * t - 0.5 * (m - t) ** 2 + np.log(f0) - 0.5 * np.log(2 * np.pi)
                got, mean = amplitude_integral(t, 4.0, np.log(4.0), 0.5, beta, 0.0,
                                               lo / 2.0, hi / 2.0)  # fmt: skip
                tol, tol_mean = {4.0: (5e-3, 0.03), 6.0: (2e-3, 0.01)}.get(t, (1e-3, 5e-3))
                assert abs(got - want) < tol, (beta, lo, hi, t, got - want)
                assert abs(mean - f1 / f0) < tol_mean, (beta, lo, hi, t, mean, f1 / f0)
