"""Multiplicative and additive shear bias of the Bayesian shear layer on synthetic data.

The data satisfy the paper's assumptions exactly: intrinsic ellipticities ``e_s`` drawn
from a prior of the functional form of eq. ``funcprior`` (B, C, D = 0.19, 0.58, 2.4); a
reduced shear ``+g`` or ``-g`` applied with ``e = (e_s + g)/(1 + g* e_s)``; an observed
``e_obs = e + noise`` with Gaussian noise of width ``s`` per galaxy (the *same* noise at
``+g`` and ``-g``); and the Gaussian likelihood ``ln L(e) = -|e - e_obs|^2 / (2 s^2)`` on
the ellipticity grid. The prior is estimated (direct maximisation of the marginal
likelihood) from an independent unsheared sample, as in the paper, or taken as the true
one with ``--true-prior``.

Two designs cancel most of the shape noise:

- ``twins`` (default, as in STEP2): 90-degree twins ``e_s`` and ``-e_s``, each with its
  own noise. ``m`` is known to ~4e-4 with 200,000 galaxies; ``c`` keeps the noise of the
  zero-shear mean (~3e-4 at 200,000).
- ``ring4``: each ``e_s`` also rotated by 45 and 135 degrees (``i e_s``, ``-e_s``,
  ``-i e_s`` in the e plane) with its noise rotated alike. ``c`` is then zero by symmetry
  (a check, not a measurement) and the paper formula's ``m`` is much less noisy.

For each component, ``m = (g_hat(+g) - g_hat(-g)) / (2 g) - 1`` and
``c = (g_hat(+g) + g_hat(-g)) / 2``, for three sensitivities: the exact first-order
response (the default of :func:`pylensfit.shear.shapes`), the paper's eq. ``partial``,
and none (``sens = 1``). Errors are delete-one jackknife errors over blocks of 20,000.

Usage::

    python benchmarks/bench_shear_bias.py --ngal 200000 --seed 1
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from pylensfit.grid import ellipticity_grid, refined_grid
from pylensfit.prior import Prior, estimate_prior
from pylensfit.shear import (
    apply_shear,
    kernel_columns,
    sensitivity_from_sums,
    sums_with,
)

TRUE_PARAMS = {"B": 0.19, "C": 0.58, "D": 2.4}
METHODS = ("exact", "paper", "none")
CHUNK = 20_000


def gaussian_lnL(e_obs: np.ndarray, s: np.ndarray, egrid: np.ndarray) -> np.ndarray:
    """``ln L_a(e) = -|e - e_obs_a|^2 / (2 s_a^2)`` on the grid, shifted to max 0."""
    d1 = egrid[None, :, 0] - e_obs[:, 0:1]
    d2 = egrid[None, :, 1] - e_obs[:, 1:2]
    lnL = -(d1**2 + d2**2) / (2.0 * s[:, None] ** 2)
    return lnL - lnL.max(axis=1, keepdims=True)


def make_population(ngal, smin, smax, design, rng):
    """Intrinsic shapes, noise and widths, with twins (or rings) adjacent."""
    truth = Prior(**TRUE_PARAMS)
    k = 2 if design == "twins" else 4
    base = truth.sample(ngal // k, rng=rng)
    es = base[:, 0] + 1j * base[:, 1]
    rot = np.exp(2j * np.pi * np.arange(k) / k)  # e -> -e: 90 deg; e -> i e: 45 deg
    es = (es[:, None] * rot[None, :]).ravel()
    if design == "twins":
        s = rng.uniform(smin, smax, es.size)
        noise = s * (rng.standard_normal(es.size) + 1j * rng.standard_normal(es.size))
    else:
        s0 = rng.uniform(smin, smax, base.shape[0])
        n0 = s0 * (rng.standard_normal(s0.size) + 1j * rng.standard_normal(s0.size))
        s = np.repeat(s0, k)
        noise = (n0[:, None] * rot[None, :]).ravel()
    return es, noise, s


def block_sums(es, noise, s, g1, g2, egrid, prior, refine):
    """Per block of CHUNK galaxies: sums of <e_i> and of each sensitivity, shape (nb, 4, 2)."""
    nb = -(-es.size // CHUNK)
    out = np.zeros((nb, 4, 2))
    for b in range(nb):
        sl = slice(b * CHUNK, (b + 1) * CHUNK)
        e1, e2 = apply_shear(es[sl].real, es[sl].imag, g1, g2)
        e_obs = np.column_stack([e1 + noise[sl].real, e2 + noise[sl].imag])
        lnL = gaussian_lnL(e_obs, s[sl], egrid)
        S = sums_with(lnL, egrid, kernel_columns(prior, refined_grid(egrid, refine)), refine, None)
        out[b, 0] = (S[:, 1:3] / S[:, :1]).sum(axis=0)
        for i, meth in enumerate(("exact", "paper")):
            s1, s2 = sensitivity_from_sums(S, meth)
            out[b, 1 + i] = [s1.sum(), s2.sum()]
        out[b, 3] = S.shape[0]
    return out


def m_and_c(plus, minus, g, comp, j):
    """m, c of component ``comp`` for sensitivity ``j`` from the block sums."""
    gp = plus[..., 0, comp] / plus[..., j, comp]
    gm = minus[..., 0, comp] / minus[..., j, comp]
    return (gp - gm) / (2 * g) - 1.0, 0.5 * (gp + gm)


def jackknife(plus, minus, g, comp, j):
    """Estimate and delete-one-block jackknife error of (m, c)."""
    P, M = plus.sum(axis=0), minus.sum(axis=0)
    m, c = m_and_c(P, M, g, comp, j)
    nb = plus.shape[0]
    if nb < 2:
        return m, c, np.nan, np.nan
    mj, cj = m_and_c(P[None] - plus, M[None] - minus, g, comp, j)
    f = (nb - 1) / nb
    return (
        m,
        c,
        np.sqrt(f * np.sum((mj - mj.mean()) ** 2)),
        np.sqrt(f * np.sum((cj - cj.mean()) ** 2)),
    )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ngal", type=int, default=200_000, help="galaxies per shear value")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--prior-ngal", type=int, default=30_000, help="unsheared prior sample")
    ap.add_argument("--true-prior", action="store_true", help="use the true prior")
    ap.add_argument("--g", type=float, nargs="+", default=[0.02], help="|g| of the +-g pairs")
    ap.add_argument("--step", type=float, default=0.1, help="likelihood grid step")
    ap.add_argument("--refine", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--widths", nargs="+", default=["0.05-0.1", "0.1-0.3", "0.05-0.3"])
    ap.add_argument("--design", choices=["twins", "ring4"], default="twins")
    args = ap.parse_args(argv)

    egrid = ellipticity_grid(args.step)
    truth = Prior(**TRUE_PARAMS, egrid=egrid)
    src = "true" if args.true_prior else f"estimated from {args.prior_ngal} unsheared"
    print(
        f"ngal={args.ngal}, design={args.design}, same noise at +-g, grid step {args.step}, "
        f"seed {args.seed}, prior {src}"
    )
    head = f"{'widths':>9} {'g':>5} {'refine':>6} {'sens':>6}"
    print(f"{head} {'m1':>16} {'m2':>16} {'c1':>18} {'c2':>18}")
    for wi, w in enumerate(args.widths):
        smin, smax = (float(v) for v in w.split("-"))
        if args.true_prior:
            prior = truth
        else:
            prng = np.random.default_rng([args.seed, wi, 1])
            e = truth.sample(args.prior_ngal, rng=prng)
            sp = prng.uniform(smin, smax, args.prior_ngal)
            lnL = gaussian_lnL(e + sp[:, None] * prng.standard_normal(e.shape), sp, egrid)
            prior = estimate_prior(lnL, egrid)
            print(f"# {w}: {prior!r}, at bound: {prior.info['at_bound']}")
        es, noise, s = make_population(
            args.ngal, smin, smax, args.design, np.random.default_rng([args.seed, wi, 2])
        )
        for g in args.g:
            for refine in args.refine:
                t0 = time.perf_counter()
                sums = {}
                for comp in (0, 1):
                    for sign in (+1, -1):
                        gg = [0.0, 0.0]
                        gg[comp] = sign * g
                        sums[comp, sign] = block_sums(es, noise, s, *gg, egrid, prior, refine)
                dt = time.perf_counter() - t0
                for j, meth in enumerate(METHODS, start=1):
                    cols = []
                    for comp in (0, 1):
                        m, c, dm, dc = jackknife(sums[comp, 1], sums[comp, -1], g, comp, j)
                        cols.append((m, dm, c, dc))
                    (m1, dm1, c1, dc1), (m2, dm2, c2, dc2) = cols
                    print(
                        f"{w:>9} {g:5.3f} {refine:>6d} {meth:>6} "
                        f"{m1:+8.4f}+-{dm1:.4f} {m2:+8.4f}+-{dm2:.4f} "
                        f"{c1:+9.5f}+-{dc1:.5f} {c2:+9.5f}+-{dc2:.5f}"
                        + (f"  ({dt:.0f} s)" if meth == "exact" else ""),
                        flush=True,
                    )


if __name__ == "__main__":
    main()
