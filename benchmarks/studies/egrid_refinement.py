"""Which likelihoods the 0.1 e-grid under-samples, and how large a window of finer cells
about each galaxy's peak fixes it: the emulation behind ``Config.e_refine``.

Every block of the precision set (``pylensfit_validation.precision``: four renderings per galaxy,
+-g, unrotated and rotated by 90 degrees; here by default exponential galaxies fitted
with the exponential model, the population's own priors and flux bounds: the case in
which the likelihood is narrowest) is fitted on the grid of 0.1 and on the grid of 0.025,
the Bayesian integrals' own cells, where ``ln L`` is then exact. On those cells m is
computed from (fixed point, paired jackknife over groups of 100 galaxies, per bin of
true S/N, minus the exact grid's m):

* ``0.1 quintic``: the 0.1 fit interpolated (:func:`pylensfit.grid.refine_lnL`, refine
  4), what the integrals use by default;
* ``0.05 everywhere``: exact values on every other cell (a lattice of 0.05), the cells
  between them interpolated by the quintic's midpoint stencil;
* ``0.05 in +-R (S/N >= s), A out | floor``: those values only in a square of
  half-width ``R`` about the 0.1 grid's peak cell, for galaxies of true S/N >= s; outside
  it the 0.1 grid's interpolation, or a floor of -1000.

The fits of 0.025 are cached per block (``--cache``), so that other variants can be
tried without fitting again::

    python benchmarks/studies/egrid_refinement.py --ngal 2000 --seed 21     # ~12 min on 2 cores
"""

from __future__ import annotations

import argparse
import importlib.util
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import scipy.sparse as sp

from pylensfit.grid import refine_lnL
from pylensfit.likelihood import fit_stamps
from pylensfit.runner import run_tasks, worker_pool
from pylensfit_validation import precision as P

_W6 = np.array([3.0, -25.0, 150.0, 150.0, -25.0, 3.0]) / 256.0
_O6 = np.array([-5, -3, -1, 1, 3, 5])


def _sublattice(grid: np.ndarray, step: float):
    """Sparse map: the cells of even lattice index kept, the odd ones from the quintic's
    midpoint stencil along each odd axis (cells whose stencil leaves the grid kept)."""
    li = np.rint(grid / step - 0.5).astype(int)
    pos = {(a, b): j for j, (a, b) in enumerate(li)}
    rows, cols, vals = [], [], []
    for j, (a, b) in enumerate(li):
        ta = list(zip(a + _O6, _W6, strict=True)) if a % 2 else [(a, 1.0)]
        tb = list(zip(b + _O6, _W6, strict=True)) if b % 2 else [(b, 1.0)]
        idx = [(pos.get((x, y)), wx * wy) for x, wx in ta for y, wy in tb]
        if not all(k is not None for k, _ in idx):
            idx = [(j, 1.0)]
        for k, wt in idx:
            rows.append(j)
            cols.append(k)
            vals.append(wt)
    return sp.csr_matrix((vals, (rows, cols)), shape=(len(li), len(li)))


