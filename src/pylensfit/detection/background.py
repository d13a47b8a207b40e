"""The sky background and its noise (:func:`measure_background`, :class:`Background`)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import sep

from .inputs import as_image, bad_pixels, extract

log = logging.getLogger("pylensfit.detection")


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
        data = as_image(image)
        if data.shape != self.shape:
            raise ValueError(f"image shape {data.shape} differs from background {self.shape}")
        data -= self.back
        data[self.bad] = 0.0
        return data


class BackgroundGrid(NamedTuple):
    """The image as SEP's background takes it: native float64 with the unusable pixels
    (``bad``) set to 0, and the box (``bh x bw``) and filter (``fw``) sides in pixels and
    boxes."""

    data: np.ndarray
    bad: np.ndarray
    bh: int
    bw: int
    fw: int

    def sep_background(self, mask: np.ndarray) -> sep.Background:
        """SEP's background of :attr:`data` with the pixels of ``mask`` left out."""
        return sep.Background(self.data, mask=mask, bw=self.bw, bh=self.bh, fw=self.fw,
                              fh=self.fw)  # fmt: skip


def measure_background(image, *, mask=None, weight=None, box: int = 64, filter_size: int = 3,
                       mask_sources: bool = True, source_threshold: float = 3.0,
                       source_radius: float = 6.0, rescale_rms: bool = True
                       ) -> Background:  # fmt: skip
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
    box : int
        Background box side in pixels (clipped to the image size).
    filter_size : int
        Median-filter size in boxes.
    mask_sources : bool
        Mask detected objects and measure again.
    source_threshold : float
        Detection threshold (in rms) of the objects masked.
    source_radius : float
        Masked ellipse size in units of the objects' ``a``, ``b``.
    rescale_rms : bool
        Rescale the rms map to the robust sigma of the sky pixels.

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
    grid = background_grid(image, mask, weight, box, filter_size)
    bkg, sky = grid.sep_background(grid.bad), ~grid.bad
    if mask_sources:
        bkg, sky = mask_objects(grid, bkg, source_threshold, source_radius)
    back = np.asarray(bkg.back(), dtype=np.float64)
    rms = np.asarray(bkg.rms(), dtype=np.float64)
    scale = rms_scale(grid.data, back, rms, sky) if rescale_rms else 1.0
    return Background(back=back, rms=rms * scale, global_back=float(bkg.globalback),
                      global_rms=float(bkg.globalrms) * scale, bad=grid.bad)  # fmt: skip


def background_grid(image, mask, weight, box: int, filter_size: int) -> BackgroundGrid:
    """The checked image and box sides of :func:`measure_background` (``ValueError`` for
    an image with no usable pixel or a box or filter side under 1)."""
    data = as_image(image)
    bad, _ = bad_pixels(data, mask, weight)
    if bad.all():
        if not np.isfinite(data).any():
            raise ValueError("image has no finite pixel: cannot measure a background")
        raise ValueError("every pixel is masked or has zero weight: cannot measure a background")
    box = int(box)
    filter_size = int(filter_size)
    if box < 1 or filter_size < 1:
        raise ValueError(f"box and filter_size must be >= 1, got {box} and {filter_size}")
    data[bad] = 0.0  # SEP ignores masked pixels but must not see NaN
    return BackgroundGrid(data, bad, min(box, data.shape[0]), min(box, data.shape[1]),
                          filter_size)  # fmt: skip


def mask_objects(grid: BackgroundGrid, bkg: sep.Background, threshold: float, radius: float
                 ) -> tuple[sep.Background, np.ndarray]:  # fmt: skip
    """The background measured again with the objects detected above ``threshold`` rms on
    ``bkg`` masked out to ``radius`` times their isophotal ellipses, and the map of the sky
    pixels left (``bkg`` and the unmasked pixels where there is none, or where the mask
    would leave no background box half free)."""
    data, bad = grid.data, grid.bad
    sky = ~bad
    rms = bkg.rms()
    ok = ~bad & (rms > 0) & np.isfinite(rms)
    if not ok.any():
        return bkg, sky
    sub = np.where(ok, data - bkg.back(), 0.0)
    objs = extract(sub, float(threshold), np.where(ok, rms, 1.0), ~ok)
    if not len(objs):
        return bkg, sky
    src = np.zeros(data.shape, dtype=bool)
    sep.mask_ellipse(src, objs["x"], objs["y"], objs["a"], objs["b"], objs["theta"],
                     r=float(radius))  # fmt: skip
    if not usable_boxes(bad | src, grid.bh, grid.bw):
        log.warning(
            "masking the objects (to %g times their isophotal ellipses) leaves "
            "no %d x %d background box half free: background measured "
            "without the object mask", radius, grid.bw, grid.bh,
        )
        return bkg, sky
    sky = ~(bad | src)
    return grid.sep_background(~sky), sky


def rms_scale(data: np.ndarray, back: np.ndarray, rms: np.ndarray, sky: np.ndarray) -> float:
    """The robust sigma (1.4826 MAD) of ``(data - back) / rms`` over the sky pixels, the
    factor that makes the rms map unbiased for Gaussian noise (1 with fewer than 100 sky
    pixels or no positive value)."""
    sky = sky & (rms > 0) & np.isfinite(rms)
    if sky.sum() < 100:
        return 1.0
    r = (data[sky] - back[sky]) / rms[sky]
    scale = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    return scale if np.isfinite(scale) and scale > 0 else 1.0


def usable_boxes(masked: np.ndarray, bh: int, bw: int) -> bool:
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
