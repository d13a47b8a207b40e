"""Paired +-g shear bias of pylensfit and HSM REGAUSS on an independently rendered population.

A check of the shear bias on galaxies that none of pylensfit's own simulation code drew:
this script renders its population with GalSim directly (it imports nothing of
``pylensfit_validation.precision``, ``pylensfit_validation.simulate``,
``pylensfit_validation.validation`` or ``pylensfit_validation.convergence``), measures
every rendering with pylensfit's public stamps API and with GalSim's HSM REGAUSS, and
prints the multiplicative and additive biases ``m``
and ``c`` of both, per PSF and averaged over the PSFs.

The design is that of the metacalibration-style paired simulations (four renderings per
galaxy, +-g and a 90-degree rotation, the +g and -g renderings sharing their noise
field): ``m`` is a difference of the +g and -g estimates of the *same* galaxies under the
*same* noise, so both the intrinsic shapes and the noise cancel in it to first order,
and what is left is the bias, not the noise.

The recipe
----------
Population (drawn with ``numpy.random.default_rng(seed)``; the calibration sample with
``default_rng([seed, 1])``), per galaxy:

* kind, in fixed proportions 40/30/30 (shuffled):

  (a) a single Sersic profile, ``n`` uniform in [0.5, 4.5], truncated at 8 half-light
      radii for ``n >= 2`` (``galsim.Sersic(trunc=8 hlr)``, the half-light radius that of
      the truncated profile; below ``n = 2`` untruncated, the wings beyond 8 hlr being
      negligible and GalSim's solver for the truncated radius failing near n ~ 0.6);
  (b) an exponential disc with 10-40% of its flux in ``galsim.RandomKnots`` (20-50
      knots of the disc's half-light radius), disc and knots sheared together by the
      intrinsic ellipticity;
  (c) a bulge + disc: an exponential disc and a de Vaucouleurs bulge (truncated at 8 of
      its half-light radii) of half the disc's half-light radius, bulge fraction
      uniform in [0.1, 0.6], the bulge ROUNDER than the disc (``|e_bulge| = (0.3-0.6)
      |e_disc|``) at the same position angle;

* intrinsic ellipticity (reduced-shear convention ``|e| = (a - b) / (a + b)``, GalSim's
  ``shear(g1, g2)``): ``|e|`` Rayleigh with ``sigma_e = 0.25`` per component, truncated
  at 0.8, position angle uniform;
* half-light radius (the disc's for kind c) lognormal about the PSF's FWHM / 2,
  ``hlr = FWHM / 2 * exp(N(0, 0.35))`` (95% within 0.5-2 times), clipped to 0.35-3;
* S/N from ``dN/dS ~ S^-2`` on [10, 100], the matched-filter S/N
  ``sqrt(sum(img^2)) / sigma`` of the noiseless unsheared image; the flux is the one that
  gives that S/N at the fixed noise ``sigma = 1``;
* a sub-pixel centre offset uniform in +-0.5 pixel in x and y, the same for all the
  galaxy's renderings;
* a PSF: galaxies come in blocks of ``--block`` (25) and the blocks cycle through

  ===  ======================================================
  P0   round Moffat, beta = 3.5, FWHM 3 px
  P1   Moffat, beta = 3.5, FWHM 3 px, e = (0.05, -0.03)
  P2   Kolmogorov, FWHM 4 px, e = (0.0, 0.08) (the large one)
  P3   Moffat, beta = 2.5, FWHM 3.4 px, e = (0.08, 0.06) (|e| = 0.1)
  ===  ======================================================

Renderings: each galaxy ``i`` of the main sample is drawn four times,

  ===  =====================  ================================================
  k    shear ``(g1, g2)``     intrinsic shape
  ===  =====================  ================================================
  0    ``(+g, +g)``           as drawn
  1    ``(+g, +g)``           rotated by 90 degrees
  2    ``(-g, -g)``           as drawn
  3    ``(-g, -g)``           rotated by 90 degrees
  ===  =====================  ================================================

(``--g``, default 0.02), each with Gaussian noise of ``sigma = 1`` whose seed depends on
the galaxy and the rotation but not on the sign of the shear,
``SeedSequence([seed, sample, i, rotated])``: the noise field of k = 2 is that of k = 0,
the noise field of k = 3 that of k = 1, and the two rotations have independent noise.
``--independent-noise`` gives every rendering its own noise instead (seed
``SeedSequence([seed, sample, i, k])``; k = 0, 1 are then the same images as in the
shared design), where only the intrinsic shapes cancel. Stamps are
64 x 64 float32 ``[k, y, x]``, drawn with ``method="auto"`` (the pixel response
included), the galaxy at pixel ``[32, 32]`` plus its offset; the PSF image given to both
methods is drawn the same way, centred on ``[32, 32]`` of a 64 x 64 image. A separate
unsheared calibration sample of ``--ncal`` galaxies (default ``min(ngal, 20000)``) of the
same population (one rendering each, same PSF blocks) gives pylensfit its priors.

Measurement, one PSF at a time; the calibration sample's stamps of the PSF are rendered
and used once, then the main sample's galaxies of the PSF are rendered, measured by both
methods and dropped ``--chunk`` galaxies (``4 x --chunk`` stamps) at a time, keeping of
each rendering only ``e1, e2, sens1, sens2`` and a usable flag of pylensfit (and, for
``--estimator plf``, its ln L grid), and REGAUSS's two distortions and usable flag:

* pylensfit, ``--method api`` (default), per PSF::

      priors = plf.calibrate(cal_stamps, psf_image, noise_sigma=1.0)     # once
      tab = plf.measure_stamps(chunk_stamps, psf_image, noise_sigma=1.0,
                               priors=priors)                            # per chunk

  usable rows ``flags == 0`` and ``weight > 0``. ``--method lower`` uses the lower
  layer instead: ``fit_stamps`` (``Config(model="bulge+disc", n_bulge_fractions=3,
  max_stamp_size=64)``) on the calibration sample, ``estimate_prior`` from its usable
  rows (once per PSF), ``fit_stamps`` + ``shapes`` on each chunk; usable rows have no
  flag from either and are not point sources.
* REGAUSS: ``galsim.hsm.EstimateShear(gal, psf, shear_est="REGAUSS", sky_var=sigma^2,
  strict=False)``, the distortions ``corrected_e1, corrected_e2``; a rendering is
  unusable if HSM reports an error (``error_message``) or ``correction_status != 0``,
  and, with ``--hsm-cuts standard`` (default), if the resolution factor is below 0.3 or
  ``|e| >= 2`` (the usual cuts; noise outliers with ``|e| >> 1`` at S/N ~ 10 otherwise
  dominate the means; ``--hsm-cuts none``: failures only).

Shear: a galaxy counts only if all four of its renderings are usable (paired selection).
Per PSF and sign, pylensfit's ``g_i(+-) = sum e_i / sum sens_i`` over the two renderings
sheared by ``+-g`` of the selected galaxies (``--estimator plf``, api only:
``plf.estimate_shear``, the fixed point, on the ln L grids of those renderings
instead); REGAUSS's ``g_i(+-) = <e_i> / (2 R)`` with ``R = 1 - e_rms^2``, ``e_rms^2`` the
per-component mean square of the selected distortions of that PSF (all four renderings,
noise included). Then

    m_i = (g_i(+) - g_i(-)) / (2 g) - 1,    c_i = (g_i(+) + g_i(-)) / 2,

with jackknife errors over ``--groups`` (50) groups of galaxies (a galaxy's four
renderings always in the same group, so that the errors see the pairing). Because both
components are sheared together, ``m_1`` includes the (small) response of ``e_1`` to
``g_2`` and vice versa. REGAUSS's ``R`` is the same for +g and -g and does not cancel:
its own sampling error, ``~0.15 / sqrt(4 n)`` relative, stays in its ``m``.

Timing: rendering runs in ``--jobs`` spawned processes and is not timed against the
methods; REGAUSS runs in ``--jobs`` other spawned processes (one thread each), pylensfit
in this process with numba's threads, one after the other on each chunk; both
wall-clock, printed as stamps (renderings) per second, pylensfit with and without its
calibration. The pools' start-up and numba's compilation (a warm-up fit of four stamps)
are not timed. Peak memory is ``ru_maxrss`` of this process and of the largest REGAUSS
worker. This process holds at once one PSF's calibration stamps (``ncal / 4 x 16 KiB``),
one chunk's stamps (``4 x chunk x 16 KiB``) and pylensfit's working arrays for them,
and, for all of the main sample, the population's parameters (~110 B per galaxy) and the
kept columns (~200 B per galaxy; with ``--estimator plf`` also 4 ln L grids of 316
float32, ~5 KiB per galaxy), so that its peak grows with ``--ngal`` only through those.

Usage::

    python benchmarks/unseen_paired.py --ngal 800 --ncal 800 --jobs 2 --seed 3
    python benchmarks/unseen_paired.py --ngal 400 --ncal 400 --method lower --jobs 2
    python benchmarks/unseen_paired.py --ngal 240000 --jobs 2 --seed 5 \
        --out /tmp/unseen_240k.ecsv

``--ngal`` and ``--ncal`` are totals over the four PSFs (a quarter each). With the shared
noise the error of pylensfit's ``m`` per PSF and component is ~0.015 with 800 galaxies
(200 per PSF) and ~0.008 with 4000 (~0.004 on the mean over PSFs), against ~0.25 with
800 under ``--independent-noise``; what is left is the scatter between each galaxy's
actual response to the shear and its sensitivity ``sens`` (~0.24 per galaxy), so
``sigma(m) ~ 0.24 / sqrt(ngal / 4)`` per PSF: 1e-3 per PSF takes ``--ngal 240000`` (the
last command; 2 cores: ~35 ms per galaxy in all, ~2-2.5 h), 1e-3 on the mean over the
PSFs ``--ngal 60000`` (~40 min). REGAUSS's errors are about twice pylensfit's. The
additive ``c`` does not cancel in the pairs: with the +-g noise shared its error is ~1.4
times that with independent noise (2 noise fields per galaxy instead of 4).
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import resource
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np
import yaml

#: stamp side (pixels) and the galaxy's pixel ``[CENTRE, CENTRE]``
STAMP = 64
CENTRE = STAMP // 2
#: per-pixel noise standard deviation; the flux sets the S/N
SIGMA = 1.0
#: kinds of galaxy and their fixed proportions (per 10 galaxies)
KINDS = ("sersic", "knotty", "bulge+disc")
KIND_PATTERN = (0, 0, 0, 0, 1, 1, 1, 2, 2, 2)
#: S/N range of the ``dN/dS ~ S^-2`` power law
SNR_RANGE = (10.0, 100.0)
#: intrinsic ellipticity: Rayleigh sigma per component, truncation
SIGMA_E = 0.25
E_MAX = 0.8
#: lognormal width of the half-light radius about the PSF's FWHM / 2, and its clip
LN_SIZE_SIGMA = 0.35
SIZE_CLIP = (0.35, 3.0)
#: Sersic and de Vaucouleurs truncation, in half-light radii, for Sersic n >= TRUNC_MIN_N
TRUNC_HLR = 8.0
TRUNC_MIN_N = 2.0

#: the PSFs: (name, kind, FWHM px, beta (Moffat), e1, e2)
PSFS = (
    ("P0 round Moffat", "moffat", 3.0, 3.5, 0.0, 0.0),
    ("P1 Moffat e=(.05,-.03)", "moffat", 3.0, 3.5, 0.05, -0.03),
    ("P2 Kolmogorov 4px", "kolmogorov", 4.0, None, 0.0, 0.08),
    ("P3 Moffat e=(.08,.06)", "moffat", 3.4, 2.5, 0.08, 0.06),
)
#: the renderings of a main-sample galaxy: (rotated by 90 degrees, sign of the shear)
RENDERINGS = ((False, +1), (True, +1), (False, -1), (True, -1))


# ----------------------------------------------------------------------------------------
# The population
# ----------------------------------------------------------------------------------------
@dataclass
class Population:
    """Parameters of every galaxy of one sample (one entry per galaxy).

    Attributes
    ----------
    psf : numpy.ndarray
        Index into :data:`PSFS`.
    kind : numpy.ndarray
        Index into :data:`KINDS`.
    n_sersic : numpy.ndarray
        Sersic index (kind a).
    hlr : numpy.ndarray
        Half-light radius in pixels (the disc's for kind c).
    e1, e2 : numpy.ndarray
        Intrinsic ellipticity (reduced-shear convention; the disc's for kinds b, c).
    knot_frac, knot_n, knot_seed : numpy.ndarray
        Kind b: flux fraction in knots, number of knots, the knots' GalSim seed.
    bulge_frac, bulge_e_ratio : numpy.ndarray
        Kind c: bulge-to-total flux ratio, ``|e_bulge| / |e_disc|``.
    snr : numpy.ndarray
        Target matched-filter S/N.
    dx, dy : numpy.ndarray
        Sub-pixel centre offset (pixels).
    """

    psf: np.ndarray
    kind: np.ndarray
    n_sersic: np.ndarray
    hlr: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    knot_frac: np.ndarray
    knot_n: np.ndarray
    knot_seed: np.ndarray
    bulge_frac: np.ndarray
    bulge_e_ratio: np.ndarray
    snr: np.ndarray
    dx: np.ndarray
    dy: np.ndarray

    def __len__(self) -> int:
        return len(self.psf)

    def row(self, i: int) -> dict:
        """The parameters of galaxy ``i`` as a dict of Python scalars."""
        return {k: getattr(self, k)[i].item() for k in self.__dataclass_fields__}

    def take(self, idx: np.ndarray) -> Population:
        """The sub-population of the galaxies ``idx``."""
        return Population(**{k: getattr(self, k)[idx] for k in self.__dataclass_fields__})


def draw_population(n: int, rng: np.random.Generator, block: int) -> Population:
    """Draw the parameters of ``n`` galaxies of the population (module docstring).

    Parameters
    ----------
    n : int
        Number of galaxies.
    rng : numpy.random.Generator
        The sample's generator.
    block : int
        Galaxies per PSF block; block ``b`` gets PSF ``b % len(PSFS)``.

    Returns
    -------
    Population
    """
    psf = (np.arange(n) // block) % len(PSFS)
    kind = rng.permutation(np.resize(np.array(KIND_PATTERN), n))
    # |e|: Rayleigh(sigma_e) truncated at E_MAX (redrawn above it); random angle
    emod = rng.rayleigh(SIGMA_E, n)
    while np.any(bad := emod >= E_MAX):
        emod[bad] = rng.rayleigh(SIGMA_E, int(bad.sum()))
    phi = rng.uniform(0.0, np.pi, n)
    fwhm = np.array([p[2] for p in PSFS])[psf]
    hlr = fwhm / 2 * np.clip(np.exp(rng.normal(0.0, LN_SIZE_SIGMA, n)), *SIZE_CLIP)
    lo, hi = SNR_RANGE
    snr = 1.0 / (1.0 / lo - rng.uniform(0.0, 1.0, n) * (1.0 / lo - 1.0 / hi))
    return Population(
        psf=psf,
        kind=kind,
        n_sersic=rng.uniform(0.5, 4.5, n),
        hlr=hlr,
        e1=emod * np.cos(2 * phi),
        e2=emod * np.sin(2 * phi),
        knot_frac=rng.uniform(0.1, 0.4, n),
        knot_n=rng.integers(20, 51, n),
        knot_seed=rng.integers(1, 2**31 - 1, n),
        bulge_frac=rng.uniform(0.1, 0.6, n),
        bulge_e_ratio=rng.uniform(0.3, 0.6, n),
        snr=snr,
        dx=rng.uniform(-0.5, 0.5, n),
        dy=rng.uniform(-0.5, 0.5, n),
    )


# ----------------------------------------------------------------------------------------
# Rendering (GalSim; runs in the worker processes)
# ----------------------------------------------------------------------------------------
def make_psf(i: int):
    """The GalSim profile of PSF ``i`` of :data:`PSFS`."""
    import galsim

    _, kind, fwhm, beta, e1, e2 = PSFS[i]
    p = galsim.Moffat(beta=beta, fwhm=fwhm) if kind == "moffat" else galsim.Kolmogorov(fwhm=fwhm)
    return p.shear(g1=e1, g2=e2) if (e1 or e2) else p


def psf_image(i: int) -> np.ndarray:
    """PSF ``i`` drawn with the pixel (``method="auto"``), centred on ``[32, 32]``, 64 x 64.

    Parameters
    ----------
    i : int
        Index into :data:`PSFS`.

    Returns
    -------
    numpy.ndarray
        ``(64, 64)`` float32 image of unit sum.
    """
    im = make_psf(i).drawImage(nx=STAMP, ny=STAMP, scale=1.0, method="auto",
                               use_true_center=False)  # fmt: skip
    a = im.array.astype(np.float32)
    return a / a.sum()


def make_galaxy(p: dict):
    """The unit-flux intrinsic GalSim profile of a galaxy of parameters ``p``.

    Parameters
    ----------
    p : dict
        One row of a :class:`Population` (:meth:`Population.row`).

    Returns
    -------
    galsim.GSObject
    """
    import galsim

    kind, hlr = KINDS[p["kind"]], p["hlr"]
    if kind == "sersic":
        n = p["n_sersic"]
        trunc = TRUNC_HLR * hlr if n >= TRUNC_MIN_N else 0.0
        gal = galsim.Sersic(n=n, half_light_radius=hlr, trunc=trunc)
        return gal.shear(g1=p["e1"], g2=p["e2"])
    if kind == "knotty":
        fk = p["knot_frac"]
        disc = galsim.Exponential(half_light_radius=hlr, flux=1.0 - fk)
        knots = galsim.RandomKnots(int(p["knot_n"]), half_light_radius=hlr, flux=fk,
                                   rng=galsim.BaseDeviate(int(p["knot_seed"])))  # fmt: skip
        return galsim.Add(disc, knots).shear(g1=p["e1"], g2=p["e2"])
    fb, r = p["bulge_frac"], p["bulge_e_ratio"]
    disc = galsim.Exponential(half_light_radius=hlr, flux=1.0 - fb)
    disc = disc.shear(g1=p["e1"], g2=p["e2"])
    hb = 0.5 * hlr
    bulge = galsim.DeVaucouleurs(half_light_radius=hb, trunc=TRUNC_HLR * hb, flux=fb)
    bulge = bulge.shear(g1=r * p["e1"], g2=r * p["e2"])  # rounder, same position angle
    return galsim.Add(disc, bulge)


def _draw(gal, psf, p: dict) -> np.ndarray:
    import galsim

    im = galsim.Convolve(gal, psf).drawImage(
        nx=STAMP, ny=STAMP, scale=1.0, method="auto", use_true_center=False,
        offset=(p["dx"], p["dy"]),
    )  # fmt: skip
    return im.array.astype(np.float64)


def noise_key(r: int, shared: bool) -> int:
    """The last entry of rendering ``r``'s noise seed (module docstring).

    Parameters
    ----------
    r : int
        Index into :data:`RENDERINGS`.
    shared : bool
        ``True`` (the paired design): the key is the rotation (0 or 1), so that the +g
        and -g renderings of one rotation get the same noise field; ``False``
        (``--independent-noise``): the key is ``r``, one field per rendering.

    Returns
    -------
    int
    """
    return int(RENDERINGS[r][0]) if shared else r


def render_chunk(args) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render a chunk of galaxies of one PSF (a worker's task).

    Parameters
    ----------
    args : tuple
        ``(pop, idx, psf_index, g, seed, sample, shared)``: the chunk's
        :class:`Population`, the galaxies' indices in their sample (for the noise seeds),
        the PSF, the shear (``None``: the unsheared calibration sample, one rendering per
        galaxy), the run's seed, the sample's number (0 main, 1 calibration) and whether
        the +g and -g renderings share their noise (:func:`noise_key`).

    Returns
    -------
    stamps : numpy.ndarray
        ``(n, 4, 64, 64)`` (main) or ``(n, 64, 64)`` (calibration) float32, noise added.
    flux : numpy.ndarray
        ``(n,)`` the flux that gives each galaxy its S/N.
    idx : numpy.ndarray
        The galaxies' indices, as given.
    """
    import galsim

    pop, idx, ipsf, g, seed, sample, shared = args
    psf = make_psf(ipsf)
    n_r = 1 if g is None else len(RENDERINGS)
    out = np.empty((len(pop), n_r, STAMP, STAMP), dtype=np.float32)
    flux = np.empty(len(pop))
    for j in range(len(pop)):
        p = pop.row(j)
        gal = make_galaxy(p)
        unit = _draw(gal, psf, p)
        flux[j] = p["snr"] * SIGMA / math.sqrt(float(np.sum(unit**2)))
        gal = gal.withFlux(flux[j])
        noise = {}
        for r in range(n_r):
            if g is None:
                img = unit * flux[j]
            else:
                rot, sign = RENDERINGS[r]
                gr = gal.rotate(90 * galsim.degrees) if rot else gal
                img = _draw(gr.shear(g1=sign * g, g2=sign * g), psf, p)
            key = noise_key(r, shared)
            if key not in noise:
                ss = np.random.SeedSequence([seed, sample, int(idx[j]), key])
                noise[key] = np.random.default_rng(ss).normal(0.0, SIGMA, img.shape)
            out[j, r] = img + noise[key]
    return (out[:, 0] if g is None else out), flux, idx


def render(pop: Population, idx: np.ndarray, g: float | None, seed: int, sample: int,
           pool: ProcessPoolExecutor, task: int, shared: bool = True) -> np.ndarray:  # fmt: skip
    """Render galaxies ``idx`` of a sample (all of one PSF) in the worker pool.

    Parameters
    ----------
    pop : Population
        The whole sample.
    idx : numpy.ndarray
        The galaxies to render, all of one PSF.
    g : float or None
        Shear of the paired design, or ``None`` for the unsheared calibration sample.
    seed, sample : int
        The run's seed and the sample's number (noise seeds).
    pool : concurrent.futures.ProcessPoolExecutor
        The rendering workers (:func:`_pool`).
    task : int
        Galaxies per worker task.
    shared : bool
        Shared +-g noise (:func:`noise_key`).

    Returns
    -------
    numpy.ndarray
        ``(len(idx), 4, 64, 64)`` or ``(len(idx), 64, 64)`` float32, in the order of
        ``idx``.
    """
    n = len(idx)
    if n == 0:
        shape = (0, STAMP, STAMP) if g is None else (0, len(RENDERINGS), STAMP, STAMP)
        return np.empty(shape, dtype=np.float32)
    ipsf = int(pop.psf[idx[0]])
    if np.any(pop.psf[idx] != ipsf):
        raise ValueError("render: the galaxies must all be of one PSF")
    shape = (n, STAMP, STAMP) if g is None else (n, len(RENDERINGS), STAMP, STAMP)
    stamps = np.empty(shape, dtype=np.float32)
    starts = list(range(0, n, task))
    tasks = [(pop.take(idx[k:k + task]), idx[k:k + task], ipsf, g, seed, sample, shared)
             for k in starts]  # fmt: skip
    for k, (s, _, _) in zip(starts, pool.map(render_chunk, tasks), strict=True):
        stamps[k:k + len(s)] = s
    return stamps


def _pool(jobs: int) -> ProcessPoolExecutor:
    # spawn, never fork: numba's OpenMP layer does not survive a fork
    return ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn"))


def _start(pool: ProcessPoolExecutor, jobs: int) -> None:
    """Start the pool's workers and import GalSim in each (not timed)."""
    list(pool.map(_warm_worker, [0.5] * jobs))


def _warm_worker(pause: float) -> None:
    import galsim  # noqa: F401

    time.sleep(pause)  # hold this worker so that the others get a warm-up task too


# ----------------------------------------------------------------------------------------
# REGAUSS (runs in the worker processes)
# ----------------------------------------------------------------------------------------
def regauss_chunk(args) -> tuple[np.ndarray, np.ndarray, float]:
    """REGAUSS distortions of a chunk of stamps of one PSF (a worker's task).

    Parameters
    ----------
    args : tuple
        ``(stamps, psf_index, cuts)``: ``(n, 64, 64)`` stamps, the PSF, ``"standard"``
        or ``"none"`` (see the module docstring).

    Returns
    -------
    e : numpy.ndarray
        ``(n, 2)`` ``corrected_e1, corrected_e2``; NaN where unusable.
    ok : numpy.ndarray
        ``(n,)`` bool, usable.
    maxrss : float
        The worker's peak resident memory so far (MiB).
    """
    import galsim

    stamps, ipsf, cuts = args
    pim = galsim.Image(psf_image(ipsf), scale=1.0)
    e = np.full((len(stamps), 2), np.nan)
    for i, s in enumerate(stamps):
        r = galsim.hsm.EstimateShear(galsim.Image(s, scale=1.0), pim, shear_est="REGAUSS",
                                     sky_var=SIGMA**2, strict=False)  # fmt: skip
        if r.error_message or r.correction_status != 0:
            continue
        e1, e2 = r.corrected_e1, r.corrected_e2
        if not (math.isfinite(e1) and math.isfinite(e2)):
            continue
        if cuts == "standard" and (r.resolution_factor < 0.3 or math.hypot(e1, e2) >= 2):
            continue
        e[i] = e1, e2
    return e, np.isfinite(e[:, 0]), _rss_mib(resource.RUSAGE_SELF)



def run_regauss(stamps: np.ndarray, ipsf: int, pool: ProcessPoolExecutor, task: int,
                cuts: str) -> tuple[np.ndarray, np.ndarray, float, float]:  # fmt: skip
    """REGAUSS on every rendering of a chunk of galaxies of one PSF, in the worker pool.

    Parameters
    ----------
    stamps : numpy.ndarray
        ``(n, 4, 64, 64)`` main-sample stamps, all of PSF ``ipsf``.
    ipsf : int
        Index into :data:`PSFS`.
    pool : concurrent.futures.ProcessPoolExecutor
        The REGAUSS workers (:func:`_pool`, started with :func:`_start`).
    task : int
        Galaxies per worker task.
    cuts : str
        ``"standard"`` or ``"none"``.

    Returns
    -------
    e : numpy.ndarray
        ``(n, 4, 2)`` distortions (NaN where unusable).
    ok : numpy.ndarray
        ``(n, 4)`` bool.
    maxrss : float
        The largest worker's peak resident memory so far (MiB).
    wall : float
        Wall seconds of the measurement.
    """
    n, n_r = stamps.shape[:2]
    e = np.full((n, n_r, 2), np.nan)
    ok = np.zeros((n, n_r), dtype=bool)
    starts = list(range(0, n, task))
    tasks = [(stamps[k:k + task].reshape(-1, STAMP, STAMP), ipsf, cuts) for k in starts]
    rss = 0.0
    t0 = time.perf_counter()
    for k, (ee, oo, r) in zip(starts, pool.map(regauss_chunk, tasks), strict=True):
        m = len(oo) // n_r
        e[k:k + m] = ee.reshape(m, n_r, 2)
        ok[k:k + m] = oo.reshape(m, n_r)
        rss = max(rss, r)
    return e, ok, rss, time.perf_counter() - t0


# ----------------------------------------------------------------------------------------
# pylensfit
# ----------------------------------------------------------------------------------------
def _lower_config():
    import pylensfit as plf

    return plf.Config(model="bulge+disc", n_bulge_fractions=3, max_stamp_size=STAMP)


#: ``--set`` overrides of the default configuration (applied in every process)
CONFIG_OVERRIDES: dict = {}


#: ``--response``, ``--metacal-step``, ``--metacal-seed``
RESPONSE: dict = {"response": "model", "step": 0.01, "seed": 0}


def _api_config():
    """``Config()`` with the ``--set`` overrides (None without any: the defaults)."""
    import pylensfit as plf

    return plf.Config(**CONFIG_OVERRIDES) if CONFIG_OVERRIDES else None


def pylensfit_priors(method: str, cal_stamps: np.ndarray, psf_img: np.ndarray):
    """pylensfit's priors for one PSF, from its calibration stamps (once per PSF).

    Parameters
    ----------
    method : {"api", "lower"}
        ``"api"``: ``plf.calibrate``; ``"lower"``: ``fit_stamps`` + ``estimate_prior``.
    cal_stamps : numpy.ndarray
        ``(n_cal, 64, 64)`` unsheared calibration stamps of the PSF.
    psf_img : numpy.ndarray
        The PSF image (:func:`psf_image`).

    Returns
    -------
    priors : pylensfit.Priors or pylensfit.Prior
        What :func:`pylensfit_measure` needs.
    wall : float
        Wall seconds.
    """
    import pylensfit as plf

    t0 = time.perf_counter()
    if method == "api":
        for name in ("calibrate", "measure_stamps"):
            if not hasattr(plf, name):
                raise SystemExit(f"pylensfit has no {name}() yet: run with --method lower")
        priors = plf.calibrate(cal_stamps, psf_img, noise_sigma=SIGMA, config=_api_config())
        return priors, time.perf_counter() - t0
    fits = plf.fit_stamps(cal_stamps, psf_img, SIGMA, config=_lower_config())
    ok = (np.asarray(fits.flags) == 0) & ~np.asarray(fits.is_star)
    prior = plf.estimate_prior(fits.lnL[ok], fits.egrid)
    return prior, time.perf_counter() - t0


def pylensfit_measure(method: str, priors, stamps: np.ndarray, psf_img: np.ndarray,
                      keep_lnL: bool = False):  # fmt: skip
    """Measure a chunk of stamps of one PSF with pylensfit; keep only a few columns.

    Parameters
    ----------
    method : {"api", "lower"}
        ``"api"``: ``plf.measure_stamps``; ``"lower"``: ``fit_stamps`` + ``shapes``.
    priors
        :func:`pylensfit_priors`' priors of the PSF.
    stamps : numpy.ndarray
        ``(m, 64, 64)`` stamps to measure.
    psf_img : numpy.ndarray
        The PSF image (:func:`psf_image`).
    keep_lnL : bool
        Also keep the ln L grids and the table's ``meta`` (``--estimator plf``, api).

    Returns
    -------
    cols : dict
        ``e`` and ``sens`` ``(m, 2)`` float64, ``ok`` ``(m,)`` bool (usable and finite);
        with ``keep_lnL`` also ``lnL`` ``(m, n_e)`` float32 and ``meta`` (the
        ``measure_stamps`` table's ``egrid``, ``prior`` and ``refine``).
    wall : float
        Wall seconds.
    """
    import pylensfit as plf

    t0 = time.perf_counter()
    if method == "api" and RESPONSE["response"] == "metacal":
        return _measure_metacal(priors, stamps, psf_img, t0)
    if method == "api":
        tab = plf.measure_stamps(stamps, psf_img, noise_sigma=SIGMA, priors=priors,
                                 config=_api_config())  # fmt: skip
        usable = (np.asarray(tab["flags"]) == 0) & (np.asarray(tab["weight"], dtype=float) > 0)
    else:
        fits = plf.fit_stamps(stamps, psf_img, SIGMA, config=_lower_config())
        tab = plf.shapes(fits.lnL, fits.egrid, priors)
        flags = np.asarray(fits.flags, dtype=np.int32) | np.asarray(tab["flags"], np.int32)
        usable = (flags == 0) & ~np.asarray(fits.is_star)
    wall = time.perf_counter() - t0
    e = np.column_stack([np.asarray(tab[c], dtype=float) for c in ("e1", "e2")])
    s = np.column_stack([np.asarray(tab[c], dtype=float) for c in ("sens1", "sens2")])
    cols = {"e": e, "sens": s,
            "ok": usable & np.all(np.isfinite(e), axis=1) & np.all(np.isfinite(s), axis=1)}
    if keep_lnL:
        cols["lnL"] = np.asarray(tab["lnL"], dtype=np.float32)
        cols["meta"] = {k: tab.meta[k] for k in ("egrid", "prior", "refine")}
    return cols, wall


def _columns(tab, e_cols, s_cols) -> dict:
    """``e``, ``sens`` ``(m, 2)`` and ``ok`` (usable, finite) of a ``measure_stamps`` table."""
    usable = (np.asarray(tab["flags"]) == 0) & (np.asarray(tab["weight"], dtype=float) > 0)
    e = np.column_stack([np.asarray(tab[c], dtype=float) for c in e_cols])
    s = np.column_stack([np.asarray(tab[c], dtype=float) for c in s_cols])
    return {"e": e, "sens": s,
            "ok": usable & np.all(np.isfinite(e), axis=1) & np.all(np.isfinite(s), axis=1)}


def _measure_metacal(priors, stamps: np.ndarray, psf_img: np.ndarray, t0: float):
    """``--response metacal``: ``plf.measure_stamps(..., response="metacal")`` on the +g
    and on the -g renderings in two calls with the same seed, so that a galaxy's +g and
    -g renderings (which share their pixel noise) also share the metacalibration's added
    noise field; the shapes ``e1_mcal, e2_mcal`` with the responses ``R11, R22``, and
    lensfit's own ``e1, e2, sens1, sens2`` of the same fits beside them (``model_*``)."""
    import pylensfit as plf

    n_r = len(RENDERINGS)
    st = stamps.reshape(-1, n_r, STAMP, STAMP)
    plus = np.array([sg > 0 for _, sg in RENDERINGS])
    parts = {}
    for sign in (True, False):
        which = np.flatnonzero(plus == sign)
        tab = plf.measure_stamps(st[:, which].reshape(-1, STAMP, STAMP), psf_img,
                                 noise_sigma=SIGMA, priors=priors, config=_api_config(),
                                 response="metacal", metacal_step=RESPONSE["step"],
                                 seed=RESPONSE["seed"])  # fmt: skip
        parts[sign] = (which, _columns(tab, ("e1_mcal", "e2_mcal"), ("R11", "R22")),
                       _columns(tab, ("e1", "e2"), ("sens1", "sens2")))  # fmt: skip
    wall = time.perf_counter() - t0
    cols = {}
    for key, k in (("", 1), ("model_", 2)):
        for c in ("e", "sens", "ok"):
            shape = (len(st), n_r) + parts[True][k][c].shape[1:]
            out = np.zeros(shape, dtype=parts[True][k][c].dtype)
            for which, *cc in parts.values():
                out[:, which] = cc[k - 1][c].reshape((len(st), len(which)) + shape[2:])
            cols[key + c] = out.reshape((-1,) + shape[2:])
    return cols, wall


def warm_up(stamps: np.ndarray, psf_img: np.ndarray) -> None:
    """Compile pylensfit's kernels on a few stamps (not timed).

    Parameters
    ----------
    stamps : numpy.ndarray
        A few ``(k, 64, 64)`` stamps.
    psf_img : numpy.ndarray
        Their PSF image.
    """
    import pylensfit as plf

    fits = plf.fit_stamps(stamps, psf_img, SIGMA, config=plf.Config())
    plf.shapes(fits.lnL, fits.egrid, plf.Prior())



# ----------------------------------------------------------------------------------------
# m and c
# ----------------------------------------------------------------------------------------
def _groups(n: int, n_groups: int) -> np.ndarray:
    return np.arange(n) * min(n_groups, n) // max(n, 1)


def _jackknife(fn, n: int, n_groups: int) -> tuple[np.ndarray, np.ndarray]:
    """``fn(selection)`` on all ``n`` galaxies and its jackknife error over groups."""
    full = np.asarray(fn(np.ones(n, dtype=bool)))
    grp = _groups(n, n_groups)
    G = int(grp.max()) + 1 if n else 0
    if G < 2:
        return full, np.full_like(full, np.nan)
    loo = np.array([fn(grp != k) for k in range(G)])
    err = np.sqrt((G - 1) / G * np.sum((loo - loo.mean(axis=0)) ** 2, axis=0))
    return full, err


def _m_c(gp: np.ndarray, gm: np.ndarray, g: float) -> np.ndarray:
    """``[m1, m2, c1, c2]`` from the +g and -g estimates ``(2,)`` each."""
    return np.concatenate([(gp - gm) / (2 * g) - 1, (gp + gm) / 2])


def m_c_ratio(e: np.ndarray, s: np.ndarray, g: float, n_groups: int):
    """pylensfit's m and c, ``g(+-) = sum e / sum sens`` over the +-g renderings.

    Parameters
    ----------
    e, s : numpy.ndarray
        ``(n, 4, 2)`` posterior-mean ellipticities and shear sensitivities of the
        paired-selected galaxies, renderings in the order of :data:`RENDERINGS`.
    g : float
        The shear.
    n_groups : int
        Jackknife groups.

    Returns
    -------
    value, err : numpy.ndarray
        ``[m1, m2, c1, c2]`` and their jackknife errors.
    """
    plus = np.array([sg > 0 for _, sg in RENDERINGS])

    def fn(sel):
        gp = e[sel][:, plus].sum(axis=(0, 1)) / s[sel][:, plus].sum(axis=(0, 1))
        gm = e[sel][:, ~plus].sum(axis=(0, 1)) / s[sel][:, ~plus].sum(axis=(0, 1))
        return _m_c(gp, gm, g)

    return _jackknife(fn, len(e), n_groups)


def m_c_plf_estimator(lnL: np.ndarray, meta: dict, g: float, n_groups: int):
    """pylensfit's m and c from ``plf.estimate_shear`` (the fixed point) on the +-g rows.

    Parameters
    ----------
    lnL : numpy.ndarray
        ``(n, 4, n_e)`` ln L grids of the paired-selected galaxies' renderings (order of
        :data:`RENDERINGS`).
    meta : dict
        ``egrid``, ``prior``, ``refine`` of the PSF's ``measure_stamps`` tables.
    g : float
        The shear.
    n_groups : int
        Jackknife groups.

    Returns
    -------
    value, err : numpy.ndarray
        ``[m1, m2, c1, c2]`` and their jackknife errors.
    """
    from astropy.table import Table

    import pylensfit as plf

    plus = np.array([sg > 0 for _, sg in RENDERINGS])

    def fn(sel):
        est = [plf.estimate_shear(Table({"lnL": lnL[sel][:, which].reshape(-1, lnL.shape[2])},
                                        meta=meta))
               for which in (plus, ~plus)]  # fmt: skip
        gp, gm = (np.array([x.g1, x.g2]) for x in est)
        return _m_c(gp, gm, g)

    return _jackknife(fn, len(lnL), n_groups)


def m_c_regauss(e: np.ndarray, g: float, n_groups: int):
    """REGAUSS's m and c, ``g(+-) = <e> / (2 R)``, ``R = 1 - e_rms^2`` of the sample.

    Parameters
    ----------
    e : numpy.ndarray
        ``(n, 4, 2)`` distortions of the paired-selected galaxies.
    g : float
        The shear.
    n_groups : int
        Jackknife groups (R is estimated again in each).

    Returns
    -------
    value, err : numpy.ndarray
        ``[m1, m2, c1, c2]`` and their jackknife errors.
    """
    plus = np.array([sg > 0 for _, sg in RENDERINGS])

    def fn(sel):
        es = e[sel]
        R = 1.0 - float(np.mean(es**2))  # mean over both components: e_rms^2 per component
        gp = es[:, plus].mean(axis=(0, 1)) / (2 * R)
        gm = es[:, ~plus].mean(axis=(0, 1)) / (2 * R)
        return _m_c(gp, gm, g)

    return _jackknife(fn, len(e), n_groups)


def kind_table(pop: Population, psfs, e_plf, s_plf, ok_plf, e_hsm, ok_hsm, g: float,
               n_groups: int) -> list[dict]:
    """m and c of both methods per galaxy kind, the mean over the PSFs ``psfs``.

    Parameters
    ----------
    pop : Population
        The main sample.
    psfs : iterable of int
        The PSFs measured.
    e_plf, s_plf, ok_plf, e_hsm, ok_hsm : numpy.ndarray
        The per-rendering columns (``(n, 4, 2)`` and ``(n, 4)``).
    g : float
        The shear.
    n_groups : int
        Jackknife groups per PSF and kind.

    Returns
    -------
    list of dict
        Rows as for :func:`print_table`, the ``psf`` field naming the kind.
    """
    out = []
    for name in ("pylensfit", "REGAUSS"):
        for ik, kname in enumerate(KINDS):
            per = []
            for ipsf in sorted(psfs):
                sel = np.flatnonzero((pop.psf == ipsf) & (pop.kind == ik))
                if name == "pylensfit":
                    keep = np.all(ok_plf[sel], axis=1)
                    v, err = m_c_ratio(e_plf[sel][keep], s_plf[sel][keep], g, n_groups)
                else:
                    keep = np.all(ok_hsm[sel], axis=1)
                    v, err = m_c_regauss(e_hsm[sel][keep], g, n_groups)
                r = {"method": name, "psf": kname, "n": int(keep.sum())}
                for q, x, dx in zip(("m1", "m2", "c1", "c2"), v, err, strict=True):
                    r[q], r[f"{q}_err"] = float(x), float(dx)
                per.append(r)
            if per:
                row = _mean_row(name, per)
                row["psf"] = kname
                out.append(row)
    return out


# ----------------------------------------------------------------------------------------
# The run
# ----------------------------------------------------------------------------------------
def _rss_mib(who) -> float:
    return resource.getrusage(who).ru_maxrss / 1024.0  # KiB on Linux


def _fmt(v: float, e: float, digits: int) -> str:
    return f"{v:+.{digits}f} ± {e:.{digits}f}"


def print_table(rows: list[dict]) -> None:
    """Print the m and c table (one line per method and PSF, and the mean over PSFs)."""
    head = (f"{'method':10s} {'PSF':24s} {'n':>6s}  {'m1':>16s}  {'m2':>16s}  "
            f"{'c1':>18s}  {'c2':>18s}")  # fmt: skip
    print(head)
    print("-" * len(head))
    last = None
    for r in rows:
        if last is not None and r["method"] != last:
            print()
        last = r["method"]
        ms = [f"{_fmt(r[q], r[q + '_err'], 4):>16s}" for q in ("m1", "m2")]
        cs = [f"{_fmt(r[q], r[q + '_err'], 5):>18s}" for q in ("c1", "c2")]
        print(f"{r['method']:10s} {r['psf']:24s} {r['n']:6d}  " + "  ".join(ms + cs))


def _mean_row(method: str, rows: list[dict]) -> dict:
    out = {"method": method, "psf": "mean over PSFs", "n": int(sum(r["n"] for r in rows))}
    for q in ("m1", "m2", "c1", "c2"):
        out[q] = float(np.mean([r[q] for r in rows]))
        out[f"{q}_err"] = float(np.sqrt(np.sum([r[f"{q}_err"] ** 2 for r in rows]))) / len(rows)
    return out


def _add_row(rows: list, name: str, ipsf: int, fit: tuple) -> None:
    """Append method ``name``'s row of PSF ``ipsf`` (``(values, errors, kept)``)."""
    v, err, kp = fit
    r = {"method": name, "psf": PSFS[ipsf][0], "n": int(kp.sum())}
    for q, x, dx in zip(("m1", "m2", "c1", "c2"), v, err, strict=True):
        r[q], r[f"{q}_err"] = float(x), float(dx)
    rows.append(r)


def _add_psf_rows(rows: dict[str, list], ipsf: int, plf_fit: tuple, hsm_fit: tuple) -> None:
    """Append PSF ``ipsf``'s rows (``(values, errors, kept)`` of each method) to ``rows``."""
    for name, fit in (("pylensfit", plf_fit), ("REGAUSS", hsm_fit)):
        _add_row(rows[name], name, ipsf, fit)


def combine(paths: list[str], n_groups: int) -> int:
    """Print the per-PSF, mean and by-kind tables of runs saved with ``--columns``.

    The runs must share the population (``--ngal`` and ``--seed``); each contributes
    the PSFs it ran. pylensfit's shear is ``sum e / sum sens`` (the default estimator).
    """
    runs = [np.load(p) for p in paths]
    first = runs[0]
    pop = Population(**{k[4:]: first[k] for k in first.files if k.startswith("pop_")})
    g = float(first["g"])
    cols = {k: np.array(first[k]) for k in ("e_plf", "s_plf", "ok_plf", "e_hsm", "ok_hsm")}
    done: set[int] = set()
    for path, r in zip(paths, runs, strict=True):
        if not all(np.array_equal(r[f"pop_{k}"], getattr(pop, k))
                   for k in pop.__dataclass_fields__) or float(r["g"]) != g:
            raise SystemExit(f"{path}: another population or shear than {paths[0]}'s")
        psfs = {int(i) for i in r["psfs_run"]}
        if psfs & done:
            raise SystemExit(f"{path}: PSFs {sorted(psfs & done)} are in an earlier file")
        sel = np.isin(pop.psf, sorted(psfs))
        for k in cols:
            cols[k][sel] = r[k][sel]
        done |= psfs
    rows = {"pylensfit": [], "REGAUSS": []}
    for ipsf in sorted(done):
        sel = np.flatnonzero(pop.psf == ipsf)
        keep_p = np.all(cols["ok_plf"][sel], axis=1)
        keep_h = np.all(cols["ok_hsm"][sel], axis=1)
        vp, ep = m_c_ratio(cols["e_plf"][sel][keep_p], cols["s_plf"][sel][keep_p], g, n_groups)
        vh, eh = m_c_regauss(cols["e_hsm"][sel][keep_h], g, n_groups)
        _add_psf_rows(rows, ipsf, (vp, ep, keep_p), (vh, eh, keep_h))
    table_rows = [r for name in rows for r in (*rows[name], _mean_row(name, rows[name]))]
    print(f"{len(paths)} runs, PSFs {sorted(done)}; g = {g}")
    print_table(table_rows)
    print("\nby kind (paired selection; the mean over the PSFs run):")
    print_table(kind_table(pop, done, cols["e_plf"], cols["s_plf"], cols["ok_plf"],
                           cols["e_hsm"], cols["ok_hsm"], g, n_groups))  # fmt: skip
    return 0


def main(argv=None) -> int:
    """Run the benchmark (see the module docstring); returns the exit status."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ngal", type=int, default=4000,
                    help="main-sample galaxies, total over the 4 PSFs (4 renderings each)")
    ap.add_argument("--ncal", type=int, default=None,
                    help="unsheared calibration galaxies, total (default min(ngal, 20000))")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--g", type=float, default=0.02, help="shear: (+g, +g) and (-g, -g)")
    ap.add_argument("--independent-noise", action="store_true",
                    help="a noise field per rendering (default: +g and -g share theirs)")
    ap.add_argument("--jobs", type=int, default=2, help="processes for rendering and REGAUSS")
    ap.add_argument("--method", choices=("api", "lower"), default="api",
                    help="pylensfit layer: calibrate+measure_stamps, or fit_stamps+shapes")
    ap.add_argument("--estimator", choices=("ratio", "plf"), default="ratio",
                    help="pylensfit shear: sum e / sum sens, or plf.estimate_shear (api)")
    ap.add_argument("--response", choices=("model", "metacal"), default="model",
                    help="pylensfit's response (api): lensfit's sensitivity, or "
                         "metacalibration (measure_stamps(response='metacal'))")
    ap.add_argument("--metacal-step", type=float, default=0.01)
    ap.add_argument("--metacal-seed", type=int, default=0)
    ap.add_argument("--hsm-cuts", choices=("standard", "none"), default="standard",
                    help="REGAUSS cuts beyond failures: resolution >= 0.3 and |e| < 2")
    ap.add_argument("--block", type=int, default=25, help="galaxies per PSF block")
    ap.add_argument("--groups", type=int, default=50, help="jackknife groups per PSF")
    ap.add_argument("--chunk", type=int, default=500,
                    help="main-sample galaxies rendered and measured at a time (per PSF)")
    ap.add_argument("--task", type=int, default=25, help="galaxies per worker task")
    ap.add_argument("--psfs", default=None,
                    help="comma-separated PSF indices to run (default: all; the population "
                         "is the same, so runs of different PSFs combine)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a Config default for pylensfit (api method), e.g. "
                         "--set prior_form=spline; repeatable")  # fmt: skip
    ap.add_argument("--out", default=None, help="write the table (ECSV) here")
    ap.add_argument("--columns", default=None,
                    help="write the per-rendering columns and the population (NPZ) here")
    ap.add_argument("--combine", nargs="+", default=None, metavar="NPZ",
                    help="measure nothing: combine the --columns files of runs of different "
                         "PSFs (the same --ngal and --seed) and print their tables")
    a = ap.parse_args(argv)  # fmt: skip
    for item in a.set:
        key, sep, value = item.partition("=")
        if not sep:
            ap.error(f"--set {item!r}: expected KEY=VALUE")
        CONFIG_OVERRIDES[key.strip()] = yaml.safe_load(value)
    if a.combine:
        return combine(a.combine, a.groups)
    if a.response == "metacal" and (a.method != "api" or a.estimator != "ratio"):
        ap.error("--response metacal needs --method api and --estimator ratio")
    RESPONSE.update(response=a.response, step=a.metacal_step, seed=a.metacal_seed)
    if a.estimator == "plf" and a.method != "api":
        ap.error("--estimator plf needs --method api (the table's lnL and meta)")
    if min(a.chunk, a.task, a.jobs, a.block) < 1:
        ap.error("--chunk, --task, --jobs and --block must be positive")
    ncal = min(a.ngal, 20000) if a.ncal is None else a.ncal
    try:
        run_psfs = (range(len(PSFS)) if a.psfs is None
                    else sorted({int(x) for x in a.psfs.split(",")}))  # fmt: skip
    except ValueError:
        ap.error(f"--psfs: not a comma-separated list of integers: {a.psfs!r}")
    if any(not 0 <= i < len(PSFS) for i in run_psfs):
        ap.error(f"--psfs: indices must be in 0..{len(PSFS) - 1}")
    shared = not a.independent_noise
    keep_lnL = a.estimator == "plf"

    import pylensfit as plf

    try:
        import numba

        threads = numba.get_num_threads()
    except Exception:  # pragma: no cover - numba is a dependency
        threads = -1

    t_start = time.perf_counter()
    pop = draw_population(a.ngal, np.random.default_rng(a.seed), a.block)
    cal = draw_population(ncal, np.random.default_rng([a.seed, 1]), a.block)
    n_r = len(RENDERINGS)
    # the kept per-rendering columns
    e_plf = np.full((a.ngal, n_r, 2), np.nan)
    s_plf = np.full((a.ngal, n_r, 2), np.nan)
    ok_plf = np.zeros((a.ngal, n_r), dtype=bool)
    e_hsm = np.full((a.ngal, n_r, 2), np.nan)
    ok_hsm = np.zeros((a.ngal, n_r), dtype=bool)
    # with --response metacal: lensfit's own sensitivity on the same fits
    e_mod, s_mod, ok_mod = np.full_like(e_plf, np.nan), np.full_like(s_plf, np.nan), \
        np.zeros_like(ok_plf)
    lnL, meta = {}, {}
    t_render = t_cal = t_meas = t_hsm = rss_hsm = 0.0
    max_chunk_mib = max_cal_mib = 0.0
    done = set()
    with _pool(a.jobs) as rpool, _pool(a.jobs) as hpool:
        _start(rpool, a.jobs)
        _start(hpool, a.jobs)
        for ipsf in run_psfs:
            sel = np.flatnonzero(pop.psf == ipsf)
            csel = np.flatnonzero(cal.psf == ipsf)
            if len(sel) == 0:
                continue
            psf_img = psf_image(ipsf)
            t0 = time.perf_counter()
            cal_stamps = render(cal, csel, None, a.seed, 1, rpool, a.task)
            t_render += time.perf_counter() - t0
            max_cal_mib = max(max_cal_mib, cal_stamps.nbytes / 2**20)
            if not done:
                warm_up(cal_stamps[:4], psf_img)
            priors, tc = pylensfit_priors(a.method, cal_stamps, psf_img)
            t_cal += tc
            ell = getattr(priors, "ellipticity", priors)
            print(f"PSF {ipsf}: ellipticity prior {ell!r}, at a bound: "
                  f"{ell.info.get('at_bound') or 'no'}", flush=True)
            del cal_stamps
            for k in range(0, len(sel), a.chunk):
                idx = sel[k:k + a.chunk]
                t0 = time.perf_counter()
                stamps = render(pop, idx, a.g, a.seed, 0, rpool, a.task, shared)
                t_render += time.perf_counter() - t0
                max_chunk_mib = max(max_chunk_mib, stamps.nbytes / 2**20)
                ee, oo, rss, th = run_regauss(stamps, ipsf, hpool, a.task, a.hsm_cuts)
                e_hsm[idx], ok_hsm[idx] = ee, oo
                rss_hsm, t_hsm = max(rss_hsm, rss), t_hsm + th
                cols, tm = pylensfit_measure(a.method, priors, stamps.reshape(-1, STAMP, STAMP),
                                             psf_img, keep_lnL)  # fmt: skip
                del stamps
                t_meas += tm
                e_plf[idx] = cols["e"].reshape(len(idx), n_r, 2)
                s_plf[idx] = cols["sens"].reshape(len(idx), n_r, 2)
                ok_plf[idx] = cols["ok"].reshape(len(idx), n_r)
                if "model_e" in cols:
                    e_mod[idx] = cols["model_e"].reshape(len(idx), n_r, 2)
                    s_mod[idx] = cols["model_sens"].reshape(len(idx), n_r, 2)
                    ok_mod[idx] = cols["model_ok"].reshape(len(idx), n_r)
                if keep_lnL:
                    if ipsf not in lnL:
                        n_e = cols["lnL"].shape[1]
                        lnL[ipsf] = np.empty((len(sel), n_r, n_e), dtype=np.float32)
                        meta[ipsf] = cols["meta"]
                    lnL[ipsf][k:k + len(idx)] = cols["lnL"].reshape(len(idx), n_r, -1)
                del cols
            done.add(ipsf)
    noise = "independent per rendering" if a.independent_noise else "shared by +g and -g"
    n_main = int(np.isin(pop.psf, sorted(done)).sum())
    n_cal = int(np.isin(cal.psf, sorted(done)).sum())
    print(f"rendered {n_main} x {n_r} + {n_cal} calibration stamps ({STAMP}^2) in "
          f"{t_render:.1f} s with {a.jobs} processes, {a.chunk} galaxies at a time; "
          f"seed {a.seed}, g = {a.g}, kinds {'/'.join(KINDS)} 40/30/30; noise {noise}")  # fmt: skip

    # m and c per PSF, paired selection
    rows = {"pylensfit": [], "REGAUSS": []}
    for ipsf in sorted(done):
        sel = np.flatnonzero(pop.psf == ipsf)
        keep_p = np.all(ok_plf[sel], axis=1)
        keep_h = np.all(ok_hsm[sel], axis=1)
        if keep_lnL:
            vp, ep = m_c_plf_estimator(lnL[ipsf][keep_p], meta[ipsf], a.g, a.groups)
        else:
            vp, ep = m_c_ratio(e_plf[sel][keep_p], s_plf[sel][keep_p], a.g, a.groups)
        vh, eh = m_c_regauss(e_hsm[sel][keep_h], a.g, a.groups)
        _add_psf_rows(rows, ipsf, (vp, ep, keep_p), (vh, eh, keep_h))
        if a.response == "metacal":
            keep_m = np.all(ok_mod[sel], axis=1)
            vm, em = m_c_ratio(e_mod[sel][keep_m], s_mod[sel][keep_m], a.g, a.groups)
            _add_row(rows.setdefault("plf-model", []), "plf-model", ipsf, (vm, em, keep_m))
    table_rows = [r for name in rows for r in (*rows[name], _mean_row(name, rows[name]))]
    kind_rows = kind_table(pop, done, e_plf, s_plf, ok_plf, e_hsm, ok_hsm, a.g, a.groups)
    if a.response == "metacal":
        kind_rows += [r for r in kind_table(pop, done, e_mod, s_mod, ok_mod, e_hsm, ok_hsm,
                                            a.g, a.groups) if r["method"] == "pylensfit"]
        for r in kind_rows[-len(KINDS):]:
            r["method"] = "plf-model"

    n_main = a.ngal * n_r
    n_all = n_main + ncal
    rate_meas = n_main / t_meas if t_meas > 0 else math.nan
    rate_tot = n_all / (t_cal + t_meas) if t_cal + t_meas > 0 else math.nan
    rate_hsm = n_main / t_hsm if t_hsm > 0 else math.nan
    kept_mib = sum(x.nbytes for x in (e_plf, s_plf, ok_plf, e_hsm, ok_hsm, *lnL.values()))
    kept_mib /= 2**20
    label = ("calibrate + measure_stamps" if a.method == "api"
             else "fit_stamps + estimate_prior + shapes")  # fmt: skip
    est = "sum e / sum sens" if a.estimator == "ratio" else "plf.estimate_shear"
    if a.response == "metacal":
        est = (f"metacalibration, sum e_mcal / sum R (step {a.metacal_step}); plf-model: "
               "lensfit's sensitivity on the same fits")
    print(f"pylensfit --method {a.method} ({label}; shear {est}); REGAUSS cuts: {a.hsm_cuts}")
    print(f"{'':22s} {'pylensfit':>14s} {'REGAUSS':>14s}")
    print(f"{'stamps per second':22s} {rate_meas:14.1f} {rate_hsm:14.1f}   "
          f"(pylensfit incl. calibration: {rate_tot:.1f})")  # fmt: skip
    print(f"{'galaxies per second':22s} {a.ngal / t_meas if t_meas > 0 else math.nan:14.2f} "
          f"{a.ngal / t_hsm if t_hsm > 0 else math.nan:14.2f}   (4 renderings each)")
    print(f"{'wall seconds':22s} {t_meas:14.1f} {t_hsm:14.1f}   "
          f"(pylensfit calibration: {t_cal:.1f})")  # fmt: skip
    print(f"{'workers / threads':22s} {f'1 x {threads} thr':>14s} {f'{a.jobs} x 1 thr':>14s}")
    print(f"{'peak RSS (MiB)':22s} {_rss_mib(resource.RUSAGE_SELF):14.0f} {rss_hsm:14.0f}   "
          f"(pylensfit's: this process, holding at most {max_chunk_mib:.1f} MiB of main and "
          f"{max_cal_mib:.1f} MiB of calibration stamps at once, {kept_mib:.1f} MiB of kept "
          f"columns)")  # fmt: skip
    print(f"{'renderings usable':22s} {ok_plf.mean():14.3f} {ok_hsm.mean():14.3f}")
    print()
    print_table(table_rows)
    print("\nby kind (paired selection; the mean over the PSFs run):")
    print_table(kind_rows)
    print(f"\ntotal {time.perf_counter() - t_start:.1f} s; pylensfit {plf.__version__}")

    if a.out:
        from astropy.table import Table

        t = Table(rows=[[r[k] for k in table_rows[0]] for r in table_rows],
                  names=list(table_rows[0]))  # fmt: skip
        t.meta.update(ngal=a.ngal, ncal=ncal, seed=a.seed, g=a.g, method=a.method,
                      estimator=a.estimator, hsm_cuts=a.hsm_cuts, block=a.block,
                      groups=a.groups, chunk=a.chunk, noise="independent"
                      if a.independent_noise else "shared", rate_pylensfit=rate_meas,
                      rate_pylensfit_total=rate_tot, rate_regauss=rate_hsm,
                      t_render=t_render, argv=sys.argv[1:])  # fmt: skip
        t.write(a.out, format="ascii.ecsv", overwrite=True)
        print(f"wrote {a.out}")
    if a.columns:
        np.savez_compressed(a.columns, e_plf=e_plf, s_plf=s_plf, ok_plf=ok_plf, e_hsm=e_hsm,
                            ok_hsm=ok_hsm, psfs_run=np.array(sorted(done)), g=a.g,
                            e_mod=e_mod, s_mod=s_mod, ok_mod=ok_mod, response=a.response,
                            **{f"pop_{k}": getattr(pop, k)
                               for k in pop.__dataclass_fields__})  # fmt: skip
        print(f"wrote {a.columns}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
