"""From FITS images to a shear catalogue (paper sections 2.3-2.4 and 4).

:func:`measure` walks the whole path for each input image:

1. read the image, its weight (inverse variance) and mask maps and its WCS, and mask
   the saturated (``Config.saturation`` or the ``SATURATE`` card) and non-finite pixels;
2. measure the background and its rms and detect the objects with ``sep``
   (:mod:`pylensfit.detection`), or take the positions of an input catalogue;
3. select stars on the stellar locus (peak S/N above ``star_min_peak_snr``), stack them
   into a PSF (:func:`pylensfit.psf.stack_psf`) and co-add it with the PSFs of the
   separate star-field images;
4. cut a postage stamp about every object and flag those that cannot be fitted (edge,
   masked, saturated or NaN pixels, close pairs: :mod:`pylensfit.stamps`);
5. compute every object's ``ln L(e)`` grid (:func:`pylensfit.fit_stamps`), again with
   the neighbours' models and the sky's change taken out; an object whose model does not
   fit its stamp (a defect) is flagged ``DEFECT`` and left out of the others' stamps and
   the sky.

The images are independent and run in parallel: in a local process pool (``jobs``, one
BLAS and numba thread per worker) or on a dask.distributed cluster (``scheduler``).
Each finished image is written at once (atomically) to ``<output>.parts/``, so a run
that is killed and restarted does only the images that are missing. When all are done,
the prior is estimated from the galaxies of the run (unless one is given), the
posterior means, covariances and sensitivities computed from the stored grids, and the
catalogue written (:mod:`pylensfit.catalogue`). Every object that was detected has a
row; the ``flags`` column says why an object was not measured.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import logging
import math
import os
import re
import shutil
import time
import warnings
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
from astropy.io import fits
from astropy.table import Table, vstack

from . import flags as _flags
from ._version import __version__
from .assemble import FIT_COLUMNS, ObjectContext, assemble, fit_columns, usable_galaxies
from .calibration import CalibrationSample, Priors, run_recipe
from .catalogue import COLUMNS, FITCLASS, atomic_write, column_table, flag_cards
from .config import Config
from .detection import (
    close_pairs,
    detect,
    grow_mask,
    measure_background,
    saturation_level,
    saturation_mask,
    select_stars,
)
from .forced import forced_threshold, position_snr
from .grid import ellipticity_grid
from .likelihood import StampFits, blend_fits, e_annuli, fit_stamps, merge_fits
from .models import model_bank, render_models
from .prior import (
    Prior,
    SizePrior,
    SplinePrior,
)
from .psf import (
    PSFError,
    PSFResult,
    centre_on_stamp,
    combine_psfs,
    psf_from_image,
    stack_psf,
)
from .psfmodel import ConstantPSF, PolynomialPSF, PSFModel, n_terms, read_psf_model
from .runner import report_progress, run_tasks, single_thread, worker_pool
from .shear import refine_lnL
from .skyframe import (
    SkyFrame,
    frame_of_table,
    local_frame,
    pixel_frame,
    to_sky,
    wcs_from_header,
)
from .stamps import add_patches, cut_stamps, patch_origins

__all__ = ["InputError", "measure", "read_catalogue", "subtract_neighbours", "write_catalogue"]

log = logging.getLogger(__name__)


class InputError(ValueError):
    """Bad input: a missing or unreadable file, an empty image, an empty catalogue."""


# ----------------------------------------------------------------------------------------
# Input
# ----------------------------------------------------------------------------------------
@dataclass
class _Image:
    path: str
    data: np.ndarray
    header: fits.Header
    weight: np.ndarray | None
    bad: np.ndarray  # masked, zero-weight or non-finite pixels


@contextmanager
def _open(path: str, what: str) -> Iterator[fits.HDUList]:
    """Open a FITS file; a missing or unreadable file is an :class:`InputError`."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{path}: {what} not found")
    with open(p, "rb") as fh:  # ours to close, whatever astropy makes of the content
        try:
            hdul = fits.open(fh, memmap=False)
            hdul.verify("exception")
        except Exception as err:  # astropy raises OSError, ValueError, VerifyError, ...
            # on one line: a verification report spans several, between boilerplate lines
            why = " ".join(ln.strip() for ln in str(err).splitlines() if ln.strip() and not
                           ln.startswith(("Verification reported errors", "Note: astropy")))
            if "SIMPLE" in why:  # astropy's hint is for its API, not for a user of ours
                why = "no SIMPLE card at its start: not a FITS file, or a damaged one"
            raise InputError(f"{path}: not a readable FITS file ({why})") from None
        with hdul:
            yield hdul


def _first_image(hdul: fits.HDUList, path: str, name: str | None = None) -> tuple:
    if name is not None:
        if name not in hdul:
            raise InputError(f"{path}: no HDU named {name}")
        hdus = [hdul[name]]
    else:
        hdus = [h for h in hdul if isinstance(h, (fits.PrimaryHDU, fits.ImageHDU))]
    for h in hdus:
        try:
            data = h.data
        except Exception as err:
            raise InputError(f"{path}: cannot read image data ({err})") from None
        if data is not None and data.ndim == 2:
            return np.asarray(data, dtype=np.float64), h.header
    raise InputError(f"{path}: no 2-D image in the file")


def _read_image(path: str, weight: str | None = None, mask: str | None = None) -> _Image:
    """Read an image, its weight map and mask (HDUs ``WEIGHT`` / ``MASK`` or files)."""
    with _open(path, "image") as hdul:
        data, header = _first_image(hdul, path)
        w = _first_image(hdul, path, "WEIGHT")[0] if "WEIGHT" in hdul else None
        m = _first_image(hdul, path, "MASK")[0] if "MASK" in hdul else None
    if weight is not None:
        with _open(weight, "weight map") as h:
            w = _first_image(h, weight)[0]
    if mask is not None:
        with _open(mask, "mask") as h:
            m = _first_image(h, mask)[0]
    for arr, what in ((w, "weight map"), (m, "mask")):
        if arr is not None and arr.shape != data.shape:
            raise InputError(f"{path}: {what} shape {arr.shape} differs from the image's "
                             f"{data.shape}")  # fmt: skip
    finite = np.isfinite(data)
    if not finite.any():
        raise InputError(f"{path}: empty image (no finite pixel)")
    if np.nanmax(data) == np.nanmin(data):
        raise InputError(f"{path}: empty image (all pixels equal {np.nanmax(data):g})")
    bad = ~finite
    if w is not None:
        bad |= ~(np.isfinite(w) & (w > 0))
    if m is not None:
        bad |= np.nan_to_num(m) != 0
    if bad.all():
        raise InputError(f"{path}: every pixel is masked or has zero weight")
    return _Image(path=path, data=data, header=header, weight=w, bad=bad)


def _read_positions(path: str, image_path: str) -> Table:
    """An input catalogue: ``x, y`` (0-based) or SExtractor's ``X_IMAGE, Y_IMAGE``."""
    try:
        t = Table.read(path)
    except FileNotFoundError:
        raise InputError(f"{path}: input catalogue not found") from None
    except Exception as err:
        raise InputError(f"{path}: cannot read the input catalogue ({err})") from None
    if len(t) == 0:
        raise InputError(f"{path}: empty input catalogue (for {image_path})")
    names = {c.lower(): c for c in t.colnames}
    if "x" in names and "y" in names:
        x, y = t[names["x"]], t[names["y"]]
    elif "x_image" in names and "y_image" in names:
        x, y = t[names["x_image"]] - 1.0, t[names["y_image"]] - 1.0  # FITS 1-based
    else:
        raise InputError(f"{path}: input catalogue needs columns x, y (0-based) or "
                         "X_IMAGE, Y_IMAGE (1-based)")  # fmt: skip
    out = Table()
    try:
        out["x"] = np.asarray(x, dtype=float)
        out["y"] = np.asarray(y, dtype=float)
    except (TypeError, ValueError) as err:
        raise InputError(f"{path}: the input catalogue's positions are not numbers "
                         f"({err})") from None  # fmt: skip
    for c in t.colnames:
        if c not in out.colnames:
            out[c] = t[c]
    lost = ~(np.isfinite(out["x"]) & np.isfinite(out["y"]))
    if lost.any():
        log.warning("%s: %d row(s) without a finite position (rows %s): kept, flagged "
                    "BAD_POSITION and not measured", path, int(lost.sum()),
                    ", ".join(map(str, np.flatnonzero(lost)[:5])) + (", ..." if lost.sum() > 5
                                                                     else ""))  # fmt: skip
    return out


# ----------------------------------------------------------------------------------------
# One image
# ----------------------------------------------------------------------------------------
#: where an input catalogue's row without a finite position is put (times its rank)
_NOWHERE = -1e7


def _detect(img: _Image, cfg: Config, positions: Table | None):
    """Background-subtracted image, the object table (detections or input positions) and
    the :class:`~pylensfit.detection.Background`."""
    bkg = measure_background(img.data, mask=img.bad, weight=img.weight, box=cfg.background_box)
    det = detect(
        img.data, weight=img.weight, mask=img.bad, threshold=cfg.detect_threshold,
        min_area=cfg.detect_min_area, background=bkg, stamp_size=cfg.stamp_size,
    )  # fmt: skip
    sub = bkg.subtract(img.data)
    if positions is None:
        return sub, det, bkg
    # an input catalogue: its positions, with the detections' photometry where they match
    from scipy.spatial import cKDTree

    out = positions.copy()
    out["id"] = np.arange(1, len(out) + 1)
    # a row without a finite position: far off the image and from every other row, where
    # it is cut, paired and fitted with nothing (flagged BAD_POSITION by _image_task)
    lost = ~(np.isfinite(out["x"]) & np.isfinite(out["y"]))
    out["no_position"] = lost
    out["x"][lost] = out["y"][lost] = _NOWHERE * np.arange(1, lost.sum() + 1)
    photometry = ("flux", "flux_err", "snr", "peak_snr", "r_half", "mag", "sep_flag")
    for c in photometry:
        out[c] = np.nan if c != "sep_flag" else 0
    rms = bkg.rms
    if len(det):
        d, j = cKDTree(np.column_stack([det["x"], det["y"]])).query(
            np.column_stack([out["x"], out["y"]]), distance_upper_bound=2.0
        )
        hit = np.isfinite(d)
        for c in photometry:
            out[c][hit] = det[c][j[hit]]
    out["noise_sigma"] = _noise_at(img, out["x"], out["y"], bkg, rms)
    return sub, out, bkg


def _value_at(image: np.ndarray, x, y) -> np.ndarray:
    """``image`` at the pixels nearest ``(x, y)`` (clipped to the image)."""
    ix = np.clip(np.round(np.asarray(x)).astype(int), 0, image.shape[1] - 1)
    iy = np.clip(np.round(np.asarray(y)).astype(int), 0, image.shape[0] - 1)
    return np.asarray(image, dtype=float)[iy, ix]


def _noise_at(img: _Image, x, y, bkg, rms_map) -> np.ndarray:
    if img.weight is not None:
        w = _value_at(img.weight, x, y)
        return np.where(w > 0, 1.0 / np.sqrt(np.where(w > 0, w, 1.0)), np.nan)
    if rms_map is not None:
        return _value_at(rms_map, x, y)
    return np.full(np.shape(x), float(bkg.global_rms))


def _mask_saturated(img: _Image, cfg: Config) -> np.ndarray:
    """Mask what no galaxy model fits, before the background, the detection and the fit.

    The pixels at or above the saturation level (``cfg.saturation``, else the image's
    ``SATURATE`` card: :func:`~pylensfit.detection.saturation_level`) and the non-finite
    ones are added to ``img.bad`` (in place), each grown by ``cfg.saturation_grow`` px.

    Parameters
    ----------
    img : _Image
        The image; its ``bad`` map is updated.
    cfg : Config

    Returns
    -------
    numpy.ndarray
        Boolean ``(ny, nx)``: the saturated pixels, grown (the ``SATURATED`` flag's map).

    Raises
    ------
    InputError
        If no pixel is left unmasked.
    """
    level = saturation_level(img.header, cfg.saturation)
    sat = saturation_mask(img.data, level, cfg.saturation_grow)
    img.bad |= sat | grow_mask(~np.isfinite(img.data), cfg.saturation_grow)
    if img.bad.all():
        why = "" if level is None else f" or at or above the saturation level {level:g}"
        raise InputError(f"{img.path}: every pixel is masked, has zero weight, is not "
                         f"finite or lies within {cfg.saturation_grow} px of such{why}")
    if sat.any():
        log.info("%s: %d pixels at or above the saturation level %g (grown by %d px) "
                 "masked", img.path, int(sat.sum()), level, cfg.saturation_grow)  # fmt: skip
    return sat


def _box_any(mask: np.ndarray, x: np.ndarray, y: np.ndarray, size: int) -> np.ndarray:
    """Whether the ``size x size`` stamp about each ``(x, y)`` (as
    :func:`~pylensfit.stamps.cut_stamps` cuts it; clipped to the image) holds a pixel of
    ``mask``: a summed-area table, O(1) per object."""
    if x.size == 0 or not mask.any():
        return np.zeros(x.size, dtype=bool)
    ny, nx = mask.shape
    sat = np.zeros((ny + 1, nx + 1), dtype=np.int64)
    sat[1:, 1:] = np.cumsum(np.cumsum(mask, axis=0, dtype=np.int64), axis=1)
    ix0, iy0 = patch_origins(x, y, size)
    x0, y0 = np.clip(ix0, 0, nx), np.clip(iy0, 0, ny)
    x1, y1 = np.clip(ix0 + size, 0, nx), np.clip(iy0 + size, 0, ny)
    return sat[y1, x1] - sat[y0, x1] - sat[y1, x0] + sat[y0, x0] > 0


