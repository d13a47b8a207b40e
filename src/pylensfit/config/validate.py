"""The one validator of the configuration, driven by the tables of :mod:`.fields`.

:func:`coerce` reads a value as its parameter's type (from Python, YAML or a string),
:func:`validate_section` checks a section's values against the table (type, range,
allowed values) and then the section's few cross-field rules, each a small named
function of :data:`RULES`. :func:`normalise` applies the two documented normalisations
that :class:`pylensfit.Config` makes of the values it is given (and nothing else does).
"""

from __future__ import annotations

import numbers
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from .fields import SECTIONS, Param, in_bounds

__all__ = ["RULES", "ConfigError", "coerce", "normalise", "validate_section"]


class ConfigError(ValueError):
    """An invalid configuration value or file."""


# ---------------------------------------------------------------------------------------
# One parameter: type and range from its table row
# ---------------------------------------------------------------------------------------
def _as_bool(val: Any) -> bool:
    """``True``/``False``, 1/0 or the strings true/false, yes/no, on/off."""
    if isinstance(val, (bool, np.bool_)):
        return bool(val)
    if isinstance(val, numbers.Real) and val in (0, 1):
        return bool(val)
    words = {"true": True, "yes": True, "on": True, "1": True,
             "false": False, "no": False, "off": False, "0": False}  # fmt: skip
    if isinstance(val, str) and val.strip().lower() in words:
        return words[val.strip().lower()]
    raise ValueError(val)


def _as_floats(val: Any) -> tuple[float, ...]:
    """A tuple of floats from a sequence or a comma-separated string ``"0.5, 2, 4"``."""
    if isinstance(val, str):
        val = [v for v in val.replace("(", "").replace(")", "").split(",") if v.strip()]
    if isinstance(val, (bool, numbers.Number)):
        raise ValueError(val)
    return tuple(float(v) for v in val)


def _as_number(val: Any, typ: type) -> float | int:
    if isinstance(val, bool) or (hasattr(val, "dtype") and val.dtype.kind == "b"):
        raise ValueError(val)  # yes/no is no number
    num = float(val)
    if typ is int:
        if not num.is_integer():
            raise ValueError(val)
        return int(num)
    return num


def coerce(p: Param, val: Any) -> Any:
    """``val`` as parameter ``p``'s type: numbers of either kind (an int only if whole),
    yes/no strings for a bool, a sequence or comma-separated string for a tuple.

    Raises :class:`ConfigError` (``"configuration key 'x' must be int ..."``) if it is
    not one; the range is :func:`check`'s.
    """
    if val is None and p.optional:
        return None
    try:
        if p.type is bool:
            return _as_bool(val)
        if p.type in (int, float):
            return _as_number(val, p.type)
        if p.type is tuple:
            return _as_floats(val)
        if not isinstance(val, str):
            raise ValueError(val)
        return val
    except (TypeError, ValueError):
        where = f" in {p.allowed}" if p.bounds and p.type is not tuple else ""
        raise ConfigError(f"configuration key {p.name!r} must be {p.type_name}{where}, "
                          f"got {val!r}") from None  # fmt: skip


def _is_type(p: Param, val: Any) -> bool:
    if val is None:
        return p.optional
    if p.type is bool:
        return isinstance(val, bool)
    if p.type is int:
        return isinstance(val, numbers.Integral) and not isinstance(val, bool)
    if p.type is float:
        return isinstance(val, numbers.Real) and not isinstance(val, bool)
    if p.type is tuple:
        return isinstance(val, tuple) and all(_is_type(_ELEMENT, v) for v in val)
    return isinstance(val, p.type)


_ELEMENT = Param("element", float, 0.0, "")


def check(p: Param, val: Any) -> None:
    """Raise :class:`ConfigError` unless ``val`` is of ``p``'s type, in its range and among
    its allowed values; the message names the parameter and what it allows."""
    if not _is_type(p, val):
        where = f" in {p.allowed}" if p.allowed and p.type is not tuple else ""
        raise ConfigError(f"configuration key {p.name!r} must be {p.type_name}{where}, "
                          f"got {val!r}")  # fmt: skip
    if val is None:
        return
    if p.choices and val not in p.choices:
        raise ConfigError(f"{p.name} must be one of {p.allowed}, got {val!r}")
    if p.bounds:
        values = val if p.type is tuple else (val,)
        if not all(in_bounds(float(v), p.bounds) for v in values):
            what = "hold values" if p.type is tuple else "be"
            raise ConfigError(f"{p.name} must {what} in {p.bounds}, got {val!r}")


# ---------------------------------------------------------------------------------------
# The cross-field rules, one small function each, by section
# ---------------------------------------------------------------------------------------
def _need(ok: bool, msg: str) -> None:
    if not ok:
        raise ConfigError(msg)


