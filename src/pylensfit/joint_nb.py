"""The compiled kernel of :mod:`pylensfit.joint`: the Laplace terms of every model, on the
likelihood's own tile kernels.

One pass per galaxy (``prange``) over the models, a tile of
:data:`~pylensfit.likelihood.tile_nb.TILE` columns at a time: the Newton step in position
and the expected-Hessian fallback
(:func:`~pylensfit.likelihood.laplace_nb.position_tile`), the uniform amplitude integral
(:func:`~pylensfit.likelihood.amplitude_nb.amplitude_tile`) and the position prior
(:func:`~pylensfit.likelihood.laplace_nb.fisher_tile`) of the single-exposure fit, read
with the noise ``sigma = 1`` and the model's ``S`` replaced by the galaxy's ``Q = sum_k
f_k^2 S_k / sigma_k^2`` (the module docstring of :mod:`pylensfit.joint`). The per-model
constants that the single fit reads from its PSF bank are here summed over the exposures
per galaxy; nothing of the block's size is written but ``ln L``.

numba caches a compiled kernel by its own file: after editing the likelihood's kernels
remove the caches (``find src -name '*.nb[ic]' -delete``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from .likelihood.amplitude_nb import AMP_UNIFORM, amplitude_tile
from .likelihood.laplace_nb import fisher_tile, position_tile
from .likelihood.tile_nb import TILE, W_DETM, W_HS, W_QUAD, W_ROWS, W_VAL, W_X, W_Y

__all__ = ["Norms", "ModelOutputs", "laplace_models"]


class Norms(NamedTuple):
    """The models' norms, per exposure: ``S[k, :, p, j]`` is ``sum m^2`` of model ``j``
    seen in exposure ``k`` through its PSF ``p`` (one for all galaxies, ``p = 0``, or one
    per galaxy) and the Hessian of its autocorrelation at 0 ``(xx, xy, yy)``, per unit
    of ``f_k^2 / sigma_k^2``; ``w2[k, g]`` is that weight of galaxy ``g`` (0 where the
    exposure is not used)."""

    S: np.ndarray  # (K, 4, n_psf, c), arcsec^-2 for the Hessian
    w2: np.ndarray  # (K, m)


class ModelOutputs(NamedTuple):
    """The kernel's results: ``ln L`` of every model and the most likely model's."""

    lnl: np.ndarray  # (m, c) ln L(e, r); NaN where no exposure is usable
    best: np.ndarray  # (m,) int: the most likely model (the first of equal ones)
    h: np.ndarray  # (m,) its H*
    x: np.ndarray  # (m,) its peak X*, from the origin, arcsec
    y: np.ndarray

    @classmethod
    def empty(cls, m: int, c: int) -> ModelOutputs:
        """Arrays for ``m`` galaxies and ``c`` models."""
        return cls(np.empty((m, c)), np.zeros(m, dtype=np.int64), np.full(m, np.nan),
                   np.full(m, np.nan), np.full(m, np.nan))  # fmt: skip


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def _read_tile(A, norms, g, t0, nt, V, cm):
    """Galaxy ``g``'s products of the columns ``t0 .. t0 + nt`` into ``V`` (``(6, TILE)``)
    and the models' constants ``(Q, sqrt Q, mxx, mxy, myy, ln Q)`` summed over the
    exposures into ``cm`` (``(6, TILE)``); the rest of the tile a harmless model."""
    S, w2 = norms
    p = g % S.shape[2]  # one PSF for all (0) or one per galaxy
    for q in range(6):
        for k in range(nt):
            V[q, k] = A[q, g, t0 + k]
        for k in range(nt, TILE):
            V[q, k] = 0.0
    for r in range(4):
        row = 0 if r == 0 else r + 1  # Q, then the Hessian after sqrt Q
        for k in range(nt):
            acc = 0.0
            for e in range(S.shape[0]):
                acc += w2[e, g] * S[e, r, p, t0 + k]
            cm[row, k] = acc
    for k in range(nt):
        cm[1, k] = math.sqrt(cm[0, k])
        cm[5, k] = math.log(cm[0, k])
    for k in range(nt, TILE):
        cm[0, k] = 1.0
        cm[1, k] = 1.0
        cm[2, k] = -1.0
        cm[3, k] = 0.0
        cm[4, k] = -1.0
        cm[5, k] = 0.0


@njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def _store_tile(W, cm, g, t0, nt, best, out):
    """The tile's ``ln L`` into ``out.lnl[g]`` (NaN where ``Q = 0``: no usable exposure),
    the most likely model so far into ``out`` (its ``ln L`` is ``best``, returned)."""
    for k in range(nt):
        j = t0 + k
        if cm[0, k] > 0.0:
            lnl = W[W_VAL, k] - 0.5 * math.log(W[W_DETM, k]) - 0.5 * W[W_QUAD, k]
        else:
            lnl = math.nan
        out.lnl[g, j] = lnl
        if j == 0 or lnl > best:
            out.best[g] = j
            out.h[g] = W[W_HS, k] if cm[0, k] > 0.0 else math.nan
            out.x[g] = W[W_X, k] if cm[0, k] > 0.0 else math.nan
            out.y[g] = W[W_Y, k] if cm[0, k] > 0.0 else math.nan
            if lnl > best:
                best = lnl
    return best


@njit(parallel=True, cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})
def laplace_models(A, norms, gals, laplace, out):
    """``ln L(e, r)`` of every model of a block and the most likely model's ``H*`` and
    ``X*``, into ``out`` (:class:`ModelOutputs`).

    ``A`` ``(6, m, c)``: ``H``, its gradient and Hessian at the origin (the joint
    products, any float type); ``norms``: :class:`Norms`; ``gals``: the likelihood's
    :class:`~pylensfit.likelihood.grid_nb.Galaxies` (``sigma`` 1: the weights are in
    ``A`` and ``norms``; ``x0, y0`` the catalogue position from the origin, arcsec);
    ``laplace``: its :class:`~pylensfit.likelihood.grid_nb.Laplace` (``b2`` arcsec^2,
    ``max_step`` arcsec; ``cubic`` is not read: second order).
    """
    sigma, x0, y0 = gals
    b2 = laplace[0]
    max2 = laplace[1] * laplace[1]
    m, c = A.shape[1], A.shape[2]
    tab = np.empty((4, 0))
    for g in prange(m):
        V = np.zeros((6, TILE))
        cm = np.empty((6, TILE))
        W = np.empty((W_ROWS, TILE))
        best = -np.inf
        for t0 in range(0, c, TILE):
            nt = min(TILE, c - t0)
            _read_tile(A, norms, g, t0, nt, V, cm)
            position_tile(V, cm, sigma[g], max2, W)
            amplitude_tile(cm, AMP_UNIFORM, 0.0, 0.0, math.inf, 0.0, tab, W)
            fisher_tile(x0[g], y0[g], b2, W)
            best = _store_tile(W, cm, g, t0, nt, best, out)
