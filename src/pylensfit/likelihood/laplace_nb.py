"""numba kernels of the Laplace terms in position: the Newton step to the peak of the
cross-correlation, the third-order refinement, the position prior.

:func:`laplace_lnl` is the reference, one model at a time, of the terms that the kernel
(:func:`pylensfit.likelihood.grid_nb.laplace_grid`) evaluates a tile of models at a
time (:func:`position_tile`, :func:`cubic_tile`,
:func:`~pylensfit.likelihood.amplitude_nb.amplitude_tile`, :func:`fisher_tile`);
``tests/test_likelihood.py`` holds the two together (docs: method, eq-position).
"""

from __future__ import annotations

import math

from numba import njit

from .amplitude_nb import amplitude_integral
from .tile_nb import W_AXX, W_AXY, W_AYY, W_DETM, W_DL, W_HS, W_ISS, W_OK, W_QUAD, W_X, W_Y


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"}, inline="always")
def _cubic_hessian(hxx, hxy, hyy, txxx, txxy, txyy, tyyy, x, y):
    """The Hessian of ``h``'s third-order expansion at ``(x, y)``."""
    return (hxx + txxx * x + txxy * y, hxy + txxy * x + txyy * y,
            hyy + txyy * x + tyyy * y)  # fmt: skip



@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"}, inline="always")
def _cubic_value(v, t3, x, y):
    """``h`` at ``(x, y)`` by its third-order expansion about the origin: ``v`` is ``(h,
    dh/dx, dh/dy, d2h/dx2, d2h/dxdy, d2h/dy2)`` there, ``t3`` the third derivatives
    ``(xxx, xxy, xyy, yyy)``."""
    h0, gx, gy, hxx, hxy, hyy = v
    txxx, txxy, txyy, tyyy = t3
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
def laplace_lnl(v, t3, cubic, model, gal, b2, max_step2, amp):
    """ln L of one model, marginalised over amplitude (> 0) and position (Laplace).

    ``v`` holds ``h`` and its first and second derivatives at the origin, ``(h, dh/dx,
    dh/dy, d2h/dx2, d2h/dxdy, d2h/dy2)``, and ``t3`` the third ``(xxx, xxy, xyy, yyy)``.
    ``model`` is ``(S, sqrt S, ln S, mxx, mxy, myy)``: ``S = sum m^2`` and the Hessian
    of the model's autocorrelation; ``gal`` the noise and the catalogue position
    ``(sigma, x0, y0)``; ``b2`` the position prior's variance; ``max_step2`` the square
    of the longest Newton step. ``amp`` is the amplitude prior ``(amp_pow, amp_lns,
    amp_lo, amp_hi)``: with ``amp_pow = -inf`` it is uniform (the paper's): ``0.5 t^2 +
    ln Phi(t) - 0.5 ln S`` for the model's S/N ``t = h / (sigma sqrt S)``. With a finite
    ``amp_pow = beta`` it is a power law in the model's S/N, ``p(A | model) ~ t^-beta
    dt/dA``, between bounds ``amp_lo``, ``amp_hi`` on the flux
    (:func:`~pylensfit.likelihood.amplitude_nb.amplitude_integral`; the ``sqrt S`` of
    the Gaussian's width in ``A`` cancels that of ``dt/dA``), plus ``amp_lns * 0.5 ln
    S``: ``amp_lns = beta - 1`` makes it a power law ``A^-beta`` in the amplitude (the
    flux) itself, the same for every model. With ``cubic``, the third derivatives refine
    the peak (two Newton steps on the cubic expansion) and give the Hessian at the peak
    rather than at the origin. Returns ``(ln L, h*, X*, Y*)``. See
    :func:`pylensfit.likelihood.fit_stamps`.
    """
    h0, gx, gy, hxx, hxy, hyy = v
    s, sqs, lns, mxx, mxy, myy = model
    sig, x0, y0 = gal
    ss = sig * sqs
    iss = 1.0 / ss
    x, y, hxx, hxy, hyy, ok = _newton_step(v, (mxx, mxy, myy), ss, s, max_step2)
    hstar = h0 + gx * x + gy * y + 0.5 * (hxx * x * x + 2.0 * hxy * x * y + hyy * y * y)
    if cubic and ok:
        x, y, hstar, hxx, hxy, hyy = _cubic_peak(v, t3, x, y, hstar, max_step2)
    amp_pow, amp_lns, amp_lo, amp_hi = amp
    val, dl = amplitude_integral(hstar * iss, s, lns, iss, amp_pow, amp_lns, amp_lo, amp_hi)
    dl = -dl * iss
    # Fisher matrix of position, F = -(dl/dh) Hess h
    detm, quad = _position_prior(dl, hxx, hxy, hyy, x - x0, y - y0, b2)
    lnl = val - 0.5 * math.log(detm) - 0.5 * quad
    return lnl, hstar, x, y


