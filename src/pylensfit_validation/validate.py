"""``validate``: m, c, sigma_c and Q of a simulated set, per PSF and per bin, with the
diagnostics of its PSFs and priors."""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from astropy.table import Table, vstack

from pylensfit.config import Config
from pylensfit.prior import (
    Prior,
    estimate_prior,
    estimate_prior_and_bulge,
    mix_bulge_fractions,
)
from pylensfit.psf import PSFResult, psf_diagnostics, psf_from_image
from pylensfit.psfmodel import PSFModel
from pylensfit.shear import shapes

from .estimates import (
    BIN_COLUMNS,
    bins_table,
    check_frame,
    matched_galaxies,
    mc_rows,
    measured_catalogues,
    prior_check,
    set_frame,
    shapes_to_sky,
    shear_estimates,
)
from .galaxies import PSFProfile
from .reports import write_report
from .simulate import (
    map_psf_model,
)
from .stats import (
    BIN_LABELS,
    DEFAULT_BINS,
    MC_COLUMNS,
    MORPHOLOGY_EDGES,
    PSF_HELDOUT_TARGET,
    TARGETS,
    leakage_table,
    mc_summary,
    nanmean,
    quantile_edges,
    shear_groups,
)
from .step import read_manifest, spec_for

__all__ = [
    "step_config",
    "true_psf_image",
    "validate",
]


def step_config(n_bulge_fractions: int = 5) -> Config:
    """``Config()`` with ``n_bulge_fractions`` bulge fractions (the default's three, or five).

    The bulge+disc model (bulge half-light radius 0.6 disc scale lengths) with its bulge
    fraction marginalised over ``n_bulge_fractions`` values evenly spaced on [0, 1], every
    prior estimated by the calibration recipe on the zero-shear fields.

    * Five fractions rather than three take 0.004 off STEP2's ``<m>``: -0.0042 +- 0.0020
      (m1) and -0.0043 +- 0.0021 (m2), paired on the same 100,000-galaxy set, for about
      a third more time. The Sersic and bulge+disc galaxies gain; the knotty discs do not.
    * The estimated size prior: with the flat one, STEP1's ``<m>`` is higher by about
      0.01 and STEP2's by 0.011.

    Measurements in ``benchmarks/README.md``. The quick tier
    (:func:`quick_validation`) uses three fractions, to stay within its 10 minutes.
    """
    return Config(n_bulge_fractions=n_bulge_fractions)


