"""Metacalibration of postage stamps: the shear response measured on the data themselves.

lensfit's shear sensitivity (:func:`pylensfit.shear.shear_sensitivity`) is the response
of the posterior mean to a shear *if the galaxy is one of the models*. A galaxy whose
profile the model family does not hold (a Sersic index below 1, star-forming knots)
responds otherwise, and ``sum <e> / sum s`` is biased by the difference (model bias).
Metacalibration (Huff & Mandelbaum 2017, Sheldon & Huff 2017) measures the response of
any estimator on the data: the stamp is deconvolved by its PSF, sheared by a small
``+-delta`` in each component, and convolved again with a slightly larger PSF ``P_r``;
the estimator applied to the four sheared images gives its response by finite
differences,

    R_ij = (<e_i>(+delta_j) - <e_i>(-delta_j)) / (2 delta),

and to the unsheared one (deconvolved and convolved with ``P_r`` too) the measurement
whose mean ``R^-1 <e>`` estimates the shear. Here the estimator is lensfit's posterior
mean: the fit's likelihood ``L(e)`` of each image (with ``P_r`` as its PSF) and the
prior give ``<e>`` (:func:`response`).

The operation on a stamp ``I`` with PSF ``P`` (both sampled on the same ``N x N`` grid,
centred on element ``[N//2, N//2]``) is, in Fourier space,

    I_s(k) = I(S k) P_r(k) / P(S k),    P_r(k) = P(f k),

with ``S = [[1 + d1, d2], [d2, 1 - d1]] / sqrt(1 - |d|^2)`` the shear's (area-preserving)
matrix, ``f = 1 + 2 |delta|`` the reconvolution PSF's dilation (ngmix's choice: it keeps
``|P_r(k)| <= |P(S k)|``, so no frequency's noise is amplified) and ``I(q)``, ``P(q)``
the transforms of the pixel values at any frequency ``q``,
``sum_x I(x) exp(-i q.x)`` (``x`` from the stamp's centre): the band-limited
interpolation of the samples. The transforms at the sheared frequencies are one real
matrix product per image set (``(n, N^2) @ (N^2, N (N/2 + 1))``, twice), exact, with
no interpolation kernel to choose.

The deconvolution and shear turn the white pixel noise into anisotropic correlated
noise, which would itself respond to ``delta``. As ngmix does, a second noise field of
the same level, rotated by 90 degrees, is put through the same operation, rotated back
and added ("fixnoise"): its anisotropy cancels that of the data's noise. The images
then carry twice the pixel noise variance at low frequencies, where the galaxies'
signal is; their fits assume ``sqrt(2)`` times the input noise, white
(:attr:`MetacalImages.noise_sigma`). The noise power of the unsheared image is
``sigma^2 (|P_r(k) / P(k)|^2 + |P_r(R k) / P(R k)|^2)`` (``R`` the 90-degree turn): that
level at low ``|k|``, less towards Nyquist. On exact exponential models under a round
PSF at S/N 7-20 the response measured so matches the true shear's within its error,
``(m1 + m2) / 2 = -0.002 +- 0.004`` (``benchmarks/studies/metacal_faint.py``,
``benchmarks/README.md``).

The operation is exact for a galaxy whose light (through the PSF's wings too) the stamp
holds: the transforms are those of the stamp's pixels alone. Where the stamp cuts the
light, the shear of the cut image is not the cut image of the sheared galaxy, and the
difference reaches the whole stamp, its core included: under a Kolmogorov PSF (FWHM 4
px) a de Vaucouleurs galaxy of half-light radius 1.5 px on 32 pixels (0.6 % of its light
in the edge rows) has its sheared images wrong by 20 % of the shear's signal, on 96
pixels by 0.04 %. Noise-free, the posterior mean's response on the realistic population
on 32-pixel stamps is then 4.5 +- 1.2 % too large in ``e1`` (0.7 +- 0.3 % in ``e2``),
on 64 pixels exact (``benchmarks/studies/metacal_operation.py``): give the operation
stamps that hold the galaxies' light (``Config().largest_stamp``; the fits cut them to
their tiers).

Under a WCS whose local Jacobian ``J = d(x, y) / d(u, v)`` (pixels by sky coordinates,
any units; :func:`pylensfit.exposures.local_jacobian`) rotates, flips or distorts the
pixels, the shears are made on the sky: the pixel frequencies go to ``J^-T S J^T k``, so
that ``R`` is the response of the pixel frame's estimate to the sky's shear, and the
``"round"`` reconvolution PSF (:func:`round_reconvolution`) is round on the sky, not in
the pixels (Sheldon & Huff 2017, arXiv:1702.02601; ngmix issue 72 is the error of
making it round in the pixel frame).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from astropy.table import Table

from .config import Config
from .joint import fit_exposures
from .likelihood import fit_stamps
from .prior import mix_bulge_fractions, usable_rows
from .psf import centre_on_stamp
from .shear import posterior_moments, shear_sensitivity

__all__ = ["METACAL_TYPES", "MetacalBranches", "MetacalImages", "metacal_branches",
           "metacal_exposures", "metacal_fits", "metacal_images", "metacal_shapes",
           "metacal_shear", "response", "round_reconvolution"]

#: The images of one metacalibration: unsheared, and sheared by ``+-delta`` in ``e1``
#: and in ``e2``.
METACAL_TYPES: tuple[str, ...] = ("noshear", "1p", "1m", "2p", "2m")


@dataclass
class MetacalImages:
    """The metacalibration images of a set of stamps.

    Attributes
    ----------
    images : dict of numpy.ndarray
        ``(n, N, N)`` float32 images per type of :data:`METACAL_TYPES`.
    psf : numpy.ndarray
        ``(N, N)`` the reconvolution PSF ``P_r`` (unit sum), the PSF of every image.
    noise_sigma : float or numpy.ndarray
        The white per-pixel noise the fits should assume: ``sqrt(2)`` times the input's
        (the data's noise and the added field's); one per stamp if the input had one per
        stamp.
    step : float
        The shear ``delta`` of the sheared images.
    """

    images: dict[str, np.ndarray]
    psf: np.ndarray
    noise_sigma: float | np.ndarray
    step: float


def _shear_matrix(d1: float, d2: float) -> np.ndarray:
    """The area-preserving matrix of a reduced shear ``(d1, d2)``."""
    return np.array([[1 + d1, d2], [d2, 1 - d1]]) / math.sqrt(1.0 - d1 * d1 - d2 * d2)


def _shears(step: float) -> dict[str, tuple[float, float]]:
    return {"noshear": (0.0, 0.0), "1p": (step, 0.0), "1m": (-step, 0.0),
            "2p": (0.0, step), "2m": (0.0, -step)}  # fmt: skip


@lru_cache(maxsize=8)
def _dft_matrices(n: int, a11: float, a12: float, a21: float, a22: float):
    """``cos`` and ``sin`` of ``q.x`` for the ``rfft2`` frequencies ``k`` mapped to
    ``q = A k``, and the pixels ``x`` of an ``n x n`` stamp (from its centre):
    ``(n^2, n (n/2 + 1))`` float64 each, rows in the stamp's C order."""
    x1 = np.arange(n) - n // 2
    ys, xs = np.meshgrid(x1, x1, indexing="ij")
    kx, ky = _frequencies(n)
    qx = a11 * kx + a12 * ky
    qy = a21 * kx + a22 * ky
    ph = np.outer(xs.ravel(), qx.ravel()) + np.outer(ys.ravel(), qy.ravel())
    return np.cos(ph), np.sin(ph)


