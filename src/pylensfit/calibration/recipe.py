"""The recipe's passes (:class:`Recipe`, :class:`RecipePass`, :func:`run_recipe`) and its
estimates of the flux, position, ellipticity, bulge-fraction and size priors."""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..config import Config
from ..likelihood import e_annuli, reweight_lnL_r
from ..models import model_bank
from ..prior import (
    Prior,
    RadialPrior,
    SizePrior,
    estimate_bulge_weights,
    estimate_flux_range,
    estimate_flux_slope,
    estimate_prior,
    estimate_prior_and_bulge,
    estimate_size_prior,
    mix_bulge_fractions,
)
from .priors import (
    MIN_GALAXIES,
    MIN_POSITION_SIGMA,
    CalibrationSample,
    CalibrationWarning,
    Priors,
)

log = logging.getLogger(__name__)

def estimate_position_sigma(dx, dy, snr, *, n_bins: int = 8) -> tuple[float | None, float]:
    """The scatter of the catalogue positions about the galaxies' true centres.

    The fitted centre less the catalogue position scatters by the catalogue's own error
    and by the fit's, which falls as ``1 / S/N``. Per bin of S/N the robust variance
    (from the median absolute deviation) of ``dx`` and ``dy`` is fitted as ``s0^2 + a /
    S/N^2`` by weighted least squares; ``s0`` is the part that does not fall with S/N
    (a simulation's sub-pixel offsets, an external catalogue's astrometric scatter), and
    it is the width returned (uniform offsets of +-0.5 px, standard deviation 0.289:
    0.285 estimated from 480 galaxies).

    A catalogue detected on the image itself has no such part: its centroid errors fall
    with S/N as the fit's do, and they are correlated with the fit's (both come from the
    same pixels), so the scatter of the one about the other does not measure them. On
    STEP1-like fields detected by sep the difference scatters by 0.03 px where the
    detections are 0.05-0.28 px from the true centres. Where ``s0^2`` is not larger than
    the S/N term at the sample's median S/N, ``a / S/N_med^2``, no width is returned and
    the configured one (a broad prior) is kept.

    Parameters
    ----------
    dx, dy : array_like
        Fitted centre less catalogue position, pixels.
    snr : array_like
        Matched-filter S/N of each galaxy's best model.
    n_bins : int
        Quantile bins of S/N.

    Returns
    -------
    sigma : float or None
        The width (pixels, at least :data:`MIN_POSITION_SIGMA`), or None when the
        scatter has no part that does not fall with S/N.
    a : float
        The fitted ``a`` (px^2).
    """
    dx, dy, snr = (np.asarray(v, dtype=float).ravel() for v in (dx, dy, snr))
    ok = np.isfinite(dx) & np.isfinite(dy) & np.isfinite(snr) & (snr > 0)
    dx, dy, snr = dx[ok], dy[ok], snr[ok]
    if dx.size < 2 * n_bins:
        raise ValueError(f"{dx.size} galaxies: too few to estimate the position prior")
    edges = np.quantile(snr, np.linspace(0, 1, n_bins + 1))
    idx = np.clip(np.searchsorted(edges, snr, side="right") - 1, 0, n_bins - 1)
    X, y, w = [], [], []
    for k in range(n_bins):
        s = idx == k
        if s.sum() < 8:
            continue
        d = np.concatenate([dx[s] - np.median(dx[s]), dy[s] - np.median(dy[s])])
        d = d[np.abs(d) <= 5 * 1.4826 * np.median(np.abs(d))]  # failed centres out
        v = float(np.mean(d**2))
        X.append([1.0, float(np.mean(1.0 / snr[s] ** 2))])
        y.append(v)
        w.append(d.size / max(v, 1e-12) ** 2)  # var(v) ~ 2 v^2 / n
    X, y, w = np.asarray(X), np.asarray(y), np.sqrt(np.asarray(w))
    if len(y) < 2:
        raise ValueError("too few galaxies per bin of S/N to estimate the position prior")
    coef, *_ = np.linalg.lstsq(X * w[:, None], y * w, rcond=None)
    s0, a = float(coef[0]), float(coef[1])
    if a < 0:  # no fall with S/N: one variance for all
        s0, a = float(np.average(y, weights=w**2)), 0.0
    med = float(np.median(snr))
    if not s0 > a / med**2:  # no constant part: a catalogue detected on the image itself
        return None, a
    return max(math.sqrt(s0), MIN_POSITION_SIGMA), a