def validate(directory: str | Path, *, config=None, jobs: int = 1, estimator: str = "fixed-point",
             report: str | Path | None = None, progress: bool = True, remeasure: bool = False,
             bins: dict[str, int | Sequence[float]] | None = None, bin_min_count: int = 300,
             true_psf: bool = False, truth_control: bool = False,
             psf_models: Mapping[int, str | os.PathLike] | None = None):  # fmt: skip
    """Run the pipeline on a simulated set and measure m, c, sigma_c and Q per PSF and bin.

    1. **Measure** each PSF's zero-shear (prior) fields and its shear fields with its own
       star field, keeping the catalogues in ``DIR/measured/psf{k}_prior.fits`` and
       ``psf{k}_shear.fits`` (with ``.json`` sidecars recording the configuration and the
       fields' seeds). A later call with the same configuration reuses them, so a large set
       is re-analysed (other estimator, other bins) without re-measuring;
       ``remeasure=True`` forces a new measurement. With ``size_prior: estimated`` the
       size prior is estimated on each PSF's zero-shear field and the shear fields are
       measured with it (recorded in their sidecars), as the ellipticity prior comes
       from the zero-shear fields.
    2. **Match** every usable galaxy (``flags == 0``, ``fitclass == 0``) to the truth of
       its image (nearest truth object within 5 px), for the diagnostics, the pairing of
       the twins and the truth control variate only: every usable row enters the shear,
       matched or not, as in a survey.
    3. **Prior** from the galaxies of the zero-shear fields of all PSFs (as in the paper).
    4. **Shear** per image (the mean shear over mean sensitivity, docs: method, eq-key2,
       or the sheared-prior fixed point, eq-fixed-point,
       ``estimator``). For STEP2-like sets, each image and its 90-degree-rotated twin are
       combined galaxy by galaxy (the galaxies measured in every member are summed over
       the members, which cancels their shape noise; every other usable detection of the
       group's images enters on its own); these group estimates enter the fits and Q,
       the single-image ones are kept in ``meta``. The bins use the matched galaxies.
    5. **Fit** ``g_meas - g_true = m g_true + c`` per PSF and component, ``<m>``,
       ``sigma_c`` and Q (paper section 5).
    6. **Bins** (paper Table 2): the same per bin of each quantity in ``bins``, with a
       prior per bin estimated from the prior-field galaxies of that bin
       (:func:`pylensfit.prior.estimate_prior_binned`; a bin with fewer than
       ``bin_min_count`` of them uses the global prior, as noted in the table).
    7. **PSF leakage**: ``alpha`` of ``g = c + alpha e_psf`` (:func:`psf_leakage`) per
       PSF and over all PSFs, on the galaxies matched to the truth (their residuals
       from the input shear; twin groups summed), with the truth's PSF ellipticity at
       each galaxy and with the catalogue's model PSF.

    The binned quantities are those a lensing analysis would use:

    - ``"mag"``: the measured magnitude (detection flux, zeropoint 0), as the paper's
      SExtractor magnitudes; an observable, independent of the shear.
    - ``"snr"``: the measured matched-filter S/N of the best model (``model_SNratio``):
      the noise regime, where noise bias shows.
    - ``"size"``: the true size over the PSF FWHM, ``r_true / FWHM`` (the disc scale
      length for step1, the half-light radius for step2): how well a galaxy is resolved,
      from the truth as in the paper (a measured size would add the selection bias of a
      cut on the noisy fit); unmatched detections drop out of these bins only.
    - ``"morphology"``: a STEP2 galaxy's kind (Sersic, bulge+disc, knotty disc), from
      the truth: where the model family fits worst. Its prior per bin is the kind's own.

    A twin pair's bin is that of its members' mean value (it never straddles two bins).
    Bins partition the usable galaxies with a finite value.

    Parameters
    ----------
    directory : str or pathlib.Path
        A set written by :func:`simulate_step`.
    config : Config, optional
        Pipeline settings (default ``Config()``, what a user gets: every prior estimated
        per PSF on the zero-shear field by the calibration recipe; :func:`step_config`
        is the variant with five bulge fractions).
    jobs : int
        Local worker processes of :func:`pylensfit.measure`.
    estimator : {"fixed-point", "key2"}
        Shear estimator: the fixed point of :func:`pylensfit.shear_fixed_point` (default;
        for twins, that of both images together, with the error of :func:`twin_shear`),
        or the paper's mean shear over mean sensitivity (docs: method, eq-key2), whose
        ``+g^2`` term STEP's shears of up to 0.1 bring out: +0.009 in m on the 100k STEP1
        set (``benchmarks/README.md``, "What the studies found").
    report : str or pathlib.Path, optional
        Write a Markdown report here with its PNG figures beside it
        (:func:`write_report`).
    progress : bool
        Progress bars while measuring.
    remeasure : bool
        Measure again even if kept catalogues match.
    bins : dict, optional
        ``{quantity: n_bins or edges}`` for quantities ``"mag"``, ``"snr"``, ``"size"``,
        ``"morphology"`` (default :data:`DEFAULT_BINS`; ``{}`` for none). On a STEP2-like
        set, one bin per galaxy kind of :data:`STEP2_KINDS` is added unless ``bins`` is
        empty or gives ``"morphology"`` itself. An integer gives bins of equal counts of
        shear-field galaxies, the outer edges widened to every galaxy. A quantity that
        no galaxy has (``"morphology"`` on a STEP1-like set) is skipped.
    bin_min_count : int
        Fewest prior-field galaxies for a bin to get its own prior.
    true_psf : bool
        Diagnostic: fit with each PSF's true image (:func:`true_psf_image`, as large as
        the largest stamp; if the PSF varies over the field, its map
        :func:`pylensfit_validation.simulate.map_psf_model`: each galaxy with its own PSF), not the
        stars', keeping the catalogues in ``DIR/measured_true_psf/``. The difference from
        a run with the modelled PSF is what the PSF model does to m and c (same noise).
    psf_models : mapping, optional
        ``{psf index: file}`` for every PSF: its fields fitted with the model in the
        file (:func:`pylensfit.psfmodel.read_psf_model`: Piff's, a polynomial model, an
        image), not its star field's; catalogues in ``DIR/measured_psf_models/``.
    truth_control : bool
        Take the truth's shape noise out of each image's (or group's) estimate with
        :func:`truth_control_variate`: the true sheared ellipticities' departure from
        the image's shear, whose expectation is zero, as a control variate. The same m
        and c are estimated with smaller errors: a single image loses its shape noise;
        a twin group the rotation's second-order residual at large shears. What a
        selection does stays in. The per-image and per-group estimates only, not the
        bins (whose galaxies are a measured subset: the population's mean is not
        theirs).

    Returns
    -------
    astropy.table.Table
        One row per PSF and a last row ``all`` (a joint fit):
        ``m1, m1_err, c1, c1_err, m2, m2_err, c2, c2_err, Q, n_gal``. ``meta`` holds
        ``mean_m`` (over PSFs and components), ``mean_m_err`` (its error),
        ``mean_m_err_paper`` (the paper's, the mean of the PSFs' errors: Kitching et al.
        2008, section 4.2), ``sigma_c``, ``sigma_c_stat`` (what the fits' errors alone
        give), ``sigma_c_hat`` and ``sigma_c_upper`` (the offsets' own spread over PSFs
        with the noise taken out, and its 95 % upper limit: :func:`c_scatter`;
        ``c1_chi2``, ``c2_chi2``, ``c_dof``, ``c1_p``, ``c2_p`` its chi-squares), ``prior``,
        ``mode`` (``"pairs"`` or ``"images"``), ``estimates`` (the per-image or per-pair
        table the fits used), ``images`` (single-image estimates), ``pairs`` (step2),
        ``single`` (step2: the per-PSF fit table from single images), ``fits`` (per PSF and
        component, with the m-c correlation ``rho``), ``bins`` (one row per quantity, bin
        and PSF plus ``psf == "all"``, a joint fit: ``kind, bin, lo, hi, center`` (median
        value), ``n_gal`` (galaxies in the bin), ``n_used`` (in the fits: images or pairs
        with fewer than 2 galaxies or pairs in the bin drop out), ``n_prior``,
        ``prior_fallback``, ``m1 ... c2_err, Q``, ``mean_m, mean_m_err`` (over the two
        components; for ``all``, over PSFs and components as ``<m>``), ``mean_c,
        mean_c_err``), ``bin_edges``,
        ``psf_check``, ``prior_check``, ``diagnosis`` and ``measured`` (the catalogue
        paths and whether each was reused), ``psf_source`` (``"stars"`` or ``"true"``),
        ``leakage`` (the PSF leakage ``alpha`` of :func:`psf_leakage` per PSF and ``all``,
        with the true and with the model PSF: columns ``psf, source, alpha1, alpha1_err,
        alpha2, alpha2_err, c1, c1_err, c2, c2_err, n``).

        Shapes, shears and the truth are compared in the sky frame of the set's WCS
        (its manifest's ``wcs_rotation_deg`` and ``wcs_flip``): the shapes from the
        ``lnL`` grids are taken to it with the truth's ``e1_sky, e2_sky``
        (:func:`pylensfit_validation.simulate.pixel_to_sky_shear`), the fixed point solves for the
        sky-frame shear, and the manifest's shears are the sky frame's.
    """
    opts = _Options(estimator=estimator, jobs=jobs, progress=progress, remeasure=remeasure,
                    min_count=bin_min_count, true_psf=true_psf, truth_control=truth_control,
                    psf_models={int(k): Path(v) for k, v in (psf_models or {}).items()})
    man = read_manifest(directory)
    sky, bins = set_frame(man), _bin_quantities(man, bins)
    cfg = config if config is not None else Config()
    out = _analyse(man, cfg, sky, bins, opts)
    if report is not None:
        write_report(out, man, Path(report))
    return out


