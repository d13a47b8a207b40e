"""The ``pylensfit`` commands of the validation harness: ``simulate``, ``validate`` and
``demo``.

They reach the ``pylensfit`` command through the entry-point group
:data:`pylensfit.cli.COMMANDS_GROUP` (``pylensfit.commands`` in ``pyproject.toml``):
each entry point names one of :func:`add_simulate`, :func:`add_validate` and
:func:`add_demo`, which adds its subcommand to the command's parser. The simulation and
validation modules load only when their command runs.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from pylensfit import Config, measure
from pylensfit.cli import worker_count
from pylensfit.runner import available_cores
from pylensfit.shear import shear_table

__all__ = ["add_demo", "add_simulate", "add_validate", "simulate_main"]


def _config(args: argparse.Namespace) -> Config:
    return Config.from_yaml(args.config) if getattr(args, "config", None) else Config()


def _simulate(args: argparse.Namespace) -> int:
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


def _validate_dither(args: argparse.Namespace) -> int:
    """``pylensfit validate --dither SET...``."""
    from .dither_validate import validate_dither  # start-up cost: only for this command

    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
    res = validate_dither(args.dither, config=_config(args), out=args.out)
    for what, t in (("shear per set", res.shears), ("m and c", res.bias),
                    ("PSF of each exposure against its truth", res.psf)):
        print(f"\n{what}:")
        t = t.copy()
        for c in t.colnames:
            if t[c].dtype.kind == "f":
                t[c].info.format = ".4g"
        t.pprint_all()
    return 0


def _validate(args: argparse.Namespace) -> int:
    from .validate import validate  # start-up cost: only for this command

    if args.precision:
        return _precision(args)
    if args.dither:
        return _validate_dither(args)
    if args.convergence:
        return _convergence(args)
    cfg = _config(args) if args.config else None
    bins = {k: args.bins for k in ("mag", "snr", "size")} if args.bins > 0 else {}
    if args.quick:
        from .quick import quick_validation  # start-up cost: only for this command

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
    from .reports import nan_note  # start-up cost: only for this command

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


def add_simulate(sub) -> None:
    """Add ``pylensfit simulate`` (its own parser, :func:`simulate_main`) to ``sub``, the
    ``pylensfit`` command's subparsers."""
    si = sub.add_parser(
        "simulate", add_help=False, help="simulate a STEP-like set (simulate -h for more)"
    )
    si.add_argument("args", nargs=argparse.REMAINDER)
    si.set_defaults(func=_simulate, pass_through=True)


def add_validate(sub) -> None:
    """Add ``pylensfit validate`` to ``sub``, the ``pylensfit`` command's subparsers."""
    v = sub.add_parser("validate", help="m, c, sigma_c and Q on a simulated set")
    v.add_argument("directory", nargs="?", help="a set from `pylensfit simulate`")
    v.add_argument("--config", help="YAML configuration (default: Config(), what `pylensfit "
                   "measure` uses; see `pylensfit config`)")
    v.add_argument("--jobs", type=worker_count, default=1, help="local worker processes")
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
    dv = v.add_argument_group("dithered exposures, fitted jointly (no directory needed)")
    dv.add_argument("--dither", nargs="+", metavar="SET",
                    help="sets from `pylensfit simulate dither` of one --seed that differ by "
                         "their --shear: m and c of the joint fit (measure --exposures) and of "
                         "one exposure alone, and each exposure's PSF against its truth "
                         "(catalogues in --out)")  # fmt: skip
    _add_precision_args(v)
    cv = v.add_argument_group("convergence study (paper Figure 2), no directory needed")
    cv.add_argument("--convergence", action="store_true",
                    help="<e>, <e^2> and sensitivity against de, dr, r_max and a catalogue "
                         "offset on a GalSim sample (--ngal, --seed)")  # fmt: skip
    cv.add_argument("--out", help="with --convergence (convergence.png/.ecsv/.md) or --quick: "
                    "output directory")  # fmt: skip
    v.set_defaults(func=_validate)


