"""Object detection, photometry, star selection and close-pair rejection (paper sections 2.3-2.4).

Detection uses SEP, the Source Extractor algorithms as a library (Bertin & Arnouts 1996;
Barbary 2016), as the paper used SExtractor to find galaxies and stars::

    bkg = measure_background(image, weight=weight)      # background and noise maps
    cat = detect(image, weight=weight, background=bkg)  # one row per object
    sub = bkg.subtract(image)                            # the image the catalogue measured
    stars = select_stars(cat)                            # stellar locus, peak S/N > 30
    pairs = close_pairs(cat["x"], cat["y"])              # another object in the stamp

Conventions: images are indexed ``[y, x]``; positions are 0-based with pixel centres at
integer values (pixel ``(x, y)`` is element ``[y, x]``), which is SEP's convention too. A
postage stamp of side ``n`` about ``(x, y)`` covers elements ``rint(y) - n//2`` to
``rint(y) - n//2 + n - 1`` (and the same in x), as in :mod:`pylensfit.likelihood`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import sep
from astropy.table import Table
from scipy.ndimage import binary_dilation
from scipy.spatial import cKDTree

from .flags import flag_value

__all__ = [
    "Background",
    "close_pairs",
    "detect",
    "grow_mask",
    "measure_background",
    "saturation_level",
    "saturation_mask",
    "select_stars",
    "SEP_FLAGS",
]

log = logging.getLogger(__name__)

#: SEP's object and aperture flags, name -> bit (the ``sep_flag`` column)
SEP_FLAGS: dict[str, int] = {
    "OBJ_MERGED": int(sep.OBJ_MERGED),  # deblended from a blend with other objects
    "OBJ_TRUNC": int(sep.OBJ_TRUNC),  # isophote touches the image edge
    "OBJ_DOVERFLOW": int(sep.OBJ_DOVERFLOW),
    "OBJ_SINGU": int(sep.OBJ_SINGU),  # singular second moments
    "APER_TRUNC": int(sep.APER_TRUNC),  # photometry aperture crosses the image edge
    "APER_HASMASKED": int(sep.APER_HASMASKED),  # masked or bad pixels in the aperture
    "APER_ALLMASKED": int(sep.APER_ALLMASKED),
    "APER_NONPOSITIVE": int(sep.APER_NONPOSITIVE),
}

#: SEP flags that disqualify an object as a PSF star
_STAR_BAD_SEP = (
    SEP_FLAGS["OBJ_MERGED"]
    | SEP_FLAGS["OBJ_TRUNC"]
    | SEP_FLAGS["OBJ_SINGU"]
    | SEP_FLAGS["APER_TRUNC"]
    | SEP_FLAGS["APER_HASMASKED"]
    | SEP_FLAGS["APER_ALLMASKED"]
)

_COLUMNS: tuple[tuple[str, str, str, str], ...] = (
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


# --------------------------------------------------------------------------------------
# input checks


def _as_image(image, name: str = "image") -> np.ndarray:
    """A native-byte-order float64 copy of a 2-D array (FITS data are big-endian)."""
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D array, got {arr.ndim} dimension(s) {arr.shape}")
    if arr.shape[0] < 2 or arr.shape[1] < 2:
        raise ValueError(f"{name} must be at least 2 x 2 pixels, got shape {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
    return np.array(arr, dtype=np.float64, order="C")  # native order, a copy


def _bad_pixels(image: np.ndarray, mask, weight) -> tuple[np.ndarray, np.ndarray | None]:
    """Boolean map of unusable pixels, and the weight map as native float64 (or None)."""
    bad = ~np.isfinite(image)
    if mask is not None:
        m = _as_image(mask, "mask")
        if m.shape != image.shape:
            raise ValueError(f"mask shape {m.shape} differs from image shape {image.shape}")
        bad |= ~(m <= 0)  # mask > 0, or non-finite mask values
    w = None
    if weight is not None:
        w = _as_image(weight, "weight")
        if w.shape != image.shape:
            raise ValueError(f"weight shape {w.shape} differs from image shape {image.shape}")
        bad |= ~(w > 0) | ~np.isfinite(w)
    return bad, w


# --------------------------------------------------------------------------------------
# background


@dataclass(frozen=True)
class Background:
    """A spatially varying sky background and its noise (SEP / Source Extractor method).

    Attributes
    ----------
    back : numpy.ndarray
        Background level map, same shape as the image (image units).
    rms : numpy.ndarray
        Background noise (standard deviation per pixel) map, image units.
    global_back : float
        Global background level (image units).
    global_rms : float
        Global background rms (image units).
    bad : numpy.ndarray
        Boolean map of the pixels left out: non-finite, ``mask > 0`` or ``weight == 0``.
    """

    back: np.ndarray
    rms: np.ndarray
    global_back: float
    global_rms: float
    bad: np.ndarray = field(repr=False)

    @property
    def shape(self) -> tuple[int, int]:
        """Shape of the maps, ``(ny, nx)``."""
        return self.back.shape

    def subtract(self, image) -> np.ndarray:
        """``image - back`` as native float64, with the bad pixels set to 0.

        Parameters
        ----------
        image : array_like
            The image the background was measured on (any byte order).

        Returns
        -------
        numpy.ndarray
            Background-subtracted image; the pixels in :attr:`bad` are 0.
        """
        data = _as_image(image)
        if data.shape != self.shape:
            raise ValueError(f"image shape {data.shape} differs from background {self.shape}")
        data -= self.back
        data[self.bad] = 0.0
        return data


def measure_background(
    image,
    *,
    mask=None,
    weight=None,
    box: int = 64,
    filter_size: int = 3,
    mask_sources: bool = True,
    source_threshold: float = 3.0,
    source_radius: float = 6.0,
    rescale_rms: bool = True,
) -> Background:
    """Measure the sky background and its rms with SEP (Source Extractor's algorithm).

    In boxes of ``box x box`` pixels the sigma-clipped mode of the pixel values gives the
    background and the clipped standard deviation its rms; the box values are median
    filtered over ``filter_size x filter_size`` boxes and interpolated with a bicubic spline.

    With ``mask_sources`` (default) this is done twice: objects detected above
    ``source_threshold`` rms on the first estimate are masked out to ``source_radius``
    times their isophotal ellipse (``a``, ``b``), and the background is measured again.
    The wings of the objects otherwise raise the background; in a 512 x 512 field of 65
    objects at noise 5 the bias falls from about 0.15 to 0.03 (0.03 to 0.006 sigma).

    SEP's clipped standard deviation underestimates the sigma of Gaussian noise by about
    1.6%; with ``rescale_rms`` (default) the rms map is scaled so that the normalised
    residuals ``(image - back) / rms`` of the sky pixels (unmasked, off the masked
    objects) have a robust sigma (1.4826 times their median absolute deviation) of 1.
    The map's shape is SEP's; its scale is then unbiased for Gaussian noise.

    Parameters
    ----------
    image : array_like
        2-D image, indexed ``[y, x]``, any byte order (FITS big-endian data are converted).
    mask : array_like, optional
        Pixels with ``mask > 0`` are left out.
    weight : array_like, optional
        Inverse-variance map; pixels with ``weight <= 0`` (or non-finite) are left out.
    box : int, optional
        Background box side in pixels (clipped to the image size). Default 64.
    filter_size : int, optional
        Median-filter size in boxes. Default 3.
    mask_sources : bool, optional
        Mask detected objects and measure again. Default True.
    source_threshold : float, optional
        Detection threshold (in rms) of the objects masked. Default 3.
    source_radius : float, optional
        Masked ellipse size in units of the objects' ``a``, ``b``. Default 6.
    rescale_rms : bool, optional
        Rescale the rms map to the robust sigma of the sky pixels. Default True.

    Returns
    -------
    Background
        The background and rms maps and their global values. Non-finite pixels, as well as
        masked and zero-weight ones, are left out of the estimate (and flagged in
        :attr:`Background.bad`).

    Raises
    ------
    ValueError
        If the image is not 2-D, or has no finite, unmasked pixel.
    """
    data = _as_image(image)
    bad, _ = _bad_pixels(data, mask, weight)
    if bad.all():
        if not np.isfinite(data).any():
            raise ValueError("image has no finite pixel: cannot measure a background")
        raise ValueError("every pixel is masked or has zero weight: cannot measure a background")
    box = int(box)
    filter_size = int(filter_size)
    if box < 1 or filter_size < 1:
        raise ValueError(f"box and filter_size must be >= 1, got {box} and {filter_size}")
    bh, bw = min(box, data.shape[0]), min(box, data.shape[1])
    data[bad] = 0.0  # SEP ignores masked pixels but must not see NaN
    bkg = sep.Background(data, mask=bad, bw=bw, bh=bh, fw=filter_size, fh=filter_size)
    sky = ~bad  # pixels of sky for the rms rescaling
    if mask_sources:
        rms = bkg.rms()
        ok = ~bad & (rms > 0) & np.isfinite(rms)
        if ok.any():
            sub = np.where(ok, data - bkg.back(), 0.0)
            objs = _extract(sub, float(source_threshold), np.where(ok, rms, 1.0), ~ok)
            if len(objs):
                src = np.zeros(data.shape, dtype=bool)
                sep.mask_ellipse(
                    src,
                    objs["x"],
                    objs["y"],
                    objs["a"],
                    objs["b"],
                    objs["theta"],
                    r=float(source_radius),
                )
                if _usable_boxes(bad | src, bh, bw):
                    sky = ~(bad | src)
                    bkg = sep.Background(
                        data, mask=~sky, bw=bw, bh=bh, fw=filter_size, fh=filter_size
                    )
                else:
                    log.warning(
                        "masking the objects (to %g times their isophotal ellipses) leaves "
                        "no %d x %d background box half free: background measured "
                        "without the object mask", source_radius, bw, bh,
                    )
    back = np.asarray(bkg.back(), dtype=np.float64)
    rms = np.asarray(bkg.rms(), dtype=np.float64)
    global_rms = float(bkg.globalrms)
    if rescale_rms:
        sky &= (rms > 0) & np.isfinite(rms)
        if sky.sum() >= 100:
            r = (data[sky] - back[sky]) / rms[sky]
            scale = 1.4826 * float(np.median(np.abs(r - np.median(r))))
            if np.isfinite(scale) and scale > 0:
                rms *= scale
                global_rms *= scale
    return Background(
        back=back,
        rms=rms,
        global_back=float(bkg.globalback),
        global_rms=global_rms,
        bad=bad,
    )


def _usable_boxes(masked: np.ndarray, bh: int, bw: int) -> bool:
    """Whether some background box keeps at least half its pixels unmasked.

    SEP (as Source Extractor, ``BACK_MINGOODFRAC``) discards a box with fewer and fills
    it from its neighbours; with every box discarded it returns a background of 0, which
    would be subtracted as if measured.
    """
    ny, nx = masked.shape
    for y0 in range(0, ny, bh):
        for x0 in range(0, nx, bw):
            if np.mean(~masked[y0 : y0 + bh, x0 : x0 + bw]) >= 0.5:
                return True
    return False


# --------------------------------------------------------------------------------------
# detection and measurement


def _extract(data, thresh, err, bad, **kwargs):
    """``sep.extract``, raising SEP's pixel-stack and sub-object limits when they are hit."""
    old_stack, old_sub = sep.get_extract_pixstack(), sep.get_sub_object_limit()
    try:
        for _ in range(12):
            try:
                return sep.extract(data, thresh, err=err, mask=bad, **kwargs)
            except Exception as exc:  # SEP raises a bare Exception
                msg = str(exc)
                if "pixel buffer full" in msg:
                    sep.set_extract_pixstack(max(4 * sep.get_extract_pixstack(), data.size // 4))
                elif "deblending overflow" in msg:
                    sep.set_sub_object_limit(4 * sep.get_sub_object_limit())
                else:
                    raise
        raise RuntimeError("sep.extract: pixel-stack / sub-object limits still too small")
    finally:
        sep.set_extract_pixstack(old_stack)
        sep.set_sub_object_limit(old_sub)


def _stamp_windows(arr: np.ndarray, ix: np.ndarray, iy: np.ndarray, n: int, fill, chunk=2048):
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


def _half_radius(sub, x, y, rmax) -> np.ndarray:
    """Radius holding half of the flux inside ``rmax``; ``rmax / 3`` where undefined."""
    r, _ = sep.flux_radius(sub, x, y, rmax, 0.5, subpix=1)  # a first guess: no sub-pixels
    return np.where(np.isfinite(r) & (r > 0) & (r <= rmax), r, rmax / 3.0)


def _empty_table() -> Table:
    """A catalogue with no rows and the columns, units and descriptions of :data:`_COLUMNS`."""
    t = Table()
    for name, dtype, unit, desc in _COLUMNS:
        t[name] = np.zeros(0, dtype=dtype)
        t[name].unit = unit or None
        t[name].description = desc
    return t


def _detect_inputs(
    image,
    weight,
    mask,
    background: Background | None,
    box: int,
    filter_size: int,
    mask_sources: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray, Background]:
    """Check and normalise :func:`detect`'s image, maps and background.

    Returns the image as native float64, the bad-pixel map, the weight map (or None), the
    map of non-finite pixels and the background (measured here when not given).
    """
    data = _as_image(image)
    bad, w = _bad_pixels(data, mask, weight)
    if not np.isfinite(data).any():
        raise ValueError("image has no finite pixel: nothing to detect")
    nonfinite = ~np.isfinite(data)
    if background is None:
        background = measure_background(
            data,
            mask=mask,
            weight=weight,
            box=box,
            filter_size=filter_size,
            mask_sources=mask_sources,
        )
    elif not isinstance(background, Background):
        raise ValueError("background must be a Background from measure_background")
    elif background.shape != data.shape:
        raise ValueError(f"background shape {background.shape} differs from {data.shape}")
    return data, bad, w, nonfinite, background


def _stamp_and_aperture(
    stamp_size: int, min_aperture: float, max_aperture: float | None
) -> tuple[int, float]:
    """The stamp side as an int (checked >= 2) and the aperture cap (default: the stamp)."""
    n = int(stamp_size)
    if n < 2:
        raise ValueError(f"stamp_size must be >= 2, got {stamp_size}")
    if max_aperture is None:
        max_aperture = float(max(n, min_aperture))
    return n, max_aperture


def _detection_maps(
    data: np.ndarray, bad: np.ndarray, w: np.ndarray | None, background: Background
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Background-subtracted image, noise sigma map, detection bad map and SEP's error map."""
    sub = data - background.back
    sub[bad] = 0.0
    if w is not None:
        with np.errstate(divide="ignore"):
            sigma = np.where(bad, np.inf, 1.0 / np.sqrt(np.where(bad, 1.0, w)))
    else:
        sigma = np.array(background.rms, dtype=np.float64)
    bad_det = bad | ~(sigma > 0) | ~np.isfinite(sigma)
    err = np.where(bad_det, 1.0, sigma)  # masked pixels: SEP gives them infinite noise
    return sub, sigma, bad_det, err


def _detect_meta_table(
    background: Background, threshold: float, zeropoint: float, n: int
) -> Table:
    """The empty catalogue with the global background, threshold, zeropoint and stamp in meta."""
    t = _empty_table()
    t.meta.update(
        BKG=background.global_back,
        BKGRMS=background.global_rms,
        THRESH=float(threshold),
        ZP=float(zeropoint),
        STAMP=n,
    )
    return t


def _run_extract(
    sub: np.ndarray,
    threshold: float,
    err: np.ndarray,
    bad_det: np.ndarray,
    min_area: int,
    deblend_nthresh: int,
    deblend_cont: float,
    filter_kernel: np.ndarray | None | str,
) -> np.ndarray:
    """Run SEP's extraction and deblending with :func:`detect`'s options."""
    kw = dict(
        minarea=int(min_area),
        deblend_nthresh=int(deblend_nthresh),
        deblend_cont=float(deblend_cont),
    )
    if not (isinstance(filter_kernel, str) and filter_kernel == "default"):
        kw["filter_kernel"] = filter_kernel
    return _extract(sub, float(threshold), err, bad_det, **kw)


def _refine_positions(
    sub: np.ndarray,
    objs: np.ndarray,
    bad_det: np.ndarray,
    min_aperture: float,
    max_aperture: float,
    windowed: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions (barycentre, or windowed centroid where it is sound) and first ``r_half``."""
    x = objs["x"].astype(np.float64)
    y = objs["y"].astype(np.float64)
    a = objs["a"].astype(np.float64)
    # first half-light radius: normalised to the flux inside max(6a, min_aperture)
    rmax0 = np.clip(np.nan_to_num(6.0 * a, nan=min_aperture), min_aperture, max_aperture)
    r0 = _half_radius(sub, x, y, rmax0)
    if windowed:
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
        r0 = _half_radius(sub, x, y, rmax0)
    return x, y, r0


def _aperture_photometry(
    sub: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    r0: np.ndarray,
    sigma: np.ndarray,
    bad_det: np.ndarray,
    sep_flag: np.ndarray,
    aperture: float,
    min_aperture: float,
    max_aperture: float,
    gain: float | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Circular-aperture flux, its error and ``r_half``; updates ``sep_flag`` in place.

    Returns ``(aper_radius, flux, flux_err, r_half, sep_flag)``.
    """
    badf = bad_det.astype(np.float64)
    rap = np.clip(aperture * r0, min_aperture, max_aperture)
    # bad pixels are summed as 0 with no variance (SEP's own masking rescales by area)
    flux, flux_err, aflag = sep.sum_circle(
        sub, x, y, rap, err=np.where(bad_det, 0.0, sigma), gain=gain, subpix=5
    )
    nbad, _, _ = sep.sum_circle(badf, x, y, rap, subpix=0)
    sep_flag |= aflag.astype(np.int32)
    sep_flag |= np.where(nbad > 0, SEP_FLAGS["APER_HASMASKED"], 0).astype(np.int32)
    r_half, _ = sep.flux_radius(sub, x, y, rap, 0.5, normflux=flux, subpix=5)
    r_half = np.where((flux > 0) & np.isfinite(r_half) & (r_half > 0), r_half, np.nan)
    return rap, flux, flux_err, r_half, sep_flag


def _pixel_quantities(
    objs: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    flux: np.ndarray,
    flux_err: np.ndarray,
    sigma: np.ndarray,
    bad_det: np.ndarray,
    background: Background,
    zeropoint: float,
) -> dict[str, np.ndarray]:
    """Background maps at the objects, peak, peak S/N, S/N and magnitude (table columns)."""
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


def _stamp_quantities(
    x: np.ndarray,
    y: np.ndarray,
    flux_iso: np.ndarray,
    bkg_rms: np.ndarray,
    bad: np.ndarray,
    nonfinite: np.ndarray,
    bad_det: np.ndarray,
    sigma: np.ndarray,
    w: np.ndarray | None,
    n: int,
    faint_ratio: float | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-stamp pylensfit ``flags`` (EDGE, MASKED, BAD_PIXELS, CLOSE_PAIR) and noise sigma."""
    ny, nx = bad.shape
    flags = np.zeros(len(x), dtype=np.int64)
    noise_sigma = bkg_rms.copy()
    ix0 = np.rint(x).astype(np.int64)
    iy0 = np.rint(y).astype(np.int64)
    lo_x, lo_y = ix0 - n // 2, iy0 - n // 2
    edge = (lo_x < 0) | (lo_y < 0) | (lo_x + n > nx) | (lo_y + n > ny)
    flags[edge] |= flag_value("EDGE")
    masked_only = bad & ~nonfinite
    for sl, win in _stamp_windows(masked_only, ix0, iy0, n, False):
        flags[sl] |= np.where(win.any(axis=(1, 2)), flag_value("MASKED"), 0)
    for sl, win in _stamp_windows(nonfinite, ix0, iy0, n, False):
        flags[sl] |= np.where(win.any(axis=(1, 2)), flag_value("BAD_PIXELS"), 0)
    if w is not None:
        smap = np.where(bad_det, np.nan, sigma)
        for sl, win in _stamp_windows(smap, ix0, iy0, n, np.nan):
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


def _catalogue_table(objs: np.ndarray, cols: dict[str, np.ndarray], meta) -> Table:
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
    for name, dtype, unit, desc in _COLUMNS:
        out[name] = np.asarray(cols[name], dtype=dtype)
        out[name].unit = unit or None
        out[name].description = desc
    return out


def detect(
    image,
    *,
    weight=None,
    mask=None,
    threshold: float = 1.5,
    min_area: int = 5,
    deblend_nthresh: int = 32,
    deblend_cont: float = 0.005,
    background: Background | None = None,
    gain: float | None = None,
    zeropoint: float = 0.0,
    stamp_size: int = 32,
    aperture: float = 5.0,
    min_aperture: float = 3.0,
    max_aperture: float | None = None,
    windowed: bool = True,
    faint_ratio: float | None = None,
    filter_kernel: np.ndarray | None | str = "default",
    box: int = 64,
    filter_size: int = 3,
    mask_sources: bool = True,
) -> Table:
    """Detect and measure the objects of an image with SEP (SExtractor as a library).

    The background (``background``, or :func:`measure_background` with ``box`` and
    ``filter_size``) is subtracted, then pixels more than ``threshold`` noise sigmas above
    it in the filtered image, in connected groups of at least ``min_area``, make an object;
    blends are split by multi-threshold deblending. The noise sigma per pixel is
    ``1/sqrt(weight)`` when a weight map is given, else the background rms map.

    Each object is then measured on the background-subtracted image (get it with
    ``Background.subtract``): the position is the isophotal barycentre, refined by a
    Gaussian-windowed centroid (``windowed``); ``r_half`` is the radius enclosing half of
    the flux in a first circle of radius ``max(6 a, min_aperture)``; the flux is summed in a
    circle of radius ``aper_radius = clip(aperture * r_half, min_aperture, max_aperture)``
    (5 r_half holds > 99% of the flux of an exponential disc) and ``r_half`` is then
    re-measured as the radius holding half of that flux. Masked and bad pixels count as 0
    in the sums (no area rescaling) and set ``APER_HASMASKED`` in ``sep_flag``. The
    aperture of a blended object (``OBJ_MERGED``) holds some of its neighbours' light:
    its ``flux`` and ``r_half`` are biased high; ``flux_iso`` is the deblended estimate.

    Every detection counts for the ``CLOSE_PAIR`` flag, including the noise peaks that
    a low ``threshold`` lets through (about 50 in 512 x 512 pixels at 1.5 sigma).

    Parameters
    ----------
    image : array_like
        2-D image indexed ``[y, x]``, with sky background; any byte order.
    weight : array_like, optional
        Inverse-variance map ``1/sigma^2`` in image units; 0 marks unusable pixels.
    mask : array_like, optional
        Pixels with ``mask > 0`` are unusable (never detected, left out of sums).
    threshold : float, optional
        Detection threshold in units of the per-pixel noise sigma. Default 1.5.
    min_area : int, optional
        Minimum number of pixels above threshold. Default 5.
    deblend_nthresh : int, optional
        Number of deblending thresholds. Default 32.
    deblend_cont : float, optional
        Minimum contrast for deblending (1 disables it). Default 0.005.
    background : Background, optional
        A background measured beforehand (by :func:`measure_background`).
    gain : float, optional
        Electrons per image unit, adding the objects' Poisson noise to ``flux_err``.
    zeropoint : float, optional
        Magnitude zeropoint: ``mag = zeropoint - 2.5 log10(flux)``. Default 0.
    stamp_size : int, optional
        Postage-stamp side in pixels (paper: 32), for ``noise_sigma`` and ``flags``.
    aperture : float, optional
        Photometry aperture radius in units of ``r_half``. Default 5.
    min_aperture, max_aperture : float, optional
        Bounds of the aperture radius in pixels; ``max_aperture`` defaults to
        ``stamp_size``.
    windowed : bool, optional
        Refine positions with SEP's windowed centroid (``XWIN_IMAGE``; window sigma
        ``r_half / 1.175``); kept where it converges within ``max(1, r_half / 2)`` pixels
        of the barycentre and inside the object's footprint. Default True.
    faint_ratio : float, optional
        Passed to :func:`close_pairs` for the ``CLOSE_PAIR`` flag, with the isophotal
        fluxes ``flux_iso`` (the aperture fluxes of blended objects include their
        neighbours' light). Default None: every object with a neighbour in its stamp.
    filter_kernel : numpy.ndarray or None, optional
        Detection filter; default SEP's 3x3 pyramid, None for no filtering.
    box, filter_size : int, optional
        Background box and filter sizes when ``background`` is not given.
    mask_sources : bool, optional
        Mask objects when measuring the background (see :func:`measure_background`).

    Returns
    -------
    astropy.table.Table
        One row per object, columns (units in ``Table[col].unit``):

        ``id`` (1-based), ``x``, ``y`` (pix, 0-based), ``flux``, ``flux_err`` (image
        units, aperture), ``flux_iso`` (image units, deblended isophotal footprint),
        ``snr``, ``mag``, ``peak`` (image units), ``peak_snr`` (peak over the noise sigma
        at the peak pixel), ``a``, ``b`` (pix), ``theta`` (rad, from +x towards +y),
        ``r_half``, ``aper_radius`` (pix), ``npix``, ``background``, ``bkg_rms`` (image
        units, background maps at the object), ``noise_sigma`` (image units: median of
        ``1/sqrt(weight)`` over the stamp's usable pixels when a weight map is given, else
        ``bkg_rms``), ``sep_flag``
        (:data:`SEP_FLAGS`), ``flags`` (:mod:`pylensfit.flags` bits EDGE, MASKED,
        BAD_PIXELS, CLOSE_PAIR of the ``stamp_size`` stamp). An image without objects
        gives an empty table with these columns. ``meta`` holds the global background
        (``BKG``), rms (``BKGRMS``), ``THRESH``, ``ZP`` and ``STAMP``.

    Raises
    ------
    ValueError
        If the image is not 2-D, has no finite pixel, or a map has another shape.
    """
    data, bad, w, nonfinite, background = _detect_inputs(
        image, weight, mask, background, box, filter_size, mask_sources
    )
    n, max_aperture = _stamp_and_aperture(stamp_size, min_aperture, max_aperture)
    sub, sigma, bad_det, err = _detection_maps(data, bad, w, background)
    t = _detect_meta_table(background, threshold, zeropoint, n)
    if bad_det.all():
        return t
    objs = _run_extract(
        sub, threshold, err, bad_det, min_area, deblend_nthresh, deblend_cont, filter_kernel
    )
    if len(objs) == 0:
        return t
    x, y, r0 = _refine_positions(sub, objs, bad_det, min_aperture, max_aperture, windowed)
    sep_flag = objs["flag"].astype(np.int32)
    rap, flux, flux_err, r_half, sep_flag = _aperture_photometry(
        sub, x, y, r0, sigma, bad_det, sep_flag, aperture, min_aperture, max_aperture, gain
    )
    pix = _pixel_quantities(objs, x, y, flux, flux_err, sigma, bad_det, background, zeropoint)
    flags, noise_sigma = _stamp_quantities(
        x, y, objs["flux"], pix["bkg_rms"], bad, nonfinite, bad_det, sigma, w, n, faint_ratio
    )
    cols = dict(
        pix,
        x=x,
        y=y,
        flux=flux,
        flux_err=flux_err,
        r_half=r_half,
        aper_radius=rap,
        noise_sigma=noise_sigma,
        sep_flag=sep_flag,
        flags=flags,
    )
    return _catalogue_table(objs, cols, t.meta)


# --------------------------------------------------------------------------------------
# star selection


def _star_candidates(catalogue, min_peak_snr: float, saturation: float | None,
                     exclude_flags: int | None, position_order: int):  # fmt: skip
    """:func:`select_stars`' step 1: ``(cand, r_half, snr, pos)``, the candidates (bool),
    their half-light radii and S/N (every row), and the positions ``(x, y)`` where the
    locus centre may follow them (None otherwise)."""

    def col(name, default=None):
        try:
            return np.asarray(catalogue[name], dtype=np.float64)
        except (KeyError, ValueError):
            if default is None:
                raise ValueError(f"catalogue has no column {name!r}") from None
            return default

    r_half = col("r_half")
    k = len(r_half)
    flux = col("flux")
    peak_snr = col("peak_snr")
    snr = col("snr", np.full(k, np.inf))
    with np.errstate(invalid="ignore"):
        cand = np.isfinite(r_half) & (r_half > 0) & (flux > 0) & (peak_snr >= min_peak_snr)
    for name, bits in (("sep_flag", _STAR_BAD_SEP), ("flags", exclude_flags)):
        if name == "flags" and bits is None:
            bits = flag_value("EDGE", "MASKED", "BAD_PIXELS")
        try:
            values = np.asarray(catalogue[name]).astype(np.int64)
        except (KeyError, ValueError):
            continue
        cand &= (values & int(bits)) == 0
    if saturation is not None:
        raw = col("peak") + col("background", np.zeros(k))
        cand &= raw < saturation - 1e-5 * abs(saturation)
    pos = None
    if position_order > 0:
        xy = [col(c, np.full(k, np.nan)) for c in ("x", "y")]
        if np.all(np.isfinite(xy[0][cand])) and np.all(np.isfinite(xy[1][cand])):
            pos = xy

    return cand, r_half, snr, pos


def select_stars(
    catalogue,
    *,
    min_peak_snr: float = 30.0,
    column: str | None = None,
    saturation: float | None = None,
    nsigma: float = 3.0,
    window: float = 0.05,
    min_width: float = 0.003,
    min_stars: int = 3,
    exclude_flags: int | None = None,
    min_fraction: float = 0.25,
    position_order: int = 2,
) -> np.ndarray:
    """Select PSF stars on the stellar locus of size against magnitude.

    Point sources all have the PSF's size whatever their flux, so in ``log10 r_half``
    against magnitude they form a narrow horizontal band at the small-size end, while
    galaxies spread over larger sizes. Compact galaxies convolved with the PSF are only
    a little larger than it (0.1 dex for an exponential of half-light radius 0.45 times
    the PSF's FWHM), and where they outnumber the stars their sizes may crowd more
    densely than the stars'; where the PSF's size varies over the image (10 % is
    common) the stars' band is as wide as that gap. The algorithm:

    1. Candidates: finite ``r_half > 0`` and ``flux > 0``, ``peak_snr >= min_peak_snr``
       (paper section 2.4: stars of peak S/N > 30 make a good PSF), no SEP flag of
       blending, truncation, singular moments or masked aperture (``sep_flag``), none of
       ``exclude_flags`` in ``flags``, and, with ``saturation``, a raw peak
       ``peak + background`` below ``saturation`` (less a 1e-5 relative margin for the
       float32 rounding of SEP's peak).
    2. Locus: windows ``[s, s + 2 window]`` of ``s = log10 r_half`` over the candidates;
       the first (smallest-size) window holding at least ``min_fraction`` of the
       densest window's count (and ``min_stars``), then the densest window that starts
       within ``2 window`` of it: the smallest-size clump of sizes, not the most
       populous one, which compact galaxies may make.
    3. Band: an object lies on the locus when ``|s - c(x, y)| <= nsigma * sigma_i``, with
       ``sigma_i^2 = width^2 + (0.434 / snr_i)^2``: the measurement noise of
       ``log10 r_half`` (about ``0.434 / snr`` in simulations) added to an intrinsic width
       (pixelisation, what the centre does not follow) that is fitted so that the
       normalised deviations of the members have a robust (1.4826 MAD) sigma of 1, at
       least ``min_width``. The centre ``c`` is first the members' median, then (with
       ``x`` and ``y`` columns) a polynomial in the position of total degree up to
       ``position_order`` (as many terms as the members allow at 5 members a term),
       fitted to the members weighted by ``1 / sigma_i^2``: it follows the PSF's size
       over the image, so that the band is as narrow as the stars' noise and the compact
       galaxies, larger than the PSF where they are, fall outside it. Centre, width and
       membership are iterated from the window's members until stable.

    Parameters
    ----------
    catalogue : astropy.table.Table or mapping of arrays
        Output of :func:`detect` (``r_half``, ``flux``, ``peak_snr``, and if present
        ``snr``, ``sep_flag``, ``flags``, ``peak``, ``background``, ``x``, ``y``).
    min_peak_snr : float, optional
        Minimum peak signal-to-noise ratio. Default 30 (paper section 2.4).
    column : str, optional
        Name of a user-supplied star column (bool, or int where nonzero means star) that
        overrides the selection: its values are returned as a boolean array.
    saturation : float, optional
        Saturation level of the raw image (image units, background included).
    nsigma : float, optional
        Half-width of the band in sigmas. Default 3.
    window : float, optional
        Half-width in dex of the window that finds the locus. Default 0.05 (12%).
    min_width : float, optional
        Smallest intrinsic width of the locus in dex. Default 0.003 (0.7%).
    min_stars : int, optional
        Fewest candidates needed to define a locus; with fewer, nothing is selected (said
        in the log at INFO level). Default 3.
    exclude_flags : int, optional
        Bits of ``flags`` that disqualify a star; default EDGE | MASKED | BAD_PIXELS.
    min_fraction : float, optional
        In ``(0, 1]``: the smallest count, relative to the densest window's, of the
        window that finds the locus. Default 0.25: the stars are found below compact
        galaxies up to four times as dense in size; a clump of fewer objects below them
        (hot pixels, cosmic rays) is passed over.
    position_order : int, optional
        Highest total degree in ``(x, y)`` of the locus centre. Default 2; 0 for a
        centre constant over the image.

    Returns
    -------
    numpy.ndarray
        Boolean array, True for the selected stars.
    """
    if column is not None:
        try:
            values = np.asarray(catalogue[column])
        except (KeyError, ValueError, IndexError):
            raise ValueError(f"star column {column!r} not in the catalogue") from None
        if values.dtype == bool:
            return values.copy()
        if np.issubdtype(values.dtype, np.integer):
            return values != 0
        raise ValueError(f"star column {column!r} must be bool or int, got {values.dtype}")
    if not 0.0 < min_fraction <= 1.0:
        raise ValueError(f"min_fraction must be in (0, 1], got {min_fraction}")

    cand, r_half, snr, pos = _star_candidates(catalogue, min_peak_snr, saturation,
                                              exclude_flags, position_order)  # fmt: skip
    k = len(r_half)
    sel = np.zeros(k, dtype=bool)
    idx = np.flatnonzero(cand)
    if len(idx) < max(int(min_stars), 1):  # info: a caller says what it does instead
        log.info(
            "select_stars: %d candidate(s) with peak S/N >= %g, fewer than min_stars=%d: "
            "no star selected", len(idx), min_peak_snr, min_stars,
        )
        return sel
    s = np.log10(r_half[idx])
    with np.errstate(divide="ignore", invalid="ignore"):
        noise = np.where(snr[idx] > 0, 0.434 / snr[idx], np.inf)
    noise = np.nan_to_num(noise, nan=np.inf)
    member = _locus_window(s, window, min_fraction, int(min_stars))
    design = None if pos is None else _locus_design(pos[0][idx], pos[1][idx], position_order)
    centre = np.full(s.size, np.median(s[member]))
    settled = design is None  # the centre a polynomial in the position, where one is
    for _ in range(30):
        width = _locus_width(s[member] - centre[member], noise[member], min_width)
        new = np.abs(s - centre) <= nsigma * np.hypot(width, noise)
        if not new.any() or (settled and np.array_equal(new, member)):
            break
        member = new
        if design is not None:
            centre = _locus_centre(s, design, member, np.hypot(width, noise))
            settled = True
        else:
            centre[:] = np.median(s[member])
    sel[idx[member]] = True
    return sel


def _locus_window(s: np.ndarray, window: float, min_fraction: float, min_stars: int
                  ) -> np.ndarray:  # fmt: skip
    """The members of the window ``[s0, s0 + 2 window]`` that finds the stellar locus
    (:func:`select_stars`, step 2)."""
    ss = np.sort(s)
    counts = np.searchsorted(ss, ss + 2 * window, side="right") - np.arange(ss.size)
    need = min(int(counts.max()), max(min_stars, min_fraction * counts.max()))
    first = ss[np.flatnonzero(counts >= need)[0]]
    near = np.flatnonzero((ss >= first) & (ss <= first + 2 * window))
    start = ss[near[np.argmax(counts[near])]]
    return (s >= start) & (s <= start + 2 * window)


def _locus_design(x: np.ndarray, y: np.ndarray, order: int) -> np.ndarray:
    """``(n, p)`` monomials ``u^i v^j``, ``i + j <= order``, of the positions scaled to
    ``[-1, 1]`` over their range."""
    u = [(q - 0.5 * (q.max() + q.min())) / max(0.5 * np.ptp(q), 1.0) for q in (x, y)]
    return np.column_stack([u[0] ** i * u[1] ** (d - i)
                            for d in range(order + 1) for i in range(d, -1, -1)])  # fmt: skip


def _locus_centre(s: np.ndarray, design: np.ndarray, member: np.ndarray, sigma: np.ndarray
                  ) -> np.ndarray:  # fmt: skip
    """The locus centre at every candidate: a polynomial in the position fitted to the
    members weighted by ``1 / sigma^2``, of the highest degree with 5 members a term
    (the members' median with fewer than 15)."""
    n = int(member.sum())
    p = design.shape[1]
    order = int(round((np.sqrt(8 * p + 1) - 3) / 2))  # p = (order + 1)(order + 2) / 2
    while order > 0 and n < 5 * (order + 1) * (order + 2) // 2:
        order -= 1
    if order == 0:
        return np.full(s.size, np.median(s[member]))
    p = (order + 1) * (order + 2) // 2
    w = 1.0 / sigma[member]
    coef = np.linalg.lstsq(design[member, :p] * w[:, None], s[member] * w, rcond=None)[0]
    return design[:, :p] @ coef


def _locus_width(dev: np.ndarray, noise: np.ndarray, floor: float) -> float:
    """Smallest intrinsic width ``w >= floor`` with robust sigma of ``dev / hypot(w, noise)``
    at most 1 (the robust sigma falls as ``w`` grows, so bisect)."""

    def rsig(w):
        return 1.4826 * np.median(np.abs(dev) / np.hypot(w, noise))

    if rsig(floor) <= 1.0:
        return float(floor)
    lo, hi = floor, max(floor, 1.4826 * float(np.median(np.abs(dev))))
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if rsig(mid) <= 1.0 else (mid, hi)
    return float(hi)


# --------------------------------------------------------------------------------------
# close pairs


def close_pairs(
    x, y, *, flux=None, stamp_size: int = 32, faint_ratio: float | None = None
) -> np.ndarray:
    """Objects with another detected object inside their postage stamp (paper section 2.3).

    Object ``i`` and ``j`` are a close pair when ``|x_i - x_j| < stamp_size / 2`` and
    ``|y_i - y_j| < stamp_size / 2``; the paper rejects every such object. With
    ``faint_ratio`` (the improvement the paper's conclusions suggest), an object is kept
    when every neighbour in its stamp is fainter than ``faint_ratio`` times its own flux;
    the faint neighbours themselves are still flagged. Pairs are found with a KD-tree in
    the Chebyshev metric, so the cost grows as ``N log N``.

    Parameters
    ----------
    x, y : array_like
        Object positions in pixels.
    flux : array_like, optional
        Object fluxes; required with ``faint_ratio``.
    stamp_size : int, optional
        Postage-stamp side in pixels. Default 32 (the paper's).
    faint_ratio : float, optional
        In ``(0, 1]``; None (default) flags every member of a pair.

    Returns
    -------
    numpy.ndarray
        Boolean array, True for objects to reject as close pairs.
    """
    x = np.asarray(x, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    if x.shape != y.shape:
        raise ValueError(f"x and y differ in length: {x.size} and {y.size}")
    k = x.size
    out = np.zeros(k, dtype=bool)
    if faint_ratio is not None:
        if flux is None:
            raise ValueError("faint_ratio needs the fluxes (flux=...)")
        if not 0 < faint_ratio <= 1:
            raise ValueError(f"faint_ratio must be in (0, 1], got {faint_ratio}")
        flux = np.asarray(flux, dtype=np.float64).ravel()
        if flux.size != k:
            raise ValueError(f"flux has {flux.size} values for {k} positions")
    if k < 2:
        return out
    half = stamp_size / 2.0
    ok = np.isfinite(x) & np.isfinite(y)
    pos = np.flatnonzero(ok)
    if pos.size < 2:
        return out
    tree = cKDTree(np.column_stack([x[pos], y[pos]]))
    pairs = tree.query_pairs(half, p=np.inf, output_type="ndarray")
    if pairs.size == 0:
        return out
    i, j = pos[pairs[:, 0]], pos[pairs[:, 1]]
    strict = (np.abs(x[i] - x[j]) < half) & (np.abs(y[i] - y[j]) < half)
    i, j = i[strict], j[strict]
    if faint_ratio is None:
        out[i] = True
        out[j] = True
        return out
    # i is spoiled by j unless j is fainter than faint_ratio * flux_i (NaN spoils)
    with np.errstate(invalid="ignore"):
        i_spoiled = ~(flux[j] < faint_ratio * flux[i])
        j_spoiled = ~(flux[i] < faint_ratio * flux[j])
    out[i[i_spoiled]] = True
    out[j[j_spoiled]] = True
    return out


# --------------------------------------------------------------------------------------
# saturation


def saturation_level(header, level: float | None = None) -> float | None:
    """The saturation level of an image, in its data units (ADU).

    ``level`` if given, else the header's ``SATURATE`` card, which SExtractor reads for
    its ``SATUR_LEVEL`` (``SATUR_KEY``); ``None`` when neither gives a positive finite
    number (a card that is not one is ignored with a warning).

    Parameters
    ----------
    header : astropy.io.fits.Header or mapping or None
        The image's header.
    level : float, optional
        A level that overrides the card (``Config.saturation``).

    Returns
    -------
    float or None
        The level, in the units of the raw pixel values (before the background is
        subtracted), or ``None``: no saturation cut.
    """
    if level is not None:
        return float(level)
    card = None if header is None else header.get("SATURATE")
    if card is None:
        return None
    try:
        val = float(card)
    except (TypeError, ValueError):
        val = float("nan")
    if not (np.isfinite(val) and val > 0):
        log.warning("SATURATE card %r is not a positive number: no saturation cut", card)
        return None
    return val


def grow_mask(mask, grow: int) -> np.ndarray:
    """``mask`` grown by ``grow`` px (Chebyshev distance: a square of side ``2 grow + 1``
    about every masked pixel).

    Parameters
    ----------
    mask : array_like
        2-D boolean map, True where masked.
    grow : int
        Margin in pixels (0: the mask as it is).

    Returns
    -------
    numpy.ndarray
        Boolean map of the same shape.
    """
    m = np.asarray(mask, dtype=bool)
    g = int(grow)
    if g <= 0 or not m.any():
        return m.copy()
    return binary_dilation(m, structure=np.ones((2 * g + 1, 2 * g + 1), dtype=bool))


def saturation_mask(image, level: float | None, grow: int = 2) -> np.ndarray:
    """Pixels at or above the saturation level ``level``, the mask grown by ``grow`` px.

    The core of a saturated star or a bleed trail is flat-topped, which no galaxy model
    (nor the PSF) fits: the fit gives a model of absurd flux and size. These pixels are
    masked before the background, the detection and the fit, with a margin where the
    charge has spilled and the PSF's core is clipped.

    Parameters
    ----------
    image : array_like
        2-D raw image (data units, background included), indexed ``[y, x]``.
    level : float or None
        Saturation level in the image's units (:func:`saturation_level`); ``None``: no
        pixel is saturated.
    grow : int, optional
        Margin in pixels (:func:`grow_mask`). Default 2.

    Returns
    -------
    numpy.ndarray
        Boolean ``(ny, nx)`` map, True where masked (non-finite pixels are not included:
        they are masked apart).
    """
    data = np.asarray(image)
    if level is None:
        return np.zeros(data.shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        hit = np.isfinite(data) & (data >= level)
    return grow_mask(hit, grow)
