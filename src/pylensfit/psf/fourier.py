"""Fourier helpers of the star stacks: padding, exact sub-pixel shifts, Gaussian centring.

A star or PSF image is centred on the peak of its cross-correlation with a round
Gaussian (the package's centre convention) and moved by an exact Fourier (periodic
sinc) shift; these are the pieces :func:`~pylensfit.psf.stack_psf` and the PSF models
of :mod:`pylensfit.psfmodel` share.
"""

from __future__ import annotations

import numpy as np

from .._util import newton_peak, rfft_frequencies


def pad_to(images: np.ndarray, n: int) -> np.ndarray:
    """Zero-pad (or crop) a ``(m, s, s)`` stack to ``(m, n, n)`` keeping ``[s//2, s//2]``."""
    s = images.shape[-1]
    lo = n // 2 - s // 2
    if lo < 0:
        return images[..., -lo : -lo + n, -lo : -lo + n]
    out = np.zeros(images.shape[:-2] + (n, n))
    out[..., lo : lo + s, lo : lo + s] = images
    return out


def subpixel_shift(F0: np.ndarray, X: np.ndarray, Y: np.ndarray, big: int, size: int) -> np.ndarray:
    """Images ``s(x + X)`` from their ``rfft2`` on ``big x big``, cropped to ``size``.

    The exact Fourier (periodic sinc) shift: a star centred at ``big//2 + X`` lands on
    ``big//2``, which becomes element ``size//2`` of the crop.
    """
    kx, ky, _ = rfft_frequencies(big)
    ramp = np.exp(1j * (kx[None] * X[:, None, None] + ky[None] * Y[:, None, None]))
    img = np.fft.irfft2(F0 * ramp, s=(big, big))
    lo = big // 2 - size // 2
    return img[:, lo : lo + size, lo : lo + size]


def gaussian_ft(big: int, sigma: float) -> np.ndarray:
    """``rfft2`` (on ``big x big``) of a round unit-flux Gaussian of ``sigma`` pixels."""
    kx, ky, _ = rfft_frequencies(big)
    return np.exp(-0.5 * (kx * kx + ky * ky) * sigma**2)


def gaussian_peak(D: np.ndarray, sigma: float, x0: np.ndarray, y0: np.ndarray, radius: float):
    """Peak of the cross-correlation with a round Gaussian nearest ``(x0, y0)``.

    Integer maximum within ``radius`` of ``(x0, y0)`` (offsets from the frame centre),
    then Newton steps. Returns ``X, Y, ok`` (``ok`` false: no positive, curved peak).
    """
    big = D.shape[-2]
    R = gaussian_ft(big, sigma)
    cc = np.fft.irfft2(D * R[None], s=(big, big))  # cc[i, iy, ix] = h(X=(ix, iy))
    off = (np.arange(big) + big // 2) % big - big // 2
    dx = off[None, None, :] - x0[:, None, None]
    dy = off[None, :, None] - y0[:, None, None]
    d2 = dx * dx + dy * dy
    masked = np.where(d2 <= radius * radius, cc, -np.inf)
    flat = masked.reshape(len(D), -1).argmax(axis=1)
    iy, ix = np.unravel_index(flat, (big, big))
    peak = cc[np.arange(len(D)), iy, ix]
    X, Y, ok = newton_peak(D, np.broadcast_to(R, D.shape[1:])[None], off[ix], off[iy])
    return X, Y, ok & (peak > 0)


def gaussian_image(size: int, sigma: float) -> np.ndarray:
    """A ``size x size`` round Gaussian of ``sigma`` pixels at ``[size//2, size//2]``, sum 1."""
    r = np.arange(size) - size // 2
    g = np.exp(-0.5 * (r[:, None] ** 2 + r[None, :] ** 2) / sigma**2)
    return g / g.sum()
