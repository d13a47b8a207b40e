"""A population prior over the bulge fraction of the bulge+disc family.

:func:`mix_bulge_fractions` marginalises each galaxy's likelihood over the fractions
under a prior ``pi_k``; :func:`estimate_bulge_weights` estimates ``pi_k`` by maximum
marginal likelihood, and :func:`estimate_prior_and_bulge` estimates it together with the
ellipticity prior.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.special import logsumexp

from .estimate import estimate_prior
from .functional import Prior
from .radial import RadialPrior

log = logging.getLogger(__name__)


def mix_bulge_fractions(
    lnL_bulge: np.ndarray, lnL_star: np.ndarray, weights: np.ndarray | None = None
) -> np.ndarray:
    """``ln L(e)`` with the bulge fraction marginalised under a prior ``pi_k``.

    ``L(e) = sum_k pi_k L_k(e) + L_star``: each fraction's likelihood (summed over the
    sizes, :attr:`pylensfit.StampFits.lnL_bulge`) weighted by its prior probability, and
    the point source, common to all fractions, once.

    Parameters
    ----------
    lnL_bulge : numpy.ndarray
        ``(n, n_b, n_e)`` per-fraction ``ln L_k(e)``.
    lnL_star : numpy.ndarray
        ``(n,)`` the point source's ``ln L`` on the same scale.
    weights : numpy.ndarray, optional
        ``(n_b,)`` prior probabilities ``pi_k`` (normalised here); uniform by default.

    Returns
    -------
    numpy.ndarray
        ``(n, n_e)`` float32, each row shifted so that its maximum is 0 (NaN rows stay NaN).
    """
    lb = np.asarray(lnL_bulge)
    n_b = lb.shape[1]
    w = np.full(n_b, 1.0 / n_b) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (n_b,) or np.any(w < 0) or not w.sum() > 0:
        raise ValueError(f"weights must be {n_b} non-negative numbers, not {weights!r}")

    b = (w / w.sum())[None, :, None]
    ls = np.asarray(lnL_star, dtype=float)
    out = np.empty((lb.shape[0], lb.shape[2]), dtype=np.float32)
    # in float64, a block of galaxies at a time: the temporaries stay a few MB however
    # large the sample (the precision mode's calibration holds 80,000 galaxies' grids)
    for s in _chunks(lb.shape[0], lb.shape[1] * lb.shape[2]):
        galaxy = logsumexp(np.asarray(lb[s], dtype=float), axis=1, b=b)
        with np.errstate(invalid="ignore"):  # NaN rows (objects not measured) stay NaN
            o = np.logaddexp(galaxy, ls[s, None])
            o -= np.max(o, axis=1, keepdims=True)
        out[s] = o
    return out


def _chunks(n: int, row_size: int, target: int = 1 << 22) -> list[slice]:
    """Slices of ``n`` rows of ``row_size`` numbers each, about ``target`` numbers a slice."""
    step = max(1, target // max(1, row_size))
    return [slice(i, min(n, i + step)) for i in range(0, n, step)]


def _fraction_evidence(lnL_bulge, lnL_star, prior: Prior):
    """Per galaxy: ``Z_k = sum_e P(e) L_k(e) de^2`` and ``Z_star``, scaled by one factor."""
    lb = np.asarray(lnL_bulge)  # float32 or float64, converted a block at a time
    ls = np.asarray(lnL_star, dtype=float)
    p = prior.grid_pdf() * prior.step**2
    Z = np.empty(lb.shape[:2])
    top = np.empty(lb.shape[0])
    for s in _chunks(lb.shape[0], lb.shape[1] * lb.shape[2]):
        b = np.asarray(lb[s], dtype=float)
        top[s] = np.maximum(np.max(b, axis=(1, 2), initial=-np.inf), ls[s])
        b -= top[s, None, None]
        np.exp(b, out=b)
        Z[s] = np.einsum("gke,e->gk", b, p)
    return Z, np.exp(ls - top) * p.sum()


def estimate_bulge_weights(
    lnL_bulge: np.ndarray,
    lnL_star: np.ndarray,
    prior: Prior,
    *,
    start: np.ndarray | None = None,
    tol: float = 1e-7,
    max_iter: int = 2000,
) -> np.ndarray:
    """Population prior ``pi_k`` of the bulge fractions, by maximum marginal likelihood.

    Maximises ``l(pi) = sum_a ln(sum_k pi_k Z_ak + Z_a,star)`` over the simplex, where
    ``Z_ak = sum_e P(e) L_ak(e) de^2`` is galaxy ``a``'s evidence for fraction ``k`` under
    the ellipticity prior ``P``: the same hierarchical estimate as that of the
    ellipticity prior (:func:`estimate_prior`), for the model's one discrete parameter.
    The EM update ``pi_k <- sum_a pi_k Z_ak / Z_a`` (normalised) has for fixed points the
    stationary points of ``l`` on the simplex, and each step cannot decrease ``l``.

    A uniform prior over the fractions is a strong assumption that the data can test: for
    a disc-dominated population it puts two thirds of the weight on models with a bulge,
    and the mixture of ill-fitting models biases the ellipticities of faint galaxies
    (``m ~ +0.025`` for exponential discs fitted with fractions 0, 0.5, 1;
    ``benchmarks/studies/exact_model_bias.py``).

    Parameters
    ----------
    lnL_bulge : numpy.ndarray
        ``(n, n_b, n_e)`` per-fraction likelihoods of the sample (usable rows only).
    lnL_star : numpy.ndarray
        ``(n,)`` the point source's ``ln L``.
    prior : Prior
        Ellipticity prior on the same grid.
    start : numpy.ndarray, optional
        Starting weights (uniform by default).
    tol, max_iter : float, int
        Stop when no weight changes by more than ``tol`` in a step, or after ``max_iter``.

    Returns
    -------
    numpy.ndarray
        ``(n_b,)`` weights summing to 1.
    """
    lb = np.asarray(lnL_bulge)
    if lb.ndim != 3 or lb.shape[0] == 0:
        raise ValueError(f"lnL_bulge must be a non-empty (n, n_b, n_e) array, not {lb.shape}")
    ls = np.asarray(lnL_star, float)
    ok = np.isfinite(ls)
    for s in _chunks(lb.shape[0], lb.shape[1] * lb.shape[2]):
        ok[s] &= np.isfinite(lb[s]).all(axis=(1, 2))
    if not ok.any():
        raise ValueError("no usable likelihood to estimate the bulge-fraction prior")
    Z, Zs = _fraction_evidence(lb if ok.all() else lb[ok], ls[ok], prior)
    n_b = lb.shape[1]
    w = np.full(n_b, 1.0 / n_b) if start is None else np.asarray(start, float) / np.sum(start)
    for _ in range(max_iter):
        tot = Z @ w + Zs
        new = w * np.sum(Z / tot[:, None], axis=0)
        new /= new.sum()
        done = np.max(np.abs(new - w)) < tol
        w = new
        if done:
            break
    return w


def estimate_prior_and_bulge(
    lnL_bulge: np.ndarray,
    lnL_star: np.ndarray,
    egrid: np.ndarray,
    *,
    method: str = "direct",
    n_iter: int = 4,
    tol: float = 1e-3,
    form: str = "functional",
) -> tuple[RadialPrior, np.ndarray]:
    """The ellipticity prior and the bulge-fraction prior together, from one sample.

    Alternates :func:`estimate_prior` on the mixed likelihoods
    (:func:`mix_bulge_fractions`) with :func:`estimate_bulge_weights` under that prior,
    from uniform weights, until no weight moves by more than ``tol`` (at most ``n_iter``
    rounds); the prior returned is the one estimated with the final weights, of the
    given ``form`` (:func:`estimate_prior`).

    Returns
    -------
    prior : Prior or SplinePrior
    weights : numpy.ndarray
        ``(n_b,)`` prior probabilities of the bulge fractions.
    """
    lb = np.asarray(lnL_bulge)
    w = np.full(lb.shape[1], 1.0 / lb.shape[1])
    prior = estimate_prior(mix_bulge_fractions(lb, lnL_star, w), egrid, method=method,
                           form=form)  # fmt: skip
    for _ in range(n_iter):
        new = estimate_bulge_weights(lb, lnL_star, prior, start=w)
        moved = np.max(np.abs(new - w))
        w = new
        prior = estimate_prior(mix_bulge_fractions(lb, lnL_star, w), egrid, method=method,
                               start=prior.params, form=form)  # fmt: skip
        if moved < tol:
            break
    log.info("bulge-fraction prior %s with %r", np.round(w, 4).tolist(), prior)
    return prior, w