#: A PSF model fitted to an image's stars is suspect (a warning, the flag PSF_SUSPECT on
#: the rows fitted with it, ``psf_heldout_suspect`` in the PSFS HDU) where its held-out
#: stars' ellipticity residuals have a mean square (``heldout_chi2_de``) above this many
#: times their noise's: the model's error at least twice the stars' own noise (an excess
#: of 2e-3 to 1e-2 at their S/N of 50 to 300, against a goal of 1e-3). A model as good as
#: the stars can tell gives 1 (+- 1 / sqrt(heldout_n) by the noise); one made partly of
#: compact galaxies their intrinsic ellipticities, 0.2 to 0.3: hundreds to thousands.
PSF_SUSPECT_CHI2 = 5.0
#: ... and where that mean square is that improbable from the noise alone (its chi-square
#: p-value ``heldout_pvalue_de``): a model of few held-out stars is not judged on chance.
PSF_SUSPECT_PVALUE = 1e-3


def _heldout_suspect(model: PolynomialPSF, path: str) -> bool:
    """Whether ``model``'s held-out check fails (:data:`PSF_SUSPECT_CHI2`,
    :data:`PSF_SUSPECT_PVALUE`); sets ``heldout_suspect`` (1.0 or 0.0; NaN where no star
    was held out) in its diagnostics and logs a warning where it fails."""
    d = model.diagnostics
    chi2, pvalue = d.get("heldout_chi2_de", math.nan), d.get("heldout_pvalue_de", math.nan)
    if not (d.get("heldout_n", 0) > 0 and math.isfinite(chi2) and math.isfinite(pvalue)):
        d["heldout_suspect"] = math.nan
        return False
    suspect = chi2 > PSF_SUSPECT_CHI2 and pvalue < PSF_SUSPECT_PVALUE
    d["heldout_suspect"] = float(suspect)
    if suspect:
        log.warning("%s: the PSF model fails its check on %d held-out stars: ellipticity "
                    "residual rms %.1e / %.1e (e1 / e2) against %.1e from their noise, mean "
                    "square %.3g times the noise's (p = %.1e); its %d stars are likely in "
                    "part galaxies: the rows fitted with it are flagged PSF_SUSPECT", path,
                    int(d["heldout_n"]), d.get("heldout_rms_de1", math.nan),
                    d.get("heldout_rms_de2", math.nan), d.get("heldout_noise_de", math.nan),
                    chi2, pvalue, int(d.get("n_used", 0)))  # fmt: skip
    return suspect


def _psf_stars(img: _Image, det: Table, cfg: Config, star_col) -> np.ndarray:
    """The detections selected as PSF stars; ``PSFError`` if fewer than psf_min_stars."""
    stars = select_stars(det, min_peak_snr=cfg.star_min_peak_snr, column=star_col)
    if stars.sum() < cfg.psf_min_stars:
        raise PSFError(f"{img.path}: {int(stars.sum())} star(s) pass the selection "
                       f"(peak S/N > {cfg.star_min_peak_snr:g}), fewer than "
                       f"psf_min_stars = {cfg.psf_min_stars}")  # fmt: skip
    return stars


def _psf_from_stars(sub: np.ndarray, img: _Image, det: Table, cfg: Config, star_col):
    stars = _psf_stars(img, det, cfg, star_col)
    res = stack_psf(
        sub, np.asarray(det["x"])[stars], np.asarray(det["y"])[stars],
        noise_sigma=np.asarray(det["noise_sigma"])[stars],
        size=cfg.stamp_size, weight=None if img.weight is None else img.weight,
        min_correlation=cfg.psf_min_correlation, source=img.path,
    )  # fmt: skip
    if res.n_used < cfg.psf_min_stars:
        raise PSFError(f"{img.path}: only {res.n_used} star(s) survive the PSF stacking, "
                       f"fewer than psf_min_stars = {cfg.psf_min_stars}")  # fmt: skip
    return res, stars


def _poly_from_stars(sub: np.ndarray, img: _Image, det: Table, cfg: Config, star_col):
    """The image's stars' polynomial PSF model (:class:`PolynomialPSF`) and the star mask."""
    stars = _psf_stars(img, det, cfg, star_col)
    ny, nx = sub.shape
    try:
        model = PolynomialPSF.fit(
            sub, np.asarray(det["x"])[stars], np.asarray(det["y"])[stars],
            noise_sigma=np.asarray(det["noise_sigma"])[stars],
            weight=None if img.weight is None else img.weight, order=cfg.psf_order,
            size=cfg.stamp_size, bounds=(0.0, nx - 1.0, 0.0, ny - 1.0),
            min_correlation=cfg.psf_min_correlation, source=img.path)  # fmt: skip
    except ValueError as err:  # too few stars for any order
        raise PSFError(f"{img.path}: {err}") from None
    if model.diagnostics.get("n_used", 0) < cfg.psf_min_stars:
        raise PSFError(f"{img.path}: only {model.diagnostics.get('n_used', 0)} star(s) "
                       f"survive the PSF fit, fewer than psf_min_stars = "
                       f"{cfg.psf_min_stars}")  # fmt: skip
    _heldout_suspect(model, img.path)
    return model, stars


def _n_selected(img: _Image, det: Table, cfg: Config, star_col) -> int:
    """How many detections pass the star selection (0 where fewer than psf_min_stars)."""
    try:
        return int(_psf_stars(img, det, cfg, star_col).sum())
    except PSFError:
        return 0


def _n_used(psf: PSFResult | PSFModel) -> int:
    """How many stars a PSF (stacked, or a model over the field) was made from."""
    if isinstance(psf, PSFModel):
        return int(psf.diagnostics.get("n_used", 0))
    return int(psf.n_used)


def _varying_from_stars(sub: np.ndarray, img: _Image, det: Table, cfg: Config, star_col):
    """``Config.psf_model = "auto"``: the stars' polynomial model and star mask where
    they show the PSF varying over the image (:meth:`PolynomialPSF.variation`'s p-value
    below ``Config.psf_vary_pvalue``) or where its held-out check fails (the stack of the
    same stars would be as wrong: the model is kept so that the check is recorded and its
    rows flagged PSF_SUSPECT), else None (the constant stack is used)."""
    n_stars = _n_selected(img, det, cfg, star_col)
    order = cfg.psf_order  # the fit's own floor, 5 stars a coefficient, said quietly
    while order > 0 and n_stars < 5 * n_terms(order):
        order -= 1
    if order == 0:
        return None
    try:
        model, stars = _poly_from_stars(sub, img, det, cfg.replace(psf_order=order), star_col)
    except PSFError as err:
        log.info("%s", err)
        return None
    var = model.variation()
    model.diagnostics.update(var)
    varies = var["vary_pvalue"] < cfg.psf_vary_pvalue
    suspect = model.diagnostics.get("heldout_suspect") == 1.0
    log.info("%s: %d stars; the PSF %s over the image (p = %.2g that a constant PSF "
             "varies as much; fitted rms variation %.1e in e, %.1e in size): %s", img.path,
             var["vary_n"], "varies" if varies else "does not vary", var["vary_pvalue"],
             var["vary_rms_de"], var["vary_rms_dsigma"],
             "the polynomial model" if varies or suspect else "the stacked PSF")  # fmt: skip
    return (model, stars) if varies or suspect else None


@dataclass
class _CellPSFs:
    """A PSF varying over an image, sampled for the fits of its objects.

    With ``Config.psf_interpolation = "centre"`` the PSF at the centre of each of the
    ``psf_cells x psf_cells`` cells, each object fitted with its cell's; with
    ``"bilinear"`` the PSF at the cells' corners, each object fitted with its cell's
    four and the fits blended with the bilinear weights of its position
    (:func:`pylensfit.likelihood.blend_fits`).
    """

    images: np.ndarray  # (n_nodes, N, N) the PSF at each node
    e: np.ndarray  # (2, n_nodes) its ellipticity
    cell: np.ndarray  # (n,) each object's cell (the objects fitted together)
    nodes: np.ndarray  # (k, n) the nodes each object is fitted with (the same in a cell)
    weights: np.ndarray  # (k, n) their weights, summing to 1

    @property
    def psf_e(self) -> np.ndarray:
        """``(2, n)`` each object's PSF ellipticity, its nodes' weighted."""
        return np.einsum("kn,ckn->cn", self.weights, self.e[:, self.nodes])

    @property
    def nearest(self) -> np.ndarray:
        """``(n,)`` each object's heaviest node (the PSF its model is rendered with)."""
        return self.nodes[np.argmax(self.weights, axis=0), np.arange(self.nodes.shape[1])]


def _cell_psfs(model: PSFModel, shape: tuple[int, int], cells: int, x: np.ndarray,
               y: np.ndarray, bilinear: bool) -> _CellPSFs:  # fmt: skip
    """The PSF model sampled at the centres (or, ``bilinear``, the corners) of ``cells x
    cells`` cells of an image of ``shape``, for objects at pixels ``x, y``."""
    ny, nx = shape
    x, y = np.nan_to_num(np.asarray(x, float)), np.nan_to_num(np.asarray(y, float))
    i = np.clip(np.floor((x + 0.5) * cells / nx), 0, cells - 1).astype(np.int64)
    j = np.clip(np.floor((y + 0.5) * cells / ny), 0, cells - 1).astype(np.int64)
    cell = j * cells + i
    if not bilinear:
        cx = (np.arange(cells) + 0.5) * nx / cells - 0.5
        cy = (np.arange(cells) + 0.5) * ny / cells - 0.5
        nodes, weights = cell[None], np.ones((1, cell.size))
    else:  # the cells' corners, from the image's edge to edge
        cx = np.arange(cells + 1) * nx / cells - 0.5
        cy = np.arange(cells + 1) * ny / cells - 0.5
        fu = np.clip((x - cx[i]) / (nx / cells), 0.0, 1.0)
        fv = np.clip((y - cy[j]) / (ny / cells), 0.0, 1.0)
        k = cells + 1
        nodes = np.stack([j * k + i, j * k + i + 1, (j + 1) * k + i, (j + 1) * k + i + 1])
        weights = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv])
    X, Y = np.meshgrid(cx, cy)
    images = model.draw(X.ravel(), Y.ravel())
    e1, e2, _ = model.shape_at(X.ravel(), Y.ravel())
    return _CellPSFs(images=images, e=np.vstack([e1, e2]), cell=cell, nodes=nodes,
                     weights=weights)  # fmt: skip


@dataclass(frozen=True)
class _StarfieldTask:
    """One star-field image to build a PSF from (a task of :func:`_starfield_task`)."""

    path: str
    index: int
    config: Config
    single_thread: bool = False  # set by the runner on its workers


@dataclass(frozen=True)
class _ImageTask:
    """One image to measure (a task of :func:`_image_task`)."""

    path: str
    index: int
    config: Config
    weight: str | None = None  # the image's weight and mask files
    mask: str | None = None
    catalogue: str | None = None  # an input catalogue instead of detection
    star_psfs: tuple = ()  # the star fields' PSFs (PSFResult or PSFModel)
    star_column: str | None = None
    psf_dir: str | None = None
    psf: PSFResult | PSFModel | None = None  # a given PSF: no stars stacked
    size_prior: SizePrior | None = None
    keep_lnL_r: bool | str = False  # keep L(r): True, or "annuli" (per ring of |e|)
    size_marginal_prior: Any = None
    single_thread: bool = False  # set by the runner on its workers


def _starfield_task(task: _StarfieldTask) -> PSFResult | PSFModel:
    """The PSF of a separate star-field image."""
    single_thread(task.single_thread)
    cfg = task.config
    img = _read_image(task.path)
    _mask_saturated(img, cfg)
    sub, det, _ = _detect(img, cfg, None)
    if len(det) == 0:
        raise InputError(f"{img.path}: no object detected in the star field")
    try:
        if cfg.psf_model == "polynomial":
            return _poly_from_stars(sub, img, det, cfg, None)[0]
        if cfg.psf_model == "auto":
            varying = _varying_from_stars(sub, img, det, cfg, None)
            if varying is not None:
                return varying[0]
        return _psf_from_stars(sub, img, det, cfg, None)[0]
    except PSFError as err:
        raise InputError(f"{img.path}: no usable star for the PSF ({err})") from None


