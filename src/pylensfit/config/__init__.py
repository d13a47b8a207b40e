"""Configuration: typed parameters in sections, whose defaults are the recommended method.

The same parameters come from keyword arguments, a dict or a YAML file::

    cfg = Config(e_step=0.05)
    cfg = Config.from_yaml("lensfit.yaml", r_max=8.0)
    cfg = Config.paper()                 # Kitching et al. (2008)'s setup, for reproduction
    cfg = Config.preset("paper", e_step=0.05)
    cfg.grid.e_step == cfg.e_step        # a parameter through its section, or directly

``Config()`` is the best measured method: the bulge+disc model with its bulge fraction
marginalised over three values, and every prior (ellipticity, bulge fraction, size per
fraction, the flux prior's power and limits, the position prior's width) estimated from
the data by :func:`pylensfit.calibrate`. :data:`PRESETS` holds the named alternatives
(``pylensfit config --preset NAME`` prints one); a YAML file may name its preset with a
``preset:`` key, its other keys overriding it.

The modules, one per concern:

* :mod:`.fields`: the declarative tables, one per section: each parameter's name, type,
  default, allowed values or range, unit and description;
* :mod:`.sections`: the frozen dataclass of each section, generated from its table;
* :mod:`.validate`: the one validator driven by the tables, the few cross-field rules
  and the two normalisations :class:`Config` makes;
* :mod:`.core`: :class:`Config`, composed of the sections;
* :mod:`.presets`: the named configurations.
"""

from .core import Config
from .fields import OWNER, PARAMS, SECTIONS, Param, Section
from .presets import PRESETS
from .sections import (
    PSF,
    SECTION_CLASSES,
    Centring,
    Detection,
    Grid,
    Models,
    Neighbours,
    Numerics,
    Priors,
    Selection,
    Shear,
    Stamps,
)
from .validate import ConfigError

__all__ = ["OWNER", "PARAMS", "PRESETS", "PSF", "SECTIONS", "SECTION_CLASSES", "Centring",
           "Config", "ConfigError", "Detection", "Grid", "Models", "Neighbours", "Numerics",
           "Param", "Priors", "Section", "Selection", "Shear", "Stamps"]  # fmt: skip
