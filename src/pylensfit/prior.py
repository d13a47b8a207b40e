"""The ellipticity prior: its functional form, its fit, and its estimation from the data.

The prior is the functional form of Kitching et al. (2008, arXiv:0802.1528, section 3.1;
docs: method, eq-funcprior)::

    P(e) = A cos(|e| pi / 2) exp[-(2 |e| / (B (1 + |e|^D)))^C],

a function of ``|e|`` only (a zero-shear population), with ``A`` fixed by the
normalisation *on the ellipticity grid*: ``sum_grid P(e) de^2 = 1``, so that ``P`` is a
density in the (e1, e2) plane (units: per unit e1 per unit e2) whose cell probabilities
``P de^2`` sum to one over the grid of :func:`pylensfit.grid.ellipticity_grid`.

Estimating ``(B, C, D)`` from stored likelihood grids ``ln L_a(e)`` (one row per galaxy)
maximises the marginal likelihood of the sample,

    l(B, C, D) = sum_a w_a ln sum_e P(e) L_a(e) de^2,

either with the paper's iteration (section 3: the summed posterior is the next prior,
refitted to the functional form by minimising a cross-entropy; this *is* the EM
algorithm for (B, C, D)) or by maximising ``l`` directly (the default). Both reach the
same fixed point; see :func:`estimate_prior` (docs: method, eq-prior-iteration).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import interpolate, optimize
from scipy.special import logsumexp

from ._util import (
    check_egrid,
    check_lnL,
    json_kind,
    jsonable,
    other_file_hint,
    read_json,
    read_json_entry,
)
from .grid import ellipticity_grid, grid_step
from .models import half_light_radius, run_half_light_radius

__all__ = [
    "PRIOR_BOUNDS",
    "SPLINE_KNOTS",
    "SPLINE_SMOOTHING",
    "BinnedPrior",
    "Prior",
    "RadialPrior",
    "SplinePrior",
    "SizePrior",
    "estimate_bulge_weights",
    "estimate_flux_range",
    "estimate_flux_slope",
    "estimate_prior",
    "estimate_prior_and_bulge",
    "estimate_prior_binned",
    "estimate_size_prior",
    "mix_bulge_fractions",
    "select_size_prior_smoothing",
    "fit_functional_prior",
    "marginal_log_likelihood",
    "prior_is_valid",
    "usable_rows",
    "MIN_FLUX_RANGE_SAMPLE",
]

log = logging.getLogger(__name__)

#: Box bounds on the parameters ``(B, C, D)`` of the functional prior. Together with the
#: joint conditions of :func:`prior_is_valid` they keep the prior positive, finite and
#: free of turning points for ``0 < |e| < 1``. The lower bounds on ``B`` and ``C`` stop
#: the degenerate direction (``B -> 0`` with ``C`` falling, which small or noisy samples
#: drift along) where the cusp at ``e = 0`` becomes sharper than the grid resolves: the
#: scale ``B/2`` where the exponent reaches 1 stays above 0.01, and the cells nearest the
#: origin (``|e| = 0.07`` for ``de = 0.1``) cannot constrain anything smaller.
PRIOR_BOUNDS: dict[str, tuple[float, float]] = {
    "B": (0.02, 5.0),
    "C": (0.2, 5.0),
    "D": (0.5, 10.0),
}

#: Largest allowed value of the exponent ``(2|e| / (B (1 + |e|^D)))^C`` on ``|e| < 1``:
#: the exponential factor then stays above ``exp(-200) ~ 1e-87``, positive and finite.
_MAX_EXPONENT = 200.0
#: Constraint values are capped here (keeps them well scaled for the optimiser).
_CONSTRAINT_CAP = 5.0
#: Tolerance on the joint conditions (the optimiser's own tolerance is ~1e-10).
_CONSTRAINT_TOL = 1e-6
#: Radii where the no-turning-point condition is imposed: a turning point can only appear
#: beyond ``r* = (D-1)^(-1/D) >= 0.80`` for ``D <= 10``.
_TURN_RADII = np.linspace(0.78, 0.9995, 444)
#: Required margin of the decrease of ``ln P`` near ``|e| = 1``, relative to that of the
#: cosine factor alone.
_TURN_MARGIN = 0.02
#: The defaults, a STEP-like population (docs: method, eq-funcprior).
DEFAULT_PARAMS = (0.19, 0.58, 2.4)

_NAMES = ("B", "C", "D")
_LOG_BOUNDS = [(math.log(PRIOR_BOUNDS[k][0]), math.log(PRIOR_BOUNDS[k][1])) for k in _NAMES]


# ----------------------------------------------------------------------------------------
# The functional form (docs: method, eq-funcprior)
# ----------------------------------------------------------------------------------------
def _exponent_terms(r: np.ndarray, B: float, C: float, D: float):
    """``t = u^C`` with ``u = 2 r / (B (1 + r^D))``, plus ``ln u`` and ``r^D``.

    ``r`` must lie in ``[0, 1)``; at ``r = 0``, ``t = 0`` and ``ln u = -inf``.
    """
    rD = r**D
    with np.errstate(divide="ignore"):
        lnu = np.log(2.0 * r) - math.log(B) - np.log1p(rD)
    t = np.exp(C * lnu)
    return t, lnu, rD


def _log_f(r: np.ndarray, B: float, C: float, D: float) -> np.ndarray:
    """Unnormalised ``ln P`` of the functional prior (eq-funcprior) at radii ``0 <= r < 1``."""
    t, _, _ = _exponent_terms(r, B, C, D)
    return np.log(np.cos(0.5 * np.pi * r)) - t


def _dlogf_dr(r: np.ndarray, B: float, C: float, D: float) -> np.ndarray:
    """Radial derivative ``d ln P / d|e|`` (``-inf`` at ``r = 0`` when ``C < 1``)."""
    t, _, rD = _exponent_terms(r, B, C, D)
    with np.errstate(divide="ignore", invalid="ignore"):
        cusp = C * t * (1.0 + (1.0 - D) * rD) / (r * (1.0 + rD))
    cusp = np.where(r > 0, cusp, np.inf if C < 1 else (2.0 / B if C == 1 else 0.0))
    return -0.5 * np.pi * np.tan(0.5 * np.pi * r) - cusp


def _dlogf_dlogparams(r: np.ndarray, B: float, C: float, D: float) -> np.ndarray:
    """Derivatives of the unnormalised ``ln P`` w.r.t. ``(ln B, ln C, ln D)``, shape (3, n)."""
    t, lnu, rD = _exponent_terms(r, B, C, D)
    with np.errstate(divide="ignore", invalid="ignore"):
        d_lnc = np.where(r > 0, -C * t * lnu, 0.0)
        d_lnd = np.where(r > 0, D * C * t * rD * np.log(r) / (1.0 + rD), 0.0)
    return np.stack([C * t, d_lnc, d_lnd])


def _constraints(B: float, C: float, D: float) -> np.ndarray:
    """The joint conditions of :func:`prior_is_valid`, each ``>= 0`` when satisfied.

    Element 0, positive and finite: ``ln 200 - C ln max u >= 0``, i.e. the exponent
    ``u^C <= 200`` on ``|e| < 1``, where ``u = 2|e| / (B (1 + |e|^D))`` has its maximum at
    ``|e| = 1`` for ``D <= 2`` and at ``r* = (D-1)^(-1/D)`` otherwise.

    Elements 1..: no turning point. ``d ln P/d|e| = -(pi/2) tan(pi |e|/2)
    - C u^C (1 + (1-D)|e|^D) / (|e| (1 + |e|^D))``; the first term is negative and the
    second is positive only for ``D > 2`` and ``|e| > r* >= 0.80`` (for ``D <= 10``). The
    conditions are ``-cos(pi |e|/2) d ln P/d|e| >= 0.02 (pi/2) sin(pi |e|/2)`` (the
    decrease at least 2% of that of the cosine factor alone) on :data:`_TURN_RADII`.
    """
    if D > 2.0:
        rstar = (D - 1.0) ** (-1.0 / D)
        usup = 2.0 * rstar * (D - 1.0) / (B * D)
    else:
        usup = 1.0 / B
    c_pos = math.log(_MAX_EXPONENT) - C * math.log(usup)
    r = _TURN_RADII
    t, _, rD = _exponent_terms(r, B, C, D)
    half = 0.5 * np.pi * r
    slope = 0.5 * np.pi * np.sin(half) + C * t * (1.0 + (1.0 - D) * rD) / (r * (1.0 + rD)) * np.cos(
        half
    )
    c_turn = slope - _TURN_MARGIN * 0.5 * np.pi * np.sin(half)
    return np.concatenate([[c_pos], np.minimum(c_turn, _CONSTRAINT_CAP)])


def prior_is_valid(B: float, C: float, D: float) -> bool:
    """Whether ``(B, C, D)`` lies in the allowed parameter region.

    The region is the box :data:`PRIOR_BOUNDS` and joint conditions that keep the
    functional prior (eq-funcprior) positive, finite and strictly decreasing in ``|e|``
    on ``0 < |e| < 1`` (no turning points, paper section 3.1): the exponent
    ``(2|e| / (B (1 + |e|^D)))^C <= 200``, and ``d ln P / d|e| < 0`` with a margin on a
    fine set of radii where the ``1 + |e|^D`` factor can create a turning point (near
    ``|e| = 1`` when ``D > 2``); see ``_constraints``.

    Parameters
    ----------
    B, C, D : float
        Parameters of the functional prior (docs: method, eq-funcprior; dimensionless).

    Returns
    -------
    bool
    """
    vals = {"B": B, "C": C, "D": D}
    for k, v in vals.items():
        lo, hi = PRIOR_BOUNDS[k]
        if not (np.isfinite(v) and lo * (1 - 1e-9) <= v <= hi * (1 + 1e-9)):
            return False
    return bool(np.all(_constraints(B, C, D) >= -_CONSTRAINT_TOL))


# ----------------------------------------------------------------------------------------
# The prior classes
# ----------------------------------------------------------------------------------------
class RadialPrior:
    """An ellipticity prior that depends on ``|e|`` only, normalised on a grid.

    The base of the two forms, the functional :class:`Prior` of Kitching et al. (2008)
    and the flexible :class:`SplinePrior`. A form supplies the unnormalised
    ``ln f(|e|)`` and its radial derivative; the density is ``P(e) = A f(|e|)`` with
    ``A`` fixed by ``sum_grid P de^2 = 1`` on :attr:`egrid` (units: per unit e1 per unit
    e2).

    Attributes
    ----------
    egrid : numpy.ndarray
        ``(n_e, 2)`` normalisation grid (cell centres).
    step : float
        Its cell side ``de``.
    A : float
        Normalisation constant, ``1 / sum_grid f(e) de^2`` (per unit e^2).
    method : str
        How the prior was obtained (``"fixed"`` when given).
    history : list of dict
        One entry per estimation step, with ``marginal_lnL`` where computed.
    info : dict
        Bookkeeping of the estimation: ``n_used``, ``n_excluded``, ``at_bound``, ...
    """

    #: the form's name in :meth:`to_dict` and in catalogue headers
    form = ""

    def _log_f(self, r: np.ndarray) -> np.ndarray:
        """Unnormalised ``ln P`` at radii ``0 <= r < 1``."""
        raise NotImplementedError

    def _dlogf_dr(self, r: np.ndarray) -> np.ndarray:
        """``d ln P / d|e|`` at radii ``0 < r < 1``."""
        raise NotImplementedError

    def _normalise(self, step: float | None, egrid: np.ndarray | None, method: str,
                   history, info) -> None:  # fmt: skip
        """Set the grid, its step and ``A``, and the bookkeeping."""
        if egrid is None:
            egrid = ellipticity_grid(0.1 if step is None else float(step))
        egrid = np.ascontiguousarray(egrid, dtype=float)
        self.step = float(f"{grid_step(egrid):.12g}")
        if step is not None and not math.isclose(float(step), self.step, rel_tol=1e-6):
            raise ValueError(f"step={step} disagrees with the grid's cell side {self.step}")
        r = np.hypot(egrid[:, 0], egrid[:, 1])
        if np.any(r >= 1.0):
            raise ValueError("the normalisation grid must lie inside |e| < 1")
        self.egrid = egrid
        self.method = method
        self.history: list[dict[str, Any]] = [dict(h) for h in (history or [])]
        self.info: dict[str, Any] = dict(info or {})
        lf = self._log_f(r)
        m = float(np.max(lf))
        self._log_norm = m + math.log(float(np.sum(np.exp(lf - m))) * self.step**2)
        self.A = math.exp(-self._log_norm)

    # -- evaluation ------------------------------------------------------------------
    def log_pdf(self, e1: np.ndarray | float, e2: np.ndarray | float) -> np.ndarray:
        """Natural log of :meth:`pdf` (``-inf`` for ``|e| >= 1``)."""
        e1, e2 = np.broadcast_arrays(np.asarray(e1, dtype=float), np.asarray(e2, dtype=float))
        r = np.hypot(e1, e2)
        inside = r < 1.0
        out = np.full(r.shape, -np.inf)
        out[inside] = self._log_f(r[inside]) - self._log_norm
        return out

    def pdf(self, e1: np.ndarray | float, e2: np.ndarray | float) -> np.ndarray:
        """Prior density at ``(e1, e2)``.

        Parameters
        ----------
        e1, e2 : array_like
            Ellipticity components (broadcast together).

        Returns
        -------
        numpy.ndarray
            ``P(e)`` per unit e^2, with ``A`` fixed by ``sum_grid P de^2 = 1`` on
            :attr:`egrid`; zero for ``|e| >= 1``.
        """
        return np.exp(self.log_pdf(e1, e2))

    def grad(self, e1: np.ndarray | float, e2: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Analytic gradient ``(dP/de1, dP/de2)`` of :meth:`pdf` (same normalisation).

        ``P`` depends on ``|e|`` only, so ``dP/de_i = P (d ln P / d|e|) e_i / |e|``. At
        ``e = 0`` the prior may have a cusp and the gradient need not exist; there (and
        for ``|e| >= 1``) zeros are returned. The grids of
        :func:`pylensfit.ellipticity_grid` never contain ``e = 0``.

        Returns
        -------
        tuple of numpy.ndarray
            ``dP/de1, dP/de2`` per unit e^3.
        """
        e1, e2 = np.broadcast_arrays(np.asarray(e1, dtype=float), np.asarray(e2, dtype=float))
        r = np.hypot(e1, e2)
        ok = (r > 0) & (r < 1.0)
        g = np.zeros(r.shape)
        rr = r[ok]
        p = np.exp(self._log_f(rr) - self._log_norm)
        g[ok] = p * self._dlogf_dr(rr) / rr
        return g * e1, g * e2

    def radial_pdf(self, r: np.ndarray | float) -> np.ndarray:
        """1-D density of ``|e|``, ``2 pi |e| P(|e|)`` (paper section 3.1), per unit ``|e|``."""
        r = np.asarray(r, dtype=float)
        return 2.0 * np.pi * r * self.pdf(r, np.zeros_like(r))

    def grid_pdf(self) -> np.ndarray:
        """:meth:`pdf` on :attr:`egrid`, shape ``(n_e,)``; sums to ``1 / de^2``."""
        return self.pdf(self.egrid[:, 0], self.egrid[:, 1])

    def sample(self, n: int, *, rng: np.random.Generator) -> np.ndarray:
        """Draw ellipticities from the continuous prior.

        ``|e|`` is drawn by inverse CDF of ``2 pi |e| P(|e|)`` tabulated on a fine radial
        grid (20,001 points on ``[0, 1]``), the angle ``2 phi`` uniformly.

        Parameters
        ----------
        n : int
            Number of draws.
        rng : numpy.random.Generator
            Random generator (explicit, for reproducibility).

        Returns
        -------
        numpy.ndarray
            ``(n, 2)`` array of ``(e1, e2)``.
        """
        rgrid = np.linspace(0.0, 1.0, 20001)
        dens = np.zeros_like(rgrid)
        dens[:-1] = self.radial_pdf(rgrid[:-1])
        cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(rgrid))])
        cdf /= cdf[-1]
        r = np.interp(rng.random(n), cdf, rgrid)
        phi = rng.uniform(0.0, 2.0 * np.pi, n)
        return np.column_stack([r * np.cos(phi), r * np.sin(phi)])

    # -- persistence ------------------------------------------------------------------
    def form_dict(self) -> dict[str, Any]:
        """The form and its parameters (``form`` and ``B, C, D`` or ``coef``)."""
        raise NotImplementedError

    def on_grid(self, egrid: np.ndarray) -> RadialPrior:
        """The same prior normalised on another grid ``egrid`` (``(n_e, 2)``)."""
        d = self.form_dict()
        return type(self)(**{k: d[k] for k in self._KEYS}, egrid=egrid, method=self.method,
                          history=self.history, info=self.info)  # fmt: skip

    def header_cards(self) -> list[tuple[str, float | str, str]]:
        """``(keyword, value, comment)`` FITS cards that describe the prior."""
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (form, parameters, grid step, method, history, info)."""
        d: dict[str, Any] = {
            **self.form_dict(),
            "step": self.step,
            "method": self.method,
            "history": self.history,
            "info": jsonable(self.info),
        }
        std = ellipticity_grid(self.step)
        if std.shape != self.egrid.shape or not np.allclose(std, self.egrid, atol=1e-12):
            d["egrid"] = self.egrid.tolist()
        return d

    def save(self, path: str | Path) -> None:
        """Write the prior to a small JSON file (parameters, grid step, history)."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=1))

    @classmethod
    def load(cls, path: str | Path) -> RadialPrior:
        """Read a prior written by :meth:`save` (either form).

        Raises
        ------
        ValueError
            One line naming the file: unreadable, not JSON, or not a prior.
        """
        return cls.from_dict(read_json(path), source=str(path))

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "prior dict") -> RadialPrior:
        """The prior of :meth:`to_dict`, of the form it names (``"form"``; functional
        where absent).

        Parameters
        ----------
        d : dict
            The functional form's ``B``, ``C``, ``D`` or the spline's ``coef``, and
            ``step`` (or ``egrid``); optionally ``method``, ``history`` and ``info``.
        source : str
            What ``d`` came from (a file name), for the error message.

        Raises
        ------
        ValueError
            One line naming ``source`` if ``d`` is not a prior.
        """
        what = f"{source}: not an ellipticity prior"
        if not isinstance(d, dict):
            raise ValueError(f"{what} (a JSON {json_kind(d)}; a prior holds B, C, D and step "
                             "or coef and step)")  # fmt: skip
        form = d.get("form", Prior.form)
        kinds = {Prior.form: Prior, SplinePrior.form: SplinePrior}
        if form not in kinds or (cls is not RadialPrior and kinds[form] is not cls):
            raise ValueError(f"{what} of form {cls.form!r} (form {form!r})")
        kind = kinds[form]
        need = f"a {form} prior holds {', '.join(kind._KEYS)} and step"
        missing = [k for k in kind._KEYS if k not in d]
        if "step" not in d and "egrid" not in d:
            missing.append("step")
        if missing:
            hint = other_file_hint(d, {"priors": "priors", "size_prior": "size prior"})
            raise ValueError(f"{what} (no entry {', '.join(map(repr, missing))}; {need}{hint})")
        try:
            egrid = np.asarray(d["egrid"], dtype=float) if "egrid" in d else None
            if egrid is not None:
                egrid = check_egrid(egrid)
            return kind(
                **{k: d[k] for k in kind._KEYS},
                step=None if egrid is not None else d["step"],
                egrid=egrid,
                method=str(d.get("method", "fixed")),
                history=d.get("history") or [],
                info=d.get("info") or {},
            )
        except (TypeError, ValueError) as err:
            raise ValueError(f"{what} ({err})") from None


