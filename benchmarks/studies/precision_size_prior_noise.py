"""The calibration sample's noise in m, through the size priors: its spread over samples.

``pylensfit validate --precision`` estimates one size prior per PSF from that PSF's
unsheared calibration galaxies (a quarter of the sample: 5,000 of this script's
default 20,000), and m moves with it: over three random calibration samples of 20,000
galaxies, m's standard deviation is 0.001 on the mean of PSFs and up to 0.003 for one
PSF, an error the jackknife of the main sample does not see. This measures that spread for
several estimators of the size prior at once, on the same main sample:

1. For each calibration seed, the calibration's first pass (flat size prior) is run as
   :func:`pylensfit_validation.precision.precision` runs it, and each PSF's ``L(r)`` (marginalised
   over e with the first pass's ellipticity prior) is kept, with the configuration and
   bulge weights the size prior would be estimated with. ``--cache DIR`` keeps them.
2. Each setting (``--smooth``, ``--knot-step``; the knots' spacing in ln h and the EMS
   smoothing of :func:`pylensfit.prior.estimate_size_prior`) estimates the size priors of
   every calibration sample, and of pairs of samples pooled (``--pairs``: 10,000
   calibration galaxies per PSF instead of 5,000).
3. The main sample (``--ngal``, ``--seed``) is fitted with every set of size priors, the
   other priors fixed at the first calibration seed's (the ellipticity prior's estimate
   moves m by about 2e-4).

It prints m1, m2 per PSF and their mean for each setting and sample, the standard
deviation over the samples, and each setting's mean m over them, whose shift between
settings is what the smoothing costs in bias::

    python benchmarks/studies/precision_size_prior_noise.py --ngal 4000 --seed 11 \\
        --cal-seeds 5 9 11 13 17 19 --smooth 0.25 0.45 --knot-step 0.1 0.1 --pairs \\
        --cache /tmp/calnoise
"""

from __future__ import annotations

import argparse
import itertools
import time
from pathlib import Path

import numpy as np

import pylensfit.prior as prior_mod
from pylensfit.models import model_bank
from pylensfit.prior import RadialPrior
from pylensfit.runner import run_tasks, worker_pool
from pylensfit_validation import precision as P


class _Captured(Exception):
    pass


def _first_pass(spec, cfg, jobs: int, cache: Path | None) -> dict:
    """Per PSF ``L(r)`` of the calibration's first pass, with its config and bulge weights."""
    npsf = len(spec.psfs)
    tag = "_stratified" if spec.stratified_calibration else ""
    f = None if cache is None else cache / f"cal_seed{spec.seed}_n{spec.ncal}{tag}.npz"
    if f is not None and f.exists():
        d = np.load(f, allow_pickle=True)
        return {"lnL_r": list(d["lnL_r"]), "bulge_weights": d["bulge_weights"],
                "power": float(d["power"])}  # fmt: skip
    got: list = []
    real = prior_mod.estimate_size_prior

    def capture(lnL_r, bank, config, *, bulge_weights=None, **kw):
        got.append((np.array(lnL_r), config, np.asarray(bulge_weights, float)))
        if len(got) == npsf:
            raise _Captured

    prior_mod.estimate_size_prior = capture
    t0 = time.perf_counter()
    try:
        P.precision(P.spec_with(spec, ngal=2 * npsf), config=cfg, jobs=jobs, progress=False)
        raise SystemExit("the calibration did not estimate a size prior (size_prior?)")
    except _Captured:
        pass
    finally:
        prior_mod.estimate_size_prior = real
    print(f"calibration seed {spec.seed}: first pass {time.perf_counter() - t0:.0f} s, "
          f"flux power {got[0][1].amplitude_prior_power:.3f}, bulge weights "
          f"{np.round(got[0][2], 3).tolist()}")  # fmt: skip
    out = {"lnL_r": [g[0] for g in got], "bulge_weights": got[0][2],
           "power": got[0][1].amplitude_prior_power}  # fmt: skip
    if f is not None:
        f.parent.mkdir(parents=True, exist_ok=True)
        arr = np.empty(npsf, dtype=object)
        arr[:] = out["lnL_r"]
        np.savez(f, lnL_r=arr, bulge_weights=out["bulge_weights"], power=out["power"])
    return out


