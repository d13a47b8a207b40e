"""From the exposures of one field to a shear catalogue, each galaxy fitted jointly on
every exposure that holds it (:func:`pylensfit.joint.fit_exposures`; lensfit's survey
version, Miller et al. 2013, arXiv:1210.8201).

:func:`measure_exposures` walks the path:

1. read each exposure (:meth:`pylensfit.exposures.Exposure.from_fits`): image, ``WEIGHT``
   HDU, celestial WCS (SIP and TPV distortions included) and zero point, which gives the
   exposure's flux scale against the common unit (the first exposure's zero point unless
   one is given);
2. each exposure's PSF: given (a PSF image or a model over the field, one per exposure or
   one for all), or from its star field (``stars``, one per exposure), or from its own
   stars, by the single-image pipeline's rules (``Config.psf_model``: a stack, or a
   polynomial model where the stars show the PSF varying);
3. the galaxies' sky positions: an input catalogue (``ra, dec`` or ``ALPHA_J2000,
   DELTA_J2000``, degrees), or detection on a co-add of the exposures made for detection
   only (:func:`detection_coadd`: each exposure resampled with reproject onto one tangent
   plane, in the common flux unit, weighted by its inverse variance; the co-add is never
   fitted);
4. every galaxy's stamp in every exposure (:func:`pylensfit.exposures.cut_exposures`); an
   exposure where the galaxy is off the image, on its edge, on a masked or zero-weight
   centre or a chip gap drops out of that galaxy's fit alone;
5. the joint fit and the shapes under the priors
   (:func:`pylensfit.calibration.measure_exposure_stamps`), by groups of galaxies
   whose WCS Jacobians agree within 1e-4 in every exposure (:func:`jacobian_groups`:
   one Jacobian per exposure and group), the priors
   given or estimated from the set's own joint fits
   (:func:`pylensfit.calibration.calibrate_exposures`);
6. the stamp tiers (:func:`_retier`): a galaxy that needs a larger stamp by the
   single-image fit's rule (``Config.stamp_hlr_ratio``, up to ``max_stamp_size``) and
   holds no other object of ``model_SNratio >= Config.close_pair_min_snr`` within it is
   fitted again on it, on the frequencies ``|k| <= pi / j`` of a stamp ``j`` times the
   base;
7. the neighbours taken out of each exposure (:func:`_subtract_neighbours`: every
   object's sky-frame model rendered into every exposure through its WCS, PSF and flux
   scale, :func:`pylensfit.images.neighbours.exposure_light`) and the galaxies whose
   stamps hold their light fitted again, ``Config.neighbour_iterations`` rounds;
8. the catalogue: one row per position, shapes in the sky frame, ``n_exposures`` and
   ``exposures_used`` saying which exposures each galaxy's fit used, ``CLOSE_PAIR`` as
   the single-image pipeline sets it (from the fits' S/N), written atomically.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import astropy.units as u
import numpy as np
from astropy.table import Table, vstack
from astropy.wcs import WCS

from ..calibration import Priors, calibrate_exposures, measure_exposure_stamps
from ..catalogue import COLUMNS
from ..config import Config
from ..detection import close_pairs, detect, flag_close_pairs
from ..exposures import (
    Exposure,
    ExposureStamps,
    cut_exposures,
    local_jacobian,
    mask_cosmic_rays,
    sky_to_pixel,
)
from ..flags import FLAGS
from ..joint import ViewArrays, first_exposure
from ..likelihood.tiers import stamp_tiers, tier_sizes
from ..metacal import metacal_branches, metacal_exposures
from ..psf import PSFResult
from ..psfmodel import PSFModel
from .catalogue_io import write_catalogue
from .image_psf import starfield_task
from .inputs import InputError, check_inputs, load_given, open_input, read_given_psfs
from .metacal_rows import METACAL_BLOCK, empty_columns, noise_fields, store_branches
from .neighbours import exposure_light, exposure_neighbour_stamps, sky_models
from .records import StarfieldTask

log = logging.getLogger(__name__)

__all__ = ["ExposureSet", "detection_coadd", "jacobian_groups", "measure_exposures",
           "read_exposures", "read_sky_positions"]  # fmt: skip

@dataclass(frozen=True)
class ExposureSet:
    """The exposures of one field, read, with their PSFs.

    Attributes
    ----------
    exposures : list of pylensfit.exposures.Exposure
        In the order given; ``Exposure.psf`` set.
    paths : list of str
        Their files.
    zero_point : float or None
        The common flux unit's zero point (magnitudes), None where the files have none.
    psf_sources : list of str
        Where each exposure's PSF came from, in words.
    psf_suspect : numpy.ndarray
        ``(K,)`` bool: the exposure's PSF model fails its check on held-out stars (the
        rows fitted with it are flagged ``PSF_SUSPECT``).
    """

    exposures: list[Exposure]
    paths: list[str]
    zero_point: float | None
    psf_sources: list[str]
    psf_suspect: np.ndarray


def _zero_point(path: str, key: str) -> float | None:
    """The zero point card of ``path``'s first HDU, or None."""
    with open_input(path, "exposure") as h:
        v = h[0].header.get(key)
    return None if v is None else float(v)


