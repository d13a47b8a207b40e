"""The error that fitting each galaxy with its cell's PSF leaves, against its own PSF.

``measure`` with a PSF that varies over the field (``Config.psf_model = "polynomial"``,
or a Piff model) cuts every image into ``psf_cells x psf_cells`` cells and fits each
galaxy with the PSF at its cell's centre, so that the models are convolved with one PSF
per cell, not one per galaxy. This script measures what that approximation costs in
accuracy, against fitting every galaxy with the PSF at its own position, on the same
stamps (the same noise), with the PSF known exactly (the field's true PSF map, so that
the PSF model's own error is not in the comparison):

* galaxies at uniform random positions ``(u, v)`` in ``[-1, 1]^2`` over the field, under
  the survey PSF map of ``pylensfit simulate --psf-variation survey`` (a Moffat PSF of
  FWHM 3 px, beta 3.5, whose ellipticity is ``0.04 (u + i v)^2``, 0 at the centre to
  0.08 in the corners, and whose FWHM changes by +-10 % across the field);
* a mix of exponential discs and bulge+disc galaxies (half the light in a de Vaucouleurs
  bulge of half the disc's half-light radius), half-light radii lognormal about 0.8 of
  the PSF's FWHM, |e| Rayleigh with 0.25 per component, S/N 15-100;
* each galaxy rendered by GalSim four times, at ``+(g, g)`` and ``-(g, g)`` with
  ``g = 0.02``, each as drawn and turned by 90 degrees, the +g and -g renderings sharing
  their noise;
* every stamp measured by ``pylensfit.measure_stamps`` under one set of priors
  (calibrated once on the stamps with the field's central PSF), with its own PSF and,
  for each number of cells, as ``Config.psf_interpolation`` fits it: with the PSF at
  the centre of its cell ("centre"), with its cell's four corners' fits blended with its
  position's bilinear weights ("bilinear") and in one fit with the corners' PSFs mixed
  by the same weights (``pylensfit.likelihood.MixedPSF``, "fourier").

It prints, per number of cells: the rms and mean of ``e_cell - e_own`` over the stamps,
its slope against the PSF's ellipticity error ``e_psf(cell centre) - e_psf(own)`` (the
galaxies' leakage of the approximation's PSF error), the difference of ``m`` and of the
PSF leakage ``alpha`` (the slope of the twins' mean ``e`` against the true PSF
ellipticity) from those of the fits with each galaxy's own PSF, and the time per
stamp, beside the fit with each galaxy's own PSF (the peer)::

    python benchmarks/psf_cells.py --ngal 1500 --cells 2 4 8 16     # about 10 min on 2 cores
"""

from __future__ import annotations

import argparse
import resource
import time
import warnings

import galsim
import numpy as np

import pylensfit as plf
from pylensfit_validation.simulate import PSF_VARIATIONS, PSFMap

STAMP = 32
G = 0.02


def _psf_image(pmap: PSFMap, u: float, v: float) -> np.ndarray:
    """The PSF at ``(u, v)`` with the pixel response, unit sum, centred on ``[N//2, N//2]``."""
    img = pmap.profile(u, v).drawImage(nx=STAMP, ny=STAMP, scale=1.0,
                                       offset=(0.5, 0.5)).array  # fmt: skip
    return img / img.sum()


