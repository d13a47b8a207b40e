"""The stamp tiers: the stamp side each galaxy is fitted on, from its PSF-convolved size."""

from __future__ import annotations

import logging

import numpy as np

from ..config import Config
from ..models import fourier_profile, half_light_radius, rfft_frequencies
from ..psf import psf_transform
from .bank import MixedPSF, interior
from .windows import centre, cut_windows


def tier_sizes(config: Config, shape: tuple[int, ...]) -> list[int]:
    """The stamp sides of the tiers that stamps of ``shape`` (``(ny, nx)``) allow.

    The multiples of ``config.stamp_size`` up to ``config.largest_stamp`` that the
    stamps hold, and above them the stamps' own side (rounded down to an even number)
    where it is smaller than ``largest_stamp``: 48-pixel stamps give ``[32, 48]`` under
    the default ``max_stamp_size=64``, 64-pixel ones ``[32, 64]``.

    Parameters
    ----------
    config : Config
        ``stamp_size`` (the base tier) and ``max_stamp_size`` (the largest).
    shape : tuple of int
        The given stamps' sides.

    Returns
    -------
    list of int
        Increasing stamp sides; ``[config.stamp_size]`` alone where there are no tiers or
        the stamps hold no more than the base stamp.
    """
    n0 = config.stamp_size
    top = min(config.largest_stamp, *(int(v) for v in shape))
    sizes = list(range(n0, top + 1, n0)) or [n0]
    top -= top % 2
    if top > sizes[-1]:
        sizes.append(top)
    return sizes


def warn_small_stamps(shape: tuple[int, ...], cfg: Config, top: int,
                       n_short: int | None) -> None:  # fmt: skip
    """Log that the given stamps are smaller than ``cfg.largest_stamp``: ``n_short``
    galaxies wanted a larger stamp than ``top``, the largest side they allow (None: the
    stamps allow no tier above the base stamp)."""
    log = logging.getLogger("pylensfit.likelihood")
    if n_short is None:
        log.warning("stamps of %dx%d px: max_stamp_size=%d cannot act, the largest galaxies "
                    "are fitted on %d-pixel stamps (give stamps of %d px)", shape[1],
                    shape[2], cfg.largest_stamp, top, cfg.largest_stamp)  # fmt: skip
    else:
        log.warning("stamps of %dx%d px: %d galaxies need stamps larger than %d px and are "
                    "fitted on %d (max_stamp_size=%d: give stamps of %d px)", shape[1],
                    shape[2], n_short, top, top, cfg.largest_stamp,
                    cfg.largest_stamp)  # fmt: skip


def stamp_tiers(stamps, psf, sigma, cfg: Config, cx, cy,
                 sizes: list[int]) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """:func:`_stamp_tiers` under one PSF image, or for a
    :class:`~pylensfit.likelihood.bank.MixedPSF` under each stamp's heaviest image."""
    if not isinstance(psf, MixedPSF):
        return _stamp_tiers(stamps, psf, sigma, cfg, cx, cy, sizes)
    size = np.empty(len(stamps), dtype=int)
    wanted = np.empty(len(stamps), dtype=int)
    near = psf.nearest
    for c in np.unique(near):
        i = np.flatnonzero(near == c)
        size[i], wanted[i] = _stamp_tiers(stamps[i], psf.images[c], sigma[i], cfg, cx[i],
                                          cy[i], sizes)  # fmt: skip
    return size, wanted


