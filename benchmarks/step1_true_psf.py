"""The PSF model's part in a STEP1 set's m and c: the same galaxies, stacked and true PSF.

For a STEP1 set simulated with `--twins --noise-twins` and measured twice, by
`pylensfit validate DIR` (the PSF stacked from the stars, catalogues in DIR/measured) and by
`pylensfit validate DIR --true-psf` (each PSF's true image, DIR/measured_true_psf), every
galaxy's four renderings (image, rotated twin and their noise twins) are matched to the
truth by position in both runs, and only the galaxies measured in all eight catalogue
rows are kept. Per PSF and run: g1 per shear field = sum(w e1) / sum(w s1), a straight line
through the fields' (g1_true, g1) for m1 and c1, and c2 = sum(w e2) / sum(w s2) over all
fields (STEP1 shears along g1 only). The difference of the two runs is taken on the same
galaxies and noise, and its error (as every error here) by jackknife over 25 blocks of
galaxies, so it is far smaller than either run's error. The catalogue's e are those of
the pipeline's default prior in both runs (validate's own prior per PSF differs; so the
values here differ from the reports' by their noise).

::

    python benchmarks/step1_true_psf.py DIR

(1 minute.)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from astropy.io import fits
from scipy.spatial import cKDTree

MEMBERS = ("", "_neg", "_rot", "_rot_neg")
RUNS = ("measured", "measured_true_psf")
N_BLOCKS = 25


def sums(d: Path, run: str, k: int, files: list[str]) -> dict[str, np.ndarray]:
    """Per shear field and truth galaxy: sum over the four renderings of w e and w s
    (NaN where a rendering is not a measured galaxy)."""
    cat = fits.getdata(d / run / f"psf{k}_shear.fits", "CATALOG")
    img = np.asarray(cat["image"]).astype(str)
    out = {}
    for f in files:
        t = fits.getdata(d / f, "TRUTH")
        tree = cKDTree(np.c_[t["x"], t["y"]])
        acc = np.zeros((len(t), 4))
        for m in MEMBERS:
            c = cat[img == f.replace(".fits", f"{m}.fits")]
            dist, idx = tree.query(np.c_[c["x"], c["y"]])
            ok = (c["flags"] == 0) & (c["fitclass"] == 0) & (dist < 1.5)
            # one measurement per truth galaxy and rendering: a second match voids it
            count = np.bincount(idx[ok], minlength=len(t))
            part = np.full((len(t), 4), np.nan)
            w = c["weight"][ok]
            vals = np.c_[w * c["e1"][ok], w * c["e2"][ok], w * c["sens1"][ok], w * c["sens2"][ok]]
            part[idx[ok]] = vals
            part[count != 1] = np.nan
            part[np.asarray(t["is_star"], bool)] = np.nan
            acc += part
        out[f] = acc
    return out


def estimates(a: dict, g_true: np.ndarray, blocks: dict) -> np.ndarray:
    """``(N_BLOCKS + 1, 3)``: m1, c1, c2 on all galaxies, then leaving each block out."""
    out = np.zeros((N_BLOCKS + 1, 3))
    for b in range(-1, N_BLOCKS):
        g1, e2, s2 = [], 0.0, 0.0
        for f in a:
            keep = blocks[f] != b
            x = a[f][keep]
            g1.append(x[:, 0].sum() / x[:, 2].sum())
            e2, s2 = e2 + x[:, 1].sum(), s2 + x[:, 3].sum()
        slope, icpt = np.polyfit(g_true, np.array(g1), 1)
        out[b + 1] = (slope - 1.0, icpt, e2 / s2)
    return out


def jackknife(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    loo = v[1:]
    n = loo.shape[0]
    return v[0], np.sqrt((n - 1) / n * ((loo - loo.mean(0)) ** 2).sum(0))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("dir", type=Path)
    p.add_argument("--psf", type=int, nargs="+", help="these PSFs only (default all)")
    a = p.parse_args()
    man = json.loads((a.dir / "manifest.json").read_text())
    base = [f for f in man["fields"] if f["role"] == "shear" and not f["twin"]
            and not f.get("noise_twin")]  # fmt: skip
    rng = np.random.default_rng(0)
    print("| PSF | run | m1 | c1 | c2 |\n|---|---|---|---|---|")
    diffs = []
    for k in a.psf if a.psf else range(len(man["psfs"])):
        fl = sorted((f for f in base if f["psf"] == k), key=lambda f: f["shear_index"])
        files = [f["file"] for f in fl]
        g_true = np.array([f["g1"] for f in fl])
        runs = [sums(a.dir, r, k, files) for r in RUNS]
        both = {f: np.isfinite(runs[0][f]).all(1) & np.isfinite(runs[1][f]).all(1)
                for f in files}  # fmt: skip
        sel = [{f: r[f][both[f]] for f in files} for r in runs]
        blocks = {f: rng.integers(0, N_BLOCKS, both[f].sum()) for f in files}
        est = [estimates(s, g_true, blocks) for s in sel]
        n = sum(int(both[f].sum()) for f in files)
        for name, v in (("stacked PSF", est[0]), ("true PSF", est[1]),
                        ("difference", est[0] - est[1])):  # fmt: skip
            val, err = jackknife(v)
            cells = " | ".join(f"{x:+.5f} ± {e:.5f}" for x, e in zip(val, err, strict=True))
            print(f"| {k} | {name} (n={n}) | {cells} |")
        diffs.append(est[0] - est[1])
    val, err = jackknife(np.mean(diffs, axis=0))
    print("mean of PSFs, difference: " + ", ".join(
        f"{q} {x:+.5f} ± {e:.5f}" for q, x, e in zip(("m1", "c1", "c2"), val, err, strict=True)))


if __name__ == "__main__":
    main()
