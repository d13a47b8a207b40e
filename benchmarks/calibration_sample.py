"""m and c against the size of the calibration sample: calibrate once, measure in one pass.

On a STEP1-like set (``pylensfit simulate step1``, with 90-degree rotated twins and noise
twins, so that the shape noise and the noise's first-order effect cancel in the group
means), this measures the shear fields of the PSFs chosen three ways per sample size::

    pylensfit calibrate psfK_g*.fits --stars psfK_stars.fits --sample N -o priorsN.json
    pylensfit measure psfK_g*.fits --stars psfK_stars.fits --priors priorsN.json -o catN.fits
    pylensfit shear catN.fits -o shearN.ecsv

beside the full recipe on every image (``pylensfit measure`` with
``calibration_sample: 0``), and fits ``g_meas = (1 + m) g + c`` per component to the
per-image shears, as ``benchmarks/survey_cli.py`` does. The same images and noise are
measured every way, so ``dm``, the fit of the difference of the group means from the
full recipe's, is the priors' own effect, with an error far below that of ``m``::

    python benchmarks/calibration_sample.py --ngal 12000 --nshear 8 --sizes 250,1000 \\
        --draws 3 --psfs 0 --jobs 2

``--draws K`` draws each sample K times (seeds ``--seed`` to ``--seed + K - 1``): the
scatter of ``dm`` over the draws is the priors' noise at that size.

``--keep DIR`` keeps the set, the priors and the catalogues (a rerun reuses them).
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


def _cli(*args: str) -> float:
    """Run ``pylensfit ARGS``; its wall time (s)."""
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "pylensfit.cli", *args], capture_output=True,
                         text=True)  # fmt: skip
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(args[:2])} failed:\n{res.stdout}\n{res.stderr}")
    return time.perf_counter() - t0


def _group_means(cat: Path, out: Path, fields: list[dict]) -> np.ndarray:
    """``(n_shears, 4)``: true ``g1, g2`` and measured ``g1, g2``, each the mean over the
    shear's images (its twins)."""
    out.unlink(missing_ok=True)
    _cli("shear", str(cat), "-o", str(out))
    tab = Table.read(out)
    per = {str(g).split("=", 1)[1]: r for g, r in zip(tab["group"], tab, strict=True)
           if "=" in str(g)}  # fmt: skip
    by: dict[int, list] = {}
    for f in fields:
        r = per[Path(f["file"]).name]
        by.setdefault(f["shear_index"], []).append((f["g1"], f["g2"], r["g1"], r["g2"]))
    return np.array([np.mean(v, axis=0) for _, v in sorted(by.items())])


def _fit(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float, float]:
    """``y = (1 + m) x + c`` (``m`` of ``y = m x + c`` where ``x`` is already taken off):
    ``m, m_err, c, c_err`` with the errors from the residuals."""
    a = np.column_stack([x, np.ones_like(x)])
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    r = y - a @ coef
    s2 = float(r @ r) / max(len(y) - 2, 1)
    err = np.sqrt(np.diag(s2 * np.linalg.inv(a.T @ a)))
    return float(coef[0]), float(err[0]), float(coef[1]), float(err[1])


