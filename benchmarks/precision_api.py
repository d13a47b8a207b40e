"""m and c of the precision population measured through the public stamps API.

``pylensfit validate --precision`` (:func:`pylensfit_validation.precision.precision`) measures its
population with its own fitting passes: the calibration recipe run over the blocks of
the calibration sample (:func:`pylensfit.calibration.run_recipe`), then ``fit_stamps``
and the per-rendering reduction on every block of renderings. A user measures with
:func:`pylensfit.calibrate` and :func:`pylensfit.measure_stamps` instead. This script
measures the precision mode's own renderings (same seed, same galaxies, same noise)
through those two calls with their defaults and reports m and c per PSF as the precision
mode does, so that the two can be compared on the same images::

    python benchmarks/precision_api.py --ngal 20000 --ncal 12000 --jobs 2 --compare
    python benchmarks/precision_api.py --ngal 80000 --ncal 40000 --jobs 2 --compare
    python benchmarks/precision_api.py --ngal 400 --ncal 400 --psf round       # smoke run

``--ngal`` and ``--ncal`` are totals over the PSFs (blocks of 500 galaxies shared out
in turn, so each must exceed ``500 (n_psf - 1)``).

The renderings
--------------
The spec is ``pylensfit_validation.precision.spec_with(ngal=..., ncal=..., seed=..., psfs=...,
g=..., noise_twins=...)``, what ``validate --precision`` builds from the same options.
Every block of it is rendered by :func:`pylensfit_validation.precision.render_block`, the function
the precision mode's workers call, on stamps of ``Config().largest_stamp`` (64) pixels,
as the precision mode renders them for ``Config()`` (galaxies larger than the 32-pixel
base stamp are fitted on 64 pixels, the others on the central 32: ``fit_stamps`` chooses
per galaxy). Block ``b`` goes to PSF ``b % n_psf``, in the calibration sample as in the
main sample, as the precision mode shares them out. The PSF image is the one
``render_block`` returns (64 x 64, the pixel response included, unit sum); the noise
sigma is ``spec.noise_sigma`` (1). A main block's stamps are ``(n, R, 64, 64)``: each
galaxy's ``R = 4`` renderings (+g, +g rotated, -g, -g rotated; 8 with
``--noise-twins``, the same four with their noise negated), flattened galaxy by galaxy.

The measurement
---------------
Per PSF, on all of that PSF's calibration stamps at once (``ncal / n_psf`` unsheared
galaxies, one rendering each)::

    priors = plf.calibrate(cal_stamps, psf_image, noise_sigma=1.0)          # config=None
    table = plf.measure_stamps(block_stamps, psf_image, noise_sigma=1.0,
                               priors=priors)                               # per block

both with ``config=None`` (``Config()``, as the precision mode's default) and the
stamps' centres as the catalogue positions. The one difference from the precision mode's
calibration: it runs the recipe once over all PSFs, with the ellipticity prior, the
bulge-fraction weights, the flux power and the position prior common to them and the
size prior and flux limits per PSF; ``calibrate`` on one PSF's stamps estimates all of
them from that PSF's galaxies. With one PSF (``--psf round``) the two recipes see the
same stamps in the same order.

A rendering is usable when its row has ``flags == 0`` and ``weight > 0``; a galaxy counts
only if all its renderings are usable (the precision mode's ``paired`` selection). Two
estimators, both from the table alone:

- ``exact`` (eq. ``key2``): per PSF and sign, ``g_i(+-) = sum e_i / sum sens_i`` over
  the galaxies' renderings at ``+-g``, the table's ``e1, e2, sens1, sens2`` columns;
  ``m_i = (g_i(+) - g_i(-)) / (2 g) - 1``, ``c_i = (g_i(+) + g_i(-)) / 2``. It carries the
  known ``m ~ +|g|^2`` (``+8e-4`` at ``g = (0.02, 0.02)``).
- ``fixed-point`` (what ``validate --precision`` prints): the sheared-prior fixed point
  of :func:`pylensfit.estimate_shear`, from the table's ``lnL`` grids and its
  ``meta["prior"]``, linearised about the nominal shear as the precision mode does it
  (:func:`pylensfit_validation.precision.reduce_likelihoods` on the table's ``lnL``; one Newton
  step, within 1e-6 of the iterated estimate).

Errors and control variates are those of the precision mode, through its public
:func:`pylensfit_validation.precision.bias_table`: delete-one-group jackknife over groups of 100
galaxies (each block of 500 cut into five), m and c corrected with the intrinsic shapes'
spin-4 parts (:func:`pylensfit_validation.precision.shape_controls`) where a PSF has at least 20
groups (column ``cv``). The errors hold the priors fixed, as the precision mode's. The
script also prints the largest difference between the table's ``e`` and ``sens`` and
the same quantities recomputed from its ``lnL`` by the precision mode's reduction (it
should be at float rounding).

``--compare`` then runs :func:`pylensfit_validation.precision.precision` on the same spec in the
same process (``config=None``, the same ``--jobs``) and prints its per-PSF rows of the
same two estimators beside, with the differences API - precision. Both measure the same
renderings, so the difference is not limited by the errors printed (which are mostly the
noise that the two share): with one PSF it should be at rounding; with several it is the
effect of per-PSF priors.

Timing: wall-clock of the calibration (every PSF) and of the main pass, galaxies per
second of the main pass and of the whole; ``--jobs`` spawned worker processes with one
thread each (``--jobs 1``: this process). Calibration runs one PSF per worker (with one
PSF, in this process with ``--jobs`` threads), the main pass one block per worker, each
worker rendering its own stamps; the workers' start-up and model banks (30-40 s each)
are in the times, as in the precision mode's (where this process builds the bank, with
one PSF or ``--jobs 1``, ``precision()`` after it finds it built and is that much
faster). This
process holds per galaxy ~0.5 kB of results; a worker holds one PSF's calibration stamps
(``ncal / n_psf x 16 KiB``) and the calibration's grids (~40 kB per calibration galaxy at
their peak), or one block's stamps.

The error of m per PSF and component falls as ``1 / sqrt(ngal / n_psf)``: the precision
mode's 200,000 galaxies over four PSFs give about 0.0006 on the mean of PSFs, 0.0012 per
PSF, so ``--ngal 80000`` (20,000 per PSF) gives about 0.002 per PSF. The calibration
sample's own noise is not in the errors, and it differs between the two paths when there
are several PSFs (their priors are not estimated alike); ``--ncal 40000`` (10,000 per
PSF) keeps it well below that.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import sys
import time
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed

import numpy as np

import pylensfit as plf
from pylensfit.config import Config
from pylensfit_validation import precision as pm

#: the estimators reported (names as in the precision mode's table)
ESTIMATORS = ("fixed-point", "exact")
#: galaxies per jackknife group, as the precision mode's
JACKKNIFE_GALAXIES = 100


def _threads(n: int) -> None:
    import numba
    from threadpoolctl import threadpool_limits

    threadpool_limits(n)
    numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))


def _shear_sets(renderings: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Renderings at +g and at -g (``k % 4 < 2`` is +g, as in the precision mode)."""
    ks = range(renderings)
    return tuple(k for k in ks if k % 4 < 2), tuple(k for k in ks if k % 4 >= 2)


