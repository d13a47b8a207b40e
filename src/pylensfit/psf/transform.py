"""The PSF as the likelihood engine uses it: its transform on a stamp's frequencies.

The PSF image includes the pixel response (it is a star image), so the observed
model is ``M_k = G_k P_k`` on the stamp's DFT frequencies with no extra pixel factor.
This assumes that the PSF band-limits the data at the pixel Nyquist frequency
(paper section 2.4); aliasing of modes above Nyquist is not modelled.
"""

from __future__ import annotations

import numpy as np

from .._util import rfft_frequencies


class PSFError(ValueError):
    """A PSF image that cannot be used."""


def centre_on_stamp(image: np.ndarray, n: int) -> np.ndarray:
    """Crop or zero-pad ``image`` to ``n x n``, moving element ``[s//2, s//2]`` to the centre."""
    image = np.asarray(image, dtype=float)
    out = np.zeros((n, n))
    src = []
    dst = []
    for size in image.shape:
        lo = size // 2 - n // 2  # source index that lands on destination 0
        s0, s1 = max(lo, 0), min(lo + n, size)
        src.append(slice(s0, s1))
        dst.append(slice(s0 - lo, s1 - lo))
    out[dst[0], dst[1]] = image[src[0], src[1]]
    return out


def psf_transform(psf: np.ndarray, n: int) -> np.ndarray:
    """DFT of a PSF image on an ``n x n`` stamp, phase-referenced to its centre.

    Parameters
    ----------
    psf : numpy.ndarray
        2-D PSF image of any size and normalisation, centred on element
        ``[s//2, s//2]``, including the pixel response.
    n : int
        Stamp side in pixels.

    Returns
    -------
    numpy.ndarray
        Complex ``(n, n // 2 + 1)`` array ``P_k`` normalised to ``P_0 = 1``.

    Raises
    ------
    PSFError
        If the image is not 2-D, has non-finite values or a non-positive sum.
    """
    psf = np.asarray(psf, dtype=float)
    if psf.ndim != 2:
        raise PSFError(f"PSF image must be 2-D, got shape {psf.shape}")
    if not np.all(np.isfinite(psf)):
        raise PSFError("PSF image has non-finite pixels")
    img = centre_on_stamp(psf, n)
    total = img.sum()
    if not total > 0:
        raise PSFError(f"PSF image has non-positive total flux ({total:g}) within {n}x{n}")
    kx, ky, _ = rfft_frequencies(n)
    c = n // 2
    return np.fft.rfft2(img / total) * np.exp(1j * (kx * c + ky * c))
