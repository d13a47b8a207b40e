"""The ellipticity grid shared by the likelihood engine and the Bayesian shear layer.

The grid is made of the *centres* of square cells of side ``step`` tiling the
(e1, e2) plane, ``+-step/2, +-3 step/2, ...``, kept where ``|e| < emax`` (``emax = 1``
by default). No grid point ever sits at ``e = 0``: the fitted prior has a cusp there
when its exponent ``C < 1`` and a grid through the origin biases the shear
(docs: method, eq-egrid). For ``step = 0.1`` this is the paper's
"less than 20 x 20" grid: 20 x 20 cells minus the corners outside the unit circle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numba
import numpy as np

from ._util import check_egrid, check_lnL

__all__ = [
    "DEFAULT_REFINE",
    "DEFAULT_STENCIL",
    "ellipticity_grid",
    "grid_step",
    "refine_lnL",
    "refined_grid",
]


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
#: Default refinement factor of the integration grid (see :func:`pylensfit.shear.shapes`).
DEFAULT_REFINE = 4
#: Points per axis of the stencil that interpolates ``ln L`` onto the integration grid:
#: 6, the quintic Lagrange interpolant. The Keys cubic (4) reproduces quadratics only:
#: between nodes 0.1 apart the likelihood of a galaxy at S/N 10-30 is not quadratic
#: enough, and its interpolation raised m by +0.0006; the quintic's moves it by -0.00005
#: +- 0.00003 (``benchmarks/studies/egrid_interpolation.py``).
DEFAULT_STENCIL = 6

#: Before interpolation ``ln L - max ln L`` is floored here (``-inf`` entries included):
#: the floor keeps the interpolation finite, and lies deep enough that the quintic
#: stencil, three cells each way, still sees a likelihood of width 0.01 on the grid of
#: 0.1 exactly (-450 three cells from its peak).
_LNL_FLOOR = -1000.0

# ----------------------------------------------------------------------------------------
# Refinement of the integration grid
# ----------------------------------------------------------------------------------------
def _keys_weights(t: np.ndarray, a: float = -0.5) -> tuple[np.ndarray, np.ndarray]:
    """Keys (1981) cubic-convolution weights at fractional positions ``t`` (in cells).

    Returns the first stencil index ``floor(t) - 1`` and the ``(n, 4)`` weights. With
    ``a = -1/2`` the interpolant reproduces quadratics exactly.
    """
    i0 = np.floor(t).astype(int)
    f = t - i0
    d = np.stack([1.0 + f, f, 1.0 - f, 2.0 - f], axis=1)
    near = (a + 2.0) * d**3 - (a + 3.0) * d**2 + 1.0
    far = a * d**3 - 5.0 * a * d**2 + 8.0 * a * d - 4.0 * a
    w = np.where(d <= 1.0, near, far)
    return i0 - 1, w


def _lagrange_weights(t: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Lagrange weights of the ``width`` lattice points nearest ``t`` (``width`` even).

    Returns the first stencil index ``floor(t) - width/2 + 1`` and the ``(n, width)``
    weights of the polynomial of degree ``width - 1`` through the points ``floor(t) -
    width/2 + 1 ... floor(t) + width/2``: exact for polynomials of that degree.
    """
    i0 = np.floor(t).astype(int)
    f = t - i0
    nodes = np.arange(width) - (width // 2 - 1)  # relative to floor(t)
    w = np.ones((t.size, width))
    for j in range(width):
        for k in range(width):
            if k != j:
                w[:, j] *= (f - nodes[k]) / (nodes[j] - nodes[k])
    return i0 - (width // 2 - 1), w


def _stencil_weights(t: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The interpolation stencils of :func:`refine_lnL`: first index and weights.

    ``width = 4``: the Keys cubic convolution (exact for quadratics); ``width = 6``:
    the quintic Lagrange interpolant of the six nearest lattice points (exact for
    quintics), the default (:data:`DEFAULT_STENCIL`).
    """
    if width == 4:
        return _keys_weights(t)
    if width == 6:
        return _lagrange_weights(t, 6)
    raise ValueError(f"stencil must be 4 (cubic) or 6 (quintic), got {width}")


@dataclass(frozen=True)
class Refiner:
    """Precomputed pieces of the grid refinement (see :func:`refine_lnL`).

    ``cell`` places the grid values on the padded square lattice (side ``m``, row-major
    in ``(e2, e1)``) and ``fill (n_out, 4)`` fills the rest (:func:`_fill_lattice`);
    ``j0, w`` are the stencils (``width`` points, :func:`_stencil_weights`) of the fine
    1-D coordinates (the same on both axes); the lattice cell below a fine coordinate
    is ``j0 + width // 2 - 1``; ``fx, fy`` index the fine cells kept (inside the disc) into the
    fine 1-D coordinates; ``fine`` holds their centres; ``cell`` is the lattice index of
    each grid cell.
    """

    fine: np.ndarray
    m: int
    width: int
    j0: np.ndarray
    w: np.ndarray
    fx: np.ndarray
    fy: np.ndarray
    row_y: np.ndarray
    row_lo: np.ndarray
    row_hi: np.ndarray
    cell: np.ndarray
    fill: np.ndarray

    def lattice(self, x: np.ndarray) -> np.ndarray:
        """``ln L`` rows ``x (n, n_e)`` on the padded lattice ``(n, m*m)``: the grid's
        cells, and outside them the limited quadratic extrapolation of
        :func:`_fill_lattice`."""
        X = np.zeros((x.shape[0], self.m * self.m))
        X[:, self.cell] = x
        _fill_lattice(X, self.fill, _LNL_FLOOR)
        return X

    def excess(self, X: np.ndarray) -> np.ndarray:
        """Largest rise of the interpolant inside a cell above the cell's corners, per row.

        The interpolant reproduces a quadratic ``ln L``, which rises inside a cell above
        its highest corner by at most ``|D11| / 8 + |D22| / 8 + |D12| / 4`` (the second
        differences, the same in every cell); those of the 3 x 3 lattice cells about the
        peak are used, plus 1. :func:`refine_lnL` and the posterior sums cap every fine
        value there: a likelihood that falls off a cliff (a bright galaxy's near
        ``|e| = 1``, where the models degenerate, or its floor) would otherwise be
        interpolated, through the negative lobes of the kernel, into a spurious
        peak far from its own (per-galaxy responses of -10 at S/N 100).
        """
        m = self.m
        pk = self.cell[np.argmax(X[:, self.cell], axis=1)]
        rows = np.arange(X.shape[0])

        def at(dy, dx):
            return X[rows, pk + dy * m + dx]

        f0 = at(0, 0)
        d11 = at(0, 1) - 2 * f0 + at(0, -1)
        d22 = at(1, 0) - 2 * f0 + at(-1, 0)
        d12 = 0.25 * (at(1, 1) - at(1, -1) - at(-1, 1) + at(-1, -1))
        return (np.abs(d11) + np.abs(d22)) / 8.0 + np.abs(d12) / 4.0 + 1.0

    def keys(self) -> np.ndarray:
        """The interpolation map ``K (n_f, m*m)`` from the padded lattice to the fine cells."""
        K = np.zeros((self.fine.shape[0], self.m, self.m))
        jx, jy = self.j0[self.fx], self.j0[self.fy]
        wx, wy = self.w[self.fx], self.w[self.fy]
        rows = np.arange(self.fine.shape[0])
        for a in range(self.width):
            for b in range(self.width):
                np.add.at(K, (rows, jy + a, jx + b), wy[:, a] * wx[:, b])
        return K.reshape(self.fine.shape[0], -1)


@lru_cache(maxsize=8)
def _refiner_cached(key: bytes, n_e: int, refine: int, stencil: int) -> Refiner:
    egrid = np.frombuffer(key, dtype=float).reshape(n_e, 2)
    return _build_refiner(egrid, refine, stencil)


def refiner(egrid: np.ndarray, refine: int, stencil: int = DEFAULT_STENCIL) -> Refiner:
    eg = np.ascontiguousarray(egrid, dtype=float)
    return _refiner_cached(eg.tobytes(), eg.shape[0], int(refine), int(stencil))


def refined_grid(egrid: np.ndarray, refine: int, stencil: int = DEFAULT_STENCIL) -> np.ndarray:
    """The integration grid of a refinement: the fine cell centres inside ``|e| < 1``.

    Parameters
    ----------
    egrid : numpy.ndarray
        ``(n_e, 2)`` grid of cell centres on a square lattice of side ``de``.
    refine : int
        The fine grid has cells of side ``de / refine``; 1: ``egrid`` itself.
    stencil : int
        Lattice points per axis of the interpolant (as :func:`refine_lnL`).

    Returns
    -------
    numpy.ndarray
        ``(n_f, 2)`` fine cell centres, the grid of the columns of :func:`kernel_columns`
        and :func:`sheared_prior_columns` for :func:`sums_with` (``egrid`` itself when
        ``refine == 1``).
    """
    return egrid if refine == 1 else refiner(egrid, refine, stencil).fine


def _build_refiner(egrid: np.ndarray, refine: int, stencil: int = DEFAULT_STENCIL) -> Refiner:
    step = grid_step(egrid)
    coords = np.unique(np.round(egrid.ravel() / step - 0.5, 6))
    if np.any(np.abs(coords - np.round(coords)) > 1e-4):
        raise ValueError(
            "refine > 1 needs a grid of cell centres on a square lattice "
            "(as made by pylensfit.ellipticity_grid)"
        )
    kmin = int(np.round(coords.min()))
    kmax = int(np.round(coords.max()))
    pad = stencil // 2
    lo = kmin - pad
    m = kmax - kmin + 1 + 2 * pad
    xc = (np.arange(m) + lo + 0.5) * step  # padded lattice centres (both axes)
    ix = np.round(egrid[:, 0] / step - 0.5).astype(int) - lo
    iy = np.round(egrid[:, 1] / step - 0.5).astype(int) - lo

    # The lattice cells that are not on the grid (outside |e| < 1, and the padding) are
    # filled, in order of increasing radius, by (limited) quadratic extrapolation along
    # the axis of the larger |coord| from the three cells next to them towards the
    # centre: exact for quadratic ln L (_fill_lattice).
    fill: list[list[int]] = []  # (target, a, b, c): target from a, b, c (nearest first)
    have = np.zeros((m, m), dtype=bool)
    have[iy, ix] = True
    X, Y = np.meshgrid(xc, xc, indexing="xy")
    missing = np.argwhere(~have)
    order = np.argsort(np.hypot(X, Y)[~have], kind="stable")
    for jy, jx in missing[order]:
        if abs(X[jy, jx]) >= abs(Y[jy, jx]):
            s = 1 if X[jy, jx] > 0 else -1
            src = [(jy, jx - s), (jy, jx - 2 * s), (jy, jx - 3 * s)]
        else:
            s = 1 if Y[jy, jx] > 0 else -1
            src = [(jy - s, jx), (jy - 2 * s, jx), (jy - 3 * s, jx)]
        if not all(0 <= a < m and 0 <= b < m and have[a, b] for a, b in src):
            raise ValueError("cannot extend the ellipticity grid for refinement")
        have[jy, jx] = True
        fill.append([jy * m + jx] + [a * m + b for a, b in src])

    # Fine grid: cell centres of side step/refine inside the disc covered by the grid.
    rmax = min(1.0, float(np.max(np.hypot(egrid[:, 0], egrid[:, 1]))) + step / math.sqrt(2.0))
    step_f = step / refine
    nh = int(np.ceil(rmax / step_f - 0.5 - 1e-9)) + 1
    u = (np.arange(-nh, nh) + 0.5) * step_f
    UX, UY = np.meshgrid(u, u, indexing="xy")
    keep = np.hypot(UX, UY) < rmax
    fy, fx = np.nonzero(keep)
    fine = np.column_stack([u[fx], u[fy]])
    j0, w = _stencil_weights((u - xc[0]) / step, int(stencil))
    if j0.min() < 0 or j0.max() + stencil - 1 >= m:
        raise ValueError("cannot extend the ellipticity grid for refinement")
    # the kept cells of each fine row form one run of e1 indices (the disc is convex)
    row_y = np.unique(fy)
    row_lo = np.array([fx[fy == y].min() for y in row_y])
    row_hi = np.array([fx[fy == y].max() + 1 for y in row_y])
    if int(np.sum(row_hi - row_lo)) != fx.size:
        raise ValueError("cannot extend the ellipticity grid for refinement")
    return Refiner(
        fine=fine,
        m=m,
        width=int(stencil),
        j0=j0.astype(np.int64),
        w=np.ascontiguousarray(w),
        fx=fx.astype(np.int64),
        fy=fy.astype(np.int64),
        row_y=row_y.astype(np.int64),
        row_lo=row_lo.astype(np.int64),
        row_hi=row_hi.astype(np.int64),
        cell=(iy * m + ix).astype(np.int64),
        fill=np.array(fill, dtype=np.int64).reshape(-1, 4),
    )


@numba.njit(cache=True)
def _fill_lattice(X, fill, floor):  # pragma: no cover
    """Fill the lattice cells outside the grid, row by row, in ``fill``'s order.

    Cell ``t`` from the three cells ``a, b, c`` inward of it: the quadratic extrapolation
    ``3 a - 3 b + c``, limited to ``a + max(0, min(a - b, b - c))`` and floored at
    ``floor``. A concave run (a peak, ``a - 2 b + c <= 0``) never meets the limit, so a
    Gaussian likelihood is still extrapolated exactly; a convex one (a kink or a cliff in
    a faint galaxy's bumpy ``ln L`` near ``|e| = 1``) would otherwise rise without bound
    beyond the grid (``+29`` over the grid's maximum from cells at ``-31``, ``-15``: the
    interpolant's spurious peak then moved that galaxy's mean e by 1.0).
    """
    for g in range(X.shape[0]):
        for k in range(fill.shape[0]):
            a = X[g, fill[k, 1]]
            b = X[g, fill[k, 2]]
            c = X[g, fill[k, 3]]
            v = 3.0 * a - 3.0 * b + c
            lim = a + max(0.0, min(a - b, b - c))
            X[g, fill[k, 0]] = max(min(v, lim), floor)


def refine_lnL(
    lnL: np.ndarray,
    egrid: np.ndarray,
    *,
    refine: int = DEFAULT_REFINE,
    stencil: int = DEFAULT_STENCIL,
) -> tuple[np.ndarray, np.ndarray]:
    """Interpolate log-likelihood grids onto a finer grid of cell centres.

    Each row (shifted to a maximum of 0 and floored at -200) is interpolated on the
    square lattice of the grid, by default with the quintic Lagrange interpolant of the
    6 x 6 nearest lattice cells (``stencil=4``: the Keys (1981) cubic convolution);
    lattice cells outside the grid (``|e| >= 1``) are first filled by quadratic
    extrapolation (limited where ``ln L`` is convex: :func:`_fill_lattice`). Both steps
    reproduce a quadratic ``ln L`` (a Gaussian likelihood) exactly; the interpolant
    assumes a likelihood resolved by the grid (a width of at least about half a cell).
    Each fine value is capped a little above the highest of the four lattice cells
    about it (:meth:`Refiner.excess`), against the kernel's negative lobes at a cliff.
    :func:`pylensfit.shear.shapes` applies the same map block by block inside a compiled kernel.

    Parameters
    ----------
    lnL : numpy.ndarray
        ``(n_gal, n_e)`` log-likelihood on ``egrid`` (usable rows only).
    egrid : numpy.ndarray
        ``(n_e, 2)`` grid of cell centres on a square lattice of side ``de``.
    refine : int
        The fine grid has cells of side ``de / refine``.
    stencil : int
        Lattice points per axis of the interpolant: 6 (quintic Lagrange, the default)
        or 4 (Keys cubic convolution).

    Returns
    -------
    lnL_fine : numpy.ndarray
        ``(n_gal, n_f)`` interpolated ``ln L`` (relative to each row's maximum on the
        input grid).
    fine_grid : numpy.ndarray
        ``(n_f, 2)`` fine cell centres inside ``|e| < 1``.
    """
    egrid = check_egrid(egrid)
    lnL = check_lnL(lnL, egrid)
    if int(refine) != refine or refine < 1:
        raise ValueError(f"refine must be a positive integer, got {refine}")
    x = relative_lnL(lnL)
    if refine == 1:
        return x, egrid
    r = refiner(egrid, int(refine), int(stencil))
    X = r.lattice(x)
    # separable: along e1 on every lattice row, then along e2 (the map of r.keys())
    W1 = np.zeros((r.j0.size, r.m))
    for a in range(r.width):
        W1[np.arange(r.j0.size), r.j0 + a] = r.w[:, a]
    n = X.shape[0]
    T = (X.reshape(-1, r.m) @ W1.T).reshape(n, r.m, -1)  # (n, e2 lattice, e1 fine)
    T = np.ascontiguousarray(T.transpose(1, 0, 2)).reshape(r.m, -1)
    fine = (W1 @ T).reshape(W1.shape[0], n, -1)[r.fy, :, r.fx].T  # (n, n_f)
    # the cap of Refiner.excess: the highest of the four lattice cells about each fine cell
    m = r.m
    h = r.width // 2 - 1
    jx, jy = r.j0[r.fx] + h, r.j0[r.fy] + h
    Xr = X.reshape(-1, m, m)
    top = np.maximum(Xr[:, :, :-1], Xr[:, :, 1:])
    top = np.maximum(top[:, :-1, :], top[:, 1:, :])  # top[:, i, j]: max of cells i..i+1, j..j+1
    return np.minimum(fine, top[:, jy, jx] + r.excess(X)[:, None]), r.fine


def relative_lnL(lnL: np.ndarray) -> np.ndarray:
    x = np.asarray(lnL, dtype=np.float64)
    x = x - np.max(x, axis=1, keepdims=True)
    np.maximum(x, _LNL_FLOOR, out=x)
    return x