def _psf_of(k: int, path: str, star_field: str | None, given, cfg: Config):
    """Exposure ``k``'s PSF (an image or a model with ``draw``) and its source."""
    if given is not None:
        if isinstance(given, PSFModel):
            return given, "given model"
        return (given.image if isinstance(given, PSFResult) else np.asarray(given)), "given"
    src = star_field if star_field is not None else path
    try:
        res = starfield_task(StarfieldTask(path=src, index=k, config=cfg))
    except InputError as err:
        what = "its star field" if star_field is not None else "its own stars"
        raise InputError(f"{path}: no PSF from {what} ({err})") from None
    kind = "polynomial model" if isinstance(res, PSFModel) else "stack"
    where = "star field" if star_field is not None else "exposure's stars"
    return (res if isinstance(res, PSFModel) else res.image), f"{kind} of the {where}"


def read_exposures(paths: Sequence[str], *, stars: Sequence[str] | None = None, psf=None,
                   config: Config | None = None, reference_zero_point: float | None = None,
                   zero_point_key: str = "MAGZP") -> ExposureSet:  # fmt: skip
    """Read the exposures of a field and find each one's PSF.

    Parameters
    ----------
    paths : sequence of str
        The exposures' FITS files (image in the first HDU with a celestial WCS, inverse
        variance in a ``WEIGHT`` HDU if present, zero point in ``zero_point_key``).
    stars : sequence of str, optional
        One star-field image per exposure, for its PSF (default: the exposure's own
        stars).
    psf : optional
        The PSFs instead: a FITS image or PSF model file, a ``PSFResult``, a
        ``PSFModel`` or an array, for every exposure or one per exposure.
    config : Config, optional
        ``psf_model``, ``psf_order``, ``psf_min_stars`` and the star selection's
        settings (default ``Config()``).
    reference_zero_point : float, optional
        The common flux unit's zero point, magnitudes (default: the first exposure's).
    zero_point_key : str
        The zero point's header card.

    Returns
    -------
    ExposureSet
        The exposures; each galaxy's flux is in the common unit.

    Raises
    ------
    InputError
        One line naming the file and the problem (missing, unreadable, no WCS, no PSF).
    """
    cfg = config if config is not None else Config()
    paths = [os.fspath(p) for p in paths]
    stars = [os.fspath(s) for s in stars] if stars else []
    if not paths:
        raise InputError("no exposure given")
    if stars and len(stars) != len(paths):
        raise InputError(f"stars: {len(stars)} star field(s) for {len(paths)} exposures "
                         "(give one per exposure, or none)")  # fmt: skip
    for p in [*paths, *stars]:
        if not Path(p).exists():
            raise InputError(f"{p}: {'star field' if p in stars else 'exposure'} not found")
    check_inputs(paths, [None] * len(paths), [None] * len(paths), stars)
    given = read_given_psfs(psf, paths) or [None] * len(paths)
    zp = reference_zero_point
    if zp is None:
        zp = _zero_point(paths[0], zero_point_key)
    exposures, sources, suspect = [], [], []
    for k, p in enumerate(paths):
        image_psf, source = _psf_of(k, p, stars[k] if stars else None, given[k], cfg)
        suspect.append(isinstance(image_psf, PSFModel)
                       and image_psf.diagnostics.get("heldout_suspect") == 1.0)  # fmt: skip
        try:
            e = Exposure.from_fits(p, psf=image_psf, zero_point_key=zero_point_key,
                                   reference_zero_point=zp)  # fmt: skip
        except ValueError as err:
            raise InputError(str(err) if str(err).startswith(p) else f"{p}: {err}") from None
        if cfg.cosmic_rays:
            e, n_cr = mask_cosmic_rays(e)
            log.info("%s: %d cosmic-ray pixels masked", p, n_cr)
        exposures.append(e)
        sources.append(source)
    return ExposureSet(exposures=exposures, paths=paths, zero_point=zp, psf_sources=sources,
                       psf_suspect=np.array(suspect, bool))  # fmt: skip


def detection_coadd(exposures: Sequence[Exposure]) -> tuple[np.ndarray, np.ndarray, WCS]:
    """The exposures co-added for detection only: common flux unit, inverse-variance
    weights, on a tangent plane that covers them all.

    Each exposure's background-subtracted image, divided by its flux scale, and its
    weight times the flux scale squared are resampled bilinearly (reproject) onto the
    plane; the co-add is ``sum w d / sum w`` and its weight ``sum w``. Resampling
    correlates the noise, so the weight is a detection threshold's guide, not the
    co-add's true variance (the co-add is never fitted).

    Parameters
    ----------
    exposures : sequence of pylensfit.exposures.Exposure
        The exposures.

    Returns
    -------
    tuple
        ``(image, weight, wcs)``: the co-add (common flux unit per pixel), its weight
        (0 where no exposure has data) and its WCS.
    """
    # reproject: the field's library for co-adds, needed by this step alone
    from reproject import reproject_interp
    from reproject.mosaicking import find_optimal_celestial_wcs

    scale = np.sqrt(abs(np.linalg.det(exposures[0].wcs.celestial.pixel_scale_matrix)))
    wcs, shape = find_optimal_celestial_wcs([(e.shape, e.wcs.celestial) for e in exposures],
                                            resolution=float(scale) * u.deg)  # fmt: skip
    num = np.zeros(shape)
    den = np.zeros(shape)
    for e in exposures:
        w = (np.asarray(e.weight, float) if e.weight is not None
             else np.full(e.shape, 1.0 / max(e.noise_sigma or 1.0, 1e-30) ** 2))  # fmt: skip
        w = np.where(e.good() & np.isfinite(e.image), w * e.flux_scale**2, 0.0)
        d = np.where(w > 0, (np.asarray(e.image) - e.background) / e.flux_scale, 0.0)
        rd, fp = reproject_interp((d * w, e.wcs.celestial), wcs, shape, order="bilinear")
        rw, _ = reproject_interp((w, e.wcs.celestial), wcs, shape, order="bilinear")
        ok = (fp > 0) & np.isfinite(rd) & np.isfinite(rw) & (rw > 0)
        num += np.where(ok, rd, 0.0)
        den += np.where(ok, rw, 0.0)
    image = np.divide(num, den, out=np.zeros(shape), where=den > 0)
    return image, den, wcs