# ----------------------------------------------------------------------------------------
# The recipe
# ----------------------------------------------------------------------------------------
def _fallback(info: dict, what: str, why: str, default: str = "its default") -> None:
    info.setdefault("fallbacks", {})[what] = why
    warnings.warn(f"{why}: the {what} prior falls back to {default}", CalibrationWarning,
                  stacklevel=3)


#: the flux prior's power is read as flat (``info["flux_counts"]``) within this many of
#: its errors of 0
_FLAT_COUNTS_SIGMA = 2.0


def _flux_power(flux: np.ndarray, info: dict[str, Any]) -> float | None:
    """The flux prior's power ``beta`` (``p(A) ~ A^-beta``) from a pass's fluxes, or None
    where it cannot be estimated (a fallback to the configured power, with a warning).

    Any finite estimate is kept: a negative power is a population whose counts rise with
    flux (a bright selection, a cluster field), a proper prior between the flux limits.
    ``info`` records the error (``flux_power_err``) and the counts' shape
    (``flux_counts``: ``"falling with flux"``, ``"flat"`` within
    :data:`_FLAT_COUNTS_SIGMA` errors of 0, ``"rising with flux"``).
    """
    try:
        beta, beta_err = estimate_flux_slope(flux)
    except ValueError as err:
        _fallback(info, "flux power", str(err))
        return None
    if not (math.isfinite(beta) and math.isfinite(beta_err)):
        _fallback(info, "flux power", f"the counts' power estimated as {beta} +- {beta_err}")
        return None
    info["flux_power_err"] = float(beta_err)
    if abs(beta) <= _FLAT_COUNTS_SIGMA * beta_err:
        info["flux_counts"] = "flat"
    else:
        info["flux_counts"] = "falling with flux" if beta > 0 else "rising with flux"
    if beta < 0:
        log.info("flux prior: counts rising with flux, power %.3f +- %.3f", beta, beta_err)
    return float(beta)


FitPass = Callable[[list, list, bool, str], CalibrationSample]


@dataclass(frozen=True)
class RecipePass:
    """One fitting pass that the recipe asks of its caller (:class:`Recipe`).

    Attributes
    ----------
    configs : tuple of Config
        The configuration of each group of galaxies (its flux and position priors).
    size_priors : tuple of SizePrior or None
        The size prior of each group; ``None``: flat.
    keep_lnL_r : bool
        Keep each galaxy's ``L(r)`` per ring of ``|e|``
        (:func:`pylensfit.likelihood.e_annuli`) in the sample handed back.
    label : str
        What the pass is, for messages and progress bars.
    """

    configs: tuple[Config, ...]
    size_priors: tuple[SizePrior | None, ...]
    keep_lnL_r: bool
    label: str


@dataclass
class _Plan:
    """What the recipe estimates, and what it was given instead."""

    names: list[str]
    prior: Prior | None
    given_bw: np.ndarray | None
    fit_bulge: bool
    fit_size: bool
    fit_flux: bool
    fit_bounds: bool
    fit_pos: bool
    per_group: bool


