"""Throughput and memory of the likelihood engine, next to GalSim HSM and AnaCal FPFS.

For one profile's grid (``Config(model=--model)``: de = 0.1, sizes up to 10 px; de
Vaucouleurs by default) on 32 x 32 stamps this prints galaxies per second of
:func:`pylensfit.fit_stamps` with 1 and 2 single-threaded worker processes and with one
multithreaded process, the peak resident memory of every process, and, measured in the
same run on the same stamps, GalSim HSM REGAUSS (``galsim.hsm.EstimateShear``) and,
where ``pip install anacal`` works, AnaCal's FPFS.

Usage::

    python benchmarks/bench_likelihood.py                  # 4000 galaxies, ~2-3 min
    python benchmarks/bench_likelihood.py --ngal 1000 --jobs 1,2,4 --model exponential
    python benchmarks/bench_likelihood.py --install-anacal # pip install anacal first

What is timed
-------------
* rendering the galaxies with GalSim is not timed;
* pylensfit, N processes: the stamps are split into N contiguous chunks, one per
  ``spawn`` worker whose BLAS and numba are pinned to one thread and which has already
  made one small warm-up fit (numba kernels loaded, model bank built). All workers
  then wait on a barrier; each times its own ``fit_stamps`` call. ``gal/s`` is all
  galaxies over the slowest worker's time; ``wall`` is the main process's wall time
  from the barrier's release to the last result received;
* pylensfit, threaded: one ``fit_stamps`` call on all stamps in the main process with
  numba and BLAS set to ``--threads`` threads (after a warm-up call);
* HSM REGAUSS: one ``EstimateShear`` call per stamp in the main process (one thread);
* AnaCal FPFS: one ``anacal.fpfs.process_image`` call on a mosaic of the stamps
  (64 per row) with a detection list at the stamp centres, after a warm-up call;
  building the mosaic is not timed. Once without and once with the pure-noise image
  that AnaCal uses for its noise-bias correction (which measures twice).

Peak resident memory is ``getrusage(RUSAGE_SELF).ru_maxrss``: for the worker rows, the
largest of the workers (and the sum over them); for the rows run in the main process
it is the main process's high-water mark after that step, which also holds the
simulated stamps and everything run before it (the baseline is printed).
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import importlib
import multiprocessing as mp
import os
import resource
import subprocess
import sys
import time

import numpy as np

STAMP = 32
NOISE_SIGMA = 1.0
BARRIER_TIMEOUT = 600.0

# --------------------------------------------------------------------------------------
# simulation (not timed)


def simulate(ngal: int, seed: int, model: str):
    """STEP-like galaxies: true e (shear convention), S/N and stamps, and the PSF image."""
    import galsim

    rng = np.random.default_rng(seed)
    psf = galsim.Moffat(beta=3.5, fwhm=3.0).shear(g1=0.03, g2=0.01)
    psf_img = psf.drawImage(nx=STAMP, ny=STAMP, scale=1.0, offset=(0.5, 0.5)).array
    # |e| < 0.6 uniform over the disc, half-light radius 1.5-4 px, S/N 10-100
    # (log-uniform), centre within +-0.5 px of element [16, 16]
    emod = 0.6 * np.sqrt(rng.uniform(size=ngal))
    phi = rng.uniform(0.0, np.pi, size=ngal)
    e_true = np.column_stack([emod * np.cos(2 * phi), emod * np.sin(2 * phi)])
    hlr = rng.uniform(1.5, 4.0, size=ngal)
    snr = np.exp(rng.uniform(np.log(10.0), np.log(100.0), size=ngal))
    offs = rng.uniform(-0.5, 0.5, size=(ngal, 2))
    stamps = np.empty((ngal, STAMP, STAMP))
    for i in range(ngal):
        if model == "devaucouleurs":
            gal = galsim.DeVaucouleurs(half_light_radius=hlr[i], trunc=8.0 * hlr[i])
        else:
            gal = galsim.Exponential(half_light_radius=hlr[i])
        gal = gal.shear(g1=e_true[i, 0], g2=e_true[i, 1])
        img = galsim.Convolve(gal, psf).withFlux(1.0)
        off = (0.5 + offs[i, 0], 0.5 + offs[i, 1])
        a = img.drawImage(nx=STAMP, ny=STAMP, scale=1.0, offset=off).array
        # matched-filter S/N = flux * sqrt(sum a^2) / sigma
        stamps[i] = a * (snr[i] * NOISE_SIGMA / np.sqrt(np.sum(a * a)))
    stamps += rng.normal(scale=NOISE_SIGMA, size=stamps.shape)
    return e_true, snr, stamps, psf_img


def maxrss_mib() -> float:
    """Peak resident memory of this process in MiB (ru_maxrss is KiB on Linux)."""
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kib / (1024.0 * 1024.0) if sys.platform == "darwin" else kib / 1024.0


# --------------------------------------------------------------------------------------
# pylensfit in worker processes

_W: dict = {}


def _worker_init(barrier, model: str, warm_stamps: np.ndarray, psf_img: np.ndarray) -> None:
    """Pin BLAS and numba to one thread, then warm up (numba kernels, model bank)."""
    import numba
    from threadpoolctl import threadpool_limits

    from pylensfit import Config, fit_stamps

    _W["limits"] = threadpool_limits(1)  # keep a reference: the limit stays in force
    numba.set_num_threads(1)
    _W["barrier"] = barrier
    _W["config"] = Config(model=model)
    fit_stamps(warm_stamps, psf_img, NOISE_SIGMA, config=_W["config"])


def _worker_fit(stamps: np.ndarray, psf_img: np.ndarray):
    """Wait for all workers, then time one ``fit_stamps`` call on this chunk."""
    from pylensfit import fit_stamps

    _W["barrier"].wait(timeout=BARRIER_TIMEOUT)
    t0 = time.perf_counter()
    fits = fit_stamps(stamps, psf_img, NOISE_SIGMA, config=_W["config"])
    dt = time.perf_counter() - t0
    return dt, fits.lnL, maxrss_mib()


def bench_processes(nproc: int, stamps, psf_img, model: str) -> dict:
    ctx = mp.get_context("spawn")
    barrier = ctx.Barrier(nproc + 1)  # the workers and this process
    chunks = np.array_split(stamps, nproc)
    warm = np.ascontiguousarray(stamps[:8])
    with cf.ProcessPoolExecutor(
        max_workers=nproc,
        mp_context=ctx,
        initializer=_worker_init,
        initargs=(barrier, model, warm, psf_img),
    ) as ex:
        futs = [ex.submit(_worker_fit, np.ascontiguousarray(c), psf_img) for c in chunks]
        try:
            barrier.wait(timeout=BARRIER_TIMEOUT)
        except Exception:
            for f in futs:  # a worker died: show why
                if f.done() and f.exception() is not None:
                    raise f.exception() from None
            raise
        t0 = time.perf_counter()
        res = [f.result() for f in futs]
        wall = time.perf_counter() - t0
    times = [r[0] for r in res]
    rss = [r[2] for r in res]
    lnL = np.concatenate([r[1] for r in res])
    return {
        "method": "pylensfit",
        "procs": nproc,
        "threads": 1,
        "rate": len(stamps) / max(times),
        "wall": wall,
        "rss": f"{max(rss):.0f}" + (f" (sum {sum(rss):.0f})" if nproc > 1 else ""),
        "fail": int((~np.isfinite(lnL).all(axis=1)).sum()),
        "lnL": lnL,
        "times": times,
    }


# --------------------------------------------------------------------------------------
# pylensfit multithreaded, HSM, FPFS: in this process


def bench_threads(nthreads: int, stamps, psf_img, model: str) -> tuple[dict, object]:
    import numba
    from threadpoolctl import threadpool_limits

    from pylensfit import Config, fit_stamps

    nthreads = min(nthreads, numba.config.NUMBA_NUM_THREADS)
    cfg = Config(model=model)
    with threadpool_limits(nthreads):
        numba.set_num_threads(nthreads)
        fit_stamps(stamps[:8], psf_img, NOISE_SIGMA, config=cfg)  # warm-up
        t0 = time.perf_counter()
        fits = fit_stamps(stamps, psf_img, NOISE_SIGMA, config=cfg)
        dt = time.perf_counter() - t0
    row = {
        "method": "pylensfit",
        "procs": 1,
        "threads": nthreads,
        "rate": len(stamps) / dt,
        "wall": dt,
        "rss": f"{maxrss_mib():.0f} (main)",
        "fail": int((~np.isfinite(fits.lnL).all(axis=1)).sum()),
    }
    return row, fits


def bench_hsm(stamps, psf_img) -> tuple[dict, np.ndarray]:
    import galsim
    from threadpoolctl import threadpool_limits

    psf_im = galsim.Image(psf_img)
    e = np.full((len(stamps), 2), np.nan)
    fail = 0
    with threadpool_limits(1):
        galsim.hsm.EstimateShear(galsim.Image(stamps[0]), psf_im, shear_est="REGAUSS",
                                 strict=False)  # fmt: skip
        t0 = time.perf_counter()
        for i in range(len(stamps)):
            r = galsim.hsm.EstimateShear(galsim.Image(stamps[i]), psf_im, shear_est="REGAUSS",
                                         strict=False)  # fmt: skip
            if r.error_message or r.correction_status != 0:
                fail += 1
            else:
                e[i] = r.corrected_e1, r.corrected_e2
        dt = time.perf_counter() - t0
    row = {"method": "HSM REGAUSS", "procs": 1, "threads": 1, "rate": len(stamps) / dt,
           "wall": dt, "rss": f"{maxrss_mib():.0f} (main)", "fail": fail}  # fmt: skip
    # distortion (a^2-b^2)/(a^2+b^2) -> the shear convention (a-b)/(a+b) of the truth
    emod = np.hypot(e[:, 0], e[:, 1])
    return row, e / (1.0 + np.sqrt(np.clip(1.0 - emod**2, 0.0, None)))[:, None]


def import_anacal(install: bool):
    """``anacal`` or a reason string; with ``install``, try ``pip install anacal`` once."""
    try:
        return importlib.import_module("anacal")
    except ImportError:
        pass
    if not install:
        return "anacal not installed: pip install anacal (or pass --install-anacal)"
    print("pip install anacal ...", flush=True)
    p = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "anacal"],
                       capture_output=True, text=True)  # fmt: skip
    importlib.invalidate_caches()
    try:
        return importlib.import_module("anacal")
    except ImportError as err:
        tail = (p.stderr or p.stdout).strip().splitlines()[-1:] or [""]
        return f"anacal: pip install failed (rc {p.returncode}): {tail[0]} [{err}]"


def bench_fpfs(anacal, stamps, psf_img, seed: int) -> tuple[list[dict], np.ndarray]:
    """AnaCal FPFS on a mosaic of the stamps, measured at the stamp centres."""
    ngal = len(stamps)
    ncol = 64
    nrow = -(-ngal // ncol)
    full = np.zeros((nrow * ncol, STAMP, STAMP))
    full[:ngal] = stamps
    mosaic = full.reshape(nrow, ncol, STAMP, STAMP).transpose(0, 2, 1, 3)
    mosaic = np.ascontiguousarray(mosaic.reshape(nrow * STAMP, ncol * STAMP))
    iy, ix = np.divmod(np.arange(ngal), ncol)
    det = np.zeros(ngal, dtype=[("y", "f8"), ("x", "f8")])
    det["y"] = iy * STAMP + STAMP // 2
    det["x"] = ix * STAMP + STAMP // 2
    noise = np.random.default_rng(seed + 1000).normal(scale=NOISE_SIGMA, size=mosaic.shape)
    # sigma_shapelets in arcsec = px here (pixel_scale 1); mag_zero = AnaCal's reference
    # zero point, so its c0 is used as given
    cfg = anacal.fpfs.FpfsConfig(npix=STAMP, sigma_shapelets1=2.0)
    mag_zero = float(anacal.task.THRESHOLD_REF_MAG_ZERO)

    def call(det_, noise_array):
        return anacal.fpfs.process_image(
            fpfs_config=cfg, pixel_scale=1.0, noise_variance=NOISE_SIGMA**2,
            mag_zero=mag_zero, gal_array=mosaic, psf_array=psf_img, detection=det_,
            noise_array=noise_array,
        )  # fmt: skip

    rows = []
    out = None
    for label, noise_array in (("AnaCal FPFS", None), ("AnaCal FPFS+renoise", noise)):
        call(det[:4], noise_array)  # warm-up (shapelet basis)
        t0 = time.perf_counter()
        cat = call(det, noise_array)
        dt = time.perf_counter() - t0
        e1 = np.asarray(cat["fpfs1_e1"])
        rows.append({"method": label, "procs": 1, "threads": 1, "rate": ngal / dt,
                     "wall": dt, "rss": f"{maxrss_mib():.0f} (main)",
                     "fail": int((~np.isfinite(e1)).sum())})  # fmt: skip
        if out is None:
            out = np.column_stack([e1, np.asarray(cat["fpfs1_e2"])])
    return rows, out


# --------------------------------------------------------------------------------------


def corr(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman rank correlation over the finite pairs (HSM's |e| can exceed 1)."""
    from scipy.stats import spearmanr

    ok = np.isfinite(a) & np.isfinite(b)
    return float(spearmanr(a[ok], b[ok])[0]) if ok.sum() > 2 else float("nan")


