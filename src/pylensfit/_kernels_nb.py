"""numba kernel of the likelihood engine: Laplace terms and the sum over r, fused.

Called by :mod:`pylensfit.likelihood` on the outputs of the six matrix products (docs:
method, eq-matrix-products). One pass over (galaxy, model) pairs, parallel over
galaxies, with the sum over radius kept as a running log-sum-exp so that nothing of size
(galaxies x models) is written back. :func:`_laplace_lnl` is the per-model reference of
the Laplace terms; :func:`laplace_grid` evaluates them a tile of models at a time, in
branch-free loops that LLVM vectorises (``tests/test_likelihood.py`` holds the two
together).
"""

from __future__ import annotations

import functools
import math
import os
import threading
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext

import numba
import numpy as np
from numba import njit, prange
from scipy.special import log_ndtr

_LN2PI = math.log(2.0 * math.pi)

#: held around each launch of a parallel kernel while numba's threading layer is its
#: work queue (the fork-safe layer where TBB is absent, chosen by
#: :func:`pylensfit.likelihood._fork_safe_threading`): that layer aborts the process
#: ("Concurrent access has been detected") when two threads launch kernels at once, as
#: the image tasks of a dask worker with several threads do
_LAUNCH_LOCK = threading.Lock()


def _renew_launch_lock() -> None:
    """A fresh lock in a forked child: a thread of the parent may have held the old one."""
    global _LAUNCH_LOCK
    _LAUNCH_LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_renew_launch_lock)


def launch_guard() -> AbstractContextManager:
    """The lock on the work queue (and before any layer has started, since this launch
    may start the work queue); a context that does nothing on TBB or OpenMP."""
    try:
        layer = numba.threading_layer()
    except ValueError:  # no parallel kernel has run yet
        return _LAUNCH_LOCK
    return _LAUNCH_LOCK if layer == "workqueue" else nullcontext()


def _one_launch_at_a_time(kernel: Callable) -> Callable:
    """``kernel`` (a parallel numba dispatcher) called from Python under :func:`launch_guard`."""

    @functools.wraps(kernel, updated=())
    def launch(*args):
        with launch_guard():
            return kernel(*args)

    launch.kernel = kernel
    return launch


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
_AMP_FLOOR = 1.0
#: floor on the curvature ``1 - beta / u0^2`` of the expansion point: reached only for
#: models of S/N below ~2, which carry no weight
_AMP_MIN_CURV = 0.5


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"}, inline="always")
def _amplitude_integral(t, s, lns, iss, amp_pow, amp_lns, amp_lo, amp_hi):
    """ln of the amplitude integral of one model and the amplitude's posterior mean in S/N
    units (see :func:`_laplace_lnl`), for the model's S/N ``t``, ``S = sum m^2``, ``ln
    S`` and ``iss = 1 / (sigma sqrt S)``.

    Uniform prior (``amp_pow = -inf``, :data:`AMP_UNIFORM`): ``0.5 t^2 + ln Phi(t)``,
    exact, and ``t + phi(t) / Phi(t)``. Power law ``u^-beta`` (any finite ``beta``; a
    negative one for counts that rise with flux) in the S/N ``u`` between bounds ``lo <
    hi`` (the flux
    bounds ``amp_lo``, ``amp_hi`` in the model's S/N units, ``lo`` at least
    ``_AMP_FLOOR``): ``0.5 t^2 + ln int_lo^hi u^-beta phi(u - t) du``, with the log of the
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
    lo = max(amp_lo * s * iss, _AMP_FLOOR)  # flux to S/N: sqrt(S) / sigma = S * iss
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
    c = max(1.0 - beta / (u0 * u0), _AMP_MIN_CURV)
    mu = u0 + g1 / c
    rc = math.sqrt(c)
    lm, dm = _bounded_mass((mu - lo) * rc, (mu - hi) * rc)
    val = 0.5 * t * t + g0 + 0.5 * g1 * g1 / c - 0.5 * math.log(c) + lm + 0.5 * amp_lns * lns
    return val, mu + dm / rc


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"}, inline="always")
def _cubic_hessian(hxx, hxy, hyy, txxx, txxy, txyy, tyyy, x, y):
    """The Hessian of ``h``'s third-order expansion at ``(x, y)``."""
    return (hxx + txxx * x + txxy * y, hxy + txxy * x + txyy * y,
            hyy + txyy * x + tyyy * y)  # fmt: skip


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"}, inline="always")
def _cubic_value(h0, gx, gy, hxx, hxy, hyy, txxx, txxy, txyy, tyyy, x, y):
    """``h`` at ``(x, y)`` by its third-order expansion about the origin."""
    return (
        h0 + gx * x + gy * y
        + 0.5 * (hxx * x * x + 2.0 * hxy * x * y + hyy * y * y)
        + (txxx * x * x * x + 3 * txxy * x * x * y + 3 * txyy * x * y * y
           + tyyy * y * y * y) / 6.0
    )  # fmt: skip


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"}, inline="always")
def _position_prior(dl, hxx, hxy, hyy, dx, dy, b2):
    """``det M`` and the quadratic form of the catalogue offset ``(dx, dy)`` for the
    position Fisher matrix ``F = dl Hess h`` and the prior width ``b``: ``M = I + b^2
    F``, and ``(F^-1 + b^2 I)^-1 = F M^-1 = (F + b^2 det(F) I) / det(M)`` (F and M
    commute)."""
    f11 = dl * hxx
    f12 = dl * hxy
    f22 = dl * hyy
    detf = f11 * f22 - f12 * f12
    m11 = 1.0 + b2 * f11
    m22 = 1.0 + b2 * f22
    m12 = b2 * f12
    detm = m11 * m22 - m12 * m12
    quad = (
        (f11 + b2 * detf) * dx * dx + 2.0 * f12 * dx * dy + (f22 + b2 * detf) * dy * dy
    ) / detm
    return detm, quad


