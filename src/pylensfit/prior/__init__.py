"""The priors: the ellipticity prior, its functional form, its fit, and its estimation
from the data; the bulge-fraction, size and flux priors.

The ellipticity prior is the functional form of Kitching et al. (2008, arXiv:0802.1528,
section 3.1; docs: method, eq-funcprior)::

    P(e) = A cos(|e| pi / 2) exp[-(2 |e| / (B (1 + |e|^D)))^C],

a function of ``|e|`` only (a zero-shear population), with ``A`` fixed by the
normalisation *on the ellipticity grid*: ``sum_grid P(e) de^2 = 1``, so that ``P`` is a
density in the (e1, e2) plane (units: per unit e1 per unit e2) whose cell probabilities
``P de^2`` sum to one over the grid of :func:`pylensfit.grid.ellipticity_grid`; or the
flexible :class:`SplinePrior`.

Estimating ``(B, C, D)`` from stored likelihood grids ``ln L_a(e)`` (one row per galaxy)
maximises the marginal likelihood of the sample,

    l(B, C, D) = sum_a w_a ln sum_e P(e) L_a(e) de^2,

either with the paper's iteration (section 3: the summed posterior is the next prior,
refitted to the functional form by minimising a cross-entropy; this *is* the EM
algorithm for (B, C, D)) or by maximising ``l`` directly (the default). Both reach the
same fixed point; see :func:`estimate_prior` (docs: method, eq-prior-iteration). The
direct maximisation reaches it in one go, whereas EM creeps towards it when the
likelihoods are broad (its rate is set by the fraction of information the noise hides;
at widths 0.1-0.3 many tens of steps are needed), so direct is the default. The
parameters are degenerate (``B`` and ``C`` trade off) while the shape of ``P`` is well
determined: judge convergence by ``l`` or by the prior's values. Memory: the
likelihoods are held as one float64 ``(n_gal, n_e)`` array (2.5 kB per galaxy on the
paper's grid); each step costs one product with it.

The package holds one module per prior and step: ``radial`` (the base class
:class:`RadialPrior`), ``functional`` (:class:`Prior`, its form and allowed region),
``spline`` (:class:`SplinePrior` and its fit), ``sample`` (the likelihood rows an
estimate uses, :func:`usable_rows`), ``fit`` (the functional prior's fits),
``estimate`` (:func:`estimate_prior`, :func:`estimate_prior_binned`), ``bulge`` (the
bulge fractions' prior), ``size`` and ``size_estimate`` (:class:`SizePrior` and its
estimate) and ``flux`` (the amplitude prior's power and bounds).
"""

from . import flux, functional, spline
from .bulge import estimate_bulge_weights, estimate_prior_and_bulge, mix_bulge_fractions
from .estimate import BinnedPrior, estimate_prior, estimate_prior_binned
from .fit import fit_functional_prior, marginal_log_likelihood
from .flux import estimate_flux_range, estimate_flux_slope
from .functional import Prior, prior_is_valid
from .radial import RadialPrior
from .sample import usable_rows
from .size import SizePrior
from .size_estimate import estimate_size_prior, select_size_prior_smoothing
from .spline import SplinePrior

__all__ = [
    "PRIOR_BOUNDS",
    "SPLINE_KNOTS",
    "SPLINE_SMOOTHING",
    "BinnedPrior",
    "Prior",
    "RadialPrior",
    "SplinePrior",
    "SizePrior",
    "estimate_bulge_weights",
    "estimate_flux_range",
    "estimate_flux_slope",
    "estimate_prior",
    "estimate_prior_and_bulge",
    "estimate_prior_binned",
    "estimate_size_prior",
    "mix_bulge_fractions",
    "select_size_prior_smoothing",
    "fit_functional_prior",
    "marginal_log_likelihood",
    "prior_is_valid",
    "usable_rows",
    "MIN_FLUX_RANGE_SAMPLE",
]

# The constants are bound here with their documentation, that of the API reference.

#: Box bounds on the parameters ``(B, C, D)`` of the functional prior. Together with the
#: joint conditions of :func:`prior_is_valid` they keep the prior positive, finite and
#: free of turning points for ``0 < |e| < 1``. The lower bounds on ``B`` and ``C`` stop
#: the degenerate direction (``B -> 0`` with ``C`` falling, which small or noisy samples
#: drift along) where the cusp at ``e = 0`` becomes sharper than the grid resolves: the
#: scale ``B/2`` where the exponent reaches 1 stays above 0.01, and the cells nearest the
#: origin (``|e| = 0.07`` for ``de = 0.1``) cannot constrain anything smaller.
PRIOR_BOUNDS = functional.PRIOR_BOUNDS
#: Knots of :class:`SplinePrior`'s cubic B-spline in ``|e|``: uniform on ``[0, 1]`` with
#: interior knots every 0.2, eight coefficients. Finer than the likelihoods resolve on the
#: paper's grid (cells 0.1 wide, likelihood widths 0.1-0.3) would only add noise.
SPLINE_KNOTS = spline.SPLINE_KNOTS
#: Default weight of :class:`SplinePrior`'s roughness penalty (see :func:`estimate_prior`).
SPLINE_SMOOTHING = spline.SPLINE_SMOOTHING
#: Fewest usable fluxes from which :func:`estimate_flux_range` estimates a range.
MIN_FLUX_RANGE_SAMPLE = flux.MIN_FLUX_RANGE_SAMPLE
