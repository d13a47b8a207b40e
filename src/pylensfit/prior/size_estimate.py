"""The size prior estimated from the data: smoothed EM on a grid in ``ln h``.

:func:`estimate_size_prior` estimates a :class:`~pylensfit.prior.size.SizePrior` by
maximum marginal likelihood of the galaxies' likelihoods in size (EMS, a smoothed EM);
:func:`select_size_prior_smoothing` chooses its smoothing by cross-validation.
"""

from __future__ import annotations

import logging

import numpy as np

from .size import SizePrior, node_basis, node_sizes

log = logging.getLogger(__name__)


def size_likelihood_rows(lnL_r: np.ndarray) -> np.ndarray:
    """Rows of ``lnL_r`` that enter :func:`estimate_size_prior`: no NaN and some finite
    size. ``-inf`` is a size whose likelihood underflows against the galaxy's best (or a
    size not evaluated), zero likelihood, not a failed fit: a row finite at every size
    would leave out the galaxies whose ``L(r)`` rules some sizes out, the better
    measured ones."""
    L = np.asarray(lnL_r)
    return ~np.isnan(L).any(axis=1) & np.isfinite(L.max(axis=1))


def estimate_size_prior(
    lnL_r: np.ndarray,
    bank,
    config,
    *,
    bulge_weights: np.ndarray | None = None,
    knot_step: float = 0.1,
    n_iter: int | None = None,
    smooth: float | str | None = None,
    per_run: bool | None = None,
) -> SizePrior:
    """The size prior by maximum marginal likelihood, smoothed EM on a ln(h) grid.

    Galaxy ``a``'s evidence under the prior is ``Z_a = sum_j pi_k(j) w_j p(ln h_j) / r_j
    L_a(r_j) + s L_a(star)``, linear in the knot values of ``p`` and in ``s``: a mixture
    whose weights EM estimates, each step followed by a light smoothing of the density
    between neighbouring knots (EMS, Silverman et al. 1990) so that the deconvolved
    distribution does not break into spikes where the likelihoods are broad.

    Parameters
    ----------
    lnL_r : numpy.ndarray
        ``(n, n_r + 1)`` per-size likelihoods of the sample (``StampFits.lnL_r``, flat
        size prior), rows with NaN ignored.
    bank, config :
        The model bank and configuration of the fits.
    bulge_weights : numpy.ndarray, optional
        Prior of the bulge fractions (uniform by default).
    knot_step : float
        Knot spacing in ``ln h``.
    n_iter : int, optional
        EM steps (default ``max(500, 100 / smooth)``: the less smoothing, the slower EM
        converges).
    smooth : float or "cv", optional
        Weight moved to each neighbouring knot in a smoothing step, or ``"cv"``: the
        one :func:`select_size_prior_smoothing` chooses from this sample (default
        ``"cv"`` with ``config.size_prior_smoothing_cv``, else
        ``config.size_prior_smoothing``).
    per_run : bool, optional
        One density per run of the model family (bulge fraction), estimated jointly: the
        prior of (run, size), of which the density conditional on each run is kept
        (default ``config.size_prior_per_run``). The factorised prior gives every run
        the same distribution of half-light radii; in a population whose kinds differ in
        size (knotty discs smaller than bulges), a fraction's sizes are not the others'.
        The joint estimate's run shares are not kept: ``bulge_weights`` are what mixes
        the runs in the fits; here they only start EM.

    Returns
    -------
    SizePrior
    """
    if smooth is None:
        smooth = ("cv" if getattr(config, "size_prior_smoothing_cv", False)
                  else float(getattr(config, "size_prior_smoothing", 0.25)))  # fmt: skip
    if per_run is None:
        per_run = bool(getattr(config, "size_prior_per_run", False))
    if isinstance(smooth, str) and smooth != "cv":
        raise ValueError(f"smooth must be a number or 'cv', got {smooth!r}")
    comp, knots, n_blk, w0 = size_mixture(lnL_r, bank, config, bulge_weights, knot_step,
                                           per_run)  # fmt: skip
    if smooth == "cv":
        smooth, score = _cross_validate(comp, n_blk, w0, SIZE_PRIOR_SMOOTHINGS, 5, 0)
        log.info("size prior smoothing %g chosen by cross-validation (held-out ln Z "
                 "relative to it: %s)", smooth, np.round(score, 1).tolist())  # fmt: skip
    smooth = float(smooth)
    if n_iter is None:
        n_iter = _ems_steps(smooth)
    K = knots.size
    w = _ems(comp, w0, n_blk, np.array([smooth]), np.array([n_iter]))[:, 0]
    star = float(w[-1])
    if not per_run:
        return SizePrior(ln_h=knots, density=w[:K] / knot_step, star=star, smoothing=smooth)
    dens = w[:-1].reshape(n_blk, K)
    mass = dens.sum(axis=1, keepdims=True)
    # a run EM has emptied to underflow takes the others' shape (its weight is ~0 anyway)
    dens = np.where(mass > 1e-250, dens / np.maximum(mass, 1e-300), dens.sum(axis=0) / mass.sum())
    dens = dens * (1.0 - star) / knot_step
    return SizePrior(ln_h=knots, density=dens, star=star, smoothing=smooth)


