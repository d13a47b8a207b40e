"""Neighbour subtraction: the neighbours' models taken out of each stamp (method, not
plumbing).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from .. import flags as _flags
from ..config import Config
from ..exposures import cut_stamps as cut_exposure_stamps
from ..grid import refine_lnL
from ..models import render_models
from ..stamps import add_patches, cut_stamps, patch_origins

__all__ = [
    "NeighbourScene",
    "subtract_neighbours",
    "implausible_models",
    "neighbour_light",
    "SkyModels",
    "sky_models",
    "exposure_light",
    "exposure_neighbour_stamps",
]


_MODEL_KEYS = ("flux", "x", "y", "is_star", "r_best", "lnL", "bulge_best", "flags", "stamp")


@dataclass
class NeighbourScene:
    """The objects of one image as :func:`subtract_neighbours` sees them.

    Attributes
    ----------
    shape : tuple of int
        Image shape ``(ny, nx)``.
    x, y : numpy.ndarray
        Every object's stamp position (the stamps' centres), pixels.
    xf, yf : numpy.ndarray
        Every object's fitted position, pixels; the ``store`` of
        :func:`subtract_neighbours` updates them in place.
    noise : numpy.ndarray
        Every object's noise sigma (data units).
    fitted : numpy.ndarray
        Indices of the objects fitted, in the order of the first fits.
    psf : numpy.ndarray or tuple
        PSF image, or ``(images, cell)``: ``(n_cells, N, N)`` PSF images and each
        object's cell (``(n_objects,)``), every model rendered with its cell's PSF.
    data : numpy.ndarray, optional
        ``(n, N, N)`` every object's stamp as the fits saw it (``N =
        cfg.largest_stamp``): with it, every round first judges the current models
        (:func:`implausible_models`). The objects whose models do not fit their stamps
        (a defect: a saturated star, a bleed trail, a hot pixel) are suspects: their
        models are rendered neither into the others' stamps nor into the sky's field,
        and they are fitted again with the others' light taken out; a suspect whose new
        fit describes its stamp is cleared (a first fit spoiled by a bright neighbour),
        the others are ``DEFECT``. After the last round the suspects' last fits are
        judged once more.
    """

    shape: tuple[int, int]
    x: np.ndarray
    y: np.ndarray
    xf: np.ndarray
    yf: np.ndarray
    noise: np.ndarray
    fitted: np.ndarray
    psf: np.ndarray | tuple | None
    data: np.ndarray | None = None


def subtract_neighbours(scene: NeighbourScene, first, cfg: Config, refit: Callable,
                        store: Callable, *, sky: Callable | None = None,
                        ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Fit galaxies again with their neighbours' best-fit models taken out of the stamps.

    ``cfg.neighbour_iterations`` rounds: each renders every fitted object's current model
    (:func:`neighbour_light`) and refits the galaxies of the first fit (``flags == 0``)
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
    scene : NeighbourScene
        The image's objects, their fitted positions, PSF and stamps.
    first : StampFits
        The first fits of ``scene.fitted``.
    cfg : Config
    refit : callable
        ``refit(idx, others)`` fits the stamps of objects ``idx`` less ``others``.
    store : callable
        ``store(fits, idx)`` records the fits of objects ``idx`` (and updates
        ``scene.xf, scene.yf``).
    sky : callable, optional
        ``sky(field) -> (ny, nx)``: the change of the background when it is measured on
        the image less ``field``, the rendered models of all fitted objects.

    Returns
    -------
    done : numpy.ndarray
        Indices of the objects whose neighbours' light was taken out (a subset of those
        fitted again when ``sky`` is given).
    defect : numpy.ndarray
        Boolean, one per ``scene.fitted``: the objects whose best model does not fit
        their stamp (none without ``scene.data``).
    """
    rounds = _Rounds(scene, first, cfg)
    fitted = scene.fitted
    ok = first.flags == 0
    done = np.zeros(0, dtype=np.int64)
    refitted = np.zeros(fitted.size, dtype=bool)  # in the last round
    for _ in range(int(cfg.neighbour_iterations)):
        less, near, go = rounds.light_to_take_out(sky)
        sel = np.flatnonzero(ok & (go | rounds.suspect))
        refitted[:] = False
        if sel.size == 0:
            break
        idx = fitted[sel]
        f2 = refit(idx, less[idx])
        store(f2, idx)
        rounds.update(sel, f2)
        refitted[sel] = True
        done = np.union1d(done, fitted[ok & near])
    if scene.data is not None and (rounds.suspect & refitted).any():  # the suspects' last fits
        rounds.suspect = rounds.judge(*rounds.light())
    return done, rounds.suspect


