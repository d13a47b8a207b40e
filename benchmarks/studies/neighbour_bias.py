"""Paired +-g bias from the light of lattice neighbours, and what subtracting them leaves.

STEP1-like scenes: a bulge+disc galaxy (bulge fraction 0.5, bulge half-light radius 0.6
disc scale lengths, scale length uniform in --rd, S/N log-uniform 15-150) at the centre
of a square lattice of pitch --spacing with its 8 neighbours (positions jittered by
+-6 px, their own sizes, fluxes and shapes), all sheared by +-(g, g) and rendered with
GalSim through the round Moffat PSF, each with a 90-degree twin in which every galaxy
is rotated (as `pylensfit simulate step1 --twins` makes them). The central galaxy is
fitted with its exact model on a stamp about it; m and c come from the four renderings
(`precision.bias_table`, with the intrinsic shapes' spin-4 parts as control variates,
rows `cv`). Modes:

* ``alone``: the central galaxy without neighbours;
* ``neighbours``: with them;
* ``subtracted``: with them, every object of the scene fitted, and the central galaxy
  fitted again with the others' best-fit models subtracted, as `pylensfit.measure` does
  (`Config.subtract_neighbours`).

::

    python benchmarks/studies/neighbour_bias.py --mode alone neighbours subtracted --ngal 2000
    python benchmarks/studies/neighbour_bias.py --mode neighbours --noise-free --rd 2.5 3.5
    python benchmarks/studies/neighbour_bias.py --mode alone --size-prior true --g 0.1 --ngal 10000

``--size-prior true`` fits with the population's own size prior (the disc scale length
uniform in ``--rd``) instead of the flat one: with the ellipticity prior and the bulge
fraction also the population's, every prior is then exact.
"""

from __future__ import annotations

import argparse
import math
import time

import galsim
import numpy as np
from precision_ab import _kv

import pylensfit.pipeline as pl
from pylensfit.config import Config
from pylensfit.likelihood import fit_stamps
from pylensfit.prior import Prior, SizePrior
from pylensfit.stamps import cut_stamps
from pylensfit_validation.precision import (
    PRECISION_PSFS,
    bias_table,
    draw_image,
    galsim_psf,
    psf_image,
    reduce_renderings,
    shape_controls,
)
from pylensfit_validation.simulate import draw_shapes, galaxy_profile

#: Half-light radius over disc scale length of the galaxy drawn here (bulge fraction 0.5,
#: bulge half-light radius 0.6 scale lengths), measured on its GalSim profile.
HLR_PER_RD = 1.1293544742710435
#: The galaxies' S/N, log-uniform (STEP1's, `simulate.FieldSpec.snr_range`).
SNR_RANGE = (15.0, 150.0)

_LATTICE = np.array([(0, 0)] + [(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1) if i or j])


def scene(rng, a, psf, prior, with_neighbours: bool, canvas: int):
    """Four renderings (+g, +g twin, -g, -g twin) of one scene on ``canvas`` px, the
    central galaxy at the canvas centre + a sub-pixel offset; positions, intrinsic e."""
    nobj = 9  # drawn in every mode, so that the modes share the central galaxies
    rd = rng.uniform(*a.rd, nobj)
    snr = np.exp(rng.uniform(*np.log(SNR_RANGE), nobj))
    e = draw_shapes(prior, nobj, rng, 0.99)
    jit = rng.uniform(-6.0, 6.0, (nobj, 2))
    jit[0] = rng.uniform(-0.5, 0.5, 2)
    pos = _LATTICE[:nobj] * a.spacing + jit
    shown = nobj if with_neighbours else 1
    flux = np.empty(nobj)
    for k in range(shown):
        if a.flux_range is not None:  # log-uniform in flux, the same draws as the S/N's
            t = np.log(snr[k] / SNR_RANGE[0]) / np.log(SNR_RANGE[1] / SNR_RANGE[0])
            flux[k] = a.flux_range[0] * (a.flux_range[1] / a.flux_range[0]) ** t
            continue
        ref = draw_image(galsim.Convolve(galaxy_profile("bulge+disc", rd[k]), psf), 64)
        flux[k] = snr[k] / math.sqrt(float(np.sum(ref.astype(float) ** 2)))
    out = np.zeros((4, canvas, canvas))
    for i, (g, rot) in enumerate([(a.g, False), (a.g, True), (-a.g, False), (-a.g, True)]):
        for k in range(shown):
            gal = galaxy_profile("bulge+disc", rd[k]).shear(g1=e[k, 0], g2=e[k, 1])
            if rot:
                gal = gal.rotate(90 * galsim.degrees)
            out[i] += flux[k] * draw_image(galsim.Convolve(gal.shear(g1=g, g2=g), psf), canvas,
                                      tuple(pos[k]))  # fmt: skip
    c = canvas // 2
    return out, pos[:shown] + c, e[0]


