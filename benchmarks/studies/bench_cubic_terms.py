"""Error of the Laplace ln L(e) with and without the third-order position terms.

Reuses the brute-force marginalisation of tests/test_likelihood.py (real-space chi-square
on a fine grid of positions, amplitude integrated numerically) and prints, for a few S/N,
the largest |d ln L| over up to 12 cells where L > 1e-3 of its peak, with the quadratic
expansion only (``cubic_snr = 0``) and with the cubic terms (``cubic_snr = inf``). This is
the measurement behind the default ``Config.cubic_snr = 20``.

    python benchmarks/studies/bench_cubic_terms.py [--snr 10 14 20 30]
"""

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
from pylensfit import Config, fit_stamps  # noqa: E402
from test_likelihood import N, _galaxy, brute_force_lnL  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--snr", type=float, nargs="+", default=[10, 14, 20, 30])
    args = ap.parse_args()
    cfg = Config(model="exponential", r_step=0.5, r_max=6.0, e_step=0.1, dtype="float64")
    x0 = np.array([N // 2, N // 2], float)
    print(f"{'S/N':>5} {'quadratic':>10} {'cubic':>8}   (max |d lnL| vs brute force)")
    for snr in args.snr:
        d, psf = _galaxy(snr, (0.7, -0.4))
        res = {cs: fit_stamps(d, psf, 1.0, config=cfg.replace(cubic_snr=cs)).lnL[0].astype(float)
               for cs in (0.0, 1e9)}  # fmt: skip
        eng = res[1e9]
        order = np.argsort(eng)
        inside = order[eng[order] > np.log(1e-3)]
        cells = inside[np.unique(np.linspace(0, inside.size - 1, min(12, inside.size)).astype(int))]
        b = brute_force_lnL(cfg, d, 1.0, psf, x0, cells)
        ref = np.nanargmax(b)
        err = {cs: np.abs((e - e[ref]) - (b - b[ref]))[cells].max() for cs, e in res.items()}
        print(f"{snr:5.0f} {err[0.0]:10.4f} {err[1e9]:8.4f}")


if __name__ == "__main__":
    main()
