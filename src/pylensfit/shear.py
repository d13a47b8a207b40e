"""Per-galaxy posterior moments and shear sensitivities, and the shear of a sample.

For each galaxy ``a`` with a log-likelihood grid ``ln L_a(e)`` and a prior ``P(e)``
(:class:`pylensfit.prior.Prior`), the posterior is ``p_a(e) = P(e) L_a(e) / sum_e P L_a``
and (Kitching et al. 2008, arXiv:0802.1528, section 3.3; docs: method, eq-posterior)

    <e_i>_a = sum_e e_i P(e) L_a(e) / sum_e P(e) L_a(e),

with the variances and covariance computed likewise. The *shear sensitivity*
``d<e_i>_a / dg_i`` comes in two versions (:func:`shear_sensitivity`):

- ``"paper"``, the paper's sensitivity (Kitching et al. 2008, section 2.1; docs: method,
  eq-partial), which treats a shear as a translation of the prior in the e plane;
- ``"exact"`` (the default), the first-order response to the reduced-shear map
  ``e = (e_s + g) / (1 + g* e_s)`` of section 2.1 (docs: method, eq-sensitivity-exact),
  which removes the multiplicative bias (~ +0.008) that the translation approximation
  leaves even when the prior and likelihoods are exact.

The shear of a sample is the paper's mean shear over mean sensitivity (section 3.3;
docs: method, eq-key2), ``g_i = sum_a <e_i>_a / sum_a d<e_i>_a/dg_i``
(:func:`estimate_shear`). Everything is vectorised: for a block of galaxies all the sums
are one matrix product ``L (n_gal, n_e) @ K (n_e, 14)``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np
from astropy.table import Table

from . import grid
from ._kernels_nb import launch_guard
from ._util import check_egrid, check_lnL
from .flags import flag_value
from .grid import (
    DEFAULT_REFINE,
    DEFAULT_STENCIL,
    refined_grid,
    refiner,
    relative_lnL,
)
from .prior import BinnedPrior, Prior, RadialPrior, usable_rows
from .skyframe import SkyFrame, frame_of_table, shear_to_pixel, spin2_matrix, to_sky

__all__ = [
    "FLAG_BAD_LIKELIHOOD",
    "FLAG_NAMES",
    "ShearEstimate",
    "apply_shear",
    "estimate_shear",
    "kernel_columns",
    "moments_from_sums",
    "posterior_moments",
    "sensitivity_from_sums",
    "shapes",
    "shear_fixed_point",
    "shear_sensitivity",
    "shear_table",
    "sheared_prior_columns",
    "sums_with",
    "table_frame",
]

#: Flag bit: the likelihood row is unusable (all ``-inf``, or contains NaN / ``+inf``);
#: the ``FIT_FAILED`` bit of the catalogue's flag table (:mod:`pylensfit.flags`).
FLAG_BAD_LIKELIHOOD = flag_value("FIT_FAILED")
#: Name table of the flag bits of :func:`shapes`.
FLAG_NAMES = {FLAG_BAD_LIKELIHOOD: "FIT_FAILED"}

#: Elements (galaxies x fine cells) processed per block.
_BLOCK_ELEMENTS = 1 << 22

_SENS_METHODS = ("exact", "paper")


#: Names that live in :mod:`pylensfit.grid`; importing them from here warns.
_MOVED = {"DEFAULT_REFINE", "DEFAULT_STENCIL", "refine_lnL", "refined_grid"}


def __getattr__(name: str):
    if name in _MOVED:
        warnings.warn(f"pylensfit.shear.{name} is pylensfit.grid.{name}; the old name "
                      "goes in the next release", DeprecationWarning, stacklevel=2)
        return getattr(grid, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# ----------------------------------------------------------------------------------------
# Reduced shear
# ----------------------------------------------------------------------------------------
def apply_shear(
    e1: np.ndarray, e2: np.ndarray, g1: float, g2: float
) -> tuple[np.ndarray, np.ndarray]:
    """Shear intrinsic ellipticities: ``e = (e_s + g) / (1 + g* e_s)`` (paper section 2.1).

    Parameters
    ----------
    e1, e2 : array_like
        Intrinsic ellipticity components ``e_s`` (``|e_s| < 1``).
    g1, g2 : float
        Reduced shear components (``|g| < 1``).

    Returns
    -------
    tuple of numpy.ndarray
        The sheared ``(e1, e2)``.
    """
    es = np.asarray(e1, dtype=float) + 1j * np.asarray(e2, dtype=float)
    g = complex(g1, g2)
    e = (es + g) / (1.0 + np.conj(g) * es)
    return e.real, e.imag




#: Fine cells with ``ln L`` this far below the galaxy's maximum are skipped (weight
#: below 4e-18 each).
_LNL_SKIP = -40.0


@numba.njit(parallel=True, cache=True)
def _fine_sums_kernel(X, cap, m, j0, w, row_y, row_lo, row_hi, K, out):  # pragma: no cover
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


# ----------------------------------------------------------------------------------------
# The posterior sums
# ----------------------------------------------------------------------------------------
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


def _posterior_sums(
    lnL: np.ndarray,
    egrid: np.ndarray,
    prior: Prior,
    refine: int,
    block_size: int | None,
) -> np.ndarray:
    """``S = L @ K`` (n_gal, 14) for usable rows, with ``L`` normalised per row.

    ``refine = 1``: ``L = exp(lnL - max)`` on the grid, one BLAS product per block.
    ``refine > 1``: per block, one BLAS product maps the grid values onto the padded
    lattice, then a compiled kernel (parallel over galaxies) interpolates, exponentiates
    and accumulates, without storing the fine grids.
    """
    grid = refined_grid(egrid, refine)
    return sums_with(lnL, egrid, kernel_columns(prior, grid), refine, block_size)


def moments_from_sums(S: np.ndarray) -> dict[str, np.ndarray]:
    """Posterior means and covariances of ``e`` from the sums of :func:`kernel_columns`.

    Parameters
    ----------
    S : numpy.ndarray
        ``(n_gal, 14)`` sums ``sum L K`` (:func:`sums_with` of :func:`kernel_columns`).

    Returns
    -------
    dict of numpy.ndarray
        ``e1, e2`` (posterior means), ``e1_var, e2_var`` (floored at 0) and ``e12_cov``.
    """
    s0 = S[:, 0]
    m1 = S[:, 1] / s0
    m2 = S[:, 2] / s0
    return {
        "e1": m1,
        "e2": m2,
        "e1_var": np.maximum(S[:, 3] / s0 - m1**2, 0.0),
        "e2_var": np.maximum(S[:, 4] / s0 - m2**2, 0.0),
        "e12_cov": S[:, 5] / s0 - m1 * m2,
    }


def sensitivity_from_sums(S: np.ndarray, method: str) -> tuple[np.ndarray, np.ndarray]:
    """Shear sensitivities of each galaxy from the sums of :func:`kernel_columns`.

    Parameters
    ----------
    S : numpy.ndarray
        ``(n_gal, 14)`` sums ``sum L K`` (:func:`sums_with` of :func:`kernel_columns`).
    method : {"exact", "paper"}
        ``"paper"``: the paper's sensitivity (docs: method, eq-partial); anything else:
        the exact response (see :func:`shear_sensitivity`).

    Returns
    -------
    s1, s2 : numpy.ndarray
        ``(n_gal,)`` sensitivities of ``e1`` and ``e2``.
    """
    s0 = S[:, 0]
    m1 = S[:, 1] / s0
    m2 = S[:, 2] / s0
    if method == "paper":
        # the paper's sensitivity (eq-partial): 1 - sum (<e_i> - e_i) L dP/de_i / sum P L
        s1 = 1.0 - (m1 * S[:, 10] - S[:, 11]) / s0
        s2 = 1.0 - (m2 * S[:, 12] - S[:, 13]) / s0
    else:
        # exact: <1 -+ (e1^2 - e2^2)> - sum (e_i - <e_i>) L dPg_i / sum P L
        s1 = (S[:, 0] - S[:, 3] + S[:, 4]) / s0 - (S[:, 7] - m1 * S[:, 6]) / s0
        s2 = (S[:, 0] + S[:, 3] - S[:, 4]) / s0 - (S[:, 9] - m2 * S[:, 8]) / s0
    return s1, s2


def _check_inputs(lnL, egrid, prior, sensitivity="exact", refine=1):
    egrid = check_egrid(egrid)
    lnL = check_lnL(lnL, egrid)
    if not isinstance(prior, (RadialPrior, BinnedPrior)):
        raise TypeError("prior must be a pylensfit Prior or SplinePrior, got "
                        f"{type(prior).__name__}")
    if sensitivity not in _SENS_METHODS:
        raise ValueError(f"sensitivity must be 'exact' or 'paper', got {sensitivity!r}")
    if int(refine) != refine or refine < 1:
        raise ValueError(f"refine must be a positive integer, got {refine}")
    return lnL, egrid


def _all_sums(lnL, egrid, prior, refine, block_size, values):
    """Sums for every row (NaN for unusable rows) and the usable mask."""
    n = lnL.shape[0]
    ok = usable_rows(lnL)
    S = np.full((n, 14), np.nan)
    if isinstance(prior, BinnedPrior):
        if values is None:
            raise ValueError("a BinnedPrior needs values= (the binning column, one per row)")
        values = np.asarray(values, dtype=float)
        if values.shape != (n,):
            raise ValueError(f"values must have shape ({n},), got {values.shape}")
        idx = prior.bin_index(values)
        for b in np.unique(idx):  # a loop over bins, not galaxies
            sel = ok & (idx == b)
            if np.any(sel):
                S[sel] = _posterior_sums(
                    lnL[sel], egrid, prior.prior_for_bin(int(b)), refine, block_size
                )
    elif np.any(ok):
        S[ok] = _posterior_sums(lnL[ok], egrid, prior, refine, block_size)
    return S, ok


# ----------------------------------------------------------------------------------------
# Public per-galaxy functions
# ----------------------------------------------------------------------------------------
def posterior_moments(
    lnL: np.ndarray,
    egrid: np.ndarray,
    prior: Prior,
    *,
    refine: int = DEFAULT_REFINE,
    block_size: int | None = None,
) -> dict[str, np.ndarray]:
    """Posterior means, variances and covariance of ``(e1, e2)`` (docs: method, eq-posterior).

    ``<e_i> = sum_e e_i P L / sum_e P L`` and
    ``var(e_i) = sum_e (e_i - <e_i>)^2 P L / sum_e P L``, ``cov`` likewise.

    Parameters
    ----------
    lnL : numpy.ndarray
        ``(n_gal, n_e)`` natural-log likelihood on ``egrid`` (any per-row offset).
    egrid : numpy.ndarray
        ``(n_e, 2)`` grid of cell centres.
    prior : Prior
        The ellipticity prior.
    refine : int
        Integration grid refinement factor (see :func:`shapes`).
    block_size : int, optional
        Galaxies per block (default: about 4 million grid elements per block).

    Returns
    -------
    dict of numpy.ndarray
        ``e1, e2`` (dimensionless), ``e1_var, e2_var, e12_cov``; NaN for unusable rows.
    """
    lnL, egrid = _check_inputs(lnL, egrid, prior, refine=refine)
    S, _ = _all_sums(lnL, egrid, prior, int(refine), block_size, None)
    return moments_from_sums(S)


def shear_sensitivity(
    lnL: np.ndarray,
    egrid: np.ndarray,
    prior: Prior,
    *,
    method: str = "exact",
    refine: int = DEFAULT_REFINE,
    block_size: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Shear sensitivities ``d<e_1>/dg_1`` and ``d<e_2>/dg_2`` of each galaxy.

    ``method="paper"`` is the paper's sensitivity (Kitching et al. 2008, arXiv:0802.1528,
    section 2.1, recast in section 3.3; docs: method, eq-partial),

        d<e_i>/dg_i = 1 - sum_e (<e_i> - e_i) L(e) dP/de_i / sum_e P L,

    the response when a shear translates the prior in the e plane.

    ``method="exact"`` (default) is the first-order response to the reduced-shear map
    ``e = (e_s + g)/(1 + g* e_s)``: data and prior sheared together move ``e`` by
    ``de/dg`` (not by 1), and the zero-shear prior differs from the sheared population
    ``P(e_s) |de_s/de|`` by ``g_k dPg_k``, with ``P_k = dP/de_k``,

        dPg1 = P_1 (-1 + e1^2 - e2^2) + P_2 (2 e1 e2) + 4 e1 P,
        dPg2 = P_1 (2 e1 e2) + P_2 (-1 - e1^2 + e2^2) + 4 e2 P,
        d<e_1>/dg_1 = <1 - e1^2 + e2^2> - sum_e (e_1 - <e_1>) L dPg1 / sum_e P L,
        d<e_2>/dg_2 = <1 + e1^2 - e2^2> - sum_e (e_2 - <e_2>) L dPg2 / sum_e P L.

    Both tend to 0 for a flat likelihood; for a sharp one at ``e``, the paper's tends to
    1 and the exact one to the noise-free response ``1 - e1^2 + e2^2``,
    ``1 + e1^2 - e2^2``.

    Parameters
    ----------
    lnL, egrid, prior, refine, block_size
        As in :func:`posterior_moments`.
    method : {"exact", "paper"}
        Which response.

    Returns
    -------
    tuple of numpy.ndarray
        ``(sens1, sens2)``, dimensionless; NaN for unusable rows.
    """
    lnL, egrid = _check_inputs(lnL, egrid, prior, method, refine)
    S, _ = _all_sums(lnL, egrid, prior, int(refine), block_size, None)
    return sensitivity_from_sums(S, method)


