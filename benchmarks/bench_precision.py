"""Throughput and bias of the precision mode, next to GalSim HSM REGAUSS on the same renderings.

Renders ``--ngal`` galaxies of the precision population (``pylensfit_validation.precision``: four
renderings each, +-g with shared noise and 90-degree twins, morphologies from
exponential to knotty discs, fluxes of reference S/N 10-200) for every PSF, then
measures every rendering

* with pylensfit (``fit_stamps`` + the per-rendering reduction of the precision mode,
  one process, one thread), with the prior, the flux prior's power and each PSF's flux
  range estimated from an unsheared calibration sample of ``--ncal`` galaxies (one
  pass, the size prior flat);
* with GalSim HSM REGAUSS (``galsim.hsm.EstimateShear``, one thread), on the same
  stamps and with the true PSF image, with the usual cuts (resolution >= 0.3, |e| < 2;
  a galaxy counts if all four renderings pass), shear from the distortions as
  ``g = <e> / (2 R)`` with the responsivity ``R = 1 - e_rms^2`` of each sample, the
  noise variance (from the rotated twins) subtracted from ``<e_i^2>`` as HSC does.

and prints renderings per second, peak memory, and m and c (fixed-point and exact
sensitivity for pylensfit, REGAUSS with its responsivity) with jackknife errors over
blocks of 50 galaxies, per PSF and overall. Rendering is timed separately.

Usage::

    python benchmarks/bench_precision.py                  # 400 galaxies per PSF, ~5 min
    python benchmarks/bench_precision.py --ngal 100 --psf round
"""

from __future__ import annotations

import argparse
import math
import resource
import time

import numpy as np


def maxrss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def hsm_shapes(stamps: np.ndarray, psf: np.ndarray) -> np.ndarray:
    """REGAUSS distortions ``(n, 2)``; NaN where HSM fails."""
    import galsim

    psf_im = galsim.Image(psf)
    out = np.full((len(stamps), 2), np.nan)
    for i, s in enumerate(stamps):
        r = galsim.hsm.EstimateShear(galsim.Image(s), psf_im, shear_est="REGAUSS", strict=False)
        ok = not r.error_message and r.correction_status == 0
        # the usual REGAUSS cuts (HSC: resolution >= 0.3, |e| < 2), else noise outliers
        # at S/N ~ 10 with |e| >> 1 dominate every mean
        if ok and r.resolution_factor >= 0.3 and math.hypot(r.corrected_e1, r.corrected_e2) < 2:
            out[i] = r.corrected_e1, r.corrected_e2
    return out


def hsm_m_c(e: np.ndarray, blocks: np.ndarray, g: float) -> tuple[np.ndarray, np.ndarray, ...]:
    """m, c (2 components) and jackknife errors of REGAUSS from paired renderings.

    ``e`` is ``(n, 4, 2)`` in the precision rendering order; galaxies with any failed
    rendering are dropped (paired selection, as for pylensfit).
    """
    ok = np.isfinite(e).all(axis=(1, 2))
    e, blocks = e[ok], blocks[ok]
    ub = np.unique(blocks)

    def est(sel):
        ee = e[sel]
        # responsivity 1 - e_rms^2 of the intrinsic shapes (Bernstein & Jarvis 2002), the
        # measurement noise's share of <e^2> taken out as in HSC: the rotated twins'
        # sum e_0 + e_1 is pure noise to first order, variance 2 sigma_n^2
        noise2 = np.mean((ee[:, 0] + ee[:, 1]) ** 2 + (ee[:, 2] + ee[:, 3]) ** 2, axis=0) / 4
        R = 1.0 - (np.mean(ee**2, axis=(0, 1)) - noise2)
        gp = ee[:, :2].mean(axis=(0, 1)) / (2 * R)
        gm = ee[:, 2:].mean(axis=(0, 1)) / (2 * R)
        return (gp - gm) / (2 * g) - 1, (gp + gm) / 2

    m, c = est(np.ones(len(e), bool))
    jk = [est(blocks != b) for b in ub]
    k = len(ub)
    jm = np.array([j[0] for j in jk])
    jc = np.array([j[1] for j in jk])
    m_err = np.sqrt((k - 1) / k * ((jm - jm.mean(0)) ** 2).sum(0))
    c_err = np.sqrt((k - 1) / k * ((jc - jc.mean(0)) ** 2).sum(0))
    return m, m_err, c, c_err, int(ok.sum())


