"""Dithered exposures of one patch of sky, simulated with GalSim: the same galaxies seen
by ``K`` exposures, each with its own pointing, astrometry, PSF, noise and zero point.

The galaxies (a jittered lattice on the sky, the model bank's families in turn, shapes
from the functional prior) are sheared in the sky frame and rendered into each exposure
through its WCS: a pointing offset of tens of arcsec, a sub-pixel phase, a rotation of
up to a degree, a pixel scale a little off the nominal one, a flip on some exposures
and a chip gap (a band of columns without data, weight 0) through the middle of each.
Each exposure has its own seeing (the Moffat FWHM within +-15 % of the nominal one)
and PSF ellipticity (pixel frame), its own noise and photometric zero point.

Conventions are those of :mod:`pylensfit.exposures` and
:mod:`pylensfit_validation.simulate`: the sky frame has axes ``(W, N)``, north up and
west to the right; pixel positions are 0-based (FITS pixel ``x + 1``); the galaxies'
sizes are in arcsec (the model bank's meaning of ``r``, :meth:`GalaxyProfile.from_model`),
the PSFs' in pixels; an ellipticity is GalSim's reduced shear ``g`` of the profile. A
galaxy of flux ``F`` (the common unit) has ``F 10**(0.4 (MAGZP - zero_point))`` counts in
an exposure of zero point ``MAGZP`` (:func:`pylensfit.exposures.flux_scale_from_zero_point`).

:func:`simulate_dither` writes a set's directory::

    exp{k}.fits        image (TAN WCS, MAGZP), WEIGHT (inverse variance, 0 in the gap),
                       TRUTH (each galaxy's position in the exposure and whether its
                       centre is on data)
    exp{k}_stars.fits  a star field with the exposure's PSF, pixel scale and WCS
                       orientation (:func:`pylensfit_validation.simulate.simulate_field`)
    truth.fits         the galaxies in sky coordinates: ra, dec, intrinsic and sheared
                       shapes (sky frame), shear, size, flux
    manifest.json      the spec and every exposure's parameters (:func:`read_dither`)
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS

from pylensfit.catalogue import atomic_write
from pylensfit.exposures import flux_scale_from_zero_point, sky_offsets_to_world, sky_to_pixel
from pylensfit.prior import Prior
from pylensfit.shear import apply_shear

from .galaxies import PSFProfile
from .simulate import (
    MIXED_KINDS,
    FieldSpec,
    draw_shapes,
    galaxy_profile,
    simulate_field,
    write_field,
)

__all__ = [
    "DitherExposure",
    "DitherSet",
    "DitherSpec",
    "dither_exposures",
    "dither_galaxies",
    "exposure_wcs",
    "read_dither",
    "render_exposure",
    "simulate_dither",
]


@dataclass(frozen=True)
class DitherSpec:
    """What to simulate: the galaxies on the sky and how the exposures vary.

    Attributes
    ----------
    n_exposures : int
        Exposures of the patch, ``K`` (1 or more; surveys take 3-8).
    ngal : int
        Galaxies, on a square lattice of pitch ``spacing`` (arcsec) jittered by up to
        ``jitter`` (arcsec) on each axis, centred on ``(ra0, dec0)`` (degrees).
    g1, g2 : float
        The shear, sky frame.
    model : str
        ``"mixed"`` (:data:`pylensfit_validation.simulate.MIXED_KINDS` in turn), or one
        of them.
    size_range : tuple of float
        Galaxy sizes, arcsec (uniform; the model bank's ``r``).
    snr_range : tuple of float
        Matched-filter S/N of each galaxy in one nominal exposure (log-uniform): the
        nominal pixel scale, seeing, noise and zero point, a round PSF.
    prior_params : tuple of float
        ``(B, C, D)`` of the functional prior of the intrinsic shapes.
    max_e : float
        Largest intrinsic ``|e|``.
    pixel_scale : float
        Nominal pixel scale, arcsec.
    scale_spread : float
        Each exposure's pixel scale is the nominal one times ``1 + U(-1, 1) scale_spread``.
    dither : float
        Each pointing is offset by ``U(-1, 1) dither`` arcsec on each axis.
    rotation_max : float
        Each WCS is rotated by ``U(-1, 1) rotation_max`` degrees.
    flip_fraction : float
        The fraction of the exposures (rounded, drawn at random) whose WCS is a mirror
        image.
    psf_fwhm : float
        Nominal seeing, the Moffat FWHM in pixels of the nominal scale; each exposure's
        is ``psf_fwhm (1 + U(-1, 1) seeing_spread)`` (in its own pixels).
    seeing_spread : float
        See ``psf_fwhm``.
    psf_beta : float
        Moffat index.
    psf_e_max : float
        Each exposure's PSF ellipticity is uniform in the disc ``|e| < psf_e_max`` (pixel
        frame).
    noise_sigma : float
        Nominal noise per pixel (counts); each exposure's within +-10 % of it.
    sky : float
        Sky level, counts.
    zero_point : float
        The common flux unit's zero point (magnitudes); each exposure's is within
        ``+-zero_point_spread`` of it.
    zero_point_spread : float
        See ``zero_point``.
    gap : int
        Width of the chip gap through the middle of each image, pixels (0: none).
    margin : float
        Sky beyond the dithered lattice on every side of the images, arcsec.
    star_field_size : int
        Side of each exposure's star field, pixels.
    stamp : int
        Side of the drawing of each galaxy, pixels.
    ra0, dec0 : float
        The patch's centre, degrees.
    """

    n_exposures: int = 5
    ngal: int = 400
    g1: float = 0.0
    g2: float = 0.0
    model: str = "mixed"
    size_range: tuple[float, float] = (0.24, 0.7)
    snr_range: tuple[float, float] = (15.0, 150.0)
    prior_params: tuple[float, float, float] = (0.19, 0.58, 2.4)
    max_e: float = 0.99
    spacing: float = 8.0
    jitter: float = 1.2
    pixel_scale: float = 0.2
    scale_spread: float = 0.01
    dither: float = 30.0
    rotation_max: float = 1.0
    flip_fraction: float = 0.34
    psf_fwhm: float = 3.5
    seeing_spread: float = 0.15
    psf_beta: float = 3.5
    psf_e_max: float = 0.06
    noise_sigma: float = 1.0
    sky: float = 50.0
    zero_point: float = 30.0
    zero_point_spread: float = 0.1
    gap: int = 12
    margin: float = 8.0
    star_field_size: int = 512
    stamp: int = 64
    ra0: float = 150.0
    dec0: float = 2.0

    def __post_init__(self) -> None:
        if self.n_exposures < 1 or self.ngal < 1:
            raise ValueError(f"n_exposures and ngal must be >= 1, not {self.n_exposures}, "
                             f"{self.ngal}")  # fmt: skip
        if self.model != "mixed" and self.model not in MIXED_KINDS:
            raise ValueError(f"model must be 'mixed' or one of {MIXED_KINDS}, not {self.model!r}")

    @property
    def lattice_side(self) -> int:
        """Lattice points per side."""
        return math.ceil(math.sqrt(self.ngal))

    @property
    def image_size(self) -> int:
        """Side of every exposure's image, pixels: the lattice, the largest dither and
        ``margin`` on every side, rotated by up to ``rotation_max``, at the smallest
        pixel scale."""
        t = math.radians(self.rotation_max)
        half = self.lattice_side * self.spacing / 2 + self.jitter + self.dither
        half = half * (math.cos(t) + math.sin(t)) + self.margin
        return int(math.ceil(2 * half / (self.pixel_scale * (1.0 - self.scale_spread))))


@dataclass(frozen=True)
class DitherExposure:
    """One exposure of a dithered set.

    Attributes
    ----------
    index : int
        Its index.
    offset_w, offset_n : float
        Its pointing (the image centre's sky position) less the patch's centre, west
        and north, arcsec.
    phase_x, phase_y : float
        Sub-pixel phase of the pointing: the reference pixel is the image's centre plus
        these, pixels.
    rotation : float
        Rotation of the WCS ``theta``, degrees (pixel to sky frame,
        :mod:`pylensfit_validation.simulate`).
    flip : bool
        Whether the WCS is a mirror image.
    pixel_scale : float
        Arcsec per pixel.
    psf_fwhm : float
        Moffat FWHM, pixels.
    psf_e1, psf_e2 : float
        PSF ellipticity, pixel frame.
    noise_sigma : float
        Noise per pixel, counts.
    zero_point : float
        Photometric zero point (``MAGZP``).
    noise_seed, star_seed : int
        Seeds of the noise and of the star field.
    """

    index: int
    offset_w: float
    offset_n: float
    phase_x: float
    phase_y: float
    rotation: float
    flip: bool
    pixel_scale: float
    psf_fwhm: float
    psf_e1: float
    psf_e2: float
    noise_sigma: float
    zero_point: float
    noise_seed: int
    star_seed: int

    @property
    def file(self) -> str:
        """The exposure's file name."""
        return f"exp{self.index}.fits"

    @property
    def star_file(self) -> str:
        """Its star field's file name."""
        return f"exp{self.index}_stars.fits"


def dither_exposures(spec: DitherSpec, rng: np.random.Generator) -> tuple[DitherExposure, ...]:
    """Draw every exposure's pointing, WCS, PSF, noise, zero point and seeds.

    Parameters
    ----------
    spec : DitherSpec
        The set.
    rng : numpy.random.Generator
        The set's generator (drawn from in a fixed order).

    Returns
    -------
    tuple of DitherExposure
        ``spec.n_exposures`` exposures.
    """
    K = spec.n_exposures
    u = lambda: rng.uniform(-1.0, 1.0, K)  # noqa: E731
    off_w, off_n, rotation, scale, seeing, noise = u(), u(), u(), u(), u(), u()
    phase = rng.uniform(0.0, 1.0, (K, 2))
    e = np.sqrt(rng.uniform(0.0, 1.0, K)) * spec.psf_e_max * np.exp(2j * np.pi * rng.random(K))
    flip = np.zeros(K, bool)
    flip[rng.permutation(K)[: round(spec.flip_fraction * K)]] = True
    zp = spec.zero_point + spec.zero_point_spread * u()
    seeds = rng.integers(1, 2**31 - 1, (K, 2))
    return tuple(DitherExposure(
        index=k, offset_w=float(spec.dither * off_w[k]), offset_n=float(spec.dither * off_n[k]),
        phase_x=float(phase[k, 0]), phase_y=float(phase[k, 1]),
        rotation=float(spec.rotation_max * rotation[k]), flip=bool(flip[k]),
        pixel_scale=float(spec.pixel_scale * (1 + spec.scale_spread * scale[k])),
        psf_fwhm=float(spec.psf_fwhm * (1 + spec.seeing_spread * seeing[k])),
        psf_e1=float(e[k].real), psf_e2=float(e[k].imag),
        noise_sigma=float(spec.noise_sigma * (1 + 0.1 * noise[k])), zero_point=float(zp[k]),
        noise_seed=int(seeds[k, 0]), star_seed=int(seeds[k, 1]),
    ) for k in range(K))  # fmt: skip


def exposure_wcs(spec: DitherSpec, exp: DitherExposure) -> WCS:
    """An exposure's TAN WCS: ``CD = s diag(-1, 1) Rot(theta) F`` at its pointing.

    Parameters
    ----------
    spec : DitherSpec
        The set (its centre and image size).
    exp : DitherExposure
        The exposure.

    Returns
    -------
    astropy.wcs.WCS
        The reference pixel is the image's centre plus the sub-pixel phase, at the
        pointing.
    """
    ra, dec = sky_offsets_to_world(spec.ra0, spec.dec0, exp.offset_w, exp.offset_n)
    t = np.radians(exp.rotation)
    rot = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [float(ra), float(dec)]
    n = spec.image_size
    w.wcs.crpix = [n / 2 + 0.5 + exp.phase_x, n / 2 + 0.5 + exp.phase_y]
    flip = np.diag([1.0, -1.0 if exp.flip else 1.0])
    w.wcs.cd = exp.pixel_scale / 3600.0 * np.diag([-1.0, 1.0]) @ rot @ flip
    return w


def dither_galaxies(spec: DitherSpec, rng: np.random.Generator) -> Table:
    """The galaxies on the sky: positions, kinds, sizes, shapes, shear, fluxes.

    Parameters
    ----------
    spec : DitherSpec
        The set.
    rng : numpy.random.Generator
        The set's generator.

    Returns
    -------
    astropy.table.Table
        ``id``, ``ra, dec`` (degrees), ``model``, ``r`` (arcsec), ``snr`` (in a nominal
        exposure), ``flux`` (the common unit: counts at ``spec.zero_point``),
        ``e1_int, e2_int`` (intrinsic), ``e1, e2`` (sheared), ``g1, g2`` (the shear),
        all in the sky frame.
    """
    m = spec.lattice_side
    grid = (np.arange(m) - (m - 1) / 2) * spec.spacing
    gw, gn = (a.ravel()[: spec.ngal] for a in np.meshgrid(grid, grid))
    gw = gw + rng.uniform(-spec.jitter, spec.jitter, gw.size)
    gn = gn + rng.uniform(-spec.jitter, spec.jitter, gn.size)
    ra, dec = sky_offsets_to_world(spec.ra0, spec.dec0, gw, gn)
    n = gw.size
    r = rng.uniform(*spec.size_range, n)
    snr = np.exp(rng.uniform(*np.log(spec.snr_range), n))
    prior = Prior(B=spec.prior_params[0], C=spec.prior_params[1], D=spec.prior_params[2])
    e_int = draw_shapes(prior, n, rng, spec.max_e)
    e1, e2 = apply_shear(e_int[:, 0], e_int[:, 1], spec.g1, spec.g2)
    kinds = [MIXED_KINDS[i % len(MIXED_KINDS)] if spec.model == "mixed" else spec.model
             for i in range(n)]  # fmt: skip
    truth = Table()
    truth["id"] = np.arange(n)
    truth["ra"], truth["dec"] = ra, dec
    truth["model"] = kinds
    truth["r"] = r
    truth["snr"] = snr
    truth["flux"] = _fluxes(spec, kinds, r, e_int, snr)
    truth["e1_int"], truth["e2_int"] = e_int[:, 0], e_int[:, 1]
    truth["e1"], truth["e2"] = e1, e2
    truth["g1"], truth["g2"] = np.full(n, spec.g1), np.full(n, spec.g2)
    truth.meta.update({"g1": spec.g1, "g2": spec.g2, "nexp": spec.n_exposures})
    return truth


def _fluxes(spec: DitherSpec, kinds, r, e_int, snr) -> np.ndarray:
    """Each galaxy's flux from its S/N in a nominal exposure (unlensed, round PSF)."""
    import galsim  # galsim: heavy import, only for rendering

    psf = PSFProfile("moffat", spec.psf_fwhm, spec.psf_beta).galsim()
    out = np.empty(len(kinds))
    for i, kind in enumerate(kinds):  # rendering is GalSim's, one object at a time
        gal = galaxy_profile(kind, r[i] / spec.pixel_scale).shear(g1=e_int[i, 0], g2=e_int[i, 1])
        arr = galsim.Convolve(gal, psf).drawImage(nx=spec.stamp, ny=spec.stamp, scale=1.0).array
        out[i] = snr[i] * spec.noise_sigma / np.sqrt((arr**2).sum())
    return out


def _gap(spec: DitherSpec) -> slice:
    """The chip gap's columns."""
    c = spec.image_size // 2
    return slice(c - spec.gap // 2, c - spec.gap // 2 + spec.gap)


def render_exposure(
    spec: DitherSpec, exp: DitherExposure, truth: Table
) -> tuple[np.ndarray, np.ndarray, Table]:
    """Render the galaxies of ``truth`` in one exposure with GalSim.

    Each galaxy's sky-frame profile (arcsec) is carried into the exposure's pixels by
    GalSim's local WCS at the galaxy (``galsim.FitsWCS`` of :func:`exposure_wcs`),
    convolved with the exposure's PSF (pixel frame) and drawn at its position.

    Parameters
    ----------
    spec : DitherSpec
        The set.
    exp : DitherExposure
        The exposure.
    truth : astropy.table.Table
        :func:`dither_galaxies`'s table.

    Returns
    -------
    image : numpy.ndarray
        ``(n, n)`` float32, counts, sky and noise included, 0 in the chip gap.
    weight : numpy.ndarray
        Inverse variance, 0 in the chip gap.
    positions : astropy.table.Table
        ``id``, ``x, y`` (0-based pixels through the WCS), ``on_data`` (the centre's
        pixel is on the image and not in the gap).
    """
    import galsim  # galsim: heavy import, only for rendering

    n = spec.image_size
    w = exposure_wcs(spec, exp)
    gw = galsim.FitsWCS(header=galsim.FitsHeader(header=w.to_header()))
    x, y = sky_to_pixel(w, truth["ra"], truth["dec"])
    psf = PSFProfile("moffat", exp.psf_fwhm, spec.psf_beta, exp.psf_e1, exp.psf_e2).galsim()
    counts = np.asarray(truth["flux"]) * flux_scale_from_zero_point(exp.zero_point,
                                                                     spec.zero_point)  # fmt: skip
    image = galsim.ImageF(n, n, scale=1.0)  # bounds 1..n: numpy (x, y) is galsim (x+1, y+1)
    for i in range(len(truth)):  # rendering is GalSim's, one object at a time
        pos = galsim.PositionD(x[i] + 1.0, y[i] + 1.0)
        local = gw.local(image_pos=pos)
        gal = galaxy_profile(str(truth["model"][i]), float(truth["r"][i]))
        gal = gal.shear(g1=float(truth["e1_int"][i]), g2=float(truth["e2_int"][i]))
        gal = gal.shear(g1=spec.g1, g2=spec.g2).withFlux(float(counts[i]))
        obj = galsim.Convolve(local.toImage(gal), psf)
        stamp = obj.drawImage(nx=spec.stamp, ny=spec.stamp, scale=1.0, center=pos)
        b = stamp.bounds & image.bounds
        if b.isDefined():
            image[b] += stamp[b]
    rng = np.random.default_rng(exp.noise_seed)
    arr = image.array.astype(np.float64) + spec.sky + rng.normal(scale=exp.noise_sigma,
                                                                  size=(n, n))  # fmt: skip
    weight = np.full((n, n), 1.0 / exp.noise_sigma**2)
    gap = _gap(spec)
    arr[:, gap], weight[:, gap] = 0.0, 0.0
    ix, iy = (np.rint(np.nan_to_num(a, nan=-1.0)).astype(int) for a in (x, y))
    on = (ix >= 0) & (ix < n) & (iy >= 0) & (iy < n)
    on &= ~((ix >= gap.start) & (ix < gap.stop))
    pos = Table({"id": np.asarray(truth["id"]), "x": x, "y": y, "on_data": on})
    return arr.astype(np.float32), weight.astype(np.float32), pos


def _write_exposure(path: Path, spec: DitherSpec, exp: DitherExposure, image: np.ndarray,
                    weight: np.ndarray, positions: Table) -> None:  # fmt: skip
    """Write one exposure: the image with its WCS header, ``WEIGHT`` and ``TRUTH``."""
    hdr = exposure_wcs(spec, exp).to_header()
    hdr["MAGZP"] = (exp.zero_point, "zero point: magnitude of one count")
    hdr["GAIN"] = (0.0, "no Poisson noise: background-limited simulation")
    hdr["SKYLEVEL"] = (spec.sky, "sky level, counts")
    hdr["SIMG1"] = (spec.g1, "input reduced shear g1 (sky frame: W, N)")
    hdr["SIMG2"] = (spec.g2, "input reduced shear g2 (sky frame: W, N)")
    hdr["SIMROT"] = (exp.rotation, "[deg] WCS rotation theta, pixel to sky")
    hdr["SIMFLIP"] = (exp.flip, "WCS flipped: dy -> -dy before the rotation")
    hdr["SIMSCALE"] = (exp.pixel_scale, "[arcsec] pixel scale")
    hdr["SIMFWHM"] = (exp.psf_fwhm, "[px] PSF Moffat FWHM")
    hdr["SIMPSFE1"] = (exp.psf_e1, "PSF e1 (pixel frame)")
    hdr["SIMPSFE2"] = (exp.psf_e2, "PSF e2 (pixel frame)")
    hdus = [fits.PrimaryHDU(image, header=hdr), fits.ImageHDU(weight, name="WEIGHT"),
            fits.BinTableHDU(positions, name="TRUTH")]  # fmt: skip
    atomic_write(fits.HDUList(hdus), path, overwrite=True)


def _write_star_field(path: Path, spec: DitherSpec, exp: DitherExposure) -> None:
    """The exposure's star field: its PSF, pixel scale, WCS orientation and noise."""
    fspec = FieldSpec(size=spec.star_field_size, star_fraction=1.0, psf_fwhm=exp.psf_fwhm,
                      psf_beta=spec.psf_beta, psf_e1=exp.psf_e1, psf_e2=exp.psf_e2,
                      noise_sigma=exp.noise_sigma, sky=spec.sky,
                      pixel_scale_arcsec=exp.pixel_scale, wcs_rotation_deg=exp.rotation,
                      wcs_flip=exp.flip)  # fmt: skip
    img, w, truth = simulate_field(fspec, seed=exp.star_seed)
    ra, dec = sky_offsets_to_world(spec.ra0, spec.dec0, exp.offset_w, exp.offset_n)
    write_field(path, img, w, fspec, ra0=float(ra), dec0=float(dec), truth=truth)


def simulate_dither(out: str | Path, spec: DitherSpec | None = None, *, seed: int = 1) -> Path:
    """Simulate a dithered set with GalSim and write it (module docstring).

    Parameters
    ----------
    out : str or pathlib.Path
        Output directory (created).
    spec : DitherSpec, optional
        What to simulate (default ``DitherSpec()``).
    seed : int
        Seed of everything: the galaxies first, then the exposures (so that sets of
        different ``n_exposures`` from one seed share their galaxies).

    Returns
    -------
    pathlib.Path
        The directory.
    """
    spec = spec or DitherSpec()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    truth = dither_galaxies(spec, np.random.default_rng([seed, 0]))
    exposures = dither_exposures(spec, np.random.default_rng([seed, 1]))
    for exp in exposures:
        image, weight, positions = render_exposure(spec, exp, truth)
        _write_exposure(out / exp.file, spec, exp, image, weight, positions)
        _write_star_field(out / exp.star_file, spec, exp)
    truth.meta["seed"] = seed
    atomic_write(fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU(truth, name="TRUTH")]),
                 out / "truth.fits", overwrite=True)  # fmt: skip
    manifest = {"kind": "dither", "seed": seed, "image_size": spec.image_size,
                "spec": asdict(spec), "truth": "truth.fits",
                "exposures": [asdict(e) | {"file": e.file, "star_file": e.star_file}
                              for e in exposures]}  # fmt: skip
    with open(out / "manifest.json", "w") as fh:
        json.dump(manifest, fh, indent=1)
    return out


