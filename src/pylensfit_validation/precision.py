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
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from astropy.table import Table, vstack

from pylensfit.calibration import MIN_FLUX_RANGE_GALAXIES, CalibrationSample, run_recipe
from pylensfit.config import Config
from pylensfit.prior import Prior, SizePrior
from pylensfit.runner import run_tasks, worker_pool

from .precision_bias import (
    BIAS_COLUMNS,
    JACKKNIFE_GALAXIES,
    bias_table,
    block_task,
    measured_bulge_fraction,
    psf_mean,
    reduce_likelihoods,
    reduce_renderings,
    shape_controls,
    shear_from_sums,
    usable_fits,
)
from .precision_render import (
    ESTIMATORS,
    MORPHOLOGIES,
    N_QUANTITIES,
    PRECISION_PSFS,
    QUANTITIES,
    PrecisionSpec,
    block_count,
    draw_image,
    flux_and_noise,
    galsim_psf,
    population_flux_range,
    population_prior,
    population_size_prior,
    population_table,
    profile_of,
    psf_image,
    reference_norm,
    render_block,
    shear_sets,
)
from .precision_report import write_report

__all__ = [
    "breakdowns",
    "BULGE_EDGES",
    "MISALIGN_EDGES",
    "SERSIC_EDGES",
    "SERSIC_EDGES_WIDE",
    "SIZE_EDGES",
    "SNR_EDGES",
    "default_config",
    "precision",
    "spec_with",
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
    "BIAS_COLUMNS",
    "JACKKNIFE_GALAXIES",
    "bias_table",
    "block_task",
    "measured_bulge_fraction",
    "psf_mean",
    "reduce_likelihoods",
    "reduce_renderings",
    "shape_controls",
    "shear_from_sums",
    "usable_fits",
    "write_report",
]

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


def breakdowns(gal: Table, psfs: tuple[dict, ...]) -> dict[str, dict[str, np.ndarray]]:
    """The samples of the bias tables: by name (``psf``, ``snr``, ``size``, ...), each
    sample's label and its rows of ``gal`` (the galaxy table of :func:`precision`, or a
    dict of its columns)."""
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
    ncb = block_count(spec.ncal, spec.block_size)
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
    for _, r in sorted(run_tasks(block_task, tasks, run.jobs, run.scheduler, label,
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
    nb = block_count(spec.ngal, spec.block_size)
    tasks = [{"spec": spec, "config": cal.cfgs[b % npsf], "prior": cal.prior,
              "bulge_weights": cal.bulge_weights, "size_prior": cal.size_priors[b % npsf],
              "psf": b % npsf, "block": b, "calibration": False}
             for b in range(nb)]  # fmt: skip
    parts: dict[int, dict] = {}
    for t, r in run_tasks(block_task, tasks, run.jobs, run.scheduler, "precision",
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
    # jackknife groups: the blocks cut into runs of JACKKNIFE_GALAXIES (the galaxies
    # are independent; the blocks only share out the work), so that a small run still
    # has the groups per PSF that the control variates need
    per_block = -(-spec.block_size // JACKKNIFE_GALAXIES)
    gal["jk"] = np.concatenate([r["block"] * per_block + np.arange(len(r["truth"]))
                                // JACKKNIFE_GALAXIES for r in res])  # fmt: skip
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
    for name, groups in breakdowns(gal, spec.psfs).items():
        t = bias_table(Q, usable, gal["jk"], spec.g, groups=groups, controls=X)
        t["breakdown"] = name
        tabs.append(t)
        if name == "psf" and npsf > 1:
            tabs.insert(1, psf_mean(t))
    t = bias_table(Q, usable, gal["jk"], spec.g, selection="independent", controls=X)
    t["breakdown"] = "selection"
    t.replace_column("group", np.full(len(t), "independent"))
    tabs.append(t)
    t = bias_table(Q, usable, gal["jk"], spec.g)
    t["breakdown"] = "no controls"
    tabs.append(t)
    if Q.shape[1] == 8:  # the same galaxies without their noise twins: what the twins buy
        psf_groups = breakdowns(gal, spec.psfs)["psf"] if npsf > 1 else {}
        t = bias_table(Q[:, :4], usable[:, :4], gal["jk"], spec.g, controls=X,
                       groups={"all": np.ones(len(gal), bool), **psf_groups})  # fmt: skip
        if npsf > 1:
            t = vstack([t[:1], psf_mean(t[t["group"] != "all"])[BIAS_COLUMNS], t[1:]])
        t["breakdown"] = "no noise twins"
        tabs.append(t)
    out = vstack(tabs)
    return out[["breakdown", *[c for c in out.colnames if c != "breakdown"]]]


def _fp_step(Q: np.ndarray, usable: np.ndarray, g: float) -> float:
    """The fixed-point linearisation's largest distance of the estimate from the nominal shear."""
    step = 0.0
    for s, ks in enumerate(shear_sets(Q.shape[1])):
        w = usable.all(axis=1)
        T = np.nan_to_num(Q[w][:, ks].astype(float)).sum(axis=(0, 1))
        gn = np.array([g, g]) * (1 if s == 0 else -1)
        gh = shear_from_sums(T, np.asarray(len(ks) * float(w.sum())), gn, "fixed-point")
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
