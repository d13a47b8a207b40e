"""A PSF that varies over the field, measured from its stars: leakage, m and the PSF models.

Two STEP2-like sets are simulated with the same seed, so that they hold the same
galaxies (positions, shapes, fluxes, shears) and the same noise, and differ only in the
PSF: one has the survey PSF map of ``pylensfit simulate --psf-variation survey`` (FWHM
+-10 % across the field, an ellipticity that changes by up to 0.08 from the centre to
the corners, the stars following the same map), the other the map's central PSF
everywhere (``--psf-variation none``). Then:

1. **PSF models against the truth.** On each PSF's star field, 20 % of the stars are
   held out; the polynomial model (:class:`pylensfit.psfmodel.PolynomialPSF`) of each
   order in ``--orders``, and with ``--piff`` a Piff model (``PixelGrid`` with a
   polynomial interpolation, fitted by Piff), are fitted to the others, and their
   adaptive-moment ellipticity at the held-out stars and at the galaxies of one shear
   field is compared with the truth's (the noise-free PSF there): the rms residual per
   component (the stars' own noise does not enter).
2. **The galaxies** (with ``--measure``), each set through
   :func:`pylensfit_validation.validation.validate` with the defaults otherwise: the
   constant set with the constant PSF stacked from its stars; the varying set with the
   polynomial model (``psf_model = "polynomial"``,
   ``psf_order = --order``), with the constant stacked PSF (the comparison), with each
   galaxy's true PSF (``validate(true_psf=True)``: the PSF map, no model error) and with
   ``--piff`` with the Piff models (``validate(psf_models=...)``). The catalogues are
   kept in the sets' folders and reused.
3. **Paired analysis.** The usable galaxies of each varying-set run are matched to the
   constant set's (same image, within 1 px). Per PSF:

   * ``dm = m(varying) - m(constant)``, from the mean shear over mean sensitivity of
     the matched galaxies of each image (the catalogue's ``e`` and ``sens``; sky frame),
     fitted against the input shears; the same galaxies and noise in both, so that
     shape noise cancels in ``dm``;
   * the PSF leakage ``alpha`` (:func:`pylensfit_validation.validation.psf_leakage`) of the
     paired residuals ``(e - s g)_varying - (e - s g)_constant`` against the true PSF
     ellipticity at each galaxy: the same slope as the varying set's own leakage, whose
     expectation the constant set's term does not change (its PSF does not follow the
     map), with the shape noise taken out;
   * errors by jackknife over 64 blocks of the field (a galaxy's twins share its
     position, so they leave together).

   The true PSF's run, paired with the constant set, is the leakage that the method
   leaves with a perfect PSF model; each model's run paired with the true PSF's (the
   same pixels, fitted with two PSFs) is the model's own part, free of the galaxies'
   noise to first order.

   It also prints :func:`pylensfit_validation.validation.validate`'s own m, c and unpaired
   leakage of each run.

::

    python benchmarks/psf_field.py --out DIR --piff             # PSF models, 4 min
    python benchmarks/psf_field.py --out DIR --piff --measure   # + galaxies
    python benchmarks/psf_field.py --out DIR --measure --runs polynomial true  # a subset
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time
import warnings
from functools import cache
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.table import Table
from scipy.spatial import cKDTree

import pylensfit as plf
from pylensfit.psfmodel import PolynomialPSF, fit_piff, read_psf_model
from pylensfit_validation.simulate import pixel_to_sky_shear
from pylensfit_validation.validation import psf_leakage, read_manifest, simulate_step, validate

BLOCKS = 8  # jackknife blocks per side of the field
RUNS = ("polynomial", "stacked", "true", "piff")  # the varying set's runs (--runs)


# -- the sets -----------------------------------------------------------------------------


def _simulate(out: Path, ngal: int, seed: int, jobs: int) -> tuple[Path, Path]:
    """The varying and the constant set (kept if already there)."""
    dirs = {}
    for name, var in (("varying", "survey"), ("constant", "none")):
        d = out / name
        if not (d / "manifest.json").exists():
            simulate_step("step2", d, ngal=ngal, seed=seed, noise_twins=True,
                          psf_variation=var, jobs=jobs)  # fmt: skip
        dirs[name] = d
    return dirs["varying"], dirs["constant"]


def _linked(src: Path, dst: Path) -> Path:
    """A second view of the set ``src`` (links to its files) with its own catalogues."""
    dst.mkdir(parents=True, exist_ok=True)
    for f in src.iterdir():
        if f.is_file() and not (dst / f.name).exists():
            os.symlink(f.resolve(), dst / f.name)
    return dst


# -- 1. PSF models against the truth ----------------------------------------------------


def _star_field(man: dict, k: int) -> tuple[np.ndarray, Table, float]:
    """PSF ``k``'s star field: the image less its sky, its truth and the noise sigma."""
    sf = next(s for s in man["star_fields"] if int(s["psf"]) == k)
    with fits.open(sf["path"]) as h:
        image = h[0].data.astype(float) - float(man["fieldspec"]["sky"])
        truth = Table(h["TRUTH"].data)
    return image, truth, float(man["noise_sigma"])


