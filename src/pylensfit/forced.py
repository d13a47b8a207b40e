"""The significance of a source at a given (forced) position.

An input catalogue's position is measured wherever it lies, blank sky included. The fit
looks for its galaxy within ``Config.max_offset`` of the position and keeps the best of
many models there, so on blank sky its best model's S/N is the largest of many noise
peaks (and of a neighbour's wings): above ``Config.min_snr`` far more often than a noise
detection's. Here the evidence for a source is measured where the catalogue puts it: a
bank of matched filters (round exponentials of a few half-light radii, the point source
among them, convolved with the PSF) is evaluated at the catalogue position itself, with
no search over positions, and the best is kept,

.. math::

    \\nu = \\max_j \\frac{\\sum_x d(x)\\, m_j(x - x_0)}{\\sigma \\sqrt{\\sum_x m_j(x)^2}} .

On pure white noise each filter's value is a standard normal variable, so the chance
that the best of ``K`` exceeds ``u`` is at most ``K`` times the normal tail beyond ``u``
(Bonferroni). :func:`false_alarm_threshold` inverts that bound: a row whose ``nu`` is
below the threshold of false-alarm probability ``Config.forced_false_alarm`` is no
evidence of a source (the pipeline flags it ``LOW_SNR``). The bank's filters are
correlated (0.94 to 0.98 between neighbours in size), so the bound is conservative: at the
threshold of 1e-3 (``u = 3.48`` for four filters) 6.4e-4 of 200,000 pure-noise stamps
pass, at 1e-2 (``u = 2.81``) 5.0e-3.

A galaxy at its catalogue position loses little: its ``nu`` is 0.55 to 1.0 of its
matched-filter S/N (0.94 typically; the round filters lose up to a quarter of an
elongated galaxy's, ``|e| > 0.8``), so every galaxy of S/N 10 passes. A catalogue
position off its galaxy by more than the PSF's width lowers ``nu``; correlated noise
(resampled or co-added images) raises the false-alarm probability above the white-noise
bound.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtri

from ._util import per_object, rfft_frequencies
from .config import Config
from .models import fourier_profile, half_light_radius
from .psf import psf_transform

__all__ = ["FORCED_HALF_LIGHT_RADII", "false_alarm_threshold", "forced_threshold", "position_snr"]

#: half-light radii (px) of the round exponential filters (0: the point source, the PSF)
FORCED_HALF_LIGHT_RADII: tuple[float, ...] = (0.0, 1.0, 2.0, 4.0)

#: stamps filtered at a time (bounded memory)
_BLOCK = 2048


def false_alarm_threshold(false_alarm: float,
                          n_filters: int = len(FORCED_HALF_LIGHT_RADII)) -> float:  # fmt: skip
    """The S/N ``u`` above which the best of ``n_filters`` matched filters lies with
    probability at most ``false_alarm`` on pure white noise.

    Each filter's S/N at a fixed position is a standard normal variable there, so
    ``P(max > u) <= n_filters * Q(u)`` (``Q`` the normal tail); ``u`` solves the bound's
    equality, ``u = Q^-1(false_alarm / n_filters)``.

    Parameters
    ----------
    false_alarm : float
        The false-alarm probability, in ``(0, 1)``.
    n_filters : int, optional
        The filters' number (default: :data:`FORCED_HALF_LIGHT_RADII`'s).

    Returns
    -------
    float
        The threshold ``u``.
    """
    if not 0.0 < false_alarm < 1.0:
        raise ValueError(f"false_alarm must be in (0, 1), got {false_alarm}")
    if n_filters < 1:
        raise ValueError(f"n_filters must be >= 1, got {n_filters}")
    return float(-ndtri(false_alarm / n_filters))


def position_snr(
    stamps: np.ndarray,
    psf: np.ndarray,
    noise_sigma,
    centres: tuple[np.ndarray, np.ndarray],
    *,
    half_light_radii: tuple[float, ...] = FORCED_HALF_LIGHT_RADII,
) -> np.ndarray:
    """The best matched-filter S/N of each stamp at a given position (no search).

    Parameters
    ----------
    stamps : numpy.ndarray
        ``(n, N, N)`` (or one ``(N, N)``) background-subtracted images indexed
        ``[k, y, x]``.
    psf : numpy.ndarray
        2-D PSF image including the pixel response, centred on ``[s//2, s//2]``, any size
        and normalisation.
    noise_sigma : float or numpy.ndarray
        Per-pixel noise standard deviation (white noise), scalar or one per stamp.
    centres : tuple of numpy.ndarray
        The positions ``(x, y)`` in stamp pixels (0-based), one per stamp.
    half_light_radii : tuple of float, optional
        The filters: round exponentials of these half-light radii (px; 0 the point
        source) convolved with the PSF.

    Returns
    -------
    numpy.ndarray
        ``(n,)`` the largest of the filters' S/N at each position, NaN where the stamp
        holds a non-finite pixel or the noise is not finite and positive.
    """
    stamps = np.asarray(stamps, dtype=float)
    if stamps.ndim == 2:
        stamps = stamps[None]
    if stamps.ndim != 3 or stamps.shape[1] != stamps.shape[2]:
        raise ValueError(f"stamps must have shape (n, N, N), got {stamps.shape}")
    n_obj, n = stamps.shape[0], stamps.shape[1]
    sigma = per_object(noise_sigma, n_obj, "noise_sigma")
    cx = per_object(centres[0], n_obj, "centres[0]")
    cy = per_object(centres[1], n_obj, "centres[1]")
    placed = np.isfinite(cx) & np.isfinite(cy)
    cx[~placed] = cy[~placed] = 0.0
    kx, ky, w = rfft_frequencies(n)
    r = np.asarray(half_light_radii, dtype=float) / half_light_radius("exponential")
    # the filters centred on the origin, and their norms (Parseval over the half plane)
    M = fourier_profile(np.hypot(kx, ky)[None] * r[:, None, None], "exponential")
    M = M * psf_transform(np.asarray(psf, dtype=float), n)[None]
    norm = np.sqrt((w[None] * np.abs(M) ** 2).sum(axis=(1, 2))) / n
    Mw = np.conj(M) * w[None] / n**2
    out = np.full(n_obj, np.nan)
    for s0 in range(0, n_obj, _BLOCK):
        sl = slice(s0, min(s0 + _BLOCK, n_obj))
        D = np.fft.rfft2(np.nan_to_num(stamps[sl], nan=0.0, posinf=0.0, neginf=0.0))
        # each filter moved from the origin to the position: D times the conjugate
        # phase ramp, separable in the rows and the columns
        D *= (np.exp(1j * ky[:, 0][None, :, None] * cy[sl, None, None])
              * np.exp(1j * kx[0][None, None, :] * cx[sl, None, None]))  # fmt: skip
        h = np.einsum("iab,jab->ij", D, Mw).real
        out[sl] = (h / norm[None]).max(axis=1)
    good = np.isfinite(stamps).all(axis=(1, 2)) & np.isfinite(sigma) & (sigma > 0)
    good &= placed
    out[good] /= sigma[good]
    out[~good] = np.nan
    return out


def forced_threshold(config: Config) -> float | None:
    """The threshold of :func:`position_snr` below which an input catalogue's row is
    flagged ``LOW_SNR`` (:func:`false_alarm_threshold` of
    ``config.forced_false_alarm``); ``None`` where no such cut applies
    (``forced_false_alarm = 1``, or ``min_snr = 0``: every fitted galaxy used)."""
    if config.forced_false_alarm >= 1.0 or not config.min_snr > 0:
        return None
    return false_alarm_threshold(config.forced_false_alarm)
