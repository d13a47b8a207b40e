"""Cost of the joint fit of K exposures per galaxy, beside the single-exposure fit.

Renders ``--ngal`` exponential galaxies into 4 exposures (rotated by 0, 30, 60 and 90
degrees, the last a mirror image, each with its own Gaussian PSF; not timed), then times
in the same process, each after a warm-up call on a few galaxies:

* ``fit_stamps`` of every galaxy on exposure 0 (one single-exposure fit per galaxy);
* ``fit_exposures`` of every galaxy on its first K = 1, 2, 4 exposures (the exposures'
  model banks, built in the warm-up, reused as ``fit_stamps`` reuses its bank);
* ``fit_exposures`` on the 4 exposures with each exposure's PSF image given once per
  galaxy, ``(K, n, s, s)``, as :func:`pylensfit.joint.fit_views` gives them (``PSF/gal``),
  and the same with each galaxy's image scaled by its own factor (``PSF/gal*``: the
  same fit, the models' norms computed per galaxy as for a PSF that varies);
* ``fit_exposures`` on the 4 exposures with Jacobians new to the process (scaled by
  ``1 + 1e-9``): the call builds their banks.

Both on the same grid (``--model``, de = 0.1, sizes 0-10 px in 0.2 px: the paper's
grid), the uniform amplitude prior, untruncated models, float32 products, BLAS on one
thread; ``--config default``: both with ``Config()`` (bulge+disc with three bulge
fractions, the geometric size grid with ``r_floor``, the flux prior) on 48-pixel stamps
fitted whole (``stamp_size = 48``, ``max_stamp_size = 0``: no tiers). The calls run
``--repeat`` times in turn, the best of each printed: microseconds per (galaxy,
exposure), of wall-clock time and of the process's CPU time (all threads; on a machine
that other jobs share it varies less than the wall clock, with ``NUMBA_NUM_THREADS=1``
the two agree), and the peak of the memory numpy allocates during the call
(``tracemalloc``, banks included).

Usage::

    python benchmarks/bench_joint.py                 # 512 galaxies, ~1 min
    python benchmarks/bench_joint.py --ngal 256 --model devaucouleurs
    NUMBA_NUM_THREADS=1 python benchmarks/bench_joint.py --ngal 256   # one thread
    NUMBA_NUM_THREADS=1 python benchmarks/bench_joint.py --config default --ngal 128
"""

from __future__ import annotations

import argparse
import os
import time
import tracemalloc

import numpy as np
from threadpoolctl import threadpool_limits

from pylensfit.config import Config
from pylensfit.joint import fit_exposures
from pylensfit.likelihood import fit_stamps
from pylensfit.models import render_models

SCALE = 0.2  # arcsec per pixel


