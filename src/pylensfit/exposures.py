"""Exposures of a field and each galaxy's view in them, for fitting a galaxy on all of
its exposures at once.

A survey measures each galaxy jointly on every exposure that holds it (CFHTLenS 7,
KiDS 5): one shape, size and sky position shared by the exposures, each exposure with
its own PSF, noise, photometric scale and astrometry. An :class:`Exposure` is one
exposure of a field (image, weight or mask, celestial WCS, flux scale, PSF source); an
:class:`ExposureStamps` is the view of ``n`` galaxies in one exposure (their stamps,
weights, noise, PSFs, local WCS Jacobians, flux scale and why an exposure is not usable
for a galaxy), and :class:`ExposureStamp` one galaxy's view in one exposure.

Conventions
-----------
* Pixel coordinates are 0-based with pixel centres on integers, ``x`` along the
  columns (FITS pixel ``x + 1``); a stamp's element ``[j, i]`` is pixel
  ``(x0 + i, y0 + j)``.
* The sky frame at a galaxy is that of :mod:`pylensfit.skyframe` (TreeCorr's for RA/Dec
  catalogues, GalSim's ``(u, v)``): the gnomonic tangent plane at the galaxy with axes
  ``(W, N)``, north up and **west** to the right, in arcsec. An offset of ``dW`` to the
  west and ``dN`` to the north is ``(dRA cos(dec), dDec) = (-dW, dN)`` to first order.
* The local WCS Jacobian of an exposure at a galaxy is
  ``J = d(x, y) / d(W, N)``, in pixels per arcsec: ``(dx, dy) = J (dW, dN)``, so
  ``J[0, 0] = dx/dW``, ``J[0, 1] = dx/dN``, ``J[1, 0] = dy/dW``, ``J[1, 1] = dy/dN``.
  It is the inverse of GalSim's local ``JacobianWCS`` (``galsim.FitsWCS.local``, which
  gives ``d(u, v)/d(x, y)``) and of :mod:`pylensfit.skyframe`'s ``d(W, N)/d(x, y)``
  (there in degrees). A north-up, east-left image of pixel scale ``s`` has
  ``J = diag(1, 1) / s``; ``det J < 0`` is a mirror image (a flipped WCS);
  ``1 / sqrt(|det J|)`` is the local pixel scale in arcsec.
* A profile ``f(u)`` on the sky is ``f(J^-1 x)`` in the exposure's pixels. A shape or
  shear given in the sky frame is carried to an exposure's pixel frame exactly by
  :func:`sky_to_exposure_shear` (:func:`pylensfit.skyframe.shear_to_pixel` through the
  decomposition of ``J^-1`` into a flip, the WCS's distortion, a rotation and a scale,
  :class:`pylensfit.skyframe.SkyFrame`); a size of ``r`` arcsec is
  ``r sqrt(|det J|)`` pixels.
* ``flux_scale`` is an exposure's counts per unit of the common flux: a galaxy of flux
  ``F`` gives ``flux_scale * F`` counts in the exposure. From photometric zero points
  (magnitudes of one count), ``flux_scale = 10**(0.4 (ZP - ZP_ref))``
  (:func:`flux_scale_from_zero_point`).
"""

from __future__ import annotations

import enum
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
from astropy.io import fits
from astropy.stats import sigma_clipped_stats
from astropy.wcs import WCS

from .skyframe import SkyFrame, local_frame, shear_to_pixel, wcs_from_header

__all__ = [
    "ARCSEC",
    "Exposure",
    "ExposureStamp",
    "ExposureStamps",
    "PSFSource",
    "StampFlag",
    "cut_exposures",
    "cut_stamps",
    "flux_scale_from_zero_point",
    "galaxy_views",
    "local_jacobian",
    "mask_cosmic_rays",
    "sky_offsets_to_world",
    "sky_to_exposure_shear",
    "sky_to_pixel",
]

#: Degrees per arcsec.
ARCSEC = 1.0 / 3600.0


