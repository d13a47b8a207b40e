"""The functional prior's parameters fitted to data: the marginal likelihood and its maximum.

Estimating ``(B, C, D)`` from stored likelihood grids ``ln L_a(e)`` (one row per galaxy)
maximises the marginal likelihood of the sample,

    l(B, C, D) = sum_a w_a ln sum_e P(e) L_a(e) de^2,

either with the paper's iteration (the summed posterior is the next
prior, refitted to the functional form by minimum cross-entropy,
:func:`fit_functional_prior`; this *is* the EM algorithm for (B, C, D)) or by maximising
``l`` directly (the default). Both reach the same fixed point;
:func:`estimate_functional` runs either on a prepared sample (docs: method,
eq-prior-iteration). The variables of the fits are ``x = (ln B, ln C, ln D)``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy import optimize

from .._util import check_egrid
from .functional import (
    DEFAULT_PARAMS,
    LOG_BOUNDS,
    PARAM_NAMES,
    Prior,
    constraints,
    dlogf_dlogparams,
    log_f,
    prior_is_valid,
)
from .sample import PreparedSample, prepare_sample

log = logging.getLogger(__name__)

#: ``record(iteration, x, marginal_lnL)``: how the fits log each step in a history.
Recorder = Callable[[int, np.ndarray, float], None]


def _grid_logq(r: np.ndarray, x: np.ndarray):
    """Log cell probabilities ``ln(P de^2)`` on the grid and their derivatives.

    ``x = (ln B, ln C, ln D)``. Returns ``logq (n_e,)`` and ``dlogq (3, n_e)``.
    """
    B, C, D = np.exp(x)
    lf = log_f(r, B, C, D)
    m = float(np.max(lf))
    q = np.exp(lf - m)
    z = float(np.sum(q))
    q /= z
    logq = lf - m - math.log(z)
    dlf = dlogf_dlogparams(r, B, C, D)
    dlogq = dlf - (dlf @ q)[:, None]
    return logq, dlogq, q


def _marginal_terms(L: np.ndarray, w: np.ndarray, r: np.ndarray, x: np.ndarray):
    """``l(x) = sum_a w_a ln sum_e q_e L_ae`` and its gradient in ``x``."""
    logq, dlogq, q = _grid_logq(r, x)
    M = np.empty((r.size, 4))
    M[:, 0] = q
    M[:, 1:] = (q * dlogq).T
    S = L @ M
    z = np.maximum(S[:, 0], 1e-300)
    ell = float(w @ np.log(z))
    grad = (w / z) @ S[:, 1:]
    return ell, grad


def marginal_log_likelihood(
    lnL: np.ndarray,
    egrid: np.ndarray,
    prior: Prior,
    *,
    weights: np.ndarray | None = None,
) -> float:
    """Marginal log-likelihood of a sample under a prior.

    ``l = sum_a w_a ln sum_e P(e) L_a(e) de^2`` over the usable rows, with each ``L_a``
    scaled to a maximum of 1 (so ``l`` is defined up to a constant per galaxy that does
    not depend on the prior). The prior is evaluated on ``egrid`` and normalised there.

    Parameters
    ----------
    lnL : numpy.ndarray
        ``(n_gal, n_e)`` log-likelihood grids.
    egrid : numpy.ndarray
        ``(n_e, 2)`` grid of cell centres.
    prior : Prior
        The prior.
    weights : numpy.ndarray, optional
        Per-galaxy weights ``w_a`` (default 1).

    Returns
    -------
    float
    """
    sample = prepare_sample(lnL, egrid, weights)
    p = prior.on_grid(sample.egrid).grid_pdf()
    q = p / p.sum()
    return float(sample.w @ np.log(np.maximum(sample.L @ q, 1e-300)))


def _slsqp(fun_and_grad, x0: np.ndarray, *, ftol: float, maxiter: int, callback=None):
    cons = {"type": "ineq", "fun": lambda x: constraints(*np.exp(x))}
    return optimize.minimize(
        fun_and_grad,
        x0,
        jac=True,
        method="SLSQP",
        bounds=LOG_BOUNDS,
        constraints=[cons],
        options={"ftol": ftol, "maxiter": maxiter},
        callback=callback,
    )


def _start_x(start) -> np.ndarray:
    B, C, D = (float(v) for v in (DEFAULT_PARAMS if start is None else start))
    if not prior_is_valid(B, C, D):
        raise ValueError(f"start=({B:g}, {C:g}, {D:g}) is outside the allowed parameter region")
    return np.log([B, C, D])


def _at_bound(x: np.ndarray) -> list[str]:
    out = []
    for name, xi, (lo, hi) in zip(PARAM_NAMES, x, LOG_BOUNDS, strict=True):
        if xi <= lo + 1e-6 or xi >= hi - 1e-6:
            out.append(name)
    B, C, D = np.exp(x)
    c = constraints(B, C, D)
    if c[0] < 1e-4:
        out.append("positivity condition")
    if np.min(c[1:]) < 1e-4:
        out.append("no-turning-point condition")
    return out


def fit_functional_prior(
    p_out: np.ndarray,
    egrid: np.ndarray,
    *,
    start: tuple[float, float, float] | None = None,
) -> Prior:
    """Fit the functional prior (eq-funcprior) to a gridded distribution by minimum cross-entropy.

    Minimises ``H = -sum_e p_out(e) ln P_func(e)`` over ``(B, C, D)`` (paper section
    3.1), with ``P_func`` normalised on the grid. The argument order is that of the
    documentation (docs: method, eq-prior-iteration): the paper's displayed equation
    swaps the two distributions, which would let the fit collapse onto a spike at the
    maximum of ``p_out``. Minimising ``H`` with ``p_out`` the summed posterior is
    exactly the M-step of the EM algorithm for ``(B, C, D)``.

    Parameters
    ----------
    p_out : numpy.ndarray
        ``(n_e,)`` non-negative values on ``egrid`` (any normalisation: a density or cell
        probabilities).
    egrid : numpy.ndarray
        ``(n_e, 2)`` grid of cell centres.
    start : tuple of float, optional
        Starting ``(B, C, D)`` (default the STEP-like values).

    Returns
    -------
    Prior
        With ``method="cross-entropy"`` and ``info["cross_entropy"]`` the minimum of ``H``
        for ``p_out`` normalised to unit sum.
    """
    egrid = check_egrid(egrid)
    p = np.asarray(p_out, dtype=float)
    if p.shape != (egrid.shape[0],):
        raise ValueError(f"p_out must have shape ({egrid.shape[0]},), got {p.shape}")
    if np.any(~np.isfinite(p)) or np.any(p < 0) or p.sum() <= 0:
        raise ValueError("p_out must be finite, non-negative and not all zero")
    p = p / p.sum()
    r = np.hypot(egrid[:, 0], egrid[:, 1])
    x, h = _cross_entropy_fit(p, r, _start_x(start))
    B, C, D = np.exp(x)
    return Prior(
        B=B,
        C=C,
        D=D,
        egrid=egrid,
        method="cross-entropy",
        info={"cross_entropy": h, "at_bound": _at_bound(x)},
    )


def _cross_entropy_fit(p: np.ndarray, r: np.ndarray, x0: np.ndarray):
    def fun(x):
        logq, dlogq, _ = _grid_logq(r, x)
        return -float(p @ logq), -(dlogq @ p)

    res = _slsqp(fun, x0, ftol=1e-12, maxiter=200)
    x = np.clip(res.x, [b[0] for b in LOG_BOUNDS], [b[1] for b in LOG_BOUNDS])
    if not prior_is_valid(*np.exp(x)):  # the optimiser may end a hair outside
        x = x0
    return x, float(fun(x)[0])


# ----------------------------------------------------------------------------------------
# Estimation from the likelihood grids
# ----------------------------------------------------------------------------------------
def _prior_em(L: np.ndarray, w: np.ndarray, r: np.ndarray, x: np.ndarray, n_iter: int,
              tol: float, history: list[dict[str, Any]], record: Recorder,
              ) -> tuple[np.ndarray, bool]:  # fmt: skip
    """:func:`estimate_prior`'s EM iteration from ``x`` (log B, C, D): the summed
    posterior (the E-step), then the functional form fitted to it by minimum cross
    entropy (the M-step). Returns the final ``x`` and whether it converged."""
    wsum = float(w.sum())
    converged = False
    ell_prev = -np.inf
    for it in range(n_iter + 1):
        _, _, q = _grid_logq(r, x)
        z = np.maximum(L @ q, 1e-300)
        ell = float(w @ np.log(z))
        record(it, x, ell)
        if it > 0 and abs(ell - ell_prev) <= tol * wsum:
            converged = True
            break
        if it == n_iter:
            break
        ell_prev = ell
        # E-step: the summed posterior (eq-prior-iteration) -> cell probabilities p_out
        p_out = q * ((w / z) @ L) / wsum
        # M-step: minimum cross-entropy fit of the functional form (eq-funcprior)
        x, _ = _cross_entropy_fit(p_out, r, x)
    return x, converged


def _prior_direct(L: np.ndarray, w: np.ndarray, r: np.ndarray, x: np.ndarray, n_iter: int,
                  tol: float, history: list[dict[str, Any]], record: Recorder,
                  ) -> tuple[np.ndarray, bool]:  # fmt: skip
    """:func:`estimate_prior`'s direct maximisation of the marginal likelihood from ``x``
    (log B, C, D) by SLSQP, with its analytic gradient. Returns the best allowed iterate
    and whether SLSQP converged."""
    wsum = float(w.sum())
    cache: dict[bytes, tuple[float, np.ndarray]] = {}

    def fun(xx):
        key = xx.tobytes()
        if key not in cache:
            ell, g = _marginal_terms(L, w, r, xx)
            cache.clear()
            cache[key] = (ell, g)
        ell, g = cache[key]
        return -ell / wsum, -g / wsum

    record(0, x, -fun(x)[0] * wsum)
    it_count = [0]

    def cb(xk):
        it_count[0] += 1
        record(it_count[0], xk, -fun(np.asarray(xk, dtype=float))[0] * wsum)

    res = _slsqp(fun, x, ftol=tol, maxiter=n_iter, callback=cb)
    # the result, or (should it end a hair outside the allowed region) the best
    # allowed iterate
    xr = np.clip(res.x, [b[0] for b in LOG_BOUNDS], [b[1] for b in LOG_BOUNDS])
    candidates = [(-fun(xr)[0] * wsum, xr)] + [
        (h["marginal_lnL"], np.log([h[k] for k in PARAM_NAMES])) for h in history
    ]
    valid = [(ell, xx) for ell, xx in candidates if prior_is_valid(*np.exp(xx))]
    x = max(valid, key=lambda c: c[0])[1]
    if not np.allclose(np.log([history[-1][k] for k in PARAM_NAMES]), x, rtol=0, atol=1e-12):
        record(len(history), x, -fun(x)[0] * wsum)
    return x, bool(res.success)


def estimate_functional(sample: PreparedSample, *, method: str, n_iter: int | None,
                        start: tuple[float, float, float] | None, tol: float) -> Prior:
    """:func:`pylensfit.prior.estimate_prior` with ``form="functional"`` on a prepared
    sample: ``method`` ``"em"`` (at most ``n_iter`` steps, default 10) or ``"direct"``
    (at most ``n_iter`` optimiser iterations, default 200) from ``start``; a warning is
    logged when the fit ends on a bound."""
    history: list[dict[str, Any]] = []

    def record(it: int, xx: np.ndarray, ell: float) -> None:
        B, C, D = np.exp(xx)
        history.append(
            {"iteration": it, "B": float(B), "C": float(C), "D": float(D), "marginal_lnL": ell}
        )

    L, w, r = sample.L, sample.w, sample.radii
    if method == "em":
        x, converged = _prior_em(L, w, r, _start_x(start), 10 if n_iter is None else int(n_iter),
                                 tol, history, record)  # fmt: skip
    else:
        x, converged = _prior_direct(L, w, r, _start_x(start),
                                     200 if n_iter is None else int(n_iter), tol, history,
                                     record)  # fmt: skip
    bounds_hit = _at_bound(x)
    if bounds_hit:
        log.warning(
            "prior estimate ended on a bound (%s): the sample may be too small or too noisy "
            "to fix the prior's shape",
            ", ".join(bounds_hit),
        )
    B, C, D = np.exp(x)
    return Prior(B=B, C=C, D=D, egrid=sample.egrid, method=method, history=history,
                 info={"n_used": int(L.shape[0]), "n_excluded": sample.n_excluded,
                       "at_bound": bounds_hit, "converged": converged,
                       "n_steps": len(history) - 1})  # fmt: skip

