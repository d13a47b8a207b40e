"""A flexible ellipticity prior: a cubic B-spline in ``|e|``, and its estimation.

``ln P = ln cos(pi |e| / 2) + s(|e|)`` with ``s`` a cubic B-spline on
:data:`SPLINE_KNOTS`, normalised on the ellipticity grid as every
:class:`~pylensfit.prior.radial.RadialPrior` is. :func:`estimate_spline` fits its
coefficients by maximum marginal likelihood with a roughness penalty
(:func:`pylensfit.prior.estimate_prior` with ``form="spline"``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy import interpolate, optimize

from .functional import DEFAULT_PARAMS, log_f
from .radial import RadialPrior
from .sample import PreparedSample

#: Knots of :class:`SplinePrior`'s cubic B-spline (:data:`pylensfit.prior.SPLINE_KNOTS`).
SPLINE_KNOTS = np.concatenate([[0.0] * 4, [0.2, 0.4, 0.6, 0.8], [1.0] * 4])
#: Default weight of the roughness penalty (:data:`pylensfit.prior.SPLINE_SMOOTHING`).
SPLINE_SMOOTHING = 10.0


def _spline_design(r: np.ndarray) -> np.ndarray:
    """``(n, K)`` values of the cubic B-spline basis on :data:`SPLINE_KNOTS` at ``r``."""
    r = np.clip(np.asarray(r, dtype=float), 0.0, 1.0 - 1e-12)
    return interpolate.BSpline.design_matrix(r, SPLINE_KNOTS, 3).toarray()


class SplinePrior(RadialPrior):
    """A flexible ellipticity prior: ``ln P = ln cos(pi |e| / 2) + s(|e|)`` with ``s`` a
    cubic B-spline, normalised on a grid.

    The functional form of Kitching et al. (2008) has three parameters and a shape of its
    own; a population outside it (discs of one inclination distribution, bulges of
    another) drives its estimate onto a bound of the parameters. The spline follows any
    smooth radial distribution with no bound to end on: eight coefficients on
    :data:`SPLINE_KNOTS` (uniform in ``|e|``, every 0.2), estimated by
    :func:`estimate_prior` with ``form="spline"`` as the functional form is, by maximum
    marginal likelihood of the sample. The cosine factor takes ``P`` to zero at
    ``|e| = 1``, as the functional form does.

    Parameters
    ----------
    coef : sequence of float
        The spline's eight coefficients (a constant added to all of them changes nothing).
        Default: the spline closest to the functional prior's STEP-like defaults.
    step, egrid, method, history, info
        As for :class:`Prior`.

    Attributes
    ----------
    coef : numpy.ndarray
        ``(8,)`` the coefficients.
    """

    form = "spline"
    _KEYS = ("coef",)

    def __init__(
        self,
        *,
        coef: Sequence[float] | None = None,
        step: float | None = None,
        egrid: np.ndarray | None = None,
        method: str = "fixed",
        history: Sequence[dict[str, Any]] | None = None,
        info: dict[str, Any] | None = None,
    ) -> None:
        k = len(SPLINE_KNOTS) - 4
        c = _spline_start() if coef is None else np.asarray(coef, dtype=float).ravel()
        if c.shape != (k,) or not np.all(np.isfinite(c)):
            raise ValueError(f"coef must be {k} finite numbers, got {coef!r}")
        self.coef = c - c.mean()
        self._s = interpolate.BSpline(SPLINE_KNOTS, self.coef, 3)
        self._ds = self._s.derivative()
        self._normalise(step, egrid, method, history, info)

    def _log_f(self, r: np.ndarray) -> np.ndarray:
        r = np.asarray(r, dtype=float)
        return np.log(np.cos(0.5 * np.pi * r)) + self._s(np.clip(r, 0.0, 1.0))

    def _dlogf_dr(self, r: np.ndarray) -> np.ndarray:
        r = np.asarray(r, dtype=float)
        return -0.5 * np.pi * np.tan(0.5 * np.pi * r) + self._ds(np.clip(r, 0.0, 1.0))

    @property
    def params(self) -> tuple[float, ...]:
        """The coefficients, as a tuple."""
        return tuple(float(v) for v in self.coef)

    def form_dict(self) -> dict[str, Any]:
        return {"form": self.form, "coef": self.coef.tolist()}

    def header_cards(self) -> list[tuple[str, float | str, str]]:
        return [("PRIORFRM", self.form, "ellipticity prior form: cubic B-spline in |e|")] + [
            (f"PRIORS{j}", float(v), f"spline coefficient {j}") for j, v in enumerate(self.coef)]

    def __repr__(self) -> str:
        c = ", ".join(f"{v:.3g}" for v in self.coef)
        return f"SplinePrior(coef=[{c}], step={self.step:g}, method={self.method!r})"


def _spline_start() -> np.ndarray:
    """The coefficients whose spline is closest (least squares in ``ln P``) to the
    functional prior with its STEP-like defaults, on ``|e| < 0.95``."""
    r = np.linspace(0.0, 0.95, 200)
    target = log_f(r, *DEFAULT_PARAMS) - np.log(np.cos(0.5 * np.pi * r))
    c = np.linalg.lstsq(_spline_design(r), target, rcond=None)[0]
    return c - c.mean()


def _roughness() -> np.ndarray:
    """``D^T D`` with ``D`` the second differences of the spline's coefficients."""
    k = len(SPLINE_KNOTS) - 4
    d2 = np.diff(np.eye(k), n=2, axis=0)
    return d2.T @ d2


