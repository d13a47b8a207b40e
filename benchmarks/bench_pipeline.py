"""End-to-end throughput of :func:`pylensfit.measure`: FITS images in, FITS catalogue out.

On simulated 4k x 4k fields this prints galaxies per second from the FITS images to the
written catalogue with 1 and 2 jobs, the peak resident memory, and where the time goes
(reading + detection, PSF, stamps, fit; then the prior, shapes and writing in the
parent), next to GalSim HSM REGAUSS run on stamps cut from the same images about the
same galaxies.

Usage::

    python benchmarks/bench_pipeline.py                 # 2 x 4096^2 fields, Config()
    python benchmarks/bench_pipeline.py --method paper  # Config.paper(), one pass
    python benchmarks/bench_pipeline.py --size 1024     # quick
    python benchmarks/bench_pipeline.py --jobs 1,2 --threads 1 --keep /tmp/bench-fields
    python benchmarks/bench_pipeline.py --priors sample  # calibrate once, one pass timed

The fields
----------
``--nimages`` independent fields of ``--size`` x ``--size`` pixels (default two 4096^2
fields, ~10,200 objects each at the default ``--spacing`` of 40 px, 8% of them stars),
rendered with GalSim (:func:`pylensfit_validation.simulate.simulate_field`, not timed), plus one
1024^2 star field (``star_fraction=1``) passed as ``stars=``. Two whole fields rather
than one field cut into quadrants: ``measure`` parallelises over images, so 2 jobs need
at least 2 images, and whole fields keep the per-image costs (background, detection,
PSF stacking) at the size of a real 4k detector without seams whose objects would be
flagged EDGE. gal/s hardly depends on how the area is split (per-image costs scale with
the area).

What is timed
-------------
Each run is one ``measure(images, stars=[star field], config=Config(),
output=<tmp>/catalog.fits, jobs=N)`` call (the calibration recipe's passes, every prior
estimated from the fields' galaxies; with ``--method paper``, ``config=Config.paper(model=
...), prior=Prior()``, one pass) in a fresh ``spawn`` process
(so that its peak RSS is its own), after an untimed warm-up ``measure`` of a 512^2 field
in that process (numba kernels loaded from their cache, model bank built). ``wall`` is
the wall time of the call, output written. With N > 1 the pool's workers are new
processes and pay their own start-up (imports, numba cache load, model bank) inside
``wall``. ``--prior estimate`` lets ``measure`` estimate the prior instead (its cost is
printed separately either way). ``--priors FILE`` gives every run saved priors
(``measure(priors=FILE)``: one measuring pass); ``--priors sample`` first estimates them
with :func:`pylensfit.calibrate_images` on the same images (``Config.calibration_sample``
objects, timed on its own and printed), as a survey calibrates once and measures every
image in one pass.

``cat.meta["timing"]`` sums the per-image seconds of the stages "read+detect", "psf",
"stamps", "fit": with N jobs these are worker seconds (N workers run at once), so
``other = wall - sum / min(N, nimages)`` is an estimate of the rest: the star field's
PSF, spawning the pool, assembling the catalogue with the prior and shapes, writing. The
parent's share is timed separately after the run (``estimate_prior``, ``shapes``,
``write_catalogue`` on the run's catalogue), and "read+detect" is split into reading,
background and detection + photometry on the first image.

``--threads`` (default: numba's and BLAS's defaults, all cores) sets the threads of the
``jobs=1`` run, which fits in the calling process; the pool's workers always run one
thread each.

Peak resident memory is ``getrusage().ru_maxrss`` of the run's process (``RUSAGE_SELF``,
warm-up included) and of its largest pool worker (``RUSAGE_CHILDREN``).

HSM REGAUSS (``galsim.hsm.EstimateShear``) runs in this process, one thread, on 32 x 32
stamps cut from the images about the catalogue positions of the measured galaxies, sky
subtracted with the median of each stamp's border, with the image's PSF from the
catalogue; only the ``EstimateShear`` calls are timed.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import multiprocessing as mp
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent / "studies"))
from precision_ab import _kv  # noqa: E402  (KEY=VALUE strings as Config changes)

STAGES = ("read+detect", "psf", "stamps", "fit")
STAR_SIZE = 1024
WARM_SIZE = 512


def rss_mib(who=resource.RUSAGE_SELF) -> float:
    """Peak resident memory in MiB (ru_maxrss is KiB on Linux, bytes on macOS)."""
    v = resource.getrusage(who).ru_maxrss
    return v / 2**20 if sys.platform == "darwin" else v / 1024.0


def load() -> str:
    return "/".join(f"{v:.2f}" for v in os.getloadavg())


# --------------------------------------------------------------------------------------
# simulation (not timed): one spawn process per field


def _simulate(path: str, size: int, spacing: float, model: str, seed: int, stars: bool) -> int:
    from pylensfit_validation.simulate import FieldSpec, simulate_field, write_field

    extra = {"star_fraction": 1.0} if stars else {}
    spec = FieldSpec(size=size, spacing=spacing, model=model, **extra)
    img, w, truth = simulate_field(spec, seed=seed)
    write_field(path, img, w, spec, truth=None if stars else truth)
    return len(truth)


def simulate(work: Path, args) -> tuple[list[str], str, str]:
    images = [str(work / f"field_{k}.fits") for k in range(args.nimages)]
    stars = str(work / "stars.fits")
    warm = str(work / "warmup.fits")
    jobs = [(p, args.size, args.spacing, args.model, args.seed + k, False)
            for k, p in enumerate(images)]  # fmt: skip
    jobs += [(stars, STAR_SIZE, args.spacing, args.model, args.seed + 1000, True),
             (warm, WARM_SIZE, args.spacing, args.model, args.seed + 2000, False)]  # fmt: skip
    nproc = min(len(jobs), os.cpu_count() or 1)
    t0 = time.perf_counter()
    with cf.ProcessPoolExecutor(max_workers=nproc, mp_context=mp.get_context("spawn")) as ex:
        n = list(ex.map(_simulate, *zip(*jobs, strict=True)))
    print(f"simulated {args.nimages} x {args.size}^2 {args.model} fields ({n[0]} objects each, "
          f"~8% stars), a {STAR_SIZE}^2 star field ({n[-2]} stars) and a {WARM_SIZE}^2 warm-up "
          f"field with GalSim in {time.perf_counter() - t0:.1f} s on {nproc} processes "
          f"(not timed) -> {work}", flush=True)  # fmt: skip
    return images, stars, warm


# --------------------------------------------------------------------------------------
# one timed measure() in a fresh process


_KEEP: dict = {}


def _config(method: str, model: str, changes: dict | None = None):
    """``Config()`` (the recipe: every prior estimated in the run) or ``Config.paper``,
    with ``changes`` (``--set``) applied."""
    from pylensfit import Config

    if method == "default":
        return Config(**(changes or {}))
    fit_model = "devaucouleurs" if model == "mixed" else model
    return Config.paper(model=fit_model, **(changes or {}))


def _run(images, stars, warm, out, jobs, model, prior_mode, threads, extras, method, changes,
         priors=None):
    import numba

    import pylensfit
    from pylensfit import Prior

    if threads:
        from threadpoolctl import threadpool_limits

        _KEEP["limits"] = threadpool_limits(threads)  # a reference keeps the limit in force
        numba.set_num_threads(threads)

    cfg = _config(method, model, changes)
    prior = Prior() if prior_mode == "fixed" and method == "paper" else None
    pylensfit.measure([warm], stars=[stars], config=cfg, prior=Prior(), output=out + ".warm",
                      overwrite=True, jobs=1, progress=False)  # fmt: skip
    t0 = time.perf_counter()
    cat = pylensfit.measure(images, stars=[stars], config=cfg, prior=prior, output=out,
                            overwrite=True, jobs=jobs, progress=False,
                            priors=priors)  # fmt: skip
    wall = time.perf_counter() - t0
    res = {
        "wall": wall, "timing": dict(cat.meta["timing"]), "nobj": len(cat),
        "ngal": int(np.sum(np.asarray(cat["weight"]) > 0)),
        "nstar": int(np.sum(np.asarray(cat["fitclass"]) == 1)),
        "rss_self": rss_mib(), "rss_children": rss_mib(resource.RUSAGE_CHILDREN),
        "threads": 1 if jobs > 1 else numba.get_num_threads(),
        "prior": repr(cat.meta["prior"]), "out_mib": os.path.getsize(out) / 2**20,
    }  # fmt: skip
    if not extras:
        return res
    # the parent's share, timed on their own: prior, shapes, writing
    lnL = np.asarray(cat["lnL"])
    egrid = cat.meta["egrid"]
    gal = np.asarray(cat["weight"]) > 0
    t0 = time.perf_counter()
    est = pylensfit.estimate_prior(lnL[gal], egrid, method=cfg.prior_method)
    res["t_prior"] = time.perf_counter() - t0
    res["prior_est"] = repr(est)
    if est.info.get("at_bound"):
        res["prior_est"] += f" (at bound: {est.info['at_bound']})"
    t0 = time.perf_counter()
    pylensfit.shapes(lnL, egrid, est, sensitivity=cfg.sensitivity, refine=cfg.integration_refine)
    res["t_shapes"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pylensfit.write_catalogue(cat, out + ".again", overwrite=True)
    res["t_write"] = time.perf_counter() - t0
    os.remove(out + ".again")
    res["numba_threads"] = numba.get_num_threads()
    res["gal"] = {c: np.asarray(cat[c])[gal] for c in ("image_index", "x", "y", "e1", "e2")}
    res["psf_images"] = np.asarray(cat.meta["psf_images"])
    return res


def timed_run(images, stars, warm, out, jobs, args, extras) -> dict:
    with cf.ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn")) as ex:
        return ex.submit(_run, images, stars, warm, out, jobs, args.model, args.prior,
                         args.threads, extras, args.method, _kv(args.set),
                         args.priors).result()  # fmt: skip


def calibrate_once(images: list[str], stars: str, cfg, jobs: int, work: Path) -> str:
    """The priors of :func:`pylensfit.calibrate_images` on ``images``, saved in ``work``
    (timed here, in this process)."""
    import pylensfit

    t0 = time.perf_counter()
    pri = pylensfit.calibrate_images(images, stars=[stars], config=cfg, jobs=jobs,
                                     progress=False)  # fmt: skip
    t = time.perf_counter() - t0
    path = str(work / "priors.json")
    pri.save(path)
    print(f"calibrate_images, jobs={jobs}: {t:.1f} s on {len(pri.info['sample_images'])} "
          f"of {len(images)} images ({pri.n_galaxies} galaxies), load {load()}",
          flush=True)  # fmt: skip
    return path


# --------------------------------------------------------------------------------------
# peers and details, in this process


def detection_detail(path: str, cfg) -> dict:
    """Split "read+detect" of one image: FITS read, background, detection + photometry."""
    from astropy.io import fits

    from pylensfit.detection import detect, measure_background

    t0 = time.perf_counter()
    with fits.open(path, memmap=False) as h:
        data = np.asarray(h[0].data, dtype=np.float64)
        w = np.asarray(h["WEIGHT"].data, dtype=np.float64)
    t1 = time.perf_counter()
    bad = ~np.isfinite(data) | ~(w > 0)
    bkg = measure_background(data, mask=bad, weight=w, box=cfg.background_box)
    t2 = time.perf_counter()
    det = detect(
        data, weight=w, mask=bad, threshold=cfg.detect_threshold,
        min_area=cfg.detect_min_area, background=bkg, stamp_size=cfg.stamp_size,
    )  # fmt: skip
    t3 = time.perf_counter()
    return {"read": t1 - t0, "background": t2 - t1, "detect": t3 - t2, "n": len(det),
            "rss": rss_mib()}  # fmt: skip


def hsm(images: list[str], gal: dict, psf_images: np.ndarray, stamp: int = 32):
    """HSM REGAUSS on stamps cut about the catalogue positions; e in the shear convention."""
    import galsim
    from astropy.io import fits
    from threadpoolctl import threadpool_limits

    n = len(gal["x"])
    e = np.full((n, 2), np.nan)
    fail = 0
    dt = 0.0
    h = stamp // 2
    for k, path in enumerate(images):
        sel = np.flatnonzero(gal["image_index"] == k)
        if not sel.size:
            continue
        with fits.open(path, memmap=False) as hd:
            data = np.asarray(hd[0].data, dtype=np.float64)
        pad = np.pad(data, stamp, mode="constant", constant_values=np.nan)
        ix = np.rint(gal["x"][sel]).astype(int)
        iy = np.rint(gal["y"][sel]).astype(int)
        off = np.arange(stamp) - h + stamp
        cut = pad[(iy[:, None] + off)[:, :, None], (ix[:, None] + off)[:, None, :]]
        border = np.concatenate([cut[:, :2].reshape(len(sel), -1),
                                 cut[:, -2:].reshape(len(sel), -1),
                                 cut[:, 2:-2, :2].reshape(len(sel), -1),
                                 cut[:, 2:-2, -2:].reshape(len(sel), -1)], axis=1)  # fmt: skip
        cut -= np.nanmedian(border, axis=1)[:, None, None]
        cut = np.nan_to_num(cut)
        psf = galsim.Image(np.ascontiguousarray(psf_images[k], dtype=np.float64))
        # galsim.Image(array) has bounds 1..n: element [j, i] is position (i + 1, j + 1)
        gx = gal["x"][sel] - (ix - h) + 1.0
        gy = gal["y"][sel] - (iy - h) + 1.0
        with threadpool_limits(1):
            # warm-up
            galsim.hsm.EstimateShear(galsim.Image(cut[0]), psf, shear_est="REGAUSS",
                                     strict=False)  # fmt: skip
            t0 = time.perf_counter()
            for j in range(len(sel)):
                r = galsim.hsm.EstimateShear(
                    galsim.Image(cut[j]), psf, shear_est="REGAUSS", strict=False,
                    guess_centroid=galsim.PositionD(gx[j], gy[j]),
                )  # fmt: skip
                if r.error_message or r.correction_status != 0:
                    fail += 1
                else:
                    e[sel[j]] = r.corrected_e1, r.corrected_e2
            dt += time.perf_counter() - t0
    emod = np.hypot(e[:, 0], e[:, 1])  # distortion -> shear convention (a-b)/(a+b)
    e = e / (1.0 + np.sqrt(np.clip(1.0 - emod**2, 0.0, None)))[:, None]
    return {"t": dt, "n": n, "fail": fail, "e": e}


def true_e1(images: list[str], gal: dict) -> np.ndarray:
    """The true (sheared) e1 of the nearest simulated object within 2 px, else NaN."""
    from astropy.table import Table
    from scipy.spatial import cKDTree

    out = np.full(len(gal["x"]), np.nan)
    for k, path in enumerate(images):
        sel = np.flatnonzero(gal["image_index"] == k)
        t = Table.read(path, hdu="TRUTH")
        d, j = cKDTree(np.column_stack([t["x"], t["y"]])).query(
            np.column_stack([gal["x"][sel], gal["y"][sel]]), distance_upper_bound=2.0
        )
        ok = np.isfinite(d)
        out[sel[ok]] = np.asarray(t["e1"])[j[ok]]
    return out


def corr(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.stats import spearmanr

    ok = np.isfinite(a) & np.isfinite(b)
    return float(spearmanr(a[ok], b[ok])[0]) if ok.sum() > 2 else float("nan")


# --------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=int, default=4096, help="field side in pixels (4096)")
    p.add_argument("--nimages", type=int, default=2,
                   help="number of size x size fields (2: one per job with --jobs 2)")  # fmt: skip
    p.add_argument("--jobs", default="1,2", help="jobs values to time (1,2)")
    p.add_argument("--model", default="mixed",
                   choices=["mixed", "exponential", "devaucouleurs", "bulge+disc"],
                   help="FieldSpec.model: the simulated population (mixed: exponential, de "
                        "Vaucouleurs and bulge+disc in turn)")  # fmt: skip
    p.add_argument("--method", choices=["default", "paper"], default="default",
                   help="Config() with every prior estimated in the run (default), or "
                        "Config.paper(model=) (de Vaucouleurs for the mixed population)")
    p.add_argument("--seed", type=int, default=1, help="random seed (1)")
    p.add_argument("--spacing", type=float, default=40.0,
                   help="lattice pitch in px (40: ~10,000 objects per 4096^2 field)")  # fmt: skip
    p.add_argument("--threads", type=int, default=0,
                   help="threads of the jobs=1 run (0: numba/BLAS default)")  # fmt: skip
    p.add_argument("--prior", choices=["fixed", "estimate"], default="fixed",
                   help="with --method paper: prior=Prior() (fixed) or estimated by measure "
                        "(estimate)")  # fmt: skip
    p.add_argument("--priors", metavar="FILE|sample",
                   help="saved priors for every run (one measuring pass), or 'sample': "
                        "estimated first by calibrate_images on the same images")  # fmt: skip
    p.add_argument("--no-hsm", action="store_true", help="skip the HSM REGAUSS peer")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                   help="changes to the method's configuration (r_floor=0)")
    p.add_argument("--keep", metavar="DIR", help="keep the simulated fields and catalogues here")
    args = p.parse_args(argv)
    jobs = [int(j) for j in args.jobs.split(",") if j.strip()]

    import astropy
    import galsim
    import numba
    import sep

    import pylensfit
    cfg = _config(args.method, args.model, _kv(args.set))
    print(f"pylensfit {pylensfit.__version__} ({os.path.dirname(pylensfit.__file__)})")
    print(f"GalSim {galsim.__version__}, sep {sep.__version__}, astropy {astropy.__version__}, "
          f"numpy {np.__version__}, numba {numba.__version__} ({numba.get_num_threads()} "
          f"threads), {os.cpu_count()} CPUs, load {load()}")  # fmt: skip
    print(f"model {cfg.model}, {cfg.stamp_size}x{cfg.stamp_size} stamps, de={cfg.e_step}, "
          f"r={cfg.r_min:g}..{cfg.r_max:g} px step {cfg.r_step}, method {args.method}"
          + (f", prior {args.prior}" if args.method == "paper" else ", every prior estimated"),
          flush=True)  # fmt: skip

    if args.keep:
        work = Path(args.keep)
        work.mkdir(parents=True, exist_ok=True)
    else:
        work = Path(tempfile.mkdtemp(prefix="pylensfit-bench-"))
    try:
        images, stars, warm = simulate(work, args)
        if args.priors == "sample":
            args.priors = calibrate_once(images, stars, cfg, max(jobs), work)
        rows = []
        extras = None
        for nj in jobs:
            print(f"measure, jobs={nj} ...", flush=True)
            out = str(work / f"catalog_jobs{nj}.fits")
            r = timed_run(images, stars, warm, out, nj, args, extras is None)
            r["jobs"] = nj
            rows.append(r)
            if extras is None:
                extras = r
            print(f"  {r['wall']:.1f} s, {r['ngal'] / r['wall']:.0f} gal/s, load {load()}",
                  flush=True)  # fmt: skip

        hs = None
        if not args.no_hsm and extras is not None:
            print(f"HSM REGAUSS on {len(extras['gal']['x'])} galaxies ...", flush=True)
            hs = hsm(images, extras["gal"], extras["psf_images"], cfg.stamp_size)
        hs_rss = rss_mib()
        print("detection detail (first image, outside measure) ...", flush=True)
        det = detection_detail(images[0], cfg)

        # ---------------------------------------------------------------- report
        nimg = len(images)
        print()
        print(f"{nimg} x {args.size}^2 fields + {STAR_SIZE}^2 star field, model {args.model}, "
              f"method {args.method}; FITS in -> FITS catalogue out")  # fmt: skip
        hdr = (f"{'method':<14} {'procs x thr':>11} {'objects':>8} {'galaxies':>8} "
               f"{'wall s':>7} {'gal/s':>7} {'RSS MiB main':>12} {'worker':>7}")  # fmt: skip
        print(hdr)
        print("-" * len(hdr))
        for r in rows:
            pt = f"{r['jobs']} x {r['threads']}"
            wrk = f"{r['rss_children']:.0f}" if r["jobs"] > 1 else "-"
            print(f"{'pylensfit':<14} {pt:>11} {r['nobj']:8d} {r['ngal']:8d} {r['wall']:7.1f} "
                  f"{r['ngal'] / r['wall']:7.0f} {r['rss_self']:12.0f} {wrk:>7}")  # fmt: skip
        if hs is not None:
            print(f"{'HSM REGAUSS':<14} {'1 x 1':>11} {'':>8} {hs['n']:8d} {hs['t']:7.1f} "
                  f"{hs['n'] / hs['t']:7.0f} {hs_rss:12.0f} {'-':>7}   "
                  f"(stamps only; {hs['fail']} failures)")  # fmt: skip

        print()
        print("where the time goes: per-image stages summed over images (worker seconds with "
              "jobs > 1); other = wall - sum / min(jobs, nimages)")  # fmt: skip
        hdr = (f"{'procs x thr':>11} " + " ".join(f"{s:>17}" for s in STAGES)
               + f" {'other':>15} {'wall':>7}")  # fmt: skip
        print(hdr)
        print("-" * len(hdr))
        for r in rows:
            tot = sum(r["timing"][s] for s in STAGES)
            par = min(r["jobs"], nimg)
            other = r["wall"] - tot / par
            cells = " ".join(f"{r['timing'][s]:8.1f} s ({100 * r['timing'][s] / tot:3.0f}%)"
                             for s in STAGES)  # fmt: skip
            pt = f"{r['jobs']} x {r['threads']}"
            print(f"{pt:>11} {cells} {other:6.1f} s ({100 * other / r['wall']:3.0f}%) "
                  f"{r['wall']:7.1f}")  # fmt: skip
        if extras is not None:
            e = extras
            print(f"in the parent after the images (jobs={e['jobs']} run's catalogue, "
                  f"{e['numba_threads']} numba threads): estimate_prior {e['t_prior']:.2f} s on "
                  f"{e['ngal']} galaxies -> {e['prior_est']}; shapes {e['t_shapes']:.2f} s "
                  f"({e['nobj']} rows); write_catalogue {e['t_write']:.2f} s "
                  f"({e['out_mib']:.0f} MiB)")  # fmt: skip
            if args.prior == "fixed" and args.method == "paper":
                print(f"  (the timed runs used prior=Prior(); estimating it in measure adds "
                      f"~{e['t_prior']:.1f} s to wall)")  # fmt: skip
        print(f"read+detect of {Path(images[0]).name} ({det['n']} detections): FITS read "
              f"{det['read']:.2f} s, background (2 passes, sources masked) "
              f"{det['background']:.2f} s, detection + photometry "
              f"{det['detect']:.2f} s; this process's peak RSS {hs_rss:.0f} -> "
              f"{det['rss']:.0f} MiB")  # fmt: skip
        if hs is not None and extras is not None:
            et = true_e1(images, extras["gal"])
            g = extras["gal"]
            print(f"sanity, rank corr(e1): pylensfit posterior mean vs true "
                  f"{corr(g['e1'], et):.3f}, HSM vs true {corr(hs['e'][:, 0], et):.3f}, "
                  f"pylensfit vs HSM {corr(g['e1'], hs['e'][:, 0]):.3f}")  # fmt: skip
        print("peak RSS: main = the run's process (ru_maxrss, warm-up included), worker = its "
              f"largest pool worker; this process now {rss_mib():.0f} MiB; load now {load()} "
              "(rerun if other work shared the CPUs)")  # fmt: skip
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
