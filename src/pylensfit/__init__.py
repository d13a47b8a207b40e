"""pylensfit: Bayesian galaxy shape and weak-lensing shear measurement (lensfit).

The public API (see README.md and ``DESIGN.md`` section 6)::

    import pylensfit as plf
    cfg = plf.Config()
    egrid = plf.ellipticity_grid(step=0.1)
    fits = plf.fit_stamps(stamps, psf, noise_sigma=4.0, config=cfg)
    prior = plf.estimate_prior(fits.lnL, fits.egrid)
    shapes = plf.shapes(fits.lnL, fits.egrid, prior)
    g = plf.estimate_shear(shapes)
    cat = plf.measure(["field.fits"], stars=["starfield.fits"], config=cfg, jobs=2)
"""

from ._version import __version__
from .config import Config, ConfigError
from .grid import ellipticity_grid
from .likelihood import StampFits, fit_stamps
from .pipeline import InputError, measure, read_catalogue, write_catalogue
from .prior import BinnedPrior, Prior, SizePrior, estimate_prior, estimate_prior_binned
from .shear import ShearEstimate, estimate_shear, shapes, shear_fixed_point

__all__ = [
    "BinnedPrior",
    "Config",
    "ConfigError",
    "InputError",
    "Prior",
    "ShearEstimate",
    "SizePrior",
    "StampFits",
    "ellipticity_grid",
    "estimate_prior",
    "estimate_prior_binned",
    "estimate_shear",
    "fit_stamps",
    "measure",
    "read_catalogue",
    "shapes",
    "shear_fixed_point",
    "write_catalogue",
    "__version__",
]