def read_sky_positions(path: str) -> Table:
    """An input catalogue of sky positions: ``ra, dec`` or ``ALPHA_J2000, DELTA_J2000``
    (degrees); its other columns are kept.

    Raises
    ------
    InputError
        One line naming the file: missing, unreadable, empty, or without the columns.
    """
    try:
        t = Table.read(path)
    except FileNotFoundError:
        raise InputError(f"{path}: input catalogue not found") from None
    except Exception as err:  # astropy raises many kinds for a file it cannot read
        raise InputError(f"{path}: cannot read the input catalogue ({err})") from None
    if len(t) == 0:
        raise InputError(f"{path}: empty input catalogue")
    names = {c.lower(): c for c in t.colnames}
    pair = next(((names[a], names[b]) for a, b in (("ra", "dec"), ("alpha_j2000", "delta_j2000"))
                 if a in names and b in names), None)  # fmt: skip
    if pair is None:
        raise InputError(f"{path}: input catalogue needs columns ra, dec or ALPHA_J2000, "
                         "DELTA_J2000 (degrees)")  # fmt: skip
    out = Table()
    try:
        out["ra"] = np.asarray(t[pair[0]], dtype=float)
        out["dec"] = np.asarray(t[pair[1]], dtype=float)
    except (TypeError, ValueError) as err:
        raise InputError(f"{path}: the sky positions are not numbers ({err})") from None
    for c in t.colnames:
        if c not in pair and c not in out.colnames:
            out[c] = t[c]
    return out


def detect_positions(coadd: tuple[np.ndarray, np.ndarray, WCS], cfg: Config) -> Table:
    """The objects detected on the co-add (:func:`detection_coadd`), with ``ra, dec``
    (degrees) and the detection's photometry (:func:`pylensfit.detection.detect`)."""
    image, weight, wcs = coadd
    det = detect(image, weight=weight, mask=weight <= 0, threshold=cfg.detect_threshold,
                 min_area=cfg.detect_min_area, stamp_size=cfg.stamp_size)  # fmt: skip
    if len(det) == 0:
        raise InputError("the co-add of the exposures: no object detected")
    sky = wcs.pixel_to_world(np.asarray(det["x"]), np.asarray(det["y"]))
    out = Table()
    out["ra"] = sky.spherical.lon.deg
    out["dec"] = sky.spherical.lat.deg
    for c in ("flux", "flux_err", "snr", "r_half", "mag"):
        if c in det.colnames:
            out[c] = det[c]
    out["x_coadd"], out["y_coadd"] = det["x"], det["y"]
    return out


def jacobian_groups(exposures: Sequence[Exposure], ra, dec, tolerance: float) -> np.ndarray:
    """Group the positions whose local WCS Jacobians agree within ``tolerance`` in every
    exposure, so that one Jacobian per exposure serves each group.

    Each exposure's Jacobian at a position, relative to the exposure's median one,
    ``J J_med^-1 - I``, is rounded to multiples of ``tolerance``; positions with the same
    rounded matrices in every exposure form a group. Within a group each exposure's
    Jacobians differ by less than ``tolerance`` per element, which changes a model's
    ellipticity by about as much (:func:`pylensfit.joint.fit_views`). A TAN projection
    varies by 1e-6 over 5 arcmin: a field without distortion is one group.

    Parameters
    ----------
    exposures : sequence of pylensfit.exposures.Exposure
        The exposures.
    ra, dec : array_like
        The positions, degrees.
    tolerance : float
        The largest relative difference of the Jacobians within a group.

    Returns
    -------
    numpy.ndarray
        ``(n,)`` int group labels; positions without a finite Jacobian in some exposure
        are rounded there as if they had the median one.
    """
    return _labels([local_jacobian(e.wcs, ra, dec) for e in exposures], tolerance)


def _labels(jacobians: list[np.ndarray], tolerance: float) -> np.ndarray:
    """:func:`jacobian_groups` of the positions' Jacobians, ``(n, 2, 2)`` per exposure."""
    keys = []
    for J in jacobians:
        ok = np.all(np.isfinite(J), axis=(1, 2))
        med = np.median(J[ok], axis=0) if ok.any() else np.eye(2)
        D = np.where(ok[:, None, None], J @ np.linalg.inv(med) - np.eye(2), 0.0)
        keys.append(np.round(D.reshape(len(J), 4) / tolerance).astype(np.int64))
    return np.unique(np.concatenate(keys, axis=1), axis=0, return_inverse=True)[1].ravel()