@lru_cache(maxsize=16)
def _dft_vectors(n: int, a: float, b: float) -> tuple[np.ndarray, np.ndarray]:
    """``exp(-i a k_x x)`` ``(n, n/2 + 1)`` and ``exp(-i b k_y y)`` ``(n, n)`` (rows ``y``,
    columns ``k_y``) for the pixels from the stamp's centre: the transform at ``A k``
    for a diagonal ``A = diag(a, b)`` is separable."""
    x1 = np.arange(n) - n // 2
    kx = 2 * np.pi * np.fft.rfftfreq(n)
    ky = 2 * np.pi * np.fft.fftfreq(n)
    return np.exp(-1j * a * np.outer(x1, kx)), np.exp(-1j * b * np.outer(x1, ky))


def _transform(img: np.ndarray, A: np.ndarray) -> np.ndarray:
    """``sum_x img(x) exp(-i (A k).x)`` on the ``rfft2`` frequencies: ``(m, n, n/2+1)``.

    A diagonal ``A`` (the unsheared image and the shears along the pixel axes) takes two
    one-dimensional products, ``n^3`` per image; any other takes one ``n^4`` product."""
    m, n = img.shape[0], img.shape[-1]
    if A[0, 1] == 0.0 and A[1, 0] == 0.0:
        Ex, Ey = _dft_vectors(n, float(A[0, 0]), float(A[1, 1]))
        return np.matmul(Ey.T, img.astype(np.float64, copy=False) @ Ex)
    C, S = _dft_matrices(n, *(float(v) for v in A.ravel()))
    flat = img.reshape(m, n * n).astype(np.float64, copy=False)
    return (flat @ C - 1j * (flat @ S)).reshape(m, n, n // 2 + 1)


def _frequencies(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``kx, ky`` of the ``rfft2`` frequencies of an ``n x n`` stamp, ``(n, n/2 + 1)``."""
    return np.meshgrid(2 * np.pi * np.fft.rfftfreq(n), 2 * np.pi * np.fft.fftfreq(n),
                       indexing="xy")  # fmt: skip


def _to_image(F: np.ndarray, n: int) -> np.ndarray:
    """The real image (centred on ``[n//2, n//2]``) whose centred transform is ``F``."""
    kx, ky = _frequencies(n)
    shift = np.exp(-1j * (n // 2) * (kx + ky))
    return np.fft.irfft2(F * shift, s=(n, n), axes=(-2, -1))


def _checked_inputs(stamps, psf, noise_sigma, step: float, dilation, types):
    """:func:`metacal_images`' inputs checked: ``(stamps (n, N, N), single, psf (unit
    sum), noise sigma, dilation)``; ``ValueError`` naming the first problem."""
    st = np.asarray(stamps, dtype=np.float64)
    single = st.ndim == 2
    st = st[None] if single else st
    psf = np.asarray(psf, dtype=np.float64)
    n = st.shape[-1]
    if st.ndim != 3 or st.shape[-2] != n or psf.shape != (n, n):
        raise ValueError(f"metacal_images needs square stamps and a PSF of their size, got "
                         f"{st.shape} and {psf.shape}")  # fmt: skip
    if not 0.0 < step < 0.2:
        raise ValueError(f"step must be in (0, 0.2), got {step}")
    f = 1.0 + 2.0 * step if dilation is None else float(dilation)
    if not 1.0 + step <= f < 2.0:
        raise ValueError(f"dilation must be in [1 + step, 2), got {dilation}")
    unknown = set(types) - set(METACAL_TYPES)
    if unknown:
        raise ValueError(f"unknown metacal types {sorted(unknown)}; use {METACAL_TYPES}")
    if not np.isfinite(st).all() or not np.isfinite(psf).all():
        raise ValueError("metacal_images got non-finite pixels")
    sig = np.asarray(noise_sigma, dtype=np.float64)
    if sig.ndim > 1 or (sig.ndim == 1 and sig.shape != st.shape[:1]) or not (
            np.isfinite(sig).all() and (sig >= 0).all()):
        raise ValueError(f"noise_sigma must be >= 0, one value or one per stamp ({st.shape[0]}), "
                         f"got {noise_sigma!r}")  # fmt: skip
    return st, single, psf / psf.sum(), sig, f


def _rotated_noise(st: np.ndarray, sig: np.ndarray, noise_fields, seed) -> np.ndarray | None:
    """The added noise field (``noise_fields`` times ``sig``) turned by 90 degrees about
    the stamps' centre ``[N//2, N//2]``; None for noise-free stamps."""
    if not bool((sig > 0).any()):
        return None
    if noise_fields is None:
        if seed is None:
            raise ValueError("metacal_images needs noise_fields or a seed for noisy stamps")
        noise_fields = np.random.default_rng(seed).standard_normal(st.shape)
    noise = np.asarray(noise_fields, dtype=np.float64).reshape(st.shape) * (
        sig[:, None, None] if sig.ndim == 1 else sig)
    # np.rot90 turns about (N-1)/2: roll by one pixel after it to turn about N//2 on an
    # even stamp
    rot = np.rot90(noise, 1, axes=(-2, -1))
    return np.roll(rot, 1, axis=-2) if st.shape[-1] % 2 == 0 else rot


def _centre_offsets(centres, st: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The galaxies' centres from the stamps' centres ``[N//2, N//2]`` (px)."""
    n = st.shape[-1]
    if centres is None:
        return np.zeros(st.shape[0]), np.zeros(st.shape[0])
    cx = np.broadcast_to(np.asarray(centres[0], float) - n // 2, st.shape[:1])
    cy = np.broadcast_to(np.asarray(centres[1], float) - n // 2, st.shape[:1])
    if not (np.isfinite(cx).all() and np.isfinite(cy).all()):
        raise ValueError("metacal_images got non-finite centres")
    return cx, cy


def metacal_images(
    stamps: np.ndarray,
    psf: np.ndarray,
    noise_sigma: float | np.ndarray,
    *,
    step: float = 0.01,
    noise_fields: np.ndarray | None = None,
    seed: int | None = None,
    types: tuple[str, ...] = METACAL_TYPES,
    centres: tuple[np.ndarray, np.ndarray] | None = None,
    dilation: float | None = None,
    jacobian: np.ndarray | None = None,
    reconvolution: str = "dilate",
) -> MetacalImages:
    """Deconvolve, shear by ``+-step`` and reconvolve a set of stamps (module docstring).

    Parameters
    ----------
    stamps : numpy.ndarray
        ``(n, N, N)`` (or one ``(N, N)``) images indexed ``[k, y, x]``, each galaxy
        near element ``[N//2, N//2]``, the point about which it is sheared unless
        ``centres`` are given.
    psf : numpy.ndarray
        ``(N, N)`` PSF image including the pixel response, centred on ``[N//2, N//2]``,
        any normalisation. It should be at least Nyquist sampled.
    noise_sigma : float or numpy.ndarray
        The stamps' white per-pixel noise, one value or one per stamp (0: noise-free
        stamps, no added field).
    step : float
        The shear ``delta`` of the sheared images (ngmix's 0.01 by default).
    noise_fields : numpy.ndarray, optional
        ``(n, N, N)`` the added noise fields, unit variance (scaled by ``noise_sigma``):
        give the same ones to renderings that share their pixel noise, so that paired
        measurements stay paired. Drawn from ``seed`` if not given.
    seed : int, optional
        Seed of the added noise fields (required with noise unless ``noise_fields``).
    types : tuple of str
        Which of :data:`METACAL_TYPES` to make.
    centres : tuple of numpy.ndarray, optional
        ``(x, y)`` per stamp, in its pixels (0-based): the points about which the
        images are sheared (default the element ``[N//2, N//2]``). Give the galaxies'
        fitted centres (:attr:`pylensfit.likelihood.StampFits.x`, ``.y``): a shear about
        another point also moves the galaxy, by ``delta`` times its offset, and the
        estimator's response to that move (through the position prior about the
        catalogue position) is not a response to shear.
    dilation : float, optional
        The reconvolution PSF's dilation ``f`` (``P_r(k) = P(f k)``), at least
        ``1 + |step|`` so that no frequency's noise is amplified (default ``1 + 2 step``):
        give one value to compare steps at the same reconvolution PSF, and so the same
        estimator.
    jacobian : numpy.ndarray, optional
        ``(2, 2)`` the pixels' ``J = d(x, y) / d(u, v)`` (any units): the shears are the
        sky's (module docstring). Default: the pixel frame.
    reconvolution : {"dilate", "round"}
        ``P_r``: the PSF dilated by ``f``, or the round PSF of
        :func:`round_reconvolution` (round on the sky).

    Returns
    -------
    MetacalImages
        The images, the reconvolution PSF and the noise level to fit them with.
    """
    st, single, psf, sig, f = _checked_inputs(stamps, psf, noise_sigma, step, dilation, types)
    Jn = _normalised_jacobian(jacobian)
    n = st.shape[-1]
    rot = _rotated_noise(st, sig, noise_fields, seed)
    noisy = rot is not None
    centre = _centre_offsets(centres, st)
    Pr = _reconvolution(psf, f, Jn, reconvolution)
    out = {}
    for t in types:
        S = _shear_matrix(*_shears(step)[t])
        A = np.linalg.solve(Jn.T, S @ Jn.T)  # J^-T S J^T: the sky's shear on pixel frequencies
        img = _sheared(st, rot, psf, Pr, A, centre)
        out[t] = (img[0] if single else img).astype(np.float32)
    psf_r = _to_image(Pr[None], n)[0]
    sig_fit = (sig if sig.ndim else float(sig)) * (math.sqrt(2.0) if noisy else 1.0)
    return MetacalImages(images=out, psf=psf_r / psf_r.sum(), noise_sigma=sig_fit, step=float(step))


def _normalised_jacobian(jacobian) -> np.ndarray:
    """``J / sqrt(|det J|)`` (the identity for None): only the Jacobian's shape matters."""
    if jacobian is None:
        return np.eye(2)
    J = np.asarray(jacobian, dtype=np.float64)
    det = float(np.linalg.det(J)) if J.shape == (2, 2) and np.isfinite(J).all() else 0.0
    if det == 0.0:
        raise ValueError(f"jacobian must be a finite, invertible (2, 2) matrix, got {jacobian!r}")
    return J / math.sqrt(abs(det))


def _transform_at(img: np.ndarray, qx: np.ndarray, qy: np.ndarray) -> np.ndarray:
    """``sum_x img(x) exp(-i q.x)`` of one ``(n, n)`` image (``x`` from ``[n//2, n//2]``)
    at the frequencies ``(qx, qy)`` (any shape, rad / px)."""
    n = img.shape[-1]
    x1 = np.arange(n) - n // 2
    ex = np.exp(-1j * np.multiply.outer(qx.ravel(), x1))  # (q, n) along x
    ey = np.exp(-1j * np.multiply.outer(qy.ravel(), x1))  # (q, n) along y
    return np.sum((ey @ img) * ex, axis=1).reshape(qx.shape)


def round_reconvolution(psf: np.ndarray, dilation: float,
                        jacobian: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """A round reconvolution PSF's transform: no larger than the dilated PSF's anywhere.

    On the sky frequencies ``q = J^T k`` (``J`` normalised to ``|det J| = 1``), the
    transform is ``p(|q|) = min over directions of |P(f J^-T q)|``, made non-increasing
    in ``|q|``: round on the sky, and, where ``|P|`` falls along every ray from the
    origin (every PSF without zeros in its transform), ``p <= |P(S k)|`` for the
    metacalibration's shears ``S`` (``|S k| <= f |k|``), so that no frequency's noise is
    amplified.

    Parameters
    ----------
    psf : numpy.ndarray
        ``(N, N)`` PSF image of unit sum, centred on ``[N//2, N//2]``.
    dilation : float
        ``f``, at least ``1 + |step|``.
    jacobian : numpy.ndarray, optional
        ``(2, 2)`` the pixels' ``d(x, y) / d(u, v)`` (default the identity).

    Returns
    -------
    numpy.ndarray
        ``(N, N/2 + 1)`` real, the transform on the ``rfft2`` frequencies of the stamp
        (about its centre), 1 at ``k = 0``.
    """
    Jn = _normalised_jacobian(jacobian)
    n = psf.shape[-1]
    kx, ky = _frequencies(n)
    q = np.hypot(Jn[0, 0] * kx + Jn[1, 0] * ky, Jn[0, 1] * kx + Jn[1, 1] * ky)
    rho = np.linspace(0.0, float(q.max()) * 1.001, 2 * n + 1)
    theta = np.linspace(0.0, np.pi, 4 * n, endpoint=False)  # |P(-k)| = |P(k)|
    ux, uy = np.cos(theta), np.sin(theta)
    Jit = np.linalg.inv(Jn.T) * float(dilation)
    px = np.multiply.outer(rho, Jit[0, 0] * ux + Jit[0, 1] * uy)
    py = np.multiply.outer(rho, Jit[1, 0] * ux + Jit[1, 1] * uy)
    amp = np.abs(_transform_at(psf / psf.sum(), px, py)).min(axis=1)
    amp = np.minimum.accumulate(amp)
    return np.interp(q, rho, amp / amp[0])


def _reconvolution(psf: np.ndarray, f: float, Jn: np.ndarray, how: str) -> np.ndarray:
    """The reconvolution PSF's transform on the ``rfft2`` frequencies (``how``: "dilate",
    "round")."""
    if how == "round":
        return round_reconvolution(psf, f, Jn)
    if how != "dilate":
        raise ValueError(f"reconvolution must be 'dilate' or 'round', got {how!r}")
    return _transform(psf[None], np.diag([f, f]))[0]


def _sheared(st: np.ndarray, rot: np.ndarray | None, psf: np.ndarray, Pr: np.ndarray,
             A: np.ndarray, centre: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """The stamps ``st`` deconvolved by ``psf``, their frequencies mapped by ``A`` about
    the galaxies' ``centre`` offsets, reconvolved by ``Pr`` (a transform); with the
    rotated noise field ``rot`` put through the same and turned back."""
    n = st.shape[-1]
    kx, ky = _frequencies(n)
    cx, cy = centre
    Ps = _transform(psf[None], A)[0]
    good = np.abs(Ps) > 1e-9 * abs(Ps[0, 0])
    kern = np.where(good, Pr / np.where(good, Ps, 1.0), 0.0)
    # about the centre c: exp(i (A k - k).c) on the transforms about the stamp's centre
    qx, qy = A[0, 0] * kx + A[0, 1] * ky - kx, A[1, 0] * kx + A[1, 1] * ky - ky
    move = np.exp(1j * (qx * cx[:, None, None] + qy * cy[:, None, None])) * kern
    img = _to_image(_transform(st, A) * move, n)
    if rot is not None:  # the rotated field sheared by the same delta, then turned back
        nz = _to_image(_transform(rot, A) * kern, n)
        if n % 2 == 0:
            nz = np.roll(nz, -1, axis=-2)
        img += np.rot90(nz, -1, axes=(-2, -1))
    return img


def response(e: dict[str, np.ndarray], step: float) -> np.ndarray:
    """The metacalibration response matrix of each galaxy from its sheared images' means.

    Parameters
    ----------
    e : dict of numpy.ndarray
        ``(n, 2)`` posterior mean ellipticities of the images ``1p, 1m, 2p, 2m``.
    step : float
        Their shear ``delta``.

    Returns
    -------
    numpy.ndarray
        ``(n, 2, 2)``: ``R[:, i, j] = (<e_i>(+delta_j) - <e_i>(-delta_j)) / (2 delta)``.
    """
    r1 = (np.asarray(e["1p"]) - np.asarray(e["1m"])) / (2 * step)
    r2 = (np.asarray(e["2p"]) - np.asarray(e["2m"])) / (2 * step)
    return np.stack([r1, r2], axis=-1)


def metacal_shapes(
    stamps: np.ndarray, psf: np.ndarray, noise_sigma: float, prior, *, config=None,
    size_prior=None, bulge_weights: np.ndarray | None = None, step: float = 0.01,
    noise_fields: np.ndarray | None = None, seed: int | None = None, fits=None,
    centres: tuple[np.ndarray, np.ndarray] | None = None,
    position_prior_sigma: float | None = 2.0, dilation: float | None = None,
    jacobian: np.ndarray | None = None, reconvolution: str = "dilate",
) -> Table:
    """lensfit's posterior mean ellipticity of each stamp with its metacalibrated response.

    The stamps are fitted (or ``fits`` given) for their galaxies' centres; the five
    metacalibration images are made about those centres and fitted
    (:func:`metacal_fits`); the posterior means under ``prior``
    (:func:`pylensfit.shear.posterior_moments`) of the unsheared image are the
    measurement, those of the sheared ones give the response (:func:`response`). The
    shear of a sample is then :func:`metacal_shear`.

    Parameters
    ----------
    stamps : numpy.ndarray
        ``(n, N, N)`` background-subtracted stamps, each galaxy near ``[N//2, N//2]``,
        large enough to hold the galaxies' light (module docstring).
    psf : numpy.ndarray
        ``(N, N)`` PSF image (pixel response included), centred on ``[N//2, N//2]``.
    noise_sigma : float or numpy.ndarray
        The stamps' per-pixel noise, > 0, one value or one per stamp (for noise-free
        stamps give ``noise_fields`` of zeros: the fits then assume ``sqrt(2)
        noise_sigma`` without any added).
    prior : pylensfit.prior.Prior
        The ellipticity prior of the posterior means.
    config : Config, optional
        The fit's configuration (:func:`pylensfit.likelihood.fit_stamps`).
    size_prior : pylensfit.prior.SizePrior, optional
        As :func:`pylensfit.likelihood.fit_stamps`.
    bulge_weights : numpy.ndarray, optional
        Prior probabilities of the bulge fractions (uniform if ``None``), with a
        bulge+disc model whose fraction is marginalised.
    step, noise_fields, seed, dilation, jacobian, reconvolution
        As :func:`metacal_images`.
    fits, centres : StampFits or tuple of numpy.ndarray, optional
        Fits of ``stamps`` already made, or the galaxies' fitted centres ``(x, y)``
        (stamp pixels, element ``[y, x]``); without either the stamps are fitted.
    position_prior_sigma : float or None
        As :func:`metacal_fits`.

    Returns
    -------
    astropy.table.Table
        One row per stamp: ``e1, e2`` (the unsheared image's posterior means), ``R11,
        R12, R21, R22`` (``R_ij = d<e_i>/dg_j``), ``s1, s2`` (lensfit's own exact
        sensitivities of the unsheared image, :func:`pylensfit.shear.shear_sensitivity`:
        the response if the galaxy were one of the models) and ``flag`` (0 when all six
        fits are usable; else the values are NaN).
    """
    _check_shapes_inputs(noise_sigma, position_prior_sigma)
    st = np.asarray(stamps, dtype=np.float32)
    st = st[None] if st.ndim == 2 else st
    kw = {"config": config, "size_prior": size_prior}
    cx, cy = _fitted_centres(st, psf, noise_sigma, kw, fits, centres)
    ok = np.isfinite(cx) & np.isfinite(cy)
    mf = metacal_fits(st, psf, noise_sigma, config=config, size_prior=size_prior, step=step,
                      noise_fields=noise_fields, seed=seed, centres=(cx, cy),
                      position_prior_sigma=position_prior_sigma, dilation=dilation,
                      jacobian=jacobian, reconvolution=reconvolution)  # fmt: skip
    refine = (config or Config()).output_refine
    e, sens = {}, None
    for t in METACAL_TYPES:
        e[t], good, sens_t = _posterior_means(mf[t], prior, bulge_weights, refine,
                                              t == "noshear")  # fmt: skip
        ok, sens = ok & good, sens_t if t == "noshear" else sens
    return _shapes_table(e, response(e, step), sens, ok, step)


def metacal_fits(
    stamps: np.ndarray, psf: np.ndarray, noise_sigma, *, config=None, size_prior=None,
    step: float = 0.01, noise_fields: np.ndarray | None = None, seed: int | None = None,
    centres: tuple[np.ndarray, np.ndarray], position_prior_sigma: float | None = 2.0,
    dilation: float | None = None, jacobian: np.ndarray | None = None,
    reconvolution: str = "dilate",
) -> dict:
    """The fits of the five metacalibration images of a set of stamps, about their centres.

    The images of :func:`metacal_images` about ``centres`` (a centre that is not finite:
    the stamp's centre), each fitted (:func:`pylensfit.likelihood.fit_stamps`) with the
    reconvolution PSF and the noise level of the images (``sqrt(2)`` times the input's)
    on the whole stamp, under the configuration with ``position_prior_sigma``.

    Parameters
    ----------
    stamps, psf, noise_sigma
        As :func:`metacal_images` (``noise_sigma > 0``).
    config, size_prior
        As :func:`pylensfit.likelihood.fit_stamps` (default ``Config()``).
    step, noise_fields, seed, dilation, jacobian, reconvolution
        As :func:`metacal_images`.
    centres : tuple of numpy.ndarray
        ``(x, y)`` per stamp (stamp pixels, element ``[y, x]``): the galaxies' fitted
        centres, about which the images are sheared.
    position_prior_sigma : float or None
        Width (px) of the position prior of the five fits (None: the configuration's).
        The images are sheared about the fitted centre, whose noise moves the galaxy
        against the prior's centre by ``delta`` times that noise: a narrow prior adds a
        response to that move, which is not the shear's; the default is the paper's wide
        2 px (``benchmarks/README.md``, precision_metacal).

    Returns
    -------
    dict of StampFits
        The fits per type of :data:`METACAL_TYPES`.
    """
    if position_prior_sigma is not None and not position_prior_sigma > 0:
        raise ValueError(f"position_prior_sigma must be > 0 or None, got {position_prior_sigma}")
    st = np.asarray(stamps, dtype=np.float32)
    st = st[None] if st.ndim == 2 else st
    n = st.shape[-1]
    cx, cy = (np.broadcast_to(np.asarray(c, float), st.shape[:1]) for c in centres)
    ok = np.isfinite(cx) & np.isfinite(cy)
    mc = metacal_images(st, psf, noise_sigma, step=step, noise_fields=noise_fields, seed=seed,
                        centres=(np.where(ok, cx, n // 2), np.where(ok, cy, n // 2)),
                        dilation=dilation, jacobian=jacobian,
                        reconvolution=reconvolution)  # fmt: skip
    cfg = config or Config()
    if position_prior_sigma is not None:
        cfg = cfg.replace(position_prior_sigma=float(position_prior_sigma))
    return {t: fit_stamps(mc.images[t], mc.psf, mc.noise_sigma, config=cfg,
                          size_prior=size_prior) for t in METACAL_TYPES}  # fmt: skip


def metacal_exposures(
    stamps: np.ndarray, psf: np.ndarray, noise_sigma, jacobian: np.ndarray, *,
    offsets: tuple[np.ndarray, np.ndarray] | None = None, centres=None, flux_scale=1.0,
    usable: np.ndarray | None = None, config=None, pixel_scale: float | None = None,
    size_prior=None, step: float = 0.01, noise_fields: np.ndarray | None = None,
    seed: int | None = None, position_prior_sigma: float | None = 2.0,
    dilation: float | None = None, reconvolution: str = "dilate",
) -> dict:
    """The joint fits of the metacalibration images of galaxies seen in several exposures.

    Each exposure's stamp of a galaxy is metacalibrated on its own (:func:`metacal_images`
    with that exposure's PSF, noise, added noise field and Jacobian): the shears
    ``+-delta`` are the sky's, whatever each exposure's rotation, flip or distortion,
    about the galaxy's fitted sky position seen in that exposure. The five images are
    then each fitted on all the exposures together
    (:func:`pylensfit.joint.fit_exposures`, each exposure with its reconvolution PSF and
    ``sqrt(2)`` times its noise), so that :func:`metacal_branches` of the result gives
    the sky-frame posterior means and their response ``R_ij = d<e_i>/dg_j`` to the sky's
    shear.

    Parameters
    ----------
    stamps, psf, noise_sigma, jacobian, flux_scale, usable, centres, pixel_scale
        As :func:`pylensfit.joint.fit_exposures` (``noise_sigma > 0``): ``(K, n, N, N)``
        stamps; one PSF, one per exposure or one per exposure and galaxy; ``J_k =
        d(x, y)/d(W, N)`` in pixels per arcsec; ``centres`` the catalogue positions, the
        centres of the position prior. The stamps should hold the galaxies' light (module
        docstring).
    offsets : tuple of numpy.ndarray, optional
        ``(x, y)`` each ``(n,)``: the galaxies' fitted sky offsets from the catalogue
        positions, arcsec (:attr:`pylensfit.joint.JointFits.x`, ``.y``), about which the
        images are sheared. Default: a joint fit of the stamps under ``config``.
    config, size_prior
        As :func:`pylensfit.joint.fit_exposures` (default ``Config()``).
    step, dilation, reconvolution
        As :func:`metacal_images`.
    noise_fields : numpy.ndarray, optional
        ``(K, n, N, N)`` the added noise fields, unit variance; drawn from ``seed`` if not
        given.
    seed : int, optional
        Seed of the added noise fields.
    position_prior_sigma : float or None
        Width of the five fits' position prior, reference pixels (None: the
        configuration's), as :func:`metacal_fits`.

    Returns
    -------
    dict of pylensfit.joint.JointFits
        The joint fits per type of :data:`METACAL_TYPES`.
    """
    st = np.asarray(stamps, dtype=float)
    st = st[None] if st.ndim == 3 else st
    K, n, N = st.shape[0], st.shape[1], st.shape[-1]
    J = np.asarray(jacobian, dtype=float).reshape(K, 2, 2)
    sig = _per_exposure(noise_sigma, K, n)
    use = np.ones((K, n), bool) if usable is None else np.array(
        np.broadcast_to(np.asarray(usable, dtype=bool), (K, n)))  # fmt: skip
    use &= np.isfinite(st).all(axis=(2, 3)) & np.isfinite(sig) & (sig > 0)
    st, sig = np.where(use[..., None, None], np.nan_to_num(st), 0.0), np.where(use, sig, 1.0)
    cfg = config or Config()
    kw = {"flux_scale": flux_scale, "usable": use, "centres": centres,
          "pixel_scale": pixel_scale, "size_prior": size_prior}
    if offsets is None:
        f = fit_exposures(st, psf, sig, J, config=cfg, **kw)
        offsets = (f.x, f.y)
    X = np.nan_to_num(np.column_stack([np.broadcast_to(np.asarray(o, float), (n,))
                                       for o in offsets]))  # fmt: skip
    cx, cy = ((np.full((K, n), float(N // 2)),) * 2 if centres is None
              else (_per_exposure(c, K, n) for c in centres))  # fmt: skip
    at = (cx + J[:, 0, 0, None] * X[:, 0] + J[:, 0, 1, None] * X[:, 1],
          cy + J[:, 1, 0, None] * X[:, 0] + J[:, 1, 1, None] * X[:, 1])
    fields = (np.random.default_rng(seed).standard_normal(st.shape) if noise_fields is None
              else np.asarray(noise_fields, dtype=float).reshape(st.shape))  # fmt: skip
    images, psf_r, sig_r = _exposure_images(st, psf, sig, J, at, fields, step=step,
                                            dilation=dilation, reconvolution=reconvolution)
    if position_prior_sigma is not None:
        cfg = cfg.replace(position_prior_sigma=float(position_prior_sigma))
    kw.update(flux_scale=_per_exposure(flux_scale, K, n), centres=(cx, cy))
    return _fit_branches(images, psf_r, sig_r, J, cfg, kw)


def _fit_branches(images: dict, psf_r: np.ndarray, sig_r: np.ndarray, J: np.ndarray,
                  cfg: Config, kw: dict) -> dict:  # fmt: skip
    """The five images of every galaxy in one :func:`fit_exposures` (each exposure's bank
    built once, the galaxies' fits independent of each other), split per type; ``kw``'s
    ``flux_scale``, ``usable`` and ``centres`` per exposure and galaxy."""
    T, n = len(METACAL_TYPES), sig_r.shape[1]
    tile = {"flux_scale": np.tile(kw["flux_scale"], T), "usable": np.tile(kw["usable"], T),
            "centres": tuple(np.tile(c, T) for c in kw["centres"])}
    f = fit_exposures(np.concatenate([images[t] for t in METACAL_TYPES], axis=1),
                      psf_r if psf_r.ndim == 3 else np.concatenate([psf_r] * T, axis=1),
                      np.tile(sig_r, T), J, config=cfg, **(kw | tile))  # fmt: skip
    return {t: f.take(slice(i * n, (i + 1) * n)) for i, t in enumerate(METACAL_TYPES)}


def _per_exposure(value, K: int, n: int) -> np.ndarray:
    """A scalar, ``(K,)`` or ``(K, n)`` value as ``(K, n)`` floats."""
    a = np.asarray(value, dtype=float)
    return np.array(np.broadcast_to(a[:, None] if a.ndim == 1 and a.size == K else a, (K, n)))


def _exposure_images(st, psf, sig, J, at, fields, **mc_kw):
    """Each exposure's metacalibration images ``{type: (K, n, N, N)}``, their
    reconvolution PSFs ``(K, N, N)`` (``(K, n, N, N)`` for a PSF per galaxy) and noise
    ``(K, n)``; one :func:`metacal_images` per exposure and PSF image."""
    K, n, N = st.shape[0], st.shape[1], st.shape[-1]
    p = np.asarray(psf, dtype=float)
    p = np.broadcast_to(p, (K, 1) + p.shape) if p.ndim == 2 else p
    p = p[:, None] if p.ndim == 3 else p
    if p.shape[1] > 1 and np.array_equal(p, np.broadcast_to(p[:, :1], p.shape)):
        p = p[:, :1]  # the same PSF for every galaxy of an exposure: one operation each
    images = {t: np.zeros(st.shape, np.float32) for t in METACAL_TYPES}
    psf_r, sig_r = np.zeros(p.shape[:2] + (N, N)), np.zeros((K, n))
    for k in range(K):
        for j in range(p.shape[1]):  # one PSF for the exposure, or one per galaxy
            g = np.arange(n) if p.shape[1] == 1 else np.array([j])
            mc = metacal_images(st[k, g], centre_on_stamp(p[k, j], N), sig[k, g],
                                noise_fields=fields[k, g], centres=(at[0][k, g], at[1][k, g]),
                                jacobian=J[k], **mc_kw)  # fmt: skip
            for t in METACAL_TYPES:
                images[t][k, g] = mc.images[t]
            psf_r[k, j], sig_r[k, g] = mc.psf, mc.noise_sigma
    return images, psf_r[:, 0] if p.shape[1] == 1 else psf_r, sig_r


@dataclass(frozen=True)
class MetacalBranches:
    """Each metacalibration image's posterior means and what a selection cuts on.

    Attributes
    ----------
    e : dict of numpy.ndarray
        ``(n, 2)`` posterior means per type of :data:`METACAL_TYPES` (NaN where the
        fit is not usable).
    snr : dict of numpy.ndarray
        ``(n,)`` the matched-filter S/N of each image's most likely model.
    usable : dict of numpy.ndarray
        ``(n,)`` bool: the fit is usable (a finite ``ln L`` row, no fit flag) and not a
        point source.
    step : float
        The images' shear ``delta``.
    """

    e: dict[str, np.ndarray]
    snr: dict[str, np.ndarray]
    usable: dict[str, np.ndarray]
    step: float

    @property
    def R(self) -> np.ndarray:
        """``(n, 2, 2)`` each galaxy's response (:func:`response`; NaN where a sheared
        image's fit is not usable)."""
        return response(self.e, self.step)


def metacal_branches(fits: dict, prior, *, bulge_weights: np.ndarray | None = None,
                     refine: int = 4, step: float = 0.01) -> MetacalBranches:  # fmt: skip
    """The posterior means, S/N and usability of the fits of :func:`metacal_fits`.

    Parameters
    ----------
    fits : dict of StampFits
        The fits per type of :data:`METACAL_TYPES`.
    prior : pylensfit.prior.Prior
        The ellipticity prior of the posterior means.
    bulge_weights : numpy.ndarray, optional
        As :func:`metacal_shapes`.
    refine : int
        The integrals' grid refinement (``Config.output_refine``).
    step : float
        The images' shear ``delta``.

    Returns
    -------
    MetacalBranches
    """
    e, snr, usable = {}, {}, {}
    for t in METACAL_TYPES:
        f = fits[t]
        mean, good, _ = _posterior_means(f, prior, bulge_weights, refine, False)
        e[t] = np.where(good[:, None], mean, np.nan)
        snr[t] = np.asarray(f.snr, dtype=float)
        usable[t] = good & ~np.asarray(f.is_star, dtype=bool)
    return MetacalBranches(e=e, snr=snr, usable=usable, step=float(step))


def _check_shapes_inputs(noise_sigma, position_prior_sigma) -> None:
    if not np.all(np.asarray(noise_sigma) > 0):
        raise ValueError(f"metacal_shapes needs noise_sigma > 0, got {noise_sigma}")
    if position_prior_sigma is not None and not position_prior_sigma > 0:
        raise ValueError(f"position_prior_sigma must be > 0 or None, got {position_prior_sigma}")


def _fitted_centres(st: np.ndarray, psf: np.ndarray, noise_sigma, kw: dict, fits,
                    centres) -> tuple[np.ndarray, np.ndarray]:
    """The galaxies' centres (stamp pixels): ``centres``, or those of ``fits``, or of a
    fit of the stamps (with ``kw``)."""
    if centres is not None:
        return tuple(np.broadcast_to(np.asarray(c, float), st.shape[:1]) for c in centres)
    if fits is None:
        fits = fit_stamps(st, psf, noise_sigma, **kw)
    return np.asarray(fits.x, float), np.asarray(fits.y, float)


def _posterior_means(f, prior, bulge_weights, refine: int, sensitivities: bool):
    """The posterior means ``(n, 2)`` of the fits ``f`` of a metacalibration image, its
    usable rows, and, with ``sensitivities``, lensfit's sensitivities ``(s1, s2)`` (else
    None)."""
    lnL = f.lnL
    if f.lnL_bulge is not None:
        lnL = mix_bulge_fractions(f.lnL_bulge, f.lnL_star, bulge_weights)
    good = usable_rows(lnL) & (np.asarray(f.flags) == 0)
    lnL = np.where(good[:, None], lnL, 0.0)
    mom = posterior_moments(lnL, f.egrid, prior, refine=refine)
    sens = (shear_sensitivity(lnL, f.egrid, prior, refine=refine) if sensitivities
            else None)  # fmt: skip
    return np.column_stack([mom["e1"], mom["e2"]]), good, sens


def _shapes_table(e: dict, R: np.ndarray, sens, ok: np.ndarray, step: float) -> Table:
    """:func:`metacal_shapes`' table (NaN on the rows not usable in every image)."""
    nan = np.where(ok, 1.0, np.nan)
    out = Table()
    out["e1"], out["e2"] = e["noshear"][:, 0] * nan, e["noshear"][:, 1] * nan
    for i in range(2):
        for j in range(2):
            out[f"R{i + 1}{j + 1}"] = R[:, i, j] * nan
    out["s1"], out["s2"] = sens[0] * nan, sens[1] * nan
    out["flag"] = np.where(ok, 0, 1).astype(np.int16)
    out.meta["METASTEP"] = float(step)
    return out


def metacal_shear(shapes: Table) -> tuple[np.ndarray, np.ndarray]:
    """The shear of a sample from :func:`metacal_shapes`: ``<R>^-1 <e>`` over its usable rows.

    Returns
    -------
    g : numpy.ndarray
        ``(2,)`` the shear estimate.
    R : numpy.ndarray
        ``(2, 2)`` the mean response.
    """
    ok = np.asarray(shapes["flag"]) == 0
    if not ok.any():
        raise ValueError("metacal_shear: no usable rows")
    e = np.column_stack([shapes["e1"], shapes["e2"]])[ok].mean(0)
    R = np.array([[shapes["R11"], shapes["R12"]], [shapes["R21"], shapes["R22"]]],
                 dtype=float)[:, :, ok].mean(-1)  # fmt: skip
    return np.linalg.solve(R, e), R
