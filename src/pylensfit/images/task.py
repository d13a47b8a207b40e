"""One image's task: read, detect, PSF, stamps, fits and neighbours, and the image's rows."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.table import Table

from .. import flags as _flags
from ..catalogue import FITCLASS
from ..detection import measure_background
from ..forced import forced_threshold
from ..grid import ellipticity_grid
from ..likelihood import e_annuli
from ..models import model_bank
from ..psf import PSFResult
from ..runner import single_thread
from ..skyframe import local_frame, pixel_frame, wcs_from_header
from .image_psf import CellPSFs, cell_psfs, image_psf, psf_source_of
from .inputs import Image, detect_objects, mask_saturated, read_image, read_positions, value_at
from .metacal_rows import MetacalInputs, metacal_columns
from .neighbours import (
    NeighbourScene,
    implausible_models,
    neighbour_light,
    subtract_neighbours,
)
from .records import ImageResult, ImageTask, psf_summary
from .tiers import ImageFitter, ImageResults, forced_snrs, image_stamps

__all__ = ["image_task"]

# the pipeline's one logger: its name predates the split into modules
log = logging.getLogger("pylensfit.pipeline")


def image_task(task: ImageTask) -> ImageResult:
    """Measure one image: every detected object gets a row, measured or flagged."""
    t0 = time.perf_counter()
    single_thread(task.single_thread)
    cfg = task.config
    path = task.path
    img = read_image(path, task.weight, task.mask)
    saturated = mask_saturated(img, cfg)
    positions = read_positions(task.catalogue, path) if task.catalogue else None
    sub, det, bkg = detect_objects(img, cfg, positions)
    t_detect = time.perf_counter()
    n = len(det)
    lost = np.asarray(det["no_position"]) if "no_position" in det.colnames else np.zeros(n, bool)
    flags = np.zeros(n, dtype=np.int32)
    psf, field_model, own_stars, psf_note = image_psf(task, cfg, img, sub, det)
    if psf is None:
        flags[:] |= _flags.flag_value("PSF_FAILED")
        if n:
            log.error("%s: no usable star for the PSF in the image or the star fields (%s); "
                      "its %d objects are flagged PSF_FAILED", path, psf_note, n)  # fmt: skip
    if psf is not None and task.psf_dir:
        (field_model or psf).write(Path(task.psf_dir) / f"{Path(path).stem}.psf.fits",
                                   overwrite=True)  # fmt: skip
    cells = None
    if field_model is not None:
        cells = cell_psfs(field_model, sub.shape, cfg.psf_cells, np.asarray(det["x"], float),
                          np.asarray(det["y"], float),
                          bilinear=cfg.psf_interpolation != "centre")  # fmt: skip
    t_psf = time.perf_counter()
    st = image_stamps(sub, img, det, cfg, saturated, flags)
    if positions is not None:  # an input catalogue: the evidence at each position itself
        det["forced_SNratio"] = forced_snrs(st, np.asarray(det["noise_sigma"], dtype=float),
                                            psf, cells)  # fmt: skip
    t_stamps = time.perf_counter()
    res, back, redo, taken = _fit_objects(task, img, sub, det, bkg, st, psf, cells, flags)
    t_fit = time.perf_counter()
    mcal = _metacal(task, st, res, taken, det, psf, cells)
    rows = _image_rows(task, img, det, res, back, psf, cells, own_stars, redo, lost)
    rows.update(mcal)
    if field_model is not None and field_model.diagnostics.get("heldout_suspect") == 1.0:
        rows["flags"] = rows["flags"] | _flags.flag_value("PSF_SUSPECT")
    timing = {"read+detect": t_detect - t0, "psf": t_psf - t_detect,
              "stamps": t_stamps - t_psf, "fit": t_fit - t_stamps}  # fmt: skip
    if task.metacal_priors is not None:
        timing["metacal"] = time.perf_counter() - t_fit
    return ImageResult(
        index=task.index, path=path, rows=rows, lnL=res.lnL, lnL_bulge=res.lnL_bulge,
        lnL_r=res.lnL_r, egrid=ellipticity_grid(cfg.output_e_step, emax=cfg.e_max),
        psf=None if psf is None else psf_summary(psf, field_model), psf_note=psf_note,
        psf_source=psf_source_of(task, psf, field_model, own_stars), timing=timing)  # fmt: skip


def _fit_objects(task: ImageTask, img: Image, sub: np.ndarray, det: Table, bkg,
                 st, psf: PSFResult | None, cells: CellPSFs | None, flags: np.ndarray,
                 ) -> tuple[ImageResults, np.ndarray, np.ndarray, np.ndarray | None]:  # fmt: skip
    """Fit every object of ``flags == 0``, again with its neighbours and the sky's change
    taken out (:func:`subtract_neighbours`), and flag ``DEFECT`` (in ``flags``) the
    objects whose model does not fit their stamp: the fits, the background map they end
    on, the objects refitted with their neighbours taken out and, to be metacalibrated,
    the light each object's last fit took out of its largest stamp (else None)."""
    cfg = task.config
    x = np.asarray(det["x"], dtype=float)
    y = np.asarray(det["y"], dtype=float)
    noise = np.asarray(det["noise_sigma"], dtype=float)
    bank = model_bank(cfg)
    egrid = ellipticity_grid(cfg.output_e_step, emax=cfg.e_max)  # fit_stamps' grid
    rings = e_annuli(bank.egrid) if task.keep_lnL_r == "annuli" else None
    res = ImageResults.empty(x, y, st, flags, bank, egrid, task.keep_lnL_r, rings)
    fit = ImageFitter(
        st=st, noise=noise, cfg=cfg, psf_image=None if psf is None else psf.image,
        cells=cells, size_prior=task.size_prior, rings=rings,
        size_marginal_prior=task.size_marginal_prior,
        taken_out=None if task.metacal_priors is None else np.zeros(st.bstamps.shape,
                                                                    np.float32))  # fmt: skip
    todo = np.flatnonzero(flags == 0)
    # the PSF the neighbours are rendered with: each object's heaviest node's, or the image's
    render_psf = (cells.images, cells.nearest) if cells is not None else (
        psf.image if psf is not None else None)
    # a model that does not fit its stamp (a defect: a saturated star, a bleed trail, a
    # hot pixel) is flagged DEFECT and kept out of the others' stamps and of the sky
    defect = np.zeros(todo.size, dtype=bool)
    redo = np.zeros(0, dtype=np.int64)
    back = bkg.back
    if not todo.size:
        return res, back, redo, fit.taken_out
    fits_ = fit(todo)
    res.store(fits_, todo)
    scene = NeighbourScene(shape=sub.shape, x=x, y=y, xf=res.xf, yf=res.yf, noise=noise,
                           fitted=todo, psf=render_psf, data=st.bstamps)  # fmt: skip
    if cfg.subtract_neighbours and todo.size > 1 or cfg.model_background:

        def sky(field):
            """The change of the background measured on the image less ``field``."""
            nonlocal back
            back = measure_background(img.data - field, mask=img.bad, weight=img.weight,
                                      box=cfg.background_box).back  # fmt: skip
            return back - bkg.back

        redo, defect = subtract_neighbours(scene, fits_, cfg, fit, res.store,
                                           sky=sky if cfg.model_background else None)  # fmt: skip
    else:  # no refit: the first fits are judged as they are
        others, _, own, _ = neighbour_light(sub.shape, x, y, res.xf, res.yf, todo, fits_,
                                             render_psf, cfg, own_too=True)  # fmt: skip
        defect = implausible_models(st.bstamps, todo, noise, fits_, cfg, others, own)
    if defect.any():
        flags[todo[defect]] |= _flags.flag_value("DEFECT")
        log.info("%s: %d object(s) whose best model does not fit the stamp flagged DEFECT "
                 "(Config.max_reduced_chi2, max_residual_fraction)", task.path,
                 int(defect.sum()))  # fmt: skip
    return res, back, redo, fit.taken_out


