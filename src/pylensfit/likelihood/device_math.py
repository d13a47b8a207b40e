"""The likelihood kernel's arithmetic in ``jax.numpy``, for the device path
(:mod:`~pylensfit.likelihood.device`): the same terms as the numba kernels, written over
whole arrays of (member, galaxy, column) instead of a tile at a time.

Each function mirrors one numba kernel: :func:`position` is
:func:`~pylensfit.likelihood.laplace_nb.position_tile`, :func:`cubic` is
:func:`~pylensfit.likelihood.laplace_nb.cubic_tile` (applied where a galaxy's flag is
set), :func:`amplitude` is
:func:`~pylensfit.likelihood.amplitude_nb.amplitude_integral` (evaluated directly, where
the kernel reads tables of it that are within 2e-8 of it), :func:`position_prior` is
``_position_prior`` and :func:`collapse` is
:func:`~pylensfit.likelihood.radius_nb.collapse_models`. They run in float64 (the
products in the configuration's ``dtype``), as the kernels do. ``jax`` is an optional
dependency (``pip install pylensfit[gpu]``): without it this module imports, and its
functions are not called.
"""

from __future__ import annotations

import math

from .amplitude_nb import AMP_FLOOR, AMP_MIN_CURV
from .radius_nb import PRIOR_KINK, UNDERFLOW

try:  # optional dependency: pip install pylensfit[gpu] (the device path only)
    import jax.numpy as jnp
    from jax.scipy.special import log_ndtr
except ImportError:  # the CPU path needs none of this module
    jnp = log_ndtr = None

_LN2PI = math.log(2.0 * math.pi)


def amplitude_terms(t):
    """``0.5 t^2 + ln Phi(t)`` and ``t + phi(t) / Phi(t)`` (the uniform prior's
    amplitude integral and its ``h`` derivative times ``sigma sqrt S``)."""
    lp = log_ndtr(t)
    return 0.5 * t * t + lp, t + jnp.exp(-0.5 * t * t - 0.5 * _LN2PI - lp)


def bounded_mass(a, b):
    """``ln(Phi(a) - Phi(b))`` and its ``a`` derivative for ``a > b`` (``b`` may be
    -inf), written with ``Phi(-b) - Phi(-a)`` where ``b > 0`` as the kernel does."""
    va, da = amplitude_terms(a)
    lpa = va - 0.5 * a * a
    la = da - a
    # both near 1 (b > 0): the upper tails
    vq, dq = amplitude_terms(-b)
    lp = vq - 0.5 * b * b
    lam_b = dq + b
    vq2, dq2 = amplitude_terms(-a)
    rho = jnp.exp(vq2 - 0.5 * a * a - lp)
    lam_a = dq2 + a
    up = (lp + jnp.log1p(-rho), (lam_a * rho - lam_b) / (1.0 - rho))
    # else: Phi(b) / Phi(a); phi(b) / Phi(a) directly, which is 0 at b = -inf
    r = jnp.exp(log_ndtr(b) - lpa)
    pb = jnp.exp(-0.5 * b * b - 0.5 * _LN2PI - lpa)
    low = (lpa + jnp.log1p(-r), (la - pb) / (1.0 - r))
    inf = jnp.isneginf(b)
    pos = b > 0.0
    return (jnp.where(inf, lpa, jnp.where(pos, up[0], low[0])),
            jnp.where(inf, la, jnp.where(pos, up[1], low[1])))  # fmt: skip


def amplitude(t, s, lns, iss, amp):
    """ln of the amplitude integral and the amplitude's posterior mean in S/N units, of
    :func:`~pylensfit.likelihood.amplitude_nb.amplitude_integral`; ``amp`` is ``(power,
    lns coefficient, flux lo, flux hi)``, power ``-inf`` for the uniform prior."""
    amp_pow, amp_lns, amp_lo, amp_hi = amp
    if amp_pow == -math.inf:
        val, dl = amplitude_terms(t)
        return val - 0.5 * lns, dl
    beta = amp_pow
    lo = jnp.maximum(amp_lo * s * iss, AMP_FLOOR)
    hi = amp_hi * s * iss
    disc = t * t - 4.0 * beta
    g0 = -beta * jnp.log(lo) - 0.5 * (lo - t) * (lo - t)
    ustar = 0.5 * (t + jnp.sqrt(jnp.maximum(disc, 0.0)))
    u = jnp.minimum(ustar, hi)
    gu = -beta * jnp.log(u) - 0.5 * (u - t) * (u - t)
    inner = (disc > 0.0) & (ustar > lo) & (gu >= g0)
    u0 = jnp.where(inner, u, lo)
    g0 = jnp.where(inner, gu, g0)
    g1 = t - u0 - beta / u0
    c = jnp.maximum(1.0 - beta / (u0 * u0), AMP_MIN_CURV)
    mu = u0 + g1 / c
    rc = jnp.sqrt(c)
    if amp_hi == math.inf:  # no upper bound (known when compiled): ln Phi(a) alone
        va, da = amplitude_terms((mu - lo) * rc)
        a = (mu - lo) * rc
        lm, dm = va - 0.5 * a * a, da - a
    else:
        lm, dm = bounded_mass((mu - lo) * rc, (mu - hi) * rc)
    val = 0.5 * t * t + g0 + 0.5 * g1 * g1 / c - 0.5 * jnp.log(c) + lm + 0.5 * amp_lns * lns
    return val, mu + dm / rc