def add_demo(sub) -> None:
    """Add ``pylensfit demo`` to ``sub``, the ``pylensfit`` command's subparsers."""
    d = sub.add_parser("demo", help="simulate a small field with GalSim and run everything")
    d.add_argument("--size", type=int, default=1024, help="field side in pixels")
    d.add_argument("--g1", type=float, default=0.04, help="true shear g1")
    d.add_argument("--g2", type=float, default=-0.02, help="true shear g2")
    d.add_argument("--seed", type=int, default=1, help="random seed")
    d.add_argument("--jobs", type=worker_count, help="local worker processes (default: the "
                   "machine's cores, at most 2: one per image)")
    d.add_argument("--outdir", help="keep the files here (default: a temporary folder, "
                   "removed at the end)")
    d.set_defaults(func=_demo)


def _simulate_parser() -> argparse.ArgumentParser:
    """``pylensfit simulate``'s parser (:func:`simulate_main`)."""
    from .simulate import POPULATIONS, PSF_VARIATIONS  # start-up cost: only for simulate

    p = argparse.ArgumentParser(
        prog="pylensfit simulate",
        description="simulate a STEP1/STEP2-like validation set or dithered exposures"
    )
    p.add_argument("kind", choices=["step1", "step2", "dither"],
                   help="a STEP1- or STEP2-like set, or dithered exposures of one patch")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--ngal", type=int, default=None,
                   help="galaxies over the shear fields (default 20000; dither: galaxies on "
                        "the patch, default 400)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--noise", type=float, default=1.0, help="noise sigma per pixel")
    p.add_argument("--size", type=int, default=None, help="field size (px)")
    p.add_argument("--nshear", type=int, default=None, help="shear values per PSF")
    p.add_argument("--star-field-size", type=int, default=None,
                   help="side of the star fields (px; default the shear fields')")
    p.add_argument("--twins", action=argparse.BooleanOptionalAction, default=None,
                   help="a 90-degree-rotated twin of every shear field (default: step2 "
                        "yes, step1 no); with twins the shape noise cancels in validate")
    p.add_argument("--jobs", type=int, default=1, help="fields rendered in parallel")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--noise-twins", action="store_true",
                   help="a noise twin of every shear field (the same noise negated): the "
                        "noise's first-order effect cancels in validate, resolving c per "
                        "PSF to ~1e-4; --ngal counts the renderings")
    p.add_argument("--psf-variation", choices=sorted(PSF_VARIATIONS), default="none",
                   help="PSF variation over every field, star fields included (survey: "
                        "FWHM +-10%% and |e| up to 0.08 corner to corner)")
    p.add_argument("--wcs-rotation", type=float, default=0.0, metavar="DEG",
                   help="rotation of every field's WCS, pixel to sky (degrees); the "
                        "shears are the sky frame's")
    p.add_argument("--wcs-flip", action="store_true",
                   help="flip every field's WCS (dy -> -dy before the rotation)")
    p.add_argument("--spacing", type=float, default=40.0,
                   help="step1, step2: pitch of the objects' lattice (px, default 40); a wider "
                        "one keeps the neighbours' light out of the stamps")
    p.add_argument("--shear-positions", action="store_true",
                   help="step1, step2: shear the galaxies' positions too, about each field's "
                        "centre (the lensed sky: each galaxy's neighbours move with the shear)")
    p.add_argument("--population", choices=POPULATIONS, default="aligned",
                   help="step2 galaxies: aligned (bulges aligned with their discs, Sersic "
                        "n 0.5-4) or realistic (bulges of their own size, shape and "
                        "misalignment, Sersic n 0.3-6; step1: aligned only)")
    p.add_argument("--exposures", type=int, default=None, metavar="K",
                   help="dither: exposures of the patch (default 5; surveys take 3-8), "
                        "each with its own pointing, WCS, PSF, noise and zero point")
    p.add_argument("--shear", type=float, nargs=2, default=None, metavar=("G1", "G2"),
                   help="dither: the shear of the patch, sky frame (default 0 0); sets of "
                        "the same --seed differ only by it (the same galaxies and noise)")
    return p


