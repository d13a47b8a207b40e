"""Per-galaxy posterior moments and shear sensitivities, and the table of shapes.

For each galaxy ``a`` with a log-likelihood grid ``ln L_a(e)`` and a prior ``P(e)``,
the posterior means, variances and covariance of ``e`` (:func:`posterior_moments`) and
the shear sensitivities ``d<e_i>_a / dg_i`` (:func:`shear_sensitivity`) are read from the
posterior sums of :func:`pylensfit.shear.sums.kernel_columns` (:func:`all_sums`);
:func:`shapes` gives them all as a table.
"""

from __future__ import annotations

import numpy as np
from astropy.table import Table

from .._util import check_egrid, check_lnL
from ..flags import flag_value
from ..grid import DEFAULT_REFINE, refined_grid
from ..prior import BinnedPrior, Prior, RadialPrior, usable_rows
from .sums import kernel_columns, sums_with

#: Flag bit of an unusable likelihood row (:data:`pylensfit.shear.FLAG_BAD_LIKELIHOOD`).
FLAG_BAD_LIKELIHOOD = flag_value("FIT_FAILED")
#: Name table of the flag bits of :func:`shapes` (:data:`pylensfit.shear.FLAG_NAMES`).
FLAG_NAMES = {FLAG_BAD_LIKELIHOOD: "FIT_FAILED"}
#: The shear sensitivities (:func:`shear_sensitivity`).
_SENS_METHODS = ("exact", "paper")


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


def check_inputs(lnL, egrid, prior, sensitivity: str = "exact",
                 refine: int = 1) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """``lnL`` and ``egrid`` checked (:func:`pylensfit._util.check_lnL`), with the prior's
    kind, the sensitivity's name and the refinement factor."""
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


def all_sums(lnL: np.ndarray, egrid: np.ndarray, prior: RadialPrior | BinnedPrior,
             refine: int, block_size: int | None,
             values: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The ``(n_gal, 14)`` posterior sums of :func:`~pylensfit.shear.sums.kernel_columns`
    for every row (NaN for unusable rows; a :class:`~pylensfit.prior.BinnedPrior` takes
    each row's prior by its ``values``) and the ``(n_gal,)`` usable mask."""
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
    lnL, egrid = check_inputs(lnL, egrid, prior, refine=refine)
    S, _ = all_sums(lnL, egrid, prior, int(refine), block_size, None)
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
    lnL, egrid = check_inputs(lnL, egrid, prior, method, refine)
    S, _ = all_sums(lnL, egrid, prior, int(refine), block_size, None)
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
    lnL, egrid = check_inputs(lnL, egrid, prior, sensitivity, refine)
    S, ok = all_sums(lnL, egrid, prior, int(refine), block_size, values)
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
