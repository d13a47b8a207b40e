"""A PSF with its per-star diagnostics (:class:`PSFResult`): made from an image, read,
written and co-added."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.table import Table

from .._util import atomic_write
from .diagnostics import psf_diagnostics
from .transform import PSFError, centre_on_stamp

#: Columns of the per-star table, :meth:`PSFResult.stars`.
STAR_COLUMNS = ("x_cat", "y_cat", "x", "y", "flux", "snr", "correlation", "chi2", "used",
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
        cols = {name: getattr(self, name) for name in STAR_COLUMNS}
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
        kw = {name: np.asarray(t[name], dtype=float) for name in STAR_COLUMNS[:-2]}
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
    cols = {name: np.concatenate([getattr(r, name) for r in results]) for name in STAR_COLUMNS}
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
