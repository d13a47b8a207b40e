"""Time one block of ``validate --precision`` (render, fit, reduce) in one process, one thread.

The unit of work of the precision run, without the process pool: the measure for an
A/B of the likelihood kernel. For an A/B against an older commit, run it once as is and
once with that commit's ``src`` first on the path::

    python benchmarks/studies/precision_block.py
    git worktree add --detach /tmp/old <commit>
    PYTHONPATH=/tmp/old/src python benchmarks/studies/precision_block.py

Prints the seconds of the block, of the GalSim rendering, of the fit and of the
reduction, per PSF (blocks ``psf + 4`` of ``PrecisionSpec(seed=5)``, after one warm-up
block that compiles the kernels and builds the banks).

``--flux-bounds`` fits each block also with the flux prior bounded at the population's
flux range (the precision mode's default estimates it) and prints both fits' CPU
seconds, the better of ``--repeat`` tries each, interleaved::

    python benchmarks/studies/precision_block.py --psf 1 --seed 41 --flux-bounds --repeat 5
"""

from __future__ import annotations

import argparse
import time

import pylensfit
from pylensfit_validation import precision as P


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--psf", type=int, nargs="+", default=[0, 2],
                    help="indices into PRECISION_PSFS (default: round and kolmogorov)")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--flux-bounds", action="store_true",
                    help="time the fit with and without the population's flux bounds")
    ap.add_argument("--repeat", type=int, default=3,
                    help="with --flux-bounds: tries per fit (the best is printed)")
    a = ap.parse_args()
    print(f"pylensfit from {pylensfit.__file__}")
    spec = P.PrecisionSpec(ngal=8000, ncal=0, seed=a.seed)
    cfg = P.default_config(spec)
    prior = P.population_prior(spec)
    if a.flux_bounds:
        _fit_cost(spec, cfg, a.psf, a.repeat)
        return
    for psf in a.psf:
        task = {"spec": spec, "config": cfg, "prior": prior, "calibration": False,
                "bulge_weights": [1 / 3, 1 / 3, 1 / 3], "psf": psf, "block": psf,
                "size_prior": P.population_size_prior(spec, psf),
                "single_thread": True}  # fmt: skip
        P.block_task(task)  # warm-up: compilation, banks
        task["block"] = psf + 4
        t0 = time.perf_counter()
        r = P.block_task(task)
        print(f"PSF {spec.psfs[psf]['name']}: block {time.perf_counter() - t0:.1f} s "
              f"(render {r['render_s']:.1f}, fit {r['fit_s']:.1f}, reduce {r['reduce_s']:.1f}) "
              f"for {spec.block_size} galaxies x 4 renderings")  # fmt: skip


def _fit_cost(spec, cfg, psfs, repeat: int) -> None:
    """CPU seconds of ``fit_stamps`` on one block, unbounded and bounded flux prior."""
    from pylensfit.likelihood import fit_stamps
    from pylensfit.runner import single_thread

    single_thread(True)
    for psf in psfs:
        stamps, img, _ = P.render_block(spec, psf, psf + 4, stamp_size=cfg.largest_stamp)
        st = stamps.reshape(-1, *stamps.shape[2:])
        lo, hi = P.population_flux_range(spec, psf, stamp_size=cfg.largest_stamp)
        cfgs = {"unbounded": cfg,
                "bounded": cfg.replace(amplitude_prior_min=lo, amplitude_prior_max=hi)}
        sp = P.population_size_prior(spec, psf, stamp_size=cfg.largest_stamp)
        fit_stamps(st[:8], img, spec.noise_sigma, config=cfgs["bounded"], size_prior=sp)
        best = dict.fromkeys(cfgs, float("inf"))
        for _ in range(repeat):
            for k, c in cfgs.items():
                t0 = time.process_time()
                fit_stamps(st, img, spec.noise_sigma, config=c, size_prior=sp)
                best[k] = min(best[k], time.process_time() - t0)
        print(f"PSF {spec.psfs[psf]['name']}, {len(st)} renderings: fit CPU unbounded "
              f"{best['unbounded']:.2f} s, bounded at {lo:.4g}-{hi:.4g} "
              f"{best['bounded']:.2f} s ({best['bounded'] / best['unbounded']:.2f} times)")


if __name__ == "__main__":
    main()