def likelihood_mean_e(fits) -> np.ndarray:
    lnL = fits.lnL.astype(float)
    w = np.exp(lnL - np.nanmax(lnL, axis=1, keepdims=True))
    w /= w.sum(axis=1, keepdims=True)
    return w @ fits.egrid


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--ngal", type=int, default=4000, help="number of galaxies (4000)")
    p.add_argument("--seed", type=int, default=1, help="random seed (1)")
    p.add_argument("--model", default="devaucouleurs", choices=["devaucouleurs", "exponential"],
                   help="simulated profile and pylensfit model (devaucouleurs)")  # fmt: skip
    p.add_argument("--jobs", default="1,2", help="worker-process counts to time (1,2)")
    p.add_argument("--threads", type=int, default=2,
                   help="threads of the single-process multithreaded run (2)")  # fmt: skip
    p.add_argument("--install-anacal", action="store_true",
                   help="pip install anacal if it is missing")  # fmt: skip
    args = p.parse_args(argv)
    jobs = [int(j) for j in args.jobs.split(",") if j.strip()]

    import galsim
    import numba

    import pylensfit
    from pylensfit import Config

    cfg = Config(model=args.model)
    n_e = len(pylensfit.ellipticity_grid(cfg.e_step, emax=cfg.e_max))
    n_r = int(round((cfg.r_max - max(cfg.r_min, cfg.r_step)) / cfg.r_step)) + 1
    print(f"pylensfit {pylensfit.__version__} ({os.path.dirname(pylensfit.__file__)})")
    print(f"GalSim {galsim.__version__}, numpy "
          f"{np.__version__}, numba {numba.__version__}, {os.cpu_count()} CPUs "
          f"(load {os.getloadavg()[0]:.2f})")  # fmt: skip
    print(f"grid: de={cfg.e_step}, r={cfg.r_min:g}..{cfg.r_max:g} px step {cfg.r_step} "
          f"({n_e} e x {n_r} r + point source = {n_e * n_r + 1} models), "
          f"{cfg.stamp_size}x{cfg.stamp_size} stamps, model {cfg.model}")  # fmt: skip

    t0 = time.perf_counter()
    e_true, _snr, stamps, psf_img = simulate(args.ngal, args.seed, args.model)
    base_rss = maxrss_mib()
    print(f"simulated {args.ngal} {args.model} galaxies (|e|<0.6, hlr 1.5-4 px, S/N 10-100, "
          f"Moffat PSF FWHM 3 px) in {time.perf_counter() - t0:.1f} s (not timed); "
          f"main-process RSS after simulation {base_rss:.0f} MiB")  # fmt: skip

    rows = []
    print("HSM REGAUSS ...", flush=True)
    row, e_hsm = bench_hsm(stamps, psf_img)
    rows.append(row)

    anacal = import_anacal(args.install_anacal)
    e_fpfs = None
    anacal_note = None
    if isinstance(anacal, str):
        anacal_note = anacal
    else:
        print(f"AnaCal {anacal.__version__} FPFS ...", flush=True)
        try:
            fpfs_rows, e_fpfs = bench_fpfs(anacal, stamps, psf_img, args.seed)
            rows.extend(fpfs_rows)
        except Exception as err:  # its API changes between versions
            anacal_note = f"AnaCal {anacal.__version__} FPFS skipped: {err!r}"
    if anacal_note:
        print(anacal_note)

    print(f"pylensfit, 1 process x {args.threads} threads ...", flush=True)
    row, fits = bench_threads(args.threads, stamps, psf_img, args.model)
    rows.append(row)
    lnL_ref = fits.lnL

    for nproc in jobs:
        print(f"pylensfit, {nproc} process(es) x 1 thread ...", flush=True)
        row = bench_processes(nproc, stamps, psf_img, args.model)
        times = ", ".join(f"{t:.2f}" for t in row["times"])
        near = lnL_ref > -20.0  # the cells that matter; float32 rounding far below the peak
        dmax = np.max(np.abs(row["lnL"] - lnL_ref)[near]) if near.any() else np.nan
        print(f"  worker fit times [s]: {times}; max |lnL - threaded lnL| where lnL > -20: "
              f"{dmax:.1e}")  # fmt: skip
        rows.append(row)

    order = {"pylensfit": 0}
    rows.sort(key=lambda r: (order.get(r["method"], 1), r["procs"], r["threads"]))
    print()
    print(f"{args.ngal} galaxies, {STAMP}x{STAMP} stamps, model {args.model}")
    hdr = (f"{'method':<20} {'procs x threads':>15} {'gal/s':>9} {'wall s':>8} "
           f"{'peak RSS MiB':>18} {'failures':>8}")  # fmt: skip
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        pt = f"{r['procs']} x {r['threads']}"
        print(f"{r['method']:<20} {pt:>15} {r['rate']:9.0f} {r['wall']:8.2f} {r['rss']:>18} "
              f"{r['fail']:8d}")  # fmt: skip
    if anacal_note:
        print(f"{'AnaCal FPFS':<20} {anacal_note}")
    print(f"(main-process RSS after simulation, before any measurement: {base_rss:.0f} MiB; "
          "pylensfit N x 1 gal/s = all galaxies / slowest worker's fit time)")  # fmt: skip

    e_plf = likelihood_mean_e(fits)
    c_pt = corr(e_plf[:, 0], e_true[:, 0])
    c_ht = corr(e_hsm[:, 0], e_true[:, 0])
    c_ph = corr(e_plf[:, 0], e_hsm[:, 0])
    msg = (f"sanity, rank corr(e1): pylensfit likelihood-mean vs true {c_pt:.3f}, HSM vs true "
           f"{c_ht:.3f}, pylensfit vs HSM {c_ph:.3f}")  # fmt: skip
    if e_fpfs is not None:
        msg += f", FPFS vs true {corr(e_fpfs[:, 0], e_true[:, 0]):.3f}"
    print(msg)
    flagged = int((fits.flags != 0).sum())
    nstar = int(fits.is_star.sum())
    print(f"pylensfit flags != 0: {flagged} (of which STAR: {nstar}); load average now "
          f"{os.getloadavg()[0]:.2f} (rerun if other work shared the CPUs)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
