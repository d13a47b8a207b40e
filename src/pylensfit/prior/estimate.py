"""The ellipticity prior estimated from stored likelihood grids, whole or per bin.

:func:`estimate_prior` maximises the marginal likelihood of the sample,
``l = sum_a w_a ln sum_e P(e) L_a(e) de^2`` (``P`` normalised on the grid), for either
form: the functional :class:`~pylensfit.prior.functional.Prior`
(:func:`pylensfit.prior.fit.estimate_functional`, the paper's EM iteration or a direct
maximisation) or the :class:`~pylensfit.prior.spline.SplinePrior`
(:func:`pylensfit.prior.spline.estimate_spline`).

How the methods compare, their convergence and their memory: :mod:`pylensfit.prior`.

:func:`estimate_prior_binned` estimates one prior per bin of a catalogue column
(:class:`BinnedPrior`), from the same stored grids.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._util import check_egrid, check_lnL
from .fit import estimate_functional
from .functional import Prior
from .radial import RadialPrior
from .sample import prepare_sample, usable_rows
from .spline import SPLINE_SMOOTHING, estimate_spline

log = logging.getLogger(__name__)


def estimate_prior(
    lnL: np.ndarray,
    egrid: np.ndarray,
    *,
    method: str = "direct",
    n_iter: int | None = None,
    start: tuple[float, float, float] | None = None,
    weights: np.ndarray | None = None,
    tol: float = 1e-12,
    form: str = "functional",
    smoothing: float = SPLINE_SMOOTHING,
) -> RadialPrior:
    """Estimate the ellipticity prior from stored likelihood grids.

    Both methods maximise the marginal likelihood of the sample,
    ``l(B, C, D) = sum_a w_a ln sum_e P(e) L_a(e) de^2`` (``P`` normalised on the grid),
    under the bounds of :func:`prior_is_valid`:

    - ``"em"``: the paper's iteration (section 3):
      ``P_{i+1}(e) = (1/N) sum_a P_i(e) L_a(e) / sum_e P_i L_a`` (the summed, individually
      normalised posteriors), followed by a minimum cross-entropy fit of the functional
      form (:func:`fit_functional_prior`): the EM algorithm for ``(B, C, D)``.
    - ``"direct"`` (default): maximise ``l`` over ``(ln B, ln C, ln D)`` with scipy's SLSQP
      and the analytic gradient, the same fixed point in one go (EM creeps towards it
      when the likelihoods are broad; :mod:`pylensfit.prior` compares the two).

    The recovered prior is limited by sampling noise: with likelihood widths 0.1-0.3 its
    fractional residual rms (where ``P`` exceeds 5% of its peak) is ~0.01-0.035 from
    30,000 galaxies and ~0.04 from 3,000. With ``form="spline"`` the prior is a
    :class:`SplinePrior`, whose eight coefficients ``c`` maximise
    ``l(c) - (smoothing / 2) |D c|^2`` (``D`` their second differences) by L-BFGS with
    the analytic gradient; it has no bound to end on, and ``method`` must be ``"direct"``.

    Parameters
    ----------
    lnL : numpy.ndarray
        ``(n_gal, n_e)`` natural-log likelihood on ``egrid`` (float32 allowed), each row
        shifted by its own maximum here. Rows that contain NaN or ``+inf``, or are all
        ``-inf``, are excluded (counted in ``prior.info["n_excluded"]``, no warning).
    egrid : numpy.ndarray
        ``(n_e, 2)`` grid of cell centres (:func:`pylensfit.ellipticity_grid`).
    method : {"direct", "em"}
        Estimation method.
    n_iter : int, optional
        EM: maximum number of iterations (default 10, the paper's); direct: maximum
        number of optimiser iterations (default 200).
    start : tuple of float, optional
        Starting ``(B, C, D)`` (default the STEP-like 0.19, 0.58, 2.4), or the spline's
        coefficients.
    weights : numpy.ndarray, optional
        ``(n_gal,)`` non-negative per-galaxy weights ``w_a`` (default 1).
    tol : float
        Stop when ``l`` per unit weight changes by less than this between steps (EM) or
        as the optimiser's ``ftol`` (direct).
    form : {"functional", "spline"}
        The prior's form: :class:`Prior` (eq-funcprior) or :class:`SplinePrior`.
    smoothing : float
        ``form="spline"``: weight of the roughness penalty (dimensionless, per sample).

    Returns
    -------
    Prior or SplinePrior
        Normalised on ``egrid``; ``history`` has the parameters and ``marginal_lnL`` at
        every step, ``info`` has ``n_used``, ``n_excluded``, ``at_bound`` (a warning is
        logged when the fit ends on a bound), ``converged`` and ``n_steps``.

    Raises
    ------
    ValueError
        On grids of the wrong shape, an empty sample, or no usable row.
    """
    _check_choices(method, form)
    sample = prepare_sample(lnL, egrid, weights)
    if form == "spline":
        return estimate_spline(sample, start=start, n_iter=n_iter, tol=tol, smoothing=smoothing)
    return estimate_functional(sample, method=method, n_iter=n_iter, start=start, tol=tol)


def _check_choices(method: str, form: str) -> None:
    """:func:`estimate_prior`'s ``method`` and ``form``, checked."""
    if method not in ("direct", "em"):
        raise ValueError(f"method must be 'direct' or 'em', got {method!r}")
    if form not in ("functional", "spline"):
        raise ValueError(f"form must be 'functional' or 'spline', got {form!r}")
    if form == "spline" and method != "direct":
        raise ValueError("the spline prior is estimated by method 'direct' only")


# ----------------------------------------------------------------------------------------
# A prior per bin of a catalogue column
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BinnedPrior:
    """Priors estimated in bins of a catalogue column (magnitude, size, ...).

    Attributes
    ----------
    edges : numpy.ndarray
        ``(n_bins + 1,)`` increasing bin edges; bin ``i`` is ``edges[i] <= v < edges[i+1]``
        (the last bin includes its upper edge).
    priors : tuple of Prior
        One prior per bin (the parent prior where the bin fell back).
    counts : numpy.ndarray
        Number of usable galaxies per bin.
    fallback : numpy.ndarray
        ``True`` where the bin had fewer than ``min_count`` usable galaxies and uses the
        parent prior.
    parent : Prior
        The prior of all usable galaxies (also used for values outside the edges or NaN).
    min_count : int
        The minimum count that was required.
    """

    edges: np.ndarray
    priors: tuple[Prior, ...]
    counts: np.ndarray
    fallback: np.ndarray
    parent: Prior
    min_count: int
    notes: tuple[str, ...] = field(default=())

    def bin_index(self, values: np.ndarray) -> np.ndarray:
        """Bin of each value (``-1`` outside the edges or NaN)."""
        return _bin_index(np.asarray(values, dtype=float), self.edges)

    def prior_for_bin(self, i: int) -> Prior:
        """The prior of bin ``i`` (the parent for ``i = -1``)."""
        return self.parent if i < 0 else self.priors[i]


def _bin_index(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    idx = np.searchsorted(edges, values, side="right") - 1
    idx[values == edges[-1]] = edges.size - 2
    idx[(idx < 0) | (idx >= edges.size - 1) | ~np.isfinite(values)] = -1
    return idx


def estimate_prior_binned(
    lnL: np.ndarray,
    egrid: np.ndarray,
    values: np.ndarray,
    edges: Sequence[float] | np.ndarray,
    *,
    min_count: int = 1000,
    **kwargs: Any,
) -> BinnedPrior:
    """Estimate one prior per bin of a catalogue column (paper section 4.2).

    The stored likelihood grids are reused, so a prior per bin costs no refit of the
    images. A bin with fewer than ``min_count`` usable galaxies falls back to the parent
    prior (estimated from all usable galaxies); this is logged as a warning and recorded
    in ``fallback`` and ``notes``. The default ``min_count = 1000`` follows the measured
    growth of the prior's residual below a few thousand galaxies at likelihood widths
    0.1-0.3 (see the package's prior tests); the paper's own limit was ~300 for STEP1.

    Parameters
    ----------
    lnL : numpy.ndarray
        ``(n_gal, n_e)`` log-likelihood grids.
    egrid : numpy.ndarray
        ``(n_e, 2)`` grid.
    values : numpy.ndarray
        ``(n_gal,)`` values of the binning column (any unit).
    edges : sequence of float
        Increasing bin edges, in the unit of ``values``.
    min_count : int
        Minimum number of usable galaxies for a bin to get its own prior.
    **kwargs
        Passed to :func:`estimate_prior` (``method``, ``n_iter``, ``start``, ``weights``,
        ``tol``).

    Returns
    -------
    BinnedPrior
    """
    egrid = check_egrid(egrid)
    lnL = check_lnL(lnL, egrid)
    values = np.asarray(values, dtype=float)
    if values.shape != (lnL.shape[0],):
        raise ValueError(f"values must have shape ({lnL.shape[0]},), got {values.shape}")
    edges = np.asarray(edges, dtype=float)
    if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
        raise ValueError("edges must be a 1-D increasing sequence of at least two values")
    weights = kwargs.pop("weights", None)
    parent = estimate_prior(lnL, egrid, weights=weights, **kwargs)
    ok = usable_rows(lnL)
    if weights is not None:
        ok &= np.asarray(weights, dtype=float) > 0
    idx = _bin_index(values, edges)
    nb = edges.size - 1
    counts = np.array([np.count_nonzero(ok & (idx == i)) for i in range(nb)])
    priors: list[Prior] = []
    fallback = np.zeros(nb, dtype=bool)
    notes: list[str] = []
    for i in range(nb):
        if counts[i] < min_count:
            fallback[i] = True
            msg = (
                f"bin {i} [{edges[i]:g}, {edges[i + 1]:g}) has {counts[i]} usable galaxies "
                f"(< min_count={min_count}): using the parent prior"
            )
            log.warning(msg)
            notes.append(msg)
            priors.append(parent)
            continue
        sel = idx == i
        w = None if weights is None else np.asarray(weights, dtype=float)[sel]
        priors.append(estimate_prior(lnL[sel], egrid, weights=w, **kwargs))
    return BinnedPrior(
        edges=edges,
        priors=tuple(priors),
        counts=counts,
        fallback=fallback,
        parent=parent,
        min_count=int(min_count),
        notes=tuple(notes),
    )


# ----------------------------------------------------------------------------------------
# The size prior