#: the smoothings :func:`select_size_prior_smoothing` chooses among
SIZE_PRIOR_SMOOTHINGS = (0.02, 0.05, 0.1, 0.25)


def select_size_prior_smoothing(
    lnL_r: np.ndarray,
    bank,
    config,
    *,
    candidates: tuple[float, ...] = SIZE_PRIOR_SMOOTHINGS,
    folds: int = 5,
    bulge_weights: np.ndarray | None = None,
    knot_step: float = 0.1,
    per_run: bool | None = None,
    seed: int = 0,
) -> tuple[float, np.ndarray]:
    """The size prior's smoothing that predicts held-out galaxies best.

    :func:`estimate_size_prior`'s EMS smoothing is a regularisation whose strength does
    not fall as the sample grows: each EM step is followed by the same smoothing, so the
    estimate stays softer than the population however many galaxies there are (the edges
    of a box in size come out rounded, and ``m`` moves with them:
    ``benchmarks/studies/precision_ab.py --b size_prior_smoothing=0.02``). This chooses
    it from the data: the sample is cut into ``folds`` groups at random (``seed``); for
    each candidate, the prior estimated from all groups but one gives the held-out
    group's galaxies their evidence ``Z_a``, and the candidate whose held-out
    ``sum_a ln Z_a`` over the groups is largest is returned. Every fit of every fold and
    candidate shares the passes over the likelihoods (:func:`_ems`).

    Parameters
    ----------
    lnL_r, bank, config, bulge_weights, knot_step, per_run :
        As :func:`estimate_size_prior`.
    candidates : tuple of float
        Smoothings to choose among, each in ``(0, 0.5)``.
    folds : int
        Groups of the cross-validation (at least 2).
    seed : int
        Seed of the galaxies' assignment to groups.

    Returns
    -------
    smooth : float
        The chosen smoothing.
    score : numpy.ndarray
        Held-out ``sum ln Z`` per candidate, less its largest (0 at the chosen one).
    """
    cand = np.asarray(candidates, dtype=float)
    if cand.ndim != 1 or cand.size == 0 or not np.all((cand > 0) & (cand < 0.5)):
        raise ValueError("candidates must be smoothings in (0, 0.5)")
    if int(folds) < 2:
        raise ValueError("folds must be at least 2")
    folds = int(folds)
    if per_run is None:
        per_run = bool(getattr(config, "size_prior_per_run", False))
    comp, _, n_blk, w0 = size_mixture(lnL_r, bank, config, bulge_weights, knot_step, per_run)
    return _cross_validate(comp, n_blk, w0, tuple(cand), folds, seed)


def _cross_validate(comp: np.ndarray, n_blk: int, w0: np.ndarray, candidates, folds: int,
                    seed: int) -> tuple[float, np.ndarray]:
    """:func:`select_size_prior_smoothing` on the mixture of :func:`size_mixture`."""
    cand = np.asarray(candidates, dtype=float)
    group = np.random.default_rng(seed).permutation(comp.shape[0]) % folds
    fold = np.tile(np.arange(folds), cand.size)  # fit i: candidate i // folds, fold i % folds
    train = group[:, None] != fold[None, :]
    W = _ems(comp, w0, n_blk, np.repeat(cand, folds),
             np.repeat([_ems_steps(c) for c in cand], folds), rows=train)  # fmt: skip
    with np.errstate(divide="ignore"):
        lnZ = np.log(np.maximum(comp @ W, 1e-300))
    score = np.where(train, 0.0, lnZ).sum(axis=0).reshape(cand.size, folds).sum(axis=1)
    best = int(np.argmax(score))
    return float(cand[best]), score - score[best]


