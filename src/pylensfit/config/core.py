""":class:`Config`: the settings of a run, composed of the sections of :mod:`.sections`."""

from __future__ import annotations

import difflib
import operator
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from ..bankruns import bank_runs
from .fields import OWNER, PARAMS, SECTIONS
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
from .validate import ConfigError, coerce, normalise

__all__ = ["Config"]


def unknown_keys_error(unknown: list[str], known: list[str], where: str = "") -> ConfigError:
    """One line: the keys (at most three named) and the closest known ones (the three
    closest to a single key, the closest to each of two or three)."""
    unknown = sorted(unknown, key=str)
    shown = unknown[:3]
    n_close = 3 if len(unknown) == 1 else 1 if len(unknown) <= 3 else 0
    said = []
    for u in shown:
        close = difflib.get_close_matches(str(u), known, n=n_close) if n_close else []
        said.append(f"{u!r}" + (f" (did you mean {' or '.join(map(repr, close))}?)"
                                 if close else ""))  # fmt: skip
    more = f" and {len(unknown) - len(shown)} more" if len(unknown) > len(shown) else ""
    return ConfigError(f"unknown configuration key{'s' if len(unknown) > 1 else ''} "
                       f"{', '.join(said)}{more}{where}; `pylensfit config` lists them "
                       "all")  # fmt: skip


def _section_values(name: str, given: Any) -> dict[str, Any]:
    """The values a section keyword gives: a section object's, or a mapping's (coerced)."""
    cls = SECTION_CLASSES[name]
    if isinstance(given, cls):
        return {p.name: getattr(given, p.name) for p in _SECTION[name].params}
    if not isinstance(given, Mapping):
        raise ConfigError(f"configuration section {name!r} must be a {cls.__name__} or a "
                          f"mapping, got {given!r}")  # fmt: skip
    own = [p.name for p in _SECTION[name].params]
    bad = [k for k in given if k not in own]
    if bad:
        raise unknown_keys_error(bad, own, f" in section {name!r}")
    return {k: coerce(PARAMS[k], v) for k, v in given.items()}


_SECTION = {s.name: s for s in SECTIONS}