class StampFlag(enum.IntFlag):
    """Why an exposure is not usable for a galaxy (bit flags; 0: usable).

    Attributes
    ----------
    OFF_IMAGE
        The galaxy's centre is not on the exposure's image (or its position is not
        finite).
    EDGE
        The stamp crosses the image's edge (its pixels off the image have weight 0).
    CENTRE_MASKED
        The pixel at the galaxy's centre is masked or has zero weight (a chip gap, a
        bad column).
    MASKED
        More of the stamp's pixels on the image are masked or have zero weight than
        ``max_masked_fraction`` allows.
    BAD_PIXELS
        Non-finite pixels of non-zero weight in the stamp.
    BAD_WCS
        The local Jacobian is not finite or singular there.
    PSF_FAILED
        The PSF source gave no finite PSF at the galaxy.
    """

    OFF_IMAGE = 1
    EDGE = 2
    CENTRE_MASKED = 4
    MASKED = 8
    BAD_PIXELS = 16
    BAD_WCS = 32
    PSF_FAILED = 64


@runtime_checkable
class PSFSource(Protocol):
    """A PSF that varies over an exposure (:class:`pylensfit.psfmodel.PSFModel` is one).

    ``draw(x, y)`` takes 1-D arrays of 0-based pixel positions and returns the
    ``(n, size, size)`` PSF images there (the pixel response included, centred on
    element ``[size // 2, size // 2]``).
    """

    def draw(self, x, y) -> np.ndarray: ...


def flux_scale_from_zero_point(zero_point, reference):
    """An exposure's counts per unit of the common flux, from photometric zero points.

    Parameters
    ----------
    zero_point : float or array_like
        The exposure's zero point (magnitude of one count, or of one count per second
        for images in counts per second).
    reference : float
        The zero point of the common flux unit.

    Returns
    -------
    float or numpy.ndarray
        ``10**(0.4 (zero_point - reference))``.
    """
    return 10.0 ** (0.4 * (np.asarray(zero_point, dtype=float) - reference))


def sky_offsets_to_world(ra, dec, dw, dn) -> tuple[np.ndarray, np.ndarray]:
    """Positions offset from ``(ra, dec)`` in the gnomonic tangent plane there.

    Parameters
    ----------
    ra, dec : array_like
        Tangent points, degrees (in the celestial frame of the WCS they are used with).
    dw, dn : array_like
        Offsets to the west and to the north in the tangent plane, arcsec (broadcast
        with ``ra, dec``).

    Returns
    -------
    ra, dec : numpy.ndarray
        The offset positions, degrees, ``ra`` in ``[0, 360)``.
    """
    a, d = np.radians(np.asarray(ra, dtype=float)), np.radians(np.asarray(dec, dtype=float))
    xi = -np.radians(np.asarray(dw, dtype=float) * ARCSEC)  # east
    eta = np.radians(np.asarray(dn, dtype=float) * ARCSEC)  # north
    ca, sa, cd, sd = np.cos(a), np.sin(a), np.cos(d), np.sin(d)
    # the tangent point's unit vector plus xi east + eta north, projected back
    vx = cd * ca - xi * sa - eta * sd * ca
    vy = cd * sa + xi * ca - eta * sd * sa
    vz = sd + eta * cd
    ra_out = np.degrees(np.arctan2(vy, vx)) % 360.0
    return ra_out, np.degrees(np.arctan2(vz, np.hypot(vx, vy)))


def sky_to_pixel(wcs: WCS, ra, dec, *, tolerance: float = 1e-8) -> tuple[np.ndarray, np.ndarray]:
    """0-based pixel positions of sky positions, through the full WCS (SIP, TPV included).

    Parameters
    ----------
    wcs : astropy.wcs.WCS
        The exposure's celestial WCS.
    ra, dec : array_like
        Positions, degrees, in the WCS's celestial frame.
    tolerance : float
        Convergence of the inversion of a distortion (pixels,
        :meth:`astropy.wcs.WCS.all_world2pix`).

    Returns
    -------
    x, y : numpy.ndarray
        1-D, pixels; NaN where the input is not finite.
    """
    ra = np.atleast_1d(np.asarray(ra, dtype=float))
    dec = np.atleast_1d(np.asarray(dec, dtype=float))
    ra, dec = np.broadcast_arrays(ra, dec)
    x = np.full(ra.shape, np.nan)
    y = np.full(ra.shape, np.nan)
    ok = np.isfinite(ra) & np.isfinite(dec)
    if ok.any():
        with warnings.catch_warnings():  # far off the image the inversion may not converge
            warnings.simplefilter("ignore", RuntimeWarning)
            x[ok], y[ok] = wcs.all_world2pix(ra[ok], dec[ok], 0, tolerance=tolerance,
                                             quiet=True)  # fmt: skip
    return x, y