@dataclass(frozen=True)
class _Options:
    """:func:`validate`'s options for the analysis (the estimator checked here)."""

    estimator: str
    jobs: int
    progress: bool
    remeasure: bool
    min_count: int  # bin_min_count
    true_psf: bool
    truth_control: bool
    psf_models: dict[int, Path] = field(default_factory=dict)  # {PSF index: model file}

    def __post_init__(self) -> None:
        """Refuse an unknown estimator, or both the true PSFs and model files."""
        if self.estimator not in ("key2", "fixed-point"):
            raise ValueError(
                f"estimator must be 'key2' or 'fixed-point', got {self.estimator!r}"
            )
        if self.true_psf and self.psf_models:
            raise ValueError("true_psf and psf_models exclude each other")


def _bin_quantities(man: dict, bins: dict[str, int | Sequence[float]] | None
                    ) -> dict[str, int | Sequence[float]]:  # fmt: skip
    """:func:`validate`'s ``bins``, checked, with the galaxy kinds of a STEP2-like set."""
    bins = dict(DEFAULT_BINS if bins is None else bins)
    if bins and man.get("fieldspec", {}).get("model") == "step2":
        bins.setdefault("morphology", MORPHOLOGY_EDGES)
    for k in bins:
        if k not in BIN_LABELS:
            raise ValueError(f"unknown bin quantity {k!r}; use {sorted(BIN_LABELS)}")
    return bins


