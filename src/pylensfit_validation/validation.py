"""The STEP-like validation of the method (paper sections 4-5), gathered: the public
names of the modules that do its parts.

* :mod:`pylensfit_validation.step`: STEP1- and STEP2-like sets simulated with GalSim
  (:func:`simulate_step`, :func:`read_manifest`, :func:`render_step2_field`).
* :mod:`pylensfit_validation.stats`: m and c, Q, the shear of twin pairs and groups, the
  truth's control variate, the spread of the offsets over PSFs, the PSF leakage, bins.
* :mod:`pylensfit_validation.estimates`: a set's catalogues, measured once and kept,
  matched to the truth, and their shear estimates.
* :mod:`pylensfit_validation.validate`: :func:`validate`, m, c, sigma_c and Q per PSF and
  per bin, with the diagnostics of the PSFs and priors.
* :mod:`pylensfit_validation.reports`: :func:`write_report`, the Markdown report and its
  figures.
* :mod:`pylensfit_validation.quick`: :func:`quick_validation`, the quick tier.
"""

from __future__ import annotations

from . import estimates as _estimates
from . import quick as _quick
from . import reports as _reports
from . import stats as _stats
from . import step as _step
from . import validate as _validate
from .estimates import *  # noqa: F403
from .quick import *  # noqa: F403
from .reports import *  # noqa: F403
from .stats import *  # noqa: F403
from .step import *  # noqa: F403
from .validate import *  # noqa: F403

# every public name of the parts, listed once (in each part's __all__)
__all__ = [*_step.__all__, *_stats.__all__, *_estimates.__all__, *_validate.__all__,
           *_reports.__all__, *_quick.__all__]  # fmt: skip
