"""Resuming a run: the task keys, the part files and the temporaries."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.table import Table

from .._version import __version__
from ..catalogue import atomic_write
from ..config import Config
from ..prior import SizePrior
from .records import HELDOUT_KEYS, PSF_KEYS, ImageResult, ImageTask, PSFSummary

__all__ = [
    "part_path",
    "write_part",
    "remove_stale_temporaries",
    "parts_dropped_if_unused",
    "resumed_results",
    "pass_key",
]

# the pipeline's one logger: its name predates the split into modules
log = logging.getLogger("pylensfit.pipeline")


# ----------------------------------------------------------------------------------------
# Parts: one file per finished image, for restarts
# ----------------------------------------------------------------------------------------
def _task_key(task: ImageTask) -> str:
    """A digest of everything that determines an image's result."""
    stamp = []
    for k in ("path", "weight", "mask", "catalogue"):
        p = getattr(task, k)
        if p:
            st = Path(p).stat()
            stamp.append((k, os.path.abspath(p), st.st_size, st.st_mtime_ns))
    given = task.psf  # a given PSF (its image), else the star fields' PSFs
    psfs = [given] if given is not None else task.star_psfs
    sp = None if task.size_prior is None else task.size_prior.to_dict()
    key = [stamp, task.config.to_dict(), task.star_column, given is not None,
           [r.digest for r in psfs], sp, __version__]
    mp = task.metacal_priors  # the metacalibration's posterior means depend on them
    if mp is not None:
        key.append([mp.ellipticity.to_dict(), None if mp.bulge_weights is None
                    else [float(w) for w in mp.bulge_weights]])  # fmt: skip
    blob = json.dumps(key, sort_keys=True, default=str)
    return hashlib.sha1(blob.encode()).hexdigest()[:16]


def part_path(parts: Path, task: ImageTask) -> Path:
    return parts / f"{task.index:05d}_{Path(task.path).stem}_{_task_key(task)}.fits"


def write_part(path: Path, res: ImageResult) -> None:
    """One finished image as a part file, which :func:`_read_part` reads back as it was.

    The arrays go in HDUs of their own dtypes; the rest (index, path, PSF summary, PSF
    note, timing) as JSON in the one-row table ``INFO``: floats by ``repr`` and text of
    any length and characters, so that a resumed run writes the catalogue of a run never
    stopped (header cards round floats to 16 digits; the PSF HDU's are for reading).
    """
    t = Table(res.rows)
    psf = None if res.psf is None else {k: res.psf.numbers[k] for k in PSF_KEYS + HELDOUT_KEYS}
    info = {"index": int(res.index), "path": res.path, "psf": psf,
            "psf_note": res.psf_note, "psf_source": res.psf_source,
            "timing": res.timing}  # fmt: skip
    hdr = fits.Header()
    hdr["INDEX"] = int(res.index)
    hdus = [fits.PrimaryHDU(header=hdr), fits.table_to_hdu(t),
            fits.ImageHDU(res.lnL, name="LNL"),
            fits.ImageHDU(res.egrid, name="EGRID"),
            fits.BinTableHDU(Table({"json": [json.dumps(info)]}), name="INFO")]  # fmt: skip
    hdus[1].name = "ROWS"
    if res.lnL_bulge is not None:
        hdus.append(fits.ImageHDU(res.lnL_bulge, name="LNLB"))
    if res.psf is not None:
        ph = fits.ImageHDU(res.psf.image, name="PSF")
        for k in PSF_KEYS:
            ph.header[k.upper()[:8]] = res.psf.numbers[k]
        hdus.append(ph)
    atomic_write(fits.HDUList(hdus), path, overwrite=True)


def _read_part(path: Path) -> ImageResult:
    """An image's result from its part file (:func:`write_part`); a file without the
    ``INFO`` table (an older format) raises, and the image is redone."""
    with fits.open(path, memmap=False) as h:
        info = json.loads(str(h["INFO"].data["json"][0]))
        rows = Table(h["ROWS"].data)
        psf = None
        if info["psf"] is not None:
            psf = PSFSummary(numbers=dict(info["psf"]),
                             image=np.array(h["PSF"].data, dtype=float))  # fmt: skip
        return ImageResult(
            index=int(info["index"]), path=info["path"],
            rows={c: np.asarray(rows[c]) for c in rows.colnames},
            lnL=np.array(h["LNL"].data, dtype=np.float32),
            lnL_bulge=np.array(h["LNLB"].data, dtype=np.float32) if "LNLB" in h else None,
            egrid=np.array(h["EGRID"].data, dtype=float), psf=psf,
            psf_note=info["psf_note"], psf_source=info.get("psf_source", ""),
            timing=info["timing"])  # fmt: skip


def _is_temporary(p: Path, name: str | None = None) -> bool:
    """Whether ``p`` is a temporary of :func:`pylensfit.catalogue.atomic_write` (of the
    file ``name``, else of any file): ``.<name>.<8 characters>.tmp``."""
    stem = re.escape(name) if name is not None else r".+"
    return re.fullmatch(rf"\.{stem}\.[a-z0-9_]{{8}}\.tmp", p.name) is not None


def remove_stale_temporaries(out: Path, parts: Path) -> None:
    """Remove what writes of ``out`` and of its part files killed before they finished
    left behind (a write that finishes renames its temporary)."""
    stale = []
    if out.parent.is_dir():
        stale += [p for p in out.parent.iterdir() if _is_temporary(p, out.name)]
    if parts.is_dir():
        stale += [p for p in parts.iterdir() if _is_temporary(p)]
    for p in stale:
        log.info("%s: removing the temporary of a write that did not finish", p)
        p.unlink(missing_ok=True)


@contextmanager
def parts_dropped_if_unused(parts: Path | None) -> Iterator[None]:
    """A run's context: a run that fails (an error in its input or its work) leaves no
    ``parts`` behind; a run that is interrupted (``KeyboardInterrupt``, a signal) keeps
    them for a later run to resume from, unless they hold nothing to resume (no part
    file, no priors: at most temporaries)."""
    try:
        yield
    except Exception:
        if parts is not None and parts.is_dir():
            shutil.rmtree(parts, ignore_errors=True)
        raise
    except BaseException:
        if parts is not None and parts.is_dir() and all(_is_temporary(p)
                                                        for p in parts.iterdir()):
            shutil.rmtree(parts, ignore_errors=True)
        raise


def resumed_results(tasks: list[ImageTask], parts: Path | None, results: dict,
             ) -> list[ImageTask]:  # fmt: skip
    """The tasks still to do: those of ``tasks`` whose part file in ``parts`` is read into
    ``results`` are not (a damaged part is redone)."""
    if parts is None:
        return list(tasks)
    todo = []
    for t in tasks:
        pp = part_path(parts, t)
        if pp.exists():
            try:
                results[t.index] = _read_part(pp)
                log.info("%s: resumed from %s", t.path, pp)
                continue
            except Exception as err:  # a damaged part is redone
                log.warning("%s: unreadable part file %s (%s); redoing", t.path, pp, err)
        todo.append(t)
    return todo


def pass_key(cfg: Config, size_prior: SizePrior | None, keep) -> str:
    """What identifies a fitting pass over the images: its settings and size prior."""
    sp = None if size_prior is None else size_prior.to_dict()
    return json.dumps([cfg.to_dict(), sp, keep], sort_keys=True, default=str)