@dataclass
class _MeasuredSet:
    """A set's galaxies measured per PSF (:func:`_measure_set`)."""

    fields: dict[str, dict]  # the manifest's fields by file name
    psfs: list[int]  # the PSFs' indices, sorted
    pg: Table  # galaxies of the zero-shear (prior) fields
    sg: Table  # galaxies of the shear fields
    egrid: np.ndarray  # the ellipticity grid of the lnL grids
    measured: dict[str, dict]  # meta["measured"]: catalogue paths, whether reused
    psf_rows: list[tuple]  # rows of meta["psf_check"]
    priors_of: dict[int, Any]  # the priors estimated on each PSF's zero-shear field


def _analyse(man: dict, cfg: Config, sky: tuple[float, bool],
             bins: dict[str, int | Sequence[float]], opts: _Options) -> Table:  # fmt: skip
    """:func:`validate`'s stages after the arguments and the manifest, up to the report."""
    ms = _measure_set(man, cfg, sky, opts)
    prior, bulge_weights = _set_prior(ms, cfg)
    e_s_of = partial(_sky_shapes, egrid=ms.egrid, cfg=cfg, sky=sky)
    e, s = e_s_of(ms.sg, prior)
    pairs = any(f["twin"] or f.get("noise_twin") for f in man["fields"])
    fits = _shear_fits(ms, e, s, prior, cfg, sky, opts, pairs)
    out = Table(rows=fits.mc, names=MC_COLUMNS)
    out.meta.update(mc_summary(out[:-1]))
    out.meta["prior"] = prior
    out.meta["priors"] = [ms.priors_of[k] for k in sorted(ms.priors_of)]
    out.meta["bulge_weights"] = None if bulge_weights is None else bulge_weights.tolist()
    out.meta["bulge_runs"] = None if bulge_weights is None else cfg.run_labels
    out.meta["mode"] = "pairs" if pairs else "images"
    out.meta["estimator"] = opts.estimator
    out.meta["estimates"] = fits.pairs if pairs else fits.images
    out.meta["images"] = fits.images
    out.meta["pairs"] = fits.pairs
    out.meta["single"] = fits.single
    out.meta["fits"] = Table(rows=fits.fit_rows, names=("psf", "component", "m", "m_err", "c",
                                                        "c_err", "rho"))  # fmt: skip
    out.meta["measured"] = ms.measured
    out.meta["psf_source"] = ("true" if opts.true_psf else
                              "models" if opts.psf_models else "stars")  # fmt: skip
    out.meta["truth_control"] = bool(opts.truth_control)
    out.meta["leakage"] = leakage_table(ms.sg, e, s, ms.fields, ms.psfs, pairs)
    out.meta["bins"], out.meta["bin_edges"] = _bins(ms, pairs, bins, e_s_of, cfg, sky, opts)
    _add_diagnostics(out, ms, man, prior)
    return out


