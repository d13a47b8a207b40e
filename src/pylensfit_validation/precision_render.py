"""The precision mode's population and renderings: :class:`PrecisionSpec`, the PSFs and
galaxy kinds, and each block of galaxies rendered with GalSim at ``+-g`` (with their
90-degree twins and noise twins) as :mod:`pylensfit_validation.precision` describes."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from astropy.table import Table

from pylensfit.prior import Prior, SizePrior

from .galaxies import GalaxyProfile, PSFProfile, draw_bulge_shapes, draw_sersic_indices
from .simulate import POPULATIONS, draw_shapes

__all__ = [
    "ESTIMATORS",
    "MORPHOLOGIES",
    "N_QUANTITIES",
    "PRECISION_PSFS",
    "PrecisionSpec",
    "QUANTITIES",
    "block_count",
    "draw_image",
    "flux_and_noise",
    "galsim_psf",
    "population_flux_range",
    "population_prior",
    "population_size_prior",
    "population_table",
    "profile_of",
    "psf_image",
    "reference_norm",
    "render_block",
    "shear_sets",
]

PRECISION_PSFS: tuple[dict, ...] = (
    {"name": "round", "kind": "moffat", "fwhm": 3.0, "beta": 3.5, "e1": 0.0, "e2": 0.0},
    {"name": "e=0.10", "kind": "moffat", "fwhm": 3.0, "beta": 3.5, "e1": 0.10, "e2": 0.0},
    {"name": "kolmogorov", "kind": "kolmogorov", "fwhm": 4.0, "e1": 0.0, "e2": 0.03},
    {"name": "asymmetric", "kind": "asymmetric", "fwhm": 3.0, "beta": 3.5, "e1": 0.02,
     "e2": -0.02, "lobe_flux": 0.2, "lobe_shift": 1.0},
)  # fmt: skip

#: Galaxy morphologies of the precision population (codes are the indices).
MORPHOLOGIES: tuple[str, ...] = ("exponential", "devaucouleurs", "bulge+disc", "sersic", "knots")

ESTIMATORS = ("fixed-point", "exact", "paper")
# per-rendering quantities kept by the workers
QUANTITIES = ("e1", "e2", "sx1", "sx2", "sp1", "sp2", "fe1", "fe2", "J11", "J12", "J21", "J22")
N_QUANTITIES = len(QUANTITIES)


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
        each block (:func:`population_table`): the morphologies in proportion, and a Latin
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
def galsim_psf(p: dict):
    """The GalSim profile of a PSF of :data:`PRECISION_PSFS` (no pixel response)."""
    return PSFProfile.from_dict(p).galsim()


def draw_image(obj, n: int, offset=(0.0, 0.0)) -> np.ndarray:
    """``obj`` with the pixel response on ``n x n``, its centre at element ``[n//2, n//2]``."""
    half = 0.5 if n % 2 == 0 else 0.0
    return obj.drawImage(nx=n, ny=n, scale=1.0, offset=(offset[0] + half, offset[1] + half)).array


def psf_image(p: dict, n: int) -> tuple[np.ndarray, float]:
    """The PSF image on the stamp grid and its half-light radius (pixels)."""
    import galsim  # galsim: heavy import, only for rendering

    psf = galsim_psf(p)
    img = draw_image(psf, n)
    hlr = galsim.Image(draw_image(psf, 4 * n), scale=1.0).calculateHLR()
    return img / img.sum(), float(hlr)


def profile_of(row) -> Any:
    """The unit-flux galaxy of one row of :func:`population_table` (pixels).

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
    _, psf_hlr = psf_image(spec.psfs[psf_index], int(stamp_size))
    lo, hi = np.log(np.asarray(spec.size_ratio_range, dtype=float) * psf_hlr)
    eps = 1e-4 * (hi - lo)
    knots = np.concatenate([[lo - eps], np.linspace(lo, hi, 50), [hi + eps]])
    dens = np.concatenate([[0.0], np.full(50, 1.0 / (hi - lo)), [0.0]])
    return SizePrior(ln_h=knots, density=dens * (1 - 1e-6), star=1e-6)


def _stratified(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` uniform deviates on [0, 1), one in each of ``n`` equal strata, shuffled."""
    return (rng.permutation(n) + rng.random(n)) / max(n, 1)


def population_table(spec: PrecisionSpec, n: int, psf_hlr: float, rng: np.random.Generator,
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
        The galaxies' parameters (:func:`population_table`).
    """
    import galsim  # galsim: heavy import, only for rendering

    p = spec.psfs[psf_index]
    n_stamp = int(stamp_size)
    psf_img, psf_hlr = psf_image(p, n_stamp)
    nblocks = block_count(spec.ncal if calibration else spec.ngal, spec.block_size)
    ntot = spec.ncal if calibration else spec.ngal
    n = min(spec.block_size, ntot - block * spec.block_size)
    if n <= 0 or block >= nblocks:
        raise ValueError(f"block {block} is outside the set ({nblocks} blocks)")
    rng = np.random.default_rng([spec.seed, int(calibration), block])
    t = population_table(spec, n, psf_hlr, rng,
                         stratified=calibration and spec.stratified_calibration)
    psf = galsim_psf(p)
    if calibration:
        shears = [(0.0, False)]
    else:
        shears = [(+spec.g, False), (+spec.g, True), (-spec.g, False), (-spec.g, True)]
    out = np.empty((n, len(shears), n_stamp, n_stamp), dtype=np.float32)
    for a in range(n):  # GalSim renders one profile at a time
        gal = profile_of(t[a])
        gal = gal.shear(g1=float(t["e1_int"][a]), g2=float(t["e2_int"][a]))
        off = (float(t["dx"][a]), float(t["dy"][a]))
        for k, (g, rot) in enumerate(shears):
            obj = gal.rotate(90 * galsim.degrees) if rot else gal
            out[a, k] = draw_image(galsim.Convolve(obj.shear(g1=g, g2=g), psf), n_stamp, off)
    if spec.noise_twins and not calibration:  # the same objects; their noise negated below
        out = np.concatenate([out, out], axis=1)
    flux_and_noise(out, t, spec, block, reference_norm(spec, psf_index, n_stamp),
                    calibration=calibration, noise=noise)  # fmt: skip
    return out, psf_img, t


def reference_norm(spec: PrecisionSpec, psf_index: int, stamp_size: int = 32) -> float:
    """``sqrt(sum I^2)`` of a unit-flux round exponential of the population's median size
    (``sqrt`` of the product of ``spec.size_ratio_range`` times the PSF's half-light
    radius) under PSF ``psf_index``: a flux ``F`` has the reference S/N ``F *
    reference_norm / noise_sigma`` (see :class:`PrecisionSpec`, ``snr_range``)."""
    import galsim  # galsim: heavy import, only for rendering

    p = spec.psfs[psf_index]
    _, psf_hlr = psf_image(p, int(stamp_size))
    r_ref = math.sqrt(spec.size_ratio_range[0] * spec.size_ratio_range[1]) * psf_hlr
    gal = GalaxyProfile("exponential", r_ref).galsim()
    img = draw_image(galsim.Convolve(gal, galsim_psf(p)), int(stamp_size))
    return math.sqrt(float(np.sum(img.astype(float) ** 2)))


def population_flux_range(spec: PrecisionSpec, psf_index: int = 0, *,
                          stamp_size: int = 32) -> tuple[float, float]:  # fmt: skip
    """The population's flux limits under PSF ``psf_index`` (``spec.snr_range`` in flux
    units, :func:`reference_norm`): a diagnostic, the bounds of a flux prior that knows
    the population."""
    f = spec.noise_sigma / reference_norm(spec, psf_index, stamp_size)
    return spec.snr_range[0] * f, spec.snr_range[1] * f


def flux_and_noise(out: np.ndarray, t: Table, spec: PrecisionSpec, block: int, ref: float,
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


def shear_sets(n_renderings: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The renderings at ``+g`` and at ``-g``, for four renderings per galaxy or eight
    (with noise twins): ``k % 4 < 2`` is ``+g``."""
    if n_renderings not in (4, 8):
        raise ValueError(f"a galaxy has 4 or 8 renderings (with noise twins), got "
                         f"{n_renderings}")  # fmt: skip
    ks = range(n_renderings)
    return tuple(k for k in ks if k % 4 < 2), tuple(k for k in ks if k % 4 >= 2)


def block_count(n: int, size: int) -> int:
    """The number of blocks of ``size`` galaxies that hold ``n`` galaxies."""
    return -(-int(n) // int(size))