def shapes(
    lnL: np.ndarray,
    egrid: np.ndarray,
    prior: Prior | BinnedPrior,
    *,
    sensitivity: str = "exact",
    refine: int = DEFAULT_REFINE,
    values: np.ndarray | None = None,
    block_size: int | None = None,
) -> Table:
    """Posterior ellipticities, their covariance and shear sensitivities per galaxy.

    The Bayesian integrals (the posterior means, docs: method, eq-posterior, and
    :func:`shear_sensitivity`) are sums over
    an integration grid. With ``refine = k > 1`` that grid has cells of side ``de / k``
    and ``ln L`` is interpolated onto it (:func:`refine_lnL`: the quintic Lagrange
    interpolant of the 6 x 6 nearest cells, exact for Gaussian likelihoods and, unlike
    the cubic convolution, accurate for the non-quadratic ``ln L`` of faint galaxies), the
    prior and its gradient being evaluated analytically.
    The default ``k = 4`` (``de = 0.025`` from the paper's 0.1) is set by measurement: on
    synthetic sheared populations with likelihood widths 0.05-0.3 and the prior
    estimated from an unsheared sample, the exact response gives ``m ~ +0.004`` with
    ``k = 1``, and ``|m| <= 0.001`` with ``k = 4`` (``benchmarks/bench_shear_bias.py``).
    The cost is ~16x more integration cells (still a few ms per thousand galaxies).

    Parameters
    ----------
    lnL : numpy.ndarray
        ``(n_gal, n_e)`` natural-log likelihood on ``egrid`` (float32 allowed; each row is
        shifted by its own maximum here).
    egrid : numpy.ndarray
        ``(n_e, 2)`` grid of cell centres (:func:`pylensfit.ellipticity_grid`).
    prior : Prior or BinnedPrior
        The prior; a :class:`~pylensfit.prior.BinnedPrior` needs ``values``.
    sensitivity : {"exact", "paper"}
        The shear response (see :func:`shear_sensitivity`); ``"paper"`` is the
        paper's (docs: method, eq-partial) and reproduces the paper.
    refine : int
        Integration grid refinement factor (1: integrate on ``egrid`` itself).
    values : numpy.ndarray, optional
        ``(n_gal,)`` binning column for a ``BinnedPrior``.
    block_size : int, optional
        Galaxies per block (memory ~ ``8 * block_size * n_e * refine^2`` bytes).

    Returns
    -------
    astropy.table.Table
        Columns ``e1, e2`` (posterior means), ``e1_var, e2_var, e12_cov``, ``sens1,
        sens2`` (dimensionless) and ``flags`` (``FLAG_BAD_LIKELIHOOD``, the ``FIT_FAILED``
        bit, for rows that are all ``-inf`` or contain NaN / ``+inf``: their moments are
        NaN, their sensitivities 0). ``meta`` records the sensitivity, refinement and prior.
    """
    lnL, egrid = _check_inputs(lnL, egrid, prior, sensitivity, refine)
    S, ok = _all_sums(lnL, egrid, prior, int(refine), block_size, values)
    mom = moments_from_sums(S)
    s1, s2 = sensitivity_from_sums(S, sensitivity)
    flags = np.where(ok, 0, FLAG_BAD_LIKELIHOOD).astype(np.int32)
    t = Table()
    for k in ("e1", "e2", "e1_var", "e2_var", "e12_cov"):
        t[k] = mom[k]
    t["sens1"] = np.where(ok, s1, 0.0)
    t["sens2"] = np.where(ok, s2, 0.0)
    t["flags"] = flags
    t.meta["sensitivity"] = sensitivity
    t.meta["refine"] = int(refine)
    t.meta["flag_names"] = {str(k): v for k, v in FLAG_NAMES.items()}
    if isinstance(prior, RadialPrior):
        t.meta["prior"] = {**prior.form_dict(), "step": prior.step}
    return t