class _Rounds:
    """The state of :func:`subtract_neighbours`' rounds: the current models, the
    suspects and the sky's change."""

    def __init__(self, scene: NeighbourScene, first, cfg: Config) -> None:
        self.scene, self.cfg = scene, cfg
        self.cur = {k: np.array(getattr(first, k)) for k in _MODEL_KEYS}
        self.cur["egrid"] = first.egrid
        self.suspect = np.zeros(scene.fitted.size, dtype=bool)
        self.dsky = None

    def light(self):
        """Every fitted model's light, the suspects' into their own stamps only
        (:func:`neighbour_light`: ``others, field, own, aside``)."""
        s = self.scene
        return neighbour_light(s.shape, s.x, s.y, s.xf, s.yf, s.fitted,
                               SimpleNamespace(**self.cur), s.psf, self.cfg,
                               exclude=self.suspect, own_too=True)  # fmt: skip

    def judge(self, others, field, own, aside) -> np.ndarray:
        """The suspects: every model's light taken out, the suspects' too."""
        s = self.scene
        return implausible_models(s.data, s.fitted, s.noise, SimpleNamespace(**self.cur),
                                  self.cfg, others if aside is None else others + aside,
                                  own, self.dsky)  # fmt: skip

    def chi2(self, light: np.ndarray) -> np.ndarray:
        """The light taken out of each fitted stamp, in units of its noise (on the window
        each object was fitted on: the base stamp or a larger tier)."""
        fitted = self.scene.fitted
        out = np.empty(fitted.size)
        nl, win = light.shape[1], np.asarray(self.cur["stamp"])
        for s in np.unique(win):
            a, i = nl // 2 - int(s) // 2, np.flatnonzero(win == s)
            out[i] = np.sum(light[fitted[i], a : a + int(s), a : a + int(s)] ** 2, axis=(1, 2))
        return out / self.scene.noise[fitted] ** 2

    def light_to_take_out(self, sky: Callable | None):
        """One round's light to take out of every stamp (the neighbours' and the sky's
        change), whether the neighbours' alone exceed ``neighbour_min_chi2`` and whether
        both do; the suspects judged first."""
        s, cfg = self.scene, self.cfg
        others, field, own, aside = self.light()
        if s.data is not None:
            now = self.judge(others, field, own, aside)
            if (now != self.suspect).any():
                self.suspect = now
                others, field, own, aside = self.light()
        if not cfg.subtract_neighbours:
            others[:] = 0.0
        if sky is not None:
            self.dsky = cut_stamps(sky(field), s.x, s.y, cfg.largest_stamp)[0]
        near = self.chi2(others) > cfg.neighbour_min_chi2
        less = others if self.dsky is None else others + self.dsky
        go = near if self.dsky is None else self.chi2(less) > cfg.neighbour_min_chi2
        return less, near, go

    def update(self, sel: np.ndarray, fits) -> None:
        """The models of the fitted objects ``sel`` (positions in ``scene.fitted``)."""
        for k in _MODEL_KEYS:
            self.cur[k][sel] = getattr(fits, k)


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


