"""The shear of every group of a catalogue's rows, in a table (:func:`shear_table`).

The groups are the distinct values of a column, bins of another, and all the rows;
each gets :func:`~pylensfit.shear.estimate_shear`'s estimate, the fixed point reading the
catalogue's inputs once (:class:`~pylensfit.shear.estimate.FixedPointSample`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
from astropy.table import Table

from ..prior import Prior
from .estimate import FixedPointSample, estimate_shear
from .fixed_point import ShearEstimate
from .selection import MetacalSample


class Group(NamedTuple):
    """A group of a catalogue's rows: its name in :func:`shear_table` and its rows."""

    name: str
    #: ``(n,)`` a mask of the table's rows
    rows: np.ndarray


def shear_table(
    shapes_table: Table,
    *,
    by: str | None = None,
    column: str | None = None,
    edges: Sequence[float] | None = None,
    estimator: str = "fixed-point",
    prior: Prior | None = None,
    egrid: np.ndarray | None = None,
    refine: int | None = None,
    weighted: bool = False,
    min_snr: float | None = None,
    step: float | None = None,
) -> Table:
    """Shear of every group of a catalogue, with errors (:func:`estimate_shear` per group).

    Parameters
    ----------
    shapes_table : astropy.table.Table
        A table with ``e1, e2, sens1, sens2`` and, optionally, ``flags`` (the output of
        :func:`shapes` or :func:`pylensfit.measure`).
    by : str, optional
        Column whose distinct values define the groups (e.g. ``"image"``).
    column, edges : str and sequence of float, optional
        Bin the rows by ``column`` with bin ``edges`` (e.g. magnitude bins); rows
        outside the edges are left out of the binned rows.

    estimator : {"fixed-point", "key2", "metacal"}
        ``"fixed-point"`` (default): :func:`shear_fixed_point` on its ``lnL`` column (a
        2-D column of ln L grids, as in :func:`pylensfit.measure`'s catalogue) with
        ``prior`` and ``egrid``, rows with ``flags != 0`` (or ``weight == 0``) left out;
        ``"key2"``: :func:`estimate_shear` with ``estimator="key2"`` on the table's ``e1,
        e2, sens1, sens2``; ``"metacal"``: the metacalibration's ``<R_gamma + R_S>^-1
        <e_mcal>`` with the selection response, the cut made on each metacalibration
        image's S/N and fit (:mod:`pylensfit.shear.selection`; a catalogue measured with
        ``Config.response = "metacal"``).
    prior, egrid, refine
        For ``"fixed-point"`` (default: the table's ``meta``).
    weighted : bool
        Weight the galaxies by the ``weight`` column (:func:`estimate_shear`; not with
        ``"metacal"``).
    min_snr, step : float, optional
        For ``"metacal"``: the S/N cut and the images' shear (default: the table's
        configuration's ``min_snr`` and ``metacal_step``).

    Returns
    -------
    astropy.table.Table
        One row per group (then per bin) and a last row ``all``: ``group``, ``n``,
        ``g1, g1_err, g2, g2_err``. A group with no usable row has ``n = 0`` and NaN.
    """
    groups = [*_groups_by(shapes_table, by), *_bins_of(shapes_table, column, edges),
              Group("all", np.ones(len(shapes_table), dtype=bool))]  # fmt: skip
    if estimator not in ("key2", "fixed-point", "metacal"):
        raise ValueError(f"estimator must be 'key2', 'fixed-point' or 'metacal', got "
                         f"{estimator!r}")  # fmt: skip
    if estimator == "metacal":
        if weighted:
            raise ValueError("the metacal estimator weighs every selected galaxy equally")
        return _shear_rows(groups, MetacalSample.of(shapes_table, min_snr=min_snr,
                                                    step=step).estimate)  # fmt: skip
    if estimator == "fixed-point":
        sample = FixedPointSample.of(shapes_table, prior=prior, egrid=egrid, refine=refine,
                                     weighted=weighted)  # fmt: skip
        return _shear_rows(groups, sample.estimate)
    return _shear_rows(groups, lambda rows: estimate_shear(shapes_table[rows], estimator="key2",
                                                           weighted=weighted))  # fmt: skip


def _groups_by(table: Table, by: str | None) -> list[Group]:
    """One group per distinct value of the column ``by`` (none for ``None``)."""
    if by is None:
        return []
    if by not in table.colnames:
        raise ValueError(f"the table has no column {by!r} to group by")
    vals = np.asarray(table[by])
    return [Group(f"{by}={v}", vals == v) for v in np.unique(vals)]


def _bins_of(table: Table, column: str | None, edges: Sequence[float] | None) -> list[Group]:
    """One group per bin of ``column`` between ``edges`` (none for ``column=None``)."""
    if column is None:
        return []
    if column not in table.colnames:
        raise ValueError(f"the table has no column {column!r} to bin by")
    try:
        e = np.asarray(edges, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"bin edges must be numbers, got {edges!r}") from None
    if e.ndim != 1 or e.size < 2 or not np.all(np.isfinite(e)) or np.any(np.diff(e) <= 0):
        raise ValueError(f"bin edges must be at least two finite increasing numbers, got "
                         f"{e.tolist()}")  # fmt: skip
    v = np.asarray(table[column])
    if v.ndim != 1:
        raise ValueError(f"column {column!r} holds arrays of shape {v.shape[1:]}, not one "
                         "number per row: cannot bin by it")  # fmt: skip
    if not (np.issubdtype(v.dtype, np.number) or np.issubdtype(v.dtype, np.bool_)):
        raise ValueError(f"column {column!r} is not numeric ({v.dtype}): cannot bin by it")
    v = v.astype(float)
    return [Group(f"{lo:g}<={column}<{hi:g}", (v >= lo) & (v < hi))
            for lo, hi in zip(e[:-1], e[1:], strict=True)]  # fmt: skip


def _shear_rows(groups: list[Group], one: Callable[[np.ndarray], ShearEstimate]) -> Table:
    """The table of :func:`shear_table`: ``one`` on each group's rows (``n = 0`` and NaN
    where it finds no usable row)."""
    rows = []
    for name, sel in groups:
        try:
            g = one(sel)
            rows.append((name, g.n, g.g1, g.g1_err, g.g2, g.g2_err))
        except ValueError:
            rows.append((name, 0, np.nan, np.nan, np.nan, np.nan))
    return Table(rows=rows, names=("group", "n", "g1", "g1_err", "g2", "g2_err"))
