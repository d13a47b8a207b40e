"""numba kernels of the amplitude integral: the uniform prior's ``ln Phi`` and inverse
Mills ratio, the power-law prior with and without flux bounds, and its table.

:func:`amplitude_tile` evaluates the amplitude part of the Laplace terms
(:func:`~pylensfit.likelihood.laplace_nb.laplace_lnl`) for a tile of models
(docs: method, eq-amplitude and eq-flux-prior).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from scipy.special import log_ndtr

from .tile_nb import W_DL, W_HS, W_ISS, W_VAL

_LN2PI = math.log(2.0 * math.pi)


def _phi_table(t0: float, t1: float, step: float):
    """Knots of ``ln Phi(t)``, ``lambda = phi / Phi`` and ``d lambda / dt`` for Hermite."""
    t = np.arange(t0, t1 + 2 * step, step)
    g = log_ndtr(t)
    lam = np.exp(-0.5 * t * t - 0.5 * _LN2PI - g)
    return g, lam, -lam * (t + lam)


#: ``ln Phi`` and the inverse Mills ratio on [-20, 7.5], cubic Hermite between knots
#: 1/64 apart: 4e-11 from scipy's values, five times faster than erfc, log and exp
_T0, _T1, _TH = -20.0, 7.5, 1.0 / 64.0
_LNPHI, _LAM, _DLAM = _phi_table(_T0, _T1, _TH)


@njit(cache=True, fastmath={"contract", "arcp", "afn"}, inline="always")
def _hermite(x, step):
    """Knot index and cubic Hermite weights ``(i, h00, h10, h01, h11)`` at ``x`` (in
    knot spacings from the first knot; knots ``step`` apart): the value is ``h00 f_i +
    h10 f'_i + h01 f_{i+1} + h11 f'_{i+1}``."""
    i = int(x)
    f = x - i
    f2 = f * f
    f3 = f2 * f
    return (i, 2.0 * f3 - 3.0 * f2 + 1.0, (f3 - 2.0 * f2 + f) * step, 3.0 * f2 - 2.0 * f3,
            (f3 - f2) * step)  # fmt: skip


@njit(cache=True, fastmath={"contract", "arcp", "afn"}, inline="always")
def _amplitude_terms(t):
    """``0.5 t^2 + ln Phi(t)`` and ``t + phi(t)/Phi(t)`` for the S/N ``t = h / (sigma sqrt S)``.

    ``exp(0.5 t^2) Phi(t)`` is the integral over a positive amplitude (uniform prior)
    of ``exp(-chi^2 / 2)``, up to factors independent of ``t``; the second value is
    ``sigma sqrt(S)`` times its ``h`` derivative, which sets the curvature in position.
    """
    if t > _T1:  # Phi(t) = 1 to 3e-14
        val = 0.5 * t * t
        dl = t
    elif t >= _T0:  # cubic Hermite interpolation of ln Phi and lambda = phi / Phi
        i, h00, h10, h01, h11 = _hermite((t - _T0) * (1.0 / _TH), _TH)
        val = 0.5 * t * t + (h00 * _LNPHI[i] + h10 * _LAM[i] + h01 * _LNPHI[i + 1]
                             + h11 * _LAM[i + 1])  # fmt: skip
        dl = t + (h00 * _LAM[i] + h10 * _DLAM[i] + h01 * _LAM[i + 1] + h11 * _DLAM[i + 1])
    else:  # asymptotic series of Mills' ratio, no cancellation
        u = 1.0 / (t * t)
        corr = 1.0 - u + 3.0 * u * u - 15.0 * u * u * u
        val = -math.log(-t) - 0.5 * _LN2PI + math.log(corr)
        dl = (-1.0 / t) * (1.0 - 3.0 * u + 15.0 * u * u) / corr
    return val, dl


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def _bounded_mass(a, b):
    """``ln(Phi(a) - Phi(b))`` and its ``a`` derivative, for ``a > b`` (``b`` may be -inf).

    The Gaussian mass of the amplitude between the bounds of a flux prior: with the S/N
    ``t`` and the bounds ``u_lo < u_hi`` in S/N units, ``a = t - u_lo``, ``b = t - u_hi``.
    The derivative (``a`` and ``b`` move together with ``t``) is ``(phi(a) - phi(b)) /
    (Phi(a) - Phi(b))``. Where both are near 1 (``b > 0``) it is written with
    ``Phi(-b) - Phi(-a)``, which keeps the difference's precision.
    """
    va, da = _amplitude_terms(a)
    lpa = va - 0.5 * a * a
    la = da - a  # phi(a) / Phi(a)
    if b == -math.inf:
        return lpa, la
    if b > 0.0:
        vq, dq = _amplitude_terms(-b)
        lp = vq - 0.5 * b * b  # ln Phi(-b)
        lam_b = dq + b  # phi(b) / Phi(-b)
        vq, dq = _amplitude_terms(-a)
        rho = math.exp(vq - 0.5 * a * a - lp)  # Phi(-a) / Phi(-b)
        lam_a = dq + a
        return lp + math.log1p(-rho), (lam_a * rho - lam_b) / (1.0 - rho)
    vb, db = _amplitude_terms(b)
    r = math.exp(vb - 0.5 * b * b - lpa)  # Phi(b) / Phi(a)
    return lpa + math.log1p(-r), (la - (db - b) * r) / (1.0 - r)


#: the amplitude prior's power that stands for the uniform prior (any finite power is a
#: power law, a negative one included: counts that rise with flux)
AMP_UNIFORM = -math.inf
#: where no lower bound is given, a power-law amplitude prior starts at this S/N (the
#: law diverges at 0 for ``beta >= 1``)
AMP_FLOOR = 1.0
#: floor on the curvature ``1 - beta / u0^2`` of the expansion point: reached only for
#: models of S/N below ~2, which carry no weight
AMP_MIN_CURV = 0.5


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"}, inline="always")
def amplitude_integral(t, s, lns, iss, amp_pow, amp_lns, amp_lo, amp_hi):
    """ln of the amplitude integral of one model and the amplitude's posterior mean in S/N
    units (see :func:`~pylensfit.likelihood.laplace_nb.laplace_lnl`), for the model's S/N
    ``t``, ``S = sum m^2``, ``ln S`` and ``iss = 1 / (sigma sqrt S)``.

    Uniform prior (``amp_pow = -inf``, :data:`AMP_UNIFORM`): ``0.5 t^2 + ln Phi(t)``,
    exact, and ``t + phi(t) / Phi(t)``. Power law ``u^-beta`` (any finite ``beta``; a
    negative one for counts that rise with flux) in the S/N ``u`` between bounds ``lo <
    hi`` (the flux
    bounds ``amp_lo``, ``amp_hi`` in the model's S/N units, ``lo`` at least
    ``AMP_FLOOR``): ``0.5 t^2 + ln int_lo^hi u^-beta phi(u - t) du``, with the log of the
    integrand ``g(u) = -beta ln u - (u - t)^2 / 2`` expanded to second order about its
    maximum ``u0`` on ``[lo, hi]`` (the root ``u* = (t + sqrt(t^2 - 4 beta)) / 2`` of
    ``g'``, or the bound it lies beyond) and the Gaussian so made integrated exactly
    between the bounds. Within 1e-3 of the exact integral for ``t >= 8`` wherever the
    bounds lie (3e-3 at ``t = 6``, 1e-2 at ``t = 4``, for ``beta <= 2``); the Laplace form
    at ``t`` itself, ``0.5 t^2 - beta ln t + ln(Phi(t - lo) - Phi(t - hi))``, was off by
    0.03 at ``t = 10`` without bounds and by 0.14 (``t = 10``) to 1.9 (``t = 4``) against
    a bound at ``lo = 10``, where the prior's ``u^-beta`` pulls the integrand's mass onto
    the bound (``tests/test_likelihood.py``). The second value, ``d val / dt``, is the
    mean of that Gaussian truncated to the bounds (the posterior mean of ``u``; within
    5e-3 of it for ``t >= 8``).
    """
    if amp_pow == AMP_UNIFORM:
        val, dl = _amplitude_terms(t)
        return val - 0.5 * lns, dl
    beta = amp_pow
    lo = max(amp_lo * s * iss, AMP_FLOOR)  # flux to S/N: sqrt(S) / sigma = S * iss
    hi = amp_hi * s * iss
    disc = t * t - 4.0 * beta
    u0 = lo
    g0 = -beta * math.log(lo) - 0.5 * (lo - t) * (lo - t)
    if disc > 0.0:
        ustar = 0.5 * (t + math.sqrt(disc))
        if ustar > lo:  # the interior maximum, unless the bound's (below the minimum
            # at the smaller root) is higher
            u = min(ustar, hi)
            gu = -beta * math.log(u) - 0.5 * (u - t) * (u - t)
            if gu >= g0:
                u0 = u
                g0 = gu
    g1 = t - u0 - beta / u0
    c = max(1.0 - beta / (u0 * u0), AMP_MIN_CURV)
    mu = u0 + g1 / c
    rc = math.sqrt(c)
    lm, dm = _bounded_mass((mu - lo) * rc, (mu - hi) * rc)
    val = 0.5 * t * t + g0 + 0.5 * g1 * g1 / c - 0.5 * math.log(c) + lm + 0.5 * amp_lns * lns
    return val, mu + dm / rc


#: the power-law amplitude integral without flux bounds depends on ``t`` alone (given
#: ``beta``): :func:`power_law_table` tabulates it from ``t0 = max(_PT_MIN, beta + 1.5)``
#: (above which its expansion point is the interior root, so it is smooth in ``t``) to
#: ``_PT_MAX``, knots ``_PT_STEP`` apart, for cubic Hermite interpolation
_PT_MIN, _PT_MAX, _PT_STEP = 4.0, 264.0, 1.0 / 16.0
#: a model whose S/N ``t`` is this far inside the flux bounds (in its S/N units) reads the
#: unbounded table: the bounds then change the integral's log and the amplitude's mean
#: by ``Phi(-5.8) ~ 3e-9`` at most, the table's own error being 2e-8
_PT_BOUND_MARGIN = 6.0


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def power_law_table(beta):
    """Knots of the unbounded power-law amplitude integral for :func:`amplitude_tile`.

    Returns ``(t0, tab)``: ``tab[0]`` is ``val - 0.5 t^2`` of :func:`amplitude_integral`
    (lower limit ``AMP_FLOOR``, no upper bound, ``S = 1``), ``tab[2]`` its second value
    (the amplitude's posterior mean), ``tab[1]`` and ``tab[3]`` their ``t`` derivatives
    (central differences), at ``t = t0 + i * _PT_STEP``. The interpolant is within 2e-8
    of the direct evaluation (``tests/test_likelihood.py``), and costs what the uniform
    prior's table does: the direct evaluation's root, logs and divisions took a third of
    a precision block's time.

    Rows 4 to 9 serve a lower flux bound ``lo`` below the interior root ``u*`` (see
    :func:`_amplitude_integral_lo`): there the integral is ``0.5 t^2 + P(t) + ln
    Phi(a)`` with ``a = (u* - lo) sqrt(c)`` and the amplitude's mean ``u* + lambda(a) /
    sqrt(c)``, ``P = -beta ln u* - (u* - t)^2 / 2 - ln(c) / 2`` and ``c = 1 - beta /
    u*^2`` functions of ``t`` alone: ``P``, ``u*`` and ``sqrt(c)`` with their ``t``
    derivatives.
    """
    t0 = max(_PT_MIN, beta + 1.5)
    n = int((_PT_MAX - t0) / _PT_STEP) + 2
    tab = np.empty((10, n))
    h = 1e-4
    for i in range(n):
        t = t0 + i * _PT_STEP
        v, d = amplitude_integral(t, 1.0, 0.0, 1.0, beta, 0.0, 0.0, math.inf)
        vp, dp = amplitude_integral(t + h, 1.0, 0.0, 1.0, beta, 0.0, 0.0, math.inf)
        vm, dm = amplitude_integral(t - h, 1.0, 0.0, 1.0, beta, 0.0, 0.0, math.inf)
        tab[0, i] = v - 0.5 * t * t
        tab[1, i] = (vp - vm) / (2.0 * h) - t
        tab[2, i] = d
        tab[3, i] = (dp - dm) / (2.0 * h)
        for r, x in enumerate((t, t + h, t - h)):
            u = 0.5 * (x + math.sqrt(x * x - 4.0 * beta))
            c = 1.0 - beta / (u * u)
            p = -beta * math.log(u) - 0.5 * (u - x) * (u - x) - 0.5 * math.log(c)
            if r == 0:
                tab[4, i], tab[6, i], tab[8, i] = p, u, math.sqrt(c)
            elif r == 1:
                tab[5, i], tab[7, i], tab[9, i] = p, u, math.sqrt(c)
            else:
                tab[5, i] = (tab[5, i] - p) / (2.0 * h)
                tab[7, i] = (tab[7, i] - u) / (2.0 * h)
                tab[9, i] = (tab[9, i] - math.sqrt(c)) / (2.0 * h)
    return t0, tab


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"}, inline="always")
def _amplitude_integral_lo(t, lo, beta):
    """:func:`amplitude_integral` for a power law with a lower flux bound ``lo > 1``
    (S/N units) and no upper one, for ``t >= beta + 1.5``: ``val - 0.5 t^2`` without the
    ``amp_lns`` term, and the amplitude's mean.

    The same expansion (about the interior root ``u*`` of ``g'``, or ``lo`` where
    ``u* <= lo``; from ``t = beta + 1.5`` the smaller root is below 1, so ``g`` rises
    from ``lo`` to ``u*`` and the comparison of the two is not needed) and the same
    Gaussian mass above ``lo``, with no upper tail: for a model whose S/N is
    ``_PT_BOUND_MARGIN`` below the upper bound that tail changes the log by ``Phi(-5.8)
    ~ 3e-9`` at most, as for the table. A root, two logs and one normal-tail lookup,
    where the general form takes three logs, two lookups, an exponential and a
    ``log1p``: the faint models near the lower bound are most of a bounded fit's
    direct evaluations.
    """
    ustar = 0.5 * (t + math.sqrt(t * t - 4.0 * beta))
    u0 = ustar if ustar > lo else lo
    g1 = t - u0 - beta / u0
    c = max(1.0 - beta / (u0 * u0), AMP_MIN_CURV)
    mu = u0 + g1 / c
    rc = math.sqrt(c)
    a = (mu - lo) * rc
    va, da = _amplitude_terms(a)
    val = (-beta * math.log(u0) - 0.5 * (u0 - t) * (u0 - t) + 0.5 * g1 * g1 / c
           - 0.5 * math.log(c) + va - 0.5 * a * a)  # fmt: skip
    return val, mu + (da - a) / rc


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def amplitude_tile(cm, amp_pow, amp_lns, amp_lo, amp_hi, t0, tab, W):
    """The amplitude integral of :func:`~pylensfit.likelihood.laplace_nb.laplace_lnl` for a
    tile: its log (row ``W_VAL`` of the tile's work array ``W``) and ``-(d val / d h)``
    (``W_DL``). A table per model (:func:`_amplitude_terms`; for a
    power law, ``tab`` from :func:`power_law_table`, or ``tab`` of width 0 for none),
    read where the model's S/N is ``_PT_BOUND_MARGIN`` inside the flux bounds (all of
    them without bounds); within that of the lower bound only, the lower bound's
    evaluation :func:`_amplitude_integral_lo`; else the direct evaluation: scalar."""
    n_tab = tab.shape[1]
    t1 = t0 + (n_tab - 2) * _PT_STEP
    for k in range(W.shape[1]):
        iss = W[W_ISS, k]
        t = W[W_HS, k] * iss
        lo_u = amp_lo * cm[0, k] * iss  # the flux bounds in the model's S/N units
        hi_u = amp_hi * cm[0, k] * iss
        if (n_tab > 0 and t >= t0 and t < t1 and hi_u - t >= _PT_BOUND_MARGIN
                and (lo_u <= AMP_FLOOR or t - lo_u >= _PT_BOUND_MARGIN)):
            i, h00, h10, h01, h11 = _hermite((t - t0) * (1.0 / _PT_STEP), _PT_STEP)
            val = (0.5 * t * t + h00 * tab[0, i] + h10 * tab[1, i] + h01 * tab[0, i + 1]
                   + h11 * tab[1, i + 1] + 0.5 * amp_lns * cm[5, k])  # fmt: skip
            dl = h00 * tab[2, i] + h10 * tab[3, i] + h01 * tab[2, i + 1] + h11 * tab[3, i + 1]
        elif n_tab > 0 and t >= t0 and hi_u - t >= _PT_BOUND_MARGIN and lo_u > AMP_FLOOR:
            ustar = 0.0
            if t < t1:
                i, h00, h10, h01, h11 = _hermite((t - t0) * (1.0 / _PT_STEP), _PT_STEP)
                ustar = (h00 * tab[6, i] + h10 * tab[7, i] + h01 * tab[6, i + 1]
                         + h11 * tab[7, i + 1])  # fmt: skip
            if ustar > lo_u:  # the interior root above the bound: P, u*, sqrt(c) of t
                rc = h00 * tab[8, i] + h10 * tab[9, i] + h01 * tab[8, i + 1] + h11 * tab[9, i + 1]
                a = (ustar - lo_u) * rc
                va, da = _amplitude_terms(a)
                val = (0.5 * t * t + h00 * tab[4, i] + h10 * tab[5, i] + h01 * tab[4, i + 1]
                       + h11 * tab[5, i + 1] + va - 0.5 * a * a
                       + 0.5 * amp_lns * cm[5, k])  # fmt: skip
                dl = ustar + (da - a) / rc
            else:
                val, dl = _amplitude_integral_lo(t, lo_u, amp_pow)
                val += 0.5 * t * t + 0.5 * amp_lns * cm[5, k]
        else:
            val, dl = amplitude_integral(t, cm[0, k], cm[5, k], iss, amp_pow, amp_lns,
                                          amp_lo, amp_hi)  # fmt: skip
        W[W_VAL, k] = val
        W[W_DL, k] = -dl * iss



def amplitude_table(amp_pow):
    """The power-law table ``(t0, tab)`` that
    :func:`~pylensfit.likelihood.grid_nb.laplace_grid` needs for an amplitude prior
    (computed once for many calls of
    :func:`~pylensfit.likelihood.grid_nb.laplace_grid_tab`). With flux bounds too: the
    models whose S/N is ``_PT_BOUND_MARGIN`` or more inside both read it."""
    if amp_pow != AMP_UNIFORM:
        return power_law_table(amp_pow)
    return 0.0, np.empty((4, 0))
