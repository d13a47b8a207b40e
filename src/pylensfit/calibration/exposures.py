"""The recipe on galaxies seen in several exposures, each fitted on all of them at once:
:func:`calibrate_exposures` and :func:`measure_exposure_stamps`.

The joint fit (:func:`pylensfit.joint.fit_views`) measures one sky-frame shape, size,
flux and position per galaxy from its views in every exposure that holds it. Its sizes
and lengths are in reference pixels of ``pixel_scale`` arcsec (the median pixel scale
of the exposures at the galaxies), its fluxes in the common flux unit of
:attr:`pylensfit.exposures.ExposureStamps.flux_scale`: the priors that
:func:`calibrate_exposures` estimates describe the population in those units, as the
joint fit sees it, and ``Priors.info["pixel_scale"]`` records the reference pixel
(:func:`measure_exposure_stamps` fits with it).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from astropy.table import Table

from .. import flags as _flags
from ..assemble import usable_galaxies
from ..catalogue import COLUMNS
from ..config import Config
from ..exposures import ExposureStamps
from ..grid import ellipticity_grid
from ..joint import JointFits, ViewArrays, first_exposure, fit_views
from ..likelihood import StampFits, e_annuli
from ..metacal import metacal_branches, metacal_exposures
from ..prior import Prior
from ..psf import psf_diagnostics
from .priors import CalibrationSample, Priors
from .recipe import run_recipe
from .stamps import stamps_table

log = logging.getLogger(__name__)


def _reference_scale(views: Sequence[ExposureStamps]) -> float:
    """The joint fit's reference pixel scale of ``views``: the median over the exposures
    of their median pixel scale at the galaxies, arcsec."""
    per = [np.nanmedian(v.pixel_scale) if np.isfinite(v.pixel_scale).any() else np.nan
           for v in views]  # fmt: skip
    return float(np.nanmedian(per))


def _sample(fits: JointFits, keep: np.ndarray) -> CalibrationSample:
    """The rows ``keep`` of joint fits as the recipe reads them: offsets in reference
    pixels, fluxes in the common flux unit."""
    s = fits.pixel_scale
    one = CalibrationSample.from_fits(fits, keep, 0.0, 0.0)
    one.dx, one.dy = one.dx / s, one.dy / s  # arcsec to reference pixels
    return one


def calibrate_exposures(
    views: Sequence[ExposureStamps],
    *,
    config: Config | None = None,
    prior: Prior | None = None,
) -> Priors:
    """Estimate every prior of the method from galaxies fitted jointly on their exposures.

    The recipe of :func:`pylensfit.calibrate` (:func:`pylensfit.calibration.run_recipe`),
    each pass a joint fit of every galaxy on all of its usable exposures
    (:func:`pylensfit.joint.fit_views`): the flux prior from the joint fluxes (common
    flux unit), the position prior from the fitted sky offsets, the ellipticity and
    bulge-fraction priors from the joint ``ln L(e)`` (sky frame), the size prior from
    the joint ``L(r)``. The priors describe the population as the joint fit sees it.

    Parameters
    ----------
    views : sequence of pylensfit.exposures.ExposureStamps
        One per exposure (:func:`pylensfit.exposures.cut_exposures`), each with its PSF
        at the galaxies; galaxy ``i`` is element ``i`` of each.
    config : Config, optional
        Settings (default ``Config()``); its lengths in reference pixels (module
        docstring). The joint fit's limits hold: one bulge size, no Sersic ladder.
    prior : Prior, optional
        An ellipticity prior to keep instead of estimating it.

    Returns
    -------
    Priors
        The priors, sizes and position width in reference pixels of
        ``info["pixel_scale"]`` arcsec, flux limits in the common flux unit;
        ``info["joint_fit"]`` is True.

    Warns
    -----
    CalibrationWarning
        For each prior that the sample is too small to estimate (its default is used).
    """
    cfg = config if config is not None else Config()
    scale = _reference_scale(views)
    groups = e_annuli(ellipticity_grid(cfg.e_step, emax=cfg.e_max))

    def fit_pass(cfgs, sps, keep, label):
        fits = fit_views(views, config=cfgs[0], pixel_scale=scale, size_prior=sps[0],
                         lnL_r_groups=groups if keep else None)  # fmt: skip
        ok = usable_galaxies(fits.flags, fits.is_star, fits.snr, cfgs[0].min_snr)
        log.info("%s: %d of %d galaxies usable", label, int(ok.sum()), len(ok))
        return _sample(fits, ok)

    priors = run_recipe(fit_pass, cfg, 1, prior=prior)[0]
    priors.info.update(joint_fit=True, pixel_scale=scale)
    return priors


def _combined(views: Sequence[ExposureStamps], used: np.ndarray,
              scale: float) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Per galaxy, the noise and the PSF size of its used exposures combined, as one
    exposure of the reference pixel (``scale`` arcsec) would have them.

    Exposure ``k`` (pixel area ``a_k``, noise ``sigma_k``, flux scale ``f_k``) gives a
    round source of flux ``F`` the squared S/N ``F^2 f_k^2 a_k / sigma_k^2`` per unit
    of the source's area on the sky: the combined noise per reference pixel (area
    ``a = scale^2``) in the common flux unit is ``(sum_k f_k^2 a_k / (a sigma_k^2))^-1/2``,
    and the PSF size (reference pixels) the mean of the exposures' (each exposure's
    median PSF image, adaptive moments) with those weights. NaN where none is used.
    """
    K = len(views)
    w = np.zeros((K, len(views[0])))
    psf = np.full(K, np.nan)
    for k, v in enumerate(views):  # one PSF size per exposure, not per galaxy
        area = np.abs(1.0 / np.linalg.det(np.where(np.isfinite(v.jacobian), v.jacobian,
                                                   np.eye(2))))  # fmt: skip
        on = (used >> k) & 1 > 0
        w[k] = np.where(on, v.flux_scale**2 * area / (scale**2 * v.noise_sigma**2), 0.0)
        if v.psf is not None and on.any():
            img = np.nanmedian(np.asarray(v.psf)[on], axis=0)
            psf[k] = psf_diagnostics(img)["sigma"] * np.nanmedian(v.pixel_scale[on]) / scale
    tot = w.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        sigma = np.where(tot > 0, 1.0 / np.sqrt(tot), np.nan)
        good = np.isfinite(psf)[:, None] & (w > 0)
        psf_sigma = (np.where(good, w * np.nan_to_num(psf)[:, None], 0.0).sum(axis=0)
                     / np.where(good, w, 0.0).sum(axis=0))  # fmt: skip
    return sigma, psf_sigma


