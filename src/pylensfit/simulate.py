"""Simulated fields with GalSim: sheared galaxies, stars, noise, weight maps and truth.

The demo and the tests of the pipeline use these fields; the STEP-like validation sets
(issue 5) build on them. Conventions: pixel coordinates are 0-based with pixel centres
on integers (``x`` indexes columns); the ellipticity ``e = (a - b) / (a + b)`` is
GalSim's reduced-shear ``g`` of the profile, and a shear ``g`` maps an intrinsic
ellipticity ``e_s`` to ``(e_s + g) / (1 + g* e_s)`` exactly (GalSim composes the two
shears).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS

from .catalogue import atomic_write
from .models import DEVAUC_TRUNCATION
from .prior import Prior
from .shear import apply_shear

__all__ = [
    "MIXED_KINDS",
    "FieldSpec",
    "add_object",
    "add_sky_and_noise",
    "draw_population",
    "draw_shapes",
    "field_psf",
    "galaxy_profile",
    "lensed_shapes",
    "simulate_field",
    "truth_table",
    "write_field",
]


@dataclass(frozen=True)
class FieldSpec:
    """What to put in a simulated field (pixels as units unless said otherwise).

    Objects sit on a jittered square lattice of pitch ``spacing`` (so that close pairs
    are the exception the pipeline flags, not the rule), a fraction ``star_fraction`` of
    them stars. ``noise_sign = -1`` adds the noise field of the same noise seed negated:
    the field's noise twin, whose first-order noise response cancels the original's.
    """

    size: int = 1024
    spacing: float = 40.0
    jitter: float = 6.0
    g1: float = 0.0
    g2: float = 0.0
    rotate: bool = False
    model: str = "exponential"  # or "devaucouleurs", "bulge+disc", "mixed" (MIXED_KINDS)
    psf_fwhm: float = 3.0
    psf_beta: float = 3.5
    psf_e1: float = 0.03
    psf_e2: float = -0.02
    noise_sigma: float = 1.0
    sky: float = 50.0
    snr_range: tuple[float, float] = (15.0, 150.0)
    size_range: tuple[float, float] = (1.2, 3.5)
    star_fraction: float = 0.08
    star_peak_snr: tuple[float, float] = (40.0, 1000.0)
    prior_params: tuple[float, float, float] = (0.19, 0.58, 2.4)
    max_e: float = 0.99  # a cut below ~0.95 takes the truth out of the functional form
    pixel_scale_arcsec: float = 0.2
    noise_sign: float = 1.0
    extra: dict = field(default_factory=dict)


def field_psf(spec: FieldSpec):
    """The PSF of a simulated field: a sheared Moffat profile (no pixel response).

    Parameters
    ----------
    spec : FieldSpec
        Its ``psf_beta``, ``psf_fwhm`` (pixels), ``psf_e1`` and ``psf_e2``.

    Returns
    -------
    galsim.GSObject
        The profile, to convolve with and to draw with GalSim's pixel.
    """
    import galsim  # galsim: heavy import, only for rendering

    return galsim.Moffat(beta=spec.psf_beta, fwhm=spec.psf_fwhm).shear(
        g1=spec.psf_e1, g2=spec.psf_e2
    )


#: the kinds of ``FieldSpec(model="mixed")``, taken in turn object by object
MIXED_KINDS = ("exponential", "devaucouleurs", "bulge+disc")


def galaxy_profile(model: str, r: float, index: int = 0):
    """The round, unit-flux GalSim profile of a simulated galaxy of size ``r``.

    Parameters
    ----------
    model : {"exponential", "devaucouleurs", "bulge+disc", "mixed"}
        The profile (:attr:`FieldSpec.model`); ``"mixed"`` takes the kinds of
        :data:`MIXED_KINDS` in turn by ``index``.
    r : float
        Size in pixels, as the model bank's (:mod:`pylensfit.models`): the exponential's
        scale length, the de Vaucouleurs half-light radius (truncated at
        :data:`~pylensfit.models.DEVAUC_TRUNCATION` of them), the bulge+disc's disc
        scale length (bulge half-light radius ``0.6 r``, half the flux each).
    index : int
        The object's index, for ``model="mixed"``.

    Returns
    -------
    galsim.GSObject
        The profile, before any shear and the PSF.

    Raises
    ------
    ValueError
        For an unknown ``model``.
    """
    import galsim  # galsim: heavy import, only for rendering

    if model == "mixed":
        model = MIXED_KINDS[index % len(MIXED_KINDS)]
    T = DEVAUC_TRUNCATION

    if model == "exponential":
        return galsim.Exponential(scale_radius=r)
    if model == "devaucouleurs":
        return galsim.DeVaucouleurs(half_light_radius=r, trunc=T * r)
    if model == "bulge+disc":
        rb = 0.6 * r
        return galsim.Add(
            galsim.DeVaucouleurs(half_light_radius=rb, trunc=T * rb).withFlux(0.5),
            galsim.Exponential(scale_radius=r).withFlux(0.5),
        )
    raise ValueError(f"unknown model {model!r}")


def draw_population(spec: FieldSpec, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """Positions on the jittered lattice, star flags, sizes, S/N and intrinsic shapes.

    Returns ``x, y, is_star, r, snr, star_peak_snr, e_int`` (``e_int`` drawn from the
    functional prior with ``spec.prior_params``, ``|e| <= spec.max_e``).
    """
    n = int(spec.size)
    m = int((n - 2 * spec.spacing) // spec.spacing) + 1
    grid = spec.spacing + spec.spacing * np.arange(m)
    xx, yy = np.meshgrid(grid, grid)
    x = xx.ravel() + rng.uniform(-spec.jitter, spec.jitter, xx.size)
    y = yy.ravel() + rng.uniform(-spec.jitter, spec.jitter, yy.size)
    n_obj = x.size
    is_star = rng.random(n_obj) < spec.star_fraction
    r = rng.uniform(*spec.size_range, n_obj)
    snr = np.exp(rng.uniform(*np.log(spec.snr_range), n_obj))
    star_snr = np.exp(rng.uniform(*np.log(spec.star_peak_snr), n_obj))
    prior = Prior(B=spec.prior_params[0], C=spec.prior_params[1], D=spec.prior_params[2])
    e_int = draw_shapes(prior, n_obj, rng, spec.max_e)
    return x, y, is_star, r, snr, star_snr, e_int


def draw_shapes(prior: Prior, n: int, rng: np.random.Generator, e_max: float) -> np.ndarray:
    """``(n, 2)`` ellipticities from ``prior``, redrawn where ``|e| > e_max``."""
    e = prior.sample(n, rng=rng)
    big = np.hypot(*e.T) > e_max
    while np.any(big):
        e[big] = prior.sample(int(big.sum()), rng=rng)
        big = np.hypot(*e.T) > e_max
    return e


def lensed_shapes(
    spec: FieldSpec, e_int: np.ndarray, is_star: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Intrinsic shapes (flipped for a 90-degree twin) and their sheared values (complex).

    Parameters
    ----------
    spec : FieldSpec
        The shear ``g1, g2`` and whether the field is the rotated twin (``rotate``).
    e_int : numpy.ndarray
        ``(n, 2)`` intrinsic ellipticities as drawn.
    is_star : numpy.ndarray
        ``(n,)`` star flags: stars get ``e_obs = 0``.

    Returns
    -------
    e_int : numpy.ndarray
        ``(n, 2)`` intrinsic ellipticities, negated for a rotated twin.
    e_obs : numpy.ndarray
        ``(n,)`` complex sheared ellipticities ``e1 + i e2``.
    """
    if spec.rotate:
        e_int = -e_int  # a 90-degree rotation of an ellipse flips e
    e1, e2 = apply_shear(e_int[:, 0], e_int[:, 1], spec.g1, spec.g2)
    e_obs = e1 + 1j * e2
    e_obs[is_star] = 0.0
    return e_int, e_obs