def _measure_set(man: dict, cfg: Config, sky: tuple[float, bool],
                 opts: _Options) -> _MeasuredSet:  # fmt: skip
    """Measure (or reuse the kept catalogues of) each PSF's zero-shear and shear fields."""
    fields = {f["file"]: f for f in man["fields"]}
    by_psf: dict[int, list] = {}
    for f in man["fields"]:
        by_psf.setdefault(int(f["psf"]), []).append(f)
    missing = sorted(set(by_psf) - set(opts.psf_models))
    if opts.psf_models and missing:
        raise ValueError(f"psf_models has no file for PSF {missing} of {man['dir']}")
    stars = {int(s["psf"]): s for s in man["star_fields"]}
    sub = ("measured_true_psf" if opts.true_psf else
           "measured_psf_models" if opts.psf_models else "measured")  # fmt: skip
    mdir = Path(man["dir"]) / sub
    pgs, sgs, measured, psf_rows = [], [], {}, []
    priors_of: dict = {}
    egrid = None
    for k, fl in sorted(by_psf.items()):
        fwhm = float(man["psfs"][k]["fwhm"])
        given = _true_psf(man, k, cfg.largest_stamp) if opts.true_psf else None
        if k in opts.psf_models:
            given = opts.psf_models[k]  # read by measure, as a file given to it
        for role, lst in (("prior", pgs), ("shear", sgs)):
            sel = [f for f in fl if f["role"] == role]
            if not sel:
                continue
            name = f"psf{k}_{role}"
            # the priors come from the zero-shear field by the calibration recipe (as a
            # survey's from its own galaxies): the shear fields are measured once, with them
            pr = priors_of.get(k) if role == "shear" else None
            cat, reused = measured_catalogues(name, sel, stars[k], cfg, mdir, jobs=opts.jobs,
                                    progress=opts.progress, remeasure=opts.remeasure,
                                    priors=pr, psf=given)  # fmt: skip
            check_frame(cat, sky, name)
            if role == "prior":
                priors_of[k] = cat.meta["priors"]
            measured[name] = {"path": str(mdir / f"{name}.fits"), "reused": reused}
            egrid = cat.meta["egrid"]
            lst.append(matched_galaxies(cat, fields, k, fwhm, sky))
            if role == "shear" and "psfs" in cat.meta:
                psf_rows.append(_psf_check_row(k, man["psfs"][k], cat))
    if not pgs:
        raise ValueError(f"{man['dir']}: no zero-shear (prior) field in the manifest")
    return _MeasuredSet(fields=fields, psfs=sorted(by_psf), pg=vstack(pgs), sg=vstack(sgs),
                        egrid=egrid, measured=measured, psf_rows=psf_rows,
                        priors_of=priors_of)  # fmt: skip


def _psf_check_row(k: int, psf_params: dict, cat: Table) -> tuple:
    """A row of ``meta["psf_check"]``: PSF ``k``'s true and modelled FWHM and ellipticity."""
    p = cat.meta["psfs"]
    meas = [nanmean(p[f"psf_{q}"]) for q in ("fwhm", "e1", "e2")]
    tru = _true_psf_diagnostics(psf_params)
    return (k, tru["fwhm"], tru["e1"], tru["e2"], *meas, *_heldout_pooled(p))


#: ``meta["psf_check"]``'s columns: the true and the measured PSF, and the PSF model's
#: residuals on its held-out stars pooled over the images (:func:`_heldout_pooled`).
_PSF_CHECK_NAMES = ("psf", "fwhm_true", "e1_true", "e2_true", "fwhm_meas", "e1_meas",
                    "e2_meas", "heldout_n", "heldout_rms_de1", "heldout_rms_de2",
                    "heldout_noise_de", "heldout_excess_de1", "heldout_excess_de2")  # fmt: skip


def _heldout_pooled(p: Table) -> tuple:
    """A varying PSF model's held-out stars over all images of a catalogue's ``PSFS``
    table: their number, the rms of star minus model ellipticity per component, the rms
    the stars' noise alone gives, and the excess ``sqrt(rms^2 - noise^2)`` (0 if
    negative), each pooled as ``sqrt(sum n x^2 / sum n)``; NaN without held-out stars
    (a constant PSF, or a catalogue written before the PSFS table had them). Images
    measured with one model (a star field's, or one model file for several images)
    repeat its check: each distinct check is counted once."""
    if "psf_heldout_n" not in p.colnames:
        return (0, *([math.nan] * 5))
    cols = [f"psf_heldout_{q}" for q in ("n", "mean_de1", "mean_de2", "rms_de1", "rms_de2",
                                         "noise_de") if f"psf_heldout_{q}" in p.colnames]
    keys = np.column_stack([np.nan_to_num(np.asarray(p[c], dtype=float), nan=-1.0)
                            for c in cols])  # fmt: skip
    p = p[np.sort(np.unique(keys, axis=0, return_index=True)[1])]
    n = np.nan_to_num(np.asarray(p["psf_heldout_n"], dtype=float))
    if n.sum() <= 0:
        return (0, *([math.nan] * 5))

    def pool(col: str) -> float:
        v = np.asarray(p[col], dtype=float)
        ok = (n > 0) & np.isfinite(v)
        return float(np.sqrt(np.sum(n[ok] * v[ok] ** 2) / np.sum(n[ok])))

    rms = [pool(f"psf_heldout_rms_de{i}") for i in (1, 2)]
    noise = pool("psf_heldout_noise_de")
    excess = [math.sqrt(max(r**2 - noise**2, 0.0)) for r in rms]
    return (int(n.sum()), *rms, noise, *excess)