class Prior(RadialPrior):
    """The functional ellipticity prior (docs: method, eq-funcprior), normalised on a grid.

    Parameters
    ----------
    B, C, D : float
        Parameters of the functional prior (docs: method, eq-funcprior; dimensionless).
        The defaults (0.19, 0.58, 2.4) describe a STEP-like population. They must
        satisfy :func:`prior_is_valid`.
    step : float, optional
        Cell side ``de`` of the normalisation grid (default 0.1, the paper's grid).
        Ignored when ``egrid`` is given.
    egrid : numpy.ndarray, optional
        ``(n_e, 2)`` grid of cell centres (from :func:`pylensfit.ellipticity_grid`) on
        which the prior is normalised.

    Attributes
    ----------
    B, C, D : float
        The parameters; ``egrid``, ``step`` and ``A`` as for :class:`RadialPrior`.
    method : str
        How the parameters were obtained: ``"fixed"`` (given), ``"direct"``, ``"em"`` or
        ``"cross-entropy"`` (fitted to a gridded distribution).
    history : list of dict
        One entry per estimation step: ``iteration``, ``B``, ``C``, ``D`` and
        ``marginal_lnL`` (``sum_a w_a ln sum_e P L_a de^2``, with each ``L_a`` scaled to a
        maximum of 1), where computed.
    info : dict
        Bookkeeping of the estimation: ``n_used``, ``n_excluded`` (rows rejected as
        unusable), ``at_bound`` (parameters that ended on a bound), ``converged``, ...
    """

    form = "functional"
    _KEYS = ("B", "C", "D")

    def __init__(
        self,
        *,
        B: float = DEFAULT_PARAMS[0],
        C: float = DEFAULT_PARAMS[1],
        D: float = DEFAULT_PARAMS[2],
        step: float | None = None,
        egrid: np.ndarray | None = None,
        method: str = "fixed",
        history: Sequence[dict[str, Any]] | None = None,
        info: dict[str, Any] | None = None,
    ) -> None:
        B, C, D = float(B), float(C), float(D)
        if not prior_is_valid(B, C, D):
            raise ValueError(
                f"prior parameters (B, C, D) = ({B:g}, {C:g}, {D:g}) are outside the allowed "
                f"region (box {PRIOR_BOUNDS} plus the positivity / no-turning-point conditions "
                "of prior_is_valid)"
            )
        self.B, self.C, self.D = B, C, D
        self._normalise(step, egrid, method, history, info)

    def _log_f(self, r: np.ndarray) -> np.ndarray:
        return _log_f(r, self.B, self.C, self.D)

    def _dlogf_dr(self, r: np.ndarray) -> np.ndarray:
        return _dlogf_dr(r, self.B, self.C, self.D)

    @property
    def params(self) -> tuple[float, float, float]:
        """``(B, C, D)``."""
        return (self.B, self.C, self.D)

    def form_dict(self) -> dict[str, Any]:
        return {"form": self.form, "B": self.B, "C": self.C, "D": self.D}

    def header_cards(self) -> list[tuple[str, float | str, str]]:
        return [("PRIORFRM", self.form, "ellipticity prior form"),
                ("PRIOR_B", self.B, "prior B (Kitching et al. 2008, section 3.1)"),
                ("PRIOR_C", self.C, "prior C"), ("PRIOR_D", self.D, "prior D")]  # fmt: skip

    def __repr__(self) -> str:
        return (
            f"Prior(B={self.B:.4g}, C={self.C:.4g}, D={self.D:.4g}, step={self.step:g}, "
            f"method={self.method!r})"
        )


