"""The stamps' windows: cut about each galaxy, cleaned, transformed, and centred on the
peak of their cross-correlation with a round model."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import flags as _flags
from .._util import newton_peak
from ..config import Config
from ..models import ModelBank, fourier_profile, model_bank, rfft_frequencies
from .bank import MixedPSF, PairBank, PSFBank
from .grid_nb import Galaxies, MixedModels, Models
from .pairs import window_bank


def cut_windows(stamps: np.ndarray, n: int, cx: np.ndarray, cy: np.ndarray):
    """Cut ``n x n`` windows centred on round(c) (zero padded); return them and new centres."""
    k, ny, nx = stamps.shape
    if ny == n and nx == n:
        return stamps, cx, cy
    ix = np.rint(cx).astype(int) - n // 2
    iy = np.rint(cy).astype(int) - n // 2
    inside = k and ix.min() >= 0 and iy.min() >= 0 and ix.max() + n <= nx and iy.max() + n <= ny
    # zeros about the stamps only where a window reaches beyond them (the copy is a
    # good part of a precision block's time)
    pad = 0 if inside else n
    padded = np.pad(stamps, ((0, 0), (pad, pad), (pad, pad))) if pad else stamps
    rows = (iy[:, None] + pad + np.arange(n)[None, :]).clip(0, ny + 2 * pad - 1)
    cols = (ix[:, None] + pad + np.arange(n)[None, :]).clip(0, nx + 2 * pad - 1)
    out = padded[np.arange(k)[:, None, None], rows[:, :, None], cols[:, None, :]]
    return out, cx - ix, cy - iy


def round_reference(P: np.ndarray, config: Config) -> np.ndarray:
    """The round exponential of scale ``config.centring_scale`` convolved with the PSF
    transform ``P`` (``(n, n // 2 + 1)``): what :func:`centre` cross-correlates with."""
    kx, ky, _ = rfft_frequencies(config.stamp_size)
    return fourier_profile(np.hypot(kx, ky) * config.centring_scale, "exponential") * P


def centre(D: np.ndarray, P: np.ndarray, config: Config, x0: np.ndarray, y0: np.ndarray):
    """Integer-then-parabola peak of the cross-correlation with a round model.

    ``D`` is phase-referenced to the stamp centre ``n//2``; ``x0, y0`` are catalogue
    offsets from it; ``P`` the PSF transform ``(n, n//2 + 1)``, or one per galaxy
    ``(n_gal, n, n//2 + 1)``. Returns the offsets of the peak and a flag for "no positive
    peak".
    """
    n = config.stamp_size
    ref = round_reference(P, config)
    refc = np.conj(ref) if ref.ndim == 3 else np.conj(ref)[None]
    cc = np.fft.irfft2(D * refc, s=(n, n))  # cc[g, iy, ix] = h(X=(ix, iy))
    off = (np.arange(n) + n // 2) % n - n // 2
    rad = max(config.max_offset, 0.75)
    d2 = (off[None, None, :] - x0[:, None, None]) ** 2 + (
        off[None, :, None] - y0[:, None, None]
    ) ** 2
    masked = np.where(d2 <= rad * rad, cc, -np.inf)
    flat = masked.reshape(len(D), -1).argmax(axis=1)
    iy, ix = np.unravel_index(flat, (n, n))
    g = np.arange(len(D))
    v0 = cc[g, iy, ix]

    def parabola(vm, vp):
        den = vm - 2 * v0 + vp
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.where(den < 0, 0.5 * (vm - vp) / den, 0.0)
        return np.clip(step, -0.5, 0.5)

    dx = parabola(cc[g, iy, (ix - 1) % n], cc[g, iy, (ix + 1) % n])
    dy = parabola(cc[g, (iy - 1) % n, ix], cc[g, (iy + 1) % n, ix])
    xc = off[ix] + dx
    yc = off[iy] + dy
    # Newton iterations on the exact (Fourier-interpolated) cross-correlation: every
    # model's Laplace step then starts from a fraction of its own peak width
    xc, yc, _ = newton_peak(D, ref, xc, yc, n_steps=3)
    no_peak = ~(v0 > 0)
    xc = np.where(no_peak, x0, xc)
    yc = np.where(no_peak, y0, yc)
    return xc, yc, no_peak


@dataclass
class Window:
    """One stamp size's galaxies cleaned, transformed and centred: what every stage reads.

    ``xc, yc`` (the origin of the expansion in position, offsets from the centre pixel
    ``c``) are moved in place by the centring pass
    (:func:`pylensfit.likelihood.evaluate.evaluate_grid`), and ``flags`` gains bits in
    place. On the device path (:func:`prepare_window` with ``on_device``) ``pixels``
    holds the cleaned windows, and ``D``, ``xc``, ``yc``, ``no_peak`` and the
    ``NO_PEAK`` flags are filled by
    :func:`~pylensfit.likelihood.device.device_grid`, which transforms and centres them
    there.
    With a PSF mixed per galaxy (:class:`~pylensfit.likelihood.bank.MixedPSF`)
    ``pb`` is a :class:`~pylensfit.likelihood.bank.PairBank`, ``P_gal`` each galaxy's
    PSF transform and ``wp`` its pair weights.
    """

    n_gal: int
    n: int  # stamp side
    c: int  # centre pixel, n // 2
    bank: ModelBank
    pb: PSFBank | PairBank
    sigma: np.ndarray  # (n_gal,) noise, 1 for the bad stamps
    flags: np.ndarray  # (n_gal,) int32 bit mask
    bad: np.ndarray  # (n_gal,) bad pixels or bad noise
    shift_x: np.ndarray  # window origin in the input stamps
    shift_y: np.ndarray
    x0: np.ndarray  # catalogue positions, offsets from the centre pixel
    y0: np.ndarray
    kx: np.ndarray  # rfft2 frequencies of the window
    ky: np.ndarray
    D: np.ndarray  # (n_gal, n, n // 2 + 1) transforms, phase-referenced to the centre
    xc: np.ndarray
    yc: np.ndarray
    no_peak: np.ndarray  # no positive peak of the cross-correlation
    pixels: np.ndarray | None = None  # (n_gal, n, n) the cleaned windows (device path)
    P_gal: np.ndarray | None = None  # (n_gal, n_freq) each galaxy's PSF transform
    wp: np.ndarray | None = None  # (n_gal, n_pairs) each galaxy's pair weights

    def conj_psf(self) -> np.ndarray:
        """The conjugate PSF transform, ``(n_freq,)``, or one per galaxy ``(n_gal, n_freq)``."""
        return np.conj(self.pb.P if self.P_gal is None else self.P_gal)

    def models(self, cols: np.ndarray | None = None,
               sel: slice | np.ndarray = slice(None)) -> Models | MixedModels:  # fmt: skip
        """The kernel's per-model sums of the models ``cols`` (default: all) for the
        galaxies ``sel``: :class:`~pylensfit.likelihood.grid_nb.Models` under one PSF,
        :class:`~pylensfit.likelihood.grid_nb.MixedModels` under a PSF per galaxy."""
        if self.wp is None:
            return self.pb.models(cols)
        return self.pb.models(self.wp[sel], cols)

    def model_S(self, j: np.ndarray, sel: slice | np.ndarray = slice(None)) -> np.ndarray:
        """``sum m^2`` of each galaxy's model ``j[g]`` (galaxies ``sel``, ``j`` one per
        galaxy)."""
        if self.wp is None:
            return self.pb.S[j]
        return self.pb.S_of(self.wp[sel], j)

    def galaxies(self, sel: slice | np.ndarray) -> Galaxies:
        """The galaxies ``sel`` as the kernel reads them
        (:class:`~pylensfit.likelihood.grid_nb.Galaxies`): their noise and catalogue
        positions from the origin of the expansion."""
        return Galaxies(self.sigma[sel], self.x0[sel] - self.xc[sel], self.y0[sel] - self.yc[sel])


def _clean_stamps(stamps: np.ndarray, sigma: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Flag the stamps with non-finite pixels or a bad noise value and neutralise them.

    Returns the stamps and the noise (the bad ones zeros and 1), the flags and the bad
    stamps' mask.
    """
    flags = np.zeros(stamps.shape[0], dtype=np.int32)
    bad_pix = ~np.isfinite(stamps).all(axis=(1, 2))
    bad_sig = ~(np.isfinite(sigma) & (sigma > 0))
    flags[bad_pix] |= _flags.flag_value("BAD_PIXELS")
    flags[bad_sig] |= _flags.flag_value("BAD_NOISE")
    bad = bad_pix | bad_sig
    if bad.any():
        stamps = np.where(bad[:, None, None], 0.0, stamps)
        stamps = np.nan_to_num(stamps, nan=0.0, posinf=0.0, neginf=0.0)
        sigma = np.where(bad, 1.0, sigma)
    return stamps, sigma, flags, bad


def prepare_window(stamps: np.ndarray, psf: np.ndarray, sigma: np.ndarray, cfg: Config,
                   cx: np.ndarray, cy: np.ndarray, on_device: bool = False) -> Window:  # fmt: skip
    """Cut and clean the windows, their transforms, the PSF bank and the centres (``psf``:
    a PSF image, or a :class:`~pylensfit.likelihood.bank.MixedPSF` for these stamps; with
    ``on_device``, the windows only: the device transforms and centres them)."""
    n_gal = stamps.shape[0]
    n = cfg.stamp_size
    bank = model_bank(cfg)
    pb = window_bank(psf, cfg, bank)
    cx_in, cy_in = cx, cy
    stamps, cx, cy = cut_windows(stamps, n, cx, cy)
    stamps, sigma, flags, bad = _clean_stamps(stamps, sigma)
    kx, ky, _ = rfft_frequencies(n)
    c = n // 2
    x0 = cx - c
    y0 = cy - c
    P_gal = wp = None
    if isinstance(psf, MixedPSF):  # the centring's round model under each galaxy's PSF
        P_gal = np.ascontiguousarray(psf.weights.T @ pb.P)
        wp = pb.pair_weights(psf.weights)
    if on_device:
        D = np.zeros((n_gal, *kx.shape), dtype=complex)
        xc, yc, no_peak = x0.copy(), y0.copy(), np.zeros(n_gal, dtype=bool)
    else:
        D = np.fft.rfft2(stamps) * np.exp(1j * (kx * c + ky * c))[None]
        P = pb.P.reshape(kx.shape) if P_gal is None else P_gal.reshape(n_gal, *kx.shape)
        xc, yc, no_peak = centre(D, P, cfg, x0, y0)
        flags[no_peak & ~bad] |= _flags.flag_value("NO_PEAK")
    return Window(n_gal=n_gal, n=n, c=c, bank=bank, pb=pb, sigma=sigma, flags=flags, bad=bad,
                  shift_x=cx_in - cx, shift_y=cy_in - cy, x0=x0, y0=y0, kx=kx, ky=ky, D=D,
                  xc=xc, yc=yc, no_peak=no_peak,
                  pixels=np.asarray(stamps, dtype=float) if on_device else None,
                  P_gal=P_gal, wp=wp)  # fmt: skip
