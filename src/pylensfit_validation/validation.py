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

import hashlib
import json
import logging
import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from functools import lru_cache, partial
from pathlib import Path
from typing import Any

import numpy as np
from astropy.table import Table, vstack
from scipy.optimize import brentq
from scipy.spatial import cKDTree

from pylensfit import pipeline
from pylensfit.config import Config
from pylensfit.prior import (
    Prior,
    estimate_prior,
    estimate_prior_and_bulge,
    estimate_prior_binned,
    mix_bulge_fractions,
)
from pylensfit.psf import PSFResult, psf_diagnostics, psf_from_image
from pylensfit.psfmodel import PSFModel
from pylensfit.runner import run_tasks
from pylensfit.shear import ShearEstimate, estimate_shear, shapes, shear_fixed_point
from pylensfit.skyframe import SkyFrame, sensitivity_to_sky

from .figures import pyplot_or_none
from .galaxies import GalaxyProfile, PSFProfile, draw_bulge_shapes, draw_sersic_indices
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
    map_psf_model,
    pixel_shear,
    pixel_to_sky_shear,
    simulate_field,
    star_peaks,
    to_pixel_frame,
    truth_table,
    write_field,
)

__all__ = [
    "STEP1_PSFS",
    "STEP2_PSFS",
    "STEP1_SHEARS",
    "simulate_step",
    "read_manifest",
    "render_step2_field",
    "TARGETS",
    "DEFAULT_BINS",
    "QUICK_NGAL",
    "QUICK_PRIOR_NGAL",
    "fit_m_c",
    "psf_leakage",
    "true_psf_image",
    "truth_control_variate",
    "quality_factor",
    "twin_shear",
    "group_shear",
    "c_scatter",
    "bin_index",
    "validate",
    "write_report",
    "quick_validation",
    "step_config",
]

log = logging.getLogger(__name__)

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


def _spec_for(psf: dict, **kw) -> FieldSpec:
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
        renderings, so the set holds half as many distinct galaxies. Off by default
        (a set from a given seed is the same as before the option existed).
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
        sspec = _spec_for(psf, **{**lay.common, "size": lay.star_size, "star_fraction": 1.0})
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
        spec = _spec_for(psf, **kw, g1=g1, g2=g2, rotate=twin, noise_sign=-1.0 if neg else 1.0)
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


# ----------------------------------------------------------------------------------------
# Validation: m, c, sigma_c and Q (Kitching et al. 2008, sections 4 and 5.1; docs: method,
# eq-m-c and eq-quality-factor)
# ----------------------------------------------------------------------------------------
#: Targets: ``|<m>| <= 0.006`` (within its error), ``sigma_c <= 2e-4``, ``Q >= 100``.
TARGETS: dict[str, float] = {"m": 0.006, "sigma_c": 2e-4, "Q": 100.0}
#: The largest excess rms ellipticity residual (the model's, beyond the stars' noise)
#: of a varying PSF model on its held-out stars that the report calls met.
PSF_HELDOUT_TARGET = 1e-3

#: Default binnings of :func:`validate`: four bins (equal counts) of each quantity.
DEFAULT_BINS: dict[str, int] = {"mag": 4, "snr": 4, "size": 4}

_BIN_LABEL = {
    "mag": "magnitude (measured, zeropoint 0)",
    "snr": "S/N (measured model_SNratio)",
    "size": "size r_true / PSF FWHM",
    "morphology": "morphology (STEP2: 0 Sersic, 1 bulge+disc, 2 knotty disc)",
}
#: The ``morphology`` bins that :func:`validate` adds on a STEP2-like set: one per kind.
_MORPHOLOGY_EDGES = (-0.5, 0.5, 1.5, 2.5)
_MATCH_RADIUS = 5.0  # px: detections farther than this from every truth object are unmatched


def _fit_m_c_cov(g_true, g_meas, g_err) -> tuple[float, float, np.ndarray | None]:
    """``(m, c, cov)`` of the chi-square fit; ``m = nan`` and ``cov = None`` without leverage."""
    gt = np.asarray(g_true, dtype=float)
    d = np.asarray(g_meas, dtype=float) - gt
    w = 1.0 / np.asarray(g_err, dtype=float) ** 2
    A = np.column_stack([gt, np.ones_like(gt)])
    F = A.T @ (A * w[:, None])
    if np.linalg.cond(F) > 1e12:  # all g_true equal: only c is measured
        c = float(np.sum(w * d) / np.sum(w))
        return math.nan, c, None
    cov = np.linalg.inv(F)
    m, c = cov @ (A.T @ (w * d))
    return float(m), float(c), cov


def fit_m_c(g_true, g_meas, g_err) -> tuple[float, float, float, float]:
    """Chi-square fit of ``g_meas - g_true = m g_true + c``: ``(m, m_err, c, c_err)``.

    The model is linear, so the 1-sigma errors projected from the (m, c) chi-square grid
    (``delta chi^2 = 1``) are the square roots of the diagonal of the fit covariance.
    """
    m, c, cov = _fit_m_c_cov(g_true, g_meas, g_err)
    if cov is None:
        w = 1.0 / np.asarray(g_err, dtype=float) ** 2
        return math.nan, math.nan, c, float(1.0 / math.sqrt(np.sum(w)))
    return m, float(math.sqrt(cov[0, 0])), c, float(math.sqrt(cov[1, 1]))


def quality_factor(g_true: np.ndarray, g_meas: np.ndarray, g_err: np.ndarray) -> float:
    """Paper's ``Q = 1000 sigma_stat^2 / <(g_meas - g_true)^2>`` over images and components.

    ``g_*`` are ``(n_images, 2)``; ``sigma_stat^2`` is the mean statistical variance of
    the images' estimates (``g_err^2``), the spread an unbiased method would show.
    """
    d2 = (np.asarray(g_meas) - np.asarray(g_true)) ** 2
    return float(1000.0 * np.mean(np.asarray(g_err) ** 2) / np.mean(d2))


def twin_shear(
    e_a: np.ndarray, e_b: np.ndarray, sens_a: np.ndarray, sens_b: np.ndarray
) -> ShearEstimate:
    """Shear of an image and its 90-degree-rotated twin, galaxy by galaxy (STEP2).

    Each galaxy ``a`` of the image is paired with its rotated counterpart ``b``; the
    intrinsic ellipticities cancel in ``e_a + e_b`` to first order in the shear
    (Kitching et al. 2008, section 4.2, after Massey et al. 2007). The pair's estimate
    is the mean shear over mean sensitivity (docs: method, eq-key2) over both images,
    ``g_i = sum_pairs (e_a,i + e_b,i) / sum_pairs (s_a,i + s_b,i)``, and its error comes
    from the scatter of the per-pair sums,
    ``std(e_a,i + e_b,i - g_i (s_a,i + s_b,i)) sqrt(N_pairs) / sum_pairs (s_a,i + s_b,i)``,
    so that it shows the cancellation (only measurement noise and the residual
    ``O(g e^2)`` terms remain). :func:`group_shear` is the same for groups of any size
    (twins and noise twins).

    Parameters
    ----------
    e_a, e_b : numpy.ndarray
        ``(n_pairs, 2)`` posterior mean ellipticities of the matched galaxies in the image
        and in its twin (row ``i`` of both is the same galaxy).
    sens_a, sens_b : numpy.ndarray
        ``(n_pairs, 2)`` their shear sensitivities ``d<e_i>/dg_i``.

    Returns
    -------
    ShearEstimate
        ``n`` is the number of pairs used (rows with any non-finite value are skipped).

    Raises
    ------
    ValueError
        On arrays of different shapes, no usable pair, or a non-positive summed sensitivity.
    """
    arrs = [np.asarray(a, dtype=float).reshape(-1, 2) for a in (e_a, e_b, sens_a, sens_b)]
    if len({a.shape for a in arrs}) != 1:
        raise ValueError("e_a, e_b, sens_a, sens_b must have the same (n_pairs, 2) shape")
    return group_shear(np.stack(arrs[:2], axis=1), np.stack(arrs[2:], axis=1))


def group_shear(e: np.ndarray, sens: np.ndarray) -> ShearEstimate:
    """Shear of a group of renderings of the same galaxies, summed galaxy by galaxy.

    A group is an image and its twins: the 90-degree-rotated one (the intrinsic shapes
    cancel) and, for a set simulated with noise twins, the two with their noise negated
    (the noise's first-order response cancels). The estimate is the mean shear over mean
    sensitivity (docs: method, eq-key2) over the whole group,
    ``g_i = sum_galaxies sum_members e_i / sum_galaxies sum_members s_i``, and its error
    comes from the scatter of the per-galaxy sums over the members,
    ``std(sum_members (e_i - g_i s_i)) sqrt(N) / sum s_i`` (the ratio estimator's), so
    that it shows the cancellations.

    Parameters
    ----------
    e : numpy.ndarray
        ``(n_galaxies, n_members, 2)`` posterior mean ellipticities; row ``i`` of every
        member is the same galaxy.
    sens : numpy.ndarray
        Their shear sensitivities ``d<e_i>/dg_i``, the same shape.

    Returns
    -------
    ShearEstimate
        ``n`` is the number of galaxies used (those with any non-finite value in any
        member are skipped).

    Raises
    ------
    ValueError
        On arrays of different or wrong shapes, no usable galaxy, or a non-positive summed
        sensitivity.
    """
    e, sens = np.asarray(e, dtype=float), np.asarray(sens, dtype=float)
    if e.shape != sens.shape or e.ndim != 3 or e.shape[2] != 2:
        raise ValueError("e and sens must have the same (n_galaxies, n_members, 2) shape, "
                         f"got {e.shape} and {sens.shape}")  # fmt: skip
    ok = np.all(np.isfinite(e), axis=(1, 2)) & np.all(np.isfinite(sens), axis=(1, 2))
    n = int(ok.sum())
    if n == 0:
        raise ValueError("no usable galaxy to estimate shear")
    esum, ssum = e[ok].sum(axis=1), sens[ok].sum(axis=1)
    out = []
    for i in range(2):
        s = float(ssum[:, i].sum())
        if not s > 0:
            raise ValueError(f"the sum of the group sensitivities (component {i + 1}) is {s}")
        g = float(esum[:, i].sum()) / s
        # the ratio estimator's error: the scatter of the residuals e - g s (at STEP's
        # shears of up to 0.1 the sensitivities' own scatter times g is most of std(e)
        # once the twins have cancelled the shapes and the noise)
        err = float(np.std(esum[:, i] - g * ssum[:, i], ddof=1)) * math.sqrt(n) / s if n > 1 \
            else math.nan
        out.append((g, err))
    return ShearEstimate(g1=out[0][0], g2=out[1][0], g1_err=out[0][1], g2_err=out[1][1], n=n)


def truth_control_variate(r: np.ndarray, t: np.ndarray, t_pop: np.ndarray,
                          scale: float) -> tuple[float, float]:
    """The truth's shape noise as a control variate for one shear component of one image.

    A simulation knows each galaxy's true sheared ellipticity ``e_true`` (for a group of
    renderings, summed over its members), and ``t = e_true - g`` has expectation zero
    over an isotropic population of intrinsic shapes, exactly (``e_true = (e_s + g) /
    (1 + g* e_s)`` is analytic in ``e_s``, so its mean over the position angle is its
    value at ``e_s = 0``). Its sample mean over an image's population is pure sampling
    noise: for a single image, the shape noise itself; for a 90-degree twin pair, the
    second-order term ``-2 g* e_s^2`` that the rotation leaves, which makes c2 of a STEP1
    field at ``g1 = 0.1`` scatter 2.4 times as much as at ``g1 = 0``. The estimate
    ``g_hat`` (whatever the estimator) becomes ``g_hat - beta N <t>_pop / D``, where
    ``<t>_pop`` is the mean of ``t`` over **every** truth galaxy of the image (measured
    or not), ``N`` the measured truth galaxies, ``D`` the estimator's denominator
    (``sum s`` for the mean shear over mean sensitivity, eq-key2) and ``beta`` the
    regression slope of the residuals ``e - g s`` on ``t``. The galaxies lost to cuts
    and failed fits differ from the population only by their own ``t``: what a selection
    that responds to the shape does to the estimate stays in it; only the population's
    sampling noise goes. The error is that of
    ``sum (e - g s) - beta sum_measured (t - <t>)`` (the measurement's part) with the
    unmeasured galaxies' share of the population noise,
    ``beta^2 var(t) N (1 - N / N_pop)``.

    Parameters
    ----------
    r : numpy.ndarray
        ``(n,)`` the residuals ``e - g s`` of the galaxies in the estimate: posterior mean
        ellipticities less the shear times their sensitivities (group sums).
    t : numpy.ndarray
        ``(n,)`` their ``e_true - g`` (group sums); NaN for a row that is not a truth
        galaxy (a star fitted as a galaxy, a spurious detection).
    t_pop : numpy.ndarray
        ``(N_pop,)`` the same for every truth galaxy of the image (or group).
    scale : float
        ``1 / D``, the estimator's denominator.

    Returns
    -------
    delta, err : float
        The correction to subtract from the estimate, and the corrected estimate's error.
        ``delta = 0`` and the plain error where ``t`` does not vary (a twin pair at
        ``g = 0``, where the rotation cancels it exactly).
    """
    r = np.asarray(r, dtype=float)
    t = np.asarray(t, dtype=float)
    t_pop = np.asarray(t_pop, dtype=float)
    gal = np.isfinite(t)
    n, n_g = r.size, int(gal.sum())
    tc = t[gal] - t[gal].mean() if n_g else t[gal]
    den = float(np.sum(tc**2))
    beta = float(np.sum((r[gal] - r[gal].mean()) * tc) / den) if n_g > 2 and den > 1e-20 else 0.0
    z = r.copy()
    z[gal] -= beta * tc
    frac = min(n_g / t_pop.size, 1.0) if t_pop.size else 1.0
    var_pop = float(np.var(t_pop, ddof=1)) if t_pop.size > 1 else 0.0
    delta = beta * n_g * float(t_pop.mean()) * scale if t_pop.size else 0.0
    err = math.sqrt(n * float(np.var(z, ddof=1)) + beta**2 * var_pop * n_g * (1.0 - frac)) * scale
    return delta, err


def _truth(path: str | os.PathLike) -> Table:
    """The ``TRUTH`` table of a simulated field, read once per file version (matching the
    galaxies and the truth control read each field's; do not modify it)."""
    st = os.stat(path)
    return _truth_cached(os.fspath(path), st.st_mtime_ns, st.st_size)


@lru_cache(maxsize=256)
def _truth_cached(path: str, mtime_ns: int, size: int) -> Table:
    return Table.read(path, hdu="TRUTH")