@dataclass(frozen=True)
class DitherSet:
    """A dithered set read back (:func:`read_dither`).

    Attributes
    ----------
    directory : pathlib.Path
        Its directory.
    spec : DitherSpec
        What was simulated.
    seed : int
        Its seed.
    exposures : tuple of DitherExposure
        The exposures, in order.
    truth : astropy.table.Table
        The galaxies in sky coordinates (:func:`dither_galaxies`).
    """

    directory: Path
    spec: DitherSpec
    seed: int
    exposures: tuple[DitherExposure, ...]
    truth: Table

    def path(self, k: int) -> Path:
        """Exposure ``k``'s file."""
        return self.directory / self.exposures[k].file

    def star_path(self, k: int) -> Path:
        """Exposure ``k``'s star field."""
        return self.directory / self.exposures[k].star_file


def read_dither(directory: str | Path) -> DitherSet:
    """Read the manifest and the truth of a set written by :func:`simulate_dither`.

    Parameters
    ----------
    directory : str or pathlib.Path
        The set's directory.

    Returns
    -------
    DitherSet
        The set.
    """
    directory = Path(directory)
    with open(directory / "manifest.json") as fh:
        man = json.load(fh)
    sp = man["spec"]
    spec = DitherSpec(**{k: tuple(v) if isinstance(v, list) else v for k, v in sp.items()})
    names = {f.name for f in DitherExposure.__dataclass_fields__.values()}
    exposures = tuple(DitherExposure(**{k: v for k, v in e.items() if k in names})
                      for e in man["exposures"])  # fmt: skip
    truth = Table.read(directory / man["truth"], hdu="TRUTH")
    return DitherSet(directory=directory, spec=spec, seed=int(man["seed"]),
                     exposures=exposures, truth=truth)  # fmt: skip