def _m(Q: np.ndarray, ok: np.ndarray, g: float) -> np.ndarray:
    """Fixed-point m1, m2 of renderings ``Q (n, 4, n_q)``."""
    T = Q[ok].sum(0)
    N = np.asarray(2.0 * ok.sum())
    gv = np.array([g, g])
    gp = P.shear_from_sums(T[0] + T[1], N, gv, "fixed-point")
    gm = P.shear_from_sums(T[2] + T[3], N, -gv, "fixed-point")
    return (gp - gm) / (2 * g) - 1.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ngal", type=int, default=4000)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--ncal", type=int, default=20_000)
    ap.add_argument("--cal-seeds", type=int, nargs="+", default=[5, 9, 11, 13])
    ap.add_argument("--smooth", type=float, nargs="+", default=[0.25])
    ap.add_argument("--knot-step", type=float, nargs="+", default=None,
                    help="one per --smooth (default 0.1 each)")
    ap.add_argument("--pairs", action="store_true",
                    help="also the size priors of consecutive pairs of calibration seeds pooled")
    ap.add_argument("--random-calibration", action="store_true",
                    help="the calibration samples drawn at random, not stratified "
                         "(PrecisionSpec.stratified_calibration)")
    ap.add_argument("--cache", type=Path, default=None)
    a = ap.parse_args()
    knots = a.knot_step or [0.1] * len(a.smooth)
    if len(knots) != len(a.smooth):
        raise SystemExit("--knot-step needs one value per --smooth")
    spec = P.PrecisionSpec(ngal=a.ngal, seed=a.seed, ncal=a.ncal,
                           stratified_calibration=not a.random_calibration)
    cfg = P.default_config(spec)
    npsf = len(spec.psfs)
    cal = {s: _first_pass(P.spec_with(spec, seed=s), cfg, a.jobs, a.cache) for s in a.cal_seeds}
    ref = cal[a.cal_seeds[0]]
    cfg_fit = cfg.replace(amplitude_prior_power=ref["power"])
    bank = model_bank(cfg_fit)
    # the other priors, fixed: the ellipticity prior and bulge weights of the first seed's
    # full calibration
    t0 = time.perf_counter()
    full = P.precision(P.spec_with(spec, seed=a.cal_seeds[0], ngal=2 * npsf), config=cfg,
                       jobs=a.jobs, progress=False)  # fmt: skip
    prior = RadialPrior.from_dict({**full.meta["prior"], "step": cfg.e_step})
    bw = full.meta["bulge_prior"]["weights"]
    print(f"fixed priors (seed {a.cal_seeds[0]}): {prior!r}, "
          f"bulge weights {np.round(bw, 3).tolist()} "
          f"({time.perf_counter() - t0:.0f} s)")  # fmt: skip
    samples: list[tuple[str, list]] = [(str(s), [cal[s]["lnL_r"][k] for k in range(npsf)])
                                       for s in a.cal_seeds]  # fmt: skip
    if a.pairs:
        for s1, s2 in zip(a.cal_seeds[::2], a.cal_seeds[1::2], strict=False):
            samples.append((f"{s1}+{s2}", [np.concatenate([cal[s1]["lnL_r"][k],
                                                           cal[s2]["lnL_r"][k]])
                                           for k in range(npsf)]))  # fmt: skip
    sets = {}
    for (sm, ks), (name, L) in itertools.product(zip(a.smooth, knots, strict=True), samples):
        sets[(sm, ks, name)] = [prior_mod.estimate_size_prior(L[k], bank, cfg_fit,
                                                              bulge_weights=ref["bulge_weights"],
                                                              smooth=sm, knot_step=ks)
                                for k in range(npsf)]  # fmt: skip
    nb = -(-spec.ngal // spec.block_size)
    keys = list(sets)
    tasks = [{"spec": spec, "config": cfg_fit, "prior": prior, "bulge_weights": bw,
              "size_prior": sets[key][b % npsf], "psf": b % npsf, "block": b,
              "calibration": False, "key": i}
             for b in range(nb) for i, key in enumerate(keys)]  # fmt: skip
    res: dict = {i: {} for i in range(len(keys))}
    t0 = time.perf_counter()
    with worker_pool(a.jobs) as pool:
        for t, r in run_tasks(P.block_task, tasks, a.jobs, None, "size priors", True, pool):
            res[t["key"]][t["block"]] = r
    print(f"{len(tasks)} block fits in {time.perf_counter() - t0:.0f} s")
    psf = np.concatenate([np.full(len(res[0][b]["truth"]), b % npsf) for b in range(nb)])
    Q = {i: np.concatenate([res[i][b]["Q"] for b in range(nb)]).astype(float) for i in res}
    ok = np.logical_and.reduce([np.concatenate([res[i][b]["usable"] for b in range(nb)]).all(1)
                                for i in res])  # fmt: skip
    names = [p["name"] for p in spec.psfs]
    print(f"main sample: {spec.ngal} galaxies, seed {spec.seed}, {int(ok.sum())} usable in "
          f"every fit; m1 / m2 (fixed point, no control variates)")
    print(f"| smooth, knot step | sample | {' | '.join(names)} | mean of PSFs |\n"
          f"|{'---|' * (npsf + 3)}")
    table = {}
    for i, (sm, ks, name) in enumerate(keys):
        m = np.array([_m(Q[i][psf == k], ok[psf == k], spec.g) for k in range(npsf)])
        table[(sm, ks, name)] = np.vstack([m, m.mean(0)])
        cells = [f"{v[0]:+.4f} / {v[1]:+.4f}" for v in table[(sm, ks, name)]]
        print(f"| {sm}, {ks} | {name} | " + " | ".join(cells) + " |")
    print(f"\nstandard deviation over the calibration samples (m1 and m2 pooled), and the "
          f"mean over them\n| smooth, knot step | samples | {' | '.join(names)} | mean of "
          f"PSFs |\n|{'---|' * (npsf + 3)}")
    for sm, ks in zip(a.smooth, knots, strict=True):
        for label, which in (("single", [str(s) for s in a.cal_seeds]),
                             ("pairs", [n for n, _ in samples if "+" in n])):
            rows = np.array([table[(sm, ks, n)] for n in which])  # (n_s, npsf + 1, 2)
            if len(rows) < 2:
                continue
            sd = np.sqrt(np.mean(rows.var(0, ddof=1), -1))
            mu = rows.mean((0, 2))
            print(f"| {sm}, {ks} | {label} ({len(rows)}) sd | "
                  + " | ".join(f"{v:.4f}" for v in sd) + " |")
            print(f"| {sm}, {ks} | {label} ({len(rows)}) mean | "
                  + " | ".join(f"{v:+.4f}" for v in mu) + " |")


if __name__ == "__main__":
    main()
