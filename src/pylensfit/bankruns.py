"""The runs of sizes of the model bank: which profiles the bank holds.

A run is one profile family, ``(1 - fraction) A + fraction B``, evaluated on the bank's
grid of sizes: the bulge+disc family's bulge fractions and the Sersic ladder's indices
(:class:`pylensfit.Config`'s ``model``, ``n_bulge_fractions``, ``bulge_size_ratio``,
``sersic_ladder``). This module holds only their description, so that
:class:`pylensfit.Config` can list its runs without importing the models themselves.
"""

from __future__ import annotations

from typing import NamedTuple

__all__ = ["DISC_HLR", "Run", "bank_runs"]

#: Half-light radius of the exponential disc in scale lengths.
DISC_HLR = 1.6783469900166608


class Run(NamedTuple):
    """One run of sizes of the model bank: the profile ``(1 - fraction) A + fraction B``.

    Both components have the model's ellipticity. ``A`` is a Sersic profile of index
    ``n_a`` and the disc's half-light radius (:data:`DISC_HLR` ``r``; for ``n_a = 1`` the
    exponential disc of scale length ``r``), ``B`` a Sersic profile of index ``n`` and
    half-light radius ``size * r``. The bulge+disc family's runs are ``Run(f, s)``: a de
    Vaucouleurs bulge (``n = 4``) of ``s`` disc scale lengths with flux fraction ``f``.
    The Sersic ladder (``Config.sersic_ladder``) adds ``Run(1, DISC_HLR, n)`` (a Sersic
    profile of the disc's half-light radius) and the half-and-half mixtures of adjacent
    indices. Profiles above ``n = 2`` are truncated at
    :data:`~pylensfit.models.DEVAUC_TRUNCATION` half-light radii.
    """

    fraction: float
    size: float
    n: float = 4.0
    n_a: float = 1.0

    @property
    def components(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """``((n_a, DISC_HLR), (n, size))``: each component's index and half-light radius
        per unit ``r``."""
        return (float(self.n_a), DISC_HLR), (float(self.n), float(self.size))

    @property
    def is_bulge_disc(self) -> bool:
        """A run of the bulge+disc family (an exponential disc and a de Vaucouleurs bulge)."""
        return self.n_a == 1.0 and self.n == 4.0 and self.size != DISC_HLR

    @property
    def bulge_fraction(self) -> float:
        """The bulge fraction of a bulge+disc run; not a number for the Sersic ladder's."""
        return self.fraction if self.is_bulge_disc else float("nan")

    def label(self, sized: bool = False) -> str:
        """How reports name the run: the bulge fraction (``"0.5"``; with ``sized`` and a
        bulge, ``"0.5 (bulge 0.6)"``), or ``"Sersic 2"`` / ``"Sersic 1+2"`` for the
        ladder's."""
        if self.is_bulge_disc:
            f = self.fraction
            return f"{f:g}" if f == 0 or not sized else f"{f:g} (bulge {self.size:g})"
        if self.fraction == 1.0:
            return f"Sersic {self.n:g}"
        return f"Sersic {self.n_a:g}+{self.n:g}"


def bank_runs(
    model: str,
    bulge_fraction: float,
    bulge_size_ratio: float,
    n_bulge: int = 1,
    bulge_size_ratio2: float = 0.0,
    sersic_ladder: tuple[float, ...] = (),
) -> tuple[Run, ...]:
    """The runs of sizes of a model bank, in the bank's column order.

    One run, the fixed ``bulge_fraction``, unless the fractions are marginalised
    (``n_bulge > 1``, ``"bulge+disc"``): then ``n_bulge`` fractions evenly spaced on [0, 1]
    with ``bulge_size_ratio``, with ``bulge_size_ratio2 > 0`` the fractions above 0 again
    with that bulge size (the pure disc has no bulge to size), and with ``sersic_ladder``
    its Sersic profiles and the half-and-half mixtures of adjacent indices, the disc's
    ``n = 1`` included among them (:class:`Run`).
    """
    if n_bulge == 1 or model != "bulge+disc":
        return (Run(float(bulge_fraction), float(bulge_size_ratio)),)
    fr = [k / (n_bulge - 1) for k in range(n_bulge)]
    runs = [Run(f, float(bulge_size_ratio)) for f in fr]
    if bulge_size_ratio2 > 0:
        runs += [Run(f, float(bulge_size_ratio2)) for f in fr[1:]]
    if sersic_ladder:
        ladder = sorted({1.0, *(float(v) for v in sersic_ladder)})
        for k, n in enumerate(ladder):  # each index's mixture with the one below, itself
            if k:
                runs.append(Run(0.5, DISC_HLR, n, ladder[k - 1]))
            if n != 1.0:  # the disc is already the first run
                runs.append(Run(1.0, DISC_HLR, n))
    return tuple(runs)