def _residual(model, x, y, e_true: np.ndarray) -> tuple[float, float, float, float]:
    """rms and mean of the model's ellipticity minus the truth's at ``(x, y)``."""
    e1, e2, _ = model.shape_at(x, y)
    d = np.column_stack([e1, e2]) - e_true
    return (*np.sqrt(np.nanmean(d**2, axis=0)), *np.nanmean(d, axis=0))


def psf_models(man: dict, orders: list[int], piff_order: int | None, out: Path,
               seed: int) -> tuple[Table, dict[int, Path]]:  # fmt: skip
    """Step 1: every model's residuals per PSF, and the Piff files written."""
    rows, piff_files = [], {}
    for k in range(len(man["psfs"])):
        image, truth, sigma = _star_field(man, k)
        st = truth[np.asarray(truth["is_star"], bool)]
        x, y = np.asarray(st["x"], float), np.asarray(st["y"], float)
        hold = np.random.default_rng([seed, k]).random(x.size) < 0.2
        e_star = np.column_stack([st["psf_e1_obs"], st["psf_e2_obs"]])
        gal = _galaxy_truth(man, k)
        e_gal = np.column_stack([gal["psf_e1_obs"], gal["psf_e2_obs"]])
        models: list[tuple[str, object]] = []
        for o in orders:
            m = PolynomialPSF.fit(image, x[~hold], y[~hold], noise_sigma=sigma, order=o,
                                  holdout=0.0, source=f"psf{k}_stars")  # fmt: skip
            models.append((f"polynomial {m.order}", m))
        if piff_order is not None:
            t0 = time.perf_counter()
            path = fit_piff(image, x[~hold], y[~hold], out / "piff" / f"psf{k}.piff",
                            noise_sigma=sigma, order=piff_order, overwrite=True)  # fmt: skip
            piff_files[k] = path
            print(f"  PSF {k}: Piff fitted in {time.perf_counter() - t0:.1f} s")
            models.append((f"piff {piff_order}", read_psf_model(path)))
        for name, m in models:
            rows.append((k, name, int(hold.sum()), *_residual(m, x[hold], y[hold], e_star[hold]),
                         *_residual(m, gal["x"], gal["y"], e_gal)[:2]))  # fmt: skip
    names = ("psf", "model", "n_heldout", "rms_de1", "rms_de2", "mean_de1", "mean_de2",
             "gal_rms_de1", "gal_rms_de2")  # fmt: skip
    return Table(rows=rows, names=names), piff_files


def _galaxy_truth(man: dict, k: int) -> Table:
    """The galaxies of PSF ``k``'s first shear field (their true PSF shapes)."""
    f = next(f for f in man["fields"] if int(f["psf"]) == k and f["role"] == "shear")
    t = _truth(f["path"])
    return t[~np.asarray(t["is_star"], bool)]


# -- 2. the galaxies ----------------------------------------------------------------------