def _set_prior(ms: _MeasuredSet, cfg: Config) -> tuple[Prior, np.ndarray | None]:
    """The ellipticity prior from the zero-shear fields' galaxies (and the bulge weights).

    With the bulge prior estimated, both samples' ``lnL`` are replaced by their mixture
    over the bulge fractions with the estimated weights (None otherwise).
    """
    pg, sg = ms.pg, ms.sg
    bulge_weights = None
    if cfg.bulge_prior == "estimated" and all("lnL_bulge" in t.colnames for t in (pg, sg)):
        # the prior over the bulge fractions with the ellipticity prior, from the prior
        # fields; both samples' L(e) mixed with it
        prior, bulge_weights = estimate_prior_and_bulge(
            np.asarray(pg["lnL_bulge"]), np.asarray(pg["lnL_star"]), ms.egrid,
            method=cfg.prior_method, form=cfg.prior_form)  # fmt: skip
        for t in (pg, sg):
            t["lnL"] = mix_bulge_fractions(np.asarray(t["lnL_bulge"]),
                                           np.asarray(t["lnL_star"]), bulge_weights)
    else:
        prior = estimate_prior(np.asarray(pg["lnL"]), ms.egrid, method=cfg.prior_method,
                               form=cfg.prior_form)  # fmt: skip
    return prior, bulge_weights


def _sky_shapes(t: Table, p: Prior, *, egrid: np.ndarray, cfg: Config,
                sky: tuple[float, bool]) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The ``(n, 2)`` ellipticities and sensitivities of ``t``'s galaxies under prior ``p``,
    in the set's sky frame."""
    if len(t) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    sh = shapes(np.asarray(t["lnL"]), egrid, p, sensitivity=cfg.sensitivity,
                refine=cfg.output_refine)  # fmt: skip
    # the lnL grids are the pixel frame's; the truth and the shears the sky frame's
    return shapes_to_sky(np.column_stack([sh["e1"], sh["e2"]]),
                   np.column_stack([sh["sens1"], sh["sens2"]]), sky)


@dataclass
class _ShearFits:
    """The shear estimates of :func:`validate` and the fits of m and c on them."""

    images: Table  # per-image estimates
    pairs: Table | None  # per-group estimates (twins), or None
    single: Table  # the per-PSF fit table from the single images
    mc: list[tuple]  # rows of the result table, from the groups if any
    fit_rows: list[tuple]  # rows of meta["fits"]


def _shear_fits(ms: _MeasuredSet, e: np.ndarray, s: np.ndarray, prior: Prior, cfg: Config,
                sky: tuple[float, bool], opts: _Options, pairs: bool) -> _ShearFits:  # fmt: skip
    """Shear per image (and per twin group if ``pairs``) and the fits of m and c per PSF."""
    kw = dict(estimator=opts.estimator, prior=prior, egrid=ms.egrid, refine=cfg.output_refine,
              truth_control=opts.truth_control, sky=sky)  # fmt: skip
    img = shear_estimates(ms.sg, e, s, ms.fields, pairs=False, **kw)
    mc, fit_rows = mc_rows(img, ms.psfs)
    single = Table(rows=mc, names=MC_COLUMNS)
    pair_tab = None
    if pairs:
        pair_tab = shear_estimates(ms.sg, e, s, ms.fields, pairs=True, **kw)
        mc, fit_rows = mc_rows(pair_tab, ms.psfs)
    return _ShearFits(images=img, pairs=pair_tab, single=single, mc=mc, fit_rows=fit_rows)


def _bins(ms: _MeasuredSet, pairs: bool, bins: dict[str, int | Sequence[float]],
          e_s_of: Callable[[Table, Prior], tuple[np.ndarray, np.ndarray]], cfg: Config,
          sky: tuple[float, bool], opts: _Options) -> tuple[Table, dict[str, np.ndarray]]:
    """``meta["bins"]`` and ``meta["bin_edges"]`` (paper Table 2).

    A twin group's value is the mean of its members'; adds a ``_bin_{kind}`` column to
    the shear fields' galaxies per binned quantity.
    """
    sg, pg = ms.sg, ms.pg
    gid = shear_groups(sg, ms.fields)[0] if pairs else np.full(len(sg), -1)
    has = gid >= 0
    bin_rows, bin_edges = [], {}
    for kind, spec in bins.items():
        v = np.asarray(sg[kind], float)
        if not np.isfinite(v).any():  # a quantity that this set's galaxies lack
            continue
        vb = v.copy()
        if has.any():
            tot = np.bincount(gid[has], weights=v[has])
            vb[has] = tot[gid[has]] / np.bincount(gid[has])[gid[has]]
        use = has if pairs else np.ones(len(sg), bool)
        sg["_bin_" + kind] = np.where(use, vb, np.nan)
        edges = quantile_edges(np.asarray(sg["_bin_" + kind]), spec, np.asarray(pg[kind], float))
        if edges.size < 2:
            continue
        bin_edges[kind] = edges
        bin_rows += bins_table(kind, edges, pg, sg, e_s_of, ms.psfs, ms.fields, pairs,
                                opts.estimator, ms.egrid, cfg, opts.min_count,
                                sky)  # fmt: skip
    return (Table(rows=bin_rows, names=BIN_COLUMNS) if bin_rows else Table()), bin_edges


