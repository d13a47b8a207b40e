"""Where the noise detections end: the model S/N of detections on pure-noise images.

``Config.min_snr`` keeps detections whose best model's matched-filter S/N is below it out
of the shear (flag ``LOW_SNR``, weight 0). This script measures, with the pipeline as a
survey runs it (sep detection at the default threshold, the fit), the S/N of every
detection on images of pure Gaussian noise, and beside it that of the galaxies of a
simulated field (exponential discs of S/N 15-150 under the same PSF), and prints for each
candidate floor the fraction of noise detections and of galaxies it keeps::

    python benchmarks/noise_detections.py --images 4 --size 512 --seed 1

The PSF is given (a Moffat of FWHM 3 px, beta 3.5), so that no star field is needed; the
fits use ``Config.paper(min_snr=0)`` (one pass: the S/N of the best model hardly depends on
the priors).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from astropy.io import fits


def _psf(n: int = 64) -> np.ndarray:
    import galsim

    return galsim.Moffat(beta=3.5, fwhm=3.0).drawImage(nx=n, ny=n, scale=1.0).array


def _noise_image(path: Path, size: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    img = (100.0 + rng.normal(size=(size, size))).astype(np.float32)
    hdus = [fits.PrimaryHDU(img), fits.ImageHDU(np.ones_like(img), name="WEIGHT")]
    fits.HDUList(hdus).writeto(path, overwrite=True)


def main(argv: list[str] | None = None) -> int:
    import pylensfit as plf
    from pylensfit_validation.simulate import FieldSpec, simulate_field, write_field

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=4, help="pure-noise images")
    ap.add_argument("--size", type=int, default=512, help="image side, pixels")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--floors", default="0,4,5,6,7,8,10")
    args = ap.parse_args(argv)
    floors = [float(v) for v in args.floors.split(",")]
    cfg = plf.Config.paper(min_snr=0.0)
    psf = _psf()
    work = Path(tempfile.mkdtemp(prefix="plf-noise-"))
    noise = []
    for k in range(args.images):
        p = work / f"noise_{k}.fits"
        _noise_image(p, args.size, args.seed * 100 + k)
        noise.append(p)
    spec = FieldSpec(size=args.size, star_fraction=0.0, psf_e1=0.0, psf_e2=0.0)
    img, w, _ = simulate_field(spec, seed=args.seed, noise_seed=args.seed + 7)
    gal_path = work / "galaxies.fits"
    write_field(gal_path, img, w, spec)
    t0 = time.perf_counter()
    rows = {}
    for name, paths in (("noise", noise), ("galaxies", [gal_path])):
        cat = plf.measure(paths, psf=psf, config=cfg, prior=plf.Prior(), jobs=args.jobs,
                          progress=False)  # fmt: skip
        ok = (np.asarray(cat["fitclass"]) == 0) & np.isfinite(np.asarray(cat["model_SNratio"]))
        ok &= np.asarray(cat["flags"]) == 0
        rows[name] = (len(cat), np.asarray(cat["model_SNratio"], dtype=float)[ok])
    dt = time.perf_counter() - t0
    n_noise, s_noise = rows["noise"]
    n_gal, s_gal = rows["galaxies"]
    print(f"{args.images} pure-noise images of {args.size}^2 px: {n_noise} detections, "
          f"{s_noise.size} measured as galaxies; model S/N quantiles 50/90/99/100%: "
          + " / ".join(f"{q:.2f}" for q in np.quantile(s_noise, [0.5, 0.9, 0.99, 1.0]))
          if s_noise.size else "no detection measured")  # fmt: skip
    print(f"a field of exponential galaxies (S/N 15-150): {n_gal} detections, {s_gal.size} "
          f"measured; S/N quantiles 1/5/50%: "
          + " / ".join(f"{q:.2f}" for q in np.quantile(s_gal, [0.01, 0.05, 0.5])))
    print(f"{'min_snr':>8} {'noise rows kept':>16} {'per image':>10} {'galaxies kept':>14}")
    for f in floors:
        kn = int(np.sum(s_noise >= f))
        print(f"{f:8.1f} {kn:16d} {kn / args.images:10.1f} {np.mean(s_gal >= f):14.4f}")
    print(f"({dt:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
