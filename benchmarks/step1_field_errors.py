"""Are a STEP1 set's per-field c2 errors right? Halves, spatial blocks and the truth.

For a STEP1 set simulated with ``--twins --noise-twins`` and measured by ``pylensfit
validate DIR`` (catalogues in DIR/measured, or ``--run measured_true_psf``), every
galaxy's four renderings are summed as in ``benchmarks/step1_true_psf.py`` (key2 with the
catalogue's prior), and per shear field:

- c2 = sum(w e2) / sum(w s2) with the ratio estimator's error (scatter of ``e - c2 s``);
- the same error from 8 x 8 spatial blocks of the field (neighbours sharing noise
  through the sky, the deblending or the background would make it larger);
- the chi-square of the difference of two random halves of the field's galaxies (what
  the per-galaxy errors say of the scatter inside a field);
- ``truth``: c2 of the twin-summed *true* sheared ellipticities of the same galaxies,
  ``(e(e_s) + e(-e_s)) / 2 - g`` (the rotation leaves ``-2 g e_s^2``, zero on average
  but not in one field), and c2 with it taken out as a control variate
  (``pylensfit_validation.validation.truth_control_variate``, as ``validate --truth-control``).

Then the chi-square of c2 about each PSF's mean, with and without the control variate.

::

    python benchmarks/step1_field_errors.py DIR [--run measured]

(1-2 minutes on kept catalogues.)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from astropy.io import fits

from pylensfit_validation.validation import read_truth, truth_control_variate, truth_terms
from step1_true_psf import MEMBERS, sums

N_SIDE = 8  # spatial blocks per side


def field_rows(d: Path, run: str, k: int, fl: list[dict], rng) -> list[tuple]:
    S = sums(d, run, k, [f["file"] for f in fl])
    rows = []
    for f in fl:
        g = np.array([f["g1"], f["g2"]])
        # sum over the group's renderings of e_true - g per truth object (NaN: stars)
        names = [f["file"].replace(".fits", f"{m}.fits") for m in MEMBERS]
        t_all = truth_terms({n: {"path": d / n, "g1": g[0], "g2": g[1]} for n in names}, names)
        t = read_truth(d / names[0])
        gal = ~np.asarray(t["is_star"], bool)
        x = S[f["file"]]
        ok = np.isfinite(x).all(1)
        e, s, tt = x[ok, 1], x[ok, 3], t_all[ok, 1]
        den = s.sum()
        c2 = e.sum() / den
        r = e - c2 * s
        err = np.std(r, ddof=1) * np.sqrt(r.size) / den
        # spatial blocks: the variance of the sum from the blocks' sums
        size = float(fits.getheader(d / f["file"])["NAXIS1"])
        xy = np.c_[t["x"], t["y"]][ok]
        b = np.clip((xy / (size / N_SIDE)).astype(int), 0, N_SIDE - 1) @ [N_SIDE, 1]
        tot = np.bincount(b, r, N_SIDE**2)
        err_sp = np.sqrt(N_SIDE**2 / (N_SIDE**2 - 1) * ((tot - tot.mean()) ** 2).sum()) / den
        # two random halves
        h = rng.random(r.size) < 0.5
        parts = []
        for sel in (h, ~h):
            v = e[sel].sum() / s[sel].sum()
            parts.append((v, np.std(e[sel] - v * s[sel], ddof=1) * np.sqrt(sel.sum())
                          / s[sel].sum()))  # fmt: skip
        chi_half = (parts[0][0] - parts[1][0]) ** 2 / (parts[0][1] ** 2 + parts[1][1] ** 2)
        truth = (tt.sum() / 4) / (r.size) if r.size else np.nan
        delta, err_c = truth_control_variate(r, tt, t_all[gal, 1], 1.0 / den)
        rows.append((k, f["g1"], c2, err, err_sp, chi_half, truth, c2 - delta, err_c))
    return rows


def chi2_about_mean(v: np.ndarray, e: np.ndarray) -> float:
    w = e**-2
    return float((((v - (w * v).sum() / w.sum()) / e) ** 2).sum())


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("dir", type=Path)
    p.add_argument("--run", default="measured")
    p.add_argument("--seed", type=int, default=1, help="of the random halves")
    a = p.parse_args()
    man = json.loads((a.dir / "manifest.json").read_text())
    rng = np.random.default_rng(a.seed)
    print("| PSF | g1 | c2 (1e-4) | spatial / galaxy error | halves chi2 | truth c2 | "
          "controlled c2 |\n|---|---|---|---|---|---|---|")
    rows = []
    for k in range(len(man["psfs"])):
        fl = sorted((f for f in man["fields"] if f["role"] == "shear" and f["psf"] == k
                     and not f["twin"] and not f.get("noise_twin")),
                    key=lambda f: f["shear_index"])  # fmt: skip
        for r in field_rows(a.dir, a.run, k, fl, rng):
            rows.append(r)
            print(f"| {r[0]} | {r[1]:.3f} | {r[2] * 1e4:+.1f} ± {r[3] * 1e4:.1f} | "
                  f"{r[4] / r[3]:.2f} | {r[5]:.1f} | {r[6] * 1e4:+.1f} | "
                  f"{r[7] * 1e4:+.1f} ± {r[8] * 1e4:.1f} |")
    a_ = np.array(rows)
    psf = a_[:, 0].astype(int)
    chi_p = sum(chi2_about_mean(a_[psf == k, 2], a_[psf == k, 3]) for k in np.unique(psf))
    chi_c = sum(chi2_about_mean(a_[psf == k, 7], a_[psf == k, 8]) for k in np.unique(psf))
    dof = len(a_) - len(np.unique(psf))
    print(f"\nc2 about each PSF's mean: chi-square {chi_p:.1f} (controlled {chi_c:.1f}) on {dof}; "
          f"halves: {a_[:, 5].sum():.1f} on {len(a_)}; spatial / galaxy errors: mean "
          f"{np.mean(a_[:, 4] / a_[:, 3]):.3f}; corr(c2, truth) over fields "
          f"{np.corrcoef(a_[:, 2], a_[:, 6])[0, 1]:.2f}")


if __name__ == "__main__":
    main()
