"""The compiled kernel of the posterior sums on a refined integration grid.

Called by :func:`pylensfit.shear.sums.sums_with`, which maps each block of likelihood
grids onto the padded lattice of :class:`pylensfit.grid.Refiner` first.
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: Fine cells with ``ln L`` this far below the galaxy's maximum are skipped (weight
#: below 4e-18 each).
_LNL_SKIP = -40.0


@numba.njit(parallel=True, cache=True)
def fine_sums_kernel(X, cap, m, j0, w, row_y, row_lo, row_hi, K, out):  # pragma: no cover
    """Fused interpolation, exponentiation and accumulation for a block of galaxies.

    ``X (nb, m*m)``: ``ln L`` on the padded square lattice (row-major in ``(e2, e1)``).
    The fine cells are stored row by row: row ``i`` has fine 1-D indices ``row_y[i]``
    (e2) and ``row_lo[i] <= jx < row_hi[i]`` (e1); ``j0, w`` are the stencils (``W =
    w.shape[1]`` points) of the fine 1-D coordinates. ``out[a] = sum_f exp(lnL_f -
    max_f lnL_f) K[f]``. Each fine value is capped at ``cap[a]`` above the highest of
    its four lattice cells (:meth:`pylensfit.grid.Refiner.excess`).
    """
    nb = X.shape[0]
    nf1 = j0.shape[0]
    nw = w.shape[1]
    h = nw // 2 - 1  # the lattice cell below a fine coordinate is j0 + h
    nrow = row_y.shape[0]
    n_f = K.shape[0]
    nk = K.shape[1]
    for a in numba.prange(nb):
        T = np.empty((m, nf1))  # interpolated along e1, on the lattice rows
        for iy in range(m):
            base = iy * m
            for jf in range(nf1):
                j = base + j0[jf]
                acc0 = 0.0
                for q in range(nw):
                    acc0 += w[jf, q] * X[a, j + q]
                T[iy, jf] = acc0
        v = np.empty(n_f)
        vmax = -np.inf
        f = 0
        for i in range(nrow):  # along e2, one fine row at a time
            jy = row_y[i]
            j = j0[jy]
            for jx in range(row_lo[i], row_hi[i]):
                val = 0.0
                for q in range(nw):
                    val += w[jy, q] * T[j + q, jx]
                c = (j + h) * m + j0[jx] + h
                top = max(max(X[a, c], X[a, c + 1]), max(X[a, c + m], X[a, c + m + 1]))
                val = min(val, top + cap[a])
                v[f] = val
                if val > vmax:
                    vmax = val
                f += 1
        acc = np.zeros(nk)
        for f in range(n_f):
            d = v[f] - vmax
            if d > _LNL_SKIP:
                lf = math.exp(d)
                for k in range(nk):
                    acc[k] += lf * K[f, k]
        for k in range(nk):
            out[a, k] = acc[k]


