"""Which prior makes the precision run's m: the same renderings with estimated or given priors.

``pylensfit validate --precision`` estimates three priors from an unsheared calibration
sample: the ellipticity prior, the size prior (one per PSF) and the weights of the
bulge fractions. This runs :func:`pylensfit_validation.precision.precision` on a chosen population
(``--morphology-weights`` over exponential, de Vaucouleurs, bulge+disc, Sersic, knots)
with any of them replaced by the population's own:

- ``--true-prior``: the functional prior the intrinsic ellipticities are drawn from;
- ``--true-size-prior``: log-uniform over the drawn sizes, per PSF
  (:func:`pylensfit_validation.precision.population_size_prior`; exact for the exponential, de
  Vaucouleurs and Sersic galaxies, whose half-light radius is the one drawn);
- ``--bulge-weights W0 W05 W1``: the weights of the bulge fractions 0, 0.5, 1.

The amplitude and position priors are the precision mode's
(:func:`pylensfit_validation.precision.default_config`: the flux's power law, its power estimated
from the calibration sample, the catalogue positions' scatter) unless
``--amplitude-prior uniform|snr`` (the paper's uniform prior; ``t^-2`` in each model's
S/N), ``--amplitude-prior-power`` or ``--position-prior-sigma`` say otherwise.

The seed fixes the renderings and the noise, so runs that differ only in the priors are
paired and their difference in m is far better measured than either m. It prints the
fixed-point rows of the ``all``, PSF, S/N, size and morphology breakdowns::

    python benchmarks/studies/precision_priors.py --ngal 20000 --seed 5
    python benchmarks/studies/precision_priors.py --ngal 20000 --seed 5 \\
        --morphology-weights 1 1 0 0 0
    python benchmarks/studies/precision_priors.py --ngal 20000 --seed 5 \\
        --morphology-weights 1 1 0 0 0 \\
        --true-prior --true-size-prior --bulge-weights 0.5 0 0.5
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from pylensfit import Config
from pylensfit_validation.precision import (
    PRECISION_PSFS,
    default_config,
    population_flux_range,
    population_prior,
    population_size_prior,
    precision,
    spec_with,
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ngal", type=int, default=20_000)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--morphology-weights", type=float, nargs=5, default=None,
                    metavar="W", help="exponential, de Vaucouleurs, bulge+disc, Sersic, knots")
    ap.add_argument("--true-prior", action="store_true")
    ap.add_argument("--true-size-prior", action="store_true")
    ap.add_argument("--bulge-weights", type=float, nargs=3, default=None, metavar="W")
    ap.add_argument("--amplitude-prior", choices=["uniform", "snr", "flux"], default="flux",
                    help="Config.amplitude_prior ('snr': t^-2 in the model's S/N)")
    ap.add_argument("--amplitude-prior-power", type=float, default=None,
                    help="the amplitude prior's power (default: 'flux' estimated from the "
                         "calibration sample, 'snr' 2)")  # fmt: skip
    ap.add_argument("--position-prior-sigma", type=float, default=None,
                    help="Config.position_prior_sigma (default: offset / sqrt(3))")
    ap.add_argument("--size-prior-smoothing", type=float, default=Config().size_prior_smoothing,
                    help="Config.size_prior_smoothing of the estimated size prior")
    ap.add_argument("--size-prior-per-run", action=argparse.BooleanOptionalAction,
                    default=True,
                    help="Config.size_prior_per_run: one size distribution per bulge "
                    "fraction of the family, estimated jointly (the precision mode's "
                    "default; --no-size-prior-per-run for one size prior)")
    ap.add_argument("--psf", nargs="+", default=None, choices=[p["name"] for p in PRECISION_PSFS],
                    help="only these PSFs (default: all four)")
    ap.add_argument("--snr", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="PrecisionSpec.snr_range (the reference S/N of the fluxes)")
    ap.add_argument("--size", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="PrecisionSpec.size_ratio_range (half-light radius / PSF's)")
    ap.add_argument("--e-step", type=float, default=None, help="Config.e_step (default 0.1)")
    ap.add_argument("--e-refine", type=int, default=1,
                    help="Config.e_refine, the adaptive refinement (default 1: none)")
    ap.add_argument("--refine", type=int, default=None,
                    help="Config.integration_refine (default 4): the Bayesian integrals' grid "
                         "is this many times finer than the model grid")  # fmt: skip
    ap.add_argument("--offset", type=float, default=None,
                    help="PrecisionSpec.offset (0: centred galaxies, the position prior "
                         "pinned to 0.01 px)")  # fmt: skip
    ap.add_argument("--model", choices=["bulge+disc", "exponential", "devaucouleurs"],
                    default="bulge+disc",
                    help="the fitted model (default: the precision mode's bulge+disc with three "
                         "bulge fractions; one profile alone costs a third)")  # fmt: skip
    ap.add_argument("--flux-bounds", action="store_true",
                    help="bound the flux prior at the population's flux range "
                         "(Config.amplitude_prior_min/max; one PSF only)")  # fmt: skip
    ap.add_argument("--estimate-flux-bounds", action=argparse.BooleanOptionalAction,
                    default=True,
                    help="estimate each PSF's flux range from the calibration sample "
                         "(precision(flux_bounds=True)) and bound the flux prior there "
                         "(default, as the precision mode; --no-estimate-flux-bounds: the "
                         "unbounded power law)")  # fmt: skip
    ap.add_argument("--out", default=None,
                    help="also write the result table here (ECSV, without the per-galaxy meta)")
    a = ap.parse_args()
    kw = {}
    if a.morphology_weights:
        kw["morphology_weights"] = tuple(a.morphology_weights)
    if a.psf:
        kw["psfs"] = tuple(p for p in PRECISION_PSFS if p["name"] in a.psf)
    if a.snr:
        kw["snr_range"] = tuple(a.snr)
    if a.size:
        kw["size_ratio_range"] = tuple(a.size)
    if a.offset is not None:
        kw["offset"] = a.offset
    spec = spec_with(ngal=a.ngal, seed=a.seed, **kw)
    cfg = default_config(spec).replace(amplitude_prior=a.amplitude_prior,
                                       size_prior_smoothing=a.size_prior_smoothing,
                                       size_prior_per_run=a.size_prior_per_run)  # fmt: skip
    if a.e_step is not None:
        cfg = cfg.replace(e_step=a.e_step)
    if a.e_refine > 1:
        cfg = cfg.replace(e_refine=a.e_refine)
    if a.refine is not None:
        cfg = cfg.replace(integration_refine=a.refine)
    if a.model != "bulge+disc":
        cfg = cfg.replace(model=a.model, n_bulge_fractions=1)
    if a.position_prior_sigma is not None:
        cfg = cfg.replace(position_prior_sigma=a.position_prior_sigma)
    if a.amplitude_prior_power is not None:
        cfg = cfg.replace(amplitude_prior_power=a.amplitude_prior_power)
    if a.flux_bounds:
        if len(spec.psfs) != 1:
            ap.error("--flux-bounds needs one PSF (--psf NAME): the flux range is per PSF")
        lo, hi = population_flux_range(spec, 0, stamp_size=cfg.largest_stamp)
        cfg = cfg.replace(amplitude_prior_min=lo, amplitude_prior_max=hi)
    prior = population_prior(spec) if a.true_prior else None
    sizes = None
    if a.true_size_prior:
        sizes = [population_size_prior(spec, k, stamp_size=cfg.largest_stamp)
                 for k in range(len(spec.psfs))]  # fmt: skip
    t0 = time.perf_counter()
    res = precision(spec, config=cfg, jobs=a.jobs, prior=prior, size_prior=sizes,
                    bulge_weights=a.bulge_weights, progress=False,
                    flux_slope=a.amplitude_prior_power,
                    flux_bounds=a.estimate_flux_bounds)  # fmt: skip
    if a.out:
        keep = res.copy(copy_data=False)
        keep.meta.pop("galaxies", None)
        keep.write(a.out, format="ascii.ecsv", overwrite=True)
    cfg = cfg.replace(amplitude_prior_power=res.meta["config"]["amplitude_prior_power"])
    fs = res.meta["flux_slope"]
    bounds = ""
    if a.flux_bounds:
        bounds = f" within {cfg.amplitude_prior_min:.3g}-{cfg.amplitude_prior_max:.3g}"
    print(f"{a.ngal} galaxies, seed {a.seed}, morphology weights {spec.morphology_weights}, "
          f"PSFs {', '.join(p['name'] for p in spec.psfs)}, S/N {spec.snr_range}, sizes "
          f"{spec.size_ratio_range}, model {cfg.model}, e_step {cfg.e_step} (refined "
          f"{cfg.e_refine}x, integrals {cfg.integration_refine}x finer), "
          f"amplitude prior {cfg.amplitude_prior} (power {cfg.amplitude_prior_power:.3f}"
          f"{', estimated' if fs and fs['estimated'] else ''}), "
          f"{bounds}, "
          f"position prior "
          f"{cfg.position_prior_sigma:.3g} px, size prior smoothing "
          f"{cfg.size_prior_smoothing}{' per run' if cfg.size_prior_per_run else ''}, "
          f"{time.perf_counter() - t0:.0f} s")  # fmt: skip
    for b in res.meta.get("flux_bounds") or []:
        print(f"flux bounds {b['psf']} (estimated): {b['lo']:.4g} ± {b['lo_err']:.2g}, "
              f"{b['hi']:.4g} ± {b['hi_err']:.2g} (population's {b['true'][0]:.4g}, "
              f"{b['true'][1]:.4g})")  # fmt: skip
    p, bp = res.meta["prior"], res.meta["bulge_prior"]
    print(f"ellipticity prior {'given' if p['given'] else 'estimated'}: B, C, D = "
          f"{p['B']:.3f}, {p['C']:.3f}, {p['D']:.3f}; bulge weights "
          f"{'none' if bp['weights'] is None else np.round(bp['weights'], 3).tolist()} "
          f"({bp['method']})")  # fmt: skip
    for one in res.meta["size_prior"] or []:
        how = "given" if res.meta["size_prior_given"] else "estimated"
        dens = np.asarray(one["density"])
        rows = [("", np.asarray(one.get("marginal", dens)))]
        if dens.ndim == 2:  # one per run of the family: each run's too
            rows += [(f", run {i}", d) for i, d in enumerate(dens)]
        for label, d in rows:
            q = np.exp(np.interp([0.05, 0.5, 0.95], np.cumsum(d) / np.sum(d), one["ln_h"]))
            print(f"size prior {one['psf']}{label} ({how}): 5 / 50 / 95 % = "
                  + " / ".join(f"{v:.2f}" for v in q) + " px")
    keep = np.isin(res["breakdown"], ["all", "psf", "snr", "size", "morphology", "sersic_n",
                                      "no controls"])  # fmt: skip
    show = res[keep & (res["estimator"] == "fixed-point")]
    show = show[show["n_gal"] > 0]
    for c in ("m1", "m1_err", "m2", "m2_err", "c1", "c2"):
        show[c].format = "+.4f"
    show["breakdown", "group", "n_gal", "m1", "m1_err", "m2", "m2_err", "c1", "c2"].pprint_all()


if __name__ == "__main__":
    main()