def _prior_spline(L: np.ndarray, w: np.ndarray, r: np.ndarray, c0: np.ndarray, n_iter: int,
                  tol: float, smoothing: float,
                  record: Callable[[int, np.ndarray, float], None],
                  ) -> tuple[np.ndarray, bool]:  # fmt: skip
    """:func:`estimate_prior`'s maximisation for the spline form: ``l(c) - (smoothing/2)
    |D c|^2`` by L-BFGS with its analytic gradient (``D`` the coefficients' second
    differences). Returns the coefficients and whether the optimiser converged."""
    wsum = float(w.sum())
    bm = _spline_design(r)
    lc = np.log(np.cos(0.5 * np.pi * r))
    R = _roughness()
    M = np.empty((r.size, bm.shape[1] + 1))

    def terms(c):
        lf = lc + bm @ c
        q = np.exp(lf - lf.max())
        q /= q.sum()
        M[:, 0] = q
        M[:, 1:] = q[:, None] * bm
        S = L @ M
        z = np.maximum(S[:, 0], 1e-300)
        ell = float(w @ np.log(z))
        g = (w / z) @ S[:, 1:] - wsum * (q @ bm)
        return ell, g

    def fun(c):
        ell, g = terms(c)
        pen = 0.5 * smoothing * float(c @ R @ c) + 0.5 * float(c.mean()) ** 2 * wsum
        gpen = smoothing * (R @ c) + c.mean() * wsum / c.size
        return -(ell - pen) / wsum, -(g - gpen) / wsum

    record(0, c0, terms(c0)[0])
    res = optimize.minimize(fun, c0, jac=True, method="L-BFGS-B",
                            options={"ftol": tol, "gtol": 1e-9, "maxiter": n_iter})  # fmt: skip
    c = np.asarray(res.x, dtype=float)
    record(int(res.nit), c, terms(c)[0])
    return c, bool(res.success)


def estimate_spline(sample: PreparedSample, *, start: Sequence[float] | None,
                    n_iter: int | None, tol: float, smoothing: float) -> SplinePrior:  # fmt: skip
    """:func:`pylensfit.prior.estimate_prior` with ``form="spline"`` on a prepared sample.

    ``start``: the coefficients to start from (the default shape for ``None`` or a
    functional start ``(B, C, D)``); ``n_iter``: the optimiser's iterations (default
    500); ``tol``: its ``ftol`` (at most 1e-9); ``smoothing``: the roughness penalty's
    weight.
    """
    L, w, r = sample.L, sample.w, sample.radii
    c0 = _spline_start() if start is None else np.asarray(start, dtype=float)
    if c0.shape != (len(SPLINE_KNOTS) - 4,):
        c0 = _spline_start()  # a functional start (B, C, D): the default shape instead
    history: list[dict[str, Any]] = []

    def record(it: int, c: np.ndarray, ell: float) -> None:
        history.append({"iteration": it, "coef": [float(v) for v in c], "marginal_lnL": ell})

    c, converged = _prior_spline(L, w, r, c0, 500 if n_iter is None else int(n_iter),
                                 min(tol, 1e-9), float(smoothing), record)  # fmt: skip
    return SplinePrior(coef=c, egrid=sample.egrid, method="direct", history=history,
                       info={"n_used": int(L.shape[0]), "n_excluded": sample.n_excluded,
                             "at_bound": [],
                             "converged": converged, "n_steps": history[-1]["iteration"],
                             "smoothing": float(smoothing)})  # fmt: skip
