"""The sample the priors are estimated from: likelihood rows, checked and scaled.

:func:`usable_rows` says which rows of a likelihood grid can be used;
:func:`prepare_sample` checks a sample once and holds it as a :class:`PreparedSample`,
``L = exp(ln L - max)`` per usable row with its weight, the input of every estimate of
the ellipticity prior.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .._util import check_egrid, check_lnL


class PreparedSample(NamedTuple):
    """A sample of likelihood grids, checked and ready for the estimates.

    Attributes
    ----------
    egrid : numpy.ndarray
        ``(n_e, 2)`` grid of cell centres.
    L : numpy.ndarray
        ``(n_used, n_e)`` float64 likelihoods of the usable rows, each scaled to a
        maximum of 1.
    w : numpy.ndarray
        ``(n_used,)`` their weights ``w_a`` (1 by default).
    used : numpy.ndarray
        ``(n_gal,)`` which rows of the input are used.
    n_excluded : int
        Rows left out (unusable, or of weight 0).
    """

    egrid: np.ndarray
    L: np.ndarray
    w: np.ndarray
    used: np.ndarray
    n_excluded: int

    @property
    def radii(self) -> np.ndarray:
        """``(n_e,)`` the grid's ``|e|``."""
        return np.hypot(self.egrid[:, 0], self.egrid[:, 1])


def usable_rows(lnL: np.ndarray) -> np.ndarray:
    """Rows of ``lnL`` that can be used: no NaN, no ``+inf``, at least one finite value.

    Rows that are all ``-inf``, all NaN, or contain any NaN are unusable (``-inf`` entries
    in an otherwise finite row are fine: ``L = 0`` there).
    """
    lnL = np.asarray(lnL)
    bad = np.isnan(lnL).any(axis=1) | np.isposinf(lnL).any(axis=1)
    bad |= ~np.isfinite(lnL).any(axis=1)
    return ~bad


def _likelihood_matrix(lnL: np.ndarray) -> np.ndarray:
    """``L = exp(lnL - rowmax)`` in float64 (rows assumed usable)."""
    L = np.asarray(lnL, dtype=np.float64)
    L = L - np.max(L, axis=1, keepdims=True)
    np.exp(L, out=L)
    return L


def prepare_sample(lnL: np.ndarray, egrid: np.ndarray,
                   weights: np.ndarray | None) -> PreparedSample:  # fmt: skip
    """The usable rows of ``lnL (n_gal, n_e)`` on ``egrid`` with their ``weights``.

    Raises
    ------
    ValueError
        On grids of the wrong shape, bad weights, an empty sample or no usable row.
    """
    egrid = check_egrid(egrid)
    lnL = check_lnL(lnL, egrid)
    if lnL.shape[0] == 0:
        raise ValueError("empty sample: lnL has no rows (no galaxies)")
    ok = usable_rows(lnL)
    if weights is not None:
        weights = np.asarray(weights, dtype=float)
        if weights.shape != (lnL.shape[0],):
            raise ValueError(
                f"weights must have shape ({lnL.shape[0]},) (one per row of lnL), "
                f"got {weights.shape}"
            )
        if np.any(~np.isfinite(weights)) or np.any(weights < 0):
            raise ValueError("weights must be finite and non-negative")
        ok &= weights > 0
    n_excl = int(np.count_nonzero(~ok))
    if not np.any(ok):
        raise ValueError(
            f"empty sample: none of the {lnL.shape[0]} likelihood rows is usable "
            "(rows that are all -inf, contain NaN or +inf, or have zero weight are excluded)"
        )
    L = _likelihood_matrix(lnL[ok])
    w = np.ones(L.shape[0]) if weights is None else weights[ok]
    return PreparedSample(egrid, L, w, ok, n_excl)
