"""PSF models that vary across the field.

:func:`pylensfit.psf.stack_psf` gives one PSF per image. Real surveys need the PSF at
each galaxy's position: lensfit's survey version (Miller et al. 2013, CFHTLenS,
arXiv:1210.8201) models every pixel of the PSF as a polynomial in the position,
fitted to the stars, as PSFEx does. This module provides:

* :class:`PSFModel`, the interface: ``draw(x, y)``, ``shape_at(x, y)``, ``centre``,
  ``diagnostics``, ``digest``, ``write``;
* :class:`ConstantPSF`, one :class:`~pylensfit.psf.PSFResult` everywhere;
* :class:`PolynomialPSF`, the per-pixel polynomial fitted to the stars
  (:meth:`PolynomialPSF.fit`), with outlier rejection and held-out diagnostics;
* :class:`PiffPSF`, a model fitted by Piff (optional dependency), and
  :func:`fit_piff`, which fits one to an image's stars with Piff;
* :func:`read_psf_model`, which reads any of them back.

Every drawn image follows the convention of :mod:`pylensfit.psf`: ``(size, size)``,
unit sum, pixel response included, centred on element ``[size//2, size//2]`` defined
as the peak of its cross-correlation with a round Gaussian of ``centroid_sigma``.
Positions are 0-based image pixels with pixel centres on integers, ``x`` indexing the
columns (arrays are ``[y, x]``).
"""

from __future__ import annotations

import hashlib
import json
import logging
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.table import Table
from scipy.stats import chi2 as chi2_dist
from scipy.stats import f as f_dist

from ._util import (
    atomic_write,
    atomic_write_with,
    jsonable,
    newton_peak,
    per_object,
    rfft_frequencies,
)
from .psf import (
    REASONS,
    PSFError,
    PSFResult,
    adaptive_moments,
    check_star_inputs,
    gaussian_ft,
    gaussian_image,
    gaussian_peak,
    pad_to,
    psf_diagnostics,
    read_psf,
    star_cutouts,
    subpixel_shift,
)

__all__ = [
    "ConstantPSF",
    "PSFModel",
    "PiffNotInstalledError",
    "PiffPSF",
    "PolynomialPSF",
    "fit_piff",
    "n_terms",
    "read_psf_model",
]

log = logging.getLogger(__name__)

#: ``PSFMODEL`` header value of a file written by :meth:`PolynomialPSF.write`.
_POLY_KIND = "POLYNOMIAL"

#: Columns of the per-star table of :class:`PolynomialPSF`.
_TABLE_COLUMNS = ("x_cat", "y_cat", "x", "y", "flux", "snr", "correlation", "chi2", "used",
                  "reason", "heldout", "e1_star", "e2_star", "sigma_star", "e1_model",
                  "e2_model", "sigma_model")  # fmt: skip

_CHUNK = 1024  # positions drawn at once (bounds the memory of the Fourier re-centring)


class PiffNotInstalledError(ImportError):
    """Piff, needed for :class:`PiffPSF`, is not installed."""


# ---------------------------------------------------------------------------------------
# Small helpers
# ---------------------------------------------------------------------------------------
def n_terms(order: int) -> int:
    """Number of monomials ``u^i v^j`` with ``i + j <= order``."""
    return (order + 1) * (order + 2) // 2


def _exponents(order: int) -> list[tuple[int, int]]:
    """``(i, j)`` of the monomials ``u^i v^j``, by total degree then by power of ``v``."""
    return [(d - j, j) for d in range(order + 1) for j in range(d + 1)]


def _design(u: np.ndarray, v: np.ndarray, order: int) -> np.ndarray:
    """``(n, n_terms)`` matrix of the monomials at normalised positions ``u, v``."""
    return np.stack([u**i * v**j for i, j in _exponents(order)], axis=-1)


def _positions(x, y) -> tuple[np.ndarray, np.ndarray, bool]:
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