def _sky_columns(t: Table, a: str, b: str) -> tuple[str, str]:
    """The sky-frame columns ``a_sky, b_sky`` of a truth table, or the pixel-frame ``a, b``
    of a table without them (simulated with the plain WCS only, where the pixel frame
    is the sky frame)."""
    if f"{a}_sky" in t.colnames and f"{b}_sky" in t.colnames:
        return f"{a}_sky", f"{b}_sky"
    return a, b


def _truth_terms(fields: dict[str, dict], names: list[str]) -> np.ndarray:
    """``(n_truth, 2)``: ``sum over the images names of (e_true - g)`` per truth object of a
    group's images (which share their truth rows); NaN for stars. ``e_true`` and ``g``
    in the sky frame (the truth's ``e1_sky, e2_sky``; the manifest's shears)."""
    out = None
    for name in names:
        f = fields[name]
        t = _truth(f["path"])
        c1, c2 = _sky_columns(t, "e1", "e2")
        d = np.column_stack([np.asarray(t[c1], float) - f["g1"],
                             np.asarray(t[c2], float) - f["g2"]])  # fmt: skip
        d[np.asarray(t["is_star"], bool)] = np.nan
        out = d if out is None else out + d
    return out


def _controlled(res: tuple, e: np.ndarray, s: np.ndarray, t: np.ndarray, t_pop: np.ndarray,
                own_scale: bool = False) -> tuple:  # fmt: skip
    """``(g1, g1_err, g2, g2_err)`` of an estimate with :func:`truth_control_variate` applied
    (``e, s``: the ``(n, 2)`` ellipticities and sensitivities, group sums, it used). The
    estimator's denominator is ``sum s``, or with ``own_scale`` (a single image's fixed
    point, whose error is ``std(e) sqrt(n)`` over its Jacobian) the one its error gives."""
    out = list(res)
    ok = np.all(np.isfinite(e), axis=1) & np.all(np.isfinite(s), axis=1)
    e, s, t = e[ok], s[ok], t[ok]
    for i in range(2):
        g, err = res[2 * i], res[2 * i + 1]
        den = float(s[:, i].sum())
        if not (np.isfinite(g) and np.isfinite(err) and den > 0 and e.shape[0] > 2):
            continue
        scale = (err / (float(np.std(e[:, i], ddof=1)) * math.sqrt(e.shape[0])) if own_scale
                 else 1.0 / den)  # fmt: skip
        r = e[:, i] - (e[:, i].sum() / den) * s[:, i]
        pop = t_pop[:, i][np.isfinite(t_pop[:, i])]
        delta, err_c = truth_control_variate(r, t[:, i], pop, scale)
        out[2 * i], out[2 * i + 1] = g - delta, err_c
    return tuple(out)


# -- measured catalogues, kept under DIR/measured/ ----------------------------------------
#: the kept catalogues' version: one whose sidecar holds another is measured again. It
#: changes when the same configuration measures differently (3: the size prior estimated
#: from every measured galaxy; 4: the calibration recipe of :func:`pylensfit.calibrate`)
_MEASURE_VERSION = 4


def _ident(fields: list[dict], star: dict, cfg, priors=None, psf=None) -> dict:
    """What a kept catalogue was made from: the configuration, the fields' seeds, the
    priors given to the measurement (if any) and the PSF given to it (if any: a
    digest of its image or of its model file; otherwise it came from the star field)."""
    ids = []
    for f in [*fields, star]:
        # the manifest's entry, and the file as it is now (a set simulated again in the
        # same directory, with other parameters but the same seeds, is measured again)
        st = Path(f["path"]).stat() if f.get("path") else None
        ids.append({**{k: v for k, v in f.items() if k != "path"},
                    "bytes": st and st.st_size, "mtime_ns": st and st.st_mtime_ns})  # fmt: skip
    ident = {"version": _MEASURE_VERSION, "config": cfg.to_dict(), "fields": ids}
    if priors is not None:
        ident["priors"] = priors.to_dict()
    if isinstance(psf, Path):  # a PSF model file: its bytes
        ident["psf"] = hashlib.sha1(psf.read_bytes()).hexdigest()
    elif psf is not None:
        ident["psf"] = psf.digest
    return json.loads(json.dumps(ident))


def _measured(name: str, fields: list[dict], star: dict, cfg, mdir: Path, *, jobs: int,
              progress: bool, remeasure: bool, priors=None,
              psf=None) -> tuple[Table, bool]:  # fmt: skip
    """The catalogue of ``fields`` from ``mdir/<name>.fits``, measured unless kept.

    A kept catalogue is reused when its sidecar ``<name>.json`` records the same
    configuration, the same fields (names and seeds) and the same ``priors``.
    Otherwise the fields are measured with :func:`pylensfit.pipeline.measure`
    (``output=``: written atomically, resumable from its ``.parts`` folder; under
    ``priors``, a :class:`~pylensfit.Priors`, if given, else with the priors estimated
    from the fields by the calibration recipe) and the sidecar
    written after the catalogue. With ``psf`` (a :class:`~pylensfit.psf.PSFResult`, a
    :class:`~pylensfit.psfmodel.PSFModel` or the path of a PSF model file) the fields
    are measured with it instead of the star field's PSF.
    """
    cat_path, side = mdir / f"{name}.fits", mdir / f"{name}.json"
    ident = _ident(fields, star, cfg, priors, psf)
    if not remeasure and cat_path.exists() and side.exists():
        try:
            same = json.loads(side.read_text()) == ident
        except (OSError, ValueError):
            same = False
        if same:
            try:
                return pipeline.read_catalogue(cat_path), True
            except (OSError, ValueError) as err:  # a damaged file is remeasured
                log.warning("%s: unreadable kept catalogue (%s); measuring again", cat_path, err)
    mdir.mkdir(parents=True, exist_ok=True)
    side.unlink(missing_ok=True)
    pipeline.measure([f["path"] for f in fields], stars=[star["path"]] if psf is None else None,
                     psf=psf, config=cfg, priors=priors,
                     output=cat_path, overwrite=True, jobs=jobs, progress=progress)  # fmt: skip
    tmp = side.with_name(f".{side.name}.tmp")
    tmp.write_text(json.dumps(ident, indent=1))
    os.replace(tmp, side)
    return pipeline.read_catalogue(cat_path), False


def _galaxies(cat: Table, fields: dict[str, dict], psf: int, psf_fwhm: float,
              sky: tuple[float, bool] = (0.0, False)) -> Table:  # fmt: skip
    """The usable galaxies of a catalogue, matched to the truth of their images.

    Every detection is matched to the nearest truth object within ``_MATCH_RADIUS``
    pixels of its fitted centre (one detection per truth object: the nearest). Returns
    the rows with ``flags == 0``, ``fitclass == 0`` (galaxy) and a finite ``ln L`` grid,
    with ``psf``, ``truth_index`` (-1: unmatched), ``truth_star``, ``e1_int, e2_int``
    (sky frame), ``size`` (truth ``r`` over the FWHM of the PSF at the galaxy, the
    truth's ``psf_fwhm``, or ``psf_fwhm`` (pixels) for a truth without it; NaN when
    unmatched or matched to a star), ``morphology`` (the index in :data:`STEP2_KINDS`
    of a STEP2 galaxy's kind; NaN otherwise), ``mag``, ``snr`` (``model_SNratio``),
    ``psf_e1_true, psf_e2_true`` (the truth's adaptive-moment PSF ellipticity at the
    galaxy, ``psf_e1_obs, psf_e2_obs``, taken to the sky frame by ``sky``, the set's
    WCS rotation in degrees and flip; NaN when unmatched or without them),
    ``psf_e1_model, psf_e2_model`` (the catalogue's ``PSF_e1, PSF_e2``) and ``lnL``.
    """
    lnL = np.asarray(cat["lnL"])
    use = ((np.asarray(cat["flags"]) == 0) & (np.asarray(cat["fitclass"]) == 0)
           & np.isfinite(lnL).all(axis=1))  # fmt: skip
    g = cat[use]
    n = len(g)
    images = np.asarray(g["image"]).astype(str)
    tidx = np.full(n, -1, dtype=np.int64)
    tstar = np.zeros(n, dtype=bool)
    cols = ("r", "fwhm", "e1", "e2", "morph", "pe1", "pe2")
    v = {c: np.full(n, np.nan) for c in cols}
    for name in np.unique(images):
        truth = _truth(fields[name]["path"])
        sel = np.flatnonzero(images == name)
        tree = cKDTree(np.column_stack([truth["x"], truth["y"]]))
        xy = np.column_stack([np.asarray(g["x"])[sel], np.asarray(g["y"])[sel]])
        d, j = tree.query(xy, distance_upper_bound=_MATCH_RADIUS)
        idx = np.flatnonzero(np.isfinite(d))
        idx = idx[np.argsort(d[idx], kind="stable")]
        _, first = np.unique(j[idx], return_index=True)
        keep = idx[first]
        rows, jj = sel[keep], j[keep]
        tidx[rows] = jj
        tstar[rows] = np.asarray(truth["is_star"])[jj]
        v["r"][rows] = np.asarray(truth["r"])[jj]
        v["fwhm"][rows] = (np.asarray(truth["psf_fwhm"], float)[jj]
                           if "psf_fwhm" in truth.colnames else psf_fwhm)  # fmt: skip
        for k, c in zip(("e1", "e2"), _sky_columns(truth, "e1_int", "e2_int"), strict=True):
            v[k][rows] = np.asarray(truth[c])[jj]
        if "psf_e1_obs" in truth.colnames and "psf_e2_obs" in truth.colnames:
            v["pe1"][rows], v["pe2"][rows] = pixel_to_sky_shear(
                np.asarray(truth["psf_e1_obs"], float)[jj],
                np.asarray(truth["psf_e2_obs"], float)[jj], *sky)
        if "kind" in truth.colnames:
            names, inv = np.unique(np.asarray(truth["kind"]).astype(str)[jj], return_inverse=True)
            code = np.array([STEP2_KINDS.index(k) if k in STEP2_KINDS else np.nan for k in names])
            v["morph"][rows] = code[inv]
    out = Table()
    out["psf"] = np.full(n, psf, dtype=np.int64)
    out["image"] = images
    out["truth_index"] = tidx
    out["truth_star"] = tstar
    out["e1_int"], out["e2_int"] = v["e1"], v["e2"]
    out["size"] = np.where(tstar, np.nan, v["r"] / v["fwhm"])
    out["morphology"] = np.where(tstar, np.nan, v["morph"])
    out["mag"] = np.asarray(g["mag"], dtype=float)
    out["snr"] = np.asarray(g["model_SNratio"], dtype=float)
    out["psf_e1_true"] = np.where(tstar, np.nan, v["pe1"])
    out["psf_e2_true"] = np.where(tstar, np.nan, v["pe2"])
    for i in (1, 2):
        out[f"psf_e{i}_model"] = (np.asarray(g[f"PSF_e{i}"], dtype=float)
                                  if f"PSF_e{i}" in g.colnames else np.full(n, np.nan))  # fmt: skip
    out["lnL"] = np.asarray(g["lnL"], dtype=np.float32)
    if "lnL_bulge" in g.colnames:  # each bulge fraction's L(e), for their prior
        out["lnL_bulge"] = np.asarray(g["lnL_bulge"], dtype=np.float32)
        out["lnL_star"] = np.asarray(g["lnL_star"], dtype=float)
    return out


def _check_frame(cat: Table, sky: tuple[float, bool], name: str) -> None:
    """Raise ``ValueError`` when a catalogue's sky frame (its ``sky_angle``, ``sky_flip``
    columns, from the images' WCS) is not the set's (``sky``: the manifest's WCS
    rotation in degrees and its flip), to 0.1 degree: the comparison with the truth
    takes the shapes to the sky frame with the manifest's."""
    if "sky_angle" not in cat.colnames or "sky_flip" not in cat.colnames or not len(cat):
        return
    ang = np.asarray(cat["sky_angle"], dtype=float)
    ok = np.isfinite(ang)
    if "flags" in cat.colnames:  # the measured rows (a position: the WCS's frame)
        ok &= np.asarray(cat["flags"]) == 0
    if "ALPHA_J2000" in cat.colnames:
        ok &= np.isfinite(np.asarray(cat["ALPHA_J2000"], dtype=float))
    if not ok.any():
        return
    # spin-2 quantities see the angle modulo 180 degrees
    dev = (ang[ok] - sky[0] + 90.0) % 180.0 - 90.0
    flip = np.asarray(cat["sky_flip"], dtype=bool)[ok]
    if np.max(np.abs(dev)) > 0.1 or np.any(flip != bool(sky[1])):
        raise ValueError(
            f"{name}: the catalogue's sky frame (rotation {np.median(ang[ok]):.3f} deg, "
            f"flipped {bool(np.median(flip))}) is not the manifest's ({sky[0]:g} deg, "
            f"flipped {bool(sky[1])}): the images' WCS disagrees with the set")


def _groups(gal: Table, fields: dict[str, dict]) -> tuple[np.ndarray, np.ndarray]:
    """Each galaxy's group of renderings: an image with its rotated and noise twins.

    The members of a group are the shear fields of one PSF and shear (``(psf,
    shear_index)``): the image, its 90-degree twin and, for a set with noise twins, the
    two with the noise negated. A galaxy belongs to a group when all its members measured
    it (matched by truth index). Returns ``gid``, the group of each row (``-1``: none, or
    a set without twins), numbered consecutively, and ``base``, the file name of the
    group's first member (the unrotated image with the noise as drawn) per row.
    """
    n = len(gal)
    gid = np.full(n, -1, dtype=np.int64)
    base = np.full(n, "", dtype=object)
    images = np.asarray(gal["image"]).astype(str)
    tidx = np.asarray(gal["truth_index"])
    members: dict[tuple, list[dict]] = {}
    for f in fields.values():
        if f["role"] == "shear":
            members.setdefault((f["psf"], f["shear_index"]), []).append(f)
    nxt = 0
    for key in sorted(members):
        mem = sorted(members[key], key=lambda f: (bool(f["twin"]), bool(f.get("noise_twin"))))
        if len(mem) < 2:
            continue
        rows = [np.flatnonzero((images == f["file"]) & (tidx >= 0)) for f in mem]
        common = tidx[rows[0]]
        for r in rows[1:]:
            common = np.intersect1d(common, tidx[r])
        for r in rows:
            _, ir, ic = np.intersect1d(tidx[r], common, return_indices=True)
            gid[r[ir]] = nxt + ic
            base[r[ir]] = mem[0]["file"]
        nxt += common.size
    return gid, base


