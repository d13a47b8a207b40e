"""The PSF of an image from its stars: :func:`stack_psf` (paper section 2.4)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .._util import per_object
from .centring import Candidates, Centred, centre_on_gaussian, cut_stars, refine_pass
from .diagnostics import psf_diagnostics
from .fourier import gaussian_peak, pad_to, subpixel_shift
from .result import PSFResult
from .stars import StarChecks, check_star_inputs
from .transform import PSFError


class Stack(NamedTuple):
    """The final stack of :func:`stack_psf`: the unit-sum image, its pixel variance and
    its sum before the normalisation, and the shift ``(sx, sy)`` (``(1,)`` arrays, pixels)
    that put its Gaussian cross-correlation peak on the centre."""

    image: np.ndarray
    var: float
    total: float
    sx: np.ndarray
    sy: np.ndarray


def stack_psf(image: np.ndarray, x, y, *, noise_sigma, size: int = 32,
              weight: np.ndarray | None = None, n_iter: int = 2, min_correlation: float = 0.9,
              max_chi2: float | None = 2.0, model_error: float = 0.01, core_level: float = 0.01,
              max_shift: float = 2.0, min_snr: float = 10.0, centroid_sigma: float = 2.0,
              margin: int = 4, weighting: str = "inverse_variance", source: str = "image",
              ) -> PSFResult:  # fmt: skip
    """Estimate the PSF by stacking star images (paper section 2.4).

    The stars are cut out, centred on a round Gaussian by exact Fourier shifts and
    stacked; ``n_iter`` passes then re-centre each star on the stack, measure its flux,
    correlation and core chi-square against the stack without it and reject the
    outliers (the steps are those of :mod:`pylensfit.psf`). The result is the band-limited part of
    the pixel-convolved PSF, centred on ``[size//2, size//2]``, of unit sum.

    Parameters
    ----------
    image : numpy.ndarray
        2-D background-subtracted image indexed ``[y, x]``.
    x, y : array_like
        Catalogue positions of candidate stars in 0-based pixels (pixel centres at
        integers).
    noise_sigma : float or array_like
        Per-pixel noise standard deviation, scalar or one per star (image units).
    size : int
        Side of the PSF image in pixels.
    weight : numpy.ndarray, optional
        Weight map of the image's shape; a star whose cutout holds a pixel of weight
        ``<= 0`` (or non-finite) is rejected. Its values are not otherwise used.
    n_iter : int
        Number of re-centre / reject / re-stack passes (the paper's two stages).
    min_correlation, max_chi2, model_error, core_level, max_shift, min_snr, centroid_sigma, margin
        The tests of the stars and the centring, with the meanings (and defaults) of the
        attributes of :class:`~pylensfit.psf.StarChecks` (fractions, pixels).
    weighting : {"inverse_variance", "median"}
        ``"inverse_variance"``: the stack is the mean of the unit-flux stars weighted
        by ``flux^2 / sigma^2``, the inverse variance of their pixels (optimal for a
        common PSF in white noise; bright stars dominate). ``"median"``: the pixel-wise
        median of the unit-flux stars at every stage (robust, ~25% noisier, and
        ignores the S/N).
    source : str
        Label of the image (e.g. its file name), used in error messages and stored.

    Returns
    -------
    PSFResult
        The PSF image and the per-star diagnostics.

    Raises
    ------
    PSFError
        If no usable star remains.
    ValueError
        For inconsistent arguments.
    """
    image, x, y, weight = check_star_inputs(image, x, y, weight, size)
    if weighting not in ("inverse_variance", "median"):
        raise ValueError(f"weighting must be 'inverse_variance' or 'median', got {weighting!r}")
    if n_iter < 0:
        raise ValueError(f"n_iter must be >= 0, got {n_iter}")
    checks = StarChecks(min_correlation, max_chi2, model_error, core_level, max_shift, min_snr,
                        centroid_sigma, margin)  # fmt: skip
    sigma_all = per_object(noise_sigma, x.size, "noise_sigma")
    cand, stamps = cut_stars(image, weight, x, y, sigma_all, checks.cutout_side(size), source)
    cen = centre_on_gaussian(cand, stamps, x, y, size, checks)
    for it in range(n_iter):
        refine_pass(cand, cen, it == 0 or weighting == "median", checks)
    stack = final_stack(cand, cen, weighting, size, centroid_sigma, source)
    meta = {"n_iter": n_iter, "min_correlation": min_correlation, "max_chi2": max_chi2,
            "max_shift": max_shift, "min_snr": min_snr, "centroid_sigma": centroid_sigma,
            "weighting": weighting}  # fmt: skip
    return build_result(cand, cen, x, y, stack, meta)


def final_stack(cand: Candidates, cen: Centred, weighting: str, size: int,
                centroid_sigma: float, source: str) -> Stack:  # fmt: skip
    """The stack of the surviving stars, centred on its Gaussian cross-correlation peak
    and of unit sum (:class:`PSFError` if its sum is not positive)."""
    used = cand.used_now()
    if weighting == "median":
        psf, var = cen.median_stack(used)
    else:
        num, wts = cen.mean_parts(used)
        psf, var = num / wts.sum(), 1.0 / wts.sum()
    # put the Gaussian cross-correlation peak of the stack on [c, c]
    big = cen.D.shape[-2]
    Pbig = pad_to(psf[None], big)
    Dp = np.fft.rfft2(Pbig) * cen.phase[None]
    sx, sy, okp = gaussian_peak(Dp, centroid_sigma, np.zeros(1), np.zeros(1), 1.0)
    if not okp[0]:
        sx, sy = np.zeros(1), np.zeros(1)
    psf = subpixel_shift(np.fft.rfft2(Pbig), sx, sy, big, size)[0]
    total = psf.sum()
    if not total > 0:
        raise PSFError(f"{source}: the stack of {used.sum()} stars has non-positive flux")
    return Stack(psf / total, var, total, sx, sy)


def build_result(cand: Candidates, cen: Centred, x: np.ndarray, y: np.ndarray, stack: Stack,
                 meta: dict) -> PSFResult:  # fmt: skip
    """The :class:`PSFResult` of :func:`stack_psf`: measured centres, reasons, noise and
    the size and shape diagnostics of the stack."""
    idx, rec = cand.idx, cand.record
    rec.x[idx] = cand.ix[idx] + cen.X + stack.sx[0]
    rec.y[idx] = cand.iy[idx] + cen.Y + stack.sy[0]
    reason = cand.reason
    reason_arr = np.array([str(r) for r in reason], dtype=str) if cand.n else np.array([], str)
    return PSFResult(
        image=stack.image,
        x_cat=x.copy(),
        y_cat=y.copy(),
        x=rec.x,
        y=rec.y,
        flux=rec.flux,
        snr=rec.snr,
        correlation=rec.correlation,
        chi2=rec.chi2,
        used=reason_arr == "",
        reason=reason_arr,
        pixel_noise=float(np.sqrt(stack.var) / stack.total),
        source=cand.source,
        meta=meta,
        **psf_diagnostics(stack.image),
    )