def _simulate_dither(a: argparse.Namespace) -> int:
    """``pylensfit simulate dither``: :func:`pylensfit_validation.dither.simulate_dither`."""
    from .dither import DitherSpec, read_dither, simulate_dither  # start-up cost: this command

    kw = {"n_exposures": 5 if a.exposures is None else a.exposures, "noise_sigma": a.noise}
    if a.shear is not None:
        kw["g1"], kw["g2"] = a.shear
    if a.ngal is not None:
        kw["ngal"] = a.ngal
    if a.star_field_size:
        kw["star_field_size"] = a.star_field_size
    s = read_dither(simulate_dither(a.out, DitherSpec(**kw), seed=a.seed))
    print(f"dither: {len(s.exposures)} exposures of {s.spec.image_size} px, {len(s.truth)} "
          f"galaxies (truth in sky coordinates: {s.directory / 'truth.fits'}), a star field "
          f"per exposure -> {s.directory}")  # fmt: skip
    return 0


def simulate_main(argv: list[str] | None = None) -> int:
    """``pylensfit simulate step1|step2|dither --out DIR [--ngal N] [--seed S] ...``.

    Among the options, ``--psf-variation {none,survey}``, ``--wcs-rotation DEG``,
    ``--wcs-flip``, ``--population {aligned,realistic}`` and ``--shear-positions``
    (:func:`simulate_step`'s ``psf_variation``, ``wcs_rotation_deg``, ``wcs_flip``,
    ``population``, ``shear_positions``);
    ``dither --exposures K`` writes ``K`` dithered exposures of one patch
    (:func:`pylensfit_validation.dither.simulate_dither`; ``--ngal``, ``--seed``,
    ``--noise``, ``--star-field-size`` apply).

    The ``simulate`` command's own parser, handed the rest of the command line.

    Parameters
    ----------
    argv : list of str, optional
        Arguments (default ``sys.argv[1:]``).

    Returns
    -------
    int
        Exit status.
    """
    from .step import read_manifest, simulate_step  # start-up cost: only for this command

    p = _simulate_parser()
    a = p.parse_args(argv)
    if a.kind == "dither":
        return _simulate_dither(a)
    if a.exposures is not None or a.shear is not None:
        p.error("--exposures and --shear are options of the dither kind")
    if a.ngal is None:
        a.ngal = 20000
    d = simulate_step(
        a.kind,
        a.out,
        ngal=a.ngal,
        seed=a.seed,
        noise_sigma=a.noise,
        field_size=a.size,
        n_shear=a.nshear,
        star_field_size=a.star_field_size,
        twins=a.twins,
        noise_twins=a.noise_twins,
        psf_variation=a.psf_variation,
        wcs_rotation_deg=a.wcs_rotation,
        wcs_flip=a.wcs_flip,
        population=a.population,
        shear_positions=a.shear_positions,
        spacing=a.spacing,
        jobs=a.jobs,
        progress=not a.quiet,
    )
    man = read_manifest(d)
    n_shear = sum(f["role"] == "shear" for f in man["fields"])
    got = man["ngal_shear_fields"]
    why = ("" if got == a.ngal else f" (--ngal {a.ngal} rounded to {n_shear} fields of a "
           f"whole square lattice of objects each)")  # fmt: skip
    print(
        f"{a.kind}: {len(man['fields'])} fields of {man['field_size']} px, "
        f"{got} galaxies in shear fields{why}, "
        f"{len(man['star_fields'])} star fields -> {d}"
    )
    return 0
