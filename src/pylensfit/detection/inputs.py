"""The images as SEP takes them: native float64 maps, the unusable pixels, SEP's flags
(:data:`SEP_FLAGS`) and its extraction with its buffers grown on demand."""

from __future__ import annotations

import numpy as np
import sep

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


def as_image(image, name: str = "image") -> np.ndarray:
    """A native-byte-order float64 copy of a 2-D array (FITS data are big-endian)."""
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D array, got {arr.ndim} dimension(s) {arr.shape}")
    if arr.shape[0] < 2 or arr.shape[1] < 2:
        raise ValueError(f"{name} must be at least 2 x 2 pixels, got shape {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
    return np.array(arr, dtype=np.float64, order="C")  # native order, a copy


def bad_pixels(image: np.ndarray, mask, weight) -> tuple[np.ndarray, np.ndarray | None]:
    """Boolean map of unusable pixels, and the weight map as native float64 (or None)."""
    bad = ~np.isfinite(image)
    if mask is not None:
        m = as_image(mask, "mask")
        if m.shape != image.shape:
            raise ValueError(f"mask shape {m.shape} differs from image shape {image.shape}")
        bad |= ~(m <= 0)  # mask > 0, or non-finite mask values
    w = None
    if weight is not None:
        w = as_image(weight, "weight")
        if w.shape != image.shape:
            raise ValueError(f"weight shape {w.shape} differs from image shape {image.shape}")
        bad |= ~(w > 0) | ~np.isfinite(w)
    return bad, w


def extract(data, thresh, err, bad, **kwargs):
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