def _as_stamp_fits(fits: JointFits, views: Sequence[ExposureStamps], used: np.ndarray
                   ) -> tuple[StampFits, np.ndarray, np.ndarray]:  # fmt: skip
    """The joint fits as :class:`~pylensfit.StampFits` for the stamps' table, in the
    pixels of each galaxy's first used exposure (``x, y`` its fitted centre there, as
    the catalogue position ``c_k + J_k X``), sizes in reference pixels, fluxes in the
    common flux unit, ``STAR`` flagged as the single fit flags it; and the catalogue
    positions ``(x, y)`` in that exposure."""
    n = len(fits)
    k0 = first_exposure(used, none=0)
    g = np.arange(n)
    xs, ys = np.stack([v.x for v in views]), np.stack([v.y for v in views])
    J = np.stack([v.jacobian for v in views])[k0, g]  # (n, 2, 2)
    cx, cy = xs[k0, g], ys[k0, g]
    off = np.einsum("nij,nj->ni", J, np.stack([fits.x, fits.y], axis=1))
    star = np.asarray(fits.is_star, dtype=bool)
    flags = fits.flags | np.where(star, _flags.flag_value("STAR"), 0).astype(np.int32)
    sf = StampFits(
        egrid=fits.egrid, lnL=fits.lnL, lnL_peak=fits.lnL_peak,
        r_best=fits.r_marginal / fits.pixel_scale, flux=fits.flux, x=cx + off[:, 0],
        y=cy + off[:, 1], snr=fits.snr, is_star=star, flags=flags, e1_best=fits.e1_best,
        e2_best=fits.e2_best, lnL_bulge=fits.lnL_bulge, lnL_star=fits.lnL_star,
        bulge_fractions=fits.bulge_fractions, bulge_best=fits.bulge_best,
        stamp=np.full(n, views[0].stamps.shape[-1]),
    )  # fmt: skip
    return sf, cx, cy