#: Knots of :class:`SplinePrior`'s cubic B-spline in ``|e|``: uniform on ``[0, 1]`` with
#: interior knots every 0.2, eight coefficients. Finer than the likelihoods resolve on the
#: paper's grid (cells 0.1 wide, likelihood widths 0.1-0.3) would only add noise.
SPLINE_KNOTS = np.concatenate([[0.0] * 4, [0.2, 0.4, 0.6, 0.8], [1.0] * 4])
#: Default weight of :class:`SplinePrior`'s roughness penalty (see :func:`estimate_prior`).
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
    target = _log_f(r, *DEFAULT_PARAMS) - np.log(np.cos(0.5 * np.pi * r))
    c = np.linalg.lstsq(_spline_design(r), target, rcond=None)[0]
    return c - c.mean()


def _roughness() -> np.ndarray:
    """``D^T D`` with ``D`` the second differences of the spline's coefficients."""
    k = len(SPLINE_KNOTS) - 4
    d2 = np.diff(np.eye(k), n=2, axis=0)
    return d2.T @ d2


def _prior_spline(L: np.ndarray, w: np.ndarray, r: np.ndarray, c0: np.ndarray, n_iter: int,
                  tol: float, smoothing: float, record) -> tuple[np.ndarray, bool]:  # fmt: skip
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


