"""Paired +-g bias of the engine alone: galaxies of one morphology fitted with that model.

With the true profile in the model family, the population's true prior and a high S/N,
m should vanish apart from engine error (grids, quadrature, interpolation). Prints m, c
for all galaxies and by size (in PSF half-light radii), plain and (rows ``cv``) with the
intrinsic shapes' spin-4 parts as control variates (precision.shape_controls), which
take out the shape noise that the rotated twins leave; rows ``n`` bin the Sersic
galaxies by index. The bins by true size are
conditional on the truth: with a size prior, a Bayesian estimate is biased low for the
smallest and high for the largest galaxies of the population while the whole is not::

    python benchmarks/studies/exact_model_bias.py exponential --snr 40 200 --size 0.5 1.0
    python benchmarks/studies/exact_model_bias.py devaucouleurs --stamp 64 --config r_rel_step=0
    python benchmarks/studies/exact_model_bias.py exponential --snr 30 30.01 --size 0.5 0.7 \
        --noise-free --size-prior estimate --ngal 4000
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from brute_likelihood import true_size_prior  # this folder's (run as a script)

from pylensfit.config import Config
from pylensfit.likelihood import fit_stamps
from pylensfit.models import model_bank
from pylensfit.prior import estimate_bulge_weights, estimate_size_prior
from pylensfit_validation.precision import (
    MORPHOLOGIES,
    bias_table,
    population_prior,
    reduce_renderings,
    render_block,
    shape_controls,
    spec_with,
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("morphology", choices=[*MORPHOLOGIES, "mix"],
                    help="galaxies of one morphology, or 'mix': the precision mode's mixture")
    ap.add_argument("--ngal", type=int, default=2000)
    ap.add_argument("--snr", type=float, nargs=2, default=(40.0, 200.0))
    ap.add_argument("--size", type=float, nargs=2, default=(0.5, 2.5))
    ap.add_argument("--psf", default="round")
    ap.add_argument("--psf-fwhm", type=float, default=None,
                    help="the PSF with this FWHM (pixels) instead of its own: how the bias "
                         "follows the PSF's sampling")
    ap.add_argument("--stamp", type=int, default=32)
    ap.add_argument("--seed", type=int, default=41)
    ap.add_argument("--model", default=None, help="model family (default: the morphology)")
    ap.add_argument("--bulge-prior", choices=["uniform", "estimate"], default="uniform",
                    help="bulge-fraction prior: uniform, or estimated from an unsheared "
                         "calibration sample of --ngal galaxies (true e prior)")
    ap.add_argument("--size-prior", choices=["flat", "estimate", "true"], default="flat",
                    help="size prior: the paper's flat one, estimated from the unsheared "
                         "calibration sample (prior.estimate_size_prior), or the population's "
                         "true one (log-uniform in half-light radius over --size)")
    ap.add_argument("--noise-free", action="store_true",
                    help="render without noise (the fits still assume sigma = 1, so the "
                         "likelihood keeps the width of the S/N): the bias of the model and "
                         "the priors alone, without noise bias")
    ap.add_argument("--pedestal", type=float, default=0.0,
                    help="add this constant (in noise sigmas) to every pixel of the "
                         "sheared renderings: a background left after sky subtraction")
    ap.add_argument("--config", nargs="*", default=[], help="Config overrides KEY=VALUE")
    a = ap.parse_args()
    def value(v: str):
        try:
            return float(v)
        except ValueError:
            return v

    over = {k: value(v) for k, v in (s.split("=", 1) for s in a.config)}
    exact = a.morphology in ("exponential", "devaucouleurs")
    over.update(model=a.model or (a.morphology if exact else "bulge+disc"))
    weights = tuple(1.0 if m == a.morphology else 0.0 for m in MORPHOLOGIES)
    if a.morphology == "mix":
        weights = spec_with().morphology_weights
    psf_spec = a.psf
    if a.psf_fwhm is not None:
        psf_spec = {**spec_with(psfs=[a.psf]).psfs[0], "fwhm": a.psf_fwhm}
    spec = spec_with(
        ngal=a.ngal, ncal=a.ngal, block_size=500, seed=a.seed, snr_range=tuple(a.snr),
        psfs=[psf_spec], morphology_weights=weights, size_ratio_range=tuple(a.size),
    )
    cfg = Config(stamp_size=a.stamp, **over)
    prior = population_prior(spec)
    t0 = time.time()
    bw = sp = None
    est_bulge = a.bulge_prior == "estimate" and cfg.n_bulge_fractions > 1

    def calibration(size_prior):
        lb, ls, lr = [], [], []
        for b in range(-(-spec.ncal // spec.block_size)):
            st, psf, _ = render_block(spec, 0, b, stamp_size=a.stamp, calibration=True,
                                      noise=not a.noise_free)  # fmt: skip
            f = fit_stamps(st[:, 0], psf, 1.0, config=cfg, size_prior=size_prior)
            ok = (f.flags == 0) & ~f.is_star
            lr.append(f.lnL_r[ok])
            if f.lnL_bulge is not None:
                lb.append(f.lnL_bulge[ok])
                ls.append(f.lnL_star[ok])
        return (np.concatenate(lb) if lb else None, np.concatenate(ls) if ls else None,
                np.concatenate(lr))  # fmt: skip

    if a.size_prior == "true":  # log-uniform between the population's bounds
        sp = true_size_prior(spec, a.size, a.stamp)
        if cfg.model == "bulge+disc":
            raise SystemExit("--size-prior true: for the exact models only")
    if est_bulge or a.size_prior == "estimate":
        lb, ls, lr = calibration(None)
        if est_bulge:
            bw = estimate_bulge_weights(lb, ls, prior)
        if a.size_prior == "estimate":
            sp = estimate_size_prior(lr, model_bank(cfg), cfg, bulge_weights=bw)
            q = np.quantile(np.exp(sp.ln_h), [0.0, 1.0])
            cdf = np.cumsum(sp.density) / np.sum(sp.density)
            pct = np.exp(np.interp([0.05, 0.5, 0.95], cdf, sp.ln_h))
            print(f"size prior: half-light radius 5/50/95% {np.round(pct, 2).tolist()} px "
                  f"(knots {q[0]:.2f}-{q[1]:.2f}), point sources {sp.star:.2e}")
            if est_bulge:
                lb, ls, _ = calibration(sp)
                bw = estimate_bulge_weights(lb, ls, prior)
        if est_bulge:
            print(f"bulge-fraction prior {np.round(bw, 4).tolist()} from {spec.ncal} galaxies")
    Q, U, S, X, N = [], [], [], [], []
    for b in range(-(-a.ngal // spec.block_size)):
        st, psf, t = render_block(spec, 0, b, stamp_size=a.stamp, noise=not a.noise_free)
        st = st + np.float32(a.pedestal * spec.noise_sigma)
        n = len(st)
        f = fit_stamps(st.reshape(n * 4, a.stamp, a.stamp), psf, 1.0, config=cfg,
                       size_prior=sp)
        q, u = reduce_renderings(f, prior, spec.g, refine=cfg.integration_refine,
                                 bulge_weights=bw)
        Q.append(q)
        U.append(u)
        S.append(np.asarray(t["size_ratio"]))
        N.append(np.asarray(t["sersic_n"]))
        X.append(shape_controls(t["e1_int"], t["e2_int"]))
    Q, U, S, X, N = map(np.concatenate, (Q, U, S, X, N))
    B = np.arange(S.size) * 40 // S.size  # 40 jackknife groups (a few render blocks are too few)
    print(f"{a.morphology}, model {cfg.model}, {a.ngal} galaxies, S/N {a.snr}, "
          f"{time.time() - t0:.0f} s")  # fmt: skip
    edges = np.unique(np.clip([a.size[0], 1.0, 1.6, a.size[1]], *a.size))
    groups = [("all", np.ones(S.size, bool))]
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        groups.append((f"size {lo:g}-{hi:g}", (S >= lo) & (S < hi)))
    for lo, hi in ((0.5, 0.9), (0.9, 1.3), (1.3, 2.0), (2.0, 3.0), (3.0, 4.01)):  # Sersic index
        groups.append((f"n {lo:g}-{hi:g}", (N >= lo) & (N < hi)))
    for label, sel in groups:
        if sel.sum() < 2 * spec.block_size // 10:
            continue
        for tag, x in (("", None), (" cv", X[sel])):
            r = bias_table(Q[sel], U[sel], B[sel], spec.g, controls=x)
            r = r[r["estimator"] == "fixed-point"][0]
            print(f"{label + tag:17s} m1 {r['m1']:+.4f} ± {r['m1_err']:.4f}  "
                  f"m2 {r['m2']:+.4f} ± {r['m2_err']:.4f}  "
                  f"c1 {r['c1']:+.5f}  c2 {r['c2']:+.5f}  n {r['n_gal']}")  # fmt: skip


if __name__ == "__main__":
    main()
