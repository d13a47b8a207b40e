"""The shear bias that blending and detection add in ``measure``, nothing matched to the truth.

Fields at survey density where a share of the galaxies have a neighbour 1.5-4 arcsec
away are measured from FITS images to catalogue with :func:`pylensfit.measure` (sep
detection, neighbour subtraction, the default cuts); the same galaxies, one per cell of a
lattice so that none has a neighbour, are measured the same way. The difference of the
two ``m`` is what blending and detection add to the shape measurement's own bias.

The renderings (GalSim directly; no code of ``pylensfit_validation``):

* ``--fields`` fields of ``--size`` pixels at 0.2 arcsec per pixel, noise ``sigma = 1``,
  a round Moffat PSF (beta 3.5, FWHM 0.7 arcsec) given to ``measure`` as an image;
* galaxies: exponential discs, half of them with a de Vaucouleurs bulge of half the
  disc's half-light radius carrying 10-50 % of the flux; half-light radius lognormal
  about 0.35 arcsec (0.2-1.2); ``|e|`` Rayleigh with 0.25 per component (below 0.8);
  S/N 10-100 (``dN/dS ~ S^-2``, the matched-filter S/N of the unsheared galaxy alone);
* positions uniform over the field (``--density`` galaxies per arcmin^2, 30 by default),
  and for a fraction ``--pairs`` (0.3) of them a companion of the same population at a
  separation uniform in 1.5-4 arcsec in a random direction;
* each field rendered four times: sheared by ``+(g, g)`` and by ``-(g, g)`` (``--g``,
  0.02; the positions sheared too, about the field's centre), each as drawn and with
  every galaxy turned by 90 degrees; the +g and -g renderings share their noise field;
* the isolated control: every galaxy of the field (companions included) alone in a
  cell of a lattice of 48-pixel cells, the same four renderings.

Shear, per rendering, from every usable row of the catalogue (``flags == 0``, weight >
0): ``g_i = sum e_i / sum sens_i``; then ``m_i = (g_i(+) - g_i(-)) / 2g - 1`` and ``c_i
= (g_i(+) + g_i(-)) / 2`` over the field's rotated pair, with jackknife errors over the
fields. The usable rows per sign of the shear are printed too: a selection that depends
on the shear shows as a difference between +g and -g. ``measure`` rejects a galaxy with
another significant detection inside its 32-pixel stamp (``CLOSE_PAIR``, the paper's
rule; ``Config.close_pair_faint_ratio`` keeps the brighter of a pair): ``--set``
compares such settings on the same renderings.

Usage::

    python benchmarks/blend_bias.py --fields 8 --size 1024 --jobs 2      # ~25 min
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import numpy as np

PIXEL = 0.2  # arcsec per pixel
PSF_FWHM = 0.7  # arcsec
CELL = 48  # px, the isolated control's lattice
#: (rotated, sign of the shear) of the four renderings
RENDERINGS = ((False, +1), (True, +1), (False, -1), (True, -1))


def draw_galaxies(n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """The intrinsic parameters of ``n`` galaxies (module docstring)."""
    hlr = np.clip(0.35 * np.exp(rng.normal(0.0, 0.4, n)), 0.2, 1.2)
    emag = np.minimum(rng.rayleigh(0.25, n), 0.79)
    phi = rng.uniform(0, np.pi, n)
    u = rng.uniform(0, 1, n)
    snr = 10.0 / (1.0 - u * (1.0 - 10.0 / 100.0))  # dN/dS ~ S^-2 on [10, 100]
    bulge = np.where(rng.uniform(0, 1, n) < 0.5, rng.uniform(0.1, 0.5, n), 0.0)
    return {"hlr": hlr, "e1": emag * np.cos(2 * phi), "e2": emag * np.sin(2 * phi),
            "snr": snr, "bulge": bulge}  # fmt: skip


def _profile(p: dict, i: int, rotated: bool, g: float):
    import galsim

    disc = galsim.Exponential(half_light_radius=p["hlr"][i])
    if p["bulge"][i] > 0:
        bulge = galsim.DeVaucouleurs(half_light_radius=0.5 * p["hlr"][i], trunc=4 * p["hlr"][i])
        prof = (1 - p["bulge"][i]) * disc + p["bulge"][i] * bulge
    else:
        prof = disc
    e1, e2 = p["e1"][i], p["e2"][i]
    if rotated:
        e1, e2 = -e1, -e2
    return prof.shear(g1=e1, g2=e2).shear(g1=g, g2=g)


def _psf():
    import galsim

    return galsim.Moffat(beta=3.5, fwhm=PSF_FWHM)


def _flux_for_snr(prof, snr: float) -> float:
    """The flux that gives ``prof`` (unit flux, PSF-convolved) the S/N ``snr`` at sigma 1."""
    import galsim

    img = galsim.Convolve(prof, _psf()).drawImage(scale=PIXEL, nx=64, ny=64)
    return snr / math.sqrt(float(np.sum(img.array.astype(np.float64) ** 2)))


def layout(size: int, density: float, pairs: float,
           rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Positions (px) of one field's galaxies: uniform, a share with a close companion."""
    area = (size * PIXEL / 60.0) ** 2
    n = rng.poisson(density * area / (1 + pairs))
    x = rng.uniform(20, size - 20, n)
    y = rng.uniform(20, size - 20, n)
    comp = rng.uniform(0, 1, n) < pairs
    sep = rng.uniform(1.5, 4.0, int(comp.sum())) / PIXEL
    ang = rng.uniform(0, 2 * np.pi, int(comp.sum()))
    cx = np.clip(x[comp] + sep * np.cos(ang), 5, size - 5)
    cy = np.clip(y[comp] + sep * np.sin(ang), 5, size - 5)
    return np.concatenate([x, cx]), np.concatenate([y, cy])


