"""Command-line interface: a thin layer over the public API.

::

    pylensfit measure IMAGE... [--stars STARFIELD...] [--config FILE] -o OUT
    pylensfit prior CATALOG... -o PRIOR
    pylensfit shear CATALOG... [--prior PRIOR] [--bin-by COLUMN:EDGES]
    pylensfit simulate step1|step2 --out DIR [--ngal N] [--seed S] [--twins] [--noise-twins]
        [--jobs N]
    pylensfit validate DIR [--report FILE]   # m, c, sigma_c, Q per PSF
    pylensfit validate --precision [--ngal N] [--psf NAME...] [--noise-twins]  # paired +-g
    pylensfit validate --convergence [--out DIR]   # grid convergence (paper Figure 2)
    pylensfit validate --quick [--out DIR] [--jobs 2]   # small STEP1+STEP2, < 10 min
    pylensfit config [-o FILE]          # the default configuration as YAML
    pylensfit demo                      # simulate, measure, prior, shear
"""

from __future__ import annotations

import argparse
import difflib
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import NoReturn

import numpy as np
from astropy.table import vstack

from .config import PRESETS, Config
from .pipeline import InputError, catalogue_frame, measure, read_catalogue
from .prior import RadialPrior, estimate_prior
from .runner import available_cores
from .shear import shapes, shear_table
from .skyframe import sensitivity_to_sky, to_sky

__all__ = ["main"]

log = logging.getLogger("pylensfit")


def _config(args: argparse.Namespace):
    return Config.from_yaml(args.config) if getattr(args, "config", None) else Config()


def _measure(args: argparse.Namespace) -> int:
    cat = measure(
        args.images, stars=args.stars, weights=args.weights, masks=args.masks,
        catalogues=args.catalogues, star_column=args.star_column, config=_config(args),
        prior=args.prior, size_prior=args.size_prior, priors=args.priors, output=args.output,
        psf_dir=args.psf_dir,
        psf=_psf_arg(args.psf), overwrite=args.overwrite,
        jobs=args.jobs,
        scheduler=args.scheduler, progress=not args.quiet,
    )  # fmt: skip
    n_ok = int(np.sum(np.asarray(cat["weight"]) > 0))
    print(f"{args.output}: {len(cat)} objects, {n_ok} galaxies measured, "
          f"{int(np.sum(cat['fitclass'] == 1))} stars; {cat.meta['priors']!r}")  # fmt: skip
    return 0


def _psf_arg(paths):
    """``--psf``: none, one file for every image, or one per image."""
    if not paths:
        return None
    return paths[0] if len(paths) == 1 else paths


def _read_catalogues(paths: list[str], need: tuple[str, ...] = ("flags", "fitclass"),
                     bin_column: str | None = None):
    """The catalogues of ``paths`` stacked; ``InputError`` naming the file that lacks a
    column of ``need`` (numeric) or ``bin_column`` (``--bin-by``), or whose ellipticity
    grid differs from the first's."""
    cats = [read_catalogue(p) for p in paths]
    egrid = cats[0].meta["egrid"]
    for p, c in zip(paths, cats, strict=True):
        missing = [n for n in need if n not in c.colnames]
        if missing:
            raise InputError(f"{p}: no column {', '.join(missing)} (not a catalogue from "
                             "`pylensfit measure`?)")  # fmt: skip
        for n in need:
            if n != "image" and not _numeric(c[n]):
                raise InputError(f"{p}: column {n} is not numeric ({c[n].dtype})")
        if bin_column is not None:
            _check_bin_column(c, bin_column, p)
        if c.meta["egrid"].shape != egrid.shape or not np.allclose(c.meta["egrid"], egrid):
            raise InputError(f"{p}: its ellipticity grid differs from {paths[0]}'s")
    meta = dict(cats[0].meta)
    if len(cats) > 1 and all("image_index" in c.colnames for c in cats):
        # one image index per image over the catalogues (an image's pixel frame)
        off = 0
        for c in cats:
            c["image_index"] = np.asarray(c["image_index"], dtype=np.int64) + off
            off = int(np.max(c["image_index"], initial=off - 1)) + 1
    cat = vstack(cats, metadata_conflicts="silent") if len(cats) > 1 else cats[0]
    cat.meta.update(meta)
    return cat


