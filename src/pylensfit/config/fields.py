"""The declarative tables of the configuration: one list of :class:`Param` per section.

Each parameter has its name, type, default, allowed range or values, unit and a one-line
description of what it does. Everything else is generated from these tables: the section
dataclasses (:mod:`pylensfit.config.sections`), the validation
(:mod:`pylensfit.config.validate`), :meth:`pylensfit.Config.describe` and the reference
tables of the documentation. What a setting was measured to do is stated in the
benchmarks' README and on the validation page, not here.

A range is written as an interval: ``"[0, 1)"``, ``"(0, inf]"`` (``inf`` allowed),
``"(-inf, inf)"`` (any finite number). For a tuple of numbers it bounds each element.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from typing import Any

__all__ = ["OWNER", "PARAMS", "SECTIONS", "Param", "Section", "in_bounds", "parse_bounds"]


@dataclass(frozen=True)
class Param:
    """One configuration parameter: what the tables declare about it."""

    name: str
    type: type  # int, float, bool, str or tuple (a tuple of floats)
    default: Any
    doc: str
    unit: str = ""
    bounds: str = ""  # an interval, "[lo, hi)" etc.; "" for none
    choices: tuple = ()  # the allowed values of a str parameter
    optional: bool = False  # None allowed as well

    @property
    def type_name(self) -> str:
        """The type as the reference tables write it."""
        name = "tuple of float" if self.type is tuple else self.type.__name__
        return f"{name} or None" if self.optional else name

    @property
    def allowed(self) -> str:
        """The allowed values or range, as error messages and the tables write them."""
        if self.choices:
            return ", ".join(repr(c) for c in self.choices)
        return self.bounds


@dataclass(frozen=True)
class Section:
    """A section of the configuration: its attribute name, title and parameters."""

    name: str
    title: str
    doc: str
    params: tuple[Param, ...]


@cache
def parse_bounds(text: str) -> tuple[float, float, bool, bool]:
    """``(lo, hi, lo_open, hi_open)`` of an interval written ``"[lo, hi)"``."""
    text = text.strip()
    if text[0] not in "[(" or text[-1] not in "])" or text.count(",") != 1:
        raise ValueError(f"not an interval: {text!r}")
    lo, hi = (float(v) for v in text[1:-1].split(","))
    return lo, hi, text[0] == "(", text[-1] == ")"


def in_bounds(value: float, text: str) -> bool:
    """Whether ``value`` lies in the interval ``text`` (NaN never does)."""
    lo, hi, lo_open, hi_open = parse_bounds(text)
    if math.isnan(value):
        return False
    above = value > lo if lo_open else value >= lo
    below = value < hi if hi_open else value <= hi
    return above and below


P = Param

STAMPS = Section("stamps", "Postage stamps", "The stamps the galaxies are fitted on.", (
    P("stamp_size", int, 32, "Side of the base postage stamp, also the side of the models "
      "and of the PSF images.", "px", "[8, inf)"),
    P("max_stamp_size", int, 64, "Largest stamp side for large galaxies (stamp tiers: whole "
      "multiples of stamp_size, each fitted on the frequencies |k| <= pi / j of a stamp j "
      "times as large). Rounded down to a multiple of stamp_size; a value below twice "
      "stamp_size is 0: one stamp for all. Stamps given to fit_stamps that are smaller "
      "give their own side as the largest tier.", "px", "[0, inf)"),
    P("stamp_hlr_ratio", float, 10.0, "The stamp tiers' rule: a galaxy gets the smallest "
      "tier at least this many of its PSF-convolved half-light radii wide.", "", "(0, inf]"),
    P("k_max", float, 0.0, "Largest |k| of the Fourier terms the likelihood sums; 0: all "
      "below Nyquist. The stamp tiers set it to pi / j on a stamp j times stamp_size.",
      "rad/px", "[0, inf]"),
))

GRID = Section("grid", "Ellipticity and size grid", "The grid of model ellipticities and "
               "sizes that the likelihood is evaluated on (Kitching et al. 2008, section "
               "2.3).", (
    P("e_step", float, 0.1, "Step of the ellipticity grid (cell centres, |e| < e_max).", "",
      "(0, 0.5]"),
    P("e_max", float, 1.0, "Largest |e| of the ellipticity grid.", "", "(0, 1]"),
    P("e_refine", int, 1, "Adaptive refinement of the e grid: with k > 1 the likelihood is "
      "returned on cells of e_step / k, a galaxy's narrow peak (refine_lnl, refine_width) "
      "fitted again on the fine cells and the rest interpolated; 1: none.", "", "[1, 8]"),
    P("refine_width", float, 0.4, "With e_refine > 1: the largest half-width in e of a "
      "refined galaxy's window.", "", "(0, inf]"),
    P("refine_lnl", float, 12.0, "With e_refine > 1: a galaxy is refined on the e_step cells "
      "whose ln L is within this of its maximum (and the fine cells next to them).", "",
      "(0, inf]"),
    P("r_min", float, 0.0, "Smallest model size (0: the point-source model); below r_max.",
      "px", "[0, inf)"),
    P("r_max", float, 10.0, "Largest model size.", "px", "(0, inf)"),
    P("r_step", float, 0.4, "Model size step, the largest step of the size grid.", "px",
      "(0, inf)"),
    P("r_rel_step", float, 0.1, "Largest size step relative to the size: below r_step / "
      "r_rel_step the sizes are geometric (ratio 1 + r_rel_step); 0: the paper's uniform "
      "grid.", "", "[0, 1)"),
    P("r_floor", float, 0.05, "Smallest model size of the geometric grid (r_rel_step > 0); "
      "0: r_step / 2.", "px", "[0, inf)"),
))

MODELS = Section("models", "Galaxy models", "The galaxy profiles of the model bank. A "
                 "model other than 'bulge+disc' has one profile: n_bulge_fractions, "
                 "bulge_size_ratio2 and sersic_ladder then take their no-op values (1, 0 "
                 "and ()), whatever is given.", (
    P("model", str, "bulge+disc", "Galaxy model.", choices=("devaucouleurs", "exponential",
                                                             "bulge+disc")),
    P("bulge_fraction", float, 0.5, "Bulge-to-total flux ratio of the bulge+disc model with "
      "one fraction (n_bulge_fractions 1).", "", "[0, 1]"),
    P("bulge_size_ratio", float, 0.6, "Bulge half-light radius / disc scale length of the "
      "bulge+disc model.", "", "(0, inf)"),
    P("bulge_size_ratio2", float, 0.0, "A second bulge size (half-light radius / disc scale "
      "length, other than bulge_size_ratio): every fraction above 0 is fitted with a bulge "
      "of either size, weights estimated as the fractions'. 0: one size. Needs "
      "n_bulge_fractions >= 2; 0 for another model.", "", "[0, inf)"),
    P("sersic_ladder", tuple, (), "Sersic indices of a ladder of profiles of the disc's "
      "half-light radius fitted beside the bulge+disc runs, e.g. (0.5, 2, 4): each index "
      "and the half-and-half mixture of each adjacent pair (models.bank_runs). Distinct, "
      "not 1; a list or a comma-separated string is read as a tuple. Empty: none. Needs "
      "n_bulge_fractions >= 2; () for another model.", "", "[0.3, 6.2]"),
    P("n_bulge_fractions", int, 3, "Bulge+disc model: marginalise over this many bulge "
      "fractions, evenly spaced on [0, 1] (1: the fixed bulge_fraction). 1 for another "
      "model.", "", "[1, inf)"),
    P("truncate_models", bool, True, "Cut the models at the stamp's edge as the data are "
      "(subtract the wings a model wraps round the periodic stamp, "
      "models.wrap_correction); False: the periodic models."),
))

PRIORS = Section("priors", "Priors", "The priors of the marginalisations (docs: method, "
                 "eq-amplitude, eq-flux-prior and eq-position) and their estimation from "
                 "the data by calibrate.", (
    P("bulge_prior", str, "estimated", "Prior over the marginalised bulge fractions: "
      "estimated from the data with the ellipticity prior "
      "(prior.estimate_prior_and_bulge), or uniform.", choices=("estimated", "uniform")),
    P("size_prior", str, "estimated", "Prior over the model size in the sum over r: 'flat' "
      "(uniform in half-light radius, the paper's) or 'estimated' from the data "
      "(prior.estimate_size_prior).", choices=("flat", "estimated")),
    P("size_prior_smoothing", float, 0.25, "The estimated size prior's EMS smoothing: weight "
      "moved to each neighbouring knot (0.1 in ln h apart) per EM step; less resolves "
      "sharper features.", "", "(0, 0.5)"),
    P("size_prior_smoothing_cv", bool, False, "Choose the size prior's smoothing from the "
      "data instead: the one of prior.SIZE_PRIOR_SMOOTHINGS of the largest held-out "
      "evidence over five folds (prior.select_size_prior_smoothing)."),
    P("size_prior_per_run", bool, True, "Estimate one size distribution per run of the model "
      "family (bulge fraction), the prior of size given the fraction, instead of one for "
      "all."),
    P("size_prior_cut", float, 1e-4, "Tails of an estimated size prior, relative to its "
      "largest node's mass: below its mode the mass is floored here, above it sizes of "
      "less mass are left out of the sum over r. 0: no floor, every size of non-zero mass.",
      "", "[0, 1)"),
    P("size_prior_floor_stride", int, 3, "The floored sizes below the size prior's mode are "
      "summed on every stride-th size, each carrying the floor's mass of the sizes about "
      "it; 1: every size.", "", "[1, inf)"),
    P("amplitude_prior", str, "flux", "Prior of the model amplitude: 'uniform' (positive "
      "amplitudes, the paper's), 'snr' (power law t^-power in the model's S/N t) or 'flux' "
      "(power law A^-power in the amplitude itself: galaxy counts in flux).",
      choices=("uniform", "snr", "flux")),
    P("estimate_flux_prior", bool, True, "With amplitude_prior 'flux': calibrate estimates the "
      "power (prior.estimate_flux_slope) and, unless amplitude_prior_min / max are set, the "
      "limits of the flux distribution (prior.estimate_flux_range). False: the values "
      "given."),
    P("amplitude_prior_power", float, 2.0, "Power of the 'snr' or 'flux' amplitude prior "
      "(1: scale-invariant; 0: flat; negative: counts rising with flux).", "",
      "(-inf, inf)"),
    P("amplitude_prior_min", float, 0.0, "With amplitude_prior 'flux': the prior's lower "
      "bound in flux (0: none); below amplitude_prior_max.", "flux", "[0, inf)"),
    P("amplitude_prior_max", float, math.inf, "With amplitude_prior 'flux': the prior's upper "
      "bound in flux (inf: none).", "flux", "(0, inf]"),
    P("position_prior_sigma", float, 2.0, "Width of the Gaussian prior on position about the "
      "catalogue position (with estimate_position_prior, the calibration's starting "
      "value).", "px", "(0, inf]"),
    P("estimate_position_prior", bool, True, "calibrate estimates position_prior_sigma from "
      "the scatter of the fitted centres about the catalogue positions, less the part that "
      "falls as 1 / S/N (calibration.estimate_position_sigma)."),
    P("calibration_sample", int, 20000, "Objects that measure and calibrate_images run the "
      "calibration recipe on: whole images drawn at random (calibration_seed) until their "
      "detections reach it, then one measuring pass over every image. 0: every image.", "",
      "[0, inf)"),
    P("calibration_seed", int, 0, "Seed of the calibration sample's draw of images.", "",
      "[0, inf)"),
    P("prior_method", str, "direct", "Estimation of the ellipticity prior: maximum marginal "
      "likelihood ('direct') or 'em'.", choices=("direct", "em")),
    P("prior_form", str, "spline", "Form of the estimated ellipticity prior: a cubic B-spline "
      "in |e| (prior.SplinePrior; estimated with prior_method 'direct') or Kitching et al. "
      "(2008)'s three-parameter 'functional' form (prior.Prior).",
      choices=("functional", "spline")),
))

CENTRING = Section("centring", "Centring", "The search for each galaxy's centre and the "
                   "expansion of the likelihood in position.", (
    P("max_offset", float, 8.0, "Search radius of the cross-correlation peak about the "
      "catalogue position.", "px", "[0, inf]"),
    P("centring_scale", float, 1.5, "Scale length of the round exponential used to find the "
      "centre.", "px", "(0, inf]"),
    P("max_newton_step", float, 1.0, "Largest Newton step from the centre before the model "
      "Hessian is used.", "px", "(0, inf]"),
    P("cubic_snr", float, 20.0, "Galaxies below this S/N get the third-order expansion of the "
      "cross-correlation in position (0: never, inf: always).", "", "[0, inf]"),
))

NUMERICS = Section("numerics", "Numerics", "Precision, blocking and device of the matrix "
                   "products.", (
    P("dtype", str, "float32", "Precision of the matrix products.",
      choices=("float32", "float64")),
    P("block_size", int, 128, "Galaxies per block of matrix products.", "", "[1, inf)"),
    P("backend", str, "cpu", "Where the likelihood on the model grid runs: 'cpu' (numpy and "
      "numba), 'jax' (a JAX device, e.g. a GPU: pip install pylensfit[gpu]), 'auto' (JAX "
      "where it finds a GPU or TPU, else 'cpu').", choices=("cpu", "jax", "auto")),
))

SHEAR = Section("shear", "Bayesian shear", "The shear sensitivity and its integrals "
                "(Kitching et al. 2008, sections 2.1 and 3).", (
    P("sensitivity", str, "exact", "Shear sensitivity: 'exact' (docs: method, "
      "eq-sensitivity-exact) or the paper's section 2.1 (docs: method, eq-partial).",
      choices=("exact", "paper")),
    P("integration_refine", int, 4, "The Bayesian integrals run on an e grid this many "
      "times finer (ln L interpolated).", "", "[1, inf)"),
    P("response", str, "model", "The shear response of measure's catalogue: 'model' (sens1, "
      "sens2: lensfit's exact response if the galaxy is one of the models) or 'metacal' "
      "(also each galaxy's response measured on itself by metacalibration, with the "
      "quantities the selection response needs: the columns e1_mcal ... mcal_flags; "
      "metacal module).", choices=("model", "metacal")),
    P("metacal_step", float, 0.01, "With response 'metacal': the shear +-delta of the "
      "metacalibration images.", "", "(0, 0.2)"),
    P("metacal_reconvolution", str, "round", "With response 'metacal': the PSF of the "
      "metacalibration images, 'round' (round on the sky, nowhere above the PSF dilated "
      "by 1 + 2 metacal_step: metacal.round_reconvolution; it keeps the PSF's anisotropy "
      "out of the images, so out of c) or 'dilate' (that dilated PSF itself).",
      choices=("round", "dilate")),
    P("metacal_seed", int, 0, "With response 'metacal': seed of the added noise fields "
      "(each object's from this seed, its image's index in the run and its row in the "
      "image).", "", "[0, inf)"),
))

SELECTION = Section("selection", "Selection", "Which measured rows are used.", (
    P("min_snr", float, 5.0, "A galaxy is used (weight > 0) and enters the calibration only "
      "if its best model's matched-filter S/N is at least this; fainter rows get the "
      "LOW_SNR flag.", "", "[0, inf]"),
    P("forced_false_alarm", float, 1e-3, "An input catalogue's row is used only if the "
      "matched-filter S/N at its position (column forced_SNratio) reaches the threshold "
      "that white noise exceeds with this probability (forced.false_alarm_threshold); "
      "rows below get LOW_SNR. 1, or min_snr 0: no such cut.", "", "(0, 1]"),
))

DETECTION = Section("detection", "Detection and masking", "Detection and photometry with "
                    "sep, the background and the masking of saturated pixels.", (
    P("detect_threshold", float, 1.5, "Detection threshold per pixel on the filtered image.",
      "noise sigma", "(0, inf]"),
    P("detect_min_area", int, 5, "Fewest connected pixels of a detection.", "px",
      "[1, inf)"),
    P("background_box", int, 64, "Mesh size of the background and rms maps.", "px",
      "[8, inf)"),
    P("saturation", float, None, "Saturation level of the raw pixel values (background "
      "included): pixels at or above it are masked (grown by saturation_grow) before the "
      "background, the detection and the fit, their objects flagged SATURATED and MASKED. "
      "None: the image's SATURATE card; no cut without one.", "data units", "(0, inf)",
      optional=True),
    P("saturation_grow", int, 2, "Margin by which saturated and non-finite pixels are masked "
      "about them (a square of side 2 saturation_grow + 1).", "px", "[0, inf)"),
))

PSF = Section("psf", "Stars and PSF", "Star selection and the PSF model (Kitching et al. "
              "2008, section 2.4).", (
    P("point_source_size", float, 0.1, "An object whose most likely model size is below "
      "this, or the point source, is a star (flag STAR).", "px", "[0, inf]"),
    P("star_min_peak_snr", float, 30.0, "Stars used for the PSF have a peak S/N above "
      "this.", "", "(0, inf]"),
    P("psf_min_correlation", float, 0.9, "Stars whose normalised cross-correlation with the "
      "stack is below this are rejected.", "", "(0, 1)"),
    P("psf_min_stars", int, 3, "Fewest usable stars for a PSF from one source.", "",
      "[1, inf)"),
    P("psf_model", str, "auto", "'constant': one stacked PSF per image; 'polynomial': every "
      "PSF pixel a polynomial in (x, y) fitted to the stars (psfmodel.PolynomialPSF), each "
      "galaxy fitted with the PSF at its position; 'auto': the polynomial where the stars "
      "show the PSF varying (p-value below psf_vary_pvalue), else the constant stack.",
      choices=("auto", "constant", "polynomial")),
    P("psf_vary_pvalue", float, 1e-3, "psf_model 'auto': the polynomial model is used where "
      "the chance that stars of a constant PSF vary as much is below this.", "", "(0, 1)"),
    P("psf_order", int, 3, "Total degree of the polynomial PSF (lowered for few stars).", "",
      "[0, 6]"),
    P("psf_cells", int, 8, "A PSF varying over the image: the image is cut into psf_cells x "
      "psf_cells cells whose galaxies are fitted together, with the PSF at the cells' "
      "corners or centres (psf_interpolation).", "", "[1, inf)"),
    P("psf_interpolation", str, "fourier", "A varying PSF in the fits: 'fourier' (one fit "
      "per galaxy with the PSFs of its cell's four corners mixed by its position's "
      "bilinear weights: exactly the PSF interpolated at the galaxy, likelihood.MixedPSF), "
      "'bilinear' (four fits, one with each corner's PSF, blended with the same weights, "
      "likelihood.blend_fits) or 'centre' (the PSF at its cell's centre).",
      choices=("bilinear", "fourier", "centre")),
))

NEIGHBOURS = Section("neighbours", "Neighbours and defects", "Close pairs, the refits with "
                     "the neighbours' models subtracted and the check of each fit's "
                     "residual.", (
    P("close_pair_min_snr", float, 5.0, "Detections below this aperture S/N do not make a "
      "galaxy a close pair.", "", "[0, inf]"),
    P("close_pair_faint_ratio", float, 0.0, "Keep a galaxy whose neighbours inside its stamp "
      "are all fainter than this fraction of its flux (0: reject every close pair).", "",
      "[0, 1)"),
    P("cosmic_rays", bool, True, "measure --exposures: mask each exposure's cosmic rays "
      "(L.A.Cosmic by astroscrappy, pylensfit.exposures.mask_cosmic_rays); a galaxy whose "
      "stamp holds one in an exposure is fitted without that exposure."),
    P("subtract_neighbours", bool, True, "Fit every galaxy again with its neighbours' "
      "best-fit models subtracted from its stamp."),
    P("model_background", bool, True, "Measure the sky background again on the image less "
      "every fitted object's model, and fit the galaxies again with it."),
    P("neighbour_iterations", int, 2, "Rounds of refitting with the models of the previous "
      "fit (neighbours subtracted, and with model_background the sky measured again); each "
      "costs another fit.", "", "[1, inf)"),
    P("neighbour_min_chi2", float, 0.01, "Refit a galaxy only if the neighbours' models in "
      "its stamp sum to more than this.", "noise variances", "[0, inf]"),
    P("max_reduced_chi2", float, 10.0, "An object whose residual on its base stamp (less its "
      "own and its neighbours' models) has a reduced chi-square above this, and more than "
      "max_residual_fraction of its model's power, is flagged DEFECT (weight 0) and its "
      "model subtracted nowhere. inf: no such check.", "", "(1, inf]"),
    P("max_residual_fraction", float, 0.1, "With max_reduced_chi2: the residual's power "
      "beyond the noise, sum(r^2 - sigma^2) / sum(m^2), above which an object is DEFECT.",
      "", "(0, inf]"),
))

#: the sections, in the order of :meth:`pylensfit.Config.to_dict` and the reference
SECTIONS: tuple[Section, ...] = (STAMPS, GRID, MODELS, PRIORS, CENTRING, NUMERICS, SHEAR,
                                 SELECTION, DETECTION, PSF, NEIGHBOURS)  # fmt: skip

#: every parameter by name, and the section that owns it
PARAMS: dict[str, Param] = {p.name: p for s in SECTIONS for p in s.params}
OWNER: dict[str, str] = {p.name: s.name for s in SECTIONS for p in s.params}
if len(PARAMS) != sum(len(s.params) for s in SECTIONS):
    raise RuntimeError("a parameter is declared in two sections")
