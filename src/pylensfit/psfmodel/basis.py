"""The polynomial basis of :class:`~pylensfit.psfmodel.PolynomialPSF`, and the drawing
helpers every model shares: positions checked, images re-centred by the convention,
their adaptive moments."""

from __future__ import annotations

import numpy as np

from .._util import newton_peak, rfft_frequencies
from ..psf import PSFError
from ..psf.diagnostics import adaptive_moments
from ..psf.fourier import gaussian_ft, gaussian_peak

CHUNK = 1024  # positions drawn at once (bounds the memory of the Fourier re-centring)


def n_terms(order: int) -> int:
    """Number of monomials ``u^i v^j`` with ``i + j <= order``."""
    return (order + 1) * (order + 2) // 2


def exponents(order: int) -> list[tuple[int, int]]:
    """``(i, j)`` of the monomials ``u^i v^j``, by total degree then by power of ``v``."""
    return [(d - j, j) for d in range(order + 1) for j in range(d + 1)]


def design(u: np.ndarray, v: np.ndarray, order: int) -> np.ndarray:
    """``(n, n_terms)`` matrix of the monomials at normalised positions ``u, v``."""
    return np.stack([u**i * v**j for i, j in exponents(order)], axis=-1)


def positions(x, y) -> tuple[np.ndarray, np.ndarray, bool]:
    """Positions as float 1-D arrays, and whether they were scalars."""
    xa = np.asarray(x, dtype=float)
    ya = np.asarray(y, dtype=float)
    scalar = xa.ndim == 0 and ya.ndim == 0
    xa, ya = np.atleast_1d(xa), np.atleast_1d(ya)
    if xa.ndim != 1 or xa.shape != ya.shape:
        raise ValueError(f"x and y must be scalars or 1-D of equal length, got {xa.shape} "
                         f"and {ya.shape}")  # fmt: skip
    if not (np.all(np.isfinite(xa)) and np.all(np.isfinite(ya))):
        raise ValueError("x and y must be finite")
    return xa, ya, scalar


def phase(big: int) -> np.ndarray:
    """Phase ramp referencing an ``rfft2`` on ``big x big`` to element ``[big//2, big//2]``."""
    kx, ky, _ = rfft_frequencies(big)
    return np.exp(1j * (kx * (big // 2) + ky * (big // 2)))


def shift_ft(D: np.ndarray, X: np.ndarray, Y: np.ndarray, size: int) -> np.ndarray:
    """Images ``s(x + X)`` cropped to ``size``, from ``rfft2`` transforms referenced to the
    centre of their odd ``big x big`` frame (as :func:`pylensfit.psf.subpixel_shift`, with a
    separable phase ramp)."""
    big = D.shape[-2]
    kx, ky, _ = rfft_frequencies(big)
    c = big // 2
    ex = np.exp(1j * kx[0][None, :] * (X - c)[:, None])
    ey = np.exp(1j * ky[:, 0][None, :] * (Y - c)[:, None])
    img = np.fft.irfft2(D * ey[:, :, None] * ex[:, None, :], s=(big, big))
    lo = c - size // 2
    return img[:, lo : lo + size, lo : lo + size]


def recentre(D: np.ndarray, size: int, centroid_sigma: float, search: float | None = None):
    """Centre images by the convention, crop them to ``size``, scale them to unit sum.

    Each image's Gaussian cross-correlation peak is moved to the centre of the frame by
    an exact Fourier shift, the image cropped to ``size x size`` about it and scaled to
    unit sum.

    Parameters
    ----------
    D : numpy.ndarray
        ``(n, big, big//2 + 1)`` ``rfft2`` of odd ``big x big`` images, phase-referenced
        to element ``[big//2, big//2]``.
    size : int
        Side of the output.
    centroid_sigma : float
        Width of the Gaussian of the convention (pixels).
    search : float, optional
        Look for the peak by an integer search within this radius (pixels) before the
        Newton steps; by default Newton steps from the frame centre (for images known
        to be centred to a small fraction of a pixel).

    Returns
    -------
    out : numpy.ndarray
        ``(n, size, size)`` centred images.
    sx, sy : numpy.ndarray
        Offset in pixels of the peak before the shift (0 where no peak was found).
    total : numpy.ndarray
        Sum of each cropped image before the scaling.

    Raises
    ------
    PSFError
        If an image has a non-positive sum.
    """
    zero = np.zeros(len(D))
    if search is None:
        R = np.broadcast_to(gaussian_ft(D.shape[-2], centroid_sigma), D.shape[1:])[None]
        sx, sy, ok = newton_peak(D, R, zero, zero, n_steps=4)
    else:
        sx, sy, ok = gaussian_peak(D, centroid_sigma, zero, zero, search)
    sx, sy = np.where(ok, sx, 0.0), np.where(ok, sy, 0.0)
    out = shift_ft(D, sx, sy, size)
    total = out.sum(axis=(1, 2))
    if not np.all(total > 0):
        raise PSFError(f"{int(np.sum(~(total > 0)))} drawn PSF image(s) have a non-positive sum")
    return out / total[:, None, None], sx, sy, total


def moments_many(images: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """GalSim adaptive moments ``(sigma, e1, e2)`` of each of ``(n, s, s)`` images."""
    res = np.array([adaptive_moments(im) for im in images], dtype=float).reshape(-1, 3)
    return res[:, 0], res[:, 1], res[:, 2]