@njit(cache=True, fastmath={"contract", "arcp", "afn"}, inline="always")
def _laplace_lnl(h0, gx, gy, hxx, hxy, hyy, txxx, txxy, txyy, tyyy, cubic, s, sqs, lns,
                 mxx, mxy, myy, sig, x0, y0, b2, max_step2, amp_pow, amp_lns, amp_lo=0.0,
                 amp_hi=math.inf):  # fmt: skip
    """ln L of one model, marginalised over amplitude (> 0) and position (Laplace).

    ``s``, ``sqs``, ``lns`` are ``S = sum m^2``, its square root and its log. With
    ``amp_pow = -inf`` the amplitude prior is uniform (the paper's): ``0.5 t^2 + ln Phi(t) -
    0.5 ln S`` for the model's S/N ``t = h / (sigma sqrt S)``. With a finite ``amp_pow =
    beta`` it is a power law in the model's S/N, ``p(A | model) ~ t^-beta dt/dA``, between
    bounds ``amp_lo``, ``amp_hi`` on the flux (:func:`_amplitude_integral`; the ``sqrt
    S`` of the Gaussian's width in ``A`` cancels that of ``dt/dA``), plus ``amp_lns * 0.5
    ln S``: ``amp_lns = beta - 1`` makes it a power law ``A^-beta`` in the amplitude (the
    flux) itself, the same for every model. With
    ``cubic``, the third derivatives ``t...`` of ``h`` refine the peak (two Newton steps
    on the cubic expansion) and give the Hessian at the peak rather than at the origin.
    Returns ``(ln L, h*, X*, Y*)``. See :func:`pylensfit.likelihood.fit_stamps`.
    """
    ss = sig * sqs
    iss = 1.0 / ss
    det = hxx * hyy - hxy * hxy
    ok = hxx < 0.0 and det > 0.0
    if ok:
        idet = 1.0 / det
        x = (hxy * gy - hyy * gx) * idet
        y = (hxy * gx - hxx * gy) * idet
        if x * x + y * y > max_step2:
            ok = False
    if not ok:
        # the data Hessian is not a maximum here (noise, or far from the peak):
        # use the expected Hessian, that of the model's autocorrelation
        scale = max(h0, ss) / s
        hxx = scale * mxx
        hxy = scale * mxy
        hyy = scale * myy
        idet = 1.0 / (hxx * hyy - hxy * hxy)
        x = (hxy * gy - hyy * gx) * idet
        y = (hxy * gx - hxx * gy) * idet
        rr = x * x + y * y
        if rr > max_step2:
            f = math.sqrt(max_step2 / rr)
            x *= f
            y *= f
        cubic = False
    hstar = h0 + gx * x + gy * y + 0.5 * (hxx * x * x + 2.0 * hxy * x * y + hyy * y * y)
    if cubic:
        for _ in range(2):
            ax, axy, ay = _cubic_hessian(hxx, hxy, hyy, txxx, txxy, txyy, tyyy, x, y)
            d3 = ax * ay - axy * axy
            if not (ax < 0.0 and d3 > 0.0):
                break
            rx = gx + hxx * x + hxy * y + 0.5 * (txxx * x * x + 2 * txxy * x * y + txyy * y * y)
            ry = gy + hxy * x + hyy * y + 0.5 * (txxy * x * x + 2 * txyy * x * y + tyyy * y * y)
            nx = x + (axy * ry - ay * rx) / d3
            ny = y + (axy * rx - ax * ry) / d3
            if nx * nx + ny * ny > max_step2:
                break
            x = nx
            y = ny
        ax, axy, ay = _cubic_hessian(hxx, hxy, hyy, txxx, txxy, txyy, tyyy, x, y)
        if ax < 0.0 and ax * ay - axy * axy > 0.0:
            hstar = _cubic_value(h0, gx, gy, hxx, hxy, hyy, txxx, txxy, txyy, tyyy, x, y)
            hxx = ax
            hxy = axy
            hyy = ay
    val, dl = _amplitude_integral(hstar * iss, s, lns, iss, amp_pow, amp_lns, amp_lo, amp_hi)
    dl = -dl * iss
    # Fisher matrix of position, F = -(dl/dh) Hess h
    detm, quad = _position_prior(dl, hxx, hxy, hyy, x - x0, y - y0, b2)
    lnl = val - 0.5 * math.log(detm) - 0.5 * quad
    return lnl, hstar, x, y


@njit(cache=True, fastmath={"contract", "arcp", "afn"}, inline="always")
def _narrow_peak_factor(lm, l0, lp):
    """Correction of the sum over the r grid for a peak narrower than the grid step.

    ``sum_j L(r_j) dr`` is the trapezoid rule, exact to ``exp(-2 pi^2 s^2)`` for a
    Gaussian of width ``s`` grid steps, but for ``s < 1`` its value oscillates with
    the sub-step position of the peak: a bright galaxy's ``L(e)`` then jumps from one
    e cell to the next as the best size moves across the r grid. With the parabola
    through ``ln L`` at the largest sample and its neighbours (width ``s``, offset
    ``d``), the factor is ``sqrt(2 pi) s / sum_j exp(-(j - d)^2 / (2 s^2))``: the ratio
    of that Gaussian's integral to its grid sum, which makes the r marginalisation
    exact for a Gaussian peak and tends to 1 (to 3e-9) for ``s >= 1``.
    """
    a = lm - 2.0 * l0 + lp
    if a >= -1.0:  # s >= 1 step, or no peak: the grid sum is accurate
        return 1.0
    s2 = -1.0 / a
    d = 0.5 * (lm - lp) / a
    gsum = 0.0
    for j in range(-7, 8):
        gsum += math.exp(-0.5 * (j - d) * (j - d) / s2)
    if not gsum > 1e-300:  # a cliff in ln(w L) (a prior's edge), not a peak
        return 1.0
    return math.sqrt(2.0 * math.pi * s2) / gsum