def _stamp_tiers(stamps, psf, sigma, cfg: Config, cx, cy,
                 sizes: list[int]) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The stamp side of every stamp, one of ``sizes`` (:func:`tier_sizes`), and the side
    each galaxy needs (pixels, at least ``stamp_size``).

    Each galaxy's size is that of the round exponential of largest matched-filter S/N
    on the largest tier's window (half-light radii 0.1-12 px, about the centre that a
    fit on the base stamp starts from), its PSF-convolved half-light radius ``R``
    measured on the convolved model's image. It needs ``stamp_hlr_ratio * R``; its side
    is the smallest of ``sizes`` at least that (the largest where none is), at most what
    the given stamp holds about the galaxy; stamps without a positive peak get the base
    side.
    """
    n0 = cfg.stamp_size
    nw = sizes[-1]
    kx, ky, w = rfft_frequencies(nw)
    c = nw // 2
    P = psf_transform(psf, nw)
    # the centre from the base stamp's window about the same pixel (a quarter of the
    # largest window's cost: two thirds of this function's time were the centring)
    kx0, ky0, _ = rfft_frequencies(n0)
    c0 = n0 // 2
    P0 = psf_transform(psf, n0)
    ccfg = cfg.replace(max_stamp_size=0, k_max=0.0)
    # round exponentials (and their convolved half-light radii, from their images)
    M = fourier_profile(np.hypot(kx, ky).ravel()[:, None] * np.geomspace(0.1, 12.0, 24)[None]
                        / half_light_radius("exponential"), "exponential") * P.ravel()[:, None]
    wt = w.ravel() * interior(nw)
    S = (wt[:, None] * np.abs(M) ** 2).sum(axis=0)
    img = np.fft.irfft2(M.T.reshape(-1, *kx.shape) * np.exp(-1j * (kx * c + ky * c)),
                        s=(nw, nw)).reshape(M.shape[1], -1)  # fmt: skip
    rad = np.hypot(*(np.mgrid[:nw, :nw] - c)).ravel()
    order = np.argsort(rad)
    cum = np.cumsum(img[:, order], axis=1)
    hlr = rad[order][np.argmax(cum >= 0.5 * cum[:, -1:], axis=1)]
    wanted = np.full(len(stamps), n0, dtype=int)
    step = 4 * cfg.block_size
    for s0 in range(0, len(stamps), step):
        sl = slice(s0, min(s0 + step, len(stamps)))
        win, wx, wy = cut_windows(np.nan_to_num(stamps[sl], nan=0.0, posinf=0.0, neginf=0.0),
                                  nw, cx[sl], cy[sl])  # fmt: skip
        D = np.fft.rfft2(win) * np.exp(1j * (kx * c + ky * c))[None]
        D0 = (np.fft.rfft2(win[:, c - c0:c - c0 + n0, c - c0:c - c0 + n0])
              * np.exp(1j * (kx0 * c0 + ky0 * c0))[None])  # fmt: skip
        xc, yc, no_peak = centre(D0, P0, ccfg, wx - c, wy - c)
        # the phase ramp, separable: one exp per row and per column of the frequencies
        ph = (np.exp(1j * ky[:, 0][None, :, None] * yc[:, None, None])
              * np.exp(1j * kx[0][None, None, :] * xc[:, None, None]))  # fmt: skip
        ph = ph.reshape(len(D), -1)
        h = ((D.reshape(len(D), -1) * ph * wt) @ np.conj(M)).real
        best = np.argmax(h / np.sqrt(S), axis=1)
        need = np.ceil(cfg.stamp_hlr_ratio * hlr[best]).astype(int)
        ok = ~no_peak & (h[np.arange(len(D)), best] > 0) & np.isfinite(sigma[sl])
        wanted[sl] = np.where(ok, np.maximum(need, n0), n0)
    side = np.asarray(sizes)
    size = side[np.minimum(np.searchsorted(side, wanted), side.size - 1)]
    # no window beyond the given stamps: n <= 2 min(ic, N - ic) along both axes
    ix, iy = np.rint(cx).astype(int), np.rint(cy).astype(int)
    room = np.minimum.reduce([ix, stamps.shape[2] - ix, iy, stamps.shape[1] - iy])
    fits_in = side[np.maximum(np.searchsorted(side, 2 * room, side="right") - 1, 0)]
    return np.minimum(size, fits_in), wanted