def add_object(image, obj, flux: float, x: float, y: float, size: int = 64) -> None:
    """Draw ``obj`` with ``flux`` centred at 0-based ``(x, y)`` and add it to ``image``.

    Parameters
    ----------
    image : galsim.Image
        The field, bounds ``1..n`` (numpy ``(x, y)`` is GalSim's ``(x + 1, y + 1)``);
        changed in place.
    obj : galsim.GSObject
        The object, PSF included.
    flux : float
        Its total flux.
    x, y : float
        Its centre in 0-based pixel coordinates.
    size : int
        Side of the stamp it is drawn on; what falls outside ``image`` is dropped.
    """
    import galsim  # galsim: heavy import, only for rendering

    stamp = obj.withFlux(flux).drawImage(
        nx=size, ny=size, scale=1.0, center=galsim.PositionD(x + 1.0, y + 1.0)
    )
    b = stamp.bounds & image.bounds
    if b.isDefined():
        image[b] += stamp[b]


def add_sky_and_noise(
    image, spec: FieldSpec, seed: int, noise_seed: int | None
) -> tuple[np.ndarray, np.ndarray]:
    """The rendered image plus sky and Gaussian noise (float32), and its weight map.

    Parameters
    ----------
    image : galsim.Image
        The noise-free field.
    spec : FieldSpec
        Its ``sky``, ``noise_sigma`` and ``noise_sign`` (-1: the noise negated, the
        field's noise twin).
    seed : int
        The field's seed: the noise's when ``noise_seed`` is ``None``.
    noise_seed : int, optional
        Seed of the noise.

    Returns
    -------
    image : numpy.ndarray
        The field with sky and noise, float32.
    weight : numpy.ndarray
        Inverse-variance map ``1 / noise_sigma^2``, float32.
    """
    arr = image.array.astype(np.float64)
    noise_rng = np.random.default_rng([seed, 1] if noise_seed is None else noise_seed)
    noise = noise_rng.normal(scale=spec.noise_sigma, size=arr.shape)
    arr += spec.sky + (-noise if spec.noise_sign < 0 else noise)
    weight = np.full(arr.shape, 1.0 / spec.noise_sigma**2, dtype=np.float32)
    return arr.astype(np.float32), weight


