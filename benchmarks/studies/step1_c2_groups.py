"""STEP1's c2 by galaxy group, split by S/N, nearest-neighbour distance and neighbour refits.

For a STEP1 set simulated with `--twins --noise-twins` and measured by `pylensfit validate
DIR` (catalogues in DIR/measured), each galaxy's four renderings (image, rotated twin and
their noise twins) are matched to the truth by position, and c2 = sum(w e2) / sum(w s2)
is taken over the galaxies measured in all four, with the error from the scatter of the
per-galaxy sums. STEP1 shears along g1 only, so c2 is the mean e2 response: zero by the
reflection y -> -y for a round PSF. The catalogue's e2 are those of the pipeline's prior,
not `validate`'s prior per PSF, so the values differ from the report's by their noise.

::

    python benchmarks/studies/step1_c2_groups.py DIR

(1 minute.)
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from astropy.io import fits
from scipy.spatial import cKDTree

MEMBERS = ("", "_neg", "_rot", "_rot_neg")


def groups(d: Path, npsf: int = 5, nshear: int = 20) -> dict[str, np.ndarray]:
    """Per galaxy measured in all four renderings: summed w e2 and w s2, and its truth."""
    out = []
    for k in range(npsf):
        cat = fits.getdata(d / "measured" / f"psf{k}_shear.fits", "CATALOG")
        img = np.asarray(cat["image"]).astype(str)
        for j in range(nshear):
            names = [f"psf{k}_g{j}{s}.fits" for s in MEMBERS]
            if names[0] not in set(img):
                continue
            t = fits.getdata(d / names[0], "TRUTH")
            tree = cKDTree(np.c_[t["x"], t["y"]])
            n = len(t)
            e = np.full((n, 4), np.nan)
            s = np.full((n, 4), np.nan)
            nn = np.full(n, np.nan)
            refit = np.zeros(n, bool)
            for m, fn in enumerate(names):
                c = cat[img == fn]
                dist, idx = tree.query(np.c_[c["x"], c["y"]])
                ok = (c["flags"] == 0) & (c["fitclass"] == 0) & (dist < 1.5)
                e[idx[ok], m] = (c["weight"] * c["e2"])[ok]
                s[idx[ok], m] = (c["weight"] * c["sens2"])[ok]
                if m == 0:
                    pos = np.c_[c["x"], c["y"]]
                    nn[idx] = cKDTree(pos).query(pos, k=2)[0][:, 1]
                    refit[idx[ok]] = c["refit_neighbours"][ok]
            full = np.all(np.isfinite(e), axis=1) & ~t["is_star"]
            out.append({"e": e[full].sum(1), "s": s[full].sum(1), "snr": t["snr"][full],
                        "nn": nn[full], "refit": refit[full],
                        "psf": np.full(full.sum(), k)})  # fmt: skip
    return {q: np.concatenate([g[q] for g in out]) for q in out[0]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("dir", type=Path)
    a = p.parse_args()
    r = groups(a.dir)

    def c2(sel: np.ndarray) -> str:
        e, s = r["e"][sel], r["s"][sel]
        v = e.sum() / s.sum()
        err = np.std(e - v * s) * np.sqrt(sel.sum()) / s.sum()
        return f"{v:+.5f} +- {err:.5f} (n={sel.sum()})"

    faint = r["snr"] < np.nanmedian(r["snr"])
    every = np.ones(len(faint), bool)
    print(f"all {c2(every)} | faint {c2(faint)} | bright {c2(~faint)}")
    for lo, hi in ((0, 30), (30, 36), (36, 39), (39, np.inf)):
        sel = (r["nn"] >= lo) & (r["nn"] < hi)
        print(f"nearest neighbour {lo}-{hi} px: {c2(sel)} | faint {c2(sel & faint)}")
    for v in (False, True):
        sel = r["refit"] == v
        print(f"neighbours refitted {v}: {c2(sel)} | faint {c2(sel & faint)}")
    for k in np.unique(r["psf"]):
        sel = r["psf"] == k
        print(f"PSF {k}: {c2(sel)} | faint {c2(sel & faint)}")


if __name__ == "__main__":
    main()