@dataclass
class _State:
    """The priors estimated so far, carried from one pass to the next."""

    cfg: Config
    cfgs: list[Config]
    sps: list
    out_power: float | None
    ranges: list
    pos_sigma: float | None = None
    info: dict[str, Any] = field(default_factory=dict)

    def fit(self, keep_lnL_r: bool, label: str) -> RecipePass:
        """The next pass, under the priors so far."""
        return RecipePass(configs=tuple(self.cfgs), size_priors=tuple(self.sps),
                          keep_lnL_r=keep_lnL_r, label=label)  # fmt: skip


class Recipe:
    """The calibration recipe, one fitting pass at a time (see the module docstring).

    The caller fits the galaxies as :attr:`next_pass` says and hands the usable ones back
    to :meth:`feed`, until :attr:`next_pass` is ``None``; :attr:`priors` are then the
    result. The recipe fits nothing itself: the caller (:func:`calibrate` on postage
    stamps, :func:`pylensfit.measure` and :func:`pylensfit.calibrate_images` on images,
    the validation modes) owns its data and how they are fitted::

        recipe = Recipe(config)
        while recipe.next_pass is not None:
            recipe.feed(fit(recipe.next_pass))
        priors = recipe.priors[0]

    Parameters
    ----------
    config : Config
        The configuration: which priors to estimate, and the starting ones.
    n_groups : int
        Groups of galaxies whose size prior and flux limits are estimated apart (the
        PSFs of a simulation, whose sizes and fluxes are drawn relative to the PSF); the
        ellipticity, bulge and position priors and the flux power are common.
    prior, size_priors, bulge_weights, flux_slope
        Given instead of estimated (diagnostics).
    flux_bounds : bool
        Estimate the flux prior's limits (with ``amplitude_prior="flux"``,
        ``estimate_flux_prior`` and no limits in the configuration).
    size_prior_per_group : bool
        One size prior per group (else one for all).
    group_names : sequence of str, optional
        For messages.
    """

    def __init__(self, config: Config, n_groups: int = 1, *, prior: Prior | None = None,
                 size_priors: Sequence[SizePrior | None] | None = None,
                 bulge_weights: Sequence[float] | None = None,
                 flux_slope: float | None = None, flux_bounds: bool = True,
                 size_prior_per_group: bool = True,
                 group_names: Sequence[str] | None = None) -> None:  # fmt: skip
        plan, state = _plan(config, n_groups, prior, size_priors, bulge_weights, flux_slope,
                            flux_bounds, size_prior_per_group, group_names)  # fmt: skip
        self._steps = _recipe_steps(plan, state)
        self._next: RecipePass | None = next(self._steps)
        self._priors: list[Priors] | None = None

    @property
    def next_pass(self) -> RecipePass | None:
        """The pass to fit next; ``None`` when the priors are estimated."""
        return self._next

    def feed(self, sample: CalibrationSample) -> None:
        """Hand the recipe the usable galaxies (:func:`usable_galaxies`) of
        :attr:`next_pass`, fitted as it says."""
        if self._next is None:
            raise RuntimeError("the recipe has no pass left to feed")
        try:
            self._next = self._steps.send(sample)
        except StopIteration as done:
            self._next, self._priors = None, done.value

    @property
    def priors(self) -> list[Priors]:
        """The priors, one per group (sharing the ellipticity prior and bulge weights)."""
        if self._priors is None:
            raise RuntimeError(f"the recipe's pass {self._next.label!r} is not fitted yet")
        return self._priors


def run_recipe(
    fit_pass: FitPass,
    config: Config,
    n_groups: int = 1,
    **kw: Any,
) -> list[Priors]:
    """Estimate the priors with a caller's fitting pass (:class:`Recipe` driven to its
    end).

    Parameters
    ----------
    fit_pass : callable
        ``fit_pass(configs, size_priors, keep_lnL_r, label) -> CalibrationSample``: fit
        the calibration galaxies as :class:`RecipePass` says (its fields in that
        order, as lists); only the usable galaxies (:func:`usable_galaxies`) in the
        sample.
    config, n_groups, **kw
        As for :class:`Recipe` (``prior``, ``size_priors``, ``bulge_weights``,
        ``flux_slope``, ``flux_bounds``, ``size_prior_per_group``, ``group_names``).

    Returns
    -------
    list of Priors
        One per group (sharing the ellipticity prior and bulge weights).
    """
    recipe = Recipe(config, n_groups, **kw)
    while (step := recipe.next_pass) is not None:
        recipe.feed(fit_pass(list(step.configs), list(step.size_priors), step.keep_lnL_r,
                             step.label))  # fmt: skip
    return recipe.priors


