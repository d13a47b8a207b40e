"""numba kernel of the likelihood engine: Laplace terms and the sum over r, fused.

Called on the outputs of the six matrix products
(:class:`~pylensfit.likelihood.evaluate.Products`; docs: method, eq-matrix-products).
One pass over (galaxy, model) pairs, parallel over galaxies, with the sum over radius
kept as a running log-sum-exp so that nothing of size (galaxies x models) is written
back. The kernel's inputs come in bundles, each a named tuple documented here:
:class:`Columns` (the bank's columns), :class:`Models` (the per-model sums; under a
PSF mixed per galaxy :class:`MixedModels`, their sums per pair of PSFs, for
:func:`laplace_grid_mixed`), :class:`Galaxies`, :class:`Sums` (the weights of the sums
over r and e), :class:`Amplitude` (the amplitude prior), :class:`Laplace` (the
position's settings) and :class:`Outputs`.

numba caches a compiled kernel by its own file: the kernel here is compiled again when
this file changes, not when a kernel or constant it takes from another file
(``tile_nb``, ``laplace_nb``, ``amplitude_nb``, ``radius_nb``) does. After editing
those, remove the caches (``find src -name '*.nb[ic]' -delete``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from .._kernels_nb import one_launch_at_a_time
from .amplitude_nb import AMP_UNIFORM, amplitude_tile, power_law_table
from .laplace_nb import cubic_tile, fisher_tile, position_tile
from .radius_nb import collapse_models
from .tile_nb import (
    GROUP,
    TILE,
    W_DETM,
    W_HS,
    W_QUAD,
    W_ROWS,
    W_VAL,
    W_X,
    W_Y,
    galaxy_tables,
    pair_tables,
    read_tile,
    tile_tables,
)


class Columns(NamedTuple):
    """The columns of the model bank that the kernel evaluates
    (:class:`~pylensfit.likelihood.folded.FoldedBank`).

    With ``prod`` of ``n_chi = 1`` column ``c`` is model ``members[c, 0]``; with ``n_chi
    = 4`` the products are folded by the square's symmetries and model ``members[c, h]``
    (``h`` = 1, s1, s2, s1 s2) has ``sum_chi chi(h) prod[chi, :, c]``. Columns ``c <
    n_base = n_cols - mix_a.size`` are ``prod``'s columns ``c``; the others are not in
    ``prod``: their products are ``(1 - f) prod[.., a] + f prod[.., b]`` with ``a =
    mix_a[c - n_base]`` etc. (the bulge+disc fractions between the pure disc and the
    pure bulge; empty: none). ``prod``'s columns from ``n_base`` on are read only as
    such ``a`` or ``b`` (a pure fraction's size that the size prior leaves out where the
    mixed fraction's is in).
    """

    members: np.ndarray  # (n_cols, 1 or 4) int: the models of each column (-1: none)
    mix_a: np.ndarray  # (n_cols - n_base,) int
    mix_b: np.ndarray  # (n_cols - n_base,) int
    mix_f: np.ndarray  # (n_cols - n_base,) float


class Models(NamedTuple):
    """Per model, ``sum m^2`` and the Hessian of the model's autocorrelation at 0 (the
    PSF bank, :class:`~pylensfit.likelihood.bank.PSFBank`), ``(n_models,)`` each."""

    S: np.ndarray
    mxx: np.ndarray
    mxy: np.ndarray
    myy: np.ndarray


class MixedModels(NamedTuple):
    """Per model, the sums of :class:`Models` for a PSF mixed per galaxy from ``K`` PSFs,
    ``sum_c w_c P_c`` (:class:`~pylensfit.likelihood.bank.PairBank`): each
    ``(n_pairs, n_models)``, one row per pair of PSFs, and ``w`` ``(n_gal, n_pairs)``
    the galaxies' pair weights; galaxy ``g``'s ``S`` is ``w[g] @ S``."""

    S: np.ndarray
    mxx: np.ndarray
    mxy: np.ndarray
    myy: np.ndarray
    w: np.ndarray


class Galaxies(NamedTuple):
    """Per galaxy, ``(n_gal,)`` each: the noise per pixel and the catalogue position
    relative to the re-centred origin."""

    sigma: np.ndarray
    x0: np.ndarray
    y0: np.ndarray


class Sums(NamedTuple):
    """The weights of the sums over r and over e.

    ``L(e) = sum_k pi_k L_k(e) + w_star L_star``, where ``L_k(e)`` is the weighted sum
    over the sizes of run ``k`` (``n_r // n_sub`` runs of ``n_sub`` increasing radii,
    one per bulge fraction; ``n_r = node_w.size``), and the point source, common to all
    fractions, is counted once. The sum over r is corrected run by run
    (:func:`~pylensfit.likelihood.radius_nb._narrow_peak_factor`, applied to ``ln(w_j
    L_j)``: the trapezoid rule in the grid index; to ``ln L_j`` at a prior's edge,
    :data:`~pylensfit.likelihood.radius_nb.PRIOR_KINK`). ``L(r) = sum_e e_w L(e, r)``
    is kept per group of e cells (``n_e = e_w.size``).
    """

    #: (n_r,) weight of each size of an e cell in the sum over r: the quadrature weight
    #: of the size grid (:func:`pylensfit.models.radius_weights`) times the size prior.
    #: For the flat prior of the paper, uniform in half-light radius for every bulge
    #: fraction, a run's weights carry the Jacobian ``dh / dr`` of its fraction (relative
    #: to the first run's); for an estimated prior (:class:`pylensfit.prior.SizePrior`)
    #: they are the prior mass of each node. Sizes of weight 0 are left out: their
    #: models need no column, and a run's narrow-peak factor stops at them as at the
    #: run's ends
    node_w: np.ndarray
    #: the point source's weight
    w_star: float
    #: (n_r // n_sub,) log prior weight of each bulge fraction (summing to 1)
    ln_pi: np.ndarray
    #: (n_e,) weights of the e cells (summing to 1) in ``L(r)``: an ellipticity prior's
    #: mass per cell
    e_w: np.ndarray
    #: (n_e,) group of each e cell (``0 .. n_grp - 1``, ``n_grp = lnlr.shape[1]`` of
    #: :class:`Outputs`): the sum over e of ``L(r)`` is kept per group
    e_grp: np.ndarray
    #: sizes per run
    n_sub: int


class Amplitude(NamedTuple):
    """The amplitude prior (:func:`~pylensfit.likelihood.laplace_nb.laplace_lnl`)."""

    #: uniform if :data:`~pylensfit.likelihood.amplitude_nb.AMP_UNIFORM` (``-inf``),
    #: else the power of a power law in the model's S/N
    power: float
    #: coefficient of ``0.5 ln S`` added to a power-law prior: 0 for a power law in the
    #: model's S/N, ``power - 1`` for one in the flux
    lns: float
    #: bounds on the flux of a power-law prior (0 and inf: none)
    lo: float
    hi: float


class Laplace(NamedTuple):
    """The position's settings of the Laplace terms."""

    b2: float  # variance of the position prior (pixels^2)
    max_step: float  # the longest Newton step (pixels)
    cubic: bool  # the third-order expansion in position (``prod`` has its rows)