def position(V, cm, sig, max_step2):
    """The peak ``(x, y)``, ``h*``, the Hessian used ``(hxx, hxy, hyy)`` and whether it
    is the data's, of :func:`~pylensfit.likelihood.laplace_nb.position_tile`. ``V``:
    ``(q, ...)`` the products ``h, dh/dx, ...``; ``cm``: ``(6, ...)`` ``S, sqrt S, mxx,
    mxy, myy, ln S``; ``sig`` the noise, broadcast against them."""
    h0, gx, gy, hxx, hxy, hyy = (V[q].astype(jnp.float64) for q in range(6))
    ss = sig * cm[1]
    det = hxx * hyy - hxy * hxy
    idet = 1.0 / det
    x1 = (hxy * gy - hyy * gx) * idet
    y1 = (hxy * gx - hxx * gy) * idet
    far = x1 * x1 + y1 * y1 > max_step2
    ok = (hxx < 0.0) & (det > 0.0) & ~far
    scale = jnp.where(ss > h0, ss, h0) / cm[0]
    exx, exy, eyy = scale * cm[2], scale * cm[3], scale * cm[4]
    eidet = 1.0 / (exx * eyy - exy * exy)
    x2 = (exy * gy - eyy * gx) * eidet
    y2 = (exy * gx - exx * gy) * eidet
    rr = x2 * x2 + y2 * y2
    f = jnp.where(rr > max_step2, jnp.sqrt(max_step2 / rr), 1.0)
    x = jnp.where(ok, x1, x2 * f)
    y = jnp.where(ok, y1, y2 * f)
    hxx = jnp.where(ok, hxx, exx)
    hxy = jnp.where(ok, hxy, exy)
    hyy = jnp.where(ok, hyy, eyy)
    hs = h0 + gx * x + gy * y + 0.5 * (hxx * x * x + 2.0 * hxy * x * y + hyy * y * y)
    return x, y, hs, (hxx, hxy, hyy), ok


def _cubic_hessian(v, x, y):
    """The Hessian of the third-order expansion at ``(x, y)``; ``v`` the ten rows."""
    return (v[3] + v[6] * x + v[7] * y, v[4] + v[7] * x + v[8] * y,
            v[5] + v[8] * x + v[9] * y)  # fmt: skip


def cubic(V, pos, go, max_step2):
    """:func:`~pylensfit.likelihood.laplace_nb.cubic_tile` where ``go`` (the data
    Hessian used, and the galaxy fitted with the third-order expansion): two Newton
    steps on the cubic expansion, then ``h*`` and the Hessian at the peak. ``pos``:
    :func:`position`'s ``(x, y, h*, hessian)``."""
    v = [V[q].astype(jnp.float64) for q in range(10)]
    h0, gx, gy, hxx, hxy, hyy, txxx, txxy, txyy, tyyy = v
    x, y, hs, hess = pos
    ok = go
    for _ in range(2):
        ax, axy, ay = _cubic_hessian(v, x, y)
        d3 = ax * ay - axy * axy
        go = go & (ax < 0.0) & (d3 > 0.0)
        rx = gx + hxx * x + hxy * y + 0.5 * (txxx * x * x + 2 * txxy * x * y + txyy * y * y)
        ry = gy + hxy * x + hyy * y + 0.5 * (txxy * x * x + 2 * txyy * x * y + tyyy * y * y)
        nx = x + (axy * ry - ay * rx) / d3
        ny = y + (axy * rx - ax * ry) / d3
        go = go & ~(nx * nx + ny * ny > max_step2)
        x = jnp.where(go, nx, x)
        y = jnp.where(go, ny, y)
    ax, axy, ay = _cubic_hessian(v, x, y)
    fin = ok & (ax < 0.0) & (ax * ay - axy * axy > 0.0)
    hc = (h0 + gx * x + gy * y + 0.5 * (hxx * x * x + 2.0 * hxy * x * y + hyy * y * y)
          + (txxx * x * x * x + 3 * txxy * x * x * y + 3 * txyy * x * y * y
             + tyyy * y * y * y) / 6.0)  # fmt: skip
    hess = tuple(jnp.where(fin, a, b) for a, b in zip((ax, axy, ay), hess, strict=True))
    return x, y, jnp.where(fin, hc, hs), hess


