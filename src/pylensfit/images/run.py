""":func:`measure`, the pipeline's entry point: from FITS images to a shear catalogue."""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from astropy.table import Table

from ..calibration import Priors
from ..config import Config
from ..prior import Prior, SizePrior
from ..psf import PSFResult
from ..psfmodel import PSFModel
from ..runner import worker_pool
from .catalogue_io import write_catalogue
from .image_psf import starfield_task
from .inputs import InputError, as_list, check_inputs, load_given, read_given_psfs
from .parts import parts_dropped_if_unused, remove_stale_temporaries
from .passes import LastPass, Workers, assemble_results, calibration_passes, measure_pass
from .records import ImageResult, ImageTask, StarfieldTask
from .sample import sample_tasks

__all__ = ["calibrate_images", "measure"]

# the pipeline's one logger: its name predates the split into modules
log = logging.getLogger("pylensfit.pipeline")


def measure(
    images: str | os.PathLike | Iterable[str | os.PathLike], *,
    stars: Iterable[str | os.PathLike] | None = None,
    weights: Iterable[str | os.PathLike | None] | None = None,
    masks: Iterable[str | os.PathLike | None] | None = None,
    catalogues: Iterable[str | os.PathLike | None] | None = None,
    star_column: str | None = None, config: Config | None = None,
    prior: Prior | str | os.PathLike | None = None,
    size_prior: SizePrior | str | os.PathLike | None = None,
    priors: Priors | str | os.PathLike | None = None,
    psf: PSFResult | PSFModel | np.ndarray | str | os.PathLike | Sequence | None = None,
    output: str | os.PathLike | None = None, psf_dir: str | os.PathLike | None = None,
    overwrite: bool = False, jobs: int = 1, scheduler: str | None = None, progress: bool = True,
) -> Table:
    """Measure the shapes of every object in FITS images: images in, catalogue out.

    Parameters
    ----------
    images : str or list of str
        FITS images (background need not be subtracted), with ``WEIGHT`` (inverse
        variance) and ``MASK`` (non-zero = bad) HDUs used if present.
    stars : list of str, optional
        Star-field images; their PSFs are co-added with each image's own (a polynomial
        model: the one of the most stars).
    psf : PSFResult, PSFModel, numpy.ndarray or str, or a list of them, optional
        The PSF instead of stars, for every image or one per image: an image (pixel
        response included, centred on ``[n//2, n//2]``) or its file, a
        :class:`~pylensfit.psfmodel.PSFModel` or its file (a Piff model too).
    weights, masks, catalogues : list of str, optional
        Weight, mask and input-catalogue files, one per image (``None`` entries
        allowed); a catalogue (``x, y`` 0-based or ``X_IMAGE, Y_IMAGE`` 1-based)
        replaces detection.
    star_column : str, optional
        Column of the input catalogue that marks the PSF stars (no locus selection).
    config : Config, optional
        Settings (default ``Config()``, the recommended method; ``response="metacal"``).
    prior, size_prior : Prior, SizePrior or str, optional
        An ellipticity or size prior (or a saved one's path) kept instead of estimated.
    priors : Priors or str, optional
        Every prior (or a saved :class:`~pylensfit.Priors`, as :func:`calibrate_images`
        writes it): every image is measured in one pass under them. Without it the
        recipe (:mod:`pylensfit.calibration`) estimates them first, on a sample of the
        images (``Config.calibration_sample``). Kept in ``meta["priors"]``.
    output : str, optional
        Catalogue path (FITS); finished images are kept in ``<output>.parts/`` until it
        is written, and a restarted run resumes.
    psf_dir : str, optional
        Write each image's PSF here as ``<image stem>.psf.fits`` (a folder the dask
        workers share; :meth:`pylensfit.psf.PSFResult.write`, with a ``STARS`` table).
    overwrite, progress : bool
        Replace an existing output; show progress bars.
    jobs, scheduler : int, str, optional
        Local worker processes (one BLAS / numba thread each; 1: this process), or the
        address of a dask.distributed scheduler to run the images on instead.

    Returns
    -------
    astropy.table.Table
        The catalogue (:data:`pylensfit.catalogue.COLUMNS`; ``lnL`` the ``(n, n_e)``
        grids) with ``meta``: the ellipticity grid, the priors, the PSF diagnostics.

    Raises
    ------
    InputError
        A bad input file (missing, unreadable, truncated, empty, given twice; a star
        field without stars): one line naming it. Every input is opened first.
    """
    cfg = config if config is not None else Config()
    inp = _measure_inputs(images, stars, weights, masks, catalogues, psf, prior, size_prior,
                          priors, output, overwrite)  # fmt: skip
    # one set of workers for every pass; a failed run leaves no empty <output>.parts/
    with worker_pool(jobs, scheduler) as pool, parts_dropped_if_unused(inp.parts):
        workers = Workers(jobs=jobs, scheduler=scheduler, progress=progress, pool=pool)
        tasks = _image_tasks(inp, cfg, star_column, psf_dir, workers)
        results, priors = _measure_images(tasks, cfg, inp, workers)
    cat = assemble_results([results[i] for i in range(len(tasks))], cfg, priors)
    if inp.out is not None:
        write_catalogue(cat, inp.out, overwrite=overwrite)
        shutil.rmtree(inp.parts, ignore_errors=True)
    return cat


