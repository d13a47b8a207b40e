"""The sections of :class:`pylensfit.Config`: one frozen dataclass per table of
:mod:`.fields`, generated from it.

Each section owns its parameters: ``Grid(e_step=0.05)`` is checked against the grid's
table and cross-field rules when it is made (:func:`.validate.validate_section`), and
changes nothing it is given. ``cfg.grid`` is the section of a configuration.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from .fields import SECTIONS, Section
from .validate import validate_section

__all__ = ["SECTION_CLASSES", "Centring", "Detection", "Grid", "Models", "Neighbours",
           "Numerics", "PSF", "Priors", "Selection", "Shear", "Stamps"]  # fmt: skip


def _post_init(self) -> None:
    validate_section(self.section, self.__dict__)


def _to_dict(self) -> dict[str, Any]:
    """Plain ``dict`` of the section's parameters (sequences as lists)."""
    return {f.name: list(v) if isinstance(v, tuple) else v
            for f in dataclasses.fields(self) for v in [getattr(self, f.name)]}  # fmt: skip


def _class_doc(section: Section) -> str:
    lines = [f"{section.title}: {section.doc}", "", "Parameters", "----------"]
    for p in section.params:
        unit = f", {p.unit}" if p.unit else ""
        lines += [f"{p.name} : {p.type_name}, default {p.default!r}{unit}", f"    {p.doc}"]
    return "\n".join(lines).replace("|", "\\|")  # |e| is no reStructuredText substitution


def make_section(section: Section, cls_name: str) -> type:
    """The frozen dataclass of ``section``'s table: one field per parameter, its default
    and its row (``metadata["param"]``), validated when made."""
    specs = [(p.name, p.type if not p.optional else p.type | None,
              dataclasses.field(default=p.default, metadata={"param": p, "doc": p.doc}))
             for p in section.params]  # fmt: skip
    cls = dataclasses.make_dataclass(
        cls_name, specs, frozen=True,
        namespace={"__post_init__": _post_init, "to_dict": _to_dict,
                   "section": section.name, "__doc__": _class_doc(section),
                   "__module__": __name__},
    )  # fmt: skip
    return cls


Stamps = make_section(SECTIONS[0], "Stamps")
Grid = make_section(SECTIONS[1], "Grid")
Models = make_section(SECTIONS[2], "Models")
Priors = make_section(SECTIONS[3], "Priors")
Centring = make_section(SECTIONS[4], "Centring")
Numerics = make_section(SECTIONS[5], "Numerics")
Shear = make_section(SECTIONS[6], "Shear")
Selection = make_section(SECTIONS[7], "Selection")
Detection = make_section(SECTIONS[8], "Detection")
PSF = make_section(SECTIONS[9], "PSF")
Neighbours = make_section(SECTIONS[10], "Neighbours")

#: section name -> its dataclass, in the order of :data:`.fields.SECTIONS`
SECTION_CLASSES: dict[str, type] = {
    c.section: c for c in (Stamps, Grid, Models, Priors, Centring, Numerics, Shear,
                           Selection, Detection, PSF, Neighbours)
}  # fmt: skip
if list(SECTION_CLASSES) != [s.name for s in SECTIONS]:
    raise RuntimeError("the section classes are out of the tables' order")
