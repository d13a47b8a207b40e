"""The change of m between two `pylensfit validate` runs of one set, paired image by image.

Two configurations measured on the same STEP-like set see the same galaxies and the same
noise, so most of each run's error (0.006 on <m> for 100,000 STEP2 galaxies) cancels in
their difference. This reads both runs' kept catalogues (``DIR/measured``; run
``pylensfit validate`` on each first: two directories holding the same fields, e.g. one
of symbolic links, since a run with another configuration measures again over the
first), prints m and c of each per PSF, and fits each image's (or twin pair's) change of
shear estimate against its true shear,

    g_B - g_A = dm g_true + dc,

per component, over all PSFs and per PSF, the error from the residuals::

    python benchmarks/studies/validate_paired.py /tmp/runs/step2 - /tmp/runs/step2b five.yaml

(``-``: `validate`'s default configuration).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    import pylensfit_validation.validate as V
    from pylensfit import pipeline
    from pylensfit.config import Config

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dir_a")
    ap.add_argument("config_a", help="YAML of run A ('-': validate's default)")
    ap.add_argument("dir_b")
    ap.add_argument("config_b", help="YAML of run B ('-': validate's default)")
    a = ap.parse_args(argv)

    def kept(name, sel, star, cfg, mdir, **kw):  # the runs' catalogues, never measured again
        path = Path(mdir) / f"{name}.fits"
        if not path.exists():
            raise SystemExit(f"{path}: no catalogue; run `pylensfit validate` on it first")
        return pipeline.read_catalogue(path), True

    V.measured_catalogues = kept  # validate's name for the kept catalogues
    runs = [V.validate(d, config=Config.from_yaml(y) if y != "-" else None, progress=False)
            for d, y in ((a.dir_a, a.config_a), (a.dir_b, a.config_b))]  # fmt: skip
    for name, r in zip("AB", runs, strict=True):
        print(f"{name}: <m> {r.meta['mean_m']:+.4f} ± {r.meta['mean_m_err']:.4f}, "
              f"sigma_c {r.meta['sigma_c']:.2e}")  # fmt: skip
        for row in r:
            print(f"   psf {row['psf']!s:4s} m1 {row['m1']:+.4f} ± {row['m1_err']:.4f}  "
                  f"m2 {row['m2']:+.4f} ± {row['m2_err']:.4f}")  # fmt: skip
    ea, eb = (r.meta["estimates"] for r in runs)
    where = {f: i for i, f in enumerate(eb["file"])}
    eb = eb[np.array([where[f] for f in ea["file"]])]
    print("B - A: g_B - g_A = dm g_true + dc per component, error from the residuals")
    for psf in [None, *sorted(set(ea["psf"]))]:
        sel = np.ones(len(ea), bool) if psf is None else np.asarray(ea["psf"]) == psf
        out = []
        for c in "12":
            g = np.asarray(ea[f"g{c}_true"], float)[sel]
            d = (np.asarray(eb[f"g{c}"], float) - np.asarray(ea[f"g{c}"], float))[sel]
            X = np.column_stack([g, np.ones_like(g)])
            coef = np.linalg.lstsq(X, d, rcond=None)[0]
            s2 = float(np.sum((d - X @ coef) ** 2)) / max(len(g) - 2, 1)
            err = np.sqrt(s2 * np.linalg.inv(X.T @ X)[0, 0])
            out.append(f"dm{c} {coef[0]:+.4f} ± {err:.4f}  dc{c} {coef[1]:+.5f}")
        print(f"{'all' if psf is None else f'psf {psf}':6s} " + " | ".join(out)
              + f"  ({int(sel.sum())} estimates)")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