def render(args) -> list[np.ndarray]:
    """The four renderings of one field (blended or on the lattice), shared noise."""
    import galsim

    x, y, p, size, g, seed, isolated = args
    n = len(x)
    if isolated:  # one galaxy per cell
        side = int(math.ceil(math.sqrt(n)))
        size = side * CELL
        x = (np.arange(n) % side + 0.5) * CELL
        y = (np.arange(n) // side + 0.5) * CELL
    out = []
    psf = _psf()
    for rotated, sign in RENDERINGS:
        img = galsim.ImageF(size, size, scale=PIXEL)
        gs = sign * g
        S = np.array([[1 + gs, gs], [gs, 1 - gs]]) / math.sqrt(1 - 2 * gs * gs)
        c = size / 2.0
        for i in range(n):
            dx, dy = x[i] - c, y[i] - c
            if rotated and isolated:  # the lattice stays; the galaxy turns
                px, py = dx, dy
            elif rotated:  # the scene turns by 90 degrees about the field's centre
                px, py = -dy, dx
            else:
                px, py = dx, dy
            if not isolated:
                px, py = S @ np.array([px, py])
            prof = galsim.Convolve(_profile(p, i, rotated, gs) * p["flux"][i], psf)
            X, Y = px + c + 1.0, py + c + 1.0  # GalSim's 1-based pixel centres
            b = galsim.BoundsI(int(X) - 32, int(X) + 32, int(Y) - 32, int(Y) + 32) & img.bounds
            if b.isDefined():
                prof.drawImage(image=img[b], add_to_image=True, center=galsim.PositionD(X, Y))
        noise_rng = np.random.default_rng([seed, int(rotated)])
        arr = img.array + noise_rng.standard_normal(img.array.shape).astype(np.float32)
        out.append(arr)
    return out


def write_field(path: Path, arr: np.ndarray) -> None:
    from astropy.io import fits

    fits.PrimaryHDU(arr.astype(np.float32)).writeto(path, overwrite=True)


def field_shears(cat, nimg: int) -> np.ndarray:
    """``(nimg, 2)`` ``sum e / sum sens`` per image over its usable rows, and the count."""
    im = np.asarray(cat["image_index"])
    ok = (np.asarray(cat["flags"]) == 0) & (np.asarray(cat["weight"], float) > 0)
    e = np.column_stack([np.asarray(cat["e1"], float), np.asarray(cat["e2"], float)])
    s = np.column_stack([np.asarray(cat["sens1"], float), np.asarray(cat["sens2"], float)])
    ok &= np.isfinite(e).all(1) & np.isfinite(s).all(1)
    out = np.zeros((nimg, 2, 2))
    for j in range(nimg):
        sel = ok & (im == j)
        out[j, 0] = e[sel].sum(0)
        out[j, 1] = s[sel].sum(0)
    return out, np.bincount(im[ok], minlength=nimg)


def m_c(sums: np.ndarray, g: float) -> tuple[np.ndarray, np.ndarray]:
    """``[m1, m2, c1, c2]`` and jackknife errors from ``(fields, 4, 2, 2)`` sums."""
    plus = np.array([sg > 0 for _, sg in RENDERINGS])

    def fn(sel):
        gp = sums[sel][:, plus, 0].sum((0, 1)) / sums[sel][:, plus, 1].sum((0, 1))
        gm = sums[sel][:, ~plus, 0].sum((0, 1)) / sums[sel][:, ~plus, 1].sum((0, 1))
        return np.concatenate([(gp - gm) / (2 * g) - 1, (gp + gm) / 2])

    n = len(sums)
    full = fn(np.ones(n, bool))
    loo = np.array([fn(np.arange(n) != k) for k in range(n)])
    return full, np.sqrt((n - 1) / n * ((loo - loo.mean(0)) ** 2).sum(0))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fields", type=int, default=8)
    ap.add_argument("--size", type=int, default=1024, help="field side (px)")
    ap.add_argument("--density", type=float, default=30.0, help="galaxies per arcmin^2")
    ap.add_argument("--pairs", type=float, default=0.3, help="share with a close companion")
    ap.add_argument("--g", type=float, default=0.02)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--keep", default=None, help="keep the images and catalogues here")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a Config override for measure (repeatable), e.g. "
                         "--set close_pair_faint_ratio=0.5")  # fmt: skip
    a = ap.parse_args(argv)
    import yaml

    overrides = {}
    for item in a.set:
        key, sep, value = item.partition("=")
        if not sep:
            ap.error(f"--set {item!r}: expected KEY=VALUE")
        overrides[key.strip()] = yaml.safe_load(value)
    from concurrent.futures import ProcessPoolExecutor

    import galsim

    import pylensfit as plf

    rng = np.random.default_rng(a.seed)
    fields = []
    for _ in range(a.fields):
        x, y = layout(a.size, a.density, a.pairs, rng)
        p = draw_galaxies(len(x), rng)
        p["flux"] = np.array([_flux_for_snr(_profile(p, i, False, 0.0), p["snr"][i])
                              for i in range(len(x))])  # fmt: skip
        fields.append((x, y, p))
    work = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="blend_bias_"))
    work.mkdir(parents=True, exist_ok=True)
    psf_path = work / "psf.fits"
    psf_img = _psf().drawImage(scale=PIXEL, nx=48, ny=48, offset=(0.5, 0.5)).array
    write_field(psf_path, psf_img / psf_img.sum())
    t0 = time.perf_counter()
    results = {}
    for label, isolated in (("blended", False), ("isolated", True)):
        jobs = [(x, y, p, a.size, a.g, a.seed * 1000 + f, isolated)
                for f, (x, y, p) in enumerate(fields)]  # fmt: skip
        with ProcessPoolExecutor(a.jobs) as pool:
            imgs = list(pool.map(render, jobs))
        paths = []
        for f, four in enumerate(imgs):
            for k, arr in enumerate(four):
                path = work / f"{label}_f{f:03d}_r{k}.fits"
                write_field(path, arr)
                paths.append(path)
        t1 = time.perf_counter()
        cat = plf.measure([str(p) for p in paths], psf=str(psf_path), jobs=a.jobs,
                          progress=False, config=plf.Config(**overrides))  # fmt: skip
        t_meas = time.perf_counter() - t1
        sums, counts = field_shears(cat, len(paths))
        v, err = m_c(sums.reshape(a.fields, 4, 2, 2), a.g)
        results[label] = (v, err, counts.reshape(a.fields, 4), t_meas, len(cat))
    n_true = sum(len(x) for x, _, _ in fields)
    print(f"{a.fields} fields of {a.size}^2 px at {PIXEL}\"/px, {n_true} galaxies "
          f"({a.density}/arcmin^2, {a.pairs:.0%} with a companion 1.5-4\" away), g = {a.g}, "
          f"seed {a.seed}; Config({overrides or ''}); galsim {galsim.__version__}, "
          f"pylensfit {plf.__version__}")
    print(f"{'fields':10s} {'rows':>7s} {'usable +g':>10s} {'usable -g':>10s} "
          f"{'m1':>18s} {'m2':>18s} {'c1':>18s} {'c2':>18s} {'s':>6s}")  # fmt: skip
    for label, (v, err, counts, tm, nrow) in results.items():
        cp, cm = counts[:, :2].sum(), counts[:, 2:].sum()
        cols = [f"{x:+.4f} ± {e:.4f}" for x, e in zip(v, err, strict=True)]
        print(f"{label:10s} {nrow:7d} {cp:10d} {cm:10d} " + " ".join(f"{c:>18s}" for c in cols)
              + f" {tm:6.0f}")
    vb, eb = results["blended"][:2]
    vi, ei = results["isolated"][:2]
    d = vb - vi
    de = np.hypot(eb, ei)
    print("blended - isolated: " + ", ".join(
        f"{q} {x:+.4f} ± {e:.4f}" for q, x, e in zip(("m1", "m2", "c1", "c2"), d, de,
                                                     strict=True)))  # fmt: skip
    print(f"total {time.perf_counter() - t0:.0f} s; files in {work}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