def main() -> None:
    from threadpoolctl import threadpool_limits

    from pylensfit.likelihood import fit_stamps
    from pylensfit.prior import estimate_flux_range, estimate_flux_slope, estimate_prior
    from pylensfit_validation.precision import (
        bias_table,
        default_config,
        reduce_renderings,
        render_block,
        spec_with,
        usable_fits,
    )

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ngal", type=int, default=400, help="galaxies per PSF (x4 renderings)")
    p.add_argument("--ncal", type=int, default=2000, help="calibration galaxies for the prior")
    p.add_argument("--psf", nargs="+", help="PSF names (default all)")
    p.add_argument("--seed", type=int, default=1)
    a = p.parse_args()
    import numba

    numba.set_num_threads(1)
    threadpool_limits(1)
    base = spec_with(psfs=a.psf, seed=a.seed)
    npsf = len(base.psfs)
    bs = 50
    spec = spec_with(base, ngal=a.ngal * npsf, block_size=bs, ncal=a.ncal)
    cfg = default_config(spec).replace(size_prior="flat")  # the precision mode's, flat sizes
    ns = cfg.largest_stamp  # rendered as large as the largest stamp tier
    print(f"precision population: {a.ngal} galaxies x 4 renderings per PSF, {npsf} PSFs, "
          f"model {cfg.model}, {ns}-pixel renderings (stamp tiers up to {ns}), one process, "
          "one thread")  # fmt: skip
    # calibration sample and prior (not timed against the peer)
    lnl, flux, flux_err, on, egrid = [], [], [], [], None
    for b in range(-(-spec.ncal // bs)):
        st, psf, _ = render_block(spec, b % npsf, b, stamp_size=ns, calibration=True)
        f = fit_stamps(st[:, 0], psf, spec.noise_sigma, config=cfg)
        ok = usable_fits(f)
        lnl.append(f.lnL[ok])
        flux.append(f.flux[ok])
        flux_err.append((f.flux / f.snr)[ok])
        on.append(np.full(ok.sum(), b % npsf))
        egrid = f.egrid
    prior = estimate_prior(np.concatenate(lnl), egrid, form=cfg.prior_form)
    flux, flux_err, on = map(np.concatenate, (flux, flux_err, on))
    beta, beta_err = estimate_flux_slope(flux)
    cfg = cfg.replace(amplitude_prior_power=beta)  # the counts' slope, as precision() does
    # and each PSF's flux range, as precision() does by default (flux_bounds=True)
    ranges = [estimate_flux_range(flux[on == k], flux_err[on == k], beta=beta)
              for k in range(npsf)]  # fmt: skip
    cfgs = [cfg.replace(amplitude_prior_min=r["lo"], amplitude_prior_max=r["hi"])
            for r in ranges]  # fmt: skip
    print(f"prior from {spec.ncal} unsheared galaxies: {prior!r}, flux slope {beta:.3f} ± "
          f"{beta_err:.3f}, flux ranges "
          + ", ".join(f"{r['lo']:.4g}-{r['hi']:.4g}" for r in ranges)
          + f"; peak memory so far {maxrss_mib():.0f} MiB")  # fmt: skip
    t_render = t_fit = t_hsm = 0.0
    rows = []
    for ip, pdef in enumerate(spec.psfs):
        Qs, Us, Bs, Hs = [], [], [], []
        for b in range(ip, -(-spec.ngal // bs), npsf):
            t0 = time.perf_counter()
            st, psf, truth = render_block(spec, ip, b, stamp_size=ns)
            t1 = time.perf_counter()
            n = len(st)
            flat = st.reshape(n * 4, *st.shape[2:])
            f = fit_stamps(flat, psf, spec.noise_sigma, config=cfgs[ip])
            Q, ok = reduce_renderings(f, prior, spec.g, refine=cfg.integration_refine)
            t2 = time.perf_counter()
            H = hsm_shapes(flat, psf)
            t3 = time.perf_counter()
            t_render += t1 - t0
            t_fit += t2 - t1
            t_hsm += t3 - t2
            Qs.append(Q)
            Us.append(ok)
            Bs.append(np.full(n, b))
            Hs.append(H.reshape(n, 4, 2))
        Q, U, B, H = map(np.concatenate, (Qs, Us, Bs, Hs))
        t = bias_table(Q, U, B, spec.g)
        for r in t[t["estimator"] != "paper"]:
            rows.append((pdef["name"], f"pylensfit {r['estimator']}", r["m1"], r["m1_err"],
                         r["m2"], r["m2_err"], r["c1"], r["c1_err"], r["c2"], r["c2_err"],
                         r["n_gal"]))  # fmt: skip
        m, me, c, ce, nh = hsm_m_c(H, B, spec.g)
        rows.append((pdef["name"], "HSM REGAUSS", m[0], me[0], m[1], me[1], c[0], ce[0], c[1],
                     ce[1], nh))  # fmt: skip
    nr = 4 * spec.ngal
    print(f"\nrendering (GalSim, not compared): {nr / t_render:.0f} renderings/s")
    print("| method | renderings/s | galaxies/s (x4 renderings) | peak memory |")
    print("|---|---|---|---|")
    print(f"| pylensfit fit + reduction | {nr / t_fit:.0f} | {spec.ngal / t_fit:.0f} | "
          f"{maxrss_mib():.0f} MiB (process) |")  # fmt: skip
    print(f"| GalSim HSM REGAUSS | {nr / t_hsm:.0f} | {spec.ngal / t_hsm:.0f} | same process |")
    print("\n| PSF | method | m1 | m2 | c1 | c2 | galaxies |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]:+.4f} ± {r[3]:.4f} | {r[4]:+.4f} ± {r[5]:.4f} | "
              f"{r[6]:+.5f} ± {r[7]:.5f} | {r[8]:+.5f} ± {r[9]:.5f} | {r[10]} |")  # fmt: skip


if __name__ == "__main__":
    main()