def local_jacobian(
    wcs: WCS, ra, dec, *, step: float = 0.5, tolerance: float = 1e-10
) -> np.ndarray:
    """The local WCS Jacobian ``J = d(x, y)/d(W, N)`` of an exposure at each galaxy.

    Central differences of :meth:`astropy.wcs.WCS.all_world2pix` (distortions included)
    over offsets of ``+-step`` arcsec to the west and to the north in each galaxy's
    gnomonic tangent plane (:func:`sky_offsets_to_world`). Rotated, sheared and
    mirror-image (``det J < 0``) WCSs need nothing special.

    Parameters
    ----------
    wcs : astropy.wcs.WCS
        The exposure's celestial WCS.
    ra, dec : array_like
        Galaxy positions, degrees, in the WCS's celestial frame.
    step : float
        Half the difference's baseline, arcsec: the truncation error is of order
        ``step^2`` times the third derivative of the distortion (below 1e-12 relative
        for a TAN projection at 0.5 arcsec).
    tolerance : float
        Convergence of the inversion of a distortion, pixels; it bounds the error of
        ``J`` by about ``tolerance / step`` pixels per arcsec.

    Returns
    -------
    numpy.ndarray
        ``(n, 2, 2)``, pixels per arcsec: ``(dx, dy) = J (dW, dN)`` (module docstring);
        NaN for a position that is not finite.
    """
    ra = np.atleast_1d(np.asarray(ra, dtype=float))
    dec = np.atleast_1d(np.asarray(dec, dtype=float))
    ra, dec = np.broadcast_arrays(ra, dec)
    n = ra.size
    dw = np.repeat([step, -step, 0.0, 0.0], n)
    dn = np.repeat([0.0, 0.0, step, -step], n)
    r4, d4 = sky_offsets_to_world(np.tile(ra, 4), np.tile(dec, 4), dw, dn)
    x, y = (a.reshape(4, n) for a in sky_to_pixel(wcs, r4, d4, tolerance=tolerance))
    J = np.empty((n, 2, 2))
    with np.errstate(invalid="ignore"):  # a WCS that fails there: NaN (or inf - inf)
        J[:, :, 0] = np.stack([x[0] - x[1], y[0] - y[1]], -1) / (2 * step)
        J[:, :, 1] = np.stack([x[2] - x[3], y[2] - y[3]], -1) / (2 * step)
    return J


def sky_to_exposure_shear(g1, g2, frame: SkyFrame) -> tuple[np.ndarray, np.ndarray]:
    """A shape or shear given in the sky frame, in an exposure's pixel frame.

    The exact map of the ellipse through the local WCS
    (:func:`pylensfit.skyframe.shear_to_pixel`): the inverse rotation, the WCS's
    distortion removed as a reduced shear, the flip of a mirror-image WCS.

    Parameters
    ----------
    g1, g2 : array_like
        Sky-frame reduced shear or ellipticity (``(W, N)`` axes), one per galaxy.
    frame : pylensfit.skyframe.SkyFrame
        The exposure's frame at the galaxies (:attr:`ExposureStamps.frame`).

    Returns
    -------
    g1, g2 : numpy.ndarray
        The same in the exposure's pixel frame.
    """
    return shear_to_pixel(g1, g2, frame)


