"""pylensfit: Bayesian galaxy shape and weak-lensing shear measurement (lensfit).

The public API (see README.md)::

    import pylensfit as plf
    priors = plf.calibrate(stamps, psf, noise_sigma=4.0)      # every prior, from the data
    table = plf.measure_stamps(stamps, psf, noise_sigma=4.0, priors=priors)
    g = plf.estimate_shear(table)                             # the sheared-prior fixed point
    cat = plf.measure(["field.fits"], stars=["starfield.fits"], jobs=2)   # FITS to catalogue

``plf.Config()`` is the recommended method, ``plf.Config.paper()`` Kitching et al.
(2008)'s. The lower layer: :func:`fit_stamps` (likelihood grids), :func:`estimate_prior`,
:func:`shapes` (posterior means and sensitivities).
"""

from ._version import __version__
from .calibration import (
    CalibrationWarning,
    Priors,
    calibrate,
    calibrate_exposures,
    measure_exposure_stamps,
    measure_stamps,
)
from .config import Config, ConfigError
from .grid import ellipticity_grid
from .images import (
    InputError,
    calibrate_images,
    measure,
    measure_exposures,
    read_catalogue,
    write_catalogue,
)
from .likelihood import StampFits, fit_stamps
from .prior import (
    BinnedPrior,
    Prior,
    SizePrior,
    SplinePrior,
    estimate_prior,
    estimate_prior_binned,
)
from .shear import ShearEstimate, estimate_shear, shapes, shear_fixed_point

__all__ = [
    "BinnedPrior",
    "CalibrationWarning",
    "Priors",
    "calibrate",
    "calibrate_exposures",
    "calibrate_images",
    "measure_exposure_stamps",
    "measure_stamps",
    "Config",
    "ConfigError",
    "InputError",
    "Prior",
    "ShearEstimate",
    "SizePrior",
    "SplinePrior",
    "StampFits",
    "ellipticity_grid",
    "estimate_prior",
    "estimate_prior_binned",
    "estimate_shear",
    "fit_stamps",
    "measure",
    "measure_exposures",
    "read_catalogue",
    "shapes",
    "shear_fixed_point",
    "write_catalogue",
    "__version__",
]