def _plan(cfg: Config, n_groups: int, prior, size_priors, bulge_weights, flux_slope,
          flux_bounds: bool, per_group: bool, group_names) -> tuple[_Plan, _State]:  # fmt: skip
    """:class:`Recipe`'s arguments checked: what it estimates, and its starting priors."""
    names = list(group_names) if group_names is not None else [str(k) for k in range(n_groups)]
    given_bw = None
    if bulge_weights is not None:
        given_bw = np.asarray(bulge_weights, dtype=float)
        nf = len(cfg.bulge_runs)
        if given_bw.shape != (nf,) or given_bw.min() < 0 or given_bw.sum() <= 0:
            raise ValueError(f"bulge_weights needs {nf} non-negative weights "
                             f"(one per Config.bulge_runs), got {bulge_weights!r}")  # fmt: skip
        given_bw = given_bw / given_bw.sum()
    given_sp = list(size_priors) if size_priors is not None else None
    if given_sp is not None and len(given_sp) != n_groups:
        raise ValueError(f"size_priors needs one per group ({n_groups})")
    flux = cfg.amplitude_prior == "flux" and cfg.estimate_flux_prior
    if cfg.amplitude_prior == "flux" and flux_slope is not None:
        cfg = cfg.replace(amplitude_prior_power=float(flux_slope))
    plan = _Plan(
        names=names, prior=prior, given_bw=given_bw,
        fit_bulge=(cfg.bulge_prior == "estimated" and cfg.n_bulge_fractions > 1
                   and given_bw is None),
        fit_size=cfg.size_prior == "estimated" and given_sp is None,
        fit_flux=flux and flux_slope is None,
        fit_bounds=(flux and flux_bounds and cfg.amplitude_prior_min == 0
                    and not math.isfinite(cfg.amplitude_prior_max)),
        fit_pos=cfg.estimate_position_prior, per_group=per_group)  # fmt: skip
    state = _State(cfg=cfg, cfgs=[cfg] * n_groups,
                   sps=[None] * n_groups if given_sp is None else given_sp,
                   out_power=cfg.amplitude_prior_power if cfg.amplitude_prior == "flux" else None,
                   ranges=[None] * n_groups)  # fmt: skip
    return plan, state


def _recipe_steps(plan: _Plan, st: _State) -> Generator[RecipePass, CalibrationSample,
                                                          list[Priors]]:  # fmt: skip
    """The recipe of the module docstring: yields each pass, is sent its sample, and
    returns the priors."""
    cal = yield st.fit(plan.fit_size, "calibration")
    if _flux_and_position_priors(cal, plan, st):
        cal = None  # the first pass's grids freed before the second's arrive
        cal = yield st.fit(plan.fit_size, "calibration with the flux and position priors")
    prior, bw = _ellipticity_priors(cal, plan.prior, plan.given_bw, plan.fit_bulge, st.cfg,
                                    st.info)  # fmt: skip
    if plan.fit_size:
        if len(cal) < MIN_GALAXIES:
            _fallback(st.info, "size", f"{len(cal)} usable galaxies (fewer than "
                      f"{MIN_GALAXIES})")  # fmt: skip
        else:
            st.sps = _size_priors(cal, st.cfgs, st.sps, prior, bw, plan.names,
                                  plan.per_group, st.info)  # fmt: skip
            cal = None
            cal = yield st.fit(False, "calibration with the size prior")
            prior, bw = _ellipticity_priors(cal, plan.prior, plan.given_bw, plan.fit_bulge,
                                            st.cfg, st.info)  # fmt: skip
    info = st.info
    info["prior_given"] = plan.prior is not None
    if isinstance(prior, RadialPrior) and prior.info.get("at_bound"):
        info["ellipticity_at_bound"] = list(prior.info["at_bound"])
    log.info("priors estimated from %d galaxies: %r, bulge weights %s", len(cal), prior,
             None if bw is None else np.round(bw, 3).tolist())
    return [Priors(ellipticity=prior, bulge_weights=None if bw is None else np.asarray(bw),
                   size=st.sps[k], flux_power=st.out_power, flux_range=st.ranges[k],
                   position_sigma=st.pos_sigma, n_galaxies=len(cal),
                   info={**info, "group": plan.names[k]})
            for k in range(len(plan.names))]  # fmt: skip


