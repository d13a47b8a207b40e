"""Where the command line's metacalibration differs from the model's sensitivity: the same
catalogues split by the galaxies' properties.

Reads a ``benchmarks/survey_cli.py --keep DIR --response metacal`` directory (the set's
``manifest.json`` and ``catK.fits``) and prints, over the PSFs given:

- m1 and c1 of each estimator fitted to the means of each shear's group of images (the
  field, its rotated twin and their noise twins), on the rows each selects and on the rows
  the model's cuts keep (``flags == 0``, weight > 0) for both, so that a difference of
  selection shows;
- the mean of ``g_hat - g`` over the groups at ``|g| <= 0.01`` (c's estimate where m's
  part is below 1e-4), with its error from the groups' scatter;
- the difference of the two estimates per galaxy (``e1_mcal / <R11> - e1 / <w sens1>``,
  on the rows both keep, over all shears: m's part and c's together) split by S/N, the
  stamp tier, the detected half-light radius, the sub-pixel phase and the sign of ``dx^2
  - dy^2`` (the fitted centre's offset from its stamp's centre).

Usage::

    python benchmarks/survey_cli.py --kind step1 --ngal 40000 --seed 11 --noise-twins \\
        --response metacal --estimator fixed-point metacal --keep DIR
    python benchmarks/studies/metacal_cli_split.py DIR --psfs 0,1,2,3,4
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import numpy as np


def _groups(cat, sample, fields, model_rows, mcal_rows):
    """Per shear index: (g1, the mean over its images of the metacalibration's g1 on
    ``mcal_rows`` (None: the rows its own selection keeps), of the model's on
    ``model_rows``)."""
    img = np.asarray(cat["image"]).astype(str)
    w = np.asarray(cat["weight"], float)
    e1 = np.asarray(cat["e1"], float)
    s1 = np.asarray(cat["sens1"], float)
    out = {}
    for f in fields:
        im = np.char.endswith(img, f["file"])
        a = im & model_rows
        model = np.sum(w[a] * e1[a]) / np.sum(w[a] * s1[a])
        mcal = sample.shear(im if mcal_rows is None else im & mcal_rows).g[0]
        out.setdefault(f["shear_index"], []).append((f["g1"], mcal, model))
    return np.array([np.mean(v, axis=0) for _, v in sorted(out.items())])


def _fit(q: np.ndarray) -> tuple[float, float]:
    """m and c of ``g_hat = (1 + m) g + c``."""
    A = np.column_stack([q[:, 0], np.ones(len(q))])
    (a, c), *_ = np.linalg.lstsq(A, q[:, 1], rcond=None)
    return a - 1.0, c


def main(argv: list[str] | None = None) -> int:
    import pylensfit as plf
    from pylensfit.shear import MetacalSample

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", type=Path)
    ap.add_argument("--psfs", default="0,1,2,3,4")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    man = json.loads((args.dir / "set" / "manifest.json").read_text())
    res, small, parts = {"own": [], "model's rows": []}, [], []
    for k in (int(v) for v in args.psfs.split(",")):
        cat = plf.read_catalogue(args.dir / f"cat{k}.fits")
        sample = MetacalSample.of(cat)
        fields = [f for f in man["fields"] if f["role"] == "shear" and f["psf"] == k]
        model_rows = (np.asarray(cat["flags"]) == 0) & (np.asarray(cat["weight"]) > 0)
        for name, rows in (("own", None), ("model's rows", model_rows)):
            q = _groups(cat, sample, fields, model_rows, rows)
            if rows is None:
                small.append(q[q[:, 0] <= 0.01])
            res[name].append((*_fit(q[:, [0, 1]]), *_fit(q[:, [0, 2]])))
        both = model_rows & sample.selections["noshear"] & np.isfinite(sample.R).all(axis=(1, 2))
        w = np.asarray(cat["weight"], float)
        d = (sample.e[both, 0] / sample.R[both, 0, 0].mean()
             - np.asarray(cat["e1"], float)[both] * w[both].sum()
             / np.sum(w[both] * np.asarray(cat["sens1"], float)[both]))  # fmt: skip
        x, y = np.asarray(cat["x"], float)[both], np.asarray(cat["y"], float)[both]
        dx = x - np.floor(np.asarray(cat["x_detect"], float)[both] + 0.5)
        dy = y - np.floor(np.asarray(cat["y_detect"], float)[both] + 0.5)
        parts.append(dict(d=d, snr=np.asarray(cat["model_SNratio"], float)[both],
                          tier=np.asarray(cat["stamp_size"])[both],
                          rh=np.asarray(cat["r_half"], float)[both], fx=x % 1.0,
                          q=dx * dx - dy * dy))  # fmt: skip
    for name, v in res.items():
        v = np.array(v)
        print(f"{name:13s} metacal m1 {v[:, 0].mean():+.4f} c1 {v[:, 1].mean():+.5f}   "
              f"model m1 {v[:, 2].mean():+.4f} c1 {v[:, 3].mean():+.5f}   "
              f"(per PSF c1: metacal {np.round(v[:, 1], 4)}, model {np.round(v[:, 3], 4)})")
    sm = np.concatenate(small)
    for j, name in ((1, "metacal"), (2, "model")):
        r = sm[:, j] - sm[:, 0]
        print(f"g <= 0.01, mean g_hat - g: {name} {r.mean():+.5f} ± "
              f"{r.std(ddof=1) / np.sqrt(r.size):.5f} ({r.size} groups)")
    P = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    q3 = np.nanpercentile(P["rh"], [33.3, 66.7])
    splits = [(f"S/N {a:g}-{b:g}", (P["snr"] >= a) & (P["snr"] < b))
              for a, b in ((0, 25), (25, 50), (50, np.inf))]  # fmt: skip
    splits += [(f"tier {t}", P["tier"] == t) for t in np.unique(P["tier"])]
    splits += [("r_half small", P["rh"] < q3[0]), ("r_half large", P["rh"] >= q3[1]),
               ("x phase < 0.5", P["fx"] < 0.5), ("x phase >= 0.5", P["fx"] >= 0.5),
               ("dx^2 > dy^2", P["q"] > 0), ("dx^2 < dy^2", P["q"] < 0)]  # fmt: skip
    print("metacal - model per galaxy (m's part and c's):")
    for name, sel in splits:
        d = P["d"][sel]
        print(f"  {name:16s} {d.mean():+.5f} ± {d.std(ddof=1) / np.sqrt(d.size):.5f} "
              f"({d.size} galaxies)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
