"""lensfit's sensitivity against a metacalibrated response, on the same precision renderings.

The precision mode's blocks (``pylensfit_validation.precision``: four renderings per galaxy, +-g,
unrotated and rotated by 90 degrees, the same noise at +g and -g) are measured three
ways, with the same priors (estimated by the precision mode's calibration of the
default configuration, or the population's with ``--true-priors``):

- ``lensfit``: the precision mode's own estimate (the fixed point of the posterior
  means under the sheared prior);
- ``lensfit-mc``: lensfit's ``sum <e> / sum s`` (exact sensitivity) on the unsheared
  metacalibration image (deconvolved, reconvolved with the 2 % larger PSF, fixnoise
  added): what the doubled noise and the wider PSF do alone;
- ``metacal``: ``R^-1 sum <e>`` on that image, with ``R`` from the posterior means of
  the four images sheared by +-delta (:mod:`pylensfit.metacal`): the response of the
  posterior mean measured on the galaxy instead of assumed from the models;
- ``corrected``: lensfit's ``<e>`` on the renderings themselves over their exact
  sensitivity ``s0`` plus metacalibration's measure of the model bias,
  ``sum <e> / sum (s0 + R - s_mc)`` (``s_mc`` the sensitivity on the unsheared
  metacalibration image): the model bias measured on the galaxy, the measurement
  without the metacalibration images' doubled noise.

m per PSF, per morphology, per true S/N (and per morphology above S/N 20) and for the
mean of PSFs, each with the jackknife error over
groups of 100 galaxies, and the paired differences ``metacal - lensfit``::

    python benchmarks/precision_metacal.py --ngal 4000 --psf e=0.10 --jobs 2
    python benchmarks/precision_metacal.py --ngal 8000 --psf e=0.10 --morphology-weights 0 0 0 1 0
    python benchmarks/precision_metacal.py --ngal 8000 --psf e=0.10 --flux-bounds estimated \
        --antithetic
    python benchmarks/precision_metacal.py --ngal 4000 --psf round --true-priors --antithetic \
        --morphology-weights 1 0 0 0 0 --set model=exponential   # exact models
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from pylensfit.runner import run_tasks, worker_pool
from pylensfit_validation import precision as P
from pylensfit_validation.simulate import POPULATIONS

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent / "studies"))
from precision_ab import _jk_err, _kv, _m_jk, _priors  # noqa: E402

from bench_precision import hsm_shapes  # noqa: E402

_EST = ("lensfit", "lensfit-mc", "metacal", "corrected")


def _block(task: dict) -> dict:
    """Render, fit and metacalibrate one block (runs in a worker)."""
    from pylensfit.likelihood import fit_stamps
    from pylensfit.metacal import metacal_shapes
    from pylensfit.prior import mix_bulge_fractions, usable_rows
    from pylensfit.runner import single_thread
    from pylensfit.shear import posterior_moments, shear_sensitivity

    single_thread(task.get("single_thread", False))
    spec, cfg, prior, bw = task["spec"], task["config"], task["prior"], task["bulge_weights"]
    stamps, psf, truth = P.render_block(spec, task["psf"], task["block"],
                                        stamp_size=cfg.largest_stamp,
                                        noise=task["noise"])  # fmt: skip
    n, N = stamps.shape[0], stamps.shape[-1]
    flat = stamps.reshape(4 * n, N, N)
    # the added noise: one field per galaxy and rotation, shared by +g and -g as the
    # renderings' own noise is
    nf = np.random.default_rng([spec.seed, 17, task["block"]]).standard_normal((n, 2, N, N))
    fields = nf[:, [0, 1, 0, 1]].reshape(4 * n, N, N)
    sets = [(flat, fields)]
    if task["antithetic"] and task["noise"]:  # the same galaxies with the noise negated
        clean = P.render_block(spec, task["psf"], task["block"], stamp_size=cfg.largest_stamp,
                               noise=False)[0].reshape(4 * n, N, N)  # fmt: skip
        sets.append((2 * clean - flat, -fields))
    kw = {"config": cfg, "size_prior": task["size_prior"]}
    out = {"QA": 0.0, "e": 0.0, "s": 0.0, "R": 0.0, "e0": 0.0, "s0": 0.0}
    ok = np.ones(4 * n, bool)
    times = np.zeros(3)
    for imgs, fld in sets:
        t0 = time.perf_counter()
        fits = fit_stamps(imgs, psf, spec.noise_sigma, **kw)
        QA, okA = P.reduce_renderings(fits, prior, spec.g, refine=cfg.output_refine,
                                      bulge_weights=bw)  # fmt: skip
        # lensfit's own <e> and exact sensitivity on the renderings themselves
        lnL = fits.lnL if fits.lnL_bulge is None else mix_bulge_fractions(
            fits.lnL_bulge, fits.lnL_star, bw)
        lnL = np.where(usable_rows(lnL)[:, None], lnL, 0.0)
        mom = posterior_moments(lnL, fits.egrid, prior, refine=cfg.output_refine)
        s0 = shear_sensitivity(lnL, fits.egrid, prior, refine=cfg.output_refine)
        t1 = time.perf_counter()
        if task["about_stamp"]:  # the stamp's centre as the galaxy's
            fits = replace(fits, x=np.full(4 * n, N // 2.0), y=np.full(4 * n, N // 2.0))
        elif task["about_true"]:  # the galaxy's true centre (an oracle)
            fits = replace(fits, x=N // 2 + np.repeat(np.asarray(truth["dx"], float), 4),
                           y=N // 2 + np.repeat(np.asarray(truth["dy"], float), 4))
        sh = metacal_shapes(imgs, psf, spec.noise_sigma, prior, config=cfg, fits=fits,
                            bulge_weights=bw, step=task["step"],
                            noise_fields=fld if task["noise"] else np.zeros_like(fld),
                            size_prior=task["size_prior"],
                            position_prior_sigma=task["mc_position_prior"],
                            dilation=task["dilation"],
                            reconvolution=task["reconvolution"] or cfg.metacal_reconvolution)
        ok &= okA.reshape(-1) & (np.asarray(sh["flag"]) == 0)
        w = 1.0 / len(sets)
        out["QA"] = out["QA"] + w * np.nan_to_num(QA)
        out["e"] = out["e"] + w * np.nan_to_num(np.column_stack([sh["e1"], sh["e2"]]))
        out["s"] = out["s"] + w * np.nan_to_num(np.column_stack([sh["s1"], sh["s2"]]))
        out["e0"] = out["e0"] + w * np.nan_to_num(np.column_stack([mom["e1"], mom["e2"]]))
        out["s0"] = out["s0"] + w * np.nan_to_num(np.column_stack([s0[0], s0[1]]))
        out["R"] = out["R"] + w * np.nan_to_num(
            np.stack([np.column_stack([sh["R11"], sh["R12"]]),
                      np.column_stack([sh["R21"], sh["R22"]])], 1))  # fmt: skip
        t2 = time.perf_counter()
        if task["hsm"]:
            hsm_shapes(imgs, psf)  # GalSim HSM REGAUSS on the same renderings, timed only
        times += [t1 - t0, t2 - t1, time.perf_counter() - t2]
    out = {"QA": out["QA"], "e": out["e"].reshape(n, 4, 2), "s": out["s"].reshape(n, 4, 2),
           "R": out["R"].reshape(n, 4, 2, 2), "e0": out["e0"].reshape(n, 4, 2),
           "s0": out["s0"].reshape(n, 4, 2)}  # fmt: skip
    return {"block": task["block"], "psf": task["psf"], "truth": truth,
            "ok": ok.reshape(n, 4).all(1), **out, "fit_s": times[0], "mc_s": times[1],
            "hsm_s": times[2]}


def _m_metacal(e, s, R, ok, jk, g, est):
    """m1, m2 of all galaxies, then of each delete-one group (``(1 + k, 2)``)."""
    ug, gi = np.unique(jk[ok], return_inverse=True)
    k = ug.size

    def gsum(v):  # (n, ...) summed over each rendering pair and group: (k, ...)
        return np.stack([np.bincount(gi, weights=x, minlength=k)
                         for x in v[ok].reshape(ok.sum(), -1).T], -1).reshape((k,) + v.shape[1:])

    E, D = [], []
    for sign in (0, 2):  # renderings 0-1 at +g, 2-3 at -g
        E.append(gsum(e[:, sign] + e[:, sign + 1]))
        if est == "metacal":
            D.append(gsum(R[:, sign] + R[:, sign + 1]))
        else:
            sv = gsum(s[:, sign] + s[:, sign + 1])
            d = np.zeros(sv.shape + (2,))
            d[..., 0, 0], d[..., 1, 1] = sv[..., 0], sv[..., 1]
            D.append(d)
    # one response for +g and -g, their mean (as a survey's mean response over its shears)
    Dm = 0.5 * (D[0] + D[1])
    Dt = np.concatenate([Dm.sum(0)[None], Dm.sum(0)[None] - Dm])
    out = []
    for Ek in E:
        Et = np.concatenate([Ek.sum(0)[None], Ek.sum(0)[None] - Ek])
        out.append(np.linalg.solve(Dt, Et[..., None])[..., 0])
    return (out[0] - out[1]) / (2 * g) - 1.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ngal", type=int, default=4000)
    ap.add_argument("--seed", type=int, default=41)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--psf", nargs="*", default=None, help="PSF names or indices (default all)")
    ap.add_argument("--morphology-weights", nargs=5, type=float, default=None, metavar="W",
                    help="exponential, de Vaucouleurs, bulge+disc, Sersic, knots")
    ap.add_argument("--population", choices=list(POPULATIONS), default="aligned",
                    help="PrecisionSpec.population: the galaxies (realistic: misaligned and "
                         "rounder bulges, Sersic 0.3-6)")  # fmt: skip
    ap.add_argument("--g", type=float, default=None, help="the applied shear per component")
    ap.add_argument("--offset", type=float, default=None,
                    help="PrecisionSpec.offset (0: centred galaxies, position prior 0.01 px)")
    ap.add_argument("--ncal", type=int, default=20_000,
                    help="PrecisionSpec.ncal (default 20,000, as recorded)")
    ap.add_argument("--step", type=float, default=0.01, help="metacalibration's delta")
    ap.add_argument("--dilation", type=float, default=None,
                    help="the reconvolution PSF's dilation (default 1 + 2 step)")
    ap.add_argument("--reconvolution", choices=("round", "dilate"), default=None,
                    help="the reconvolution PSF (default Config.metacal_reconvolution's)")
    ap.add_argument("--no-hsm", action="store_true",
                    help="skip GalSim HSM REGAUSS (timed on the same renderings otherwise)")
    ap.add_argument("--true-priors", action="store_true",
                    help="the population's priors (else those the calibration estimates)")
    ap.add_argument("--noise-free", action="store_true",
                    help="fit noise-free renderings (the fits still assume the spec's noise; "
                         "no field added): model bias alone, without the responses' noise")
    ap.add_argument("--about-stamp-centre", action="store_true",
                    help="shear about the stamp's centre (the catalogue position), not the "
                         "galaxy's fitted centre")
    ap.add_argument("--about-true-centre", action="store_true",
                    help="shear about the galaxy's true centre (an oracle), not its fitted "
                         "centre: what the fitted centre's noise does to the response")
    ap.add_argument("--metacal-position-prior", type=float, default=2.0, metavar="SIGMA",
                    help="the metacalibration images' fits' position prior width, px "
                         "(metacal_shapes' position_prior_sigma; 0: the fits' own)")
    ap.add_argument("--antithetic", action="store_true",
                    help="also measure every rendering with its noise (and the added field) "
                         "negated, and average: the responses' noise cancels to first order")
    ap.add_argument("--save", default=None, help="also write the per-rendering arrays here (npz)")
    ap.add_argument("--flux-bounds", choices=["none", "estimated", "oracle"], default="none",
                    help="the flux prior's bounds: none (the unbounded power law), estimated "
                         "by the calibration (as the precision mode's default does) or the "
                         "population's")  # fmt: skip
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="changes to the default configuration (model=exponential)")
    a = ap.parse_args()
    kw = {} if a.morphology_weights is None else {"morphology_weights": tuple(a.morphology_weights)}
    if a.g is not None:
        kw["g"] = a.g
    if a.ncal is not None:
        kw["ncal"] = a.ncal
    if a.offset is not None:
        kw["offset"] = a.offset
    spec = P.spec_with(P.PrecisionSpec(ngal=a.ngal, seed=a.seed, population=a.population),
                       psfs=a.psf, **kw)
    cfg = P.default_config(spec).replace(**_kv(a.set))
    prior, sps, bw, cfgs = _priors(spec, cfg, not a.true_priors, a.jobs, a.flux_bounds)
    npsf = len(spec.psfs)
    nb = -(-spec.ngal // spec.block_size)
    tasks = [{"spec": spec, "config": cfgs[b % npsf], "prior": prior, "bulge_weights": bw,
              "size_prior": sps[b % npsf], "psf": b % npsf, "block": b, "step": a.step,
              "noise": not a.noise_free, "about_stamp": a.about_stamp_centre,
              "about_true": a.about_true_centre,
              "mc_position_prior": a.metacal_position_prior or None,
              "antithetic": a.antithetic, "dilation": a.dilation, "hsm": not a.no_hsm,
              "reconvolution": a.reconvolution}
             for b in range(nb)]  # fmt: skip
    res = {}
    t0 = time.perf_counter()
    with worker_pool(a.jobs) as pool:
        for t, r in run_tasks(_block, tasks, a.jobs, None, "metacal", True, pool):
            res[t["block"]] = r
    cat = [res[b] for b in range(nb)]
    cpu = {k: sum(r[k] for r in cat) for k in ("fit_s", "mc_s", "hsm_s")}
    nr = sum(4 * len(r["ok"]) for r in cat) * (2 if a.antithetic and not a.noise_free else 1)
    print(f"{nb} blocks in {time.perf_counter() - t0:.0f} s ({a.jobs} jobs); renderings per "
          f"CPU second: lensfit's fit {nr / cpu['fit_s']:.1f}, with metacalibration "
          f"{nr / (cpu['fit_s'] + cpu['mc_s']):.1f}"
          + ("" if a.no_hsm else f", GalSim HSM REGAUSS {nr / cpu['hsm_s']:.1f}")
          + " (same process)")
    QA = np.concatenate([r["QA"] for r in cat]).astype(float)
    e, s, R, e0, s0 = (np.concatenate([r[k] for r in cat]).astype(float)
                       for k in ("e", "s", "R", "e0", "s0"))
    ok = np.concatenate([r["ok"] for r in cat])
    truth = [r["truth"] for r in cat]
    psf = np.concatenate([np.full(len(t), r["psf"]) for t, r in zip(truth, cat, strict=True)])
    morph = np.concatenate([np.asarray(t["morph"]) for t in truth])
    per = -(-spec.block_size // P.JACKKNIFE_GALAXIES)
    jk = np.concatenate([r["block"] * per + np.arange(len(t)) // P.JACKKNIFE_GALAXIES
                         for t, r in zip(truth, cat, strict=True)])  # fmt: skip
    if a.save:
        np.savez(a.save, QA=QA, e=e, s=s, R=R, e0=e0, s0=s0, ok=ok, jk=jk, psf=psf,
                 morph=morph, g=spec.g, snr=np.concatenate([np.asarray(t["snr"]) for t in truth]),
                 r=np.concatenate([np.asarray(t["r"]) for t in truth]))  # fmt: skip
    print(f"{ok.sum()} of {ok.size} galaxies measured in all 24 fits; prior {prior!r}; "
          f"bulge weights {np.round(bw, 3).tolist()}")
    R_mean = R[ok].mean((0, 1))
    s_mean = s[ok].mean((0, 1))
    print(f"mean R = [[{R_mean[0, 0]:.4f}, {R_mean[0, 1]:+.4f}], [{R_mean[1, 0]:+.4f}, "
          f"{R_mean[1, 1]:.4f}]]; mean lensfit sensitivity on the metacal image "
          f"{s_mean[0]:.4f}, {s_mean[1]:.4f}")
    R11, R22, s1, s2 = R[ok][..., 0, 0], R[ok][..., 1, 1], s[ok][..., 0], s[ok][..., 1]
    print(f"per rendering std: R11 {R11.std():.3f}, s1 {s1.std():.3f}, R11 - s1 "
          f"{(R11 - s1).std():.3f}; R22 {R22.std():.3f}, s2 {s2.std():.3f}, R22 - s2 "
          f"{(R22 - s2).std():.3f}")

    Rc = R.copy()  # s0 + R - s_mc
    for i in range(2):
        Rc[..., i, i] += s0[..., i] - s[..., i]

    def row(name, sel):
        if sel.sum() < 200:
            return
        okk = ok & sel
        ms = {"lensfit": _m_jk(QA[okk], np.ones(okk.sum(), bool), jk[okk], spec.g)}
        one = np.ones(okk.sum(), bool)
        for est in _EST[1:3]:
            ms[est] = _m_metacal(e[okk], s[okk], R[okk], one, jk[okk], spec.g, est)
        ms["corrected"] = _m_metacal(e0[okk], s[okk], Rc[okk], one, jk[okk], spec.g, "metacal")
        def cell(v):  # m1 / m2 with their jackknife errors
            err = _jk_err(v)
            return f"{v[0, 0]:+.4f} ± {err[0]:.4f} / {v[0, 1]:+.4f} ± {err[1]:.4f}"

        cells = [cell(ms[x]) for x in _EST]
        cells += [cell(ms["metacal"] - ms[y]) for y in ("lensfit", "lensfit-mc")]
        print(f"| {name} | {okk.sum()} | " + " | ".join(cells) + " |")

    print("\n| sample | galaxies | lensfit m1 / m2 | lensfit-mc | metacal | corrected "
          "| metacal - lensfit | metacal - lensfit-mc |")
    print("|---|---|---|---|---|---|---|---|")
    for i, p in enumerate(spec.psfs):
        row(p["name"], psf == i)
    row("all", np.ones_like(ok))
    for j, mname in enumerate(P.MORPHOLOGIES):
        row(mname, morph == j)
    snr = np.concatenate([np.asarray(t["snr"]) for t in truth])
    for lo, hi in ((0, 20), (20, 40), (40, np.inf)):
        row(f"S/N {lo}-{hi:g}", (snr >= lo) & (snr < hi))
    for j, mname in enumerate(P.MORPHOLOGIES):  # the kinds above the faint end
        row(f"{mname}, S/N >= 20", (morph == j) & (snr >= 20))


if __name__ == "__main__":
    main()