# ----------------------------------------------------------------------------------------
# The shear of a sample (docs: method, eq-key2 and eq-fixed-point)
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ShearEstimate:
    """Shear of a sample (docs: method, eq-key2 and eq-fixed-point).

    Attributes
    ----------
    g1, g2 : float
        Reduced shear estimates (dimensionless).
    g1_err, g2_err : float
        Their 1-sigma statistical errors, ``std(<e_i>) sqrt(N) / sum_a sens_i``.
    n : int
        Number of galaxies used.
    """

    g1: float
    g2: float
    g1_err: float
    g2_err: float
    n: int


def estimate_shear(
    shapes_table: Table,
    *,
    estimator: str = "fixed-point",
    prior: Prior | None = None,
    egrid: np.ndarray | None = None,
    refine: int | None = None,
    e1_col: str = "e1",
    e2_col: str = "e2",
    sens1_col: str = "sens1",
    sens2_col: str = "sens2",
    flags_col: str = "flags",
    weight_col: str = "weight",
    weighted: bool = False,
) -> ShearEstimate:
    """Shear of a sample of galaxies.

    ``estimator="fixed-point"`` (the default): :func:`shear_fixed_point`, the shear
    ``g`` at which the posterior means under the prior sheared by ``g`` average to
    ``g``, exact to all orders in ``g``; it needs the table's ``lnL`` column and the
    ellipticity prior and grid (``meta["prior"]``, ``meta["egrid"]`` and
    ``meta["refine"]`` of :func:`pylensfit.measure_stamps`' table and of
    :func:`pylensfit.measure`'s catalogue, or given here).

    ``estimator="key2"``: Kitching et al. (2008)'s estimator (their mean shear over mean
    sensitivity, section 3.3; docs: method, eq-key2: the sum of the posterior means over
    the sum of the sensitivities), high by a factor ``1 + |g|^2`` (``m ~ +8e-4`` at
    ``g = (0.02, 0.02)``); it needs only ``e1, e2, sens1, sens2``, as :func:`shapes`
    gives them.
    ``g_i = sum_a <e_i>_a / sum_a d<e_i>_a/dg_i``, with the error of paper section 4.1,
    ``sigma / sqrt(N)`` in the form ``std_a(<e_i>_a) sqrt(N) / sum_a d<e_i>_a/dg_i``.
    Rows with a nonzero flag (when the table has ``flags_col``), a zero weight (when it
    has ``weight_col``) or non-finite values are skipped.

    A catalogue of :func:`pylensfit.measure` gives its shapes in the sky frame
    (:mod:`pylensfit.skyframe`); the fixed point then works image by image in each
    image's pixel frame (its ``lnL`` grids') and returns the sky-frame shear, and
    ``"key2"`` uses the sky-frame ``e1, e2, sens1, sens2`` as they are.

    With ``weighted=True`` each galaxy counts with its ``weight_col`` value (the
    catalogue's inverse-variance weight, :func:`pylensfit.weights.lensfit_weights`):
    ``sum_a w_a (<e>_a(P_g) - g) = 0`` for the fixed point, ``sum w e / sum w sens``
    for ``"key2"``.

    Parameters
    ----------
    shapes_table : astropy.table.Table
        :func:`pylensfit.measure_stamps`' table, a catalogue of :func:`pylensfit.measure`,
        or (``"key2"``) the output of :func:`shapes`.
    estimator : {"fixed-point", "key2"}
        The estimator.
    prior, egrid, refine
        For ``"fixed-point"``: the ellipticity prior, grid and integration refinement
        (default: the table's ``meta``).
    e1_col, e2_col, sens1_col, sens2_col, flags_col, weight_col : str
        Column names.
    weighted : bool
        Weight each galaxy by its ``weight_col`` (default: every usable galaxy equally).

    Returns
    -------
    ShearEstimate

    Raises
    ------
    ValueError
        On a missing column or prior, an empty sample (no usable row), or a sum of
        sensitivities that is not positive.
    """
    if estimator not in ("fixed-point", "key2"):
        raise ValueError(f"estimator must be 'fixed-point' or 'key2', got {estimator!r}")
    if estimator == "fixed-point":
        meta = shapes_table.meta
        prior = prior if prior is not None else meta.get("prior")
        egrid = egrid if egrid is not None else meta.get("egrid")
        if "lnL" not in shapes_table.colnames or not isinstance(prior, RadialPrior) \
                or egrid is None:
            raise ValueError("the fixed-point estimator needs the table's lnL column and its "
                             "prior and egrid (measure_stamps' table, a measure catalogue, or "
                             "prior= and egrid=); for shapes()' output use estimator='key2'")
        lnL = np.asarray(shapes_table["lnL"], dtype=float)
        use = np.ones(len(shapes_table), dtype=bool)
        if flags_col in shapes_table.colnames:
            use &= np.asarray(shapes_table[flags_col]) == 0
        if weight_col in shapes_table.colnames:
            use &= np.asarray(shapes_table[weight_col], dtype=float) > 0
        if not use.any():
            raise ValueError("empty sample: no usable (unflagged, weighted) row to estimate "
                             "shear")  # fmt: skip
        ref = int(refine if refine is not None else meta.get("refine", DEFAULT_REFINE))
        w = _weights(shapes_table, weight_col, weighted)
        frame, groups = table_frame(shapes_table)
        return shear_fixed_point(
            lnL[use], np.asarray(egrid, dtype=float), prior, refine=ref,
            weights=None if w is None else w[use],
            frame=None if frame is None else _rows_frame(frame, use),
            groups=None if groups is None else groups[use])  # fmt: skip
    for c in (e1_col, e2_col, sens1_col, sens2_col):
        if c not in shapes_table.colnames:
            raise ValueError(f"the table has no column {c!r}")
    e1 = np.asarray(shapes_table[e1_col], dtype=float)
    e2 = np.asarray(shapes_table[e2_col], dtype=float)
    s1 = np.asarray(shapes_table[sens1_col], dtype=float)
    s2 = np.asarray(shapes_table[sens2_col], dtype=float)
    use = np.isfinite(e1) & np.isfinite(e2) & np.isfinite(s1) & np.isfinite(s2)
    if flags_col in shapes_table.colnames:
        use &= np.asarray(shapes_table[flags_col]) == 0
    if weight_col in shapes_table.colnames:
        use &= np.asarray(shapes_table[weight_col], dtype=float) > 0
    w = _weights(shapes_table, weight_col, weighted)
    if w is not None:
        use &= np.isfinite(w) & (w > 0)
    n = int(np.count_nonzero(use))
    if n == 0:
        raise ValueError("empty sample: no usable (unflagged, finite) row to estimate shear")
    out = []
    for e, s, name in ((e1[use], s1[use], "sens1"), (e2[use], s2[use], "sens2")):
        if w is not None:
            wu = w[use]
            ssum = float(np.sum(wu * s))
            if not ssum > 0:
                raise ValueError(f"the weighted sum of the sensitivities ({name}) is not "
                                 f"positive: {ssum}")  # fmt: skip
            g = float(np.sum(wu * e)) / ssum
            err = float(np.sqrt(np.sum(wu**2 * (e - g * s) ** 2))) / ssum if n > 1 else math.nan
            out.append((g, err))
            continue
        ssum = float(np.sum(s))
        if not ssum > 0:
            raise ValueError(f"the sum of the sensitivities ({name}) is not positive: {ssum}")
        g = float(np.sum(e)) / ssum
        err = float(np.std(e, ddof=1)) * math.sqrt(n) / ssum if n > 1 else math.nan
        out.append((g, err))
    return ShearEstimate(g1=out[0][0], g2=out[1][0], g1_err=out[0][1], g2_err=out[1][1], n=n)