def _flux_and_position_priors(cal: CalibrationSample, plan: _Plan, st: _State) -> bool:
    """The flux prior's power and limits and the position prior's width from the first
    pass, into ``st``; whether the pass must be fitted again under them."""
    n_groups = len(plan.names)
    if plan.fit_flux:
        if len(cal) >= MIN_GALAXIES:
            beta = _flux_power(cal.flux, st.info)
            if beta is not None:
                st.cfg = st.cfg.replace(amplitude_prior_power=beta)
                st.out_power = beta
        else:
            _fallback(st.info, "flux power", f"{len(cal)} usable galaxies (fewer than "
                      f"{MIN_GALAXIES})")  # fmt: skip
    st.cfgs = [st.cfg] * n_groups
    if plan.fit_bounds:
        st.cfgs, st.ranges = _flux_ranges(cal, st.cfg, plan.names, st.info)
    if plan.fit_flux and st.out_power is not None and st.out_power < 0:
        unbounded = [k for k in range(n_groups)
                     if not math.isfinite(st.cfgs[k].amplitude_prior_max)]  # fmt: skip
        if unbounded:  # counts that rise with flux need the prior's upper limit
            _fallback(st.info, "flux power", f"counts rising with flux (power "
                      f"{st.out_power:.3f}) and no upper flux limit",
                      default="the flat power 0")  # fmt: skip
            st.info["flux_power_estimated"] = st.out_power
            st.out_power = 0.0
            st.cfg = st.cfg.replace(amplitude_prior_power=0.0)
            st.cfgs = [c.replace(amplitude_prior_power=0.0) for c in st.cfgs]
    fit_pos = plan.fit_pos
    if fit_pos:
        try:
            st.pos_sigma, a = estimate_position_sigma(cal.dx, cal.dy, cal.snr)
            st.info["position_snr_term"] = a
            if st.pos_sigma is None:  # positions from the image itself: the broad prior kept
                st.info["position_kept"] = ("no scatter independent of S/N (positions "
                                            "detected on the image): the configured width")
                st.pos_sigma = st.cfg.position_prior_sigma
                fit_pos = False
            else:
                st.cfgs = [c.replace(position_prior_sigma=st.pos_sigma) for c in st.cfgs]
        except ValueError as err:
            _fallback(st.info, "position", str(err))
    changed = plan.fit_bounds or fit_pos
    if plan.fit_size:
        return changed
    return (changed or plan.fit_flux) and (plan.prior is None or plan.fit_bulge)