def _measure_all(args, sim: Path, work: Path, fields: dict,
                 ways: list[tuple[str, int | None, int]]) -> dict:
    """Each way's catalogue per PSF, and its times: ``{label: {"cats": [...], ...}}``."""
    cfg0 = work / "every_image.yaml"
    cfg0.write_text("priors:\n  calibration_sample: 0\n")
    runs: dict[str, dict] = {}
    for label, size, seed in ways:
        run = runs[label] = {"cats": [], "t_cal": 0.0, "t_meas": 0.0, "n_gal": 0}
        for k, fs in fields.items():
            imgs = [str(sim / f["file"]) for f in fs]
            common = ["--stars", str(sim / f"psf{k}_stars.fits"), "--jobs", str(args.jobs), "-q"]
            tag = "full" if size is None else f"n{size}_s{seed}"
            cat = work / f"cat{k}_{tag}.fits"
            if size is None and not cat.exists():
                run["t_meas"] += _cli("measure", *imgs, *common, "--config", str(cfg0),
                                      "-o", str(cat))  # fmt: skip
            elif size is not None and not cat.exists():
                pri = work / f"priors{k}_{tag}.json"
                pri.unlink(missing_ok=True)
                run["t_cal"] += _cli("calibrate", *imgs, *common, "--sample", str(size),
                                     "--seed", str(seed), "-o", str(pri))  # fmt: skip
                run["t_meas"] += _cli("measure", *imgs, *common, "--priors", str(pri),
                                      "-o", str(cat))  # fmt: skip
            c = Table.read(cat, hdu="CATALOG")
            run["n_gal"] += int(np.sum((np.asarray(c["flags"]) == 0)
                                       & (np.asarray(c["weight"]) > 0)))  # fmt: skip
            run["cats"].append((k, cat))
    return runs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ngal", type=int, default=10000, help="galaxies over the shear fields "
                    "of all five PSFs")  # fmt: skip
    ap.add_argument("--nshear", type=int, default=4, help="shear values per PSF")
    ap.add_argument("--sizes", default="250,1000", help="calibration sample sizes (objects)")
    ap.add_argument("--psfs", default="0", help="comma-separated PSF indices measured")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--draws", type=int, default=1, help="draws of each sample size")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--keep", default=None, help="keep the set, priors and catalogues here")
    args = ap.parse_args(argv)
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="plf-calsample-"))
    work.mkdir(parents=True, exist_ok=True)
    sim = work / "set"
    if not (sim / "manifest.json").exists():
        _cli("simulate", "step1", "--out", str(sim), "--ngal", str(args.ngal), "--seed",
             str(args.seed), "--nshear", str(args.nshear), "--twins", "--noise-twins",
             "--jobs", str(args.jobs), "--quiet")  # fmt: skip
    man = json.loads((sim / "manifest.json").read_text())
    psfs = [int(v) for v in args.psfs.split(",")]
    shear = [f for f in man["fields"] if f["role"] == "shear"]
    fields = {k: [f for f in shear if f["psf"] == k] for k in psfs}
    sizes = [int(v) for v in args.sizes.split(",")]
    print(f"step1: {sum(len(v) for v in fields.values())} shear fields of "
          f"{man['field_size']} px (PSFs {args.psfs}), calibration samples {sizes} objects")
    ways = [("full recipe", None, 0)] + [(f"sample {n} #{d + 1}", n, args.seed + d)
                                         for n in sizes for d in range(args.draws)]
    runs = _measure_all(args, sim, work, fields, ways)
    means = {label: np.concatenate([_group_means(cat, work / f"shear_{cat.stem}.ecsv",
                                                 fields[k]) for k, cat in run["cats"]])
             for label, run in runs.items()}  # fmt: skip
    full = means["full recipe"]
    print(f"{'calibration':<16} {'m1':>18} {'c1':>20} {'dm1 vs full':>18} {'c2':>20}  "
          f"{'cal s':>6} {'meas s':>6} {'gal/s':>6}")
    for label, g in means.items():
        m1, m1e, c1, c1e = _fit(g[:, 0], g[:, 2] - g[:, 0])
        c2, c2e = float(np.mean(g[:, 3])), float(np.std(g[:, 3]) / np.sqrt(len(g)))
        dm = _fit(g[:, 0], g[:, 2] - full[:, 2]) if label != "full recipe" else None
        run = runs[label]
        t_all = run["t_cal"] + run["t_meas"]
        print(f"{label:<16} {m1:+.4f} +- {m1e:.4f}  {c1:+.5f} +- {c1e:.5f}  "
              + (f"{dm[0]:+.4f} +- {dm[1]:.4f}" if dm else f"{'':>16}")
              + f"  {c2:+.5f} +- {c2e:.5f}  {run['t_cal']:6.0f} {run['t_meas']:6.0f} "
              f"{run['n_gal'] / t_all if t_all > 0 else np.nan:6.1f}", flush=True)  # fmt: skip
    print(f"(errors from the fits' residuals over {len(full)} group means; gal/s: usable "
          f"galaxies over calibration and measurement, --jobs {args.jobs})")
    for n in sizes:
        dms = [_fit(g[:, 0], g[:, 2] - full[:, 2])[0] for label, g in means.items()
               if label.startswith(f"sample {n} #")]  # fmt: skip
        print(f"sample {n}: dm1 over {len(dms)} draws {np.mean(dms):+.4f}, scatter "
              f"{np.std(dms, ddof=1) if len(dms) > 1 else np.nan:.4f}")
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
