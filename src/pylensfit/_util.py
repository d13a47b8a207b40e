"""Small numerical helpers shared by the PSF and likelihood stages."""

from __future__ import annotations

import numpy as np

from .models import rfft_frequencies

__all__ = ["newton_peak", "per_object"]


def per_object(value, n: int, name: str) -> np.ndarray:
    """A scalar or ``(n,)`` array as a fresh float ``(n,)`` array; wrong shapes raise."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        return np.full(n, float(arr))
    if arr.shape != (n,):
        raise ValueError(f"{name} must be a scalar or have shape ({n},), got {arr.shape}")
    return arr.copy()


def newton_peak(D: np.ndarray, R: np.ndarray, X: np.ndarray, Y: np.ndarray, n_steps: int = 6):
    """Maximise ``h(X) = sum_x s(x + X) r(x)`` by Newton steps on its Fourier series.

    ``D`` and ``R`` are ``rfft2`` transforms phase-referenced to the centre of the
    (odd) ``big x big`` frame. Steps longer than a pixel or at a point of non-negative
    curvature are refused. Returns the peak and whether the curvature there is negative.
    """
    big = D.shape[-2]
    kx, ky, w = rfft_frequencies(big)
    kx1, ky1 = kx[0], ky[:, 0]  # kx varies along the columns, ky along the rows
    base = D * np.conj(R) * (w / big**2)
    X = X.astype(float)
    Y = Y.astype(float)
    for _ in range(n_steps):
        # the phase ramp is separable: one exp per row and per column, not per frequency
        ex = np.exp(1j * kx1[None, :] * X[:, None])
        ey = np.exp(1j * ky1[None, :] * Y[:, None])
        Dp = base * ey[:, :, None] * ex[:, None, :]
        re, im = Dp.real, Dp.imag
        re_x = re @ kx1  # (n, rows): sums over the columns weighted by kx
        gx = -(im @ kx1).sum(axis=1)
        hxx = -(re @ (kx1 * kx1)).sum(axis=1)
        gy = -(im.sum(axis=2) @ ky1)
        hyy = -(re.sum(axis=2) @ (ky1 * ky1))
        hxy = -(re_x @ ky1)
        det = hxx * hyy - hxy * hxy
        good = (hxx < 0) & (det > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            sx = np.where(good, (hxy * gy - hyy * gx) / det, 0.0)
            sy = np.where(good, (hxy * gx - hxx * gy) / det, 0.0)
        ok = good & (np.hypot(sx, sy) < 1.0)
        X = np.where(ok, X + sx, X)
        Y = np.where(ok, Y + sy, Y)
    return X, Y, good
