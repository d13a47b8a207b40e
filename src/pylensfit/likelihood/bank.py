"""The PSF's part of the model bank: each model's ``sum m^2`` and autocorrelation Hessian
under one PSF, cached over the last PSFs; the frequencies that the likelihood sums over."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from ..config import Config
from ..models import in_disc, rfft_frequencies
from ..psf import psf_transform
from .grid_nb import Models


@dataclass(frozen=True)
class PSFBank:
    """Per-PSF quantities: the PSF transform and the per-model sums that need no data."""

    P: np.ndarray  # (n_freq,) complex
    S: np.ndarray  # (n_models,) sum m^2
    mxx: np.ndarray  # (n_models,) Hessian of the model autocorrelation at 0
    mxy: np.ndarray
    myy: np.ndarray

    def models(self, cols: np.ndarray | None = None) -> Models:
        """The per-model sums of the models ``cols`` (default: all), the kernel's
        :class:`~pylensfit.likelihood.grid_nb.Models`."""
        if cols is None:
            return Models(self.S, self.mxx, self.mxy, self.myy)
        return Models(self.S[cols], self.mxx[cols], self.mxy[cols], self.myy[cols])


def interior(n: int, k_max: float = 0.0) -> np.ndarray:
    """``rfft2`` frequencies of an ``n x n`` stamp that are not Nyquist (``|j| < n/2``),
    and with ``k_max > 0`` no farther than ``k_max`` from the origin.

    The engine sums over these only. A Nyquist frequency stands for both ``+pi`` and
    ``-pi``, where neither an elliptical model nor a shift in position has one value:
    without it the likelihood is exactly covariant under the square's symmetries (a
    90-degree rotation of the data maps ``L(e)`` to ``L(-e)``), which
    :func:`folded_bank` uses. With the PSF at least Nyquist sampled the dropped
    frequencies carry a negligible part of the signal. The disc ``|k| <= k_max`` keeps
    those symmetries; under white noise the Fourier terms are independent, so the sum
    over a subset is the exact likelihood of that part of the data.
    """
    kx, ky, _ = rfft_frequencies(n)
    jmax = (n - 1) // 2
    jx = np.rint(kx * n / (2 * np.pi)).astype(int)
    jy = np.rint(ky * n / (2 * np.pi)).astype(int)
    keep = (np.abs(jx) <= jmax) & (np.abs(jy) <= jmax)
    if k_max > 0:
        keep &= in_disc(kx, ky, k_max)
    return keep.ravel()


def keep_last(cache: dict, key, value, size: int) -> None:
    """Store ``value`` in ``cache``, dropping the oldest entry beyond ``size``."""
    if len(cache) >= size:
        cache.pop(next(iter(cache)))
    cache[key] = value


#: the last PSFs' banks: a pipeline fits an image's galaxies with one PSF in several
#: calls (blocks, neighbour subtraction), or with one PSF per cell of a PSF over the
#: field (Config.psf_cells^2 per stamp tier, so 8 x 8 cells and two tiers need 128); a
#: precision block its renderings. An entry holds 4 floats per model (1.4 MB for
#: Config()'s 44,557 models).
_PSF_BANKS: dict = {}
_PSF_BANKS_KEPT = 144


def psf_bank(psf: np.ndarray, config: Config, bank) -> PSFBank:
    """:func:`_psf_bank_of` of the PSF image, reused while the same image and bank recur."""
    psf = np.ascontiguousarray(psf)
    key = (hashlib.blake2b(psf.tobytes(), digest_size=16).digest(), psf.shape, psf.dtype.str,
           config.stamp_size, float(config.k_max), id(bank))  # fmt: skip
    hit = _PSF_BANKS.get(key)
    if hit is not None and hit[0] is bank:
        return hit[1]
    pb = _psf_bank_of(psf, config, bank)
    keep_last(_PSF_BANKS, key, (bank, pb), _PSF_BANKS_KEPT)
    return pb


def _psf_bank_of(psf: np.ndarray, config: Config, bank) -> PSFBank:
    """The PSF's transform and each model's ``sum m^2`` and autocorrelation Hessian."""
    n = config.stamp_size
    P = psf_transform(psf, n)
    kx, ky, w = rfft_frequencies(n)
    p2 = (w * np.abs(P) ** 2 / n**2).ravel() * interior(n, config.k_max)
    kx = kx.ravel()
    ky = ky.ravel()
    W = np.stack([p2, -p2 * kx * kx, -p2 * kx * ky, -p2 * ky * ky])
    if bank.rows is not None:
        W = W[:, bank.rows]
    out = np.empty((4, bank.G.shape[1]))
    for c0 in range(0, bank.G.shape[1], 4096):  # in chunks: no bank-sized temporary
        out[:, c0 : c0 + 4096] = W @ np.square(bank.G[:, c0 : c0 + 4096], dtype=np.float64)
    return PSFBank(P=P.ravel(), S=out[0], mxx=out[1], mxy=out[2], myy=out[3])