def _numeric(col) -> bool:
    """Whether a table column holds numbers (or booleans), one per row."""
    dt = np.asarray(col).dtype
    return np.ndim(col) == 1 and (np.issubdtype(dt, np.number) or np.issubdtype(dt, np.bool_))


def _check_bin_column(cat, column: str, path: str) -> None:
    """``ValueError`` naming ``--bin-by`` and ``path`` if ``cat`` cannot be binned by
    ``column``."""
    if column not in cat.colnames:
        close = difflib.get_close_matches(column, cat.colnames, n=3)
        hint = f"; closest: {', '.join(close)}" if close else ""
        raise ValueError(f"--bin-by: {path} has no column {column!r}{hint}")
    if not _numeric(cat[column]):
        what = ("holds arrays, not one number per row" if np.ndim(cat[column]) > 1
                else f"is not numeric ({cat[column].dtype})")  # fmt: skip
        raise ValueError(f"--bin-by: column {column!r} of {path} {what}; bin by a numeric "
                         "column such as mag")  # fmt: skip


def _usable_galaxies(cat) -> np.ndarray:
    lnL = np.asarray(cat["lnL"])
    use = (np.asarray(cat["flags"]) == 0) & (np.asarray(cat["fitclass"]) == 0)
    if "weight" in cat.colnames:
        use &= np.asarray(cat["weight"], dtype=float) > 0
    return use & np.isfinite(lnL).all(axis=1)


def _prior(args: argparse.Namespace) -> int:
    cat = _read_catalogues(args.catalogs)
    gal = _usable_galaxies(cat)
    if not gal.any():
        raise ValueError("no measured galaxy in the catalogue(s): cannot estimate a prior")
    if args.form == "spline" and args.method != "direct":
        raise ValueError("--form spline is estimated with --method direct")
    prior = estimate_prior(np.asarray(cat["lnL"])[gal], cat.meta["egrid"], method=args.method,
                           form=args.form)  # fmt: skip
    prior.save(args.output)
    for h in prior.history[-3:]:
        par = (" ".join(f"{v:.3f}" for v in h["coef"]) if "coef" in h
               else f"B={h['B']:.4f} C={h['C']:.4f} D={h['D']:.4f}")
        print(f"  step {h.get('iteration', '?')}: {par} "
              f"marginal lnL={h.get('marginal_lnL', float('nan')):.3f}")  # fmt: skip
    print(f"{args.output}: {prior!r} from {int(gal.sum())} galaxies")
    return 0


def _shear(args: argparse.Namespace) -> int:
    per_image = () if args.no_per_image else ("image",)
    cat = _read_catalogues(args.catalogs, need=("flags", "fitclass", *per_image),
                           bin_column=args.bin_column)  # fmt: skip
    cfg = cat.meta.get("config")
    prior = RadialPrior.load(args.prior) if args.prior else cat.meta.get("prior")
    if prior is None:
        raise ValueError("no prior: give --prior (see `pylensfit prior`)")
    sens = args.sensitivity or (cfg.sensitivity if cfg is not None else "exact")
    refine = cfg.output_refine if cfg is not None else 4
    gal = _usable_galaxies(cat)
    if not gal.any():
        raise ValueError("no measured galaxy in the catalogue(s)")
    sh = shapes(np.asarray(cat["lnL"])[gal], cat.meta["egrid"], prior, sensitivity=sens,
                refine=refine)  # fmt: skip
    for c in (*per_image, *([args.bin_column] if args.bin_column else [])):
        sh[c] = cat[c][gal]
    # the shapes in the sky frame, the fixed point per image in its pixel frame
    frame = catalogue_frame(cat[gal])
    sh["e1"], sh["e2"] = to_sky(sh["e1"], sh["e2"], frame)
    sh["sens1"], sh["sens2"] = sensitivity_to_sky(sh["sens1"], sh["sens2"], frame)
    for c in ("sky_angle", "sky_flip", "wcs_g1", "wcs_g2", "image_index", "weight"):
        if c in cat.colnames:
            sh[c] = cat[c][gal]
    if args.estimator == "fixed-point":
        sh["lnL"] = np.asarray(cat["lnL"])[gal]
    tab = shear_table(sh, by=None if args.no_per_image else "image",
                      column=args.bin_column, edges=args.bin_edges, estimator=args.estimator,
                      prior=prior, egrid=cat.meta["egrid"], refine=refine,
                      weighted=args.weighted)  # fmt: skip
    for c in ("g1", "g2"):
        tab[c].format = "+.5f"
    for c in ("g1_err", "g2_err"):
        tab[c].format = ".5f"
    tab.pprint_all()
    if args.output:
        tab.write(args.output, overwrite=True)
    return 0