def _validated(d: Path, label: str, jobs: int, **kw) -> Table:
    """:func:`pylensfit_validation.validation.validate` of one run, its summary printed."""
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", plf.CalibrationWarning)
        res = validate(d, jobs=jobs, progress=False, bins={}, **kw)
    reused = all(v["reused"] for v in res.meta["measured"].values())
    took = "kept catalogues" if reused else f"{time.perf_counter() - t0:.0f} s"
    lk = res.meta["leakage"]
    tr = lk[(lk["source"] == "truth") & (lk["psf"] == "all")][0]
    print(f"  {label}: m1 = {res['m1'][-1]:+.4f} +- {res['m1_err'][-1]:.4f}, m2 = "
          f"{res['m2'][-1]:+.4f} +- {res['m2_err'][-1]:.4f}, sigma_c = "
          f"{res.meta['sigma_c']:.2e}; alpha (true PSF, unpaired) = {tr['alpha1']:+.4f} "
          f"+- {tr['alpha1_err']:.4f} / {tr['alpha2']:+.4f} +- {tr['alpha2_err']:.4f} "
          f"({took})")  # fmt: skip
    return res


# -- 3. paired analysis ---------------------------------------------------------------------


@cache
def _truth(path: str) -> Table:
    """An image's truth table, read once (every run of a set pairs with the same)."""
    return Table.read(path, hdu="TRUTH")


def _rows(res: Table, k: int, man: dict) -> Table:
    """PSF ``k``'s usable galaxies of a run's shear catalogue, with their image's shear,
    block and true PSF ellipticity (sky frame)."""
    cat = plf.read_catalogue(res.meta["measured"][f"psf{k}_shear"]["path"])
    ok = ((np.asarray(cat["flags"]) == 0) & (np.asarray(cat["fitclass"]) == 0)
          & (np.asarray(cat["weight"]) > 0) & ~np.asarray(cat["is_star"], bool))  # fmt: skip
    cat = cat[ok]
    fields = {f["file"]: f for f in man["fields"]}
    names = [str(n) for n in cat["image"]]
    cat["g1"] = [fields[n]["g1"] for n in names]
    cat["g2"] = [fields[n]["g2"] for n in names]
    size = float(man["field_size"])
    bx = np.clip((np.asarray(cat["x"]) / size * BLOCKS).astype(int), 0, BLOCKS - 1)
    by = np.clip((np.asarray(cat["y"]) / size * BLOCKS).astype(int), 0, BLOCKS - 1)
    cat["block"] = bx * BLOCKS + by
    rot, flip = float(man.get("wcs_rotation_deg") or 0.0), bool(man.get("wcs_flip", False))
    pe = np.full((len(cat), 2), np.nan)
    for n in set(names):
        sel = np.flatnonzero(np.asarray(names) == n)
        t = _truth(fields[n]["path"])
        dist, j = cKDTree(np.column_stack([t["x"], t["y"]])).query(
            np.column_stack([cat["x"][sel], cat["y"][sel]]), distance_upper_bound=2.0)
        hit = np.isfinite(dist)
        a, b = pixel_to_sky_shear(np.asarray(t["psf_e1_obs"], float)[j[hit]],
                                  np.asarray(t["psf_e2_obs"], float)[j[hit]], rot, flip)
        pe[sel[hit]] = np.column_stack([a, b])
    cat["psf_e_true"] = pe
    return cat


def _pair(a: Table, b: Table) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the rows of ``a`` and ``b`` on the same image within 1 px."""
    ia, ib = [], []
    na, nb = np.asarray(a["image"]).astype(str), np.asarray(b["image"]).astype(str)
    for n in np.unique(na):
        sa, sb = np.flatnonzero(na == n), np.flatnonzero(nb == n)
        if not sb.size:
            continue
        dist, j = cKDTree(np.column_stack([b["x"][sb], b["y"][sb]])).query(
            np.column_stack([a["x"][sa], a["y"][sa]]), distance_upper_bound=1.0)
        hit = np.isfinite(dist)
        ia.append(sa[hit])
        ib.append(sb[j[hit]])
    return np.concatenate(ia), np.concatenate(ib)


def _m_c(E: np.ndarray, S: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``(m1, c1, m2, c2)`` from per-image sums ``E, S`` ``(n_img, 2)`` and shears ``g``."""
    out = []
    for i in (0, 1):
        gm = E[:, i] / S[:, i]
        A = np.column_stack([g[:, i], np.ones(len(g))])
        out += list(np.linalg.lstsq(A, gm - g[:, i], rcond=None)[0])
    return np.array(out)


