"""A tile of models, the unit of work of the likelihood kernel
(:func:`pylensfit.likelihood.grid_nb.laplace_grid`): its width, the rows of its work
array, its tables of model constants and the reading of a galaxy's products into it.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: columns of the model bank handled together by :func:`laplace_grid`: each stage of the
#: Laplace terms runs over a tile as one loop of independent iterations, which LLVM
#: vectorises (AVX2) and the CPU overlaps, where one model at a time is one long chain of
#: dependent divisions and logs (measured on the precision mode's bank, 68,256 models, one
#: thread: 115 ns per model before, 47 after; the tile's arrays are one per kind, with
#: the column offset taken out of their indices, or LLVM does not vectorise)
TILE = 256


@njit(cache=True, inline="always")
def fold(V, q, k, p0, p1, p2, p3):
    """The four models of a folded column from its four characters' products
    (:class:`~pylensfit.likelihood.folded.FoldedBank`), into ``V[:, q, k]``."""
    s02 = p0 + p2
    s13 = p1 + p3
    d02 = p0 - p2
    d13 = p1 - p3
    V[0, q, k] = s02 + s13
    V[1, q, k] = s02 - s13
    V[2, q, k] = d02 + d13
    V[3, q, k] = d02 - d13


#: rows of a tile's work array ``W`` (one column per model of the tile): the peak
#: ``X*``, ``h*``, the Hessian there, ``1 / (sigma sqrt S)``, whether the data Hessian
#: was used, the amplitude integral's log and ``-d/dh`` of it, the position prior's
#: quadratic form and ``det M``
W_X, W_Y, W_HS, W_AXX, W_AXY, W_AYY, W_ISS, W_OK, W_VAL, W_DL, W_QUAD, W_DETM = range(12)
#: the number of rows of ``W``
W_ROWS = 12


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def tile_tables(cols, consts):
    """The kernel's tables (:func:`~pylensfit.likelihood.grid_nb.laplace_grid`): the
    length of the run of mixed columns starting at each (``mix_run``), and every tile's
    model indices ``cj`` and model constants ``cm`` (S, sqrt S, mxx, mxy, myy, ln S), in
    the order the tiles read them. ``cols``: ``(members, mix_a, mix_b, mix_f)``
    (:class:`~pylensfit.likelihood.grid_nb.Columns`); ``consts``: ``(S, sqrt S, mxx,
    mxy, myy, ln S)`` per model."""
    members, mix_a, mix_b, mix_f = cols
    s_m, sq_m, mxx, mxy, myy, ln_m = consts
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
    n_tiles = -(-n_cols // TILE)
    cj = np.full((n_tiles, n_memb, TILE), -1, dtype=np.int64)
    cm = np.zeros((n_tiles, n_memb, 6, TILE))
    cm[:, :, 0] = 1.0  # S, sqrt S, mxx, mxy, myy, ln S of the padding
    cm[:, :, 1] = 1.0
    cm[:, :, 2] = -1.0
    cm[:, :, 4] = -1.0
    for it in range(n_tiles):
        for hm in range(n_memb):
            for k in range(min(TILE, n_cols - it * TILE)):
                j = members[it * TILE + k, hm]
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
def read_tile(prod, g, t0, nt, n_q, mix, V):
    """Fill ``V`` with galaxy ``g``'s products of the tile of columns ``t0 .. t0 + nt``
    (:func:`~pylensfit.likelihood.grid_nb.laplace_grid`). ``mix``: ``(n_base, mix_a,
    mix_b, mix_f, mix_run)``, the first mixed column and the mixed columns' tables."""
    n_base, mix_a, mix_b, mix_f, mix_run = mix
    n_gal = prod.shape[1] // n_q
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
                    fold(V, q, k + kk, prod[0, row, ia], prod[1, row, ia],
                         prod[2, row, ia], prod[3, row, ia])  # fmt: skip
            elif n_chi == 4:
                for kk in range(ln):
                    ia = ca + kk
                    ib = cb + kk
                    fold(V, q, k + kk, fa * prod[0, row, ia] + fm * prod[0, row, ib],
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
def pair_tables(cols, pairs):
    """The tiles' pair sums for a PSF mixed per galaxy
    (:class:`~pylensfit.likelihood.grid_nb.MixedModels`): ``cp[it, hm, q, p, k]``, sum
    ``q`` (S, mxx, mxy, myy) of pair ``p`` of the model in slot ``k`` of tile ``it``,
    member ``hm`` (0 for the padding), in the order the tiles read them. ``cols``: as
    :func:`tile_tables`'; ``pairs``: ``(S, mxx, mxy, myy)``, each ``(n_pairs,
    n_models)``."""
    members = cols[0]
    n_cols, n_memb = members.shape
    n_pairs = pairs[0].shape[0]
    n_tiles = -(-n_cols // TILE)
    cp = np.zeros((n_tiles, n_memb, 4, n_pairs, TILE))
    for it in range(n_tiles):
        for hm in range(n_memb):
            for k in range(min(TILE, n_cols - it * TILE)):
                j = members[it * TILE + k, hm]
                if j >= 0:
                    for q in range(4):
                        src = pairs[q]
                        for p in range(n_pairs):
                            cp[it, hm, q, p, k] = src[p, j]
    return cp


#: galaxies whose model constants :func:`galaxy_tables` sums in one sweep over the pair
#: sums: each tile's pair sums are read once for all of them (the pair sums of Config()'s
#: bank are 18 MB; read once per galaxy they cost about 4 ms a galaxy)
GROUP = 4


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def galaxy_tables(cj, cp, wp, cm):
    """A few galaxies' model constants into ``cm`` (``(n_g, n_tiles, n_memb, 6,
    TILE)``, each as :func:`tile_tables`' ``cm``): each of S, mxx, mxy, myy the sum over
    the pairs of ``cp`` (:func:`pair_tables`) weighted by the galaxy's pair weights
    ``wp[a]`` (``(n_g, n_pairs)``), then ``sqrt S`` and ``ln S``; the padding slots
    (``cj < 0``) a harmless model."""
    n_tiles, n_memb, _, n_pairs, _ = cp.shape
    n_g = wp.shape[0]
    for it in range(n_tiles):
        for hm in range(n_memb):
            for q in range(4):
                r = 0 if q == 0 else q + 1
                for a in range(n_g):
                    for k in range(TILE):
                        cm[a, it, hm, r, k] = 0.0
                for p in range(n_pairs):
                    src = cp[it, hm, q, p]
                    for a in range(n_g):
                        wv = wp[a, p]
                        row = cm[a, it, hm, r]
                        for k in range(TILE):
                            row[k] += wv * src[k]
            for a in range(n_g):
                for k in range(TILE):
                    if cj[it, hm, k] < 0:
                        cm[a, it, hm, 0, k] = 1.0
                        cm[a, it, hm, 2, k] = -1.0
                        cm[a, it, hm, 3, k] = 0.0
                        cm[a, it, hm, 4, k] = -1.0
                    s = cm[a, it, hm, 0, k]
                    cm[a, it, hm, 1, k] = math.sqrt(s)
                    cm[a, it, hm, 5, k] = math.log(s)