def _calibration_task(spec: pm.PrecisionSpec, k: int, stamp: int, threads: int | None):
    """Render PSF ``k``'s calibration blocks and run ``calibrate`` on them (a worker)."""
    if threads:
        _threads(threads)
    t0 = time.perf_counter()
    nblocks = -(-spec.ncal // spec.block_size)
    stamps, psf = [], None
    for b in range(k, nblocks, len(spec.psfs)):
        s, psf, _ = pm.render_block(spec, k, b, stamp_size=stamp, calibration=True)
        stamps.append(s[:, 0])
    stamps = np.concatenate(stamps)
    t1 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", plf.CalibrationWarning)
        priors = plf.calibrate(stamps, psf, noise_sigma=spec.noise_sigma)
    return {"psf": k, "priors": priors, "n": len(stamps), "render_s": t1 - t0,
            "fit_s": time.perf_counter() - t1,
            "warnings": [str(w.message) for w in caught
                         if issubclass(w.category, plf.CalibrationWarning)]}  # fmt: skip


def _block_task(spec: pm.PrecisionSpec, k: int, b: int, priors, stamp: int,
                threads: int | None):  # fmt: skip
    """Render main block ``b`` (PSF ``k``), ``measure_stamps`` it, reduce it (a worker)."""
    if threads:
        _threads(threads)
    t0 = time.perf_counter()
    stamps, psf, truth = pm.render_block(spec, k, b, stamp_size=stamp)
    n, R = stamps.shape[:2]
    t1 = time.perf_counter()
    tab = plf.measure_stamps(stamps.reshape(n * R, stamp, stamp), psf,
                             noise_sigma=spec.noise_sigma, priors=priors)  # fmt: skip
    t2 = time.perf_counter()
    api = np.column_stack([np.asarray(tab[c], float) for c in ("e1", "e2", "sens1", "sens2")])
    usable = ((np.asarray(tab["flags"]) == 0) & (np.asarray(tab["weight"]) > 0)
              & np.isfinite(api).all(axis=1))  # fmt: skip
    rk = np.tile(np.arange(R), n)  # rendering index of each row
    Q = np.full((n * R, 12), np.nan)
    lnL = np.asarray(tab["lnL"], dtype=float)
    for ks, sign in zip(_shear_sets(R), (1.0, -1.0), strict=True):
        sel = usable & np.isin(rk, ks)
        if sel.any():
            Q[sel] = pm.reduce_likelihoods(lnL[sel], tab.meta["egrid"], tab.meta["prior"],
                                           (sign * spec.g, sign * spec.g),
                                           refine=tab.meta["refine"])  # fmt: skip
    diff = float(np.max(np.abs(Q[usable, :4] - api[usable]))) if usable.any() else 0.0
    Q[usable, :4] = api[usable]  # the ratio estimator from the table's own columns
    return {"psf": k, "block": b, "Q": Q.reshape(n, R, 12), "usable": usable.reshape(n, R),
            "e_int": np.column_stack([truth["e1_int"], truth["e2_int"]]),
            "render_s": t1 - t0, "fit_s": t2 - t1, "diff": diff}  # fmt: skip


def _mean_row(rows: list[dict], est: str) -> dict:
    t = [r for r in rows if r["estimator"] == est]
    out = {"group": "mean of PSFs", "estimator": est, "n_gal": sum(r["n_gal"] for r in t),
           "controlled": all(r["controlled"] for r in t)}  # fmt: skip
    for q in ("m1", "m2", "c1", "c2"):
        out[q] = float(np.mean([r[q] for r in t]))
        out[f"{q}_err"] = float(math.sqrt(sum(r[f"{q}_err"] ** 2 for r in t)) / len(t))
    return out


def _fmt(v: float, e: float, digits: int = 4) -> str:
    return f"{v:+.{digits}f} ± {e:.{digits}f}"


def _print_rows(label: str, rows: list[dict]) -> None:
    print(f"{'path':<10} {'PSF':<13} {'estimator':<12} {'m1':>17} {'m2':>17} {'c1':>19} "
          f"{'c2':>19} {'galaxies':>9} cv")  # fmt: skip
    for r in rows:
        print(f"{label:<10} {r['group']:<13} {r['estimator']:<12} "
              f"{_fmt(r['m1'], r['m1_err']):>17} {_fmt(r['m2'], r['m2_err']):>17} "
              f"{_fmt(r['c1'], r['c1_err'], 5):>19} {_fmt(r['c2'], r['c2_err'], 5):>19} "
              f"{r['n_gal']:>9} {'yes' if r['controlled'] else 'no'}")  # fmt: skip


def _map(pool, fn, calls: list[tuple]) -> list:
    """``fn(*call)`` for every call: on the pool's workers, one thread each, or here."""
    if pool is None:
        return [fn(*call, None) for call in calls]
    futs = [pool.submit(fn, *call, 1) for call in calls]
    for f in as_completed(futs):
        f.result()  # a worker's exception surfaces as soon as it happens
    return [f.result() for f in futs]


def run_api(spec: pm.PrecisionSpec, jobs: int) -> dict:
    """The API path on the precision spec: the per-PSF rows and the timing."""
    stamp = Config().largest_stamp
    npsf = len(spec.psfs)
    names = [p["name"] for p in spec.psfs]
    _threads(jobs)
    t0 = time.perf_counter()
    pool = (ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn"))
            if jobs > 1 else None)  # fmt: skip  # spawn: numba's threads do not survive a fork
    try:
        # calibration: one PSF per worker (here, with the jobs' threads, for one PSF)
        cal = _map(pool if npsf > 1 else None, _calibration_task,
                   [(spec, k, stamp) for k in range(npsf)])
        priors = [c["priors"] for c in sorted(cal, key=lambda c: c["psf"])]
        t_cal = time.perf_counter() - t0
        for c in cal:
            print(f"calibrate [{names[c['psf']]}]: {c['n']} stamps, {c['priors']!r}")
            for w in c["warnings"]:
                print(f"  CalibrationWarning: {w}")
        nb = -(-spec.ngal // spec.block_size)
        res = _map(pool, _block_task,
                   [(spec, b % npsf, b, priors[b % npsf], stamp) for b in range(nb)])
    finally:
        if pool is not None:
            pool.shutdown()
    t_main = time.perf_counter() - t0 - t_cal
    res.sort(key=lambda r: r["block"])
    Q = np.concatenate([r["Q"] for r in res])
    usable = np.concatenate([r["usable"] for r in res])
    psf = np.concatenate([np.full(len(r["Q"]), r["psf"]) for r in res])
    per_block = -(-spec.block_size // JACKKNIFE_GALAXIES)
    jk = np.concatenate([r["block"] * per_block + np.arange(len(r["Q"])) // JACKKNIFE_GALAXIES
                         for r in res])  # fmt: skip
    e_int = np.concatenate([r["e_int"] for r in res])
    X = pm.shape_controls(e_int[:, 0], e_int[:, 1])
    tab = pm.bias_table(Q, usable, jk, spec.g, groups={n: psf == k for k, n in enumerate(names)},
                        controls=X)  # fmt: skip
    rows = [dict(zip(tab.colnames, r, strict=True)) for r in tab if r["estimator"] in ESTIMATORS]
    rows.sort(key=lambda r: (names.index(r["group"]), ESTIMATORS.index(r["estimator"])))
    if npsf > 1:
        rows += [_mean_row(rows, est) for est in ESTIMATORS]
    return {"rows": rows, "t_cal": t_cal, "t_main": t_main,
            "n_paired": int(usable.all(axis=1).sum()), "n_gal": len(Q),
            "render_s": sum(r["render_s"] for r in res) + sum(c["render_s"] for c in cal),
            "fit_s": sum(r["fit_s"] for r in res) + sum(c["fit_s"] for c in cal),
            "diff": max(r["diff"] for r in res)}  # fmt: skip


def run_precision(spec: pm.PrecisionSpec, jobs: int) -> dict:
    """``pylensfit_validation.precision.precision`` on the spec: its per-PSF rows and timing."""
    res = pm.precision(spec, jobs=jobs, progress=False)
    names = [p["name"] for p in spec.psfs]
    sel = (((res["breakdown"] == "psf") | ((res["breakdown"] == "all")
                                           & (res["group"] == "mean of PSFs")))
           & np.isin(res["estimator"], ESTIMATORS))  # fmt: skip
    rows = [dict(zip(res.colnames, r, strict=True)) for r in res[sel]]
    order = [*names, "mean of PSFs"]
    rows.sort(key=lambda r: (order.index(r["group"]), ESTIMATORS.index(r["estimator"])))
    return {"rows": rows, "timing": res.meta["timing"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ngal", type=int, default=20000, help="galaxies of the main sample "
                    "(x4 renderings), over all PSFs")  # fmt: skip
    ap.add_argument("--ncal", type=int, default=12000,
                    help="unsheared calibration galaxies, over all PSFs")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--psf", nargs="+", default=None,
                    help="PSF names (default all four of the precision mode: "
                    + ", ".join(p["name"] for p in pm.PRECISION_PSFS) + ")")  # fmt: skip
    ap.add_argument("--g", type=float, default=None, help="shear per component (0.02)")
    ap.add_argument("--noise-twins", action="store_true",
                    help="eight renderings per galaxy (the precision mode's --noise-twins)")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--compare", action="store_true",
                    help="run validate --precision's precision() on the same spec as well")
    args = ap.parse_args(argv)
    spec = pm.spec_with(ngal=args.ngal, ncal=args.ncal, seed=args.seed, psfs=args.psf,
                        g=args.g, noise_twins=args.noise_twins or None)  # fmt: skip
    names = [p["name"] for p in spec.psfs]
    short = len(names) * spec.block_size
    if spec.ngal <= short - spec.block_size or spec.ncal <= short - spec.block_size:
        ap.error(f"blocks of {spec.block_size} galaxies go to the PSFs in turn: --ngal and "
                 f"--ncal must exceed {short - spec.block_size} for every one of the "
                 f"{len(names)} PSFs to get galaxies")  # fmt: skip
    print(f"precision population: {spec.ngal} galaxies x {8 if spec.noise_twins else 4} "
          f"renderings, {spec.ncal} calibration galaxies, PSFs {', '.join(names)}, "
          f"g = ±({spec.g}, {spec.g}), seed {spec.seed}; stamps "
          f"{Config().largest_stamp} px; {args.jobs} job(s)", flush=True)  # fmt: skip
    api = run_api(spec, args.jobs)
    t_api = api["t_cal"] + api["t_main"]
    print(f"\nAPI path: {api['n_paired']} of {api['n_gal']} galaxies usable in all their "
          f"renderings; largest |table - reduction| of e, sens: {api['diff']:.1e}")
    _print_rows("api", api["rows"])
    print(f"time {t_api:.0f} s (calibration {api['t_cal']:.0f} s, main pass "
          f"{api['t_main']:.0f} s): {spec.ngal / api['t_main']:.2f} galaxies/s in the main "
          f"pass, {spec.ngal / t_api:.2f} galaxies/s overall; CPU {api['render_s']:.0f} s "
          f"rendering, {api['fit_s']:.0f} s calibrate + measure_stamps", flush=True)  # fmt: skip
    if args.compare:
        t0 = time.perf_counter()
        ref = run_precision(spec, args.jobs)
        t_ref = time.perf_counter() - t0
        print()
        _print_rows("precision", ref["rows"])
        print("\ndifference api - precision (same renderings):")
        print(f"{'PSF':<13} {'estimator':<12} {'dm1':>9} {'dm2':>9} {'dc1':>9} {'dc2':>9}")
        key = {(r["group"], r["estimator"]): r for r in ref["rows"]}
        for r in api["rows"]:
            p = key.get((r["group"], r["estimator"]))
            if p is None:
                continue
            d = [r[q] - p[q] for q in ("m1", "m2", "c1", "c2")]
            print(f"{r['group']:<13} {r['estimator']:<12} "
                  + " ".join(f"{v:+9.1e}" for v in d))  # fmt: skip
        tim = ref["timing"]
        print(f"precision(): {t_ref:.0f} s (calibration {tim['calibration_s']:.0f} s, main "
              f"pass {tim['main_s']:.0f} s): {tim['galaxies_per_s']:.2f} galaxies/s in the "
              f"main pass, {spec.ngal / t_ref:.2f} galaxies/s overall")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
