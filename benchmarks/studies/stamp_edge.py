"""The stamp's edge: how much more a large galaxy responds to g2 than to g1.

A ring of 16 noise-free exponential galaxies (intrinsic |e| = 0.2, position angles
0-180 degrees), each sheared by +-g along e1 and along e2 (g = 0.02), rendered by
GalSim (or by pylensfit's own models, ``--renderer model``, on a 96-pixel canvas cut to
the stamp) under a precision-mode PSF, at a given S/N, and fitted with the exponential
model and the STEP prior. R_i is the posterior mean's response ``(<e_i>(+g_i) -
<e_i>(-g_i)) / 2g`` averaged over the ring; by symmetry R1 = R2 for a round PSF. The
square stamp breaks the symmetry between the pixel axes (e1) and the diagonals (e2):
the models are cut at the edge (``Config.truncate_models``), but the light that the
PSF scatters across it is not where the periodic model puts it, and a galaxy whose
convolved half-light radius is more than a tenth of the stamp responds differently to
g1 and g2. ``Config.max_stamp_size`` fits such galaxies on larger stamps
(``benchmarks/README.md``, "What the studies found")::

    python benchmarks/studies/stamp_edge.py
    python benchmarks/studies/stamp_edge.py --psf round kolmogorov --ratio 1 1.5 2 2.5 --snr 200
    python benchmarks/studies/stamp_edge.py --profile devaucouleurs --psf kolmogorov --ratio 1.5 2

``--profile devaucouleurs`` renders and fits de Vaucouleurs galaxies (truncated at 8
half-light radii, as the model): their wings need more than the tiers' ten convolved
half-light radii (the column "128, |k| <= pi/4").
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import pylensfit_validation.precision as PR
from pylensfit import Config, Prior, fit_stamps
from pylensfit.models import half_light_radius, render_models
from pylensfit.shear import posterior_moments

#: (label, stamp rendered, Config changes)
SETUPS = (
    ("32", 32, {}),
    ("48", 48, {"stamp_size": 48}),
    ("64", 64, {"stamp_size": 64}),
    ("64, |k| <= pi/2", 64, {"stamp_size": 64, "k_max": np.pi / 2}),
    ("tiers to 96", 96, {"max_stamp_size": 96}),
    ("128, |k| <= pi/4", 128, {"stamp_size": 128, "k_max": np.pi / 4}),
)


def ring(psf_name: str, ratio: float, n: int, *, renderer: str, snr: float, g: float = 0.02,
         n_angles: int = 16, profile: str = "exponential",
         ) -> tuple[np.ndarray, np.ndarray, float]:  # fmt: skip
    """The ring's renderings on ``n x n``, the PSF image and the galaxy's half-light radius."""
    import galsim

    p = next(q for q in PR.PRECISION_PSFS if q["name"] == psf_name)
    psf_img, psf_hlr = PR.psf_image(p, n)
    r = ratio * psf_hlr
    gpsf = PR.galsim_psf(p)
    imgs = []
    for a in np.arange(n_angles) * np.pi / n_angles:
        z = 0.2 * np.exp(2j * a)
        for s in (g, -g, 1j * g, -1j * g):
            if renderer == "galsim":
                gal = PR.profile_of(profile, r, 0.0, 4.0, 0, 0.0, 0).shear(g1=z.real, g2=z.imag)
                sheared = galsim.Convolve(gal.shear(g1=s.real, g2=s.imag), gpsf)
                imgs.append(PR.draw_image(sheared, n))
            else:
                e = (z + s) / (1 + np.conj(s) * z)
                c = 96
                im = render_models(2 * c, psf_img, [c], [c], [e.real], [e.imag],
                                   [r / half_light_radius(profile)], [1.0],
                                   model=profile)[0]  # fmt: skip
                imgs.append(im[c - n // 2 : c - n // 2 + n, c - n // 2 : c - n // 2 + n])
    imgs = np.array(imgs)
    return imgs * snr / np.sqrt(np.sum(imgs[0] ** 2)), psf_img, r


def responses(imgs, psf_img, cfg: Config, g: float = 0.02):
    fits = fit_stamps(imgs, psf_img, 1.0, config=cfg)
    mom = posterior_moments(fits.lnL, fits.egrid, Prior())
    e1 = mom["e1"].reshape(-1, 4)
    e2 = mom["e2"].reshape(-1, 4)
    r1 = np.mean(e1[:, 0] - e1[:, 1]) / (2 * g)
    r2 = np.mean(e2[:, 2] - e2[:, 3]) / (2 * g)
    return r1, r2, fits


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--psf", nargs="+", default=["round", "kolmogorov", "asymmetric"])
    ap.add_argument("--ratio", nargs="+", type=float, default=[1.0, 1.5, 2.0, 2.5],
                    help="galaxy half-light radius over the PSF's")  # fmt: skip
    ap.add_argument("--snr", type=float, default=40.0)
    ap.add_argument("--renderer", choices=["galsim", "model"], default="galsim")
    ap.add_argument("--profile", choices=["exponential", "devaucouleurs"],
                    default="exponential", help="rendered and fitted")  # fmt: skip
    a = ap.parse_args()
    base = Config(model=a.profile, position_prior_sigma=0.01)
    print(f"{a.profile} ring, S/N {a.snr:g}, renderer {a.renderer}; R2/R1 - 1 per stamp "
          "setup (stamp sizes used by the tiers in brackets)\n")  # fmt: skip
    print("| PSF | r / PSF r | r (px) | " + " | ".join(s[0] for s in SETUPS) + " |")
    print("|---|---|---|" + "---|" * len(SETUPS))
    t0 = time.time()
    for psf_name in a.psf:
        for ratio in a.ratio:
            cells = []
            for _label, n, kw in SETUPS:
                imgs, psf_img, r = ring(psf_name, ratio, n, renderer=a.renderer, snr=a.snr,
                                        profile=a.profile)  # fmt: skip
                r1, r2, fits = responses(imgs, psf_img, base.replace(**kw))
                cell = f"{r2 / r1 - 1:+.4f}"
                if "max_stamp_size" in kw:
                    cell += f" ({', '.join(str(v) for v in np.unique(fits.stamp))})"
                cells.append(cell)
            print(f"| {psf_name} | {ratio:g} | {r:.2f} | " + " | ".join(cells) + " |",
                  flush=True)  # fmt: skip
    print(f"\n{time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
