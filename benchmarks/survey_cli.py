"""m and c through the command line, as a survey runs it: every usable detection counted.

For each PSF of a STEP1- or STEP2-like set (``pylensfit simulate``, with 90-degree
rotated twins so that the intrinsic shapes cancel pair by pair), this runs::

    pylensfit measure psfK_g*.fits --stars psfK_stars.fits -o catK.fits
    pylensfit shear catK.fits -o shearK.ecsv

with no configuration (``Config()``: the priors estimated from the run's own galaxies,
the star field stacked for the PSF, detection by sep), and fits ``g_meas = (1 + m) g +
c`` per component to the per-image shears of ``pylensfit shear``. Nothing is matched to
the truth: every row the catalogue calls usable is in the shear, as in a survey. The
pair means (field and rotated twin) carry no shape noise; the error of m and c comes
from the residuals of the fit (pair means), so it is the measurement's own scatter::

    python benchmarks/survey_cli.py --kind step1 --ngal 40000 --seed 1 --jobs 2
    python benchmarks/survey_cli.py --kind step2 --ngal 40000 --seed 2 --jobs 2

``--keep DIR`` keeps the simulated set and the catalogues; ``--psfs 0,3`` measures only
those PSFs; ``--config FILE`` passes a YAML configuration to ``pylensfit measure``.
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


def _cli(*args: str) -> None:
    cmd = [sys.executable, "-m", "pylensfit.cli", *args]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(args[:2])} failed:\n{res.stdout}\n{res.stderr}")


def _fit(g_true: np.ndarray, g_meas: np.ndarray) -> tuple[float, float, float, float]:
    """Least-squares ``g_meas = (1 + m) g_true + c``; errors from the residuals."""
    a = np.column_stack([g_true, np.ones_like(g_true)])
    coef, *_ = np.linalg.lstsq(a, g_meas, rcond=None)
    resid = g_meas - a @ coef
    dof = max(len(g_meas) - 2, 1)
    s2 = float(resid @ resid) / dof
    cov = s2 * np.linalg.inv(a.T @ a)
    err = np.sqrt(np.diag(cov))
    return float(coef[0] - 1.0), float(err[0]), float(coef[1]), float(err[1])


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
    ap.add_argument("--config", default=None, help="YAML configuration for measure")
    ap.add_argument("--keep", default=None, help="keep the set and catalogues here")
    args = ap.parse_args(argv)

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="plf-survey-"))
    work.mkdir(parents=True, exist_ok=True)
    sim = work / "set"
    t0 = time.perf_counter()
    if not (sim / "manifest.json").exists():
        extra = ["--nshear", str(args.nshear)] if args.nshear else []
        extra += ["--noise-twins"] if args.noise_twins else []
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
    rows = []
    n_meas = 0
    t_meas = 0.0
    for k in psfs:
        fields = [f for f in shear_fields if f["psf"] == k]
        cat = work / f"cat{k}.fits"
        t1 = time.perf_counter()
        if not cat.exists():
            cfg = ["--config", args.config] if args.config else []
            _cli("measure", *[str(sim / f["file"]) for f in fields], "--stars",
                 str(sim / f"psf{k}_stars.fits"), "-o", str(cat), "--jobs", str(args.jobs),
                 "-q", *cfg)  # fmt: skip
        t_meas += time.perf_counter() - t1
        out = work / f"shear{k}.ecsv"
        out.unlink(missing_ok=True)
        _cli("shear", str(cat), "-o", str(out))
        tab = Table.read(out)
        c = Table.read(cat)
        usable = (np.asarray(c["flags"]) == 0) & (np.asarray(c["weight"]) > 0)
        n_meas += int(usable.sum())
        per = {str(g).split("=", 1)[1]: r
               for g, r in zip(tab["group"], tab, strict=True) if "=" in str(g)}
        by = {}
        for f in fields:
            r = per[f["file"]]
            by.setdefault(f["shear_index"], []).append((f["g1"], f["g2"], r["g1"], r["g2"]))
        pairs = np.array([np.mean(v, axis=0) for _, v in sorted(by.items())])
        m1, sm1, c1, sc1 = _fit(pairs[:, 0], pairs[:, 2])
        if np.ptp(pairs[:, 1]) > 0:
            m2, sm2, c2, sc2 = _fit(pairs[:, 1], pairs[:, 3])
        else:  # STEP1: g2 = 0 everywhere; c2 is the mean
            m2, sm2 = np.nan, np.nan
            c2 = float(np.mean(pairs[:, 3]))
            sc2 = float(np.std(pairs[:, 3], ddof=1) / np.sqrt(len(pairs)))
        p = man["psfs"][k]
        rows.append((k, int(usable.sum()), m1, sm1, m2, sm2, c1, sc1, c2, sc2))
        print(f"PSF {k} (fwhm {p['fwhm']}, beta {p['beta']}, e {p['e1']:+.2f},{p['e2']:+.2f}): "
              f"{int(usable.sum())} usable rows of {len(c)}; m1 {m1:+.4f} +- {sm1:.4f}  "
              f"m2 {m2:+.4f} +- {sm2:.4f}  c1 {c1:+.5f} +- {sc1:.5f}  c2 {c2:+.5f} +- {sc2:.5f}",
              flush=True)  # fmt: skip
    r = np.array(rows, dtype=float)
    for name, col in (("m1", 2), ("m2", 4)):
        v, s = r[:, col], r[:, col + 1]
        ok = np.isfinite(v)
        if ok.any():
            print(f"<{name}> over PSFs {np.mean(v[ok]):+.4f} +- "
                  f"{np.sqrt(np.sum(s[ok] ** 2)) / ok.sum():.4f}")  # fmt: skip
    print(f"measured {n_meas} usable rows in {t_meas:.0f} s ({n_meas / max(t_meas, 1e-9):.1f} "
          f"galaxies/s, FITS to catalogue, --jobs {args.jobs})")  # fmt: skip
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
