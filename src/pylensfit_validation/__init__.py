"""pylensfit_validation: the validation harness of pylensfit.

Simulations and the measurements of the method's bias on them, shipped with pylensfit
but apart from the method: the method (``pylensfit``) imports nothing of it, and it uses
only the method's public API.

* :mod:`pylensfit_validation.galaxies`, :mod:`pylensfit_validation.simulate`: galaxy and
  PSF profiles, simulated fields (GalSim).
* :mod:`pylensfit_validation.validation`: STEP1- and STEP2-like sets, ``validate`` (m, c,
  sigma_c and Q), its reports, and the quick tier.
* :mod:`pylensfit_validation.precision`: paired +-g renderings that resolve m to 1e-3.
* :mod:`pylensfit_validation.convergence`: the grid convergence study (the paper's
  Figure 2).
* :mod:`pylensfit_validation.cli`: the ``pylensfit`` subcommands ``simulate``,
  ``validate`` and ``demo`` (entry-point group ``pylensfit.commands``).
"""

__all__: list[str] = []
