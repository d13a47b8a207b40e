"""Per-galaxy posterior moments and shear sensitivities, and the shear of a sample.

For each galaxy ``a`` with a log-likelihood grid ``ln L_a(e)`` and a prior ``P(e)``
(:class:`pylensfit.prior.Prior`), the posterior is ``p_a(e) = P(e) L_a(e) / sum_e P L_a``
and (Kitching et al. 2008, arXiv:0802.1528, section 3.3; docs: method, eq-posterior)

    <e_i>_a = sum_e e_i P(e) L_a(e) / sum_e P(e) L_a(e),

with the variances and covariance computed likewise. The *shear sensitivity*
``d<e_i>_a / dg_i`` comes in two versions (:func:`shear_sensitivity`):

- ``"paper"``, the paper's sensitivity (Kitching et al. 2008, section 2.1; docs: method,
  eq-partial), which treats a shear as a translation of the prior in the e plane;
- ``"exact"`` (the default), the first-order response to the reduced-shear map
  ``e = (e_s + g) / (1 + g* e_s)`` of section 2.1 (docs: method, eq-sensitivity-exact),
  which removes the multiplicative bias (~ +0.008) that the translation approximation
  leaves even when the prior and likelihoods are exact.

The shear of a sample is the paper's mean shear over mean sensitivity (section 3.3;
docs: method, eq-key2), ``g_i = sum_a <e_i>_a / sum_a d<e_i>_a/dg_i``
(:func:`estimate_shear`). Everything is vectorised: for a block of galaxies all the sums
are one matrix product ``L (n_gal, n_e) @ K (n_e, 14)``.

The package holds one module per step: ``reduced`` (the reduced-shear map,
:func:`apply_shear`, :func:`sheared_prior_columns`), ``sums`` and its compiled kernel
``sums_nb`` (the posterior sums, :func:`kernel_columns`, :func:`sums_with`),
``posterior`` (:func:`posterior_moments`, :func:`shear_sensitivity`, :func:`shapes`),
``frames`` (the sky frames of a catalogue's rows and images), ``fixed_point``
(:func:`shear_fixed_point`, :class:`ShearEstimate`), ``estimate``
(:func:`estimate_shear`), ``selection`` (the metacalibration's estimator with the
selection response, :class:`MetacalSample`) and ``table`` (:func:`shear_table`).
"""

import warnings

from .. import grid
from . import posterior
from .estimate import estimate_shear
from .fixed_point import ShearEstimate, shear_fixed_point
from .frames import table_frame
from .posterior import (
    moments_from_sums,
    posterior_moments,
    sensitivity_from_sums,
    shapes,
    shear_sensitivity,
)
from .reduced import apply_shear, sheared_prior_columns
from .selection import MetacalSample, MetacalShear, metacal_selections, selection_response
from .sums import kernel_columns, sums_with
from .table import shear_table

__all__ = [
    "FLAG_BAD_LIKELIHOOD",
    "FLAG_NAMES",
    "MetacalSample",
    "MetacalShear",
    "ShearEstimate",
    "apply_shear",
    "estimate_shear",
    "kernel_columns",
    "metacal_selections",
    "moments_from_sums",
    "posterior_moments",
    "selection_response",
    "sensitivity_from_sums",
    "shapes",
    "shear_fixed_point",
    "shear_sensitivity",
    "shear_table",
    "sheared_prior_columns",
    "sums_with",
    "table_frame",
]

# The constants are bound here with their documentation, that of the API reference.

#: Flag bit: the likelihood row is unusable (all ``-inf``, or contains NaN / ``+inf``);
#: the ``FIT_FAILED`` bit of the catalogue's flag table (:mod:`pylensfit.flags`).
FLAG_BAD_LIKELIHOOD = posterior.FLAG_BAD_LIKELIHOOD
#: Name table of the flag bits of :func:`shapes`.
FLAG_NAMES = posterior.FLAG_NAMES

#: Names that live in :mod:`pylensfit.grid`; importing them from here warns.
_MOVED = {"DEFAULT_REFINE", "DEFAULT_STENCIL", "refine_lnL", "refined_grid"}


def __getattr__(name: str):
    if name in _MOVED:
        warnings.warn(f"pylensfit.shear.{name} is pylensfit.grid.{name}; the old name "
                      "goes in the next release", DeprecationWarning, stacklevel=2)
        return getattr(grid, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
