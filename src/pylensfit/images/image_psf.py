"""An image's PSF: its stars, the star fields' PSFs, the polynomial model over the field
and the PSF cells.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from astropy.table import Table

from ..config import Config
from ..detection import select_stars
from ..psf import PSFError, PSFResult, combine_psfs, stack_psf
from ..psfmodel import PolynomialPSF, PSFModel, n_terms
from ..runner import single_thread
from .inputs import Image, InputError, detect_objects, mask_saturated, read_image
from .records import ImageTask, StarfieldTask

__all__ = [
    "PSF_SUSPECT_CHI2",
    "PSF_SUSPECT_PVALUE",
    "CellPSFs",
    "cell_psfs",
    "starfield_task",
    "image_psf",
    "psf_source_of",
]

# the pipeline's one logger: its name predates the split into modules
log = logging.getLogger("pylensfit.pipeline")


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


def _psf_stars(img: Image, det: Table, cfg: Config, star_col) -> np.ndarray:
    """The detections selected as PSF stars; ``PSFError`` if fewer than psf_min_stars."""
    stars = select_stars(det, min_peak_snr=cfg.star_min_peak_snr, column=star_col)
    if stars.sum() < cfg.psf_min_stars:
        raise PSFError(f"{img.path}: {int(stars.sum())} star(s) pass the selection "
                       f"(peak S/N > {cfg.star_min_peak_snr:g}), fewer than "
                       f"psf_min_stars = {cfg.psf_min_stars}")  # fmt: skip
    return stars


def _psf_from_stars(sub: np.ndarray, img: Image, det: Table, cfg: Config, star_col):
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


def _poly_from_stars(sub: np.ndarray, img: Image, det: Table, cfg: Config, star_col):
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


def _n_selected(img: Image, det: Table, cfg: Config, star_col) -> int:
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


def _varying_from_stars(sub: np.ndarray, img: Image, det: Table, cfg: Config, star_col):
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
class CellPSFs:
    """A PSF varying over an image, sampled for the fits of its objects.

    With ``Config.psf_interpolation = "centre"`` the PSF at the centre of each of the
    ``psf_cells x psf_cells`` cells, each object fitted with its cell's; with
    ``"bilinear"`` the PSF at the cells' corners, each object fitted with its cell's
    four and the fits blended with the bilinear weights of its position
    (:func:`pylensfit.likelihood.blend_fits`); with ``"fourier"`` the same corners and
    weights, each object fitted once with its cell's four PSFs mixed by its weights
    (:class:`pylensfit.likelihood.MixedPSF`).
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


def cell_psfs(model: PSFModel, shape: tuple[int, int], cells: int, x: np.ndarray,
               y: np.ndarray, bilinear: bool) -> CellPSFs:  # fmt: skip
    """The PSF model sampled at the centres (or, ``bilinear``, the corners: for
    ``psf_interpolation`` "bilinear" and "fourier") of ``cells x cells`` cells of an
    image of ``shape``, for objects at pixels ``x, y``."""
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
    return CellPSFs(images=images, e=np.vstack([e1, e2]), cell=cell, nodes=nodes,
                     weights=weights)  # fmt: skip


def starfield_task(task: StarfieldTask) -> PSFResult | PSFModel:
    """The PSF of a separate star-field image."""
    single_thread(task.single_thread)
    cfg = task.config
    img = read_image(task.path)
    mask_saturated(img, cfg)
    sub, det, _ = detect_objects(img, cfg, None)
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


def image_psf(task: ImageTask, cfg: Config, img: Image, sub: np.ndarray, det: Table,
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


def psf_source_of(task: ImageTask, psf: PSFResult | None, field_model: PSFModel | None,
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