def _sample(n_ok: np.ndarray, size: int, seed: int) -> np.ndarray:
    """A seeded draw of at most ``size`` of the indices ``n_ok``, in order."""
    if n_ok.size <= size:
        return n_ok
    return np.sort(np.random.default_rng(seed).choice(n_ok, size, replace=False))


def _calibrate(eset: ExposureSet, ra, dec, usable: np.ndarray, groups: np.ndarray,
               cfg: Config) -> Priors:  # fmt: skip
    """The priors of the set's own joint fits, on a seeded sample of the usable positions
    of its largest group of one Jacobian per exposure (``groups``,
    :func:`jacobian_groups`)."""
    largest = np.bincount(groups[usable]).argmax() if usable.any() else 0
    idx = _sample(np.flatnonzero(usable & (groups == largest)), cfg.calibration_sample,
                  cfg.calibration_seed)  # fmt: skip
    if idx.size == 0:
        raise InputError(f"{eset.paths[0]}: no position to calibrate the priors on")
    views = cut_exposures(eset.exposures, ra[idx], dec[idx], size=cfg.stamp_size)
    log.info("calibrating the priors on the joint fits of %d of %d positions", idx.size,
             len(ra))  # fmt: skip
    return calibrate_exposures(views, config=cfg)


def _positions(eset: ExposureSet, catalogue: str | None, cfg: Config) -> Table:
    """The input catalogue's sky positions, or the co-add's detections."""
    if catalogue is not None:
        return read_sky_positions(os.fspath(catalogue))
    return detect_positions(detection_coadd(eset.exposures), cfg)


