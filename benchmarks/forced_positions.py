"""Forced positions on blank sky: how many come out usable, and the galaxies kept.

An input catalogue (``measure(..., catalogues=)``) may hold positions where the image
has no source: a deeper detection, another band's catalogue. This script simulates
fields of exponential galaxies (S/N 6-60, no stars, a Moffat PSF of FWHM 3 px given),
writes an input catalogue of the galaxies' true positions plus one blank position in
each cell of the galaxies' lattice (more than a stamp's half-width from every galaxy,
so that no row is a close pair), and measures it twice: with the cut on the S/N at the
catalogue position (``Config.forced_false_alarm``, the default 1e-3) and without it
(``forced_false_alarm=1``: the best model's S/N above ``Config.min_snr`` alone). It
prints, per field and in all, the fraction of blank positions usable (flags 0, weight
> 0) and the completeness of the galaxies of true S/N >= 10 and below::

    python benchmarks/forced_positions.py --seeds 1,2,3,4 --size 512
    python benchmarks/forced_positions.py --seeds 1,2 --calibrate   # Config(), priors estimated

Without ``--calibrate`` the fits use the defaults in one pass under fixed priors (the
flat size prior, the uniform amplitude prior, the 2-pixel position prior), as the
tests do.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from astropy.table import Table


def _psf(n: int = 48) -> np.ndarray:
    import galsim

    return galsim.Moffat(beta=3.5, fwhm=3.0).drawImage(nx=n, ny=n, scale=1.0,
                                                       offset=(0.5, 0.5)).array  # fmt: skip


def field_with_blanks(work: Path, size: int, seed: int, spacing: float, jitter: float):
    """Write a simulated field and its input catalogue (true positions, then blanks).

    Returns the image's path, the catalogue's path, whether each row is blank and each
    row's true S/N (NaN for a blank)."""
    from pylensfit_validation.simulate import FieldSpec, simulate_field, write_field

    spec = FieldSpec(size=size, spacing=spacing, jitter=jitter, star_fraction=0.0,
                     psf_e1=0.0, psf_e2=0.0, snr_range=(6.0, 60.0))  # fmt: skip
    img, w, truth = simulate_field(spec, seed=seed, noise_seed=seed + 7)
    image = work / f"field{seed}.fits"
    write_field(image, img, w, spec, truth=truth)
    rng = np.random.default_rng(seed + 100)
    g = np.arange(1.5 * spacing, size - spacing, spacing)  # the lattice's cell centres
    bx, by = (v.ravel() + rng.uniform(-2.0, 2.0, v.size) for v in np.meshgrid(g, g))
    x = np.r_[np.asarray(truth["x"]), bx]
    y = np.r_[np.asarray(truth["y"]), by]
    blank = np.r_[np.zeros(len(truth), bool), np.ones(bx.size, bool)]
    snr = np.r_[np.asarray(truth["snr"], dtype=float), np.full(bx.size, np.nan)]
    cat = work / f"positions{seed}.fits"
    Table({"x": x, "y": y}).write(cat, overwrite=True)
    return image, cat, blank, snr


def main(argv: list[str] | None = None) -> int:
    import pylensfit as plf

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1,2,3,4")
    ap.add_argument("--size", type=int, default=512, help="image side, pixels")
    ap.add_argument("--spacing", type=float, default=48.0, help="galaxies' lattice pitch, px")
    ap.add_argument("--jitter", type=float, default=4.0)
    ap.add_argument("--calibrate", action="store_true", help="Config() with its calibration")
    ap.add_argument("--jobs", type=int, default=1)
    args = ap.parse_args(argv)
    if args.calibrate:
        base, kw = plf.Config(), {}
    else:
        base = plf.Config(r_max=6.0, size_prior="flat", estimate_flux_prior=False,
                          estimate_position_prior=False, amplitude_prior="uniform")  # fmt: skip
        kw = {"prior": plf.Prior()}
    work = Path(tempfile.mkdtemp(prefix="plf-forced-"))
    runs = {"min_snr alone": base.replace(forced_false_alarm=1.0), "with the cut": base}
    tot = {k: [] for k in runs}
    print(f"{'seed':>4} {'run':>14} {'blanks':>7} {'usable':>7} {'gal>=10':>8} {'kept':>6} "
          f"{'gal<10':>7} {'kept':>6} {'time':>6}")  # fmt: skip
    for seed in (int(s) for s in args.seeds.split(",")):
        image, cat, blank, snr = field_with_blanks(work, args.size, seed, args.spacing,
                                                   args.jitter)  # fmt: skip
        for name, cfg in runs.items():
            t0 = time.perf_counter()
            out = plf.measure([image], catalogues=[cat], psf=_psf(), config=cfg, jobs=args.jobs,
                              progress=False, **kw)  # fmt: skip
            dt = time.perf_counter() - t0
            use = (np.asarray(out["flags"]) == 0) & (np.asarray(out["weight"]) > 0)
            bright, faint = ~blank & (snr >= 10), ~blank & (snr < 10)
            tot[name].append((use[blank].sum(), blank.sum(), use[bright].sum(), bright.sum(),
                              use[faint].sum(), faint.sum()))  # fmt: skip
            print(f"{seed:4d} {name:>14} {blank.sum():7d} {use[blank].mean():7.3f} "
                  f"{bright.sum():8d} {use[bright].mean():6.3f} {faint.sum():7d} "
                  f"{use[faint].mean():6.3f} {dt:5.0f}s")  # fmt: skip
    for name, rows in tot.items():
        a = np.sum(rows, axis=0)
        print(f"all: {name}: blank positions usable {a[0]}/{a[1]} = {a[0] / a[1]:.3f}; "
              f"galaxies of S/N >= 10 kept {a[2]}/{a[3]} = {a[2] / a[3]:.3f}; below 10 "
              f"{a[4]}/{a[5]} = {a[4] / max(a[5], 1):.3f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