def _add_diagnostics(out: Table, ms: _MeasuredSet, man: dict, prior: Prior) -> None:
    """Add the PSF models' and the prior's checks against the truth, and the diagnosis."""
    pg = ms.pg
    out.meta["psf_check"] = (Table(rows=ms.psf_rows, names=_PSF_CHECK_NAMES)
                             if ms.psf_rows else Table())  # fmt: skip
    gal_p = ~np.asarray(pg["truth_star"]) & (np.asarray(pg["truth_index"]) >= 0)
    true_params = man.get("fieldspec", {}).get("prior_params")
    out.meta["prior_check"] = prior_check(
        prior, np.column_stack([pg["e1_int"], pg["e2_int"]])[gal_p], true_params
    )
    out.meta["diagnosis"] = _diagnose(out)


def _diagnose(res: Table) -> dict[str, Any]:
    """Whether each target of :data:`TARGETS` is met, with the evidence for why not."""
    meta = res.meta
    m, me = meta["mean_m"], meta["mean_m_err"]
    d: dict[str, Any] = {}
    if not np.isfinite(m):
        d["m"] = ("untested", "no PSF has a measured m")
    elif abs(m) <= TARGETS["m"]:
        d["m"] = ("met", f"|<m>| = {abs(m):.4f} <= {TARGETS['m']}")
    elif abs(m) - me <= TARGETS["m"]:
        d["m"] = ("met within error", f"|<m>| = {abs(m):.4f} +- {me:.4f}")
    else:
        d["m"] = ("not met", f"|<m>| = {abs(m):.4f} +- {me:.4f} > {TARGETS['m']}")
    if np.isfinite(me) and me > TARGETS["m"]:
        d["m"] = (d["m"][0], d["m"][1] + f"; but sigma(<m>) = {me:.4f} exceeds the target: "
                  "the set is too small to test it")  # fmt: skip
    sc, scs = meta["sigma_c"], meta["sigma_c_stat"]
    if sc <= TARGETS["sigma_c"]:
        d["sigma_c"] = ("met", f"sigma_c = {sc:.2e} <= {TARGETS['sigma_c']:.0e}")
    else:
        noise = sc <= 2 * scs
        why = f"the fits' errors alone give {scs:.2e}, so the spread is " + (
            "consistent with noise: the set is too small to test it"
            if noise
            else "more than noise: PSF residuals (see the PSF table)"
        )
        d["sigma_c"] = ("not met", f"sigma_c = {sc:.2e} > {TARGETS['sigma_c']:.0e}; {why}")
    up = meta.get("sigma_c_upper", math.nan)
    if np.isfinite(up):
        d["sigma_c"] = (d["sigma_c"][0], d["sigma_c"][1] + (
            f"; the offsets' own spread (noise taken out) {meta['sigma_c_hat']:.1e}, "
            f"< {up:.1e} at 95 % (chi-square of c over PSFs {meta['c1_chi2']:.1f} and "
            f"{meta['c2_chi2']:.1f} on {meta['c_dof']})"))  # fmt: skip
    q = float(res["Q"][-1])
    if np.isfinite(q) and q >= TARGETS["Q"]:
        d["Q"] = ("met", f"Q = {q:.0f} >= {TARGETS['Q']:.0f}")
    else:
        per = res[:-1]
        worst = per[np.argsort(np.nan_to_num(np.asarray(per["Q"], float), nan=-1.0))[:2]]
        d["Q"] = ("not met", f"Q = {q:.0f} < {TARGETS['Q']:.0f}; lowest per PSF: "
                  + ", ".join(f"PSF {r['psf']} Q = {r['Q']:.0f}" for r in worst))  # fmt: skip
    d["all_met"] = all(d[k][0].startswith("met") for k in ("m", "sigma_c", "Q"))
    # the evidence: significant m in bins, PSF model residuals, the prior residual
    b = meta.get("bins")
    sig = []
    if b is not None and len(b):
        for r in b[b["psf"] == "all"]:
            if np.isfinite(r["mean_m"]) and abs(r["mean_m"]) > 2 * r["mean_m_err"]:
                sig.append(f"{r['kind']} bin {r['bin']} [{r['lo']:.3g}, {r['hi']:.3g}): "
                           f"<m> = {r['mean_m']:+.4f} +- {r['mean_m_err']:.4f}")  # fmt: skip
    d["bins_significant"] = sig
    pc = meta.get("psf_check")
    if pc is not None and len(pc):
        de = np.hypot(pc["e1_meas"] - pc["e1_true"], pc["e2_meas"] - pc["e2_true"])
        d["psf_worst"] = (str(pc["psf"][int(np.argmax(de))]), float(np.max(de)))
        held = pc[np.asarray(pc["heldout_n"]) > 0]
        if len(held):  # a PSF model varying over the field: its held-out stars' check
            ex = np.maximum(held["heldout_excess_de1"], held["heldout_excess_de2"])
            j = int(np.argmax(ex))
            # the rms^2 of n stars scatters by rms^2 sqrt(2 / n): the excess's 2-sigma floor
            r2 = max(held["heldout_rms_de1"][j], held["heldout_rms_de2"][j]) ** 2
            low = math.sqrt(max(ex[j] ** 2 - 2 * r2 * math.sqrt(2 / held["heldout_n"][j]), 0))
            state = ("met" if ex[j] < PSF_HELDOUT_TARGET else "met within error"
                     if low < PSF_HELDOUT_TARGET else "not met")  # fmt: skip
            d["psf_heldout"] = (state, f"largest excess rms of held-out star minus model "
                                f"ellipticity {ex[j]:.1e} (PSF {held['psf'][j]}, "
                                f"{held['heldout_n'][j]} stars; rms "
                                f"{held['heldout_rms_de1'][j]:.1e} / "
                                f"{held['heldout_rms_de2'][j]:.1e} of which the stars' noise "
                                f"{held['heldout_noise_de'][j]:.1e}; 2 sigma below: "
                                f"{low:.1e}), target < {PSF_HELDOUT_TARGET:.0e}")  # fmt: skip
    return d