def _image_sums(t: Table, img: np.ndarray, blk: np.ndarray, n_img: int) -> tuple:
    """``(n_img, BLOCKS^2, 2)`` sums of ``e`` and ``sens`` per image and block."""
    E = np.zeros((n_img, BLOCKS**2, 2))
    S = np.zeros_like(E)
    for i, (e, s) in enumerate((("e1", "sens1"), ("e2", "sens2"))):
        np.add.at(E[:, :, i], (img, blk), np.asarray(t[e], float))
        np.add.at(S[:, :, i], (img, blk), np.asarray(t[s], float))
    return E, S


def _jackknife(values: np.ndarray) -> np.ndarray:
    """Jackknife errors from the ``(n_blocks, ...)`` delete-one values."""
    n = values.shape[0]
    return np.sqrt((n - 1) / n * np.sum((values - values.mean(axis=0)) ** 2, axis=0))


def paired(var: Table, const: Table) -> dict[str, float]:
    """``dm, dc`` and the paired leakage ``alpha`` of one PSF's matched galaxies."""
    ia, ib = _pair(var, const)
    v, c = var[ia], const[ib]
    names, img = np.unique(np.asarray(v["image"]).astype(str), return_inverse=True)
    g = np.array([[v["g1"][img == i][0], v["g2"][img == i][0]] for i in range(len(names))])
    blk = np.asarray(v["block"])
    Ev, Sv = _image_sums(v, img, blk, len(names))
    Ec, Sc = _image_sums(c, img, blk, len(names))
    full = _m_c(Ev.sum(1), Sv.sum(1), g) - _m_c(Ec.sum(1), Sc.sum(1), g)
    jk = np.array([_m_c(Ev.sum(1) - Ev[:, b], Sv.sum(1) - Sv[:, b], g)
                   - _m_c(Ec.sum(1) - Ec[:, b], Sc.sum(1) - Sc[:, b], g)
                   for b in range(BLOCKS**2)])  # fmt: skip
    err = _jackknife(jk)
    gg = np.column_stack([v["g1"], v["g2"]])
    sv, sc = (np.column_stack([t["sens1"], t["sens2"]]) for t in (v, c))
    s = 0.5 * (sv + sc)
    r = ((np.column_stack([v["e1"], v["e2"]]) - sv * gg)
         - (np.column_stack([c["e1"], c["e2"]]) - sc * gg))
    pe = np.asarray(v["psf_e_true"], float)

    def alpha(sel):
        lk = psf_leakage(r[sel, 0], r[sel, 1], s[sel, 0], s[sel, 1], pe[sel, 0], pe[sel, 1])
        return np.array([lk["alpha1"], lk["alpha2"]]), np.array([lk["alpha1_err"],
                                                                 lk["alpha2_err"]])

    a, a_err = alpha(np.ones(len(v), bool))
    a_jk = _jackknife(np.array([alpha(blk != b)[0] for b in range(BLOCKS**2)]))
    return {"n": len(v), "dm1": full[0], "dm1_err": err[0], "dc1": full[1], "dc1_err": err[1],
            "dm2": full[2], "dm2_err": err[2], "dc2": full[3], "dc2_err": err[3],
            "alpha1": a[0], "alpha1_err": max(a_err[0], a_jk[0]),
            "alpha2": a[1], "alpha2_err": max(a_err[1], a_jk[1])}  # fmt: skip


def _combined(rows: list[dict]) -> dict[str, float]:
    """Inverse-variance means over PSFs of the paired figures."""
    out = {"n": sum(r["n"] for r in rows)}
    for q in ("dm1", "dc1", "dm2", "dc2", "alpha1", "alpha2"):
        w = np.array([1.0 / r[q + "_err"] ** 2 for r in rows])
        out[q] = float(np.sum(w * [r[q] for r in rows]) / w.sum())
        out[q + "_err"] = float(1.0 / np.sqrt(w.sum()))
    return out