def measure_exposure_stamps(
    views: Sequence[ExposureStamps],
    *,
    priors: Priors | str | Path | None = None,
    config: Config | None = None,
    response: str = "model",
    metacal_step: float = 0.01,
    seed: int = 0,
) -> Table:
    """Shapes, errors, sensitivities and weights of galaxies fitted on all of their
    exposures at once.

    Each galaxy is fitted jointly on its usable exposures under the priors
    (:func:`pylensfit.joint.fit_views`, the size prior and the flux and position priors
    of :meth:`Priors.apply` included), and its table row assembled as
    :func:`pylensfit.measure_stamps`' (:func:`pylensfit.assemble.assemble`): the
    joint fit's shapes are in the sky frame ``(W, N)`` already.

    Parameters
    ----------
    views : sequence of pylensfit.exposures.ExposureStamps
        One per exposure (:func:`pylensfit.exposures.cut_exposures`), each with its PSF
        at the galaxies; galaxy ``i`` is element ``i`` of each. As for
        :func:`pylensfit.joint.fit_views`, each exposure's Jacobian is the median of its
        galaxies': give the galaxies of a region where it varies little.
    priors : Priors or str, optional
        The priors (or the path of a saved one), those of :func:`calibrate_exposures`
        (their ``info["pixel_scale"]`` is the fit's reference pixel); by default
        :func:`calibrate_exposures` estimates them from ``views`` themselves.
    config : Config, optional
        Settings (default ``Config()``); the one the priors were estimated with.
    response, metacal_step, seed
        As :func:`pylensfit.measure_stamps`: with ``"metacal"`` each galaxy is also
        metacalibrated on all its exposures (:func:`pylensfit.metacal.metacal_exposures`:
        each exposure's stamp sheared on the sky about the fitted position, the five
        images fitted jointly); ``measure_stamps``' metacalibration columns, sky frame.

    Returns
    -------
    astropy.table.Table
        One row per galaxy, in order, with :func:`pylensfit.measure_stamps`' columns
        (:data:`pylensfit.calibration.stamps.STAMP_COLUMNS`, their meanings those of
        :data:`pylensfit.catalogue.COLUMNS`) and ``lnL``, plus ``n_exposures`` and
        ``exposures_used``. ``e1, e2`` and their covariance and sensitivities, and
        ``e1_best, e2_best``, are in the sky frame. The image columns are those of the
        galaxy's first used exposure (the lowest bit of ``exposures_used``; exposure 0
        where none): ``x, y`` the fitted centre in its image pixels, ``x_detect,
        y_detect`` the catalogue position there. The fit's quantities are those of all
        its exposures: ``model_flux`` in the common flux unit, ``scalelength`` in
        reference pixels, ``noise_sigma`` the exposures' combined noise per reference
        pixel in the common flux unit (:func:`_combined`), which with the exposures'
        combined PSF size sets the classes of the weights. A galaxy without a usable
        exposure is flagged ``NOT_MEASURED`` with NaN shapes and weight 0. ``meta``: as
        :func:`pylensfit.measure_stamps`', and ``pixel_scale`` (arcsec).
    """
    if response not in ("model", "metacal"):
        raise ValueError(f"response must be 'model' or 'metacal', got {response!r}")
    cfg = config if config is not None else Config()
    if isinstance(priors, (str, Path)):
        priors = Priors.load(priors)
    if priors is None:
        priors = calibrate_exposures(views, config=cfg)
    if not isinstance(priors, Priors):
        raise TypeError(f"priors must be a Priors object or a path, got {type(priors).__name__}")
    scale = float(priors.info.get("pixel_scale", _reference_scale(views)))
    run_cfg = priors.apply(cfg)
    fits = fit_views(views, config=run_cfg, pixel_scale=scale, size_prior=priors.size)
    used = fits.exposures_used
    sf, cx, cy = _as_stamp_fits(fits, views, used)
    sigma, psf_sigma = _combined(views, used, scale)
    t = stamps_table(sf, priors, run_cfg, cx, cy, sigma, psf_sigma)
    t["n_exposures"] = np.asarray(fits.n_exposures, dtype=np.int16)
    t["exposures_used"] = np.asarray(used, dtype=np.int64)
    for c in ("n_exposures", "exposures_used"):
        t[c].description = COLUMNS[c][1]
    t.meta["pixel_scale"] = scale
    if response == "metacal":
        _add_metacal(t, ViewArrays.of(views), priors, run_cfg, fits, scale, metacal_step, seed)
    return t


#: galaxies metacalibrated at a time by :func:`measure_exposure_stamps`
_METACAL_BLOCK = 1024


def _add_metacal(t: Table, arr: ViewArrays, priors: Priors, run_cfg: Config, fits: JointFits,
                 scale: float, step: float, seed: int) -> None:  # fmt: skip
    """:func:`measure_exposure_stamps`' metacalibration columns, in place: each block's
    added noise fields drawn from ``(seed, first row)``; NaN where a galaxy has no
    usable exposure or one of its five fits is not usable."""
    cols = {c: np.full(len(t), np.nan) for c in ("e1_mcal", "e2_mcal", "R11", "R12", "R21",
                                                 "R22")}  # fmt: skip
    for start in range(0, len(t), _METACAL_BLOCK):
        rows = np.arange(start, min(start + _METACAL_BLOCK, len(t)))
        a = arr.take(rows)
        fields = np.random.default_rng([seed, start]).standard_normal(a.stamps.shape)
        mc = metacal_exposures(a.stamps, a.psf, a.noise_sigma, a.jacobian,
                               offsets=(fits.x[rows], fits.y[rows]), centres=a.centres,
                               flux_scale=a.flux_scale, usable=a.usable, config=run_cfg,
                               pixel_scale=scale, size_prior=priors.size, step=step,
                               noise_fields=fields,
                               reconvolution=run_cfg.metacal_reconvolution)  # fmt: skip
        br = metacal_branches(mc, priors.ellipticity, bulge_weights=priors.bulge_weights,
                              refine=run_cfg.output_refine, step=step)  # fmt: skip
        ok = np.all([br.usable[k] for k in br.usable], axis=0)
        R = np.where(ok[:, None, None], br.R, np.nan)
        for i in range(2):
            cols[f"e{i + 1}_mcal"][rows] = np.where(ok, br.e["noshear"][:, i], np.nan)
            for j in range(2):
                cols[f"R{i + 1}{j + 1}"][rows] = R[:, i, j]
    for c, v in cols.items():
        t[c] = v
        t[c].description = COLUMNS[c][1]
    t.meta["metacal_step"] = float(step)
