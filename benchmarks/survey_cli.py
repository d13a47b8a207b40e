"""m and c through the command line, as a survey runs it: every usable detection counted.

For each PSF of a STEP1- or STEP2-like set (``pylensfit simulate``, with 90-degree
rotated twins so that the intrinsic shapes cancel pair by pair), this runs::

    pylensfit measure psfK_g*.fits --stars psfK_stars.fits -o catK.fits
    pylensfit shear catK.fits -o shearK.ecsv

with no configuration (``Config()``: the priors estimated from the run's own galaxies,
the star field stacked for the PSF, detection by sep), and fits ``g_meas = (1 + m) g +
c`` per component to the per-image shears of ``pylensfit shear``. Nothing is matched to
the truth: every row the catalogue calls usable is in the shear, as in a survey. The
group means (field and rotated twin, and with ``--noise-twins`` both with the noise
negated) carry no shape noise and no first-order noise; the errors of m and c come from
the residuals of the fits to the group means, pooled over the PSFs and components, so
they are the measurement's own scatter::

    python benchmarks/survey_cli.py --kind step1 --ngal 40000 --seed 11 --noise-twins
    python benchmarks/survey_cli.py --kind step2 --ngal 40000 --seed 12 --noise-twins

Each takes about half an hour on 2 cores (``--jobs 2``).

``--keep DIR`` keeps the simulated set and the catalogues; ``--psfs 0,3`` measures only
those PSFs; ``--config FILE`` passes a YAML configuration to ``pylensfit measure``.
``--response metacal`` measures each galaxy's response on itself too, and ``--estimator
fixed-point metacal`` reports each estimator on the same catalogues (the metacalibration's
with the selection response of ``shear``'s cuts)::

    python benchmarks/survey_cli.py --kind step1 --ngal 8000 --seed 11 --noise-twins \
        --response metacal --estimator fixed-point metacal

``--priors-of DIR`` measures each PSF under the priors of an earlier ``--keep DIR`` run's
catalogue (``measure --priors``: one pass, which reproduces that run's catalogue to the
last bit on the same images), so that two sets of the same galaxies are compared under
the same priors; ``--paired-with DIR`` prints this run's m and c less that run's, image by
image (the noise and the galaxies' shapes cancel in the differences).

``--shear-positions`` shears the galaxies' positions with their shapes (the lensed sky):
metacalibration shears the neighbours' light in its stamps too, and on fields whose
lattice stays put at every shear it measures a response the fields do not have.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from astropy.table import Table

from pylensfit import read_catalogue


def _cli(*args: str) -> None:
    cmd = [sys.executable, "-m", "pylensfit.cli", *args]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(args[:2])} failed:\n{res.stdout}\n{res.stderr}")


def _shear_table(work: Path, k: int, estimator: str, run: bool = True) -> dict:
    """``pylensfit shear --estimator ESTIMATOR``'s per-image shears of ``work/catK.fits``
    (run unless ``run`` is false and the table is kept), by image file."""
    out = work / f"shear{k}_{estimator}.ecsv"
    if run or not out.exists():
        out.unlink(missing_ok=True)
        _cli("shear", str(work / f"cat{k}.fits"), "-o", str(out), "--estimator", estimator)
    tab = Table.read(out)
    return {str(g).split("=", 1)[1]: r for g, r in zip(tab["group"], tab, strict=True)
            if "=" in str(g)}  # fmt: skip


def _group_means(fields: list, per: dict, base: dict | None = None) -> np.ndarray:
    """``(g1, g2, g1_meas, g2_meas)`` averaged over each shear's images; with ``base``
    (another run's ``per`` of the same images) the measured shear is ``g + (this run's -
    base's)``, so that the fit's m and c are the paired differences."""
    by = {}
    for f in fields:
        r = per[f["file"]]
        d = (r["g1"], r["g2"]) if base is None else (
            f["g1"] + r["g1"] - base[f["file"]]["g1"], f["g2"] + r["g2"] - base[f["file"]]["g2"])
        by.setdefault(f["shear_index"], []).append((f["g1"], f["g2"], *d))
    return np.array([np.mean(v, axis=0) for _, v in sorted(by.items())])


def _usable(work: Path, k: int, estimator: str) -> tuple[int, int]:
    """The usable rows of ``work/catK.fits`` under ``estimator`` and all its rows."""
    c = Table.read(work / f"cat{k}.fits", hdu="CATALOG")
    usable = (np.asarray(c["flags"]) == 0) & (np.asarray(c["weight"]) > 0)
    if estimator == "metacal":
        usable = np.asarray(c["mcal_flags"]) == 0
    return int(usable.sum()), len(c)


def _report(work: Path, man: dict, shear_fields: list, psfs: list, estimator: str,
            paired: Path | None = None) -> None:  # fmt: skip
    """Fit ``g_meas = (1 + m) g + c`` per PSF and component to the group means of
    ``pylensfit shear --estimator ESTIMATOR``'s per-image shears of each catalogue; with
    ``paired`` (an earlier ``--keep`` run of the same images' galaxies) the paired
    differences ``dm, dc`` of this run less that one."""
    groups = []
    for k in psfs:
        fields = [f for f in shear_fields if f["psf"] == k]
        per = _shear_table(work, k, estimator, run=paired is None)
        base = None if paired is None else _shear_table(paired, k, estimator, run=False)
        groups.append((k, *_usable(work, k, estimator), _group_means(fields, per, base)))
    _print_fits(man, groups, "d" if paired is not None else "")


def _print_fits(man: dict, groups: list, d: str) -> None:
    """The fits of :func:`_report`, each PSF and component on its own; the residuals'
    variance pooled over all of them (the groups' noise is alike), so that a fit of 4-5
    points gets a stable error. ``d`` prefixes the names (paired differences)."""
    fits, resid = [], []
    for k, n_use, n_rows, pairs in groups:
        row = {"psf": k, "n": n_use, "rows": n_rows}
        for i in (0, 1):
            x, y = pairs[:, i], pairs[:, 2 + i]
            a = np.column_stack([x, np.ones_like(x)]) if np.ptp(x) > 0 else np.ones((len(x), 1))
            coef, *_ = np.linalg.lstsq(a, y, rcond=None)
            resid.append(y - a @ coef)
            row[f"a{i}"], row[f"coef{i}"] = a, coef
        fits.append(row)
    r_all = np.concatenate(resid)
    dof = r_all.size - sum(row[f"coef{i}"].size for row in fits for i in (0, 1))
    s2 = float(r_all @ r_all) / max(dof, 1)
    out_rows = []
    for row in fits:
        vals = {}
        for i in (0, 1):
            coef, a = row[f"coef{i}"], row[f"a{i}"]
            err = np.sqrt(np.diag(s2 * np.linalg.inv(a.T @ a)))
            if coef.size == 2:
                vals[f"m{i + 1}"], vals[f"c{i + 1}"] = (coef[0] - 1.0, err[0]), (coef[1], err[1])
            else:  # STEP1's g2 = 0 everywhere: c2 alone
                vals[f"m{i + 1}"], vals[f"c{i + 1}"] = (np.nan, np.nan), (coef[0], err[0])
        out_rows.append(vals)
        p = man["psfs"][row["psf"]]
        print(f"PSF {row['psf']} (fwhm {p['fwhm']}, beta {p['beta']}, e {p['e1']:+.2f},"
              f"{p['e2']:+.2f}): {row['n']} usable rows of {row['rows']}; "
              + "  ".join(f"{d}{q} {vals[q][0]:+.4f} +- {vals[q][1]:.4f}" for q in ("m1", "m2"))
              + "  " + "  ".join(f"{d}{q} {vals[q][0]:+.5f} +- {vals[q][1]:.5f}"
                                 for q in ("c1", "c2")), flush=True)  # fmt: skip
    print(f"(errors from the fits' residuals pooled over PSFs and components: {dof} degrees "
          f"of freedom, rms {np.sqrt(s2):.5f} per group mean)")  # fmt: skip
    for q in ("m1", "m2", "c1", "c2"):
        v = np.array([r[q][0] for r in out_rows])
        e = np.array([r[q][1] for r in out_rows])
        ok = np.isfinite(v)
        if ok.any():
            err = np.sqrt(np.sum(e[ok] ** 2)) / ok.sum()
            print(f"<{d}{q}> over PSFs {np.mean(v[ok]):+.5f} +- {err:.5f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kind", choices=["step1", "step2"], default="step1")
    ap.add_argument("--ngal", type=int, default=40000, help="galaxies over the shear fields")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--psfs", default=None, help="comma-separated PSF indices (default all)")
    ap.add_argument("--nshear", type=int, default=None, help="shear values per PSF")
    ap.add_argument("--noise-twins", action="store_true",
                    help="a noise twin of every field (the noise negated): the noise's first-order "
                         "effect cancels in the pair means too; --ngal counts the renderings")
    ap.add_argument("--shear-positions", action="store_true",
                    help="simulate --shear-positions: the galaxies' positions sheared too")
    ap.add_argument("--priors-of", default=None, metavar="DIR",
                    help="measure each PSF K under the priors of DIR/catK.fits (an earlier "
                         "--keep DIR run of the same kind): one pass, paired with that run")
    ap.add_argument("--paired-with", default=None, metavar="DIR",
                    help="also print m and c of this run less those of DIR (an earlier --keep "
                         "run of the same galaxies, with the same --estimator), paired image "
                         "by image")
    ap.add_argument("--config", default=None, help="YAML configuration for measure")
    ap.add_argument("--keep", default=None, help="keep the set and catalogues here")
    ap.add_argument("--response", choices=("model", "metacal"), default=None,
                    help="measure --response (default: the configuration's)")
    ap.add_argument("--estimator", nargs="+", default=["fixed-point"],
                    choices=("fixed-point", "key2", "metacal"),
                    help="shear --estimator, each on the same catalogues")
    args = ap.parse_args(argv)

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="plf-survey-"))
    work.mkdir(parents=True, exist_ok=True)
    sim = work / "set"
    t0 = time.perf_counter()
    if not (sim / "manifest.json").exists():
        extra = ["--nshear", str(args.nshear)] if args.nshear else []
        extra += ["--noise-twins"] if args.noise_twins else []
        extra += ["--shear-positions"] if args.shear_positions else []
        _cli("simulate", args.kind, "--out", str(sim), "--ngal", str(args.ngal), "--seed",
             str(args.seed), "--twins", "--jobs", str(args.jobs), "--quiet", *extra)  # fmt: skip
    man = json.loads((sim / "manifest.json").read_text())
    t_sim = time.perf_counter() - t0
    shear_fields = [f for f in man["fields"] if f["role"] == "shear"]
    psfs = sorted({f["psf"] for f in shear_fields})
    if args.psfs:
        psfs = [int(v) for v in args.psfs.split(",")]
    print(f"{args.kind}: {man['ngal_shear_fields']} galaxies in {len(shear_fields)} shear "
          f"fields of {man['field_size']} px, {len(man['psfs'])} PSFs; simulated in "
          f"{t_sim:.0f} s")  # fmt: skip
    n_meas, t_meas = 0, 0.0
    for k in psfs:
        fields = [f for f in shear_fields if f["psf"] == k]
        cat = work / f"cat{k}.fits"
        t1 = time.perf_counter()
        if not cat.exists():
            cfg = ["--config", args.config] if args.config else []
            cfg += ["--response", args.response] if args.response else []
            if args.priors_of:
                pri = work / f"priors{k}.json"
                read_catalogue(Path(args.priors_of) / f"cat{k}.fits").meta["priors"].save(pri)
                cfg += ["--priors", str(pri)]
            _cli("measure", *[str(sim / f["file"]) for f in fields], "--stars",
                 str(sim / f"psf{k}_stars.fits"), "-o", str(cat), "--jobs", str(args.jobs),
                 "-q", *cfg)  # fmt: skip
        t_meas += time.perf_counter() - t1
        c = Table.read(cat, hdu="CATALOG")
        n_meas += int(((np.asarray(c["flags"]) == 0) & (np.asarray(c["weight"]) > 0)).sum())
    for estimator in args.estimator:
        print(f"--estimator {estimator}:")
        _report(work, man, shear_fields, psfs, estimator)
        if args.paired_with:
            print(f"--estimator {estimator}, this run less {args.paired_with}, paired:")
            _report(work, man, shear_fields, psfs, estimator, Path(args.paired_with))
    if t_meas > 1.0:  # not when every catalogue was kept from an earlier run
        print(f"measured {n_meas} usable rows in {t_meas:.0f} s ({n_meas / t_meas:.1f} "
              f"galaxies/s, FITS to catalogue, --jobs {args.jobs})")  # fmt: skip
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