@njit(cache=True, fastmath={"contract", "arcp", "afn"}, inline="always")
def _run_peak_factor(lwm, lw0, lwp, lm, l0, lp, kink):
    """:func:`_narrow_peak_factor` at the largest ``ln(w_j L_j)`` of a run of sizes.

    ``lwm, lw0, lwp`` are ``ln(w L)`` at that node and its neighbours, ``lm, l0, lp``
    ``ln L`` there and ``kink`` the second difference of ``ln w``. Where the prior bends
    by more than :data:`_PRIOR_KINK` (an edge) the factor comes from ``ln L`` alone, and
    only if ``L`` itself peaks at the node; else it is 1.
    """
    if abs(kink) <= _PRIOR_KINK:
        return _narrow_peak_factor(lwm, lw0, lwp)
    if l0 >= lm and l0 >= lp:
        return _narrow_peak_factor(lm, l0, lp)
    return 1.0


#: columns of the model bank handled together by :func:`laplace_grid`: each stage of the
#: Laplace terms runs over a tile as one loop of independent iterations, which LLVM
#: vectorises (AVX2) and the CPU overlaps, where one model at a time is one long chain of
#: dependent divisions and logs (measured on the precision mode's bank, 68,256 models, one
#: thread: 115 ns per model before, 47 after; the tile's arrays are one per kind, with
#: the column offset taken out of their indices, or LLVM does not vectorise)
_TILE = 256
@njit(cache=True, inline="always")
def _fold(V, q, k, p0, p1, p2, p3):
    """The four models of a folded column from its four characters' products
    (:func:`pylensfit.likelihood._folded_bank`), into ``V[:, q, k]``."""
    s02 = p0 + p2
    s13 = p1 + p3
    d02 = p0 - p2
    d13 = p1 - p3
    V[0, q, k] = s02 + s13
    V[1, q, k] = s02 - s13
    V[2, q, k] = d02 + d13
    V[3, q, k] = d02 - d13


# rows of a tile's work array ``W``
_X, _Y, _HS, _AXX, _AXY, _AYY, _ISS, _OK, _VAL, _DL, _QUAD, _DETM = range(12)
_NW = 12


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def _position_tile(V, cm, sig, max_step2, W):
    """The position part of :func:`_laplace_lnl` for one member's models of a tile,
    without branches: the peak ``X*`` (one Newton step, or the expected Hessian's where
    the data Hessian is not a maximum or the step is too long), ``h*``, the Hessian and
    the S/N ``t``. ``V`` (q, k): the products; ``cm`` (6, k): ``S, sqrt S, mxx, mxy, myy,
    ln S``; ``W`` (_NW, k): the results."""
    for k in range(V.shape[1]):
        h0 = V[0, k]
        gx = V[1, k]
        gy = V[2, k]
        hxx = V[3, k]
        hxy = V[4, k]
        hyy = V[5, k]
        ss = sig * cm[1, k]
        iss = 1.0 / ss
        det = hxx * hyy - hxy * hxy
        idet = 1.0 / det
        x1 = (hxy * gy - hyy * gx) * idet
        y1 = (hxy * gx - hxx * gy) * idet
        far = x1 * x1 + y1 * y1 > max_step2
        ok = (hxx < 0.0) & (det > 0.0) & (not far)
        # the expected Hessian, that of the model's autocorrelation
        scale = (ss if ss > h0 else h0) / cm[0, k]
        exx = scale * cm[2, k]
        exy = scale * cm[3, k]
        eyy = scale * cm[4, k]
        eidet = 1.0 / (exx * eyy - exy * exy)
        x2 = (exy * gy - eyy * gx) * eidet
        y2 = (exy * gx - exx * gy) * eidet
        rr = x2 * x2 + y2 * y2
        f = math.sqrt(max_step2 / rr) if rr > max_step2 else 1.0
        x = x1 if ok else x2 * f
        y = y1 if ok else y2 * f
        hxx = hxx if ok else exx
        hxy = hxy if ok else exy
        hyy = hyy if ok else eyy
        hstar = h0 + gx * x + gy * y + 0.5 * (hxx * x * x + 2.0 * hxy * x * y + hyy * y * y)
        W[_X, k] = x
        W[_Y, k] = y
        W[_HS, k] = hstar
        W[_AXX, k] = hxx
        W[_AXY, k] = hxy
        W[_AYY, k] = hyy
        W[_ISS, k] = iss
        W[_OK, k] = 1.0 if ok else 0.0


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def _cubic_tile(V, max_step2, W):
    """The third-order refinement of :func:`_laplace_lnl` for a tile (where the data
    Hessian was used): two Newton steps on the cubic expansion, and ``h*`` and the
    Hessian at the peak."""
    for k in range(V.shape[1]):
        h0 = V[0, k]
        gx = V[1, k]
        gy = V[2, k]
        hxx = V[3, k]
        hxy = V[4, k]
        hyy = V[5, k]
        txxx = V[6, k]
        txxy = V[7, k]
        txyy = V[8, k]
        tyyy = V[9, k]
        ok = W[_OK, k] > 0.0
        x = W[_X, k]
        y = W[_Y, k]
        go = ok
        for _ in range(2):
            ax, axy, ay = _cubic_hessian(hxx, hxy, hyy, txxx, txxy, txyy, tyyy, x, y)
            d3 = ax * ay - axy * axy
            go = go & (ax < 0.0) & (d3 > 0.0)
            rx = gx + hxx * x + hxy * y + 0.5 * (txxx * x * x + 2 * txxy * x * y + txyy * y * y)
            ry = gy + hxy * x + hyy * y + 0.5 * (txxy * x * x + 2 * txyy * x * y + tyyy * y * y)
            nx = x + (axy * ry - ay * rx) / d3
            ny = y + (axy * rx - ax * ry) / d3
            go = go & (not (nx * nx + ny * ny > max_step2))
            x = nx if go else x
            y = ny if go else y
        ax, axy, ay = _cubic_hessian(hxx, hxy, hyy, txxx, txxy, txyy, tyyy, x, y)
        fin = ok & (ax < 0.0) & (ax * ay - axy * axy > 0.0)
        hc = _cubic_value(h0, gx, gy, hxx, hxy, hyy, txxx, txxy, txyy, tyyy, x, y)
        W[_X, k] = x
        W[_Y, k] = y
        W[_HS, k] = hc if fin else W[_HS, k]
        W[_AXX, k] = ax if fin else W[_AXX, k]
        W[_AXY, k] = axy if fin else W[_AXY, k]
        W[_AYY, k] = ay if fin else W[_AYY, k]