def calibrate_images(
    images: str | os.PathLike | Iterable[str | os.PathLike], *,
    stars: Iterable[str | os.PathLike] | None = None,
    weights: Iterable[str | os.PathLike | None] | None = None,
    masks: Iterable[str | os.PathLike | None] | None = None,
    catalogues: Iterable[str | os.PathLike | None] | None = None,
    star_column: str | None = None, config: Config | None = None,
    prior: Prior | str | os.PathLike | None = None,
    size_prior: SizePrior | str | os.PathLike | None = None,
    psf: PSFResult | PSFModel | np.ndarray | str | os.PathLike | Sequence | None = None,
    sample: int | None = None, seed: int | None = None, jobs: int = 1,
    scheduler: str | None = None, progress: bool = True,
) -> Priors:
    """Estimate every prior of the method once, on a sample of a survey's images.

    The calibration recipe (:mod:`pylensfit.calibration`) on whole images drawn at
    random until their objects reach ``sample`` (:mod:`pylensfit.images.sample`): each
    galaxy fitted as :func:`measure` fits it. ``Priors.save`` keeps the priors for
    ``measure(priors=...)`` (``pylensfit measure --priors``), which measures every image
    in one pass under them, with the same ``config``.

    Parameters
    ----------
    images, stars, weights, masks, catalogues, star_column, config, prior, size_prior, psf
        As for :func:`measure`.
    sample : int, optional
        Objects (detections, or input catalogue rows) of the images drawn; 0: every
        image. Default ``Config.calibration_sample`` (20,000).
    seed : int, optional
        Seed of the draw; default ``Config.calibration_seed``.
    jobs, scheduler, progress
        As for :func:`measure`.

    Returns
    -------
    Priors
        The priors; ``info["sample_images"]`` names the images of the sample.

    Raises
    ------
    InputError
        A missing or unreadable input: one line naming the file and the problem.
    """
    cfg = config if config is not None else Config()
    cfg = cfg.replace(**{k: v for k, v in (("calibration_sample", sample),
                                           ("calibration_seed", seed)) if v is not None})
    inp = _measure_inputs(images, stars, weights, masks, catalogues, psf, prior, size_prior,
                          None, None, False)  # fmt: skip
    with worker_pool(jobs, scheduler) as pool:
        workers = Workers(jobs=jobs, scheduler=scheduler, progress=progress, pool=pool)
        tasks = _image_tasks(inp, cfg, star_column, None, workers)
        return _calibrate(tasks, cfg, inp, workers, LastPass())


def _image_tasks(inp: _MeasureInputs, cfg: Config, star_column: str | None,
                 psf_dir: str | os.PathLike | None,
                 workers: Workers) -> list[ImageTask]:  # fmt: skip
    """The images' tasks, with the PSFs of the star fields (built first: they go to every
    image)."""
    if psf_dir is not None:
        Path(psf_dir).mkdir(parents=True, exist_ok=True)
    st_tasks = [StarfieldTask(path=p, index=i, config=cfg) for i, p in enumerate(inp.stars)]
    star_psfs = [res for _, res in workers.run(starfield_task, st_tasks, "star fields")]
    star_psfs.sort(key=lambda r: inp.stars.index(r.source))
    return [
        ImageTask(path=p, index=i, config=cfg, weight=w, mask=m, catalogue=c,
                  star_psfs=tuple(star_psfs), star_column=star_column,
                  psf_dir=None if psf_dir is None else str(psf_dir),
                  psf=None if inp.psfs is None else inp.psfs[i])
        for i, (p, w, m, c) in enumerate(zip(inp.images, inp.weights, inp.masks,
                                             inp.catalogues, strict=True))
    ]  # fmt: skip