def _weights(table: Table, col: str, weighted: bool) -> np.ndarray | None:
    if not weighted:
        return None
    if col not in table.colnames:
        raise ValueError(f"weighted=True needs the table's {col!r} column")
    return np.asarray(table[col], dtype=float)


def table_frame(table: Table) -> tuple[SkyFrame | None, np.ndarray | None]:
    """The sky frame of each row of a catalogue and the rows' images (``image_index``),
    or ``(None, None)`` for a table in the pixel frame (no frame columns, or the pixel
    frame everywhere)."""
    need = ("sky_angle", "sky_flip", "wcs_g1", "wcs_g2", "image_index")
    if not all(c in table.colnames for c in need):
        return None, None
    fr = frame_of_table(table)
    if fr.is_identity():
        return None, None
    return fr, np.asarray(table["image_index"])


def _rows_frame(frame: SkyFrame, sel: np.ndarray) -> SkyFrame:
    return SkyFrame(angle=frame.angle[sel], flip=frame.flip[sel], g1=frame.g1[sel],
                    g2=frame.g2[sel], has_wcs=frame.has_wcs[sel])  # fmt: skip


def shear_table(
    shapes_table: Table,
    *,
    by: str | None = None,
    column: str | None = None,
    edges: Sequence[float] | None = None,
    estimator: str = "fixed-point",
    prior: Prior | None = None,
    egrid: np.ndarray | None = None,
    refine: int | None = None,
    weighted: bool = False,
) -> Table:
    """Shear of every group of a catalogue, with errors (:func:`estimate_shear` per group).

    Parameters
    ----------
    shapes_table : astropy.table.Table
        A table with ``e1, e2, sens1, sens2`` and, optionally, ``flags`` (the output of
        :func:`shapes` or :func:`pylensfit.measure`).
    by : str, optional
        Column whose distinct values define the groups (e.g. ``"image"``).
    column, edges : str and sequence of float, optional
        Bin the rows by ``column`` with bin ``edges`` (e.g. magnitude bins); rows
        outside the edges are left out of the binned rows.

    estimator : {"fixed-point", "key2"}
        ``"fixed-point"`` (default): :func:`shear_fixed_point` on its ``lnL`` column (a
        2-D column of ln L grids, as in :func:`pylensfit.measure`'s catalogue) with
        ``prior`` and ``egrid``, rows with ``flags != 0`` (or ``weight == 0``) left out;
        ``"key2"``: :func:`estimate_shear` with ``estimator="key2"`` on the table's ``e1,
        e2, sens1, sens2``.
    prior, egrid, refine
        For ``"fixed-point"`` (default: the table's ``meta``).
    weighted : bool
        Weight the galaxies by the ``weight`` column (:func:`estimate_shear`).

    Returns
    -------
    astropy.table.Table
        One row per group (then per bin) and a last row ``all``: ``group``, ``n``,
        ``g1, g1_err, g2, g2_err``. A group with no usable row has ``n = 0`` and NaN.
    """
    keys: list[tuple[str, np.ndarray]] = []
    n = len(shapes_table)
    if by is not None:
        if by not in shapes_table.colnames:
            raise ValueError(f"the table has no column {by!r} to group by")
        vals = np.asarray(shapes_table[by])
        for v in np.unique(vals):
            keys.append((f"{by}={v}", vals == v))
    if column is not None:
        if column not in shapes_table.colnames:
            raise ValueError(f"the table has no column {column!r} to bin by")
        try:
            e = np.asarray(edges, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"bin edges must be numbers, got {edges!r}") from None
        if e.ndim != 1 or e.size < 2 or not np.all(np.isfinite(e)) or np.any(np.diff(e) <= 0):
            raise ValueError(f"bin edges must be at least two finite increasing numbers, got "
                             f"{e.tolist()}")  # fmt: skip
        v = np.asarray(shapes_table[column])
        if v.ndim != 1:
            raise ValueError(f"column {column!r} holds arrays of shape {v.shape[1:]}, not one "
                             "number per row: cannot bin by it")  # fmt: skip
        if not (np.issubdtype(v.dtype, np.number) or np.issubdtype(v.dtype, np.bool_)):
            raise ValueError(f"column {column!r} is not numeric ({v.dtype}): cannot bin by it")
        v = v.astype(float)
        for lo, hi in zip(e[:-1], e[1:], strict=True):
            keys.append((f"{lo:g}<={column}<{hi:g}", (v >= lo) & (v < hi)))
    keys.append(("all", np.ones(n, dtype=bool)))
    if estimator not in ("key2", "fixed-point"):
        raise ValueError(f"estimator must be 'key2' or 'fixed-point', got {estimator!r}")
    if estimator == "fixed-point":
        prior = prior if prior is not None else shapes_table.meta.get("prior")
        egrid = egrid if egrid is not None else shapes_table.meta.get("egrid")
        refine = int(refine if refine is not None
                     else shapes_table.meta.get("refine", DEFAULT_REFINE))  # fmt: skip
        if (not isinstance(prior, RadialPrior) or egrid is None
                or "lnL" not in shapes_table.colnames):
            raise ValueError("the fixed-point estimator needs the table's lnL column, "
                             "prior= and egrid= (or estimator='key2')")  # fmt: skip
        lnL = np.asarray(shapes_table["lnL"])
        usable = np.ones(n, dtype=bool)
        if "flags" in shapes_table.colnames:
            usable = np.asarray(shapes_table["flags"]) == 0
        if "weight" in shapes_table.colnames:
            usable &= np.asarray(shapes_table["weight"], dtype=float) > 0
        w = _weights(shapes_table, "weight", weighted)
        frame, groups = table_frame(shapes_table)
    rows = []
    for name, sel in keys:
        try:
            if estimator == "fixed-point":
                u = sel & usable
                g = shear_fixed_point(
                    lnL[u], egrid, prior, refine=refine, weights=None if w is None else w[u],
                    frame=None if frame is None else _rows_frame(frame, u),
                    groups=None if groups is None else groups[u])  # fmt: skip
            else:
                g = estimate_shear(shapes_table[sel], estimator="key2", weighted=weighted)
            rows.append((name, g.n, g.g1, g.g1_err, g.g2, g.g2_err))
        except ValueError:
            rows.append((name, 0, np.nan, np.nan, np.nan, np.nan))
    return Table(rows=rows, names=("group", "n", "g1", "g1_err", "g2", "g2_err"))