@njit(cache=True, fastmath={"contract", "arcp", "afn"}, inline="always")
def _newton_step(v, mhess, ss, s, max_step2):
    """:func:`laplace_lnl`'s Newton step from the origin: ``(X*, Y*)``, the Hessian used
    and whether it is the data's. Where the data Hessian is not a maximum, or the step
    is longer than ``sqrt(max_step2)``, the expected Hessian is used instead: that of the
    model's autocorrelation ``mhess`` scaled by ``max(h, ss) / S`` (``ss = sigma sqrt
    S``), the step cut to the longest."""
    h0, gx, gy, hxx, hxy, hyy = v
    mxx, mxy, myy = mhess
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
    return x, y, hxx, hxy, hyy, ok


@njit(cache=True, fastmath={"contract", "arcp", "afn"}, inline="always")
def _cubic_peak(v, t3, x, y, hstar, max_step2):
    """:func:`laplace_lnl`'s third-order refinement from the Newton step's peak ``(x,
    y)`` (``h*`` there), where the data Hessian was used: two Newton steps on the cubic
    expansion, each taken only while its Hessian is a maximum and the step short
    enough; then ``(X*, Y*, h*)`` and the Hessian at the peak, or at ``(x, y)`` ``h*``
    and the data Hessian where the expansion's Hessian there is not a maximum."""
    h0, gx, gy, hxx, hxy, hyy = v
    txxx, txxy, txyy, tyyy = t3
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
        return x, y, _cubic_value(v, t3, x, y), ax, axy, ay
    return x, y, hstar, hxx, hxy, hyy


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def position_tile(V, cm, sig, max_step2, W):
    """The position part of :func:`laplace_lnl` for one member's models of a tile,
    without branches: the peak ``X*`` (one Newton step, or the expected Hessian's where
    the data Hessian is not a maximum or the step is too long), ``h*``, the Hessian and
    the S/N ``t``. ``V`` (q, k): the products; ``cm`` (6, k): ``S, sqrt S, mxx, mxy, myy,
    ln S``; ``W`` (W_ROWS, k): the results."""
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
        W[W_X, k] = x
        W[W_Y, k] = y
        W[W_HS, k] = hstar
        W[W_AXX, k] = hxx
        W[W_AXY, k] = hxy
        W[W_AYY, k] = hyy
        W[W_ISS, k] = iss
        W[W_OK, k] = 1.0 if ok else 0.0


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def cubic_tile(V, max_step2, W):
    """The third-order refinement of :func:`laplace_lnl` for a tile (where the data
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
        ok = W[W_OK, k] > 0.0
        x = W[W_X, k]
        y = W[W_Y, k]
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
        hc = _cubic_value((h0, gx, gy, hxx, hxy, hyy), (txxx, txxy, txyy, tyyy), x, y)
        W[W_X, k] = x
        W[W_Y, k] = y
        W[W_HS, k] = hc if fin else W[W_HS, k]
        W[W_AXX, k] = ax if fin else W[W_AXX, k]
        W[W_AXY, k] = axy if fin else W[W_AXY, k]
        W[W_AYY, k] = ay if fin else W[W_AYY, k]



@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def fisher_tile(x0, y0, b2, W):
    """The position prior part of :func:`laplace_lnl` for a tile: ``det M`` and the
    quadratic form of the catalogue offset."""
    for k in range(W.shape[1]):
        W[W_DETM, k], W[W_QUAD, k] = _position_prior(
            W[W_DL, k], W[W_AXX, k], W[W_AXY, k], W[W_AYY, k], W[W_X, k] - x0, W[W_Y, k] - y0, b2
        )
