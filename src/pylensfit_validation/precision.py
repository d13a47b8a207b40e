"""Paired precision measurement of the shear bias: ``pylensfit validate --precision``.

Independent simulated images cannot resolve ``|m| ~ 1e-3``: the intrinsic shapes of the
galaxies scatter the measured shear by ``~0.3 / sqrt(N)``. This mode follows the design
of the metacalibration papers (Sheldon & Huff 2017, Pujol et al. 2019) and cancels that
scatter by construction. Every galaxy is rendered with GalSim four times:

====  ==========  ==========  ====================
 k     shear       rotated     noise field
====  ==========  ==========  ====================
 0     ``+g``      no          ``n_a``
 1     ``+g``      90 deg      ``n_b``
 2     ``-g``      no          ``n_a``
 3     ``-g``      90 deg      ``n_b``
====  ==========  ==========  ====================

with ``g = (g0, g0)`` (``g0 = 0.02`` by default): the rotation cancels the intrinsic
ellipticity in the mean, the shared noise at ``+g`` and ``-g`` cancels the noise in the
difference. With :class:`PrecisionSpec` ``noise_twins`` every galaxy has four more
renderings, ``k = 4..7``: those of ``k - 4`` with the noise field negated (``-n_a``,
``-n_b``). The noise's first-order effect on each posterior mean is odd in the noise and
cancels between a rendering and its noise twin (antithetic variates), in ``c`` as in
``m``; its second-order effects (noise bias) are even and stay, so nothing the
measurement owes is cancelled. Without them ``c`` carries the noise of every rendering,
which the ``+-g`` pairing adds rather than cancels.

Per sample (a PSF, a bin of S/N, size, morphology or bulge fraction)

    m_i = (g_hat_i(+g) - g_hat_i(-g)) / (2 g0) - 1,    c_i = (g_hat_i(+g) + g_hat_i(-g)) / 2,

where ``g_hat(+-g)`` is the shear of renderings 0-1 (2-3; with noise twins 0, 1, 4, 5 and
2, 3, 6, 7) measured as a user would: the
ellipticity prior comes from a separate *unsheared* calibration sample of the same
population (:func:`pylensfit.prior.estimate_prior`), never from the sheared renderings;
the PSF is the true one (this mode measures the shape measurement, not the PSF model).
Both components are sheared together, so ``m_1`` includes the cross term
``m_12 g_2 / g_1`` (zero by symmetry for a round PSF, second order otherwise).

Three shear estimators are reported side by side:

- ``exact``: the paper's mean shear over mean sensitivity (Kitching et al. 2008,
  arXiv:0802.1528, section 3.3; docs: method, eq-key2), ``sum <e> / sum s``, with the
  exact sensitivity (docs: method, eq-sensitivity-exact). Its known second-order bias is
  ``m ~ +|g|^2`` (noise-free, ``sum s = N (1 - |g|^2)``), ``+8e-4`` at
  ``g = (0.02, 0.02)``.
- ``paper``: the same with the paper's sensitivity (section 2.1; docs: method,
  eq-partial).
- ``fixed-point``: the sheared-prior fixed point of
  :func:`pylensfit.shear.shear_fixed_point`, exact to all orders in ``g``. Streaming
  keeps per galaxy the posterior mean and its derivative under the prior sheared by the
  nominal shear ``g_n`` of the rendering (``+g`` or ``-g``), so the estimate is one
  Newton step from ``g_n``: its error is second order in ``g_hat - g_n`` (a few 1e-3:
  ``<1e-6``; ``tests/test_precision.py`` checks it against the iterated estimator).

Errors are delete-one-group jackknife over groups of 100 galaxies (each block of work
cut into runs), and m and c are corrected with control variates, the intrinsic shapes'
spin-4 parts (:func:`shape_controls`), which take out the shape noise that the rotated
twins leave. The errors hold the priors fixed. The calibration sample's own noise is not
in them: with 20,000 calibration galaxies drawn stratified (:class:`PrecisionSpec`
``stratified_calibration``) and every prior estimated (ellipticity, bulge fractions, a
size prior per fraction and PSF, the flux prior's slope and limits), ``(m1 + m2) / 2`` on
the mean of PSFs scattered by 0.0010 between four independent 200,000-galaxy samples,
where the jackknife gives 0.0004, and ``m1 - m2`` by 0.0010 against 0.0008: a noise of
about 0.0009 common to both components. The default ``ncal`` of 80,000 takes its variance
to a quarter (as ``1 / ncal``). A galaxy is
used only if all four renderings are measured (``paired`` selection, the default and
the reported numbers); the ``independent`` selection, where each rendering's own flags
decide, is reported too: the difference is the bias that a selection responding to the
shear adds (stars, failed fits).

The work streams: each block is rendered, fitted and reduced to 12 numbers per
rendering in a worker; nothing is written to disk and memory grows by ~0.3 kB per
galaxy. The calibration sample's likelihood grids are kept while the priors are
estimated, about 40 kB per calibration galaxy at their peak
(``benchmarks/studies/calibration_memory.py``). Blocks run on the project's runner (local
processes or dask.distributed).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from astropy.table import Table, vstack
from scipy.special import logsumexp

from pylensfit.calibration import MIN_FLUX_RANGE_GALAXIES, CalibrationSample, run_recipe
from pylensfit.config import Config
from pylensfit.likelihood import e_annuli, fit_stamps
from pylensfit.models import model_bank
from pylensfit.prior import Prior, SizePrior, mix_bulge_fractions
from pylensfit.runner import run_tasks, single_thread, worker_pool
from pylensfit.shear import (
    DEFAULT_STENCIL,
    kernel_columns,
    moments_from_sums,
    refined_grid,
    sensitivity_from_sums,
    sheared_prior_columns,
    sums_with,
)

from .figures import pyplot_or_none
from .galaxies import GalaxyProfile, PSFProfile, draw_bulge_shapes, draw_sersic_indices
from .simulate import POPULATIONS, draw_shapes

__all__ = [
    "PRECISION_PSFS",
    "MORPHOLOGIES",
    "PrecisionSpec",
    "render_block",
    "precision",
    "default_config",
    "reference_norm",
    "population_flux_range",
    "population_prior",
    "population_size_prior",
    "bias_table",
    "measured_bulge_fraction",
    "shape_controls",
    "reduce_likelihoods",
    "reduce_renderings",
]

#: PSFs of the precision mode (pixel units): a round Moffat, a Moffat of ellipticity
#: 0.10, a larger Kolmogorov, and an asymmetric (coma-like) PSF: a Moffat core with a
#: fainter, broader lobe displaced along x.
PRECISION_PSFS: tuple[dict, ...] = (
    {"name": "round", "kind": "moffat", "fwhm": 3.0, "beta": 3.5, "e1": 0.0, "e2": 0.0},
    {"name": "e=0.10", "kind": "moffat", "fwhm": 3.0, "beta": 3.5, "e1": 0.10, "e2": 0.0},
    {"name": "kolmogorov", "kind": "kolmogorov", "fwhm": 4.0, "e1": 0.0, "e2": 0.03},
    {"name": "asymmetric", "kind": "asymmetric", "fwhm": 3.0, "beta": 3.5, "e1": 0.02,
     "e2": -0.02, "lobe_flux": 0.2, "lobe_shift": 1.0},
)  # fmt: skip

#: Galaxy morphologies of the precision population (codes are the indices).
MORPHOLOGIES: tuple[str, ...] = ("exponential", "devaucouleurs", "bulge+disc", "sersic", "knots")

_ESTIMATORS = ("fixed-point", "exact", "paper")
# per-rendering quantities kept by the workers
_Q = ("e1", "e2", "sx1", "sx2", "sp1", "sp2", "fe1", "fe2", "J11", "J12", "J21", "J22")
_NQ = len(_Q)


@dataclass(frozen=True)
class PrecisionSpec:
    """What the precision mode simulates.

    Attributes
    ----------
    ngal : int
        Galaxies (each rendered four times, eight with ``noise_twins``).
    g : float
        Shear per component: renderings at ``+(g, g)`` and ``-(g, g)``.
    psfs : tuple of dict
        PSFs (see :data:`PRECISION_PSFS`); galaxies are shared out among them by block.
    snr_range : tuple of float
        Flux range, in units of the S/N (``sqrt(sum I^2) / sigma``) that a round
        exponential of the population's median size (``sqrt`` of the product of
        ``size_ratio_range`` times the PSF's half-light radius) has under the galaxy's
        PSF. The flux is a property of the galaxy alone, as in the sky: it does not
        depend on the galaxy's shape, size or shear, so a galaxy's own S/N (column
        ``snr`` of the truth, that of its rendering at ``+g``) is higher for small and
        round galaxies, lower for large and elongated ones (about 5-300 for the
        defaults). Earlier versions scaled each galaxy to a drawn S/N of its ``+g``
        rendering, which made the flux of all four renderings follow the ``+g`` shape;
        a prior that knows the flux distribution then misreads the ``-g`` and rotated
        renderings, and m moved by -0.004 to -0.02.
    snr_slope : float
        ``dN/dF ~ F^-snr_slope`` in flux (2: the faint end of galaxy counts dominates).
    size_ratio_range : tuple of float
        Half-light radius over the PSF's half-light radius, log-uniform (the bulge+disc
        and knotty galaxies use their disc's half-light radius).
    morphology_weights : tuple of float
        Fractions of :data:`MORPHOLOGIES`.
    prior_params : tuple of float
        ``(B, C, D)`` of the functional prior of the intrinsic ellipticities.
    max_e : float
        Largest intrinsic ``|e|``.
    noise_sigma : float
        Pixel noise.
    offset : float
        Each galaxy's centre lies uniformly within ``+-offset`` pixels of the stamp's
        centre along both axes (0: centred, for tests of the likelihood at a known
        position).
    offset_shape : str
        ``"square"``: the offsets uniform in the square ``+-offset`` (as a galaxy's true
        centre lies within its pixel); ``"gaussian"``: isotropic Gaussian offsets of the
        same variance per axis (``offset / sqrt 3``), drawn from the same two uniforms
        (Box-Muller), the distribution of a centroid's errors about its catalogue
        position and the one the position prior assumes.
    block_size : int
        Galaxies per block (unit of work and of the jackknife).
    ncal : int
        Galaxies of the unsheared calibration sample for the priors (default 80,000,
        20,000 per PSF). Their sampling noise moves m alike in both components and for
        every kind of galaxy, and the jackknife's errors hold it fixed: with 20,000,
        ``(m1 + m2) / 2`` on the mean of PSFs scattered by 0.0010 between four
        independent 200,000-galaxy samples where the jackknife gives 0.0004
        (``benchmarks/README.md``, "What the studies found"). 80,000 take that noise's
        variance to a quarter for about 8 more minutes and 2.4 GB more memory in a
        200,000-galaxy run (40 kB per calibration galaxy).
    stratified_calibration : bool
        Draw the calibration sample's morphologies, fluxes and sizes stratified within
        each block (:func:`_population`): the morphologies in proportion, and a Latin
        hypercube in flux and size within each morphology. The sample then follows the
        population's distributions to ``1 / n`` instead of ``1 / sqrt(n)``, and its
        priors, estimated from ``ncal / 4`` galaxies per PSF, carry the noise of the pixels
        alone, not that of which galaxies happened to be drawn. A survey estimates its
        priors from the galaxies it measures; a simulation that draws them anew from the
        population adds a noise of its own to m, which the jackknife does not see. Over
        six calibration samples the standard deviation of m on the mean of PSFs fell
        from 0.0009 to 0.0004 (per PSF from 0.0008-0.0019 to 0.0005-0.0008), its mean
        unchanged (``benchmarks/studies/precision_size_prior_noise.py``).
        False: drawn at random, as the main sample.
    noise_twins : bool
        Render every galaxy eight times instead of four: the four of the module table and
        the same four with their noise fields negated (the module docstring). The
        renderings ``k = 0..3`` are those of the set without twins (same galaxies, same
        noise): the twins are added, nothing else is drawn. At the same number of
        renderings (half the galaxies) c's errors are 2.9 times smaller and m's the same
        (``benchmarks/precision_noise_twins.py``, 16,000 galaxies, four PSFs): m's error
        is the noise's second-order effect, which the +-g pairing leaves and the twins
        do not cancel either, c's the first-order one.
    seed : int
        Seed: everything is a function of it.
    population : {"aligned", "realistic"}
        ``"aligned"``: every bulge aligned with its disc and as elongated, a bulge of half
        its disc's half-light radius, Sersic indices 0.5-4. ``"realistic"``: what real
        galaxies have and no model of the bulge+disc family holds
        (:data:`pylensfit_validation.galaxies.REALISTIC`):
        Sersic indices 0.3-6 (log-uniform), bulges of 0.25-0.8 of their disc's
        half-light radius, the bulge+disc galaxies' bulges 0.2-1 times as elongated as
        their discs and misaligned by a Gaussian angle of 30 degrees rms, and the knotty
        discs' bulges 0-0.6 times as elongated (10 degrees rms), drawn after every
        parameter of the aligned population, so the two share their galaxies' fluxes,
        sizes, disc shapes and noise (column ``misalign``: the bulge's position angle
        less its disc's, degrees).
    """

    ngal: int = 200_000
    g: float = 0.02
    psfs: tuple[dict, ...] = PRECISION_PSFS
    snr_range: tuple[float, float] = (10.0, 200.0)
    snr_slope: float = 2.0
    size_ratio_range: tuple[float, float] = (0.5, 2.5)
    morphology_weights: tuple[float, ...] = (0.25, 0.15, 0.25, 0.2, 0.15)
    prior_params: tuple[float, float, float] = (0.19, 0.58, 2.4)
    max_e: float = 0.99
    noise_sigma: float = 1.0
    offset: float = 0.5
    offset_shape: str = "square"
    block_size: int = 500
    ncal: int = 80_000
    stratified_calibration: bool = True
    noise_twins: bool = False
    seed: int = 1
    population: str = "aligned"
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.ngal < 2 * len(self.psfs) or self.block_size < 1:
            raise ValueError("precision needs at least two galaxies per PSF and block_size >= 1")
        if not 0 <= self.offset <= 4:
            raise ValueError(f"offset must be in [0, 4] pixels, got {self.offset}")
        if self.offset_shape not in ("square", "gaussian"):
            raise ValueError(f"offset_shape must be 'square' or 'gaussian', got "
                             f"{self.offset_shape!r}")  # fmt: skip
        if not 0 < self.g < 0.2:
            raise ValueError(f"g must be in (0, 0.2), got {self.g}")
        if len(self.morphology_weights) != len(MORPHOLOGIES):
            raise ValueError(f"morphology_weights needs {len(MORPHOLOGIES)} values")
        w = np.asarray(self.morphology_weights, dtype=float)
        if not (np.all(np.isfinite(w)) and np.all(w >= 0) and w.sum() > 0):
            raise ValueError(f"morphology_weights must be >= 0 with a positive sum, got "
                             f"{tuple(self.morphology_weights)}")  # fmt: skip
        lo, hi = (float(v) for v in self.snr_range)
        if not 0 < lo <= hi:
            raise ValueError(f"snr_range must be 0 < lo <= hi, got {tuple(self.snr_range)}")
        if self.population not in POPULATIONS:
            raise ValueError(f"population must be one of {POPULATIONS}, not "
                             f"{self.population!r}")  # fmt: skip


# ----------------------------------------------------------------------------------------
# Rendering
# ----------------------------------------------------------------------------------------
def _galsim_psf(p: dict):
    """The GalSim profile of a PSF of :data:`PRECISION_PSFS` (no pixel response)."""
    return PSFProfile.from_dict(p).galsim()


def _draw(obj, n: int, offset=(0.0, 0.0)) -> np.ndarray:
    """``obj`` with the pixel response on ``n x n``, its centre at element ``[n//2, n//2]``."""
    half = 0.5 if n % 2 == 0 else 0.0
    return obj.drawImage(nx=n, ny=n, scale=1.0, offset=(offset[0] + half, offset[1] + half)).array


def _psf_image(p: dict, n: int) -> tuple[np.ndarray, float]:
    """The PSF image on the stamp grid and its half-light radius (pixels)."""
    import galsim  # galsim: heavy import, only for rendering

    psf = _galsim_psf(p)
    img = _draw(psf, n)
    hlr = galsim.Image(_draw(psf, 4 * n), scale=1.0).calculateHLR()
    return img / img.sum(), float(hlr)


def _profile(row) -> Any:
    """The unit-flux galaxy of one row of :func:`_population` (pixels).

    :class:`~pylensfit_validation.galaxies.GalaxyProfile`, every size a half-light radius, with a
    bulge of half-light radius ``bulge_size_ratio r`` (``r`` the disc's; 0.5, the
    STEP2-like sets' bulge, in the aligned population), flux ``bulge_frac`` and its own
    shear ``bulge_g1/2``: round unless the bulge has a shape of its own.
    """
    morph = MORPHOLOGIES[int(row["morph"])]
    bulge_shear = (float(row["bulge_g1"]), float(row["bulge_g2"]))
    return GalaxyProfile(morph, float(row["r"]), sersic_n=float(row["sersic_n"]),
                         bulge_fraction=float(row["bulge_frac"]),
                         bulge_size_ratio=float(row["bulge_size_ratio"]),
                         knot_fraction=float(row["knot_frac"]), n_knots=int(row["n_knots"]),
                         knot_seed=int(row["knot_seed"]),
                         bulge_shear=bulge_shear).galsim()  # fmt: skip


def population_prior(spec: PrecisionSpec) -> Prior:
    """The functional ellipticity prior that the population's intrinsic shapes are drawn
    from (``spec.prior_params``; a diagnostic for :func:`precision`, as ``prior``)."""
    return Prior(**dict(zip("BCD", spec.prior_params, strict=True)))


def population_size_prior(spec: PrecisionSpec, psf_index: int = 0, *,
                          stamp_size: int = 32) -> SizePrior:  # fmt: skip
    """The population's own size prior for one PSF (a diagnostic for :func:`precision`).

    Log-uniform in half-light radius over ``spec.size_ratio_range`` times the PSF's
    half-light radius, as :func:`render_block` draws the sizes. It is exact for the
    exponential, de Vaucouleurs and Sersic galaxies; the bulge+disc and knotty galaxies
    draw their disc's half-light radius, so theirs are smaller.
    """
    _, psf_hlr = _psf_image(spec.psfs[psf_index], int(stamp_size))
    lo, hi = np.log(np.asarray(spec.size_ratio_range, dtype=float) * psf_hlr)
    eps = 1e-4 * (hi - lo)
    knots = np.concatenate([[lo - eps], np.linspace(lo, hi, 50), [hi + eps]])
    dens = np.concatenate([[0.0], np.full(50, 1.0 / (hi - lo)), [0.0]])
    return SizePrior(ln_h=knots, density=dens * (1 - 1e-6), star=1e-6)


def _stratified(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` uniform deviates on [0, 1), one in each of ``n`` equal strata, shuffled."""
    return (rng.permutation(n) + rng.random(n)) / max(n, 1)


def _population(spec: PrecisionSpec, n: int, psf_hlr: float, rng: np.random.Generator,
                stratified: bool = False) -> Table:  # fmt: skip
    """Per-galaxy parameters of one block (all drawn from ``rng``).

    With ``stratified``, the morphologies are drawn in proportion to their weights
    (systematic sampling) and, within each morphology, the flux and the size as a Latin
    hypercube (one galaxy in each of the ``n_k`` equal strata of each, paired at
    random); the other parameters are drawn at random either way.
    """
    w = np.asarray(spec.morphology_weights, float)
    lsr = np.log(spec.size_ratio_range)
    if stratified:
        cum = np.cumsum(w / w.sum())
        morph = np.minimum(np.searchsorted(cum, _stratified(rng, n), side="right"), w.size - 1)
        u, v = np.empty(n), np.empty(n)
        for k in range(w.size):  # five morphologies
            sel = np.flatnonzero(morph == k)
            u[sel], v[sel] = _stratified(rng, sel.size), _stratified(rng, sel.size)
        ratio = np.exp(lsr[0] + v * (lsr[1] - lsr[0]))
    else:
        morph = rng.choice(len(MORPHOLOGIES), n, p=w / w.sum())
        u = rng.random(n)
    lo, hi = spec.snr_range
    a = spec.snr_slope
    if abs(a - 1.0) < 1e-9:
        snr = lo * (hi / lo) ** u
    else:  # inverse CDF of S^-a on [lo, hi]
        snr = (lo ** (1 - a) + u * (hi ** (1 - a) - lo ** (1 - a))) ** (1 / (1 - a))
    if not stratified:  # after the flux: the random draws keep their order (main sample)
        ratio = np.exp(rng.uniform(*lsr, n))
    e = draw_shapes(population_prior(spec), n, rng, spec.max_e)
    name = np.asarray(MORPHOLOGIES)[morph]
    bf = np.select([name == "exponential", name == "devaucouleurs", name == "bulge+disc",
                    name == "knots"],
                   [0.0, 1.0, rng.uniform(0, 1, n), rng.uniform(0, 0.3, n)], np.nan)  # fmt: skip
    t = Table()
    t["morph"] = morph.astype(np.int16)
    t["snr_ref"] = snr
    t["size_ratio"] = ratio
    t["r"] = ratio * psf_hlr
    t["e1_int"], t["e2_int"] = e[:, 0], e[:, 1]
    t["bulge_frac"] = bf
    t["sersic_n"] = np.where(name == "sersic", np.round(rng.uniform(0.5, 4.0, n), 1), np.nan)
    t["n_knots"] = np.where(name == "knots", rng.integers(10, 30, n), 0)
    t["knot_frac"] = rng.uniform(0.2, 0.5, n)
    t["knot_seed"] = rng.integers(1, 2**31 - 1, n)
    ux, uy = rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n)
    if spec.offset_shape == "gaussian":  # Box-Muller from the same two uniforms
        rad = spec.offset / math.sqrt(3.0) * np.sqrt(-2.0 * np.log(0.5 - ux))
        ux, uy = rad * np.cos(2 * np.pi * uy), rad * np.sin(2 * np.pi * uy)
    else:
        ux, uy = ux * (2.0 * spec.offset), uy * (2.0 * spec.offset)
    t["dx"], t["dy"] = ux, uy
    _bulge_shapes(t, name, rng, spec.population == "realistic")
    return t


def _bulge_shapes(t: Table, name: np.ndarray, rng: np.random.Generator, realistic: bool) -> None:
    """The bulges' sizes and own shapes (columns ``bulge_size_ratio``, ``bulge_g1/2``,
    ``misalign``); for the ``"realistic"`` population the Sersic indices again too,
    drawn after every other parameter so that both populations share those."""
    n = len(t)
    has_bulge = (name == "bulge+disc") | (name == "knots")
    t["bulge_size_ratio"] = np.full(n, 0.5)
    t["bulge_g1"], t["bulge_g2"] = np.zeros(n), np.zeros(n)
    t["misalign"] = np.where(has_bulge, 0.0, np.nan)
    if not realistic:
        return
    t["sersic_n"] = np.where(name == "sersic", draw_sersic_indices(n, rng), np.nan)
    e_int = np.stack([np.asarray(t["e1_int"]), np.asarray(t["e2_int"])], -1)
    ratio, b1, b2, dphi = draw_bulge_shapes(name == "bulge+disc", name == "knots", e_int, rng)
    t["bulge_size_ratio"] = np.where(has_bulge, ratio, 0.5)
    t["bulge_g1"], t["bulge_g2"] = b1, b2
    t["misalign"] = np.where(has_bulge, dphi, np.nan)


def render_block(
    spec: PrecisionSpec,
    psf_index: int,
    block: int,
    *,
    stamp_size: int = 32,
    calibration: bool = False,
    noise: bool = True,
) -> tuple[np.ndarray, np.ndarray, Table]:
    """Render one block of the precision set (or of its calibration sample).

    Parameters
    ----------
    spec : PrecisionSpec
        The set.
    psf_index : int
        Which of ``spec.psfs``.
    block : int
        Block number (its galaxies and noise are a function of ``spec.seed`` and it).
    stamp_size : int
        Stamp side in pixels.
    calibration : bool
        Render the unsheared calibration sample instead: one rendering per galaxy.
    noise : bool
        Add the noise (``False``: the noise-free renderings, for tests).

    Returns
    -------
    stamps : numpy.ndarray
        ``(n, R, N, N)`` renderings in the order of the module table, ``R = 4`` (8 with
        ``spec.noise_twins``; ``(n, 1, N, N)`` for the calibration sample), indexed
        ``[.., y, x]``.
    psf : numpy.ndarray
        ``(N, N)`` the PSF image (pixel response included, unit sum).
    truth : astropy.table.Table
        The galaxies' parameters (:func:`_population`).
    """
    import galsim  # galsim: heavy import, only for rendering

    p = spec.psfs[psf_index]
    n_stamp = int(stamp_size)
    psf_img, psf_hlr = _psf_image(p, n_stamp)
    nblocks = _n_blocks(spec.ncal if calibration else spec.ngal, spec.block_size)
    ntot = spec.ncal if calibration else spec.ngal
    n = min(spec.block_size, ntot - block * spec.block_size)
    if n <= 0 or block >= nblocks:
        raise ValueError(f"block {block} is outside the set ({nblocks} blocks)")
    rng = np.random.default_rng([spec.seed, int(calibration), block])
    t = _population(spec, n, psf_hlr, rng, stratified=calibration and spec.stratified_calibration)
    psf = _galsim_psf(p)
    if calibration:
        shears = [(0.0, False)]
    else:
        shears = [(+spec.g, False), (+spec.g, True), (-spec.g, False), (-spec.g, True)]
    out = np.empty((n, len(shears), n_stamp, n_stamp), dtype=np.float32)
    for a in range(n):  # GalSim renders one profile at a time
        gal = _profile(t[a])
        gal = gal.shear(g1=float(t["e1_int"][a]), g2=float(t["e2_int"][a]))
        off = (float(t["dx"][a]), float(t["dy"][a]))
        for k, (g, rot) in enumerate(shears):
            obj = gal.rotate(90 * galsim.degrees) if rot else gal
            out[a, k] = _draw(galsim.Convolve(obj.shear(g1=g, g2=g), psf), n_stamp, off)
    if spec.noise_twins and not calibration:  # the same objects; their noise negated below
        out = np.concatenate([out, out], axis=1)
    _flux_and_noise(out, t, spec, block, reference_norm(spec, psf_index, n_stamp),
                    calibration=calibration, noise=noise)  # fmt: skip
    return out, psf_img, t


def reference_norm(spec: PrecisionSpec, psf_index: int, stamp_size: int = 32) -> float:
    """``sqrt(sum I^2)`` of a unit-flux round exponential of the population's median size
    (``sqrt`` of the product of ``spec.size_ratio_range`` times the PSF's half-light
    radius) under PSF ``psf_index``: a flux ``F`` has the reference S/N ``F *
    reference_norm / noise_sigma`` (see :class:`PrecisionSpec`, ``snr_range``)."""
    import galsim  # galsim: heavy import, only for rendering

    p = spec.psfs[psf_index]
    _, psf_hlr = _psf_image(p, int(stamp_size))
    r_ref = math.sqrt(spec.size_ratio_range[0] * spec.size_ratio_range[1]) * psf_hlr
    gal = GalaxyProfile("exponential", r_ref).galsim()
    img = _draw(galsim.Convolve(gal, _galsim_psf(p)), int(stamp_size))
    return math.sqrt(float(np.sum(img.astype(float) ** 2)))


def population_flux_range(spec: PrecisionSpec, psf_index: int = 0, *,
                          stamp_size: int = 32) -> tuple[float, float]:  # fmt: skip
    """The population's flux limits under PSF ``psf_index`` (``spec.snr_range`` in flux
    units, :func:`reference_norm`): a diagnostic, the bounds of a flux prior that knows
    the population."""
    f = spec.noise_sigma / reference_norm(spec, psf_index, stamp_size)
    return spec.snr_range[0] * f, spec.snr_range[1] * f


def _flux_and_noise(out: np.ndarray, t: Table, spec: PrecisionSpec, block: int, ref: float,
                    *, calibration: bool, noise: bool) -> None:  # fmt: skip
    """Scale unit-flux renderings ``out`` (``(n, 1 or 4, N, N)``) in place to each galaxy's
    flux, ``t["snr_ref"] * noise_sigma / ref`` for the PSF's :func:`reference_norm`
    ``ref`` (``t["flux"]`` records it, ``t["snr"]`` becomes the S/N of the first
    rendering), and add the block's noise, the same field at +g and -g (renderings 4-7,
    the noise twins, where there are eight: the same fields negated)."""
    sig = spec.noise_sigma
    n, _, n_stamp, _ = out.shape
    flux = np.asarray(t["snr_ref"], dtype=float) * sig / ref
    out *= flux[:, None, None, None].astype(np.float32)
    t["flux"] = flux
    t["snr"] = np.sqrt(np.sum(out[:, 0].astype(float) ** 2, axis=(1, 2))) / sig
    if noise:
        nrng = np.random.default_rng([spec.seed, int(calibration), block, 1])
        if calibration:
            out += nrng.normal(scale=sig, size=out.shape).astype(np.float32)
        else:
            na = nrng.normal(scale=sig, size=(n, n_stamp, n_stamp)).astype(np.float32)
            nb = nrng.normal(scale=sig, size=(n, n_stamp, n_stamp)).astype(np.float32)
            out[:, 0] += na
            out[:, 2] += na  # the same noise at +g and -g
            out[:, 1] += nb
            out[:, 3] += nb
            if out.shape[1] == 8:  # the noise twins
                out[:, 4] -= na
                out[:, 6] -= na
                out[:, 5] -= nb
                out[:, 7] -= nb


def _shear_sets(n_renderings: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The renderings at ``+g`` and at ``-g``, for four renderings per galaxy or eight
    (with noise twins): ``k % 4 < 2`` is ``+g``."""
    if n_renderings not in (4, 8):
        raise ValueError(f"a galaxy has 4 or 8 renderings (with noise twins), got "
                         f"{n_renderings}")  # fmt: skip
    ks = range(n_renderings)
    return tuple(k for k in ks if k % 4 < 2), tuple(k for k in ks if k % 4 >= 2)


def _n_blocks(n: int, size: int) -> int:
    return -(-int(n) // int(size))


# ----------------------------------------------------------------------------------------
# Per-rendering reduction: the 12 numbers the estimators need
# ----------------------------------------------------------------------------------------
def reduce_likelihoods(
    lnL: np.ndarray, egrid: np.ndarray, prior: Prior, g_nominal, *, refine: int = 4,
    stencil: int | None = None,
) -> np.ndarray:
    """The per-rendering quantities of every estimator, one pass over the posteriors.

    Parameters
    ----------
    lnL : numpy.ndarray
        ``(n, n_e)`` likelihoods on ``egrid`` (usable rows only).
    egrid : numpy.ndarray
        ``(n_e, 2)`` ellipticity grid.
    prior : Prior
        The (unsheared) prior.
    g_nominal : sequence of float
        ``(g1, g2)`` about which the fixed-point estimator is linearised.
    refine : int
        Integration refinement (as :func:`pylensfit.shear.shapes`).
    stencil : int, optional
        Points per axis of the interpolation onto the integration grid
        (:func:`pylensfit.shear.refine_lnL`; default :data:`pylensfit.shear.DEFAULT_STENCIL`).

    Returns
    -------
    numpy.ndarray
        ``(n, 12)``: ``<e1>, <e2>`` under ``P``; exact sensitivities ``sx1, sx2``; the
        paper's ``sp1, sp2``; ``<e1>, <e2>`` under ``P_gn`` (the prior sheared by
        ``g_nominal``) and their derivatives ``d<e_i>/dg_j`` there (``J11, J12, J21,
        J22``).
    """
    stencil = DEFAULT_STENCIL if stencil is None else int(stencil)
    grid = refined_grid(egrid, refine, stencil)
    K0 = kernel_columns(prior, grid)
    P, d1, d2 = sheared_prior_columns(prior, grid, np.asarray(g_nominal, float))
    e1, e2 = grid[:, 0], grid[:, 1]
    K1 = np.column_stack([P, e1 * P, e2 * P, d1, e1 * d1, e2 * d1, d2, e1 * d2, e2 * d2])
    S = sums_with(lnL, egrid, np.hstack([K0, K1]), refine, None, stencil)
    S0, S1 = S[:, :14], S[:, 14:]
    mom = moments_from_sums(S0)
    sx = sensitivity_from_sums(S0, "exact")
    sp = sensitivity_from_sums(S0, "paper")
    s0 = S1[:, 0]
    f1, f2 = S1[:, 1] / s0, S1[:, 2] / s0
    return np.column_stack([
        mom["e1"], mom["e2"], sx[0], sx[1], sp[0], sp[1], f1, f2,
        (S1[:, 4] - f1 * S1[:, 3]) / s0, (S1[:, 7] - f1 * S1[:, 6]) / s0,
        (S1[:, 5] - f2 * S1[:, 3]) / s0, (S1[:, 8] - f2 * S1[:, 6]) / s0,
    ])  # fmt: skip


def reduce_renderings(fits, prior: Prior, g: float, *, refine: int = 4,
                      bulge_weights: np.ndarray | None = None,
                      stencil: int | None = None, renderings: int = 4,
                      min_snr: float = 0.0):  # fmt: skip
    """:func:`reduce_likelihoods` of the fits of ``n`` galaxies' four (or eight) renderings.

    Parameters
    ----------
    fits : StampFits
        Fits of the ``R n`` stamps, galaxy by galaxy in the module's rendering order.
    prior : Prior
        The prior.
    g : float
        The applied shear per component (nominal shears ``+(g, g)`` for renderings 0-1,
        ``-(g, g)`` for 2-3).
    refine : int
        Integration refinement.
    bulge_weights : numpy.ndarray, optional
        Prior probabilities of the bulge fractions (:func:`~pylensfit.prior.
        estimate_bulge_weights`); the fits' uniform mixture if ``None``.
    stencil : int, optional
        As :func:`reduce_likelihoods`.
    renderings : int
        Renderings per galaxy ``R``: 4, or 8 with noise twins.
    min_snr : float
        Renderings whose best model's S/N is below this are not measured
        (``Config.min_snr``).

    Returns
    -------
    Q : numpy.ndarray
        ``(n, R, 12)`` per-rendering quantities (NaN where not measured).
    usable : numpy.ndarray
        ``(n, R)`` measured renderings.
    """
    plus, minus = _shear_sets(renderings)
    R = int(renderings)
    ok = _usable(fits, min_snr)
    n = ok.size // R
    lnL = fits.lnL
    if bulge_weights is not None and fits.lnL_bulge is not None:
        lnL = mix_bulge_fractions(fits.lnL_bulge, fits.lnL_star, bulge_weights)
    Q = np.full((R * n, _NQ), np.nan)
    for ks, gn in ((plus, (g, g)), (minus, (-g, -g))):  # the nominal shear of each set
        sel = np.zeros((n, R), bool)
        sel[:, list(ks)] = True
        sel = sel.ravel() & ok
        if np.any(sel):
            Q[sel] = reduce_likelihoods(lnL[sel], fits.egrid, prior, gn, refine=refine,
                                        stencil=stencil)  # fmt: skip
    return Q.reshape(n, R, _NQ), ok.reshape(n, R)


def measured_bulge_fraction(fits, prior: Prior,
                            bulge_weights: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """Each stamp's posterior mean bulge fraction, an observed quantity to bin on.

    ``sum_k f_k p(k | data)`` with ``p(k | data)`` proportional to
    ``pi_k sum_e P(e) L_k(e)`` on the fits' ellipticity grid (the point source left
    out): the bulge fraction that the data and the priors give, not the truth's.

    Parameters
    ----------
    fits : StampFits
        Fits with the bulge fraction marginalised (``lnL_bulge``, ``bulge_fractions``).
    prior : Prior
        The ellipticity prior ``P(e)``.
    bulge_weights : numpy.ndarray, optional
        Prior probabilities ``pi_k`` of the fractions (uniform if ``None``).

    Returns
    -------
    numpy.ndarray
        ``(n,)`` posterior mean bulge fractions in ``[0, 1]`` (NaN where not measured).
    """
    lb = np.asarray(fits.lnL_bulge, dtype=float)
    n_b = lb.shape[1]
    w = np.full(n_b, 1.0 / n_b) if bulge_weights is None else np.asarray(bulge_weights, float)
    eg = np.asarray(fits.egrid, dtype=float)
    with np.errstate(divide="ignore"):
        lnp = np.log(prior.pdf(eg[:, 0], eg[:, 1]))
        lnw = np.log(w / w.sum())
    a = logsumexp(lb + lnp[None, None, :], axis=2) + lnw[None, :]
    with np.errstate(invalid="ignore"):
        post = np.exp(a - logsumexp(a, axis=1, keepdims=True))
    return post @ np.asarray(fits.bulge_fractions, dtype=float)


def _usable(fits, min_snr: float = 0.0) -> np.ndarray:
    """Measured galaxies: no flag, not a point source, S/N at least ``min_snr``."""
    snr = np.asarray(fits.snr, dtype=float)
    return (np.asarray(fits.flags) == 0) & ~np.asarray(fits.is_star) & ~(snr < min_snr)


def _block_task(task: dict[str, Any]) -> dict[str, Any]:
    """Render, fit and reduce one block (runs in a worker)."""
    single_thread(task.get("single_thread", False))
    spec: PrecisionSpec = task["spec"]
    cfg: Config = task["config"]
    t0 = time.perf_counter()
    stamps, psf, truth = render_block(spec, task["psf"], task["block"],
                                      stamp_size=cfg.largest_stamp,
                                      calibration=task["calibration"],
                                      noise=task.get("noise", True))  # fmt: skip
    t1 = time.perf_counter()
    n, nr = stamps.shape[:2]
    groups = None
    if task.get("keep_lnL_r") == "annuli":  # L(r) per |e|, for any prior of |e| later

        groups = e_annuli(model_bank(cfg).egrid)
    fits = fit_stamps(stamps.reshape(n * nr, *stamps.shape[2:]), psf, spec.noise_sigma,
                      config=cfg, size_prior=task.get("size_prior"),
                      size_marginal_prior=task.get("size_marginal_prior"),
                      lnL_r_groups=groups)  # fmt: skip
    t2 = time.perf_counter()
    ok = _usable(fits, cfg.min_snr)
    res: dict[str, Any] = {"block": task["block"], "psf": task["psf"], "truth": truth,
                           "render_s": t1 - t0, "fit_s": t2 - t1}  # fmt: skip
    if task["calibration"]:
        c = stamps.shape[-1] // 2  # the catalogue position: the stamp's centre
        res["sample"] = CalibrationSample.from_fits(fits, ok, c, c, group=task["psf"])
        if task.get("keep_lnL_r") and task.get("keep_lnL_r") != "annuli":
            res["lnL_r"] = fits.lnL_r[ok]
        return res
    Q, usable = reduce_renderings(fits, task["prior"], spec.g, refine=cfg.output_refine,
                                  bulge_weights=task.get("bulge_weights"),
                                  stencil=task.get("stencil"), renderings=nr,
                                  min_snr=cfg.min_snr)  # fmt: skip
    res["Q"] = Q.astype(np.float32)
    res["usable"] = usable
    if fits.lnL_bulge is not None:  # averaged over the renderings: even in the shear
        bf = measured_bulge_fraction(fits, task["prior"], task.get("bulge_weights"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a galaxy never measured
            res["bulge_meas"] = np.nanmean(np.where(usable, bf.reshape(n, nr), np.nan),
                                           axis=1).astype(np.float32)  # fmt: skip
    res["r_best"] = fits.r_best.reshape(n, nr)[:, 0].astype(np.float32)
    res["snr_meas"] = fits.snr.reshape(n, nr)[:, 0].astype(np.float32)
    res["stamp"] = fits.stamp.reshape(n, nr)[:, 0].astype(np.int16)
    res["reduce_s"] = time.perf_counter() - t2
    return res


# ----------------------------------------------------------------------------------------
# Estimators and the jackknife
# ----------------------------------------------------------------------------------------
def _shear_from_sums(T: np.ndarray, N: np.ndarray, gn: np.ndarray, estimator: str):
    """``(..., 2)`` shear from summed quantities ``T (..., 12)`` of ``N (...)`` renderings."""
    ix = {q: i for i, q in enumerate(_Q)}
    if estimator in ("exact", "paper"):
        s = "sx" if estimator == "exact" else "sp"
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.stack([T[..., ix["e1"]] / T[..., ix[f"{s}1"]],
                             T[..., ix["e2"]] / T[..., ix[f"{s}2"]]], axis=-1)  # fmt: skip
    # one Newton step of f(g) = sum <e>(P_g) - N g from g_nominal
    f1 = T[..., ix["fe1"]] - N * gn[0]
    f2 = T[..., ix["fe2"]] - N * gn[1]
    a, b = T[..., ix["J11"]] - N, T[..., ix["J12"]]
    c, d = T[..., ix["J21"]], T[..., ix["J22"]] - N
    with np.errstate(invalid="ignore", divide="ignore"):
        det = a * d - b * c
        return np.stack([gn[0] - (d * f1 - b * f2) / det, gn[1] - (a * f2 - c * f1) / det],
                        axis=-1)  # fmt: skip


def bias_table(
    Q: np.ndarray,
    usable: np.ndarray,
    blocks: np.ndarray,
    g: float,
    *,
    groups: dict[str, np.ndarray] | None = None,
    selection: str = "paired",
    controls: np.ndarray | None = None,
) -> Table:
    """m and c with jackknife errors for every estimator and group of galaxies.

    Parameters
    ----------
    Q : numpy.ndarray
        ``(n_gal, R, 12)`` per-rendering quantities (:func:`reduce_likelihoods`), in the
        rendering order of the module table: ``R = 4``, or 8 with the noise twins.
    usable : numpy.ndarray
        ``(n_gal, R)`` measured renderings.
    blocks : numpy.ndarray
        ``(n_gal,)`` jackknife block of each galaxy.
    g : float
        The applied shear per component (``+-(g, g)``).
    groups : dict of str to numpy.ndarray, optional
        Named boolean ``(n_gal,)`` masks; default one group ``all``.
    selection : {"paired", "independent"}
        ``paired``: a galaxy counts only if all its renderings are measured;
        ``independent``: each rendering counts on its own.
    controls : numpy.ndarray, optional
        ``(n_gal, k)`` control variates: per-galaxy quantities whose population mean is
        known to be zero and which correlate with the galaxies' response, such as the
        spin-4 parts of the intrinsic ellipticity (:func:`shape_controls`). Each of m1,
        m2, c1, c2 then becomes ``v - beta . xbar`` (``xbar`` the controls' mean over the
        measured renderings), with ``beta`` regressed from the blocks' jackknife
        pseudo-values. This removes the shape noise that 90-degree twins leave (the
        response's ``cos 4 theta`` terms) without changing the expectation; the errors
        are the jackknife of the corrected values. Groups of fewer than 20 blocks are
        left uncorrected (``beta`` would be noise).

    Returns
    -------
    astropy.table.Table
        One row per group and estimator: ``group, estimator, m1, m1_err, m2, m2_err, c1,
        c1_err, c2, c2_err, n_gal, n_blocks`` and ``controlled`` (whether the controls
        were applied); errors are delete-one-block jackknife.
    """
    Q = np.nan_to_num(np.asarray(Q, float))
    usable = np.asarray(usable, bool)
    sets = _shear_sets(Q.shape[1])
    if selection == "paired":
        w = np.repeat(usable.all(axis=1, keepdims=True), Q.shape[1], axis=1)
    elif selection == "independent":
        w = usable
    else:
        raise ValueError(f"selection must be 'paired' or 'independent', got {selection!r}")
    ub, bidx = np.unique(np.asarray(blocks), return_inverse=True)
    nb = ub.size
    groups = groups if groups is not None else {"all": np.ones(len(Q), bool)}
    X = None if controls is None else np.asarray(controls, float).reshape(len(Q), -1)
    rows = []
    gvec = np.array([g, g])
    for name, mask in groups.items():
        mask = np.asarray(mask, bool)
        n_gal = int((mask & w.any(axis=1)).sum())
        # per block sums of the + and - renderings: (2, nb, 12) and (2, nb)
        T = np.zeros((2, nb, _NQ))
        N = np.zeros((2, nb))
        for s, ks in enumerate(sets):
            ww = w[:, ks] & mask[:, None]
            qs = np.einsum("ak,akq->aq", ww, Q[:, ks])
            for q in range(_NQ):
                T[s, :, q] = np.bincount(bidx, weights=qs[:, q], minlength=nb)
            N[s] = np.bincount(bidx, weights=ww.sum(axis=1), minlength=nb)
        used = N.sum(axis=0) > 0
        tot_T, tot_N = T.sum(axis=1), N.sum(axis=1)
        # full sample first, then leave-one-block-out (only blocks with galaxies)
        TT = np.concatenate([tot_T[:, None], tot_T[:, None] - T[:, used]], axis=1)
        NN = np.concatenate([tot_N[:, None], tot_N[:, None] - N[:, used]], axis=1)
        k = int(used.sum())
        xbar = None
        if X is not None and k >= _MIN_CONTROL_BLOCKS:
            # the controls' mean over the measured renderings, full and leave-one-out
            wx = (w & mask[:, None]).sum(axis=1).astype(float)
            SX = np.stack([np.bincount(bidx, weights=wx * X[:, j], minlength=nb)
                           for j in range(X.shape[1])], axis=1)[used]  # fmt: skip
            SW = np.bincount(bidx, weights=wx, minlength=nb)[used]
            with np.errstate(invalid="ignore", divide="ignore"):
                xbar = np.concatenate([SX.sum(0)[None] / SW.sum(),
                                       (SX.sum(0) - SX) / (SW.sum() - SW)[:, None]])  # fmt: skip
        for est in _ESTIMATORS:
            gp = _shear_from_sums(TT[0], NN[0], gvec, est)
            gm = _shear_from_sums(TT[1], NN[1], -gvec, est)
            m = (gp - gm) / (2 * g) - 1.0
            c = (gp + gm) / 2.0
            row: dict[str, Any] = {"group": name, "estimator": est, "controlled": xbar is not None}
            for i in (0, 1):
                for key, v in (("m", m[:, i]), ("c", c[:, i])):
                    if xbar is not None:
                        v, applied = _controlled(v, xbar, k)
                        row["controlled"] &= applied
                    row[f"{key}{i + 1}"] = float(v[0])
                    jk = v[1:]
                    row[f"{key}{i + 1}_err"] = (
                        float(math.sqrt((k - 1) / k * np.sum((jk - jk.mean()) ** 2)))
                        if k > 1 else math.nan
                    )  # fmt: skip
            row["n_gal"] = n_gal
            row["n_blocks"] = k
            rows.append(row)
    return Table(rows=[[r[k] for k in _BIAS_COLUMNS] for r in rows], names=_BIAS_COLUMNS)


#: Columns of :func:`bias_table`.
_BIAS_COLUMNS = ["group", "estimator", "m1", "m1_err", "m2", "m2_err", "c1", "c1_err", "c2",
                 "c2_err", "n_gal", "n_blocks", "controlled"]  # fmt: skip


def _psf_mean(per_psf: Table) -> Table:
    """The unweighted mean over PSFs of each estimator's m and c, errors combined.

    The blocks go to the PSFs in turn, so the PSFs' shares of the sample are fixed by
    design; the jackknife of the ``all`` group counts as noise the change of those
    shares when a block is left out, which this mean does not have.
    """
    rows = []
    for est in dict.fromkeys(per_psf["estimator"]):
        t = per_psf[per_psf["estimator"] == est]
        k = len(t)
        row: dict[str, Any] = {"group": "mean of PSFs", "estimator": est}
        for q in ("m1", "m2", "c1", "c2"):
            row[q] = float(np.mean(t[q]))
            row[f"{q}_err"] = float(np.sqrt(np.sum(np.asarray(t[f"{q}_err"]) ** 2)) / k)
        row["n_gal"] = int(np.sum(t["n_gal"]))
        row["n_blocks"] = int(np.sum(t["n_blocks"]))
        row["controlled"] = bool(np.all(t["controlled"]))
        rows.append(row)
    out = Table(rows=[[r[n] for n in _BIAS_COLUMNS] for r in rows], names=_BIAS_COLUMNS)
    out["breakdown"] = "all"
    return out


#: Galaxies per jackknife group of :func:`precision`.
_JACKKNIFE_GALAXIES = 100

#: Fewest jackknife blocks for which :func:`bias_table` applies control variates.
_MIN_CONTROL_BLOCKS = 20


def _controlled(v: np.ndarray, xbar: np.ndarray, k: int) -> np.ndarray:
    """Control-variate correction of a statistic and its ``k`` leave-one-out values.

    ``v`` is ``(1 + k,)``: the full-sample value, then the delete-one-block values;
    ``xbar`` is ``(1 + k, n_c)``, the controls' means over the same samples. ``beta`` is
    the least-squares slope of the blocks' jackknife pseudo-values of ``v`` on those of
    ``xbar``; the result is ``v - xbar . beta`` for every sample, and whether it was
    applied (not where a value is not finite: ``v`` is returned as it is).
    """
    ok = np.isfinite(v).all() and np.isfinite(xbar).all()
    if not ok:
        return v, False
    pv = k * v[0] - (k - 1) * v[1:]
    px = k * xbar[0] - (k - 1) * xbar[1:]
    A = px - px.mean(axis=0)
    beta = np.linalg.lstsq(A, pv - pv.mean(), rcond=None)[0]
    return v - xbar @ beta, True


def shape_controls(e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """Control variates of the precision mode: the spin-4 parts of the intrinsic shape.

    A galaxy's response to a shear depends on its intrinsic ellipticity's orientation
    through ``Re(e^2) = e1^2 - e2^2`` and ``Im(e^2) = 2 e1 e2`` (``e' = e + g - conj(g)
    e^2`` to first order), which its 90-degree twin (``e -> -e``) does not cancel. Over
    an isotropic population both have mean zero exactly, so :func:`bias_table` can
    regress them out of m and c.

    Parameters
    ----------
    e1, e2 : numpy.ndarray
        Intrinsic ellipticities (unrotated rendering).

    Returns
    -------
    numpy.ndarray
        ``(n, 2)``: ``e1^2 - e2^2`` and ``2 e1 e2``.
    """
    e1 = np.asarray(e1, float)
    e2 = np.asarray(e2, float)
    return np.stack([e1 * e1 - e2 * e2, 2.0 * e1 * e2], axis=1)


# ----------------------------------------------------------------------------------------
# The run
# ----------------------------------------------------------------------------------------
#: Bin edges of the breakdowns (true S/N, size over PSF size, bulge fraction).
SNR_EDGES = (5.0, 7.5, 10.0, 12.5, 15.0, 20.0, 30.0, 50.0, 100.0, 200.0, 400.0)
SIZE_EDGES = (0.5, 0.7, 1.0, 1.4, 2.0, 2.5)
BULGE_EDGES = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)
#: the Sersic galaxies' index (0.5-4): below 1 the profile is not in the bulge+disc family
SERSIC_EDGES = (0.5, 1.0, 1.5, 2.5, 4.0)
#: the same for the realistic population's 0.3-6
SERSIC_EDGES_WIDE = (0.3, 0.5, 1.0, 1.5, 2.5, 4.0, 6.0)
#: the bulge's misalignment with its disc, |degrees| (the realistic population)
MISALIGN_EDGES = (0.0, 10.0, 20.0, 40.0, 90.0)


def _breakdowns(gal: Table, psfs: tuple[dict, ...]) -> dict[str, dict[str, np.ndarray]]:
    def binned_values(v, edges):
        out = {}
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            sel = (v >= lo) & ((v < hi) | ((hi == edges[-1]) & (v <= hi)))
            out[f"{lo:g}-{hi:g}"] = sel
        return out

    def binned(col, edges):
        return binned_values(np.asarray(gal[col], float), edges)

    psf = np.asarray(gal["psf"])
    morph = np.asarray(gal["morph"])
    out = {
        "psf": {p["name"]: psf == i for i, p in enumerate(psfs)},
        "snr": binned("snr", SNR_EDGES),
        "size": binned("size_ratio", SIZE_EDGES),
        "morphology": {m: morph == i for i, m in enumerate(MORPHOLOGIES)},
        "bulge_frac": binned("bulge_frac", BULGE_EDGES),
    }
    names = gal.colnames if isinstance(gal, Table) else list(gal)  # a Table or a dict
    if "sersic_n" in names and np.isfinite(np.asarray(gal["sersic_n"], float)).any():
        n = np.asarray(gal["sersic_n"], float)
        wide = np.nanmin(n) < SERSIC_EDGES[0] or np.nanmax(n) > SERSIC_EDGES[-1]
        out["sersic_n"] = binned("sersic_n", SERSIC_EDGES_WIDE if wide else SERSIC_EDGES)
    if "misalign" in names:
        mis = np.abs(np.asarray(gal["misalign"], float))
        if np.nanmax(mis, initial=0.0) > 0:  # the realistic population
            out["misalign"] = binned_values(mis, MISALIGN_EDGES)
    if "bulge_frac_meas" in names:  # conditional on the data, not on the truth
        out["bulge_frac_meas"] = binned("bulge_frac_meas", BULGE_EDGES)
    if len(psfs) > 1:  # the model bias's mix per PSF: m of each morphology under each PSF
        pm = {f"{p['name']} {m}": (psf == i) & (morph == j)
              for i, p in enumerate(psfs) for j, m in enumerate(MORPHOLOGIES)}  # fmt: skip
        out["psf_morphology"] = {k: v for k, v in pm.items() if v.any()}
    return out


def default_config(spec: PrecisionSpec | None = None) -> Config:
    """The configuration :func:`precision` fits with unless given one: ``Config()``.

    The defaults are the method this mode measures: the bulge+disc model with three
    bulge fractions, every prior estimated from the calibration sample by the
    calibration recipe (:mod:`pylensfit.calibration`: a size prior per bulge fraction,
    a power law in the flux bounded where the fluxes end, the position prior's width
    from the fitted centres' scatter), large galaxies on 64-pixel stamps and the size
    grid geometric (10 %) from 0.05 px up to 4 px in scale length and uniform in 0.4 px
    above. Each choice's measured effect is in the ``Config`` field's documentation. ``spec`` is
    accepted for compatibility and not used: nothing a survey cannot know is set.
    """
    return Config()


@dataclass
class _Run:
    """What the passes of one :func:`precision` run share: the set, the workers, CPU time."""

    spec: PrecisionSpec
    jobs: int
    scheduler: str | None
    progress: bool
    pool: ProcessPoolExecutor | None
    render_s: float = 0.0  # CPU seconds rendering, summed over the passes
    fit_s: float = 0.0  # CPU seconds fitting (and reducing), summed over the passes


@dataclass(frozen=True)
class _Calibrated:
    """The priors from the calibration sample, the configurations per PSF, their meta."""

    prior: Prior
    bulge_weights: np.ndarray | None
    size_priors: list[SizePrior | None]
    cfgs: list[Config]
    flux_meta: dict[str, Any] | None
    bounds_meta: list[dict[str, Any] | None] | None


def _check_arguments(spec: PrecisionSpec, cfg: Config,
                     size_prior: SizePrior | Sequence[SizePrior] | None,
                     flux_bounds: bool) -> tuple[list[SizePrior] | None, int]:  # fmt: skip
    """The given size priors (one per PSF) and the calibration blocks; errors said early."""
    npsf = len(spec.psfs)
    given_sp = None
    if size_prior is not None:
        given_sp = [size_prior] * npsf if isinstance(size_prior, SizePrior) else list(size_prior)
        if len(given_sp) != npsf or not all(isinstance(s, SizePrior) for s in given_sp):
            raise ValueError(f"size_prior needs one SizePrior or one per PSF ({npsf})")
    fit_bounds = (flux_bounds and cfg.amplitude_prior == "flux" and cfg.estimate_flux_prior
                  and cfg.amplitude_prior_min == 0
                  and not math.isfinite(cfg.amplitude_prior_max))  # fmt: skip
    ncb = _n_blocks(spec.ncal, spec.block_size)
    if ncb == 0:
        raise ValueError("spec.ncal is 0: a calibration sample is needed to estimate the "
                         "priors")  # fmt: skip
    if fit_bounds:  # the calibration sample's size per PSF, before any fit: say it now
        per_psf = min(sum(min(spec.block_size, spec.ncal - b * spec.block_size)
                          for b in range(k, ncb, npsf)) for k in range(npsf))  # fmt: skip
        if per_psf < MIN_FLUX_RANGE_GALAXIES:
            raise ValueError(f"flux_bounds needs at least {MIN_FLUX_RANGE_GALAXIES} "
                             f"calibration galaxies per PSF to estimate its flux range; "
                             f"spec.ncal = {spec.ncal} gives {per_psf} (a larger ncal, or "
                             f"flux_bounds=False)")  # fmt: skip
    return given_sp, ncb


def _calibration_pass(run: _Run, ncb: int, cfgs: list[Config],
                      size_priors: Sequence[SizePrior | None], keep: bool,
                      label: str) -> CalibrationSample:  # fmt: skip
    """One fit of the ``ncb`` calibration blocks (the recipe's ``fit_pass``), CPU time counted."""
    npsf = len(run.spec.psfs)
    tasks = [{"spec": run.spec, "config": cfgs[b % npsf], "psf": b % npsf, "block": b,
              "calibration": True, "size_prior": size_priors[b % npsf],
              "keep_lnL_r": "annuli" if keep else False}
             for b in range(ncb)]  # fmt: skip
    parts = []
    for _, r in sorted(run_tasks(_block_task, tasks, run.jobs, run.scheduler, label,
                                 run.progress, run.pool),
                       key=lambda tr: tr[0]["block"]):  # fmt: skip
        parts.append(r["sample"])
        run.render_s += r["render_s"]
        run.fit_s += r["fit_s"]
    return CalibrationSample.concatenate(parts)


def _calibrate(run: _Run, ncb: int, cfg: Config, *, prior: Prior | None,
               given_sp: list[SizePrior] | None, bulge_weights: Sequence[float] | None,
               flux_slope: float | None, flux_bounds: bool,
               size_prior_per_psf: bool) -> _Calibrated:  # fmt: skip
    """The priors of the calibration recipe (:func:`~pylensfit.calibration.run_recipe`)."""
    spec = run.spec
    cal_priors = run_recipe(
        partial(_calibration_pass, run, ncb), cfg, len(spec.psfs), prior=prior,
        size_priors=given_sp, bulge_weights=bulge_weights, flux_slope=flux_slope,
        flux_bounds=flux_bounds, size_prior_per_group=size_prior_per_psf,
        group_names=[p["name"] for p in spec.psfs])  # fmt: skip
    ellipticity = cal_priors[0].ellipticity
    weights = cal_priors[0].bulge_weights
    size_priors = [p.size for p in cal_priors]
    cfgs = [p.apply(cfg) for p in cal_priors]
    cfg = cfgs[0]
    info = cal_priors[0].info
    flux_meta = None
    if cfg.amplitude_prior == "flux":
        flux_meta = {"value": cfg.amplitude_prior_power,
                     "error": info.get("flux_power_err", 0.0),
                     "estimated": flux_slope is None and cfg.estimate_flux_prior}  # fmt: skip
    bounds_meta = None
    if info.get("flux_range"):
        bounds_meta = [None if fr is None else
                       {"psf": spec.psfs[k]["name"], **fr,
                        "true": list(population_flux_range(
                            spec, k, stamp_size=cfg.largest_stamp))}
                       for k, fr in enumerate(info["flux_range"])]  # fmt: skip
    return _Calibrated(prior=ellipticity, bulge_weights=weights, size_priors=size_priors,
                       cfgs=cfgs, flux_meta=flux_meta, bounds_meta=bounds_meta)  # fmt: skip


def _main_pass(run: _Run, cal: _Calibrated) -> list[dict[str, Any]]:
    """The renderings of every galaxy, fitted and reduced: the blocks' results in order."""
    spec = run.spec
    npsf = len(spec.psfs)
    nb = _n_blocks(spec.ngal, spec.block_size)
    tasks = [{"spec": spec, "config": cal.cfgs[b % npsf], "prior": cal.prior,
              "bulge_weights": cal.bulge_weights, "size_prior": cal.size_priors[b % npsf],
              "psf": b % npsf, "block": b, "calibration": False}
             for b in range(nb)]  # fmt: skip
    parts: dict[int, dict] = {}
    for t, r in run_tasks(_block_task, tasks, run.jobs, run.scheduler, "precision",
                          run.progress, run.pool):  # fmt: skip
        parts[t["block"]] = r
    return [parts[b] for b in range(nb)]


def _galaxy_table(res: list[dict[str, Any]],
                  spec: PrecisionSpec) -> tuple[np.ndarray, np.ndarray, Table]:  # fmt: skip
    """The blocks' reduced renderings ``Q``, their ``usable`` flags and the galaxies' truth."""
    Q = np.concatenate([r["Q"] for r in res])
    usable = np.concatenate([r["usable"] for r in res])
    gal = Table(np.hstack([np.asarray(r["truth"]) for r in res]))
    gal["psf"] = np.concatenate([np.full(len(r["truth"]), r["psf"]) for r in res])
    gal["block"] = np.concatenate([np.full(len(r["truth"]), r["block"]) for r in res])
    # jackknife groups: the blocks cut into runs of _JACKKNIFE_GALAXIES (the galaxies
    # are independent; the blocks only share out the work), so that a small run still
    # has the groups per PSF that the control variates need
    per_block = -(-spec.block_size // _JACKKNIFE_GALAXIES)
    gal["jk"] = np.concatenate([r["block"] * per_block + np.arange(len(r["truth"]))
                                // _JACKKNIFE_GALAXIES for r in res])  # fmt: skip
    gal["r_best"] = np.concatenate([r["r_best"] for r in res])
    gal["snr_meas"] = np.concatenate([r["snr_meas"] for r in res])
    gal["stamp"] = np.concatenate([r["stamp"] for r in res])
    gal["n_usable"] = usable.sum(axis=1)
    if all("bulge_meas" in r for r in res):
        gal["bulge_frac_meas"] = np.concatenate([r["bulge_meas"] for r in res])
    return Q, usable, gal


def _bias_tables(Q: np.ndarray, usable: np.ndarray, gal: Table, spec: PrecisionSpec) -> Table:
    """The :func:`bias_table` rows of every breakdown, column ``breakdown`` first."""
    npsf = len(spec.psfs)
    X = shape_controls(gal["e1_int"], gal["e2_int"])
    tabs = [bias_table(Q, usable, gal["jk"], spec.g, controls=X)]
    tabs[0]["breakdown"] = "all"
    for name, groups in _breakdowns(gal, spec.psfs).items():
        t = bias_table(Q, usable, gal["jk"], spec.g, groups=groups, controls=X)
        t["breakdown"] = name
        tabs.append(t)
        if name == "psf" and npsf > 1:
            tabs.insert(1, _psf_mean(t))
    t = bias_table(Q, usable, gal["jk"], spec.g, selection="independent", controls=X)
    t["breakdown"] = "selection"
    t.replace_column("group", np.full(len(t), "independent"))
    tabs.append(t)
    t = bias_table(Q, usable, gal["jk"], spec.g)
    t["breakdown"] = "no controls"
    tabs.append(t)
    if Q.shape[1] == 8:  # the same galaxies without their noise twins: what the twins buy
        psf_groups = _breakdowns(gal, spec.psfs)["psf"] if npsf > 1 else {}
        t = bias_table(Q[:, :4], usable[:, :4], gal["jk"], spec.g, controls=X,
                       groups={"all": np.ones(len(gal), bool), **psf_groups})  # fmt: skip
        if npsf > 1:
            t = vstack([t[:1], _psf_mean(t[t["group"] != "all"])[_BIAS_COLUMNS], t[1:]])
        t["breakdown"] = "no noise twins"
        tabs.append(t)
    out = vstack(tabs)
    return out[["breakdown", *[c for c in out.colnames if c != "breakdown"]]]


def _fp_step(Q: np.ndarray, usable: np.ndarray, g: float) -> float:
    """The fixed-point linearisation's largest distance of the estimate from the nominal shear."""
    step = 0.0
    for s, ks in enumerate(_shear_sets(Q.shape[1])):
        w = usable.all(axis=1)
        T = np.nan_to_num(Q[w][:, ks].astype(float)).sum(axis=(0, 1))
        gn = np.array([g, g]) * (1 if s == 0 else -1)
        gh = _shear_from_sums(T, np.asarray(len(ks) * float(w.sum())), gn, "fixed-point")
        step = max(step, float(np.max(np.abs(gh - gn))))
    return step


def _config_meta(cfg: Config) -> dict[str, Any]:
    """The measurement settings of ``meta["config"]``."""
    return {"model": cfg.model, "n_bulge_fractions": cfg.n_bulge_fractions,
            "bulge_size_ratio": cfg.bulge_size_ratio,
            "bulge_size_ratio2": cfg.bulge_size_ratio2,
            "sersic_ladder": list(cfg.sersic_ladder),
            "e_step": cfg.e_step, "e_refine": int(cfg.e_refine),
            "r_step": cfg.r_step, "stamp_size": cfg.stamp_size,
            "max_stamp_size": cfg.largest_stamp,
            "integration_refine": cfg.integration_refine,
            "size_prior": cfg.size_prior,
            "amplitude_prior": cfg.amplitude_prior,
            "amplitude_prior_power": cfg.amplitude_prior_power,
            "amplitude_prior_min": cfg.amplitude_prior_min,
            "amplitude_prior_max": cfg.amplitude_prior_max,
            "position_prior_sigma": cfg.position_prior_sigma}  # fmt: skip


def _prior_params_text(p: dict[str, Any]) -> str:
    """``B=..., C=..., D=...`` or the spline's coefficients, from a result's ``meta``."""
    if p.get("form") == "spline":
        return "spline coefficients " + ", ".join(f"{v:.2f}" for v in p["coef"])
    return f"B={p['B']:.3f}, C={p['C']:.3f}, D={p['D']:.3f}"


def _run_meta(spec: PrecisionSpec, cal: _Calibrated, gal: Table, step: float,
              timing: dict[str, Any], *, prior_given: bool, bulge_method: str,
              size_prior_per_psf: bool, size_prior_given: bool) -> dict[str, Any]:  # fmt: skip
    """The result's ``meta``, in the order of :func:`precision`'s documentation."""
    cfg, prior, bulge_weights = cal.cfgs[0], cal.prior, cal.bulge_weights
    meta: dict[str, Any] = {}
    meta["prior"] = {**prior.form_dict(), "given": prior_given}
    meta["bulge_prior"] = {
        "method": bulge_method if cfg.n_bulge_fractions > 1 else "none",
        "fractions": [float(run.fraction) for run in cfg.bulge_runs],
        "sizes": ([float(run.size) for run in cfg.bulge_runs]
                  if cfg.bulge_size_ratio2 > 0 or cfg.sersic_ladder else None),
        "labels": cfg.run_labels,
        "weights": None if bulge_weights is None else [float(w) for w in bulge_weights],
    }
    meta["size_prior"] = None if cal.size_priors[0] is None else [
        {"psf": spec.psfs[k]["name"], "ln_h": sp.ln_h.tolist(), "density": sp.density.tolist(),
         "star": sp.star, "smoothing": sp.smoothing,
         # a prior per run: the runs mixed with the bulge weights, for the report
         **({"marginal": sp.marginal(bulge_weights).tolist()} if sp.per_run else {})}
        for k, sp in enumerate(cal.size_priors)]  # fmt: skip
    meta["size_prior_per_psf"] = bool(size_prior_per_psf)
    meta["size_prior_given"] = size_prior_given
    meta["prior_true"] = dict(zip("BCD", spec.prior_params, strict=True))
    meta["spec"] = {k: v for k, v in asdict(spec).items() if k != "extra"}
    meta["config"] = _config_meta(cfg)
    meta["flux_slope"] = cal.flux_meta
    meta["flux_bounds"] = cal.bounds_meta
    sizes, counts = np.unique(np.asarray(gal["stamp"]), return_counts=True)
    meta["stamps"] = {int(a): int(b) for a, b in zip(sizes, counts, strict=True)}
    meta["fp_step"] = step
    meta["timing"] = timing
    meta["galaxies"] = gal
    return meta


def precision(
    spec: PrecisionSpec | None = None,
    *,
    config: Config | None = None,
    jobs: int = 1,
    scheduler: str | None = None,
    report: str | Path | None = None,
    prior: Prior | None = None,
    progress: bool = True,
    size_prior_per_psf: bool = True,
    size_prior: SizePrior | Sequence[SizePrior] | None = None,
    bulge_weights: Sequence[float] | None = None,
    flux_slope: float | None = None,
    flux_bounds: bool = True,
) -> Table:
    """Run the paired precision measurement of m and c (see the module docstring).

    Parameters
    ----------
    spec : PrecisionSpec, optional
        The simulated set (default :class:`PrecisionSpec()`: 200,000 galaxies, four PSFs).
    config : Config, optional
        Measurement settings (default: the bulge+disc model with the bulge fraction
        marginalised over 0, 0.5 and 1, as ``pylensfit validate``, and the size prior
        estimated). With ``bulge_prior="estimated"`` the prior over the fractions comes
        from the calibration sample with the ellipticity prior
        (:func:`~pylensfit.prior.estimate_prior_and_bulge`; with a given ``prior``, the
        weights alone under it). With ``size_prior="estimated"`` the calibration sample
        is fitted twice: with the flat size prior, for a first ellipticity prior and
        each galaxy's ``L(r)`` marginalised over e with it (kept per ``|e|`` in the fit,
        :func:`~pylensfit.likelihood.reweight_lnL_r`, then reweighted to that prior),
        for the size prior (:func:`~pylensfit.prior.estimate_size_prior`); then with
        the size prior, for the ellipticity and bulge-fraction priors. The renderings
        are fitted with all three. One pool of ``jobs`` workers serves every pass.
    jobs : int
        Local worker processes.
    scheduler : str, optional
        A dask.distributed scheduler address to run the blocks on instead.
    report : str or pathlib.Path, optional
        Write a Markdown report here, with one PNG per breakdown beside it and the table
        as ECSV.
    prior : Prior, optional
        Use this prior instead of estimating it from the calibration sample (a
        diagnostic: with the true population's prior, ``PrecisionSpec.prior_params``, the
        difference in m is the share of the prior's estimation).
    progress : bool
        Progress bars.
    size_prior_per_psf : bool
        With ``size_prior="estimated"``, one size prior per PSF, each from that PSF's
        calibration galaxies (default). The population's sizes are drawn relative to
        the PSF's size, so each PSF has its own size distribution in pixels; one prior
        for all of them is too wide for each, and pulls the galaxies of the small PSFs
        larger (m < 0) and those of the large PSFs smaller (m > 0).
    size_prior : SizePrior or sequence of SizePrior, optional
        Use this size prior (one for all PSFs, or one per PSF) instead of estimating it
        (a diagnostic, as ``prior``: :func:`population_size_prior` gives the
        population's own).
    bulge_weights : sequence of float, optional
        Use these weights of the bulge fractions (one per ``config.bulge_runs``,
        normalised here) instead of estimating them (a diagnostic).
    flux_slope : float, optional
        With ``config.amplitude_prior="flux"``, the power ``beta`` of the amplitude prior
        ``A^-beta``. By default it is estimated from the measured fluxes of the
        calibration sample's first pass (:func:`~pylensfit.prior.estimate_flux_slope`),
        as the number counts' slope is in a survey, and the later passes and the
        renderings are fitted with it; given, it replaces the estimate (a diagnostic:
        ``spec.snr_slope`` is the population's own).
    flux_bounds : bool
        With ``config.amplitude_prior="flux"`` and no bounds in the configuration
        (``amplitude_prior_min`` 0, ``amplitude_prior_max`` infinite), estimate the flux
        range of each PSF's calibration galaxies from the first pass's fluxes and their
        errors (:func:`~pylensfit.prior.estimate_flux_range`: the power law's limits,
        deconvolved from the noise) and fit the later passes and the renderings with the
        prior bounded there. The population's flux range is finite, and a prior without
        its lower bound keeps a weight, at the faint end, for models that fit a galaxy
        with less flux than it has: m +0.003 for exponential galaxies fitted with their
        own model (``benchmarks/studies/precision_priors.py --flux-bounds``). The
        errors' scale is fitted with the limits (the best model's flux scatters about
        twice its fixed-model error), and with the size prior to estimate, the first
        pass is repeated under the bounded prior so that the size prior's ``L(r)`` have
        the flux prior of the later passes. On by default: every prior is then estimated
        consistently, and each kind of galaxy alone is measured at m = 0 within its
        error where the family holds it (exponentials +0.010 unbounded, -0.0001 /
        -0.0028 ± 0.0016 bounded; knotty discs +0.0085 and +0.0006 / +0.0018), because
        the size prior estimated under the unbounded power law is 7-10 % small
        (``benchmarks/studies/precision_priors.py --estimate-flux-bounds``); on the
        precision mix m is +0.0012 / +0.0013 on the mean of PSFs against +0.0016 /
        +0.0020 unbounded (seed 7, 200,000 galaxies). The calibration takes a third pass
        and the fits about 1.14 times as long (``False``: the unbounded power law, the
        former default).

    Returns
    -------
    astropy.table.Table
        :func:`bias_table` rows for the breakdowns ``all``, per PSF, S/N, size,
        morphology, bulge fraction, the measured bulge fraction (``bulge_frac_meas``,
        with the fraction marginalised: :func:`measured_bulge_fraction` averaged over
        each galaxy's renderings) and (with several PSFs) morphology per PSF
        (``psf_morphology``, groups ``"<psf> <morphology>"``: the model family's bias
        differs by morphology by several per cent, and how it cancels in the mix can
        differ between PSFs) (column ``breakdown``), paired selection, with the
        intrinsic shapes as control variates (:func:`shape_controls`); the ``all``
        breakdown also has the group ``mean of PSFs`` (the PSFs' m and c averaged, the
        errors combined); plus the ``all`` rows with independent selection
        (``breakdown = "selection"``) and without the control variates (``breakdown =
        "no controls"``); with ``spec.noise_twins``, the ``all`` and per-PSF rows of the
        renderings ``k = 0..3`` alone (``breakdown = "no noise twins"``: the same
        galaxies without their twins, for what the twins buy). ``meta``:
        ``prior``, ``spec``, ``timing`` (seconds and galaxies per second),
        ``flux_slope`` (the amplitude prior's power, its error and whether it was
        estimated; with ``amplitude_prior="flux"``), ``flux_bounds`` (per PSF, those
        estimated, with their errors, and the population's), the largest
        fixed-point Newton step ``fp_step`` and ``galaxies`` (per-galaxy truth).
    """
    spec = spec if spec is not None else PrecisionSpec()
    cfg = config if config is not None else default_config(spec)
    bulge_method = "given" if bulge_weights is not None else cfg.bulge_prior
    t_start = time.perf_counter()
    given_sp, ncb = _check_arguments(spec, cfg, size_prior, flux_bounds)
    with worker_pool(jobs, scheduler) as pool:  # one set of workers for every pass
        run = _Run(spec=spec, jobs=jobs, scheduler=scheduler, progress=progress, pool=pool)
        # 1. the priors, from an unsheared calibration sample of the same population, by
        # the calibration recipe that calibrate() and measure() run (pylensfit.calibration)
        cal = _calibrate(run, ncb, cfg, prior=prior, given_sp=given_sp, flux_slope=flux_slope,
                         bulge_weights=bulge_weights, flux_bounds=flux_bounds,
                         size_prior_per_psf=size_prior_per_psf)  # fmt: skip
        t_cal = time.perf_counter() - t_start
        # 2. the four renderings of every galaxy, streamed block by block
        res = _main_pass(run, cal)
    t_main = time.perf_counter() - t_start - t_cal
    Q, usable, gal = _galaxy_table(res, spec)
    # 3. m and c, with the intrinsic shapes' spin-4 parts as control variates
    out = _bias_tables(Q, usable, gal, spec)
    step = _fp_step(Q, usable, spec.g)
    run.render_s += sum(r["render_s"] for r in res)
    run.fit_s += sum(r["fit_s"] + r["reduce_s"] for r in res)
    timing = {
        "total_s": time.perf_counter() - t_start, "calibration_s": t_cal, "main_s": t_main,
        "render_cpu_s": run.render_s, "fit_cpu_s": run.fit_s, "jobs": jobs,
        "galaxies_per_s": spec.ngal / t_main,
        "renderings_per_s": Q.shape[1] * spec.ngal / t_main,
    }  # fmt: skip
    out.meta.update(_run_meta(spec, cal, gal, step, timing, prior_given=prior is not None,
                              bulge_method=bulge_method,
                              size_prior_per_psf=size_prior_per_psf,
                              size_prior_given=given_sp is not None))  # fmt: skip
    if report is not None:
        write_report(out, report)
    return out


# ----------------------------------------------------------------------------------------
# Report
# ----------------------------------------------------------------------------------------
def _fmt(v: float, e: float, digits: int = 4) -> str:
    return f"{v:+.{digits}f} ± {e:.{digits}f}"


def _bulge_line(bp: dict | None) -> str:
    if not bp or bp.get("method") == "none":
        return ""
    if bp.get("weights") is None:
        return "Bulge-fraction prior: uniform over " + ", ".join(
            f"{f:g}" for f in bp["fractions"]) + ".\n"
    names = bp.get("labels") or [f"{f:g}" for f in bp["fractions"]]
    pairs = ", ".join(f"{n}: {w:.3f}" for n, w in zip(names, bp["weights"], strict=True))
    if bp.get("method") == "given":
        return f"Bulge-fraction prior given: {pairs}.\n"
    return f"Bulge-fraction prior estimated from the calibration sample: {pairs}.\n"


def _size_line(sps: list | None, spec: dict, given: bool = False) -> str:
    if not sps:
        return "Size prior: flat (uniform in half-light radius).\n"
    parts = []
    for one in sps:
        x, p = np.asarray(one["ln_h"]), np.asarray(one.get("marginal", one["density"]))
        cdf = np.cumsum(p) / np.sum(p)
        q = np.exp(np.interp([0.05, 0.5, 0.95], cdf, x))
        sm = "" if one.get("smoothing") is None else f", smoothing {one['smoothing']:g}"
        parts.append(f"{one['psf']}: {q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} px "
                     f"(point sources {one['star']:.1e}{sm})")  # fmt: skip
    how = ""
    if len(sps) > 1:
        shared = all(o["density"] == sps[0]["density"] for o in sps)
        how = " (one for all PSFs)" if shared else " (one per PSF)"
    src = "given" if given else "estimated from the calibration sample"
    return (f"Size prior {src}{how}, half-light radius "
            f"5 / 50 / 95 %: {'; '.join(parts)}. The population: "
            f"{spec['size_ratio_range'][0]:g}-{spec['size_ratio_range'][1]:g} PSF half-light "
            "radii, log-uniform.\n")


def _stamp_line(stamps: dict | None) -> str:
    if not stamps:
        return ""
    tot = sum(stamps.values())
    parts = ", ".join(f"{k} px {100 * v / tot:.0f} %" for k, v in sorted(stamps.items()))
    return (f"Stamps (the +g rendering's; large galaxies on larger stamps, "
            f"Config.max_stamp_size): {parts}.")  # fmt: skip


def _amplitude_line(cfg: dict, flux: dict | None, spec: dict,
                    bounds: list | None = None) -> str:  # fmt: skip
    kind = cfg.get("amplitude_prior", "uniform")
    off, shape = spec.get("offset", 0.5), spec.get("offset_shape", "square")
    where = ("all centred" if off == 0 else f"uniform within ±{off:g} px along both axes"
             if shape == "square" else f"isotropic Gaussian, {off / math.sqrt(3):.3g} px per axis")
    pos = (f" Position prior: Gaussian, {cfg.get('position_prior_sigma', float('nan')):.3g} px"
           f" (the true centres: {where}).\n")  # fmt: skip
    if kind == "uniform":
        return "Amplitude prior: uniform (positive amplitudes)." + pos
    if kind == "snr" or not flux:
        return (f"Amplitude prior: {kind}, power {cfg.get('amplitude_prior_power'):.3f}."
                + pos)  # fmt: skip
    src = (f"estimated from the calibration sample's fluxes, ± {flux['error']:.3f}"
           if flux["estimated"] else "given")  # fmt: skip
    lo, hi = cfg.get("amplitude_prior_min", 0.0), cfg.get("amplitude_prior_max", math.inf)
    within = (f", within {lo:.4g}-{hi:.4g} in flux" if lo > 0 or hi < math.inf
              else ", unbounded")  # fmt: skip
    if bounds:
        parts = "; ".join(f"{b['psf']} {b['lo']:.4g} ± {b['lo_err']:.2g} to {b['hi']:.4g} ± "
                          f"{b['hi_err']:.2g} (the population's {b['true'][0]:.4g} to "
                          f"{b['true'][1]:.4g}; the errors' scale "
                          f"{b.get('error_scale', 1.0):.2f})" for b in bounds)  # fmt: skip
        within = (", within each PSF's flux range as estimated from the calibration "
                  f"sample's fluxes and their errors: {parts}")  # fmt: skip
    return (f"Amplitude prior: A^-β in the flux{within}, β = {flux['value']:.3f} ({src}; "
            f"the population's {spec['snr_slope']:g})." + pos)  # fmt: skip


def write_report(res: Table, path: str | Path) -> None:
    """Markdown report of :func:`precision`: tables, one PNG per breakdown, the ECSV table.

    Parameters
    ----------
    res : astropy.table.Table
        The result of :func:`precision`.
    path : str or pathlib.Path
        The Markdown file; ``<stem>_<breakdown>.png`` and ``<stem>.ecsv`` go beside it.
    """
    plt = pyplot_or_none(str(path))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    spec, tim = res.meta["spec"], res.meta["timing"]
    lines = [
        "# pylensfit precision run: paired ±g renderings with rotated twins", "",
        f"{spec['ngal']} galaxies × "
        + ("8 renderings (each of the four with its noise twin, the noise negated)"
           if spec.get("noise_twins") else "4 renderings")
        + f", g = ±({spec['g']}, {spec['g']}), "
        f"{len(spec['psfs'])} PSFs, flux of reference S/N {spec['snr_range'][0]:g}-"
        f"{spec['snr_range'][1]:g} (dN/dF ∝ F^-{spec['snr_slope']:g}; the S/N of a round "
        "exponential of the median size, independent of each galaxy's shape and size), "
        "size/PSF size "
        f"{spec['size_ratio_range'][0]:g}-{spec['size_ratio_range'][1]:g}, seed {spec['seed']}, "
        f"{spec.get('population', 'aligned')} population; model {res.meta['config']['model']} "
        f"({res.meta['config'].get('n_bulge_fractions', 1)} bulge fraction(s)"
        + (f", bulges of {res.meta['config']['bulge_size_ratio']:g} and "
           f"{res.meta['config']['bulge_size_ratio2']:g} disc scale lengths"
           if res.meta["config"].get("bulge_size_ratio2") else "")
        + (", with the Sersic ladder n = " + ", ".join(
            f"{v:g}" for v in sorted([1.0, *res.meta["config"]["sersic_ladder"]]))
           if res.meta["config"].get("sersic_ladder") else "") + "). "
        + _stamp_line(res.meta.get("stamps")), "",
        ("Prior given: " if res.meta["prior"].get("given") else
         f"Prior from {spec['ncal']} unsheared calibration galaxies"
         f"{' (stratified)' if spec.get('stratified_calibration') else ''}: ") +
        _prior_params_text(res.meta["prior"]) + f" (true {tuple(spec['prior_params'])}). "
        f"Largest fixed-point Newton step {res.meta['fp_step']:.1e}.", "",
        _bulge_line(res.meta.get("bulge_prior")),
        _size_line(res.meta.get("size_prior"), spec, res.meta.get("size_prior_given", False)),
        _amplitude_line(res.meta.get("config", {}), res.meta.get("flux_slope"), spec,
                        res.meta.get("flux_bounds")),
        f"Time {tim['total_s']:.0f} s with {tim['jobs']} job(s): {tim['galaxies_per_s']:.0f} "
        f"galaxies/s ({tim['renderings_per_s']:.0f} renderings/s) in the main pass; CPU "
        f"{tim['render_cpu_s']:.0f} s rendering, {tim['fit_cpu_s']:.0f} s fitting.", "",
        "Errors are delete-one-group jackknife over groups of 100 galaxies (1 sigma), "
        "with the priors held fixed: the calibration sample's own noise is not in them "
        "(with 20,000 calibration galaxies drawn stratified in morphology, flux and size, "
        "(m1 + m2) / 2 on the mean of PSFs scattered by 0.0010 between four independent "
        "200,000-galaxy samples where the jackknife gives 0.0004: a noise of about 0.0009 "
        "common to both components, whose variance 80,000, the default, take to a "
        "quarter; benchmarks/README.md, \"What the studies found\"). m and c "
        "are corrected with "
        "control variates, the spin-4 parts of the intrinsic ellipticity (e1² - e2², "
        "2 e1 e2), whose population mean is zero: they remove the shape noise that the "
        "rotated twins leave, not the bias (column cv; groups of galaxies split into fewer "
        "than 20 jackknife groups are not corrected). The breakdown `no controls` gives "
        "the plain estimate.", "",
        "The breakdowns by true S/N, size and morphology are conditional on the truth: "
        "a Bayesian estimator with a size prior is biased in opposite directions at the "
        "two ends of the population (it pulls every galaxy towards the prior's typical "
        "size) while the whole population is not; likewise, with the bulge fraction "
        "marginalised, a faint galaxy's posterior mixes the fractions as the prior "
        "weighs them, so that at S/N 10-200 exponentials come out at m ~ +0.04 and de "
        "Vaucouleurs galaxies at -0.04 while the mix is unbiased (at S/N 100-200, or in "
        "a population of exponentials alone, each is within about 0.01; validate --precision "
        "--snr-range 100 200, --morphologies 1 0 0 0 0). The breakdown `bulge_frac_meas` "
        "bins on an observed quantity instead, each galaxy's posterior mean bulge "
        "fraction (averaged over its renderings): a Bayesian estimator whose model and "
        "priors hold is unbiased conditional on the data, not on the truth. "
        "Judge m on `all` and per PSF. "
        "The group `mean of "
        "PSFs` averages the PSFs' m and c; its error leaves out the jackknife's noise "
        "from the PSFs' shares of the sample, which the design fixes.", "",
    ]  # fmt: skip
    for bd in dict.fromkeys(res["breakdown"]):
        t = res[res["breakdown"] == bd]
        lines += [f"## {bd}", "",
                  "| group | estimator | m1 | m2 | c1 | c2 | galaxies | cv |",
                  "|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for r in t:
            cv = "yes" if r["controlled"] else "no"
            lines.append(
                f"| {r['group']} | {r['estimator']} | {_fmt(r['m1'], r['m1_err'])} | "
                f"{_fmt(r['m2'], r['m2_err'])} | {_fmt(r['c1'], r['c1_err'], 5)} | "
                f"{_fmt(r['c2'], r['c2_err'], 5)} | {r['n_gal']} | {cv} |"
            )
        if plt is not None and bd not in ("all", "selection", "no controls",
                                          "no noise twins"):
            png = path.with_name(f"{path.stem}_{bd}.png")
            labels = list(dict.fromkeys(t["group"]))
            fig, axes = plt.subplots(1, 2, figsize=(max(10.0, 0.45 * len(labels)), 3.6),
                                     sharey=True)  # fmt: skip
            x = np.arange(len(labels))
            for i, ax in zip((1, 2), axes, strict=True):
                for j, est in enumerate(_ESTIMATORS):
                    s = t[t["estimator"] == est]
                    ax.errorbar(x + (j - 1) * 0.12, s[f"m{i}"], yerr=s[f"m{i}_err"], fmt="o",
                                ms=3, label=est)  # fmt: skip
                ax.axhspan(-1e-3, 1e-3, color="0.85")
                ax.axhline(0, color="k", lw=0.5)
                ax.set_xticks(x, labels, rotation=30, fontsize=7)
                ax.set_title(f"m{i} by {bd}")
            axes[0].set_ylabel("m")
            axes[1].legend(fontsize=7)
            fig.tight_layout()
            fig.savefig(png, dpi=100)
            plt.close(fig)
            lines += ["", f"![m by {bd}]({png.name})"]
        lines.append("")
    path.write_text("\n".join(lines))
    tab = res.copy(copy_data=True)
    tab.meta = {k: v for k, v in res.meta.items() if k not in ("galaxies",)}
    tab.write(path.with_suffix(".ecsv"), overwrite=True)


def spec_with(spec: PrecisionSpec | None = None, **kw) -> PrecisionSpec:
    """``spec`` (default :class:`PrecisionSpec`) with fields replaced (``psfs`` by names)."""
    spec = spec if spec is not None else PrecisionSpec()
    if "psfs" in kw and kw["psfs"] is not None:
        names = {p["name"]: p for p in PRECISION_PSFS}
        chosen = []
        for p in kw["psfs"]:
            if isinstance(p, dict):
                chosen.append(p)
            elif str(p) in names:
                chosen.append(names[str(p)])
            elif str(p).isdigit() and int(p) < len(PRECISION_PSFS):
                chosen.append(PRECISION_PSFS[int(p)])
            else:
                raise ValueError(f"unknown PSF {p!r}: choose from {', '.join(names)}")
        kw["psfs"] = tuple(chosen)
    return replace(spec, **{k: v for k, v in kw.items() if v is not None})