def _group_members(gid: np.ndarray) -> np.ndarray:
    """``(n_groups, k)`` rows of each group's members from ``gid`` (every group of size k)."""
    use = np.flatnonzero(gid >= 0)
    if use.size == 0:
        return np.zeros((0, 1), dtype=np.int64)
    order = use[np.argsort(gid[use], kind="stable")]
    counts = np.bincount(gid[use])
    counts = counts[counts > 0]
    k = int(counts[0])
    if not np.all(counts == k):
        raise ValueError("groups of renderings of unequal size")
    return order.reshape(-1, k)


def _set_frame(man: dict) -> tuple[float, bool]:
    """The set's WCS rotation (degrees) and flip, from its manifest (plain by default)."""
    return float(man.get("wcs_rotation_deg") or 0.0), bool(man.get("wcs_flip", False))


def _frame_of(n: int, sky: tuple[float, bool]) -> SkyFrame | None:
    """The sky frame of ``n`` rows of a set's images (all share the WCS rotation and
    flip ``sky``), or None for the plain WCS, whose pixel frame is the sky frame."""
    rot, flip = float(sky[0]), bool(sky[1])
    if rot == 0.0 and not flip:
        return None
    return SkyFrame(angle=np.full(n, rot), flip=np.full(n, flip), g1=np.zeros(n),
                    g2=np.zeros(n), has_wcs=np.ones(n, bool))  # fmt: skip


def _to_sky(e: np.ndarray, s: np.ndarray, sky: tuple[float, bool]) -> tuple[np.ndarray, ...]:
    """Pixel-frame ``(n, 2)`` ellipticities and sensitivities in the set's sky frame, as
    the truth's ``e1_sky, e2_sky`` (:func:`pylensfit_validation.simulate.pixel_to_sky_shear`; the
    sensitivities as :func:`pylensfit.skyframe.sensitivity_to_sky`)."""
    fr = _frame_of(e.shape[0], sky)
    if fr is None:
        return e, s
    e1, e2 = pixel_to_sky_shear(e[:, 0], e[:, 1], *sky)
    s1, s2 = sensitivity_to_sky(s[:, 0], s[:, 1], fr)
    return np.column_stack([e1, e2]), np.column_stack([s1, s2])


def _fixed_point(lnL: np.ndarray, egrid: np.ndarray, prior: Prior, refine: int,
                 sky: tuple[float, bool]) -> ShearEstimate:  # fmt: skip
    """:func:`pylensfit.shear_fixed_point` giving the sky-frame shear of a set's images
    (one pixel frame, that of the WCS rotation and flip ``sky``)."""
    fr = _frame_of(lnL.shape[0], sky)
    if fr is None:
        return shear_fixed_point(lnL, egrid, prior, refine=refine)
    return shear_fixed_point(lnL, egrid, prior, refine=refine, frame=fr,
                             groups=np.zeros(lnL.shape[0], dtype=np.int64))  # fmt: skip


_EST_NAMES = ("psf", "file", "g1_true", "g2_true", "g1", "g1_err", "g2", "g2_err", "n", "n_pair")


def _shear_estimates(gal: Table, e: np.ndarray, s: np.ndarray, fields: dict[str, dict], *,
                     pairs: bool, estimator: str, prior: Prior, egrid: np.ndarray,
                     refine: int, truth_control: bool = False,
                     sky: tuple[float, bool] = (0.0, False)) -> Table:  # fmt: skip
    """One shear estimate per image (``pairs=False``) or per image + twin pair, with the
    truth's shape noise taken out (:func:`truth_control_variate`) if ``truth_control``.
    ``e, s`` and the estimates are in the sky frame of the set (``sky``: its WCS
    rotation, degrees, and flip)."""
    images = np.asarray(gal["image"]).astype(str)
    lnL = np.asarray(gal["lnL"])
    rows = []
    nan4 = (math.nan,) * 4
    if not pairs:
        for name in np.unique(images):
            f = fields[name]
            sel = images == name
            try:
                if estimator == "fixed-point":
                    est = _fixed_point(lnL[sel], egrid, prior, refine, sky)
                else:
                    t = Table({"e1": e[sel, 0], "e2": e[sel, 1], "sens1": s[sel, 0],
                               "sens2": s[sel, 1]})  # fmt: skip
                    est = estimate_shear(t)
                res = (est.g1, est.g1_err, est.g2, est.g2_err)
                if truth_control:
                    t_all = _truth_terms(fields, [name])
                    tix = np.asarray(gal["truth_index"])[sel]
                    t = np.full((tix.size, 2), np.nan)
                    t[tix >= 0] = t_all[tix[tix >= 0]]
                    res = _controlled(res, e[sel], s[sel], t, t_all,
                                      own_scale=estimator == "fixed-point")
            except ValueError:
                res = nan4
            rows.append((f["psf"], f["file"], f["g1"], f["g2"], *res, int(sel.sum()), 0))
    else:
        gid, base = _groups(gal, fields)
        members = _group_members(gid)
        members_base = base[members[:, 0]]
        group_files: dict[tuple, list[str]] = {}
        for g in fields.values():
            if g["role"] == "shear":
                group_files.setdefault((g["psf"], g["shear_index"]), []).append(g["file"])
        for name in np.unique(images):
            f = fields[name]
            if f["twin"] or f.get("noise_twin"):
                continue
            rows_k = members[members_base == name]
            # every usable detection of the group's images counts, as in a survey: the
            # galaxies that all members measured are summed over the members (their shape
            # noise and noise cancel), the others (unmatched detections, galaxies that a
            # member missed) are units of their own
            in_group = np.flatnonzero(np.isin(images, group_files[(f["psf"], f["shear_index"])]))
            left = np.setdiff1d(in_group, rows_k.ravel())
            e_u = np.concatenate([e[rows_k].sum(axis=1), e[left]])[:, None, :]
            s_u = np.concatenate([s[rows_k].sum(axis=1), s[left]])[:, None, :]
            try:
                est = group_shear(e_u, s_u)
                res = (est.g1, est.g1_err, est.g2, est.g2_err)
                if estimator == "fixed-point":  # the group together; error from the sums
                    fp = _fixed_point(lnL[in_group], egrid, prior, refine, sky)
                    res = (fp.g1, est.g1_err, fp.g2, est.g2_err)
                if truth_control and len(rows_k):
                    names = sorted({str(images[r]) for r in rows_k[0]})
                    t_all = _truth_terms(fields, names)
                    t = np.full((e_u.shape[0], 2), np.nan)
                    t[: len(rows_k)] = t_all[np.asarray(gal["truth_index"])[rows_k[:, 0]]]
                    res = _controlled(res, e_u[:, 0], s_u[:, 0], t, t_all)
            except ValueError:
                res = nan4
            rows.append((f["psf"], f["file"], f["g1"], f["g2"], *res, in_group.size,
                         rows_k.shape[0]))  # fmt: skip
    if not rows:
        return Table(names=_EST_NAMES, dtype=(int, str, *[float] * 6, int, int))
    return Table(rows=rows, names=_EST_NAMES)


def _mc_rows(est: Table, psfs: list[int]) -> tuple[list[tuple], list[tuple]]:
    """Per PSF and ``all``: the fit rows, and ``(psf, component, m, c, m_err, c_err, rho)``."""
    rows, fits_ = [], []
    vals = np.column_stack([np.asarray(est[c], float) for c in ("g1", "g2", "g1_err", "g2_err")])
    finite = np.all(np.isfinite(vals), axis=1) & np.all(vals[:, 2:] > 0, axis=1)
    for k in [*psfs, "all"]:
        sel = finite & (np.ones(len(est), bool) if k == "all" else np.asarray(est["psf"]) == k)
        t = est[sel]
        res: list[float] = []
        for i in (1, 2):
            if len(t) == 0:
                res += [math.nan] * 4
                continue
            m, c, cov = _fit_m_c_cov(t[f"g{i}_true"], t[f"g{i}"], t[f"g{i}_err"])
            m_, m_err, c_, c_err = fit_m_c(t[f"g{i}_true"], t[f"g{i}"], t[f"g{i}_err"])
            res += [m_, m_err, c_, c_err]
            rho = math.nan if cov is None else float(cov[0, 1] / math.sqrt(cov[0, 0] * cov[1, 1]))
            fits_.append((str(k), i, m_, m_err, c_, c_err, rho))
        if len(t):
            gt = np.column_stack([t["g1_true"], t["g2_true"]])
            gm = np.column_stack([t["g1"], t["g2"]])
            ge = np.column_stack([t["g1_err"], t["g2_err"]])
            q = quality_factor(gt, gm, ge)
        else:
            q = math.nan
        rows.append((str(k), *res, q, int(np.sum(t["n"]))))
    return rows, fits_


_MC_NAMES = ("psf", "m1", "m1_err", "c1", "c1_err", "m2", "m2_err", "c2", "c2_err", "Q", "n_gal")


def _nanmean(x) -> float:
    """Mean of the finite values (NaN, without a warning, when there is none)."""
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(x.mean()) if x.size else math.nan


def _nanstd(x) -> float:
    """Standard deviation of the finite values (NaN when there is none)."""
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(x.std()) if x.size else math.nan


def c_scatter(c: np.ndarray, c_err: np.ndarray, cl: float = 0.95) -> dict[str, float]:
    """The spread of one component of ``c`` over PSFs beyond what its errors give.

    With ``c_k = c0 + d_k + n_k``, ``d_k`` a PSF-dependent offset of spread ``sigma`` and
    ``n_k`` the fit's noise of standard deviation ``c_err[k]``, the statistic
    ``chi2(sigma) = sum_k (c_k - c_hat)^2 / (c_err_k^2 + sigma^2)`` (``c_hat`` the mean
    weighted by ``1 / (c_err_k^2 + sigma^2)``) follows a chi-square with ``n - 1``
    degrees of freedom. Returns ``chi2`` at ``sigma = 0`` with its ``dof`` and ``p``
    (the chance of a larger one from the errors alone), the estimate ``sigma_hat`` (the
    root of ``chi2(sigma) = n - 1``, 0 when ``chi2(0) < n - 1``) and the upper limit
    ``sigma_upper`` at confidence ``cl`` (the root of ``chi2(sigma)`` = its
    ``1 - cl`` quantile: larger spreads would give so small a ``chi2`` less often than
    ``1 - cl``; 0 when even ``sigma = 0`` does).
    """
    from scipy.stats import chi2 as chi2_dist  # scipy.stats: start-up cost (~0.4 s), only here

    c, e = np.asarray(c, dtype=float), np.asarray(c_err, dtype=float)
    ok = np.isfinite(c) & np.isfinite(e) & (e > 0)
    c, e = c[ok], e[ok]
    nan = {"chi2": math.nan, "dof": 0, "p": math.nan, "sigma_hat": math.nan,
           "sigma_upper": math.nan}  # fmt: skip
    if c.size < 2:
        return nan

    def chi2(sig: float) -> float:
        w = 1.0 / (e**2 + sig**2)
        return float(np.sum(w * (c - np.sum(w * c) / np.sum(w)) ** 2))

    dof = c.size - 1
    x0 = chi2(0.0)
    hi = 10.0 * (float(np.ptp(c)) + float(e.max()))  # chi2(hi) is far below any quantile

    def root(target: float) -> float:
        return 0.0 if x0 <= target else float(brentq(lambda s: chi2(s) - target, 0.0, hi))

    return {"chi2": x0, "dof": dof, "p": float(chi2_dist.sf(x0, dof)),
            "sigma_hat": root(float(dof)),
            "sigma_upper": root(float(chi2_dist.ppf(1.0 - cl, dof)))}  # fmt: skip


def _leakage_bins(e, s, x, w, n_bins: int) -> list[tuple]:
    """``(lo, hi, x_b, g_b, err_b, n_b)`` per bin of ``x`` (see :func:`psf_leakage`)."""
    u = np.unique(x)
    if u.size <= n_bins:  # one bin per value (a PSF constant over each image)
        idx, edges = np.searchsorted(u, x), np.column_stack([u, u])
    else:
        e_ = np.unique(np.quantile(x, np.linspace(0.0, 1.0, n_bins + 1)))
        idx, edges = bin_index(x, e_), np.column_stack([e_[:-1], e_[1:]])
    out = []
    for b in range(edges.shape[0]):
        sel = idx == b
        nb = int(sel.sum())
        sw = float(np.sum(w[sel] * s[sel]))
        if nb < 2 or not sw > 0:
            continue
        g = float(np.sum(w[sel] * e[sel])) / sw
        xb = float(np.sum(w[sel] * s[sel] * x[sel])) / sw
        var = nb / (nb - 1) * float(np.sum(w[sel] ** 2 * (e[sel] - g * s[sel]) ** 2))
        out.append((float(edges[b, 0]), float(edges[b, 1]), xb, g, math.sqrt(var) / sw, nb))
    return out


def _line_fit(x: np.ndarray, y: np.ndarray, err: np.ndarray,
              min_spread: float) -> tuple[float, ...]:  # fmt: skip
    """Weighted least squares ``y = c + a x``: ``(a, a_err, c, c_err, chi2, dof)``; ``a``
    NaN and ``c`` the weighted mean when ``x`` spans less than ``min_spread``."""
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(err) & (err > 0)
    x, y, w = x[ok], y[ok], 1.0 / err[ok] ** 2
    if x.size == 0:
        return (math.nan,) * 4 + (math.nan, 0)
    if x.size < 2 or not float(np.ptp(x)) >= min_spread:
        c = float(np.sum(w * y) / np.sum(w))
        return (math.nan, math.nan, c, float(1.0 / math.sqrt(np.sum(w))),
                float(np.sum(w * (y - c) ** 2)), int(x.size - 1))  # fmt: skip
    A = np.column_stack([np.ones_like(x), x])
    cov = np.linalg.inv(A.T @ (A * w[:, None]))
    c, a = cov @ (A.T @ (w * y))
    chi2 = float(np.sum(w * (y - c - a * x) ** 2))
    return (float(a), float(math.sqrt(cov[1, 1])), float(c), float(math.sqrt(cov[0, 0])), chi2,
            int(x.size - 2))  # fmt: skip