def _metacal(task: ImageTask, st, res: ImageResults, taken: np.ndarray | None, det: Table,
             psf: PSFResult | None, cells: CellPSFs | None) -> dict[str, np.ndarray]:
    """The metacalibration columns (:mod:`.metacal_rows`) where the task carries the
    measurement's priors, else none: every fitted object without a flag but ``STAR``, on
    its largest stamp as its last fit saw it, about its fitted centre."""
    if task.metacal_priors is None:
        return {}
    star = _flags.flag_value("STAR")
    full = st.use_big | (st.bstamps.shape[1] == task.config.stamp_size)
    inp = MetacalInputs(
        stamps=st.bstamps, taken_out=taken, full=full,
        cx=res.xf - res.x + st.fcx, cy=res.yf - res.y + st.fcy,
        noise=np.asarray(det["noise_sigma"], dtype=float),
        todo=np.isfinite(res.lnL).all(axis=1) & ((res.flags & ~star) == 0))  # fmt: skip
    return metacal_columns(inp, task.config, task.metacal_priors, task.index, psf, cells)


def _image_rows(task: ImageTask, img: Image, det: Table, res: ImageResults,
                back: np.ndarray, psf: PSFResult | None, cells: CellPSFs | None,
                own_stars: np.ndarray, redo: np.ndarray, lost: np.ndarray,
                ) -> dict[str, np.ndarray]:  # fmt: skip
    """The image's catalogue columns; completes the flags (``FIT_FAILED``,
    ``BAD_POSITION``) in ``res.flags``."""
    n, flags, x, y = len(det), res.flags, res.x, res.y
    ra, dec, frame = _sky(img.header, res.xf, res.yf)
    measured = np.isfinite(res.lnL).all(axis=1)
    # a fit that left no finite ln L row says so in its flags (STAR alone would not)
    flags[~measured & ((flags & ~_flags.flag_value("STAR")) == 0)] |= _flags.flag_value(
        "FIT_FAILED")
    fitclass = np.where(measured, np.where(res.is_star, FITCLASS["star"], FITCLASS["galaxy"]),
                        FITCLASS["not_measured"])  # fmt: skip
    rows = {
        "image": np.full(n, os.path.basename(task.path)),
        "image_index": np.full(n, task.index, dtype=np.int32),
        "object_id": np.asarray(det["id"], dtype=np.int64),
        "x": res.xf, "y": res.yf, "ALPHA_J2000": ra, "DELTA_J2000": dec,
        "x_detect": x, "y_detect": y,
        "mag": np.asarray(det["mag"], dtype=float),
        "flux_aper": np.asarray(det["flux"], dtype=float),
        "flux_aper_err": np.asarray(det["flux_err"], dtype=float),
        "r_half": np.asarray(det["r_half"], dtype=float),
        "sep_flag": np.asarray(det["sep_flag"], dtype=np.int32),
        "pixel_SNratio": np.asarray(det["snr"], dtype=float),
        "forced_SNratio": (np.asarray(det["forced_SNratio"], dtype=float)
                           if "forced_SNratio" in det.colnames else np.full(n, np.nan)),
        "noise_sigma": np.asarray(det["noise_sigma"], dtype=float),
        "background": value_at(back, x, y),
        **res.cols,
        "fitclass": fitclass.astype(np.int16),
        "is_star": res.is_star,
        "psf_star": own_stars,
        "PSF_e1": (cells.psf_e[0] if cells is not None else
                   np.full(n, psf.e1 if psf is not None else np.nan)),
        "PSF_e2": (cells.psf_e[1] if cells is not None else
                   np.full(n, psf.e2 if psf is not None else np.nan)),
        "sky_angle": frame.angle, "sky_flip": frame.flip,
        "wcs_g1": frame.g1, "wcs_g2": frame.g2,
        "flags": flags,
    }  # fmt: skip
    if res.lnL_bulge is not None:
        rows["lnL_star"] = res.lnL_star
    rows["refit_neighbours"] = np.zeros(n, dtype=bool)
    rows["refit_neighbours"][redo] = True
    for c in ("x", "y", "x_detect", "y_detect", "ALPHA_J2000", "DELTA_J2000", "background",
              "noise_sigma"):  # an input catalogue's rows without a position: kept as NaN
        rows[c][lost] = np.nan
    flags[lost] = _flags.flag_value("BAD_POSITION")
    _flag_weak_positions(task, flags, measured & ~lost, rows["forced_SNratio"])
    return rows


