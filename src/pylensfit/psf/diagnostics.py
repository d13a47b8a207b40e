"""Size and shape of a PSF image: effective FWHM and GalSim's adaptive moments."""

from __future__ import annotations

import numpy as np


def adaptive_moments(image: np.ndarray) -> tuple[float, float, float]:
    """``(sigma, e1, e2)`` from GalSim's adaptive moments; NaN if they fail."""
    import galsim  # galsim: heavy import, only for the adaptive moments

    c = image.shape[0] // 2
    try:
        m = galsim.hsm.FindAdaptiveMom(
            galsim.Image(np.ascontiguousarray(image, dtype=np.float64), scale=1.0),
            guess_centroid=galsim.PositionD(c + 1.0, c + 1.0),
            strict=True,
        )
    except galsim.GalSimError:
        return np.nan, np.nan, np.nan
    shape = m.observed_shape
    return float(m.moments_sigma), float(shape.g1), float(shape.g2)


def effective_fwhm(image: np.ndarray, oversample: int = 8) -> float:
    """``2 sqrt(A / pi)``, ``A`` the area above half maximum of the band-limited image."""
    from scipy.signal import resample  # scipy.signal: start-up cost (~0.5 s), only for the FWHM

    n = image.shape[0]
    fine = resample(resample(image, n * oversample, axis=0), n * oversample, axis=1)
    peak = fine.max()
    if not peak > 0:
        return np.nan
    area = np.count_nonzero(fine >= 0.5 * peak) / oversample**2
    return float(2.0 * np.sqrt(area / np.pi))


def psf_diagnostics(image: np.ndarray) -> dict[str, float]:
    """Size and shape of a PSF image, as :class:`PSFResult` records them.

    Parameters
    ----------
    image : numpy.ndarray
        Square PSF image (pixel response included), centred on element
        ``[n//2, n//2]``.

    Returns
    -------
    dict
        ``fwhm``: ``2 sqrt(A / pi)`` with ``A`` the area above half maximum of the
        band-limited image (pixels); ``sigma``, ``e1``, ``e2``: GalSim's adaptive
        moments (size in pixels; ellipticity ``(a - b) / (a + b)``), NaN if they fail.
    """
    sigma, e1, e2 = adaptive_moments(image)
    return {"fwhm": effective_fwhm(image), "sigma": sigma, "e1": e1, "e2": e2}
