"""Throughput and memory of :func:`pylensfit.fit_stamps` on the CPU path and on a JAX
device (``Config(backend="jax")``), next to GalSim HSM REGAUSS, on the same stamps.

The stamps are those of ``bench_likelihood.py`` (32 x 32, |e| < 0.6, half-light radius
1.5-4 px, S/N 10-100, Moffat PSF of FWHM 3 px), the fit the measuring pass of one
configuration (``Config(model=--model)``, the recommended bulge+disc bank by default)
without the stamp tiers (``max_stamp_size=0``: 32-pixel stamps hold no larger tier).

Usage::

    python benchmarks/bench_gpu.py                          # 2000 galaxies, cpu and jax
    python benchmarks/bench_gpu.py --ngal 50000 --backends jax --block-size 2048   # a GPU

On a GPU machine, with JAX's CUDA wheel installed (``pip install -e ".[gpu]"
"jax[cuda12]"``), ``--backends cpu,jax`` times both; JAX reports its device on the
first line. On a machine without a GPU JAX runs on its CPU backend: that number checks
the path and is no measure of a GPU.

What is timed
-------------
* rendering the galaxies with GalSim is not timed;
* each backend: one warm-up ``fit_stamps`` call on the first ``--block-size`` stamps
  (numba kernels loaded, model bank built, the JAX block function compiled for the
  block's shape), then one call on all stamps, timed; ``gal/s`` is all stamps over
  that call's wall time. The CPU path runs in this process with numba on ``--threads``
  threads (its matrix products on one BLAS thread, as ``fit_stamps`` always runs them);
  the JAX path with ``Config(block_size=--block-size)`` (the CPU path with its default
  block), whose blocks are sent to the device before the first result is read;
* HSM REGAUSS: one ``EstimateShear`` call per stamp (one thread), as in
  ``bench_likelihood.py``.

Peak memory: the process's resident high-water mark after each step
(``ru_maxrss``, which includes everything before it; the baseline after the simulation
is printed) and, on a GPU, the device's peak bytes in use (``memory_stats()``).
Agreement: the largest difference of the rows of ``ln L`` within 20 of their peak and of
the likelihood-mean ellipticities between the backends, and with ``--f64-reference``
between each and the CPU path with float64 products (the scale of the float32 products'
round-off, which grows with S/N as ``ln L`` does).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from bench_likelihood import NOISE_SIGMA, bench_hsm, likelihood_mean_e, maxrss_mib, simulate


def device_line() -> tuple[str, object]:
    """JAX's version and default device, and the device (None without JAX)."""
    try:
        import jax  # optional: the jax backend's rows need it
    except ImportError:
        return "JAX not installed (pip install 'pylensfit[gpu]')", None
    dev = jax.devices()[0]
    return f"JAX {jax.__version__}, default backend {jax.default_backend()}: {dev}", dev


def device_peak_mib(dev) -> str:
    """The device's peak memory in use (MiB), where JAX reports it (GPUs)."""
    stats = dev.memory_stats() if dev is not None else None
    if not stats or "peak_bytes_in_use" not in stats:
        return "n/a"
    return f"{stats['peak_bytes_in_use'] / 2**20:.0f}"