def _flag_weak_positions(task: ImageTask, flags: np.ndarray, measured: np.ndarray,
                         forced_snr: np.ndarray) -> None:  # fmt: skip
    """Flag ``LOW_SNR`` (in place) the measured rows of an input catalogue, usable so far
    (or stars), whose S/N at the catalogue position is below the threshold of false-alarm
    probability ``Config.forced_false_alarm`` (:func:`pylensfit.forced.forced_threshold`):
    the fit's own S/N is the best of the noise peaks within ``Config.max_offset``."""
    u = forced_threshold(task.config)
    if task.catalogue is None or u is None:
        return
    weak = measured & ((flags & ~_flags.flag_value("STAR")) == 0) & ~(forced_snr >= u)
    flags[weak] |= _flags.flag_value("LOW_SNR")
    if weak.any():
        log.info("%s: %d input position(s) with S/N below %.2f at the position itself "
                 "(false-alarm probability %g) flagged LOW_SNR", task.path, int(weak.sum()),
                 u, task.config.forced_false_alarm)  # fmt: skip


def _sky(header: fits.Header, x: np.ndarray, y: np.ndarray):
    """RA, Dec (deg, NaN without a WCS) and the sky frame (:mod:`pylensfit.skyframe`)
    at pixel positions ``x, y``."""
    w = wcs_from_header(header)
    if w is None or x.size == 0:
        return np.full(x.size, np.nan), np.full(x.size, np.nan), pixel_frame(x.size)
    ra, dec = w.all_pix2world(x, y, 0)
    return (np.asarray(ra, dtype=np.float64), np.asarray(dec, dtype=np.float64),
            local_frame(w, x, y))  # fmt: skip
