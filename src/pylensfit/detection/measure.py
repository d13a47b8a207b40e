"""Measuring the detected objects: positions, aperture photometry, the pixel and stamp
quantities, and the catalogue's columns (:data:`COLUMNS`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import sep
from astropy.table import Table

from ..flags import flag_value
from .background import Background
from .inputs import SEP_FLAGS
from .pairs import close_pairs

COLUMNS: tuple[tuple[str, str, str, str], ...] = (
    # name, dtype, unit, description ("" = dimensionless or the image's own units)
    ("id", "i8", "", "object number, 1-based"),
    ("x", "f8", "pix", "x position, 0-based, pixel centres at integers"),
    ("y", "f8", "pix", "y position, 0-based, pixel centres at integers"),
    ("flux", "f8", "", "background-subtracted flux in a circle of radius aper_radius"),
    ("flux_err", "f8", "", "1-sigma error of flux (background noise, + Poisson if gain)"),
    ("flux_iso", "f8", "", "sum of the deblended isophotal footprint (SEP's flux)"),
    ("snr", "f8", "", "flux / flux_err"),
    ("mag", "f8", "mag", "zeropoint - 2.5 log10(flux); NaN where flux <= 0"),
    ("peak", "f8", "", "highest background-subtracted pixel value"),
    ("peak_snr", "f8", "", "peak / noise sigma at the peak pixel"),
    ("a", "f8", "pix", "isophotal semi-major axis (rms along the major axis)"),
    ("b", "f8", "pix", "isophotal semi-minor axis"),
    ("theta", "f8", "rad", "major-axis angle from +x towards +y, in [-pi/2, pi/2]"),
    ("r_half", "f8", "pix", "radius of the circle holding half of flux"),
    ("aper_radius", "f8", "pix", "radius of the photometry aperture"),
    ("npix", "i8", "pix", "number of pixels of the isophotal footprint"),
    ("background", "f8", "", "background level at the object (subtracted)"),
    ("bkg_rms", "f8", "", "background rms map at the object"),
    ("noise_sigma", "f8", "", "per-pixel noise sigma for the object's stamp"),
    ("sep_flag", "i4", "", "SEP object and aperture flags (see SEP_FLAGS)"),
    ("flags", "i8", "", "pylensfit flags: EDGE, MASKED, BAD_PIXELS, CLOSE_PAIR"),
)


@dataclass(frozen=True)
class DetectionMaps:
    """The maps of :func:`~pylensfit.detection.detect`, all of the image's shape.

    Attributes
    ----------
    background : Background
        The background subtracted.
    bad, nonfinite : numpy.ndarray
        Boolean: the unusable pixels (non-finite, masked, zero weight), and the
        non-finite ones among them.
    weight : numpy.ndarray or None
        The weight map as native float64.
    sub : numpy.ndarray
        The background-subtracted image, 0 on the unusable pixels.
    sigma : numpy.ndarray
        The per-pixel noise sigma (``1/sqrt(weight)``, else the background rms).
    bad_det : numpy.ndarray
        Boolean: the pixels left out of the detection (``bad`` or no positive sigma).
    err : numpy.ndarray
        SEP's error map (``sigma``, 1 on ``bad_det``, which SEP treats as masked).
    """

    background: Background
    bad: np.ndarray
    nonfinite: np.ndarray
    weight: np.ndarray | None
    sub: np.ndarray
    sigma: np.ndarray
    bad_det: np.ndarray
    err: np.ndarray


class Photometry(NamedTuple):
    """How :func:`~pylensfit.detection.detect` measures the objects: the aperture radius
    in units of ``r_half`` and its bounds (pixels), the windowed centroid, the gain
    (electrons per image unit, or None) and the magnitude zeropoint."""

    aperture: float
    min_aperture: float
    max_aperture: float
    windowed: bool
    gain: float | None
    zeropoint: float


def stamp_windows(arr: np.ndarray, ix: np.ndarray, iy: np.ndarray, n: int, fill, chunk=2048):
    """Yield ``(slice, windows)``: ``n x n`` cut-outs of ``arr`` (``fill`` outside the image).

    The stamp of object k starts at element ``[iy[k] - n//2, ix[k] - n//2]``. Objects are
    taken ``chunk`` at a time so the ``(chunk, n, n)`` gather stays small.
    """
    pad = n
    padded = np.pad(arr, pad, mode="constant", constant_values=fill)
    off = np.arange(n) - n // 2 + pad
    for s in range(0, len(ix), chunk):
        sl = slice(s, s + chunk)
        rows = (iy[sl, None] + off)[:, :, None]
        cols = (ix[sl, None] + off)[:, None, :]
        yield sl, padded[rows, cols]


def half_radius(sub, x, y, rmax) -> np.ndarray:
    """Radius holding half of the flux inside ``rmax``; ``rmax / 3`` where undefined."""
    r, _ = sep.flux_radius(sub, x, y, rmax, 0.5, subpix=1)  # a first guess: no sub-pixels
    return np.where(np.isfinite(r) & (r > 0) & (r <= rmax), r, rmax / 3.0)


def empty_table() -> Table:
    """A catalogue with no rows and the columns, units and descriptions of :data:`COLUMNS`."""
    t = Table()
    for name, dtype, unit, desc in COLUMNS:
        t[name] = np.zeros(0, dtype=dtype)
        t[name].unit = unit or None
        t[name].description = desc
    return t


class Positions(NamedTuple):
    """The objects' positions ``x, y`` (0-based pixels) and first half-light radii
    ``r0`` (pixels), each ``(k,)``."""

    x: np.ndarray
    y: np.ndarray
    r0: np.ndarray


class Apertures(NamedTuple):
    """The objects' aperture photometry, each ``(k,)``: the aperture radius (pixels), the
    flux and its error (image units), the half-light radius within the aperture
    (pixels, NaN where undefined) and SEP's flags with the aperture's."""

    radius: np.ndarray
    flux: np.ndarray
    flux_err: np.ndarray
    r_half: np.ndarray
    sep_flag: np.ndarray


def measure_objects(objs: np.ndarray, maps: DetectionMaps, phot: Photometry, n: int,
                    faint_ratio: float | None) -> dict[str, np.ndarray]:  # fmt: skip
    """The measured columns of the catalogue of SEP's objects ``objs``: positions,
    aperture photometry, pixel quantities and the flags and noise of their ``n x n``
    stamps."""
    pos = refine_positions(objs, maps, phot)
    ap = aperture_photometry(objs, maps, pos, phot)
    pix = pixel_quantities(objs, maps, pos, ap, phot.zeropoint)
    flags, noise_sigma = stamp_quantities(objs, maps, pos, pix["bkg_rms"], n, faint_ratio)
    return dict(pix, x=pos.x, y=pos.y, flux=ap.flux, flux_err=ap.flux_err, r_half=ap.r_half,
                aper_radius=ap.radius, noise_sigma=noise_sigma, sep_flag=ap.sep_flag,
                flags=flags)  # fmt: skip


def refine_positions(objs: np.ndarray, maps: DetectionMaps, phot: Photometry) -> Positions:
    """Positions (barycentre, or windowed centroid where it is sound) and first ``r_half``."""
    sub, bad_det = maps.sub, maps.bad_det
    min_aperture, max_aperture = phot.min_aperture, phot.max_aperture
    x = objs["x"].astype(np.float64)
    y = objs["y"].astype(np.float64)
    a = objs["a"].astype(np.float64)
    # first half-light radius: normalised to the flux inside max(6a, min_aperture)
    rmax0 = np.clip(np.nan_to_num(6.0 * a, nan=min_aperture), min_aperture, max_aperture)
    r0 = half_radius(sub, x, y, rmax0)
    if phot.windowed:
        # the window's cost grows as its area: capped at 3 px, past which the position
        # gains little (the likelihood fit re-centres every object anyway)
        sig = np.clip(2.0 * r0 / 2.35, 0.5, 3.0)
        xw, yw, wflag = sep.winpos(sub, x, y, sig, mask=bad_det)
        ok = (wflag == 0) & np.isfinite(xw) & np.isfinite(yw)
        # a window that runs off (towards a neighbour, typically) is not used
        ok &= np.hypot(xw - x, yw - y) < np.maximum(1.0, 0.5 * r0)
        ok &= (xw > objs["xmin"] - 0.5) & (xw < objs["xmax"] + 0.5)
        ok &= (yw > objs["ymin"] - 0.5) & (yw < objs["ymax"] + 0.5)
        x = np.where(ok, xw, x)
        y = np.where(ok, yw, y)
        r0 = half_radius(sub, x, y, rmax0)
    return Positions(x, y, r0)


def aperture_photometry(objs: np.ndarray, maps: DetectionMaps, pos: Positions,
                        phot: Photometry) -> Apertures:  # fmt: skip
    """Circular-aperture flux, its error and ``r_half``, and SEP's flags of ``objs`` with
    the aperture's."""
    sub, bad_det, (x, y, r0) = maps.sub, maps.bad_det, pos
    sep_flag = objs["flag"].astype(np.int32)
    badf = bad_det.astype(np.float64)
    rap = np.clip(phot.aperture * r0, phot.min_aperture, phot.max_aperture)
    # bad pixels are summed as 0 with no variance (SEP's own masking rescales by area)
    flux, flux_err, aflag = sep.sum_circle(
        sub, x, y, rap, err=np.where(bad_det, 0.0, maps.sigma), gain=phot.gain, subpix=5
    )
    nbad, _, _ = sep.sum_circle(badf, x, y, rap, subpix=0)
    sep_flag |= aflag.astype(np.int32)
    sep_flag |= np.where(nbad > 0, SEP_FLAGS["APER_HASMASKED"], 0).astype(np.int32)
    r_half, _ = sep.flux_radius(sub, x, y, rap, 0.5, normflux=flux, subpix=5)
    r_half = np.where((flux > 0) & np.isfinite(r_half) & (r_half > 0), r_half, np.nan)
    return Apertures(rap, flux, flux_err, r_half, sep_flag)


def pixel_quantities(objs: np.ndarray, maps: DetectionMaps, pos: Positions, ap: Apertures,
                     zeropoint: float) -> dict[str, np.ndarray]:  # fmt: skip
    """Background maps at the objects, peak, peak S/N, S/N and magnitude (table columns)."""
    x, y, flux, flux_err = pos.x, pos.y, ap.flux, ap.flux_err
    sigma, bad_det, background = maps.sigma, maps.bad_det, maps.background
    ny, nx = bad_det.shape
    ix = np.clip(np.rint(x).astype(np.int64), 0, nx - 1)
    iy = np.clip(np.rint(y).astype(np.int64), 0, ny - 1)
    bkg_rms = background.rms[iy, ix]
    bkg_level = background.back[iy, ix]
    xp = np.clip(objs["xpeak"].astype(np.int64), 0, nx - 1)
    yp = np.clip(objs["ypeak"].astype(np.int64), 0, ny - 1)
    peak = objs["peak"].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        peak_snr = peak / np.where(bad_det[yp, xp], np.nan, sigma[yp, xp])
        snr = flux / flux_err
        mag = np.where(flux > 0, zeropoint - 2.5 * np.log10(np.where(flux > 0, flux, 1.0)), np.nan)
    return dict(
        snr=snr, mag=mag, peak=peak, peak_snr=peak_snr, background=bkg_level, bkg_rms=bkg_rms
    )


def stamp_quantities(objs: np.ndarray, maps: DetectionMaps, pos: Positions,
                     bkg_rms: np.ndarray, n: int, faint_ratio: float | None
                     ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Per-stamp pylensfit ``flags`` (EDGE, MASKED, BAD_PIXELS, CLOSE_PAIR) and noise sigma
    (the background rms ``bkg_rms`` at the objects without a weight map)."""
    x, y, flux_iso = pos.x, pos.y, objs["flux"]
    bad, nonfinite, bad_det, sigma, w = (maps.bad, maps.nonfinite, maps.bad_det, maps.sigma,
                                         maps.weight)  # fmt: skip
    ny, nx = bad.shape
    flags = np.zeros(len(x), dtype=np.int64)
    noise_sigma = bkg_rms.copy()
    ix0 = np.rint(x).astype(np.int64)
    iy0 = np.rint(y).astype(np.int64)
    lo_x, lo_y = ix0 - n // 2, iy0 - n // 2
    edge = (lo_x < 0) | (lo_y < 0) | (lo_x + n > nx) | (lo_y + n > ny)
    flags[edge] |= flag_value("EDGE")
    masked_only = bad & ~nonfinite
    for sl, win in stamp_windows(masked_only, ix0, iy0, n, False):
        flags[sl] |= np.where(win.any(axis=(1, 2)), flag_value("MASKED"), 0)
    for sl, win in stamp_windows(nonfinite, ix0, iy0, n, False):
        flags[sl] |= np.where(win.any(axis=(1, 2)), flag_value("BAD_PIXELS"), 0)
    if w is not None:
        smap = np.where(bad_det, np.nan, sigma)
        for sl, win in stamp_windows(smap, ix0, iy0, n, np.nan):
            flat = win.reshape(win.shape[0], -1)
            has = np.isfinite(flat).any(axis=1)
            med = np.full(win.shape[0], np.nan)
            if has.any():
                med[has] = np.nanmedian(flat[has], axis=1)
            noise_sigma[sl] = med
    flags |= np.where(
        close_pairs(x, y, flux=flux_iso, stamp_size=n, faint_ratio=faint_ratio),
        flag_value("CLOSE_PAIR"),
        0,
    )
    return flags, noise_sigma


def catalogue_table(objs: np.ndarray, cols: dict[str, np.ndarray], meta) -> Table:
    """The output catalogue: SEP's shape columns and ``cols``, with dtypes, units, descriptions."""
    cols = dict(
        cols,
        id=np.arange(1, len(objs) + 1),
        flux_iso=objs["flux"],
        a=objs["a"].astype(np.float64),
        b=objs["b"].astype(np.float64),
        theta=objs["theta"].astype(np.float64),
        npix=objs["npix"],
    )
    out = Table(meta=meta)
    for name, dtype, unit, desc in COLUMNS:
        out[name] = np.asarray(cols[name], dtype=dtype)
        out[name].unit = unit or None
        out[name].description = desc
    return out