@dataclass(frozen=True, eq=False)
class Exposure:
    """One exposure of a field: pixels, their weights, astrometry, photometry and PSF.

    Attributes
    ----------
    image : numpy.ndarray
        ``(ny, nx)`` pixels, counts.
    wcs : astropy.wcs.WCS
        Celestial WCS of the image (any projection and distortion astropy reads: SIP,
        TPV).
    weight : numpy.ndarray, optional
        ``(ny, nx)`` inverse variance, counts^-2; 0 where there are no data (chip gaps,
        bad pixels).
    mask : numpy.ndarray, optional
        ``(ny, nx)`` bool, True for a bad pixel.
    background : float
        Sky level subtracted from the stamps, counts.
    noise_sigma : float, optional
        Per-pixel noise, counts, where no ``weight`` is given.
    flux_scale : float
        Counts per unit of the common flux (module docstring).
    psf : numpy.ndarray or PSFSource, optional
        The PSF: one image for the whole exposure (pixel response included, centred on
        element ``[size // 2, size // 2]``), or a source with ``draw(x, y)``.
    path : str, optional
        The file the exposure was read from.
    name : str
        A label (default: the file's name).
    """

    image: np.ndarray
    wcs: WCS
    weight: np.ndarray | None = None
    mask: np.ndarray | None = None
    background: float = 0.0
    noise_sigma: float | None = None
    flux_scale: float = 1.0
    psf: np.ndarray | PSFSource | None = None
    path: str | None = None
    name: str = ""

    def __post_init__(self) -> None:
        if np.ndim(self.image) != 2:
            raise ValueError(f"an exposure's image is 2-D, not of shape {np.shape(self.image)}")
        for what in ("weight", "mask"):
            a = getattr(self, what)
            if a is not None and np.shape(a) != np.shape(self.image):
                raise ValueError(f"{what} of shape {np.shape(a)} for an image of shape "
                                 f"{np.shape(self.image)}")  # fmt: skip
        if not (self.flux_scale > 0 and np.isfinite(self.flux_scale)):
            raise ValueError(f"flux_scale must be finite and > 0, not {self.flux_scale}")
        if self.psf is not None and not isinstance(self.psf, PSFSource) and np.ndim(self.psf) != 2:
            raise ValueError("psf must be a 2-D image or have a draw(x, y) method")

    @property
    def shape(self) -> tuple[int, int]:
        """``(ny, nx)``, pixels."""
        return tuple(np.shape(self.image))

    def good(self) -> np.ndarray:
        """``(ny, nx)`` bool: pixels with data (positive weight, not masked)."""
        ok = np.ones(self.shape, bool)
        if self.weight is not None:
            ok &= np.asarray(self.weight) > 0
        if self.mask is not None:
            ok &= ~np.asarray(self.mask, dtype=bool)
        return ok

    @classmethod
    def from_fits(
        cls,
        path: str | Path,
        *,
        hdu: int | str = 0,
        weight: int | str | None = "WEIGHT",
        psf: np.ndarray | PSFSource | None = None,
        zero_point_key: str = "MAGZP",
        reference_zero_point: float | None = None,
        background: float | None = None,
    ) -> Exposure:
        """Read an exposure from a FITS file: image, WCS, weight HDU, zero point.

        Parameters
        ----------
        path : str or pathlib.Path
            The file.
        hdu : int or str
            The image's HDU.
        weight : int or str, optional
            The inverse-variance HDU (skipped if the file has none); None: no weight.
        psf : numpy.ndarray or PSFSource, optional
            The exposure's PSF (:attr:`psf`).
        zero_point_key : str
            Header card of the zero point.
        reference_zero_point : float, optional
            The common flux unit's zero point: with it and the card, ``flux_scale`` is
            :func:`flux_scale_from_zero_point`; else 1.
        background : float, optional
            Sky level, counts (default: the sigma-clipped median of the pixels with
            data).

        Returns
        -------
        Exposure
            The noise is the weight's where there is one, else the sigma-clipped
            standard deviation of the pixels.

        Raises
        ------
        ValueError
            If the HDU has no celestial WCS.
        """
        with fits.open(path) as hl:
            image = np.asarray(hl[hdu].data, dtype=np.float64)
            hdr = hl[hdu].header
            names = [h.name for h in hl]
            w = None
            if weight is not None and (not isinstance(weight, str) or weight in names):
                w = np.asarray(hl[weight].data, dtype=np.float64)
        wcs = wcs_from_header(hdr)
        if wcs is None:
            raise ValueError(f"{path}: no celestial WCS in HDU {hdu!r}")
        scale = 1.0
        if reference_zero_point is not None and zero_point_key in hdr:
            scale = float(flux_scale_from_zero_point(hdr[zero_point_key], reference_zero_point))
        good = np.isfinite(image) & (w > 0 if w is not None else True)
        noise = None
        if background is None or w is None:
            _, med, std = sigma_clipped_stats(image[good])
            background = float(med) if background is None else background
            noise = None if w is not None else float(std)
        return cls(image=image, wcs=wcs, weight=w, background=float(background),
                   noise_sigma=noise, flux_scale=scale, psf=psf, path=str(path),
                   name=Path(path).name)  # fmt: skip


