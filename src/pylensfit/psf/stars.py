"""Candidate PSF stars: checked inputs, cutouts, the tests a star must pass
(:class:`StarChecks`) and the reasons a star is rejected (:data:`REASONS`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Rejection reasons written in :attr:`PSFResult.reason` (``''`` for a used star).
REASONS = {
    "position": "non-finite catalogue position",
    "edge": "cutout leaves the image",
    "nonfinite": "non-finite pixels in the cutout",
    "weight": "zero-weight pixels in the cutout",
    "noise": "bad noise_sigma",
    "snr": "signal-to-noise below min_snr",
    "peak": "no centroid peak",
    "shift": "centroid more than max_shift from the catalogue position",
    "flux": "non-positive flux",
    "correlation": "low correlation with the stack",
    "chi2": "poor fit to the stack (chi2)",
}


@dataclass(frozen=True)
class StarChecks:
    """How candidate PSF stars are centred, measured and rejected.

    :func:`stack_psf` and :meth:`PolynomialPSF.fit <pylensfit.psfmodel.PolynomialPSF.fit>`
    take these as keywords of the same names (``clip`` for ``max_chi2`` in the latter).

    Attributes
    ----------
    min_correlation : float
        Threshold on the noise-debiased normalised cross-correlation
        ``<s, P> / sqrt((|s|^2 - N sigma^2) (|P|^2 - N var P))`` of a star ``s`` with the
        PSF ``P`` over the ``N = size^2`` pixels. For isolated stars it scatters about 1
        by 0.04, 0.005 and 0.001 at peak S/N 10, 30 and 60 (GalSim Moffat fields), so 0.9
        loses about 0.1% of stars at peak S/N 10 and none above; it rejects blends of
        two comparable stars and galaxies more extended than the PSF, whatever their S/N.
    max_chi2 : float or None
        Threshold on the reduced chi-square of ``s - flux P`` over the core pixels
        (where ``P`` exceeds ``core_level`` of its peak, ~90 pixels for a 3-pixel FWHM),
        with per-pixel variance ``sigma^2 + flux^2 var P + (model_error flux P)^2``. For
        stars it is 1 +- 0.15, so 2 is a ~6-sigma cut; it catches contaminants bright
        enough to bias the PSF but too compact for the correlation test (small galaxies,
        close binaries, cosmic rays). ``None`` disables it.
    model_error : float
        Fractional per-pixel error allowed to ``P`` in the chi-square (PSF variation,
        aliasing), so that very bright stars are not rejected for the PSF's own
        imperfections.
    core_level : float
        Fraction of the PSF's peak that delimits the core of the chi-square test.
    max_shift : float
        Largest distance in pixels between the catalogue position and the measured
        centre.
    min_snr : float
        Smallest Gaussian matched-filter signal-to-noise of a star.
    centroid_sigma : float
        Width in pixels of the Gaussian whose cross-correlation defines the centre of
        the stars and of the PSF (about the PSF's own sigma is best).
    margin : int
        Extra pixels on each side of the cutouts (at least ``max_shift + 1``).

    Raises
    ------
    ValueError
        If ``centroid_sigma`` or ``max_shift`` is not positive, or ``margin`` negative.
    """

    min_correlation: float = 0.9
    max_chi2: float | None = 2.0
    model_error: float = 0.01
    core_level: float = 0.01
    max_shift: float = 2.0
    min_snr: float = 10.0
    centroid_sigma: float = 2.0
    margin: int = 4

    def __post_init__(self):
        if not (self.centroid_sigma > 0 and self.max_shift > 0 and self.margin >= 0):
            raise ValueError("centroid_sigma and max_shift must be positive, margin >= 0")

    def cutout_side(self, size: int) -> int:
        """Side in pixels of the (odd) cutouts for a PSF of side ``size``."""
        return size + 2 * int(self.margin) + 1


def star_cutouts(image, weight, x, y, big):
    """``big x big`` cutouts about the nearest pixel of each position, and reasons."""
    ny, nx = image.shape
    n = x.size
    reason = np.full(n, "", dtype=object)
    finite = np.isfinite(x) & np.isfinite(y)
    reason[~finite] = REASONS["position"]
    ix = np.where(finite, np.rint(np.where(finite, x, 0.0)), 0).astype(np.int64)
    iy = np.where(finite, np.rint(np.where(finite, y, 0.0)), 0).astype(np.int64)
    lx = ix - big // 2
    ly = iy - big // 2
    inside = finite & (lx >= 0) & (ly >= 0) & (lx + big <= nx) & (ly + big <= ny)
    reason[finite & ~inside] = REASONS["edge"]
    idx = np.flatnonzero(inside)
    ar = np.arange(big)
    rows = (ly[idx, None] + ar)[:, :, None]
    cols = (lx[idx, None] + ar)[:, None, :]
    stamps = image[rows, cols]
    bad = ~np.isfinite(stamps).all(axis=(1, 2))
    reason[idx[bad]] = REASONS["nonfinite"]
    if weight is not None:
        wst = weight[rows, cols]
        zero = ~(wst > 0).all(axis=(1, 2)) & ~bad
        reason[idx[zero]] = REASONS["weight"]
    return stamps, idx, ix, iy, reason


def check_star_inputs(image, x, y, weight, size: int):
    """An image, star positions and weight map as float arrays, checked (``ValueError``:
    an image not 2-D, positions of unequal length, a weight map of another shape, a
    PSF side under 4)."""
    image = np.asarray(image, dtype=float)
    if image.ndim != 2:
        raise ValueError(f"image must be 2-D, got shape {image.shape}")
    x = np.atleast_1d(np.asarray(x, dtype=float))
    y = np.atleast_1d(np.asarray(y, dtype=float))
    if x.ndim != 1 or x.shape != y.shape:
        raise ValueError(f"x and y must be 1-D of equal length, got {x.shape} and {y.shape}")
    if weight is not None:
        weight = np.asarray(weight, dtype=float)
        if weight.shape != image.shape:
            raise ValueError(f"weight shape {weight.shape} differs from image {image.shape}")
    if size < 4:
        raise ValueError(f"size must be at least 4, got {size}")
    return image, x, y, weight
