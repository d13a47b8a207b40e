"""The metacalibration operation against a true shear, noise-free: images and fits.

Each galaxy of the precision mode's population (GalSim, noise-free, at its true
offset) is rendered unsheared and at ``+-(g, g)``. The true-shear difference
``D_true = (mc0(+g) - mc0(-g)) / 2`` (``mc0``: the unsheared metacalibration image, so
both sides share the reconvolution PSF) is compared with the operation's
``D_mc = ((1p - 1m) + (2p - 2m)) / 2`` at ``step = g`` on the unsheared rendering, all
sheared about the true centre:

- the images: the residual ``D_true - D_mc`` (rms over the rms of ``D_true``) by
  distance from the centre, and the response of a Gaussian-weighted quadrupole (3 px);
- the fits: lensfit's posterior mean (bulge+disc, the population's priors, fitted with
  the metacalibration images' noise level ``sqrt(2) sigma`` but no noise added),
  ``m = sum <e>-response to the true shear / sum metacalibration response - 1`` per
  component (jackknife error over the galaxies), overall, by kind and by size::

    nice -n 5 python benchmarks/studies/metacal_operation.py --ngal 100 --psf kolmogorov \
        --stamp 32 [--pad 16]

``--pad P`` puts the stamps (and the PSF) in a frame ``P`` pixels wider on each side of
zeros before the operation, and cuts them back after it.
"""

from __future__ import annotations

import argparse

import numpy as np

from pylensfit.likelihood import fit_stamps
from pylensfit.metacal import metacal_images
from pylensfit.prior import mix_bulge_fractions
from pylensfit.shear import posterior_moments
from pylensfit_validation import precision as P


def _op(st, psf, g, centres, pad, types):
    """The noise-free metacalibration images of ``types``, optionally in a zero frame."""
    if not pad:
        return metacal_images(st, psf, 0.0, step=g, centres=centres, types=types)
    n, m = st.shape[-1], st.shape[-1] + 2 * pad
    big = np.zeros(st.shape[:-2] + (m, m))
    big[..., pad:pad + n, pad:pad + n] = st
    bp = np.zeros((m, m))
    bp[pad:pad + n, pad:pad + n] = psf
    mc = metacal_images(big, bp, 0.0, step=g, types=types,
                        centres=(centres[0] + pad, centres[1] + pad))  # fmt: skip
    mc.images = {t: v[..., pad:pad + n, pad:pad + n] for t, v in mc.images.items()}
    mc.psf = mc.psf[pad:pad + n, pad:pad + n] / mc.psf[pad:pad + n, pad:pad + n].sum()
    return mc


def _taper(n, width):
    """``(n, n)``: 1 inside, falling as ``cos^2`` to 0 over the outer ``width`` pixels."""
    if not width:
        return np.ones((n, n))
    d = np.minimum(np.arange(n), np.arange(n)[::-1]) + 0.5
    w = np.where(d < width, np.sin(0.5 * np.pi * np.minimum(d / width, 1.0)) ** 2, 1.0)
    return np.outer(w, w)


