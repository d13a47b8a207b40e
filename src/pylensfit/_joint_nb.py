"""The compiled kernel of :mod:`pylensfit.joint`: the Laplace terms of every model.

One pass per galaxy (``prange``) over the models, fused: the Newton step in position,
``H*``, the amplitude integral and the position prior, from the products of the block
(no temporaries of the block's size). The reference is :func:`pylensfit.joint._laplace`'s
formula, written out in its module docstring.
"""

from __future__ import annotations

import math

from numba import njit, prange

__all__ = ["laplace_models"]

_LN_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
_SQRT_HALF = math.sqrt(0.5)
#: below this S/N, ``ln Phi`` and ``phi / Phi`` by the asymptotic series of Mills' ratio
#: (relative error ~ 105 / t^8 < 1e-9); above, by ``erfc`` (no underflow before t = -37)
_T_SERIES = -25.0


@njit(cache=True, inline="always")
def _amplitude(t):
    """``ln Phi(t)`` and ``t + phi(t) / Phi(t)`` (the uniform amplitude prior's terms)."""
    if t > _T_SERIES:
        lp = math.log(0.5 * math.erfc(-t * _SQRT_HALF))
        return lp, t + math.exp(-0.5 * t * t - _LN_SQRT_2PI - lp)
    u = 1.0 / (t * t)
    corr = 1.0 - u + 3.0 * u * u - 15.0 * u * u * u
    lp = -0.5 * t * t - math.log(-t) - _LN_SQRT_2PI + math.log(corr)
    return lp, (-1.0 / t) * (1.0 - 3.0 * u + 15.0 * u * u) / corr


@njit(cache=True, inline="always")
def _peak(A, B, g, j, max2):
    """The Newton step ``X*`` of model ``j`` of galaxy ``g`` and the Hessian used (the
    data's, or the expected one's; ``A``, ``B`` as :func:`laplace_models`')."""
    h0, gx, gy = float(A[0, g, j]), float(A[1, g, j]), float(A[2, g, j])
    hxx, hxy, hyy = float(A[3, g, j]), float(A[4, g, j]), float(A[5, g, j])
    q, mxx, mxy, myy = float(B[0, g, j]), float(B[1, g, j]), float(B[2, g, j]), float(B[3, g, j])
    det = hxx * hyy - hxy * hxy
    ok = hxx < 0.0 and det > 0.0
    x = y = 0.0
    if ok:
        x = (hxy * gy - hyy * gx) / det
        y = (hxy * gx - hxx * gy) / det
        ok = x * x + y * y <= max2
    if not ok:
        scale = max(h0, math.sqrt(q)) / q
        hxx, hxy, hyy = scale * mxx, scale * mxy, scale * myy
        det = hxx * hyy - hxy * hxy
        x = (hxy * gy - hyy * gx) / det
        y = (hxy * gx - hxx * gy) / det
        rr = x * x + y * y
        if rr > max2:
            f = math.sqrt(max2 / rr)
            x *= f
            y *= f
    return x, y, hxx, hxy, hyy


@njit(parallel=True, cache=True, error_model="numpy")
def laplace_models(A, B, x0, y0, b2, max_step, lnl, hs, xs, ys):
    """``ln L(e, r)`` of every model of a block into ``lnl`` (``(m, c)``), and ``H*``,
    ``X*`` (from the origin) into ``hs``, ``xs``, ``ys``.

    ``A`` ``(6, m, c)``: ``H``, its gradient and Hessian at the origin; ``B`` ``(4, m,
    c)``: ``Q`` and the Hessian of the expected ``H`` per unit amplitude; ``x0, y0``
    ``(m,)``: the catalogue position from the origin; ``b2``: the position prior's
    variance; ``max_step``: the longest Newton step (arcsec).
    """
    m, c = A.shape[1], A.shape[2]
    max2 = max_step * max_step
    for g in prange(m):
        for j in range(c):
            h0 = float(A[0, g, j])
            gx = float(A[1, g, j])
            gy = float(A[2, g, j])
            q = float(B[0, g, j])
            if not q > 0.0:  # no usable exposure
                lnl[g, j] = math.nan
                hs[g, j] = xs[g, j] = ys[g, j] = math.nan
                continue
            x, y, hxx, hxy, hyy = _peak(A, B, g, j, max2)
            h = h0 + gx * x + gy * y + 0.5 * (hxx * x * x + 2.0 * hxy * x * y + hyy * y * y)
            sq = math.sqrt(q)
            t = h / sq
            lp, dl = _amplitude(t)
            dl = -dl / sq
            f11, f12, f22 = dl * hxx, dl * hxy, dl * hyy
            detf = f11 * f22 - f12 * f12
            m11, m22, m12 = 1.0 + b2 * f11, 1.0 + b2 * f22, b2 * f12
            detm = m11 * m22 - m12 * m12
            dx, dy = x - x0[g], y - y0[g]
            quad = ((f11 + b2 * detf) * dx * dx + 2.0 * f12 * dx * dy
                    + (f22 + b2 * detf) * dy * dy) / detm  # fmt: skip
            lnl[g, j] = 0.5 * t * t + lp - 0.5 * math.log(q) - 0.5 * math.log(detm) - 0.5 * quad
            hs[g, j] = h
            xs[g, j] = x
            ys[g, j] = y
