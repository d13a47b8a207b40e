"""An image's stamps and their tiers, the fitter of its stamps and the store of its fits."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from astropy.table import Table

from .. import flags as _flags
from ..assemble import FIT_COLUMNS, fit_columns
from ..config import Config
from ..detection import flag_close_pairs
from ..forced import position_snr
from ..likelihood import MixedPSF, StampFits, blend_fits, fit_stamps, merge_fits
from ..prior import SizePrior
from ..psf import PSFResult
from ..runner import report_progress
from ..stamps import cut_stamps, patch_origins
from .image_psf import CellPSFs
from .inputs import Image

__all__ = ["image_stamps", "forced_snrs", "ImageFitter", "ImageResults"]


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


def image_stamps(sub: np.ndarray, img: Image, det: Table, cfg: Config,
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
        pair = flag_close_pairs(x, y, det["flux"], det["snr"], stamp_size=cfg.stamp_size,
                                min_snr=cfg.close_pair_min_snr,
                                faint_ratio=cfg.close_pair_faint_ratio)  # fmt: skip
        flags[pair] |= _flags.flag_value("CLOSE_PAIR")
    flags[~(np.isfinite(noise) & (noise > 0))] |= _flags.flag_value("BAD_NOISE")
    return _ImageStamps(stamps=stamps, bstamps=bstamps, use_big=use_big, cx=cx, cy=cy,
                        fcx=np.where(use_big, bcx, cx), fcy=np.where(use_big, bcy, cy),
                        base_cfg=base_cfg, offset=n_big // 2 - cfg.stamp_size // 2)


def forced_snrs(st: _ImageStamps, noise: np.ndarray, psf: PSFResult | None,
                cells: CellPSFs | None) -> np.ndarray:  # fmt: skip
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
class ImageFitter:
    """Fits an image's objects on their stamps, each with the PSF of its cell: its
    centre's, its corners' fits blended, or (``Config.psf_interpolation = "fourier"``)
    the corners' PSFs mixed with its position's weights in one fit
    (:class:`~pylensfit.likelihood.MixedPSF`)."""

    st: _ImageStamps
    noise: np.ndarray  # (n,) per-object noise sigma
    cfg: Config
    psf_image: np.ndarray | None  # the image's PSF (a constant PSF)
    cells: CellPSFs | None  # a varying PSF model, sampled for the fits
    size_prior: SizePrior | None
    rings: np.ndarray | None  # fit_stamps' lnL_r_groups
    size_marginal_prior: Any
    #: ``(n, n_big, n_big)`` where given: the light each object's last fit took out of
    #: its stamp (``less``), kept for the metacalibration of the stamp its fit saw
    taken_out: np.ndarray | None = None

    def __call__(self, idx: np.ndarray, less: np.ndarray | None = None) -> StampFits:
        """Fit the stamps of objects ``idx``, less ``less`` (``(len(idx), n_big, n_big)``:
        the neighbours' light and the sky's change, about each object)."""
        cp = self.cells
        if less is not None and self.taken_out is not None:
            self.taken_out[idx] = less
        if less is None:  # a first fit: the run's object bar (a refit is not counted)
            report_progress("planned", idx.size)
        if cp is None:
            return self._fit_with(idx, less, self.psf_image, 1.0 if less is None else 0.0)
        parts = []
        mixed = self.cfg.psf_interpolation == "fourier" and cp.nodes.shape[0] > 1
        for c in np.unique(cp.cell[idx]):  # one fit per cell and node of the PSF model
            sel = np.flatnonzero(cp.cell[idx] == c)
            j, lj = idx[sel], None if less is None else less[sel]
            if mixed:  # one fit, each object with the PSF at its position
                psf = MixedPSF(cp.images[cp.nodes[:, j[0]]], cp.weights[:, j])
                parts.append((sel, self._fit_with(j, lj, psf, 1.0 if less is None else 0.0)))
                continue
            share = 0.0 if less is not None else 1.0 / cp.nodes.shape[0]
            fits = [self._fit_with(j, lj, cp.images[k], share) for k in cp.nodes[:, j[0]]]
            parts.append((sel, blend_fits(fits, cp.weights[:, j])))
        return parts[0][1] if len(parts) == 1 else merge_fits(parts, idx.size)

    def _fit_with(self, idx: np.ndarray, less: np.ndarray | None,
                  psf_image: np.ndarray | MixedPSF, share: float = 0.0) -> StampFits:  # fmt: skip
        """Fit objects ``idx`` with one PSF image (or each with its own, a
        :class:`~pylensfit.likelihood.MixedPSF` with the weights of ``idx``), each on
        its stamp tier, in chunks of ``4 * Config.block_size`` objects (a whole number of
        :func:`fit_stamps`' own blocks, so that the chunks change no result), each
        chunk's objects reported to the run's progress bar as ``share`` of an object
        each."""
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
                psf = psf_image.take(ws) if isinstance(psf_image, MixedPSF) else psf_image
                parts.append((ws, fit_stamps(
                    data, psf, self.noise[j], config=c, centres=(st.fcx[j], st.fcy[j]),
                    size_prior=self.size_prior, lnL_r_groups=self.rings,
                    size_marginal_prior=self.size_marginal_prior)))  # fmt: skip
                report_progress("done", share * j.size)
        return parts[0][1] if len(parts) == 1 else merge_fits(parts, idx.size)


@dataclass
class ImageResults:
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
              rings: np.ndarray | None) -> ImageResults:  # fmt: skip
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
