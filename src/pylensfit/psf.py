"""The PSF: from a pixelised image to the transform used by the likelihood engine.

The PSF image includes the pixel response (it is a star image), so the observed
model is ``M_k = G_k P_k`` on the stamp's DFT frequencies with no extra pixel factor.
This assumes that the PSF band-limits the data at the pixel Nyquist frequency
(paper section 2.4); aliasing of modes above Nyquist is not modelled.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.table import Table

from ._util import atomic_write, newton_peak, per_object, rfft_frequencies

__all__ = [
    "REASONS",
    "PSFError",
    "PSFResult",
    "centre_on_stamp",
    "check_star_inputs",
    "combine_psfs",
    "psf_diagnostics",
    "psf_from_image",
    "psf_transform",
    "read_psf",
    "stack_psf",
]


class PSFError(ValueError):
    """A PSF image that cannot be used."""


def centre_on_stamp(image: np.ndarray, n: int) -> np.ndarray:
    """Crop or zero-pad ``image`` to ``n x n``, moving element ``[s//2, s//2]`` to the centre."""
    image = np.asarray(image, dtype=float)
    out = np.zeros((n, n))
    src = []
    dst = []
    for size in image.shape:
        lo = size // 2 - n // 2  # source index that lands on destination 0
        s0, s1 = max(lo, 0), min(lo + n, size)
        src.append(slice(s0, s1))
        dst.append(slice(s0 - lo, s1 - lo))
    out[dst[0], dst[1]] = image[src[0], src[1]]
    return out


def psf_transform(psf: np.ndarray, n: int) -> np.ndarray:
    """DFT of a PSF image on an ``n x n`` stamp, phase-referenced to its centre.

    Parameters
    ----------
    psf : numpy.ndarray
        2-D PSF image of any size and normalisation, centred on element
        ``[s//2, s//2]``, including the pixel response.
    n : int
        Stamp side in pixels.

    Returns
    -------
    numpy.ndarray
        Complex ``(n, n // 2 + 1)`` array ``P_k`` normalised to ``P_0 = 1``.

    Raises
    ------
    PSFError
        If the image is not 2-D, has non-finite values or a non-positive sum.
    """
    psf = np.asarray(psf, dtype=float)
    if psf.ndim != 2:
        raise PSFError(f"PSF image must be 2-D, got shape {psf.shape}")
    if not np.all(np.isfinite(psf)):
        raise PSFError("PSF image has non-finite pixels")
    img = centre_on_stamp(psf, n)
    total = img.sum()
    if not total > 0:
        raise PSFError(f"PSF image has non-positive total flux ({total:g}) within {n}x{n}")
    kx, ky, _ = rfft_frequencies(n)
    c = n // 2
    return np.fft.rfft2(img / total) * np.exp(1j * (kx * c + ky * c))


# ---------------------------------------------------------------------------
# PSF estimation from star images (paper section 2.4)
# ---------------------------------------------------------------------------

#: Rejection reasons written in :attr:`PSFResult.reason` (``''`` for a used star).
REASONS = {
    "position": "non-finite catalogue position",
    "edge": "cutout leaves the image",
    "nonfinite": "non-finite pixels in the cutout",
    "weight": "zero-weight pixels in the cutout",
    "noise": "bad noise_sigma",
    "snr": "signal-to-noise below min_snr",
    "peak": "no centroid peak",
    "shift": "centroid more than max_shift from the catalogue position",
    "flux": "non-positive flux",
    "correlation": "low correlation with the stack",
    "chi2": "poor fit to the stack (chi2)",
}

_STAR_COLUMNS = ("x_cat", "y_cat", "x", "y", "flux", "snr", "correlation", "chi2", "used",
                 "reason")  # fmt: skip


@dataclass
class PSFResult:
    """A PSF estimated by stacking stars, with per-star and summary diagnostics.

    Attributes
    ----------
    image : numpy.ndarray
        ``(size, size)`` float64 PSF image including the pixel response, sum 1, centred
        on element ``[size//2, size//2]`` (the peak of its cross-correlation with a round
        Gaussian of ``centroid_sigma``).
    x_cat, y_cat : numpy.ndarray
        Catalogue positions of the candidate stars (0-based image pixels).
    x, y : numpy.ndarray
        Measured centres (0-based image pixels, the stack's centre definition); NaN where
        no cutout could be made.
    flux : numpy.ndarray
        PSF-weighted flux ``<s, P> / <P, P>`` within the ``size x size`` window, in image
        units (``P`` the stack without the star itself, unit sum).
    snr : numpy.ndarray
        Matched-filter signal-to-noise ``<s, P> / (sigma |P|)`` (with the centroiding
        Gaussian for ``P`` if the star never reached the comparison with a stack).
    correlation : numpy.ndarray
        Noise-debiased normalised cross-correlation with the stack without the star, at
        the best shift (about 1 for a star; can exceed 1 by the noise).
    chi2 : numpy.ndarray
        Reduced chi-square of ``s - flux P`` in the PSF core (see :func:`stack_psf`).
        ``flux``, ``correlation`` and ``chi2`` are NaN for stars never compared with a
        stack.
    used : numpy.ndarray
        Boolean, the star is in the final stack.
    reason : numpy.ndarray
        ``''`` for a used star, else why it was rejected (a value of :data:`REASONS`).
        The diagnostics of a rejected star are those of the check that rejected it.
    fwhm : float
        Effective FWHM in pixels, ``2 sqrt(A / pi)`` with ``A`` the area above half the
        peak of the Fourier-interpolated image (the geometric mean of the major and
        minor FWHM for an elliptical PSF).
    sigma : float
        Adaptive (Gaussian-weighted) second-moment size ``det(M)^(1/4)`` in pixels.
    e1, e2 : float
        Adaptive-moment ellipticity, ``|e| = (a - b) / (a + b)``, ``e1 > 0`` along x
        (GalSim's ``observed_shape``); NaN if the moments failed.
    pixel_noise : float
        Standard deviation of each pixel of ``image`` due to the noise of the stars
        (``1 / sqrt(sum flux^2 / sigma^2)``; for the median stack, the equal-weight
        large-sample value, an overestimate for stars of unequal S/N).
    source : str
        Label of where the stars came from (e.g. a file name).
    meta : dict
        Settings of the run.
    """

    image: np.ndarray
    x_cat: np.ndarray
    y_cat: np.ndarray
    x: np.ndarray
    y: np.ndarray
    flux: np.ndarray
    snr: np.ndarray
    correlation: np.ndarray
    chi2: np.ndarray
    used: np.ndarray
    reason: np.ndarray
    fwhm: float = np.nan
    sigma: float = np.nan
    e1: float = np.nan
    e2: float = np.nan
    pixel_noise: float = np.nan
    source: str = ""
    meta: dict = field(default_factory=dict)

    @property
    def n_used(self) -> int:
        """Number of stars in the stack."""
        return int(np.count_nonzero(self.used))

    @property
    def n_rejected(self) -> int:
        """Number of candidate stars rejected."""
        return int(self.used.size - self.n_used)

    @property
    def size(self) -> int:
        """Side of the PSF image in pixels."""
        return int(self.image.shape[0])

    @property
    def digest(self) -> str:
        """SHA-1 hex digest of the image's bytes (C order): what a kept result was fitted
        with, for the resume keys of :func:`pylensfit.measure` and
        :func:`pylensfit_validation.validation.validate`."""
        return hashlib.sha1(np.ascontiguousarray(self.image).tobytes()).hexdigest()

    def stars(self):
        """The per-star diagnostics as an :class:`astropy.table.Table`."""
        cols = {name: getattr(self, name) for name in _STAR_COLUMNS}
        cols["reason"] = np.asarray(self.reason, dtype=str)
        return Table(cols)

    def write(self, path: str | Path, overwrite: bool = False) -> None:
        """Write as FITS, atomically.

        The primary HDU holds the PSF image, with header keywords ``N_USED``, ``N_REJ``,
        ``FWHM``, ``SIGMA``, ``E1``, ``E2``, ``PIXNOISE`` (NaN values are left out) and
        ``SOURCE``; the ``STARS`` binary table holds the per-star diagnostics.
        """
        prim = fits.PrimaryHDU(np.asarray(self.image, dtype=np.float64))
        hdr = prim.header
        hdr["N_USED"] = (self.n_used, "stars in the stack")
        hdr["N_REJ"] = (self.n_rejected, "candidate stars rejected")
        for key, value, comment in (
            ("FWHM", self.fwhm, "effective FWHM [pixel]"),
            ("SIGMA", self.sigma, "adaptive-moment size [pixel]"),
            ("E1", self.e1, "adaptive-moment e1, (a-b)/(a+b)"),
            ("E2", self.e2, "adaptive-moment e2, (a-b)/(a+b)"),
            ("PIXNOISE", self.pixel_noise, "noise rms of a PSF pixel"),
        ):
            if np.isfinite(value):
                hdr[key] = (float(value), comment)
        src = str(self.source)  # a long path keeps its card's room (CONTINUE cards)
        hdr["SOURCE"] = (src, "origin of the stars") if len(src) < 45 else src
        tab = fits.table_to_hdu(self.stars())
        tab.name = "STARS"
        atomic_write(fits.HDUList([prim, tab]), path, overwrite=overwrite)

    @classmethod
    def read(cls, path: str | Path) -> PSFResult:
        """Read a file written by :meth:`write`."""
        with fits.open(path) as hdul:
            image = np.array(hdul[0].data, dtype=np.float64)
            hdr = hdul[0].header
            t = Table(hdul["STARS"].data)
        kw = {name: np.asarray(t[name], dtype=float) for name in _STAR_COLUMNS[:-2]}
        return cls(
            image=image,
            used=np.asarray(t["used"], dtype=bool),
            reason=np.array([str(r).strip() for r in t["reason"]], dtype=str),
            fwhm=float(hdr.get("FWHM", np.nan)),
            sigma=float(hdr.get("SIGMA", np.nan)),
            e1=float(hdr.get("E1", np.nan)),
            e2=float(hdr.get("E2", np.nan)),
            pixel_noise=float(hdr.get("PIXNOISE", np.nan)),
            source=str(hdr.get("SOURCE", "")),
            **kw,
        )


def psf_from_image(image, source: str = "") -> PSFResult:
    """A PSF given as an image (a PSF model from elsewhere, or the true PSF of a simulation).

    Parameters
    ----------
    image : array_like
        2-D PSF image including the pixel response, centred on element ``[s//2, s//2]``
        (its centre defines the fitted galaxy positions; an offset PSF shifts them, not
        the shapes). Any normalisation: it is scaled to unit sum.
    source : str
        Where it came from (kept in :attr:`PSFResult.source`).

    Returns
    -------
    PSFResult
        The image (float64, unit sum) with its summary diagnostics (FWHM, adaptive
        moments) and no stars.

    Raises
    ------
    PSFError
        If the image is not 2-D, has non-finite pixels or a non-positive sum.
    """
    img = np.array(image, dtype=np.float64)
    where = f"{source}: " if source else ""
    if img.ndim != 2 or min(img.shape) < 3:
        raise PSFError(f"{where}a PSF image must be 2-D (at least 3 x 3), got shape {img.shape}")
    if not np.all(np.isfinite(img)):
        raise PSFError(f"{where}the PSF image has {int(np.sum(~np.isfinite(img)))} "
                       "non-finite pixel(s)")  # fmt: skip
    total = float(img.sum())
    if not total > 0:
        raise PSFError(f"{where}the PSF image has a non-positive sum ({total:g})")
    img /= total
    empty = np.zeros(0)
    return PSFResult(image=img, x_cat=empty, y_cat=empty, x=empty, y=empty, flux=empty,
                     snr=empty, correlation=empty, chi2=empty, used=np.zeros(0, bool),
                     reason=np.zeros(0, dtype=str), source=source,
                     **psf_diagnostics(img))  # fmt: skip


def read_psf(path: str | Path) -> PSFResult:
    """Read a PSF image from FITS.

    A file written by :meth:`PSFResult.write` (e.g. the pipeline's ``psf_dir``) is read
    whole; any other FITS file gives its first HDU holding a 2-D image, taken as in
    :func:`psf_from_image`.

    Raises
    ------
    PSFError
        If the file cannot be read or holds no usable 2-D image (the message names it).
    """
    path = Path(path)
    try:
        with fits.open(path) as hdul:
            if "STARS" in hdul:
                return PSFResult.read(path)
            data = next((h.data for h in hdul if getattr(h, "is_image", False)
                         and h.data is not None and h.data.ndim == 2), None)  # fmt: skip
            data = None if data is None else np.array(data, dtype=np.float64)
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise PSFError(f"{path}: not a readable PSF file ({err})") from None
    if data is None:
        raise PSFError(f"{path}: no 2-D image HDU to read the PSF from")
    return psf_from_image(data, source=str(path))


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


def adaptive_moments(image: np.ndarray) -> tuple[float, float, float]:
    """``(sigma, e1, e2)`` from GalSim's adaptive moments; NaN if they fail."""
    import galsim  # galsim: heavy import, only for the adaptive moments

    c = image.shape[0] // 2
    try:
        m = galsim.hsm.FindAdaptiveMom(
            galsim.Image(np.ascontiguousarray(image, dtype=np.float64), scale=1.0),
            guess_centroid=galsim.PositionD(c + 1.0, c + 1.0),
            strict=True,
        )
    except galsim.GalSimError:
        return np.nan, np.nan, np.nan
    shape = m.observed_shape
    return float(m.moments_sigma), float(shape.g1), float(shape.g2)


def _effective_fwhm(image: np.ndarray, oversample: int = 8) -> float:
    """``2 sqrt(A / pi)``, ``A`` the area above half maximum of the band-limited image."""
    from scipy.signal import resample  # scipy.signal: start-up cost (~0.5 s), only for the FWHM

    n = image.shape[0]
    fine = resample(resample(image, n * oversample, axis=0), n * oversample, axis=1)
    peak = fine.max()
    if not peak > 0:
        return np.nan
    area = np.count_nonzero(fine >= 0.5 * peak) / oversample**2
    return float(2.0 * np.sqrt(area / np.pi))


def psf_diagnostics(image: np.ndarray) -> dict[str, float]:
    """Size and shape of a PSF image, as :class:`PSFResult` records them.

    Parameters
    ----------
    image : numpy.ndarray
        Square PSF image (pixel response included), centred on element
        ``[n//2, n//2]``.

    Returns
    -------
    dict
        ``fwhm``: ``2 sqrt(A / pi)`` with ``A`` the area above half maximum of the
        band-limited image (pixels); ``sigma``, ``e1``, ``e2``: GalSim's adaptive
        moments (size in pixels; ellipticity ``(a - b) / (a + b)``), NaN if they fail.
    """
    sigma, e1, e2 = adaptive_moments(image)
    return {"fwhm": _effective_fwhm(image), "sigma": sigma, "e1": e1, "e2": e2}


def star_cutouts(image, weight, x, y, big):
    """``big x big`` cutouts about the nearest pixel of each position, and reasons."""
    ny, nx = image.shape
    n = x.size
    reason = np.full(n, "", dtype=object)
    finite = np.isfinite(x) & np.isfinite(y)
    reason[~finite] = REASONS["position"]
    ix = np.where(finite, np.rint(np.where(finite, x, 0.0)), 0).astype(np.int64)
    iy = np.where(finite, np.rint(np.where(finite, y, 0.0)), 0).astype(np.int64)
    lx = ix - big // 2
    ly = iy - big // 2
    inside = finite & (lx >= 0) & (ly >= 0) & (lx + big <= nx) & (ly + big <= ny)
    reason[finite & ~inside] = REASONS["edge"]
    idx = np.flatnonzero(inside)
    ar = np.arange(big)
    rows = (ly[idx, None] + ar)[:, :, None]
    cols = (lx[idx, None] + ar)[:, None, :]
    stamps = image[rows, cols]
    bad = ~np.isfinite(stamps).all(axis=(1, 2))
    reason[idx[bad]] = REASONS["nonfinite"]
    if weight is not None:
        wst = weight[rows, cols]
        zero = ~(wst > 0).all(axis=(1, 2)) & ~bad
        reason[idx[zero]] = REASONS["weight"]
    return stamps, idx, ix, iy, reason


def check_star_inputs(image, x, y, weight, size: int):
    """An image, star positions and weight map as float arrays, checked (``ValueError``:
    an image not 2-D, positions of unequal length, a weight map of another shape, a
    PSF side under 4)."""
    image = np.asarray(image, dtype=float)
    if image.ndim != 2:
        raise ValueError(f"image must be 2-D, got shape {image.shape}")
    x = np.atleast_1d(np.asarray(x, dtype=float))
    y = np.atleast_1d(np.asarray(y, dtype=float))
    if x.ndim != 1 or x.shape != y.shape:
        raise ValueError(f"x and y must be 1-D of equal length, got {x.shape} and {y.shape}")
    if weight is not None:
        weight = np.asarray(weight, dtype=float)
        if weight.shape != image.shape:
            raise ValueError(f"weight shape {weight.shape} differs from image {image.shape}")
    if size < 4:
        raise ValueError(f"size must be at least 4, got {size}")
    return image, x, y, weight


def stack_psf(
    image: np.ndarray,
    x,
    y,
    *,
    noise_sigma,
    size: int = 32,
    weight: np.ndarray | None = None,
    n_iter: int = 2,
    min_correlation: float = 0.9,
    max_chi2: float | None = 2.0,
    model_error: float = 0.01,
    core_level: float = 0.01,
    max_shift: float = 2.0,
    min_snr: float = 10.0,
    centroid_sigma: float = 2.0,
    margin: int = 4,
    weighting: str = "inverse_variance",
    source: str = "image",
) -> PSFResult:
    """Estimate the PSF by stacking star images (paper section 2.4).

    1. A ``(size + 2 margin + 1)``-square cutout is taken about the nearest pixel of each
       catalogue position (odd, so that the Fourier shift has no ambiguous Nyquist
       mode; the margin takes the periodic wrap-around of the shift). Stars whose cutout
       leaves the image or holds non-finite or zero-weight pixels are rejected.
    2. Each star is centred on the peak of its cross-correlation with a round Gaussian
       of ``centroid_sigma`` (the paper's "cross-correlation with a delta function",
       smoothed against noise) and moved there by an exact Fourier shift, i.e. the
       band-limited (sinc) interpolation that the paper performs on a 50x finer grid.
       Its amplitude is the Gaussian-weighted flux; stars below ``min_snr`` are dropped.
       The first stack is the pixel-wise median of the unit-flux stars (robust to a
       minority of contaminants).
    3. ``n_iter`` times: each remaining star is re-centred on the maximum of its
       cross-correlation with the stack ``P`` (Newton steps on the Fourier series, so
       to a small fraction of a pixel), its flux is re-measured as ``<s, P> / <P, P>``
       (unbiased for ``s = f P + noise``; its noise error correlates with the star's
       noise only along ``P``, so it changes the stack's normalisation, not its
       shape), and it is rejected if its normalised cross-correlation is below
       ``min_correlation`` or its reduced chi-square in the PSF core exceeds
       ``max_chi2``. The first pass compares with the median stack; later passes with
       the weighted stack of the other survivors (leave-one-out, so that a star's own
       noise cannot vouch for it). The stack is then remade from the survivors.
    4. The final stack is shifted so that its Gaussian cross-correlation peaks on
       ``[size//2, size//2]`` and normalised to unit sum in the window.

    The result estimates the band-limited part (``|k| < pi``) of the pixel-convolved
    PSF: power above the pixel Nyquist frequency aliases with a phase that depends on
    each star's sub-pixel position and averages away. For a Moffat of 3-pixel FWHM this
    differs from the pixel-sampled PSF by 1.3e-3 of its peak (paper section 2.4).

    Parameters
    ----------
    image : numpy.ndarray
        2-D background-subtracted image indexed ``[y, x]``.
    x, y : array_like
        Catalogue positions of candidate stars in 0-based pixels (pixel centres at
        integers).
    noise_sigma : float or array_like
        Per-pixel noise standard deviation, scalar or one per star.
    size : int
        Side of the PSF image in pixels.
    weight : numpy.ndarray, optional
        Weight map of the image's shape; a star whose cutout holds a pixel of weight
        ``<= 0`` (or non-finite) is rejected. Its values are not otherwise used.
    n_iter : int
        Number of re-centre / reject / re-stack passes (the paper's two stages).
    min_correlation : float
        Threshold on the noise-debiased normalised cross-correlation
        ``<s, P> / sqrt((|s|^2 - N sigma^2) (|P|^2 - N var P))`` over the
        ``N = size^2`` pixels. For isolated stars it scatters about 1 by 0.04, 0.005
        and 0.001 at peak S/N 10, 30 and 60 (GalSim Moffat fields), so 0.9 loses about
        0.1% of stars at peak S/N 10 and none above; it rejects blends of two
        comparable stars and galaxies more extended than the PSF, whatever their S/N.
    max_chi2 : float or None
        Threshold on the reduced chi-square of ``s - flux P`` over the core pixels
        (where the stack exceeds ``core_level`` of its peak, ~90 pixels for a 3-pixel
        FWHM), with per-pixel variance ``sigma^2 + flux^2 var P + (model_error flux
        P)^2``. For stars it is 1 +- 0.15, so 2 is a ~6-sigma cut; it catches
        contaminants bright enough to bias the stack but too compact for the
        correlation test (small galaxies, close binaries, cosmic rays). ``None``
        disables it.
    model_error : float
        Fractional per-pixel error allowed to the stack in the chi-square (PSF
        variation across the field, aliasing), so that very bright stars are not
        rejected for the stack's own imperfections.
    core_level : float
        Fraction of the stack's peak that delimits the core of the chi-square test.
    max_shift : float
        Largest distance in pixels between the catalogue position and the measured
        centre.
    min_snr : float
        Smallest Gaussian matched-filter signal-to-noise of a star.
    centroid_sigma : float
        Width in pixels of the Gaussian whose cross-correlation defines the centre of
        the stars and of the final PSF (about the PSF's own sigma is best).
    margin : int
        Extra pixels on each side of the cutouts (at least ``max_shift + 1``).
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
    image, x, y, weight = _check_stack_args(
        image, x, y, weight, size, weighting, centroid_sigma, max_shift, margin, n_iter
    )
    sigma_all = per_object(noise_sigma, x.size, "noise_sigma")
    big = size + 2 * margin + 1
    cand, stamps = _cut_stars(image, weight, x, y, sigma_all, big, source)
    cen = _centre_on_gaussian(cand, stamps, x, y, big, size, centroid_sigma, max_shift, min_snr)
    for it in range(n_iter):
        _refine_pass(cand, cen, it == 0 or weighting == "median", size, big,
                     min_correlation, max_chi2, model_error, core_level, max_shift)  # fmt: skip
    psf, var, total, sx, sy = _final_stack(cand, cen, weighting, size, big, centroid_sigma, source)
    meta = {
        "n_iter": n_iter,
        "min_correlation": min_correlation,
        "max_chi2": max_chi2,
        "max_shift": max_shift,
        "min_snr": min_snr,
        "centroid_sigma": centroid_sigma,
        "weighting": weighting,
    }
    return _build_result(cand, cen, x, y, psf, var, total, sx, sy, source, meta)


def _check_stack_args(
    image: np.ndarray,
    x,
    y,
    weight: np.ndarray | None,
    size: int,
    weighting: str,
    centroid_sigma: float,
    max_shift: float,
    margin: int,
    n_iter: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """The checked float image, positions and weight map of :func:`stack_psf`
    (``ValueError`` for inconsistent arguments)."""
    image, x, y, weight = check_star_inputs(image, x, y, weight, size)
    if weighting not in ("inverse_variance", "median"):
        raise ValueError(f"weighting must be 'inverse_variance' or 'median', got {weighting!r}")
    if not (centroid_sigma > 0 and max_shift > 0 and margin >= 0 and n_iter >= 0):
        raise ValueError("centroid_sigma and max_shift must be positive, margin and n_iter >= 0")
    return image, x, y, weight


@dataclass
class _StarRecord:
    """Per-candidate diagnostics of :func:`stack_psf` (NaN until measured), ``(n,)`` each."""

    x: np.ndarray
    y: np.ndarray
    flux: np.ndarray
    snr: np.ndarray
    correlation: np.ndarray
    chi2: np.ndarray

    @classmethod
    def empty(cls, n: int) -> _StarRecord:
        """All-NaN diagnostics for ``n`` candidates."""
        return cls(*(np.full(n, np.nan) for _ in range(6)))


@dataclass
class _Candidates:
    """The candidate stars of :func:`stack_psf`: why each is rejected, and which have cutouts.

    ``reason`` has one entry per candidate (``''`` while in play); ``idx`` indexes the
    ``m`` candidates with a usable cutout, which all the ``(m,)`` arrays follow.
    """

    n: int
    source: str
    reason: np.ndarray
    idx: np.ndarray
    ix: np.ndarray
    iy: np.ndarray
    sig: np.ndarray
    record: _StarRecord

    @property
    def m(self) -> int:
        """Number of candidates with a usable cutout."""
        return int(self.idx.size)

    def reject(self, mask: np.ndarray, why: str) -> None:
        """Reject the cutout stars of ``mask`` (``(m,)``) still in play, for ``why``."""
        self.reason[self.idx[mask & (self.reason[self.idx] == "")]] = why

    def used_now(self) -> np.ndarray:
        """``(m,)`` boolean, the cutout stars still in play."""
        return self.reason[self.idx] == ""

    def error(self) -> PSFError:
        """The error for no usable star, with the counts of the rejection reasons."""
        reason = self.reason
        counts = {r: int(np.count_nonzero(reason == r)) for r in set(reason.tolist()) if r}
        detail = ", ".join(f"{k}: {v}" for k, v in sorted(counts.items()))
        return PSFError(
            f"{self.source}: no usable PSF star among {self.n} candidates ({detail or 'none'})"
        )


@dataclass
class _Centred:
    """The cutout stars' Fourier transforms, centres and unit-flux images (``(m, ...)``)."""

    phase: np.ndarray
    F0: np.ndarray
    D: np.ndarray
    x0: np.ndarray
    y0: np.ndarray
    X: np.ndarray
    Y: np.ndarray
    unit: np.ndarray
    var_unit: np.ndarray

    def median_stack(self, use: np.ndarray) -> tuple[np.ndarray, float]:
        """Pixel-wise median of the unit-flux stars of ``use`` and its per-pixel variance."""
        med = np.median(self.unit[use], axis=0)
        var = 0.5 * np.pi * self.var_unit[use].mean() / use.sum()
        return med, var

    def mean_parts(self, use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Inverse-variance weighted sum of the unit-flux stars of ``use``, and the weights."""
        wts = np.where(use, 1.0 / self.var_unit, 0.0)
        return np.einsum("i,ijk->jk", wts, self.unit), wts


@dataclass
class _Check:
    """One comparison of the cutout stars with their reference stacks (``(m,)`` each)."""

    X: np.ndarray
    Y: np.ndarray
    stars: np.ndarray
    sp: np.ndarray
    pp: np.ndarray
    flux: np.ndarray
    correlation: np.ndarray
    chi2: np.ndarray


def _cut_stars(
    image: np.ndarray,
    weight: np.ndarray | None,
    x: np.ndarray,
    y: np.ndarray,
    sigma_all: np.ndarray,
    big: int,
    source: str,
) -> tuple[_Candidates, np.ndarray]:
    """Cut the candidates out and reject those without a usable cutout or noise level.

    Returns the candidates and the ``(m, big, big)`` cutouts; raises :class:`PSFError`
    if none is usable.
    """
    n = x.size
    stamps, idx, ix, iy, reason = star_cutouts(image, weight, x, y, big)
    bad_sig = ~(np.isfinite(sigma_all) & (sigma_all > 0))
    reason[(reason == "") & bad_sig] = REASONS["noise"]
    keep = reason[idx] == ""
    stamps, idx = stamps[keep], idx[keep]
    cand = _Candidates(
        n=n, source=source, reason=reason, idx=idx, ix=ix, iy=iy, sig=sigma_all[idx],
        record=_StarRecord.empty(n),
    )  # fmt: skip
    if cand.m == 0:
        raise cand.error()
    return cand, stamps


def _centre_on_gaussian(
    cand: _Candidates,
    stamps: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    big: int,
    size: int,
    centroid_sigma: float,
    max_shift: float,
    min_snr: float,
) -> _Centred:
    """Stage 1: centre on the Gaussian cross-correlation peak, Gaussian-weighted flux.

    Rejects stars without a peak, too far from the catalogue, below ``min_snr`` or of
    non-positive flux; raises :class:`PSFError` if none remains.
    """
    idx = cand.idx
    kx, ky, _ = rfft_frequencies(big)
    phase = np.exp(1j * (kx * (big // 2) + ky * (big // 2)))
    F0 = np.fft.rfft2(stamps)
    D = F0 * phase[None]
    x0 = x[idx] - cand.ix[idx]
    y0 = y[idx] - cand.iy[idx]
    X, Y, ok = gaussian_peak(D, centroid_sigma, x0, y0, max(max_shift, 1.0))
    cand.reject(~ok, REASONS["peak"])
    cand.reject(np.hypot(X - x0, Y - y0) > max_shift, REASONS["shift"])
    stars = subpixel_shift(F0, X, Y, big, size)
    G = gaussian_image(size, centroid_sigma)
    amp = np.einsum("ijk,jk->i", stars, G) / np.sum(G * G)
    snr = amp * np.sqrt(np.sum(G * G)) / cand.sig
    cand.record.snr[idx] = snr  # replaced by the PSF-matched S/N at each check
    cand.reject(~(snr >= min_snr), REASONS["snr"])
    cand.reject(~(amp > 0), REASONS["flux"])
    if not cand.used_now().any():
        raise cand.error()
    safe_amp = np.where(amp > 0, amp, 1.0)
    unit = stars / safe_amp[:, None, None]
    var_unit = (cand.sig / safe_amp) ** 2  # per-pixel variance of each unit-flux star
    return _Centred(phase=phase, F0=F0, D=D, x0=x0, y0=y0, X=X, Y=Y, unit=unit,
                    var_unit=var_unit)  # fmt: skip


def _reference_stacks(
    cen: _Centred, used: np.ndarray, median: bool, m: int, size: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each star's unit-sum reference: the median stack, or the leave-one-out weighted
    stack of the other ``used`` stars. Returns ``refs``, their per-pixel variance and
    the common stack (which delimits the chi-square core)."""
    if median:
        med, var = cen.median_stack(used)
        refs = np.broadcast_to(med, (m, size, size))
        var_ref = np.full(m, var)
        common = med
    else:
        num, wts = cen.mean_parts(used)
        W = wts.sum()
        w_loo = W - wts
        alone = ~(w_loo > 0)
        w_loo = np.where(alone, W, w_loo)
        refs = (num[None] - np.where(alone, 0.0, wts)[:, None, None] * cen.unit) / w_loo[
            :, None, None
        ]
        var_ref = 1.0 / w_loo
        common = num / W
    tot = refs.sum(axis=(1, 2))
    refs = refs / tot[:, None, None]
    var_ref = var_ref / tot**2
    return refs, var_ref, common


def _compare_with_stack(
    cen: _Centred,
    sig: np.ndarray,
    refs: np.ndarray,
    var_ref: np.ndarray,
    common: np.ndarray,
    size: int,
    big: int,
    model_error: float,
    core_level: float,
) -> _Check:
    """Re-centre each star on its cross-correlation with its reference; measure its flux,
    noise-debiased correlation and core chi-square against it."""
    npix = size * size
    # re-centre each star on its cross-correlation with the reference
    R = np.fft.rfft2(pad_to(refs, big)) * cen.phase[None]
    Xn, Yn, okn = newton_peak(cen.D, R, cen.X, cen.Y)
    Xn = np.where(okn, Xn, cen.X)
    Yn = np.where(okn, Yn, cen.Y)
    st = subpixel_shift(cen.F0, Xn, Yn, big, size)
    sp = np.einsum("ijk,ijk->i", st, refs)
    pp = np.einsum("ijk,ijk->i", refs, refs)
    ss = np.einsum("ijk,ijk->i", st, st)
    f = sp / pp
    tiny = 1e-300
    corr = sp / np.sqrt(
        np.maximum(ss - npix * sig**2, tiny) * np.maximum(pp - npix * var_ref, tiny)
    )
    core = common >= core_level * common.max()
    resid = st - f[:, None, None] * refs
    var_pix = (
        sig[:, None, None] ** 2
        + (f**2 * var_ref)[:, None, None]
        + (model_error * f[:, None, None] * refs) ** 2
    )
    chi2 = np.sum(np.where(core[None], resid**2 / var_pix, 0.0), axis=(1, 2)) / max(
        int(core.sum()) - 3, 1
    )
    return _Check(X=Xn, Y=Yn, stars=st, sp=sp, pp=pp, flux=f, correlation=corr, chi2=chi2)


def _refine_pass(
    cand: _Candidates,
    cen: _Centred,
    median: bool,
    size: int,
    big: int,
    min_correlation: float,
    max_chi2: float | None,
    model_error: float,
    core_level: float,
    max_shift: float,
) -> None:
    """One re-centre / reject / re-stack pass against the median (``median``) or the
    leave-one-out stack; updates ``cand`` and ``cen``, raises :class:`PSFError` if no
    star remains."""
    used = cand.used_now()
    refs, var_ref, common = _reference_stacks(cen, used, median, cand.m, size)
    chk = _compare_with_stack(cen, cand.sig, refs, var_ref, common, size, big, model_error,
                              core_level)  # fmt: skip
    f, corr, chi2 = chk.flux, chk.correlation, chk.chi2
    # record this check for the stars still in play, then reject
    active = used
    idx, sig, rec = cand.idx, cand.sig, cand.record
    cen.X = np.where(active, chk.X, cen.X)
    cen.Y = np.where(active, chk.Y, cen.Y)
    rec.flux[idx[active]] = f[active]
    rec.correlation[idx[active]] = corr[active]
    rec.chi2[idx[active]] = chi2[active]
    rec.snr[idx[active]] = (chk.sp / (sig * np.sqrt(chk.pp)))[active]
    cand.reject(active & (np.hypot(cen.X - cen.x0, cen.Y - cen.y0) > max_shift),
                REASONS["shift"])  # fmt: skip
    cand.reject(active & ~(f > 0), REASONS["flux"])
    cand.reject(active & ~(corr >= min_correlation), REASONS["correlation"])
    if max_chi2 is not None:
        cand.reject(active & ~(chi2 <= max_chi2), REASONS["chi2"])
    if not cand.used_now().any():
        raise cand.error()
    fa = np.where(f > 0, f, 1.0)
    cen.unit = np.where(active[:, None, None], chk.stars / fa[:, None, None], cen.unit)
    cen.var_unit = np.where(active, (sig / fa) ** 2, cen.var_unit)


def _final_stack(
    cand: _Candidates,
    cen: _Centred,
    weighting: str,
    size: int,
    big: int,
    centroid_sigma: float,
    source: str,
) -> tuple[np.ndarray, float, float, np.ndarray, np.ndarray]:
    """The stack of the surviving stars, centred on its Gaussian cross-correlation peak
    and of unit sum. Returns it, its pre-normalisation pixel variance, its
    pre-normalisation sum and its shift ``sx, sy``."""
    used = cand.used_now()
    if weighting == "median":
        psf, var = cen.median_stack(used)
    else:
        num, wts = cen.mean_parts(used)
        psf, var = num / wts.sum(), 1.0 / wts.sum()
    # put the Gaussian cross-correlation peak of the stack on [c, c]
    Pbig = pad_to(psf[None], big)
    Dp = np.fft.rfft2(Pbig) * cen.phase[None]
    sx, sy, okp = gaussian_peak(Dp, centroid_sigma, np.zeros(1), np.zeros(1), 1.0)
    if not okp[0]:
        sx, sy = np.zeros(1), np.zeros(1)
    psf = subpixel_shift(np.fft.rfft2(Pbig), sx, sy, big, size)[0]
    total = psf.sum()
    if not total > 0:
        raise PSFError(f"{source}: the stack of {used.sum()} stars has non-positive flux")
    psf = psf / total
    return psf, var, total, sx, sy


def _build_result(
    cand: _Candidates,
    cen: _Centred,
    x: np.ndarray,
    y: np.ndarray,
    psf: np.ndarray,
    var: float,
    total: float,
    sx: np.ndarray,
    sy: np.ndarray,
    source: str,
    meta: dict,
) -> PSFResult:
    """The :class:`PSFResult` of :func:`stack_psf`: measured centres, reasons, noise and
    the size and shape diagnostics of ``psf``."""
    idx, rec = cand.idx, cand.record
    rec.x[idx] = cand.ix[idx] + cen.X + sx[0]
    rec.y[idx] = cand.iy[idx] + cen.Y + sy[0]
    reason = cand.reason
    reason_arr = np.array([str(r) for r in reason], dtype=str) if cand.n else np.array([], str)
    return PSFResult(
        image=psf,
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
        pixel_noise=float(np.sqrt(var) / total),
        source=source,
        meta=meta,
        **psf_diagnostics(psf),
    )


def combine_psfs(results, weights=None) -> PSFResult:
    """Co-add PSFs estimated from several sources (e.g. a star field and a galaxy field).

    Parameters
    ----------
    results : sequence of PSFResult
        The PSFs; images of different sizes are padded (about their centres) to the
        largest.
    weights : array_like, optional
        One non-negative weight per result; by default the number of stars used in
        each (for stars of similar S/N, the inverse variance of each stack).

    Returns
    -------
    PSFResult
        ``sum_i w_i P_i / sum_i w_i`` (unit sum), the per-star diagnostics concatenated
        in the order of ``results``, summary diagnostics measured on the new image and
        ``source`` the labels joined by ``'+'``.

    Raises
    ------
    PSFError
        If there is no result or the weights do not sum to a positive value.
    """
    results = list(results)
    if not results:
        raise PSFError("combine_psfs: no PSF to combine")
    if weights is None:
        w = np.array([r.n_used for r in results], dtype=float)
    else:
        w = np.asarray(weights, dtype=float).ravel()
        if w.shape != (len(results),):
            raise ValueError(f"weights must have length {len(results)}, got {w.shape}")
    if not (np.all(np.isfinite(w)) and np.all(w >= 0) and w.sum() > 0):
        labels = "+".join(r.source for r in results)
        raise PSFError(f"{labels}: combine_psfs weights must be >= 0 with a positive sum: {w}")
    size = max(r.image.shape[0] for r in results)
    images = np.stack([centre_on_stamp(r.image / r.image.sum(), size) for r in results])
    w = w / w.sum()
    psf = np.einsum("i,ijk->jk", w, images)
    psf = psf / psf.sum()
    noise = np.array([r.pixel_noise for r in results], dtype=float)
    cols = {name: np.concatenate([getattr(r, name) for r in results]) for name in _STAR_COLUMNS}
    cols["used"] = cols["used"].astype(bool)
    cols["reason"] = cols["reason"].astype(str)
    return PSFResult(
        image=psf,
        pixel_noise=float(np.sqrt(np.sum((w * noise) ** 2))),
        source="+".join(r.source for r in results),
        meta={"weights": w.tolist()},
        **cols,
        **psf_diagnostics(psf),
    )