def implausible_models(data, fitted, noise, f, cfg: Config, others, own,
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
        ``(n, N, N)`` :func:`neighbour_light`'s light of the other objects and each
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


def neighbour_light(shape, x, y, xf, yf, fitted, f, psf, cfg: Config, block: int = 256,
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


@dataclass(frozen=True)
class SkyModels:
    """The best-fit models of a field's objects in the sky frame (:func:`sky_models`),
    to be rendered into each exposure (:func:`exposure_light`).

    Attributes
    ----------
    ra, dec : numpy.ndarray
        ``(n,)`` fitted positions, degrees.
    e1, e2 : numpy.ndarray
        ``(n,)`` sky-frame ``(W, N)`` ellipticity: the mean of ``L(e)`` (0 for a point
        source).
    r : numpy.ndarray
        ``(n,)`` size, arcsec (0: a point source).
    flux : numpy.ndarray
        ``(n,)`` amplitude, in the common flux unit.
    bulge : numpy.ndarray
        ``(n,)`` bulge fraction.
    rendered : numpy.ndarray
        ``(n,)`` bool: the object has a model (a finite, positive flux at a finite
        position, a measured fit); the others are rendered nowhere.
    """

    ra: np.ndarray
    dec: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    r: np.ndarray
    flux: np.ndarray
    bulge: np.ndarray
    rendered: np.ndarray


def sky_models(table, ra, dec, cfg: Config) -> SkyModels:
    """The models of :func:`pylensfit.measure_exposure_stamps`' rows at the fitted sky
    positions ``ra, dec`` (degrees): as :func:`neighbour_light`'s, the size and bulge
    fraction of the most likely model (``scalelength`` in the table's reference pixels,
    ``meta["pixel_scale"]`` arcsec), its flux (``model_flux``) and the mean ellipticity
    of ``L(e)``; a point source for a ``STAR`` row. Rows flagged ``NOT_MEASURED``,
    ``FIT_FAILED`` or ``NO_PEAK`` have no model."""
    lnL = np.asarray(table["lnL"], dtype=float)
    flags = np.asarray(table["flags"], dtype=np.int64)
    none = (
        _flags.flag_value("NOT_MEASURED")
        | _flags.flag_value("FIT_FAILED")
        | _flags.flag_value("NO_PEAK")
    )
    star = (flags & _flags.flag_value("STAR")) != 0
    flux = np.asarray(table["model_flux"], dtype=float)
    ra, dec = np.asarray(ra, dtype=float), np.asarray(dec, dtype=float)
    with np.errstate(invalid="ignore"):
        rendered = (
            ((flags & none) == 0)
            & np.isfinite(lnL).all(axis=1)
            & (flux > 0)
            & np.isfinite(flux)
            & np.isfinite(ra)
            & np.isfinite(dec)
        )
    e = np.zeros((lnL.shape[0], 2))
    if rendered.any():
        e[rendered] = _likelihood_mean_e(lnL[rendered], np.asarray(table.meta["egrid"]))
    e[star] = 0.0
    r = np.nan_to_num(np.asarray(table["scalelength"], dtype=float)) * float(
        table.meta["pixel_scale"]
    )
    bulge = np.nan_to_num(np.asarray(table["bulge_best"], dtype=float), nan=cfg.bulge_fraction)
    return SkyModels(ra=ra, dec=dec, e1=e[:, 0], e2=e[:, 1], r=np.where(star, 0.0, r),
                     flux=np.where(rendered, flux, 0.0), bulge=bulge,
                     rendered=rendered)  # fmt: skip


def _canvas(cfg: Config) -> int:
    """The side of each model's canvas: :func:`neighbour_light`'s."""
    return max(4 * cfg.stamp_size, 2 * cfg.largest_stamp)


def _exposure_patches(exposure, models: SkyModels, idx: np.ndarray, cfg: Config):
    """The models ``idx`` in one exposure's pixels, each on a canvas of
    :func:`_canvas` about its position: ``(patches, bx0, by0)`` of those on the
    exposure (and ``sel``, which of ``idx`` they are)."""
    n_big = _canvas(cfg)
    at = cut_exposure_stamps(exposure, models.ra[idx], models.dec[idx], size=1)
    ny, nx = exposure.shape
    with np.errstate(invalid="ignore"):
        near = (
            (at.x > -n_big / 2)
            & (at.x < nx + n_big / 2)
            & (at.y > -n_big / 2)
            & (at.y < ny + n_big / 2)
        )
    sel = np.flatnonzero(models.rendered[idx] & near & (at.psf is not None)
                         & np.isfinite(at.jacobian).all(axis=(1, 2)))  # fmt: skip
    if at.psf is not None:
        sel = sel[np.isfinite(at.psf[sel]).all(axis=(1, 2))]
    bx0, by0 = patch_origins(at.x[sel], at.y[sel], n_big)
    j = idx[sel]
    pat = render_models(n_big, at.psf[sel], at.x[sel] - bx0, at.y[sel] - by0, models.e1[j],
                        models.e2[j], models.r[j], models.flux[j] * exposure.flux_scale,
                        model=cfg.model, bulge_fraction=models.bulge[j],
                        bulge_size_ratio=cfg.bulge_size_ratio,
                        jacobian=at.jacobian[sel])  # fmt: skip
    return pat, bx0, by0, sel


def exposure_light(exposure, models: SkyModels, cfg: Config, block: int = 256) -> np.ndarray:
    """The image of every model of ``models`` in one exposure, counts.

    Each sky-frame model is carried into the exposure's pixels by the local Jacobian of
    its WCS at the object (:func:`pylensfit.models.render_models` with ``jacobian``),
    convolved with the exposure's PSF there, scaled by its ``flux_scale`` and rendered
    on a canvas of four stamp sides about its position (:func:`neighbour_light`'s);
    the canvases are added into an image of the exposure's shape.

    Parameters
    ----------
    exposure : pylensfit.exposures.Exposure
        The exposure (its WCS, PSF and flux scale).
    models : SkyModels
        The objects' models (:func:`sky_models`).
    cfg : Config
        ``stamp_size``, ``model``, ``bulge_size_ratio``.
    block : int
        Models rendered at a time (memory: ``block`` canvases).

    Returns
    -------
    numpy.ndarray
        ``(ny, nx)`` float64.
    """
    field = np.zeros(exposure.shape)
    todo = np.flatnonzero(models.rendered)
    for s0 in range(0, todo.size, block):
        pat, bx0, by0, _ = _exposure_patches(exposure, models, todo[s0 : s0 + block], cfg)
        add_patches(field, pat, bx0, by0)
    return field


def exposure_neighbour_stamps(field: np.ndarray, view, exposure, models: SkyModels,
                              idx: np.ndarray, cfg: Config) -> np.ndarray:  # fmt: skip
    """The light of every other object in the stamps of one exposure's view.

    Parameters
    ----------
    field : numpy.ndarray
        :func:`exposure_light` of the exposure.
    view : pylensfit.exposures.ExposureStamps
        The galaxies' stamps in the exposure (their windows ``x0, y0``).
    exposure : pylensfit.exposures.Exposure
        The exposure.
    models : SkyModels
        Every object's model; galaxy ``i`` of ``view`` is model ``idx[i]``.
    idx : numpy.ndarray
        ``(n,)`` int.
    cfg : Config

    Returns
    -------
    numpy.ndarray
        ``(n, N, N)``: ``field`` on each stamp's window (0 off the image) less the
        galaxy's own model there, rendered as in ``field``.
    """
    N = view.stamps.shape[-1]
    ny, nx = field.shape
    rows = view.y0[:, None] + np.arange(N)
    cols = view.x0[:, None] + np.arange(N)
    inside = ((rows >= 0) & (rows < ny))[:, :, None] & ((cols >= 0) & (cols < nx))[:, None, :]
    out = np.where(inside, field[np.clip(rows, 0, ny - 1)[:, :, None],
                                 np.clip(cols, 0, nx - 1)[:, None, :]], 0.0)  # fmt: skip
    pat, bx0, by0, sel = _exposure_patches(exposure, models, np.asarray(idx), cfg)
    if not sel.size:
        return out
    n_big = pat.shape[-1]
    px = (view.x0[sel] - bx0)[:, None] + np.arange(N)  # the window in each patch
    py = (view.y0[sel] - by0)[:, None] + np.arange(N)
    on = inside[sel] & ((py >= 0) & (py < n_big))[:, :, None] & \
        ((px >= 0) & (px < n_big))[:, None, :]
    win = pat[np.arange(sel.size)[:, None, None], np.clip(py, 0, n_big - 1)[:, :, None],
              np.clip(px, 0, n_big - 1)[:, None, :]]  # fmt: skip
    out[sel] -= np.where(on, win, 0.0)
    return out