#: the power-law amplitude integral without flux bounds depends on ``t`` alone (given
#: ``beta``): :func:`_power_law_table` tabulates it from ``t0 = max(_PT_MIN, beta + 1.5)``
#: (above which its expansion point is the interior root, so it is smooth in ``t``) to
#: ``_PT_MAX``, knots ``_PT_STEP`` apart, for cubic Hermite interpolation
_PT_MIN, _PT_MAX, _PT_STEP = 4.0, 264.0, 1.0 / 16.0
#: a model whose S/N ``t`` is this far inside the flux bounds (in its S/N units) reads the
#: unbounded table: the bounds then change the integral's log and the amplitude's mean
#: by ``Phi(-5.8) ~ 3e-9`` at most, the table's own error being 2e-8
_PT_BOUND_MARGIN = 6.0


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def _power_law_table(beta):
    """Knots of the unbounded power-law amplitude integral for :func:`_amplitude_tile`.

    Returns ``(t0, tab)``: ``tab[0]`` is ``val - 0.5 t^2`` of :func:`_amplitude_integral`
    (lower limit ``_AMP_FLOOR``, no upper bound, ``S = 1``), ``tab[2]`` its second value
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
        v, d = _amplitude_integral(t, 1.0, 0.0, 1.0, beta, 0.0, 0.0, math.inf)
        vp, dp = _amplitude_integral(t + h, 1.0, 0.0, 1.0, beta, 0.0, 0.0, math.inf)
        vm, dm = _amplitude_integral(t - h, 1.0, 0.0, 1.0, beta, 0.0, 0.0, math.inf)
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
    """:func:`_amplitude_integral` for a power law with a lower flux bound ``lo > 1``
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
    c = max(1.0 - beta / (u0 * u0), _AMP_MIN_CURV)
    mu = u0 + g1 / c
    rc = math.sqrt(c)
    a = (mu - lo) * rc
    va, da = _amplitude_terms(a)
    val = (-beta * math.log(u0) - 0.5 * (u0 - t) * (u0 - t) + 0.5 * g1 * g1 / c
           - 0.5 * math.log(c) + va - 0.5 * a * a)  # fmt: skip
    return val, mu + (da - a) / rc


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def _amplitude_tile(cm, amp_pow, amp_lns, amp_lo, amp_hi, t0, tab, W):
    """The amplitude integral of :func:`_laplace_lnl` for a tile: its log ``_VAL`` and
    ``-(d val / d h)`` (``_DL``). A table per model (:func:`_amplitude_terms`; for a
    power law, ``tab`` from :func:`_power_law_table`, or ``tab`` of width 0 for none),
    read where the model's S/N is ``_PT_BOUND_MARGIN`` inside the flux bounds (all of
    them without bounds); within that of the lower bound only, the lower bound's
    evaluation :func:`_amplitude_integral_lo`; else the direct evaluation: scalar."""
    n_tab = tab.shape[1]
    t1 = t0 + (n_tab - 2) * _PT_STEP
    for k in range(W.shape[1]):
        iss = W[_ISS, k]
        t = W[_HS, k] * iss
        lo_u = amp_lo * cm[0, k] * iss  # the flux bounds in the model's S/N units
        hi_u = amp_hi * cm[0, k] * iss
        if (n_tab > 0 and t >= t0 and t < t1 and hi_u - t >= _PT_BOUND_MARGIN
                and (lo_u <= _AMP_FLOOR or t - lo_u >= _PT_BOUND_MARGIN)):
            i, h00, h10, h01, h11 = _hermite((t - t0) * (1.0 / _PT_STEP), _PT_STEP)
            val = (0.5 * t * t + h00 * tab[0, i] + h10 * tab[1, i] + h01 * tab[0, i + 1]
                   + h11 * tab[1, i + 1] + 0.5 * amp_lns * cm[5, k])  # fmt: skip
            dl = h00 * tab[2, i] + h10 * tab[3, i] + h01 * tab[2, i + 1] + h11 * tab[3, i + 1]
        elif n_tab > 0 and t >= t0 and hi_u - t >= _PT_BOUND_MARGIN and lo_u > _AMP_FLOOR:
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
            val, dl = _amplitude_integral(t, cm[0, k], cm[5, k], iss, amp_pow, amp_lns,
                                          amp_lo, amp_hi)  # fmt: skip
        W[_VAL, k] = val
        W[_DL, k] = -dl * iss


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def _fisher_tile(x0, y0, b2, W):
    """The position prior part of :func:`_laplace_lnl` for a tile: ``det M`` and the
    quadratic form of the catalogue offset."""
    for k in range(W.shape[1]):
        W[_DETM, k], W[_QUAD, k] = _position_prior(
            W[_DL, k], W[_AXX, k], W[_AXY, k], W[_AYY, k], W[_X, k] - x0, W[_Y, k] - y0, b2
        )


#: below this many e-folds under a galaxy's peak, exp() underflows in double precision
_UNDERFLOW = 700.0
#: exp(x) is exactly 0 in double precision below x = -745.14: the sum over models skips
#: the call there, bit-identical (a bright galaxy's models far from its shape are most of
#: them: the kernel 13% faster on a precision block)
_EXP_ZERO = 746.0

#: a size prior whose ``ln`` weight bends by more than this between neighbouring nodes
#: has an edge there (a box, a steep population edge):
#: the narrow-peak factor then comes from ``ln L`` alone (where ``L`` peaks at that
#: node, else none), since the parabola through ``ln(w L)`` would read the cliff as a
#: peak narrower than the grid and inflate the edge node's weight (by ~30%)
_PRIOR_KINK = 1.0