def _simulate(args: argparse.Namespace) -> int:
    from .validation import main as simulate_main  # start-up cost: only for this command

    return simulate_main([a for a in args.args if a != "--"])


def _precision(args: argparse.Namespace) -> int:
    # start-up cost: the simulation modules load only for this command
    from .precision import (
        default_config,
        population_prior,
        population_size_prior,
        precision,
        spec_with,
    )

    spec = spec_with(ngal=args.ngal or 200_000, seed=args.seed, psfs=args.psf, g=args.g,
                     ncal=args.ncal, block_size=args.block_size,
                     noise_twins=args.noise_twins or None,
                     population=args.population,
                     snr_range=None if args.snr_range is None else tuple(args.snr_range),
                     morphology_weights=(None if args.morphologies is None
                                         else tuple(args.morphologies)))  # fmt: skip
    report = args.report or "precision/report.md"
    prior = population_prior(spec) if args.true_prior else None
    size_prior = None
    if args.true_size_prior:
        stamp = (_config(args) if args.config else Config()).stamp_size
        size_prior = [population_size_prior(spec, k, stamp_size=stamp)
                      for k in range(len(spec.psfs))]  # fmt: skip
    cfg = _config(args) if args.config else None
    if args.e_refine > 1:  # the adaptive e-grid refinement on top of either configuration
        cfg = (cfg or default_config(spec)).replace(e_refine=args.e_refine)
    res = precision(spec, config=cfg, jobs=args.jobs,
                    scheduler=args.scheduler, report=report, prior=prior,
                    progress=not args.quiet, size_prior=size_prior,
                    size_prior_per_psf=not args.one_size_prior,
                    flux_bounds=args.flux_bounds)  # fmt: skip
    show = res[np.isin(res["breakdown"], ["all", "psf", "no controls", "no noise twins"])]
    show = show[show["estimator"] == "fixed-point"]
    for c in ("m1", "m1_err", "m2", "m2_err", "c1", "c1_err", "c2", "c2_err"):
        show[c].format = "+.5f"
    show.pprint_all()
    tim = res.meta["timing"]
    print(f"{spec.ngal} galaxies in {tim['total_s']:.0f} s ({tim['galaxies_per_s']:.0f} "
          f"galaxies/s in the main pass); report: {report}")  # fmt: skip
    return 0


def _convergence(args: argparse.Namespace) -> int:
    from .convergence import convergence  # start-up cost: only for this command

    cfg = _config(args) if args.config else None
    tab = convergence(args.out, ngal=args.ngal or 1000, seed=args.seed, config=cfg,
                      progress=not args.quiet)  # fmt: skip
    cols = ["parameter", "value", "n_used", "e1", "e2", "e1sq", "e2sq", "sens1", "sens2",
            "d_e1", "d_e1_err", "rel_e1sq", "rel_sens1"]  # fmt: skip
    for c in cols[3:]:
        tab[c].format = "+.4f"
    tab[cols].pprint_all()
    if args.out:
        print(f"written: {args.out}/convergence.png, .ecsv, .md")
    return 0