def position_prior(dl, hess, dx, dy, b2):
    """``det M`` and the quadratic form of the catalogue offset ``(dx, dy)``, of
    ``_position_prior`` (:mod:`~pylensfit.likelihood.laplace_nb`)."""
    f11, f12, f22 = dl * hess[0], dl * hess[1], dl * hess[2]
    detf = f11 * f22 - f12 * f12
    m11 = 1.0 + b2 * f11
    m22 = 1.0 + b2 * f22
    m12 = b2 * f12
    detm = m11 * m22 - m12 * m12
    quad = ((f11 + b2 * detf) * dx * dx + 2.0 * f12 * dx * dy
            + (f22 + b2 * detf) * dy * dy) / detm  # fmt: skip
    return detm, quad


def _narrow_peak_factor(lm, l0, lp):
    """:func:`~pylensfit.likelihood.radius_nb._narrow_peak_factor` (see there)."""
    a = lm - 2.0 * l0 + lp
    s2 = -1.0 / a
    d = 0.5 * (lm - lp) / a
    j = jnp.arange(-7.0, 8.0)
    gsum = jnp.exp(-0.5 * (j - d[..., None]) ** 2 / s2[..., None]).sum(axis=-1)
    f = jnp.where(gsum > 1e-300, jnp.sqrt(2.0 * math.pi * s2) / gsum, 1.0)
    return jnp.where(a >= -1.0, 1.0, f)


def _peak_factors(lw, lr, ln_w, node_w, n_sub):
    """The narrow-peak factor of every run, at its largest ``ln(w L)`` ``km`` (``lw``,
    ``lr``: ``ln(w L)`` and ``ln L`` of shape ``(..., n_b, n_sub)``), as
    :func:`~pylensfit.likelihood.radius_nb.collapse_models` applies it; and ``km``."""
    km = jnp.argmax(lw, axis=-1)
    n_b = lw.shape[-2]
    ir = jnp.arange(n_b) * n_sub + km  # (..., n_b)
    live = node_w > 0.0
    fine = (km > 0) & (km < n_sub - 1)
    fine = fine & live[jnp.clip(ir - 1, 0, None)] & live[jnp.clip(ir + 1, None, live.size - 1)]

    def at(a, d):
        return jnp.take_along_axis(a, jnp.clip(km + d, 0, n_sub - 1)[..., None], axis=-1)[..., 0]

    lwm, lw0, lwp = at(lw, -1), at(lw, 0), at(lw, 1)
    lm, l0, lp = at(lr, -1), at(lr, 0), at(lr, 1)
    kink = (ln_w[jnp.clip(ir - 1, 0, None)] - 2.0 * ln_w[ir]
            + ln_w[jnp.clip(ir + 1, None, ln_w.size - 1)])  # fmt: skip
    f = jnp.where(jnp.abs(kink) <= PRIOR_KINK, _narrow_peak_factor(lwm, lw0, lwp),
                  jnp.where((l0 >= lm) & (l0 >= lp), _narrow_peak_factor(lm, l0, lp), 1.0))
    return jnp.where(fine, f, 1.0)


