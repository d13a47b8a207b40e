"""The amplitude (flux) prior's parameters from the measured fluxes.

:func:`estimate_flux_slope` gives the power of the number counts ``dN/dF ~ F^-beta``;
:func:`estimate_flux_range` the bounds of the flux distribution, its measurement errors
deconvolved.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import optimize


def estimate_flux_slope(
    flux: np.ndarray, *, quantiles: tuple[float, float] = (0.3, 0.95)
) -> tuple[float, float]:
    """The power ``beta`` of the number counts ``dN/dF ~ F^-beta`` from measured fluxes.

    The maximum-likelihood power law truncated to ``[a, b]``, the ``quantiles`` of the
    fluxes: within it the counts are a power law whatever happens outside (the faint
    end's noise and incompleteness, a bright cut-off), so the estimate needs neither.
    With ``x = ln(F / a)`` on ``[0, L = ln(b / a)]`` the law is a truncated exponential
    of rate ``lambda = beta - 1``, and the likelihood equation is ``mean(x) = 1/lambda -
    L / (exp(lambda L) - 1)`` (``L / 2`` at ``lambda = 0``). This is the amplitude
    prior's power for ``Config(amplitude_prior="flux")``.

    Parameters
    ----------
    flux : array_like
        Measured fluxes (any units); non-finite and non-positive values are ignored.
    quantiles : tuple of float
        The fluxes' quantiles that bound the range fitted.

    Returns
    -------
    beta, beta_err : float
        The power and its 1-sigma error (Fisher information of the truncated law).
    """
    f = np.asarray(flux, dtype=float).ravel()
    f = f[np.isfinite(f) & (f > 0)]
    lo_q, hi_q = quantiles
    if not 0 <= lo_q < hi_q <= 1:
        raise ValueError(f"quantiles must satisfy 0 <= lower < upper <= 1, got {quantiles}")
    if f.size < 20:
        raise ValueError(f"{f.size} usable fluxes: too few to estimate the counts' slope")
    a, b = np.quantile(f, [lo_q, hi_q])
    if not b > a:
        raise ValueError("the fluxes' quantiles coincide: no range to fit a slope on")
    x = np.log(f[(f >= a) & (f <= b)] / a)
    L = float(np.log(b / a))
    xbar = float(x.mean())

    def mean_x(lam: float) -> float:  # E[x] of the truncated exponential of rate lam
        u = lam * L
        if abs(u) < 1e-6:
            return L / 2 - lam * L * L / 12
        return 1.0 / lam - L / np.expm1(u)

    def var_x(lam: float) -> float:
        u = lam * L
        if abs(u) < 1e-6:
            return L * L / 12
        return 1.0 / lam**2 - L * L * np.exp(u) / np.expm1(u) ** 2

    # mean_x falls monotonically from L (lam -> -inf) to 0 (lam -> +inf)
    span = 200.0 / L
    lam = optimize.brentq(lambda v: mean_x(v) - xbar, -span, span, xtol=1e-12)
    return 1.0 + lam, float(1.0 / np.sqrt(x.size * var_x(lam)))


def _flux_range_loglike(f: np.ndarray, s: np.ndarray, lo: float, hi: float, beta: float,
                        nodes: tuple[np.ndarray, np.ndarray]) -> np.ndarray:  # fmt: skip
    """ln p(f_i) of measured fluxes under ``F^-beta`` on ``[lo, hi]`` and Gaussian errors.

    Each galaxy's integral over the true flux runs over ``[lo, hi]`` within 8 of its
    errors of the measured flux (Gauss-Legendre ``nodes`` on that interval), where all
    of its mass lies; the power law's normalisation on ``[lo, hi]`` is analytic.
    """
    x, w = nodes
    a = np.clip(f - 8.0 * s, lo, hi)
    b = np.clip(f + 8.0 * s, lo, hi)
    half = 0.5 * (b - a)
    F = 0.5 * (a + b)[:, None] + half[:, None] * x[None, :]
    z = (f[:, None] - F) / s[:, None]
    # the power law relative to lo (exponent <= 0), times the Gaussian
    lnterm = -beta * np.log(F / lo) - 0.5 * z * z
    top = lnterm.max(axis=1)
    integ = np.sum(w[None, :] * np.exp(lnterm - top[:, None]), axis=1) * half
    with np.errstate(divide="ignore"):
        ln_int = np.log(integ) + top - np.log(s) - 0.5 * math.log(2.0 * math.pi)
    lam = 1.0 - beta  # normalisation of (F / lo)^-beta on [lo, hi]
    L = math.log(hi / lo)
    norm = lo * L if abs(lam * L) < 1e-8 else lo * math.expm1(lam * L) / lam
    return ln_int - math.log(norm)


#: Fewest usable fluxes for a range (:data:`pylensfit.prior.MIN_FLUX_RANGE_SAMPLE`).
MIN_FLUX_RANGE_SAMPLE = 50


def estimate_flux_range(
    flux: np.ndarray,
    flux_err: np.ndarray,
    *,
    beta: float | None = None,
    error_scale: float | None = None,
    outlier_fraction: float = 1e-3,
) -> dict[str, float]:
    """The bounds of the flux distribution from measured fluxes with their errors.

    A population whose counts are a power law ``dN/dF ~ F^-beta`` between two limits
    ``[lo, hi]`` (a simulation's flux range; a catalogue cut in true flux) gives
    measured fluxes ``f_i = F_i + n_i`` with Gaussian errors ``sigma_i``. The maximum of
    ``sum_i ln int_lo^hi F^-beta N(f_i; F, sigma_i) dF / Z(lo, hi, beta)`` over
    ``(lo, hi)`` (and ``beta`` unless given) deconvolves the errors: near a limit the
    measured fluxes spill across it by their errors, and the limit sits where the
    counts' edge does. A fraction ``outlier_fraction`` of the density is log-uniform
    over the measured range, so that a few failed fits cannot pin a limit. These are
    the bounds of :class:`~pylensfit.Config`'s ``amplitude_prior_min`` and
    ``amplitude_prior_max``: a flux prior that allows fluxes the population never has
    keeps a weight at the faint end for models that fit a galaxy with less flux than
    it has (``benchmarks/studies/precision_priors.py --flux-bounds``).

    The errors are taken as ``error_scale * flux_err``, the scale fitted with the limits
    unless given. The most likely model's flux has a larger scatter than its
    fixed-model error ``flux / snr``: which size and profile fit best moves with the
    noise, and the flux with them. On exponential and de Vaucouleurs galaxies fitted
    with the bulge+disc family the scatter is 1.6-3.2 times ``flux / snr`` at every
    S/N, and with the errors as given the lower limit came out 8 % below the true one
    (the fluxes' spill below it read as counts), with the fitted scale (2.0) 1.7 %
    below.

    Parameters
    ----------
    flux : array_like
        Measured fluxes (the most likely model's amplitude, ``StampFits.flux``).
    flux_err : array_like
        Their 1-sigma errors (``flux / snr`` for the best model's S/N), up to a common
        factor (``error_scale``).
    beta : float, optional
        The counts' power; fitted together with the bounds if omitted.
    error_scale : float, optional
        The factor on ``flux_err``; fitted together with the bounds if omitted.
    outlier_fraction : float
        Weight of the log-uniform outlier density.

    Returns
    -------
    dict
        ``lo``, ``hi``, ``beta`` and ``error_scale`` (fitted or given), ``n`` (galaxies
        used) and ``lo_err``, ``hi_err`` (1-sigma, marginal: from the inverse of the
        log-likelihood's Hessian).
    """
    f, s = _usable_fluxes(flux, flux_err)
    model = _FluxRangeLikelihood.of(f, s, beta=beta, error_scale=error_scale,
                                    outlier_fraction=outlier_fraction)  # fmt: skip
    res = optimize.minimize(model.nll, model.start(), method="Nelder-Mead",
                            options={"xatol": 1e-5, "fatol": 1e-4, "maxiter": 4000})  # fmt: skip
    lo, hi, fitted_beta, scale = model.params(res.x)
    lo_err, hi_err = _bound_errors(model.nll, res.x)
    return {"lo": lo, "hi": hi, "beta": fitted_beta, "error_scale": scale, "n": int(f.size),
            "lo_err": lo_err, "hi_err": hi_err}  # fmt: skip


def _usable_fluxes(flux: np.ndarray, flux_err: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The finite, positive fluxes and errors of :func:`estimate_flux_range`, at least
    :data:`MIN_FLUX_RANGE_SAMPLE` of them."""
    f = np.asarray(flux, dtype=float).ravel()
    s = np.asarray(flux_err, dtype=float).ravel()
    if f.shape != s.shape:
        raise ValueError(f"flux and flux_err differ in shape: {f.shape} against {s.shape}")
    ok = np.isfinite(f) & np.isfinite(s) & (s > 0) & (f > 0)
    f, s = f[ok], s[ok]
    if f.size < MIN_FLUX_RANGE_SAMPLE:
        raise ValueError(f"{f.size} usable fluxes: too few to estimate the flux range")
    return f, s


@dataclass(frozen=True)
class _FluxRangeLikelihood:
    """:func:`estimate_flux_range`'s likelihood of the bounds, with the outlier density.

    Its parameters ``p`` are ``ln lo, ln hi``, then the ln of the error scale and the
    power where they are fitted (``error_scale`` and ``fit_beta``).
    """

    f: np.ndarray
    s: np.ndarray
    #: the power: given, or where its fit starts
    beta: float
    fit_beta: bool
    #: the factor on the errors, ``None`` where fitted
    error_scale: float | None
    outlier_fraction: float
    #: ``ln`` of the outlier density at each flux
    ln_out: np.ndarray
    #: Gauss-Legendre nodes and weights on ``[-1, 1]``
    nodes: tuple[np.ndarray, np.ndarray]

    @classmethod
    def of(cls, f: np.ndarray, s: np.ndarray, *, beta: float | None, error_scale: float | None,
           outlier_fraction: float) -> _FluxRangeLikelihood:  # fmt: skip
        """The likelihood of the fluxes ``f`` with errors ``s``; ``beta`` and
        ``error_scale`` fixed where given."""
        nodes = np.polynomial.legendre.leggauss(48)
        fmin, fmax = float(f.min()), float(f.max())
        ln_out = math.log(outlier_fraction) - np.log(f * math.log(fmax / fmin))
        b0 = estimate_flux_slope(f)[0] if beta is None else float(beta)
        if error_scale is not None and not error_scale > 0:
            raise ValueError(f"error_scale must be > 0, got {error_scale}")
        return cls(f=f, s=s, beta=b0, fit_beta=beta is None,
                   error_scale=None if error_scale is None else float(error_scale),
                   outlier_fraction=outlier_fraction, ln_out=ln_out, nodes=nodes)  # fmt: skip

    def start(self) -> np.ndarray:
        """Where the fit starts: the fluxes' 0.2 % and 99.95 % quantiles, the errors as
        given and the counts' power of :func:`estimate_flux_slope`."""
        lo0, hi0 = float(np.quantile(self.f, 0.002)), float(np.quantile(self.f, 0.9995))
        return np.array([math.log(lo0), math.log(hi0)]
                        + ([0.0] if self.error_scale is None else [])
                        + ([self.beta] if self.fit_beta else []))  # fmt: skip

    def params(self, p: np.ndarray) -> tuple[float, float, float, float]:
        """``lo, hi, beta, error_scale`` of the parameters ``p``."""
        i_b = 3 if self.error_scale is None else 2
        beta = float(p[i_b]) if self.fit_beta else self.beta
        scale = math.exp(p[2]) if self.error_scale is None else self.error_scale
        return math.exp(p[0]), math.exp(p[1]), beta, scale

    def nll(self, p: np.ndarray) -> float:
        """Minus the log-likelihood of the parameters ``p``."""
        lo, hi, beta, scale = self.params(p)
        if not hi > lo * 1.01:
            return 1e300
        lp = (_flux_range_loglike(self.f, self.s * scale, lo, hi, beta, self.nodes)
              + math.log1p(-self.outlier_fraction))  # fmt: skip
        return -float(np.sum(np.logaddexp(lp, self.ln_out)))


def _bound_errors(nll: Callable[[np.ndarray], float], p: np.ndarray) -> tuple[float, float]:
    """1-sigma errors of ``lo`` and ``hi`` at the minimum ``p`` of ``nll``: marginal ones
    (the bounds correlate with the power when it is fitted), from the inverse of the
    Hessian by central differences."""
    k, h = p.size, 2e-3
    H = np.empty((k, k))
    for i in range(k):
        for j in range(i, k):
            di, dj = np.eye(k)[i] * h, np.eye(k)[j] * h
            H[i, j] = H[j, i] = (nll(p + di + dj) - nll(p + di - dj) - nll(p - di + dj)
                                 + nll(p - di - dj)) / (4 * h * h)  # fmt: skip
    try:
        cov = np.linalg.inv(H)
        var = np.diag(cov)[:2]
    except np.linalg.LinAlgError:
        var = np.full(2, np.nan)
    errs = [math.exp(p[i]) * math.sqrt(var[i]) if var[i] > 0 else math.inf for i in (0, 1)]
    return errs[0], errs[1]