def rotation(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


def gaussian_psf(s: float, size: int = 25) -> np.ndarray:
    yy, xx = np.mgrid[:size, :size] - size // 2
    return np.exp(-(xx**2 + yy**2) / (2 * s * s))


def simulate(ngal: int, model: str, rng: np.random.Generator, N: int):
    """Stamps ``(4, ngal, N, N)``, PSFs ``(4, s, s)`` and Jacobians ``(4, 2, 2)``."""
    J = np.stack([rotation(0.0), rotation(30.0), rotation(60.0),
                  np.diag([-1.0, 1.0]) @ rotation(90.0)]) / SCALE  # fmt: skip
    psfs = np.stack([gaussian_psf(s) for s in (1.5, 1.7, 1.4, 1.6)])
    e = rng.uniform(-0.3, 0.3, (2, ngal))
    r = rng.uniform(1.0, 4.0, ngal)
    dx, dy = rng.uniform(-0.5, 0.5, (2, ngal))
    stamps = np.empty((4, ngal, N, N))
    for k in range(4):
        # the sky-frame ellipticity in the exposure's pixels: e rotated by twice the angle,
        # then the mirror image's x -> -x flips e2; sizes unchanged (same pixel scale)
        a = np.radians((0.0, 30.0, 60.0, 90.0)[k])
        c, s = np.cos(2 * a), np.sin(2 * a)
        e1, e2 = c * e[0] - s * e[1], s * e[0] + c * e[1]
        if k == 3:
            e2 = -e2
        stamps[k] = render_models(N, psfs[k], N // 2 + dx, N // 2 + dy, e1, e2, r,
                                  np.full(ngal, 300.0), model=model)  # fmt: skip
    return stamps + rng.normal(0.0, 1.0, stamps.shape), psfs, J


def timed(fn):
    """``(seconds, CPU seconds of the process, peak MiB of traced allocations)`` of one
    call."""
    tracemalloc.start()
    t0, c0 = time.perf_counter(), time.process_time()
    fn()
    dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    return dt, cpu, peak


def row(name: str, n: int, dt: float, cpu: float, peak: float) -> str:
    """One line of the table: ``n`` (galaxy, exposure) pairs in ``dt`` s (``cpu`` s)."""
    return f"{name:<28}{1e6 * dt / n:14.0f}{1e6 * cpu / n:14.0f}{peak:10.0f}"


def configuration(name: str, model: str) -> tuple[Config, int]:
    """The fits' configuration and the stamp side: the paper's grid on 32-pixel stamps,
    or ``Config()`` on 48-pixel stamps fitted whole."""
    if name == "default":
        return Config().replace(stamp_size=48, max_stamp_size=0), 48
    return Config().replace(model=model, n_bulge_fractions=1, amplitude_prior="uniform",
                            truncate_models=False, max_stamp_size=0, e_refine=1,
                            cubic_snr=0.0, r_min=0.0, r_max=10.0, r_step=0.2, r_rel_step=0.0,
                            stamp_size=32, dtype="float32"), 32  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ngal", type=int, default=512)
    ap.add_argument("--model", default="exponential")
    ap.add_argument("--config", choices=("paper", "default"), default="paper")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    cfg, N = configuration(args.config, args.model)
    stamps, psfs, J = simulate(args.ngal, args.model, np.random.default_rng(args.seed), N)
    print(f"{args.ngal} galaxies, {args.model}, {args.config} config, {N}x{N} stamps, "
          f"load {os.getloadavg()[0]:.2f}")  # fmt: skip
    print(f"{'fit':<28}{'us/(gal exp)':>14}{'cpu us':>14}{'peak MiB':>10}")
    calls = {"fit_stamps (1 exposure)": (args.ngal, lambda: fit_stamps(
        stamps[0], psfs[0], 1.0, config=cfg))}  # fmt: skip
    for K in (1, 2, 4):
        calls[f"fit_exposures K={K}"] = (args.ngal * K, lambda K=K: fit_exposures(
            stamps[:K], psfs[:K], 1.0, J[:K], config=cfg, pixel_scale=SCALE))  # fmt: skip
    per_gal = np.repeat(psfs[:, None], args.ngal, axis=1)
    calls["fit_exposures K=4, PSF/gal"] = (args.ngal * 4, lambda: fit_exposures(
        stamps, per_gal, 1.0, J, config=cfg, pixel_scale=SCALE))  # fmt: skip
    # the same images, each galaxy's scaled by its own factor (a PSF's normalisation is
    # not read): the models' norms computed per galaxy, as for a PSF that varies
    scaled = per_gal * (1.0 + np.arange(args.ngal) / args.ngal)[None, :, None, None]
    calls["fit_exposures K=4, PSF/gal*"] = (args.ngal * 4, lambda: fit_exposures(
        stamps, scaled, 1.0, J, config=cfg, pixel_scale=SCALE))  # fmt: skip
    with threadpool_limits(limits=1, user_api="blas"):
        # warm-up: numba, the banks
        fit_stamps(stamps[0, :4], psfs[0], 1.0, config=cfg)
        for K in (1, 2, 4):
            fit_exposures(stamps[:K, :4], psfs[:K], 1.0, J[:K], config=cfg, pixel_scale=SCALE)
        best = {}
        for _ in range(args.repeat):  # in turn: each sees the same load
            for name, (_, fn) in calls.items():
                t = timed(fn)
                best[name] = t if name not in best else tuple(map(min, best[name], t))
        for name, (n, _) in calls.items():
            print(row(name, n, *best[name]))
        # Jacobians new to the call (scaled by 1 + 1e-9: the same symmetries), whose
        # banks the call builds
        t = timed(lambda: fit_exposures(stamps, psfs, 1.0, J * (1 + 1e-9), config=cfg,
                                        pixel_scale=SCALE))  # fmt: skip
        print(row("fit_exposures K=4, new J", args.ngal * 4, *t))
    print(f"load at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
