"""Time one block of ``validate --precision`` (render, fit, reduce) in one process, one thread.

The unit of work of the precision run, without the process pool: this is what the
seventeenth session's A/B of the likelihood kernel measured. For an A/B against an
older commit, run it once as is and once with that commit's ``src`` first on the path::

    python benchmarks/precision_block.py
    git worktree add --detach /tmp/old <commit>
    PYTHONPATH=/tmp/old/src python benchmarks/precision_block.py

Prints the seconds of the block, of the GalSim rendering, of the fit and of the
reduction, per PSF (blocks ``psf + 4`` of ``PrecisionSpec(seed=5)``, after one warm-up
block that compiles the kernels and builds the banks).
"""

from __future__ import annotations

import argparse
import time

import pylensfit
from pylensfit import precision as P


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--psf", type=int, nargs="+", default=[0, 2],
                    help="indices into PRECISION_PSFS (default: round and kolmogorov)")
    ap.add_argument("--seed", type=int, default=5)
    a = ap.parse_args()
    print(f"pylensfit from {pylensfit.__file__}")
    spec = P.PrecisionSpec(ngal=8000, ncal=0, seed=a.seed)
    cfg = P.default_config(spec)
    prior = P.population_prior(spec)
    for psf in a.psf:
        task = {"spec": spec, "config": cfg, "prior": prior, "calibration": False,
                "bulge_weights": [1 / 3, 1 / 3, 1 / 3], "psf": psf, "block": psf,
                "size_prior": P.population_size_prior(spec, psf),
                "single_thread": True}  # fmt: skip
        P._block_task(task)  # warm-up: compilation, banks
        task["block"] = psf + 4
        t0 = time.perf_counter()
        r = P._block_task(task)
        print(f"PSF {spec.psfs[psf]['name']}: block {time.perf_counter() - t0:.1f} s "
              f"(render {r['render_s']:.1f}, fit {r['fit_s']:.1f}, reduce {r['reduce_s']:.1f}) "
              f"for {spec.block_size} galaxies x 4 renderings")  # fmt: skip


if __name__ == "__main__":
    main()
