"""Command-line interface: a thin layer over the public API.

::

    pylensfit calibrate IMAGE... [--stars STARFIELD...] [--config FILE] [--sample N]
        [--seed S] -o PRIORS   # every prior, once, on a sample of the images
    pylensfit measure IMAGE... [--stars STARFIELD...] [--config FILE] [--priors PRIORS] -o OUT
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
import json
import logging
import sys
from importlib.metadata import entry_points
from pathlib import Path
from typing import NoReturn

import numpy as np
from astropy.table import Table, vstack

from .catalogue import METACAL_COLUMNS
from .config import PRESETS, Config
from .images import (
    InputError,
    calibrate_images,
    catalogue_frame,
    measure,
    measure_exposures,
    read_catalogue,
)
from .prior import RadialPrior, estimate_prior
from .shear import shapes, shear_table
from .skyframe import sensitivity_to_sky, to_sky

__all__ = ["COMMANDS_GROUP", "build_parser", "main", "worker_count"]

#: The entry-point group through which an installed package adds subcommands to the
#: ``pylensfit`` command: each entry point names a callable that takes the command's
#: subparsers (``argparse``'s ``add_subparsers()`` object) and adds one subcommand whose
#: ``func`` default runs it (``args -> exit status``). A subcommand whose parser has the
#: default ``pass_through=True`` is handed the rest of the command line as ``args.args``.
#: The validation harness (``pylensfit_validation``) adds ``simulate``, ``validate`` and
#: ``demo`` this way.
COMMANDS_GROUP = "pylensfit.commands"

log = logging.getLogger("pylensfit")


def _config(args: argparse.Namespace):
    return Config.from_yaml(args.config) if getattr(args, "config", None) else Config()


def _measure_exposures(args: argparse.Namespace, cfg: Config) -> int:
    """``measure --exposures``: the images are exposures of one field, fitted jointly."""
    for opt in ("weights", "masks", "star_column", "prior", "size_prior", "psf_dir",
                "scheduler"):
        if getattr(args, opt):
            raise InputError(f"--{opt.replace('_', '-')} is not an option of measure "
                             "--exposures (each exposure's WEIGHT HDU is read; priors: "
                             "--priors)")  # fmt: skip
    if args.catalogues and len(args.catalogues) != 1:
        raise InputError("measure --exposures: give one catalogue of sky positions (ra, dec)")
    cat = measure_exposures(
        args.images, stars=args.stars or None,
        catalogue=args.catalogues[0] if args.catalogues else None, psf=_psf_arg(args.psf),
        priors=args.priors, config=cfg, output=args.output, overwrite=args.overwrite)  # fmt: skip
    ok = np.asarray(cat["weight"]) > 0
    k = float(np.median(cat["n_exposures"][ok])) if ok.any() else 0.0
    print(f"{args.output}: {len(cat)} objects on {len(args.images)} exposures, "
          f"{int(ok.sum())} galaxies measured (median {k:g} exposures each); "
          f"{cat.meta['priors']!r}")  # fmt: skip
    return 0


def _measure(args: argparse.Namespace) -> int:
    cfg = _config(args)
    if args.response is not None:
        cfg = cfg.replace(response=args.response)
    if args.exposures:
        return _measure_exposures(args, cfg)
    cat = measure(
        args.images, stars=args.stars, weights=args.weights, masks=args.masks,
        catalogues=args.catalogues, star_column=args.star_column, config=cfg,
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


def _calibrate(args: argparse.Namespace) -> int:
    out = Path(args.output)
    if out.exists() and not args.overwrite:
        raise FileExistsError(f"{out}: output exists (use --overwrite to replace it)")
    priors = calibrate_images(
        args.images, stars=args.stars, weights=args.weights, masks=args.masks,
        catalogues=args.catalogues, star_column=args.star_column, config=_config(args),
        prior=args.prior, size_prior=args.size_prior, psf=_psf_arg(args.psf),
        sample=args.sample, seed=args.seed, jobs=args.jobs, scheduler=args.scheduler,
        progress=not args.quiet)  # fmt: skip
    priors.save(out)
    print(f"{out}: {priors!r}, from {len(priors.info['sample_images'])} of "
          f"{priors.info['images']} images")  # fmt: skip
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


def _metacal_shear(args: argparse.Namespace) -> Table:
    """``shear --estimator metacal``'s table: the metacalibration's estimator with the
    selection response on the catalogue's metacalibration columns (sky frame)."""
    per_image = () if args.no_per_image else ("image",)
    cat = _read_catalogues(args.catalogs, need=("flags", *METACAL_COLUMNS, *per_image),
                           bin_column=args.bin_column)  # fmt: skip
    if args.weighted:
        raise ValueError("--estimator metacal weighs every selected galaxy equally: drop "
                         "--weighted")  # fmt: skip
    return shear_table(cat, by=None if args.no_per_image else "image",
                       column=args.bin_column, edges=args.bin_edges, estimator="metacal",
                       min_snr=args.min_snr)  # fmt: skip