def sheared_prior_columns(
    prior: Prior, grid: np.ndarray, g: np.ndarray, h: float = 1e-3
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``P_g`` on ``grid`` and its derivatives ``dP_g/dg_j`` (central differences).

    ``P_g(e) = P(e_s) |de_s/de|^2`` with ``e_s = (e - g)/(1 - g* e)``: the density of the
    population ``P`` after the reduced shear ``g`` (paper section 2.1); at ``g = 0`` its
    derivative is the exact sensitivity's ``dP_g/dg`` (docs: method, eq-sensitivity-exact).

    Parameters
    ----------
    prior : Prior
        The unsheared population density ``P``.
    grid : numpy.ndarray
        ``(n_e, 2)`` integration grid (:func:`refined_grid`).
    g : numpy.ndarray
        ``(g1, g2)``, the reduced shear.
    h : float
        Step of the central differences in ``g``.

    Returns
    -------
    P_g, dP_g1, dP_g2 : numpy.ndarray
        ``(n_e,)`` each: the sheared density and its derivatives with respect to
        ``g1`` and ``g2``.
    """
    e = grid[:, 0] + 1j * grid[:, 1]

    def dens(gc: complex) -> np.ndarray:
        den = 1.0 - np.conj(gc) * e
        es = (e - gc) / den
        jac = (1.0 - abs(gc) ** 2) ** 2 / np.abs(den) ** 4
        return prior.pdf(es.real, es.imag) * jac

    gc = complex(g[0], g[1])
    d1 = (dens(gc + h) - dens(gc - h)) / (2 * h)
    d2 = (dens(gc + 1j * h) - dens(gc - 1j * h)) / (2 * h)
    return dens(gc), d1, d2


def _fixed_point_terms(lnL, egrid, prior, grid, g, refine, block_size, w):
    """Posterior means ``(n, 2)`` under the prior sheared by ``g`` and the weighted sum
    of their Jacobians ``d<e_i>/dg_j`` (``(2, 2)``)."""
    P, d1, d2 = sheared_prior_columns(prior, grid, g)
    e1, e2 = grid[:, 0], grid[:, 1]
    K = np.column_stack([P, e1 * P, e2 * P, d1, e1 * d1, e2 * d1, d2, e1 * d2, e2 * d2])
    S = sums_with(lnL, egrid, K, refine, block_size)
    s0 = S[:, 0]
    m1, m2 = S[:, 1] / s0, S[:, 2] / s0
    # d<e_i>/dg_j = sum (e_i - <e_i>) L dP_g/dg_j / sum P_g L
    terms = ((S[:, 4] - m1 * S[:, 3]) / s0, (S[:, 7] - m1 * S[:, 6]) / s0,
             (S[:, 5] - m2 * S[:, 3]) / s0, (S[:, 8] - m2 * S[:, 6]) / s0)  # fmt: skip
    if w is None:
        jac = np.array([[np.sum(terms[0]), np.sum(terms[1])],
                        [np.sum(terms[2]), np.sum(terms[3])]])  # fmt: skip
    else:
        jac = np.array([[w @ terms[0], w @ terms[1]], [w @ terms[2], w @ terms[3]]])
    return np.column_stack([m1, m2]), jac


def _group_frames(frame, groups: np.ndarray):
    """One :class:`~pylensfit.skyframe.SkyFrame` per group (its rows' median rotation and
    mean distortion; the flip of its first row), and the group index of each row."""
    keys, inv = np.unique(np.asarray(groups), return_inverse=True)
    k = keys.size
    ang, g1, g2 = np.zeros(k), np.zeros(k), np.zeros(k)
    flip = np.zeros(k, dtype=bool)
    for i in range(k):  # one entry per image, not per galaxy
        sel = inv == i
        ang[i] = np.median(np.asarray(frame.angle)[sel])
        flip[i] = bool(np.asarray(frame.flip)[sel][0])
        g1[i] = np.mean(np.asarray(frame.g1)[sel])
        g2[i] = np.mean(np.asarray(frame.g2)[sel])
    return SkyFrame(angle=ang, flip=flip, g1=g1, g2=g2, has_wcs=np.ones(k, bool)), inv


def shear_fixed_point(
    lnL: np.ndarray,
    egrid: np.ndarray,
    prior: Prior,
    *,
    refine: int = DEFAULT_REFINE,
    n_iter: int = 4,
    block_size: int | None = None,
    weights: np.ndarray | None = None,
    frame=None,
    groups: np.ndarray | None = None,
) -> ShearEstimate:
    """Shear of a sample as the fixed point ``sum_a <e>_a(P_g) = N g`` (all orders in g).

    The paper's mean shear over mean sensitivity (Kitching et al. 2008, arXiv:0802.1528,
    section 3.3; docs: method, eq-key2) divides by sensitivities computed at ``g = 0``
    on data that are sheared; for a noise-free ring ``<e> = g`` and ``<e^2> = g^2``
    exactly, so the summed exact sensitivity is ``N (1 - |g|^2)`` and the estimate is
    high by a factor ``1 + |g|^2`` (``m ~ +0.006`` at ``g = 0.1`` for likelihood widths
    0.05-0.1). Here the prior itself is sheared: with ``P_g`` the density of the
    population ``P`` after a shear ``g``, the posterior mean under the true population
    averages to the population mean ``g`` exactly, so ``g`` solves
    ``f(g) = sum_a <e>_a(P_g) - N g = 0``, found by Newton steps from ``g = 0`` with the
    Jacobian ``sum_a d<e>_a/dg - N`` (the prior's share of the exact response; the first
    step is eq-key2 with the data part of the sensitivity replaced by its expectation,
    1).

    With ``weights`` ``w_a`` it solves ``sum_a w_a (<e>_a(P_g) - g) = 0``. With a sky
    ``frame`` per row and the ``groups`` (images) that share a pixel frame, ``g`` is the
    sky-frame shear: each group's prior is sheared by ``g`` taken to its pixel frame
    (:func:`pylensfit.skyframe.shear_to_pixel`) and its posterior means are taken to the
    sky frame (:func:`pylensfit.skyframe.to_sky`) before they are summed.

    Parameters
    ----------
    lnL, egrid, prior, refine, block_size
        As in :func:`shapes` (rows that are unusable are skipped).
    n_iter : int
        Newton steps (3 reach 1e-7 in g).
    weights : numpy.ndarray, optional
        ``(n_gal,)`` per-galaxy weights (rows of weight 0 are skipped; default 1).
    frame : pylensfit.skyframe.SkyFrame, optional
        The sky frame of each row (default: the pixel frame).
    groups : numpy.ndarray, optional
        ``(n_gal,)`` labels of the rows that share a pixel frame (e.g. the catalogue's
        ``image_index``); needed with ``frame``.

    Returns
    -------
    ShearEstimate
        ``g1, g2`` and their errors, ``std_a(<e_i>_a) sqrt(N) / |sum_a d<e_i>/dg_i - N|``
        (weighted: ``sqrt(sum_a w_a^2 (<e_i>_a - g_i)^2) / |sum_a w_a (d<e_i>/dg_i - 1)|``).
    """
    lnL, egrid = _check_inputs(lnL, egrid, prior, refine=refine)
    ok = usable_rows(lnL)
    w = None
    if weights is not None:
        w = np.asarray(weights, dtype=float)
        if w.shape != (lnL.shape[0],):
            raise ValueError(f"weights must have shape ({lnL.shape[0]},), got {w.shape}")
        ok &= np.isfinite(w) & (w > 0)
    n = int(ok.sum())
    if n == 0:
        raise ValueError("empty sample: no usable likelihood row to estimate shear")
    lnL = lnL[ok]
    w = None if w is None else w[ok]
    refine = int(refine)
    grid = refined_grid(egrid, refine)
    if frame is not None and frame.is_identity():
        frame = None
    if frame is not None:
        if groups is None:
            raise ValueError("a sky frame needs the groups (images) that share a pixel frame")
        gf, inv = _group_frames(frame, np.asarray(groups)[ok])
        M = spin2_matrix(gf)
        row_frame = _rows_frame(gf, inv)  # each row with its group's frame
    wsum = float(n if w is None else w.sum())
    g = np.zeros(2)
    for _ in range(n_iter):
        if frame is None:
            m, jac = _fixed_point_terms(lnL, egrid, prior, grid, g, refine, block_size, w)
        else:
            m, jac = np.empty((n, 2)), np.zeros((2, 2))
            gp1, gp2 = shear_to_pixel(np.full(gf.n, g[0]), np.full(gf.n, g[1]), gf)
            for k in range(gf.n):  # one prior per image (pixel frame)
                sel = inv == k
                if not sel.any():
                    continue
                mk, jk = _fixed_point_terms(lnL[sel], egrid, prior, grid,
                                            np.array([gp1[k], gp2[k]]), refine, block_size,
                                            None if w is None else w[sel])  # fmt: skip
                m[sel, 0], m[sel, 1] = to_sky(mk[:, 0], mk[:, 1], _rows_frame(row_frame, sel))
                jac += M[k] @ jk @ M[k].T
        jac = jac - wsum * np.eye(2)
        f = (np.array([m[:, 0].sum(), m[:, 1].sum()]) if w is None else w @ m) - wsum * g
        g = g - np.linalg.solve(jac, f)
    if w is None:
        err = [float(np.std(m[:, i], ddof=1)) * math.sqrt(n) / abs(jac[i, i]) if n > 1
               else math.nan for i in range(2)]  # fmt: skip
    else:
        err = [float(np.sqrt(np.sum(w**2 * (m[:, i] - g[i]) ** 2))) / abs(jac[i, i]) if n > 1
               else math.nan for i in range(2)]  # fmt: skip
    return ShearEstimate(g1=float(g[0]), g2=float(g[1]), g1_err=err[0], g2_err=err[1], n=n)


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
            _fine_sums_kernel(X, r.excess(X), r.m, r.j0, r.w, r.row_y, r.row_lo, r.row_hi, K,
                              S[i : i + nb])  # fmt: skip
    return S