def mask_cosmic_rays(exposure: Exposure, *, sigclip: float = 6.0,
                     objlim: float = 5.0) -> tuple[Exposure, int]:  # fmt: skip
    """The exposure with its cosmic rays masked: L.A.Cosmic (van Dokkum 2001, PASP 113,
    1420), by astroscrappy.

    The Laplacian of the image against its noise (the weight's inverse, else
    ``noise_sigma^2``) finds the edges sharper than the PSF; ``objlim`` keeps the cores
    of stars and galaxies, which the PSF has smoothed. On pure noise of unit variance,
    ``sigclip = 6`` flags no pixel in 4 million, and a hit of 10 sigma in one pixel is
    found (the default 4.5 flags one in 70,000 noise pixels: one stamp of 48^2 in 30).

    Parameters
    ----------
    exposure : Exposure
        The exposure; pixels without data (:meth:`Exposure.good`) are not searched.
    sigclip : float
        Laplacian-to-noise limit of a cosmic-ray pixel (astroscrappy's ``sigclip``).
    objlim : float
        Contrast of the Laplacian against the fine-structure image below which a sharp
        pixel is taken for an object (astroscrappy's ``objlim``).

    Returns
    -------
    exposure : Exposure
        The same with ``mask`` true on the cosmic rays too.
    n : int
        The pixels masked.
    """
    import astroscrappy  # a compiled extension, needed only here

    good = exposure.good() & np.isfinite(exposure.image)
    if exposure.weight is not None:
        w = np.asarray(exposure.weight, dtype=float)
        var = np.where(good, 1.0 / np.where(good, w, 1.0), 1.0)
    else:
        var = np.full(exposure.shape, float(exposure.noise_sigma or 1.0) ** 2)
    hits, _ = astroscrappy.detect_cosmics(
        np.where(good, exposure.image, 0.0).astype(np.float32), inmask=~good,
        invar=var.astype(np.float32), sigclip=sigclip, objlim=objlim, gain=1.0,
        readnoise=0.0, satlevel=np.inf)  # fmt: skip
    hits = np.asarray(hits, bool) & good
    mask = hits if exposure.mask is None else hits | np.asarray(exposure.mask, bool)
    return replace(exposure, mask=mask), int(hits.sum())


@dataclass(frozen=True, eq=False)
class ExposureStamp:
    """One galaxy's view in one exposure (an element of :class:`ExposureStamps`).

    Attributes
    ----------
    stamp : numpy.ndarray
        ``(N, N)`` pixels, background subtracted, 0 where there are no data.
    weight : numpy.ndarray
        ``(N, N)`` inverse variance, 0 off the image and where masked.
    noise_sigma : float
        Per-pixel noise, counts.
    psf : numpy.ndarray or None
        The PSF image at the galaxy.
    x, y : float
        The galaxy's position in the exposure, 0-based pixels.
    centre : tuple of float
        Its position in the stamp, ``(x, y)`` 0-based (near ``(N // 2, N // 2)``).
    jacobian : numpy.ndarray
        ``(2, 2)`` local WCS Jacobian ``d(x, y)/d(W, N)``, pixels per arcsec.
    frame : pylensfit.skyframe.SkyFrame
        The exposure's frame at the galaxy (one element).
    flux_scale : float
        The exposure's counts per unit of the common flux.
    flags : StampFlag
        Why the exposure is not usable for the galaxy (0: usable).
    exposure : int
        The exposure's index.
    """

    stamp: np.ndarray
    weight: np.ndarray
    noise_sigma: float
    psf: np.ndarray | None
    x: float
    y: float
    centre: tuple[float, float]
    jacobian: np.ndarray
    frame: SkyFrame
    flux_scale: float
    flags: StampFlag
    exposure: int = 0

    @property
    def usable(self) -> bool:
        """Whether the exposure is usable for the galaxy (no flag)."""
        return self.flags == 0

    @property
    def pixel_scale(self) -> float:
        """The local pixel scale ``1 / sqrt(|det J|)``, arcsec."""
        return float(1.0 / np.sqrt(np.abs(_det(self.jacobian))))