def _validate(args: argparse.Namespace) -> int:
    from .validation import validate  # start-up cost: only for this command

    if args.precision:
        return _precision(args)
    if args.convergence:
        return _convergence(args)
    cfg = _config(args) if args.config else None
    bins = {k: args.bins for k in ("mag", "snr", "size")} if args.bins > 0 else {}
    if args.quick:
        from .validation import quick_validation  # start-up cost: only for this command

        out_dir = args.out or "quick_validation"
        out = quick_validation(out_dir, jobs=args.jobs, seed=args.seed, progress=not args.quiet,
                               config=cfg, estimator=args.estimator)  # fmt: skip
        for kind, res in out.items():
            m = res.meta
            print(f"{kind}: <m> = {m['mean_m']:+.4f} +- {m['mean_m_err']:.4f}, sigma_c = "
                  f"{m['sigma_c']:.2e}, Q = {res['Q'][-1]:.0f}; report "
                  f"{out_dir}/{kind}/report.md")  # fmt: skip
        return 0
    if args.directory is None:
        raise SystemExit("pylensfit validate: give a simulated set's directory (or --quick, "
                         "--precision, --convergence)")  # fmt: skip
    res = validate(args.directory, config=cfg, jobs=args.jobs, estimator=args.estimator,
                   report=args.report, progress=not args.quiet, remeasure=args.remeasure,
                   bins=bins, true_psf=args.true_psf, truth_control=args.truth_control,
                   psf_models=dict(enumerate(args.psf_models or [])) or None)  # fmt: skip
    for c in res.colnames[1:-2]:
        res[c].format = "+.5f"
    res["Q"].format = ".0f"
    res.pprint_all()
    from .validation import nan_note  # start-up cost: only for this command

    if nan_note(res):
        print(nan_note(res))
    print(f"<m> = {res.meta['mean_m']:+.4f}, sigma_c = {res.meta['sigma_c']:.2e}, "
          f"Q = {res['Q'][-1]:.0f}; prior {res.meta['prior']!r}")  # fmt: skip
    held = res.meta.get("diagnosis", {}).get("psf_heldout")
    if held:
        print(f"PSF model on held-out stars: {held[0]} ({held[1]})")
    if args.report:
        print(f"report: {args.report}")
    return 0


def _dump_config(args: argparse.Namespace) -> int:
    cfg = Config.preset(args.preset)
    if args.output:
        cfg.to_yaml(args.output)
        print(f"{args.output}: configuration '{args.preset}' written")
    else:
        docs = Config.describe()
        for name, value in cfg.to_dict().items():
            print(f"# {docs[name][1]}\n{name}: {value!r}")
    return 0


def _demo(args: argparse.Namespace) -> int:
    """Simulate a small field with GalSim, measure it, estimate the prior and the shear."""
    if args.outdir:
        Path(args.outdir).mkdir(parents=True, exist_ok=True)
        return _run_demo(args, Path(args.outdir))
    with tempfile.TemporaryDirectory(prefix="pylensfit-demo-") as tmp:
        return _run_demo(args, Path(tmp))