def _print_shear(tab: Table, output: str | None) -> int:
    for c in ("g1", "g2"):
        tab[c].format = "+.5f"
    for c in ("g1_err", "g2_err"):
        tab[c].format = ".5f"
    tab.pprint_all()
    if output:
        tab.write(output, overwrite=True)
    return 0


def _measured_response(path: str) -> str | None:
    """The ``Config.response`` a catalogue was measured with (its ``CONFIG`` HDU), None
    where it cannot be read (reading the catalogue then says why)."""
    from astropy.io import fits  # only the small CONFIG HDU, before the catalogue is read

    try:
        with fits.open(path, memmap=True) as h:
            t = h["CONFIG"].data
            vals = {str(k): str(v) for k, v in zip(t["key"], t["value"], strict=True)}
            return str(json.loads(vals.get("response", '"model"')))
    except (OSError, KeyError, TypeError, ValueError, IndexError):  # JSONDecodeError too
        return None


def _shear(args: argparse.Namespace) -> int:
    if args.estimator is None:  # the one the catalogue's measurement was made for
        metacal = _measured_response(args.catalogs[0]) == "metacal"
        args.estimator = "metacal" if metacal else "fixed-point"
        if metacal:
            print(f"{args.catalogs[0]} was measured with --response metacal: the "
                  "metacalibration's estimator (--estimator fixed-point for the model's)")
    if args.estimator == "metacal":
        return _print_shear(_metacal_shear(args), args.output)
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
    return _print_shear(tab, args.output)


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


def worker_count(text: str) -> int:
    """The ``type`` of a ``--jobs N`` option: a positive number of worker processes.

    Parameters
    ----------
    text : str
        The option's value as typed.

    Returns
    -------
    int
        The number, at least 1.

    Raises
    ------
    argparse.ArgumentTypeError
        If ``text`` is not a positive integer (the parser reports it in one line).
    """
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


def _add_image_arguments(m: argparse.ArgumentParser) -> None:
    """The arguments that ``measure`` and ``calibrate`` share: the images and the run."""
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
    m.add_argument("--psf", nargs="+", help="the PSF instead of stacking stars: a FITS image "
                   "(pixel response included, centred on pixel [n//2, n//2]; a --psf-dir "
                   "file will do) or a PSF model over the field (a Piff file, *.piff, with "
                   "the piff extra; a polynomial model from --psf-dir), for every image or "
                   "one per image")  # fmt: skip
    m.add_argument("--overwrite", action="store_true", help="replace an existing output")
    m.add_argument("--jobs", type=worker_count, default=1, help="local worker processes")
    m.add_argument("--scheduler", help="dask.distributed scheduler address")
    m.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def _add_calibrate_parser(sub) -> None:
    """The ``calibrate`` command's parser."""
    c = sub.add_parser("calibrate", help="every prior, once, on a sample of the images")
    _add_image_arguments(c)
    c.add_argument("--sample", type=int, help="objects of the images drawn for the sample "
                   "(default the config's calibration_sample, 20000; 0: every image)")
    c.add_argument("--seed", type=int, help="seed of the draw (default the config's "
                   "calibration_seed)")  # fmt: skip
    c.add_argument("-o", "--output", required=True, help="the priors (JSON, for "
                   "`pylensfit measure --priors`)")  # fmt: skip
    c.set_defaults(func=_calibrate)


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


