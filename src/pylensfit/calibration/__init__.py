"""The calibration recipe: every prior of the method estimated from the data themselves.

lensfit is a Bayesian method: each galaxy's ellipticity is the mean of its posterior,
and the posterior needs the priors of the population. pylensfit estimates all of them
from a sample of the galaxies to be measured (a survey's own galaxies, or an unsheared
sample of the same population), by maximum marginal likelihood, as Miller et al.
(2007, "Bayesian galaxy shape measurement for weak lensing surveys I", arXiv:0708.2340)
and Kitching et al. (2008, "lensfit II", arXiv:0802.1528) estimate the ellipticity
prior:

1. a first pass fits the sample with the configuration's starting priors (the flat size
   prior, the flux prior's Euclidean power 2 unbounded, the configuration's position
   prior), keeping each galaxy's likelihood of size ``L(r)`` per ring of ``|e|``;
2. the flux prior's power (the number counts' slope,
   :func:`~pylensfit.prior.estimate_flux_slope`; negative where the counts rise with
   flux, flat at 0 where they rise with flux and the prior has no upper limit) and its
   limits, deconvolved from the flux errors
   (:func:`~pylensfit.prior.estimate_flux_range`), come from the measured fluxes; the
   position prior's width from the scatter of the fitted centres about the
   catalogue positions, less its part that falls as ``1 / S/N`` (:func:`estimate_position_sigma`);
3. the first pass again under those priors; the ellipticity prior and the prior over
   the bulge fractions from it (:func:`~pylensfit.prior.estimate_prior_and_bulge`);
4. the size prior (one density per bulge fraction) from ``L(r)`` marginalised over
   ``e`` with the ellipticity prior just estimated
   (:func:`~pylensfit.prior.estimate_size_prior`);
5. a last pass with the size prior, for the final ellipticity and bulge-fraction priors.

Which steps run follows the :class:`~pylensfit.Config`: ``size_prior="estimated"``,
``bulge_prior="estimated"``, ``amplitude_prior="flux"`` with ``estimate_flux_prior``,
``estimate_position_prior``. The result is one :class:`Priors` object, saved and read
as JSON, that :func:`measure_stamps` and :func:`pylensfit.measure` fit with.

A sample too small for a prior (fewer than :data:`MIN_GALAXIES` usable galaxies, or
:data:`MIN_FLUX_RANGE_GALAXIES` for the flux limits) gets that prior's documented
default with a warning instead: the functional ellipticity prior ``Prior()``, uniform
bulge weights, the flat size prior, the unbounded flux power law of power 2, the
configuration's position prior.

The same recipe serves :func:`calibrate` (postage stamps), :func:`pylensfit.measure`
and :func:`pylensfit.calibrate_images` (FITS images) and the validation modes: a
:class:`Recipe` says which pass to fit next (a :class:`RecipePass`: the configurations
and size priors to fit with) and is handed each pass's :class:`CalibrationSample`; the
caller fits, the recipe estimates. :func:`run_recipe` drives it with a caller's fitting
function.
"""

from __future__ import annotations

from ..assemble import flag_low_snr, usable_galaxies
from .exposures import calibrate_exposures, measure_exposure_stamps
from .priors import (
    MIN_FLUX_RANGE_GALAXIES,
    MIN_GALAXIES,
    CalibrationSample,
    CalibrationWarning,
    Priors,
)
from .recipe import Recipe, RecipePass, estimate_position_sigma, run_recipe
from .stamps import calibrate, measure_stamps

__all__ = [
    "MIN_GALAXIES",
    "MIN_FLUX_RANGE_GALAXIES",
    "CalibrationSample",
    "CalibrationWarning",
    "Priors",
    "Recipe",
    "RecipePass",
    "calibrate",
    "calibrate_exposures",
    "estimate_position_sigma",
    "flag_low_snr",
    "measure_exposure_stamps",
    "measure_stamps",
    "run_recipe",
    "usable_galaxies",
]

