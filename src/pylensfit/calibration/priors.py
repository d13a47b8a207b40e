"""The priors that the recipe estimates (:class:`Priors`, saved and read as JSON) and the
sample of fitted galaxies it estimates them from (:class:`CalibrationSample`)."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._util import json_kind, jsonable, read_json_entry
from ..assemble import mix_lnL
from ..config import Config
from ..prior import (
    MIN_FLUX_RANGE_SAMPLE,
    Prior,
    RadialPrior,
    SizePrior,
)

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
