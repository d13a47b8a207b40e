"""What the e-grid's interpolation costs in m: exact ``ln L`` on a grid of 0.05 against
``ln L`` interpolated from a grid of 0.1, on the same precision renderings.

Every block of the precision set (``pylensfit_validation.precision``: four renderings per galaxy,
+-g, unrotated and rotated by 90 degrees, the population's priors) is fitted twice, with
``e_step`` 0.1 (the default) and 0.05. On the 0.05 grid (integration refined by 2, the
same 0.025 cells as the default's refinement by 4 of the 0.1 grid), m is computed from:

* ``exact``: the 0.05 fit's own ``ln L``;
* ``grid 0.1, cubic`` / ``grid 0.1, quintic``: the 0.1 fit's ``ln L`` interpolated onto
  the 0.05 cells (``refine_lnL(refine=2, stencil=4 or 6)``);
* ``inside exact`` / ``outside exact``: the exact values inside ``|e| < --edge`` and the
  0.1 grid's (cubic) outside, and the reverse: whether the interior or the edge, where
  the models degenerate, carries the difference;
* ``sub-lattice, cubic`` / ``sub-lattice, quintic``: the 0.05 fit's own values on every
  other cell (a lattice of step 0.1), the cells between them interpolated (midpoint
  weights of the cubic, ``(-1, 9, 9, -1) / 16``, and of the quintic, ``(3, -25, 150,
  150, -25, 3) / 256``) inside ``|e| < --edge``: the interpolation alone, the fit and
  its centring the same.

It prints each one's m minus the exact one's per bin of true S/N (fixed point, paired
jackknife over groups of 100 galaxies)::

    python benchmarks/studies/egrid_interpolation.py --ngal 4000 --snr 10 30 --psf round e=0.10
"""

from __future__ import annotations

import argparse
import importlib.util
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from pylensfit.grid import refine_lnL
from pylensfit.likelihood import fit_stamps
from pylensfit.runner import run_tasks, worker_pool
from pylensfit_validation import precision as P

_MID = {4: (np.array([-1.0, 9.0, 9.0, -1.0]) / 16.0, np.array([-3, -1, 1, 3])),
        6: (np.array([3.0, -25.0, 150.0, 150.0, -25.0, 3.0]) / 256.0,
            np.array([-5, -3, -1, 1, 3, 5]))}  # fmt: skip


def _sublattice(grid: np.ndarray, inner: np.ndarray, width: int) -> np.ndarray:
    """``M (n, n)``: the values on the even-even cells of ``grid`` (a lattice of step
    0.05) kept, the others inside ``inner`` interpolated from them at midpoints along
    each odd axis (``width`` points); cells whose stencil leaves the grid kept."""
    n = grid.shape[0]
    li = np.rint(grid / 0.05 - 0.5).astype(int)
    pos = {(a, b): j for j, (a, b) in enumerate(li)}
    w, o = _MID[width]
    M = np.eye(n)
    for j, (a, b) in enumerate(li):
        if not inner[j] or (a % 2 == 0 and b % 2 == 0):
            continue
        ta = list(zip(a + o, w, strict=True)) if a % 2 else [(a, 1.0)]
        tb = list(zip(b + o, w, strict=True)) if b % 2 else [(b, 1.0)]
        idx = [(pos.get((x, y)), wx * wy) for x, wx in ta for y, wy in tb]
        if all(k is not None for k, _ in idx):
            M[j] = 0.0
            for k, wt in idx:
                M[j, k] += wt
    return M