def collapse(buf, best, sums):
    """:func:`~pylensfit.likelihood.radius_nb.collapse_models` for a block: from ``ln L``
    of every model ``buf`` ``(g, n_models)`` (point source last) and each galaxy's peak
    ``best``, ``ln L(e)``, ``ln L_k(e)`` per run and ``ln L(r)`` per group of e cells.
    ``sums``: ``(node_w, ln_w, w_star, ln_pi, e_weights, n_sub)`` with ``e_weights``
    ``(n_e, n_grp)`` the cells' weights in their groups."""
    node_w, ln_w, w_star, ln_pi, e_wg, n_sub = sums
    n_g = buf.shape[0]
    n_r = node_w.size
    n_e = e_wg.shape[0]
    live = node_w > 0.0
    l_star = buf[:, -1]
    lr = buf[:, :-1].reshape(n_g, n_e, n_r)
    b = best[:, None, None]
    ex = jnp.where(live, jnp.exp(lr - b), 0.0)
    lw = jnp.where(live, lr + ln_w, -jnp.inf)
    shape = (n_g, n_e, n_r // n_sub, n_sub)
    bacc = (ex * node_w).reshape(shape).sum(axis=-1)
    rmax = lw.reshape(shape).max(axis=-1)
    bacc = bacc * _peak_factors(lw.reshape(shape), lr.reshape(shape), ln_w, node_w, n_sub)
    lnlb = jnp.where((rmax > b - UNDERFLOW) & (bacc > 0.0), b + jnp.log(bacc), rmax)
    lw_star = l_star + math.log(w_star) if w_star > 0 else jnp.full_like(l_star, -jnp.inf)
    acc = jnp.exp(lw_star - best)[:, None] + (bacc * jnp.exp(ln_pi)).sum(axis=-1)
    emax = jnp.maximum(lw_star[:, None], (rmax + ln_pi).max(axis=-1))
    lnle = jnp.where(emax > b[..., 0] - UNDERFLOW, b[..., 0] + jnp.log(acc), emax)
    rsum = jnp.einsum("ger,ek->gkr", ex, e_wg, precision="highest")
    lnlr = jnp.where(rsum > 0.0, b + jnp.log(jnp.where(rsum > 0.0, rsum, 1.0)), -jnp.inf)
    lnlr = jnp.concatenate([lnlr, jnp.broadcast_to(l_star[:, None, None],
                                                   (n_g, e_wg.shape[1], 1))], axis=2)
    return lnle, lnlb, lnlr


def newton_peak(D, R, kw, X, Y, n_steps):
    """:func:`pylensfit._util.newton_peak` (see there) for a block: Newton steps to the
    peak of the cross-correlation of the transforms ``D`` ``(g, n, n // 2 + 1)`` with
    ``R``; ``kw`` is ``(kx, ky, w / n^2)`` of the ``rfft2`` frequencies."""
    kx1, ky1, w = kw
    base = D * jnp.conj(R)[None] * w[None]
    for _ in range(n_steps):
        ex = jnp.exp(1j * kx1[None, :] * X[:, None])
        ey = jnp.exp(1j * ky1[None, :] * Y[:, None])
        Dp = base * ey[:, :, None] * ex[:, None, :]
        re, im = Dp.real, Dp.imag
        gx = -(im * kx1).sum(axis=(1, 2))
        hxx = -(re * (kx1 * kx1)).sum(axis=(1, 2))
        gy = -(im.sum(axis=2) * ky1).sum(axis=1)
        hyy = -(re.sum(axis=2) * (ky1 * ky1)).sum(axis=1)
        hxy = -((re * kx1).sum(axis=2) * ky1).sum(axis=1)
        det = hxx * hyy - hxy * hxy
        good = (hxx < 0) & (det > 0)
        sx = jnp.where(good, (hxy * gy - hyy * gx) / det, 0.0)
        sy = jnp.where(good, (hxy * gx - hxx * gy) / det, 0.0)
        ok = good & (jnp.hypot(sx, sy) < 1.0)
        X = jnp.where(ok, X + sx, X)
        Y = jnp.where(ok, Y + sy, Y)
    return X, Y


def centre(pix, x0, y0, c, rad2):
    """:func:`pylensfit.likelihood.windows.centre` for a block of cleaned windows
    ``pix`` ``(g, n, n)``, their transforms included: returns the transforms
    (phase-referenced to the centre pixel), the centres and the windows with no positive
    peak. ``c``: the phase ramp to the centre ``phase``, the round model ``ref``, the
    offsets ``off`` of the pixels from the centre and the frequencies ``kx1, ky1, w``
    (:func:`newton_peak`); ``rad2`` the square of the search radius about ``(x0, y0)``."""
    n = pix.shape[-1]
    g = jnp.arange(pix.shape[0])
    D = jnp.fft.rfft2(pix) * c["phase"][None]
    cc = jnp.fft.irfft2(D * jnp.conj(c["ref"])[None], s=(n, n))
    off = c["off"]
    d2 = ((off[None, None, :] - x0[:, None, None]) ** 2
          + (off[None, :, None] - y0[:, None, None]) ** 2)  # fmt: skip
    flat = jnp.where(d2 <= rad2, cc, -jnp.inf).reshape(pix.shape[0], -1).argmax(axis=1)
    iy, ix = flat // n, flat % n
    v0 = cc[g, iy, ix]

    def parabola(vm, vp):
        den = vm - 2 * v0 + vp
        return jnp.clip(jnp.where(den < 0, 0.5 * (vm - vp) / den, 0.0), -0.5, 0.5)

    xc = off[ix] + parabola(cc[g, iy, (ix - 1) % n], cc[g, iy, (ix + 1) % n])
    yc = off[iy] + parabola(cc[g, (iy - 1) % n, ix], cc[g, (iy + 1) % n, ix])
    xc, yc = newton_peak(D, c["ref"], (c["kx1"], c["ky1"], c["w"]), xc, yc, 3)
    no_peak = ~(v0 > 0)
    return D, jnp.where(no_peak, x0, xc), jnp.where(no_peak, y0, yc), no_peak
