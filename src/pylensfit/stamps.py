"""Postage stamps about catalogue positions, with the reasons a stamp cannot be fitted.

Policy (paper section 2.3 leaves it open):

* a stamp is ``stamp_size`` pixels square, its element ``[N//2, N//2]`` on the pixel
  nearest the object's position; the exact position goes to the fit as the centre of
  the position prior;
* a stamp that crosses the image edge is flagged ``EDGE`` and not fitted (its missing
  pixels would bias the model's Fourier modes);
* a stamp holding a masked pixel (mask > 0, or weight 0) is flagged ``MASKED``, and one
  holding a non-finite pixel ``BAD_PIXELS``; neither is fitted. Masking a pixel inside
  a Fourier-space fit would need the model's real-space rendering, and a survey loses
  only the few per cent of galaxies that overlap a masked region;
* pixels outside the image are zero in the returned stamps, and flagged pixels are kept
  as they are so that the stamps can be inspected.
"""

from __future__ import annotations

import numpy as np

from ._kernels_nb import add_patches_nb
from .flags import flag_value

__all__ = ["add_patches", "cut_stamps", "patch_origins"]


def cut_stamps(
    image: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    size: int,
    *,
    bad: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cut ``size x size`` stamps about positions ``(x, y)``.

    Parameters
    ----------
    image : numpy.ndarray
        2-D background-subtracted image, indexed ``[y, x]``.
    x, y : numpy.ndarray
        Object positions, 0-based pixels (pixel centres on integers).
    size : int
        Stamp side.
    bad : numpy.ndarray, optional
        Boolean map of masked (or zero-weight) pixels.

    Returns
    -------
    stamps : numpy.ndarray
        ``(n, size, size)`` float64 stamps.
    cx, cy : numpy.ndarray
        The positions in stamp pixels.
    flags : numpy.ndarray
        ``EDGE``, ``MASKED`` and ``BAD_PIXELS`` bits (:mod:`pylensfit.flags`).
    """
    image = np.asarray(image)
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    ny, nx = image.shape
    n = x.size
    ix0, iy0 = patch_origins(x, y, size)
    flags = np.zeros(n, dtype=np.int32)
    inside = (ix0 >= 0) & (iy0 >= 0) & (ix0 + size <= nx) & (iy0 + size <= ny)
    flags[~inside] |= flag_value("EDGE")
    off = np.arange(size)
    rows = iy0[:, None, None] + off[None, :, None]
    cols = ix0[:, None, None] + off[None, None, :]
    valid = (rows >= 0) & (rows < ny) & (cols >= 0) & (cols < nx)
    r = np.clip(rows, 0, ny - 1)
    c = np.clip(cols, 0, nx - 1)
    stamps = np.where(valid, image[r, c], 0.0).astype(np.float64)
    nonfinite = ~np.isfinite(stamps)
    flags[nonfinite.any(axis=(1, 2))] |= flag_value("BAD_PIXELS")
    if bad is not None:
        masked = np.where(valid, np.asarray(bad, dtype=bool)[r, c], False)
        flags[masked.any(axis=(1, 2))] |= flag_value("MASKED")
    return stamps, x - ix0, y - iy0, flags


def patch_origins(x: np.ndarray, y: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Image pixel of element ``[0, 0]`` of the ``size x size`` stamps about ``(x, y)``.

    The convention of :func:`cut_stamps`: element ``[size//2, size//2]`` on the pixel
    nearest the position.
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    return (np.floor(x + 0.5).astype(np.int64) - size // 2,
            np.floor(y + 0.5).astype(np.int64) - size // 2)  # fmt: skip


def add_patches(canvas: np.ndarray, patches: np.ndarray, ix0: np.ndarray, iy0: np.ndarray) -> None:
    """Add ``(m, M, M)`` patches into ``canvas`` in place, element ``[0, 0]`` of patch ``k``
    on pixel ``(ix0[k], iy0[k])``; what falls outside the canvas is dropped. Overlapping
    patches add up, in the order of ``numpy.add.at`` over the patches' elements (compiled:
    :func:`~pylensfit._kernels_nb.add_patches_nb`)."""
    patches = np.ascontiguousarray(patches)
    if patches.shape[0]:
        add_patches_nb(canvas, patches, np.asarray(ix0, dtype=np.int64),
                       np.asarray(iy0, dtype=np.int64))  # fmt: skip