def _image_psf(task: _ImageTask, cfg: Config, img: _Image, sub: np.ndarray, det: Table,
               ) -> tuple[PSFResult | None, PSFModel | None, np.ndarray, str]:  # fmt: skip
    """The image's PSF: given, this image's stars co-added with the star fields', or the
    model of the most stars (``Config.psf_model = "polynomial"``; with ``"auto"`` the
    model of the most stars among those whose stars show the PSF varying, else the
    co-added stack).

    Returns ``(psf, field_model, own_stars, note)``: the PSF at the image's centre (None
    when no star was usable), the model varying over the image (None for a constant
    PSF), which detections were the image's own PSF stars, and why the image's own stars
    gave no PSF ("" if they did).
    """
    n = len(det)
    psfs = list(task.star_psfs)
    own_stars = np.zeros(n, dtype=bool)
    psf_note = ""
    if task.psf is not None:  # given: no stars stacked
        psfs = [task.psf]
    elif n:
        try:
            own, own_stars = _psf_from_stars(sub, img, det, cfg, task.star_column)
            psfs.append(own)
        except PSFError as err:
            psf_note = str(err)
            log.info("%s", err)
    field_model = None  # a PSF varying over the image (given, or Config.psf_model)
    if isinstance(task.psf, PSFModel):  # e.g. a Piff model
        field_model = task.psf
        psfs = [field_model.centre]
    elif cfg.psf_model == "polynomial" and task.psf is None:
        psfs = list(task.star_psfs)
        best = max([m.diagnostics.get("n_used", 0) for m in psfs], default=0)
        if n:
            try:
                # the image's own stars only where they may beat the star fields' model
                if int(_psf_stars(img, det, cfg, task.star_column).sum()) > best:
                    own_model, own_stars = _poly_from_stars(sub, img, det, cfg,
                                                            task.star_column)  # fmt: skip
                    psfs.append(own_model)
            except PSFError as err:
                psf_note = str(err)
                log.info("%s", err)
        if psfs:  # the model of the most stars (the image's own or a star field's)
            field_model = max(psfs, key=lambda m: m.diagnostics.get("n_used", 0))
            psfs = [field_model.centre]
    elif cfg.psf_model == "auto" and task.psf is None:
        # the star fields whose stars showed the PSF varying, and the image's own where
        # they may beat every star field
        models = [m for m in task.star_psfs if isinstance(m, PSFModel)]
        if n and _n_selected(img, det, cfg, task.star_column) > max(
                [_n_used(m) for m in task.star_psfs], default=0):  # fmt: skip
            varying = _varying_from_stars(sub, img, det, cfg, task.star_column)
            if varying is not None:
                models.append(varying[0])
                own_stars = varying[1]
        if models:
            field_model = max(models, key=_n_used)
            psfs = [field_model.centre]
    if not psfs:
        return None, field_model, own_stars, psf_note
    psf = combine_psfs(psfs) if len(psfs) > 1 else psfs[0]
    return psf, field_model, own_stars, psf_note


@dataclass
class _ImageStamps:
    """The stamps of an image's objects: the base stamps and, on the objects whose
    larger stamp (``Config.max_stamp_size``) lies in the image with no bad pixel, the
    larger ones, which ``fit_stamps`` then fits, choosing the tier."""

    stamps: np.ndarray  # (n, stamp_size, stamp_size)
    bstamps: np.ndarray  # (n, n_big, n_big); ``stamps`` when there is one tier
    use_big: np.ndarray  # (n,) bool: fitted on the larger stamp
    cx: np.ndarray  # the detections' positions in the base stamps (pixels)
    cy: np.ndarray
    fcx: np.ndarray  # ... in the stamps each object is fitted on
    fcy: np.ndarray
    base_cfg: Config  # the configuration of the base stamps' fits
    offset: int  # the base stamp's origin in the larger one (pixels)


def _image_stamps(sub: np.ndarray, img: _Image, det: Table, cfg: Config,
                  saturated: np.ndarray, flags: np.ndarray) -> _ImageStamps:  # fmt: skip
    """Cut the objects' stamps; set the stamp, saturation, close-pair and noise flags in
    ``flags``. The flags, close pairs and everything else are those of the base stamp."""
    n = len(det)
    x = np.asarray(det["x"], dtype=float)
    y = np.asarray(det["y"], dtype=float)
    noise = np.asarray(det["noise_sigma"], dtype=float)
    stamps, cx, cy, sflags = cut_stamps(sub, x, y, cfg.stamp_size, bad=img.bad)
    flags |= sflags
    flags[_box_any(saturated, x, y, cfg.stamp_size)] |= _flags.flag_value("SATURATED")
    n_big = cfg.largest_stamp
    if n_big > cfg.stamp_size:
        bstamps, bcx, bcy, bflags = cut_stamps(sub, x, y, n_big, bad=img.bad)
        use_big = bflags == 0
        base_cfg = cfg.replace(max_stamp_size=0)
    else:
        bstamps, bcx, bcy, use_big, base_cfg = stamps, cx, cy, np.zeros(n, bool), cfg
    if n:
        # a galaxy is a close pair if a significant detection lies inside its stamp; a
        # faint detection (often a noise peak) is one if anything does
        fr = cfg.close_pair_faint_ratio or None
        flux = np.asarray(det["flux"], dtype=float)
        sig = np.nan_to_num(np.asarray(det["snr"], dtype=float)) >= cfg.close_pair_min_snr
        pair = close_pairs(x, y, flux=flux, stamp_size=cfg.stamp_size)
        pair[sig] = close_pairs(x[sig], y[sig], flux=flux[sig], stamp_size=cfg.stamp_size,
                                faint_ratio=fr)  # fmt: skip
        flags[pair] |= _flags.flag_value("CLOSE_PAIR")
    flags[~(np.isfinite(noise) & (noise > 0))] |= _flags.flag_value("BAD_NOISE")
    return _ImageStamps(stamps=stamps, bstamps=bstamps, use_big=use_big, cx=cx, cy=cy,
                        fcx=np.where(use_big, bcx, cx), fcy=np.where(use_big, bcy, cy),
                        base_cfg=base_cfg, offset=n_big // 2 - cfg.stamp_size // 2)


def _forced_snr(st: _ImageStamps, noise: np.ndarray, psf: PSFResult | None,
                cells: _CellPSFs | None) -> np.ndarray:  # fmt: skip
    """The matched-filter S/N of every object at its catalogue position on its base
    stamp (:func:`pylensfit.forced.position_snr`), with its heaviest PSF node's image
    where the PSF varies; NaN without a PSF."""
    out = np.full(st.cx.size, np.nan)
    if psf is None or not st.cx.size:
        return out
    if cells is None:
        return position_snr(st.stamps, psf.image, noise, (st.cx, st.cy))
    node = cells.nearest
    for k in np.unique(node):
        i = np.flatnonzero(node == k)
        out[i] = position_snr(st.stamps[i], cells.images[k], noise[i], (st.cx[i], st.cy[i]))
    return out


@dataclass
class _ImageFitter:
    """Fits an image's objects on their stamps, each with the PSF of its cell."""

    st: _ImageStamps
    noise: np.ndarray  # (n,) per-object noise sigma
    cfg: Config
    psf_image: np.ndarray | None  # the image's PSF (a constant PSF)
    cells: _CellPSFs | None  # a varying PSF model, sampled for the fits
    size_prior: SizePrior | None
    rings: np.ndarray | None  # fit_stamps' lnL_r_groups
    size_marginal_prior: Any

    def __call__(self, idx: np.ndarray, less: np.ndarray | None = None) -> StampFits:
        """Fit the stamps of objects ``idx``, less ``less`` (``(len(idx), n_big, n_big)``:
        the neighbours' light and the sky's change, about each object)."""
        cp = self.cells
        if less is None:  # a first fit: the run's object bar (a refit is not counted)
            report_progress("planned", idx.size)
        if cp is None:
            return self._fit_with(idx, less, self.psf_image, 1.0 if less is None else 0.0)
        parts = []
        for c in np.unique(cp.cell[idx]):  # one fit per cell and node of the PSF model
            sel = np.flatnonzero(cp.cell[idx] == c)
            j, lj = idx[sel], None if less is None else less[sel]
            share = 0.0 if less is not None else 1.0 / cp.nodes.shape[0]
            fits = [self._fit_with(j, lj, cp.images[k], share) for k in cp.nodes[:, j[0]]]
            parts.append((sel, blend_fits(fits, cp.weights[:, j])))
        return parts[0][1] if len(parts) == 1 else merge_fits(parts, idx.size)

    def _fit_with(self, idx: np.ndarray, less: np.ndarray | None, psf_image: np.ndarray,
                  share: float = 0.0) -> StampFits:  # fmt: skip
        """Fit objects ``idx`` with one PSF image, each on its stamp tier, in chunks of
        ``4 * Config.block_size`` objects (a whole number of :func:`fit_stamps`' own
        blocks, so that the chunks change no result), each chunk's objects reported to
        the run's progress bar as ``share`` of an object each."""
        st, cfg, o = self.st, self.cfg, self.st.offset
        n_big = st.bstamps.shape[1]
        parts = []
        step = 4 * cfg.block_size
        for sel, stamps, c in ((~st.use_big[idx], st.stamps, st.base_cfg),
                               (st.use_big[idx], st.bstamps, cfg)):  # fmt: skip
            where = np.flatnonzero(sel)
            for k0 in range(0, where.size, step):
                ws = where[k0 : k0 + step]
                j = idx[ws]
                data = stamps[j]
                if less is not None:
                    lj, m = less[ws], cfg.stamp_size
                    data = data - (lj if stamps.shape[1] == n_big else lj[:, o : o + m, o : o + m])
                parts.append((ws, fit_stamps(
                    data, psf_image, self.noise[j], config=c, centres=(st.fcx[j], st.fcy[j]),
                    size_prior=self.size_prior, lnL_r_groups=self.rings,
                    size_marginal_prior=self.size_marginal_prior)))  # fmt: skip
                report_progress("done", share * j.size)
        return parts[0][1] if len(parts) == 1 else merge_fits(parts, idx.size)


@dataclass
class _ImageResults:
    """The per-object results of an image's fits, filled as the objects are fitted."""

    x: np.ndarray  # detected positions (pixels)
    y: np.ndarray
    st: _ImageStamps
    lnL: np.ndarray
    lnL_r: np.ndarray | None
    lnL_bulge: np.ndarray | None
    lnL_star: np.ndarray
    flags: np.ndarray
    cols: dict[str, np.ndarray]
    xf: np.ndarray  # fitted positions (pixels)
    yf: np.ndarray
    is_star: np.ndarray

    @classmethod
    def empty(cls, x: np.ndarray, y: np.ndarray, st: _ImageStamps, flags: np.ndarray,
              bank, egrid: np.ndarray, keep_lnL_r: Any,
              rings: np.ndarray | None) -> _ImageResults:  # fmt: skip
        """NaN results for every object; ``lnL_r`` as ``keep_lnL_r`` asks (None, True
        or ``"annuli"``: per ring of ``|e|``, ``rings`` from
        :func:`pylensfit.likelihood.e_annuli`)."""
        n = x.size
        n_b = bank.n_r // bank.n_sizes
        if keep_lnL_r == "annuli":  # L(r) per ring of |e|, for any prior of |e|
            lnL_r = np.full((n, int(rings.max()) + 1, bank.n_r + 1), np.nan, dtype=np.float32)
        else:
            lnL_r = (np.full((n, bank.n_r + 1), np.nan, dtype=np.float32) if keep_lnL_r
                     else None)  # fmt: skip
        cols = {k: np.full(n, np.nan) for k in FIT_COLUMNS}  # the catalogue's names
        cols["stamp_size"] = np.zeros(n, dtype=np.int32)
        return cls(x=x, y=y, st=st, lnL=np.full((n, egrid.shape[0]), np.nan, dtype=np.float32),
                   lnL_r=lnL_r,
                   lnL_bulge=(None if n_b == 1 else
                              np.full((n, n_b, egrid.shape[0]), np.nan, np.float32)),
                   lnL_star=np.full(n, np.nan), flags=flags, cols=cols, xf=x.copy(),
                   yf=y.copy(), is_star=np.zeros(n, dtype=bool))  # fmt: skip

    def store(self, f: StampFits, idx: np.ndarray) -> None:
        """Keep the fits ``f`` of objects ``idx``."""
        _store_fit(f, idx, self.x, self.y, self.st.fcx, self.st.fcy, self.lnL, self.lnL_r,
                   self.lnL_bulge, self.lnL_star, self.flags, self.cols, self.xf, self.yf,
                   self.is_star)  # fmt: skip


@dataclass(frozen=True)
class PSFSummary:
    """An image's PSF as the catalogue keeps it (its ``PSFS`` and ``PSFIMG`` HDUs).

    Attributes
    ----------
    numbers : dict of float
        The PSF's diagnostics at the image's centre (``_PSF_KEYS``: ``n_used``,
        ``fwhm``, ``sigma``, ...) and a varying model's held-out check
        (``_HELDOUT_KEYS``, NaN for a constant PSF).
    image : numpy.ndarray
        The PSF image at the image's centre.
    """

    numbers: dict[str, float]
    image: np.ndarray

    def get(self, key: str) -> float:
        """The number ``key`` (NaN if not kept)."""
        return self.numbers.get(key, math.nan)

    @property
    def sigma(self) -> float:
        """The PSF's size (pixels, adaptive moments)."""
        return self.get("sigma")


@dataclass(frozen=True)
class ImageResult:
    """One image measured: what :func:`_image_task` hands the run, a part file keeps
    (:func:`_write_part`, :func:`_read_part`) and :func:`_assemble` reads.

    Attributes
    ----------
    index : int
        The image's index in the run.
    path : str
        The image file.
    rows : dict of numpy.ndarray
        The image's catalogue columns before the shapes (:func:`_image_rows`), one
        entry per object, under the names of :data:`pylensfit.catalogue.COLUMNS`.
    lnL : numpy.ndarray
        ``(n, n_e)`` float32 ``ln L(e)`` of each object (NaN: not measured).
    egrid : numpy.ndarray
        ``(n_e, 2)`` the ellipticity grid of ``lnL``.
    lnL_bulge : numpy.ndarray or None
        ``(n, n_b, n_e)`` each bulge fraction's ``ln L(e)`` (marginalised fractions).
    lnL_r : numpy.ndarray or None
        ``L(r)`` (per ring of ``|e|``) where a calibration pass keeps it.
    psf : PSFSummary or None
        The image's PSF (None: it failed).
    psf_note : str
        Why the image's own stars gave no PSF ("" if they did).
    psf_source : str
        Where the PSF came from, in words.
    timing : dict of float
        Seconds per stage (``read+detect``, ``psf``, ``stamps``, ``fit``).
    """

    index: int
    path: str
    rows: dict[str, np.ndarray]
    lnL: np.ndarray
    egrid: np.ndarray
    lnL_bulge: np.ndarray | None = None
    lnL_r: np.ndarray | None = None
    psf: PSFSummary | None = None
    psf_note: str = ""
    psf_source: str = ""
    timing: dict[str, float] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.lnL.shape[0])