@dataclass(frozen=True, eq=False)
class ExposureStamps:
    """The stamps of ``n`` galaxies in one exposure, with their local WCS and flags.

    Attributes
    ----------
    stamps : numpy.ndarray
        ``(n, N, N)`` pixels, background subtracted, 0 where there are no data.
    weights : numpy.ndarray
        ``(n, N, N)`` inverse variance, 0 off the image and where masked.
    noise_sigma : numpy.ndarray
        ``(n,)`` per-pixel noise, counts (from the weights on the stamp, else the
        exposure's).
    psf : numpy.ndarray or None
        ``(n, M, M)`` PSF images at the galaxies (a read-only broadcast of the
        exposure's one image if it has one); None without a PSF source.
    x, y : numpy.ndarray
        ``(n,)`` the galaxies' positions in the exposure, 0-based pixels.
    x0, y0 : numpy.ndarray
        ``(n,)`` int, the pixel of each stamp's element ``[0, 0]``.
    jacobian : numpy.ndarray
        ``(n, 2, 2)`` local WCS Jacobians ``d(x, y)/d(W, N)``, pixels per arcsec.
    frame : pylensfit.skyframe.SkyFrame
        The exposure's frame at each galaxy (:func:`pylensfit.skyframe.local_frame`).
    flux_scale : float
        The exposure's counts per unit of the common flux.
    flags : numpy.ndarray
        ``(n,)`` int, :class:`StampFlag` bits (0: usable).
    exposure : int
        The exposure's index in its set.
    """

    stamps: np.ndarray
    weights: np.ndarray
    noise_sigma: np.ndarray
    psf: np.ndarray | None
    x: np.ndarray
    y: np.ndarray
    x0: np.ndarray
    y0: np.ndarray
    jacobian: np.ndarray
    frame: SkyFrame
    flux_scale: float
    flags: np.ndarray
    exposure: int = 0

    def __len__(self) -> int:
        return int(self.x.size)

    @property
    def usable(self) -> np.ndarray:
        """``(n,)`` bool: the exposure is usable for the galaxy."""
        return self.flags == 0

    @property
    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """The galaxies' positions in their stamps, ``(x, y)`` 0-based pixels (as
        :func:`pylensfit.measure_stamps`'s ``centres``)."""
        return self.x - self.x0, self.y - self.y0

    @property
    def pixel_scale(self) -> np.ndarray:
        """``(n,)`` local pixel scales ``1 / sqrt(|det J|)``, arcsec."""
        return 1.0 / np.sqrt(np.abs(_det(self.jacobian)))

    def reasons(self, i: int) -> list[str]:
        """The names of galaxy ``i``'s flags (empty when usable)."""
        f = StampFlag(int(self.flags[i]))
        return [m.name for m in StampFlag if m in f]

    def __getitem__(self, i: int) -> ExposureStamp:
        i = int(i)
        fr = self.frame.take(slice(i, i + 1))
        return ExposureStamp(
            stamp=self.stamps[i], weight=self.weights[i], noise_sigma=float(self.noise_sigma[i]),
            psf=None if self.psf is None else self.psf[i], x=float(self.x[i]),
            y=float(self.y[i]), centre=(float(self.x[i] - self.x0[i]),
                                        float(self.y[i] - self.y0[i])),
            jacobian=self.jacobian[i], frame=fr, flux_scale=self.flux_scale,
            flags=StampFlag(int(self.flags[i])), exposure=self.exposure,
        )  # fmt: skip