def bench_backend(backend: str, stamps, psf_img, cfg, threads: int, dev) -> tuple[dict, object]:
    import numba  # heavy import, after the simulation

    from pylensfit import Config, fit_stamps

    if backend == "jax":
        cfg = cfg.replace(backend=backend)
    else:  # the CPU path with its own blocks (Config's default)
        cfg = cfg.replace(backend=backend, block_size=Config().block_size)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    t0 = time.perf_counter()
    fit_stamps(stamps[: cfg.block_size], psf_img, NOISE_SIGMA, config=cfg)  # warm-up
    warm = time.perf_counter() - t0
    t0 = time.perf_counter()
    fits = fit_stamps(stamps, psf_img, NOISE_SIGMA, config=cfg)
    dt = time.perf_counter() - t0
    row = {"method": f"pylensfit {backend}", "rate": len(stamps) / dt, "wall": dt,
           "warm": warm, "rss": f"{maxrss_mib():.0f}",
           "dev": device_peak_mib(dev) if backend == "jax" else "-",
           "fail": int((~np.isfinite(fits.lnL).all(axis=1)).sum())}  # fmt: skip
    return row, fits


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--ngal", type=int, default=2000, help="number of galaxies (2000)")
    p.add_argument("--seed", type=int, default=1, help="random seed (1)")
    p.add_argument("--model", default="bulge+disc",
                   choices=["bulge+disc", "devaucouleurs", "exponential"],
                   help="pylensfit model (bulge+disc, the recommended one)")  # fmt: skip
    p.add_argument("--backends", default="cpu,jax", help="backends to time (cpu,jax)")
    p.add_argument("--block-size", type=int, default=1024,
                   help="galaxies per block on the device (1024)")  # fmt: skip
    p.add_argument("--threads", type=int, default=os.cpu_count() or 1,
                   help="numba threads of the cpu backend (all CPUs)")  # fmt: skip
    p.add_argument("--no-hsm", action="store_true", help="skip HSM REGAUSS")
    p.add_argument("--f64-reference", action="store_true",
                   help="also fit with float64 products on the CPU path (not timed), the "
                        "scale of the float32 round-off")  # fmt: skip
    args = p.parse_args(argv)
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]

    import galsim

    import pylensfit
    from pylensfit import Config

    line, dev = device_line()
    print(f"pylensfit {pylensfit.__version__}, GalSim {galsim.__version__}, numpy "
          f"{np.__version__}, {os.cpu_count()} CPUs (load {os.getloadavg()[0]:.2f})")  # fmt: skip
    print(line)
    sim_model = "devaucouleurs" if args.model == "devaucouleurs" else "exponential"
    t0 = time.perf_counter()
    e_true, _snr, stamps, psf_img = simulate(args.ngal, args.seed, sim_model)
    base_rss = maxrss_mib()
    print(f"simulated {args.ngal} {sim_model} galaxies in {time.perf_counter() - t0:.1f} s "
          f"(not timed); RSS after simulation {base_rss:.0f} MiB")  # fmt: skip
    cfg = Config(model=args.model, max_stamp_size=0, block_size=args.block_size)

    rows, fits = [], {}
    for backend in backends:
        print(f"pylensfit, backend {backend} ...", flush=True)
        row, fits[backend] = bench_backend(backend, stamps, psf_img, cfg, args.threads, dev)
        rows.append(row)
    if args.f64_reference:
        print("pylensfit, cpu backend with float64 products (reference, not timed) ...",
              flush=True)  # fmt: skip
        from pylensfit import fit_stamps  # after the timed rows

        fits["cpu float64"] = fit_stamps(stamps, psf_img, NOISE_SIGMA,
                                         config=cfg.replace(dtype="float64", block_size=128))
    e_hsm = None
    if not args.no_hsm:
        print("HSM REGAUSS ...", flush=True)
        row, e_hsm = bench_hsm(stamps, psf_img)
        rss = row["rss"].replace(" (main)", "")
        rows.append(dict(row, method="HSM REGAUSS", warm=0.0, dev="-", rss=rss))
    report(args, rows, fits, e_true, e_hsm, base_rss)
    return 0


def report(args, rows, fits, e_true, e_hsm, base_rss) -> None:
    print()
    print(f"{args.ngal} galaxies, 32x32 stamps, model {args.model}, device block "
          f"{args.block_size}, cpu backend on {args.threads} numba threads")  # fmt: skip
    hdr = (f"{'method':<16} {'gal/s':>9} {'wall s':>8} {'warm-up s':>9} "
           f"{'peak RSS MiB':>12} {'device peak MiB':>15} {'failures':>8}")  # fmt: skip
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        print(f"{r['method']:<16} {r['rate']:9.0f} {r['wall']:8.2f} {r['warm']:9.1f} "
              f"{r['rss']:>12} {r['dev']:>15} {r['fail']:8d}")  # fmt: skip
    print(f"(RSS after simulation, before any measurement: {base_rss:.0f} MiB)")
    for x, y in (("jax", "cpu"), ("jax", "cpu float64"), ("cpu", "cpu float64")):
        if x not in fits or y not in fits:
            continue
        a, b = fits[y], fits[x]
        near = a.lnL > -20.0
        dmax = np.max(np.abs(a.lnL - b.lnL)[near]) if near.any() else np.nan
        de = np.nanmax(np.abs(likelihood_mean_e(a) - likelihood_mean_e(b)))
        print(f"{x} vs {y}: max |d lnL| where lnL > -20: {dmax:.1e}; max |d <e>|: {de:.1e}; "
              f"flags equal: {bool((a.flags == b.flags).all())}")  # fmt: skip
    for name, f in fits.items():
        if name == "cpu float64":
            continue
        e = likelihood_mean_e(f)
        ok = np.isfinite(e[:, 0])
        c = np.corrcoef(e[ok, 0], e_true[ok, 0])[0, 1]
        print(f"sanity: corr(e1, true) pylensfit {name} {c:.3f}", end="; ")
    if e_hsm is not None:
        ok = np.isfinite(e_hsm[:, 0])
        print(f"HSM {np.corrcoef(e_hsm[ok, 0], e_true[ok, 0])[0, 1]:.3f}", end="")
    print(f"\nload average now {os.getloadavg()[0]:.2f} (rerun if other work shared the CPUs)")


if __name__ == "__main__":
    sys.exit(main())
