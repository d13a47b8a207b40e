"""Simulated fields with GalSim: sheared galaxies, stars, noise, weight maps and truth.

The demo and the tests of the pipeline use these fields; the STEP-like validation sets
(issue 5) build on them. Conventions: pixel coordinates are 0-based with pixel centres
on integers (``x`` indexes columns); the ellipticity ``e = (a - b) / (a + b)`` is
GalSim's reduced-shear ``g`` of the profile, and a shear ``g`` maps an intrinsic
ellipticity ``e_s`` to ``(e_s + g) / (1 + g* e_s)`` exactly (GalSim composes the two
shears).

Sky frame (as TreeCorr's for RA/Dec catalogues): the local axes ``(W, N)``, north up and
west to the right; a shear is positive real when elongated east-west and positive
imaginary along NW-SE. Pixel offsets map to it as ``(dW, dN) = s Rot(theta) F (dx, dy)``
with ``Rot(theta) = [[cos, -sin], [sin, cos]]``, ``F = diag(1, -1)`` for a flipped field
(else the identity) and ``s`` the pixel scale; the FITS ``CD`` matrix, which gives
``(dRA cos(dec), dDec) = (-dW, dN)``, is ``s diag(-1, 1) Rot(theta) F``. With
``theta = 0`` and no flip the pixel frame is the sky frame. An ellipticity (or shear)
maps as ``e_sky = e_pix exp(2i theta)``, or ``conj(e_pix) exp(2i theta)`` when flipped
(:func:`pixel_to_sky_shear`, :func:`sky_to_pixel_shear`). The PSF is a property of the
image: its parameters are in the pixel frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS
from scipy.interpolate import RectBivariateSpline

from pylensfit.catalogue import atomic_write
from pylensfit.prior import Prior
from pylensfit.shear import apply_shear

from .galaxies import GalaxyProfile, PSFProfile

__all__ = [
    "MIXED_KINDS",
    "POPULATIONS",
    "PSF_VARIATIONS",
    "FieldSpec",
    "PSFMap",
    "add_object",
    "add_psf_and_sky_truth",
    "add_sky_and_noise",
    "draw_population",
    "draw_shapes",
    "field_meta",
    "field_psf",
    "galaxy_profile",
    "lensed_shapes",
    "local_psfs",
    "map_psf_model",
    "normalised_position",
    "pixel_shear",
    "pixel_to_sky_shear",
    "psf_at",
    "psf_map",
    "psf_observed_moments",
    "simulate_field",
    "sky_to_pixel_shear",
    "star_peaks",
    "to_pixel_frame",
    "truth_table",
    "write_field",
]


#: The PSF variations of :attr:`FieldSpec.psf_variation`, as ``(fwhm_gradient,
#: e_quadratic)`` of :class:`PSFMap`: ``"none"`` one PSF over the field, ``"survey"``
#: gradients of a survey's size (FWHM +-10 % corner to corner, |e| up to 0.08 in the
#: corners about the centre's).
PSF_VARIATIONS: dict[str, tuple[float, float]] = {"none": (0.0, 0.0), "survey": (0.1, 0.04)}

#: The galaxy populations of :attr:`FieldSpec.population` (STEP2-like fields,
#: :func:`pylensfit_validation.validation.render_step2_field`; ranges in
#: :data:`pylensfit_validation.galaxies.REALISTIC`).
POPULATIONS: tuple[str, ...] = ("aligned", "realistic")


@dataclass(frozen=True)
class FieldSpec:
    """What to put in a simulated field (pixels as units unless said otherwise).

    Objects sit on a jittered square lattice of pitch ``spacing`` (so that close pairs
    are the exception the pipeline flags, not the rule), a fraction ``star_fraction`` of
    them stars. ``noise_sign = -1`` adds the noise field of the same noise seed negated:
    the field's noise twin, whose first-order noise response cancels the original's.

    ``g1, g2`` are the shear in the sky frame (module docstring), which the WCS's
    ``wcs_rotation_deg`` (degrees, ``theta``) and ``wcs_flip`` relate to the pixel frame.
    ``psf_fwhm, psf_beta, psf_e1, psf_e2`` are the PSF at the field's centre (pixel
    frame), ``psf_variation`` (a key of :data:`PSF_VARIATIONS`) how it varies over the
    field (:func:`psf_map`).

    ``population`` (one of :data:`POPULATIONS`) is that of the galaxies of a STEP2-like
    field (:func:`pylensfit_validation.validation.render_step2_field`): ``"aligned"``, every bulge
    aligned with its disc, or ``"realistic"``, bulges of their own size and shape
    (:data:`pylensfit_validation.galaxies.REALISTIC`). :func:`simulate_field` ignores it: its
    galaxies are the model bank's families.

    ``shear_positions`` shears the positions too, about the field's centre, with the shear
    of the galaxies' shapes: the lensing map of a galaxy's neighbours. Without it the
    lattice is the same at every shear, which no lensed sky does: its neighbours do not
    move against a galaxy, so the light they leave in its stamp does not change with the
    shear as a lensed sky's does (both estimators' m1 moves by -0.03 to -0.05 on
    STEP1-like fields, ``benchmarks/survey_cli.py --shear-positions --paired-with``).
    The stars move with the lattice (their shapes stay the PSF's): left
    in place, the galaxies moved by up to ``|g|`` times their distance from the centre
    would land on them at some shears and not at others.
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
    psf_variation: str = "none"
    wcs_rotation_deg: float = 0.0
    wcs_flip: bool = False
    population: str = "aligned"
    shear_positions: bool = False
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.psf_variation not in PSF_VARIATIONS:
            raise ValueError(
                f"psf_variation must be one of {sorted(PSF_VARIATIONS)}, "
                f"not {self.psf_variation!r}"
            )
        if self.population not in POPULATIONS:
            raise ValueError(f"population must be one of {POPULATIONS}, not "
                             f"{self.population!r}")  # fmt: skip


@dataclass(frozen=True)
class PSFMap:
    """A Moffat PSF whose FWHM and ellipticity vary smoothly over a field.

    In the normalised coordinates ``u, v`` of :func:`normalised_position` (``[-1, 1]``
    over the field, 0 at its centre)::

        fwhm(u, v) = fwhm * (1 + fwhm_gradient * (u + v) / 2)
        e1 + i e2 = (e1 + i e2)_centre + e_quadratic * (u + i v)**2

    ``e1, e2`` being GalSim's shear ``g`` of the profile in the pixel frame. With both
    coefficients zero the map is one PSF (:attr:`constant`).

    Attributes
    ----------
    fwhm : float
        FWHM at the centre (pixels).
    beta : float
        Moffat index, the same everywhere.
    e1, e2 : float
        Ellipticity at the centre.
    fwhm_gradient : float
        Fractional change of the FWHM per unit of ``(u + v) / 2``.
    e_quadratic : float
        Amplitude of the spin-2 term ``(u + i v)^2``: ``|e - e_centre|`` is
        ``e_quadratic`` on the edges' midpoints and twice that in the corners.
    """

    fwhm: float = 3.0
    beta: float = 3.5
    e1: float = 0.0
    e2: float = 0.0
    fwhm_gradient: float = 0.0
    e_quadratic: float = 0.0

    @property
    def constant(self) -> bool:
        """Whether the PSF is the same everywhere."""
        return self.fwhm_gradient == 0.0 and self.e_quadratic == 0.0

    def at(self, u, v) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The FWHM (pixels) and ellipticity ``e1, e2`` at normalised ``(u, v)``.

        Parameters
        ----------
        u, v : float or numpy.ndarray
            Normalised positions (broadcast together).

        Returns
        -------
        fwhm, e1, e2 : numpy.ndarray
            The Moffat parameters there, of the shape of ``u + v``.
        """
        u, v = np.broadcast_arrays(np.asarray(u, dtype=float), np.asarray(v, dtype=float))
        fwhm = self.fwhm * (1.0 + self.fwhm_gradient * (u + v) / 2.0)
        e = (self.e1 + 1j * self.e2) + self.e_quadratic * (u + 1j * v) ** 2
        return fwhm, e.real, e.imag

    def profile(self, u: float = 0.0, v: float = 0.0):
        """The GalSim Moffat profile at normalised ``(u, v)`` (no pixel response)."""
        if self.constant or (u == 0.0 and v == 0.0):
            return PSFProfile("moffat", self.fwhm, self.beta, self.e1, self.e2).galsim()
        fwhm, e1, e2 = self.at(u, v)
        return PSFProfile("moffat", float(fwhm), self.beta, float(e1), float(e2)).galsim()


def psf_map(spec: FieldSpec) -> PSFMap:
    """The PSF map of a field: its centre's PSF and :data:`PSF_VARIATIONS` of its kind.

    Parameters
    ----------
    spec : FieldSpec
        Its ``psf_fwhm`` (pixels), ``psf_beta``, ``psf_e1, psf_e2`` and ``psf_variation``.

    Returns
    -------
    PSFMap
        The map.
    """
    grad, quad = PSF_VARIATIONS[spec.psf_variation]
    return PSFMap(fwhm=spec.psf_fwhm, beta=spec.psf_beta, e1=spec.psf_e1, e2=spec.psf_e2,
                  fwhm_gradient=grad, e_quadratic=quad)  # fmt: skip


def normalised_position(spec: FieldSpec, x, y) -> tuple[np.ndarray, np.ndarray]:
    """``u = (x - c) / (size / 2)``, ``v = (y - c) / (size / 2)``, ``c = (size - 1) / 2``.

    Parameters
    ----------
    spec : FieldSpec
        The field (its ``size``, pixels).
    x, y : float or numpy.ndarray
        0-based pixel positions.

    Returns
    -------
    u, v : numpy.ndarray
        Normalised positions, in ``[-1, 1]`` over the field.
    """
    c = (spec.size - 1) / 2.0
    half = spec.size / 2.0
    return (np.asarray(x, dtype=float) - c) / half, (np.asarray(y, dtype=float) - c) / half


def psf_at(spec: FieldSpec, x, y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The PSF's Moffat FWHM (pixels) and ellipticity (pixel frame) at pixel ``(x, y)``.

    Parameters
    ----------
    spec : FieldSpec
        The field.
    x, y : float or numpy.ndarray
        0-based pixel positions (broadcast together).

    Returns
    -------
    fwhm, e1, e2 : numpy.ndarray
        The map's parameters there (:class:`PSFMap`); ``beta`` is ``spec.psf_beta``.
    """
    return psf_map(spec).at(*normalised_position(spec, x, y))


def field_psf(spec: FieldSpec, x: float | None = None, y: float | None = None):
    """The PSF of a simulated field at pixel ``(x, y)``: a sheared Moffat (no pixel).

    Parameters
    ----------
    spec : FieldSpec
        Its ``psf_beta``, ``psf_fwhm`` (pixels), ``psf_e1``, ``psf_e2`` and
        ``psf_variation``.
    x, y : float, optional
        0-based pixel position; default the field's centre, where the PSF is
        ``spec``'s own.

    Returns
    -------
    galsim.GSObject
        The profile, to convolve with and to draw with GalSim's pixel.
    """
    m = psf_map(spec)
    if x is None and y is None:
        return m.profile()
    u, v = normalised_position(spec, spec.size / 2 - 0.5 if x is None else x,
                               spec.size / 2 - 0.5 if y is None else y)  # fmt: skip
    return m.profile(float(u), float(v))


def local_psfs(spec: FieldSpec, x: np.ndarray, y: np.ndarray) -> list:
    """The PSF profile at each position: one shared object when the map is constant.

    Parameters
    ----------
    spec : FieldSpec
        The field.
    x, y : numpy.ndarray
        0-based pixel positions.

    Returns
    -------
    list of galsim.GSObject
        One profile per position (:func:`field_psf` there).
    """
    m = psf_map(spec)
    if m.constant:
        return [m.profile()] * len(x)
    fwhm, e1, e2 = psf_at(spec, x, y)
    return [PSFProfile("moffat", float(f), m.beta, float(a), float(b)).galsim()
            for f, a, b in zip(fwhm, e1, e2, strict=True)]  # fmt: skip


def map_psf_model(spec: FieldSpec, *, size: int = 64, order: int = 5, grid: int = 15):
    """A field's PSF map as a :class:`~pylensfit.psfmodel.PolynomialPSF`: the truth over
    the field, for fitting galaxies with their own PSF.

    The PSF is drawn noise-free with GalSim's pixel, centred on element
    ``[size//2, size//2]`` (as :func:`pylensfit_validation.validation.true_psf_image`), at the
    ``grid x grid`` positions of a square lattice spanning the field's pixel centres,
    and every pixel is fitted by least squares as a polynomial of total degree
    ``order`` in the field's normalised position. Under the ``"survey"`` map the
    model's adaptive-moment ellipticity and size are within 2e-5 of the truth's
    (:func:`psf_observed_moments`) over the field; a constant map gives the
    constant PSF (every term but the first zero to rounding).

    Parameters
    ----------
    spec : FieldSpec
        The field (its ``size``, pixels, and its PSF map, :func:`psf_map`).
    size : int
        Side of the PSF images in pixels.
    order : int
        Total degree of the polynomial.
    grid : int
        Positions per axis (``grid^2`` must exceed the polynomial's number of terms).

    Returns
    -------
    pylensfit.psfmodel.PolynomialPSF
        The model, bounds ``(0, spec.size - 1)`` on both axes, ``source`` naming the map.
    """
    from pylensfit.psfmodel import PolynomialPSF, n_terms  # psfmodel imports the PSF stack

    if grid * grid <= n_terms(order):
        raise ValueError(f"a {grid} x {grid} grid cannot fit {n_terms(order)} terms "
                         f"(order {order})")  # fmt: skip
    m = psf_map(spec)
    g = np.linspace(0.0, spec.size - 1.0, grid)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    u, v = normalised_position(spec, x, y)
    images = np.array([m.profile(a, b).drawImage(nx=size, ny=size, scale=1.0,
                                                 use_true_center=False).array
                       for a, b in zip(u, v, strict=True)])  # fmt: skip
    images /= images.sum(axis=(1, 2), keepdims=True)
    pu, pv = (2.0 * t / (spec.size - 1.0) - 1.0 for t in (x, y))  # the model's own u, v
    A = np.stack([pu**i * pv**j for d in range(order + 1) for j in range(d + 1)
                  for i in (d - j,)], axis=-1)  # fmt: skip
    coefs = np.linalg.lstsq(A, images.reshape(len(images), -1), rcond=None)[0]
    bounds = (0.0, spec.size - 1.0, 0.0, spec.size - 1.0)
    return PolynomialPSF(coefs.reshape(-1, size, size), order, bounds,
                         source=f"PSF map {spec.psf_variation!r} (truth)",
                         diagnostics={"kind": "truth", "order": order, "grid": grid})  # fmt: skip


def _hsm_psf(psf, stamp: int) -> tuple[float, float, float]:
    """HSM ``g1, g2, sigma`` of ``psf`` drawn with the pixel on a ``stamp``-square image."""
    import galsim  # galsim: heavy import, only for rendering

    mom = galsim.hsm.FindAdaptiveMom(psf.drawImage(nx=stamp, ny=stamp, scale=1.0))
    return mom.observed_shape.g1, mom.observed_shape.g2, mom.moments_sigma


def psf_observed_moments(
    spec: FieldSpec, x, y, *, nodes: int = 7, stamp: int = 33
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """GalSim adaptive moments of the pixel-convolved PSF at each position.

    The PSF is drawn with GalSim's pixel, centred on a pixel of a ``stamp``-square
    image, and measured by ``galsim.hsm.FindAdaptiveMom``; the shape of a PSF drawn off
    the pixel centre differs by < 1e-4 for FWHM >= 2.7 px. A constant map is measured
    once; a varying one on a ``nodes x nodes`` grid over the field, interpolated by a
    bicubic spline (within a few 1e-6 of measuring at each position for the ``"survey"``
    map, for 20-40 ms per field).

    Parameters
    ----------
    spec : FieldSpec
        The field.
    x, y : numpy.ndarray
        0-based pixel positions.
    nodes : int
        Grid points per axis (at least 4).
    stamp : int
        Side of the drawn PSF (pixels; odd: centred on a pixel).

    Returns
    -------
    e1, e2 : numpy.ndarray
        ``observed_shape`` ``g1, g2`` (pixel frame).
    sigma : numpy.ndarray
        ``moments_sigma`` (pixels).
    """
    x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
    m = psf_map(spec)
    if m.constant:
        vals = _hsm_psf(m.profile(), stamp)
        return tuple(np.full(x.shape, v) for v in vals)
    u, v = normalised_position(spec, x, y)
    gu = np.linspace(min(-1.0, u.min(initial=0)), max(1.0, u.max(initial=0)), nodes)
    gv = np.linspace(min(-1.0, v.min(initial=0)), max(1.0, v.max(initial=0)), nodes)
    grid = np.array([[_hsm_psf(m.profile(a, b), stamp) for b in gv] for a in gu])
    return tuple(
        RectBivariateSpline(gu, gv, grid[:, :, k], kx=3, ky=3).ev(u, v).reshape(x.shape)
        for k in range(3)
    )


def _sky_matrix(rotation_deg: float, flip: bool) -> np.ndarray:
    """``Rot(theta) F``: pixel offsets to sky-frame ``(dW, dN)`` offsets, per pixel scale."""
    t = np.deg2rad(rotation_deg)
    rot = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    return rot @ np.diag([1.0, -1.0 if flip else 1.0])


def pixel_to_sky_shear(g1, g2, rotation_deg: float, flip: bool):
    """A pixel-frame ellipticity or shear in the sky frame (module docstring).

    ``g_sky = g_pix exp(2i theta)``, or ``conj(g_pix) exp(2i theta)`` when flipped.

    Parameters
    ----------
    g1, g2 : float or numpy.ndarray
        Pixel-frame components.
    rotation_deg : float
        ``theta`` of the WCS (degrees; :attr:`FieldSpec.wcs_rotation_deg`).
    flip : bool
        Whether the WCS is flipped (:attr:`FieldSpec.wcs_flip`).

    Returns
    -------
    g1, g2 : numpy.ndarray
        Sky-frame components.
    """
    g1, g2 = np.asarray(g1, dtype=float), np.asarray(g2, dtype=float)
    if flip:
        g2 = -g2
    t = 2.0 * np.deg2rad(rotation_deg)
    c, s = np.cos(t), np.sin(t)
    return c * g1 - s * g2, s * g1 + c * g2


def sky_to_pixel_shear(g1, g2, rotation_deg: float, flip: bool):
    """A sky-frame ellipticity or shear in the pixel frame: :func:`pixel_to_sky_shear`'s inverse.

    ``g_pix = g_sky exp(-2i theta)``, or ``conj(g_sky exp(-2i theta))`` when flipped.

    Parameters
    ----------
    g1, g2 : float or numpy.ndarray
        Sky-frame components.
    rotation_deg : float
        ``theta`` of the WCS (degrees).
    flip : bool
        Whether the WCS is flipped.

    Returns
    -------
    g1, g2 : numpy.ndarray
        Pixel-frame components.
    """
    g1, g2 = np.asarray(g1, dtype=float), np.asarray(g2, dtype=float)
    t = -2.0 * np.deg2rad(rotation_deg)
    c, s = np.cos(t), np.sin(t)
    p1, p2 = c * g1 - s * g2, s * g1 + c * g2
    return (p1, -p2) if flip else (p1, p2)


def to_pixel_frame(obj, spec: FieldSpec):
    """A profile defined in the sky frame, drawn in ``spec``'s pixel frame.

    Parameters
    ----------
    obj : galsim.GSObject
        The profile in sky-frame axes ``(W, N)`` (in pixels).
    spec : FieldSpec
        The field's ``wcs_rotation_deg`` and ``wcs_flip``.

    Returns
    -------
    galsim.GSObject
        ``obj`` transformed by ``(Rot(theta) F)^-1`` (``obj`` itself for the plain WCS).
    """
    if spec.wcs_rotation_deg == 0.0 and not spec.wcs_flip:
        return obj
    j = np.linalg.inv(_sky_matrix(spec.wcs_rotation_deg, spec.wcs_flip))
    return obj.transform(j[0, 0], j[0, 1], j[1, 0], j[1, 1])


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
        scale length (bulge half-light radius ``0.6 r``, half the flux each):
        :meth:`pylensfit_validation.galaxies.GalaxyProfile.from_model`.
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
    if model == "mixed":
        model = MIXED_KINDS[index % len(MIXED_KINDS)]
    # the model bank's meaning of r; bulge+disc: STEP1's bulge of 0.6 r, half the flux
    return GalaxyProfile.from_model(model, r, bulge_fraction=0.5, bulge_size_ratio=0.6).galsim()


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
    if spec.shear_positions:
        x, y = lensed_positions(spec, x, y)
    return x, y, is_star, r, snr, star_snr, e_int


def lensed_positions(spec: FieldSpec, x: np.ndarray,
                     y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Positions sheared about the field's centre ``(size - 1) / 2`` by the field's
    pixel-frame shear (:func:`pixel_shear`), with the area-preserving matrix ``[[1 + g1,
    g2], [g2, 1 - g1]] / sqrt(1 - |g|^2)`` that GalSim's ``shear`` applies to the
    profiles (:attr:`FieldSpec.shear_positions`). An object moved off the field is drawn
    as far as it reaches into it."""
    g1, g2 = pixel_shear(spec)
    c = (spec.size - 1) / 2.0
    k = 1.0 / np.sqrt(1.0 - g1 * g1 - g2 * g2)
    dx, dy = x - c, y - c
    return c + k * ((1.0 + g1) * dx + g2 * dy), c + k * (g2 * dx + (1.0 - g1) * dy)


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

    The shapes are drawn in the sky frame, the shear ``spec.g1, g2`` is the sky frame's;
    both are returned in the pixel frame (:func:`sky_to_pixel_shear`), where the
    lensing relation keeps its form.

    Parameters
    ----------
    spec : FieldSpec
        The shear ``g1, g2``, whether the field is the rotated twin (``rotate``), and
        its WCS (``wcs_rotation_deg``, ``wcs_flip``).
    e_int : numpy.ndarray
        ``(n, 2)`` intrinsic ellipticities as drawn (sky frame).
    is_star : numpy.ndarray
        ``(n,)`` star flags: stars get ``e_obs = 0``.

    Returns
    -------
    e_int : numpy.ndarray
        ``(n, 2)`` intrinsic ellipticities, negated for a rotated twin (pixel frame).
    e_obs : numpy.ndarray
        ``(n,)`` complex sheared ellipticities ``e1 + i e2`` (pixel frame).
    """
    if spec.rotate:
        e_int = -e_int  # a 90-degree rotation of an ellipse flips e
    rot, flip = spec.wcs_rotation_deg, spec.wcs_flip
    if rot != 0.0 or flip:
        e_int = np.column_stack(sky_to_pixel_shear(e_int[:, 0], e_int[:, 1], rot, flip))
    e1, e2 = apply_shear(e_int[:, 0], e_int[:, 1], *pixel_shear(spec))
    e_obs = e1 + 1j * e2
    e_obs[is_star] = 0.0
    return e_int, e_obs


def pixel_shear(spec: FieldSpec) -> tuple[float, float]:
    """The field's shear ``spec.g1, g2`` (sky frame) in its pixel frame."""
    g1, g2 = sky_to_pixel_shear(spec.g1, spec.g2, spec.wcs_rotation_deg, spec.wcs_flip)
    return float(g1), float(g2)


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


def add_psf_and_sky_truth(truth: Table, spec: FieldSpec) -> Table:
    """Add the local PSF's and the sky frame's columns to a field's truth table.

    Parameters
    ----------
    truth : astropy.table.Table
        A truth table (:func:`truth_table`), changed in place.
    spec : FieldSpec
        The field.

    Returns
    -------
    astropy.table.Table
        ``truth`` with ``psf_fwhm`` (pixels), ``psf_e1, psf_e2`` (the map's parameters
        at each object, :func:`psf_at`), ``psf_e1_obs, psf_e2_obs, psf_sigma_obs``
        (adaptive moments of the pixel-convolved PSF there,
        :func:`psf_observed_moments`; sigma in pixels), ``e1_sky, e2_sky`` and
        ``e1_int_sky, e2_int_sky`` (the sheared and intrinsic shapes in the sky frame).
    """
    x, y = np.asarray(truth["x"], float), np.asarray(truth["y"], float)
    truth["psf_fwhm"], truth["psf_e1"], truth["psf_e2"] = psf_at(spec, x, y)
    obs = psf_observed_moments(spec, x, y)
    truth["psf_e1_obs"], truth["psf_e2_obs"], truth["psf_sigma_obs"] = obs
    rot, flip = spec.wcs_rotation_deg, spec.wcs_flip
    truth["e1_sky"], truth["e2_sky"] = pixel_to_sky_shear(truth["e1"], truth["e2"], rot, flip)
    truth["e1_int_sky"], truth["e2_int_sky"] = pixel_to_sky_shear(
        truth["e1_int"], truth["e2_int"], rot, flip
    )
    return truth


def field_meta(spec: FieldSpec, model: str, seed: int) -> dict:
    """The truth meta of a simulated field: shear (sky frame), model, PSF, seed, WCS.

    Keys of at most 8 characters (FITS header cards of the ``TRUTH`` extension):
    ``psf_var`` is ``spec.psf_variation``, ``wcs_rot`` the WCS rotation (degrees),
    ``wcs_flip`` its flip.
    """
    return {
        "g1": spec.g1,
        "g2": spec.g2,
        "model": model,
        "noise": spec.noise_sigma,
        "psf_fwhm": spec.psf_fwhm,
        "psf_e1": spec.psf_e1,
        "psf_e2": spec.psf_e2,
        "seed": seed,
        "psf_var": spec.psf_variation,
        "wcs_rot": spec.wcs_rotation_deg,
        "wcs_flip": spec.wcs_flip,
    }


def star_peaks(psfs: list, is_star: np.ndarray, stamp: int = 64) -> np.ndarray:
    """Peak of each star's unit-flux PSF drawn centred on a ``stamp``-square image.

    Parameters
    ----------
    psfs : list of galsim.GSObject
        The PSF at each object (:func:`local_psfs`); a shared object is drawn once.
    is_star : numpy.ndarray
        Star flags: only stars are drawn.
    stamp : int
        Side of the drawing (pixels).

    Returns
    -------
    numpy.ndarray
        The peaks, NaN for galaxies.
    """
    cache: dict[int, float] = {}
    out = np.full(len(psfs), np.nan)
    for i in np.flatnonzero(is_star):
        key = id(psfs[i])
        if key not in cache:
            cache[key] = psfs[i].drawImage(nx=stamp, ny=stamp, scale=1.0).array.max()
        out[i] = cache[key]
    return out


def simulate_field(
    spec: FieldSpec, *, seed: int, noise_seed: int | None = None
) -> tuple[np.ndarray, np.ndarray, Table]:
    """Render a field of sheared galaxies and stars with GalSim.

    Every object is drawn with the PSF at its own position (:func:`local_psfs`). The
    intrinsic shapes are drawn, and the shear ``spec.g1, g2`` given, in the sky frame,
    and rendered in the pixel frame of the field's WCS: a seed gives the same galaxies
    on the sky (at the same pixel positions) whatever the WCS.

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
        (sheared), both in the pixel frame, ``snr`` (matched-filter S/N of the
        noise-free object before lensing, with its local PSF), and the columns of
        :func:`add_psf_and_sky_truth` (local PSF, sky-frame shapes).
    """
    import galsim  # galsim: heavy import, only for rendering

    rng = np.random.default_rng(seed)
    n = int(spec.size)
    x, y, is_star, r, snr, star_snr, e_int = draw_population(spec, rng)
    n_obj = x.size
    e_int, e_obs = lensed_shapes(spec, e_int, is_star)
    g1, g2 = pixel_shear(spec)

    psfs = local_psfs(spec, x, y)
    peaks = star_peaks(psfs, is_star)
    image = galsim.ImageF(n, n, scale=1.0)  # bounds 1..n: numpy (x, y) is galsim (x+1, y+1)
    flux = np.empty(n_obj)
    for i in range(n_obj):  # rendering is GalSim's, one object at a time
        psf = psfs[i]
        if is_star[i]:
            obj = psf
            flux[i] = star_snr[i] * spec.noise_sigma / peaks[i]  # peak S/N as drawn
        else:
            # round profiles: the pixel-frame shears render the sky frame's galaxy
            gal = galaxy_profile(spec.model, r[i], i).shear(g1=e_int[i, 0], g2=e_int[i, 1])
            obj = galsim.Convolve(gal.shear(g1=g1, g2=g2), psf)
            # the flux from the S/N of the unlensed, unrotated galaxy: lensing keeps the
            # flux, and a rotated twin gets the same flux as its original
            e0 = -e_int[i] if spec.rotate else e_int[i]
            ref = galsim.Convolve(galaxy_profile(spec.model, r[i], i).shear(g1=e0[0], g2=e0[1]),
                                  psf)  # fmt: skip
            arr = ref.drawImage(nx=64, ny=64, scale=1.0).array
            flux[i] = snr[i] * spec.noise_sigma / np.sqrt((arr**2).sum())
        add_object(image, obj, flux[i], x[i], y[i])
    image, weight = add_sky_and_noise(image, spec, seed, noise_seed)
    truth = add_psf_and_sky_truth(truth_table(x, y, is_star, flux, r, e_int, e_obs, snr), spec)
    truth.meta.update(field_meta(spec, spec.model, seed))
    return image, weight, truth


def _wcs(spec: FieldSpec, ra0: float, dec0: float) -> WCS:
    """The field's TAN WCS: ``CD = s diag(-1, 1) Rot(theta) F`` (module docstring)."""
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [ra0, dec0]
    w.wcs.crpix = [spec.size / 2 + 0.5, spec.size / 2 + 0.5]
    s = spec.pixel_scale_arcsec / 3600.0
    if spec.wcs_rotation_deg == 0.0 and not spec.wcs_flip:
        w.wcs.cd = [[-s, 0.0], [0.0, s]]
    else:
        w.wcs.cd = s * np.diag([-1.0, 1.0]) @ _sky_matrix(spec.wcs_rotation_deg, spec.wcs_flip)
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
    The header's ``SIMG1, SIMG2`` are the sky-frame shear, ``SIMROT`` (degrees) and
    ``SIMFLIP`` the WCS's rotation and flip, ``SIMPSFV`` the PSF variation.
    """
    hdr = _wcs(spec, ra0, dec0).to_header()
    hdr["GAIN"] = (0.0, "no Poisson noise: background-limited simulation")
    hdr["SIMG1"] = (spec.g1, "input reduced shear g1 (sky frame: W, N)")
    hdr["SIMG2"] = (spec.g2, "input reduced shear g2 (sky frame: W, N)")
    hdr["SIMROT"] = (spec.wcs_rotation_deg, "[deg] WCS rotation theta, pixel to sky")
    hdr["SIMFLIP"] = (bool(spec.wcs_flip), "WCS flipped: dy -> -dy before the rotation")
    hdr["SIMPSFV"] = (spec.psf_variation, "PSF variation over the field")
    hdus = [fits.PrimaryHDU(image, header=hdr)]
    if weight is not None:
        hdus.append(fits.ImageHDU(weight, name="WEIGHT"))
    if truth is not None:
        hdus.append(fits.BinTableHDU(truth, name="TRUTH"))
    atomic_write(fits.HDUList(hdus), path, overwrite=True)
