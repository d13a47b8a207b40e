"""Two configurations on the same precision renderings: m of each, B - A paired, fit time.

The precision mode's blocks (``pylensfit_validation.precision``: four renderings per galaxy, +-g,
unrotated and rotated by 90 degrees) are fitted and reduced twice, once with the
default configuration (``precision.default_config``, changed by ``--a KEY=VALUE``) and
once with ``--b KEY=VALUE`` on top of it, with the same priors: the population's own
(its ellipticity prior, its log-uniform size prior per PSF, equal bulge-fraction
weights), or with ``--estimated`` those a calibration of config A estimates
(:func:`pylensfit_validation.precision.precision` on the same seed; with ``--own-priors`` B gets
its own, as a change of the bulge fractions needs). The renderings and their noise
are the same, so the difference B - A is measured far better than either m: its error
is the jackknife (groups of 100 galaxies) of the paired difference of the fixed-point
estimates, without control variates (the shape noise is common to both).

It prints, per PSF and for the mean of PSFs, m1 and m2 of A and B (fixed point, with the
precision mode's control variates) and B - A, and the fit's CPU seconds of each::

    python benchmarks/studies/precision_ab.py --ngal 20000 --seed 5 --b size_prior_floor_stride=1
    python benchmarks/studies/precision_ab.py --ngal 4000 --b cubic_snr=0 --jobs 2
    python benchmarks/studies/precision_ab.py --ngal 20000 --estimated --by-morphology \
        --b stamp_hlr_ratio=14
"""

from __future__ import annotations

import argparse
import ast
import math
import time

import numpy as np

from pylensfit.prior import Prior, RadialPrior, SizePrior
from pylensfit.runner import run_tasks, worker_pool
from pylensfit_validation import precision as P


def _oracle(spec, cfg) -> list:
    """``cfg`` per PSF with the flux prior bounded at the population's flux range."""
    return [cfg.replace(**dict(zip(("amplitude_prior_min", "amplitude_prior_max"),
                                   P.population_flux_range(spec, k, stamp_size=cfg.largest_stamp),
                                   strict=True)))
            for k in range(len(spec.psfs))]  # fmt: skip


def _priors(spec, cfg, estimated: bool, jobs: int, bounds: str):
    """Ellipticity prior, size prior per PSF, bulge weights and config per PSF (the flux
    prior's power and bounds: ``bounds`` none, oracle (the population's) or estimated)."""
    npsf = len(spec.psfs)
    cfgs = _oracle(spec, cfg) if bounds == "oracle" else [cfg] * npsf
    if not estimated:
        if bounds == "estimated":
            raise SystemExit("estimated flux bounds need --estimated (a calibration)")
        bw = np.full(cfg.n_bulge_fractions, 1.0 / cfg.n_bulge_fractions)
        return (P.population_prior(spec), [P.population_size_prior(spec, k) for k in range(npsf)],
                bw, cfgs)  # fmt: skip
    t0 = time.perf_counter()
    out = P.precision(P.spec_with(spec, ngal=2 * npsf), config=cfg, jobs=jobs, progress=False,
                      flux_bounds=bounds == "estimated")  # fmt: skip
    meta = out.meta
    prior = RadialPrior.from_dict({**meta["prior"], "step": cfg.e_step})
    sps = [SizePrior(ln_h=np.asarray(s["ln_h"]), density=np.asarray(s["density"]),
                     star=s["star"]) for s in meta["size_prior"]]  # fmt: skip
    bw = meta["bulge_prior"]["weights"]
    if meta["flux_slope"] is not None:
        cfgs = [c.replace(amplitude_prior_power=meta["flux_slope"]["value"]) for c in cfgs]
    if meta.get("flux_bounds"):
        cfgs = [c.replace(amplitude_prior_min=b["lo"], amplitude_prior_max=b["hi"])
                for c, b in zip(cfgs, meta["flux_bounds"], strict=True)]  # fmt: skip
        print("estimated flux bounds (population's): " + "; ".join(
            f"{b['lo']:.4g} ± {b['lo_err']:.2g} ({b['true'][0]:.4g}), {b['hi']:.4g} ± "
            f"{b['hi_err']:.2g} ({b['true'][1]:.4g})" for b in meta["flux_bounds"]))
    if meta["flux_slope"] is not None:
        print(f"flux prior power {meta['flux_slope']['value']:.3f} ± "
              f"{meta['flux_slope']['error']:.3f}")  # fmt: skip
    print(f"calibration: {time.perf_counter() - t0:.0f} s; prior {prior!r}; "
          f"bulge weights {bw}")  # fmt: skip
    return prior, sps, bw, cfgs


