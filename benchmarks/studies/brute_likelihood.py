"""The engine's L(e) against a brute-force likelihood, and the shear bias of each.

Galaxies of one exact model family (exponential or de Vaucouleurs), centred on their
stamps (``PrecisionSpec.offset = 0``), with the population's own ellipticity prior and
size prior (log-uniform in half-light radius over ``--size`` PSF radii), rendered by
GalSim at +-g with their 90-degree twins as in ``validate --precision``. Each stamp's
``ln L(e)`` is then computed two ways:

- ``engine``: :func:`pylensfit.likelihood.fit_stamps` with the position prior pinned to
  the true centre (``position_prior_sigma = 0.01`` px), the uniform amplitude prior;
- ``brute``: every model of the grid rendered at the true centre
  (:func:`pylensfit.models.render_models`), ``chi^2`` against the stamp, the amplitude
  integrated exactly, the sizes summed with the same prior weights. Two amplitude
  priors: ``uniform`` (the engine's) and ``population`` (the simulation's own: the
  model's S/N ``t`` distributed as ``t^-snr_slope`` on ``--snr``, integrated by
  Gauss-Legendre quadrature).

Point sources are kept (flag STAR cleared) so that no selection enters. m, c are the
fixed-point estimator's, with the intrinsic shapes' control variates::

    python benchmarks/studies/brute_likelihood.py devaucouleurs --snr 10 20 --size 0.5 0.7
    python benchmarks/studies/brute_likelihood.py devaucouleurs --snr 10 20 --size 0.5 0.7 \
        --noise-free
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np
from scipy.special import log_ndtr, logsumexp

from pylensfit.config import Config
from pylensfit.flags import flag_value
from pylensfit.likelihood import fit_stamps
from pylensfit.models import model_bank, render_models
from pylensfit.prior import SizePrior
from pylensfit_validation.precision import (
    MORPHOLOGIES,
    bias_table,
    population_prior,
    population_size_prior,
    reduce_renderings,
    render_block,
    shape_controls,
    spec_with,
)


def true_size_prior(spec, size, stamp_size: int = 32) -> SizePrior:
    """Log-uniform in half-light radius over ``size`` times the PSF's half-light radius
    (the precision population's sizes; also ``exact_model_bias.py --size-prior true``)."""
    one = dataclasses.replace(spec, size_ratio_range=tuple(float(v) for v in size))
    return population_size_prior(one, 0, stamp_size=stamp_size)


def amplitude_terms(t, snr, slope):
    """``ln`` of the amplitude integrals (less ``t^2 / 2``) of both priors, per model S/N ``t``."""
    uniform = log_ndtr(t)  # the -0.5 ln S of the uniform prior is added by the caller
    xg, wg = np.polynomial.legendre.leggauss(64)
    lo, hi = snr
    tq = 0.5 * (lo + hi) + 0.5 * (hi - lo) * xg
    lw = np.log(0.5 * (hi - lo) * wg) - slope * np.log(tq)
    lw -= logsumexp(lw)  # a normalised prior
    pop = np.empty_like(t)
    flat, out = t.reshape(-1), pop.reshape(-1)
    for j in range(0, flat.size, 1 << 20):
        s = flat[j : j + (1 << 20)]
        out[j : j + s.size] = logsumexp(-0.5 * (tq[None] - s[:, None]) ** 2 + lw, axis=1)
    return uniform, pop


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("morphology", choices=["exponential", "devaucouleurs"])
    ap.add_argument("--ngal", type=int, default=2000)
    ap.add_argument("--snr", type=float, nargs=2, default=(10.0, 20.0))
    ap.add_argument("--size", type=float, nargs=2, default=(0.5, 0.7))
    ap.add_argument("--psf", default="round")
    ap.add_argument("--seed", type=int, default=8)
    ap.add_argument("--e-step", type=float, default=Config().e_step, help="model grid step in e")
    ap.add_argument("--noise-free", action="store_true",
                    help="render without noise (the fits still assume sigma = 1)")
    a = ap.parse_args()
    weights = tuple(1.0 if m == a.morphology else 0.0 for m in MORPHOLOGIES)
    spec = spec_with(ngal=a.ngal, ncal=a.ngal, block_size=500, seed=a.seed,
                     snr_range=tuple(a.snr), psfs=[a.psf], morphology_weights=weights,
                     size_ratio_range=tuple(a.size), offset=0.0)  # fmt: skip
    cfg = Config(model=a.morphology, position_prior_sigma=0.01, e_step=a.e_step)
    prior = population_prior(spec)
    sp = true_size_prior(spec, a.size, cfg.stamp_size)
    bank = model_bank(cfg)
    node_w, w_star = sp.node_weights(bank, cfg)
    live = node_w > 1e-3 * node_w.max()  # the floor elsewhere: e^-7 of the mass
    eg, n_live = bank.egrid, int(live.sum())
    e1, e2 = np.repeat(eg[:, 0], n_live), np.repeat(eg[:, 1], n_live)
    r = np.tile(bank.radii[live], eg.shape[0])
    ln_w = np.log(np.tile(node_w[live], eg.shape[0]))
    star = flag_value("STAR")
    n = cfg.stamp_size
    t0 = time.time()
    Q: dict[str, list] = {"engine": [], "brute uniform": [], "brute population": []}
    U: dict[str, list] = {k: [] for k in Q}
    X, rms = [], []
    M = None
    for b in range(-(-a.ngal // spec.block_size)):
        st, psf, t = render_block(spec, 0, b, stamp_size=n, noise=not a.noise_free)
        if M is None:  # every grid model at the stamp's centre, and the point source
            M = render_models(n, psf, n // 2, n // 2, np.r_[e1, 0.0], np.r_[e2, 0.0],
                              np.r_[r, 0.0], np.ones(r.size + 1), model=a.morphology)
            M = M.reshape(r.size + 1, -1)
            S = np.sum(M * M, axis=1)
        D = st.reshape(-1, n * n).astype(float)
        f = fit_stamps(st.reshape(-1, n, n), psf, 1.0, config=cfg, size_prior=sp)
        f = dataclasses.replace(f, flags=np.asarray(f.flags) & ~star,
                                is_star=np.zeros_like(f.is_star))  # fmt: skip
        tt = (D @ M.T) / np.sqrt(S)
        uni, pop = amplitude_terms(tt, a.snr, spec.snr_slope)
        uni = uni - 0.5 * np.log(S)
        for key, amp in (("brute uniform", uni), ("brute population", pop)):
            lnl = 0.5 * tt**2 + amp
            cells = (lnl[:, :-1] + ln_w).reshape(D.shape[0], eg.shape[0], n_live)
            lnL = np.logaddexp(logsumexp(cells, axis=2), (lnl[:, -1] + np.log(w_star))[:, None])
            lnL -= lnL.max(axis=1, keepdims=True)
            if key == "brute uniform":
                d = (f.lnL - f.lnL.max(axis=1, keepdims=True)) - lnL
                near = lnL > -5
                dm = np.nanmean(np.where(near, d, np.nan), axis=1, keepdims=True)
                rms.append(np.sqrt(np.nanmean(np.where(near, (d - dm) ** 2, np.nan), axis=1)))
            fb = dataclasses.replace(f, lnL=lnL.astype(np.float32))
            q, u = reduce_renderings(fb, prior, spec.g, refine=cfg.integration_refine)
            Q[key].append(q)
            U[key].append(u)
        q, u = reduce_renderings(f, prior, spec.g, refine=cfg.integration_refine)
        Q["engine"].append(q)
        U["engine"].append(u)
        X.append(shape_controls(t["e1_int"], t["e2_int"]))
    X = np.concatenate(X)
    rms = np.concatenate(rms)
    groups = np.arange(X.shape[0]) * 40 // X.shape[0]
    print(f"{a.morphology}, {a.ngal} galaxies centred, S/N {a.snr}, size {a.size} PSF radii, "
          f"PSF {a.psf}, de {a.e_step:g}{', noise-free' if a.noise_free else ''}, "
          f"{time.time() - t0:.0f} s")
    print(f"engine - brute (uniform amplitude) ln L within 5 of the peak, rms about the mean "
          f"offset: median {np.median(rms):.3f}, 90% {np.quantile(rms, 0.9):.3f}")
    for key in Q:
        tab = bias_table(np.concatenate(Q[key]), np.concatenate(U[key]), groups, spec.g,
                         controls=X)  # fmt: skip
        row = tab[tab["estimator"] == "fixed-point"][0]
        print(f"{key:17s} m1 {row['m1']:+.4f} ± {row['m1_err']:.4f}  "
              f"m2 {row['m2']:+.4f} ± {row['m2_err']:.4f}  n {row['n_gal']}")


if __name__ == "__main__":
    main()
