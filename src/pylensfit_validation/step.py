"""STEP1- and STEP2-like validation sets simulated with GalSim (paper sections 4-5).

``simulate_step("step1", out)`` writes a STEP1-like set: bulge + disc galaxies
(de Vaucouleurs bulge, exponential disc), five PSFs (round, elliptical along ``e1``,
elliptical along ``e2``, larger, and a diagonal one with a broader wing), ``g1`` in
{0, 0.005, 0.01, 0.05, 0.1} with ``g2 = 0``, pixel 0.206 arcsec.

``simulate_step("step2", out)`` writes a STEP2-like set: complex morphologies (Sersic
profiles of varied index, bulge + disc, discs with star-forming knots), a random shear
``|g| <= 0.06`` per image in both components, each image with a twin whose galaxies are
rotated by 90 degrees before the shear (the same objects and shear, independent noise),
five PSFs of which two are highly elliptical, pixel 0.2 arcsec.

Both sets have a zero-shear field per PSF (role ``"prior"``) from which the ellipticity
prior is estimated, as in the paper, and a star-only field per PSF from which the PSF is
modelled. Every field carries its truth table in a ``TRUTH`` extension (columns as in
:func:`pylensfit_validation.simulate.simulate_field`); ``manifest.json`` lists the fields.

Either set can have its PSFs vary over the fields (``psf_variation="survey"``: FWHM
+-10 % and ``|e|`` up to 0.08 corner to corner about each PSF's centre values, the star
fields following the same map) and a rotated or flipped WCS (``wcs_rotation_deg``,
``wcs_flip``), the shears being the sky frame's (:mod:`pylensfit_validation.simulate`).

A STEP2-like set's galaxies are by default the aligned population, every bulge aligned
with its disc and as elongated; ``population="realistic"`` gives them the bulges of real
galaxies, of their own size, elongation and misalignment, and Sersic indices 0.3-6
(:data:`pylensfit_validation.galaxies.REALISTIC`, :func:`render_step2_field`).

Conventions are those of :mod:`pylensfit_validation.simulate`: sizes in pixels, numpy ``(x, y)``
0-based is GalSim ``(x + 1, y + 1)``, ``e = (a - b) / (a + b)`` and a shear ``g`` maps
``e_s`` to ``(e_s + g) / (1 + g* e_s)``.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from astropy.table import Table

from pylensfit.runner import run_tasks

from .galaxies import GalaxyProfile, draw_bulge_shapes, draw_sersic_indices
from .simulate import (
    POPULATIONS,
    PSF_VARIATIONS,
    FieldSpec,
    add_object,
    add_psf_and_sky_truth,
    add_sky_and_noise,
    draw_population,
    field_meta,
    lensed_shapes,
    local_psfs,
    pixel_shear,
    simulate_field,
    star_peaks,
    to_pixel_frame,
    truth_table,
    write_field,
)

__all__ = [
    "STEP1_PSFS",
    "STEP1_SHEARS",
    "STEP2_KINDS",
    "STEP2_PSFS",
    "read_manifest",
    "render_step2_field",
    "simulate_step",
    "spec_for",
]


#: STEP1-like PSFs: Moffat ``(fwhm [px], beta, e1, e2)``; pixel 0.206 arcsec.
STEP1_PSFS: tuple[dict, ...] = (
    {"fwhm": 3.0, "beta": 3.5, "e1": 0.0, "e2": 0.0},  # round
    {"fwhm": 3.0, "beta": 3.5, "e1": 0.05, "e2": 0.0},  # elliptical along e1
    {"fwhm": 3.0, "beta": 3.5, "e1": 0.0, "e2": 0.05},  # elliptical along e2
    {"fwhm": 4.5, "beta": 3.5, "e1": 0.0, "e2": 0.0},  # larger
    {"fwhm": 3.5, "beta": 2.5, "e1": -0.03, "e2": 0.03},  # diagonal, broad wings
)

#: STEP2-like PSFs, two of them highly elliptical; pixel 0.2 arcsec.
STEP2_PSFS: tuple[dict, ...] = (
    {"fwhm": 3.0, "beta": 3.5, "e1": 0.0, "e2": 0.0},  # round
    {"fwhm": 3.0, "beta": 3.5, "e1": 0.04, "e2": -0.02},  # mildly elliptical
    {"fwhm": 4.5, "beta": 3.0, "e1": 0.01, "e2": 0.01},  # larger
    {"fwhm": 3.0, "beta": 3.5, "e1": 0.12, "e2": 0.0},  # highly elliptical along e1
    {"fwhm": 3.5, "beta": 3.0, "e1": -0.07, "e2": 0.10},  # highly elliptical, diagonal
)

#: The galaxy kinds of a STEP2-like set (drawn 40/30/30 %), in the order of their
#: ``morphology`` code in :func:`validate`.
STEP2_KINDS: tuple[str, ...] = ("sersic", "bulge+disc", "knots")

#: STEP1 input shears ``g1`` (``g2 = 0``).
STEP1_SHEARS: tuple[float, ...] = (0.0, 0.005, 0.01, 0.05, 0.1)

_PIXEL = {"step1": 0.206, "step2": 0.2}
_STAMP = 64


def spec_for(psf: dict, **kw) -> FieldSpec:
    """The :class:`~pylensfit_validation.simulate.FieldSpec` of a field with the PSF
    ``psf`` (an entry of :data:`STEP1_PSFS` or :data:`STEP2_PSFS`) and the fields ``kw``."""
    return FieldSpec(
        psf_fwhm=psf["fwhm"], psf_beta=psf["beta"], psf_e1=psf["e1"], psf_e2=psf["e2"], **kw
    )


def _step2_galaxy(
    kind: str, r: float, n: float, bulge_frac: float, knot_frac: float, n_knots: int,
    knot_seed: int, *, bulge_size_ratio: float = 0.5,
    bulge_shear: tuple[float, float] = (0.0, 0.0),
):  # fmt: skip
    """Unit-flux STEP2-like galaxy of half-light radius r (px), before its intrinsic shear.

    :class:`~pylensfit_validation.galaxies.GalaxyProfile` with STEP2's bulge by default: half-light
    radius ``0.5 r`` (``r`` the disc's half-light radius), flux ``bulge_frac``, round (the
    aligned population). The realistic population's bulge has a half-light radius of
    ``bulge_size_ratio r`` and its own shear ``bulge_shear`` (``(g1, g2)``, applied to
    the bulge before the galaxy's intrinsic shear is applied to the whole).
    """
    if kind not in STEP2_KINDS:
        raise ValueError(f"unknown step2 galaxy kind {kind!r}")
    return GalaxyProfile(kind, r, sersic_n=n, bulge_fraction=bulge_frac,
                         bulge_size_ratio=bulge_size_ratio, knot_fraction=knot_frac,
                         n_knots=n_knots, knot_seed=knot_seed,
                         bulge_shear=bulge_shear).galsim()  # fmt: skip


def render_step2_field(
    spec: FieldSpec, *, seed: int, noise_seed: int | None = None
) -> tuple[np.ndarray, np.ndarray, Table]:
    """Render a STEP2-like field: complex morphologies, sheared, with stars and noise.

    The lattice, stars, fluxes, intrinsic ellipticities, local PSFs, frames and noise
    follow :func:`pylensfit_validation.simulate.simulate_field`; the galaxies are a mix of Sersic
    profiles, bulge + disc (de Vaucouleurs bulge, exponential disc, bulge fraction
    0-0.5), and discs with star-forming knots (``galsim.RandomKnots``) and a bulge.
    ``spec.size_range`` is the range of the discs' half-light radii (px). Each galaxy is
    built in the sky frame and drawn in the pixel frame of the WCS
    (:func:`pylensfit_validation.simulate.to_pixel_frame`), knots included: a seed gives the same
    galaxies on the sky whatever ``spec.wcs_rotation_deg`` and ``spec.wcs_flip``.

    ``spec.population`` chooses the Sersic indices and the bulges:

    - ``"aligned"``: Sersic indices uniform in 0.5-4, every bulge of half its disc's
      half-light radius, aligned with its disc and as elongated (the intrinsic shear
      applied to the whole galaxy).
    - ``"realistic"`` (:data:`pylensfit_validation.galaxies.REALISTIC`, as
      :class:`pylensfit_validation.precision.PrecisionSpec`'s): Sersic indices log-uniform in
      0.3-6, bulges of 0.25-0.8 of their disc's half-light radius with shapes of their
      own (:func:`pylensfit_validation.galaxies.draw_bulge_shapes`): on the sky the bulge+disc
      galaxies' bulges are 0.2-1 times as elongated as their discs and misaligned by a
      Gaussian angle of 30 degrees rms, the knotty discs' 0-0.6 times (10 degrees rms).
      These are drawn after every parameter of the aligned population, so the two share
      their objects' positions, S/N, sizes, disc shapes, bulge fractions, knots and
      noise, and their stars (a galaxy's flux is that of its S/N: it follows its
      profile).

    Parameters
    ----------
    spec : FieldSpec
        What to simulate (``spec.model`` is ignored). With ``spec.rotate`` each galaxy,
        bulge and knots included, is rotated by 90 degrees after its intrinsic shear and
        before the lensing shear: the twin of the field with the same ``seed``.
    seed : int
        Seed of the objects.
    noise_seed : int, optional
        Seed of the noise (default: derived from ``seed``).

    Returns
    -------
    image : numpy.ndarray
        ``(size, size)`` float32, sky included, with Gaussian noise.
    weight : numpy.ndarray
        Inverse-variance map.
    truth : astropy.table.Table
        As :func:`pylensfit_validation.simulate.simulate_field`, plus ``kind`` (galaxy type),
        ``sersic_n``, ``bulge_frac``, ``n_knots``; ``r`` is the disc's half-light
        radius. ``e1_int, e2_int`` are the (rotated, for a twin) intrinsic shears,
        applied to the whole galaxy: the disc's shape. A realistic population adds
        ``bulge_size_ratio`` (the bulge's half-light radius over ``r``) and ``misalign``
        (the bulge's position angle less its disc's on the sky, degrees; the same for a
        twin), NaN for stars and Sersic galaxies, and its meta ``pop = "realistic"``.
    """
    import galsim  # galsim: heavy import, only for rendering

    rng = np.random.default_rng(seed)
    n = int(spec.size)
    x, y, is_star, r, snr, star_snr, e_int = draw_population(spec, rng)
    n_obj = x.size
    kinds = rng.choice(np.array(STEP2_KINDS), n_obj, p=[0.4, 0.3, 0.3])
    sersic_n = np.round(rng.uniform(0.5, 4.0, n_obj), 1)  # quantised: GalSim caches by n
    bulge_frac = rng.uniform(0.0, 0.5, n_obj)
    knot_frac = rng.uniform(0.2, 0.5, n_obj)
    n_knots = rng.integers(10, 60, n_obj)
    knot_seed = rng.integers(1, 2**31 - 1, n_obj)
    realistic = spec.population == "realistic"
    bulge_ratio, b1, b2, misalign = np.full(n_obj, 0.5), *np.zeros((3, n_obj))
    if realistic:  # after every draw above: the aligned population's galaxies, re-dressed
        sersic_n = draw_sersic_indices(n_obj, rng)
        # The bulge's shear is applied in the sky frame (GalaxyProfile, before
        # to_pixel_frame) and followed by the disc's intrinsic shape in the sky frame,
        # the one drawn: e_int before lensed_shapes, the original's for a twin too (the
        # twin is the original galaxy rotated, bulge included).
        bulge_ratio, b1, b2, misalign = draw_bulge_shapes(kinds == "bulge+disc",
                                                          kinds == "knots", e_int, rng)
    e_int, e_obs = lensed_shapes(spec, e_int, is_star)  # pixel frame
    g1, g2 = pixel_shear(spec)
    # a sky-frame rotation by 90 degrees is one by -90 in a flipped pixel frame
    twin_angle = (-90 if spec.wcs_flip else 90) * galsim.degrees

    psfs = local_psfs(spec, x, y)
    peaks = star_peaks(psfs, is_star, _STAMP)
    image = galsim.ImageF(n, n, scale=1.0)  # bounds 1..n: numpy (x, y) is galsim (x+1, y+1)
    flux = np.empty(n_obj)
    for i in range(n_obj):
        psf = psfs[i]
        if is_star[i]:
            obj = psf
            flux[i] = star_snr[i] * spec.noise_sigma / peaks[i]
        else:
            gal = _step2_galaxy(
                str(kinds[i]),
                r[i],
                sersic_n[i],
                bulge_frac[i],
                knot_frac[i],
                int(n_knots[i]),
                int(knot_seed[i]),
                bulge_size_ratio=float(bulge_ratio[i]),
                bulge_shear=(float(b1[i]), float(b2[i])),
            )
            gal = to_pixel_frame(gal, spec)  # the knots' pattern: shears are pixel-frame
            # the flux from the S/N of the unlensed, unrotated galaxy (as step1's): lensing
            # keeps the flux, and a rotated twin gets the same flux as its original. (The
            # S/N of the lensed galaxy made the flux follow the shear, galaxies sheared
            # longer getting brighter by up to 0.6 %; with the uniform amplitude prior it
            # moved <m> of the 100k set by -0.0002, but no sky does that.)
            e0 = -e_int[i] if spec.rotate else e_int[i]
            gal = gal.shear(g1=e0[0], g2=e0[1])
            arr = galsim.Convolve(gal, psf).drawImage(nx=_STAMP, ny=_STAMP, scale=1.0).array
            flux[i] = snr[i] * spec.noise_sigma / np.sqrt((arr**2).sum())
            if spec.rotate:
                gal = gal.rotate(twin_angle)
            obj = galsim.Convolve(gal.shear(g1=g1, g2=g2), psf)
        add_object(image, obj, flux[i], x[i], y[i], _STAMP)
    arr, weight = add_sky_and_noise(image, spec, seed, noise_seed)
    truth = add_psf_and_sky_truth(truth_table(x, y, is_star, flux, r, e_int, e_obs, snr), spec)
    truth["kind"] = np.where(is_star, "star", kinds)
    truth["sersic_n"] = np.where(is_star | (kinds != "sersic"), np.nan, sersic_n)
    truth["bulge_frac"] = np.where(is_star | (kinds == "sersic"), np.nan, bulge_frac)
    truth["n_knots"] = np.where(~is_star & (kinds == "knots"), n_knots, 0)
    truth.meta.update({**field_meta(spec, "step2", seed), "rotate": spec.rotate})
    if realistic:  # the aligned population's bulges are STEP2's: no columns of their own
        no_bulge = is_star | (kinds == "sersic")
        truth["bulge_size_ratio"] = np.where(no_bulge, np.nan, bulge_ratio)
        truth["misalign"] = np.where(no_bulge, np.nan, misalign)
        truth.meta["pop"] = spec.population
    return arr, weight, truth


def _field_size(ngal: int, n_fields: int, spacing: float, star_fraction: float) -> int:
    """Field size (px) giving about ``ngal / n_fields`` galaxies on the lattice."""
    per_field = max(ngal / n_fields, 1.0) / max(1.0 - star_fraction, 1e-3)
    m = max(round(math.sqrt(per_field)), 1)
    return int(math.ceil((m + 1) * spacing))  # simulate_field puts m points on (m+1)*spacing


def _step2_shears(n_shear: int, gmax: float, rng: np.random.Generator) -> list[tuple]:
    """Random shears, uniform in the disc ``|g| <= gmax``, both components nonzero."""
    out = []
    while len(out) < n_shear:
        g1, g2 = rng.uniform(-gmax, gmax, 2)
        if math.hypot(g1, g2) <= gmax and abs(g1) > 1e-3 and abs(g2) > 1e-3:
            out.append((float(g1), float(g2)))
    return out


def simulate_step(
    kind: str,
    out: str | Path,
    *,
    ngal: int = 20000,
    seed: int = 1,
    noise_sigma: float = 1.0,
    field_size: int | None = None,
    n_shear: int | None = None,
    gmax: float = 0.06,
    spacing: float = 40.0,
    star_fraction: float = 0.05,
    snr_range: tuple[float, float] = (15.0, 150.0),
    size_range: tuple[float, float] | None = None,
    star_field_size: int | None = None,
    psfs: tuple[dict, ...] | None = None,
    prior_ngal: int | None = None,
    twins: bool | None = None,
    noise_twins: bool = False,
    psf_variation: str = "none",
    wcs_rotation_deg: float = 0.0,
    wcs_flip: bool = False,
    population: str = "aligned",
    shear_positions: bool = False,
    jobs: int = 1,
    progress: bool = False,
) -> Path:
    """Simulate a STEP1- or STEP2-like validation set with GalSim.

    Parameters
    ----------
    kind : {"step1", "step2"}
        Which set (see the module docstring).
    out : str or pathlib.Path
        Output directory (created).
    ngal : int
        Total number of galaxies over the shear fields (twins included); sets the field
        size from the lattice ``spacing`` unless ``field_size`` is given.
    seed : int
        Master seed; every field's object and noise seeds derive from it (in the manifest).
    noise_sigma : float
        Gaussian noise per pixel (the S/N range is relative to it).
    field_size : int, optional
        Field size in pixels (overrides the one derived from ``ngal``).
    n_shear : int, optional
        Number of shear values per PSF: step1 takes the first ``n_shear`` of
        ``STEP1_SHEARS`` (default all 5); step2 draws ``n_shear`` random shears (default
        4), shared by all PSFs, each with a rotated twin.
    gmax : float
        Largest ``|g|`` of the step2 shears.
    spacing : float
        Lattice pitch (px).
    star_fraction : float
        Fraction of the lattice points that are stars in the galaxy fields.
    snr_range : tuple of float
        Range of galaxy matched-filter S/N (log-uniform).
    size_range : tuple of float, optional
        Galaxy size range (px): scale length of the disc for step1 (default (1.2, 3.5)),
        half-light radius for step2 (default (1.5, 4.5)).
    star_field_size : int, optional
        Size of the star-only fields (default: ``field_size``). The stacked PSF's noise
        reaches c: on a 100,000-galaxy STEP1 set (~1,000 stars per PSF) its
        ellipticity is off by ~2e-5 and the galaxies' c by up to 1.3e-4 per PSF, 0.6e-4
        rms (``pylensfit validate DIR --true-psf``, ``benchmarks/step1_true_psf.py``); a star
        field of twice the side halves that.
    psfs : tuple of dict, optional
        PSFs as ``{"fwhm", "beta", "e1", "e2"}`` (default ``STEP1_PSFS``/``STEP2_PSFS``).
    prior_ngal : int, optional
        Total number of galaxies over the zero-shear (prior) fields, one per PSF; sets
        their size (default: the size of the shear fields). The prior needs a few
        thousand galaxies (docs: method, eq-prior-iteration), more than one shear field holds in a
        small set.
    twins : bool, optional
        Give every shear field a twin whose galaxies are rotated by 90 degrees before
        the shear (the same objects, independent noise), so that the intrinsic shapes
        cancel pair by pair in ``validate``. Default: step2 yes (as STEP2), step1 no (as
        STEP1, whose independent images leave the shape noise in m: sigma(m) ~ 0.03 for
        100,000 galaxies; with twins step1 can test m to a few 1e-3).
    noise_twins : bool
        Give every shear field (twins included) a noise twin ``..._neg.fits``: the same
        objects and the same noise field negated (``FieldSpec.noise_sign = -1``), so that
        in ``validate`` the noise's first-order effect on the mean ellipticity cancels
        galaxy by galaxy, as the rotated twin cancels the intrinsic shapes. What remains
        in ``c`` and ``m`` is the measurement's response to the noise at second order
        (noise bias) and to the PSF: the offsets ``c`` are then resolved to ~1e-4 per PSF
        by a set whose independent noise leaves them at ~5e-4. ``ngal`` counts the
        renderings, so the set holds half as many distinct galaxies.
    psf_variation : {"none", "survey"}
        How each PSF of ``psfs`` varies over the fields, about its parameters at the
        centre (:data:`pylensfit_validation.simulate.PSF_VARIATIONS`,
        :func:`pylensfit_validation.simulate.psf_at`).
        The star fields follow the same map on the same geometry, so a varying PSF needs
        the star and zero-shear fields of the shear fields' size.
    wcs_rotation_deg : float
        Rotation ``theta`` (degrees) of every field's WCS, pixel to sky frame
        (:mod:`pylensfit_validation.simulate`); the shears and intrinsic shapes are the sky frame's.
    wcs_flip : bool
        Flip every field's WCS (``dy -> -dy`` before the rotation).
    population : {"aligned", "realistic"}
        The step2 galaxies (:func:`render_step2_field`): ``"aligned"`` (the default),
        bulges of half their disc's half-light radius aligned with their discs and as
        elongated, Sersic indices 0.5-4; ``"realistic"``, Sersic indices 0.3-6 and
        bulges of their own size, elongation and misalignment
        (:data:`pylensfit_validation.galaxies.REALISTIC`), the same seed giving the same objects
        otherwise. A step1 set's galaxies are the model bank's bulge+disc family by
        design: only ``"aligned"``.
    shear_positions : bool
        Shear the positions too, about each field's centre, with the shapes' shear
        (:attr:`pylensfit_validation.simulate.FieldSpec.shear_positions`): the lensed sky.
    jobs : int
        Fields rendered in parallel by this many processes (the pipeline's runner); the
        set is the same for any ``jobs``: every field's seeds are drawn first, in order.
    progress : bool
        Show a progress bar over the fields.

    Returns
    -------
    pathlib.Path
        The output directory, holding ``psf{k}_g{j}.fits`` (shear fields),
        ``psf{k}_g{j}_rot.fits`` (twins), ``psf{k}_g{j}[_rot]_neg.fits`` (noise twins),
        ``psf{k}_prior.fits`` (zero shear),
        ``psf{k}_stars.fits`` (stars only) and ``manifest.json``.

    Raises
    ------
    ValueError
        For an unknown ``kind`` or ``population``, a realistic step1 set, or arguments
        that do not fit together (a varying PSF with star or zero-shear fields of
        another size).
    """
    _check_kind(kind, population)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    psfs = tuple(psfs) if psfs is not None else (STEP1_PSFS if kind == "step1" else STEP2_PSFS)
    rng = np.random.default_rng(seed)
    lay = _set_layout(kind, psfs, rng, ngal=ngal, noise_sigma=noise_sigma,
                      field_size=field_size, n_shear=n_shear, gmax=gmax, spacing=spacing,
                      star_fraction=star_fraction, snr_range=snr_range, size_range=size_range,
                      star_field_size=star_field_size, prior_ngal=prior_ngal, twins=twins,
                      noise_twins=noise_twins, psf_variation=psf_variation,
                      wcs_rotation_deg=wcs_rotation_deg, wcs_flip=wcs_flip,
                      population=population)  # fmt: skip
    lay.common["shear_positions"] = bool(shear_positions)
    tasks, star_files, fields = _field_tasks(kind, lay, out, rng)
    _render_fields(tasks, star_files, fields, jobs, progress)
    manifest = _set_manifest(kind, lay, star_files, fields, ngal=ngal, seed=seed,
                             noise_sigma=noise_sigma, prior_ngal=prior_ngal)  # fmt: skip
    with open(out / "manifest.json", "w") as fh:
        json.dump(manifest, fh, indent=1, default=list)
    return out


def _check_kind(kind: str, population: str) -> None:
    """:func:`simulate_step`'s set kind and galaxy population, or a ValueError."""
    if kind not in _PIXEL:
        raise ValueError(f"kind must be 'step1' or 'step2', not {kind!r}")
    if population not in POPULATIONS:
        raise ValueError(f"population must be one of {POPULATIONS}, not {population!r}")
    if kind == "step1" and population != "aligned":
        raise ValueError("a step1 set's galaxies are the model bank's bulge+disc family: "
                         f"population must be 'aligned', not {population!r}")  # fmt: skip


@dataclass
class _SetLayout:
    """What the fields of a simulated set share (:func:`_set_layout`)."""

    psfs: tuple[dict, ...]  # the PSFs' parameters
    shears: list[tuple[float, float]]  # the shear fields' (g1, g2), per PSF
    twins: tuple[bool, ...]  # (False,) or (False, True): the rotated twins
    negs: tuple[bool, ...]  # (False,) or (False, True): the noise twins
    size: int  # shear fields' size (px)
    star_size: int  # star fields' size (px)
    prior_size: int  # zero-shear fields' size (px)
    pixel: float  # pixel scale (arcsec)
    common: dict[str, Any]  # the FieldSpec keywords every field shares
    psf_variation: str
    wcs_rotation_deg: float
    wcs_flip: bool
    population: str = "aligned"  # the step2 galaxies' (FieldSpec.population)


def _set_shears(kind: str, n_shear: int | None, gmax: float,
                size_range: tuple[float, float] | None,
                rng: np.random.Generator) -> tuple[list[tuple[float, float]], tuple[float, float]]:
    """The set's shears and its galaxies' size range (the default of ``kind`` if None)."""
    if kind == "step1":
        shears = [(g, 0.0) for g in STEP1_SHEARS[: (n_shear or len(STEP1_SHEARS))]]
        return shears, size_range or (1.2, 3.5)
    return _step2_shears(n_shear or 4, gmax, rng), size_range or (1.5, 4.5)


def _set_layout(kind: str, psfs: tuple[dict, ...], rng: np.random.Generator, *, ngal: int,
                noise_sigma: float, field_size: int | None, n_shear: int | None, gmax: float,
                spacing: float, star_fraction: float, snr_range: tuple[float, float],
                size_range: tuple[float, float] | None, star_field_size: int | None,
                prior_ngal: int | None, twins: bool | None, noise_twins: bool,
                psf_variation: str, wcs_rotation_deg: float,
                wcs_flip: bool, population: str = "aligned") -> _SetLayout:  # fmt: skip
    """Check :func:`simulate_step`'s arguments and lay out its set: shears, twins, sizes."""
    shears, size_range = _set_shears(kind, n_shear, gmax, size_range, rng)
    if twins is None:
        twins = kind == "step2"
    twin_flags = (False, True) if twins else (False,)
    negs = (False, True) if noise_twins else (False,)
    n_fields = len(psfs) * len(shears) * len(twin_flags) * len(negs)
    size = int(field_size) if field_size else _field_size(ngal, n_fields, spacing, star_fraction)
    star_size = int(star_field_size) if star_field_size else size
    prior_size = (_field_size(prior_ngal, len(psfs), spacing, star_fraction)
                  if prior_ngal else size)  # fmt: skip
    if psf_variation not in PSF_VARIATIONS:
        raise ValueError(f"psf_variation must be one of {sorted(PSF_VARIATIONS)}, "
                         f"not {psf_variation!r}")  # fmt: skip
    if psf_variation != "none" and (star_size != size or prior_size != size):
        raise ValueError(
            "a varying PSF needs the star and zero-shear fields of the shear fields' size "
            f"({size} px), so that they follow the same PSF map; got star fields of "
            f"{star_size} px and zero-shear fields of {prior_size} px"
        )
    pixel = _PIXEL[kind]
    common = dict(
        size=size,
        spacing=spacing,
        noise_sigma=noise_sigma,
        snr_range=snr_range,
        size_range=size_range,
        star_fraction=star_fraction,
        pixel_scale_arcsec=pixel,
        model="bulge+disc",
        psf_variation=psf_variation,
        wcs_rotation_deg=float(wcs_rotation_deg),
        wcs_flip=bool(wcs_flip),
        population=population,
    )
    return _SetLayout(psfs=psfs, shears=shears, twins=twin_flags, negs=negs, size=size,
                      star_size=star_size, prior_size=prior_size, pixel=pixel, common=common,
                      psf_variation=psf_variation, wcs_rotation_deg=float(wcs_rotation_deg),
                      wcs_flip=bool(wcs_flip), population=population)  # fmt: skip


def _draw_seeds(rng: np.random.Generator) -> tuple[int, int]:
    """A field's object and noise seeds, the next two draws of the set's ``rng``."""
    s = rng.integers(1, 2**31 - 1, 2)
    return int(s[0]), int(s[1])


def _field_tasks(kind: str, lay: _SetLayout, out: Path,
                 rng: np.random.Generator) -> tuple[list[dict], list[dict], list[dict]]:
    """Every field's render task (its seeds drawn here, in order) and manifest entry.

    Returns the tasks of :func:`_render_task`, the star fields' and the galaxy fields'
    manifest entries (without their counts of objects).
    """
    fields = []
    star_files = []
    tasks = []
    for k, psf in enumerate(lay.psfs):
        star_file = f"psf{k}_stars.fits"
        s_obj, s_noise = _draw_seeds(rng)
        sspec = spec_for(psf, **{**lay.common, "size": lay.star_size, "star_fraction": 1.0})
        tasks.append({"render": "step1", "spec": sspec, "seed": s_obj, "noise_seed": s_noise,
                      "path": str(out / star_file)})  # fmt: skip
        star_files.append(
            {
                "file": star_file,
                "psf": k,
                "psf_params": dict(psf),
                "seed": s_obj,
                "noise_seed": s_noise,
            }
        )
        _galaxy_field_tasks(kind, k, psf, star_file, lay, out, rng, tasks, fields)
    return tasks, star_files, fields


def _galaxy_field_tasks(kind: str, k: int, psf: dict, star_file: str, lay: _SetLayout,
                        out: Path, rng: np.random.Generator, tasks: list[dict],
                        fields: list[dict]) -> None:  # fmt: skip
    """Append the tasks and manifest entries of PSF ``k``'s zero-shear and shear fields."""
    todo = [("prior", None, 0.0, 0.0, False, False)]
    todo += [("shear", j, g1, g2, t, ng) for j, (g1, g2) in enumerate(lay.shears)
             for t in lay.twins for ng in lay.negs]  # fmt: skip
    obj_seed = {}
    for role, j, g1, g2, twin, neg in todo:
        if role == "prior":
            name = f"psf{k}_prior.fits"
        else:
            name = f"psf{k}_g{j}" + ("_rot" if twin else "") + ("_neg" if neg else "") + ".fits"
        if not neg:  # a noise twin draws no seeds: the same objects and noise field
            s_obj, s_noise = _draw_seeds(rng)
            if twin:
                s_obj = obj_seed[j]  # the same objects, rotated; independent noise
            else:
                obj_seed[j] = s_obj
        kw = {**lay.common, "size": lay.prior_size} if role == "prior" else lay.common
        spec = spec_for(psf, **kw, g1=g1, g2=g2, rotate=twin, noise_sign=-1.0 if neg else 1.0)
        tasks.append({"render": kind, "spec": spec, "seed": s_obj, "noise_seed": s_noise,
                      "path": str(out / name)})  # fmt: skip
        fields.append(
            {
                "file": name,
                "role": role,
                "psf": k,
                "psf_params": dict(psf),
                "g1": g1,
                "g2": g2,
                "shear_index": j,
                "twin": twin,
                "noise_twin": neg,
                "star_file": star_file,
                "seed": s_obj,
                "noise_seed": s_noise,
            }
        )


def _render_fields(tasks: list[dict], star_files: list[dict], fields: list[dict], jobs: int,
                   progress: bool) -> None:  # fmt: skip
    """Render and write every field; add its counts of objects to its manifest entry."""
    counts = {}
    for t, res in run_tasks(_render_task, tasks, jobs, None, "fields", progress):
        counts[Path(t["path"]).name] = res
    for f in star_files:
        f["n_star"] = counts[f["file"]][1]
    for f in fields:
        f["n_gal"], f["n_obj"] = counts[f["file"]]


def _set_manifest(kind: str, lay: _SetLayout, star_files: list[dict], fields: list[dict], *,
                  ngal: int, seed: int, noise_sigma: float,
                  prior_ngal: int | None) -> dict[str, Any]:  # fmt: skip
    """The set's ``manifest.json`` content (:func:`read_manifest`)."""
    manifest = {
        "kind": kind,
        "pixel_scale_arcsec": lay.pixel,
        "ngal": ngal,
        "ngal_shear_fields": sum(f["n_gal"] for f in fields if f["role"] == "shear"),
        "seed": seed,
        "noise_sigma": noise_sigma,
        "field_size": lay.size,
        "star_field_size": lay.star_size,
        "prior_field_size": lay.prior_size,
        "prior_ngal": prior_ngal,
        "psfs": [dict(p) for p in lay.psfs],
        "psf_variation": lay.psf_variation,
        "wcs_rotation_deg": lay.wcs_rotation_deg,
        "wcs_flip": lay.wcs_flip,
        "population": lay.population,
        "shears": [list(s) for s in lay.shears],
        "fieldspec": {k: v for k, v in asdict(FieldSpec(**lay.common)).items()
                      if k not in ("extra",)},  # fmt: skip
        "star_fields": star_files,
        "fields": fields,
    }
    manifest["fieldspec"]["model"] = "bulge+disc" if kind == "step1" else "step2"
    return manifest


def _render_task(task: dict) -> tuple[int, int]:
    """Render one field of a set and write it (a worker of :func:`simulate_step`).

    Returns its numbers of galaxies and of objects.
    """
    render = simulate_field if task["render"] == "step1" else render_step2_field
    spec = task["spec"]
    img, w, truth = render(spec, seed=task["seed"], noise_seed=task["noise_seed"])
    write_field(task["path"], img, w, spec, truth=truth)
    return int((~np.asarray(truth["is_star"])).sum()), len(truth)


def read_manifest(directory: str | Path) -> dict:
    """Read the ``manifest.json`` of a validation set written by :func:`simulate_step`.

    Parameters
    ----------
    directory : str or pathlib.Path
        The set's directory.

    Returns
    -------
    dict
        The manifest, with ``"dir"`` (the directory) added and every field's and star
        field's ``"path"`` (absolute path of its FITS file).
    """
    directory = Path(directory)
    with open(directory / "manifest.json") as fh:
        man = json.load(fh)
    man["dir"] = str(directory)
    for f in man["fields"] + man["star_fields"]:
        f["path"] = str(directory / f["file"])
    return man
