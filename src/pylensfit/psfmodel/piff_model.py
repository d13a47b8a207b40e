"""PSF models fitted by Piff (optional dependency): :class:`PiffPSF` reads and draws
one, :func:`fit_piff` fits one to an image's stars."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..psf import PSFError, PSFResult, psf_diagnostics
from .base import PSFModel, atomic_write_bytes, sha1
from .basis import phase, recentre


class PiffNotInstalledError(ImportError):
    """Piff, needed for :class:`PiffPSF`, is not installed."""


def import_piff():
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
        piff = import_piff()
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
        D = np.fft.rfft2(stamps) * phase(big)[None]
        return recentre(D, self.size, self.centroid_sigma, search=2.0)[0]

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
        return sha1("PiffPSF", self._bytes, self.size, self.chipnum, self.origin,
                    self.centroid_sigma, self.margin)  # fmt: skip

    def write(self, path, overwrite=False):
        """Copy the Piff file (byte for byte), atomically."""
        atomic_write_bytes(self._bytes, Path(path), overwrite)


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
    piff = import_piff()
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