def _run_demo(args: argparse.Namespace, work: Path) -> int:
    """The demo's work in the folder ``work`` (removed afterwards unless ``--outdir``)."""
    from .simulate import FieldSpec, simulate_field, write_field  # start-up cost: only the demo

    g1, g2 = args.g1, args.g2
    cfg = Config()
    jobs = args.jobs or min(available_cores(), 2)  # two images: more workers wait
    t0 = time.perf_counter()
    spec = FieldSpec(size=args.size, g1=g1, g2=g2, model="mixed")
    paths = []
    for k, rot in enumerate((False, True)):  # a field and its 90-degree-rotated twin
        s = FieldSpec(**{**spec.__dict__, "rotate": rot})
        img, w, truth = simulate_field(s, seed=args.seed, noise_seed=args.seed * 10 + k)
        p = work / f"field_{'ab'[k]}.fits"
        write_field(p, img, w, s, truth=truth)
        paths.append(p)
    stars_spec = FieldSpec(**{**spec.__dict__, "size": 512, "star_fraction": 1.0})
    img, w, _ = simulate_field(stars_spec, seed=args.seed + 1000)
    write_field(work / "stars.fits", img, w, stars_spec)
    print(f"simulated 2 x {len(truth)} objects ({int(truth['is_star'].sum())} stars each; "
          f"exponential, de Vaucouleurs and bulge+disc galaxies in turn) in "
          f"{args.size}x{args.size} px fields with g = ({g1:+.4f}, {g2:+.4f}), and a star "
          f"field, in {time.perf_counter() - t0:.1f} s -> {work}")  # fmt: skip
    t1 = time.perf_counter()
    cat = measure(paths, stars=[work / "stars.fits"], config=cfg, output=work / "catalog.fits",
                  overwrite=True, jobs=jobs, progress=True)  # fmt: skip
    dt = time.perf_counter() - t1
    ngal = int(np.sum(cat["weight"] > 0))
    nstar = int(np.sum(cat["fitclass"] == 1))
    nflag = int(np.sum(cat["fitclass"] == -1))
    print(f"measured {len(cat)} objects ({ngal} galaxies, {nstar} stars, {nflag} flagged) in "
          f"{dt:.1f} s with {jobs} worker(s) ({ngal / dt:.0f} galaxies/s from FITS to "
          f"catalogue) -> {work / 'catalog.fits'}"
          f"{'' if args.outdir else ' (a temporary folder: --outdir DIR keeps the files)'}")
    print(f"priors estimated from the galaxies (Config() defaults, the calibration recipe): "
          f"{cat.meta['priors']!r}")
    tab = shear_table(cat, by="image")
    for c in ("g1", "g1_err", "g2", "g2_err"):
        tab[c].format = "+.4f"
    tab.pprint_all()
    row = tab[-1]
    ok1 = abs(row["g1"] - g1) <= 2 * row["g1_err"]
    ok2 = abs(row["g2"] - g2) <= 2 * row["g2_err"]
    print(f"true g = ({g1:+.4f}, {g2:+.4f}); recovered g = ({row['g1']:+.4f} +- "
          f"{row['g1_err']:.4f}, {row['g2']:+.4f} +- {row['g2_err']:.4f}): "
          f"{'within' if ok1 and ok2 else 'NOT within'} 2 sigma")  # fmt: skip
    return 0 if ok1 and ok2 else 2