def _ems_steps(smooth: float) -> int:
    """EM steps for a smoothing: the less smoothing, the slower EM converges."""
    return int(max(500, round(100.0 / max(smooth, 1e-3))))


def size_mixture(lnL_r, bank, config, bulge_weights, knot_step: float, per_run: bool):
    """The mixture :func:`estimate_size_prior` fits: ``comp (n, n_blk K + 1)``, each
    galaxy's likelihood per unit mass of each knot (and of the point source, last, in
    units of its best size's), the knots, the number of blocks of knots and EM's start."""
    L = np.asarray(lnL_r, dtype=float)
    n_r = bank.n_r
    if L.ndim != 2 or L.shape[1] != n_r + 1:
        raise ValueError(f"lnL_r must have shape (n, {n_r + 1}), got {L.shape}")
    L = L[size_likelihood_rows(L)]
    if L.shape[0] < 10:
        raise ValueError(f"{L.shape[0]} usable likelihoods: too few to estimate a size prior")
    r, r_w, h = node_sizes(bank, config)
    n_b = n_r // bank.n_sizes
    pi = np.full(n_b, 1.0 / n_b) if bulge_weights is None else np.asarray(bulge_weights, float)
    lo, hi = np.log(h.min()) - knot_step, np.log(h.max()) + knot_step
    knots = np.arange(lo, hi + knot_step, knot_step)
    B = node_basis(h, bank.n_sizes, knots)  # each knot's share of each node: B[j, k]
    top = L.max(axis=1, keepdims=True)
    E = np.exp(L - top)
    K = knots.size
    ns = bank.n_sizes
    if per_run:  # the joint prior of (run, knot): a block of knots per run
        M = (r_w / r)[:, None] * B
        blocks = [E[:, b * ns:(b + 1) * ns] @ M[b * ns:(b + 1) * ns] for b in range(n_b)]
        share = np.clip(pi / pi.sum(), 1e-3, None)  # EM's start
    else:  # one block, the runs mixed with the bulge weights
        M = (np.repeat(pi, ns) * r_w / r)[:, None] * B  # node mass per knot value
        blocks = [E[:, :n_r] @ M]
        share = np.ones(1)
    comp = np.column_stack([b / knot_step for b in blocks] + [E[:, n_r]])  # per unit mass
    w0 = np.append(np.repeat(share / share.sum(), K), 1.0) / (K + 1)  # the point source last
    return comp, knots, len(blocks), w0


def _ems(comp: np.ndarray, w0: np.ndarray, n_blk: int, smooth: np.ndarray,
         n_iter: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
    """Smoothed EM (EMS) of the mixture weights, several fits at once.

    Fit ``i`` (a column of the result) runs ``n_iter[i]`` steps with smoothing
    ``smooth[i]`` on the galaxies ``rows[:, i]`` (a boolean ``(n, n_fits)``; all of
    them by default), from ``w0``. Each step is EM's ``w <- w mean_a(comp_a / Z_a)``
    followed by the smoothing of every block of knots with ``[s, 1 - 2 s, s]`` (0
    outside the knots) and renormalisation. The fits share their passes over
    ``comp``: two matrix products per step for all of them.
    """
    smooth = np.asarray(smooth, dtype=float)
    n_iter = np.asarray(n_iter, dtype=int)
    nf = smooth.size
    K = (comp.shape[1] - 1) // n_blk
    W = np.repeat(np.asarray(w0, dtype=float)[:, None], nf, axis=1)
    inv_n = None if rows is None else rows / np.maximum(rows.sum(axis=0), 1)
    for it in range(int(n_iter.max())):
        live = n_iter > it
        Z = comp @ W[:, live]
        R = (1.0 / comp.shape[0]) / Z if inv_n is None else inv_n[:, live] / Z
        Wl = W[:, live] * (comp.T @ R)
        s = smooth[live]
        for b in range(n_blk):
            blk = Wl[b * K:(b + 1) * K]
            sm = (1.0 - 2.0 * s) * blk
            sm[1:] += s * blk[:-1]
            sm[:-1] += s * blk[1:]
            Wl[b * K:(b + 1) * K] = sm
        W[:, live] = Wl / Wl.sum(axis=0)
    return W