def _det(J: np.ndarray) -> np.ndarray:
    """``det J``, NaN where ``J`` is not finite."""
    fin = np.all(np.isfinite(J), axis=(-2, -1))
    return np.where(fin, np.linalg.det(np.where(fin[..., None, None], J, np.eye(2))), np.nan)


def _windows(shape: tuple[int, int], x: np.ndarray, y: np.ndarray, size: int):
    """Each stamp's corner ``x0, y0``, its clipped row and column indices and which of
    them lie on the image."""
    ny, nx = shape
    fin = np.isfinite(x) & np.isfinite(y)
    ix = np.where(fin, np.rint(np.where(fin, x, 0.0)), -(10**9)).astype(np.int64)
    iy = np.where(fin, np.rint(np.where(fin, y, 0.0)), -(10**9)).astype(np.int64)
    x0, y0 = ix - size // 2, iy - size // 2
    cols = x0[:, None] + np.arange(size)
    rows = y0[:, None] + np.arange(size)
    cin = (cols >= 0) & (cols < nx)
    rin = (rows >= 0) & (rows < ny)
    on = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    return x0, y0, np.clip(rows, 0, ny - 1), np.clip(cols, 0, nx - 1), rin, cin, on


def _stamp_noise(exposure: Exposure, weights: np.ndarray, good: np.ndarray) -> np.ndarray:
    """Per-stamp noise: ``1 / sqrt(median positive weight)``, else the exposure's."""
    n = weights.shape[0]
    if exposure.weight is None:
        s = exposure.noise_sigma
        return np.full(n, np.nan if s is None else float(s))
    w = np.where(good, weights, np.nan).reshape(n, -1)
    with warnings.catch_warnings():  # a stamp without data: NaN, flagged elsewhere
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(w, axis=1)
    return 1.0 / np.sqrt(med)


def _psf_at(exposure: Exposure, x: np.ndarray, y: np.ndarray, on: np.ndarray):
    """The PSF images at the galaxies and whether each is finite."""
    n = x.size
    if exposure.psf is None:
        return None, np.ones(n, bool)
    if not isinstance(exposure.psf, PSFSource):
        p = np.asarray(exposure.psf, dtype=float)
        return np.broadcast_to(p, (n, *p.shape)), np.full(n, np.all(np.isfinite(p)))
    size = None
    out = None
    ok = np.zeros(n, bool)
    idx = np.flatnonzero(on)
    if idx.size:
        drawn = np.asarray(exposure.psf.draw(x[idx], y[idx]), dtype=float)
        drawn = drawn.reshape(idx.size, *drawn.shape[-2:])
        size = drawn.shape[-2:]
        out = np.full((n, *size), np.nan)
        out[idx] = drawn
        ok[idx] = np.all(np.isfinite(drawn), axis=(1, 2))
    return out, ok