def _calibrate(tasks: list[ImageTask], cfg: Config, inp: _MeasureInputs, workers: Workers,
               last: LastPass) -> Priors:  # fmt: skip
    """The recipe on the calibration sample of ``tasks``; the priors name its images."""
    sample = sample_tasks(tasks, cfg.calibration_sample, cfg.calibration_seed, workers)
    priors = calibration_passes(sample, cfg, inp.prior, inp.size_prior, workers, last,
                                inp.parts)  # fmt: skip
    return replace(priors, info={**priors.info, "sample_images": [t.path for t in sample],
                                 "images": len(tasks)})  # fmt: skip


def _measure_images(tasks: list[ImageTask], cfg: Config, inp: _MeasureInputs,
                    workers: Workers) -> tuple[dict[int, ImageResult], Priors]:  # fmt: skip
    """Every image measured under the given priors, those of an interrupted run, or those
    the recipe estimates on the calibration sample; the results by image and the priors."""
    pr_file = inp.parts / "priors.json" if inp.parts is not None else None
    last = LastPass()
    priors = inp.priors
    if priors is None and pr_file is not None and pr_file.exists():
        priors = Priors.load(pr_file)  # a resumed run keeps its priors
        log.info("priors of the interrupted run read from %s", pr_file)
    if priors is None:
        priors = _calibrate(tasks, cfg, inp, workers, last)
    results = measure_pass(tasks, cfg, priors, last, inp.parts, pr_file, workers)
    return results, priors


@dataclass
class _MeasureInputs:
    """:func:`measure`'s inputs, checked: paths as strings, one entry per image."""

    images: list[str]
    stars: list[str]
    weights: list
    masks: list
    catalogues: list
    psfs: list[PSFResult | PSFModel] | None  # given PSFs, one per image
    prior: Prior | None
    size_prior: SizePrior | None
    priors: Priors | None
    out: Path | None  # the catalogue
    parts: Path | None  # the finished images' folder, ``<output>.parts/``


def _measure_inputs(images, stars, weights, masks, catalogues, psf, prior, size_prior,
                    priors, output, overwrite: bool) -> _MeasureInputs:  # fmt: skip
    """Check :func:`measure`'s inputs (every file opened) before any work starts."""
    if isinstance(images, (str, os.PathLike)):
        images = [images]
    images = [str(p) for p in images]
    if not images:
        raise InputError("no input image")
    stars = [str(p) for p in (stars or [])]
    given_psfs = read_given_psfs(psf, images)
    if given_psfs is not None and stars:
        raise InputError("give the PSF (psf=) or star fields to build it from (stars=), not both")
    weights = as_list(weights, len(images), "weights")
    masks = as_list(masks, len(images), "masks")
    catalogues = as_list(catalogues, len(images), "catalogues")
    for p in [*images, *stars, *[q for q in (*weights, *masks, *catalogues) if q]]:
        if not Path(p).exists():
            raise InputError(f"{p}: file not found")
    check_inputs(images, weights, masks, stars)
    prior = load_given(prior, Prior, "prior")
    priors = load_given(priors, Priors, "priors")
    size_prior = load_given(size_prior, SizePrior, "size prior")
    out = Path(output) if output is not None else None
    if out is not None and out.exists() and not overwrite:
        raise FileExistsError(f"{out}: output exists (use overwrite to replace it)")
    parts = out.with_name(out.name + ".parts") if out is not None else None
    if out is not None:
        remove_stale_temporaries(out, parts)
    return _MeasureInputs(images=images, stars=stars, weights=weights, masks=masks,
                          catalogues=catalogues, psfs=given_psfs, prior=prior,
                          size_prior=size_prior, priors=priors, out=out, parts=parts)