def _bin_by(text: str) -> tuple[str, list[float]]:
    """``--bin-by COLUMN:EDGE,EDGE,...``: the column and at least two increasing edges."""
    usage = f"expects COLUMN:EDGE,EDGE,... (e.g. mag:20,22,24), got {text!r}"
    try:
        col, edges = text.split(":", 1)
        e = [float(v) for v in edges.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(usage) from None
    if not col.strip():
        raise argparse.ArgumentTypeError(f"no column: {usage}")
    if len(e) < 2:
        raise argparse.ArgumentTypeError(f"one bin needs two edges: {usage}")
    if not (np.all(np.isfinite(e)) and np.all(np.diff(e) > 0)):
        raise argparse.ArgumentTypeError(f"the edges must be finite and increase: {usage}")
    return col.strip(), e


def _jobs(text: str) -> int:
    """``--jobs N``: a positive number of worker processes."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expects a positive integer, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"expects a positive number of worker processes, "
                                         f"got {n}")  # fmt: skip
    return n


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line: the command, the option and the
    problem, and where to find the usage."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see `{self.prog} -h`)\n")


def _add_prior_parser(sub) -> None:
    """The ``prior`` command's parser."""
    pr = sub.add_parser("prior", help="estimate the ellipticity prior from catalogues")
    pr.add_argument("catalogs", nargs="+", help="catalogues from `pylensfit measure`")
    pr.add_argument("-o", "--output", required=True, help="prior file (JSON)")
    pr.add_argument("--method", choices=("direct", "em"), default="direct",
                    help="direct maximisation (default) or the paper's EM iteration")  # fmt: skip
    pr.add_argument("--form", choices=("spline", "functional"), default="spline",
                    help="a cubic B-spline in |e| that follows any smooth population "
                         "(default, as Config.prior_form) or the paper's three-parameter "
                         "form")  # fmt: skip
    pr.set_defaults(func=_prior)


def _add_precision_args(v) -> None:
    """``pylensfit validate``'s precision-mode options."""
    pv = v.add_argument_group("precision mode: paired +-g renderings, no directory needed")
    pv.add_argument("--precision", action="store_true",
                    help="measure m and c from GalSim galaxies rendered at +g and -g, each "
                         "with a 90-degree twin (report to --report, default "
                         "precision/report.md)")  # fmt: skip
    pv.add_argument("--ngal", type=int, help="galaxies: x4 renderings with --precision "
                    "(default 200,000); with --convergence (default 1000)")  # fmt: skip
    pv.add_argument("--psf", nargs="+", help="PSFs by name: round, e=0.10, kolmogorov, "
                    "asymmetric (default all)")  # fmt: skip
    pv.add_argument("--seed", type=int, default=1, help="random seed (also --quick, "
                    "--convergence)")  # fmt: skip
    pv.add_argument("--g", type=float, default=0.02, help="shear per component")
    pv.add_argument("--ncal", type=int,
                    help="calibration galaxies (priors; default PrecisionSpec's, 80,000)")
    pv.add_argument("--block-size", type=int, default=500, help="galaxies per block")
    pv.add_argument("--noise-twins", action="store_true",
                    help="render every galaxy eight times: the four renderings and the same "
                         "four with their noise negated (at the same number of renderings "
                         "c's error 2.9 times smaller, m's the same)")  # fmt: skip
    pv.add_argument("--population", choices=("aligned", "realistic"), default="aligned",
                    help="galaxies: bulges aligned with their discs and as elongated, Sersic "
                         "0.5-4 (default); or realistic: bulges misaligned (30 degrees rms) "
                         "and rounder than their discs, of their own sizes, Sersic 0.3-6")
    pv.add_argument("--snr-range", type=float, nargs=2, metavar=("LO", "HI"),
                    help="the reference S/N range of the fluxes (default PrecisionSpec's, "
                         "10 200)")
    pv.add_argument("--morphologies", type=float, nargs=5, metavar="W",
                    help="fractions of exponential, de Vaucouleurs, bulge+disc, Sersic and "
                         "knotty galaxies (default PrecisionSpec's)")
    pv.add_argument("--scheduler", help="dask.distributed scheduler address")
    pv.add_argument("--true-prior", action="store_true",
                    help="diagnostic: use the population's true prior instead of estimating "
                         "it from the calibration sample")  # fmt: skip
    pv.add_argument("--true-size-prior", action="store_true",
                    help="diagnostic: use the population's own size prior per PSF "
                         "(log-uniform over the sizes drawn) instead of estimating it")
    pv.add_argument("--flux-bounds", action=argparse.BooleanOptionalAction, default=True,
                    help="bound the flux prior at each PSF's flux range, estimated from the "
                         "calibration sample's fluxes and their errors (default; "
                         "--no-flux-bounds: the unbounded power law)")  # fmt: skip
    pv.add_argument("--e-refine", type=int, default=1, metavar="K",
                    help="adaptive refinement of the e grid (Config.e_refine): the narrow "
                         "likelihoods evaluated again on cells K times finer about their "
                         "peak (1: none; 2 costs about 50 %% more fit time)")  # fmt: skip
    pv.add_argument("--one-size-prior", action="store_true",
                    help="diagnostic: one size prior for all PSFs instead of one per PSF "
                         "(the population's sizes are drawn relative to each PSF's)")  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="pylensfit", description=__doc__.replace("\n::\n", "", 1),
                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("-v", "--verbose", action="count", default=0, help="more logging")
    sub = p.add_subparsers(dest="command", required=True)

    m = sub.add_parser("measure", help="FITS images in, shear catalogue out")
    m.add_argument("images", nargs="+", help="FITS images (WEIGHT and MASK HDUs used if present)")
    m.add_argument("--stars", nargs="+", default=[], help="separate star-field images")
    m.add_argument("--weights", nargs="+", help="weight (inverse variance) maps, one per image")
    m.add_argument("--masks", nargs="+", help="mask maps (non-zero = bad), one per image")
    m.add_argument("--catalogues", nargs="+", help="input catalogues instead of detection")
    m.add_argument("--star-column", help="catalogue column marking the PSF stars")
    m.add_argument("--config", help="YAML configuration (see `pylensfit config`)")
    m.add_argument("--prior", help="a saved prior (default: estimated from the run)")
    m.add_argument("--size-prior", help="a saved size prior (JSON, SizePrior.save); default "
                                        "the config's size_prior: flat, or estimated from the run")
    m.add_argument("--priors", help="every prior, saved (JSON, Priors.save, or an earlier "
                   "run's): measured once under them; default: estimated from the run")
    m.add_argument("-o", "--output", required=True, help="output catalogue (FITS)")
    m.add_argument("--psf-dir", help="write each image's PSF and star diagnostics here")
    m.add_argument("--psf", nargs="+", help="the PSF instead of stacking stars: a FITS image "
                   "(pixel response included, centred on pixel [n//2, n//2]; a --psf-dir "
                   "file will do) or a PSF model over the field (a Piff file, *.piff, with "
                   "the piff extra; a polynomial model from --psf-dir), for every image or "
                   "one per image")  # fmt: skip
    m.add_argument("--overwrite", action="store_true", help="replace an existing output")
    m.add_argument("--jobs", type=_jobs, default=1, help="local worker processes")
    m.add_argument("--scheduler", help="dask.distributed scheduler address")
    m.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    m.set_defaults(func=_measure)

    _add_prior_parser(sub)

    sh = sub.add_parser("shear", help="shear per image and bin, with errors")
    sh.add_argument("catalogs", nargs="+", help="catalogues from `pylensfit measure`")
    sh.add_argument("--prior", help="prior file (default: the catalogue's own)")
    sh.add_argument("--bin-by", type=_bin_by, metavar="COLUMN:EDGES",
                    help="also bin by a column, e.g. mag:20,22,24")  # fmt: skip
    sh.add_argument("--sensitivity", choices=("exact", "paper"), help="sensitivity formula")
    sh.add_argument("--estimator", choices=("fixed-point", "key2"), default="fixed-point",
                    help="the sheared-prior fixed point (default), exact to all orders in g, "
                    "or Kitching et al. (2008)'s mean shear over mean sensitivity (docs: method, "
                    "eq-key2), high by a factor 1 + |g|^2")  # fmt: skip
    sh.add_argument("--weighted", action="store_true",
                    help="weight the galaxies by the catalogue's weight column (default: "
                    "equal weights, within 1%% of the same error for posterior means)")
    sh.add_argument("--no-per-image", action="store_true", help="only bins and the total")
    sh.add_argument("-o", "--output", help="write the table (format from the extension)")
    sh.set_defaults(func=_shear)

    si = sub.add_parser(
        "simulate", add_help=False, help="simulate a STEP-like set (simulate -h for more)"
    )
    si.add_argument("args", nargs=argparse.REMAINDER)
    si.set_defaults(func=_simulate)

    v = sub.add_parser("validate", help="m, c, sigma_c and Q on a simulated set")
    v.add_argument("directory", nargs="?", help="a set from `pylensfit simulate`")
    v.add_argument("--config", help="YAML configuration (default: Config(), what `pylensfit "
                   "measure` uses; see `pylensfit config`)")
    v.add_argument("--jobs", type=_jobs, default=1, help="local worker processes")
    v.add_argument("--estimator", choices=("fixed-point", "key2"), default="fixed-point",
                   help="shear estimator: the fixed point (default) or the paper's mean shear "
                        "over mean sensitivity (docs: method, eq-key2), "
                        "whose +g^2 term shows at STEP's shears of up to 0.1")
    v.add_argument("--report", help="write a Markdown report (and a PNG beside it)")
    v.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    v.add_argument("--remeasure", action="store_true",
                   help="measure again even if DIR/measured/ holds catalogues made with this "
                        "configuration")  # fmt: skip
    v.add_argument("--true-psf", action="store_true",
                   help="diagnostic: fit with the set's true PSFs instead of the PSFs stacked "
                        "from its stars (a PSF varying over the field: each galaxy with its "
                        "own; catalogues kept in DIR/measured_true_psf/)")
    v.add_argument("--psf-models", nargs="+", metavar="FILE",
                   help="one PSF model file per PSF of the set, in its order (a .piff file, "
                        "a polynomial model, a PSF image), instead of the models made from "
                        "its star fields (catalogues kept in DIR/measured_psf_models/)")
    v.add_argument("--truth-control", action="store_true",
                   help="take the truth's shape noise out of each image's or group's shear "
                        "(the true sheared ellipticities' departure from the shear, of "
                        "expectation zero, as a control variate): the same m and c, smaller "
                        "errors")
    v.add_argument("--bins", type=int, default=4,
                   help="equal-count bins of magnitude, S/N and size (0: none)")
    v.add_argument("--quick", action="store_true",
                   help="simulate small STEP1 and STEP2 sets and validate both (< 10 min with "
                        "--jobs 2; output in --out, default quick_validation)")  # fmt: skip
    _add_precision_args(v)
    cv = v.add_argument_group("convergence study (paper Figure 2), no directory needed")
    cv.add_argument("--convergence", action="store_true",
                    help="<e>, <e^2> and sensitivity against de, dr, r_max and a catalogue "
                         "offset on a GalSim sample (--ngal, --seed)")  # fmt: skip
    cv.add_argument("--out", help="with --convergence (convergence.png/.ecsv/.md) or --quick: "
                    "output directory")  # fmt: skip
    v.set_defaults(func=_validate)

    c = sub.add_parser("config", help="print or write the default configuration (YAML)")
    c.add_argument("-o", "--output", help="write to this file")
    c.add_argument("--preset", default="default",
                   help="a named configuration: " + ", ".join(
                       f"'{k}' ({v[1]})" for k, v in PRESETS.items()))
    c.set_defaults(func=_dump_config)

    d = sub.add_parser("demo", help="simulate a small field with GalSim and run everything")
    d.add_argument("--size", type=int, default=1024, help="field side in pixels")
    d.add_argument("--g1", type=float, default=0.04, help="true shear g1")
    d.add_argument("--g2", type=float, default=-0.02, help="true shear g2")
    d.add_argument("--seed", type=int, default=1, help="random seed")
    d.add_argument("--jobs", type=_jobs, help="local worker processes (default: the "
                   "machine's cores, at most 2: one per image)")
    d.add_argument("--outdir", help="keep the files here (default: a temporary folder, "
                   "removed at the end)")
    d.set_defaults(func=_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``pylensfit`` command."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["simulate"]:  # its own parser (pylensfit.validation.main)
        argv = ["simulate", "--", *argv[1:]]
    args = build_parser().parse_args(argv)
    if getattr(args, "bin_by", None):
        args.bin_column, args.bin_edges = args.bin_by
    else:
        args.bin_column, args.bin_edges = None, None
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(asctime)s %(name)s %(levelname)s: %(message)s",
    )
    try:
        return args.func(args)
    except (OSError, ValueError) as err:
        print(f"pylensfit: error: {err}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