def _task(t: dict) -> dict:
    from pylensfit.runner import single_thread

    single_thread(True)
    spec, cfg, b = t["spec"], t["config"], t["block"]
    k = b % len(spec.psfs)
    size_prior = P.population_size_prior(spec, k, stamp_size=cfg.largest_stamp)
    lo, hi = P.population_flux_range(spec, k, stamp_size=cfg.largest_stamp)
    c = cfg.replace(amplitude_prior_min=lo, amplitude_prior_max=hi)
    stamps, psf, truth = P.render_block(spec, k, b, stamp_size=cfg.largest_stamp)
    n, nr = stamps.shape[:2]
    cache = Path(t["cache"]) / f"{spec.seed}_{b}.npz"
    if cache.exists():
        z = np.load(cache)
        fa = SimpleNamespace(lnL=z["al"], lnL_peak=z["ap"], is_star=z["as_"], egrid=z["ae"])
        fc = SimpleNamespace(lnL=z["cl"], lnL_peak=z["cp"], is_star=z["cs"], egrid=z["ce"])
    else:
        st = stamps.reshape(n * nr, *stamps.shape[2:])
        fa = fit_stamps(st, psf, spec.noise_sigma, config=c, size_prior=size_prior)
        fc = fit_stamps(st, psf, spec.noise_sigma, config=c.replace(e_step=0.025),
                        size_prior=size_prior)  # fmt: skip
        np.savez(cache, al=fa.lnL, ap=fa.lnL_peak, as_=fa.is_star, ae=fa.egrid,
                 cl=fc.lnL, cp=fc.lnL_peak, cs=fc.is_star, ce=fc.egrid)  # fmt: skip
    ok = (np.isfinite(fa.lnL).all(1) & np.isfinite(fc.lnL).all(1)
          & ~fa.is_star & ~fc.is_star).reshape(n, nr).all(1)  # fmt: skip
    rows = np.repeat(ok, nr)
    XA, fine = refine_lnL(fa.lnL[rows].astype(float), fa.egrid, refine=4)
    if not np.allclose(fine, fc.egrid):
        raise RuntimeError("the refined 0.1 grid is not the grid of 0.025")
    A = XA + fa.lnL_peak[rows, None]
    C = fc.lnL[rows].astype(float) + fc.lnL_peak[rows, None]
    C2 = (_sublattice(fine, 0.025) @ C.T).T
    floor = C.max(1, keepdims=True) - 1000.0
    peak = fa.egrid[np.argmax(fa.lnL[rows], axis=1)]
    dist = np.abs(fine[None, :, :] - peak[:, None, :]).max(-1)
    snr = np.repeat(np.asarray(truth["snr"])[ok], nr)
    X = {"exact": C, "0.1 quintic": A, "0.05 everywhere": C2}
    for R in t["windows"]:
        for s in t["snr_cuts"]:
            ref = (snr >= s)[:, None]
            X[f"0.05 in +-{R} (S/N >= {s:g}), A out"] = np.where(ref & (dist <= R), C2, A)
            X[f"0.05 in +-{R} (S/N >= {s:g}), floor"] = np.where(
                ref, np.where(dist <= R, C2, floor), A)
    none = np.zeros(rows.sum(), dtype=bool)
    Q = {name: P.reduce_renderings(SimpleNamespace(lnL=L - L.max(1, keepdims=True), egrid=fine,
                                                   flags=none, is_star=none),
                                   t["prior"], spec.g, refine=1)[0]
         for name, L in X.items()}  # fmt: skip
    return {"block": b, "Q": Q, "snr": np.asarray(truth["snr"])[ok]}


def _helpers():
    """``benchmarks/studies/egrid_interpolation.py`` (its paired table) and ``precision_ab.py``."""
    path = Path(__file__).with_name("egrid_interpolation.py")
    mod = importlib.util.spec_from_file_location("egrid_interpolation", path)
    ei = importlib.util.module_from_spec(mod)
    mod.loader.exec_module(ei)
    return ei, ei.precision_ab()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ngal", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=21)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--psf", nargs="*", default=["e=0.10"])
    ap.add_argument("--spec", nargs="*", default=["morphology_weights=(1,0,0,0,0)"],
                    metavar="KEY=VALUE", help="the population (default: exponentials)")
    ap.add_argument("--config", nargs="*", default=["model=exponential", "n_bulge_fractions=1"],
                    metavar="KEY=VALUE", help="changes to precision.default_config")
    ap.add_argument("--windows", nargs="*", type=float, default=[0.15, 0.25, 0.35])
    ap.add_argument("--snr-cuts", nargs="*", type=float, default=[30.0, 60.0])
    ap.add_argument("--cache", default="egrid_refinement_cache")
    a = ap.parse_args()
    ei, ab = _helpers()
    Path(a.cache).mkdir(exist_ok=True)
    spec = P.spec_with(P.PrecisionSpec(ngal=a.ngal, seed=a.seed), psfs=a.psf,
                       **{"ncal": 20_000, **ab._kv(a.spec)})  # as recorded; --spec ncal=N
    cfg = P.default_config(spec).replace(**ab._kv(a.config))
    nb = -(-spec.ngal // spec.block_size)
    tasks = [{"spec": spec, "config": cfg, "block": b, "prior": P.population_prior(spec),
              "cache": a.cache, "windows": a.windows, "snr_cuts": a.snr_cuts}
             for b in range(nb)]  # fmt: skip
    t0 = time.perf_counter()
    res = []
    with worker_pool(a.jobs) as pool:
        for _, r in run_tasks(_task, tasks, a.jobs, None, "blocks", True, pool):
            res.append(r)
    res.sort(key=lambda r: r["block"])
    print(f"{nb} blocks ({spec.ngal} galaxies, PSFs {a.psf}, {a.spec}, {a.config}) in "
          f"{time.perf_counter() - t0:.0f} s")  # fmt: skip
    bins = [(0, 15), (15, 20), (20, 30), (30, 60), (60, 100), (100, np.inf), (0, np.inf)]
    ei.paired_table(res, spec, bins, "m1 / m2 minus the exact grid's (0.025), per bin of true "
                    "S/N:", min_n=50)  # fmt: skip


if __name__ == "__main__":
    main()