def _true_psf(man: dict, k: int, n: int) -> PSFResult | PSFModel:
    """PSF ``k``'s truth as the pipeline takes a given PSF: its image (``n`` square), or
    on a set whose PSF varies, its map over the field
    (:func:`pylensfit_validation.simulate.map_psf_model`)."""
    if man.get("psf_variation", "none") == "none":
        return psf_from_image(true_psf_image(man["psfs"][k], n), source=f"true PSF {k}")
    common = {q: tuple(v) if isinstance(v, list) else v for q, v in man["fieldspec"].items()
              if not q.startswith("psf_") or q == "psf_variation"}
    spec = spec_for(man["psfs"][k], **{**common, "size": int(man["field_size"])})
    return map_psf_model(spec, size=n)


def true_psf_image(p: dict, n: int) -> np.ndarray:
    """A simulated set's PSF as the pipeline uses one: rendered with its pixel response.

    Parameters
    ----------
    p : dict
        ``{"fwhm", "beta", "e1", "e2"}`` (a manifest's ``psfs`` entry): a Moffat profile
        sheared to ``(e1, e2)``, as :func:`pylensfit_validation.simulate.simulate_field` draws it.
    n : int
        Image side in pixels.

    Returns
    -------
    numpy.ndarray
        ``(n, n)`` image of unit sum centred on element ``[n//2, n//2]`` (the centre
        convention of :class:`pylensfit.psf.PSFResult`).
    """
    obj = PSFProfile.from_dict(p).galsim()
    img = obj.drawImage(nx=n, ny=n, scale=1.0, use_true_center=False).array
    return img / img.sum()


def _true_psf_diagnostics(p: dict, n: int = 48) -> dict:
    """FWHM and adaptive-moment shape of the input PSF rendered with its pixel response.

    Measured exactly as the pipeline measures its stacked PSF
    (:func:`pylensfit.psf.psf_diagnostics`), so that the two columns of the report compare
    like with like (the pixel widens a 3 px Moffat's FWHM by ~3% and dilutes its e).
    """
    return psf_diagnostics(true_psf_image(p, n))