def build_parser() -> argparse.ArgumentParser:
    """The ``pylensfit`` command's parser, with the subcommands of every installed package
    that adds some through the entry-point group :data:`COMMANDS_GROUP`.

    Returns
    -------
    argparse.ArgumentParser
        The parser; its ``commands`` attribute is its subparsers, ``commands.choices``
        the subcommands by name.
    """
    p = _Parser(prog="pylensfit", description=__doc__.replace("\n::\n", "", 1),
                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("-v", "--verbose", action="count", default=0, help="more logging")
    sub = p.add_subparsers(dest="command", required=True)

    _add_calibrate_parser(sub)
    m = sub.add_parser("measure", help="FITS images in, shear catalogue out")
    _add_image_arguments(m)
    m.add_argument("--priors", help="every prior, saved (JSON, `pylensfit calibrate`, "
                   "Priors.save, or an earlier run's): the images measured in one pass under "
                   "them; default: estimated from the run (Config.calibration_sample)")
    m.add_argument("-o", "--output", required=True, help="output catalogue (FITS)")
    m.add_argument("--psf-dir", help="write each image's PSF and star diagnostics here")
    m.add_argument("--response", choices=("model", "metacal"), help="Config.response: "
                   "'metacal' also measures each galaxy's response on itself "
                   "(metacalibration, with the selection response's columns; five more fits "
                   "of each galaxy); default the configuration's ('model')")  # fmt: skip
    m.add_argument("--exposures", action="store_true", help="the images are exposures of "
                   "one field (each with its WCS, WEIGHT HDU and MAGZP zero point): every "
                   "galaxy fitted jointly on all the exposures that hold it; --stars: one star "
                   "field per exposure (default each exposure's own stars); --catalogues: one "
                   "catalogue of sky positions, ra and dec in degrees (default detection on "
                   "a co-add made for it)")  # fmt: skip
    m.set_defaults(func=_measure)

    _add_prior_parser(sub)

    sh = sub.add_parser("shear", help="shear per image and bin, with errors")
    sh.add_argument("catalogs", nargs="+", help="catalogues from `pylensfit measure`")
    sh.add_argument("--prior", help="prior file (default: the catalogue's own)")
    sh.add_argument("--bin-by", type=_bin_by, metavar="COLUMN:EDGES",
                    help="also bin by a column, e.g. mag:20,22,24")  # fmt: skip
    sh.add_argument("--sensitivity", choices=("exact", "paper"), help="sensitivity formula")
    sh.add_argument("--estimator", choices=("fixed-point", "key2", "metacal"),
                    help="the sheared-prior fixed point, exact to all orders in g, "
                    "Kitching et al. (2008)'s mean shear over mean sensitivity (docs: method, "
                    "eq-key2), high by a factor 1 + |g|^2, or (a catalogue measured with "
                    "--response metacal) the metacalibration's <R_gamma + R_S>^-1 <e_mcal>, "
                    "its cut made on each sheared image's S/N and fit (the selection "
                    "response, R_S). Default: metacal for a catalogue measured with "
                    "--response metacal, else fixed-point")  # fmt: skip
    sh.add_argument("--min-snr", type=float, help="--estimator metacal: the S/N cut on each "
                    "metacalibration image's mcal_snr_* (default the catalogue's "
                    "Config.min_snr)")  # fmt: skip
    sh.add_argument("--weighted", action="store_true",
                    help="weight the galaxies by the catalogue's weight column (default: "
                    "equal weights, within 1%% of the same error for posterior means)")
    sh.add_argument("--no-per-image", action="store_true", help="only bins and the total")
    sh.add_argument("-o", "--output", help="write the table (format from the extension)")
    sh.set_defaults(func=_shear)

    c = sub.add_parser("config", help="print or write the default configuration (YAML)")
    c.add_argument("-o", "--output", help="write to this file")
    c.add_argument("--preset", default="default",
                   help="a named configuration: " + ", ".join(
                       f"'{k}' ({v[1]})" for k, v in PRESETS.items()))
    c.set_defaults(func=_dump_config)

    # the installed packages' subcommands (the validation harness's simulate, validate, demo)
    for ep in sorted(entry_points(group=COMMANDS_GROUP), key=lambda e: e.name):
        ep.load()(sub)
    p.commands = sub
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``pylensfit`` command.

    Parameters
    ----------
    argv : list of str, optional
        The arguments (default ``sys.argv[1:]``).

    Returns
    -------
    int
        The exit status: 0 on success, 1 on an error reported in one line.
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    command = parser.commands.choices.get(argv[0]) if argv else None
    if command is not None and command.get_default("pass_through"):
        argv = [argv[0], "--", *argv[1:]]  # the rest of the line is the command's own
    args = parser.parse_args(argv)
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