def _task(t: dict) -> dict:
    from pylensfit.runner import single_thread

    single_thread(True)
    spec, cfg, b, edge = t["spec"], t["config"], t["block"], t["edge"]
    k = b % len(spec.psfs)
    sp = P.population_size_prior(spec, k, stamp_size=cfg.largest_stamp)
    stamps, psf, truth = P.render_block(spec, k, b, stamp_size=cfg.largest_stamp)
    n, nr = stamps.shape[:2]
    st = stamps.reshape(n * nr, *stamps.shape[2:])
    fa = fit_stamps(st, psf, spec.noise_sigma, config=cfg, size_prior=sp)
    fb = fit_stamps(st, psf, spec.noise_sigma, config=cfg.replace(e_step=0.05), size_prior=sp)
    ok = (np.isfinite(fa.lnL).all(1) & np.isfinite(fb.lnL).all(1)).reshape(n, nr).all(1)
    rows = np.repeat(ok, nr)
    A, B = fa.lnL[rows].astype(float), fb.lnL[rows].astype(float)
    B -= B.max(1, keepdims=True)
    fine = fb.egrid
    inner = np.hypot(*fine.T) < edge
    X = {"exact": B}
    for w, name in ((4, "cubic"), (6, "quintic")):
        XA, g2 = refine_lnL(A, fa.egrid, refine=2, stencil=w)
        if not np.allclose(g2, fine):
            raise RuntimeError("the refined 0.1 grid is not the 0.05 grid")
        X[f"grid 0.1, {name}"] = XA - XA.max(1, keepdims=True)
        X[f"sub-lattice, {name}"] = B @ _sublattice(fine, inner, w).T
    XA = X["grid 0.1, cubic"]
    sel = inner[None] & (B > -4)  # align B on XA where both are well inside
    off = np.where(sel, XA - B, 0.0).sum(1) / np.maximum(sel.sum(1), 1)
    X["inside exact"] = np.where(inner[None], B + off[:, None], XA)
    X["outside exact"] = np.where(inner[None], XA, B + off[:, None])
    none = np.zeros(rows.sum(), dtype=bool)  # no flags, no stars
    Q = {name: P.reduce_renderings(SimpleNamespace(lnL=L, egrid=fine, flags=none, is_star=none),
                                   t["prior"], spec.g, refine=2)[0]
         for name, L in X.items()}  # fmt: skip
    return {"block": b, "psf": k, "Q": Q, "snr": np.asarray(truth["snr"])[ok]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ngal", type=int, default=4000)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--psf", nargs="*", default=["round", "e=0.10"])
    ap.add_argument("--snr", nargs=2, type=float, default=(10.0, 30.0),
                    help="the population's snr_range")
    ap.add_argument("--edge", type=float, default=0.8,
                    help="|e| of the inside (hybrids, sub-lattice)")
    a = ap.parse_args()
    spec = P.spec_with(P.PrecisionSpec(ngal=a.ngal, seed=a.seed), psfs=a.psf,
                       snr_range=tuple(a.snr))  # fmt: skip
    cfg = P.default_config(spec)
    prior = P.population_prior(spec)
    nb = -(-spec.ngal // spec.block_size)
    tasks = [{"spec": spec, "config": cfg, "block": b, "edge": a.edge, "prior": prior}
             for b in range(nb)]  # fmt: skip
    t0 = time.perf_counter()
    res = []
    with worker_pool(a.jobs) as pool:
        for _, r in run_tasks(_task, tasks, a.jobs, None, "blocks", True, pool):
            res.append(r)
    res.sort(key=lambda r: r["block"])
    print(f"{nb} blocks ({spec.ngal} galaxies, PSFs {a.psf}, snr_range {tuple(a.snr)}, seed "
          f"{a.seed}) fitted at e_step 0.1 and 0.05 in {time.perf_counter() - t0:.0f} s")
    bins = [(10, 15), (15, 20), (20, 30), (30, 60), (60, np.inf), (10, np.inf)]
    paired_table(res, spec, bins, "m1 / m2 minus the exact grid's (true S/N >= 10; the "
                 "faintest are noisy):", min_n=100)  # fmt: skip


def precision_ab():
    """The module ``benchmarks/studies/precision_ab.py`` (its paired jackknife and helpers)."""
    path = Path(__file__).with_name("precision_ab.py")
    mod = importlib.util.spec_from_file_location("precision_ab", path)
    ab = importlib.util.module_from_spec(mod)
    mod.loader.exec_module(ab)
    return ab


def paired_table(res: list, spec, bins: list, title: str, min_n: int = 100) -> None:
    """Print each variant's m minus the ``exact`` one's per bin of true S/N (the blocks'
    results ``res``: ``Q`` per variant, ``snr``, ``block``), paired jackknife over groups of
    ``P.JACKKNIFE_GALAXIES`` galaxies; bins with fewer than ``min_n`` galaxies left empty."""
    ab = precision_ab()
    names = list(res[0]["Q"])
    Q = {k: np.concatenate([r["Q"][k] for r in res]).astype(float) for k in names}
    snr = np.concatenate([r["snr"] for r in res])
    per = -(-spec.block_size // P.JACKKNIFE_GALAXIES)
    jk = np.concatenate([r["block"] * per + np.arange(len(r["snr"])) // P.JACKKNIFE_GALAXIES
                         for r in res])  # fmt: skip
    ok = np.ones(snr.size, bool)
    print(title)
    print("| variant | " + " | ".join(f"S/N {lo}-{hi:g}" for lo, hi in bins) + " |")
    print("|---|" + "---|" * len(bins))
    for k in names[1:]:
        cells = []
        for lo, hi in bins:
            sel = (snr >= lo) & (snr < hi)
            if sel.sum() < min_n:
                cells.append("")
                continue
            d, e = ab._paired(Q["exact"][sel], Q[k][sel], ok[sel], jk[sel], spec.g)
            cells.append(f"{d[0]:+.5f} / {d[1]:+.5f} ± {e[0]:.5f} / {e[1]:.5f}")
        print(f"| {k} | " + " | ".join(cells) + " |")

if __name__ == "__main__":
    main()