def _kv(items: list[str]) -> dict:
    """``KEY=VALUE`` strings as a dict, the values Python literals where they parse."""
    out = {}
    for s in items:
        k, v = s.split("=", 1)
        try:
            out[k] = ast.literal_eval(v)
        except (ValueError, SyntaxError):
            out[k] = v
    return out


def _m_jk(Q, ok, jk, g):
    """Fixed-point m1, m2 of all galaxies, then of each delete-one-group jackknife
    sample (``(1 + k, 2)``, ``k`` groups of ``jk``), without control variates."""
    ug, gi = np.unique(jk, return_inverse=True)
    k = ug.size
    sums = np.stack([np.stack([np.bincount(gi, weights=np.where(ok, Q[:, r, q], 0.0),
                                           minlength=k) for q in range(Q.shape[2])], -1)
                     for r in range(4)], 1)  # (k, 4, n_q) fmt: skip
    n = np.bincount(gi, weights=ok.astype(float), minlength=k)
    tot, ntot = sums.sum(0), n.sum()
    T = np.concatenate([tot[None], tot[None] - sums])  # full, then leave one out
    N = np.concatenate([[ntot], ntot - n])
    gv = np.array([g, g])
    gp = P.shear_from_sums(T[:, 0] + T[:, 1], 2 * N, gv, "fixed-point")
    gm = P.shear_from_sums(T[:, 2] + T[:, 3], 2 * N, -gv, "fixed-point")
    return (gp - gm) / (2 * g) - 1.0


def _jk_err(v: np.ndarray) -> np.ndarray:
    """The jackknife error of the statistic ``v[0]`` from its delete-one values ``v[1:]``."""
    k = len(v) - 1
    return np.sqrt((k - 1) / k * ((v[1:] - v[1:].mean(0)) ** 2).sum(0))


def _paired(QA, QB, ok, jk, g):
    """B - A of the fixed-point m1, m2 with the jackknife over ``jk`` groups."""
    d = _m_jk(QB, ok, jk, g) - _m_jk(QA, ok, jk, g)
    return d[0], _jk_err(d)


def _fp(tab, name: str):
    """The fixed-point row of group ``name`` in a
    :func:`pylensfit_validation.precision.bias_table`."""
    return tab[(tab["group"] == name) & (tab["estimator"] == "fixed-point")][0]


def _mean_err(pairs: list) -> tuple[np.ndarray, np.ndarray]:
    """The mean of ``(value, error)`` pairs (one per PSF) and its error."""
    v, e = np.asarray([p[0] for p in pairs]), np.asarray([p[1] for p in pairs])
    return v.mean(0), np.sqrt((e**2).sum(0)) / len(pairs)


