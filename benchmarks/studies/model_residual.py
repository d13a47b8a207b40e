"""How exactly the engine's models reproduce GalSim's renderings, and their shear signal.

For an exponential galaxy of ``r`` PSF half-light radii and ellipticity ``z`` under a
precision-mode PSF, rendered by GalSim (:func:`pylensfit_validation.precision.draw_image`, as the
precision mode draws its data) at shears ``+g`` and ``-g`` along e1, and by
:func:`pylensfit.models.render_models` at the same parameters (on a 192-pixel canvas cut
to the stamp), it prints:

- ``|d - m| / |d|``: the relative residual at ``+g``;
- ``rho``: the residual of the shear signal, ``|(d+ - d-) - (m+ - m-)| / |d+ - d-|``;
- ``proj``: that residual projected onto the signal, the fraction of the response the
  fits would misread (a shear bias of that order).

It measures residuals of 1e-5 of the norm and projections of -1e-5: the models are
exact::

    python benchmarks/studies/model_residual.py
"""

from __future__ import annotations

import argparse

import numpy as np

import pylensfit_validation.precision as PR
from pylensfit.models import half_light_radius, render_models


def main() -> None:
    import galsim

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--psf", nargs="+", default=["round", "asymmetric"])
    ap.add_argument("--ratio", nargs="+", type=float, default=[0.5, 1.0, 2.0])
    ap.add_argument("--stamp", type=int, default=64)
    ap.add_argument("--g", type=float, default=0.02)
    a = ap.parse_args()
    n, c = a.stamp, 96
    print("| PSF | r / PSF r | z | abs(d - m) / abs(d) | rho | proj |")
    print("|---|---|---|---|---|---|")
    for name in a.psf:
        p = next(q for q in PR.PRECISION_PSFS if q["name"] == name)
        psf_img, psf_hlr = PR.psf_image(p, n)
        gpsf = PR.galsim_psf(p)
        for ratio in a.ratio:
            r = ratio * psf_hlr
            for z in (0.3, 0.3j, 0.0):
                d, m = [], []
                for s in (a.g, -a.g):
                    gal = galsim.Exponential(half_light_radius=r).shear(g1=z.real, g2=z.imag)
                    d.append(PR.draw_image(galsim.Convolve(gal.shear(g1=s, g2=0.0), gpsf), n))
                    e = (z + s) / (1 + np.conj(s) * z)
                    im = render_models(2 * c, psf_img, [c], [c], [e.real], [e.imag],
                                       [r / half_light_radius("exponential")], [1.0],
                                       model="exponential")[0]  # fmt: skip
                    m.append(im[c - n // 2 : c + n // 2, c - n // 2 : c + n // 2])
                dd, dm = d[0] - d[1], m[0] - m[1]
                rel = np.linalg.norm(d[0] - m[0]) / np.linalg.norm(d[0])
                rho = np.linalg.norm(dd - dm) / np.linalg.norm(dd)
                proj = np.sum((dd - dm) * dd) / np.sum(dd * dd)
                print(f"| {name} | {ratio:g} | {z} | {rel:.1e} | {rho:.1e} | {proj:+.1e} |",
                      flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
