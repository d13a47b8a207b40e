"""The recipe's glue: the calibration passes over the images, the measuring pass and the
assembly of the rows.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from astropy.table import Table, vstack

from ..assemble import ObjectContext, assemble, usable_galaxies
from ..calibration import CalibrationSample, Priors, Recipe, RecipePass
from ..catalogue import COLUMNS, FITCLASS
from ..config import Config
from ..prior import Prior, SizePrior
from ..psf import centre_on_stamp
from ..runner import run_tasks
from .catalogue_io import catalogue_frame, metacal_to_sky, psf_to_sky
from .parts import part_path, pass_key, resumed_results, write_part
from .records import HELDOUT_KEYS, PSF_KEYS, ImageResult, ImageTask
from .task import image_task

__all__ = ["LastPass", "Workers", "measure_pass", "calibration_passes", "assemble_results"]

# the pipeline's one logger: its name predates the split into modules
log = logging.getLogger("pylensfit.pipeline")


@dataclass(frozen=True)
class Workers:
    """Where the images' tasks run (:func:`pylensfit.runner.run_tasks`): ``jobs`` local
    processes of ``pool``, or the dask scheduler at ``scheduler``; ``progress``: a bar."""

    jobs: int = 1
    scheduler: str | None = None
    progress: bool = False
    pool: Any = None

    def run(self, fn, tasks: list, label: str, objects: bool = False):
        """``(task, result)`` of ``fn`` on every task, as they finish."""
        return run_tasks(fn, tasks, self.jobs, self.scheduler, label, self.progress,
                         self.pool, objects=objects)  # fmt: skip


@dataclass
class LastPass:
    """The calibration recipe's last pass over the images (:func:`calibration_passes`),
    kept for :func:`measure_pass`: its key (:func:`pass_key`) and its results."""

    key: str | None = None
    results: dict[int, ImageResult] = field(default_factory=dict)

    def clear(self) -> None:
        """Forget the pass (its results' memory freed)."""
        self.key, self.results = None, {}


def measure_pass(tasks: list[ImageTask], cfg: Config, priors: Priors, last: LastPass,
                 parts: Path | None, pr_file: Path | None,
                 workers: Workers) -> dict[int, ImageResult]:  # fmt: skip
    """The measurement: every image under ``priors``, the recipe's last pass reused where
    it was made under them (its images, where the recipe ran on a sample of them; not
    with ``Config.response = "metacal"``, whose images' tasks need the priors), finished
    images kept in ``parts`` (a resumed run reads them).
    """
    results: dict[int, ImageResult] = {}
    run_cfg = priors.apply(cfg)
    metacal = run_cfg.response == "metacal"  # the image's task metacalibrates, under priors
    final = [replace(t, config=run_cfg, size_prior=priors.size,
                     metacal_priors=priors if metacal else None) for t in tasks]  # fmt: skip
    if last.key == pass_key(run_cfg, priors.size, False) and not metacal:
        results = dict(last.results)  # the recipe's last pass is the measurement
    last.clear()
    if parts is not None:
        parts.mkdir(parents=True, exist_ok=True)
        priors.save(pr_file)
    for t in final:
        if t.index in results and parts is not None:
            pp = part_path(parts, t)
            if not pp.exists():
                write_part(pp, results[t.index])
    todo = resumed_results([t for t in final if t.index not in results], parts, results)
    for t, res in workers.run(image_task, todo, "images", objects=True):
        if parts is not None:
            write_part(part_path(parts, t), res)
        results[t.index] = res
        log.info("%s: %d objects, %s", t.path, len(res),
                 ", ".join(f"{k} {v:.2f} s" for k, v in res.timing.items()))  # fmt: skip
    return results


def calibration_passes(tasks: list[ImageTask], cfg: Config, prior: Prior | None,
                       size_prior: SizePrior | None, workers: Workers, last: LastPass,
                       parts: Path | None = None) -> Priors:  # fmt: skip
    """The calibration recipe (:class:`pylensfit.calibration.Recipe`) on the images of
    ``tasks`` (all the run's, or its calibration sample).

    Each pass the recipe asks for measures every image of ``tasks`` (detection, PSF,
    neighbours and sky included) and hands the recipe its usable galaxies
    (:func:`pylensfit.calibration.usable_galaxies`); the last pass's results stay in
    ``last`` so that, when the measurement's settings are those of the last pass, its
    images are not measured again. With ``parts``, the images of every pass that keeps no
    ``L(r)`` are written there as they finish and read back by a resumed run.
    """
    recipe = Recipe(cfg, 1, prior=prior,
                    size_priors=None if size_prior is None else [size_prior])  # fmt: skip
    while (step := recipe.next_pass) is not None:
        recipe.feed(_calibration_pass(tasks, step, workers, last, parts))
    return recipe.priors[0]


def _calibration_pass(tasks: list[ImageTask], step: RecipePass, workers: Workers,
                      last: LastPass, parts: Path | None) -> CalibrationSample:  # fmt: skip
    """One pass of the recipe over the images: their usable galaxies."""
    keep = step.keep_lnL_r
    run = [replace(t, config=step.configs[0], keep_lnL_r="annuli" if keep else False,
                   psf_dir=t.psf_dir if not keep else None, size_prior=step.size_priors[0])
           for t in tasks]  # fmt: skip
    results: dict[int, ImageResult] = {}
    todo = run
    if parts is not None and not keep:
        parts.mkdir(parents=True, exist_ok=True)
        todo = resumed_results(run, parts, results)
    for t, res in workers.run(image_task, todo, step.label, objects=True):
        if parts is not None and not keep:
            write_part(part_path(parts, t), res)
        results[t.index] = res
    samples = []
    for t in tasks:
        samples.append(_usable_sample(results[t.index], step.configs[0].min_snr, keep))
        if keep:  # the sample holds what the recipe needs
            results[t.index] = replace(results[t.index], lnL_r=None)
    last.clear()
    if not keep:
        last.key, last.results = pass_key(step.configs[0], step.size_priors[0], False), results
    sample = CalibrationSample.concatenate(samples)
    log.info("%s: %d usable galaxies", step.label, len(sample))
    return sample


def _usable_sample(res: ImageResult, min_snr: float, keep: bool) -> CalibrationSample:
    """An image's usable galaxies (:func:`usable_galaxies`, a finite ``ln L`` row) as the
    recipe takes them; their ``L(r)`` per ring of ``|e|`` with ``keep``."""
    rows = res.rows
    snr = np.asarray(rows["model_SNratio"], dtype=float)
    ok = (usable_galaxies(rows["flags"], rows["fitclass"] != FITCLASS["galaxy"], snr, min_snr)
          & np.isfinite(res.lnL).all(axis=1))  # fmt: skip
    flux = np.asarray(rows["model_flux"], dtype=float)
    return CalibrationSample(
        egrid=res.egrid, lnL=res.lnL[ok], flux=flux[ok], flux_err=(flux / snr)[ok],
        snr=snr[ok], dx=(rows["x"] - rows["x_detect"])[ok],
        dy=(rows["y"] - rows["y_detect"])[ok], group=np.zeros(int(ok.sum()), dtype=int),
        lnL_bulge=None if res.lnL_bulge is None else res.lnL_bulge[ok],
        lnL_star=rows["lnL_star"][ok] if "lnL_star" in rows else None,
        lnL_r_grouped=[res.lnL_r[ok]] if keep else None)  # fmt: skip


def assemble_results(results: list[ImageResult], cfg: Config, priors: Priors) -> Table:
    """Concatenate the images, add the Bayesian shapes under the priors
    (:func:`pylensfit.assemble.assemble`, as :func:`pylensfit.measure_stamps` does)."""
    egrid = results[0].egrid
    tabs = [Table(r.rows) for r in results]
    cat = vstack(tabs, metadata_conflicts="silent") if tabs else Table()
    lnL = np.concatenate([r.lnL for r in results], axis=0)
    lnL_bulge = None
    if all(r.lnL_bulge is not None for r in results):
        lnL_bulge = np.concatenate([r.lnL_bulge for r in results], axis=0)
    n = len(cat)
    cat.add_column(np.arange(1, n + 1, dtype=np.int64), name="id", index=0)
    psf_sigma = np.concatenate([np.full(len(r), np.nan if r.psf is None else r.psf.sigma)
                                for r in results]) if results else np.zeros(0)  # fmt: skip
    ctx = ObjectContext(
        flags=np.asarray(cat["flags"], dtype=np.int32),
        not_galaxy=np.asarray(cat["fitclass"]) != FITCLASS["galaxy"],
        model_SNratio=np.asarray(cat["model_SNratio"], dtype=float),
        model_flux=np.asarray(cat["model_flux"], dtype=float),
        scalelength=np.asarray(cat["scalelength"], dtype=float),
        noise_sigma=np.asarray(cat["noise_sigma"], dtype=float), psf_sigma=psf_sigma,
        frame=catalogue_frame(cat))  # fmt: skip
    out = assemble(lnL, egrid, priors, cfg, ctx, lnL_bulge=lnL_bulge,
                   lnL_star=cat["lnL_star"] if lnL_bulge is not None else None,
                   flagged="blank")  # fmt: skip
    for c, v in out.columns.items():
        cat[c] = v
    psf_to_sky(cat, ctx.frame)
    metacal_to_sky(cat, ctx.frame)
    cat["lnL"] = out.lnL
    if lnL_bulge is not None:
        cat["lnL_bulge"] = lnL_bulge
    order = [c for c in COLUMNS if c in cat.colnames]
    cat = cat[order + [c for c in cat.colnames if c not in order]]
    for c in cat.colnames:
        if c in COLUMNS:
            unit, desc = COLUMNS[c]
            cat[c].description = desc
            if unit:
                cat[c].unit = unit
    psfs = Table()
    psfs["image"] = [os.path.basename(r.path) for r in results]
    for k in PSF_KEYS + HELDOUT_KEYS:
        psfs[f"psf_{k}"] = [np.nan if r.psf is None else r.psf.get(k) for r in results]
    psfs["psf_source"] = [r.psf_source for r in results]
    psfs["note"] = [r.psf_note for r in results]
    cat.meta["egrid"] = egrid
    cat.meta["prior"] = priors.ellipticity
    cat.meta["priors"] = priors
    cat.meta["size_prior"] = priors.size
    cat.meta["refine"] = int(cfg.output_refine)
    if lnL_bulge is not None:
        cat.meta["bulge_fractions"] = np.array([run.bulge_fraction for run in cfg.bulge_runs])
        if cfg.bulge_size_ratio2 > 0 or cfg.sersic_ladder:
            cat.meta["bulge_sizes"] = np.array([run.size for run in cfg.bulge_runs])
            cat.meta["runs"] = cfg.run_labels
        cat.meta["bulge_weights"] = priors.bulge_weights
    cat.meta["psfs"] = psfs
    # each image's PSF (zeros where it failed), on the largest PSF image's side
    side = max([cfg.stamp_size, *(max(np.shape(r.psf.image)) for r in results
                                  if r.psf is not None)])  # fmt: skip
    cat.meta["psf_images"] = np.array([
        np.zeros((side, side)) if r.psf is None
        else centre_on_stamp(r.psf.image, side) for r in results])  # fmt: skip
    cat.meta["config"] = cfg
    if "e1_mcal" in cat.colnames:
        cat.meta["metacal_step"] = float(cfg.metacal_step)
    cat.meta["timing"] = {k: float(sum(r.timing[k] for r in results))
                          for k in results[0].timing}  # fmt: skip
    return cat