class Outputs(NamedTuple):
    """The kernel's results, filled per galaxy."""

    lnle: np.ndarray  # (n_gal, n_e) ln L(e), summed over r
    lnlb: np.ndarray  # (n_gal, n_e, n_r // n_sub) ln L_k(e) of each run, no point source
    lnlr: np.ndarray  # (n_gal, n_grp, n_r + 1) ln L(r) per group; the point source last
    best: np.ndarray  # (n_gal,) int: the most likely model
    h: np.ndarray  # (n_gal,) its h*
    x: np.ndarray  # (n_gal,) its peak, from the re-centred origin
    y: np.ndarray

    @classmethod
    def empty(cls, n_gal: int, n_e: int, n_b: int, n_grp: int, n_r: int) -> Outputs:
        """Arrays for ``n_gal`` galaxies, ``n_e`` e cells, ``n_b`` runs, ``n_grp`` groups
        of e cells and ``n_r`` sizes per e cell."""
        return cls(np.empty((n_gal, n_e)), np.empty((n_gal, n_e, n_b)),
                   np.empty((n_gal, n_grp, n_r + 1)), np.empty(n_gal, dtype=np.int64),
                   np.empty(n_gal), np.empty(n_gal), np.empty(n_gal))  # fmt: skip


@njit(parallel=True, cache=True, fastmath={"contract", "arcp", "afn"})
def _laplace_grid_tab_nb(prod, cols, models, gals, sums, amp, table, laplace, out):
    """Fill per-galaxy ``ln L(e)`` (summed over r), ``ln L(r)`` and the best model.

    Two passes per galaxy: the first (:func:`_first_pass`) evaluates ``ln L(e, r)`` of
    every model into a buffer and finds the peak ``M``, a tile of ``TILE`` columns at a
    time: each stage of :func:`~pylensfit.likelihood.laplace_nb.laplace_lnl` (the
    reference, one model at a time) runs over the tile as a loop of independent
    iterations, which LLVM vectorises: 47 ns per model against 115 for the one long
    chain of divisions and logs per model; the second
    (:func:`~pylensfit.likelihood.radius_nb.collapse_models`) takes one ``exp(ln L -
    M)`` per model and accumulates both the sum over r (for ``L(e)``) and the
    ``e_w``-weighted sum over e (for ``L(r)``). Where a whole e cell lies more than 700
    e-folds under the peak (bright galaxies far from their ellipticity) its sum
    underflows and ``ln L(e)`` is replaced by its largest weighted term: exact to within
    ``ln n_r`` at a point whose posterior weight is ``exp(-700)``.

    ``prod`` ``(n_chi, 6 * n_gal or 10 * n_gal, n_cols)`` holds the matrix products:
    rows ``q * n_gal + g`` hold, for ``q = 0..5``: ``h``, ``dh/dx``, ``dh/dy``,
    ``d2h/dx2``, ``d2h/dxdy``, ``d2h/dy2`` at the re-centred origin, and with
    ``laplace.cubic`` for ``q = 6..9`` the third derivatives ``xxx, xxy, xyy, yyy``;
    its columns are those of ``cols`` (:class:`Columns`). ``models``, ``gals``,
    ``sums``, ``amp``, ``laplace`` and ``out``: :class:`Models`, :class:`Galaxies`,
    :class:`Sums`, :class:`Amplitude`, :class:`Laplace`, :class:`Outputs`. ``table``:
    the unbounded power law's table ``(t0, tab)``,
    :func:`~pylensfit.likelihood.amplitude_nb.amplitude_table` (:func:`laplace_grid`
    computes it itself), for the models well inside the flux bounds.
    """
    s_m, mxx, mxy, myy = models
    node_w, w_star, ln_pi, e_w, e_grp, n_sub = sums
    sigma, x0, y0 = gals
    members, mix_a, mix_b, mix_f = cols
    n_mod = e_w.size * node_w.size + 1
    sq_m = np.sqrt(s_m)
    ln_m = np.log(s_m)
    ln_w = np.log(node_w)
    pi = np.exp(ln_pi)
    n_base = members.shape[0] - mix_a.size  # prod's further columns only feed mixed ones
    mix_run, cj, cm = tile_tables(cols, (s_m, sq_m, mxx, mxy, myy, ln_m))
    mix = (n_base, mix_a, mix_b, mix_f, mix_run)
    rsums = (node_w, ln_w, w_star, ln_pi, pi, e_w, e_grp, n_sub)
    amp_t = (amp[0], amp[1], amp[2], amp[3], table[0], table[1])
    pos = (laplace[0], laplace[1] * laplace[1], laplace[2])
    hxy = (out.h, out.x, out.y)
    lnl = (out.lnle, out.lnlb, out.lnlr)
    best_m = out.best
    for g in prange(sigma.size):
        buf = np.empty(n_mod)
        best, jb = _first_pass(prod, g, (sigma[g], x0[g], y0[g]), mix, (cj, cm), amp_t, pos,
                               buf, hxy)  # fmt: skip
        best_m[g] = jb
        collapse_models(g, buf, best, rsums, lnl)


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def _first_pass(prod, g, gal, mix, tabs, amp, pos, buf, hxy):
    """Galaxy ``g``'s ``ln L`` of every model into ``buf``, a tile at a time; returns the
    peak and its model, whose ``h*`` and peak go to ``hxy[0][g]``, ``hxy[1][g]``,
    ``hxy[2][g]``. ``gal``: the galaxy's ``(sigma, x0, y0)``; ``mix``: the mixed
    columns' tables (:func:`~pylensfit.likelihood.tile_nb.read_tile`); ``tabs``: the
    tiles' models and their constants (:func:`~pylensfit.likelihood.tile_nb.tile_tables`);
    ``amp``: the amplitude prior and its table; ``pos``: ``(b2, max_step^2, cubic)``."""
    sig, gx0, gy0 = gal
    b2, max_step2, cubic = pos
    amp_pow, amp_lns, amp_lo, amp_hi, pt0, ptab = amp
    cj, cm = tabs
    out_h, out_x, out_y = hxy
    n_cols = mix[0] + mix[1].size
    n_memb = cj.shape[1]
    n_q = 10 if cubic else 6
    best = -np.inf
    jb = 0
    V = np.zeros((n_memb, n_q, TILE))
    W = np.empty((n_memb, W_ROWS, TILE))
    for it in range(cj.shape[0]):
        t0 = it * TILE
        nt = min(TILE, n_cols - t0)
        read_tile(prod, g, t0, nt, n_q, mix, V)
        for hm in range(n_memb):
            Vh = V[hm]
            Wh = W[hm]
            cmh = cm[it, hm]
            position_tile(Vh, cmh, sig, max_step2, Wh)
            if cubic:
                cubic_tile(Vh, max_step2, Wh)
            amplitude_tile(cmh, amp_pow, amp_lns, amp_lo, amp_hi, pt0, ptab, Wh)
            fisher_tile(gx0, gy0, b2, Wh)
        for k in range(nt):
            for hm in range(n_memb):
                j = cj[it, hm, k]
                if j < 0:
                    continue
                l = W[hm, W_VAL, k] - 0.5 * math.log(W[hm, W_DETM, k]) - 0.5 * W[hm, W_QUAD, k]
                buf[j] = l
                if l > best:
                    best = l
                    jb = j
                    out_h[g] = W[hm, W_HS, k]
                    out_x[g] = W[hm, W_X, k]
                    out_y[g] = W[hm, W_Y, k]
    return best, jb