def _split(Q, ok, jk, g):
    """m2 - m1 of one configuration with its jackknife error."""
    m = _m_jk(Q, ok, jk, g)
    d = m[:, 1] - m[:, 0]
    return d[0], _jk_err(d)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ngal", type=int, default=20_000)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--psf", nargs="*", default=None, help="PSF names or indices (default all)")
    ap.add_argument("--a", nargs="*", default=[], metavar="KEY=VALUE",
                    help="changes to precision.default_config for A")
    ap.add_argument("--b", nargs="*", default=[], metavar="KEY=VALUE",
                    help="changes to A's configuration for B")
    ap.add_argument("--spec", nargs="*", default=[], metavar="KEY=VALUE",
                    help="changes to PrecisionSpec for both (values as Python literals: "
                         "snr_range=10,20)")
    ap.add_argument("--b-spec", nargs="*", default=[], metavar="KEY=VALUE",
                    help="changes to the spec for B's renderings (offset_shape=gaussian): "
                         "the same galaxies and noise, drawn otherwise")
    ap.add_argument("--own-priors", action="store_true",
                    help="B's priors from a calibration of B (needed when B has other bulge "
                         "fractions); else A's priors for both")
    ap.add_argument("--a-flux-bounds", choices=["none", "estimated", "oracle"], default=None,
                    help="A's flux prior bounds per PSF: none, estimated by the calibration "
                         "(precision(flux_bounds=True); needs --estimated) or the "
                         "population's flux range (an oracle); default as precision's: "
                         "estimated with --estimated, else none")
    ap.add_argument("--b-flux-bounds", choices=["none", "estimated", "oracle"], default=None,
                    help="B's (default A's)")
    ap.add_argument("--b-prior", nargs=3, type=float, default=None, metavar=("B", "C", "D"),
                    help="B's ellipticity prior (eq. funcprior's B, C, D) instead of A's")
    ap.add_argument("--b-calibration-seed", type=int, default=None,
                    help="B's priors from the calibration sample of this seed (the same "
                         "population, other galaxies and noise): the priors' sampling noise")
    ap.add_argument("--calibration-seed", type=int, default=None,
                    help="the estimated priors (A's, and B's with --own-priors) from the "
                         "calibration sample of this seed instead of --seed's, the main "
                         "sample unchanged: a paired B - A over several calibration samples")
    ap.add_argument("--b-true-size-prior", action="store_true",
                    help="B's size priors the population's own (log-uniform per PSF)")
    ap.add_argument("--a-bulge-weights", nargs="+", type=float, default=None, metavar="W",
                    help="A's weights of the runs of sizes (one per bulge fraction; "
                         "normalised) instead of the calibration's or equal ones")
    ap.add_argument("--b-bulge-weights", nargs="+", type=float, default=None, metavar="W",
                    help="B's (default: B's priors' own)")
    ap.add_argument("--a-stencil", type=int, default=None, choices=[4, 6],
                    help="A's interpolation onto the integration grid: 4 (Keys cubic) or 6 "
                         "(quintic Lagrange; default pylensfit.grid.DEFAULT_STENCIL)")
    ap.add_argument("--b-stencil", type=int, default=None, choices=[4, 6],
                    help="B's (default A's)")
    ap.add_argument("--by-morphology", action="store_true",
                    help="also print B - A per morphology, per PSF and for the mean of PSFs")
    ap.add_argument("--noise-free", action="store_true",
                    help="fit noise-free renderings (the likelihood still assumes the "
                         "spec's noise): the deterministic part of m, without pixel noise")
    ap.add_argument("--by", nargs="*", default=[], choices=["snr", "size"],
                    help="also print A's and B's m2 - m1 and B - A per bin of true S/N or "
                         "size (all PSFs together)")
    ap.add_argument("--estimated", action="store_true",
                    help="the priors a calibration of A estimates (else the population's)")
    a = ap.parse_args()
    spec = P.spec_with(P.PrecisionSpec(ngal=a.ngal, seed=a.seed), psfs=a.psf,
                       **{"ncal": 20_000, **_kv(a.spec)})  # as recorded; --spec ncal=N
    spec_b = P.spec_with(spec, **_kv(a.b_spec))
    kv_a, kv_b = _kv(a.a), _kv(a.b)
    cfg_a = P.default_config(spec).replace(**kv_a)
    cfg_b = cfg_a.replace(**kv_b)
    if a.a_flux_bounds is None:
        a.a_flux_bounds = "estimated" if a.estimated else "none"
    b_bounds = a.b_flux_bounds or a.a_flux_bounds
    cal_spec = spec if a.calibration_seed is None else P.spec_with(spec, seed=a.calibration_seed)
    pri = {"A": _priors(cal_spec, cfg_a, a.estimated, a.jobs, a.a_flux_bounds)}
    if a.b_calibration_seed is not None:  # B's priors from another calibration sample
        pri["B"] = _priors(P.spec_with(spec, seed=a.b_calibration_seed), cfg_b, True, a.jobs,
                           b_bounds)  # fmt: skip
    elif a.own_priors:  # B's priors from its own calibration (or its own bulge fractions)
        pri["B"] = _priors(cal_spec, cfg_b, a.estimated, a.jobs, b_bounds)
    else:  # A's priors; B's bounds A's, the oracle's, or estimated by a calibration of B
        if b_bounds == "estimated" and a.a_flux_bounds != "estimated":
            raise SystemExit("--b-flux-bounds estimated needs --own-priors")
        ca = pri["A"][3]
        cb = [c.replace(**kv_b) for c in ca]
        if b_bounds != a.a_flux_bounds:  # none or the oracle's
            cb = [cfg_b.replace(amplitude_prior_power=ca[0].amplitude_prior_power)] * len(ca)
            if b_bounds == "oracle":
                cb = _oracle(spec, cb[0])
        pri["B"] = pri["A"][:3] + (cb,)
    if a.b_prior:  # B's ellipticity prior given
        pri["B"] = (Prior(**dict(zip("BCD", a.b_prior, strict=True))),) + tuple(pri["B"][1:])
    for w, given in (("A", a.a_bulge_weights), ("B", a.b_bulge_weights)):
        if given is not None:  # the runs' weights given
            bw = np.asarray(given, float)
            if bw.size != len(pri[w][3][0].bulge_runs) or not (bw >= 0).all() or bw.sum() <= 0:
                raise SystemExit(f"--{w.lower()}-bulge-weights needs one weight >= 0 per run "
                                 f"({len(pri[w][3][0].bulge_runs)})")
            pri[w] = pri[w][:2] + (bw / bw.sum(),) + pri[w][3:]
    if a.b_true_size_prior:  # B's size priors the population's own, per PSF
        sp_true = [P.population_size_prior(spec, k, stamp_size=pri["B"][3][0].largest_stamp)
                   for k in range(len(spec.psfs))]  # fmt: skip
        pri["B"] = (pri["B"][0], sp_true) + tuple(pri["B"][2:])
    cfg_a, cfg_b = pri["A"][3][0], pri["B"][3][0]
    npsf = len(spec.psfs)
    nb = -(-spec.ngal // spec.block_size)
    cfgs = {w: pri[w][3] for w in "AB"}
    tasks = [{"spec": spec_b if w == "B" else spec, "config": cfgs[w][b % npsf], "prior": pri[w][0],
              "bulge_weights": pri[w][2], "size_prior": pri[w][1][b % npsf], "psf": b % npsf,
              "block": b, "calibration": False, "which": w, "noise": not a.noise_free,
              "stencil": a.b_stencil or a.a_stencil if w == "B" else a.a_stencil}
             for b in range(nb) for w in "AB"]  # fmt: skip
    res: dict = {"A": {}, "B": {}}
    t0 = time.perf_counter()
    with worker_pool(a.jobs) as pool:
        for t, r in run_tasks(P.block_task, tasks, a.jobs, None, "A/B", True, pool):
            res[t["which"]][t["block"]] = r
    print(f"{len(tasks)} block fits in {time.perf_counter() - t0:.0f} s ({a.jobs} jobs)")
    cat = {w: [res[w][b] for b in range(nb)] for w in "AB"}
    Q = {w: np.concatenate([r["Q"] for r in cat[w]]).astype(float) for w in "AB"}
    ok = np.concatenate([r["usable"] for r in cat["A"]]).all(1) & np.concatenate(
        [r["usable"] for r in cat["B"]]).all(1)
    truth = [r["truth"] for r in cat["A"]]
    psf = np.concatenate([np.full(len(t), r["psf"]) for t, r in zip(truth, cat["A"], strict=True)])
    per = -(-spec.block_size // P.JACKKNIFE_GALAXIES)
    jk = np.concatenate([r["block"] * per + np.arange(len(t)) // P.JACKKNIFE_GALAXIES
                         for t, r in zip(truth, cat["A"], strict=True)])  # fmt: skip
    X = P.shape_controls(np.concatenate([t["e1_int"] for t in truth]),
                         np.concatenate([t["e2_int"] for t in truth]))  # fmt: skip
    groups = {p["name"]: psf == i for i, p in enumerate(spec.psfs)}
    tab = {w: P.bias_table(Q[w], np.repeat(ok[:, None], 4, 1), jk, spec.g, groups=groups,
                           controls=X) for w in "AB"}  # fmt: skip
    bw_txt = "".join(f"; bulge weights {w} {np.round(pri[w][2], 3).tolist()}"
                     for w in "AB" if pri[w][2] is not None)  # fmt: skip
    print(f"A: {kv_a or 'default_config'}; B: A with {kv_b}"
          f"; flux bounds A {a.a_flux_bounds}, B {b_bounds}"
          f"{'; B prior ' + str(a.b_prior) if a.b_prior else ''}"
          f"{'' if a.b_calibration_seed is None else f'; B priors of seed {a.b_calibration_seed}'}"
          f"{'' if a.calibration_seed is None else f'; calibration seed {a.calibration_seed}'}"
          f"{'; B size priors the population' + chr(39) + 's' if a.b_true_size_prior else ''}"
          f"{bw_txt}"
          f"{'; spec ' + str(_kv(a.spec)) if a.spec else ''}"
          f"{'; B spec ' + str(_kv(a.b_spec)) if a.b_spec else ''}"
          f"{'; stencil A ' + str(a.a_stencil) if a.a_stencil else ''}"
          f"{'; stencil B ' + str(a.b_stencil) if a.b_stencil else ''}")
    print(f"{spec.ngal} galaxies, seed {spec.seed}, {int(ok.sum())} with all four renderings "
          f"measured in both; priors {'estimated' if a.estimated else 'the population'}'s")
    from pylensfit.models import model_bank

    for w, cfg in (("A", cfg_a), ("B", cfg_b)):
        bank = model_bank(cfg)
        n_on = [int((sp.node_weights(bank, cfg)[0] > 0).sum()) for sp in pri[w][1]]
        print(f"{w}: sizes evaluated per PSF {n_on} of {bank.n_r}")
    print(f"| PSF | m1 A | m1 B | m2 A | m2 B | B - A, m1 | B - A, m2 |\n|{'---|' * 7}")
    diffs = []
    for name in groups:
        row = {w: _fp(tab[w], name) for w in "AB"}
        sel = groups[name] & ok
        d, e = _paired(Q["A"][sel], Q["B"][sel], ok[sel], jk[sel], spec.g)
        diffs.append((d, e))
        cells = [f"{row[w][q]:+.4f} ± {row[w][q + '_err']:.4f}" for q in ("m1", "m2") for w in "AB"]
        print(f"| {name} | " + " | ".join(cells) +
              f" | {d[0]:+.5f} ± {e[0]:.5f} | {d[1]:+.5f} ± {e[1]:.5f} |")  # fmt: skip
    d_mean, e = _mean_err(diffs)
    mean = {w: [np.mean([_fp(tab[w], n)[q] for n in groups]) for q in ("m1", "m2")]
            for w in "AB"}  # fmt: skip
    print(f"| mean of PSFs | {mean['A'][0]:+.4f} | {mean['B'][0]:+.4f} | {mean['A'][1]:+.4f} | "
          f"{mean['B'][1]:+.4f} | {d_mean[0]:+.5f} ± {e[0]:.5f} | {d_mean[1]:+.5f} ± {e[1]:.5f} |")
    print(f"c (fixed point, with controls):\n| PSF | c1 A | c1 B | c2 A | c2 B |\n|{'---|' * 5}")
    for name in groups:
        row = {w: _fp(tab[w], name) for w in "AB"}
        print(f"| {name} | " + " | ".join(f"{row[w][q]:+.5f} ± {row[w][q + '_err']:.5f}"
                                          for q in ("c1", "c2") for w in "AB") + " |")
    print("m2 - m1 (jackknife, no controls):\n| PSF | A | B |\n|---|---|---|")
    sp = {w: [] for w in "AB"}
    for name in groups:
        sel = groups[name] & ok
        cells = []
        for w in "AB":
            sp[w].append(_split(Q[w][sel], ok[sel], jk[sel], spec.g))
            cells.append(f"{sp[w][-1][0]:+.5f} ± {sp[w][-1][1]:.5f}")
        print(f"| {name} | " + " | ".join(cells) + " |")
    print("| mean of PSFs | " + " | ".join(
        "{:+.5f} ± {:.5f}".format(*_mean_err(sp[w])) for w in "AB") + " |")
    gal = {c: np.concatenate([np.asarray(t[c]) for t in truth])
           for c in ("snr", "size_ratio", "bulge_frac", "morph")}  # fmt: skip
    gal["psf"] = psf
    bins = P.breakdowns(gal, spec.psfs)  # the precision report's bins
    for by in a.by:  # bins of true S/N or size, all PSFs together
        print(f"by {by}:\n| bin | galaxies | m2 - m1, A | m2 - m1, B | B - A, m1 | B - A, m2 |"
              f"\n|{'---|' * 6}")  # fmt: skip
        for label, in_bin in bins[by].items():
            sel = ok & in_bin
            if sel.sum() < 200:
                continue
            cells = [f"{x[0]:+.4f} ± {x[1]:.4f}"
                     for x in (_split(Q[w][sel], ok[sel], jk[sel], spec.g) for w in "AB")]
            d, e = _paired(Q["A"][sel], Q["B"][sel], ok[sel], jk[sel], spec.g)
            print(f"| {label} | {int(sel.sum())} | " + " | ".join(cells) +
                  f" | {d[0]:+.4f} ± {e[0]:.4f} | {d[1]:+.4f} ± {e[1]:.4f} |")  # fmt: skip
    if a.by_morphology:
        mg = {f"{name} {mname}": groups[name] & (gal["morph"] == im)
              for name in groups for im, mname in enumerate(P.MORPHOLOGIES)}
        mtab = {w: P.bias_table(Q[w], np.repeat(ok[:, None], 4, 1), jk, spec.g, groups=mg,
                                controls=X) for w in "AB"}  # fmt: skip
        print(f"each (fixed point, with controls):\n| PSF, morphology | galaxies | m1 A | m1 B "
              f"| m2 A | m2 B |\n|{'---|' * 6}")  # fmt: skip
        for key, sel in mg.items():
            if (sel & ok).sum() < 200:
                continue
            row = {w: _fp(mtab[w], key) for w in "AB"}
            print(f"| {key} | {int((sel & ok).sum())} | " + " | ".join(
                f"{row[w][q]:+.4f} ± {row[w][q + '_err']:.4f}" for q in ("m1", "m2")
                for w in "AB") + " |")  # fmt: skip
        print(f"| B - A, m1 / m2 | {' | '.join(groups)} | mean of PSFs |\n|{'---|' * (npsf + 2)}")
        for mname in P.MORPHOLOGIES:
            cells, pairs = [], []
            for name in groups:
                sel = mg[f"{name} {mname}"] & ok
                if sel.sum() < 200:
                    cells.append("")
                    continue
                d, e = _paired(Q["A"][sel], Q["B"][sel], ok[sel], jk[sel], spec.g)
                pairs.append((d, e))
                cells.append(f"{d[0]:+.4f} / {d[1]:+.4f} ± {e[0]:.4f} / {e[1]:.4f}")
            if pairs:
                d, e = _mean_err(pairs)
                cells.append(f"{d[0]:+.4f} / {d[1]:+.4f} ± {e[0]:.4f} / {e[1]:.4f}")
            print(f"| {mname} | " + " | ".join(cells) + " |")
    for w in "AB":
        fit = sum(r["fit_s"] for r in cat[w])
        ren = sum(r["render_s"] for r in cat[w])
        print(f"{w}: fit {fit:.0f} s CPU ({fit / nb:.2f} s per block), render {ren:.0f} s")
    if not math.isfinite(float(d_mean[0])):
        raise SystemExit("the paired difference is not finite")


if __name__ == "__main__":
    main()