def amplitude_table(amp_pow):
    """The power-law table that :func:`laplace_grid` needs for an amplitude prior (computed
    once for many calls of :func:`laplace_grid_tab`). With flux bounds too: the models
    whose S/N is ``_PT_BOUND_MARGIN`` or more inside both read it."""
    if amp_pow != AMP_UNIFORM:
        return _power_law_table(amp_pow)
    return 0.0, np.empty((4, 0))


@njit(cache=True)
def _laplace_grid_nb(
    prod, members, mix_a, mix_b, mix_f, n_gal, n_e, n_r, n_sub, s_m, mxx, mxy, myy, sigma,
    x0, y0, b2, max_step,
    node_w, w_star, ln_pi, e_w, e_grp, amp_pow, amp_lns, amp_lo, amp_hi, cubic, out_lnle,
    out_lnlb, out_lnlr, out_best, out_h, out_x, out_y,
):  # fmt: skip
    """:func:`laplace_grid_tab` with the amplitude prior's table computed here."""
    if amp_pow != AMP_UNIFORM:
        pt0, ptab = _power_law_table(amp_pow)
    else:
        pt0, ptab = 0.0, np.empty((4, 0))
    _laplace_grid_tab_nb(prod, members, mix_a, mix_b, mix_f, n_gal, n_e, n_r, n_sub, s_m,
                         mxx, mxy, myy, sigma, x0, y0, b2, max_step, node_w, w_star, ln_pi,
                         e_w, e_grp, amp_pow, amp_lns, amp_lo, amp_hi, cubic, pt0, ptab,
                         out_lnle, out_lnlb, out_lnlr, out_best, out_h, out_x, out_y)  # fmt: skip