def _image_task(task: _ImageTask) -> ImageResult:
    """Measure one image: every detected object gets a row, measured or flagged."""
    t0 = time.perf_counter()
    single_thread(task.single_thread)
    cfg = task.config
    path = task.path
    img = _read_image(path, task.weight, task.mask)
    saturated = _mask_saturated(img, cfg)
    positions = _read_positions(task.catalogue, path) if task.catalogue else None
    sub, det, bkg = _detect(img, cfg, positions)
    t_detect = time.perf_counter()
    n = len(det)
    lost = np.asarray(det["no_position"]) if "no_position" in det.colnames else np.zeros(n, bool)
    flags = np.zeros(n, dtype=np.int32)
    psf, field_model, own_stars, psf_note = _image_psf(task, cfg, img, sub, det)
    if psf is None:
        flags[:] |= _flags.flag_value("PSF_FAILED")
        if n:
            log.error("%s: no usable star for the PSF in the image or the star fields (%s); "
                      "its %d objects are flagged PSF_FAILED", path, psf_note, n)  # fmt: skip
    if psf is not None and task.psf_dir:
        (field_model or psf).write(Path(task.psf_dir) / f"{Path(path).stem}.psf.fits",
                                   overwrite=True)  # fmt: skip
    x = np.asarray(det["x"], dtype=float)
    y = np.asarray(det["y"], dtype=float)
    noise = np.asarray(det["noise_sigma"], dtype=float)
    cells = None
    if field_model is not None:
        cells = _cell_psfs(field_model, sub.shape, cfg.psf_cells, x, y,
                           bilinear=cfg.psf_interpolation == "bilinear")  # fmt: skip
    t_psf = time.perf_counter()
    st = _image_stamps(sub, img, det, cfg, saturated, flags)
    if positions is not None:  # an input catalogue: the evidence at each position itself
        det["forced_SNratio"] = _forced_snr(st, noise, psf, cells)
    t_stamps = time.perf_counter()
    bank = model_bank(cfg)
    egrid = ellipticity_grid(cfg.output_e_step, emax=cfg.e_max)  # fit_stamps' grid
    rings = e_annuli(bank.egrid) if task.keep_lnL_r == "annuli" else None
    res = _ImageResults.empty(x, y, st, flags, bank, egrid, task.keep_lnL_r, rings)
    fit = _ImageFitter(
        st=st, noise=noise, cfg=cfg, psf_image=None if psf is None else psf.image,
        cells=cells, size_prior=task.size_prior, rings=rings,
        size_marginal_prior=task.size_marginal_prior)  # fmt: skip
    todo = np.flatnonzero(flags == 0)
    # the PSF the neighbours are rendered with: each object's heaviest node's, or the image's
    render_psf = (cells.images, cells.nearest) if cells is not None else (
        psf.image if psf is not None else None)
    if todo.size:
        fits_ = fit(todo)
        res.store(fits_, todo)
    # a model that does not fit its stamp (a defect: a saturated star, a bleed trail, a
    # hot pixel) is flagged DEFECT and kept out of the others' stamps and of the sky
    defect = np.zeros(todo.size, dtype=bool)
    redo = np.zeros(0, dtype=np.int64)
    back = bkg.back
    if todo.size and (cfg.subtract_neighbours and todo.size > 1 or cfg.model_background):

        def sky(field):
            """The change of the background measured on the image less ``field``."""
            nonlocal back
            back = measure_background(img.data - field, mask=img.bad, weight=img.weight,
                                      box=cfg.background_box).back  # fmt: skip
            return back - bkg.back

        redo, defect = subtract_neighbours(
            sub.shape, x, y, res.xf, res.yf, noise, todo, fits_, render_psf, cfg, fit,
            res.store, sky=sky if cfg.model_background else None,
            data=st.bstamps)  # fmt: skip
    elif todo.size:  # no refit: the first fits are judged as they are
        others, _, own, _ = _neighbour_light(sub.shape, x, y, res.xf, res.yf, todo, fits_,
                                             render_psf, cfg, own_too=True)  # fmt: skip
        defect = _implausible_models(st.bstamps, todo, noise, fits_, cfg, others, own)
    if defect.any():
        flags[todo[defect]] |= _flags.flag_value("DEFECT")
        log.info("%s: %d object(s) whose best model does not fit the stamp flagged DEFECT "
                 "(Config.max_reduced_chi2, max_residual_fraction)", path,
                 int(defect.sum()))  # fmt: skip
    t_fit = time.perf_counter()
    rows = _image_rows(task, img, det, res, back, psf, cells, own_stars, redo, lost)
    if field_model is not None and field_model.diagnostics.get("heldout_suspect") == 1.0:
        rows["flags"] = rows["flags"] | _flags.flag_value("PSF_SUSPECT")
    timing = {"read+detect": t_detect - t0, "psf": t_psf - t_detect,
              "stamps": t_stamps - t_psf, "fit": t_fit - t_stamps}  # fmt: skip
    return ImageResult(
        index=task.index, path=path, rows=rows, lnL=res.lnL, lnL_bulge=res.lnL_bulge,
        lnL_r=res.lnL_r, egrid=egrid,
        psf=None if psf is None else _psf_summary(psf, field_model), psf_note=psf_note,
        psf_source=_psf_source(task, psf, field_model, own_stars), timing=timing)  # fmt: skip


def _psf_source(task: _ImageTask, psf: PSFResult | None, field_model: PSFModel | None,
                own_stars: np.ndarray) -> str:  # fmt: skip
    """Where an image's PSF came from, in words (the PSFS HDU's ``psf_source``)."""
    if psf is None:
        return "none"
    if task.psf is not None:
        return "given model" if isinstance(task.psf, PSFModel) else "given"
    n_fields = sum(isinstance(p, PSFResult) for p in task.star_psfs)
    if field_model is not None:
        whose = "star field" if any(field_model is m for m in task.star_psfs) else "image"
        return f"polynomial model of the {whose}'s stars"
    parts = (["image's stars"] if own_stars.any() else []) + (
        [f"{n_fields} star field(s)"] if n_fields else [])
    return "stacked: " + " + ".join(parts) if parts else "stacked"


