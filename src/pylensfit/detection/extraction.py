"""Detecting and measuring the objects of an image: :func:`detect`."""

from __future__ import annotations

import numpy as np
from astropy.table import Table

from .background import Background, measure_background
from .inputs import as_image, bad_pixels, extract
from .measure import (
    aperture_photometry,
    catalogue_table,
    empty_table,
    pixel_quantities,
    refine_positions,
    stamp_quantities,
)


def detect_inputs(
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
    data = as_image(image)
    bad, w = bad_pixels(data, mask, weight)
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


def stamp_and_aperture(
    stamp_size: int, min_aperture: float, max_aperture: float | None
) -> tuple[int, float]:
    """The stamp side as an int (checked >= 2) and the aperture cap (default: the stamp)."""
    n = int(stamp_size)
    if n < 2:
        raise ValueError(f"stamp_size must be >= 2, got {stamp_size}")
    if max_aperture is None:
        max_aperture = float(max(n, min_aperture))
    return n, max_aperture


def detection_maps(
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


def detect_meta_table(
    background: Background, threshold: float, zeropoint: float, n: int
) -> Table:
    """The empty catalogue with the global background, threshold, zeropoint and stamp in meta."""
    t = empty_table()
    t.meta.update(
        BKG=background.global_back,
        BKGRMS=background.global_rms,
        THRESH=float(threshold),
        ZP=float(zeropoint),
        STAMP=n,
    )
    return t


def run_extract(
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
    return extract(sub, float(threshold), err, bad_det, **kw)


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
    data, bad, w, nonfinite, background = detect_inputs(
        image, weight, mask, background, box, filter_size, mask_sources
    )
    n, max_aperture = stamp_and_aperture(stamp_size, min_aperture, max_aperture)
    sub, sigma, bad_det, err = detection_maps(data, bad, w, background)
    t = detect_meta_table(background, threshold, zeropoint, n)
    if bad_det.all():
        return t
    objs = run_extract(
        sub, threshold, err, bad_det, min_area, deblend_nthresh, deblend_cont, filter_kernel
    )
    if len(objs) == 0:
        return t
    x, y, r0 = refine_positions(sub, objs, bad_det, min_aperture, max_aperture, windowed)
    sep_flag = objs["flag"].astype(np.int32)
    rap, flux, flux_err, r_half, sep_flag = aperture_photometry(
        sub, x, y, r0, sigma, bad_det, sep_flag, aperture, min_aperture, max_aperture, gain
    )
    pix = pixel_quantities(objs, x, y, flux, flux_err, sigma, bad_det, background, zeropoint)
    flags, noise_sigma = stamp_quantities(
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
    return catalogue_table(objs, cols, t.meta)