@dataclass(frozen=True, init=False, repr=False)
class Config:
    """Settings of a pylensfit run; the defaults are the recommended method.

    A configuration is made of sections, each owning its parameters: ``stamps``,
    ``grid``, ``models``, ``priors``, ``centring``, ``numerics``, ``shear``,
    ``selection``, ``detection``, ``psf`` and ``neighbours`` (the :ref:`config-reference`
    lists them). ``cfg.grid.e_step`` reads a parameter through its section;
    ``cfg.e_step`` is the shortcut, and ``Config(e_step=0.05)`` sets one by its name
    (a section may be given whole as well: ``Config(grid=Grid(e_step=0.05))`` or
    ``Config(grid={"e_step": 0.05})``, the flat keywords winning).

    Values are read as their parameter's type (a whole float as an int, ``"yes"`` as
    ``True``, a list or ``"0.5, 2, 4"`` as a tuple) and validated once, when the object is
    made, against the tables of :mod:`pylensfit.config.fields`. Two normalisations are
    made, stated in the parameters' descriptions: ``max_stamp_size`` is rounded down to a
    multiple of ``stamp_size`` (0 below twice it), and a model other than ``bulge+disc``
    takes ``n_bulge_fractions=1``, ``bulge_size_ratio2=0`` and ``sersic_ladder=()``.

    :meth:`paper` gives Kitching et al. (2008, "Bayesian galaxy shape measurement for
    weak lensing surveys II", arXiv:0802.1528)'s setup instead, :meth:`preset` any of
    :data:`PRESETS`. Use :meth:`describe` for the documentation of every parameter.
    """

    stamps: Stamps
    grid: Grid
    models: Models
    priors: Priors
    centring: Centring
    numerics: Numerics
    shear: Shear
    selection: Selection
    detection: Detection
    psf: PSF
    neighbours: Neighbours

    def __init__(self, **values: Any) -> None:
        given = {name: {} for name in SECTION_CLASSES}
        unknown = [k for k in values if k not in SECTION_CLASSES and k not in OWNER]
        if unknown:
            raise unknown_keys_error(unknown, list(OWNER))
        for name in SECTION_CLASSES:  # whole sections first, the flat keywords win
            if name in values:
                given[name].update(_section_values(name, values[name]))
        for key, val in values.items():
            if key in OWNER:
                given[OWNER[key]][key] = coerce(PARAMS[key], val)
        for name, cls in SECTION_CLASSES.items():
            vals = {p.name: p.default for p in _SECTION[name].params}
            vals.update(given[name])
            object.__setattr__(self, name, cls(**normalise(name, vals)))

    def __repr__(self) -> str:
        diff = {k: v for k, v in self.to_dict().items()
                if v != (list(PARAMS[k].default) if PARAMS[k].type is tuple
                         else PARAMS[k].default)}  # fmt: skip
        return f"Config({', '.join(f'{k}={v!r}' for k, v in diff.items())})"

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

    # ------------------------------------------------------------------ derived
    @property
    def largest_stamp(self) -> int:
        """The largest stamp side a galaxy is fitted on (``max_stamp_size``, or
        ``stamp_size`` without tiers): the size stamps and PSF images should have."""
        return self.stamps.max_stamp_size or self.stamps.stamp_size

    @property
    def output_e_step(self) -> float:
        """The cell side of the likelihood grid that :func:`~pylensfit.fit_stamps` returns
        (``e_step / e_refine``)."""
        return self.grid.e_step / self.grid.e_refine

    @property
    def bulge_runs(self):
        """The profile of each run of sizes of the model bank
        (:func:`pylensfit.bankruns.bank_runs`: ``Run(fraction, bulge size, ...)``):
        ``n_bulge_fractions`` fractions evenly spaced on [0, 1] with ``bulge_size_ratio``,
        then with ``bulge_size_ratio2 > 0`` the fractions above 0 again with that size,
        then the Sersic ladder's (one run, the fixed ``bulge_fraction``, unless the
        fractions are marginalised)."""
        m = self.models
        return bank_runs(m.model, float(m.bulge_fraction), float(m.bulge_size_ratio),
                         int(m.n_bulge_fractions), float(m.bulge_size_ratio2),
                         tuple(m.sersic_ladder))  # fmt: skip

    @property
    def run_labels(self) -> list[str]:
        """How reports name each of :attr:`bulge_runs` (``Run.label``)."""
        sized = self.models.bulge_size_ratio2 > 0 or bool(self.models.sersic_ladder)
        return [run.label(sized) for run in self.bulge_runs]

    @property
    def output_refine(self) -> int:
        """``integration_refine`` on the output grid: the Bayesian integrals run on cells
        of ``e_step / integration_refine`` whatever ``e_refine`` is (at least the output
        grid's own cells)."""
        return max(1, self.shear.integration_refine // self.grid.e_refine)

    # ------------------------------------------------------------------ conversions
    @classmethod
    def describe(cls) -> dict[str, tuple[Any, str]]:
        """``{name: (default, description)}`` for every parameter, section by section."""
        return {p.name: (p.default, p.doc) for s in SECTIONS for p in s.params}

    def to_dict(self) -> dict[str, Any]:
        """Plain flat ``dict`` of the parameters, section by section (for headers and YAML;
        sequences as lists)."""
        return {k: v for name in SECTION_CLASSES
                for k, v in getattr(self, name).to_dict().items()}  # fmt: skip

    def replace(self, **overrides: Any) -> Config:
        """A copy with some parameters (or whole sections) changed, validated."""
        base = self.to_dict()
        for name in SECTION_CLASSES:  # a section given whole replaces its parameters
            if name in overrides:
                for p in _SECTION[name].params:
                    base.pop(p.name, None)
        return self.from_dict({**base, **overrides})

    @classmethod
    def from_dict(cls, values: Mapping[str, Any] | None = None, **overrides: Any) -> Config:
        """Build from a flat mapping (or one of sections), with a ``preset`` key naming
        the preset that the other keys override; unknown keys get a clear message."""
        values = {**(values or {}), **overrides}
        if "preset" in values:  # a named preset, the other keys overriding it
            name = values.pop("preset")
            if name not in PRESETS:
                raise ConfigError(f"unknown preset {name!r}; known: {sorted(PRESETS)}")
            values = {**PRESETS[name][0], **values}
        return cls(**{str(k): v for k, v in values.items()})

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
        """Write the parameters as flat YAML."""
        Path(path).write_text(yaml.safe_dump(self.to_dict(), sort_keys=False))


# the flat shortcut: cfg.e_step reads cfg.grid.e_step
def _flat_doc(name: str) -> str:
    p = PARAMS[name]
    unit = f", {p.unit}" if p.unit else ""
    doc = p.doc.replace("|", "\\|")  # |e| is no reStructuredText substitution
    return f"{doc} Default {p.default!r}{unit}; ``cfg.{OWNER[name]}.{name}``."


for _name, _owner in OWNER.items():
    setattr(Config, _name, property(operator.attrgetter(f"{_owner}.{_name}"),
                                    doc=_flat_doc(_name)))  # fmt: skip
del _name, _owner