def _image_rows(task: _ImageTask, img: _Image, det: Table, res: _ImageResults,
                back: np.ndarray, psf: PSFResult | None, cells: _CellPSFs | None,
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
        "background": _value_at(back, x, y),
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


def _flag_weak_positions(task: _ImageTask, flags: np.ndarray, measured: np.ndarray,
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


def _store_fit(f, idx, x, y, cx, cy, lnL, lnL_r, lnL_bulge, lnL_star, flags, cols, xf, yf,
               is_star) -> None:  # fmt: skip
    """Write the fits ``f`` of objects ``idx`` into the image's per-object arrays."""
    lnL[idx] = f.lnL
    flags[idx] = f.flags  # the objects fitted had no flag before the fit
    if lnL_r is not None:
        lnL_r[idx] = f.lnL_r if lnL_r.ndim == 2 else f.lnL_r_grouped
    if lnL_bulge is not None:
        lnL_bulge[idx] = f.lnL_bulge
        lnL_star[idx] = f.lnL_star
    for k, v in fit_columns(f).items():  # the catalogue's names, as measure_stamps'
        cols[k][idx] = v
    ok = np.isfinite(f.x)
    xf[idx[ok]] = f.x[ok] + (x[idx[ok]] - cx[idx[ok]])
    yf[idx[ok]] = f.y[ok] + (y[idx[ok]] - cy[idx[ok]])
    is_star[idx] = f.is_star


_MODEL_KEYS = ("flux", "x", "y", "is_star", "r_best", "lnL", "bulge_best", "flags", "stamp")


def subtract_neighbours(shape, x, y, xf, yf, noise, fitted, first, psf, cfg: Config, refit,
                        store, *, sky=None, data=None):  # fmt: skip
    """Fit galaxies again with their neighbours' best-fit models taken out of the stamps.

    ``cfg.neighbour_iterations`` rounds: each renders every fitted object's current model
    (:func:`_neighbour_light`) and refits the galaxies of the first fit (``flags == 0``)
    whose stamps hold more than ``cfg.neighbour_min_chi2`` of their neighbours' light.
    The first round's neighbour models were fitted with the galaxy's own wings in their
    stamps; a second round fits the neighbours with the galaxy's model subtracted in turn
    (measured: it moves m by less than 2e-4 for the neighbours alone; the re-measured
    sky below needs it, so two rounds are the default). With
    ``cfg.subtract_neighbours`` off, no neighbour light is taken out (only ``sky``'s
    change).

    With ``sky``, every round also measures the background again on the image less the
    current model of every fitted object (``sky(field)`` returns the change of the
    background map), and that change is taken out of every stamp too; a galaxy is
    refitted when the two together exceed ``cfg.neighbour_min_chi2``. The first fit
    (on the first background, with the neighbours in the stamps) gives models too
    extended and too faint, so the sky converges over the rounds (a STEP2-like field:
    +0.056, +0.017, +0.006 noise sigma).

    Parameters
    ----------
    shape : tuple
        Image shape.
    x, y : numpy.ndarray
        Every object's stamp position (the stamps' centres).
    xf, yf : numpy.ndarray
        Every object's fitted position, updated in place by ``store``.
    noise : numpy.ndarray
        Every object's noise sigma.
    fitted : numpy.ndarray
        Indices of the objects fitted, in the order of ``first``.
    first : StampFits
        Their first fits.
    psf : numpy.ndarray or tuple
        PSF image, or ``(images, cell)``: ``(n_cells, N, N)`` PSF images and each
        object's cell (``(n_objects,)``), every model rendered with its cell's PSF.
    cfg : Config
    refit : callable
        ``refit(idx, others)`` fits the stamps of objects ``idx`` less ``others``.
    store : callable
        ``store(fits, idx)`` records the fits of objects ``idx`` (and updates ``xf, yf``).
    sky : callable, optional
        ``sky(field) -> (ny, nx)``: the change of the background when it is measured on
        the image less ``field``, the rendered models of all fitted objects.
    data : numpy.ndarray, optional
        ``(n, N, N)`` every object's stamp as the fits saw it (``N =
        cfg.largest_stamp``): with it, every round first judges the current models
        (:func:`_implausible_models`). The objects whose models do not fit their stamps
        (a defect: a saturated star, a bleed trail, a hot pixel) are suspects: their
        models are rendered neither into the others' stamps nor into ``field``, and they
        are fitted again with the others' light taken out; a suspect whose new fit
        describes its stamp is cleared (a first fit spoiled by a bright neighbour), the
        others are ``DEFECT``. After the last round the suspects' last fits are judged
        once more.

    Returns
    -------
    done : numpy.ndarray
        Indices of the objects whose neighbours' light was taken out (a subset of those
        fitted again when ``sky`` is given).
    defect : numpy.ndarray
        Boolean, one per ``fitted``: the objects whose best model does not fit their
        stamp (none without ``data``).
    """
    cur = {k: np.array(getattr(first, k)) for k in _MODEL_KEYS}
    cur["egrid"] = first.egrid
    ok = first.flags == 0
    done = np.zeros(0, dtype=np.int64)
    dsky = None
    suspect = np.zeros(fitted.size, dtype=bool)

    def light():  # every fitted model, the suspects' into their own stamps only
        return _neighbour_light(shape, x, y, xf, yf, fitted, SimpleNamespace(**cur), psf, cfg,
                                exclude=suspect, own_too=True)  # fmt: skip

    def judge(others, own, aside):  # with every model's light, the suspects' too
        return _implausible_models(data, fitted, noise, SimpleNamespace(**cur), cfg,
                                   others if aside is None else others + aside, own,
                                   dsky)  # fmt: skip

    def _chi2(light):  # the light taken out of each fitted stamp, in units of its noise
        # (the window each object was fitted on: the base stamp or a larger tier)
        out = np.empty(fitted.size)
        nl, win = light.shape[1], np.asarray(cur["stamp"])
        for s in np.unique(win):
            a, i = nl // 2 - int(s) // 2, np.flatnonzero(win == s)
            out[i] = np.sum(light[fitted[i], a : a + int(s), a : a + int(s)] ** 2, axis=(1, 2))
        return out / noise[fitted] ** 2

    refitted = np.zeros(fitted.size, dtype=bool)  # in the last round
    for _ in range(int(cfg.neighbour_iterations)):
        others, field, own, aside = light()
        if data is not None:
            now = judge(others, own, aside)
            if (now != suspect).any():
                suspect = now
                others, field, own, aside = light()
        if not cfg.subtract_neighbours:
            others[:] = 0.0
        if sky is not None:
            dsky = cut_stamps(sky(field), x, y, cfg.largest_stamp)[0]
        near = _chi2(others) > cfg.neighbour_min_chi2
        less = others if dsky is None else others + dsky
        go = near if dsky is None else _chi2(less) > cfg.neighbour_min_chi2
        sel = np.flatnonzero(ok & (go | suspect))
        refitted[:] = False
        if sel.size == 0:
            break
        idx = fitted[sel]
        f2 = refit(idx, less[idx])
        store(f2, idx)
        for k in _MODEL_KEYS:
            cur[k][sel] = getattr(f2, k)
        refitted[sel] = True
        done = np.union1d(done, fitted[ok & near])
    if data is not None and (suspect & refitted).any():  # the suspects' last fits
        others, _, own, aside = light()
        suspect = judge(others, own, aside)
    return done, suspect


def _likelihood_mean_e(lnL: np.ndarray, egrid: np.ndarray, block: int = 512) -> np.ndarray:
    """``(n, 2)`` mean of each ``L(e)`` (flat prior) on the refined integration grid: the
    ellipticity of a neighbour's model, continuous where the most likely cell is not."""
    out = np.zeros((lnL.shape[0], 2))
    for s0 in range(0, lnL.shape[0], block):
        fine, grid = refine_lnL(lnL[s0 : s0 + block], egrid)
        w = np.exp(fine)
        out[s0 : s0 + block] = (w @ grid) / w.sum(axis=1, keepdims=True)
    return out


def _rendered(f) -> np.ndarray:
    """Which fits ``f`` have a model to render: a finite, positive flux at a finite
    position."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(f.flux) & (f.flux > 0) & np.isfinite(f.x) & np.isfinite(f.y)


def _implausible_models(data, fitted, noise, f, cfg: Config, others, own,
                        dsky=None) -> np.ndarray:  # fmt: skip
    """The fitted objects whose best model does not fit their stamp (``DEFECT``).

    On the base stamp (``cfg.stamp_size`` px square about the object, where the
    close-pair test left no other detection) the residual ``r`` is the stamp less the
    object's own rendered model and its neighbours'. An object is implausible where the
    residual is both significant, a reduced chi-square ``chi2 = sum(r^2) / (sigma^2
    N^2)`` above ``cfg.max_reduced_chi2``, and a large part of the model's own power,
    ``sum(r^2 - sigma^2) / sum(m^2)`` above ``cfg.max_residual_fraction`` (``m`` the
    model on the stamp). A galaxy or a star that the models describe leaves the noise
    and a small mismatch of the profile; a saturated star, a bleed trail or a hot pixel
    (flat-topped, or sharper than the PSF) leaves a residual of thousands of noise
    variances per pixel, 0.13 to 20 times the model's power. So is a fit with no finite
    positive amplitude and no other flag than ``STAR``.

    A defect's model spreads into its neighbours' stamps and raises their residuals, so
    an object is implausible only if its stamp less its own model alone is beyond the
    limits too: a neighbour spoiled by the defect's model alone is not.

    Parameters
    ----------
    data : numpy.ndarray
        ``(n, N, N)`` every object's stamp (background subtracted, data units), cut as
        :func:`~pylensfit.stamps.cut_stamps` cuts them (``N >= cfg.stamp_size``).
    fitted : numpy.ndarray
        ``(m,)`` indices of the fitted objects, in the order of ``f``.
    noise : numpy.ndarray
        ``(n,)`` noise sigma per pixel (data units).
    f : StampFits or namespace
        The current fits of the objects ``fitted`` (``flux, x, y, flags``).
    cfg : Config
    others, own : numpy.ndarray
        ``(n, N, N)`` :func:`_neighbour_light`'s light of the other objects and each
        object's own model (``own_too=True``), data units.
    dsky : numpy.ndarray, optional
        ``(n, N, N)`` the change of the sky taken out of the stamps too.

    Returns
    -------
    numpy.ndarray
        ``(m,)`` boolean, the implausible objects.
    """
    n, big = cfg.stamp_size, data.shape[1]
    w = slice(big // 2 - n // 2, big // 2 - n // 2 + n)  # the base stamp in the larger

    def cut(a, idx):
        return a[idx][:, w, w]

    rendered = _rendered(f)
    var = noise[fitted] ** 2
    mine = cut(own, fitted)
    resid = cut(data, fitted) - mine
    if dsky is not None:
        resid -= cut(dsky, fitted)
    with np.errstate(over="ignore", invalid="ignore"):
        power = np.sum(mine * mine, axis=(1, 2)) / var  # the model's, in noise variances
    out = rendered & _poor_fit(resid, var, power, cfg)  # its own model alone
    i = np.flatnonzero(out)  # the few: with the neighbours' light taken out too
    out[i] = _poor_fit(resid[i] - cut(others, fitted[i]), var[i], power[i], cfg)
    star = _flags.flag_value("STAR")
    return out | ~rendered & ((np.asarray(f.flags) & ~star) == 0)


def _poor_fit(resid: np.ndarray, var: np.ndarray, power: np.ndarray, cfg: Config) -> np.ndarray:
    """Where residuals ``(m, N, N)`` (data units; noise variance ``var`` per stamp) are
    significant (reduced chi-square above ``cfg.max_reduced_chi2``) and more than
    ``cfg.max_residual_fraction`` of the model's ``power`` (in noise variances)."""
    npix = resid.shape[1] * resid.shape[2]
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        chi2 = np.sum(resid * resid, axis=(1, 2)) / var
        frac = (chi2 - npix) / power
        return ~(chi2 <= cfg.max_reduced_chi2 * npix) & ~(frac <= cfg.max_residual_fraction)


def _neighbour_light(shape, x, y, xf, yf, fitted, f, psf, cfg: Config, block: int = 256,
                     exclude=None, own_too: bool = False):  # fmt: skip
    """The light of every other fitted object in each object's stamp.

    Each object of ``fitted`` (fits ``f``, in the same order) is rendered
    (:func:`pylensfit.models.render_models`) with the size, bulge fraction, flux and
    position of the maximum of ``L(e, r)`` and the mean ellipticity of ``L(e)`` (a
    point source for stars) on a canvas of four times the stamp side about its position
    (the models are periodic on it: a de Vaucouleurs model has 13-28 % of its light
    beyond 16 px at r = 4 px, which a canvas of twice the stamp wraps back), and
    the canvases are added into an image of the field (and at least twice the largest
    stamp tier). Returns ``(n, N, N)``, ``N = cfg.largest_stamp``: that image cut about
    every object's position as :func:`~pylensfit.stamps.cut_stamps` cuts the stamps,
    less the object's own model; and the image of the field. The objects of
    ``exclude`` (boolean, one per ``fitted``: suspected defects) are left out of the
    field, so of every stamp but their own. With ``own_too``, two more: each object's
    own model (``(n, N, N)``, zero where none; the excluded objects' too) and the light
    of the excluded objects in each stamp, less its own (``(n, N, N)``, or ``None``
    where none is excluded). ``psf`` is the PSF image, or ``(images, cell)`` for a PSF
    per cell of the image (:func:`subtract_neighbours`).
    """
    n_stamp = cfg.largest_stamp  # the stamps of the tiers (Config.max_stamp_size)
    big = max(4 * cfg.stamp_size, 2 * n_stamp)
    good = _rendered(f)
    obj = fitted[good]
    into = np.ones(obj.size, dtype=bool) if exclude is None else ~np.asarray(exclude)[good]
    r = np.where(f.is_star[good], 0.0, np.nan_to_num(f.r_best[good]))
    e = _likelihood_mean_e(f.lnL[good], f.egrid)
    e1 = np.where(f.is_star[good], 0.0, e[:, 0])
    e2 = np.where(f.is_star[good], 0.0, e[:, 1])
    bf = np.nan_to_num(f.bulge_best[good], nan=cfg.bulge_fraction)
    flux = f.flux[good]
    field = np.zeros(shape)
    aside = np.zeros(shape) if own_too and not into.all() else None  # the excluded's
    own = np.zeros((x.size, n_stamp, n_stamp))
    bx0, by0 = patch_origins(x[obj], y[obj], big)
    lo = big // 2 - n_stamp // 2
    if isinstance(psf, tuple):  # a PSF per cell of the image: each model with its own
        images, cell = psf
        groups = [(images[c], np.flatnonzero(cell[obj] == c)) for c in np.unique(cell[obj])]
    else:
        groups = [(psf, np.arange(obj.size))]
    for p_img, members in groups:
        for s0 in range(0, members.size, block):
            sl = members[s0 : s0 + block]
            pat = render_models(big, p_img, xf[obj[sl]] - bx0[sl], yf[obj[sl]] - by0[sl],
                                e1[sl], e2[sl], r[sl], flux[sl], model=cfg.model,
                                bulge_fraction=bf[sl],
                                bulge_size_ratio=cfg.bulge_size_ratio)  # fmt: skip
            k = into[sl]
            add_patches(field, pat[k], bx0[sl][k], by0[sl][k])
            if aside is not None:
                add_patches(aside, pat[~k], bx0[sl][~k], by0[sl][~k])
            own[obj[sl]] = pat[:, lo : lo + n_stamp, lo : lo + n_stamp]
    stamps, _, _, _ = cut_stamps(field, x, y, n_stamp)
    if into.all():
        stamps -= own
    else:  # the excluded objects' own light is in no stamp
        stamps[obj[into]] -= own[obj[into]]
    if not own_too:
        return stamps, field
    if aside is not None:
        aside = cut_stamps(aside, x, y, n_stamp)[0]
        aside[obj[~into]] -= own[obj[~into]]
    return stamps, field, own, aside


_PSF_KEYS = ("n_used", "n_rejected", "fwhm", "sigma", "e1", "e2")
#: A varying PSF model's check on its held-out stars (:class:`PolynomialPSF`'s
#: ``diagnostics``), kept per image in the catalogue's ``PSFS`` HDU (NaN otherwise).
_HELDOUT_KEYS = ("heldout_n", "heldout_mean_de1", "heldout_mean_de2", "heldout_rms_de1",
                 "heldout_rms_de2", "heldout_noise_de", "heldout_excess_de1",
                 "heldout_excess_de2", "heldout_chi2_de", "heldout_pvalue_de",
                 "heldout_suspect")  # fmt: skip


def _psf_summary(psf: PSFResult, model: PSFModel | None = None) -> PSFSummary:
    """The PSF's numbers for the catalogue: the PSF at the image's centre and, for a
    model fitted over the image, its held-out stars' residuals (NaN if it has none)."""
    d = {k: float(getattr(psf, k)) for k in _PSF_KEYS}
    d["n_used"], d["n_rejected"] = int(psf.n_used), int(psf.n_rejected)
    diag = {} if model is None else model.diagnostics
    d.update({k: float(diag.get(k, math.nan)) for k in _HELDOUT_KEYS})
    return PSFSummary(numbers=d, image=np.asarray(psf.image, dtype=float))


def _sky(header: fits.Header, x: np.ndarray, y: np.ndarray):
    """RA, Dec (deg, NaN without a WCS) and the sky frame (:mod:`pylensfit.skyframe`)
    at pixel positions ``x, y``."""
    w = wcs_from_header(header)
    if w is None or x.size == 0:
        return np.full(x.size, np.nan), np.full(x.size, np.nan), pixel_frame(x.size)
    ra, dec = w.all_pix2world(x, y, 0)
    return (np.asarray(ra, dtype=np.float64), np.asarray(dec, dtype=np.float64),
            local_frame(w, x, y))  # fmt: skip


# ----------------------------------------------------------------------------------------
# Parts: one file per finished image, for restarts
# ----------------------------------------------------------------------------------------
def _task_key(task: _ImageTask) -> str:
    """A digest of everything that determines an image's result."""
    stamp = []
    for k in ("path", "weight", "mask", "catalogue"):
        p = getattr(task, k)
        if p:
            st = Path(p).stat()
            stamp.append((k, os.path.abspath(p), st.st_size, st.st_mtime_ns))
    given = task.psf  # a given PSF (its image), else the star fields' PSFs
    psfs = [given] if given is not None else task.star_psfs
    sp = None if task.size_prior is None else task.size_prior.to_dict()
    blob = json.dumps(
        [stamp, task.config.to_dict(), task.star_column, given is not None,
         [r.digest for r in psfs], sp,
         __version__], sort_keys=True, default=str,
    )  # fmt: skip
    return hashlib.sha1(blob.encode()).hexdigest()[:16]


def _part_path(parts: Path, task: _ImageTask) -> Path:
    return parts / f"{task.index:05d}_{Path(task.path).stem}_{_task_key(task)}.fits"


def _write_part(path: Path, res: ImageResult) -> None:
    """One finished image as a part file, which :func:`_read_part` reads back as it was.

    The arrays go in HDUs of their own dtypes; the rest (index, path, PSF summary, PSF
    note, timing) as JSON in the one-row table ``INFO``: floats by ``repr`` and text of
    any length and characters, so that a resumed run writes the catalogue of a run never
    stopped (header cards round floats to 16 digits; the PSF HDU's are for reading).
    """
    t = Table(res.rows)
    psf = None if res.psf is None else {k: res.psf.numbers[k] for k in _PSF_KEYS + _HELDOUT_KEYS}
    info = {"index": int(res.index), "path": res.path, "psf": psf,
            "psf_note": res.psf_note, "psf_source": res.psf_source,
            "timing": res.timing}  # fmt: skip
    hdr = fits.Header()
    hdr["INDEX"] = int(res.index)
    hdus = [fits.PrimaryHDU(header=hdr), fits.table_to_hdu(t),
            fits.ImageHDU(res.lnL, name="LNL"),
            fits.ImageHDU(res.egrid, name="EGRID"),
            fits.BinTableHDU(Table({"json": [json.dumps(info)]}), name="INFO")]  # fmt: skip
    hdus[1].name = "ROWS"
    if res.lnL_bulge is not None:
        hdus.append(fits.ImageHDU(res.lnL_bulge, name="LNLB"))
    if res.psf is not None:
        ph = fits.ImageHDU(res.psf.image, name="PSF")
        for k in _PSF_KEYS:
            ph.header[k.upper()[:8]] = res.psf.numbers[k]
        hdus.append(ph)
    atomic_write(fits.HDUList(hdus), path, overwrite=True)


def _read_part(path: Path) -> ImageResult:
    """An image's result from its part file (:func:`_write_part`); a file without the
    ``INFO`` table (an older format) raises, and the image is redone."""
    with fits.open(path, memmap=False) as h:
        info = json.loads(str(h["INFO"].data["json"][0]))
        rows = Table(h["ROWS"].data)
        psf = None
        if info["psf"] is not None:
            psf = PSFSummary(numbers=dict(info["psf"]),
                             image=np.array(h["PSF"].data, dtype=float))  # fmt: skip
        return ImageResult(
            index=int(info["index"]), path=info["path"],
            rows={c: np.asarray(rows[c]) for c in rows.colnames},
            lnL=np.array(h["LNL"].data, dtype=np.float32),
            lnL_bulge=np.array(h["LNLB"].data, dtype=np.float32) if "LNLB" in h else None,
            egrid=np.array(h["EGRID"].data, dtype=float), psf=psf,
            psf_note=info["psf_note"], psf_source=info.get("psf_source", ""),
            timing=info["timing"])  # fmt: skip


# ----------------------------------------------------------------------------------------
# The public entry point
# ----------------------------------------------------------------------------------------
def _as_list(v, n: int, name: str) -> list:
    if v is None:
        return [None] * n
    if isinstance(v, (str, os.PathLike)):
        v = [v]
    v = [None if p is None else str(p) for p in v]
    if len(v) != n:
        raise InputError(f"{name}: {len(v)} given for {n} images")
    return v


def _image_shapes(path: str, what: str) -> dict[str, tuple[int, ...]]:
    """The shapes of a FITS file's first 2-D image (key ``""``) and of its ``WEIGHT`` and
    ``MASK`` HDUs, from the headers: :func:`measure` opens every input this way before
    any work starts, so that a damaged file is reported at once, on one line naming it.

    Raises
    ------
    InputError
        A file that cannot be opened or is truncated (an HDU's data or header cut short:
        astropy reads what is there with a warning, and would leave the rest out or fail
        when the image's task runs), or one without a 2-D image.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # astropy's truncation warnings: reported below
        with _open(path, what) as hdul:
            n = len(hdul)  # every header read
            size = hdul.fileinfo(0)["file"].size  # 0 where unknown: a compressed file
            end = 0
            for i in range(n):
                info = hdul.fileinfo(i)
                end = info["datLoc"] + info["datSpan"]
                if size and end > size:
                    raise InputError(f"{path}: truncated {what} file ({size} bytes, HDU {i} "
                                     f"ends at byte {end})")  # fmt: skip
                if not size:  # compressed: its data must be read to know it is all there
                    try:
                        _ = hdul[i].data
                    except Exception as err:
                        raise InputError(f"{path}: cannot read HDU {i} of the {what} file "
                                         f"({type(err).__name__}: {err})") from None  # fmt: skip
            if size and size > end and _not_blank(path, end):
                raise InputError(f"{path}: truncated {what} file ({size - end} bytes after "
                                 f"HDU {n - 1} are not a whole HDU)")  # fmt: skip
            shapes = {}
            for h in hdul:
                if (isinstance(h, (fits.PrimaryHDU, fits.ImageHDU)) and len(h.shape) == 2
                        and min(h.shape) > 0):  # fmt: skip
                    shapes.setdefault("", tuple(h.shape))
            for name in ("WEIGHT", "MASK"):
                if name in hdul:
                    h = hdul[name]
                    shapes[name] = tuple(h.shape) if isinstance(
                        h, (fits.PrimaryHDU, fits.ImageHDU)) else ()  # fmt: skip
    if "" not in shapes:
        raise InputError(f"{path}: no 2-D image in the file")
    return shapes


def _not_blank(path: str, start: int) -> bool:
    """Whether the bytes of ``path`` from ``start`` on are not all zeros or blanks (the
    padding some writers leave after the last HDU, which astropy reads past)."""
    with open(path, "rb") as fh:
        fh.seek(start)
        while chunk := fh.read(1 << 16):
            if chunk.strip(b"\0 "):
                return True
    return False


def _check_inputs(images: list[str], weights: list, masks: list, stars: list[str]) -> None:
    """Open every input image, weight map, mask and star field before any work starts
    (:func:`_image_shapes`), and refuse an image given twice (its rows would be
    duplicated): one line naming the file and the problem."""
    first: dict[Any, str] = {}
    for p in images:
        st = os.stat(p)
        key = (st.st_dev, st.st_ino) if st.st_ino else os.path.normcase(os.path.realpath(p))
        if key in first:
            also = "" if first[key] == p else f" (the same file as {first[key]})"
            raise InputError(f"{p}: image given twice{also}; each image must be given once")
        first[key] = p
    for p, w, m in zip(images, weights, masks, strict=True):
        shapes = _image_shapes(p, "image")
        # a weight or mask file given replaces the image's own HDU (as _read_image reads)
        for f, name, what in ((w, "WEIGHT", "weight map"), (m, "MASK", "mask")):
            if f is not None:
                shape = _image_shapes(f, what)[""]
            elif name in shapes:
                shape = shapes[name]
            else:
                continue
            if len(shape) != 2:
                raise InputError(f"{p}: its {name} HDU is not a 2-D image")
            if shape != shapes[""]:
                raise InputError(f"{f or p}: {what} shape {shape} differs from the image's "
                                 f"{shapes['']}" + (f" ({p})" if f else ""))  # fmt: skip
    for p in stars:
        _image_shapes(p, "star field")


def _is_temporary(p: Path, name: str | None = None) -> bool:
    """Whether ``p`` is a temporary of :func:`pylensfit.catalogue.atomic_write` (of the
    file ``name``, else of any file): ``.<name>.<8 characters>.tmp``."""
    stem = re.escape(name) if name is not None else r".+"
    return re.fullmatch(rf"\.{stem}\.[a-z0-9_]{{8}}\.tmp", p.name) is not None


def _remove_stale_temporaries(out: Path, parts: Path) -> None:
    """Remove what writes of ``out`` and of its part files killed before they finished
    left behind (a write that finishes renames its temporary)."""
    stale = []
    if out.parent.is_dir():
        stale += [p for p in out.parent.iterdir() if _is_temporary(p, out.name)]
    if parts.is_dir():
        stale += [p for p in parts.iterdir() if _is_temporary(p)]
    for p in stale:
        log.info("%s: removing the temporary of a write that did not finish", p)
        p.unlink(missing_ok=True)


@contextmanager
def _parts_dropped_if_unused(parts: Path | None) -> Iterator[None]:
    """A run's context: a run that fails (an error in its input or its work) leaves no
    ``parts`` behind; a run that is interrupted (``KeyboardInterrupt``, a signal) keeps
    them for a later run to resume from, unless they hold nothing to resume (no part
    file, no priors: at most temporaries)."""
    try:
        yield
    except Exception:
        if parts is not None and parts.is_dir():
            shutil.rmtree(parts, ignore_errors=True)
        raise
    except BaseException:
        if parts is not None and parts.is_dir() and all(_is_temporary(p)
                                                        for p in parts.iterdir()):
            shutil.rmtree(parts, ignore_errors=True)
        raise


def measure(
    images: str | os.PathLike | Iterable[str | os.PathLike],
    *,
    stars: Iterable[str | os.PathLike] | None = None,
    weights: Iterable[str | os.PathLike | None] | None = None,
    masks: Iterable[str | os.PathLike | None] | None = None,
    catalogues: Iterable[str | os.PathLike | None] | None = None,
    star_column: str | None = None,
    config: Config | None = None,
    prior: Prior | str | os.PathLike | None = None,
    size_prior: SizePrior | str | os.PathLike | None = None,
    priors: Priors | str | os.PathLike | None = None,
    psf: PSFResult | PSFModel | np.ndarray | str | os.PathLike | Sequence | None = None,
    output: str | os.PathLike | None = None,
    psf_dir: str | os.PathLike | None = None,
    overwrite: bool = False,
    jobs: int = 1,
    scheduler: str | None = None,
    progress: bool = True,
) -> Table:
    """Measure the shapes of every object in FITS images: images in, catalogue out.

    Parameters
    ----------
    images : str or list of str
        FITS images (background need not be subtracted). A ``WEIGHT`` HDU (inverse
        variance) and a ``MASK`` HDU (non-zero = bad) in the same file are used if present.
    stars : list of str, optional
        Separate star-field images; their PSFs are co-added with each image's own
        (``Config.psf_model = "polynomial"``: the polynomial model of the most stars is
        used).
    psf : PSFResult, PSFModel, numpy.ndarray or str, or a list of them, optional
        The PSF instead of stars: an image (pixel response included, centred on
        ``[n//2, n//2]``) or its file, a :class:`~pylensfit.psfmodel.PSFModel` (a PSF
        over the field, each galaxy fitted with it at its position as
        ``Config.psf_interpolation`` says) or a file :func:`~pylensfit.psfmodel.read_psf_model`
        reads (a Piff model); one for every image or one per image.
    weights, masks : list of str, optional
        Weight and mask files, one per image (``None`` entries allowed).
    catalogues : list of str, optional
        Input catalogues (FITS or any astropy-readable table with ``x, y`` 0-based or
        ``X_IMAGE, Y_IMAGE`` 1-based), one per image, instead of detection.
    star_column : str, optional
        Column of the detection / input catalogue that marks the PSF stars (overrides
        the stellar-locus selection).
    config : Config, optional
        Settings (default ``Config()``, the recommended method).
    prior : Prior or str, optional
        An ellipticity prior (or the path of a saved one) to keep instead of estimating
        it; the other priors are still estimated.
    size_prior : SizePrior or str, optional
        A size prior (or the path of a saved one, :meth:`pylensfit.prior.SizePrior.save`)
        to keep instead of estimating it.
    priors : Priors or str, optional
        Every prior, as :func:`pylensfit.calibrate` or an earlier run gives them (or the
        path of a saved :class:`~pylensfit.Priors`): the images are measured once, under
        them. Without it the calibration recipe (:mod:`pylensfit.calibration`) estimates
        them from the run's own galaxies: passes over the images with the starting
        priors, then under the flux and position priors estimated, then under the size
        prior (with the default configuration three passes; the last is the
        measurement). The catalogue keeps them (``meta["priors"]``, HDU ``PRIORS``).
    output : str, optional
        Catalogue path (FITS). With an output, finished images are kept in
        ``<output>.parts/`` until the catalogue is written, and a restarted run resumes.
    psf_dir : str, optional
        Write each image's PSF here as ``<image stem>.psf.fits`` (the image, its size and
        ellipticity in the header, and a ``STARS`` table of every star candidate: used or
        rejected, and why; :meth:`pylensfit.psf.PSFResult.write`). With a dask scheduler
        the workers write it, so the folder must be shared with them.
    overwrite : bool
        Replace an existing output.
    jobs : int
        Local worker processes (one BLAS / numba thread each); 1 runs in this process.
    scheduler : str, optional
        Address of a dask.distributed scheduler to run the images on instead.
    progress : bool
        Show a progress bar.

    Returns
    -------
    astropy.table.Table
        The catalogue (columns: :data:`pylensfit.catalogue.COLUMNS`), with the
        ``(n, n_e)`` ``lnL`` grids as a 2-D column and ``meta`` holding the ellipticity
        grid, the prior and the per-image PSF diagnostics.

    Raises
    ------
    InputError
        A missing, unreadable or truncated file, an image given twice, an empty image, an
        empty input catalogue, a star field without usable stars: one line naming the
        file and the problem. Every image, weight map, mask and star field is opened
        (its headers read) before any work starts.
    """
    cfg = config if config is not None else Config()
    inp = _measure_inputs(images, stars, weights, masks, catalogues, psf, prior, size_prior,
                          priors, output, overwrite)  # fmt: skip
    if psf_dir is not None:
        Path(psf_dir).mkdir(parents=True, exist_ok=True)
    parts = inp.parts
    # one set of workers for every pass; a run failing before it has written a part
    # leaves no empty <output>.parts/
    with worker_pool(jobs, scheduler) as pool, _parts_dropped_if_unused(parts):
        # star fields first: their PSFs go to every image
        star_psfs = []
        st_tasks = [_StarfieldTask(path=p, index=i, config=cfg) for i, p in enumerate(inp.stars)]
        for _, res in run_tasks(_starfield_task, st_tasks, jobs, scheduler, "star fields",
                                progress, pool):  # fmt: skip
            star_psfs.append(res)
        star_psfs.sort(key=lambda r: inp.stars.index(r.source))
        tasks = [
            _ImageTask(path=p, index=i, config=cfg, weight=w, mask=m, catalogue=c,
                       star_psfs=tuple(star_psfs), star_column=star_column,
                       psf_dir=None if psf_dir is None else str(psf_dir),
                       psf=None if inp.psfs is None else inp.psfs[i])
            for i, (p, w, m, c) in enumerate(zip(inp.images, inp.weights, inp.masks,
                                                 inp.catalogues, strict=True))
        ]  # fmt: skip
        pr_file = parts / "priors.json" if parts is not None else None
        last = _LastPass()
        priors = inp.priors
        if priors is None and pr_file is not None and pr_file.exists():
            priors = Priors.load(pr_file)  # a resumed run keeps its priors
            log.info("priors of the interrupted run read from %s", pr_file)
        if priors is None:
            priors = _calibrate_images(tasks, cfg, inp.prior, inp.size_prior, jobs, scheduler,
                                       progress, pool, last, parts)  # fmt: skip
        results = _measure_pass(tasks, cfg, priors, last, parts, pr_file, jobs, scheduler,
                                progress, pool)  # fmt: skip
    cat = _assemble([results[i] for i in range(len(tasks))], cfg, priors)
    if inp.out is not None:
        write_catalogue(cat, inp.out, overwrite=overwrite)
        shutil.rmtree(parts, ignore_errors=True)
    return cat


@dataclass
class _MeasureInputs:
    """:func:`measure`'s inputs, checked: paths as strings, one entry per image."""

    images: list[str]
    stars: list[str]
    weights: list
    masks: list
    catalogues: list
    psfs: list[PSFResult | PSFModel] | None  # given PSFs, one per image
    prior: Prior | None
    size_prior: SizePrior | None
    priors: Priors | None
    out: Path | None  # the catalogue
    parts: Path | None  # the finished images' folder, ``<output>.parts/``


def _measure_inputs(images, stars, weights, masks, catalogues, psf, prior, size_prior,
                    priors, output, overwrite: bool) -> _MeasureInputs:  # fmt: skip
    """Check :func:`measure`'s inputs (every file opened) before any work starts."""
    if isinstance(images, (str, os.PathLike)):
        images = [images]
    images = [str(p) for p in images]
    if not images:
        raise InputError("no input image")
    stars = [str(p) for p in (stars or [])]
    given_psfs = _given_psfs(psf, images)
    if given_psfs is not None and stars:
        raise InputError("give the PSF (psf=) or star fields to build it from (stars=), not both")
    weights = _as_list(weights, len(images), "weights")
    masks = _as_list(masks, len(images), "masks")
    catalogues = _as_list(catalogues, len(images), "catalogues")
    for p in [*images, *stars, *[q for q in (*weights, *masks, *catalogues) if q]]:
        if not Path(p).exists():
            raise InputError(f"{p}: file not found")
    _check_inputs(images, weights, masks, stars)
    prior = _load(prior, Prior, "prior")
    priors = _load(priors, Priors, "priors")
    size_prior = _load(size_prior, SizePrior, "size prior")
    out = Path(output) if output is not None else None
    if out is not None and out.exists() and not overwrite:
        raise FileExistsError(f"{out}: output exists (use overwrite to replace it)")
    parts = out.with_name(out.name + ".parts") if out is not None else None
    if out is not None:
        _remove_stale_temporaries(out, parts)
    return _MeasureInputs(images=images, stars=stars, weights=weights, masks=masks,
                          catalogues=catalogues, psfs=given_psfs, prior=prior,
                          size_prior=size_prior, priors=priors, out=out, parts=parts)


@dataclass
class _LastPass:
    """The calibration recipe's last pass over the images (:func:`_calibrate_images`),
    kept for :func:`_measure_pass`: its key (:func:`_pass_key`) and its results."""

    key: str | None = None
    results: dict[int, ImageResult] = field(default_factory=dict)

    def clear(self) -> None:
        """Forget the pass (its results' memory freed)."""
        self.key, self.results = None, {}


def _measure_pass(tasks: list[_ImageTask], cfg: Config, priors: Priors, last: _LastPass,
                  parts: Path | None, pr_file: Path | None, jobs: int, scheduler: str | None,
                  progress: bool, pool) -> dict[int, ImageResult]:  # fmt: skip
    """The measurement: every image under ``priors``, the recipe's last pass reused where
    it was made under them, finished images kept in ``parts`` (a resumed run reads them).
    """
    results: dict[int, ImageResult] = {}
    run_cfg = priors.apply(cfg)
    final = [replace(t, config=run_cfg, size_prior=priors.size) for t in tasks]
    if last.key == _pass_key(run_cfg, priors.size, False):
        results = dict(last.results)  # the recipe's last pass is the measurement
    last.clear()
    if parts is not None:
        parts.mkdir(parents=True, exist_ok=True)
        priors.save(pr_file)
    for t in final:
        if t.index in results and parts is not None:
            pp = _part_path(parts, t)
            if not pp.exists():
                _write_part(pp, results[t.index])
    todo = _resumed([t for t in final if t.index not in results], parts, results)
    for t, res in run_tasks(_image_task, todo, jobs, scheduler, "images", progress, pool,
                            objects=True):
        if parts is not None:
            _write_part(_part_path(parts, t), res)
        results[t.index] = res
        log.info("%s: %d objects, %s", t.path, len(res),
                 ", ".join(f"{k} {v:.2f} s" for k, v in res.timing.items()))  # fmt: skip
    return results


def _resumed(tasks: list[_ImageTask], parts: Path | None, results: dict,
             ) -> list[_ImageTask]:  # fmt: skip
    """The tasks still to do: those of ``tasks`` whose part file in ``parts`` is read into
    ``results`` are not (a damaged part is redone)."""
    if parts is None:
        return list(tasks)
    todo = []
    for t in tasks:
        pp = _part_path(parts, t)
        if pp.exists():
            try:
                results[t.index] = _read_part(pp)
                log.info("%s: resumed from %s", t.path, pp)
                continue
            except Exception as err:  # a damaged part is redone
                log.warning("%s: unreadable part file %s (%s); redoing", t.path, pp, err)
        todo.append(t)
    return todo


def _load(obj, cls, what: str):
    """``obj`` as it is, or read with ``cls.load`` if a path: one line naming the file if
    it is missing or not a ``what`` file."""
    if not isinstance(obj, (str, os.PathLike)):
        return obj
    if not Path(obj).exists():
        raise InputError(f"{obj}: file not found")
    try:
        return cls.load(obj)
    except (ValueError, KeyError, TypeError, AttributeError) as err:
        msg = str(err)
        raise InputError(msg if msg.startswith(str(obj)) else
                         f"{obj}: not a {what} file ({type(err).__name__}: {msg})") from None


def _pass_key(cfg: Config, size_prior: SizePrior | None, keep) -> str:
    """What identifies a fitting pass over the images: its settings and size prior."""
    sp = None if size_prior is None else size_prior.to_dict()
    return json.dumps([cfg.to_dict(), sp, keep], sort_keys=True, default=str)


def _calibrate_images(tasks: list[_ImageTask], cfg: Config, prior: Prior | None,
                      size_prior: SizePrior | None, jobs: int, scheduler: str | None,
                      progress: bool, pool, last: _LastPass,
                      parts: Path | None = None) -> Priors:  # fmt: skip
    """The calibration recipe (:func:`pylensfit.calibration.run_recipe`) on the images.

    Each pass measures every image (detection, PSF, neighbours and sky included) and hands
    the recipe its usable galaxies (:func:`pylensfit.calibration.usable_galaxies`); the
    last pass's results stay in ``last`` so that, when the measurement's settings are
    those of the last pass, it is not done again. With ``parts``, the images of every
    pass that keeps no ``L(r)`` are written there as they finish and read back by a
    resumed run.
    """

    def fit_pass(cfgs, sps, keep, label):
        keep_r = "annuli" if keep else False
        run = [replace(t, config=cfgs[0], keep_lnL_r=keep_r,
                       psf_dir=t.psf_dir if not keep else None, size_prior=sps[0])
               for t in tasks]  # fmt: skip
        results, samples = {}, []
        todo = run
        if parts is not None and not keep:
            parts.mkdir(parents=True, exist_ok=True)
            todo = _resumed(run, parts, results)
        for t, res in run_tasks(_image_task, todo, jobs, scheduler, label, progress, pool,
                            objects=True):
            if parts is not None and not keep:
                _write_part(_part_path(parts, t), res)
            results[t.index] = res
        for i in range(len(tasks)):
            res = results[i]
            rows = res.rows
            ok = (usable_galaxies(rows["flags"], rows["fitclass"] != FITCLASS["galaxy"],
                                  rows["model_SNratio"], cfgs[0].min_snr)
                  & np.isfinite(res.lnL).all(axis=1))  # fmt: skip
            flux = np.asarray(rows["model_flux"], dtype=float)
            samples.append(CalibrationSample(
                egrid=res.egrid, lnL=res.lnL[ok], flux=flux[ok],
                flux_err=(flux / np.asarray(rows["model_SNratio"], dtype=float))[ok],
                snr=np.asarray(rows["model_SNratio"], dtype=float)[ok],
                dx=(rows["x"] - rows["x_detect"])[ok], dy=(rows["y"] - rows["y_detect"])[ok],
                group=np.zeros(int(ok.sum()), dtype=int),
                lnL_bulge=None if res.lnL_bulge is None else res.lnL_bulge[ok],
                lnL_star=rows["lnL_star"][ok] if "lnL_star" in rows else None,
                lnL_r_grouped=[res.lnL_r[ok]] if keep else None))  # fmt: skip
            if keep:  # the sample holds what the recipe needs
                results[i] = replace(res, lnL_r=None)
        last.clear()
        if not keep:
            last.key, last.results = _pass_key(cfgs[0], sps[0], False), results
        sample = CalibrationSample.concatenate(samples)
        log.info("%s: %d usable galaxies", label, len(sample))
        return sample

    return run_recipe(fit_pass, cfg, 1, prior=prior,
                      size_priors=None if size_prior is None else [size_prior])[0]


def _given_psfs(psf, images: list[str]) -> list[PSFResult | PSFModel] | None:
    """``measure``'s ``psf=`` as one :class:`PSFResult` (a constant PSF) or
    :class:`~pylensfit.psfmodel.PSFModel` (a PSF over the field, e.g. Piff's) per image
    (``None``: not given)."""
    if psf is None:
        return None
    single = isinstance(psf, (PSFResult, PSFModel, str, os.PathLike)) or (
        isinstance(psf, np.ndarray) and psf.ndim == 2)
    items = [psf] * len(images) if single else list(psf)
    if len(items) != len(images):
        raise InputError(f"psf: {len(items)} PSF(s) given for {len(images)} image(s)")
    out, cache = [], {}
    for item, img in zip(items, images, strict=True):
        if isinstance(item, ConstantPSF):
            item = item.psf
        if isinstance(item, (PSFResult, PSFModel)):
            out.append(item)
            continue
        key = str(item) if isinstance(item, (str, os.PathLike)) else id(item)
        if key not in cache:
            try:
                if isinstance(item, (str, os.PathLike)):
                    if not Path(item).exists():
                        raise InputError(f"{item}: PSF file not found")
                    model = read_psf_model(item)
                    cache[key] = model.psf if isinstance(model, ConstantPSF) else model
                else:
                    cache[key] = psf_from_image(item, source="psf=")
            except (PSFError, ImportError) as err:  # ImportError: piff not installed
                raise InputError(f"the PSF for {img}: {err}") from None
        out.append(cache[key])
    return out


def _assemble(results: list[ImageResult], cfg: Config, priors: Priors) -> Table:
    """Concatenate the images, add the Bayesian shapes under the priors
    (:func:`pylensfit.assemble.assemble`, as :func:`pylensfit.measure_stamps` does)."""
    egrid = results[0].egrid
    tabs = [Table(r.rows) for r in results]
    cat = vstack(tabs, metadata_conflicts="silent") if tabs else Table()
    lnL = np.concatenate([r.lnL for r in results], axis=0)
    lnL_bulge = None
    if all(r.lnL_bulge is not None for r in results):
        lnL_bulge = np.concatenate([r.lnL_bulge for r in results], axis=0)
    n = len(cat)
    cat.add_column(np.arange(1, n + 1, dtype=np.int64), name="id", index=0)
    psf_sigma = np.concatenate([np.full(len(r), np.nan if r.psf is None else r.psf.sigma)
                                for r in results]) if results else np.zeros(0)  # fmt: skip
    ctx = ObjectContext(
        flags=np.asarray(cat["flags"], dtype=np.int32),
        not_galaxy=np.asarray(cat["fitclass"]) != FITCLASS["galaxy"],
        model_SNratio=np.asarray(cat["model_SNratio"], dtype=float),
        model_flux=np.asarray(cat["model_flux"], dtype=float),
        scalelength=np.asarray(cat["scalelength"], dtype=float),
        noise_sigma=np.asarray(cat["noise_sigma"], dtype=float), psf_sigma=psf_sigma,
        frame=catalogue_frame(cat))  # fmt: skip
    out = assemble(lnL, egrid, priors, cfg, ctx, lnL_bulge=lnL_bulge,
                   lnL_star=cat["lnL_star"] if lnL_bulge is not None else None,
                   flagged="blank")  # fmt: skip
    for c, v in out.columns.items():
        cat[c] = v
    _psf_to_sky(cat, ctx.frame)
    cat["lnL"] = out.lnL
    if lnL_bulge is not None:
        cat["lnL_bulge"] = lnL_bulge
    order = [c for c in COLUMNS if c in cat.colnames]
    cat = cat[order + [c for c in cat.colnames if c not in order]]
    for c in cat.colnames:
        if c in COLUMNS:
            unit, desc = COLUMNS[c]
            cat[c].description = desc
            if unit:
                cat[c].unit = unit
    psfs = Table()
    psfs["image"] = [os.path.basename(r.path) for r in results]
    for k in _PSF_KEYS + _HELDOUT_KEYS:
        psfs[f"psf_{k}"] = [np.nan if r.psf is None else r.psf.get(k) for r in results]
    psfs["psf_source"] = [r.psf_source for r in results]
    psfs["note"] = [r.psf_note for r in results]
    cat.meta["egrid"] = egrid
    cat.meta["prior"] = priors.ellipticity
    cat.meta["priors"] = priors
    cat.meta["size_prior"] = priors.size
    cat.meta["refine"] = int(cfg.output_refine)
    if lnL_bulge is not None:
        cat.meta["bulge_fractions"] = np.array([run.bulge_fraction for run in cfg.bulge_runs])
        if cfg.bulge_size_ratio2 > 0 or cfg.sersic_ladder:
            cat.meta["bulge_sizes"] = np.array([run.size for run in cfg.bulge_runs])
            cat.meta["runs"] = cfg.run_labels
        cat.meta["bulge_weights"] = priors.bulge_weights
    cat.meta["psfs"] = psfs
    # each image's PSF (zeros where it failed), on the largest PSF image's side
    side = max([cfg.stamp_size, *(max(np.shape(r.psf.image)) for r in results
                                  if r.psf is not None)])  # fmt: skip
    cat.meta["psf_images"] = np.array([
        np.zeros((side, side)) if r.psf is None
        else centre_on_stamp(r.psf.image, side) for r in results])  # fmt: skip
    cat.meta["config"] = cfg
    cat.meta["timing"] = {k: float(sum(r.timing[k] for r in results))
                          for k in results[0].timing}  # fmt: skip
    return cat


def catalogue_frame(cat: Table) -> SkyFrame:
    """The sky frame of each row of a :func:`measure` catalogue (its ``sky_angle``,
    ``sky_flip``, ``wcs_g1``, ``wcs_g2`` columns; the pixel frame where it has none)."""
    return frame_of_table(cat)


def _psf_to_sky(cat: Table, frame: SkyFrame) -> None:
    """The PSF's ellipticity from the pixel frame to the sky frame (where
    :func:`pylensfit.assemble.assemble` turned the shapes), and the catalogue's frame in
    ``meta["frame"]``."""
    cat["PSF_e1"], cat["PSF_e2"] = to_sky(cat["PSF_e1"], cat["PSF_e2"], frame)
    cat.meta["frame"] = ("sky" if frame.has_wcs.all() and frame.n else
                         "pixel" if not frame.has_wcs.any() else "mixed")  # fmt: skip


# ----------------------------------------------------------------------------------------
# Catalogue files
# ----------------------------------------------------------------------------------------
def _card(header, key: str, value: str, comment: str) -> None:
    """A string card, its comment left out where the value needs the card's room (a long
    value continues on CONTINUE cards)."""
    header[key] = (value, comment) if len(value) + len(comment) < 64 else value


def write_catalogue(cat: Table, path: str | os.PathLike, *, overwrite: bool = False) -> None:
    """Write a catalogue from :func:`measure` as FITS (see :mod:`pylensfit.catalogue`)."""
    plain = cat.copy(copy_data=False)
    lnL = np.asarray(plain["lnL"], dtype=np.float32)
    plain.remove_column("lnL")
    lnL_bulge = None
    if "lnL_bulge" in plain.colnames:
        lnL_bulge = np.asarray(plain["lnL_bulge"], dtype=np.float32)
        plain.remove_column("lnL_bulge")
    plain.meta.clear()
    for c in plain.colnames:  # documented in the COLUMNS HDU (FITS comments are too short)
        plain[c].description = None
    prior = cat.meta.get("prior")
    cfg = cat.meta.get("config")
    hdr = fits.Header()
    hdr["PLFVERS"] = (__version__, "pylensfit version")
    hdr["DATE"] = (datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                   "UTC time the catalogue was written")  # fmt: skip
    hdr["NOBJ"] = (len(cat), "objects (rows)")
    if prior is not None:
        for key, value, comment in prior.header_cards():
            hdr[key] = (value, comment)
        hdr["PRIORMTH"] = (prior.method, "how the prior was obtained")
    if cfg is not None:
        hdr["SENSTVTY"] = (cfg.sensitivity, "shear sensitivity formula")
        hdr["MODEL"] = (cfg.model, "galaxy model")
    frame = cat.meta.get("frame", "pixel")
    hdr["EFRAME"] = (frame, "frame of e1,e2: sky (W,N), pixel, mixed")
    hdr.extend(flag_cards())  # one card per bit (pylensfit.catalogue)
    hdr.add_comment("FLAGn: the name of the flags column's bit of value n")
    tab = fits.table_to_hdu(plain)
    tab.name = "CATALOG"
    hdus = [fits.PrimaryHDU(header=hdr), tab, fits.ImageHDU(lnL, name="LNL"),
            fits.ImageHDU(np.asarray(cat.meta["egrid"]), name="EGRID")]  # fmt: skip
    if lnL_bulge is not None:
        hb = fits.ImageHDU(lnL_bulge, name="LNLB")
        _card(hb.header, "BULGEFR", ",".join(f"{f:g}" for f in cat.meta["bulge_fractions"]),
              "bulge fractions of the LNLB planes")  # fmt: skip
        if cat.meta.get("bulge_sizes") is not None:
            _card(hb.header, "BULGESZ", ",".join(f"{f:g}" for f in cat.meta["bulge_sizes"]),
                  "bulge sizes (disc scale lengths)")  # fmt: skip
        if cat.meta.get("runs") is not None:
            _card(hb.header, "RUNS", ";".join(cat.meta["runs"]), "each plane's profile")
        w = cat.meta.get("bulge_weights")
        if w is not None:
            _card(hb.header, "BULGEW", ",".join(f"{v:.6g}" for v in w),
                  "their estimated prior weights")
        hdus.append(hb)
    sp = cat.meta.get("size_prior")
    if sp is not None:
        # one row per knot; a prior per run of the family has a density vector per row
        hs = fits.table_to_hdu(Table({"ln_h": sp.ln_h, "density": np.asarray(sp.density).T}))
        hs.name = "SIZEPRI"
        hs.header["STAR"] = (sp.star, "prior probability of a point source")
        if sp.smoothing is not None:
            hs.header["SMOOTH"] = (sp.smoothing, "EMS smoothing of the estimate")
        hdus.append(hs)
    pr = cat.meta.get("priors")
    if pr is not None:  # every prior of the measurement, as Priors.save writes them
        hp = fits.BinTableHDU(Table({"json": [json.dumps(pr.to_dict())]}))
        hp.name = "PRIORS"
        hdus.append(hp)
    if "psfs" in cat.meta:
        p = fits.table_to_hdu(cat.meta["psfs"])
        p.name = "PSFS"
        hdus += [p, fits.ImageHDU(np.asarray(cat.meta["psf_images"], dtype=np.float32),
                                  name="PSFIMG")]  # fmt: skip
    if cfg is not None:
        d = cfg.to_dict()
        c = fits.BinTableHDU(Table({"key": list(d), "value": [json.dumps(v) for v in d.values()]}))
        c.name = "CONFIG"
        hdus.append(c)
    doc = fits.table_to_hdu(column_table())
    doc.name = "COLUMNS"
    hdus.append(doc)
    atomic_write(fits.HDUList(hdus), path, overwrite=overwrite)


def _header_prior(hdr, egrid: np.ndarray) -> Prior | SplinePrior:
    """The ellipticity prior of a catalogue's primary header (its ``PRIORFRM`` form)."""
    method = hdr.get("PRIORMTH", "fixed")
    if hdr.get("PRIORFRM") == SplinePrior.form:
        n = len(SplinePrior().coef)
        return SplinePrior(coef=[hdr[f"PRIORS{j}"] for j in range(n)], egrid=egrid,
                           method=method)  # fmt: skip
    return Prior(B=hdr["PRIOR_B"], C=hdr["PRIOR_C"], D=hdr["PRIOR_D"], egrid=egrid,
                 method=method)  # fmt: skip


def read_catalogue(path: str | os.PathLike) -> Table:
    """Read a catalogue written by :func:`write_catalogue` (``lnL`` as a 2-D column).

    Raises
    ------
    InputError
        One line naming the file: not a pylensfit catalogue (an HDU missing, ``LNL`` and
        ``EGRID`` of inconsistent shapes) or a header card or HDU that cannot be read.
    """
    with _open(str(path), "catalogue") as h:
        for need in ("CATALOG", "LNL", "EGRID"):
            if need not in h:
                raise InputError(f"{path}: not a pylensfit catalogue (no {need} HDU)")
        hdu = "CATALOG"  # the HDU being read, for the message
        try:
            cat = Table(h["CATALOG"].data)
            hdu = "LNL"
            lnL = np.array(h["LNL"].data, dtype=np.float32)
            hdu = "EGRID"
            egrid = np.array(h["EGRID"].data, dtype=float)
            if lnL.ndim != 2 or lnL.shape[0] != len(cat):
                raise InputError(f"{path}: LNL has shape {lnL.shape} for {len(cat)} objects "
                                 "(one row of ln L per object)")  # fmt: skip
            if egrid.shape != (lnL.shape[1], 2) or not np.isfinite(egrid).all():
                raise InputError(f"{path}: EGRID has shape {egrid.shape}; LNL's "
                                 f"{lnL.shape[1]} columns need ({lnL.shape[1]}, 2) finite "
                                 "ellipticities")  # fmt: skip
            cat["lnL"] = lnL
            cat.meta["egrid"] = egrid
            if "LNLB" in h:
                hdu = "LNLB"
                hb = h["LNLB"]
                cat["lnL_bulge"] = np.array(hb.data, dtype=np.float32)
                cat.meta["bulge_fractions"] = np.array(hb.header["BULGEFR"].split(","), float)
                if "BULGESZ" in hb.header:
                    cat.meta["bulge_sizes"] = np.array(hb.header["BULGESZ"].split(","), float)
                if "RUNS" in hb.header:
                    cat.meta["runs"] = hb.header["RUNS"].split(";")
                w = hb.header.get("BULGEW")
                cat.meta["bulge_weights"] = None if w is None else np.array(w.split(","), float)
            hdu = "PRIMARY"
            hdr = h[0].header
            cat.meta["frame"] = str(hdr.get("EFRAME", "pixel"))
            if "PRIOR_B" in hdr or hdr.get("PRIORFRM") == SplinePrior.form:
                cat.meta["prior"] = _header_prior(hdr, cat.meta["egrid"])
            if "SIZEPRI" in h:
                hdu = "SIZEPRI"
                hs = h["SIZEPRI"]
                cat.meta["size_prior"] = SizePrior(ln_h=np.array(hs.data["ln_h"], dtype=float),
                                                   density=np.array(hs.data["density"], float).T,
                                                   star=float(hs.header["STAR"]),
                                                   smoothing=hs.header.get("SMOOTH"))  # fmt: skip
            if "PRIORS" in h:
                try:
                    cat.meta["priors"] = Priors.from_dict(
                        json.loads(str(h["PRIORS"].data["json"][0])), source=f"{path} PRIORS")
                except ValueError as err:
                    log.warning("%s: the PRIORS HDU cannot be read (%s); left out", path, err)
            if "PSFS" in h:
                hdu = "PSFS"
                cat.meta["psfs"] = Table(h["PSFS"].data)
            if "PSFIMG" in h:
                hdu = "PSFIMG"
                cat.meta["psf_images"] = np.array(h["PSFIMG"].data, dtype=float)
            if "CONFIG" in h:
                hdu = "CONFIG"
                t = h["CONFIG"].data
                vals = {str(k): json.loads(str(v))
                        for k, v in zip(t["key"], t["value"], strict=True)}  # fmt: skip
                known = set(Config.describe())
                extra = sorted(set(vals) - known)
                if extra:  # written by another version: read what this one knows
                    log.warning("%s: configuration key(s) %s unknown to this version are left "
                                "out", path, extra)  # fmt: skip
                try:
                    cat.meta["config"] = Config.from_dict({k: v for k, v in vals.items()
                                                           if k in known})  # fmt: skip
                except ValueError as err:
                    log.warning("%s: its configuration cannot be read (%s); left out", path,
                                err)  # fmt: skip
        except InputError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as err:
            msg = err.args[0] if isinstance(err, KeyError) and err.args else err
            raise InputError(f"{path}: cannot read HDU {hdu} ({type(err).__name__}: "
                             f"{msg})") from None  # fmt: skip
    return cat