def cut_stamps(
    exposure: Exposure,
    ra,
    dec,
    *,
    size: int = 48,
    max_masked_fraction: float = 0.0,
    index: int = 0,
) -> ExposureStamps:
    """Cut each galaxy's stamp from one exposure and say whether it is usable.

    The galaxy's position in the exposure is its sky position through the full WCS
    (:func:`sky_to_pixel`); the stamp is the ``size x size`` square about the nearest
    pixel, which is element ``[size // 2, size // 2]``. The stamp is background
    subtracted; pixels off the image or without data are 0 with weight 0.

    Parameters
    ----------
    exposure : Exposure
        The exposure.
    ra, dec : array_like
        The galaxies' sky positions, degrees, in the WCS's celestial frame.
    size : int
        Side of the stamps, pixels.
    max_masked_fraction : float
        The largest fraction of a stamp's on-image pixels that may be masked or of zero
        weight for the exposure to stay usable (:attr:`StampFlag.MASKED`).
    index : int
        The exposure's index in its set (:attr:`ExposureStamps.exposure`).

    Returns
    -------
    ExposureStamps
        The stamps, their local WCS and flags (:class:`StampFlag`): off the image,
        crossing its edge, a masked or zero-weight centre, too many masked pixels,
        non-finite pixels, a singular WCS or a failed PSF make the exposure unusable for
        the galaxy.
    """
    x, y = sky_to_pixel(exposure.wcs, ra, dec)
    x0, y0, rows, cols, rin, cin, on = _windows(exposure.shape, x, y, size)
    inside = rin[:, :, None] & cin[:, None, :]
    pix = np.asarray(exposure.image)[rows[:, :, None], cols[:, None, :]] - exposure.background
    good = exposure.good()[rows[:, :, None], cols[:, None, :]] & inside
    w = (np.asarray(exposure.weight, dtype=float)[rows[:, :, None], cols[:, None, :]]
         if exposure.weight is not None else np.ones(pix.shape))  # fmt: skip
    w = np.where(good, w, 0.0)
    bad_pix = np.any(~np.isfinite(pix) & good, axis=(1, 2))
    pix = np.where(good & np.isfinite(pix), pix, 0.0)
    w = np.where(np.isfinite(pix), w, 0.0)
    c = size // 2
    n_in = inside.sum(axis=(1, 2))
    masked = (n_in - good.sum(axis=(1, 2))) > max_masked_fraction * n_in
    J = local_jacobian(exposure.wcs, ra, dec)
    det = _det(J)
    psf, psf_ok = _psf_at(exposure, x, y, on)
    flags = np.zeros(x.size, np.int64)
    flags |= np.where(~on, StampFlag.OFF_IMAGE, 0)
    flags |= np.where(~inside.all(axis=(1, 2)), StampFlag.EDGE, 0)
    flags |= np.where(on & ~good[:, c, c], StampFlag.CENTRE_MASKED, 0)
    flags |= np.where(on & masked, StampFlag.MASKED, 0)
    flags |= np.where(bad_pix, StampFlag.BAD_PIXELS, 0)
    flags |= np.where(~(np.isfinite(det) & (det != 0)), StampFlag.BAD_WCS, 0)
    flags |= np.where(on & ~psf_ok, StampFlag.PSF_FAILED, 0)
    return ExposureStamps(stamps=pix, weights=w, noise_sigma=_stamp_noise(exposure, w, good),
                          psf=psf, x=x, y=y, x0=x0, y0=y0, jacobian=J,
                          frame=local_frame(exposure.wcs, x, y),
                          flux_scale=float(exposure.flux_scale), flags=flags,
                          exposure=index)  # fmt: skip


def cut_exposures(
    exposures, ra, dec, *, size: int = 48, max_masked_fraction: float = 0.0
) -> list[ExposureStamps]:
    """:func:`cut_stamps` of every exposure: the galaxies' views, exposure by exposure.

    Parameters
    ----------
    exposures : sequence of Exposure
        The exposures of the field.
    ra, dec : array_like
        The galaxies' sky positions, degrees.
    size : int
        Side of the stamps, pixels.
    max_masked_fraction : float
        As :func:`cut_stamps`.

    Returns
    -------
    list of ExposureStamps
        One per exposure, in order (``ExposureStamps.exposure`` its index); galaxy ``i``
        is element ``i`` of each.
    """
    return [cut_stamps(e, ra, dec, size=size, max_masked_fraction=max_masked_fraction,
                       index=k) for k, e in enumerate(exposures)]  # fmt: skip


def galaxy_views(stamp_sets: list[ExposureStamps], i: int, *,
                 usable_only: bool = True) -> list[ExposureStamp]:  # fmt: skip
    """Galaxy ``i``'s views in every exposure (the usable ones by default).

    Parameters
    ----------
    stamp_sets : list of ExposureStamps
        :func:`cut_exposures`'s output.
    i : int
        The galaxy's index.
    usable_only : bool
        Leave out the exposures not usable for the galaxy.

    Returns
    -------
    list of ExposureStamp
        In the exposures' order.
    """
    return [s[i] for s in stamp_sets if not usable_only or s.flags[i] == 0]
