"""The compiled kernel of :mod:`pylensfit.joint`: the Laplace terms of every model, on the
likelihood's own tile kernels.

One pass per galaxy (``prange``) over the models, a tile of
:data:`~pylensfit.likelihood.tile_nb.TILE` columns at a time: the Newton step in position
and the expected-Hessian fallback
(:func:`~pylensfit.likelihood.laplace_nb.position_tile`), the amplitude integral
(:func:`~pylensfit.likelihood.amplitude_nb.amplitude_tile`: the uniform prior or the
power law in the flux ``A = H / Q``, its bounds in the common flux unit) and the
position prior
(:func:`~pylensfit.likelihood.laplace_nb.fisher_tile`) of the single-exposure fit, read
with the noise ``sigma = 1`` and the model's ``S`` replaced by the galaxy's ``Q = sum_k
f_k^2 S_k / sigma_k^2`` (the module docstring of :mod:`pylensfit.joint`). The per-model
constants that the single fit reads from its PSF bank are here summed over the exposures
per galaxy. Then the single fit's sum over r
(:func:`~pylensfit.likelihood.radius_nb.collapse_models`): nothing of the block's size
is written back.

numba caches a compiled kernel by its own file: after editing the likelihood's kernels
remove the caches (``find src -name '*.nb[ic]' -delete``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from .likelihood.amplitude_nb import amplitude_tile
from .likelihood.laplace_nb import fisher_tile, position_tile
from .likelihood.radius_nb import collapse_models
from .likelihood.tile_nb import TILE, W_DETM, W_HS, W_QUAD, W_ROWS, W_VAL, W_X, W_Y

__all__ = ["Folds", "Norms", "laplace_grid", "unfold"]


class Folds(NamedTuple):
    """The products of a block's rows with the exposures' folded banks, summed over the
    exposures of each kind (the same folded columns), and where each model lies in them
    (:func:`pylensfit.joint.lattice_symmetries`).

    Kind ``e``'s product of character ``c`` with folded column ``f`` in row ``r``
    (``r = q * m + g`` for galaxy ``g`` and ``q`` = ``H``, its gradient ``x, y``, its
    Hessian ``xx, xy, yy``) is ``P[off[e, c] + r * n_fc[e] + f]``; model ``j``'s
    product is ``sum_c sgn[e, c, j]`` times ``(1 - frac[e, j])`` those of the column
    ``col[e, 0, j]`` plus ``frac[e, j]`` those of ``col[e, 1, j]`` (``sgn`` the
    character ``c`` of its slot in the column; ``frac`` 0 but for the bulge+disc
    fractions between the pure disc and the pure bulge, mixed from their columns).
    """

    P: np.ndarray  # flat float32 (or float64) products
    off: np.ndarray  # (n_kinds, 4) int: where each kind's character starts
    n_fc: np.ndarray  # (n_kinds,) int: folded columns per kind
    n_chi: np.ndarray  # (n_kinds,) int: characters per kind (1, 2 or 4)
    sgn: np.ndarray  # (n_kinds, 4, n_models) float +-1 (0 for c >= n_chi)
    col: np.ndarray  # (n_kinds, 2, n_models) int
    frac: np.ndarray  # (n_kinds, n_models) float


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def _column(P, o, a, nc, sg):
    """``sum_c sg[c] P[o[c] + a]`` over the ``nc`` characters."""
    if nc == 4:
        return (sg[0] * P[o[0] + a] + sg[1] * P[o[1] + a] + sg[2] * P[o[2] + a]
                + sg[3] * P[o[3] + a])  # fmt: skip
    if nc == 2:
        return sg[0] * P[o[0] + a] + sg[1] * P[o[1] + a]
    return sg[0] * P[o[0] + a]


class Norms(NamedTuple):
    """The models' norms, per exposure: ``S[k, :, p, j]`` is ``sum m^2`` of model ``j``
    seen in exposure ``k`` through its PSF ``p`` (one for all galaxies, ``p = 0``, or one
    per galaxy) and the Hessian of its autocorrelation at 0 ``(xx, xy, yy)``, per unit
    of ``f_k^2 / sigma_k^2``; ``w2[k, g]`` is that weight of galaxy ``g`` (0 where the
    exposure is not used)."""

    S: np.ndarray  # (K, 4, n_psf, c), arcsec^-2 for the Hessian
    w2: np.ndarray  # (K, m)


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def _read_tile(folds, norms, g, t0, nt, V, cm, uniform):
    """Galaxy ``g``'s products of the models ``t0 .. t0 + nt``, summed over the exposures,
    into ``V`` (``(6, TILE)``) and the models' constants ``(Q, sqrt Q, mxx, mxy, myy, ln
    Q)`` into ``cm`` (``(6, TILE)``; ``ln Q`` 0 under the ``uniform`` amplitude prior,
    whose ``-ln(Q) / 2`` :func:`_store_tile` adds); the rest of the tile a harmless
    model."""
    P, off, n_fc, n_chi, sgn, col, frac = folds
    S, w2 = norms
    p = g % S.shape[2]  # one PSF for all (0) or one per galaxy
    m = w2.shape[1]
    for q in range(6):
        for k in range(TILE):
            V[q, k] = 0.0
    for e in range(off.shape[0]):
        nc = n_chi[e]
        step = m * n_fc[e]  # from one row q to the next
        o0 = g * n_fc[e]
        o = (off[e, 0] + o0, off[e, 1] + o0, off[e, 2] + o0, off[e, 3] + o0)
        for k in range(nt):
            j = t0 + k
            fa, fb, fm = col[e, 0, j], col[e, 1, j], frac[e, j]
            sg = (sgn[e, 0, j], sgn[e, 1, j], sgn[e, 2, j], sgn[e, 3, j])
            if fm == 0.0:
                for q in range(6):
                    V[q, k] += _column(P, o, q * step + fa, nc, sg)
            else:  # a fraction between the pure ends, mixed from their products
                for q in range(6):
                    V[q, k] += ((1.0 - fm) * _column(P, o, q * step + fa, nc, sg)
                                + fm * _column(P, o, q * step + fb, nc, sg))  # fmt: skip
    for r in range(4):
        row = 0 if r == 0 else r + 1  # Q, then the Hessian after sqrt Q
        for k in range(nt):
            acc = 0.0
            for e in range(S.shape[0]):
                acc += w2[e, g] * S[e, r, p, t0 + k]
            cm[row, k] = acc
    for k in range(nt):
        cm[1, k] = math.sqrt(cm[0, k])
        # ln Q: under the uniform prior in _store_tile, with det M's log; a power law's
        # integral has no -ln(Q) / 2 and reads ln Q for its power of the flux
        cm[5, k] = 0.0 if uniform else math.log(cm[0, k])
    for k in range(nt, TILE):
        cm[0, k] = 1.0
        cm[1, k] = 1.0
        cm[2, k] = -1.0
        cm[3, k] = 0.0
        cm[4, k] = -1.0
        cm[5, k] = 0.0


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def _store_tile(W, cm, g, t0, nt, best, buf, hxy, models):
    """The tile's ``ln L`` into ``buf`` at each model's place in the whole grid
    (``models[1]``; NaN where ``Q = 0``: no usable exposure); the most likely model so
    far (its ``ln L`` is ``best``, returned) and its ``H*`` and peak into ``hxy = (best,
    h, x, y)`` at ``g`` (the first model's where none is finite). ``models[0]``: a
    uniform amplitude prior, whose integral's ``-ln(Q) / 2`` is added here."""
    uniform = models[0] > 0.0
    full = models[1]
    for k in range(nt):
        j = t0 + k
        ok = cm[0, k] > 0.0
        # the uniform amplitude integral's -ln(Q) / 2 (cm's ln Q is 0) and det M's in one
        # log; a power law's integral has none
        lnl = (W[W_VAL, k] - 0.5 * math.log(W[W_DETM, k] * (cm[0, k] if uniform else 1.0))
               - 0.5 * W[W_QUAD, k] if ok else math.nan)  # fmt: skip
        buf[full[j]] = lnl
        if j == 0 or lnl > best:
            hxy[0][g] = j
            hxy[1][g] = W[W_HS, k] if ok else math.nan
            hxy[2][g] = W[W_X, k] if ok else math.nan
            hxy[3][g] = W[W_Y, k] if ok else math.nan
            if lnl > best:
                best = lnl
    return best


@njit(parallel=True, cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def laplace_grid(folds, norms, gals, sums, amp, laplace, models, out):
    """``ln L(e)`` summed over r, per run of sizes, and the most likely model's ``H*`` and
    ``X*`` of every galaxy of a block, into ``out``.

    ``folds``: :class:`Folds`, the products of ``H``, its gradient and Hessian at the
    origin, the models in the single fit's order (cell ``ie``'s sizes at ``ie * n_r``,
    the point source last); ``norms``: :class:`Norms`; ``gals``,
    ``sums``, ``laplace`` and ``out``: the likelihood's
    :class:`~pylensfit.likelihood.grid_nb.Galaxies` (``sigma`` 1: the weights are in
    ``A`` and ``norms``; ``x0, y0`` the catalogue position from the origin, arcsec),
    :class:`~pylensfit.likelihood.grid_nb.Sums`,
    :class:`~pylensfit.likelihood.grid_nb.Laplace` (``b2`` arcsec^2, ``max_step``
    arcsec; ``cubic`` is not read: second order) and
    :class:`~pylensfit.likelihood.grid_nb.Outputs`. ``amp``: the amplitude prior, the
    likelihood's :class:`~pylensfit.likelihood.grid_nb.Amplitude` and its table
    (:func:`~pylensfit.likelihood.amplitude_nb.amplitude_table`), ``(power, lns, lo,
    hi, t0, tab)``, the flux bounds in the common flux unit; ``models``: ``(uniform,
    full)``, 1.0 for a uniform amplitude prior (else 0.0) and ``(c,)`` int, the place of
    each of ``folds``' models in the grid of ``sums`` (cell ``ie``'s sizes at ``ie *
    n_r``, the point source last): the models of the sizes that the sum over r leaves
    out (weight 0) need not be among them. The sum over r is the single fit's
    (:func:`~pylensfit.likelihood.radius_nb.collapse_models`); ``out.best`` is the most
    likely model's index in ``folds``.
    """
    sigma, x0, y0 = gals
    node_w, w_star, ln_pi, e_w, e_grp, n_sub = sums
    rsums = (node_w, np.log(node_w), w_star, ln_pi, np.exp(ln_pi), e_w, e_grp, n_sub)
    b2 = laplace[0]
    max2 = laplace[1] * laplace[1]
    m, c = sigma.size, folds.frac.shape[1]
    amp_pow, amp_lns, amp_lo, amp_hi, t0_tab, tab = amp
    uniform = models[0] > 0.0
    n_mod = e_w.size * node_w.size + 1
    hxy = (out.best, out.h, out.x, out.y)
    for g in prange(m):
        V = np.zeros((6, TILE))
        cm = np.empty((6, TILE))
        W = np.empty((W_ROWS, TILE))
        buf = np.empty(n_mod)  # the models left out are never read
        best = -np.inf
        for t0 in range(0, c, TILE):
            nt = min(TILE, c - t0)
            _read_tile(folds, norms, g, t0, nt, V, cm, uniform)
            position_tile(V, cm, sigma[g], max2, W)
            amplitude_tile(cm, amp_pow, amp_lns, amp_lo, amp_hi, t0_tab, tab, W)
            fisher_tile(x0[g], y0[g], b2, W)
            best = _store_tile(W, cm, g, t0, nt, best, buf, hxy, models)
        collapse_models(g, buf, best, rsums, (out.lnle, out.lnlb, out.lnlr))


@njit(parallel=True, cache=True)
def unfold(P, chi, members, out):
    """Add the folded products ``P`` (``(n_chi, rows, n_fc)``) to ``out`` (``(rows, c)``,
    float64) model by model: ``out[r, members[f, h]] += sum_c chi[c, h] P[c, r, f]``
    (``members[f, h] = -1``: no model), the models of an exposure's folded columns
    (:func:`pylensfit.joint.lattice_symmetries`); each row written in the models' order,
    read from their columns."""
    n_chi, n_rows, n_fc = P.shape
    n_h = members.shape[1]
    c = out.shape[1]
    col = np.full(c, -1, dtype=np.int64)
    slot = np.zeros(c, dtype=np.int64)
    for f in range(n_fc):
        for h in range(n_h):
            j = members[f, h]
            if j >= 0:
                col[j] = f
                slot[j] = h
    for r in prange(n_rows):
        for j in range(c):
            f = col[j]
            if f < 0:
                continue
            h = slot[j]
            v = 0.0
            for ch in range(n_chi):
                v += chi[ch, h] * P[ch, r, f]
            out[r, j] += v
