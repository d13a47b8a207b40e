"""The calibration recipe: every prior of the method estimated from the data themselves.

lensfit is a Bayesian method: each galaxy's ellipticity is the mean of its posterior,
and the posterior needs the priors of the population. pylensfit estimates all of them
from a sample of the galaxies to be measured (a survey's own galaxies, or an unsheared
sample of the same population), by maximum marginal likelihood, as Miller et al.
(2007, "Bayesian galaxy shape measurement for weak lensing surveys I", arXiv:0708.2340)
and Kitching et al. (2008, "lensfit II", arXiv:0802.1528) estimate the ellipticity
prior:

1. a first pass fits the sample with the configuration's starting priors (the flat size
   prior, the flux prior's Euclidean power 2 unbounded, the configuration's position
   prior), keeping each galaxy's likelihood of size ``L(r)`` per ring of ``|e|``;
2. the flux prior's power (the number counts' slope,
   :func:`~pylensfit.prior.estimate_flux_slope`; negative where the counts rise with
   flux, flat at 0 where they rise with flux and the prior has no upper limit) and its
   limits, deconvolved from the flux errors
   (:func:`~pylensfit.prior.estimate_flux_range`), come from the measured fluxes; the
   position prior's width from the scatter of the fitted centres about the
   catalogue positions, less its part that falls as ``1 / S/N`` (:func:`estimate_position_sigma`);
3. the first pass again under those priors; the ellipticity prior and the prior over
   the bulge fractions from it (:func:`~pylensfit.prior.estimate_prior_and_bulge`);
4. the size prior (one density per bulge fraction) from ``L(r)`` marginalised over
   ``e`` with the ellipticity prior just estimated
   (:func:`~pylensfit.prior.estimate_size_prior`);
5. a last pass with the size prior, for the final ellipticity and bulge-fraction priors.

Which steps run follows the :class:`~pylensfit.Config`: ``size_prior="estimated"``,
``bulge_prior="estimated"``, ``amplitude_prior="flux"`` with ``estimate_flux_prior``,
``estimate_position_prior``. The result is one :class:`Priors` object, saved and read
as JSON, that :func:`measure_stamps` and :func:`pylensfit.measure` fit with.

A sample too small for a prior (fewer than :data:`MIN_GALAXIES` usable galaxies, or
:data:`MIN_FLUX_RANGE_GALAXIES` for the flux limits) gets that prior's documented
default with a warning instead: the functional ellipticity prior ``Prior()``, uniform
bulge weights, the flat size prior, the unbounded flux power law of power 2, the
configuration's position prior.

The same recipe serves :func:`calibrate` (postage stamps), :func:`pylensfit.measure`
and :func:`pylensfit.calibrate_images` (FITS images) and the validation modes: a
:class:`Recipe` says which pass to fit next (a :class:`RecipePass`: the configurations
and size priors to fit with) and is handed each pass's :class:`CalibrationSample`; the
caller fits, the recipe estimates. :func:`run_recipe` drives it with a caller's fitting
function.
"""

from __future__ import annotations

import json
import logging
import math
import warnings
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from astropy.table import Table