def _population(n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Positions, kinds, sizes, shapes, S/N and offsets of ``n`` galaxies."""
    e = np.hypot(*rng.normal(0.0, 0.25, (2, n)))
    while np.any(bad := e > 0.8):
        e[bad] = np.hypot(*rng.normal(0.0, 0.25, (2, int(bad.sum()))))
    phi = rng.uniform(0, np.pi, n)
    u = rng.random(n)
    return {
        "u": rng.uniform(-1, 1, n), "v": rng.uniform(-1, 1, n),
        "bulge": rng.random(n) < 0.5,
        "hlr": np.clip(0.8 * 3.0 * np.exp(rng.normal(0, 0.3, n)), 0.8, 4.0),
        "e1": e * np.cos(2 * phi), "e2": e * np.sin(2 * phi),
        "snr": 15.0 * (100.0 / 15.0) ** u,
        "dx": rng.uniform(-0.5, 0.5, n), "dy": rng.uniform(-0.5, 0.5, n),
    }  # fmt: skip


def _galaxy(p: dict, i: int):
    disc = galsim.Exponential(half_light_radius=float(p["hlr"][i]))
    if not p["bulge"][i]:
        return disc
    bulge = galsim.DeVaucouleurs(half_light_radius=0.5 * float(p["hlr"][i]),
                                 trunc=4.0 * float(p["hlr"][i]))  # fmt: skip
    return galsim.Add(0.5 * disc, 0.5 * bulge)


def _render(p: dict, pmap: PSFMap, rng: np.random.Generator):
    """``(4 n, N, N)`` stamps (renderings ``+g, +g rotated, -g, -g rotated``), the true
    PSF ellipticities at the galaxies and the shears of the renderings."""
    n = p["u"].size
    stamps = np.empty((4 * n, STAMP, STAMP), dtype=np.float32)
    gs = np.tile(np.array([G, G, -G, -G]), n)
    for i in range(n):
        psf = pmap.profile(float(p["u"][i]), float(p["v"][i]))
        gal = _galaxy(p, i)
        ref = galsim.Convolve(gal.shear(g1=float(p["e1"][i]), g2=float(p["e2"][i])), psf)
        ref = ref.drawImage(nx=STAMP, ny=STAMP, scale=1.0).array
        flux = float(p["snr"][i]) / np.sqrt(np.sum(ref**2))
        noise = [rng.normal(0.0, 1.0, (STAMP, STAMP)) for _ in range(2)]
        for k in range(4):
            ang = 90.0 if k % 2 else 0.0
            g = G if k < 2 else -G
            obj = (gal.withFlux(flux).shear(g1=float(p["e1"][i]), g2=float(p["e2"][i]))
                   .rotate(ang * galsim.degrees).shear(g1=g, g2=g))  # fmt: skip
            img = galsim.Convolve(obj, psf).drawImage(
                nx=STAMP, ny=STAMP, scale=1.0,
                offset=(0.5 + float(p["dx"][i]), 0.5 + float(p["dy"][i]))).array  # fmt: skip
            stamps[4 * i + k] = img + noise[k % 2]
    _, pe1, pe2 = pmap.at(p["u"], p["v"])
    return stamps, np.repeat(pe1, 4), np.repeat(pe2, 4), gs


class _Fitter:
    """Every stamp's posterior mean and sensitivity under fixed priors, as
    ``pylensfit.measure_stamps`` makes them, from the fits with one PSF (or one per
    stamp, ``pylensfit.likelihood.MixedPSF``) or from the fits with several PSFs blended
    (``pylensfit.likelihood.blend_fits``)."""

    def __init__(self, stamps, priors, cfg):
        self.stamps, self.priors, self.cfg = stamps, priors, cfg
        self.run_cfg = priors.apply(cfg)
        self.seconds = 0.0

    def fits(self, idx, psf):
        from pylensfit.likelihood import fit_stamps

        t0 = time.perf_counter()
        c = np.full(idx.size, STAMP // 2, dtype=float)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            f = fit_stamps(self.stamps[idx], psf, 1.0, config=self.run_cfg, centres=(c, c),
                           size_prior=self.priors.size)  # fmt: skip
        self.seconds += time.perf_counter() - t0
        return f

    def shapes(self, f, idx, e, s):
        from pylensfit.shear import shapes

        t0 = time.perf_counter()
        sh = shapes(self.priors.mix(f), f.egrid, self.priors.ellipticity,
                    sensitivity=self.cfg.sensitivity, refine=self.run_cfg.output_refine)
        ok = (np.asarray(f.flags) == 0) & (np.asarray(sh["flags"]) == 0) & ~f.is_star
        for c in range(2):
            e[c, idx] = np.where(ok, sh[f"e{c + 1}"], np.nan)
            s[c, idx] = np.where(ok, sh[f"sens{c + 1}"], np.nan)
        self.seconds += time.perf_counter() - t0


def _measure(fitter, psfs, groups, corners=None, mixed=False):
    """``e`` (2, n), ``sens`` (2, n) of every stamp and the seconds: each group with its
    PSF, or (``corners``: per group the four corner PSFs and the stamps' ``(4, n_g)``
    bilinear weights) with the corners' fits blended, or (``mixed``) in one fit with the
    corners' PSFs mixed by the weights."""
    from pylensfit.likelihood import MixedPSF, blend_fits

    n = fitter.stamps.shape[0]
    e, s = np.full((2, n), np.nan), np.full((2, n), np.nan)
    fitter.seconds = 0.0
    for g, idx in enumerate(groups):
        if corners is None:
            f = fitter.fits(idx, psfs[g])
        else:
            cps, w = corners[g]
            if mixed:
                f = fitter.fits(idx, MixedPSF(np.array(cps), w))
            else:
                f = blend_fits([fitter.fits(idx, cp) for cp in cps], w)
        fitter.shapes(f, idx, e, s)
    return e, s, fitter.seconds


def _m_alpha(e, s, gs, pe):
    """``m`` per component from the +-g pairs, and the leakage ``alpha`` per component
    (slope of the four renderings' mean ``e / s`` against the PSF ellipticity)."""
    n = e.shape[1] // 4
    ok = np.all(np.isfinite(e.reshape(2, n, 4)), axis=(0, 2))
    er, sr = e.reshape(2, n, 4)[:, ok], s.reshape(2, n, 4)[:, ok]
    plus = er[:, :, :2].sum(-1) - er[:, :, 2:].sum(-1)
    m = plus.sum(1) / (G * sr.sum(-1).sum(1)) - 1.0  # (sum_+ e - sum_- e) / (g sum s)
    mean_e = er.sum(-1) / sr.sum(-1)  # per galaxy: the shear's and the shape's cancel
    alpha = []
    for c in range(2):
        x = pe[c].reshape(n, 4)[ok, 0]
        alpha.append(np.polyfit(x, mean_e[c], 1)[0])
    return m, np.array(alpha), ok


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ngal", type=int, default=1500, help="galaxies (x4 renderings)")
    ap.add_argument("--cells", type=int, nargs="+", default=[2, 4, 8, 16],
                    help="numbers of cells per side to try")
    ap.add_argument("--seed", type=int, default=7)
    a = ap.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    fw, eq = PSF_VARIATIONS["survey"]
    pmap = PSFMap(fwhm=3.0, beta=3.5, fwhm_gradient=fw, e_quadratic=eq)
    p = _population(a.ngal, rng)
    t0 = time.perf_counter()
    stamps, pe1, pe2, gs = _render(p, pmap, rng)
    pe = np.array([pe1, pe2])
    print(f"{a.ngal} galaxies x 4 renderings in {time.perf_counter() - t0:.0f} s; PSF |e| "
          f"{np.hypot(pe1, pe2).min():.3f}-{np.hypot(pe1, pe2).max():.3f}")  # fmt: skip
    cfg = plf.Config(max_stamp_size=0)  # one 32-pixel stamp per galaxy: no larger tier
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        priors = plf.calibrate(stamps[::2], _psf_image(pmap, 0.0, 0.0), 1.0, config=cfg)
    fitter = _Fitter(stamps, priors, cfg)
    # the peer: every galaxy with the PSF at its own position
    own_psfs = [_psf_image(pmap, float(p["u"][i]), float(p["v"][i])) for i in range(a.ngal)]
    own_groups = [np.arange(4 * i, 4 * i + 4) for i in range(a.ngal)]
    e0, s0, t_own = _measure(fitter, own_psfs, own_groups)
    m0, a0, ok0 = _m_alpha(e0, s0, gs, pe)
    print(f"{'PSF':>16s} {'rms de':>9s} {'mean de1':>9s} {'mean de2':>9s} {'slope':>7s} "
          f"{'dm1':>8s} {'dm2':>8s} {'dalpha1':>8s} {'dalpha2':>8s} {'stamps/s':>9s}")
    print(f"{'own':>16s} {'-':>9s} {'-':>9s} {'-':>9s} {'-':>7s} {m0[0]:+8.4f} {m0[1]:+8.4f} "
          f"{a0[0]:+8.4f} {a0[1]:+8.4f} {stamps.shape[0] / t_own:9.0f}   (m, alpha)")

    def row(label, e, s, t, psf_e):
        m, al, _ = _m_alpha(e, s, gs, pe)
        de, dpe = e - e0, psf_e - pe  # the PSF's ellipticity error at each stamp
        ok = np.all(np.isfinite(de), axis=0)
        slope = np.polyfit(np.concatenate([dpe[0, ok], dpe[1, ok]]),
                           np.concatenate([de[0, ok], de[1, ok]]), 1)[0]  # fmt: skip
        print(f"{label:>16s} {np.sqrt(np.mean(de[:, ok] ** 2)):9.2e} "
              f"{de[0, ok].mean():+9.1e} {de[1, ok].mean():+9.1e} {slope:+7.3f} "
              f"{m[0] - m0[0]:+8.4f} {m[1] - m0[1]:+8.4f} {al[0] - a0[0]:+8.4f} "
              f"{al[1] - a0[1]:+8.4f} {stamps.shape[0] / t:9.0f}")  # fmt: skip

    ug, vg = np.repeat(p["u"], 4), np.repeat(p["v"], 4)
    for k in a.cells:
        iu = np.minimum(((ug + 1) / 2 * k).astype(int), k - 1)
        iv = np.minimum(((vg + 1) / 2 * k).astype(int), k - 1)
        cell = iu * k + iv
        groups = [np.flatnonzero(cell == c) for c in np.unique(cell)]
        node = -1 + 2 * np.arange(k + 1) / k  # the cells' edges
        # each galaxy with the PSF at its cell's centre
        cen = [((node[c // k] + node[c // k + 1]) / 2, (node[c % k] + node[c % k + 1]) / 2)
               for c in np.unique(cell)]  # fmt: skip
        e, s, t = _measure(fitter, [_psf_image(pmap, *uv) for uv in cen], groups)
        psf_e = np.empty((2, e.shape[1]))
        for g, uv in zip(groups, cen, strict=True):
            psf_e[:, g] = np.array(pmap.at(*uv)[1:])[:, None]
        row(f"{k} x {k} centres", e, s, t, psf_e)
        # each galaxy with its cell's four corners' fits blended (bilinear weights)
        corners, psf_e = [], np.empty((2, e.shape[1]))
        for c, g in zip(np.unique(cell), groups, strict=True):
            i, j = c // k, c % k
            fu = (ug[g] - node[i]) / (2 / k)
            fv = (vg[g] - node[j]) / (2 / k)
            w = np.array([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv])
            uv = [(node[i], node[j]), (node[i + 1], node[j]), (node[i], node[j + 1]),
                  (node[i + 1], node[j + 1])]  # fmt: skip
            corners.append(([_psf_image(pmap, *q) for q in uv], w))
            ce = np.array([pmap.at(*q)[1:] for q in uv])  # (4, 2)
            psf_e[:, g] = ce.T @ w
        e, s, t = _measure(fitter, None, groups, corners=corners)
        row(f"{k} x {k} bilinear", e, s, t, psf_e)
        # each galaxy once, with its cell's corners' PSFs mixed by the same weights
        e, s, t = _measure(fitter, None, groups, corners=corners, mixed=True)
        row(f"{k} x {k} fourier", e, s, t, psf_e)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"peak RSS {rss:.0f} MiB; usable galaxies {int(ok0.sum())} of {a.ngal}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
