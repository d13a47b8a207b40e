"""Configuration: one schema of typed parameters whose defaults are the recommended method.

The same parameters come from keyword arguments, a dict or a YAML file::

    cfg = Config(e_step=0.05)
    cfg = Config.from_yaml("lensfit.yaml", r_max=8.0)
    cfg = Config.paper()                 # Kitching et al. (2008)'s setup, for reproduction
    cfg = Config.preset("paper", e_step=0.05)

``Config()`` is the best measured method: the bulge+disc model with its bulge fraction
marginalised over three values, and every prior (ellipticity, bulge fraction, size per
fraction, the flux prior's power and limits, the position prior's width) estimated from
the data by :func:`pylensfit.calibrate`. :data:`PRESETS` holds the named alternatives
(``pylensfit config --preset NAME`` prints one); a YAML file may name its preset with a
``preset:`` key, its other keys overriding it.

Every field is documented in :data:`Config.__doc__` and in ``Config.describe()``;
values are validated once, when the object is made.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from .bankruns import bank_runs

__all__ = ["PRESETS", "Config", "ConfigError"]


class ConfigError(ValueError):
    """An invalid configuration value or file."""


def _f(default, doc: str):
    return field(default=default, metadata={"doc": doc})


@dataclass(frozen=True)
class Config:
    """Settings of a pylensfit run; the defaults are the recommended method.

    :meth:`paper` gives Kitching et al. (2008, "Bayesian galaxy shape measurement for
    weak lensing surveys II", arXiv:0802.1528)'s setup instead, :meth:`preset` any of
    :data:`PRESETS`. Use :meth:`describe` for the documentation of every field.
    """

    # --- model grid (paper section 2.3) ---
    stamp_size: int = _f(32, "postage-stamp side in pixels, also the model and PSF size")
    max_stamp_size: int = _f(
        64,
        "largest stamp side for large galaxies (rounded down to a multiple of stamp_size; "
        "0 or anything below twice stamp_size: one stamp for all). A galaxy whose "
        "PSF-convolved half-light radius exceeds stamp_size "
        "/ stamp_hlr_ratio is fitted on a stamp j times as large, with the frequencies |k| "
        "<= pi / j: the same cost. On a 32-pixel stamp a galaxy of 2 PSF radii under a "
        "4-pixel Kolmogorov PSF responds 1.3% more to g2 than to g1 (the edge, "
        "benchmarks/studies/stamp_edge.py); stamps given to fit_stamps that are smaller give "
        "their own side as the largest tier (48 px: 32 and 48). "
        "measure cuts them where they lie in the image with no bad pixel (else the base "
        "stamp); flags and close pairs stay the base stamp's",
    )
    stamp_hlr_ratio: float = _f(
        10.0,
        "the stamp tiers' rule: a galaxy gets the smallest tier at least this many of its "
        "PSF-convolved half-light radii wide (e1/e2 response differences below ~3e-4)",
    )
    k_max: float = _f(
        0.0,
        "largest |k| (radians per pixel) of the Fourier terms the likelihood sums; 0: all "
        "below Nyquist. The stamp tiers set it to pi / j on a stamp j times stamp_size",
    )
    e_step: float = _f(0.1, "ellipticity grid step Delta e (cell centres, |e| < e_max)")
    e_max: float = _f(1.0, "largest |e| of the ellipticity grid")
    e_refine: int = _f(
        1,
        "adaptive refinement of the e grid: with k > 1 the likelihood is given on cells of "
        "e_step / k; each galaxy whose ln L (on the e_step grid) is within refine_lnl of its "
        "maximum only inside refine_width of its peak cell is fitted again on the fine cells "
        "of that window, the other cells and galaxies are interpolated (1: none). For "
        "likelihoods narrower than the grid, where interpolation from the e_step cells "
        "biases m (+0.003 with exact models: benchmarks/studies/egrid_refinement.py)",
    )
    refine_width: float = _f(
        0.4, "with e_refine > 1: the largest half-width in e of a refined galaxy's window"
    )
    refine_lnl: float = _f(
        12.0, "with e_refine > 1: a refined galaxy's window is the e_step cells whose ln L "
        "is within this of the maximum, as their fine cells, and the fine cells next to them",
    )
    r_min: float = _f(0.0, "smallest model size in pixels (0: the point-source model)")
    r_max: float = _f(10.0, "largest model size in pixels")
    r_step: float = _f(
        0.4,
        "model size step Delta r in pixels (the largest step). 0.4: 47 sizes per fraction "
        "instead of 72 at 0.2 and a quarter of the fit's time, m moved by +0.0005 +- "
        "0.0004 on the precision population (benchmarks/studies/precision_ab.py --b r_step=0.4)",
    )
    r_rel_step: float = _f(
        0.1,
        "largest size step relative to the size: below r_step / r_rel_step the sizes are "
        "geometric (ratio 1 + r_rel_step). 0: the paper's uniform grid, which samples small "
        "galaxies' narrow likelihood in r too coarsely (m ~ +0.2 for exponentials of half "
        "the PSF's size, validate --precision)",
    )
    r_floor: float = _f(
        0.05,
        "smallest model size of the geometric grid (r_rel_step > 0), px; 0: r_step / 2. "
        "0.05 (61 sizes per fraction instead of 47, +13 % fit time): exact exponential "
        "models at S/N 100-200 under an e = 0.10 PSF give m = +0.0006 / +0.0012 +- 0.0005 "
        "and c1 = -0.00007, where r_step / 2 gave m = +0.0125 / +0.0153 and c1 = -0.00042 "
        "(benchmarks/studies/exact_model_bias.py); the precision mix moves by -0.0001 / "
        "-0.0005 +- 0.0004 (benchmarks/studies/precision_ab.py --estimated --b r_floor=0.05)",
    )
    truncate_models: bool = _f(
        True,
        "cut the models at the stamp's edge as the data are: subtract the wings that a "
        "model evaluated on the stamp's frequencies wraps round the periodic stamp "
        "(models.wrap_correction). False: the periodic models, which bias large galaxies "
        "(m2 - m1 ~ +0.02 at 1.4-2.5 PSF radii on 32-pixel stamps, validate --precision)",
    )
    model: str = _f(
        "bulge+disc", "galaxy model: 'devaucouleurs', 'exponential' or 'bulge+disc'"
    )
    bulge_fraction: float = _f(0.5, "bulge-to-total flux ratio of the bulge+disc model")
    bulge_size_ratio: float = _f(
        0.6, "bulge half-light radius / disc scale length of the bulge+disc model"
    )
    bulge_size_ratio2: float = _f(
        0.0,
        "bulge+disc model with marginalised fractions: a second bulge size (half-light radius "
        "/ disc scale length). Every fraction above 0 is then fitted with a bulge of either "
        "size (2 n_bulge_fractions - 1 runs of sizes, their weights estimated as the "
        "fractions'): the bulge's size marginalised with its fraction, a second parameter of "
        "the profile's shape (0: one size, bulge_size_ratio). 1.6x the fit's time; on the "
        "precision mix a second size of 1.0 moves m by +0.0007 "
        "(benchmarks/studies/precision_ab.py)",
    )
    sersic_ladder: tuple = _f(
        (),
        "bulge+disc model with marginalised fractions: Sersic indices of a ladder of "
        "profiles of the disc's half-light radius fitted beside the bulge+disc runs, e.g. "
        "(0.5, 2, 4): each index's Sersic profile (cut at 8 half-light radii above n = 2) "
        "and the half-and-half mixture of each adjacent pair, the disc's n = 1 among them, "
        "their weights estimated as the fractions' (models.bank_runs). Empty: none. "
        "(0.5, 2, 4) costs 2.7x the fit and raises m on the precision mix by +0.007, "
        "and by +0.011 on its Sersic and bulge+disc galaxies alone, noise-free as well; "
        "the rise is at S/N 12-50, where the posterior mixes the runs under their "
        "estimated priors, while at S/N 300 it takes the Sersic galaxies' model bias "
        "(+0.011) to 0 (benchmarks/studies/precision_ab.py --own-priors and "
        "benchmarks/studies/exact_model_bias.py): off by default",
    )
    n_bulge_fractions: int = _f(
        3,
        "bulge+disc model: marginalise over this many bulge fractions, evenly spaced on "
        "[0, 1] with a uniform prior (1: the fixed bulge_fraction). A fixed fraction biases "
        "m by about +0.09 for discs and -0.07 for bulges (validate --precision); 3 values "
        "cost 3x the models. The bulge+disc model only: the others have one profile "
        "(this, bulge_size_ratio2 and sersic_ladder are then set to their no-op values)",
    )
    bulge_prior: str = _f(
        "estimated",
        "prior over the marginalised bulge fractions: 'estimated' from the data with the "
        "ellipticity prior (prior.estimate_prior_and_bulge), or 'uniform'. Uniform weights "
        "bias discs by m ~ +0.02 (benchmarks/studies/exact_model_bias.py)",
    )
    size_prior: str = _f(
        "estimated",
        "prior over the model size in the sum over r: 'flat' (the paper's, uniform in "
        "half-light radius) or 'estimated' from the data (prior.estimate_size_prior; "
        "validate --precision). The flat prior biases faint compact galaxies, m ~ -0.07 "
        "for de Vaucouleurs galaxies at S/N 10-20 (benchmarks/studies/exact_model_bias.py)",
    )
    size_prior_smoothing: float = _f(
        0.25,
        "the estimated size prior's EMS smoothing: weight moved to each neighbouring knot "
        "(0.1 in ln h apart) per EM step. Less smoothing resolves sharper features of the "
        "size distribution (prior.estimate_size_prior). The precision populations' "
        "held-out evidence prefers 0.02 (size_prior_smoothing_cv), which takes the "
        "galaxies the family holds to m ~ 0 and moves the mix's m up by 0.0013 "
        "(benchmarks/studies/precision_ab.py --b size_prior_smoothing=0.02)",
    )
    size_prior_smoothing_cv: bool = _f(
        False,
        "choose the estimated size prior's smoothing from the data instead: the one of "
        "prior.SIZE_PRIOR_SMOOTHINGS whose prior, fitted to four fifths of the sample, "
        "gives the other fifth the largest evidence, over five folds "
        "(prior.select_size_prior_smoothing); size_prior_smoothing is then unused",
    )
    size_prior_per_run: bool = _f(
        True,
        "estimate one size distribution per run of the model family (bulge fraction), "
        "the prior of size conditional on the fraction, instead of one for all "
        "(prior.estimate_size_prior): a population whose kinds differ in size (knotty "
        "discs smaller than bulges) is not a product of a fraction prior and a size prior",
    )
    size_prior_cut: float = _f(
        1e-4,
        "the tails of an estimated size prior (SizePrior.node_weights), relative to its "
        "largest node's mass: below the prior's mode the mass is floored here (compact "
        "models keep a say); above it the sizes of less mass are left out of the sum over "
        "r and their models are not evaluated (a disc's largest sizes: a fifth of the "
        "precision mode's models). 0: no floor, every size of non-zero mass",
    )
    size_prior_floor_stride: int = _f(
        3,
        "the floored sizes below an estimated size prior's mode (size_prior_cut) are "
        "summed on every stride-th size of the bank, each carrying the floor's mass of "
        "the stride sizes about it: a coarser quadrature where the models are compact and "
        "the weights 1e-4 of the prior's peak. 1: every size. Three take 15 % of the "
        "precision mode's models out (estimated size priors), m moved by 1e-5 "
        "(benchmarks/studies/precision_ab.py)",
    )
    # --- marginalisation over amplitude (docs: method, eq-amplitude and eq-flux-prior) ---
    amplitude_prior: str = _f(
        "flux",
        "prior of the model amplitude: 'uniform' (the paper's; positive amplitudes) or "
        "'snr' (a power law t^-amplitude_prior_power in the model's S/N t, which does "
        "not weight models by their sum m^2 as the uniform prior does) or 'flux' (a power "
        "law A^-amplitude_prior_power in the amplitude itself, the same for every model: "
        "galaxy counts in flux). The uniform prior, and a position prior wider than "
        "the catalogue's errors, weight each model by 1 / sqrt(sum m^2) and by its "
        "position Fisher matrix, which favour elongated models at the faint end",
    )
    estimate_flux_prior: bool = _f(
        True,
        "with amplitude_prior 'flux': calibrate estimates the power (the counts' slope, "
        "prior.estimate_flux_slope) and, unless amplitude_prior_min / max are set, the "
        "limits of the flux distribution deconvolved from the flux errors "
        "(prior.estimate_flux_range). Without the lower limit a faint galaxy keeps a "
        "weight for models of less flux than it has (m +0.003 for exponentials). False: "
        "amplitude_prior_power, _min and _max as given",
    )
    amplitude_prior_power: float = _f(
        2.0, "power of the 'snr' or 'flux' amplitude prior (dN/dS ~ S^-power or dN/dA ~ "
        "A^-power; 1: scale-invariant; 0: flat; negative: counts that rise with flux, "
        "a bright selection's)",
    )
    amplitude_prior_min: float = _f(
        0.0, "with amplitude_prior 'flux': the prior's lower bound in flux (0: none); for "
        "simulated sets whose fluxes are drawn within a hard range (validate --precision), "
        "where the unbounded power law gives the faintest galaxies' models of low flux a "
        "weight that the population does not",
    )
    amplitude_prior_max: float = _f(
        math.inf, "with amplitude_prior 'flux': the prior's upper bound in flux (inf: none)"
    )
    # --- marginalisation over position (docs: method, eq-position) ---
    position_prior_sigma: float = _f(
        2.0, "width b of the Gaussian prior on position about the catalogue position, px "
        "(with estimate_position_prior, the starting value of the calibration)"
    )
    estimate_position_prior: bool = _f(
        True,
        "calibrate estimates position_prior_sigma from the scatter of the fitted centres "
        "about the catalogue positions, less the part that falls as 1 / S/N "
        "(calibration.estimate_position_sigma); positions detected on the image itself "
        "have no other part, and keep position_prior_sigma",
    )
    max_offset: float = _f(
        8.0, "search radius for the cross-correlation peak about the catalogue position, px"
    )
    centring_scale: float = _f(
        1.5, "scale length (px) of the round exponential used to find the centre"
    )
    max_newton_step: float = _f(
        1.0, "largest Newton step (px) from the centre before the model Hessian is used"
    )
    cubic_snr: float = _f(
        20.0,
        "galaxies below this S/N get the third-order expansion of the cross-correlation "
        "in position (4 more matrix products; 0 never, inf always). Measured max error in "
        "ln L against brute force without it: 0.19 at S/N 10, 0.027 at 14, 0.006 at 20",
    )
    # --- numerics ---
    dtype: str = _f("float32", "precision of the matrix products: 'float32' or 'float64'")
    block_size: int = _f(128, "galaxies per block of matrix products")
    # --- Bayesian shear (paper sections 2.1 and 3) ---
    sensitivity: str = _f(
        "exact",
        "shear sensitivity: 'exact' (docs: method, eq-sensitivity-exact) or 'paper' "
        "(Kitching et al. 2008, arXiv:0802.1528, section 2.1; docs: method, eq-partial)",
    )
    integration_refine: int = _f(
        4, "the Bayesian integrals run on an e grid this many times finer (ln L interpolated)"
    )
    prior_method: str = _f("direct", "prior estimation: 'direct' (maximum marginal L) or 'em'")
    prior_form: str = _f(
        "spline",
        "form of the estimated ellipticity prior: 'spline' (a cubic B-spline in |e| that "
        "follows any smooth population and has no bound to end on, prior.SplinePrior; "
        "estimated with prior_method 'direct') or 'functional' (Kitching et al. 2008's "
        "three-parameter form, prior.Prior). On the unseen paired set (P0, 20,000 "
        "galaxies) both give m = -0.0072 / -0.0074 (the functional estimate on its bound "
        "D = 0.5); on a ring population in |e| the functional form is off by 0.007-0.014 "
        "and the spline within 2e-3 (tests/test_spline_prior.py)",
    )
    min_snr: float = _f(
        5.0,
        "a galaxy is used (weight > 0), and enters the calibration, only if its best "
        "model's matched-filter S/N is at least this; fainter rows get the LOW_SNR flag. "
        "On pure-noise images 99 % of the detections fitted as galaxies are below 5.1: "
        "5 keeps 0.6 % of the detections, 7 0.1 % (benchmarks/noise_detections.py). The "
        "floor is a selection: on the precision population (20,000 galaxies, paired) m "
        "moves by -0.001 at 5 and by -0.004 at 7 against no floor",
    )
    forced_false_alarm: float = _f(
        1e-3,
        "an input catalogue's row is used only if the matched-filter S/N at its catalogue "
        "position itself (the best of round exponentials of half-light radius 0-4 px "
        "convolved with the PSF, no search over position: column forced_SNratio) reaches "
        "the threshold that pure white noise exceeds with probability at most this "
        "(pylensfit.forced.false_alarm_threshold: 3.48 at 1e-3); rows below it get the "
        "LOW_SNR flag. The fit's own S/N is the best of the noise peaks and neighbours' "
        "wings within max_offset: on blank positions of simulated fields it is above "
        "min_snr for 45 % of them (priors estimated; 23 % under fixed priors), with this "
        "cut 0.3 % are usable and every galaxy of S/N >= 10 is kept "
        "(benchmarks/forced_positions.py). 1, or min_snr 0: no such cut",
    )
    # --- detection and photometry (sep; paper section 2.3) ---
    detect_threshold: float = _f(
        1.5, "detection threshold in noise sigmas per pixel, on the filtered image "
        "(SExtractor's default; noise peaks detected have S/N ~1 and are measured as such)"
    )
    detect_min_area: int = _f(5, "minimum number of connected pixels of a detection")
    background_box: int = _f(64, "mesh size (px) of the background and rms maps")
    # --- stars and PSF (paper section 2.4) ---
    point_source_size: float = _f(
        0.1,
        "an object whose most likely model size is below this (px), or the point source, "
        "is a star (flag STAR). 0.1: the classification of a grid whose smallest size is "
        "0.2 px; with r_floor = 0.05 the point source alone would call 59 % of S/N-200 "
        "stars stars instead of 92 %, the models below 0.1 px being indistinguishable",
    )
    star_min_peak_snr: float = _f(30.0, "stars used for the PSF have peak S/N above this")
    psf_min_correlation: float = _f(
        0.9, "stars whose normalised cross-correlation with the stack is below this are rejected"
    )
    psf_min_stars: int = _f(3, "fewest usable stars for a PSF from one source")
    psf_model: str = _f(
        "auto", "'constant': one stacked PSF per image; 'polynomial': every PSF pixel a "
        "polynomial in (x, y) fitted to the stars (lensfit's survey PSF; "
        "pylensfit.psfmodel.PolynomialPSF), each galaxy fitted with the PSF at its "
        "position (psf_cells, psf_interpolation); 'auto': the polynomial where the stars "
        "show the PSF varying over the image (PolynomialPSF.variation's p-value below "
        "psf_vary_pvalue), else the constant stack"
    )
    psf_vary_pvalue: float = _f(
        1e-3, "psf_model 'auto': the polynomial model is used where the chance that "
        "stars of a constant PSF vary as much is below this"
    )
    psf_order: int = _f(3, "total degree of the polynomial PSF (lowered for few stars)")
    psf_cells: int = _f(
        8, "a PSF varying over the image (psf_model 'polynomial', a Piff model): the image "
        "is cut into psf_cells x psf_cells cells whose galaxies are fitted together, with "
        "the PSF sampled at the cells' corners or centres (psf_interpolation)"
    )
    psf_interpolation: str = _f(
        "bilinear",
        "a varying PSF in the fits: 'bilinear' (each galaxy fitted with the PSFs at its "
        "cell's four corners and the fits blended with its position's bilinear weights, "
        "likelihood.blend_fits: rms shape error 2e-4 at 8 x 8 cells under the survey map, "
        "at four times the fits) or 'centre' (the PSF at its cell's centre: 4.5e-3; "
        "benchmarks/psf_cells.py)",
    )
    # --- postage stamps (paper section 2.3) ---
    close_pair_min_snr: float = _f(
        5.0, "detections below this aperture S/N do not make a galaxy a close pair"
    )
    close_pair_faint_ratio: float = _f(
        0.0,
        "keep a galaxy whose neighbours inside its stamp are all fainter than this fraction "
        "of its flux (0: reject every close pair)",
    )

    subtract_neighbours: bool = _f(
        True,
        "fit every galaxy a second time with its neighbours' best-fit models (from the first "
        "fit) subtracted from its stamp, so that their wings do not distort its shape",
    )
    model_background: bool = _f(
        True,
        "measure the sky background again on the image less every fitted object's model "
        "and fit the galaxies again with it: the objects' wings raise SEP's estimate "
        "(0.02-0.06 noise sigma in the STEP2-like fields), which biases m by up to +0.03 "
        "(benchmarks/studies/sky_bias.py)",
    )
    neighbour_iterations: int = _f(
        2,
        "rounds of refitting with the models of the previous fit: each subtracts the "
        "neighbours' models and (model_background) measures the sky again less all models. "
        "The sky needs the second round (STEP2-like field, large PSF: sky error 0.056 -> "
        "0.017 -> 0.006 noise sigma); for the neighbours alone a second moved m by < 2e-4 "
        "(benchmarks/studies/neighbour_bias.py). Each round costs another fit",
    )
    neighbour_min_chi2: float = _f(
        0.01,
        "refit a galaxy only if the neighbours' models in its stamp sum to more than this "
        "(sum of squares in noise variances)",
    )
    max_reduced_chi2: float = _f(
        10.0,
        "an object whose best model, rendered, leaves on its base stamp a residual (the "
        "stamp less its own and its neighbours' models) of reduced chi-square above this "
        "and of more than max_residual_fraction of the model's power is flagged DEFECT "
        "(weight 0): its model is subtracted neither from its neighbours' stamps nor from "
        "the sky, and a first fit spoiled by a neighbour is cleared when its refit fits. "
        "Measured on simulated 512^2 fields: galaxies of S/N 10-200 (exponential, de "
        "Vaucouleurs, bulge+disc; fitted with the same or another profile; Config() and "
        "paper) stay below 3.2, stars of peak S/N 40-1000 under a PSF 0.036 off in "
        "ellipticity below 6.2; bright galaxies (S/N 200-3000) reach 465 and stars of "
        "peak S/N 1e4 584, but with residuals below 0.085 and 0.001 of their models' "
        "power; a 10x10 block at 65,000 or 1e9 ADU, a pixel at 1e30 or +2000 sigma, a "
        "bleed trail and stars saturated 40-16,000 times reach 3e3 to 1e57 "
        "(tests/test_defects.py). inf: no such check",
    )
    max_residual_fraction: float = _f(
        0.1,
        "with max_reduced_chi2: the residual's power beyond the noise as a fraction of the "
        "model's own on the base stamp, sum(r^2 - sigma^2) / sum(m^2), above which an "
        "object is DEFECT. Faint galaxies reach 3.5 from the noise alone (their reduced "
        "chi-square stays near 1); bright galaxies of another profile than the model's "
        "0.085, stars under a wrong PSF 0.001; the defects above 0.34 (blocks), 4.8 (a "
        "pixel), 22 (a trail), 0.13-0.18 (stars saturated 40-16,000 times; 2-5 times: "
        "0.003-0.06, a model close enough to subtract)",
    )
    saturation: float | None = _f(
        None,
        "saturation level of the raw pixel values (data units, background included): "
        "pixels at or above it are masked (grown by saturation_grow px) before the "
        "background, the detection and the fit, and the objects whose stamps hold them "
        "are flagged SATURATED and MASKED. None: the image's SATURATE card, as SExtractor "
        "reads it; no cut without one",
    )
    saturation_grow: int = _f(
        2,
        "margin in pixels by which the saturated and the non-finite pixels are masked "
        "about them (a square of side 2 saturation_grow + 1)",
    )

    def __post_init__(self) -> None:
        if not isinstance(self.sersic_ladder, tuple):  # a list from YAML, a string "0.5,2,4"
            object.__setattr__(self, "sersic_ladder", _as_floats(self.sersic_ladder))
        if self.model != "bulge+disc":  # one profile: the family's settings do not apply
            object.__setattr__(self, "n_bulge_fractions", 1)
            object.__setattr__(self, "bulge_size_ratio2", 0.0)
            object.__setattr__(self, "sersic_ladder", ())
        if isinstance(self.stamp_size, int) and isinstance(self.max_stamp_size, int) \
                and self.stamp_size >= 8 and self.max_stamp_size > 0:
            # the tiers are whole multiples of the base stamp; none above it: one stamp
            top = self.max_stamp_size // self.stamp_size * self.stamp_size
            object.__setattr__(self, "max_stamp_size", top if top > self.stamp_size else 0)
        _validate(self)

    # ------------------------------------------------------------------ presets
    @classmethod
    def preset(cls, name: str, **overrides: Any) -> Config:
        """The named configuration of :data:`PRESETS`, with overrides."""
        if name not in PRESETS:
            raise ConfigError(f"unknown preset {name!r}; known: {sorted(PRESETS)}")
        return cls.from_dict({**PRESETS[name][0], **overrides})

    @classmethod
    def paper(cls, **overrides: Any) -> Config:
        """Kitching et al. (2008, arXiv:0802.1528)'s setup, for reproducing the paper.

        The de Vaucouleurs model on 32-pixel stamps, sizes on a 0.2-pixel grid, a flat
        size prior, the uniform amplitude prior, a 2-pixel position prior and every
        galaxy that is fitted used (:data:`PRESETS` ``"paper"``). Its biases are
        measured: m ~ +0.07 to +0.11 on mixed populations (discs +0.09, bulges -0.07).
        The numerical refinements (geometric small sizes, models cut at the stamp's
        edge, the refined integration grid, the exact sensitivity) stay; set
        ``r_rel_step=0, truncate_models=False, integration_refine=1,
        sensitivity="paper"`` for the paper's numerics as well.
        """
        return cls.preset("paper", **overrides)

    # ------------------------------------------------------------------ helpers
    @property
    def largest_stamp(self) -> int:
        """The largest stamp side a galaxy is fitted on (``max_stamp_size``, or
        ``stamp_size`` without tiers): the size stamps and PSF images should have."""
        return self.max_stamp_size or self.stamp_size

    @property
    def output_e_step(self) -> float:
        """The cell side of the likelihood grid that :func:`~pylensfit.fit_stamps` returns
        (``e_step / e_refine``)."""
        return self.e_step / self.e_refine

    @property
    def bulge_runs(self):
        """The profile of each run of sizes of the model bank
        (:func:`pylensfit.bankruns.bank_runs`: ``Run(fraction, bulge size, ...)``):
        ``n_bulge_fractions`` fractions evenly spaced on [0, 1] with ``bulge_size_ratio``,
        then with ``bulge_size_ratio2 > 0`` the fractions above 0 again with that size,
        then the Sersic ladder's (one run, the fixed ``bulge_fraction``, unless the
        fractions are marginalised)."""
        return bank_runs(self.model, float(self.bulge_fraction), float(self.bulge_size_ratio),
                         int(self.n_bulge_fractions), float(self.bulge_size_ratio2),
                         tuple(self.sersic_ladder))  # fmt: skip

    @property
    def run_labels(self) -> list[str]:
        """How reports name each of :attr:`bulge_runs` (``Run.label``)."""
        sized = self.bulge_size_ratio2 > 0 or bool(self.sersic_ladder)
        return [run.label(sized) for run in self.bulge_runs]

    @property
    def output_refine(self) -> int:
        """``integration_refine`` on the output grid: the Bayesian integrals run on cells
        of ``e_step / integration_refine`` whatever ``e_refine`` is (at least the output
        grid's own cells)."""
        return max(1, self.integration_refine // self.e_refine)

    @classmethod
    def describe(cls) -> dict[str, tuple[Any, str]]:
        """``{name: (default, description)}`` for every parameter."""
        return {f.name: (f.default, f.metadata.get("doc", "")) for f in fields(cls)}

    def to_dict(self) -> dict[str, Any]:
        """Plain ``dict`` of the parameters (for headers and YAML; sequences as lists)."""
        return {k: list(v) if isinstance(v, tuple) else v
                for k, v in dataclasses.asdict(self).items()}  # fmt: skip

    def replace(self, **overrides: Any) -> Config:
        """A copy with some parameters changed (validated)."""
        return self.from_dict({**self.to_dict(), **overrides})

    @classmethod
    def from_dict(cls, values: dict[str, Any] | None = None, **overrides: Any) -> Config:
        """Build from a mapping, rejecting unknown keys with a clear message."""
        values = {**(values or {}), **overrides}
        if "preset" in values:  # a named preset, the other keys overriding it
            name = values.pop("preset")
            if name not in PRESETS:
                raise ConfigError(f"unknown preset {name!r}; known: {sorted(PRESETS)}")
            values = {**PRESETS[name][0], **values}
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(values) - set(known), key=str)
        if unknown:
            # one line: the keys (at most three named) and the closest known ones (the
            # three closest to a single key, the closest to each of two or three)
            shown = unknown[:3]
            n_close = 3 if len(unknown) == 1 else 1 if len(unknown) <= 3 else 0
            said = []
            for u in shown:
                close = difflib.get_close_matches(str(u), known, n=n_close) if n_close else []
                said.append(f"{u!r}" + (f" (did you mean {' or '.join(map(repr, close))}?)"
                                         if close else ""))  # fmt: skip
            more = f" and {len(unknown) - len(shown)} more" if len(unknown) > len(shown) else ""
            raise ConfigError(f"unknown configuration key{'s' if len(unknown) > 1 else ''} "
                              f"{', '.join(said)}{more}; `pylensfit config` lists them "
                              "all")  # fmt: skip
        kw = {}
        for name, val in values.items():
            typ = type(known[name].default)
            try:
                if typ is bool:
                    kw[name] = _as_bool(val)
                elif typ in (int, float) and isinstance(val, bool):
                    raise ValueError(val)  # yes/no is no number
                elif typ is int and not float(val).is_integer():
                    raise ValueError(val)
                else:
                    kw[name] = typ(val) if typ in (int, float) else val
            except (TypeError, ValueError):
                raise ConfigError(
                    f"configuration key {name!r} must be {typ.__name__}, got {val!r}"
                ) from None
        return cls(**kw)

    @classmethod
    def from_yaml(cls, path: str | Path, **overrides: Any) -> Config:
        """Read a YAML file of ``key: value`` pairs; keyword overrides win."""
        path = Path(path)
        try:
            text = path.read_text()
        except OSError as err:
            raise ConfigError(f"{path}: cannot read configuration file ({err.strerror})") from None
        try:
            data = yaml.safe_load(text) or {}
        except yaml.YAMLError as err:
            raise ConfigError(f"{path}: not valid YAML ({err})") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: expected a mapping of key: value pairs")
        try:
            return cls.from_dict(data, **overrides)
        except ConfigError as err:
            raise ConfigError(f"{path}: {err}") from None

    def to_yaml(self, path: str | Path) -> None:
        """Write the parameters as YAML."""
        Path(path).write_text(yaml.safe_dump(self.to_dict(), sort_keys=False))


#: named configurations: ``name -> (overrides of the defaults, description)``
PRESETS: dict[str, tuple[dict[str, Any], str]] = {
    "default": ({}, "the recommended method (Config())"),
    "paper": (
        {"model": "devaucouleurs", "n_bulge_fractions": 1, "max_stamp_size": 0,
         "r_step": 0.2, "r_floor": 0.0, "size_prior": "flat", "size_prior_per_run": False,
         "amplitude_prior": "uniform", "estimate_flux_prior": False,
         "estimate_position_prior": False, "min_snr": 0.0, "prior_form": "functional",
         "psf_model": "constant"},
        "Kitching et al. (2008)'s setup: de Vaucouleurs model, flat size prior, uniform "
        "amplitude prior, 2-pixel position prior, one stacked PSF per image",
    ),
}  # fmt: skip


def _as_floats(val: Any) -> tuple:
    """A tuple of floats from a sequence or a comma-separated string."""
    if isinstance(val, str):
        val = [v for v in val.replace("(", "").replace(")", "").split(",") if v.strip()]
    try:
        return tuple(float(v) for v in val)
    except (TypeError, ValueError):
        raise ConfigError(f"expected a sequence of numbers, got {val!r}") from None


def _as_bool(val: Any) -> bool:
    """``True``/``False``, 1/0 or the strings true/false, yes/no, on/off."""
    if isinstance(val, bool):
        return val
    if isinstance(val, (int, float)) and val in (0, 1):
        return bool(val)
    if isinstance(val, str) and val.strip().lower() in ("true", "yes", "on", "1", "false",
                                                        "no", "off", "0"):  # fmt: skip
        return val.strip().lower() in ("true", "yes", "on", "1")
    raise ValueError(val)


def _validate(c: Config) -> None:
    def need(ok: bool, msg: str) -> None:
        if not ok:
            raise ConfigError(msg)

    need(c.stamp_size >= 8, f"stamp_size must be >= 8, got {c.stamp_size}")
    need(c.max_stamp_size == 0 or (c.max_stamp_size >= c.stamp_size
                                   and c.max_stamp_size % c.stamp_size == 0),
         f"max_stamp_size must be a multiple of stamp_size ({c.stamp_size}), got "
         f"{c.max_stamp_size}")  # fmt: skip
    need(c.stamp_hlr_ratio > 0, f"stamp_hlr_ratio must be > 0, got {c.stamp_hlr_ratio}")
    need(c.k_max >= 0, f"k_max must be >= 0, got {c.k_max}")
    need(0 < c.e_step <= 0.5, f"e_step must be in (0, 0.5], got {c.e_step}")
    need(0 < c.e_max <= 1, f"e_max must be in (0, 1], got {c.e_max}")
    need(float(c.e_refine).is_integer() and 1 <= c.e_refine <= 8,
         f"e_refine must be an integer in [1, 8], got {c.e_refine!r}")  # fmt: skip
    need(c.refine_width > 0, f"refine_width must be > 0, got {c.refine_width}")
    need(c.refine_lnl > 0, f"refine_lnl must be > 0, got {c.refine_lnl}")
    need(c.r_step > 0, f"r_step must be > 0, got {c.r_step}")
    need(0 <= c.r_rel_step < 1, f"r_rel_step must be in [0, 1), got {c.r_rel_step}")
    need(c.r_floor >= 0, f"r_floor must be >= 0, got {c.r_floor}")
    need(c.point_source_size >= 0, f"point_source_size must be >= 0, got {c.point_source_size}")
    need(0 <= c.r_min < c.r_max, f"need 0 <= r_min < r_max, got {c.r_min}, {c.r_max}")
    need(
        c.model in ("exponential", "devaucouleurs", "bulge+disc"),
        f"model must be 'exponential', 'devaucouleurs' or 'bulge+disc', got {c.model!r}",
    )
    need(0 <= c.bulge_fraction <= 1, f"bulge_fraction must be in [0, 1], got {c.bulge_fraction}")
    need(c.bulge_size_ratio > 0, f"bulge_size_ratio must be > 0, got {c.bulge_size_ratio}")
    need(
        int(c.n_bulge_fractions) == c.n_bulge_fractions and c.n_bulge_fractions >= 1,
        f"n_bulge_fractions must be a positive integer, got {c.n_bulge_fractions}",
    )
    need(
        c.n_bulge_fractions == 1 or c.model == "bulge+disc",
        "n_bulge_fractions > 1 needs model 'bulge+disc'",
    )
    need(c.bulge_size_ratio2 >= 0, f"bulge_size_ratio2 must be >= 0, got {c.bulge_size_ratio2}")
    need(
        c.bulge_size_ratio2 == 0 or (c.model == "bulge+disc" and c.n_bulge_fractions >= 2),
        "bulge_size_ratio2 > 0 needs model 'bulge+disc' with n_bulge_fractions >= 2",
    )
    need(c.bulge_size_ratio2 != c.bulge_size_ratio,
         "bulge_size_ratio2 must differ from bulge_size_ratio (0: no second size)")
    ladder = c.sersic_ladder
    need(not ladder or (c.model == "bulge+disc" and c.n_bulge_fractions >= 2),
         "sersic_ladder needs model 'bulge+disc' with n_bulge_fractions >= 2")
    need(all(0.3 <= v <= 6.2 and v != 1.0 for v in ladder) and len(set(ladder)) == len(ladder),
         f"sersic_ladder must hold distinct Sersic indices in [0.3, 6.2] other than the "
         f"disc's 1, got {ladder}")
    need(c.bulge_prior in ("estimated", "uniform"),
         f"bulge_prior must be 'estimated' or 'uniform', got {c.bulge_prior!r}")
    need(c.position_prior_sigma > 0, "position_prior_sigma must be > 0")
    need(c.amplitude_prior in ("uniform", "snr", "flux"),
         f"amplitude_prior must be 'uniform', 'snr' or 'flux', got {c.amplitude_prior!r}")
    need(math.isfinite(c.amplitude_prior_power),
         f"amplitude_prior_power must be finite, got {c.amplitude_prior_power}")
    need(0 <= c.amplitude_prior_min < c.amplitude_prior_max,
         "need 0 <= amplitude_prior_min < amplitude_prior_max")  # fmt: skip
    need(0 < c.size_prior_smoothing < 0.5, "size_prior_smoothing must be in (0, 0.5)")
    need(0 <= c.size_prior_cut < 1, "size_prior_cut must be in [0, 1)")
    need(int(c.size_prior_floor_stride) == c.size_prior_floor_stride
         and c.size_prior_floor_stride >= 1, "size_prior_floor_stride must be an integer >= 1")
    need(c.max_offset >= 0, "max_offset must be >= 0")
    need(c.centring_scale > 0, "centring_scale must be > 0")
    need(c.max_newton_step > 0, "max_newton_step must be > 0")
    need(c.cubic_snr >= 0, "cubic_snr must be >= 0")
    need(c.size_prior in ("flat", "estimated"),
         f"size_prior must be 'flat' or 'estimated', got {c.size_prior!r}")  # fmt: skip
    need(c.dtype in ("float32", "float64"), f"dtype must be float32 or float64, got {c.dtype!r}")
    need(c.block_size >= 1, "block_size must be >= 1")
    need(c.sensitivity in ("exact", "paper"), "sensitivity must be 'exact' or 'paper'")
    need(c.integration_refine >= 1, "integration_refine must be >= 1")
    need(c.prior_method in ("direct", "em"), "prior_method must be 'direct' or 'em'")
    need(c.prior_form in ("functional", "spline"),
         f"prior_form must be 'functional' or 'spline', got {c.prior_form!r}")  # fmt: skip
    need(c.prior_form == "functional" or c.prior_method == "direct",
         "prior_form 'spline' is estimated with prior_method 'direct'")  # fmt: skip
    need(c.detect_threshold > 0, "detect_threshold must be > 0")
    need(c.detect_min_area >= 1, "detect_min_area must be >= 1")
    need(c.background_box >= 8, "background_box must be >= 8")
    need(c.star_min_peak_snr > 0, "star_min_peak_snr must be > 0")
    need(0 < c.psf_min_correlation < 1, "psf_min_correlation must be in (0, 1)")
    need(c.psf_min_stars >= 1, "psf_min_stars must be >= 1")
    need(c.psf_interpolation in ("bilinear", "centre"),
         f"psf_interpolation must be 'bilinear' or 'centre', got {c.psf_interpolation!r}")
    need(c.psf_model in ("auto", "constant", "polynomial"),
         f"psf_model must be 'auto', 'constant' or 'polynomial', got {c.psf_model!r}")
    need(0 < c.psf_vary_pvalue < 1, f"psf_vary_pvalue must be in (0, 1), got "
         f"{c.psf_vary_pvalue}")  # fmt: skip
    need(0 <= c.psf_order <= 6, f"psf_order must be in 0..6, got {c.psf_order}")
    need(c.psf_cells >= 1, f"psf_cells must be >= 1, got {c.psf_cells}")
    need(c.close_pair_min_snr >= 0, "close_pair_min_snr must be >= 0")
    need(0 <= c.close_pair_faint_ratio < 1, "close_pair_faint_ratio must be in [0, 1)")
    need(c.neighbour_min_chi2 >= 0, "neighbour_min_chi2 must be >= 0")
    need(c.neighbour_iterations >= 1, "neighbour_iterations must be >= 1")
    need(c.max_reduced_chi2 > 1, f"max_reduced_chi2 must be > 1, got {c.max_reduced_chi2}")
    need(c.max_residual_fraction > 0,
         f"max_residual_fraction must be > 0, got {c.max_residual_fraction}")  # fmt: skip
    need(c.saturation is None or (isinstance(c.saturation, (int, float))
                                  and not isinstance(c.saturation, bool)
                                  and math.isfinite(c.saturation) and c.saturation > 0),
         f"saturation must be None or a positive number, got {c.saturation!r}")  # fmt: skip
    need(c.saturation_grow >= 0, f"saturation_grow must be >= 0, got {c.saturation_grow}")
    need(c.min_snr >= 0, "min_snr must be >= 0")
    need(0 < c.forced_false_alarm <= 1,
         f"forced_false_alarm must be in (0, 1], got {c.forced_false_alarm}")  # fmt: skip
