"""The ellipticity grid shared by the likelihood engine and the Bayesian shear layer.

The grid is made of the *centres* of square cells of side ``step`` tiling the
(e1, e2) plane, ``+-step/2, +-3 step/2, ...``, kept where ``|e| < emax`` (``emax = 1``
by default). No grid point ever sits at ``e = 0``: the fitted prior has a cusp there
when its exponent ``C < 1`` and a grid through the origin biases the shear
(docs: method, eq-egrid). For ``step = 0.1`` this is the paper's
"less than 20 x 20" grid: 20 x 20 cells minus the corners outside the unit circle.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ellipticity_grid", "grid_step"]


def ellipticity_grid(step: float = 0.1, *, emax: float = 1.0) -> np.ndarray:
    """Cell centres of the ellipticity grid.

    Parameters
    ----------
    step : float
        Cell side ``de`` (the paper's Delta e = 0.1).
    emax : float
        Keep cells whose centre has ``|e| < emax`` (at most 1).

    Returns
    -------
    numpy.ndarray
        ``(n_e, 2)`` float64 array of ``(e1, e2)``, ordered by e2 then e1
        (row-major over a square ``n x n`` lattice with the corners removed).
    """
    step = float(step)
    if not (0.0 < step <= 1.0):
        raise ValueError(f"ellipticity grid step must be in (0, 1], got {step}")
    if not (0.0 < emax <= 1.0):
        raise ValueError(f"emax must be in (0, 1], got {emax}")
    n_half = int(np.ceil(emax / step - 0.5 - 1e-9)) + 1
    c = (np.arange(-n_half, n_half) + 0.5) * step
    e1, e2 = np.meshgrid(c, c, indexing="xy")
    keep = np.hypot(e1, e2) < emax
    return np.column_stack([e1[keep], e2[keep]])


def grid_step(egrid: np.ndarray) -> float:
    """Recover the cell side of a grid made by :func:`ellipticity_grid`.

    Raises
    ------
    ValueError
        If ``egrid`` is not an ``(n_e, 2)`` array of at least two distinct e1 values.
    """
    egrid = np.asarray(egrid, dtype=float)
    if egrid.ndim != 2 or egrid.shape[1] != 2 or egrid.shape[0] < 2:
        raise ValueError(f"ellipticity grid must have shape (n_e, 2), got {egrid.shape}")
    u = np.unique(np.round(egrid[:, 0], 12))
    if u.size < 2:
        raise ValueError("ellipticity grid needs at least two distinct e1 values")
    return float(np.min(np.diff(u)))