def _pairs(eset: ExposureSet, ra, dec, cfg: Config,
           t: Table | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Which positions fall on the first exposure's plane, and which of those are close
    pairs (:func:`pylensfit.detection.close_pairs`): with the fits ``t``, as the
    single-image pipeline flags them (a galaxy whose stamp holds another object of
    ``model_SNratio >= Config.close_pair_min_snr``, with ``close_pair_faint_ratio``;
    a fainter object if its stamp holds anything); without, every other position."""
    x0, y0 = sky_to_pixel(eset.exposures[0].wcs, ra, dec)
    ok = np.isfinite(x0) & np.isfinite(y0)
    pairs = np.zeros(len(ra), bool)
    if t is None:
        pairs[ok] = close_pairs(x0[ok], y0[ok], stamp_size=cfg.stamp_size)
    else:
        pairs[ok] = flag_close_pairs(x0[ok], y0[ok],
                                     np.nan_to_num(np.asarray(t["model_flux"], float))[ok],
                                     np.asarray(t["model_SNratio"], float)[ok],
                                     stamp_size=cfg.stamp_size, min_snr=cfg.close_pair_min_snr,
                                     faint_ratio=cfg.close_pair_faint_ratio)  # fmt: skip
    return ok, pairs


def _nowhere(ra: np.ndarray, dec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The positions, those not finite put 30 degrees from the others (on no exposure,
    where they are cut and fitted with nothing and flagged ``NOT_MEASURED``)."""
    lost = ~(np.isfinite(ra) & np.isfinite(dec))
    if not lost.any():
        return ra, dec
    d0 = float(np.mean(dec[~lost])) if (~lost).any() else 0.0
    r0 = float(np.mean(ra[~lost])) if (~lost).any() else 0.0
    return np.where(lost, r0, ra), np.where(lost, d0 - 30.0 if d0 > 0 else d0 + 30.0, dec)


@dataclass(frozen=True)
class _Groups:
    """The positions' groups of one WCS Jacobian per exposure (:func:`jacobian_groups`)
    and that Jacobian: the median of the members', fixed for every fit of the group, so
    that each exposure's bank (and its wrapped wings) is built once per group and tier."""

    labels: np.ndarray  # (n,) int
    jacobians: np.ndarray  # (n_groups, K, 2, 2), pixels per arcsec

    @classmethod
    def of(cls, eset: ExposureSet, ra, dec, tolerance: float) -> _Groups:
        """The groups of :func:`jacobian_groups` and their Jacobians, from one evaluation
        of every exposure's Jacobian at every position."""
        Js = [local_jacobian(e.wcs, ra, dec) for e in eset.exposures]
        labels = _labels(Js, tolerance)
        jac = np.tile(np.eye(2), (int(labels.max(initial=0)) + 1, len(Js), 1, 1))
        for lab in np.unique(labels):
            for k, J in enumerate(Js):
                Jm = J[labels == lab]
                fin = np.isfinite(Jm).all(axis=(1, 2))
                if fin.any():
                    jac[lab, k] = np.median(Jm[fin], axis=0)
        return cls(labels=labels, jacobians=jac)

    def views(self, eset: ExposureSet, ra, dec, idx: np.ndarray, size: int) -> list:
        """The stamps of the positions ``idx`` (one group) with the group's Jacobians."""
        views = cut_exposures(eset.exposures, ra[idx], dec[idx], size=int(size))
        jac = self.jacobians[self.labels[idx[0]]] if idx.size else None
        return [v if jac is None else replace(v, jacobian=np.broadcast_to(jac[k], (idx.size, 2, 2)))
                for k, v in enumerate(views)]  # fmt: skip


def _tier_config(cfg: Config, side: int) -> Config:
    """The configuration of the joint fits on ``side``-pixel stamps: a stamp tier ``j``
    times ``Config.stamp_size`` sums the frequencies ``|k| <= pi / j``, as the
    single-image fit's tiers do."""
    if side == cfg.stamp_size:
        return cfg
    return cfg.replace(stamp_size=int(side), max_stamp_size=0,
                       k_max=float(np.pi * cfg.stamp_size / side))  # fmt: skip


def _tier_sides(eset: ExposureSet, ra, dec, idx: np.ndarray, used: np.ndarray,
                cfg: Config) -> np.ndarray:  # fmt: skip
    """Each galaxy's stamp side, by the single-image fit's rule
    (:func:`pylensfit.likelihood.tiers.stamp_tiers`: ``Config.stamp_hlr_ratio`` of its
    PSF-convolved half-light radius) on its first exposure usable at the largest side; a
    galaxy whose base fit used an exposure (``used``, the ``exposures_used`` bits) that
    does not hold it at the largest side keeps the base side."""
    n0, top = cfg.stamp_size, cfg.largest_stamp
    sides = np.full(idx.size, n0)
    if top <= n0 or idx.size == 0:
        return sides
    big = cut_exposures(eset.exposures, ra[idx], dec[idx], size=top)
    use_t = np.stack([v.usable for v in big])
    use_b = (np.asarray(used, np.int64)[None] >> np.arange(len(big))[:, None]) & 1 == 1
    ok = (use_t == use_b).all(axis=0) & use_t.any(axis=0)
    first = np.argmax(use_t, axis=0)
    sizes = tier_sizes(cfg, (top, top))
    for k in np.unique(first[ok]):
        i = np.flatnonzero(ok & (first == k))
        cx, cy = big[k].centres
        sides[i] = stamp_tiers(big[k].stamps[i], big[k].psf[i[i.size // 2]],
                               big[k].noise_sigma[i], cfg, cx[i], cy[i], sizes)[0]  # fmt: skip
    return sides


def _measure_groups(eset: ExposureSet, ra, dec, groups: _Groups, chunk: int,
                    priors: Priors, cfg: Config) -> Table:  # fmt: skip
    """Every position measured on the base stamp, by groups of one Jacobian per exposure
    (``groups``) and chunks of at most ``chunk`` positions, in the input order."""
    parts, order = [], []
    for lab in np.unique(groups.labels):
        members = np.flatnonzero(groups.labels == lab)
        for idx in np.array_split(members, -(-members.size // chunk)):
            views = groups.views(eset, ra, dec, idx, cfg.stamp_size)
            parts.append(measure_exposure_stamps(views, priors=priors, config=cfg))
            order.append(idx)
    t = vstack(parts, metadata_conflicts="silent")
    t = t[np.argsort(np.concatenate(order), kind="stable")]
    t.meta.update(parts[0].meta)
    return t


def _retier(eset: ExposureSet, ra, dec, groups: _Groups, chunk: int, priors: Priors,
            cfg: Config, t: Table) -> None:  # fmt: skip
    """The stamp tiers: the galaxies (:func:`_refittable`) that :func:`_tier_sides` gives
    a larger stamp, and that hold no other object of ``model_SNratio >=
    Config.close_pair_min_snr`` within it, fitted again on it; their rows of ``t``
    replaced."""
    top = cfg.largest_stamp
    if top <= cfg.stamp_size:
        return
    x0, y0 = sky_to_pixel(eset.exposures[0].wcs, ra, dec)
    sig = np.isfinite(x0) & (np.nan_to_num(np.asarray(t["model_SNratio"], float))
                             >= cfg.close_pair_min_snr)  # fmt: skip
    alone = np.ones(len(ra), bool)
    alone[sig] = ~close_pairs(x0[sig], y0[sig], stamp_size=top)
    cand = _refittable(t) & alone
    for lab in np.unique(groups.labels[cand]):
        members = np.flatnonzero(cand & (groups.labels == lab))
        for idx in np.array_split(members, -(-members.size // chunk)):
            sides = _tier_sides(eset, ra, dec, idx, t["exposures_used"][idx], cfg)
            for side in np.unique(sides[sides > cfg.stamp_size]):
                sub = idx[sides == side]
                views = groups.views(eset, ra, dec, sub, side)
                new = measure_exposure_stamps(views, priors=priors,
                                              config=_tier_config(cfg, side))  # fmt: skip
                for c in new.colnames:
                    t[c][sub] = new[c]


def _measure(eset: ExposureSet, ra, dec, groups: _Groups, chunk: int, priors: Priors,
             cfg: Config) -> Table:  # fmt: skip
    """The joint fits of every position: on the base stamp (:func:`_measure_groups`),
    then on the larger stamp tiers (:func:`_retier`), then with the neighbours taken out
    (:func:`_subtract_neighbours`)."""
    t = _measure_groups(eset, ra, dec, groups, chunk, priors, cfg)
    _retier(eset, ra, dec, groups, chunk, priors, cfg, t)
    t = _subtract_neighbours(eset, ra, dec, groups, chunk, priors, cfg, t)
    if cfg.response == "metacal":
        _metacalibrate(eset, ra, dec, groups, priors, cfg, t)
    return t


def _metacalibrate(eset: ExposureSet, ra, dec, groups: _Groups, priors: Priors, cfg: Config,
                   t: Table) -> None:  # fmt: skip
    """``Config.response = "metacal"``: the measured galaxies (:func:`_refittable`)
    metacalibrated on all their exposures (:func:`pylensfit.metacal.metacal_exposures`),
    the single-image pipeline's columns (:mod:`pylensfit.images.metacal_rows`) added to
    ``t`` in the sky frame. Each galaxy's stamps are ``Config.largest_stamp`` pixels,
    less the other objects' light where the neighbours are taken out, sheared about its
    fitted sky position; an exposure that does not hold that stamp drops out of its
    fits; its added noise fields are drawn from ``(Config.metacal_seed, exposure,
    row)``."""
    cols, todo, top = empty_columns(len(t)), _refittable(t), cfg.largest_stamp
    run_cfg = priors.apply(cfg).replace(stamp_size=top, max_stamp_size=0)
    light = None
    if cfg.subtract_neighbours:
        models = sky_models(t, *_fitted_sky(t, ra, dec, eset), cfg)
        light = (models, [exposure_light(e, models, cfg) for e in eset.exposures])
    X = _sky_offsets(t, groups, len(eset.exposures))
    for lab in np.unique(groups.labels[todo]):
        members = np.flatnonzero(todo & (groups.labels == lab))
        for idx in np.array_split(members, -(-members.size // METACAL_BLOCK)):
            views = groups.views(eset, ra, dec, idx, top)
            if light is not None:
                every = np.arange(idx.size)
                views = [_take(v, every, exposure_neighbour_stamps(f, v, e, light[0], idx, cfg))
                         for v, f, e in zip(views, light[1], eset.exposures, strict=True)]
            a = ViewArrays.of(views)
            fields = np.stack([noise_fields(cfg.metacal_seed, k, idx, top)
                               for k in range(len(views))])  # fmt: skip
            mc = metacal_exposures(a.stamps, a.psf, a.noise_sigma, a.jacobian,
                                   offsets=(X[idx, 0], X[idx, 1]), centres=a.centres,
                                   flux_scale=a.flux_scale, usable=a.usable, config=run_cfg,
                                   pixel_scale=float(t.meta["pixel_scale"]),
                                   size_prior=priors.size, step=cfg.metacal_step,
                                   noise_fields=fields,
                                   reconvolution=cfg.metacal_reconvolution)  # fmt: skip
            store_branches(cols, idx, metacal_branches(
                mc, priors.ellipticity, bulge_weights=priors.bulge_weights,
                refine=run_cfg.output_refine, step=cfg.metacal_step))  # fmt: skip
    for c, v in cols.items():
        t[c] = v


def _sky_offsets(t: Table, groups: _Groups, K: int) -> np.ndarray:
    """``(n, 2)`` each row's fitted sky offset from its catalogue position, arcsec (W, N):
    its fitted centre's offset in its first used exposure's pixels through that
    exposure's Jacobian (0 where none is used)."""
    used = np.asarray(t["exposures_used"], np.int64)
    first = first_exposure(used, none=0)
    J = groups.jacobians[groups.labels, np.minimum(first, K - 1)]
    d = np.column_stack([np.asarray(t["x"], float) - np.asarray(t["x_detect"], float),
                         np.asarray(t["y"], float) - np.asarray(t["y_detect"], float)])
    X = np.linalg.solve(J, np.nan_to_num(d)[..., None])[..., 0]
    return np.where((used > 0)[:, None], X, 0.0)


def _take(view: ExposureStamps, sel: np.ndarray, less: np.ndarray) -> ExposureStamps:
    """The galaxies ``sel`` of one exposure's view, ``less`` taken out of their stamps
    (where the stamps have data)."""
    fr = view.frame.take(sel)
    w = view.weights[sel]
    return replace(view, stamps=view.stamps[sel] - np.where(w > 0, less[sel], 0.0), weights=w,
                   noise_sigma=view.noise_sigma[sel],
                   psf=None if view.psf is None else view.psf[sel], x=view.x[sel],
                   y=view.y[sel], x0=view.x0[sel], y0=view.y0[sel],
                   jacobian=view.jacobian[sel], frame=fr, flags=view.flags[sel])  # fmt: skip


def _refittable(t: Table) -> np.ndarray:
    """The rows whose neighbours are taken out: measured galaxies (a finite ``L(e)``,
    no flag but ``CLOSE_PAIR``); ``LOW_SNR`` rows (weight 0, most of them noise peaks of
    the detection) and stars are not fitted again."""
    lnL = np.asarray(t["lnL"], dtype=float)
    keep = FLAGS["CLOSE_PAIR"][0]
    return np.isfinite(lnL).all(axis=1) & ((np.asarray(t["flags"], np.int64) & ~keep) == 0)


def _neighbour_round(eset: ExposureSet, ra, dec, groups: _Groups, chunk: int,
                     priors: Priors, cfg: Config, t: Table) -> int:  # fmt: skip
    """One round of the neighbours taken out: every object's current model rendered into
    every exposure (:func:`~pylensfit.images.neighbours.exposure_light`), and the
    galaxies (:func:`_refittable`) whose stamps hold more than
    ``Config.neighbour_min_chi2`` noise variances of other objects' light, summed over
    their exposures, fitted again on their stamps less that light; their rows of ``t``
    replaced. Returns how many were fitted again."""
    ra_f, dec_f = _fitted_sky(t, ra, dec, eset)
    models = sky_models(t, ra_f, dec_f, cfg)
    fields = [exposure_light(e, models, cfg) for e in eset.exposures]
    cand = _refittable(t)
    n_done = 0
    for lab in np.unique(groups.labels[cand]):
        members = np.flatnonzero(cand & (groups.labels == lab))
        for idx in np.array_split(members, -(-members.size // chunk)):
            sides = np.asarray(t["stamp_size"], dtype=int)[idx]
            for side in np.unique(sides):
                n_done += _refit(eset, ra, dec, idx[sides == side], (models, fields, cfg, groups),
                                 priors, _tier_config(cfg, side), t)  # fmt: skip
    return n_done


def _refit(eset: ExposureSet, ra, dec, idx: np.ndarray, light: tuple, priors: Priors,
           cfg: Config, t: Table) -> int:  # fmt: skip
    """:func:`_neighbour_round` on the galaxies ``idx`` of one Jacobian group and stamp
    tier (``cfg``, :func:`_tier_config`); ``light`` the models, each exposure's image of
    them, the configuration they were rendered with and the groups."""
    models, fields, drawn, groups = light
    views = groups.views(eset, ra, dec, idx, cfg.stamp_size)
    less = [exposure_neighbour_stamps(f, v, e, models, idx, drawn)
            for f, v, e in zip(fields, views, eset.exposures, strict=True)]  # fmt: skip
    pairs = list(zip(views, less, strict=True))
    chi2 = sum(np.sum(lo * lo * v.weights, axis=(1, 2)) for v, lo in pairs)
    go = np.flatnonzero(chi2 > cfg.neighbour_min_chi2)
    if go.size:
        new = measure_exposure_stamps([_take(v, go, lo) for v, lo in pairs], priors=priors,
                                      config=cfg)  # fmt: skip
        for c in new.colnames:
            t[c][idx[go]] = new[c]
    return int(go.size)


def _subtract_neighbours(eset: ExposureSet, ra, dec, groups: _Groups, chunk: int,
                         priors: Priors, cfg: Config, t: Table) -> Table:  # fmt: skip
    """``Config.neighbour_iterations`` rounds of :func:`_neighbour_round` (none with
    ``Config.subtract_neighbours`` off); the second fits each galaxy's neighbours with its
    own model taken out in turn (the single-image pipeline's rounds,
    :func:`~pylensfit.images.neighbours.subtract_neighbours`)."""
    if not cfg.subtract_neighbours:
        return t
    for i in range(int(cfg.neighbour_iterations)):
        n = _neighbour_round(eset, ra, dec, groups, chunk, priors, cfg, t)
        log.info("neighbours taken out, round %d: %d galaxies fitted again", i + 1, n)
        if n == 0:
            break
    return t


def _catalogue(t: Table, pos: Table, eset: ExposureSet, pairs: np.ndarray,
               cfg: Config) -> Table:  # fmt: skip
    """The catalogue's columns about the measured table ``t`` (input order)."""
    n = len(t)
    ra, dec = np.asarray(pos["ra"], float), np.asarray(pos["dec"], float)
    lost = ~(np.isfinite(ra) & np.isfinite(dec))
    flags = np.asarray(t["flags"], np.int64)
    flags |= np.where(lost, FLAGS["BAD_POSITION"][0] | FLAGS["NOT_MEASURED"][0], 0)
    flags |= np.where(pairs & ~lost, FLAGS["CLOSE_PAIR"][0], 0)
    suspect_bits = int(np.sum(np.left_shift(1, np.flatnonzero(eset.psf_suspect))))
    suspect = (np.asarray(t["exposures_used"], np.int64) & suspect_bits) != 0
    flags |= np.where(suspect, FLAGS["PSF_SUSPECT"][0], 0)
    out = Table()
    out["id"] = np.arange(1, n + 1)
    out["image"] = np.full(n, Path(eset.paths[0]).name)
    out["object_id"] = out["id"]
    out["ALPHA_J2000"], out["DELTA_J2000"] = _fitted_sky(t, ra, dec, eset)
    for c in t.colnames:
        if c not in out.colnames and c not in ("x", "y", "x_detect", "y_detect"):
            out[c] = t[c]
    out["flags"] = flags.astype(np.int32)
    added = (flags & ~np.asarray(t["flags"], np.int64)) != 0  # the bits given here
    out["weight"] = np.where(added, 0.0, np.asarray(t["weight"], float))
    for c in ("e1", "e2", "e1_var", "e2_var", "e12_cov", "sens1", "sens2"):
        out[c] = np.where(added, np.nan, np.asarray(out[c], float))
    for c in out.colnames:
        if c in COLUMNS:
            out[c].unit, out[c].description = COLUMNS[c][0] or None, COLUMNS[c][1]
    out.meta.update(t.meta)
    out.meta.update(config=cfg, frame="sky", exposures=list(eset.paths),
                    psf_sources=list(eset.psf_sources))  # fmt: skip
    return out


def _fitted_sky(t: Table, ra: np.ndarray, dec: np.ndarray,
                eset: ExposureSet) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The fitted sky position: the fitted centre (``x, y`` in the pixels of each row's
    first used exposure) through that exposure's WCS; the catalogue's where none."""
    first = first_exposure(t["exposures_used"])
    x, y = np.asarray(t["x"], float), np.asarray(t["y"], float)
    ra_f, dec_f = ra.copy(), dec.copy()
    for k, e in enumerate(eset.exposures):
        rows = (first == k) & np.isfinite(x) & np.isfinite(y)
        if rows.any():
            sky = e.wcs.celestial.pixel_to_world(x[rows], y[rows])
            ra_f[rows], dec_f[rows] = sky.spherical.lon.deg, sky.spherical.lat.deg
    return ra_f, dec_f


def measure_exposures(
    exposures: Sequence[str], *, stars: Sequence[str] | None = None,
    catalogue: str | None = None, psf=None, priors: Priors | str | None = None,
    config: Config | None = None, output: str | os.PathLike | None = None,
    overwrite: bool = False, jacobian_tolerance: float = 1e-4, chunk: int = 2000,
    reference_zero_point: float | None = None,
) -> Table:
    """Shapes of the galaxies of one field, each fitted jointly on all of its exposures.

    The path of the module docstring: exposures read, each one's PSF, the positions (an
    input catalogue or the co-add's detections), the stamps, the joint fits under the
    priors (given, or estimated from the set's own joint fits on a sample of
    ``Config.calibration_sample`` positions), the neighbours taken out, the catalogue.

    Parameters
    ----------
    exposures : sequence of str
        The exposures' FITS files (:func:`read_exposures`).
    stars : sequence of str, optional
        One star-field image per exposure, for its PSF.
    catalogue : str, optional
        An input catalogue of sky positions (:func:`read_sky_positions`) instead of
        detection on the co-add.
    psf : optional
        The PSFs instead of the stars' (:func:`read_exposures`).
    priors : Priors or str, optional
        Every prior (or a saved one's path, ``Priors.save``); default estimated here.
    config : Config, optional
        Settings (default ``Config()``); ``stamp_size`` is each exposure's stamp side.
    output : str, optional
        Write the catalogue here (FITS, atomically; :func:`pylensfit.write_catalogue`).
    overwrite : bool
        Replace an existing ``output``.
    jacobian_tolerance : float
        The galaxies fitted together, with one WCS Jacobian per exposure, have Jacobians
        within this relative difference in every exposure (:func:`jacobian_groups`).
    chunk : int
        The most galaxies cut and fitted at a time (memory: ``chunk`` x exposures x
        ``stamp_size^2`` x 8 bytes of stamps, and as much of PSF images).
    reference_zero_point : float, optional
        The common flux unit's zero point (default: the first exposure's).

    Returns
    -------
    astropy.table.Table
        One row per position, in the catalogue's order: ``ALPHA_J2000, DELTA_J2000``
        (the fitted position), the shapes in the sky frame (``e1, e2``, their covariance,
        ``sens1, sens2``), ``weight``, ``flags`` (``CLOSE_PAIR`` as ``measure`` sets it;
        ``BAD_POSITION`` for a non-finite input position; ``NOT_MEASURED`` where no
        exposure is usable), ``n_exposures``,
        ``exposures_used``, the fit's columns and ``lnL``. ``meta``: ``egrid``, ``priors``,
        ``exposures``, ``psf_sources``.

    Raises
    ------
    InputError
        One line naming the file and the problem, before any output is written.
    FileExistsError
        If ``output`` exists and ``overwrite`` is false.
    """
    cfg = config if config is not None else Config()
    if output is not None and Path(output).exists() and not overwrite:
        raise FileExistsError(f"{output}: output exists (use --overwrite to replace it)")
    if priors is not None:
        priors = load_given(priors, Priors, "priors")
    eset = read_exposures(exposures, stars=stars, psf=psf, config=cfg,
                          reference_zero_point=reference_zero_point)  # fmt: skip
    pos = _positions(eset, catalogue, cfg)
    ra, dec = np.asarray(pos["ra"], float), np.asarray(pos["dec"], float)
    ok, pairs = _pairs(eset, ra, dec, cfg)
    ra_n, dec_n = _nowhere(ra, dec)
    groups = _Groups.of(eset, ra_n, dec_n, jacobian_tolerance)
    if priors is None:
        priors = _calibrate(eset, ra_n, dec_n, ok & ~pairs, groups.labels, cfg)
    t = _measure(eset, ra_n, dec_n, groups, chunk, priors, cfg)
    cat = _catalogue(t, pos, eset, _pairs(eset, ra, dec, cfg, t)[1], cfg)
    if output is not None:
        write_catalogue(cat, output, overwrite=overwrite)
    return cat