def _print_paired(label: str, runs: dict[int, dict], ref: str = "the constant set") -> None:
    print(f"\n{label}, paired with {ref} (jackknife errors)")
    print(f"{'PSF':>4} {'n':>6} {'dm1':>17} {'dm2':>17} {'alpha1':>17} {'alpha2':>17}")
    for k, r in [*runs.items(), ("all", _combined(list(runs.values())))]:
        print(f"{k!s:>4} {r['n']:6d} " + " ".join(
            f"{r[q]:+8.4f} +- {r[q + '_err']:.4f}" for q in ("dm1", "dm2", "alpha1", "alpha2")))


# -- main ----------------------------------------------------------------------------------


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True, help="folder of the two sets (kept, reused)")
    ap.add_argument("--ngal", type=int, default=16000)
    ap.add_argument("--seed", type=int, default=21)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--orders", type=int, nargs="+", default=[2, 3, 4, 5],
                    help="polynomial orders compared in step 1")
    ap.add_argument("--order", type=int, default=3, help="the polynomial order measured")
    ap.add_argument("--piff", action="store_true", help="also Piff models (the piff extra)")
    ap.add_argument("--piff-order", type=int, default=3)
    ap.add_argument("--measure", action="store_true", help="measure the galaxies (steps 2-3)")
    ap.add_argument("--runs", nargs="+", default=list(RUNS), choices=list(RUNS),
                    help="the varying set's runs measured in step 2 (default all; piff "
                         "needs --piff)")  # fmt: skip
    a = ap.parse_args(argv)
    out = Path(a.out)
    t0 = time.perf_counter()
    var, const = _simulate(out, a.ngal, a.seed, a.jobs)
    man_v, man_c = read_manifest(var), read_manifest(const)
    print(f"sets: {var} (survey PSF map), {const} (its central PSF), seed {a.seed}")
    print("\n1. PSF models against the truth (ellipticity residuals)")
    tab, piff_files = psf_models(man_v, a.orders, a.piff_order if a.piff else None, out,
                                 a.seed)  # fmt: skip
    for c in tab.colnames[3:]:
        tab[c].format = "+.5f"
    tab.pprint_all()
    if not a.measure:
        return 0
    print("\n2. the galaxies through validate")
    stacked = plf.Config(psf_model="constant")  # (the default would find the map)
    rc = _validated(const, "constant set, stacked PSF", a.jobs, config=stacked)
    runs = {}
    if "polynomial" in a.runs:
        runs["polynomial"] = _validated(
            var, f"varying set, polynomial {a.order}", a.jobs,
            config=plf.Config(psf_model="polynomial", psf_order=a.order))
    if "stacked" in a.runs:
        runs["constant PSF"] = _validated(_linked(var, out / "varying_stacked"),
                                          "varying set, stacked PSF", a.jobs,
                                          config=stacked)  # fmt: skip
    if "true" in a.runs:
        runs["true PSF"] = _validated(var, "varying set, true PSF", a.jobs, true_psf=True)
    if a.piff and "piff" in a.runs:
        runs["piff"] = _validated(var, f"varying set, Piff {a.piff_order}", a.jobs,
                                  psf_models=piff_files)  # fmt: skip
    print("\n3. paired analysis")
    summary = {}
    const_rows = {k: _rows(rc, k, man_c) for k in range(len(man_c["psfs"]))}
    var_rows = {label: {k: _rows(res, k, man_v) for k in const_rows}
                for label, res in runs.items()}  # fmt: skip
    for label, rows in var_rows.items():
        per = {k: paired(rows[k], const_rows[k]) for k in const_rows}
        _print_paired(label, per)
        summary[label] = {str(k): v for k, v in per.items()}
    # the PSF models' own part: each model's run against the true PSF's, on the same pixels
    models = [q for q in runs if q not in ("true PSF", "constant PSF")]
    for label in models if "true PSF" in runs else []:
        per = {k: paired(var_rows[label][k], var_rows["true PSF"][k]) for k in const_rows}
        _print_paired(f"{label} minus true PSF (the varying set)", per, "the true PSF's run")
        summary[f"{label} - true PSF"] = {str(k): v for k, v in per.items()}
    (out / "paired.json").write_text(json.dumps(summary, indent=1, default=float))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    print(f"\n{time.perf_counter() - t0:.0f} s, peak memory {peak:.2f} GB (this process)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