def psf_leakage(e1, e2, sens1, sens2, psf_e1, psf_e2, *, n_bins: int = 8, weights=None,
                min_spread: float = 1e-4) -> dict[str, Any]:  # fmt: skip
    """PSF leakage: the mean shear against the PSF's ellipticity, ``g_i = c_i + alpha_i e_psf,i``.

    For each component ``i`` the galaxies are binned by the ellipticity of the PSF at
    their position, ``e_psf,i`` (``n_bins`` bins of equal counts, or one bin per
    distinct value when there are no more than ``n_bins``, as for a PSF constant over
    each image). A bin's shear is the mean shear over mean sensitivity (docs: method,
    eq-key2), ``g_b = sum w e_i / sum w s_i``, with the error from the scatter of its
    galaxies, ``sqrt(n_b / (n_b - 1) sum w^2 (e_i - g_b s_i)^2) / sum w s_i``, at the
    sensitivity-weighted mean PSF ellipticity ``x_b = sum w s_i e_psf,i / sum w s_i``
    (for ``e_i = s_i (c_i + alpha_i e_psf,i)`` plus noise, ``g_b = c_i + alpha_i x_b``
    exactly). ``c_i, alpha_i`` are the weighted least-squares fit of ``g_b`` on ``x_b``
    (weights ``1 / err_b^2``), with the errors of its covariance.

    Parameters
    ----------
    e1, e2 : array_like
        ``(n,)`` ellipticities, or their residuals ``e - s g`` from a known shear ``g``,
        in the frame of ``psf_e1, psf_e2`` (dimensionless).
    sens1, sens2 : array_like
        ``(n,)`` shear sensitivities ``d<e_i>/dg_i``.
    psf_e1, psf_e2 : array_like
        ``(n,)`` the PSF's ellipticity at each galaxy (dimensionless).
    n_bins : int
        Bins per component.
    weights : array_like, optional
        ``(n,)`` per-galaxy weights (default 1, e.g. the catalogue's inverse-variance
        ``weight``); rows with a weight of 0 or any non-finite value are skipped.
    min_spread : float
        Least range of the bins' PSF ellipticities ``x_b`` for ``alpha`` to be fitted
        (dimensionless); below it only ``c`` is (a PSF constant over the sample, to
        rounding or to the ~1e-7 that the WCS's local frame moves it by).

    Returns
    -------
    dict
        ``alpha1, alpha1_err, c1, c1_err`` and the same for component 2
        (dimensionless; ``alpha`` NaN where the bins' PSF ellipticities span less than
        ``min_spread``, ``c`` then the sample's mean shear), ``chi2_1, dof_1, chi2_2,
        dof_2`` of the fits, ``n1, n2`` (galaxies used) and ``bins``, a table with one
        row per component and bin: ``component``, ``bin``, ``lo, hi`` (the bin's range of
        ``e_psf``), ``psf_e`` (``x_b``), ``g``, ``g_err``, ``n``.
    """
    e = [np.asarray(a, dtype=float).ravel() for a in (e1, e2)]
    s = [np.asarray(a, dtype=float).ravel() for a in (sens1, sens2)]
    x = [np.asarray(a, dtype=float).ravel() for a in (psf_e1, psf_e2)]
    n = e[0].size
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float).ravel()
    if any(a.size != n for a in (*e, *s, *x, w)):
        raise ValueError("e1, e2, sens1, sens2, psf_e1, psf_e2 and weights must have one "
                         "value per galaxy")  # fmt: skip
    if int(n_bins) < 1:
        raise ValueError(f"n_bins must be at least 1, got {n_bins}")
    out: dict[str, Any] = {}
    rows = []
    for i in (0, 1):
        ok = (np.isfinite(e[i]) & np.isfinite(s[i]) & np.isfinite(x[i]) & np.isfinite(w)
              & (w > 0))  # fmt: skip
        b = _leakage_bins(e[i][ok], s[i][ok], x[i][ok], w[ok], int(n_bins))
        arr = np.array([r[2:5] for r in b], dtype=float).reshape(-1, 3)
        a, ae, c, ce, chi2, dof = _line_fit(arr[:, 0], arr[:, 1], arr[:, 2], min_spread)
        k = i + 1
        out.update({f"alpha{k}": a, f"alpha{k}_err": ae, f"c{k}": c, f"c{k}_err": ce,
                    f"chi2_{k}": chi2, f"dof_{k}": dof, f"n{k}": int(ok.sum())})  # fmt: skip
        rows += [(k, j, *r) for j, r in enumerate(b)]
    out["bins"] = Table(rows=rows, names=("component", "bin", "lo", "hi", "psf_e", "g", "g_err",
                                          "n"),
                        dtype=(int, int, float, float, float, float, float, int))  # fmt: skip
    return out


_LEAK_NAMES = ("psf", "source", "alpha1", "alpha1_err", "alpha2", "alpha2_err", "c1", "c1_err",
               "c2", "c2_err", "n")  # fmt: skip


def _leakage_table(gal: Table, e: np.ndarray, s: np.ndarray, fields: dict[str, dict],
                   psfs: list[int], pairs: bool, n_bins: int = 8) -> Table:  # fmt: skip
    """:func:`psf_leakage` per PSF and for all PSFs together (``psf == "all"``), with the
    truth's PSF (``source == "truth"``: its ellipticity at each galaxy) and with the
    catalogue's model PSF (``"model"``).

    The galaxies matched to the truth enter with their residuals from their image's
    shear, ``e - s g`` (``e, s``: the ``(n, 2)`` sky-frame shapes and sensitivities of
    ``gal``'s rows; ``g`` the manifest's), so that images of different shears combine;
    for a set with twins, the members of each group are summed (their shape noise
    cancels) at the members' mean PSF ellipticity, and the galaxies outside the groups
    are left out. ``n`` counts the galaxies (or groups) used.
    """
    names, inv = np.unique(np.asarray(gal["image"]).astype(str), return_inverse=True)
    g = np.array([[fields[m]["g1"], fields[m]["g2"]] for m in names], float).reshape(-1, 2)
    r = e - s * g[inv]
    matched = (np.asarray(gal["truth_index"]) >= 0) & ~np.asarray(gal["truth_star"], bool)
    if pairs:
        mem = _group_members(_groups(gal, fields)[0])
        mem = mem[matched[mem].all(axis=1)]
    else:
        mem = np.flatnonzero(matched)[:, None]
    R, S = r[mem].sum(axis=1), s[mem].sum(axis=1)
    psf_of = np.asarray(gal["psf"])[mem[:, 0]]
    rows = []
    for source, col in (("truth", "true"), ("model", "model")):
        P = np.column_stack([np.asarray(gal[f"psf_e{i}_{col}"], float)[mem].mean(axis=1)
                             for i in (1, 2)])  # fmt: skip
        for k in [*psfs, "all"]:
            sel = np.ones(len(R), bool) if k == "all" else psf_of == k
            res = psf_leakage(R[sel, 0], R[sel, 1], S[sel, 0], S[sel, 1], P[sel, 0], P[sel, 1],
                              n_bins=n_bins)  # fmt: skip
            rows.append((str(k), source, *(res[q] for q in _LEAK_NAMES[2:-1]),
                         min(res["n1"], res["n2"])))  # fmt: skip
    return Table(rows=rows, names=_LEAK_NAMES,
                 dtype=(str, str, *[float] * 8, int))  # fmt: skip


def _summary(per: Table) -> dict[str, float]:
    """``<m>`` over PSFs and components, its errors, ``sigma_c``, its statistical floor and
    the spread of ``c`` beyond the errors (:func:`c_scatter`)."""
    ms = np.concatenate([per["m1"], per["m2"]]).astype(float)
    me = np.concatenate([per["m1_err"], per["m2_err"]]).astype(float)
    ok = np.isfinite(ms) & np.isfinite(me)
    c1, c2 = np.asarray(per["c1"], float), np.asarray(per["c2"], float)
    e1, e2 = np.asarray(per["c1_err"], float), np.asarray(per["c2_err"], float)
    return {
        "mean_m": float(np.mean(ms[ok])) if ok.any() else math.nan,
        # error of the mean of the PSFs' m (independent fits)
        "mean_m_err": float(math.sqrt(np.sum(me[ok] ** 2)) / ok.sum()) if ok.any() else math.nan,
        # the paper's error of <m> (Kitching et al. 2008, section 4.2): the PSFs' mean error
        "mean_m_err_paper": float(np.mean(me[ok])) if ok.any() else math.nan,
        "sigma_c": float(math.hypot(_nanstd(c1), _nanstd(c2))),
        # what sigma_c would be from the fits' errors alone
        "sigma_c_stat": float(np.hypot(np.sqrt(_nanmean(e1**2)), np.sqrt(_nanmean(e2**2)))),
        "mean_c1": _nanmean(c1),
        "mean_c2": _nanmean(c2),
        **_intrinsic_sigma_c(c1, e1, c2, e2),
    }


def _intrinsic_sigma_c(c1, e1, c2, e2) -> dict[str, float]:
    """``sigma_c`` of the offsets alone, the noise taken out (:func:`c_scatter` per
    component, combined as the paper's ``sqrt(sigma_c1^2 + sigma_c2^2)``)."""
    a, b = c_scatter(c1, e1), c_scatter(c2, e2)
    return {"sigma_c_hat": float(math.hypot(a["sigma_hat"], b["sigma_hat"])),
            "sigma_c_upper": float(math.hypot(a["sigma_upper"], b["sigma_upper"])),
            "c1_chi2": a["chi2"], "c2_chi2": b["chi2"], "c_dof": a["dof"],
            "c1_p": a["p"], "c2_p": b["p"]}  # fmt: skip


def _bin_edges(values: np.ndarray, spec, extra: np.ndarray) -> np.ndarray:
    """Edges from ``spec`` (a number of equal-count bins of ``values``, or the edges)."""
    if np.ndim(spec) == 0:
        n = int(spec)
        v = values[np.isfinite(values)]
        if n < 1 or v.size == 0:
            return np.array([])
        edges = np.quantile(v, np.linspace(0.0, 1.0, n + 1))
        allv = np.concatenate([v, extra[np.isfinite(extra)]])
        edges[0], edges[-1] = min(edges[0], allv.min()), max(edges[-1], allv.max())
        return np.unique(edges)
    edges = np.asarray(spec, dtype=float)
    if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
        raise ValueError(f"bin edges must increase, got {list(edges)}")
    return edges


