"""The shear of a catalogue: :func:`estimate_shear`, by the fixed point or by the
paper's mean shear over mean sensitivity (``"key2"``).

:class:`FixedPointSample` reads a catalogue's inputs to the fixed point once (its
``lnL`` grids, prior, grid, usable rows, weights and frames), so that
:func:`pylensfit.shear.shear_table` estimates every group of rows from it;
:func:`key2_shear` is the ``"key2"`` estimator on a table's columns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from astropy.table import Table

from ..grid import DEFAULT_REFINE
from ..prior import Prior, RadialPrior
from ..skyframe import SkyFrame
from .fixed_point import ShearEstimate, shear_fixed_point
from .frames import rows_frame, table_frame


def estimate_shear(
    shapes_table: Table,
    *,
    estimator: str = "fixed-point",
    prior: Prior | None = None,
    egrid: np.ndarray | None = None,
    refine: int | None = None,
    e1_col: str = "e1",
    e2_col: str = "e2",
    sens1_col: str = "sens1",
    sens2_col: str = "sens2",
    flags_col: str = "flags",
    weight_col: str = "weight",
    weighted: bool = False,
) -> ShearEstimate:
    """Shear of a sample of galaxies.

    ``estimator="fixed-point"`` (the default): :func:`shear_fixed_point`, the shear
    ``g`` at which the posterior means under the prior sheared by ``g`` average to
    ``g``, exact to all orders in ``g``; it needs the table's ``lnL`` column and the
    ellipticity prior and grid (``meta["prior"]``, ``meta["egrid"]`` and
    ``meta["refine"]`` of :func:`pylensfit.measure_stamps`' table and of
    :func:`pylensfit.measure`'s catalogue, or given here).

    ``estimator="key2"``: Kitching et al. (2008)'s mean shear over mean sensitivity
    (section 3.3; docs: method, eq-key2), ``g_i = sum_a <e_i>_a / sum_a d<e_i>_a/dg_i``,
    high by a factor ``1 + |g|^2`` (``m ~ +8e-4`` at ``g = (0.02, 0.02)``), with the error
    of paper section 4.1, ``sigma / sqrt(N)`` in the form
    ``std_a(<e_i>_a) sqrt(N) / sum_a d<e_i>_a/dg_i``; it needs only ``e1, e2, sens1,
    sens2``, as :func:`shapes` gives them. Rows with a nonzero flag (when the table has
    ``flags_col``), a zero weight (when it has ``weight_col``) or non-finite values are
    skipped.

    A catalogue of :func:`pylensfit.measure` gives its shapes in the sky frame
    (:mod:`pylensfit.skyframe`); the fixed point then works image by image in each
    image's pixel frame (its ``lnL`` grids') and returns the sky-frame shear, and
    ``"key2"`` uses the sky-frame ``e1, e2, sens1, sens2`` as they are. With
    ``weighted=True`` each galaxy counts with its ``weight_col`` value (the inverse-variance
    weight, :func:`pylensfit.weights.lensfit_weights`): ``sum_a w_a (<e>_a(P_g) - g) = 0``
    for the fixed point, ``sum w e / sum w sens`` for ``"key2"``.

    Parameters
    ----------
    shapes_table : astropy.table.Table
        :func:`pylensfit.measure_stamps`' table, a catalogue of :func:`pylensfit.measure`,
        or (``"key2"``) the output of :func:`shapes`.
    estimator : {"fixed-point", "key2"}
        The estimator.
    prior, egrid, refine
        For ``"fixed-point"``: the ellipticity prior, grid and integration refinement
        (default: the table's ``meta``).
    e1_col, e2_col, sens1_col, sens2_col, flags_col, weight_col : str
        Column names.
    weighted : bool
        Weight each galaxy by its ``weight_col`` (default: every usable galaxy equally).

    Returns
    -------
    ShearEstimate

    Raises
    ------
    ValueError
        On a missing column or prior, an empty sample (no usable row), or a sum of
        sensitivities that is not positive.
    """
    if estimator not in ("fixed-point", "key2"):
        raise ValueError(f"estimator must be 'fixed-point' or 'key2', got {estimator!r}")
    if estimator == "key2":
        return key2_shear(shapes_table, (e1_col, e2_col, sens1_col, sens2_col),
                          flags_col=flags_col, weight_col=weight_col,
                          weighted=weighted)  # fmt: skip
    sample = FixedPointSample.of(shapes_table, prior=prior, egrid=egrid, refine=refine,
                                 flags_col=flags_col, weight_col=weight_col,
                                 weighted=weighted)  # fmt: skip
    if not sample.usable.any():
        raise ValueError("empty sample: no usable (unflagged, weighted) row to estimate shear")
    return sample.estimate(sample.usable)


def _usable_rows(table: Table, flags_col: str, weight_col: str) -> np.ndarray:
    """The rows of ``table`` with no flag and a positive weight (where it has the
    columns)."""
    use = np.ones(len(table), dtype=bool)
    if flags_col in table.colnames:
        use &= np.asarray(table[flags_col]) == 0
    if weight_col in table.colnames:
        use &= np.asarray(table[weight_col], dtype=float) > 0
    return use


def _weights(table: Table, col: str, weighted: bool) -> np.ndarray | None:
    """The weights ``table[col]`` where ``weighted``, else None."""
    if not weighted:
        return None
    if col not in table.colnames:
        raise ValueError(f"weighted=True needs the table's {col!r} column")
    return np.asarray(table[col], dtype=float)


@dataclass(frozen=True)
class FixedPointSample:
    """A catalogue's inputs to :func:`shear_fixed_point`, read once for every group of
    its rows.

    Attributes
    ----------
    lnL : numpy.ndarray
        ``(n, n_e)`` the table's ``lnL`` column.
    egrid : numpy.ndarray
        ``(n_e, 2)`` the ellipticity grid.
    prior : RadialPrior
        The ellipticity prior.
    refine : int
        The integration grid's refinement.
    usable : numpy.ndarray
        ``(n,)`` the rows with no flag and a positive weight.
    weights : numpy.ndarray or None
        ``(n,)`` each row's weight (``weighted``), or None.
    frame : SkyFrame or None
        Each row's sky frame, None in the pixel frame.
    groups : numpy.ndarray or None
        ``(n,)`` each row's image, with ``frame``.
    """

    lnL: np.ndarray
    egrid: np.ndarray
    prior: RadialPrior
    refine: int
    usable: np.ndarray
    weights: np.ndarray | None
    frame: SkyFrame | None
    groups: np.ndarray | None

    @classmethod
    def of(cls, table: Table, *, prior: RadialPrior | None = None,
           egrid: np.ndarray | None = None, refine: int | None = None,
           flags_col: str = "flags", weight_col: str = "weight",
           weighted: bool = False) -> FixedPointSample:  # fmt: skip
        """The inputs of ``table``; ``prior``, ``egrid`` and ``refine`` default to its
        ``meta``, the weights are its ``weight_col`` where ``weighted``.

        Raises
        ------
        ValueError
            Without an ``lnL`` column, a prior or a grid, or with ``weighted`` and no
            ``weight_col``.
        """
        meta = table.meta
        prior = prior if prior is not None else meta.get("prior")
        egrid = egrid if egrid is not None else meta.get("egrid")
        if "lnL" not in table.colnames or not isinstance(prior, RadialPrior) or egrid is None:
            raise ValueError("the fixed-point estimator needs the table's lnL column and its "
                             "prior and egrid (measure_stamps' table, a measure catalogue, or "
                             "prior= and egrid=); for shapes()' output use estimator='key2'")
        frame, groups = table_frame(table)
        return cls(lnL=np.asarray(table["lnL"]), egrid=np.asarray(egrid, dtype=float),
                   prior=prior, refine=int(refine if refine is not None
                                           else meta.get("refine", DEFAULT_REFINE)),
                   usable=_usable_rows(table, flags_col, weight_col),
                   weights=_weights(table, weight_col, weighted), frame=frame,
                   groups=groups)  # fmt: skip

    def estimate(self, rows: np.ndarray) -> ShearEstimate:
        """:func:`shear_fixed_point` on the usable rows among ``rows`` (a mask)."""
        u = rows & self.usable
        return shear_fixed_point(
            self.lnL[u], self.egrid, self.prior, refine=self.refine,
            weights=None if self.weights is None else self.weights[u],
            frame=None if self.frame is None else rows_frame(self.frame, u),
            groups=None if self.groups is None else self.groups[u])  # fmt: skip


def key2_shear(table: Table, columns: tuple[str, str, str, str], *, flags_col: str = "flags",
               weight_col: str = "weight", weighted: bool = False) -> ShearEstimate:  # fmt: skip
    """:func:`estimate_shear` with ``estimator="key2"`` on the ``columns`` ``e1, e2,
    sens1, sens2`` of ``table``."""
    for c in columns:
        if c not in table.colnames:
            raise ValueError(f"the table has no column {c!r}")
    e1, e2, s1, s2 = (np.asarray(table[c], dtype=float) for c in columns)
    use = np.isfinite(e1) & np.isfinite(e2) & np.isfinite(s1) & np.isfinite(s2)
    use &= _usable_rows(table, flags_col, weight_col)
    w = _weights(table, weight_col, weighted)
    if w is not None:
        use &= np.isfinite(w) & (w > 0)
    n = int(np.count_nonzero(use))
    if n == 0:
        raise ValueError("empty sample: no usable (unflagged, finite) row to estimate shear")
    wu = None if w is None else w[use]
    g1, g1_err = _key2_component(e1[use], s1[use], wu, "sens1")
    g2, g2_err = _key2_component(e2[use], s2[use], wu, "sens2")
    return ShearEstimate(g1=g1, g2=g2, g1_err=g1_err, g2_err=g2_err, n=n)


def _key2_component(e: np.ndarray, s: np.ndarray, w: np.ndarray | None,
                    name: str) -> tuple[float, float]:  # fmt: skip
    """One component's ``g = sum w e / sum w s`` and its error (``name``: the
    sensitivity's column, for the message)."""
    n = e.size
    if w is not None:
        ssum = float(np.sum(w * s))
        if not ssum > 0:
            raise ValueError(f"the weighted sum of the sensitivities ({name}) is not "
                             f"positive: {ssum}")  # fmt: skip
        g = float(np.sum(w * e)) / ssum
        err = float(np.sqrt(np.sum(w**2 * (e - g * s) ** 2))) / ssum if n > 1 else math.nan
        return g, err
    ssum = float(np.sum(s))
    if not ssum > 0:
        raise ValueError(f"the sum of the sensitivities ({name}) is not positive: {ssum}")
    g = float(np.sum(e)) / ssum
    err = float(np.std(e, ddof=1)) * math.sqrt(n) / ssum if n > 1 else math.nan
    return g, err
