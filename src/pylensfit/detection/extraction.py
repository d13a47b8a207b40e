"""Detecting and measuring the objects of an image: :func:`detect`."""

from __future__ import annotations

import numpy as np
from astropy.table import Table

from .background import Background, measure_background
from .inputs import as_image, bad_pixels, extract
from .measure import DetectionMaps, Photometry, catalogue_table, empty_table, measure_objects


def detect(image, *, weight=None, mask=None, threshold: float = 1.5, min_area: int = 5,
           deblend_nthresh: int = 32, deblend_cont: float = 0.005,
           background: Background | None = None, gain: float | None = None,
           zeropoint: float = 0.0, stamp_size: int = 32, aperture: float = 5.0,
           min_aperture: float = 3.0, max_aperture: float | None = None, windowed: bool = True,
           faint_ratio: float | None = None, filter_kernel: np.ndarray | None | str = "default",
           box: int = 64, filter_size: int = 3, mask_sources: bool = True) -> Table:  # fmt: skip
    """Detect and measure the objects of an image with SEP (SExtractor as a library).

    The background (``background``, or :func:`measure_background` with ``box`` and
    ``filter_size``) is subtracted, then pixels more than ``threshold`` noise sigmas above
    it in the filtered image, in connected groups of at least ``min_area``, make an object;
    blends are split by multi-threshold deblending. The noise sigma per pixel is
    ``1/sqrt(weight)`` when a weight map is given, else the background rms map. Each
    object is then measured on the background-subtracted image (``Background.subtract``):
    position, size, aperture flux and the flags of its stamp (:mod:`pylensfit.detection`).

    Parameters
    ----------
    image : array_like
        2-D image indexed ``[y, x]``, with sky background; any byte order.
    weight : array_like, optional
        Inverse-variance map ``1/sigma^2`` in image units; 0 marks unusable pixels.
    mask : array_like, optional
        Pixels with ``mask > 0`` are unusable (never detected, left out of sums).
    threshold, min_area : float, int
        Detection threshold in units of the per-pixel noise sigma (1.5), and the fewest
        pixels above it that make an object (5).
    deblend_nthresh, deblend_cont : int, float
        Number of deblending thresholds (32) and their minimum contrast (0.005; 1
        disables the deblending).
    background : Background, optional
        A background measured beforehand (by :func:`measure_background`).
    gain : float, optional
        Electrons per image unit, adding the objects' Poisson noise to ``flux_err``.
    zeropoint : float
        Magnitude zeropoint: ``mag = zeropoint - 2.5 log10(flux)``.
    stamp_size : int
        Postage-stamp side in pixels (paper: 32), for ``noise_sigma`` and ``flags``.
    aperture, min_aperture, max_aperture : float
        Photometry aperture radius in units of ``r_half`` (5), and its bounds in pixels
        (3, and by default ``stamp_size``).
    windowed : bool
        Refine positions with SEP's windowed centroid (``XWIN_IMAGE``; window sigma
        ``r_half / 1.175``); kept where it converges within ``max(1, r_half / 2)`` pixels
        of the barycentre and inside the object's footprint.
    faint_ratio : float, optional
        Passed to :func:`close_pairs` for the ``CLOSE_PAIR`` flag, with the isophotal
        fluxes ``flux_iso`` (the aperture fluxes of blended objects include their
        neighbours' light). Default None: every object with a neighbour in its stamp.
    filter_kernel : numpy.ndarray or None, optional
        Detection filter; default SEP's 3x3 pyramid, None for no filtering.
    box, filter_size, mask_sources : int, int, bool
        Background box and filter sizes, and whether objects are masked, when
        ``background`` is not given (:func:`measure_background`).

    Returns
    -------
    astropy.table.Table
        One row per object, the columns of :mod:`pylensfit.detection` (with their units
        and descriptions); an image without objects gives an empty table with these
        columns. ``meta`` holds the global background (``BKG``), rms (``BKGRMS``),
        ``THRESH``, ``ZP`` and ``STAMP``.

    Raises
    ------
    ValueError
        If the image is not 2-D, has no finite pixel, or a map has another shape.
    """
    maps = detect_inputs(image, weight, mask, background, box, filter_size, mask_sources)
    n, max_aperture = stamp_and_aperture(stamp_size, min_aperture, max_aperture)
    t = detect_meta_table(maps.background, threshold, zeropoint, n)
    if maps.bad_det.all():
        return t
    objs = run_extract(maps, threshold, min_area, deblend_nthresh, deblend_cont, filter_kernel)
    if len(objs) == 0:
        return t
    phot = Photometry(aperture, min_aperture, max_aperture, windowed, gain, zeropoint)
    cols = measure_objects(objs, maps, phot, n, faint_ratio)
    return catalogue_table(objs, cols, t.meta)


def detect_inputs(image, weight, mask, background: Background | None, box: int,
                  filter_size: int, mask_sources: bool) -> DetectionMaps:  # fmt: skip
    """Check and normalise :func:`detect`'s image, maps and background (measured here
    when not given), and make the maps of the detection."""
    data = as_image(image)
    bad, w = bad_pixels(data, mask, weight)
    if not np.isfinite(data).any():
        raise ValueError("image has no finite pixel: nothing to detect")
    nonfinite = ~np.isfinite(data)
    if background is None:
        background = measure_background(data, mask=mask, weight=weight, box=box,
                                        filter_size=filter_size,
                                        mask_sources=mask_sources)  # fmt: skip
    elif not isinstance(background, Background):
        raise ValueError("background must be a Background from measure_background")
    elif background.shape != data.shape:
        raise ValueError(f"background shape {background.shape} differs from {data.shape}")
    sub = data - background.back
    sub[bad] = 0.0
    if w is not None:
        with np.errstate(divide="ignore"):
            sigma = np.where(bad, np.inf, 1.0 / np.sqrt(np.where(bad, 1.0, w)))
    else:
        sigma = np.array(background.rms, dtype=np.float64)
    bad_det = bad | ~(sigma > 0) | ~np.isfinite(sigma)
    err = np.where(bad_det, 1.0, sigma)  # masked pixels: SEP gives them infinite noise
    return DetectionMaps(background=background, bad=bad, nonfinite=nonfinite, weight=w, sub=sub,
                         sigma=sigma, bad_det=bad_det, err=err)  # fmt: skip


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


def run_extract(maps: DetectionMaps, threshold: float, min_area: int, deblend_nthresh: int,
                deblend_cont: float, filter_kernel: np.ndarray | None | str
                ) -> np.ndarray:  # fmt: skip
    """Run SEP's extraction and deblending with :func:`detect`'s options."""
    kw = dict(
        minarea=int(min_area),
        deblend_nthresh=int(deblend_nthresh),
        deblend_cont=float(deblend_cont),
    )
    if not (isinstance(filter_kernel, str) and filter_kernel == "default"):
        kw["filter_kernel"] = filter_kernel
    return extract(maps.sub, float(threshold), maps.err, maps.bad_det, **kw)