def bin_index(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Bin of each value, ``edges[i] <= v < edges[i+1]`` (last bin closed); ``-1`` outside.

    The same convention as :class:`pylensfit.prior.BinnedPrior`, so that a galaxy's prior
    and its shear bin agree.
    """
    values = np.asarray(values, dtype=float)
    edges = np.asarray(edges, dtype=float)
    idx = np.searchsorted(edges, values, side="right") - 1
    idx[values == edges[-1]] = edges.size - 2
    idx[(idx < 0) | (idx >= edges.size - 1) | ~np.isfinite(values)] = -1
    return idx


_BIN_NAMES = ("kind", "bin", "lo", "hi", "center", "psf", "n_gal", "n_used", "n_prior",
              "prior_fallback",
              "m1", "m1_err", "c1", "c1_err", "m2", "m2_err", "c2", "c2_err", "Q", "mean_m",
              "mean_m_err", "mean_c", "mean_c_err")  # fmt: skip


def _bins_table(kind, edges, pg, sg, e_s_of, psfs, fields, pairs, estimator, egrid, cfg,
                min_count, sky=(0.0, False)) -> list[tuple]:  # fmt: skip
    """Rows of ``meta["bins"]`` for one binned quantity (see :func:`validate`)."""
    vp, vs = np.asarray(pg[kind], float), np.asarray(sg["_bin_" + kind], float)
    okp = np.isfinite(vp)
    bp = estimate_prior_binned(np.asarray(pg["lnL"])[okp], egrid, vp[okp], edges,
                               min_count=min_count, method=cfg.prior_method)  # fmt: skip
    idx = bin_index(vs, edges)
    rows = []
    for b in range(edges.size - 1):
        prior_b = bp.prior_for_bin(b)
        sel = idx == b
        sub = sg[sel]
        e, s = e_s_of(sub, prior_b)
        est = _shear_estimates(sub, e, s, fields, pairs=pairs, estimator=estimator,
                               prior=prior_b, egrid=egrid, refine=cfg.output_refine,
                               sky=sky)  # fmt: skip
        mc, _ = _mc_rows(est, psfs)
        center = float(np.median(vs[sel])) if sel.any() else 0.5 * (edges[b] + edges[b + 1])
        for row in mc:
            # <m> over the components (and, for "all", over the PSFs as well, as the paper)
            use = mc[:-1] if row[0] == "all" else [row]
            ms = np.array([v for r in use for v in (r[1], r[5])], float)
            mes = np.array([v for r in use for v in (r[2], r[6])], float)
            ok = np.isfinite(ms) & np.isfinite(mes)
            mm = float(ms[ok].mean()) if ok.any() else math.nan
            mme = float(math.sqrt(np.sum(mes[ok] ** 2)) / ok.sum()) if ok.any() else math.nan
            mc_ = _nanmean([row[3], row[7]])
            mce = 0.5 * math.hypot(row[4], row[8])
            sp = np.asarray(sub["psf"])
            n_bin = len(sub) if row[0] == "all" else int(np.sum(sp == int(row[0])))
            rows.append((kind, b, float(edges[b]), float(edges[b + 1]), center, row[0], n_bin,
                         row[10], int(bp.counts[b]), bool(bp.fallback[b]), *row[1:10], mm, mme,
                         mc_, mce))  # fmt: skip
    return rows


def _prior_check(prior: Prior, e_int: np.ndarray, true_params, n_bins: int = 20) -> dict:
    """The recovered prior against the truth: histogram of ``|e_int|`` and residuals.

    Returns the histogram (``edges``, ``counts``, ``density``, ``density_err``), the
    recovered and true radial densities at the bin centres (``recovered``, ``true``;
    ``2 pi |e| P(|e|)``), and the fractional residual rms where the recovered density
    exceeds 5% of its peak: of the histogram (``rms_hist``, with its Poisson expectation
    ``rms_poisson``) and of the true functional form (``rms_true``, noise free).
    """
    a = np.hypot(e_int[:, 0], e_int[:, 1])
    a = a[np.isfinite(a)]
    edges = np.linspace(0.0, 1.0, n_bins + 1)
    counts, _ = np.histogram(a, edges)
    width = np.diff(edges)
    n = max(a.size, 1)
    dens = counts / (n * width)
    dens_err = np.sqrt(np.maximum(counts, 1)) / (n * width)
    mid = 0.5 * (edges[1:] + edges[:-1])
    fine = np.linspace(0.0, 1.0, 2001)
    rec_f = prior.radial_pdf(fine[:-1] + 2.5e-4)

    def binned(p: np.ndarray) -> np.ndarray:  # bin averages of a density on the fine grid
        return p.reshape(n_bins, -1).mean(axis=1)

    rec = binned(rec_f)
    out = {"edges": edges, "mid": mid, "counts": counts, "density": dens,
           "density_err": dens_err, "recovered": rec, "n": int(a.size)}  # fmt: skip
    use = rec > 0.05 * rec.max()
    frac = dens[use] / rec[use] - 1
    out["rms_hist"] = float(np.sqrt(np.mean(frac**2)))
    out["rms_poisson"] = float(np.sqrt(np.mean(1.0 / np.maximum(counts[use], 1))))
    out["true"] = None
    out["rms_true"] = math.nan
    if true_params is not None:
        tp = Prior(B=true_params[0], C=true_params[1], D=true_params[2], egrid=prior.egrid)
        tr = binned(tp.radial_pdf(fine[:-1] + 2.5e-4))
        out["true"] = tr
        out["rms_true"] = float(np.sqrt(np.mean((tr[use] / rec[use] - 1) ** 2)))
    return out


def step_config(n_bulge_fractions: int = 5) -> Config:
    """``Config()`` with ``n_bulge_fractions`` bulge fractions (the default's three, or five).

    The bulge+disc model (bulge half-light radius 0.6 disc scale lengths) with its bulge
    fraction marginalised over ``n_bulge_fractions`` values evenly spaced on [0, 1], every
    prior estimated by the calibration recipe on the zero-shear fields.

    * Five fractions rather than three take 0.004 off STEP2's ``<m>``: -0.0042 +- 0.0020
      (m1) and -0.0043 +- 0.0021 (m2), paired on the same 100,000-galaxy set, for about
      a third more time. The Sersic and bulge+disc galaxies gain; the knotty discs do not.
    * The estimated size prior: with the flat one, STEP1's ``<m>`` is higher by about
      0.01 and STEP2's by 0.011.

    Measurements in ``benchmarks/README.md``. The quick tier
    (:func:`quick_validation`) uses three fractions, to stay within its 10 minutes.
    """
    return Config(n_bulge_fractions=n_bulge_fractions)


def validate(directory: str | Path, *, config=None, jobs: int = 1, estimator: str = "fixed-point",
             report: str | Path | None = None, progress: bool = True, remeasure: bool = False,
             bins: dict[str, int | Sequence[float]] | None = None, bin_min_count: int = 300,
             true_psf: bool = False, truth_control: bool = False,
             psf_models: Mapping[int, str | os.PathLike] | None = None):  # fmt: skip
    """Run the pipeline on a simulated set and measure m, c, sigma_c and Q per PSF and bin.

    1. **Measure** each PSF's zero-shear (prior) fields and its shear fields with its own
       star field, keeping the catalogues in ``DIR/measured/psf{k}_prior.fits`` and
       ``psf{k}_shear.fits`` (with ``.json`` sidecars recording the configuration and the
       fields' seeds). A later call with the same configuration reuses them, so a large set
       is re-analysed (other estimator, other bins) without re-measuring;
       ``remeasure=True`` forces a new measurement. With ``size_prior: estimated`` the
       size prior is estimated on each PSF's zero-shear field and the shear fields are
       measured with it (recorded in their sidecars), as the ellipticity prior comes
       from the zero-shear fields.
    2. **Match** every usable galaxy (``flags == 0``, ``fitclass == 0``) to the truth of
       its image (nearest truth object within 5 px), for the diagnostics, the pairing of
       the twins and the truth control variate only: every usable row enters the shear,
       matched or not, as in a survey.
    3. **Prior** from the galaxies of the zero-shear fields of all PSFs (as in the paper).
    4. **Shear** per image (the mean shear over mean sensitivity, docs: method, eq-key2,
       or the sheared-prior fixed point, eq-fixed-point,
       ``estimator``). For STEP2-like sets, each image and its 90-degree-rotated twin are
       combined galaxy by galaxy (the galaxies measured in every member are summed over
       the members, which cancels their shape noise; every other usable detection of the
       group's images enters on its own); these group estimates enter the fits and Q,
       the single-image ones are kept in ``meta``. The bins use the matched galaxies.
    5. **Fit** ``g_meas - g_true = m g_true + c`` per PSF and component, ``<m>``,
       ``sigma_c`` and Q (paper section 5).
    6. **Bins** (paper Table 2): the same per bin of each quantity in ``bins``, with a
       prior per bin estimated from the prior-field galaxies of that bin
       (:func:`pylensfit.prior.estimate_prior_binned`; a bin with fewer than
       ``bin_min_count`` of them uses the global prior, as noted in the table).
    7. **PSF leakage**: ``alpha`` of ``g = c + alpha e_psf`` (:func:`psf_leakage`) per
       PSF and over all PSFs, on the galaxies matched to the truth (their residuals
       from the input shear; twin groups summed), with the truth's PSF ellipticity at
       each galaxy and with the catalogue's model PSF.

    The binned quantities are those a lensing analysis would use:

    - ``"mag"``: the measured magnitude (detection flux, zeropoint 0), as the paper's
      SExtractor magnitudes; an observable, independent of the shear.
    - ``"snr"``: the measured matched-filter S/N of the best model (``model_SNratio``):
      the noise regime, where noise bias shows.
    - ``"size"``: the true size over the PSF FWHM, ``r_true / FWHM`` (the disc scale
      length for step1, the half-light radius for step2): how well a galaxy is resolved,
      from the truth as in the paper (a measured size would add the selection bias of a
      cut on the noisy fit); unmatched detections drop out of these bins only.
    - ``"morphology"``: a STEP2 galaxy's kind (Sersic, bulge+disc, knotty disc), from
      the truth: where the model family fits worst. Its prior per bin is the kind's own.

    A twin pair's bin is that of its members' mean value (it never straddles two bins).
    Bins partition the usable galaxies with a finite value.

    Parameters
    ----------
    directory : str or pathlib.Path
        A set written by :func:`simulate_step`.
    config : Config, optional
        Pipeline settings (default ``Config()``, what a user gets: every prior estimated
        per PSF on the zero-shear field by the calibration recipe; :func:`step_config`
        is the variant with five bulge fractions).
    jobs : int
        Local worker processes of :func:`pylensfit.measure`.
    estimator : {"fixed-point", "key2"}
        Shear estimator: the fixed point of :func:`pylensfit.shear_fixed_point` (default;
        for twins, that of both images together, with the error of :func:`twin_shear`),
        or the paper's mean shear over mean sensitivity (docs: method, eq-key2), whose
        ``+g^2`` term STEP's shears of up to 0.1 bring out: +0.009 in m on the 100k STEP1
        set (``benchmarks/README.md``, "What the studies found").
    report : str or pathlib.Path, optional
        Write a Markdown report here with its PNG figures beside it
        (:func:`write_report`).
    progress : bool
        Progress bars while measuring.
    remeasure : bool
        Measure again even if kept catalogues match.
    bins : dict, optional
        ``{quantity: n_bins or edges}`` for quantities ``"mag"``, ``"snr"``, ``"size"``,
        ``"morphology"`` (default :data:`DEFAULT_BINS`; ``{}`` for none). On a STEP2-like
        set, one bin per galaxy kind of :data:`STEP2_KINDS` is added unless ``bins`` is
        empty or gives ``"morphology"`` itself. An integer gives bins of equal counts of
        shear-field galaxies, the outer edges widened to every galaxy. A quantity that
        no galaxy has (``"morphology"`` on a STEP1-like set) is skipped.
    bin_min_count : int
        Fewest prior-field galaxies for a bin to get its own prior.
    true_psf : bool
        Diagnostic: fit with each PSF's true image (:func:`true_psf_image`, as large as
        the largest stamp; if the PSF varies over the field, its map
        :func:`pylensfit_validation.simulate.map_psf_model`: each galaxy with its own PSF), not the
        stars', keeping the catalogues in ``DIR/measured_true_psf/``. The difference from
        a run with the modelled PSF is what the PSF model does to m and c (same noise).
    psf_models : mapping, optional
        ``{psf index: file}`` for every PSF: its fields fitted with the model in the
        file (:func:`pylensfit.psfmodel.read_psf_model`: Piff's, a polynomial model, an
        image), not its star field's; catalogues in ``DIR/measured_psf_models/``.
    truth_control : bool
        Take the truth's shape noise out of each image's (or group's) estimate with
        :func:`truth_control_variate`: the true sheared ellipticities' departure from
        the image's shear, whose expectation is zero, as a control variate. The same m
        and c are estimated with smaller errors: a single image loses its shape noise;
        a twin group the rotation's second-order residual at large shears. What a
        selection does stays in. The per-image and per-group estimates only, not the
        bins (whose galaxies are a measured subset: the population's mean is not
        theirs).

    Returns
    -------
    astropy.table.Table
        One row per PSF and a last row ``all`` (a joint fit):
        ``m1, m1_err, c1, c1_err, m2, m2_err, c2, c2_err, Q, n_gal``. ``meta`` holds
        ``mean_m`` (over PSFs and components), ``mean_m_err`` (its error),
        ``mean_m_err_paper`` (the paper's, the mean of the PSFs' errors: Kitching et al.
        2008, section 4.2), ``sigma_c``, ``sigma_c_stat`` (what the fits' errors alone
        give), ``sigma_c_hat`` and ``sigma_c_upper`` (the offsets' own spread over PSFs
        with the noise taken out, and its 95 % upper limit: :func:`c_scatter`;
        ``c1_chi2``, ``c2_chi2``, ``c_dof``, ``c1_p``, ``c2_p`` its chi-squares), ``prior``,
        ``mode`` (``"pairs"`` or ``"images"``), ``estimates`` (the per-image or per-pair
        table the fits used), ``images`` (single-image estimates), ``pairs`` (step2),
        ``single`` (step2: the per-PSF fit table from single images), ``fits`` (per PSF and
        component, with the m-c correlation ``rho``), ``bins`` (one row per quantity, bin
        and PSF plus ``psf == "all"``, a joint fit: ``kind, bin, lo, hi, center`` (median
        value), ``n_gal`` (galaxies in the bin), ``n_used`` (in the fits: images or pairs
        with fewer than 2 galaxies or pairs in the bin drop out), ``n_prior``,
        ``prior_fallback``, ``m1 ... c2_err, Q``, ``mean_m, mean_m_err`` (over the two
        components; for ``all``, over PSFs and components as ``<m>``), ``mean_c,
        mean_c_err``), ``bin_edges``,
        ``psf_check``, ``prior_check``, ``diagnosis`` and ``measured`` (the catalogue
        paths and whether each was reused), ``psf_source`` (``"stars"`` or ``"true"``),
        ``leakage`` (the PSF leakage ``alpha`` of :func:`psf_leakage` per PSF and ``all``,
        with the true and with the model PSF: columns ``psf, source, alpha1, alpha1_err,
        alpha2, alpha2_err, c1, c1_err, c2, c2_err, n``).

        Shapes, shears and the truth are compared in the sky frame of the set's WCS
        (its manifest's ``wcs_rotation_deg`` and ``wcs_flip``): the shapes from the
        ``lnL`` grids are taken to it with the truth's ``e1_sky, e2_sky``
        (:func:`pylensfit_validation.simulate.pixel_to_sky_shear`), the fixed point solves for the
        sky-frame shear, and the manifest's shears are the sky frame's.
    """
    opts = _Options(estimator=estimator, jobs=jobs, progress=progress, remeasure=remeasure,
                    min_count=bin_min_count, true_psf=true_psf, truth_control=truth_control,
                    psf_models={int(k): Path(v) for k, v in (psf_models or {}).items()})
    man = read_manifest(directory)
    sky, bins = _set_frame(man), _bin_quantities(man, bins)
    cfg = config if config is not None else Config()
    out = _analyse(man, cfg, sky, bins, opts)
    if report is not None:
        write_report(out, man, Path(report))
    return out


@dataclass(frozen=True)
class _Options:
    """:func:`validate`'s options for the analysis (the estimator checked here)."""

    estimator: str
    jobs: int
    progress: bool
    remeasure: bool
    min_count: int  # bin_min_count
    true_psf: bool
    truth_control: bool
    psf_models: dict[int, Path] = field(default_factory=dict)  # {PSF index: model file}

    def __post_init__(self) -> None:
        """Refuse an unknown estimator, or both the true PSFs and model files."""
        if self.estimator not in ("key2", "fixed-point"):
            raise ValueError(
                f"estimator must be 'key2' or 'fixed-point', got {self.estimator!r}"
            )
        if self.true_psf and self.psf_models:
            raise ValueError("true_psf and psf_models exclude each other")


def _bin_quantities(man: dict, bins: dict[str, int | Sequence[float]] | None
                    ) -> dict[str, int | Sequence[float]]:  # fmt: skip
    """:func:`validate`'s ``bins``, checked, with the galaxy kinds of a STEP2-like set."""
    bins = dict(DEFAULT_BINS if bins is None else bins)
    if bins and man.get("fieldspec", {}).get("model") == "step2":
        bins.setdefault("morphology", _MORPHOLOGY_EDGES)
    for k in bins:
        if k not in _BIN_LABEL:
            raise ValueError(f"unknown bin quantity {k!r}; use {sorted(_BIN_LABEL)}")
    return bins


@dataclass
class _MeasuredSet:
    """A set's galaxies measured per PSF (:func:`_measure_set`)."""

    fields: dict[str, dict]  # the manifest's fields by file name
    psfs: list[int]  # the PSFs' indices, sorted
    pg: Table  # galaxies of the zero-shear (prior) fields
    sg: Table  # galaxies of the shear fields
    egrid: np.ndarray  # the ellipticity grid of the lnL grids
    measured: dict[str, dict]  # meta["measured"]: catalogue paths, whether reused
    psf_rows: list[tuple]  # rows of meta["psf_check"]
    priors_of: dict[int, Any]  # the priors estimated on each PSF's zero-shear field


def _analyse(man: dict, cfg: Config, sky: tuple[float, bool],
             bins: dict[str, int | Sequence[float]], opts: _Options) -> Table:  # fmt: skip
    """:func:`validate`'s stages after the arguments and the manifest, up to the report."""
    ms = _measure_set(man, cfg, sky, opts)
    prior, bulge_weights = _set_prior(ms, cfg)
    e_s_of = partial(_sky_shapes, egrid=ms.egrid, cfg=cfg, sky=sky)
    e, s = e_s_of(ms.sg, prior)
    pairs = any(f["twin"] or f.get("noise_twin") for f in man["fields"])
    fits = _shear_fits(ms, e, s, prior, cfg, sky, opts, pairs)
    out = Table(rows=fits.mc, names=_MC_NAMES)
    out.meta.update(_summary(out[:-1]))
    out.meta["prior"] = prior
    out.meta["priors"] = [ms.priors_of[k] for k in sorted(ms.priors_of)]
    out.meta["bulge_weights"] = None if bulge_weights is None else bulge_weights.tolist()
    out.meta["bulge_runs"] = None if bulge_weights is None else cfg.run_labels
    out.meta["mode"] = "pairs" if pairs else "images"
    out.meta["estimator"] = opts.estimator
    out.meta["estimates"] = fits.pairs if pairs else fits.images
    out.meta["images"] = fits.images
    out.meta["pairs"] = fits.pairs
    out.meta["single"] = fits.single
    out.meta["fits"] = Table(rows=fits.fit_rows, names=("psf", "component", "m", "m_err", "c",
                                                        "c_err", "rho"))  # fmt: skip
    out.meta["measured"] = ms.measured
    out.meta["psf_source"] = ("true" if opts.true_psf else
                              "models" if opts.psf_models else "stars")  # fmt: skip
    out.meta["truth_control"] = bool(opts.truth_control)
    out.meta["leakage"] = _leakage_table(ms.sg, e, s, ms.fields, ms.psfs, pairs)
    out.meta["bins"], out.meta["bin_edges"] = _bins(ms, pairs, bins, e_s_of, cfg, sky, opts)
    _add_diagnostics(out, ms, man, prior)
    return out


def _measure_set(man: dict, cfg: Config, sky: tuple[float, bool],
                 opts: _Options) -> _MeasuredSet:  # fmt: skip
    """Measure (or reuse the kept catalogues of) each PSF's zero-shear and shear fields."""
    fields = {f["file"]: f for f in man["fields"]}
    by_psf: dict[int, list] = {}
    for f in man["fields"]:
        by_psf.setdefault(int(f["psf"]), []).append(f)
    missing = sorted(set(by_psf) - set(opts.psf_models))
    if opts.psf_models and missing:
        raise ValueError(f"psf_models has no file for PSF {missing} of {man['dir']}")
    stars = {int(s["psf"]): s for s in man["star_fields"]}
    sub = ("measured_true_psf" if opts.true_psf else
           "measured_psf_models" if opts.psf_models else "measured")  # fmt: skip
    mdir = Path(man["dir"]) / sub
    pgs, sgs, measured, psf_rows = [], [], {}, []
    priors_of: dict = {}
    egrid = None
    for k, fl in sorted(by_psf.items()):
        fwhm = float(man["psfs"][k]["fwhm"])
        given = _true_psf(man, k, cfg.largest_stamp) if opts.true_psf else None
        if k in opts.psf_models:
            given = opts.psf_models[k]  # read by measure, as a file given to it
        for role, lst in (("prior", pgs), ("shear", sgs)):
            sel = [f for f in fl if f["role"] == role]
            if not sel:
                continue
            name = f"psf{k}_{role}"
            # the priors come from the zero-shear field by the calibration recipe (as a
            # survey's from its own galaxies): the shear fields are measured once, with them
            pr = priors_of.get(k) if role == "shear" else None
            cat, reused = _measured(name, sel, stars[k], cfg, mdir, jobs=opts.jobs,
                                    progress=opts.progress, remeasure=opts.remeasure,
                                    priors=pr, psf=given)  # fmt: skip
            _check_frame(cat, sky, name)
            if role == "prior":
                priors_of[k] = cat.meta["priors"]
            measured[name] = {"path": str(mdir / f"{name}.fits"), "reused": reused}
            egrid = cat.meta["egrid"]
            lst.append(_galaxies(cat, fields, k, fwhm, sky))
            if role == "shear" and "psfs" in cat.meta:
                psf_rows.append(_psf_check_row(k, man["psfs"][k], cat))
    if not pgs:
        raise ValueError(f"{man['dir']}: no zero-shear (prior) field in the manifest")
    return _MeasuredSet(fields=fields, psfs=sorted(by_psf), pg=vstack(pgs), sg=vstack(sgs),
                        egrid=egrid, measured=measured, psf_rows=psf_rows,
                        priors_of=priors_of)  # fmt: skip


def _psf_check_row(k: int, psf_params: dict, cat: Table) -> tuple:
    """A row of ``meta["psf_check"]``: PSF ``k``'s true and modelled FWHM and ellipticity."""
    p = cat.meta["psfs"]
    meas = [_nanmean(p[f"psf_{q}"]) for q in ("fwhm", "e1", "e2")]
    tru = _true_psf_diagnostics(psf_params)
    return (k, tru["fwhm"], tru["e1"], tru["e2"], *meas, *_heldout_pooled(p))


#: ``meta["psf_check"]``'s columns: the true and the measured PSF, and the PSF model's
#: residuals on its held-out stars pooled over the images (:func:`_heldout_pooled`).
_PSF_CHECK_NAMES = ("psf", "fwhm_true", "e1_true", "e2_true", "fwhm_meas", "e1_meas",
                    "e2_meas", "heldout_n", "heldout_rms_de1", "heldout_rms_de2",
                    "heldout_noise_de", "heldout_excess_de1", "heldout_excess_de2")  # fmt: skip


def _heldout_pooled(p: Table) -> tuple:
    """A varying PSF model's held-out stars over all images of a catalogue's ``PSFS``
    table: their number, the rms of star minus model ellipticity per component, the rms
    the stars' noise alone gives, and the excess ``sqrt(rms^2 - noise^2)`` (0 if
    negative), each pooled as ``sqrt(sum n x^2 / sum n)``; NaN without held-out stars
    (a constant PSF, or a catalogue written before the PSFS table had them). Images
    measured with one model (a star field's, or one model file for several images)
    repeat its check: each distinct check is counted once."""
    if "psf_heldout_n" not in p.colnames:
        return (0, *([math.nan] * 5))
    cols = [f"psf_heldout_{q}" for q in ("n", "mean_de1", "mean_de2", "rms_de1", "rms_de2",
                                         "noise_de") if f"psf_heldout_{q}" in p.colnames]
    keys = np.column_stack([np.nan_to_num(np.asarray(p[c], dtype=float), nan=-1.0)
                            for c in cols])  # fmt: skip
    p = p[np.sort(np.unique(keys, axis=0, return_index=True)[1])]
    n = np.nan_to_num(np.asarray(p["psf_heldout_n"], dtype=float))
    if n.sum() <= 0:
        return (0, *([math.nan] * 5))

    def pool(col: str) -> float:
        v = np.asarray(p[col], dtype=float)
        ok = (n > 0) & np.isfinite(v)
        return float(np.sqrt(np.sum(n[ok] * v[ok] ** 2) / np.sum(n[ok])))

    rms = [pool(f"psf_heldout_rms_de{i}") for i in (1, 2)]
    noise = pool("psf_heldout_noise_de")
    excess = [math.sqrt(max(r**2 - noise**2, 0.0)) for r in rms]
    return (int(n.sum()), *rms, noise, *excess)


def _set_prior(ms: _MeasuredSet, cfg: Config) -> tuple[Prior, np.ndarray | None]:
    """The ellipticity prior from the zero-shear fields' galaxies (and the bulge weights).

    With the bulge prior estimated, both samples' ``lnL`` are replaced by their mixture
    over the bulge fractions with the estimated weights (None otherwise).
    """
    pg, sg = ms.pg, ms.sg
    bulge_weights = None
    if cfg.bulge_prior == "estimated" and all("lnL_bulge" in t.colnames for t in (pg, sg)):
        # the prior over the bulge fractions with the ellipticity prior, from the prior
        # fields; both samples' L(e) mixed with it
        prior, bulge_weights = estimate_prior_and_bulge(
            np.asarray(pg["lnL_bulge"]), np.asarray(pg["lnL_star"]), ms.egrid,
            method=cfg.prior_method, form=cfg.prior_form)  # fmt: skip
        for t in (pg, sg):
            t["lnL"] = mix_bulge_fractions(np.asarray(t["lnL_bulge"]),
                                           np.asarray(t["lnL_star"]), bulge_weights)
    else:
        prior = estimate_prior(np.asarray(pg["lnL"]), ms.egrid, method=cfg.prior_method,
                               form=cfg.prior_form)  # fmt: skip
    return prior, bulge_weights


def _sky_shapes(t: Table, p: Prior, *, egrid: np.ndarray, cfg: Config,
                sky: tuple[float, bool]) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The ``(n, 2)`` ellipticities and sensitivities of ``t``'s galaxies under prior ``p``,
    in the set's sky frame."""
    if len(t) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    sh = shapes(np.asarray(t["lnL"]), egrid, p, sensitivity=cfg.sensitivity,
                refine=cfg.output_refine)  # fmt: skip
    # the lnL grids are the pixel frame's; the truth and the shears the sky frame's
    return _to_sky(np.column_stack([sh["e1"], sh["e2"]]),
                   np.column_stack([sh["sens1"], sh["sens2"]]), sky)


@dataclass
class _ShearFits:
    """The shear estimates of :func:`validate` and the fits of m and c on them."""

    images: Table  # per-image estimates
    pairs: Table | None  # per-group estimates (twins), or None
    single: Table  # the per-PSF fit table from the single images
    mc: list[tuple]  # rows of the result table, from the groups if any
    fit_rows: list[tuple]  # rows of meta["fits"]


def _shear_fits(ms: _MeasuredSet, e: np.ndarray, s: np.ndarray, prior: Prior, cfg: Config,
                sky: tuple[float, bool], opts: _Options, pairs: bool) -> _ShearFits:  # fmt: skip
    """Shear per image (and per twin group if ``pairs``) and the fits of m and c per PSF."""
    kw = dict(estimator=opts.estimator, prior=prior, egrid=ms.egrid, refine=cfg.output_refine,
              truth_control=opts.truth_control, sky=sky)  # fmt: skip
    img = _shear_estimates(ms.sg, e, s, ms.fields, pairs=False, **kw)
    mc, fit_rows = _mc_rows(img, ms.psfs)
    single = Table(rows=mc, names=_MC_NAMES)
    pair_tab = None
    if pairs:
        pair_tab = _shear_estimates(ms.sg, e, s, ms.fields, pairs=True, **kw)
        mc, fit_rows = _mc_rows(pair_tab, ms.psfs)
    return _ShearFits(images=img, pairs=pair_tab, single=single, mc=mc, fit_rows=fit_rows)


def _bins(ms: _MeasuredSet, pairs: bool, bins: dict[str, int | Sequence[float]],
          e_s_of: Callable[[Table, Prior], tuple[np.ndarray, np.ndarray]], cfg: Config,
          sky: tuple[float, bool], opts: _Options) -> tuple[Table, dict[str, np.ndarray]]:
    """``meta["bins"]`` and ``meta["bin_edges"]`` (paper Table 2).

    A twin group's value is the mean of its members'; adds a ``_bin_{kind}`` column to
    the shear fields' galaxies per binned quantity.
    """
    sg, pg = ms.sg, ms.pg
    gid = _groups(sg, ms.fields)[0] if pairs else np.full(len(sg), -1)
    has = gid >= 0
    bin_rows, bin_edges = [], {}
    for kind, spec in bins.items():
        v = np.asarray(sg[kind], float)
        if not np.isfinite(v).any():  # a quantity that this set's galaxies lack
            continue
        vb = v.copy()
        if has.any():
            tot = np.bincount(gid[has], weights=v[has])
            vb[has] = tot[gid[has]] / np.bincount(gid[has])[gid[has]]
        use = has if pairs else np.ones(len(sg), bool)
        sg["_bin_" + kind] = np.where(use, vb, np.nan)
        edges = _bin_edges(np.asarray(sg["_bin_" + kind]), spec, np.asarray(pg[kind], float))
        if edges.size < 2:
            continue
        bin_edges[kind] = edges
        bin_rows += _bins_table(kind, edges, pg, sg, e_s_of, ms.psfs, ms.fields, pairs,
                                opts.estimator, ms.egrid, cfg, opts.min_count,
                                sky)  # fmt: skip
    return (Table(rows=bin_rows, names=_BIN_NAMES) if bin_rows else Table()), bin_edges


def _add_diagnostics(out: Table, ms: _MeasuredSet, man: dict, prior: Prior) -> None:
    """Add the PSF models' and the prior's checks against the truth, and the diagnosis."""
    pg = ms.pg
    out.meta["psf_check"] = (Table(rows=ms.psf_rows, names=_PSF_CHECK_NAMES)
                             if ms.psf_rows else Table())  # fmt: skip
    gal_p = ~np.asarray(pg["truth_star"]) & (np.asarray(pg["truth_index"]) >= 0)
    true_params = man.get("fieldspec", {}).get("prior_params")
    out.meta["prior_check"] = _prior_check(
        prior, np.column_stack([pg["e1_int"], pg["e2_int"]])[gal_p], true_params
    )
    out.meta["diagnosis"] = _diagnose(out)


def _diagnose(res: Table) -> dict[str, Any]:
    """Whether each target of :data:`TARGETS` is met, with the evidence for why not."""
    meta = res.meta
    m, me = meta["mean_m"], meta["mean_m_err"]
    d: dict[str, Any] = {}
    if not np.isfinite(m):
        d["m"] = ("untested", "no PSF has a measured m")
    elif abs(m) <= TARGETS["m"]:
        d["m"] = ("met", f"|<m>| = {abs(m):.4f} <= {TARGETS['m']}")
    elif abs(m) - me <= TARGETS["m"]:
        d["m"] = ("met within error", f"|<m>| = {abs(m):.4f} +- {me:.4f}")
    else:
        d["m"] = ("not met", f"|<m>| = {abs(m):.4f} +- {me:.4f} > {TARGETS['m']}")
    if np.isfinite(me) and me > TARGETS["m"]:
        d["m"] = (d["m"][0], d["m"][1] + f"; but sigma(<m>) = {me:.4f} exceeds the target: "
                  "the set is too small to test it")  # fmt: skip
    sc, scs = meta["sigma_c"], meta["sigma_c_stat"]
    if sc <= TARGETS["sigma_c"]:
        d["sigma_c"] = ("met", f"sigma_c = {sc:.2e} <= {TARGETS['sigma_c']:.0e}")
    else:
        noise = sc <= 2 * scs
        why = f"the fits' errors alone give {scs:.2e}, so the spread is " + (
            "consistent with noise: the set is too small to test it"
            if noise
            else "more than noise: PSF residuals (see the PSF table)"
        )
        d["sigma_c"] = ("not met", f"sigma_c = {sc:.2e} > {TARGETS['sigma_c']:.0e}; {why}")
    up = meta.get("sigma_c_upper", math.nan)
    if np.isfinite(up):
        d["sigma_c"] = (d["sigma_c"][0], d["sigma_c"][1] + (
            f"; the offsets' own spread (noise taken out) {meta['sigma_c_hat']:.1e}, "
            f"< {up:.1e} at 95 % (chi-square of c over PSFs {meta['c1_chi2']:.1f} and "
            f"{meta['c2_chi2']:.1f} on {meta['c_dof']})"))  # fmt: skip
    q = float(res["Q"][-1])
    if np.isfinite(q) and q >= TARGETS["Q"]:
        d["Q"] = ("met", f"Q = {q:.0f} >= {TARGETS['Q']:.0f}")
    else:
        per = res[:-1]
        worst = per[np.argsort(np.nan_to_num(np.asarray(per["Q"], float), nan=-1.0))[:2]]
        d["Q"] = ("not met", f"Q = {q:.0f} < {TARGETS['Q']:.0f}; lowest per PSF: "
                  + ", ".join(f"PSF {r['psf']} Q = {r['Q']:.0f}" for r in worst))  # fmt: skip
    d["all_met"] = all(d[k][0].startswith("met") for k in ("m", "sigma_c", "Q"))
    # the evidence: significant m in bins, PSF model residuals, the prior residual
    b = meta.get("bins")
    sig = []
    if b is not None and len(b):
        for r in b[b["psf"] == "all"]:
            if np.isfinite(r["mean_m"]) and abs(r["mean_m"]) > 2 * r["mean_m_err"]:
                sig.append(f"{r['kind']} bin {r['bin']} [{r['lo']:.3g}, {r['hi']:.3g}): "
                           f"<m> = {r['mean_m']:+.4f} +- {r['mean_m_err']:.4f}")  # fmt: skip
    d["bins_significant"] = sig
    pc = meta.get("psf_check")
    if pc is not None and len(pc):
        de = np.hypot(pc["e1_meas"] - pc["e1_true"], pc["e2_meas"] - pc["e2_true"])
        d["psf_worst"] = (str(pc["psf"][int(np.argmax(de))]), float(np.max(de)))
        held = pc[np.asarray(pc["heldout_n"]) > 0]
        if len(held):  # a PSF model varying over the field: its held-out stars' check
            ex = np.maximum(held["heldout_excess_de1"], held["heldout_excess_de2"])
            j = int(np.argmax(ex))
            # the rms^2 of n stars scatters by rms^2 sqrt(2 / n): the excess's 2-sigma floor
            r2 = max(held["heldout_rms_de1"][j], held["heldout_rms_de2"][j]) ** 2
            low = math.sqrt(max(ex[j] ** 2 - 2 * r2 * math.sqrt(2 / held["heldout_n"][j]), 0))
            state = ("met" if ex[j] < PSF_HELDOUT_TARGET else "met within error"
                     if low < PSF_HELDOUT_TARGET else "not met")  # fmt: skip
            d["psf_heldout"] = (state, f"largest excess rms of held-out star minus model "
                                f"ellipticity {ex[j]:.1e} (PSF {held['psf'][j]}, "
                                f"{held['heldout_n'][j]} stars; rms "
                                f"{held['heldout_rms_de1'][j]:.1e} / "
                                f"{held['heldout_rms_de2'][j]:.1e} of which the stars' noise "
                                f"{held['heldout_noise_de'][j]:.1e}; 2 sigma below: "
                                f"{low:.1e}), target < {PSF_HELDOUT_TARGET:.0e}")  # fmt: skip
    return d


def _true_psf(man: dict, k: int, n: int) -> PSFResult | PSFModel:
    """PSF ``k``'s truth as the pipeline takes a given PSF: its image (``n`` square), or
    on a set whose PSF varies, its map over the field
    (:func:`pylensfit_validation.simulate.map_psf_model`)."""
    if man.get("psf_variation", "none") == "none":
        return psf_from_image(true_psf_image(man["psfs"][k], n), source=f"true PSF {k}")
    common = {q: tuple(v) if isinstance(v, list) else v for q, v in man["fieldspec"].items()
              if not q.startswith("psf_") or q == "psf_variation"}
    spec = _spec_for(man["psfs"][k], **{**common, "size": int(man["field_size"])})
    return map_psf_model(spec, size=n)


def true_psf_image(p: dict, n: int) -> np.ndarray:
    """A simulated set's PSF as the pipeline uses one: rendered with its pixel response.

    Parameters
    ----------
    p : dict
        ``{"fwhm", "beta", "e1", "e2"}`` (a manifest's ``psfs`` entry): a Moffat profile
        sheared to ``(e1, e2)``, as :func:`pylensfit_validation.simulate.simulate_field` draws it.
    n : int
        Image side in pixels.

    Returns
    -------
    numpy.ndarray
        ``(n, n)`` image of unit sum centred on element ``[n//2, n//2]`` (the centre
        convention of :class:`pylensfit.psf.PSFResult`).
    """
    obj = PSFProfile.from_dict(p).galsim()
    img = obj.drawImage(nx=n, ny=n, scale=1.0, use_true_center=False).array
    return img / img.sum()


def _true_psf_diagnostics(p: dict, n: int = 48) -> dict:
    """FWHM and adaptive-moment shape of the input PSF rendered with its pixel response.

    Measured exactly as the pipeline measures its stacked PSF
    (:func:`pylensfit.psf.psf_diagnostics`), so that the two columns of the report compare
    like with like (the pixel widens a 3 px Moffat's FWHM by ~3% and dilutes its e).
    """
    return psf_diagnostics(true_psf_image(p, n))


# -- report --------------------------------------------------------------------------------
def _ellipse(ax, m, c, m_err, c_err, rho, **kw) -> None:
    """The ``delta chi^2 = 1`` ellipse of a fit (its shadows are the 1-sigma errors)."""
    t = np.linspace(0, 2 * np.pi, 100)
    rho = 0.0 if not np.isfinite(rho) else rho
    x = m + m_err * np.cos(t)
    y = c + c_err * (rho * np.cos(t) + math.sqrt(max(1 - rho**2, 0.0)) * np.sin(t))
    ax.plot(x, y, **kw)


def _plot_mc_plane(res: Table, png: Path, plt) -> None:
    fits_ = res.meta["fits"]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for i, ax in zip((1, 2), axes, strict=True):
        t = fits_[(fits_["component"] == i) & (fits_["psf"] != "all")]
        shown = False
        for j, r in enumerate(t):
            col = f"C{j % 10}"
            if not np.isfinite(r["m"]):
                ax.axhline(r["c"], color=col, lw=0.8, ls=":", label=f"PSF {r['psf']} (c only)")
                continue
            ax.errorbar(r["m"], r["c"], xerr=r["m_err"], yerr=r["c_err"], fmt="o", ms=4,
                        color=col, label=f"PSF {r['psf']}")  # fmt: skip
            _ellipse(ax, r["m"], r["c"], r["m_err"], r["c_err"], r["rho"], color=col, lw=0.8)
            shown = True
        a = fits_[(fits_["component"] == i) & (fits_["psf"] == "all")]
        if len(a) and np.isfinite(a["m"][0]):
            ax.errorbar(a["m"][0], a["c"][0], xerr=a["m_err"][0], yerr=a["c_err"][0], fmt="*",
                        ms=10, color="k", label="all PSFs (joint fit)")  # fmt: skip
            shown = True
        if shown:
            ax.axvspan(-TARGETS["m"], TARGETS["m"], color="g", alpha=0.1, lw=0)
        ax.axhspan(-TARGETS["sigma_c"], TARGETS["sigma_c"], color="g", alpha=0.1, lw=0)
        ax.axhline(0, color="k", lw=0.5)
        ax.axvline(0, color="k", lw=0.5)
        ax.set_xlabel(f"m{i}")
        ax.set_ylabel(f"c{i}")
        ax.set_title(f"component {i}" + ("" if shown else " (g2 = 0: only c)"))
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)


def _plot_bins(res: Table, png: Path, plt) -> None:
    b = res.meta["bins"]
    kinds = list(dict.fromkeys(str(k) for k in b["kind"]))
    fig, axes = plt.subplots(len(kinds), 2, figsize=(10, 3.2 * len(kinds)), squeeze=False)
    for row, kind in zip(axes, kinds, strict=True):
        t = b[b["kind"] == kind]
        for j, p in enumerate(x for x in dict.fromkeys(t["psf"]) if x != "all"):
            u = t[t["psf"] == p]
            row[0].plot(u["center"], u["mean_m"], "-o", ms=3, lw=0.8, alpha=0.5, color=f"C{j}",
                        label=f"PSF {p}")  # fmt: skip
            row[1].plot(u["center"], u["mean_c"], "-o", ms=3, lw=0.8, alpha=0.5, color=f"C{j}")
        a = t[t["psf"] == "all"]
        row[0].errorbar(a["center"], a["mean_m"], yerr=a["mean_m_err"], fmt="-s", color="k",
                        lw=2, label="<m> over PSFs")  # fmt: skip
        row[1].errorbar(a["center"], a["c1"], yerr=a["c1_err"], fmt="-s", color="k", lw=2,
                        label="c1 (all PSFs)")  # fmt: skip
        row[1].errorbar(a["center"], a["c2"], yerr=a["c2_err"], fmt="--^", color="0.3", lw=2,
                        label="c2 (all PSFs)")  # fmt: skip
        for ax, what, tgt in ((row[0], "m", TARGETS["m"]), (row[1], "c", TARGETS["sigma_c"])):
            ax.axhspan(-tgt, tgt, color="g", alpha=0.1, lw=0)
            ax.axhline(0, color="k", lw=0.5)
            for x in res.meta["bin_edges"][kind][1:-1]:
                ax.axvline(x, color="0.8", lw=0.5)
            ax.set_xlabel(_BIN_LABEL[kind])
            ax.set_ylabel(what)
            if kind == "snr":
                ax.set_xscale("log")
        row[0].legend(fontsize=7)
        row[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)


def _plot_prior(res: Table, png: Path, plt) -> None:
    pc = res.meta["prior_check"]
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(6, 6), sharex=True,
                                  gridspec_kw={"height_ratios": [2, 1]})  # fmt: skip
    mid = pc["mid"]
    ax.errorbar(mid, pc["density"], yerr=pc["density_err"], fmt="o", ms=3, color="k",
                label=f"truth |e_int| of the {pc['n']} prior-field galaxies")  # fmt: skip
    ax.step(pc["edges"], np.r_[pc["recovered"], pc["recovered"][-1]], where="post", color="C0",
            label=f"recovered {res.meta['prior']!r}")  # fmt: skip
    if pc["true"] is not None:
        ax.step(pc["edges"], np.r_[pc["true"], pc["true"][-1]], where="post", color="C1",
                ls="--", label="input functional form")  # fmt: skip
    ax.set_ylabel("P(|e|)")
    ax.legend(fontsize=7)
    rec = pc["recovered"]
    ax2.errorbar(mid, pc["density"] / rec - 1, yerr=pc["density_err"] / rec, fmt="o", ms=3,
                 color="k", label="truth histogram / recovered - 1")  # fmt: skip
    if pc["true"] is not None:
        ax2.plot(mid, pc["true"] / rec - 1, "--", color="C1", label="input / recovered - 1")
    ax2.axhline(0, color="k", lw=0.5)
    big = rec > 0.05 * rec.max()
    lim = max(0.25, float(np.max(np.abs(pc["density"][big] / rec[big] - 1))))
    ax2.set_ylim(-min(1.0, 1.2 * lim), min(1.0, 1.2 * lim))
    ax2.set_xlabel("|e|")
    ax2.set_ylabel("residual")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)


def _plot_residuals(est: Table, png: Path, plt, title: str) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for i, ax in zip((1, 2), axes, strict=True):
        for k in np.unique(est["psf"]):
            t = est[est["psf"] == k]
            ax.errorbar(t[f"g{i}_true"], t[f"g{i}"] - t[f"g{i}_true"], yerr=t[f"g{i}_err"],
                        fmt="o", ms=3, label=f"PSF {k}")  # fmt: skip
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(f"g{i} true")
        ax.set_title(f"component {i} ({title})")
    axes[0].set_ylabel("g measured - g true")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)


def _fmt_row(r) -> str:
    return (f"| {r['psf']} | {r['m1']:+.4f} +- {r['m1_err']:.4f} | {r['c1']:+.5f} +- "
            f"{r['c1_err']:.5f} | {r['m2']:+.4f} +- {r['m2_err']:.4f} | {r['c2']:+.5f} +- "
            f"{r['c2_err']:.5f} | {r['Q']:.0f} | {r['n_gal']} |")  # fmt: skip


_MC_HEAD = ["| PSF | m1 | c1 | m2 | c2 | Q | galaxies |", "|---|---|---|---|---|---|---|"]


def nan_note(res: Table) -> str:
    """Why a column of :func:`validate`'s table is NaN, in one line ("" if none is)."""
    notes = []
    for i in (1, 2):
        m = np.asarray(res[f"m{i}"], float)
        if m.size and np.all(np.isnan(m)):
            notes.append(f"m{i} = nan: every shear field of the set has the same g{i} (STEP1's "
                         f"are sheared along g1 only), so m{i} cannot be fitted; c{i} is the "
                         f"mean g{i} measured")  # fmt: skip
    return "; ".join(notes)


def _group_words(man: dict) -> str:
    """How a set's renderings are grouped for the estimates, in words."""
    rot = any(f["twin"] for f in man["fields"])
    neg = any(f.get("noise_twin") for f in man["fields"])
    parts = ["image"]
    if rot:
        parts.append("rotated twin")
    if neg:
        parts.append("noise twins")
    why = [w for w, on in (("shape noise", rot), ("the noise's first order", neg)) if on]
    return (" + ".join(parts) + " (matched galaxy by galaxy; " + " and ".join(why)
            + " cancel" + ("s" if len(why) == 1 else "")
            + "; every unmatched usable detection counted on its own)")


def _leakage_lines(lk: Table | None) -> list[str]:
    """The report's lines on the PSF leakage (``meta["leakage"]`` of :func:`validate`):
    one per PSF source, with all PSFs together and each PSF whose ellipticity varies."""
    if lk is None or not len(lk):
        return []

    def fit(r) -> str | None:
        if not (np.isfinite(r["alpha1"]) and np.isfinite(r["alpha2"])):
            return None
        return (f"alpha1 = {r['alpha1']:+.4f} +- {r['alpha1_err']:.4f}, alpha2 = "
                f"{r['alpha2']:+.4f} +- {r['alpha2_err']:.4f}")  # fmt: skip

    words = {"truth": "the true PSF (its adaptive-moment e at each galaxy)",
             "model": "the catalogue's model PSF (PSF_e1, PSF_e2)"}  # fmt: skip
    out = [""]
    for source, what in words.items():
        t = lk[lk["source"] == source]
        parts = [f"{'all PSFs' if r['psf'] == 'all' else 'PSF ' + r['psf']}: {fit(r)}"
                 for r in t if fit(r) is not None]  # fmt: skip
        out.append(f"- PSF leakage (g = c + alpha e_psf, sky frame) with {what}: "
                   + ("; ".join(parts) if parts else "not measured (the PSF's ellipticity "
                      "does not vary)") + ".")  # fmt: skip
    return out


def _diagnosis_lines(diag: dict[str, Any], pc: dict, has_bins: bool) -> list[str]:
    """The lines of the report's diagnosis: each target's state, and why any is not met."""
    lines: list[str] = []
    names = {"m": "|<m>| <= 0.006 (within error)", "sigma_c": "sigma_c <= 2e-4", "Q": "Q >= 100"}
    for k, label in names.items():
        lines.append(f"- **{label}**: {diag[k][0]} ({diag[k][1]}).")
    if "psf_heldout" in diag:
        lines.append(f"- **PSF model on held-out stars**: {diag['psf_heldout'][0]} "
                     f"({diag['psf_heldout'][1]}).")  # fmt: skip
    lines.append("")
    if diag["all_met"]:
        lines.append("All targets are met.")
    else:
        why = ["Where it falls short, the evidence below says why: "]
        if diag["bins_significant"]:
            sig = "; ".join(diag["bins_significant"])
            why.append(f"m departs from 0 by more than 2 sigma in {sig} (see m against "
                       "magnitude, S/N and size). ")  # fmt: skip
        elif has_bins:
            why.append("no bin of magnitude, S/N or size has m beyond 2 sigma of 0. ")
        if "psf_worst" in diag:
            why.append(f"The largest PSF-model ellipticity residual is "
                       f"{diag['psf_worst'][1]:.4f} (PSF {diag['psf_worst'][0]}); see the PSF "
                       "table. ")  # fmt: skip
        why.append(f"The recovered prior differs from the input functional form by "
                   f"{pc['rms_true']:.3f} rms (fractional, where P > 5% of its peak), and from "
                   f"the truth histogram by {pc['rms_hist']:.3f} against {pc['rms_poisson']:.3f} "
                   "expected from Poisson noise.")  # fmt: skip
        lines.append("".join(why))
    return lines


def write_report(res: Table, man: dict, path: str | Path) -> list[Path]:
    """Write the Markdown report of :func:`validate` and its PNG figures beside it.

    Figures (``<stem>`` is the report's name without its suffix): ``<stem>.png``,
    ``g_meas - g_true`` against ``g_true`` per PSF (the fits' input: pairs for step2);
    ``<stem>_mc.png``, the (m, c) plane per PSF with ``delta chi^2 = 1`` ellipses;
    ``<stem>_bins.png``, m and c against magnitude, S/N and size; ``<stem>_prior.png``,
    the recovered prior against the truth's intrinsic ``|e|`` with the residual.

    Parameters
    ----------
    res : astropy.table.Table
        The output of :func:`validate`.
    man : dict
        The set's manifest (:func:`read_manifest`).
    path : str or pathlib.Path
        The Markdown file.

    Returns
    -------
    list of pathlib.Path
        The files written (the report first).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = res.meta
    stem = path.with_suffix("")
    pngs = {"resid": path.with_suffix(".png"), "mc": Path(f"{stem}_mc.png"),
            "bins": Path(f"{stem}_bins.png"), "prior": Path(f"{stem}_prior.png")}  # fmt: skip
    has_bins = meta.get("bins") is not None and len(meta["bins"]) > 0
    if not has_bins:
        del pngs["bins"]
    plt = pyplot_or_none(str(path))
    if plt is None:
        pngs = {}
    else:
        _plot_residuals(meta["estimates"], pngs["resid"], plt, meta["mode"])
        _plot_mc_plane(res, pngs["mc"], plt)
        if has_bins:
            _plot_bins(res, pngs["bins"], plt)
        _plot_prior(res, pngs["prior"], plt)

    def figure(key: str, alt: str) -> str:
        return f"![{alt}]({pngs[key].name})" if key in pngs else "(figure not drawn)"
    diag = meta["diagnosis"]
    pc = meta["prior_check"]
    n_est = len(meta["estimates"])
    lines = [f"# pylensfit validation: {man['kind']} ({man['dir']})", "",
             f"Estimator `{meta['estimator']}`; shear per "
             + (_group_words(man) if meta["mode"] == "pairs" else "image")
             + f", {n_est} estimates. Prior from the zero-shear fields: {meta['prior']!r}"
             + ("" if meta.get("bulge_weights") is None else
                "; bulge-fraction prior " + ", ".join(
                    f"{f}: {w:.3f}" for f, w in zip(
                        meta.get("bulge_runs") or [f"{f:g}" for f in np.linspace(
                            0, 1, len(meta["bulge_weights"]))], meta["bulge_weights"],
                        strict=True))) + "."
             + (" Fitted with the true PSFs, not the stars' (diagnostic)."
                if meta.get("psf_source") == "true" else "")
             + (" The truth's shape noise taken out of each estimate (a control variate "
                "of expectation zero: `validate --truth-control`); the bins without it."
                if meta.get("truth_control") else ""), "",
             f"<m> = {meta['mean_m']:+.4f} +- {meta['mean_m_err']:.4f} (the paper's mean of the "
             f"PSFs' errors: "
             f"+- {meta['mean_m_err_paper']:.4f}), sigma_c = {meta['sigma_c']:.2e} "
             f"(from the errors alone {meta['sigma_c_stat']:.2e}; the offsets' own spread "
             f"{meta.get('sigma_c_hat', math.nan):.1e}, < "
             f"{meta.get('sigma_c_upper', math.nan):.1e} at 95 %), Q = {res['Q'][-1]:.0f}", "",
             *_MC_HEAD]  # fmt: skip
    lines += [_fmt_row(r) for r in res]
    if nan_note(res):
        lines += ["", nan_note(res) + "."]
    lines += _leakage_lines(meta.get("leakage"))
    lines += ["", figure("resid", "g_meas - g_true"), "",
              "## Diagnosis", ""]  # fmt: skip
    lines += _diagnosis_lines(diag, pc, has_bins)
    lines += ["", "## m and c in the (m, c) plane", "",
              "1-sigma error bars and the delta chi^2 = 1 ellipse of each PSF's fit; the shaded "
              "bands are |m| <= 0.006 and |c| <= 2e-4.", "",
              figure("mc", "m-c plane"), ""]  # fmt: skip
    if meta.get("single") is not None and meta["mode"] == "pairs":
        lines += ["Single images (no twin cancellation), for comparison:", "", *_MC_HEAD]
        lines += [_fmt_row(r) for r in meta["single"]]
        lines.append("")
    if has_bins:
        b = meta["bins"]
        lines += ["## m and c per bin (a prior per bin, paper Table 2)", "",
                  "| quantity | bin | galaxies | prior galaxies | <m> | m1 | c1 | m2 | c2 | Q |",
                  "|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for r in b[b["psf"] == "all"]:
            fb = " (global prior)" if r["prior_fallback"] else ""
            span = (STEP2_KINDS[int(r["bin"])] if r["kind"] == "morphology"
                    else f"[{r['lo']:.3g}, {r['hi']:.3g})")  # fmt: skip
            lines.append(
                f"| {r['kind']} | {span} | {r['n_gal']} | "
                f"{r['n_prior']}{fb} | {r['mean_m']:+.4f} +- {r['mean_m_err']:.4f} | "
                f"{r['m1']:+.4f} +- {r['m1_err']:.4f} | {r['c1']:+.5f} +- {r['c1_err']:.5f} | "
                f"{r['m2']:+.4f} +- {r['m2_err']:.4f} | {r['c2']:+.5f} +- {r['c2_err']:.5f} | "
                f"{r['Q']:.0f} |"
            )
        lines += ["", "Faint lines: each PSF; bold: all PSFs.", "",
                  figure("bins", "m and c per bin"), ""]  # fmt: skip
    pcheck = meta["psf_check"]
    held = bool(len(pcheck)) and bool(np.any(np.asarray(pcheck["heldout_n"]) > 0))
    if len(pcheck):
        lines += ["## PSF models", "",
                  "Measured: the pipeline's PSF (stars, pixel included) averaged over the "
                  "shear images; true: GalSim's rendering of the input PSF with the pixel, "
                  "measured the same way (effective FWHM, adaptive-moment e).", "",
                  "| PSF | FWHM true | FWHM meas | e1 true | e1 meas | e2 true | e2 meas "
                  "| c1 | c2 |" + (" held-out stars | rms de1 / de2 | noise | excess de1 / de2 |"
                                   if held else ""),
                  "|---|---|---|---|---|---|---|---|---|" + ("---|---|---|---|"
                                                             if held else "")]  # fmt: skip
        cmap = {str(r["psf"]): r for r in res}
        for r in pcheck:
            c = cmap.get(str(r["psf"]))
            lines.append(
                f"| {r['psf']} | {r['fwhm_true']:.2f} | {r['fwhm_meas']:.2f} | "
                f"{r['e1_true']:+.4f} | {r['e1_meas']:+.4f} | {r['e2_true']:+.4f} | "
                f"{r['e2_meas']:+.4f} | {c['c1']:+.5f} | {c['c2']:+.5f} |"
                + (f" {r['heldout_n']} | {r['heldout_rms_de1']:.1e} / "
                   f"{r['heldout_rms_de2']:.1e} | {r['heldout_noise_de']:.1e} | "
                   f"{r['heldout_excess_de1']:.1e} / {r['heldout_excess_de2']:.1e} |"
                   if held else "")
            )
        if held:
            lines += ["", "Held-out stars: the PSF model's stars left out of its first fit "
                      "(pylensfit.psfmodel.PolynomialPSF), star minus model adaptive-moment "
                      "ellipticity over every image of the shear fields; noise: the rms "
                      "their own noise gives; excess: sqrt(rms^2 - noise^2), the model's "
                      f"error (target < {PSF_HELDOUT_TARGET:.0e})."]  # fmt: skip
        lines.append("")
    lines += ["## The prior", "",
              f"Recovered {meta['prior']!r} from the prior fields' galaxies against the truth "
              f"|e_int| of the {pc['n']} that were matched; fractional residual rms (where P > "
              f"5% of its peak): histogram {pc['rms_hist']:.3f} (Poisson {pc['rms_poisson']:.3f}),"
              f" input functional form {pc['rms_true']:.3f}.", "",
              figure("prior", "prior"), "",
              "Measured catalogues: " + ", ".join(
                  f"`{Path(v['path']).name}`" + (" (reused)" if v["reused"] else "")
                  for v in meta["measured"].values()), ""]  # fmt: skip
    path.write_text("\n".join(lines))
    return [path, *pngs.values()]


# ----------------------------------------------------------------------------------------
# The quick tier
# ----------------------------------------------------------------------------------------
#: Galaxies over the shear fields of the quick tier (set by timing on 2 cores, jobs=2).
QUICK_NGAL: dict[str, int] = {"step1": 5000, "step2": 5000}
#: Galaxies over the zero-shear (prior) fields of the quick tier.
QUICK_PRIOR_NGAL: dict[str, int] = {"step1": 2500, "step2": 2500}


def quick_validation(
    out: str | Path,
    *,
    jobs: int = 1,
    seed: int = 1,
    progress: bool = True,
    ngal: dict[str, int] | None = None,
    config=None,
    estimator: str = "fixed-point",
) -> dict[str, Table]:
    """The quick tier of the validation: small STEP1 and STEP2 sets, simulated and validated.

    Simulates ``out/step1`` and ``out/step2`` (:func:`simulate_step`, ``ngal`` galaxies
    over the shear fields, default :data:`QUICK_NGAL`, and :data:`QUICK_PRIOR_NGAL` over
    the zero-shear fields from which the prior is estimated; an existing set with the same
    parameters is reused), validates both (:func:`validate`, reports
    ``out/step1/report.md`` and ``out/step2/report.md``) and writes ``out/README.md``
    linking them with the timings. With ``jobs=2`` on two cores the whole tier takes
    under 10 minutes (see the package's documentation for the measured time). The sets
    are too small to test ``|<m>| <= 0.006`` (sigma(m) is several 0.01); the tier checks
    that the whole chain runs and shows no gross bias, and the reports say which targets
    the set can test.

    Parameters
    ----------
    out : str or pathlib.Path
        Output directory.
    jobs : int
        Worker processes for measuring.
    seed : int
        Master seed of the simulations (step2 uses ``seed + 1``).
    progress : bool
        Progress bars and one line per stage.
    ngal : dict, optional
        ``{"step1": n, "step2": n}`` overriding :data:`QUICK_NGAL`.
    config : Config, optional
        Pipeline settings (default ``Config()``, :func:`validate`'s).
    estimator : {"fixed-point", "key2"}
        Shear estimator (as :func:`validate`).

    Returns
    -------
    dict
        ``{"step1": table, "step2": table}`` from :func:`validate`, each with
        ``meta["timing"]`` (seconds: ``simulate``, ``validate``).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    n = {**QUICK_NGAL, **(ngal or {})}
    results: dict[str, Table] = {}
    for i, kind in enumerate(("step1", "step2")):
        d = out / kind
        t0 = time.perf_counter()
        want = {"kind": kind, "ngal": int(n[kind]), "seed": int(seed + i),
                "prior_ngal": int(QUICK_PRIOR_NGAL[kind])}  # fmt: skip
        try:
            have = read_manifest(d)
            reuse = all(have.get(k) == v for k, v in want.items())
        except (OSError, ValueError):
            reuse = False
        if not reuse:
            if progress:
                print(f"quick tier: simulating {kind} ({n[kind]} galaxies) in {d}", flush=True)
            simulate_step(kind, d, ngal=int(n[kind]), seed=int(seed + i),
                          prior_ngal=QUICK_PRIOR_NGAL[kind], jobs=jobs,
                          progress=progress)  # fmt: skip
        t1 = time.perf_counter()
        if progress:
            print(f"quick tier: validating {kind}", flush=True)
        res = validate(d, config=config or Config(), jobs=jobs, estimator=estimator,
                       report=d / "report.md", progress=progress)  # fmt: skip
        t2 = time.perf_counter()
        res.meta["timing"] = {"simulate": t1 - t0, "validate": t2 - t1}
        results[kind] = res
    lines = ["# pylensfit quick validation", ""]
    for kind, res in results.items():
        m = res.meta
        tm = m["timing"]
        lines += [f"## {kind}: [report]({kind}/report.md)", "",
                  f"<m> = {m['mean_m']:+.4f} +- {m['mean_m_err']:.4f}, sigma_c = "
                  f"{m['sigma_c']:.2e}, Q = {res['Q'][-1]:.0f}, {res['n_gal'][-1]} galaxies "
                  f"({m['mode']}); simulate {tm['simulate']:.0f} s, validate "
                  f"{tm['validate']:.0f} s.", ""]  # fmt: skip
        for k, v in m["diagnosis"].items():
            if k in ("m", "sigma_c", "Q"):
                lines.append(f"- {k}: {v[0]} ({v[1]})")
        lines.append("")
    (out / "README.md").write_text("\n".join(lines))
    return results