def _images(spec, n_stamp, pad, taper=0):
    """``D_true``, ``D_mc``, the unsheared metacalibration image, its PSF, the truth."""
    st, psf, t = P.render_block(spec, 0, 0, stamp_size=n_stamp, noise=False)
    st0 = P.render_block(P.spec_with(spec, g=1e-12), 0, 0, stamp_size=n_stamp,
                         noise=False)[0][:, 0]  # fmt: skip
    st, st0 = st * _taper(n_stamp, taper), st0 * _taper(n_stamp, taper)
    c = (n_stamp // 2 + np.asarray(t["dx"]), n_stamp // 2 + np.asarray(t["dy"]))
    g = spec.g
    ns = [_op(st[:, k], psf, g, c, pad, ("noshear",)).images["noshear"] for k in (0, 2)]
    mc = _op(st0, psf, g, c, pad, ("noshear", "1p", "1m", "2p", "2m"))
    im = {k: v.astype(float) for k, v in mc.images.items()}
    d_mc = ((im["1p"] - im["1m"]) + (im["2p"] - im["2m"])) / 2
    return (ns[0] - ns[1]) / 2, d_mc, im, mc.psf, t, c


def _image_report(d_true, d_mc, im, c) -> None:
    n = d_true.shape[-1]
    yy, xx = np.mgrid[:n, :n]
    dx, dy = xx[None] - c[0][:, None, None], yy[None] - c[1][:, None, None]
    r = np.hypot(dx, dy)
    res = d_true - d_mc
    line = []
    for lo, hi in ((0, 2), (2, 5), (5, 10), (10, 14), (14, 99)):
        k = (r >= lo) & (r < hi)
        line.append(f"r {lo}-{hi}: {np.sqrt((res ** 2 * k).sum() / (d_true ** 2 * k).sum()):.4f}")
    print("image residual rms / true difference rms,", ", ".join(line))
    w = np.exp(-(dx ** 2 + dy ** 2) / 18.0)

    def quad(img):
        f = (img * w).sum((1, 2))
        q = (img * w * (dx ** 2 - dy ** 2 + 2 * dx * dy)).sum((1, 2))
        return q / f

    q0 = quad(im["noshear"])
    ratio = (quad(im["noshear"] + d_true) - q0).sum() / (quad(im["noshear"] + d_mc) - q0).sum()
    print(f"weighted quadrupole: sum true response / sum metacal response - 1 = {ratio - 1:+.5f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ngal", type=int, default=100)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--psf", default="kolmogorov")
    ap.add_argument("--stamp", type=int, default=32)
    ap.add_argument("--pad", type=int, default=0)
    ap.add_argument("--g", type=float, default=0.01)
    ap.add_argument("--taper", type=float, default=0.0,
                    help="the stamps' outer pixels tapered (cos^2) to 0 over this width")
    ap.add_argument("--tiers", action="store_true",
                    help="the fits on Config()'s stamp tiers (default: every fit on the stamp)")
    ap.add_argument("--morphology-weights", nargs=5, type=float,
                    default=(0.25, 0.15, 0.25, 0.2, 0.15), metavar="W")  # fmt: skip
    a = ap.parse_args()
    spec = P.spec_with(P.PrecisionSpec(ngal=a.ngal, seed=a.seed, population="realistic",
                                       morphology_weights=tuple(a.morphology_weights),
                                       block_size=a.ngal, g=a.g), psfs=[a.psf])  # fmt: skip
    d_true, d_mc, im, psf_r, t, c = _images(spec, a.stamp, a.pad, a.taper)
    _image_report(d_true, d_mc, im, c)
    cfg = P.default_config(spec).replace(model="bulge+disc", position_prior_sigma=2.0)
    cfg = cfg if a.tiers else cfg.replace(max_stamp_size=0)
    prior, sp = P.population_prior(spec), P.population_size_prior(spec, 0)

    def mean(img):
        f = fit_stamps(img.astype(np.float32), psf_r, np.sqrt(2.0) * spec.noise_sigma,
                       config=cfg, size_prior=sp)  # fmt: skip
        mom = posterior_moments(mix_bulge_fractions(f.lnL_bulge, f.lnL_star), f.egrid, prior,
                                refine=cfg.output_refine)  # fmt: skip
        return np.column_stack([mom["e1"], mom["e2"]])

    base = im["noshear"]
    d_t = mean(base + d_true) - mean(base - d_true)
    d_m = mean(base + d_mc) - mean(base - d_mc)
    print(f"{a.ngal} galaxies, {a.psf} PSF, {a.stamp}-px stamps, pad {a.pad}")
    kinds = [("all", np.ones(a.ngal, bool))] + [
        (name, np.asarray(t["morph"]) == j) for j, name in enumerate(P.MORPHOLOGIES)]
    big = np.asarray(t["r"]) > np.median(np.asarray(t["r"]))
    kinds += [("larger half", big), ("smaller half", ~big)]
    for name, k in kinds:
        if k.sum() > 1:
            t_, m_ = d_t[k], d_m[k]
            m = t_.sum(0) / m_.sum(0) - 1
            jk = (t_.sum(0) - t_) / (m_.sum(0) - m_) - 1  # leave one galaxy out
            err = np.sqrt((k.sum() - 1) / k.sum() * ((jk - jk.mean(0)) ** 2).sum(0))
            print(f"fits, {name} ({k.sum()}): m1 {m[0]:+.4f} ± {err[0]:.4f}, "
                  f"m2 {m[1]:+.4f} ± {err[1]:.4f}")


if __name__ == "__main__":
    main()