def _estimate_spline(L, w, r, egrid, start, n_iter, tol, smoothing, n_excl) -> SplinePrior:
    """:func:`estimate_prior` with ``form="spline"`` on the prepared sample."""
    c0 = _spline_start() if start is None else np.asarray(start, dtype=float)
    if c0.shape != (len(SPLINE_KNOTS) - 4,):
        c0 = _spline_start()  # a functional start (B, C, D): the default shape instead
    history: list[dict[str, Any]] = []

    def record(it: int, c: np.ndarray, ell: float) -> None:
        history.append({"iteration": it, "coef": [float(v) for v in c], "marginal_lnL": ell})

    c, converged = _prior_spline(L, w, r, c0, 500 if n_iter is None else int(n_iter),
                                 min(tol, 1e-9), float(smoothing), record)  # fmt: skip
    return SplinePrior(coef=c, egrid=egrid, method="direct", history=history,
                       info={"n_used": int(L.shape[0]), "n_excluded": n_excl, "at_bound": [],
                             "converged": converged, "n_steps": history[-1]["iteration"],
                             "smoothing": float(smoothing)})  # fmt: skip


# ----------------------------------------------------------------------------------------
# Input checking
# ----------------------------------------------------------------------------------------
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


def _prepare(lnL, egrid, weights):
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
    return egrid, L, w, ok, n_excl


# ----------------------------------------------------------------------------------------
# Objectives
# ----------------------------------------------------------------------------------------
def _grid_logq(r: np.ndarray, x: np.ndarray):
    """Log cell probabilities ``ln(P de^2)`` on the grid and their derivatives.

    ``x = (ln B, ln C, ln D)``. Returns ``logq (n_e,)`` and ``dlogq (3, n_e)``.
    """
    B, C, D = np.exp(x)
    lf = _log_f(r, B, C, D)
    m = float(np.max(lf))
    q = np.exp(lf - m)
    z = float(np.sum(q))
    q /= z
    logq = lf - m - math.log(z)
    dlf = _dlogf_dlogparams(r, B, C, D)
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
    egrid, L, w, _, _ = _prepare(lnL, egrid, weights)
    p = prior.on_grid(egrid).grid_pdf()
    q = p / p.sum()
    return float(w @ np.log(np.maximum(L @ q, 1e-300)))


