"""What the sky estimate does to m: one PSF of a STEP-like set measured three ways.

    python benchmarks/studies/sky_bias.py DIR --psf K [--jobs 2]

``DIR`` is a set of ``pylensfit simulate step1|step2``. The shear fields of PSF ``K``
(and their star field) are measured

- ``sep``: with SEP's background as the first pass measures it (``model_background``
  off),
- ``true``: with the simulation's true sky (the manifest's constant ``sky``), and
- ``model``: with the sky measured again less the fitted models (the default),

all else as ``validate``'s default configuration. Each field's mean sky error (the
``background`` column less the true sky, in noise sigma) is printed, then m1, m2 of
each mode from the same galaxies (those measured in every mode; twins paired when the
set has them), with one ellipticity prior estimated from the ``sep`` catalogues, and
the paired difference of each mode from ``sep`` (a fit of the difference of the shear
estimates against the true shear: the galaxies and the noise are shared, so the
difference is measured far better than m itself). What it found: ``benchmarks/README.md``,
"What the studies found".
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
from pathlib import Path

import numpy as np
from astropy.table import vstack

MODES = ("sep", "true", "model")


def patch_true_sky(sky: float) -> None:
    """Make ``pylensfit.detection.measure_background`` return the constant ``sky`` (its
    noise map kept), in this process, for every later call of ``measure``."""
    from pylensfit import detection

    orig = detection.measure_background

    def true_sky(*a, **k):
        b = orig(*a, **k)
        return detection.Background(back=np.full_like(b.back, sky), rms=b.rms, global_back=sky,
                                    global_rms=b.global_rms, bad=b.bad)  # fmt: skip

    detection.measure_background = true_sky


def _measure(args):
    """Measure one field in one mode (in a forked worker: the patch stays in it)."""
    mode, path, star, cfg_dict, sky = args
    from pylensfit import pipeline
    from pylensfit.config import Config
    from pylensfit.prior import Prior

    cfg = Config.from_dict({**cfg_dict, "model_background": mode == "model"})
    if mode == "true":
        patch_true_sky(sky)
    cat = pipeline.measure([path], stars=[star], config=cfg, prior=Prior(), progress=False)
    cat.meta.pop("psfs", None)
    return mode, path, cat


def main(argv=None) -> int:
    from pylensfit.config import Config
    from pylensfit.prior import estimate_prior
    from pylensfit.shear import shapes
    from pylensfit_validation import validation as V

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("directory")
    ap.add_argument("--psf", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args(argv)
    man = V.read_manifest(a.directory)
    sky = float(man["fieldspec"]["sky"])
    noise = float(man["fieldspec"]["noise_sigma"])
    fields = {f["file"]: f for f in man["fields"]}
    sel = [f for f in man["fields"] if int(f["psf"]) == a.psf and f["role"] == "shear"]
    star = next(s["path"] for s in man["star_fields"] if int(s["psf"]) == a.psf)
    cfg = Config(model="bulge+disc", n_bulge_fractions=3).to_dict()
    tasks = [(m, f["path"], star, cfg, sky) for m in MODES for f in sel]
    cats: dict[str, list] = {m: [] for m in MODES}
    # one task per worker: the true-sky patch must not outlive its task
    with mp.get_context("fork").Pool(a.jobs, maxtasksperchild=1) as pool:
        for mode, path, cat in pool.imap_unordered(_measure, tasks):
            cats[mode].append(cat)
            ok = cat["flags"] == 0
            err = (np.mean(cat["background"][ok]) - sky) / noise
            print(f"{mode:5s} {Path(path).name}: sky error {err:+.4f} sigma", flush=True)
    fwhm = float(man["psfs"][a.psf]["fwhm"])
    gal = {m: V.matched_galaxies(vstack(c, metadata_conflicts="silent"), fields, a.psf, fwhm)
           for m, c in cats.items()}  # fmt: skip
    egrid = cats["sep"][0].meta["egrid"]
    prior = estimate_prior(np.asarray(gal["sep"]["lnL"]), egrid)
    pairs = any(f["twin"] or f.get("noise_twin") for f in sel)
    keyed = {}
    for m, g in gal.items():
        sh = shapes(np.asarray(g["lnL"]), egrid, prior)
        e = np.column_stack([sh["e1"], sh["e2"]])
        s = np.column_stack([sh["sens1"], sh["sens2"]])
        img = np.asarray(g["image"]).astype(str)
        t = np.asarray(g["truth_index"])
        if pairs:  # each galaxy's renderings summed, keyed by the group's first image
            gid, base = V.shear_groups(g, fields)
            mem = V.group_members(gid)
            i = mem[:, 0]
            img = base.astype(str)
            e, s = e[mem].sum(axis=1), s[mem].sum(axis=1)
        else:
            i = np.flatnonzero(t >= 0)
            e, s = e[i], s[i]
        keyed[m] = {(img[j], t[j]): (e[k], s[k]) for k, j in enumerate(i)}
    common = sorted(set.intersection(*(set(k) for k in keyed.values())))
    names = sorted({c[0] for c in common})
    print(f"{len(common)} galaxies{' (pairs)' if pairs else ''} measured in every mode, "
          f"{len(names)} images; prior {prior}")  # fmt: skip
    g_true = np.array([(fields[n]["g1"], fields[n]["g2"]) for n in names])
    est = {}
    for m in MODES:
        rows = []
        for n in names:
            es = np.array([keyed[m][c][0] for c in common if c[0] == n])
            ss = np.array([keyed[m][c][1] for c in common if c[0] == n])
            rows.append((es.sum(0) / ss.sum(0), es.std(0) * np.sqrt(len(es)) / ss.sum(0)))
        est[m] = (np.array([r[0] for r in rows]), np.array([r[1] for r in rows]))
    for m in MODES:
        out = []
        for i in range(2):
            gt = g_true[:, i]
            mm, _, cov = V.fit_m_c_cov(gt, est[m][0][:, i], est[m][1][:, i])
            line = f"m{i + 1} {mm:+.4f} +- {np.sqrt(cov[0, 0]):.4f}"
            if m != "sep" and np.ptp(gt) > 0:
                d = est[m][0][:, i] - est["sep"][0][:, i]
                if gt.size > 3:
                    coef, cov = np.polyfit(gt, d, 1, cov=True)
                    line += f" (vs sep {coef[0]:+.4f} +- {np.sqrt(cov[0, 0]):.4f})"
                else:
                    line += f" (vs sep {np.polyfit(gt, d, 1)[0]:+.4f})"
            out.append(line)
        print(f"{m:5s} " + "   ".join(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