def truth_table(x, y, is_star, flux, r, e_int, e_obs, snr) -> Table:
    """The truth columns shared by every simulated field (stars have e = 0, r = 0).

    Parameters
    ----------
    x, y : numpy.ndarray
        0-based pixel positions.
    is_star : numpy.ndarray
        Star flags.
    flux : numpy.ndarray
        Total fluxes.
    r : numpy.ndarray
        Sizes (pixels).
    e_int : numpy.ndarray
        ``(n, 2)`` intrinsic ellipticities.
    e_obs : numpy.ndarray
        ``(n,)`` complex sheared ellipticities.
    snr : numpy.ndarray
        Matched-filter S/N of each galaxy.

    Returns
    -------
    astropy.table.Table
        Columns ``x, y, is_star, flux, r, e1_int, e2_int, e1, e2, snr`` (``snr`` NaN
        for stars), as :func:`simulate_field`'s truth.
    """
    truth = Table()
    truth["x"] = x
    truth["y"] = y
    truth["is_star"] = is_star
    truth["flux"] = flux
    truth["r"] = np.where(is_star, 0.0, r)
    truth["e1_int"] = np.where(is_star, 0.0, e_int[:, 0])
    truth["e2_int"] = np.where(is_star, 0.0, e_int[:, 1])
    truth["e1"] = e_obs.real
    truth["e2"] = e_obs.imag
    truth["snr"] = np.where(is_star, np.nan, snr)
    return truth