from ._util import json_kind, jsonable, per_object, read_json_entry
from .assemble import ObjectContext, assemble, fit_columns, flag_low_snr, mix_lnL, usable_galaxies
from .catalogue import COLUMNS, FITCLASS
from .config import Config
from .likelihood import e_annuli, fit_stamps, reweight_lnL_r
from .metacal import metacal_shapes
from .models import model_bank
from .prior import (
    MIN_FLUX_RANGE_SAMPLE,
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
from .psf import centre_on_stamp, psf_diagnostics

__all__ = [
    "MIN_GALAXIES",
    "MIN_FLUX_RANGE_GALAXIES",
    "CalibrationSample",
    "CalibrationWarning",
    "Priors",
    "Recipe",
    "RecipePass",
    "calibrate",
    "estimate_position_sigma",
    "flag_low_snr",
    "measure_stamps",
    "run_recipe",
    "usable_galaxies",
]

log = logging.getLogger(__name__)

#: fewest usable galaxies for an estimated ellipticity, bulge-fraction or size prior
MIN_GALAXIES = 50
#: fewest usable galaxies (per group) for the flux prior's estimated limits
MIN_FLUX_RANGE_GALAXIES = MIN_FLUX_RANGE_SAMPLE
#: the position prior's width is never estimated below this (pixels)
MIN_POSITION_SIGMA = 0.01


class CalibrationWarning(UserWarning):
    """A prior could not be estimated from the sample and its default was used."""


# ----------------------------------------------------------------------------------------
# The priors
# ----------------------------------------------------------------------------------------
@dataclass
class Priors:
    """Every prior the method fits with, as estimated by :func:`calibrate`.

    Attributes
    ----------
    ellipticity : Prior
        The ellipticity prior: the functional form of Kitching et al. (2008,
        arXiv:0802.1528, section 3.1; docs: method, eq-funcprior).
    bulge_weights : numpy.ndarray or None
        Prior probability of each run of the model family (bulge fraction,
        ``Config.bulge_runs``), summing to 1; ``None``: uniform.
    size : SizePrior or None
        The prior of the half-light radius in the sum over sizes; ``None``: flat.
    flux_power : float or None
        The power ``beta`` of the flux prior ``A^-beta`` (``Config.amplitude_prior_power``
        with ``amplitude_prior="flux"``); ``None``: the configuration's. Negative for
        counts that rise with flux (a bright selection), between the flux limits.
    flux_range : tuple of float or None
        The flux prior's limits ``(lo, hi)`` in data units; ``None``: unbounded (or the
        configuration's).
    position_sigma : float or None
        Width of the Gaussian position prior about the catalogue position, pixels
        (``Config.position_prior_sigma``); ``None``: the configuration's.
    n_galaxies : int
        Usable galaxies the priors were estimated from.
    info : dict
        Errors of the estimates and notes (``flux_power_err``, ``flux_counts``: the
        counts' shape that the power estimates, ``"falling with flux"``, ``"flat"`` or
        ``"rising with flux"`` (a negative power), ``flux_power_estimated``: the estimate
        where it fell back, ``flux_range``, ``position_snr_term``, ``fallbacks``: the
        priors that fell back to their defaults, and why).
    """

    ellipticity: Prior = field(default_factory=Prior)
    bulge_weights: np.ndarray | None = None
    size: SizePrior | None = None
    flux_power: float | None = None
    flux_range: tuple[float, float] | None = None
    position_sigma: float | None = None
    n_galaxies: int = 0
    info: dict[str, Any] = field(default_factory=dict)

    def apply(self, config: Config) -> Config:
        """``config`` with this object's flux and position priors set in it."""
        kw: dict[str, Any] = {}
        if self.flux_power is not None and config.amplitude_prior == "flux":
            kw["amplitude_prior_power"] = float(self.flux_power)
        if self.flux_range is not None and config.amplitude_prior == "flux":
            kw["amplitude_prior_min"], kw["amplitude_prior_max"] = map(float, self.flux_range)
        if self.position_sigma is not None:
            kw["position_prior_sigma"] = float(self.position_sigma)
        return config.replace(**kw) if kw else config

    def mix(self, fits) -> np.ndarray:
        """``ln L(e)`` of :class:`~pylensfit.StampFits` with the bulge fractions mixed
        under :attr:`bulge_weights` (the fits' own ``lnL`` without marginalised
        fractions or weights)."""
        return mix_lnL(fits.lnL, fits.lnL_bulge, fits.lnL_star, self.bulge_weights)

    # -- persistence ---------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-able contents (:meth:`from_dict` inverts it)."""
        return {
            "ellipticity": self.ellipticity.to_dict(),
            "bulge_weights": None if self.bulge_weights is None
            else [float(w) for w in self.bulge_weights],
            "size": None if self.size is None else self.size.to_dict(),
            "flux_power": self.flux_power,
            "flux_range": None if self.flux_range is None else [float(v) for v in self.flux_range],
            "position_sigma": self.position_sigma,
            "n_galaxies": int(self.n_galaxies),
            "info": jsonable(self.info),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "priors") -> Priors:
        """The object of :meth:`to_dict`; ``ValueError`` naming ``source`` if malformed."""
        if not isinstance(d, dict) or "ellipticity" not in d:
            detail = (f"a JSON {json_kind(d)}" if not isinstance(d, dict)
                      else "no 'ellipticity' entry")  # fmt: skip
            raise ValueError(f"{source}: not a priors file ({detail})")
        try:
            ell = RadialPrior.from_dict(d["ellipticity"], source="entry 'ellipticity'")
            size = None if d.get("size") is None else SizePrior.from_dict(
                d["size"], source="entry 'size'")  # fmt: skip
            bw = d.get("bulge_weights")
            fr = d.get("flux_range")
            return cls(
                ellipticity=ell,
                bulge_weights=None if bw is None else np.asarray(bw, dtype=float),
                size=size,
                flux_power=None if d.get("flux_power") is None else float(d["flux_power"]),
                flux_range=None if fr is None else (float(fr[0]), float(fr[1])),
                position_sigma=None if d.get("position_sigma") is None
                else float(d["position_sigma"]),
                n_galaxies=int(d.get("n_galaxies", 0)),
                info=dict(d.get("info", {})),
            )
        except (KeyError, TypeError, ValueError, IndexError) as err:
            why = str(err) if type(err) is ValueError else f"{type(err).__name__}: {err}"
            raise ValueError(f"{source}: malformed priors ({why})") from None

    def save(self, path: str | Path) -> None:
        """Write as JSON."""
        Path(path).write_text(json.dumps({"priors": self.to_dict()}, indent=1))

    @classmethod
    def load(cls, path: str | Path) -> Priors:
        """Read a file written by :meth:`save`; ``ValueError`` naming the file if it is
        not one."""
        d = read_json_entry(path, "priors", "priors", {"B": "prior", "size_prior": "size prior"})
        return cls.from_dict(d, source=str(path))

    def __repr__(self) -> str:
        parts = [f"ellipticity={self.ellipticity!r}"]
        if self.bulge_weights is not None:
            parts.append("bulge_weights=[" + ", ".join(f"{w:.3f}" for w in self.bulge_weights)
                         + "]")
        if self.size is not None:
            h = np.exp(self.size.ln_h)
            dens = self.size.marginal(self.bulge_weights)
            mean = float(np.sum(h * dens) / np.sum(dens)) if np.sum(dens) > 0 else math.nan
            parts.append(f"size=SizePrior(mean half-light radius {mean:.3g} px"
                         f"{', per run' if self.size.per_run else ''})")
        else:
            parts.append("size=flat")
        if self.flux_power is not None:
            parts.append(f"flux_power={self.flux_power:.3f}")
        if self.flux_range is not None:
            parts.append(f"flux_range=({self.flux_range[0]:.4g}, {self.flux_range[1]:.4g})")
        if self.position_sigma is not None:
            parts.append(f"position_sigma={self.position_sigma:.3f} px")
        parts.append(f"n_galaxies={self.n_galaxies}")
        if self.info.get("fallbacks"):
            parts.append(f"fallbacks={sorted(self.info['fallbacks'])}")
        return "Priors(" + ", ".join(parts) + ")"


# ----------------------------------------------------------------------------------------
# What a fitting pass hands the recipe
# ----------------------------------------------------------------------------------------
@dataclass
class CalibrationSample:
    """The usable galaxies of one fitting pass, as the recipe needs them.

    Attributes
    ----------
    egrid : numpy.ndarray
        ``(n_e, 2)`` the fits' ellipticity grid.
    lnL : numpy.ndarray
        ``(n, n_e)`` ``ln L(e)`` of each galaxy (bulge fractions mixed uniformly).
    flux, flux_err, snr : numpy.ndarray
        ``(n,)`` the best model's flux (data units), its fixed-model error ``flux /
        snr`` and its matched-filter S/N.
    dx, dy : numpy.ndarray
        ``(n,)`` fitted centre less catalogue position, pixels.
    group : numpy.ndarray
        ``(n,)`` integer group (a PSF, an image set) of each galaxy; 0 for one group.
    lnL_bulge, lnL_star : numpy.ndarray or None
        Per bulge fraction ``ln L(e)`` and the point source's ``ln L`` (marginalised
        fractions only).
    lnL_r_grouped : list of numpy.ndarray or None
        Blocks of ``StampFits.lnL_r_grouped`` (``L(r)`` per ring of ``|e|``) where kept.
    """

    egrid: np.ndarray
    lnL: np.ndarray
    flux: np.ndarray
    flux_err: np.ndarray
    snr: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    group: np.ndarray
    lnL_bulge: np.ndarray | None = None
    lnL_star: np.ndarray | None = None
    lnL_r_grouped: list | None = None

    def __len__(self) -> int:
        return int(self.lnL.shape[0])

    @classmethod
    def from_fits(cls, fits, keep: np.ndarray, cx, cy, group=0) -> CalibrationSample:
        """The rows ``keep`` of :class:`~pylensfit.StampFits` fitted about ``(cx, cy)``."""
        keep = np.asarray(keep, dtype=bool)
        n = int(keep.sum())
        grp = np.broadcast_to(np.asarray(group), keep.shape)[keep].astype(int)
        return cls(
            egrid=np.asarray(fits.egrid),
            lnL=np.asarray(fits.lnL)[keep],
            flux=np.asarray(fits.flux, dtype=float)[keep],
            flux_err=(np.asarray(fits.flux, dtype=float) / np.asarray(fits.snr, float))[keep],
            snr=np.asarray(fits.snr, dtype=float)[keep],
            dx=(np.asarray(fits.x, float) - np.broadcast_to(cx, keep.shape))[keep],
            dy=(np.asarray(fits.y, float) - np.broadcast_to(cy, keep.shape))[keep],
            group=grp if grp.size == n else np.zeros(n, int),
            lnL_bulge=None if fits.lnL_bulge is None else fits.lnL_bulge[keep],
            lnL_star=None if fits.lnL_star is None else np.asarray(fits.lnL_star)[keep],
            lnL_r_grouped=None if fits.lnL_r_grouped is None else [fits.lnL_r_grouped[keep]],
        )

    @classmethod
    def concatenate(cls, parts: Sequence[CalibrationSample]) -> CalibrationSample:
        """One sample of several (blocks, images)."""
        parts = [p for p in parts if p is not None]
        if not parts:
            raise ValueError("no calibration sample")

        def cat(name):
            vals = [getattr(p, name) for p in parts]
            return None if any(v is None for v in vals) else np.concatenate(vals)

        lr = [p.lnL_r_grouped for p in parts]
        return cls(egrid=parts[0].egrid, lnL=cat("lnL"), flux=cat("flux"),
                   flux_err=cat("flux_err"), snr=cat("snr"), dx=cat("dx"), dy=cat("dy"),
                   group=cat("group"), lnL_bulge=cat("lnL_bulge"), lnL_star=cat("lnL_star"),
                   lnL_r_grouped=None if any(v is None for v in lr)
                   else [b for v in lr for b in v])  # fmt: skip


# ----------------------------------------------------------------------------------------
# The position prior's width
# ----------------------------------------------------------------------------------------
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
def _stamp_centres(stamps: np.ndarray, centres):
    n, ny, nx = stamps.shape
    if centres is None:
        return np.full(n, nx // 2, dtype=float), np.full(n, ny // 2, dtype=float)
    return per_object(centres[0], n, "centres[0]"), per_object(centres[1], n, "centres[1]")


def _as_stamps(stamps) -> np.ndarray:
    s = np.asarray(stamps)
    if s.ndim == 2:
        s = s[None]
    if s.ndim != 3:
        raise ValueError(f"stamps must have shape (n, N, N), got {s.shape}")
    return s


def calibrate(
    stamps: np.ndarray,
    psf: np.ndarray,
    noise_sigma,
    *,
    config: Config | None = None,
    centres: tuple[np.ndarray, np.ndarray] | None = None,
    prior: Prior | None = None,
) -> Priors:
    """Estimate every prior of the method from postage stamps of the galaxies.

    The recipe of the module docstring on ``stamps``: two to three fitting passes of
    :func:`~pylensfit.fit_stamps`, each prior estimated by maximum marginal likelihood.
    The stamps may be the galaxies to be measured themselves (a survey's own galaxies:
    the priors are of the population, not of a galaxy) or an unsheared sample of the
    same population.

    Parameters
    ----------
    stamps : numpy.ndarray
        ``(n, N, N)`` background-subtracted stamps ``[k, y, x]``, as for
        :func:`~pylensfit.fit_stamps` (``N >= Config.max_stamp_size`` for the largest
        galaxies' stamps, 64 pixels by default).
    psf : numpy.ndarray
        The PSF image (pixel response included), centred on ``[s//2, s//2]``.
    noise_sigma : float or numpy.ndarray
        Per-pixel noise standard deviation (data units), scalar or one per stamp.
    config : Config, optional
        Settings (default ``Config()``, the recommended method).
    centres : tuple of numpy.ndarray, optional
        Catalogue positions ``(x, y)`` in stamp pixels (default the stamps' centres).
    prior : Prior, optional
        An ellipticity prior to keep instead of estimating it.

    Returns
    -------
    Priors
        The priors; ``Priors.save`` keeps them for :func:`measure_stamps` and
        ``pylensfit measure --priors``.

    Warns
    -----
    CalibrationWarning
        For each prior that the sample is too small to estimate (its default is used).
    """
    cfg = config if config is not None else Config()
    stamps = _as_stamps(stamps)
    cx, cy = _stamp_centres(stamps, centres)

    def fit_pass(cfgs, sps, keep, label):
        groups = None
        if keep:
            groups = e_annuli(model_bank(cfgs[0]).egrid)
        fits = fit_stamps(stamps, psf, noise_sigma, config=cfgs[0], centres=(cx, cy),
                          size_prior=sps[0], lnL_r_groups=groups)  # fmt: skip
        ok = usable_galaxies(fits.flags, fits.is_star, fits.snr, cfgs[0].min_snr)
        log.info("%s: %d of %d stamps usable", label, int(ok.sum()), len(ok))
        return CalibrationSample.from_fits(fits, ok, cx, cy)

    return run_recipe(fit_pass, cfg, 1, prior=prior)[0]


#: the columns of :func:`measure_stamps` (every one a column of the catalogue,
#: :data:`pylensfit.catalogue.COLUMNS`, with its meaning; ``lnL`` beside them as in the
#: catalogue, and the metacalibration's with ``response="metacal"``)
STAMP_COLUMNS = ("x", "y", "x_detect", "y_detect", "noise_sigma", "model_flux",
                 "model_SNratio", "scalelength", "stamp_size", "e1", "e2", "e1_var",
                 "e2_var", "e12_cov", "sens1", "sens2", "weight", "fitclass", "is_star",
                 "e1_best", "e2_best", "bulge_best", "flags")  # fmt: skip


def stamps_table(fits, priors: Priors, run_cfg: Config, cx, cy, noise_sigma,
                 psf_sigma) -> Table:  # fmt: skip
    """:func:`measure_stamps`' table of ``fits`` (about the catalogue positions ``cx,
    cy``) under ``priors``: :func:`pylensfit.assemble.assemble`, the path the catalogue
    of :func:`pylensfit.measure` takes, every fitted row's shapes kept."""
    n = len(fits)
    cols = fit_columns(fits, run_cfg.stamp_size)
    measured = np.isfinite(np.asarray(fits.lnL)).all(axis=1)
    is_star = np.asarray(fits.is_star, dtype=bool)
    ctx = ObjectContext(flags=np.asarray(fits.flags, dtype=np.int32), not_galaxy=is_star,
                        model_SNratio=cols["model_SNratio"], model_flux=cols["model_flux"],
                        scalelength=cols["scalelength"], noise_sigma=noise_sigma,
                        psf_sigma=psf_sigma)  # fmt: skip
    out = assemble(fits.lnL, fits.egrid, priors, run_cfg, ctx, lnL_bulge=fits.lnL_bulge,
                   lnL_star=fits.lnL_star, flagged="keep")  # fmt: skip
    x, y = np.asarray(fits.x, dtype=float), np.asarray(fits.y, dtype=float)
    cols.update(out.columns)
    cols.update(
        x=np.where(np.isfinite(x), x, cx), y=np.where(np.isfinite(y), y, cy),
        x_detect=np.asarray(cx, dtype=float), y_detect=np.asarray(cy, dtype=float),
        noise_sigma=np.broadcast_to(np.asarray(noise_sigma, dtype=float), (n,)).copy(),
        fitclass=np.where(measured, np.where(is_star, FITCLASS["star"], FITCLASS["galaxy"]),
                          FITCLASS["not_measured"]).astype(np.int16),
        is_star=is_star)  # fmt: skip
    t = Table({c: cols[c] for c in STAMP_COLUMNS})
    for c in t.colnames:
        unit, desc = COLUMNS[c]
        t[c].description = desc
        if unit:
            t[c].unit = unit
    t["lnL"] = np.asarray(out.lnL, dtype=np.float32)
    t.meta.update(egrid=np.asarray(fits.egrid), prior=priors.ellipticity, priors=priors,
                  refine=int(run_cfg.output_refine), sensitivity=run_cfg.sensitivity)  # fmt: skip
    return t


def measure_stamps(
    stamps: np.ndarray, psf: np.ndarray, noise_sigma, *,
    priors: Priors | str | Path | None = None, config: Config | None = None,
    centres: tuple[np.ndarray, np.ndarray] | None = None, response: str = "model",
    metacal_step: float = 0.01, seed: int = 0,
) -> Table:
    """Shapes, errors, sensitivities and weights of galaxies on postage stamps.

    The same measurement as :func:`pylensfit.measure` on images: each stamp fitted
    under the priors (:func:`~pylensfit.fit_stamps`), the bulge fractions mixed with
    their prior, the posterior mean ellipticity, its covariance and the exact shear
    sensitivity (:func:`~pylensfit.shapes`).

    Parameters
    ----------
    stamps, psf, noise_sigma, centres
        As for :func:`calibrate`.
    priors : Priors or str, optional
        The priors (or the path of a saved one); by default :func:`calibrate` estimates
        them from ``stamps`` themselves.
    config : Config, optional
        Settings (default ``Config()``); the one the priors were estimated with.
    response : {"model", "metacal"}
        ``"model"``: the sensitivities are lensfit's exact response of the posterior
        mean if the galaxy is one of the models. ``"metacal"``: the response is also
        measured on each galaxy itself (:func:`pylensfit.metacal.metacal_shapes`), for
        galaxies the model family does not hold (Sersic profiles far from 1 and 4,
        knotty discs, misaligned bulges), at 5 to 7.5 times the cost; it adds the
        columns below.
    metacal_step : float
        The metacalibration shear ``delta`` (dimensionless).
    seed : int
        Seed of the metacalibration's added noise fields (the same input and seed give
        the same table).

    Returns
    -------
    astropy.table.Table
        One row per stamp, with the catalogue's columns of the same names, meanings and
        units (:data:`STAMP_COLUMNS`, :data:`pylensfit.catalogue.COLUMNS`): ``x, y`` the
        fitted centre in stamp pixels (the catalogue position where not fitted),
        ``x_detect, y_detect`` the catalogue position, the posterior means ``e1, e2``,
        their covariance, the shear responses ``sens1, sens2``, the ``weight`` (0 for a
        row not to use), ``flags`` (:data:`pylensfit.flags.FLAGS`) and ``lnL`` (the ``(n,
        n_e)`` grid, for :func:`~pylensfit.estimate_shear`'s fixed point), assembled as
        the catalogue's (:func:`pylensfit.assemble.assemble`); a flagged row that was
        fitted keeps its shapes here, where the catalogue has NaN. ``meta``: ``egrid``,
        ``prior``, ``priors``, ``refine``, ``sensitivity``.

        With ``response="metacal"`` also ``e1_mcal, e2_mcal`` (the posterior means on
        the unsheared metacalibration image) and ``R11, R12, R21, R22`` (their response
        ``R_ij = d<e_i>/dg_j``), NaN where a metacalibration fit failed, and
        ``meta["metacal_step"]``: the shear is then ``estimate_shear(t, estimator="key2",
        e1_col="e1_mcal", e2_col="e2_mcal", sens1_col="R11", sens2_col="R22")``. On a
        realistic mix of kinds every kind's m is within 5e-3 above S/N 20 (lensfit's own
        sensitivity: -0.028 to +0.010); a noise bias of about +0.01 is left below S/N 20.
    """
    if response not in ("model", "metacal"):
        raise ValueError(f"response must be 'model' or 'metacal', got {response!r}")
    cfg = config if config is not None else Config()
    stamps = _as_stamps(stamps)
    if isinstance(priors, (str, Path)):
        priors = Priors.load(priors)
    if priors is None:
        priors = calibrate(stamps, psf, noise_sigma, config=cfg, centres=centres)
    if not isinstance(priors, Priors):
        raise TypeError(f"priors must be a Priors object or a path, got {type(priors).__name__}")
    cx, cy = _stamp_centres(stamps, centres)
    run_cfg = priors.apply(cfg)
    fits = fit_stamps(stamps, psf, noise_sigma, config=run_cfg, centres=(cx, cy),
                      size_prior=priors.size)  # fmt: skip
    t = stamps_table(fits, priors, run_cfg, cx, cy,
                     per_object(noise_sigma, len(stamps), "noise_sigma"),
                     psf_diagnostics(np.asarray(psf, dtype=float))["sigma"])  # fmt: skip
    if response == "metacal":
        _add_metacal(t, stamps, psf, noise_sigma, priors, run_cfg, fits, metacal_step, seed)
    return t


#: stamps metacalibrated at a time by :func:`measure_stamps`
_METACAL_BLOCK = 1024


def _add_metacal(t: Table, stamps: np.ndarray, psf: np.ndarray, noise_sigma, priors: Priors,
                 run_cfg: Config, fits, step: float, seed: int) -> None:
    """``measure_stamps``' metacalibration columns, in place, about the fitted centres
    (NaN on the rows not fitted)."""
    psf = centre_on_stamp(psf, stamps.shape[-1])  # on the stamps' grid
    x, y = np.asarray(fits.x, float), np.asarray(fits.y, float)
    sig = per_object(noise_sigma, len(t), "noise_sigma")
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(sig) & (sig > 0)
    cols = {c: np.full(len(t), np.nan) for c in ("e1_mcal", "e2_mcal", "R11", "R12", "R21",
                                                 "R22")}  # fmt: skip
    for start in range(0, len(t), _METACAL_BLOCK):  # bounded memory; a seed per block
        rows = np.arange(start, min(start + _METACAL_BLOCK, len(t)))
        fields = np.random.default_rng([seed, start]).standard_normal(
            (rows.size,) + stamps.shape[1:])[ok[rows]]
        idx = rows[ok[rows]]
        if not idx.size:
            continue
        mc = metacal_shapes(stamps[idx], psf, sig[idx], priors.ellipticity, config=run_cfg,
                            size_prior=priors.size, bulge_weights=priors.bulge_weights,
                            step=step, noise_fields=fields, centres=(x[idx], y[idx]))  # fmt: skip
        for c in ("R11", "R12", "R21", "R22"):
            cols[c][idx] = mc[c]
        for i in (1, 2):
            cols[f"e{i}_mcal"][idx] = mc[f"e{i}"]
    for c, v in cols.items():
        t[c] = v
    t.meta["metacal_step"] = float(step)
