"""The posterior sums: every integral over the ellipticity grid as one product.

For a block of galaxies, every sum over the (refined) integration grid is one product
``L (n_gal, n_e) @ K (n_e, k)``: :func:`kernel_columns` gives the ``K`` of the posterior
moments and sensitivities, :func:`sums_with` the product, on the grid itself or through
the compiled kernel of :mod:`pylensfit.shear.sums_nb` on a refined grid.
"""

from __future__ import annotations

import numpy as np

from .._kernels_nb import launch_guard
from ..grid import DEFAULT_STENCIL, refiner, relative_lnL
from ..prior import Prior
from .sums_nb import fine_sums_kernel

#: Elements (galaxies x fine cells) processed per block.
_BLOCK_ELEMENTS = 1 << 22


def kernel_columns(prior: Prior, grid: np.ndarray) -> np.ndarray:
    """The ``(n_e, 14)`` matrix whose product with ``L`` gives every posterior sum.

    Columns: ``P, P e1, P e2, P e1^2, P e2^2, P e1 e2, dPg1, e1 dPg1, dPg2, e2 dPg2,
    P_1, e1 P_1, P_2, e2 P_2`` with ``P_k = dP/de_k`` and ``dPg_k`` the derivative of the
    sheared population density (see :func:`shear_sensitivity`).

    Parameters
    ----------
    prior : Prior
        The ellipticity prior ``P``.
    grid : numpy.ndarray
        ``(n_e, 2)`` integration grid (:func:`refined_grid`).

    Returns
    -------
    numpy.ndarray
        ``(n_e, 14)`` columns, the ``K`` of :func:`sums_with`, whose sums
        :func:`moments_from_sums` and :func:`sensitivity_from_sums` read.
    """
    e1, e2 = grid[:, 0], grid[:, 1]
    P = prior.pdf(e1, e2)
    P1, P2 = prior.grad(e1, e2)
    dPg1 = P1 * (-1.0 + e1**2 - e2**2) + P2 * (2.0 * e1 * e2) + 4.0 * e1 * P
    dPg2 = P1 * (2.0 * e1 * e2) + P2 * (-1.0 - e1**2 + e2**2) + 4.0 * e2 * P
    return np.column_stack(
        [P, P * e1, P * e2, P * e1**2, P * e2**2, P * e1 * e2,
         dPg1, e1 * dPg1, dPg2, e2 * dPg2, P1, e1 * P1, P2, e2 * P2]
    )  # fmt: skip


def sums_with(
    lnL: np.ndarray,
    egrid: np.ndarray,
    K: np.ndarray,
    refine: int,
    block_size: int | None,
    stencil: int = DEFAULT_STENCIL,
) -> np.ndarray:
    """``sum_f L_f K_f`` per row, on the grid (``refine = 1``) or the refined grid.

    ``L = exp(lnL - max)`` per row (floored as :func:`refine_lnL`), interpolated onto
    the refined grid when ``refine > 1`` (one BLAS product per block onto the padded
    lattice, then a compiled kernel, parallel over galaxies, that interpolates,
    exponentiates and accumulates without storing the fine grids).

    Parameters
    ----------
    lnL : numpy.ndarray
        ``(n_gal, n_e)`` log-likelihood on ``egrid`` (usable rows only).
    egrid : numpy.ndarray
        ``(n_e, 2)`` grid of cell centres.
    K : numpy.ndarray
        ``(n_f, k)`` columns on the integration grid (:func:`refined_grid`), e.g.
        :func:`kernel_columns`.
    refine : int
        Integration grid refinement factor (1: integrate on ``egrid`` itself).
    block_size : int, optional
        Galaxies per block (default: about 4 million grid elements per block).
    stencil : int
        Lattice points per axis of the interpolant (as :func:`refine_lnL`).

    Returns
    -------
    numpy.ndarray
        ``(n_gal, k)`` sums.
    """
    n = lnL.shape[0]
    S = np.empty((n, K.shape[1]))
    if refine == 1:
        nb = block_size or max(1, _BLOCK_ELEMENTS // egrid.shape[0])
        for i in range(0, n, nb):
            x = relative_lnL(lnL[i : i + nb])
            np.exp(x, out=x)
            S[i : i + nb] = x @ K
        return S
    r = refiner(egrid, refine, stencil)
    K = np.ascontiguousarray(K)
    nb = block_size or max(1, _BLOCK_ELEMENTS // (r.m * r.m))
    for i in range(0, n, nb):
        X = r.lattice(relative_lnL(lnL[i : i + nb]))
        with launch_guard():  # the work queue takes one parallel launch at a time
            fine_sums_kernel(X, r.excess(X), r.m, r.j0, r.w, r.row_y, r.row_lo, r.row_hi, K,
                              S[i : i + nb])  # fmt: skip
    return S