def tiers_are_multiples(v: Mapping[str, Any]) -> None:
    """The stamp tiers are whole multiples of the base stamp, above it (or none: 0)."""
    top, base = v["max_stamp_size"], v["stamp_size"]
    _need(top == 0 or (top > base and top % base == 0),
          f"max_stamp_size must be 0 or a multiple of stamp_size ({base}) above it, got "
          f"{top}")  # fmt: skip


def sizes_ordered(v: Mapping[str, Any]) -> None:
    """The size grid runs from r_min up to r_max."""
    _need(v["r_min"] < v["r_max"],
          f"need r_min < r_max, got {v['r_min']}, {v['r_max']}")  # fmt: skip


def fractions_need_bulge_disc(v: Mapping[str, Any]) -> None:
    """Only the bulge+disc model has fractions to marginalise over."""
    _need(v["n_bulge_fractions"] == 1 or v["model"] == "bulge+disc",
          "n_bulge_fractions > 1 needs model 'bulge+disc'")  # fmt: skip


def second_bulge_size(v: Mapping[str, Any]) -> None:
    """A second bulge size needs marginalised fractions, and differs from the first."""
    r2 = v["bulge_size_ratio2"]
    _need(r2 == 0 or (v["model"] == "bulge+disc" and v["n_bulge_fractions"] >= 2),
          "bulge_size_ratio2 > 0 needs model 'bulge+disc' with n_bulge_fractions >= 2")
    _need(r2 != v["bulge_size_ratio"],
          "bulge_size_ratio2 must differ from bulge_size_ratio (0: no second size)")


def sersic_ladder_rungs(v: Mapping[str, Any]) -> None:
    """The Sersic ladder needs marginalised fractions; its indices are distinct, not 1."""
    ladder = v["sersic_ladder"]
    _need(not ladder or (v["model"] == "bulge+disc" and v["n_bulge_fractions"] >= 2),
          "sersic_ladder needs model 'bulge+disc' with n_bulge_fractions >= 2")
    _need(1.0 not in ladder and len(set(ladder)) == len(ladder),
          f"sersic_ladder must hold distinct Sersic indices in [0.3, 6.2] other than the "
          f"disc's 1, got {ladder}")  # fmt: skip


def flux_limits_ordered(v: Mapping[str, Any]) -> None:
    """The flux prior's lower limit lies below its upper one."""
    _need(v["amplitude_prior_min"] < v["amplitude_prior_max"],
          "need 0 <= amplitude_prior_min < amplitude_prior_max")


def spline_prior_is_direct(v: Mapping[str, Any]) -> None:
    """The spline ellipticity prior is estimated by maximum marginal likelihood."""
    _need(v["prior_form"] == "functional" or v["prior_method"] == "direct",
          "prior_form 'spline' is estimated with prior_method 'direct'")


#: the cross-field rules of each section, checked after its parameters
RULES: dict[str, tuple[Callable[[Mapping[str, Any]], None], ...]] = {
    "stamps": (tiers_are_multiples,),
    "grid": (sizes_ordered,),
    "models": (fractions_need_bulge_disc, second_bulge_size, sersic_ladder_rungs),
    "priors": (flux_limits_ordered, spline_prior_is_direct),
}

_PARAMS = {s.name: s.params for s in SECTIONS}


def validate_section(section: str, values: Mapping[str, Any]) -> None:
    """Check a section's ``values`` (one for each of its parameters): each against its
    table row, then the section's :data:`RULES`."""
    for p in _PARAMS[section]:
        check(p, values[p.name])
    for rule in RULES.get(section, ()):
        rule(values)


# ---------------------------------------------------------------------------------------
# The normalisations Config makes (each stated in its parameters' docs)
# ---------------------------------------------------------------------------------------
def round_stamp_tiers(v: dict[str, Any]) -> None:
    """max_stamp_size is rounded down to a multiple of stamp_size; below twice
    stamp_size it is 0 (one stamp for all)."""
    base, top = v["stamp_size"], v["max_stamp_size"]
    if (isinstance(base, int) and isinstance(top, int) and not isinstance(top, bool)
            and base >= 8 and top > 0):
        top = top // base * base
        v["max_stamp_size"] = top if top > base else 0


def single_profile(v: dict[str, Any]) -> None:
    """A model other than bulge+disc has one profile: n_bulge_fractions 1,
    bulge_size_ratio2 0, sersic_ladder ()."""
    if v["model"] != "bulge+disc":
        v.update(n_bulge_fractions=1, bulge_size_ratio2=0.0, sersic_ladder=())


#: what :class:`pylensfit.Config` normalises in each section before validating it
NORMALISE: dict[str, tuple[Callable[[dict[str, Any]], None], ...]] = {
    "stamps": (round_stamp_tiers,),
    "models": (single_profile,),
}


def normalise(section: str, values: Mapping[str, Any]) -> dict[str, Any]:
    """A copy of a section's ``values`` with its :data:`NORMALISE` steps applied."""
    out = dict(values)
    for step in NORMALISE.get(section, ()):
        step(out)
    return out
