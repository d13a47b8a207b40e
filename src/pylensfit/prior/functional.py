"""The functional ellipticity prior of Kitching et al. (2008): its form and its class.

The prior (arXiv:0802.1528, section 3.1; docs: method, eq-funcprior) is::

    P(e) = A cos(|e| pi / 2) exp[-(2 |e| / (B (1 + |e|^D)))^C],

with ``A`` fixed by the normalisation on the ellipticity grid
(:class:`~pylensfit.prior.radial.RadialPrior`). This module holds the form, its
derivatives, the allowed region of ``(B, C, D)`` (:func:`prior_is_valid`) and
:class:`Prior`; :mod:`pylensfit.prior.fit` estimates its parameters.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from .radial import RadialPrior

#: Box bounds on ``(B, C, D)`` (why these: :data:`pylensfit.prior.PRIOR_BOUNDS`).
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

#: The parameters' names, in the order of ``(B, C, D)``.
PARAM_NAMES = ("B", "C", "D")
#: :data:`PRIOR_BOUNDS` in ``(ln B, ln C, ln D)``, the variables of the fits.
LOG_BOUNDS = [(math.log(PRIOR_BOUNDS[k][0]), math.log(PRIOR_BOUNDS[k][1])) for k in PARAM_NAMES]


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


def log_f(r: np.ndarray, B: float, C: float, D: float) -> np.ndarray:
    """Unnormalised ``ln P`` of the functional prior (eq-funcprior) at radii ``0 <= r < 1``."""
    t, _, _ = _exponent_terms(r, B, C, D)
    return np.log(np.cos(0.5 * np.pi * r)) - t


def dlogf_dr(r: np.ndarray, B: float, C: float, D: float) -> np.ndarray:
    """Radial derivative ``d ln P / d|e|`` (``-inf`` at ``r = 0`` when ``C < 1``)."""
    t, _, rD = _exponent_terms(r, B, C, D)
    with np.errstate(divide="ignore", invalid="ignore"):
        cusp = C * t * (1.0 + (1.0 - D) * rD) / (r * (1.0 + rD))
    cusp = np.where(r > 0, cusp, np.inf if C < 1 else (2.0 / B if C == 1 else 0.0))
    return -0.5 * np.pi * np.tan(0.5 * np.pi * r) - cusp


def dlogf_dlogparams(r: np.ndarray, B: float, C: float, D: float) -> np.ndarray:
    """Derivatives of the unnormalised ``ln P`` w.r.t. ``(ln B, ln C, ln D)``, shape (3, n)."""
    t, lnu, rD = _exponent_terms(r, B, C, D)
    with np.errstate(divide="ignore", invalid="ignore"):
        d_lnc = np.where(r > 0, -C * t * lnu, 0.0)
        d_lnd = np.where(r > 0, D * C * t * rD * np.log(r) / (1.0 + rD), 0.0)
    return np.stack([C * t, d_lnc, d_lnd])


def constraints(B: float, C: float, D: float) -> np.ndarray:
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
    ``|e| = 1`` when ``D > 2``); see :func:`constraints`.

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
    return bool(np.all(constraints(B, C, D) >= -_CONSTRAINT_TOL))


# ----------------------------------------------------------------------------------------
# The prior
# ----------------------------------------------------------------------------------------
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
        return log_f(r, self.B, self.C, self.D)

    def _dlogf_dr(self, r: np.ndarray) -> np.ndarray:
        return dlogf_dr(r, self.B, self.C, self.D)

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

