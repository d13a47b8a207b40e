"""pylensfit_validation: the validation harness of pylensfit.

Simulations and the measurements of the method's bias on them, shipped with pylensfit
but apart from the method: the method (``pylensfit``) imports nothing of it, and it uses
only the method's public API.

* :mod:`pylensfit_validation.galaxies`, :mod:`pylensfit_validation.simulate`: galaxy and
  PSF profiles, simulated fields (GalSim).
* :mod:`pylensfit_validation.validation`: the STEP-like validation, gathered from
  :mod:`~pylensfit_validation.step` (STEP1- and STEP2-like sets),
  :mod:`~pylensfit_validation.stats` (m, c, Q, leakage, bins),
  :mod:`~pylensfit_validation.estimates` (a set's catalogues and shear estimates),
  :mod:`~pylensfit_validation.validate` (``validate``),
  :mod:`~pylensfit_validation.reports` (its report) and
  :mod:`~pylensfit_validation.quick` (the quick tier).
* :mod:`pylensfit_validation.precision`: paired +-g renderings that resolve m to 1e-3,
  gathered from :mod:`~pylensfit_validation.precision_render` (the population and its
  renderings), :mod:`~pylensfit_validation.precision_bias` (the bias tables) and
  :mod:`~pylensfit_validation.precision_report` (the report).
* :mod:`pylensfit_validation.convergence`: the grid convergence study (the paper's
  Figure 2).
* :mod:`pylensfit_validation.cli`: the ``pylensfit`` subcommands ``simulate``,
  ``validate`` and ``demo`` (entry-point group ``pylensfit.commands``).
"""

__all__: list[str] = []