def simulate_field(
    spec: FieldSpec, *, seed: int, noise_seed: int | None = None
) -> tuple[np.ndarray, np.ndarray, Table]:
    """Render a field of sheared galaxies and stars with GalSim.

    Parameters
    ----------
    spec : FieldSpec
        What to simulate.
    seed : int
        Seed of the objects (positions, shapes, sizes, fluxes). A field with the same
        seed and ``spec.rotate=True`` is the 90-degree-rotated twin: the same objects,
        each galaxy rotated before the shear.
    noise_seed : int, optional
        Seed of the noise (default: derived from ``seed``).

    Returns
    -------
    image : numpy.ndarray
        ``(size, size)`` float32, sky included (``spec.sky``), with Gaussian noise.
    weight : numpy.ndarray
        Inverse-variance map, ``1 / noise_sigma^2``.
    truth : astropy.table.Table
        One row per object: ``x, y`` (0-based pixels), ``is_star``, ``flux``, ``r`` (scale
        length or half-light radius, px), ``e1_int, e2_int`` (intrinsic), ``e1, e2``
        (sheared), ``snr`` (matched-filter S/N of the noise-free object before lensing).
    """
    import galsim  # galsim: heavy import, only for rendering

    rng = np.random.default_rng(seed)
    n = int(spec.size)
    x, y, is_star, r, snr, star_snr, e_int = draw_population(spec, rng)
    n_obj = x.size
    e_int, e_obs = lensed_shapes(spec, e_int, is_star)

    psf = field_psf(spec)
    image = galsim.ImageF(n, n, scale=1.0)  # bounds 1..n: numpy (x, y) is galsim (x+1, y+1)
    flux = np.empty(n_obj)
    unit_psf = psf.drawImage(nx=64, ny=64, scale=1.0).array
    psf_peak = unit_psf.max()
    for i in range(n_obj):  # rendering is GalSim's, one object at a time
        if is_star[i]:
            obj = psf
            flux[i] = star_snr[i] * spec.noise_sigma / psf_peak  # peak S/N as drawn
        else:
            gal = galaxy_profile(spec.model, r[i], i).shear(g1=e_int[i, 0], g2=e_int[i, 1])
            obj = galsim.Convolve(gal.shear(g1=spec.g1, g2=spec.g2), psf)
            # the flux from the S/N of the unlensed, unrotated galaxy: lensing keeps the
            # flux, and a rotated twin gets the same flux as its original
            e0 = -e_int[i] if spec.rotate else e_int[i]
            ref = galsim.Convolve(galaxy_profile(spec.model, r[i], i).shear(g1=e0[0], g2=e0[1]),
                                  psf)  # fmt: skip
            arr = ref.drawImage(nx=64, ny=64, scale=1.0).array
            flux[i] = snr[i] * spec.noise_sigma / np.sqrt((arr**2).sum())
        add_object(image, obj, flux[i], x[i], y[i])
    image, weight = add_sky_and_noise(image, spec, seed, noise_seed)
    truth = truth_table(x, y, is_star, flux, r, e_int, e_obs, snr)
    truth.meta.update(
        {"g1": spec.g1, "g2": spec.g2, "model": spec.model, "noise": spec.noise_sigma,
         "psf_fwhm": spec.psf_fwhm, "psf_e1": spec.psf_e1, "psf_e2": spec.psf_e2,
         "seed": seed}
    )  # fmt: skip
    return image, weight, truth


def _wcs(spec: FieldSpec, ra0: float, dec0: float) -> WCS:
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [ra0, dec0]
    w.wcs.crpix = [spec.size / 2 + 0.5, spec.size / 2 + 0.5]
    s = spec.pixel_scale_arcsec / 3600.0
    w.wcs.cd = [[-s, 0.0], [0.0, s]]
    return w


def write_field(
    path,
    image: np.ndarray,
    weight: np.ndarray | None,
    spec: FieldSpec,
    *,
    ra0: float = 150.0,
    dec0: float = 2.0,
    truth: Table | None = None,
) -> None:
    """Write a simulated field as FITS: the image (with a TAN WCS) and a ``WEIGHT`` HDU.

    The truth table, if given, goes to a ``TRUTH`` extension, which the pipeline ignores.
    """
    hdr = _wcs(spec, ra0, dec0).to_header()
    hdr["GAIN"] = (0.0, "no Poisson noise: background-limited simulation")
    hdr["SIMG1"] = (spec.g1, "input reduced shear g1")
    hdr["SIMG2"] = (spec.g2, "input reduced shear g2")
    hdus = [fits.PrimaryHDU(image, header=hdr)]
    if weight is not None:
        hdus.append(fits.ImageHDU(weight, name="WEIGHT"))
    if truth is not None:
        hdus.append(fits.BinTableHDU(truth, name="TRUTH"))
    atomic_write(fits.HDUList(hdus), path, overwrite=True)