def _ellipticity_priors(cal: CalibrationSample, prior0: RadialPrior | None,
                        given_bw: np.ndarray | None, fit_bulge: bool, cfg: Config,
                        info: dict[str, Any]) -> tuple[RadialPrior, np.ndarray | None]:  # fmt: skip
    """The ellipticity prior and bulge weights from a pass: ``prior0`` kept where given,
    the bulge weights estimated under it (``fit_bulge``) or ``given_bw``; a sample too
    small for the estimate falls back to the default prior."""
    if len(cal) < MIN_GALAXIES:
        if prior0 is None:
            _fallback(info, "ellipticity", f"{len(cal)} usable galaxies (fewer than "
                      f"{MIN_GALAXIES})")  # fmt: skip
        return (prior0 if prior0 is not None else Prior(egrid=cal.egrid)), given_bw
    if fit_bulge and prior0 is None:
        return estimate_prior_and_bulge(cal.lnL_bulge, cal.lnL_star, cal.egrid,
                                        method=cfg.prior_method, form=cfg.prior_form)  # fmt: skip
    if fit_bulge:
        return prior0, estimate_bulge_weights(cal.lnL_bulge, cal.lnL_star, prior0)
    if prior0 is None:
        lnL = cal.lnL
        if given_bw is not None and cal.lnL_bulge is not None:
            lnL = mix_bulge_fractions(cal.lnL_bulge, cal.lnL_star, given_bw)
        return estimate_prior(lnL, cal.egrid, method=cfg.prior_method,
                              form=cfg.prior_form), given_bw  # fmt: skip
    return prior0, given_bw


def _flux_ranges(cal: CalibrationSample, cfg: Config, names: list[str],
                 info: dict[str, Any]) -> tuple[list[Config], list]:  # fmt: skip
    """Each group's flux prior limits (``info["flux_range"]``): the configurations with
    them, and the ``(lo, hi)`` limits (None where the estimate failed)."""
    n_groups = len(names)
    cfgs, ranges = [cfg] * n_groups, [None] * n_groups
    info["flux_range"] = []
    for k in range(n_groups):
        sel = cal.group == k
        try:
            fr = estimate_flux_range(cal.flux[sel], cal.flux_err[sel],
                                     beta=cfg.amplitude_prior_power)  # fmt: skip
        except ValueError as err:
            _fallback(info, f"flux range ({names[k]})" if n_groups > 1 else "flux range",
                      str(err))
            info["flux_range"].append(None)
            continue
        ranges[k] = (fr["lo"], fr["hi"])
        info["flux_range"].append({k2: fr[k2] for k2 in ("lo", "hi", "lo_err", "hi_err",
                                                         "error_scale")})  # fmt: skip
        cfgs[k] = cfg.replace(amplitude_prior_min=fr["lo"], amplitude_prior_max=fr["hi"])
    return cfgs, ranges


def _size_priors(cal: CalibrationSample, cfgs: list[Config], sps: list, prior: Prior,
                 bw: np.ndarray | None, names: list[str], per_group: bool,
                 info: dict[str, Any]) -> list:  # fmt: skip
    """The size prior per group (or one for all) from a pass's ``L(r)`` per ring of
    ``|e|``, each galaxy's ``L(r)`` marginalised over ``e`` with ``prior``; a group too
    small keeps its entry of ``sps``. Frees ``cal.lnL_r_grouped``."""
    n_groups = len(names)
    sps = list(sps)
    bank = model_bank(cfgs[0])
    rings = e_annuli(bank.egrid)
    lnL_r = np.concatenate([reweight_lnL_r(g, bank.egrid, rings, None, prior)
                            for g in cal.lnL_r_grouped])  # fmt: skip
    cal.lnL_r_grouped = None
    if per_group and n_groups > 1:
        for k in range(n_groups):
            sel = cal.group == k
            if sel.sum() < MIN_GALAXIES:
                _fallback(info, f"size ({names[k]})", f"{int(sel.sum())} usable "
                          f"galaxies (fewer than {MIN_GALAXIES})")  # fmt: skip
                continue
            sps[k] = estimate_size_prior(lnL_r[sel], bank, cfgs[k], bulge_weights=bw)
        return sps
    return [estimate_size_prior(lnL_r, bank, cfgs[0], bulge_weights=bw)] * n_groups


# ----------------------------------------------------------------------------------------
# Postage stamps
# ----------------------------------------------------------------------------------------