def _slsqp(fun_and_grad, x0: np.ndarray, *, ftol: float, maxiter: int, callback=None):
    cons = {"type": "ineq", "fun": lambda x: _constraints(*np.exp(x))}
    return optimize.minimize(
        fun_and_grad,
        x0,
        jac=True,
        method="SLSQP",
        bounds=_LOG_BOUNDS,
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
    for name, xi, (lo, hi) in zip(_NAMES, x, _LOG_BOUNDS, strict=True):
        if xi <= lo + 1e-6 or xi >= hi - 1e-6:
            out.append(name)
    B, C, D = np.exp(x)
    c = _constraints(B, C, D)
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
    x = np.clip(res.x, [b[0] for b in _LOG_BOUNDS], [b[1] for b in _LOG_BOUNDS])
    if not prior_is_valid(*np.exp(x)):  # the optimiser may end a hair outside
        x = x0
    return x, float(fun(x)[0])


# ----------------------------------------------------------------------------------------
# Estimation from the likelihood grids
# ----------------------------------------------------------------------------------------
def _prior_em(L: np.ndarray, w: np.ndarray, r: np.ndarray, x: np.ndarray, n_iter: int,
              tol: float, history: list[dict[str, Any]], record,
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
                  tol: float, history: list[dict[str, Any]], record,
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
    xr = np.clip(res.x, [b[0] for b in _LOG_BOUNDS], [b[1] for b in _LOG_BOUNDS])
    candidates = [(-fun(xr)[0] * wsum, xr)] + [
        (h["marginal_lnL"], np.log([h[k] for k in _NAMES])) for h in history
    ]
    valid = [(ell, xx) for ell, xx in candidates if prior_is_valid(*np.exp(xx))]
    x = max(valid, key=lambda c: c[0])[1]
    if not np.allclose(np.log([history[-1][k] for k in _NAMES]), x, rtol=0, atol=1e-12):
        record(len(history), x, -fun(x)[0] * wsum)
    return x, bool(res.success)


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
      form (:func:`fit_functional_prior`). This is the EM algorithm for ``(B, C, D)``: each
      step cannot decrease ``l``, and its fixed point is a maximum of ``l``.
    - ``"direct"`` (default): maximise ``l`` over ``(ln B, ln C, ln D)`` with scipy's SLSQP
      and the analytic gradient. It reaches the same fixed point in one go, whereas EM
      creeps towards it when the likelihoods are broad (its rate is set by the fraction of
      information the noise hides; at widths 0.1-0.3 many tens of steps are needed),
      so direct is the default.

    The parameters are degenerate (``B`` and ``C`` trade off) while the shape of ``P`` is
    well determined: judge convergence by ``l`` or by the prior's values. The recovered
    prior is limited by sampling noise: with likelihood widths 0.1-0.3 its fractional
    residual rms (where ``P`` exceeds 5% of its peak) is ~0.01-0.035 from 30,000 galaxies
    and ~0.04 from 3,000.

    With ``form="spline"`` the prior is a :class:`SplinePrior`, whose eight coefficients
    ``c`` maximise ``l(c) - (smoothing / 2) |D c|^2`` (``D`` their second differences, a
    roughness penalty that matters only where few galaxies constrain the shape) by
    L-BFGS with the analytic gradient; it has no bound to end on. ``method`` must then
    be ``"direct"``.

    Memory: the likelihoods are held as one float64 ``(n_gal, n_e)`` array
    (2.5 kB per galaxy on the paper's grid); each step costs one product with it.

    Parameters
    ----------
    lnL : numpy.ndarray
        ``(n_gal, n_e)`` natural-log likelihood on ``egrid`` (float32 allowed). Each row
        is shifted by its own maximum here. Rows that contain NaN or ``+inf``, or are all
        ``-inf``, are excluded (counted in ``prior.info["n_excluded"]``, no warning).
    egrid : numpy.ndarray
        ``(n_e, 2)`` grid of cell centres (:func:`pylensfit.ellipticity_grid`).
    method : {"direct", "em"}
        Estimation method.
    form : {"functional", "spline"}
        The prior's form: :class:`Prior` (Kitching et al. 2008's, eq-funcprior) or the
        flexible :class:`SplinePrior`.
    smoothing : float
        ``form="spline"``: weight of the roughness penalty (dimensionless, per sample).
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
    if method not in ("direct", "em"):
        raise ValueError(f"method must be 'direct' or 'em', got {method!r}")
    if form not in ("functional", "spline"):
        raise ValueError(f"form must be 'functional' or 'spline', got {form!r}")
    if form == "spline" and method != "direct":
        raise ValueError("the spline prior is estimated by method 'direct' only")
    egrid, L, w, _, n_excl = _prepare(lnL, egrid, weights)
    r = np.hypot(egrid[:, 0], egrid[:, 1])
    if form == "spline":
        return _estimate_spline(L, w, r, egrid, start, n_iter, tol, smoothing, n_excl)
    x = _start_x(start)
    history: list[dict[str, Any]] = []

    def record(it: int, xx: np.ndarray, ell: float) -> None:
        B, C, D = np.exp(xx)
        history.append(
            {"iteration": it, "B": float(B), "C": float(C), "D": float(D), "marginal_lnL": ell}
        )

    if method == "em":
        x, converged = _prior_em(L, w, r, x, 10 if n_iter is None else int(n_iter), tol,
                                 history, record)  # fmt: skip
    else:
        x, converged = _prior_direct(L, w, r, x, 200 if n_iter is None else int(n_iter),
                                     tol, history, record)  # fmt: skip
    n_steps = len(history) - 1

    bounds_hit = _at_bound(x)
    if bounds_hit:
        log.warning(
            "prior estimate ended on a bound (%s): the sample may be too small or too noisy "
            "to fix the prior's shape",
            ", ".join(bounds_hit),
        )
    B, C, D = np.exp(x)
    return Prior(
        B=B,
        C=C,
        D=D,
        egrid=egrid,
        method=method,
        history=history,
        info={
            "n_used": int(L.shape[0]),
            "n_excluded": n_excl,
            "at_bound": bounds_hit,
            "converged": converged,
            "n_steps": n_steps,
        },
    )


# ----------------------------------------------------------------------------------------
# A population prior over the bulge fraction
# ----------------------------------------------------------------------------------------
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
# ----------------------------------------------------------------------------------------
def _node_sizes(bank, config) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per size node of an e cell: ``r``, its quadrature weight and half-light radius."""
    n_b = bank.n_r // bank.n_sizes
    runs = config.bulge_runs
    if len(runs) != n_b:
        raise ValueError(f"the model bank has {n_b} runs of sizes, the configuration {len(runs)}")
    if n_b == 1:
        unit = np.array([half_light_radius(bank.model, bulge_fraction=float(runs[0].fraction),
                                           bulge_size_ratio=float(runs[0].size))])
    else:
        unit = np.array([run_half_light_radius(run) for run in runs])
    r = np.asarray(bank.radii, float)
    r_w = np.tile(np.asarray(bank.r_weights, float), n_b)
    return r, r_w, r * np.repeat(unit, bank.n_sizes)


def _node_basis(h: np.ndarray, n_sizes: int, knots: np.ndarray) -> np.ndarray:
    """``(n_nodes, K)``: the mean of each knot's hat function over each node's hat.

    A density ``p`` linear between ``knots`` (0 outside, as :meth:`SizePrior.pdf`) is
    ``sum_k p_k hat_k``. Node ``j`` of a run of sizes (``n_sizes`` increasing ``h``)
    reads the prior as its mean ``pbar_j`` over a symmetric hat in ``ln h`` whose
    half-width is the node's spacing ``(ln h_{j+1} - ln h_{j-1}) / 2`` (the neighbour's
    spacing mirrored at the run's ends): ``p(h_j)`` to ``delta^2 p'' / 12`` where the
    prior is smooth, and the share of the node's hat inside where a box's edge cuts
    between nodes, so that the sum over the grid moves smoothly with the edge instead of
    in node-sized jumps.
    Row ``j`` holds ``int hat_k phi_j / int phi_j``; two-point Gauss-Legendre on every
    interval between the knots and the hat's corners is exact for these products of
    linear functions.
    """
    knots = np.asarray(knots, dtype=float)
    x = np.log(np.asarray(h, dtype=float))
    out = np.empty((x.size, knots.size))
    for s0 in range(0, x.size, n_sizes):
        c = x[s0 : s0 + n_sizes]
        if c.size > 1:
            ext = np.concatenate([[2 * c[0] - c[1]], c, [2 * c[-1] - c[-2]]])
            d = 0.5 * (ext[2:] - ext[:-2])
        else:
            d = np.array([0.05])
        # every function here is linear between these points
        b = np.unique(np.concatenate([c - d, c, c + d, knots]))
        mid, half = 0.5 * (b[1:] + b[:-1]), 0.5 * np.diff(b)
        t = np.concatenate([mid - half / np.sqrt(3.0), mid + half / np.sqrt(3.0)])
        wt = np.concatenate([half, half])
        phi = np.maximum(1.0 - np.abs(t[None] - c[:, None]) / d[:, None], 0.0) * wt
        # the knots' hats at t: two neighbours each, none outside the knots
        i = np.clip(np.searchsorted(knots, t) - 1, 0, knots.size - 2)
        f = (t - knots[i]) / (knots[i + 1] - knots[i])
        inside = (t >= knots[0]) & (t <= knots[-1])
        H = np.zeros((t.size, knots.size))
        H[np.arange(t.size), i] = np.where(inside, 1.0 - f, 0.0)
        H[np.arange(t.size), i + 1] = np.where(inside, f, 0.0)
        out[s0 : s0 + c.size] = phi @ H / d[:, None]
    return out


@dataclass(frozen=True)
class SizePrior:
    """Population prior of the galaxies' half-light radius, and of point sources.

    The paper sums ``L(e, r)`` over ``r`` with a uniform prior. A faint galaxy's
    likelihood in size is broad, and which sizes the sum weights moves its ``L(e)``: for
    de Vaucouleurs galaxies at S/N 10-20 fitted with their exact profile, the uniform
    prior gives ``m = -0.074 ± 0.021``, the estimated one ``-0.049 ± 0.021`` (400
    galaxies, paired, true ellipticity prior). This prior is estimated from the data
    (:func:`estimate_size_prior`), as the ellipticity prior is.

    Attributes
    ----------
    ln_h : numpy.ndarray
        ``(K,)`` evenly spaced knots in ``ln`` of the half-light radius (pixels).
    density : numpy.ndarray
        ``(K,)`` the density per unit ``ln h`` at the knots, linear between them and 0
        outside; integrates to ``1 - star``. Or ``(n_runs, K)``: one density per run of
        the model family (bulge fraction), each integrating to ``1 - star``, the size
        prior conditional on the run (:func:`estimate_size_prior` with ``per_run``); the
        runs' shares stay the bulge weights'.
    star : float
        Prior probability of a point source.
    smoothing : float, optional
        The EMS smoothing of the estimate (:func:`estimate_size_prior`), where known.
    """

    ln_h: np.ndarray
    density: np.ndarray
    star: float = 1e-6
    smoothing: float | None = None

    @property
    def per_run(self) -> bool:
        """Whether the prior holds one density per run of the model family."""
        return np.ndim(self.density) == 2

    def pdf(self, h) -> np.ndarray:
        """Density per unit ``ln h`` at half-light radii ``h`` (pixels); with one density
        per run, ``(n_runs,) + h.shape``."""
        with np.errstate(divide="ignore"):
            x = np.log(np.asarray(h, dtype=float))
        if self.per_run:
            return np.stack([np.interp(x, self.ln_h, d, left=0.0, right=0.0)
                             for d in self.density])  # fmt: skip
        return np.interp(x, self.ln_h, self.density, left=0.0, right=0.0)

    def marginal(self, weights=None) -> np.ndarray:
        """``(K,)`` the density over all runs, each weighted by ``weights`` (the bulge
        weights; equal by default); a single density as it is."""
        if not self.per_run:
            return np.asarray(self.density, dtype=float)
        d = np.asarray(self.density, dtype=float)
        w = np.full(d.shape[0], 1.0 / d.shape[0]) if weights is None else np.asarray(weights, float)
        if w.shape != (d.shape[0],):
            raise ValueError(f"{d.shape[0]} runs in the size prior, {w.size} weights")
        return (w / w.sum()) @ d

    def to_dict(self) -> dict[str, Any]:
        """JSON-able parameters (:meth:`from_dict` inverts it)."""
        return {"ln_h": [float(v) for v in self.ln_h],
                "density": np.asarray(self.density, dtype=float).tolist(),
                "star": float(self.star),
                **({} if self.smoothing is None
                   else {"smoothing": float(self.smoothing)})}  # fmt: skip

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "size prior dict") -> SizePrior:
        """The prior of :meth:`to_dict`.

        Parameters
        ----------
        d : dict
            ``ln_h`` and ``density``; optionally ``star`` and ``smoothing``.
        source : str
            What ``d`` came from (a file name), for the error message.

        Raises
        ------
        ValueError
            One line naming ``source`` if ``d`` is not a size prior.
        """
        what = f"{source}: not a size prior"
        if not isinstance(d, dict):
            raise ValueError(f"{what} (a JSON {json_kind(d)}; a size prior holds ln_h and "
                             "density)")  # fmt: skip
        missing = [k for k in ("ln_h", "density") if k not in d]
        if missing:
            raise ValueError(f"{what} (no entry {', '.join(map(repr, missing))}; a size prior "
                             f"holds ln_h and density{other_file_hint(d, {})})")  # fmt: skip
        try:
            ln_h = np.asarray(d["ln_h"], dtype=float)
            dens = np.asarray(d["density"], dtype=float)
            star = float(d.get("star", 1e-6))
            sm = d.get("smoothing")
            sm = None if sm is None else float(sm)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{what} ({err})") from None
        if ln_h.ndim != 1 or dens.ndim not in (1, 2) or dens.shape[-1] != ln_h.size \
                or ln_h.size < 2:
            raise ValueError(f"{what} (it needs ln_h and density (one row per run, or one) "
                             "of the same length >= 2)")  # fmt: skip
        if not (np.all(np.isfinite(ln_h)) and np.all(np.diff(ln_h) > 0)
                and np.all(np.isfinite(dens)) and np.all(dens >= 0)
                and np.all(dens.reshape(-1, ln_h.size).sum(axis=1) > 0)):
            raise ValueError(f"{what} (it needs increasing ln_h and a non-negative density)")
        if not 0 <= star < 1:
            raise ValueError(f"{what} (star must be in [0, 1), got {star:g})")
        return cls(ln_h=ln_h, density=dens, star=star, smoothing=sm)

    def save(self, path: str | Path) -> None:
        """Write the prior as JSON."""
        Path(path).write_text(json.dumps({"size_prior": self.to_dict()}, indent=1))

    @classmethod
    def load(cls, path: str | Path) -> SizePrior:
        """Read a prior written by :meth:`save`.

        Raises
        ------
        ValueError
            One line naming the file: unreadable, not JSON, or not a size prior.
        """
        d = read_json_entry(path, "size_prior", "size prior", {"priors": "priors", "B": "prior"})
        return cls.from_dict(d, source=str(path))

    def node_weights(self, bank, config) -> tuple[np.ndarray, float]:
        """Weights of the model bank's sizes and of the point source in the sum over r.

        Node ``j`` (size ``r_j``, quadrature weight ``w_j``, half-light radius ``h_j``)
        gets the prior mass ``w_j pbar_j / r_j`` (``d ln h = dr / r``), ``pbar_j`` the
        prior's average over the node's hat in ``ln h`` (:func:`_node_basis`: ``p(h_j)``
        where the prior is smooth, the exact share of an edge that cuts between nodes).

        The tails, below ``config.size_prior_cut`` times the largest mass, are treated
        apart. Below the prior's mode the mass is floored there: sizes well under the
        PSF's are hard to tell apart, and what the prior holds there is the estimate's
        smoothing more than the data; those compact models keep a say in a bright
        galaxy's ``L(e)`` near ``|e| = 1``; without them (no floor and no tail cut,
        ``size_prior_cut=0``) ``m`` moves by less than 0.0005, paired
        (``benchmarks/studies/precision_ab.py --b size_prior_cut=0``). Above the mode
        the sizes are resolved, and the nodes in the tail get 0: the fit leaves them out
        of the sum over r and does not evaluate their models (a disc's largest sizes, a
        fifth of the bank in the precision mode).

        The floored nodes are summed on a coarser grid, every
        ``config.size_prior_floor_stride``-th size of the bank (the same sizes for every
        bulge fraction, so that a mixed fraction's columns are the pure ones' at the
        same size), each carrying the floor's mass of the floored nodes nearest to it:
        the total mass is unchanged, and the fit evaluates a third of those models with
        the default stride of three (in the precision mode 15 % of the models with the
        estimated size priors, a third with the population's own). The models there are
        compact and weigh 1e-4 of the prior's peak; the coarser sum moved the precision
        run's ``m`` by 1e-5 (``benchmarks/studies/precision_ab.py``). A bright galaxy
        far below the prior, whose size those models resolve, is the case it is not for.
        """
        r, r_w, h = _node_sizes(bank, config)
        basis = _node_basis(h, bank.n_sizes, self.ln_h)
        if self.per_run:
            n_b = bank.n_r // bank.n_sizes
            dens = np.asarray(self.density, dtype=float)
            if dens.shape[0] != n_b:
                raise ValueError(f"the size prior has {dens.shape[0]} runs, the model bank {n_b}")
            run = np.repeat(np.arange(n_b), bank.n_sizes)
            w = r_w * np.einsum("jk,jk->j", basis, dens[run]) / r
            mode = np.exp(self.ln_h[np.argmax(dens, axis=1)])[run]
            # each run's tails against its own largest mass
            top = w.reshape(n_b, bank.n_sizes).max(axis=1)[run]
        else:
            w = r_w * (basis @ self.density) / r
            mode = np.exp(self.ln_h[np.argmax(self.density)])
            top = w.max()
        if not w.max() > 0:
            raise ValueError("the size prior has no mass on the model bank's sizes")
        tail = config.size_prior_cut * top
        above = h > mode
        floored = ~above & (w < tail)
        w = np.where(above, np.where(w >= tail, w, 0.0), np.maximum(w, tail))
        stride = int(getattr(config, "size_prior_floor_stride", 1))
        if stride > 1 and floored.any():
            w = _thin_floor(w, floored, bank.n_sizes, stride)
        return w, float(max(self.star, 1e-12))


def _thin_floor(w: np.ndarray, floored: np.ndarray, n_sizes: int, stride: int) -> np.ndarray:
    """:meth:`SizePrior.node_weights`' floored nodes on every ``stride``-th size.

    In each run of ``n_sizes`` sizes (a bulge fraction), the floored nodes at size
    index ``j`` with ``j % stride == stride - 1`` are kept; every other floored node
    gives its weight to the kept one nearest to it in the run (the larger on a tie) and
    gets 0. A run whose floored nodes include none of those indices keeps them all.
    """
    w = np.array(w, dtype=float)
    for run in range(w.size // n_sizes):
        seg = w[run * n_sizes:(run + 1) * n_sizes]  # a view
        f = np.flatnonzero(floored[run * n_sizes:(run + 1) * n_sizes])
        kept = f[f % stride == stride - 1]
        if kept.size == 0:
            continue
        pos = np.clip(np.searchsorted(kept, f), 1, kept.size)
        lo, hi = kept[pos - 1], kept[np.minimum(pos, kept.size - 1)]
        near = np.where(np.abs(f - lo) < np.abs(hi - f), lo, hi)  # ties: the larger size
        mass = np.zeros(n_sizes)
        np.add.at(mass, near, seg[f])
        seg[f] = 0.0
        seg[kept] = mass[kept]
    return w


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
    comp, knots, n_blk, w0 = _size_mixture(lnL_r, bank, config, bulge_weights, knot_step,
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
    comp, _, n_blk, w0 = _size_mixture(lnL_r, bank, config, bulge_weights, knot_step, per_run)
    return _cross_validate(comp, n_blk, w0, tuple(cand), folds, seed)


def _cross_validate(comp: np.ndarray, n_blk: int, w0: np.ndarray, candidates, folds: int,
                    seed: int) -> tuple[float, np.ndarray]:
    """:func:`select_size_prior_smoothing` on the mixture of :func:`_size_mixture`."""
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


def _size_mixture(lnL_r, bank, config, bulge_weights, knot_step: float, per_run: bool):
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
    r, r_w, h = _node_sizes(bank, config)
    n_b = n_r // bank.n_sizes
    pi = np.full(n_b, 1.0 / n_b) if bulge_weights is None else np.asarray(bulge_weights, float)
    lo, hi = np.log(h.min()) - knot_step, np.log(h.max()) + knot_step
    knots = np.arange(lo, hi + knot_step, knot_step)
    B = _node_basis(h, bank.n_sizes, knots)  # each knot's share of each node: B[j, k]
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


def estimate_flux_slope(
    flux: np.ndarray, *, quantiles: tuple[float, float] = (0.3, 0.95)
) -> tuple[float, float]:
    """The power ``beta`` of the number counts ``dN/dF ~ F^-beta`` from measured fluxes.

    The maximum-likelihood power law truncated to ``[a, b]``, the ``quantiles`` of the
    fluxes: within it the counts are a power law whatever happens outside (the faint
    end's noise and incompleteness, a bright cut-off), so the estimate needs neither.
    With ``x = ln(F / a)`` on ``[0, L = ln(b / a)]`` the law is a truncated exponential
    of rate ``lambda = beta - 1``, and the likelihood equation is ``mean(x) = 1/lambda -
    L / (exp(lambda L) - 1)`` (``L / 2`` at ``lambda = 0``). This is the amplitude
    prior's power for ``Config(amplitude_prior="flux")``.

    Parameters
    ----------
    flux : array_like
        Measured fluxes (any units); non-finite and non-positive values are ignored.
    quantiles : tuple of float
        The fluxes' quantiles that bound the range fitted.

    Returns
    -------
    beta, beta_err : float
        The power and its 1-sigma error (Fisher information of the truncated law).
    """
    f = np.asarray(flux, dtype=float).ravel()
    f = f[np.isfinite(f) & (f > 0)]
    lo_q, hi_q = quantiles
    if not 0 <= lo_q < hi_q <= 1:
        raise ValueError(f"quantiles must satisfy 0 <= lower < upper <= 1, got {quantiles}")
    if f.size < 20:
        raise ValueError(f"{f.size} usable fluxes: too few to estimate the counts' slope")
    a, b = np.quantile(f, [lo_q, hi_q])
    if not b > a:
        raise ValueError("the fluxes' quantiles coincide: no range to fit a slope on")
    x = np.log(f[(f >= a) & (f <= b)] / a)
    L = float(np.log(b / a))
    xbar = float(x.mean())

    def mean_x(lam: float) -> float:  # E[x] of the truncated exponential of rate lam
        u = lam * L
        if abs(u) < 1e-6:
            return L / 2 - lam * L * L / 12
        return 1.0 / lam - L / np.expm1(u)

    def var_x(lam: float) -> float:
        u = lam * L
        if abs(u) < 1e-6:
            return L * L / 12
        return 1.0 / lam**2 - L * L * np.exp(u) / np.expm1(u) ** 2

    # mean_x falls monotonically from L (lam -> -inf) to 0 (lam -> +inf)
    span = 200.0 / L
    lam = optimize.brentq(lambda v: mean_x(v) - xbar, -span, span, xtol=1e-12)
    return 1.0 + lam, float(1.0 / np.sqrt(x.size * var_x(lam)))


def _flux_range_loglike(f: np.ndarray, s: np.ndarray, lo: float, hi: float, beta: float,
                        nodes: tuple[np.ndarray, np.ndarray]) -> np.ndarray:  # fmt: skip
    """ln p(f_i) of measured fluxes under ``F^-beta`` on ``[lo, hi]`` and Gaussian errors.

    Each galaxy's integral over the true flux runs over ``[lo, hi]`` within 8 of its
    errors of the measured flux (Gauss-Legendre ``nodes`` on that interval), where all
    of its mass lies; the power law's normalisation on ``[lo, hi]`` is analytic.
    """
    x, w = nodes
    a = np.clip(f - 8.0 * s, lo, hi)
    b = np.clip(f + 8.0 * s, lo, hi)
    half = 0.5 * (b - a)
    F = 0.5 * (a + b)[:, None] + half[:, None] * x[None, :]
    z = (f[:, None] - F) / s[:, None]
    # the power law relative to lo (exponent <= 0), times the Gaussian
    lnterm = -beta * np.log(F / lo) - 0.5 * z * z
    top = lnterm.max(axis=1)
    integ = np.sum(w[None, :] * np.exp(lnterm - top[:, None]), axis=1) * half
    with np.errstate(divide="ignore"):
        ln_int = np.log(integ) + top - np.log(s) - 0.5 * math.log(2.0 * math.pi)
    lam = 1.0 - beta  # normalisation of (F / lo)^-beta on [lo, hi]
    L = math.log(hi / lo)
    norm = lo * L if abs(lam * L) < 1e-8 else lo * math.expm1(lam * L) / lam
    return ln_int - math.log(norm)


#: fewest usable fluxes from which :func:`estimate_flux_range` estimates a range
MIN_FLUX_RANGE_SAMPLE = 50


def estimate_flux_range(
    flux: np.ndarray,
    flux_err: np.ndarray,
    *,
    beta: float | None = None,
    error_scale: float | None = None,
    outlier_fraction: float = 1e-3,
) -> dict[str, float]:
    """The bounds of the flux distribution from measured fluxes with their errors.

    A population whose counts are a power law ``dN/dF ~ F^-beta`` between two limits
    ``[lo, hi]`` (a simulation's flux range; a catalogue cut in true flux) gives
    measured fluxes ``f_i = F_i + n_i`` with Gaussian errors ``sigma_i``. The maximum of
    ``sum_i ln int_lo^hi F^-beta N(f_i; F, sigma_i) dF / Z(lo, hi, beta)`` over
    ``(lo, hi)`` (and ``beta`` unless given) deconvolves the errors: near a limit the
    measured fluxes spill across it by their errors, and the limit sits where the
    counts' edge does. A fraction ``outlier_fraction`` of the density is log-uniform
    over the measured range, so that a few failed fits cannot pin a limit. These are
    the bounds of :class:`~pylensfit.Config`'s ``amplitude_prior_min`` and
    ``amplitude_prior_max``: a flux prior that allows fluxes the population never has
    keeps a weight at the faint end for models that fit a galaxy with less flux than
    it has (``benchmarks/studies/precision_priors.py --flux-bounds``).

    The errors are taken as ``error_scale * flux_err``, the scale fitted with the limits
    unless given. The most likely model's flux has a larger scatter than its
    fixed-model error ``flux / snr``: which size and profile fit best moves with the
    noise, and the flux with them. On exponential and de Vaucouleurs galaxies fitted
    with the bulge+disc family the scatter is 1.6-3.2 times ``flux / snr`` at every
    S/N, and with the errors as given the lower limit came out 8 % below the true one
    (the fluxes' spill below it read as counts), with the fitted scale (2.0) 1.7 %
    below.

    Parameters
    ----------
    flux : array_like
        Measured fluxes (the most likely model's amplitude, ``StampFits.flux``).
    flux_err : array_like
        Their 1-sigma errors (``flux / snr`` for the best model's S/N), up to a common
        factor (``error_scale``).
    beta : float, optional
        The counts' power; fitted together with the bounds if omitted.
    error_scale : float, optional
        The factor on ``flux_err``; fitted together with the bounds if omitted.
    outlier_fraction : float
        Weight of the log-uniform outlier density.

    Returns
    -------
    dict
        ``lo``, ``hi``, ``beta`` and ``error_scale`` (fitted or given), ``n`` (galaxies
        used) and ``lo_err``, ``hi_err`` (1-sigma, marginal: from the inverse of the
        log-likelihood's Hessian).
    """
    f = np.asarray(flux, dtype=float).ravel()
    s = np.asarray(flux_err, dtype=float).ravel()
    if f.shape != s.shape:
        raise ValueError(f"flux and flux_err differ in shape: {f.shape} against {s.shape}")
    ok = np.isfinite(f) & np.isfinite(s) & (s > 0) & (f > 0)
    f, s = f[ok], s[ok]
    if f.size < MIN_FLUX_RANGE_SAMPLE:
        raise ValueError(f"{f.size} usable fluxes: too few to estimate the flux range")
    nodes = np.polynomial.legendre.leggauss(48)
    fmin, fmax = float(f.min()), float(f.max())
    ln_out = math.log(outlier_fraction) - np.log(f * math.log(fmax / fmin))
    b0 = estimate_flux_slope(f)[0] if beta is None else float(beta)
    if error_scale is not None and not error_scale > 0:
        raise ValueError(f"error_scale must be > 0, got {error_scale}")
    lo0, hi0 = float(np.quantile(f, 0.002)), float(np.quantile(f, 0.9995))
    # the parameters: ln lo, ln hi, then ln of the error scale and the power where fitted
    i_k = 2 if error_scale is None else None
    i_b = None if beta is not None else (3 if error_scale is None else 2)

    def nll(p: np.ndarray) -> float:
        lo, hi = math.exp(p[0]), math.exp(p[1])
        bt = b0 if i_b is None else float(p[i_b])
        k = float(error_scale) if i_k is None else math.exp(p[i_k])
        if not hi > lo * 1.01:
            return 1e300
        lp = _flux_range_loglike(f, s * k, lo, hi, bt, nodes) + math.log1p(-outlier_fraction)
        return -float(np.sum(np.logaddexp(lp, ln_out)))

    x0 = ([math.log(lo0), math.log(hi0)] + ([0.0] if i_k is not None else [])
          + ([b0] if i_b is not None else []))  # fmt: skip
    res = optimize.minimize(nll, np.array(x0), method="Nelder-Mead",
                            options={"xatol": 1e-5, "fatol": 1e-4, "maxiter": 4000})  # fmt: skip
    p = res.x
    lo, hi = math.exp(p[0]), math.exp(p[1])
    # the Hessian by central differences; the errors are the marginal ones (the bounds
    # correlate with the power when it is fitted)
    k, h = p.size, 2e-3
    H = np.empty((k, k))
    for i in range(k):
        for j in range(i, k):
            di, dj = np.eye(k)[i] * h, np.eye(k)[j] * h
            H[i, j] = H[j, i] = (nll(p + di + dj) - nll(p + di - dj) - nll(p - di + dj)
                                 + nll(p - di - dj)) / (4 * h * h)  # fmt: skip
    try:
        cov = np.linalg.inv(H)
        var = np.diag(cov)[:2]
    except np.linalg.LinAlgError:
        var = np.full(2, np.nan)
    errs = [math.exp(p[i]) * math.sqrt(var[i]) if var[i] > 0 else math.inf for i in (0, 1)]
    return {"lo": lo, "hi": hi, "beta": b0 if i_b is None else float(p[i_b]),
            "error_scale": float(error_scale) if i_k is None else math.exp(p[i_k]),
            "n": int(f.size), "lo_err": errs[0], "hi_err": errs[1]}  # fmt: skip