def subtracted_centrals(scenes, canvas: int, N: int, psf_img, cfg):
    """The central galaxies' stamps after neighbour subtraction, as `measure` does it: the
    scenes' renderings side by side in one image, every object fitted, then
    `pipeline.subtract_neighbours`. Returns ``(n_scenes, 4, N, N)``."""
    n_tile = 4 * len(scenes)
    per_row = math.ceil(math.sqrt(n_tile))
    rows = -(-n_tile // per_row)
    mosaic = np.zeros((rows * canvas, per_row * canvas))
    xs, ys, central = [], [], []
    start = 0
    for j in range(n_tile):
        img, pos = scenes[j // 4]
        r0, c0 = divmod(j, per_row)
        mosaic[r0 * canvas:(r0 + 1) * canvas, c0 * canvas:(c0 + 1) * canvas] = img[j % 4]
        central.append(start)
        start += len(pos)
        xs.append(pos[:, 0] + c0 * canvas)
        ys.append(pos[:, 1] + r0 * canvas)
    x, y = np.concatenate(xs), np.concatenate(ys)
    stk, cx, cy, _ = cut_stamps(mosaic, x, y, N)
    first = fit_stamps(stk, psf_img, 1.0, config=cfg, centres=(cx, cy))
    xf, yf = first.x + (x - cx), first.y + (y - cy)
    cleaned = stk.copy()

    def refit(idx, others):
        cleaned[idx] = stk[idx] - others
        return fit_stamps(cleaned[idx], psf_img, 1.0, config=cfg, centres=(cx[idx], cy[idx]))

    def store(f, idx):
        xf[idx] = f.x + (x[idx] - cx[idx])
        yf[idx] = f.y + (y[idx] - cy[idx])

    pl.subtract_neighbours(pl.NeighbourScene(mosaic.shape, x, y, xf, yf, np.ones(x.size),
                                             np.arange(x.size), psf_img),
                           first, cfg, refit, store)  # fmt: skip
    return cleaned[np.asarray(central)].reshape(len(scenes), 4, N, N)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mode", nargs="+", default=["alone", "neighbours", "subtracted"],
                    choices=["alone", "neighbours", "subtracted"])  # fmt: skip
    ap.add_argument("--ngal", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--rd", type=float, nargs=2, default=(1.2, 3.5),
                    help="disc scale length range (px)")
    ap.add_argument("--spacing", type=float, default=40.0)
    ap.add_argument("--g", type=float, default=0.02)
    ap.add_argument("--iterations", type=int, default=1,
                    help="rounds of neighbour subtraction (Config.neighbour_iterations)")
    ap.add_argument("--noise-free", action="store_true",
                    help="no noise (the fits still assume sigma = 1)")
    ap.add_argument("--size-prior", choices=["flat", "true"], default="flat",
                    help="the fit's size prior: flat, or the population's own")
    ap.add_argument("--flux-range", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="draw the fluxes log-uniform in [LO, HI] instead of the S/N in "
                         "SNR_RANGE: with --config amplitude_prior=flux amplitude_prior_power=1 "
                         "amplitude_prior_min=LO amplitude_prior_max=HI the flux prior is exact")
    ap.add_argument("--config", nargs="*", default=[], metavar="KEY=VALUE",
                    help="Config overrides, e.g. amplitude_prior=snr amplitude_prior_power=1 "
                         "(the population's own S/N distribution, log-uniform)")
    a = ap.parse_args()
    over = _kv(a.config)
    N = 32
    canvas = int(2 * a.spacing + 2 * N + 16)
    prior = Prior(B=0.19, C=0.58, D=2.4)
    p = PRECISION_PSFS[0]
    psf = galsim_psf(p)
    psf_img, _ = psf_image(p, N)
    cfg = Config(model="bulge+disc", n_bulge_fractions=1, bulge_fraction=0.5,
                 bulge_size_ratio=0.6, stamp_size=N,
                 neighbour_iterations=a.iterations, **over)  # fmt: skip
    size_prior = None
    if a.size_prior == "true":  # r uniform: p(ln h) proportional to h on the box
        ln_h = np.arange(np.log(HLR_PER_RD * a.rd[0]) - 0.05,
                         np.log(HLR_PER_RD * a.rd[1]) + 0.06, 0.005)  # fmt: skip
        h = np.exp(ln_h)
        dens = np.where((h >= HLR_PER_RD * a.rd[0]) & (h <= HLR_PER_RD * a.rd[1]), h, 0.0)
        size_prior = SizePrior(ln_h=ln_h, density=dens * (1 - 1e-6) / np.trapezoid(dens, ln_h),
                               star=1e-6)  # fmt: skip
    for mode in a.mode:
        rng = np.random.default_rng(a.seed)  # the same scenes and noise in every mode
        t0 = time.time()
        Q, U, X = [], [], []
        block = 100
        for _ in range(-(-a.ngal // block)):
            st = np.zeros((block, 4, N, N))
            es = np.zeros((block, 2))
            scenes = []
            for i in range(block):
                img, pos, es[i] = scene(rng, a, psf, prior, mode != "alone", canvas)
                if not a.noise_free:
                    na, nb = rng.normal(size=(2, canvas, canvas))
                    img += np.stack([na, nb, na, nb])
                scenes.append((img, pos))
                for k in range(4):
                    st[i, k] = cut_stamps(img[k], pos[:1, 0], pos[:1, 1], N)[0][0]
            if mode == "subtracted":
                st[:] = subtracted_centrals(scenes, canvas, N, psf_img, cfg)
            f = fit_stamps(st.reshape(4 * block, N, N), psf_img, 1.0, config=cfg,
                           size_prior=size_prior)  # fmt: skip
            q, u = reduce_renderings(f, prior, a.g, refine=cfg.integration_refine)
            Q.append(q)
            U.append(u)
            X.append(shape_controls(es[:, 0], es[:, 1]))
        Q, U, X = map(np.concatenate, (Q, U, X))
        groups = np.arange(len(Q)) * 40 // len(Q)
        for tag, x in (("", None), (" cv", X)):
            r = bias_table(Q, U, groups, a.g, controls=x)
            r = r[r["estimator"] == "fixed-point"][0]
            print(f"{mode + tag:14s} m1 {r['m1']:+.4f} ± {r['m1_err']:.4f}  "
                  f"m2 {r['m2']:+.4f} ± {r['m2_err']:.4f}  c1 {r['c1']:+.5f}  "
                  f"c2 {r['c2']:+.5f}  n {r['n_gal']}  ({time.time() - t0:.0f} s)",
                  flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