laplace_grid_tab = one_launch_at_a_time(_laplace_grid_tab_nb)


@njit(cache=True)
def _laplace_grid_nb(prod, cols, models, gals, sums, amp, laplace, out):
    """:func:`laplace_grid_tab` with the amplitude prior's table computed here."""
    if amp[0] != AMP_UNIFORM:
        table = power_law_table(amp[0])
    else:
        table = (0.0, np.empty((4, 0)))
    _laplace_grid_tab_nb(prod, cols, models, gals, sums, amp, table, laplace, out)


laplace_grid = one_launch_at_a_time(_laplace_grid_nb)


@njit(parallel=True, cache=True, fastmath={"contract", "arcp", "afn"})
def _laplace_grid_mixed_nb(prod, cols, models, gals, sums, amp, laplace, out):
    """:func:`laplace_grid` with a PSF mixed per galaxy: ``models`` a
    :class:`MixedModels`, each galaxy's model constants summed from the pairs' with its
    pair weights (:func:`~pylensfit.likelihood.tile_nb.galaxy_tables`, about 40
    multiply-adds per model against the thousands of its products), a group of
    :data:`~pylensfit.likelihood.tile_nb.GROUP` galaxies at a time, before their passes."""
    s_p, xx_p, xy_p, yy_p, wp = models
    node_w, w_star, ln_pi, e_w, e_grp, n_sub = sums
    sigma, x0, y0 = gals
    members, mix_a, mix_b, mix_f = cols
    if amp[0] != AMP_UNIFORM:
        table = power_law_table(amp[0])
    else:
        table = (0.0, np.empty((4, 0)))
    n_mod = e_w.size * node_w.size + 1
    ln_w = np.log(node_w)
    pi = np.exp(ln_pi)
    n_base = members.shape[0] - mix_a.size
    one = np.ones(s_p.shape[1])
    mix_run, cj, _ = tile_tables(cols, (one, one, one, one, one, one))
    cp = pair_tables(cols, (s_p, xx_p, xy_p, yy_p))
    mix = (n_base, mix_a, mix_b, mix_f, mix_run)
    rsums = (node_w, ln_w, w_star, ln_pi, pi, e_w, e_grp, n_sub)
    amp_t = (amp[0], amp[1], amp[2], amp[3], table[0], table[1])
    pos = (laplace[0], laplace[1] * laplace[1], laplace[2])
    hxy = (out.h, out.x, out.y)
    lnl = (out.lnle, out.lnlb, out.lnlr)
    best_m = out.best
    for gg in prange(-(-sigma.size // GROUP)):
        g0 = gg * GROUP
        n_g = min(GROUP, sigma.size - g0)
        cm = np.empty((n_g, cj.shape[0], cj.shape[1], 6, TILE))
        galaxy_tables(cj, cp, wp[g0 : g0 + n_g], cm)
        buf = np.empty(n_mod)
        for a in range(n_g):
            g = g0 + a
            best, jb = _first_pass(prod, g, (sigma[g], x0[g], y0[g]), mix, (cj, cm[a]), amp_t,
                                   pos, buf, hxy)  # fmt: skip
            best_m[g] = jb
            collapse_models(g, buf, best, rsums, lnl)


laplace_grid_mixed = one_launch_at_a_time(_laplace_grid_mixed_nb)
