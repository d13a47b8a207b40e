"""The precision mode's memory against the size of its calibration sample.

``pylensfit validate --precision`` keeps every calibration galaxy's likelihood grids
(``L(e)`` per bulge fraction, and in the first pass ``L(r)`` per annulus of |e| for the
size prior) while the priors are estimated; the main sample streams and keeps 12 numbers
per rendering. This runs :func:`pylensfit_validation.precision.precision` (the mode's defaults,
``--jobs`` workers) with a small main sample and each calibration size given, samples the
main process's resident memory every 0.2 s, and prints its peak, the wall time and the
fixed-point m (the same seed gives the same calibration galaxies, so runs at two sizes
share their first ones); the slope between two sizes is the memory per calibration
galaxy. The workers' memory (their model banks, one block's renderings and fits) does not
grow with the calibration and is not in it. Needs psutil (installed with the ``test`` or
``dask`` extras, through dask.distributed)::

    python benchmarks/studies/calibration_memory.py --ncal 4000 12000
"""

from __future__ import annotations

import argparse
import threading
import time

import psutil

from pylensfit_validation import precision as P


def peak_rss(ncal: int, ngal: int, seed: int, jobs: int) -> tuple[float, float, float, dict]:
    """Peak resident memory (bytes) of this process over a precision run, the memory at its
    start, its wall seconds, and the fixed-point ``all`` row."""
    proc = psutil.Process()
    peak, done = [proc.memory_info().rss], threading.Event()

    def sample() -> None:
        while not done.is_set():
            peak[0] = max(peak[0], proc.memory_info().rss)
            time.sleep(0.2)

    start = proc.memory_info().rss
    th = threading.Thread(target=sample, daemon=True)
    th.start()
    t0 = time.perf_counter()
    out = P.precision(P.PrecisionSpec(ngal=ngal, ncal=ncal, seed=seed), jobs=jobs,
                      progress=False)  # fmt: skip
    wall = time.perf_counter() - t0
    done.set()
    th.join()
    row = out[(out["breakdown"] == "all") & (out["estimator"] == "fixed-point")][0]
    return float(peak[0]), float(start), wall, {"m1": row["m1"], "m2": row["m2"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ncal", type=int, nargs="+", default=[4000, 12000],
                    help="calibration sizes, one run each")
    ap.add_argument("--ngal", type=int, default=2000, help="main sample (small: it streams)")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args()
    rows = []
    for n in a.ncal:
        peak, start, wall, m = peak_rss(n, a.ngal, a.seed, a.jobs)
        rows.append((n, peak))
        print(f"ncal {n:>7}: peak {peak / 1e9:.2f} GB (at start {start / 1e9:.2f}), "
              f"{wall:.0f} s, m1 {m['m1']:+.5f} m2 {m['m2']:+.5f}", flush=True)
    if len(rows) > 1:
        (n0, p0), (n1, p1) = rows[0], rows[-1]
        print(f"per calibration galaxy: {(p1 - p0) / (n1 - n0) / 1e3:.0f} kB "
              f"(between {n0} and {n1})")


if __name__ == "__main__":
    main()
