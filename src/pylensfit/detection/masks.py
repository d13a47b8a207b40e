"""Saturated pixels: the saturation level of an image and the mask of its saturated
pixels, grown by a margin."""

from __future__ import annotations

import logging

import numpy as np
from scipy.ndimage import binary_dilation

log = logging.getLogger("pylensfit.detection")


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