laplace_grid = _one_launch_at_a_time(_laplace_grid_nb)


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def _tile_tables(members, mix_a, mix_b, mix_f, s_m, sq_m, mxx, mxy, myy, ln_m):
    """:func:`_laplace_grid_tab_nb`'s tables: the length of the run of mixed columns
    starting at each (``mix_run``), and every tile's model indices ``cj`` and model
    constants ``cm`` (S, sqrt S, mxx, mxy, myy, ln S), in the order the tiles read them."""
    n_cols = members.shape[0]
    # runs of mixed columns whose base columns are consecutive and whose fraction is one
    n_mix = mix_a.size
    mix_run = np.ones(n_mix, dtype=np.int64)
    for d in range(n_mix - 2, -1, -1):
        if (mix_a[d + 1] == mix_a[d] + 1 and mix_b[d + 1] == mix_b[d] + 1
                and mix_f[d + 1] == mix_f[d]):  # fmt: skip
            mix_run[d] = mix_run[d + 1] + 1
    n_memb = members.shape[1]
    # the model constants of every (member, column) slot, tile by tile, in the order the
    # tiles read them (padding: a harmless model, member -1)
    n_tiles = -(-n_cols // _TILE)
    cj = np.full((n_tiles, n_memb, _TILE), -1, dtype=np.int64)
    cm = np.zeros((n_tiles, n_memb, 6, _TILE))
    cm[:, :, 0] = 1.0  # S, sqrt S, mxx, mxy, myy, ln S of the padding
    cm[:, :, 1] = 1.0
    cm[:, :, 2] = -1.0
    cm[:, :, 4] = -1.0
    for it in range(n_tiles):
        for hm in range(n_memb):
            for k in range(min(_TILE, n_cols - it * _TILE)):
                j = members[it * _TILE + k, hm]
                cj[it, hm, k] = j
                if j >= 0:
                    cm[it, hm, 0, k] = s_m[j]
                    cm[it, hm, 1, k] = sq_m[j]
                    cm[it, hm, 2, k] = mxx[j]
                    cm[it, hm, 3, k] = mxy[j]
                    cm[it, hm, 4, k] = myy[j]
                    cm[it, hm, 5, k] = ln_m[j]
    return mix_run, cj, cm


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def _read_tile(prod, g, n_gal, t0, nt, n_q, n_base, mix_a, mix_b, mix_f, mix_run, V):
    """Fill ``V`` with galaxy ``g``'s products of the tile of columns ``t0 .. t0 + nt``
    (:func:`_laplace_grid_tab_nb`)."""
    n_chi = prod.shape[0]
    one = prod.dtype.type(1.0)
    zero = prod.dtype.type(0.0)
    # the rows of every model of the tile's columns: the column's own values
    # (n_chi = 1) or the four sign combinations of the four characters (n_chi = 4),
    # read row by row (contiguous) rather than column by column
    for q in range(n_q):
        row = q * n_gal + g
        # runs of base columns, read directly, and of mixed columns, each the
        # mix of two runs of base columns in prod's precision
        k = 0
        while k < nt:
            c = t0 + k
            if c < n_base:
                ca, cb = c, c
                fa, fm = one, zero  # unused: the base columns are read as they are
                ln = min(n_base - c, nt - k)
            else:
                ca = mix_a[c - n_base]
                cb = mix_b[c - n_base]
                fm = prod.dtype.type(mix_f[c - n_base])
                fa = prod.dtype.type(1.0 - mix_f[c - n_base])
                ln = min(mix_run[c - n_base], nt - k)
            if c < n_base and n_chi == 4:
                for kk in range(ln):
                    ia = ca + kk
                    _fold(V, q, k + kk, prod[0, row, ia], prod[1, row, ia],
                          prod[2, row, ia], prod[3, row, ia])  # fmt: skip
            elif n_chi == 4:
                for kk in range(ln):
                    ia = ca + kk
                    ib = cb + kk
                    _fold(V, q, k + kk, fa * prod[0, row, ia] + fm * prod[0, row, ib],
                          fa * prod[1, row, ia] + fm * prod[1, row, ib],
                          fa * prod[2, row, ia] + fm * prod[2, row, ib],
                          fa * prod[3, row, ia] + fm * prod[3, row, ib])  # fmt: skip
            elif c < n_base:
                for kk in range(ln):
                    V[0, q, k + kk] = prod[0, row, ca + kk]
            else:
                for kk in range(ln):
                    V[0, q, k + kk] = (fa * prod[0, row, ca + kk]
                                       + fm * prod[0, row, cb + kk])  # fmt: skip
            k += ln


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def _collapse_models(g, buf, best, w_star, n_e, n_r, n_sub, e_grp, e_w, node_w, ln_w, ln_pi,
                     pi, out_lnle, out_lnlb, out_lnlr):  # fmt: skip
    """Galaxy ``g``'s second pass (:func:`_laplace_grid_tab_nb`): from its ``ln L`` of
    every model ``buf`` (peak ``best``), ``ln L(e)`` summed over r, ``ln L_k(e)`` per run
    and ``ln L(r)`` per group of e cells."""
    star = buf.size - 1
    n_blk = n_r // n_sub
    n_grp = out_lnlr.shape[1]
    lw_star = buf[star] + math.log(w_star)
    ex_star = math.exp(lw_star - best)
    rsum = np.zeros((n_grp, n_r))
    lwr = np.empty(n_sub)
    for ie in range(n_e):
        ge = e_grp[ie]
        ew = e_w[ie]
        acc = ex_star
        emax = lw_star
        for ib in range(n_blk):  # runs of increasing r, one per bulge fraction
            bacc = 0.0
            rmax = -np.inf
            km = 0
            for irr in range(n_sub):
                ir = ib * n_sub + irr
                if not node_w[ir] > 0.0:  # outside the size prior: not evaluated
                    lwr[irr] = -np.inf
                    continue
                l = buf[ie * n_r + ir]
                dlb = l - best
                ex = math.exp(dlb) if dlb > -_EXP_ZERO else 0.0
                bacc += ex * node_w[ir]
                rsum[ge, ir] += ex * ew
                lw = l + ln_w[ir]
                lwr[irr] = lw
                if lw > rmax:
                    rmax = lw
                    km = irr
            ir = ib * n_sub + km
            if 0 < km < n_sub - 1 and node_w[ir - 1] > 0.0 and node_w[ir + 1] > 0.0:
                bacc *= _run_peak_factor(
                    lwr[km - 1], lwr[km], lwr[km + 1], buf[ie * n_r + ir - 1],
                    buf[ie * n_r + ir], buf[ie * n_r + ir + 1],
                    ln_w[ir - 1] - 2.0 * ln_w[ir] + ln_w[ir + 1],
                )  # fmt: skip
            if rmax > best - _UNDERFLOW and bacc > 0.0:
                out_lnlb[g, ie, ib] = best + math.log(bacc)
            else:
                out_lnlb[g, ie, ib] = rmax
            acc += bacc * pi[ib]
            if rmax + ln_pi[ib] > emax:
                emax = rmax + ln_pi[ib]
        if emax > best - _UNDERFLOW:
            out_lnle[g, ie] = best + math.log(acc)
        else:
            out_lnle[g, ie] = emax
    for a in range(n_grp):
        for ir in range(n_r):
            if rsum[a, ir] > 0.0:
                out_lnlr[g, a, ir] = best + math.log(rsum[a, ir])
            else:
                out_lnlr[g, a, ir] = -np.inf
        out_lnlr[g, a, n_r] = buf[star]


@njit(parallel=True, cache=True, fastmath={"contract", "arcp", "afn"})
def _laplace_grid_tab_nb(
    prod, members, mix_a, mix_b, mix_f, n_gal, n_e, n_r, n_sub, s_m, mxx, mxy, myy, sigma,
    x0, y0, b2, max_step,
    node_w, w_star, ln_pi, e_w, e_grp, amp_pow, amp_lns, amp_lo, amp_hi, cubic, pt0, ptab,
    out_lnle, out_lnlb, out_lnlr, out_best, out_h, out_x, out_y,
):  # fmt: skip
    """Fill per-galaxy ``ln L(e)`` (summed over r), ``ln L(r)`` and the best model.

    Two passes per galaxy: the first evaluates ``ln L(e, r)`` of every model into a
    buffer and finds the peak ``M``, a tile of ``_TILE`` columns at a time: each stage of
    :func:`_laplace_lnl` (the reference, one model at a time) runs over the tile as a
    loop of independent iterations (:func:`_position_tile`, :func:`_cubic_tile`,
    :func:`_amplitude_tile`, :func:`_fisher_tile`), which LLVM vectorises: 47 ns per model
    against 115 for the one long chain of divisions and logs per model; the second takes one
    ``exp(ln L - M)`` per model and accumulates both the sum over r (for ``L(e)``) and
    the ``e_w``-weighted sum over e (for ``L(r)``).
    Where a whole e cell lies more than 700 e-folds under the peak (bright galaxies far
    from their ellipticity) its sum underflows and ``ln L(e)`` is replaced by its
    largest weighted term: exact to within ``ln n_r`` at a point whose posterior weight
    is ``exp(-700)``.

    Parameters
    ----------
    prod : (n_chi, 6 * n_gal or 10 * n_gal, n_cols) array
        The matrix products. Rows ``q * n_gal + g`` hold, for ``q = 0..5``: ``h``,
        ``dh/dx``, ``dh/dy``, ``d2h/dx2``, ``d2h/dxdy``, ``d2h/dy2`` at the re-centred
        origin, and with ``cubic`` for ``q = 6..9`` the third derivatives ``xxx, xxy,
        xyy, yyy``. With ``n_chi = 1`` column ``c`` is model ``members[c, 0]``; with
        ``n_chi = 4`` the products are folded by the square's symmetries
        (:func:`pylensfit.likelihood._folded_bank`) and model ``members[c, h]`` (``h``
        = 1, s1, s2, s1 s2) has ``sum_chi chi(h) prod[chi, :, c]``.
    members : (n_cols, 1 or 4) int array
        The models of each column (-1: none).
    mix_a, mix_b, mix_f : (n_cols - n_base,) arrays
        Columns ``c < n_base = n_cols - mix_a.size`` are ``prod``'s columns ``c``; the
        others are not in ``prod``: their products are ``(1 - f) prod[.., a] + f
        prod[.., b]`` with ``a = mix_a[c - n_base]`` etc. (the bulge+disc fractions
        between the pure disc and the pure bulge; empty: none). ``prod``'s columns from
        ``n_base`` on are read only as such ``a`` or ``b`` (a pure fraction's size that
        the size prior leaves out where the mixed fraction's is in).
    n_sub : int
        The r axis of an e cell is ``n_r // n_sub`` runs of ``n_sub`` increasing radii
        (one per bulge fraction); the sum over r is corrected run by run
        (:func:`_narrow_peak_factor`, applied to ``ln(w_j L_j)``: the trapezoid rule in
        the grid index; to ``ln L_j`` at a prior's edge, ``_PRIOR_KINK``).
    s_m, mxx, mxy, myy : (n_models,) arrays
        ``sum m^2`` and the Hessian of the model autocorrelation per model.
    sigma, x0, y0 : (n_gal,) arrays
        Noise per pixel and catalogue position relative to the re-centred origin.
    node_w, w_star : (n_r,) array and float
        Weight of each size of an e cell in the sum over r and of the point source:
        the quadrature weight of the size grid (:func:`pylensfit.models.radius_weights`)
        times the size prior. For the flat prior of the paper, uniform in half-light
        radius ``h`` for every bulge fraction, a run's weights carry the Jacobian ``dh /
        dr`` of its fraction (relative to the first run's); for an estimated prior
        (:class:`pylensfit.prior.SizePrior`) they are the prior mass of each node.
        Sizes of weight 0 are left out: their models need no column (``members``), and
        a run's narrow-peak factor stops at them as at the run's ends.
    ln_pi : (n_r // n_sub,) array
        Log prior weight of each bulge fraction (summing to 1): ``L(e) = sum_k pi_k
        L_k(e) + w_star L_star``, where ``L_k(e)`` is the weighted sum over the sizes of
        run ``k`` and the point source, common to all fractions, is counted once.
    amp_pow : float
        The amplitude prior (:func:`_laplace_lnl`): uniform if :data:`AMP_UNIFORM`
        (``-inf``), else the power of a power law in the model's S/N.
    amp_lns : float
        Coefficient of ``0.5 ln S`` added to a power-law amplitude prior: 0 for a power
        law in the model's S/N, ``amp_pow - 1`` for one in the flux.
    amp_lo, amp_hi : float
        Bounds on the flux of a power-law amplitude prior (0 and inf: none).
    pt0, ptab : float and (4, n) array
        The unbounded power law's table, :func:`amplitude_table` (``laplace_grid``
        computes it itself), for the models well inside the flux bounds.
    e_w : (n_e,) array
        Weights of the e cells (summing to 1) in ``L(r) = sum_e e_w L(e, r)``: an
        ellipticity prior's mass per cell.
    e_grp : (n_e,) int array
        Group of each e cell (``0 .. n_grp - 1``, ``n_grp = out_lnlr.shape[1]``): the sum
        over e of ``L(r)`` is kept per group (all zeros: one sum).
    out_lnlr : (n_gal, n_grp, n_r + 1) array
        ``ln L(r)`` per group of e cells; the point source's ``ln L`` in the last column
        of every group.
    out_lnlb : (n_gal, n_e, n_r // n_sub) array
        ``ln L_k(e)`` of each run (bulge fraction) alone, without the point source.
    """
    n_mod = n_e * n_r + 1
    max_step2 = max_step * max_step
    sq_m = np.sqrt(s_m)
    ln_m = np.log(s_m)
    ln_w = np.log(node_w)
    pi = np.exp(ln_pi)
    n_cols = members.shape[0]
    n_base = n_cols - mix_a.size  # prod's further columns only feed mixed ones
    n_memb = members.shape[1]
    n_q = 10 if cubic else 6
    n_tiles = -(-n_cols // _TILE)
    mix_run, cj, cm = _tile_tables(members, mix_a, mix_b, mix_f, s_m, sq_m, mxx, mxy, myy, ln_m)
    for g in prange(n_gal):
        sig = sigma[g]
        gx0 = x0[g]
        gy0 = y0[g]
        buf = np.empty(n_mod)
        best = -np.inf
        jb = 0
        V = np.zeros((n_memb, n_q, _TILE))
        W = np.empty((n_memb, _NW, _TILE))
        for it in range(n_tiles):
            t0 = it * _TILE
            nt = min(_TILE, n_cols - t0)
            _read_tile(prod, g, n_gal, t0, nt, n_q, n_base, mix_a, mix_b, mix_f, mix_run, V)
            for hm in range(n_memb):
                Vh = V[hm]
                Wh = W[hm]
                cmh = cm[it, hm]
                _position_tile(Vh, cmh, sig, max_step2, Wh)
                if cubic:
                    _cubic_tile(Vh, max_step2, Wh)
                _amplitude_tile(cmh, amp_pow, amp_lns, amp_lo, amp_hi, pt0, ptab, Wh)
                _fisher_tile(gx0, gy0, b2, Wh)
            for k in range(nt):
                for hm in range(n_memb):
                    j = cj[it, hm, k]
                    if j < 0:
                        continue
                    l = W[hm, _VAL, k] - 0.5 * math.log(W[hm, _DETM, k]) - 0.5 * W[hm, _QUAD, k]
                    buf[j] = l
                    if l > best:
                        best = l
                        jb = j
                        out_h[g] = W[hm, _HS, k]
                        out_x[g] = W[hm, _X, k]
                        out_y[g] = W[hm, _Y, k]
        out_best[g] = jb
        _collapse_models(g, buf, best, w_star, n_e, n_r, n_sub, e_grp, e_w, node_w, ln_w,
                         ln_pi, pi, out_lnle, out_lnlb, out_lnlr)


laplace_grid_tab = _one_launch_at_a_time(_laplace_grid_tab_nb)


@njit(cache=True, fastmath={"contract", "arcp", "afn"}, inline="always")
def _profile_value(rr, model_code, fb, bsr, b_dev, norm_dev, trunc, inv_n):
    """Surface brightness of a unit-flux round profile of unit scale at radius ``rr``.

    ``model_code``: 0 exponential (scale length), 1 de Vaucouleurs (half-light radius,
    truncated at ``trunc``), 2 bulge + disc (disc scale length; bulge of fraction
    ``fb`` and half-light radius ``bsr``), 3 one Sersic component of half-light radius
    ``bsr``, ``exp(-b_dev x^inv_n) / norm_dev`` (``x`` in half-light radii) cut at
    ``trunc`` half-light radii.
    """
    if model_code == 3:
        x = rr / bsr
        if x <= trunc:
            return math.exp(-b_dev * x**inv_n) / (norm_dev * bsr * bsr)
        return 0.0
    v = 0.0
    if model_code != 1 and fb < 1.0:
        v += (1.0 - fb) * math.exp(-rr) / (2.0 * math.pi)
    if model_code == 1 or (model_code == 2 and fb > 0.0):
        s = 1.0 if model_code == 1 else bsr
        w = 1.0 if model_code == 1 else fb
        x = rr / s
        if x <= trunc:
            v += w * math.exp(-b_dev * x**0.25) / (norm_dev * s * s)
    return v


@njit(cache=True, inline="always")
def _stamp_share(a, i, shared):
    """The share of copy ``a`` (stamps away) that pixel line ``i`` of the stamp holds.

    The central copy is the stamp's own (1), except on an even stamp's first line, whose
    periodic image at ``+n/2`` (copy 1) it shares half and half; other copies wrap in (0).
    """
    if a == 0:
        return 0.5 if shared and i == 0 else 1.0
    if a == 1 and shared and i == 0:
        return 0.5
    return 0.0


@njit(parallel=True, cache=True)
def _wrapped_wings_nb(e1s, e2s, radii, fracs, model_code, bsr, b_dev, norm_dev, trunc, inv_n,
                      n, max_copies, out):  # fmt: skip
    """The wings that a periodic model wraps into an ``n x n`` stamp.

    A model evaluated on the stamp's discrete frequencies is the periodic sum of its
    copies ``m(x + j n)``; a stamp cut from the sky holds only ``m(x)`` (docs: method,
    eq-fourier-model, ``Config.truncate_models``). For each ellipticity
    ``(e1s[i], e2s[i])``, bulge fraction ``fracs[b]`` and size ``radii[j]`` (column
    ``b * len(radii) + j``), ``out[i, col]`` receives the sum of the copies ``j != 0``
    on the stamp's pixels (offsets ``-n/2 ... n/2 - 1`` from the centre, ``[iy, ix]``),
    with the two pixel lines at ``+-n/2`` (one periodic line) shared half and half,
    which keeps the square's symmetries. Pixel-centre values: the wings are smooth on
    the pixel scale. Columns without wings beyond the stamp stay zero.
    """
    n_e = e1s.size
    n_r = radii.size
    n_b = fracs.size
    h = n // 2
    shared = n % 2 == 0  # an even stamp's first line is at -n/2, its copy at +n/2
    for t in prange(n_e * n_b * n_r):
        i = t // (n_b * n_r)
        col = t % (n_b * n_r)
        fb = fracs[col // n_r]
        r = radii[col % n_r]
        e1 = e1s[i]
        e2 = e2s[i]
        ee = math.sqrt(e1 * e1 + e2 * e2)
        inv = 1.0 / math.sqrt(1.0 - ee * ee)
        stretch = math.sqrt((1.0 + ee) / (1.0 - ee))
        # the model's extent: 25 scale lengths of the disc (a fraction 4e-10 of its flux
        # beyond), the bulge's truncation radius
        ext = 0.0
        if model_code == 3:
            ext = trunc * bsr
        elif model_code != 1 and fb < 1.0:
            ext = 25.0
        if model_code == 1 or (model_code == 2 and fb > 0.0):
            s = 1.0 if model_code == 1 else bsr
            ext = max(ext, trunc * s)
        ext *= r * stretch
        if ext <= h:
            continue
        kmax = min(int(math.ceil(ext / n + 0.5)), max_copies)
        for iy in range(n):
            py = iy - h
            for ix in range(n):
                px = ix - h
                # the profile is point-symmetric and, off the shared lines, so is the
                # set of copies kept: the pixel at -p has the value of p
                my = 2 * h - iy
                mx = 2 * h - ix
                off_shared = not shared or (ix > 0 and iy > 0)  # then -p is in the stamp
                if off_shared and (my < iy or (my == iy and mx < ix)):
                    out[i, col, iy, ix] = out[i, col, my, mx]
                    continue
                acc = 0.0
                for a in range(-kmax, kmax + 1):
                    x = px + a * n
                    inx = _stamp_share(a, ix, shared)
                    if abs(x) > ext + 1.0:
                        continue
                    for b in range(-kmax, kmax + 1):
                        y = py + b * n
                        iny = _stamp_share(b, iy, shared)
                        keep = 1.0 - inx * iny
                        if keep == 0.0 or abs(y) > ext + 1.0:
                            continue
                        ux = ((1.0 - e1) * x - e2 * y) * inv
                        uy = (-e2 * x + (1.0 + e1) * y) * inv
                        rr = math.sqrt(ux * ux + uy * uy) / r
                        acc += keep * _profile_value(rr, model_code, fb, bsr, b_dev,
                                                     norm_dev, trunc, inv_n) / (r * r)  # fmt: skip
                out[i, col, iy, ix] = acc


wrapped_wings = _one_launch_at_a_time(_wrapped_wings_nb)