def _phase(big: int) -> np.ndarray:
    """Phase ramp referencing an ``rfft2`` on ``big x big`` to element ``[big//2, big//2]``."""
    kx, ky, _ = rfft_frequencies(big)
    return np.exp(1j * (kx * (big // 2) + ky * (big // 2)))


def _shift_ft(D: np.ndarray, X: np.ndarray, Y: np.ndarray, size: int) -> np.ndarray:
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


def _recentre(D: np.ndarray, size: int, centroid_sigma: float, search: float | None = None):
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
    out = _shift_ft(D, sx, sy, size)
    total = out.sum(axis=(1, 2))
    if not np.all(total > 0):
        raise PSFError(f"{int(np.sum(~(total > 0)))} drawn PSF image(s) have a non-positive sum")
    return out / total[:, None, None], sx, sy, total


def _moments_many(images: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """GalSim adaptive moments ``(sigma, e1, e2)`` of each of ``(n, s, s)`` images."""
    res = np.array([adaptive_moments(im) for im in images], dtype=float).reshape(-1, 3)
    return res[:, 0], res[:, 1], res[:, 2]


def _sha1(*parts) -> str:
    h = hashlib.sha1()
    for part in parts:
        if isinstance(part, np.ndarray):
            h.update(np.ascontiguousarray(part, dtype=np.float64).tobytes())
        elif isinstance(part, bytes):
            h.update(part)
        else:
            h.update(repr(part).encode())
        h.update(b"|")
    return h.hexdigest()


def _atomic_write_bytes(data: bytes, path: Path, overwrite: bool) -> None:
    """Write ``data`` through a temporary file renamed when complete."""
    atomic_write_with(lambda tmp: Path(tmp).write_bytes(data), path, overwrite=overwrite)


# ---------------------------------------------------------------------------------------
# The interface
# ---------------------------------------------------------------------------------------
class PSFModel(ABC):
    """A PSF that may vary across the field.

    Attributes
    ----------
    size : int
        Side in pixels of the drawn images.
    diagnostics : dict
        How the model was made (stars used and rejected, polynomial order, held-out
        residuals; see the subclasses).
    """

    size: int
    diagnostics: dict

    @abstractmethod
    def _draw(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """``(n, size, size)`` images at 1-D positions."""

    def draw(self, x, y) -> np.ndarray:
        """The PSF at image positions.

        Parameters
        ----------
        x, y : float or array_like
            Scalars or 1-D arrays of 0-based image pixel positions (pixel centres on
            integers, ``x`` along the columns).

        Returns
        -------
        numpy.ndarray
            ``(size, size)`` for scalars, else ``(n, size, size)``; each image includes
            the pixel response, has unit sum and is centred on ``[size//2, size//2]``
            (the peak of its cross-correlation with a round Gaussian).
        """
        xa, ya, scalar = _positions(x, y)
        out = self._draw(xa, ya)
        return out[0] if scalar else out

    def shape_at(self, x, y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Adaptive-moment shape of the PSF at image positions.

        Parameters
        ----------
        x, y : float or array_like
            0-based image pixel positions, as for :meth:`draw`.

        Returns
        -------
        e1, e2, sigma : numpy.ndarray
            GalSim's adaptive-moment ellipticity ``(a - b) / (a + b)`` (``e1 > 0`` along
            x) and size ``det(M)^(1/4)`` in pixels of :meth:`draw` at each position
            (NaN where the moments fail); arrays of the positions' length (length 1 for
            scalars).
        """
        xa, ya, _ = _positions(x, y)
        res = [_moments_many(self._draw(xa[i : i + _CHUNK], ya[i : i + _CHUNK]))
               for i in range(0, xa.size, _CHUNK)]  # fmt: skip
        sigma, e1, e2 = (np.concatenate([r[k] for r in res]) if res else np.zeros(0)
                         for k in range(3))  # fmt: skip
        return e1, e2, sigma

    @property
    @abstractmethod
    def centre(self) -> PSFResult:
        """The PSF at the field centre (or the constant PSF) as a :class:`PSFResult`."""

    @property
    @abstractmethod
    def digest(self) -> str:
        """SHA-1 hex digest of what defines the drawn images (for resume keys)."""

    @abstractmethod
    def write(self, path: str | Path, overwrite: bool = False) -> None:
        """Write the model to ``path`` atomically; :func:`read_psf_model` reads it back."""


# ---------------------------------------------------------------------------------------
# Constant
# ---------------------------------------------------------------------------------------
class ConstantPSF(PSFModel):
    """The same PSF image at every position.

    Parameters
    ----------
    psf : PSFResult
        The PSF (e.g. from :func:`pylensfit.psf.stack_psf` or
        :func:`pylensfit.psf.psf_from_image`), centred by the convention.
    """

    def __init__(self, psf: PSFResult):
        self.psf = psf
        self.size = psf.size
        image = np.asarray(psf.image, dtype=float)
        total = float(np.sum(image))
        # a unit-sum image (every PSFResult) is drawn as it is: dividing by a sum that
        # differs from 1 in the last bit would change every pixel by an ulp
        self._image = image if abs(total - 1.0) <= 1e-12 else image / total
        self.diagnostics = {"kind": "constant", "order": 0, "n_stars": int(psf.used.size),
                            "n_used": psf.n_used, "n_rejected": psf.n_rejected,
                            "source": psf.source}  # fmt: skip

    def __repr__(self) -> str:
        p = self.psf
        return f"ConstantPSF(size={self.size}, n_used={p.n_used}, source={p.source!r})"

    def _draw(self, x, y):
        return np.repeat(self._image[None], x.size, axis=0)

    @property
    def centre(self) -> PSFResult:
        return self.psf

    @property
    def digest(self) -> str:
        """The digest of the :class:`PSFResult` (the same resume key as the image alone)."""
        return self.psf.digest

    def write(self, path, overwrite=False):
        """Write as :meth:`PSFResult.write` does."""
        self.psf.write(path, overwrite=overwrite)


# ---------------------------------------------------------------------------------------
# Polynomial: the stars
# ---------------------------------------------------------------------------------------
@dataclass
class _Stars:
    """The candidate stars that passed the first stage, and the bookkeeping of all."""

    n: int  # number of candidates in the input list
    idx: np.ndarray  # (m,) index into the input list of each star kept
    ix: np.ndarray  # (m,) integer pixel of each cutout's centre
    iy: np.ndarray
    F0: np.ndarray  # (m, big, big//2+1) rfft2 of the cutouts
    D: np.ndarray  # F0 phase-referenced to the cutout centre
    x0: np.ndarray  # (m,) catalogue position relative to the cutout centre
    y0: np.ndarray
    X: np.ndarray  # (m,) stage-1 centre relative to the cutout centre
    Y: np.ndarray
    stars: np.ndarray  # (m, size, size) stars centred at (X, Y)
    amp: np.ndarray  # (m,) Gaussian-weighted flux
    sig: np.ndarray  # (m,) pixel noise
    reason: np.ndarray  # (n,) object: '' or the stage-1 rejection reason
    snr: np.ndarray  # (n,) Gaussian matched-filter S/N (NaN where not measured)

    @property
    def m(self) -> int:
        return int(self.idx.size)


def _first_stage(image, weight, x, y, sigma_all, size, opts) -> _Stars:
    """Cutouts, Gaussian centring and S/N cut, as the first stage of ``stack_psf``."""
    big = size + 2 * opts["margin"] + 1
    stamps, idx, ix, iy, reason = star_cutouts(image, weight, x, y, big)
    bad_sig = ~(np.isfinite(sigma_all) & (sigma_all > 0))
    reason[(reason == "") & bad_sig] = REASONS["noise"]
    keep = reason[idx] == ""
    stamps, idx = stamps[keep], idx[keep]
    if idx.size == 0:
        z, zi = np.zeros(0), np.zeros(0, np.int64)
        e = np.zeros((0, big, big // 2 + 1), complex)
        return _Stars(n=x.size, idx=zi, ix=zi, iy=zi, F0=e, D=e, x0=z, y0=z, X=z, Y=z,
                      stars=np.zeros((0, size, size)), amp=z, sig=z, reason=reason,
                      snr=np.full(x.size, np.nan))  # fmt: skip
    sig = sigma_all[idx]
    F0 = np.fft.rfft2(stamps)
    D = F0 * _phase(big)[None]
    x0, y0 = x[idx] - ix[idx], y[idx] - iy[idx]
    max_shift = opts["max_shift"]
    X, Y, ok = gaussian_peak(D, opts["centroid_sigma"], x0, y0, max(max_shift, 1.0))
    stars = subpixel_shift(F0, X, Y, big, size)
    G = gaussian_image(size, opts["centroid_sigma"])
    amp = np.einsum("ijk,jk->i", stars, G) / np.sum(G * G)
    snr_k = amp * np.sqrt(np.sum(G * G)) / sig
    snr = np.full(x.size, np.nan)
    snr[idx] = snr_k
    why = np.full(idx.size, "", dtype=object)
    for mask, r in ((~ok, "peak"), (np.hypot(X - x0, Y - y0) > max_shift, "shift"),
                    (~(snr_k >= opts["min_snr"]), "snr"), (~(amp > 0), "flux")):  # fmt: skip
        why[mask & (why == "")] = REASONS[r]
    reason[idx] = why
    k = why == ""
    return _Stars(n=x.size, idx=idx[k], ix=ix[idx[k]], iy=iy[idx[k]], F0=F0[k], D=D[k],
                  x0=x0[k], y0=y0[k], X=X[k], Y=Y[k], stars=stars[k], amp=amp[k], sig=sig[k],
                  reason=reason, snr=snr)  # fmt: skip


# ---------------------------------------------------------------------------------------
# Polynomial: the fit
# ---------------------------------------------------------------------------------------
@dataclass
class _Fit:
    """One iterated polynomial fit to a subset of the stars."""

    order: int
    coefs: np.ndarray  # (p, size, size)
    cov: np.ndarray  # (p, p): (A^T W A)^-1, the covariance of the coefficients per pixel
    used: np.ndarray  # (m,) in the final solve
    why: np.ndarray  # (m,) object: '' or the last check's rejection (for candidates)
    X: np.ndarray  # (m,) centres relative to the cutout centre
    Y: np.ndarray
    unit: np.ndarray  # (m, size, size) unit-flux stars centred on (X, Y)
    flux: np.ndarray  # (m,) NaN for stars never checked
    snr: np.ndarray
    corr: np.ndarray
    chi2: np.ndarray


def _solve(A: np.ndarray, w: np.ndarray, Y: np.ndarray):
    """Weighted least squares for all pixels at once: ``coefs (p, npix)``, ``cov (p, p)``."""
    Aw = A * w[:, None]
    cov = np.linalg.pinv(A.T @ Aw, hermitian=True)
    return cov @ (Aw.T @ Y), cov


def _references(A, w, unit, used, coefs, cov):
    """The model at each star's position, independent of the star, and its pixel variance.

    Stars in the fit get the leave-one-out prediction ``y - (y - yhat) / (1 - h)`` (``h``
    the star's leverage) with variance ``q / (1 - h)``, ``q = a^T cov a``; the others the
    prediction ``yhat`` with variance ``q``.
    """
    m, size = unit.shape[0], unit.shape[-1]
    y = unit.reshape(m, -1)
    yhat = A @ coefs
    q = np.einsum("ip,pq,iq->i", A, cov, A)
    h = np.where(used, w * q, 0.0)
    loo = used & (1.0 - h > 1e-6)  # a star alone in its part of the model: no LOO
    one_h = np.where(loo, 1.0 - h, 1.0)
    ref = np.where(loo[:, None], y - (y - yhat) / one_h[:, None], yhat)
    var = q / one_h
    return ref.reshape(m, size, size), var


def _check(S: _Stars, ref, var_ref, X, Y, opts):
    """Re-centre the stars on their references and measure flux, S/N, correlation, chi2."""
    big, size = S.D.shape[-2], ref.shape[-1]
    npix = size * size
    tot = ref.sum(axis=(1, 2))
    good = tot > 0
    tot = np.where(good, tot, 1.0)
    ref = ref / tot[:, None, None]
    var_ref = var_ref / tot**2
    R = np.fft.rfft2(pad_to(ref, big)) * _phase(big)[None]
    Xn, Yn, ok = newton_peak(S.D, R, X, Y)
    Xn, Yn = np.where(ok, Xn, X), np.where(ok, Yn, Y)
    st = subpixel_shift(S.F0, Xn, Yn, big, size)
    sp = np.einsum("ijk,ijk->i", st, ref)
    pp = np.einsum("ijk,ijk->i", ref, ref)
    ss = np.einsum("ijk,ijk->i", st, st)
    sig = S.sig
    f = np.where(good, sp / pp, np.nan)
    tiny = 1e-300
    corr = sp / np.sqrt(
        np.maximum(ss - npix * sig**2, tiny) * np.maximum(pp - npix * var_ref, tiny)
    )
    core = ref >= opts["core_level"] * ref.max(axis=(1, 2))[:, None, None]
    resid = st - f[:, None, None] * ref
    var_pix = (sig[:, None, None] ** 2 + (f**2 * var_ref)[:, None, None]
               + (opts["model_error"] * f[:, None, None] * ref) ** 2)  # fmt: skip
    dof = np.maximum(core.sum(axis=(1, 2)) - 3, 1)
    chi2 = np.sum(np.where(core, resid**2 / var_pix, 0.0), axis=(1, 2)) / dof
    snr = sp / (sig * np.sqrt(pp))
    return Xn, Yn, st, f, snr, corr, chi2


def _verdict(S: _Stars, X, Y, f, corr, chi2, opts) -> np.ndarray:
    """Rejection reason of each star after a check (``''`` for a star kept)."""
    why = np.full(S.m, "", dtype=object)
    clip = opts["clip"]
    tests = [(np.hypot(X - S.x0, Y - S.y0) > opts["max_shift"], "shift"), (~(f > 0), "flux"),
             (~(corr >= opts["min_correlation"]), "correlation")]  # fmt: skip
    if clip is not None:
        tests.append((~(chi2 <= clip), "chi2"))
    for mask, r in tests:
        why[mask & (why == "")] = REASONS[r]
    return why


def _iterate(S: _Stars, cand: np.ndarray, order: int, uv, opts) -> _Fit:
    """Fit, check every candidate against the model at its position, refit, ``n_iter`` times.

    Every candidate is checked at every pass against the model without it, so a star
    rejected early (e.g. next to a contaminant that pulled the first fit) comes back
    when the model no longer disagrees with it.
    """
    m, size = S.m, S.stars.shape[-1]
    u, v = uv
    A = _design(u, v, order)
    safe = np.where(S.amp > 0, S.amp, 1.0)
    unit = S.stars / safe[:, None, None]
    var_unit = (S.sig / safe) ** 2
    X, Y = S.X.copy(), S.Y.copy()
    used = cand.copy()
    nan = np.full(m, np.nan)
    flux, snr, corr, chi2 = nan.copy(), nan.copy(), nan.copy(), nan.copy()
    why = np.full(m, "", dtype=object)
    c = cand
    Sc = _subset(S, c)
    for _ in range(opts["n_iter"]):
        if not used.any():
            break
        w = np.where(used, 1.0 / var_unit, 0.0)
        coefs, cov = _solve(A[used], w[used], unit[used].reshape(int(used.sum()), -1))
        ref, var_ref = _references(A, w, unit, used, coefs, cov)
        Xc, Yc, st, f, s, r, x2 = _check(Sc, ref[c], var_ref[c], X[c], Y[c], opts)
        X[c], Y[c], flux[c], snr[c], corr[c], chi2[c] = Xc, Yc, f, s, r, x2
        why[c] = _verdict(Sc, Xc, Yc, f, r, x2, opts)
        fa = np.where(f > 0, f, 1.0)
        unit[c] = np.where((f > 0)[:, None, None], st / fa[:, None, None], unit[c])
        var_unit[c] = np.where(f > 0, (S.sig[c] / fa) ** 2, var_unit[c])
        used = cand & (why == "")
    if not used.any():
        return _Fit(order, np.zeros((n_terms(order), size, size)), np.zeros((1, 1)), used, why,
                    X, Y, unit, flux, snr, corr, chi2)  # fmt: skip
    w = 1.0 / var_unit[used]
    coefs, cov = _solve(A[used], w, unit[used].reshape(int(used.sum()), -1))
    return _Fit(order, coefs.reshape(-1, size, size), cov, used, why, X, Y, unit, flux, snr,
                corr, chi2)  # fmt: skip


def _subset(S: _Stars, mask: np.ndarray) -> _Stars:
    """The stars of ``mask`` (the per-candidate bookkeeping is shared)."""
    pick = {k: getattr(S, k)[mask] for k in ("idx", "ix", "iy", "F0", "D", "x0", "y0", "X",
                                              "Y", "stars", "amp", "sig")}  # fmt: skip
    return _Stars(n=S.n, reason=S.reason, snr=S.snr, **pick)


def _affordable_order(n_stars: int, order: int, per_coef: float) -> int:
    """The highest order ``<= order`` with at least ``per_coef`` stars per coefficient."""
    while order > 0 and n_stars < per_coef * n_terms(order):
        order -= 1
    return order


def _fit_with_order(S, cand, order, uv, opts, what: str) -> _Fit:
    """:func:`_iterate`, lowering the order (with a warning) while too few stars survive."""
    per_coef = opts["min_stars_per_coefficient"]
    want = order
    n_used = int(cand.sum())
    order = _affordable_order(n_used, order, per_coef)
    while True:
        fit = _iterate(S, cand, order, uv, opts)
        n_used = int(fit.used.sum())
        lower = _affordable_order(n_used, order, per_coef)
        if lower == order or n_used == 0:
            break
        order = lower
    if order < want:
        log.warning("%s: %d usable stars (%d candidates) for a PSF of order %d (%d "
                    "coefficients, at least %g stars each): order lowered to %d", what,
                    n_used, int(cand.sum()), want, n_terms(want), per_coef, order)  # fmt: skip
    return fit


def _moment_noise(image: np.ndarray, rng: np.random.Generator, nu: float = 200.0,
                  n_real: int = 48) -> tuple[float, float]:  # fmt: skip
    """Noise of the adaptive moments of a star of this PSF, times its matched-filter S/N.

    Monte Carlo: ``n_real`` copies of ``image`` plus white noise at matched-filter S/N
    ``nu`` (the small-noise, linear regime). Returns ``k_e``, the standard deviation of
    each ellipticity component times the S/N, and ``k_s``, that of ``ln sigma``.
    """
    img = image / image.sum()
    noise = np.sqrt(np.sum(img * img)) / nu
    sims = img[None] + rng.normal(0.0, noise, (n_real,) + img.shape)
    sigma, e1, e2 = _moments_many(sims)
    ok = np.isfinite(sigma) & np.isfinite(e1) & np.isfinite(e2)
    if ok.sum() < 4:
        return np.nan, np.nan
    k_e = nu * np.sqrt(0.5 * (np.var(e1[ok], ddof=1) + np.var(e2[ok], ddof=1)))
    return float(k_e), float(nu * np.std(np.log(sigma[ok]), ddof=1))


def _heldout_summary(tab: Table, k_e: float, k_s: float) -> dict:
    """Residuals of the held-out stars (used in the final fit) against the first fit."""
    sel = np.asarray(tab["heldout"] & tab["used"])
    de1 = np.asarray(tab["e1_star"] - tab["e1_model"])[sel]
    de2 = np.asarray(tab["e2_star"] - tab["e2_model"])[sel]
    ds = np.asarray(tab["sigma_star"] / tab["sigma_model"] - 1.0)[sel]
    snr = np.asarray(tab["snr"])[sel]
    ok = np.isfinite(de1) & np.isfinite(de2) & np.isfinite(ds) & (snr > 0)
    de1, de2, ds, snr = de1[ok], de2[ok], ds[ok], snr[ok]
    if de1.size == 0:
        return {"heldout_n": 0}
    sig_e = k_e / snr
    noise_e = float(np.sqrt(np.mean(sig_e**2)))
    noise_s = float(np.sqrt(np.mean((k_s / snr) ** 2)))
    rms = {k: float(np.sqrt(np.mean(d**2))) for k, d in (("e1", de1), ("e2", de2), ("s", ds))}
    chi2 = float(np.mean(np.concatenate([de1, de2]) ** 2 / np.concatenate([sig_e, sig_e]) ** 2))
    return {
        "heldout_n": int(de1.size),
        "heldout_mean_de1": float(de1.mean()),
        "heldout_mean_de2": float(de2.mean()),
        "heldout_rms_de1": rms["e1"],
        "heldout_rms_de2": rms["e2"],
        "heldout_noise_de": noise_e,
        "heldout_excess_de1": float(np.sqrt(max(rms["e1"] ** 2 - noise_e**2, 0.0))),
        "heldout_excess_de2": float(np.sqrt(max(rms["e2"] ** 2 - noise_e**2, 0.0))),
        "heldout_chi2_de": chi2,
        "heldout_pvalue_de": float(chi2_dist.sf(2 * de1.size * chi2, 2 * de1.size)),
        "heldout_mean_dsigma": float(ds.mean()),
        "heldout_rms_dsigma": rms["s"],
        "heldout_noise_dsigma": noise_s,
        "heldout_excess_dsigma": float(np.sqrt(max(rms["s"] ** 2 - noise_s**2, 0.0))),
        "moment_noise_k_e": k_e,
        "moment_noise_k_sigma": k_s,
    }


# ---------------------------------------------------------------------------------------
# Polynomial: the model
# ---------------------------------------------------------------------------------------
class PolynomialPSF(PSFModel):
    """Every PSF pixel a polynomial in the position (lensfit's survey PSF, PSFEx's model).

    ``P(x, y) = sum_{i + j <= order} c_ij u^i v^j`` with ``u = (x - x0) / sx``,
    ``v = (y - y0) / sy``, ``x0, sx`` the centre and half-width of ``bounds`` (so
    ``u, v`` span ``[-1, 1]`` over them); drawn images are then re-centred by the
    convention (an exact Fourier shift, usually of a few hundredths of a pixel) and
    scaled to unit sum. Positions outside ``bounds`` extrapolate the polynomial.

    Usually made by :meth:`fit` or read by :func:`read_psf_model`.

    Parameters
    ----------
    coefs : numpy.ndarray
        ``(n_terms(order), size, size)`` coefficient images, in the order of the
        monomials ``u^i v^j`` by total degree ``d = i + j`` then by ``j``:
        ``1, u, v, u^2, uv, v^2, ...``.
    order : int
        Total degree of the polynomial.
    bounds : tuple of float
        ``(xmin, xmax, ymin, ymax)`` in 0-based image pixels.
    cov : numpy.ndarray, optional
        ``(p, p)`` covariance of the coefficients of a pixel per unit pixel variance of
        a unit-flux star (the inverse normal matrix of the fit; gives
        :attr:`PSFResult.pixel_noise` of :attr:`centre`).
    stars : astropy.table.Table, optional
        Per-star table of the fit (see :meth:`fit`).
    diagnostics : dict, optional
        Summary of the fit (see :meth:`fit`).
    centroid_sigma : float
        Width in pixels of the Gaussian of the centre convention.
    margin : int
        Padding in pixels of the Fourier re-centring.
    source : str
        Label of where the stars came from.

    Attributes
    ----------
    diagnostics : dict
        For a model from :meth:`fit`: ``order`` (used), ``order_requested``,
        ``n_terms``, ``n_stars`` (candidates), ``n_used``, ``n_rejected``, ``rejected``
        (count per reason), ``chi2_median`` (used stars), ``options``; and the held-out
        check, over the held-out stars that the final fit uses (so that contaminants of
        the list do not count; for a model that rejects many good stars this hides its
        worst misfits): ``n_heldout``, ``heldout_n``, ``heldout_mean_de1/2`` and
        ``heldout_rms_de1/2`` (star minus model ellipticity), ``heldout_noise_de`` (the
        rms expected from the stars' noise alone, ``k_e / snr`` per star with ``k_e``
        from a Monte Carlo of the moments of the model plus noise;
        ``moment_noise_k_e``), ``heldout_excess_de1/2`` (``sqrt(rms^2 - noise^2)``, 0
        if negative: the model's error), ``heldout_chi2_de`` (mean squared residual in
        units of the expected noise, about 1 for a model as good as the noise can
        tell), ``heldout_pvalue_de`` (the chance of a mean at least as large from the
        noise alone: the chi-square distribution of ``2 heldout_n`` degrees of
        freedom, the two components of each star), and the same for the relative size
        ``sigma_star / sigma_model - 1`` (``heldout_*_dsigma``). The noise of the
        held-out model itself is not counted.
    """

    def __init__(self, coefs, order: int, bounds, *, cov=None, stars: Table | None = None,
                 diagnostics: dict | None = None, centroid_sigma: float = 2.0,
                 margin: int = 4, source: str = ""):  # fmt: skip
        coefs = np.array(coefs, dtype=np.float64)
        order = int(order)
        if coefs.ndim != 3 or coefs.shape[0] != n_terms(order) or coefs.shape[1] != coefs.shape[2]:
            raise ValueError(f"coefs must have shape ({n_terms(order)}, size, size) for order "
                             f"{order}, got {coefs.shape}")  # fmt: skip
        b = np.asarray(bounds, dtype=float)
        if b.shape != (4,) or not np.all(np.isfinite(b)):
            raise ValueError(f"bounds must be (xmin, xmax, ymin, ymax), got {bounds!r}")
        self.coefs, self.order, self.bounds = coefs, order, tuple(float(t) for t in b)
        self.size = int(coefs.shape[-1])
        self.cov = None if cov is None else np.array(cov, dtype=np.float64)
        self.stars = stars
        self.diagnostics = dict(diagnostics or {})
        self.centroid_sigma, self.margin, self.source = float(centroid_sigma), int(margin), source
        self._centre: PSFResult | None = None
        self._ft: np.ndarray | None = None

    def __repr__(self) -> str:
        return (f"PolynomialPSF(order={self.order}, size={self.size}, bounds={self.bounds}, "
                f"n_used={self.diagnostics.get('n_used')})")  # fmt: skip

    # -- geometry -------------------------------------------------------------------
    @staticmethod
    def _scale(bounds) -> tuple[float, float, float, float]:
        xmin, xmax, ymin, ymax = bounds
        sx = 0.5 * (xmax - xmin) if xmax > xmin else 1.0
        sy = 0.5 * (ymax - ymin) if ymax > ymin else 1.0
        return 0.5 * (xmin + xmax), sx, 0.5 * (ymin + ymax), sy

    def uv(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Normalised coordinates ``(u, v)`` of 0-based image positions."""
        x0, sx, y0, sy = self._scale(self.bounds)
        return (np.asarray(x, dtype=float) - x0) / sx, (np.asarray(y, dtype=float) - y0) / sy

    # -- drawing ----------------------------------------------------------------------
    def _coef_ft(self) -> np.ndarray:
        """``(p, big * (big//2 + 1))`` phase-referenced transforms of the padded planes."""
        if self._ft is None:
            big = self.size + 2 * self.margin + 1
            F = np.fft.rfft2(pad_to(self.coefs, big)) * _phase(big)[None]
            self._ft = F.reshape(len(F), -1)
        return self._ft

    def _draw_centred(self, x, y):
        """Drawn images, the re-centring shifts and the sums before normalisation.

        The polynomial is evaluated on the Fourier transforms of the (padded)
        coefficient planes, so a position costs one inverse FFT and a few Newton steps.
        """
        big = self.size + 2 * self.margin + 1
        Fc = self._coef_ft()
        parts = []
        for i in range(0, x.size, _CHUNK):
            u, v = self.uv(x[i : i + _CHUNK], y[i : i + _CHUNK])
            D = (_design(u, v, self.order) @ Fc).reshape(-1, big, big // 2 + 1)
            parts.append(_recentre(D, self.size, self.centroid_sigma))
        if not parts:
            z = np.zeros(0)
            return np.zeros((0, self.size, self.size)), z, z, z
        return tuple(np.concatenate([p[k] for p in parts]) for k in range(4))

    def _draw(self, x, y):
        return self._draw_centred(x, y)[0]

    # -- summaries ------------------------------------------------------------------------
    @property
    def centre(self) -> PSFResult:
        """The model at the centre of :attr:`bounds`, with the fit's stars."""
        if self._centre is None:
            self._centre = self._centre_result()
        return self._centre

    def _centre_result(self) -> PSFResult:
        x0, _, y0, _ = self._scale(self.bounds)
        img, _, _, tot = self._draw_centred(np.array([x0]), np.array([y0]))
        noise = np.nan
        if self.cov is not None and self.cov.shape == (self.coefs.shape[0],) * 2:
            a = _design(np.zeros(1), np.zeros(1), self.order)[0]
            noise = float(np.sqrt(max(a @ self.cov @ a, 0.0)) / tot[0])
        t = self.stars
        if t is None:
            t = Table({c: np.zeros(0) for c in _TABLE_COLUMNS})
            t["used"] = np.zeros(0, bool)
            t["reason"] = np.zeros(0, dtype=str)
        cols = {
            c: np.asarray(t[c], dtype=float)
            for c in ("x_cat", "y_cat", "x", "y", "flux", "snr", "correlation", "chi2")
        }
        return PSFResult(image=img[0], used=np.asarray(t["used"], dtype=bool),
                         reason=np.array([str(r).strip() for r in t["reason"]], dtype=str),
                         pixel_noise=noise, source=self.source,
                         meta={"model": "polynomial", "order": self.order,
                               "position": (x0, y0)},
                         **cols, **psf_diagnostics(img[0]))  # fmt: skip

    @property
    def digest(self) -> str:
        return _sha1("PolynomialPSF", self.coefs, self.order, np.array(self.bounds),
                     self.centroid_sigma, self.margin)  # fmt: skip

    # -- fitting --------------------------------------------------------------------------
    @classmethod
    def fit(cls, image: np.ndarray, x, y, *, noise_sigma, weight: np.ndarray | None = None,
            order: int = 2, size: int = 32, bounds=None, holdout: float = 0.2,
            clip: float | None = 2.0, n_iter: int = 3, seed: int = 0,
            min_stars_per_coefficient: float = 5.0, min_correlation: float = 0.9,
            model_error: float = 0.01, core_level: float = 0.01, max_shift: float = 2.0,
            min_snr: float = 10.0, centroid_sigma: float = 2.0, margin: int = 4,
            source: str = "image") -> PolynomialPSF:  # fmt: skip
        """Fit the per-pixel polynomial to star images.

        1. Cutouts, centring on the Gaussian cross-correlation peak (exact Fourier
           shift) and the S/N cut, as in :func:`pylensfit.psf.stack_psf` (whose
           rejection reasons, :data:`pylensfit.psf.REASONS`, are recorded).
        2. ``n_iter`` passes: the unit-flux stars are fitted, every pixel at once, by
           weighted least squares (weights ``flux^2 / sigma^2``, the inverse variance
           of their pixels) with monomials ``u^i v^j``, ``i + j <= order``; then every
           candidate is compared with the model at its own position without itself
           (leave-one-out, through its leverage): re-centred on the cross-correlation
           with it, its flux measured as ``<s, P> / <P, P>``, and rejected (for this
           pass; a later pass may take it back) if it moved more than ``max_shift``,
           has non-positive flux, a noise-debiased correlation below
           ``min_correlation`` or a reduced chi-square in the PSF core above ``clip``
           (the tests of ``stack_psf``). The model is refitted to the survivors.
        3. If fewer than ``min_stars_per_coefficient`` stars per coefficient are
           usable, the order is lowered (a warning is logged), down to 0: the
           inverse-variance stack of ``stack_psf``.
        4. Held-out check: a fraction ``holdout`` of the usable stars (drawn with
           ``numpy.random.default_rng(seed)``) is left out of a second fit of the same
           order, and the adaptive moments of each held-out star are compared with
           those of that model at its position (:attr:`diagnostics`, keys
           ``heldout_*``). The returned model is the fit to all stars.

        Parameters
        ----------
        image : numpy.ndarray
            2-D background-subtracted image indexed ``[y, x]``.
        x, y : array_like
            Catalogue positions of candidate stars, 0-based pixels.
        noise_sigma : float or array_like
            Per-pixel noise standard deviation, scalar or one per star (image units).
        weight : numpy.ndarray, optional
            Weight map; a star whose cutout holds a pixel of weight ``<= 0`` is
            rejected.
        order : int
            Total degree of the polynomial (2, quadratic, by default).
        size : int
            Side of the PSF images in pixels.
        bounds : tuple of float, optional
            ``(xmin, xmax, ymin, ymax)`` mapped onto ``u, v in [-1, 1]``; by default the
            image's extent ``(0, nx - 1, 0, ny - 1)``.
        holdout : float
            Fraction of the stars held out for the diagnostics (0 for none).
        clip : float or None
            Largest reduced chi-square of a star against the model (``stack_psf``'s
            ``max_chi2``); ``None`` disables the test.
        n_iter : int
            Number of fit / check passes.
        seed : int
            Seed of the held-out draw and of the Monte Carlo of the moments' noise.
        min_stars_per_coefficient : float
            Fewest usable stars per polynomial coefficient before the order is lowered.
        min_correlation, model_error, core_level, max_shift, min_snr, centroid_sigma, margin
            As in :func:`pylensfit.psf.stack_psf` (pixels, fractions).
        source : str
            Label of the image, used in messages and stored.

        Returns
        -------
        PolynomialPSF
            The model, with :attr:`stars` (per candidate: ``x_cat, y_cat``; measured
            centre ``x, y`` in 0-based pixels, the convention of the drawn model; ``flux``,
            ``snr``, ``correlation``, ``chi2`` of the last check; ``used``; ``reason``;
            ``heldout``; adaptive moments ``e1_star, e2_star, sigma_star`` of the star and
            ``e1_model, e2_model, sigma_model`` of the model at its position, the held-out
            fit's for held-out stars, the final one's for the others) and
            :attr:`diagnostics`.

        Raises
        ------
        PSFError
            If no usable star remains.
        ValueError
            For inconsistent arguments.
        """
        image, x, y, weight = _check_inputs(image, x, y, weight, size, order, holdout, n_iter)
        opts = {"clip": clip, "n_iter": int(n_iter), "min_correlation": min_correlation,
                "model_error": model_error, "core_level": core_level, "max_shift": max_shift,
                "min_snr": min_snr, "centroid_sigma": centroid_sigma, "margin": int(margin),
                "min_stars_per_coefficient": min_stars_per_coefficient}  # fmt: skip
        if not (centroid_sigma > 0 and max_shift > 0 and margin >= 0):
            raise ValueError("centroid_sigma and max_shift must be positive, margin >= 0")
        sigma_all = per_object(noise_sigma, x.size, "noise_sigma")
        S = _first_stage(image, weight, x, y, sigma_all, size, opts)
        if S.m == 0:
            raise _no_star_error(S.reason, source)
        if bounds is None:
            bounds = (0.0, image.shape[1] - 1.0, 0.0, image.shape[0] - 1.0)
        x0, sx, y0, sy = cls._scale(bounds)
        uv = ((S.ix + S.X - x0) / sx, (S.iy + S.Y - y0) / sy)
        fit = _fit_with_order(S, np.ones(S.m, bool), int(order), uv, opts, source)
        if not fit.used.any():
            reason = S.reason.copy()
            reason[S.idx] = fit.why
            raise _no_star_error(reason, source)
        kw = {"centroid_sigma": centroid_sigma, "margin": margin, "source": source}
        model = cls(fit.coefs, fit.order, bounds, cov=fit.cov, **kw)
        rng = np.random.default_rng(seed)
        hold = _holdout_mask(fit.used, holdout, n_terms(fit.order), rng)
        model_h = None
        if hold.any():
            fit_h = _iterate(S, fit.used & ~hold, fit.order, uv, opts)
            if fit_h.used.any():
                model_h = cls(fit_h.coefs, fit.order, bounds, cov=fit_h.cov, **kw)
        if model_h is None:
            hold[:] = False
        model.stars = _star_table(S, x, y, fit, model, model_h, hold)
        k_e, k_s = _moment_noise(model._draw(np.array([x0]), np.array([y0]))[0], rng)
        model.diagnostics = _fit_diagnostics(model.stars, fit, int(order), opts, source)
        model.diagnostics.update(_heldout_summary(model.stars, k_e, k_s))
        return model

    def variation(self) -> dict:
        """Whether the stars show the PSF varying over the field, beyond their noise.

        The used stars' measured adaptive-moment ellipticities ``e1_star``, ``e2_star``
        and ``ln sigma_star`` are each fitted, weighted by ``snr^2`` (their moments'
        noise goes as ``1 / snr``), by a constant and by the model's polynomial in
        ``(u, v)``. Each quantity's chi-square improvement, in units of the polynomial
        fit's residual variance (so that the noise's scale need not be known), is
        summed: an F statistic on ``q = 3 (n_terms - 1)`` and ``3 (n - n_terms)``
        degrees of freedom, ``n`` the stars.

        Returns
        -------
        dict
            ``vary_pvalue`` (the probability of an F at least this large for a PSF
            constant over the field: small when it varies; 1 for an order-0 model or
            too few stars to tell), ``vary_rms_de`` (rms over the stars of ``|e|``'s
            fitted variation about its mean, dimensionless), ``vary_rms_dsigma`` (the
            same for the size, relative) and ``vary_n`` (the stars).
        """
        out = {"vary_pvalue": 1.0, "vary_rms_de": 0.0, "vary_rms_dsigma": 0.0, "vary_n": 0}
        t, p = self.stars, n_terms(self.order)
        if t is None or self.order == 0:
            return out
        q = [np.asarray(t[c], dtype=float) for c in ("e1_star", "e2_star", "sigma_star")]
        snr = np.asarray(t["snr"], dtype=float)
        sel = (np.asarray(t["used"], bool) & np.isfinite(snr) & (snr > 0) & (q[2] > 0)
               & np.isfinite(q[0]) & np.isfinite(q[1]))  # fmt: skip
        n = int(sel.sum())
        out["vary_n"] = n
        if n < p + 5:
            return out
        u, v = self.uv(np.asarray(t["x"], float)[sel], np.asarray(t["y"], float)[sel])
        A = _design(u, v, self.order)
        sw = snr[sel]
        stat, fitted = 0.0, []
        for y in (q[0][sel], q[1][sel], np.log(q[2][sel])):
            coef = np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)[0]
            model = A @ coef
            chi_poly = float(np.sum((sw * (y - model)) ** 2))
            mean = float(np.sum(sw**2 * y) / np.sum(sw**2))
            chi_const = float(np.sum((sw * (y - mean)) ** 2))
            stat += (chi_const - chi_poly) / max(chi_poly / (n - p), 1e-300)
            fitted.append(model - model.mean())
        dof = 3 * (p - 1)
        out["vary_pvalue"] = float(f_dist.sf(stat / dof, dof, 3 * (n - p)))
        out["vary_rms_de"] = float(np.sqrt(np.mean(fitted[0] ** 2 + fitted[1] ** 2)))
        out["vary_rms_dsigma"] = float(np.sqrt(np.mean(fitted[2] ** 2)))
        return out

    # -- files ----------------------------------------------------------------------------
    def write(self, path: str | Path, overwrite: bool = False) -> None:
        """Write as FITS, atomically.

        The primary HDU holds the ``(p, size, size)`` coefficient cube with header
        keywords ``PSFMODEL = 'POLYNOMIAL'``, ``ORDER``, ``XMIN``, ``XMAX``, ``YMIN``,
        ``YMAX`` (the bounds, 0-based pixels), ``CSIGMA``, ``MARGIN``, ``SOURCE``,
        ``N_USED``, ``N_REJ`` and ``DIAGS`` (:attr:`diagnostics` as JSON); the ``COVAR``
        image HDU the coefficients' covariance and the ``STARS`` table the stars.
        """
        prim = fits.PrimaryHDU(self.coefs)
        hdr = prim.header
        hdr["PSFMODEL"] = (_POLY_KIND, "pylensfit per-pixel polynomial PSF")
        hdr["ORDER"] = (self.order, "total degree in u=(x-x0)/sx, v=(y-y0)/sy")
        for key, val in zip(("XMIN", "XMAX", "YMIN", "YMAX"), self.bounds, strict=True):
            hdr[key] = (val, "bounds mapped on [-1, 1], 0-based pixels")
        hdr["CSIGMA"] = (self.centroid_sigma, "centre convention Gaussian sigma [pixel]")
        hdr["MARGIN"] = (self.margin, "padding of the Fourier re-centring [pixel]")
        # string cards carry no comment: a long value would have it truncated (a warning)
        hdr["SOURCE"] = str(self.source)
        hdr["TERMS"] = " ".join(f"u{i}v{j}" for i, j in _exponents(self.order))
        for key, name in (("N_USED", "n_used"), ("N_REJ", "n_rejected")):
            if name in self.diagnostics:
                hdr[key] = int(self.diagnostics[name])
        hdr["DIAGS"] = json.dumps(jsonable(self.diagnostics), sort_keys=True)
        hdus = [prim]
        if self.cov is not None:
            hdus.append(fits.ImageHDU(self.cov, name="COVAR"))
        if self.stars is not None:
            tab = fits.table_to_hdu(self.stars)
            tab.name = "STARS"
            hdus.append(tab)
        atomic_write(fits.HDUList(hdus), path, overwrite=overwrite)

    @classmethod
    def read(cls, path: str | Path) -> PolynomialPSF:
        """Read a file written by :meth:`write`."""
        with fits.open(path) as hdul:
            hdr = hdul[0].header
            if str(hdr.get("PSFMODEL", "")).strip() != _POLY_KIND:
                raise PSFError(f"{path}: not a PolynomialPSF file (no PSFMODEL = {_POLY_KIND!r})")
            coefs = np.array(hdul[0].data, dtype=np.float64)
            cov = np.array(hdul["COVAR"].data, dtype=np.float64) if "COVAR" in hdul else None
            stars = None
            if "STARS" in hdul:
                data = hdul["STARS"].data
                stars = Table({c: np.array(data[c]) for c in data.names})
            bounds = tuple(float(hdr[k]) for k in ("XMIN", "XMAX", "YMIN", "YMAX"))
            diags = json.loads(hdr.get("DIAGS", "{}"))
            kw = {
                "centroid_sigma": float(hdr.get("CSIGMA", 2.0)),
                "margin": int(hdr.get("MARGIN", 4)),
                "source": str(hdr.get("SOURCE", "")),
            }
            order = int(hdr["ORDER"])
        if stars is not None:
            stars["reason"] = np.array([str(r).strip() for r in stars["reason"]], dtype=str)
            for c in ("used", "heldout"):
                stars[c] = np.asarray(stars[c], dtype=bool)
        return cls(coefs, order, bounds, cov=cov, stars=stars, diagnostics=diags, **kw)


def _check_inputs(image, x, y, weight, size, order, holdout, n_iter):
    image, x, y, weight = check_star_inputs(image, x, y, weight, size)
    if not (int(order) == order and order >= 0):
        raise ValueError(f"order must be a non-negative integer, got {order!r}")
    if not 0.0 <= holdout < 1.0:
        raise ValueError(f"holdout must be in [0, 1), got {holdout!r}")
    if n_iter < 0:
        raise ValueError(f"n_iter must be >= 0, got {n_iter}")
    return image, x, y, weight


def _no_star_error(reason: np.ndarray, source: str) -> PSFError:
    counts = {r: int(np.count_nonzero(reason == r)) for r in set(reason.tolist()) if r}
    detail = ", ".join(f"{k}: {v}" for k, v in sorted(counts.items()))
    return PSFError(f"{source}: no usable PSF star among {reason.size} candidates "
                    f"({detail or 'none'})")  # fmt: skip


def _holdout_mask(used: np.ndarray, fraction: float, p: int, rng) -> np.ndarray:
    """A random ``fraction`` of the used stars, or none if the rest could not fit ``p`` terms."""
    hold = np.zeros(used.size, bool)
    pool = np.flatnonzero(used)
    k = int(round(fraction * pool.size))
    if k >= 1 and pool.size - k >= p + 1:
        hold[rng.choice(pool, k, replace=False)] = True
    return hold


def _star_table(S: _Stars, x, y, fit: _Fit, model, model_h, hold) -> Table:
    """The per-candidate table of :meth:`PolynomialPSF.fit`."""
    n, k = S.n, S.idx
    col = {c: np.full(n, np.nan) for c in _TABLE_COLUMNS if c not in ("used", "reason",
                                                                        "heldout")}  # fmt: skip
    col["x_cat"], col["y_cat"] = x.copy(), y.copy()
    xs, ys = S.ix + fit.X, S.iy + fit.Y
    img, sx, sy, _ = model._draw_centred(xs, ys)
    if model_h is not None and hold.any():
        img[hold] = model_h._draw(xs[hold], ys[hold])
    col["x"][k], col["y"][k] = xs + sx, ys + sy
    col["flux"][k], col["correlation"][k], col["chi2"][k] = fit.flux, fit.corr, fit.chi2
    col["snr"] = S.snr.copy()
    col["snr"][k] = np.where(np.isfinite(fit.snr), fit.snr, S.snr[k])
    col["sigma_star"][k], col["e1_star"][k], col["e2_star"][k] = _moments_many(fit.unit)
    col["sigma_model"][k], col["e1_model"][k], col["e2_model"][k] = _moments_many(img)
    reason = S.reason.copy()
    reason[k] = fit.why
    used = np.zeros(n, bool)
    used[k] = fit.used
    reason[used] = ""
    heldout = np.zeros(n, bool)
    heldout[k] = hold
    col["used"], col["heldout"] = used, heldout
    col["reason"] = np.array([str(r) for r in reason], dtype=str) if n else np.zeros(0, str)
    return Table({c: col[c] for c in _TABLE_COLUMNS})


def _fit_diagnostics(tab: Table, fit: _Fit, order_requested: int, opts: dict, source) -> dict:
    reason = np.asarray(tab["reason"], dtype=str)
    used = np.asarray(tab["used"], dtype=bool)
    chi2 = np.asarray(tab["chi2"], dtype=float)[used]
    return {
        "kind": "polynomial",
        "order": fit.order,
        "order_requested": order_requested,
        "n_terms": n_terms(fit.order),
        "n_stars": int(used.size),
        "n_used": int(used.sum()),
        "n_rejected": int((~used).sum()),
        "rejected": {r: int(np.sum(reason == r)) for r in sorted(set(reason.tolist())) if r},
        "n_heldout": int(np.sum(tab["heldout"])),
        "chi2_median": float(np.median(chi2)) if chi2.size else np.nan,
        "source": source,
        "options": dict(opts),
    }


# ---------------------------------------------------------------------------------------
# Piff
# ---------------------------------------------------------------------------------------
def _import_piff():
    try:
        import piff  # the optional [piff] extra
    except ImportError:
        raise PiffNotInstalledError(
            "reading a Piff PSF model needs piff: pip install pylensfit[piff]"
        ) from None
    return piff


class PiffPSF(PSFModel):
    """A PSF model fitted by Piff (Jarvis et al. 2021), drawn by the package's convention.

    Piff draws its model at each position (in GalSim's image coordinates: our 0-based
    pixel ``x`` is GalSim's ``x + origin``, ``origin = 1`` for a Piff model fitted on a
    FITS image) on an odd stamp of ``size + 2 margin + 1`` pixels, the profile's nominal
    centre on the stamp's central pixel; the image is then moved by an exact Fourier
    shift so that its Gaussian cross-correlation peak is on ``[size//2, size//2]``,
    cropped to ``size x size`` and scaled to unit sum. The pixel response is the one of
    Piff's model (a ``PixelGrid`` model includes it).

    Parameters
    ----------
    path : str or Path
        A file written by Piff (``piff.PSF.write``).
    size : int
        Side of the drawn images in pixels.
    chipnum : int, optional
        Piff's chip number (needed only for a model of several chips).
    centroid_sigma : float
        Width in pixels of the Gaussian of the centre convention.
    margin : int
        Padding in pixels of the Fourier re-centring.
    origin : float
        GalSim image coordinate of our pixel 0.
    centre_xy : tuple of float, optional
        Position (0-based pixels) of :attr:`centre`; by default the middle of the
        bounding box of Piff's stars.

    Raises
    ------
    PiffNotInstalledError
        If piff is not installed.
    PSFError
        If Piff cannot read the file.

    Notes
    -----
    Piff draws one position at a time (about 0.4 ms each for a ``PixelGrid`` model).
    Models that interpolate on properties other than the position (e.g. a colour) are
    not supported.
    """

    def __init__(self, path: str | Path, *, size: int = 32, chipnum: int | None = None,
                 centroid_sigma: float = 2.0, margin: int = 4, origin: float = 1.0,
                 centre_xy: tuple[float, float] | None = None):  # fmt: skip
        piff = _import_piff()
        self.path = Path(path)
        try:
            self._bytes = self.path.read_bytes()
            self.piff = piff.read(str(self.path))
        except (OSError, ValueError, KeyError, TypeError, IndexError) as err:
            first = (str(err).strip().splitlines() or [type(err).__name__])[0]
            raise PSFError(f"{self.path}: not a readable Piff file ({first})") from None
        self.size, self.chipnum, self.origin = int(size), chipnum, float(origin)
        self.centroid_sigma, self.margin = float(centroid_sigma), int(margin)
        if self.size < 4:
            raise ValueError(f"size must be at least 4, got {size}")
        sx, sy = self._star_positions()
        self.centre_xy = centre_xy
        if centre_xy is None and sx.size:
            self.centre_xy = (
                float(0.5 * (sx.min() + sx.max())),
                float(0.5 * (sy.min() + sy.max())),
            )
        self.diagnostics = {"kind": "piff", "path": str(self.path), "n_stars": int(sx.size),
                            "piff_version": str(getattr(self.piff, "piff_version", "")),
                            "piff_class": type(self.piff).__name__}  # fmt: skip
        self._centre: PSFResult | None = None

    def __repr__(self) -> str:
        return f"PiffPSF({str(self.path)!r}, size={self.size})"

    def _star_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """0-based positions of the stars stored with the model (empty if none)."""
        stars = getattr(self.piff, "stars", None) or []
        pos = [(s.image_pos.x - self.origin, s.image_pos.y - self.origin) for s in stars]
        arr = np.array(pos, dtype=float).reshape(-1, 2)
        return arr[:, 0], arr[:, 1]

    def _draw(self, x, y):
        import galsim  # galsim: heavy import, only when Piff draws

        big = self.size + 2 * self.margin + 1
        stamps = np.empty((x.size, big, big))
        for i, (xi, yi) in enumerate(zip(x + self.origin, y + self.origin, strict=True)):
            img = galsim.ImageD(big, big)
            img.setCenter(int(np.floor(xi + 0.5)), int(np.floor(yi + 0.5)))
            self.piff.draw(x=float(xi), y=float(yi), chipnum=self.chipnum, image=img,
                           center=(float(img.center.x), float(img.center.y)))  # fmt: skip
            stamps[i] = img.array
        if x.size == 0:
            return np.zeros((0, self.size, self.size))
        D = np.fft.rfft2(stamps) * _phase(big)[None]
        return _recentre(D, self.size, self.centroid_sigma, search=2.0)[0]

    @property
    def centre(self) -> PSFResult:
        """Piff's model at :attr:`centre_xy` as a :class:`PSFResult` (with no stars)."""
        if self._centre is None:
            if self.centre_xy is None:
                raise PSFError(f"{self.path}: no stars in the Piff file: pass centre_xy")
            img = self.draw(*self.centre_xy)
            empty = np.zeros(0)
            self._centre = PSFResult(image=img, x_cat=empty, y_cat=empty, x=empty, y=empty,
                                     flux=empty, snr=empty, correlation=empty, chi2=empty,
                                     used=np.zeros(0, bool), reason=np.zeros(0, dtype=str),
                                     source=str(self.path),
                                     meta={"model": "piff", "position": self.centre_xy},
                                     **psf_diagnostics(img))  # fmt: skip
        return self._centre

    @property
    def digest(self) -> str:
        return _sha1("PiffPSF", self._bytes, self.size, self.chipnum, self.origin,
                     self.centroid_sigma, self.margin)  # fmt: skip

    def write(self, path, overwrite=False):
        """Copy the Piff file (byte for byte), atomically."""
        _atomic_write_bytes(self._bytes, Path(path), overwrite)


# ---------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------
def fit_piff(image: np.ndarray, x, y, path: str | Path, *, noise_sigma: float,
             order: int = 2, pixels: int = 15, half: int = 12, overwrite: bool = False) -> Path:
    """Fit a Piff PSF model to an image's stars with Piff, and write it.

    The model is Piff's ``SimplePSF`` of a ``PixelGrid`` (``pixels`` square, one pixel
    per image pixel, the pixel response included) whose every pixel is a
    ``BasisPolynomial`` of total degree ``order`` in the position, fitted in three
    outlier-rejection passes to ``(2 half + 1)``-square cutouts about the stars (those
    not wholly inside the image are skipped), each pixel weighted ``1 / noise_sigma^2``.
    :class:`PiffPSF` reads the file back (``origin = 1``: the cutouts are placed in
    GalSim's 1-based image coordinates).

    The grid must hold the PSF's wings, not only its core: the default 15-pixel grid
    suits a Moffat PSF of FWHM about 3 px and beta 3.5. On Moffat PSFs of beta 3 and
    FWHM 3.5-4.5 px it leaves the core's ellipticity within 3e-4 of the truth but leaks
    the PSF's ellipticity into the galaxies' shears (alpha +0.05 to +0.12 per PSF on a
    STEP2-like set, ``benchmarks/psf_field.py``); ``pixels=31, half=20`` takes that to
    within the errors (+0.015 +- 0.023) at about 25 times the fitting time.

    Parameters
    ----------
    image : numpy.ndarray
        2-D background-subtracted image indexed ``[y, x]``.
    x, y : array_like
        0-based pixel positions of the stars.
    path : str or Path
        Where to write the model (a ``.piff`` file).
    noise_sigma : float
        Per-pixel noise standard deviation (image units).
    order : int
        Degree of the polynomial in the position.
    pixels : int
        Side of the ``PixelGrid`` in pixels.
    half : int
        Half-side of the star cutouts in pixels.
    overwrite : bool
        Replace an existing file.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    PiffNotInstalledError
        If piff is not installed.
    FileExistsError
        If ``path`` exists and ``overwrite`` is False.
    PSFError
        If no star's cutout lies inside the image.
    """
    piff = _import_piff()
    import galsim  # galsim: heavy import, only with piff

    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists (overwrite=False)")
    full = galsim.ImageD(np.asarray(image, dtype=float), scale=1.0)  # (1, 1) is [0, 0]
    wt = galsim.ImageD(np.full(full.array.shape, 1.0 / float(noise_sigma) ** 2), scale=1.0)
    stars = []
    for xi, yi in zip(np.asarray(x, float) + 1.0, np.asarray(y, float) + 1.0, strict=True):
        ix, iy = int(round(xi)), int(round(yi))
        b = galsim.BoundsI(ix - half, ix + half, iy - half, iy + half)
        if full.bounds.includes(b):
            data = piff.StarData(full[b].copy(), galsim.PositionD(xi, yi), weight=wt[b].copy(),
                                 properties={"chipnum": 0})  # fmt: skip
            stars.append(piff.Star(data, None))
    if not stars:
        raise PSFError(f"{path}: no star cutout lies inside the image")
    try:
        interp = piff.BasisPolynomial(order=int(order), solver="cpp")  # 2-3x faster
    except (TypeError, ValueError):
        interp = piff.BasisPolynomial(order=int(order))
    model = piff.SimplePSF(piff.PixelGrid(scale=1.0, size=int(pixels)), interp, max_iter=3)
    model.set_context({0: galsim.PixelScale(1.0)}, None)
    model.fit(stars)
    path.parent.mkdir(parents=True, exist_ok=True)
    model.write(str(path))
    return path


def _is_piff_fits(hdul) -> bool:
    return "PSF" in hdul and "PSF_WCS" in hdul and not hdul[0].header.get("PSFMODEL")


def read_psf_model(path: str | Path, **piff_options) -> PSFModel:
    """Read a PSF model: Piff's, a :class:`PolynomialPSF` or a constant PSF image.

    Parameters
    ----------
    path : str or Path
        A ``.piff`` file or a FITS file written by Piff (:class:`PiffPSF`); a file
        written by :meth:`PolynomialPSF.write` (:class:`PolynomialPSF`); a file written by
        :meth:`pylensfit.psf.PSFResult.write`, or any FITS file holding a 2-D PSF image
        (:class:`ConstantPSF`, through :func:`pylensfit.psf.read_psf`).
    **piff_options
        Keyword arguments of :class:`PiffPSF` (``size``, ``chipnum``, ...), for a Piff
        file only.

    Returns
    -------
    PSFModel

    Raises
    ------
    PSFError
        If the file cannot be read as any of them.
    PiffNotInstalledError
        For a Piff file when piff is not installed.
    """
    path = Path(path)
    if path.suffix.lower() == ".piff":
        return PiffPSF(path, **piff_options)
    try:
        with fits.open(path) as hdul:
            kind = str(hdul[0].header.get("PSFMODEL", "")).strip()
            piff_file = _is_piff_fits(hdul)
    except (OSError, ValueError) as err:
        raise PSFError(f"{path}: not a readable PSF file ({err})") from None
    if piff_file:
        return PiffPSF(path, **piff_options)
    if piff_options:
        raise TypeError(f"options {sorted(piff_options)} apply to Piff files only")
    if kind == _POLY_KIND:
        return PolynomialPSF.read(path)
    return ConstantPSF(read_psf(path))
