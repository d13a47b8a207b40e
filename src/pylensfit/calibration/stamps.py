"""The recipe on postage stamps: :func:`calibrate` and :func:`measure_stamps`."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from astropy.table import Table

from .._util import per_object
from ..assemble import ObjectContext, assemble, fit_columns, usable_galaxies
from ..catalogue import COLUMNS, FITCLASS
from ..config import Config
from ..likelihood import e_annuli, fit_stamps
from ..metacal import metacal_shapes
from ..models import model_bank
from ..prior import (
    Prior,
)
from ..psf import centre_on_stamp, psf_diagnostics
from .priors import CalibrationSample, Priors
from .recipe import run_recipe

log = logging.getLogger(__name__)

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
        knotty discs, misaligned bulges), its images fitted on the whole stamp (give
        stamps that hold the galaxies' light: 64 px for ``Config()``); it adds the
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
    (NaN on the rows not fitted).

    The metacalibration images are fitted on the whole stamp (no stamp tiers): the
    operation shears the light the stamp holds, and a fit on a cut of it loses the
    sheared wings (``benchmarks/studies/metacal_faint.py``: on the realistic
    population under a Kolmogorov PSF, fits on 32 of 64 pixels give m1 = -0.008 +-
    0.002 about the true centre, fits on all 64 +0.0007 +- 0.0027)."""
    n = stamps.shape[-1]
    psf = centre_on_stamp(psf, n)  # on the stamps' grid
    run_cfg = run_cfg.replace(stamp_size=n, max_stamp_size=0)
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
                            step=step, noise_fields=fields, centres=(x[idx], y[idx]),
                            reconvolution=run_cfg.metacal_reconvolution)  # fmt: skip
        for c in ("R11", "R12", "R21", "R22"):
            cols[c][idx] = mc[c]
        for i in (1, 2):
            cols[f"e{i}_mcal"][idx] = mc[f"e{i}"]
    for c, v in cols.items():
        t[c] = v
        t[c].description = COLUMNS[c][1]
    t.meta["metacal_step"] = float(step)
