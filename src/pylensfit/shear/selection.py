"""The metacalibration estimator of a catalogue's shear, with the selection response.

A catalogue measured with ``Config.response = "metacal"`` (:func:`pylensfit.measure`)
holds each galaxy's posterior mean on its unsheared metacalibration image (``e1_mcal,
e2_mcal``), its measured response ``R_gamma`` (``R11 ... R22``) and, for each of the five
images (``noshear, 1p, 1m, 2p, 2m``), what a selection cuts on: the S/N of its most
likely model (``mcal_snr_<type>``) and whether its fit is usable (a bit of
``mcal_flags``). A cut made on the measured quantities is itself sheared: a galaxy
sheared along its shape is measured brighter, and passes a S/N cut more often. Sheldon &
Huff (2017, arXiv:1702.02601, section 4) measure that selection's response by making the
cut with each sheared image's quantities and averaging the *unsheared* shapes over it,

    R_S[i, j] = (<e_i>_{S(j+)} - <e_i>_{S(j-)}) / (2 delta),

and the shear of the sample selected with the unsheared quantities, ``S(noshear)``, is

    g = (<R_gamma>_{S(noshear)} + R_S)^-1 <e>_{S(noshear)}.

The cut (:func:`metacal_selections`) is the one the other estimators make (no flag, a
galaxy, ``model_SNratio >= Config.min_snr``), each of its decisions made on the image of
the branch: the catalogue's ``STAR`` and ``LOW_SNR`` bits (the unsheared fit's) are
replaced by each branch's point-source decision and S/N; every other bit of ``flags``
(the stamp's, the image's) is kept.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from astropy.table import Table

from ..flags import FLAGS, METACAL_FLAGS
from .fixed_point import ShearEstimate

__all__ = ["MetacalSample", "MetacalShear", "metacal_selections", "selection_response"]

#: the metacalibration's images, in the order of ``mcal_snr_<type>`` and the bits of
#: ``mcal_flags``
TYPES = ("noshear", "1p", "1m", "2p", "2m")


class MetacalShear(NamedTuple):
    """The metacalibration shear of a sample and its parts.

    Attributes
    ----------
    g : numpy.ndarray
        ``(2,)`` the shear estimate.
    g_err : numpy.ndarray
        ``(2,)`` its statistical error (the scatter of ``e`` over ``sqrt(n)``, through
        ``R^-1``).
    R_gamma : numpy.ndarray
        ``(2, 2)`` the mean measured response of the selected galaxies.
    R_S : numpy.ndarray
        ``(2, 2)`` the selection response.
    n : int
        The galaxies selected.
    """

    g: np.ndarray
    g_err: np.ndarray
    R_gamma: np.ndarray
    R_S: np.ndarray
    n: int

    def as_estimate(self) -> ShearEstimate:
        """The estimate as the other estimators give theirs."""
        return ShearEstimate(g1=float(self.g[0]), g2=float(self.g[1]),
                             g1_err=float(self.g_err[0]), g2_err=float(self.g_err[1]),
                             n=int(self.n))  # fmt: skip


def metacal_selections(table: Table, min_snr: float) -> dict[str, np.ndarray]:
    """The rows that each metacalibration image's quantities select.

    Parameters
    ----------
    table : astropy.table.Table
        A catalogue with the metacalibration's columns
        (:data:`pylensfit.catalogue.METACAL_COLUMNS`), and ``flags`` where it has one.
    min_snr : float
        The S/N cut, on each image's ``mcal_snr_<type>`` (``Config.min_snr``).

    Returns
    -------
    dict of numpy.ndarray
        ``(n,)`` bool per type (``noshear, 1p, 1m, 2p, 2m``): no flag but ``STAR`` and
        ``LOW_SNR``, metacalibrated, that image's fit usable (``mcal_flags``) and its S/N
        at least ``min_snr``, and a finite ``e1_mcal, e2_mcal``.
    """
    need = ["e1_mcal", "e2_mcal", "mcal_flags", *(f"mcal_snr_{t}" for t in TYPES)]
    missing = [c for c in need if c not in table.colnames]
    if missing:
        raise ValueError(f"the table has no metacalibration column {missing[0]!r}: measure "
                         "with Config(response='metacal')")  # fmt: skip
    base = np.isfinite(np.asarray(table["e1_mcal"], float)) & np.isfinite(
        np.asarray(table["e2_mcal"], float))
    if "flags" in table.colnames:
        own = FLAGS["STAR"][0] | FLAGS["LOW_SNR"][0]  # the unsheared fit's decisions
        base &= (np.asarray(table["flags"]) & ~own) == 0
    mf = np.asarray(table["mcal_flags"])
    out = {}
    for t in TYPES:
        bits = METACAL_FLAGS[t][0] | METACAL_FLAGS["NOT_METACALIBRATED"][0]
        snr = np.asarray(table[f"mcal_snr_{t}"], dtype=float)
        out[t] = base & ((mf & bits) == 0) & np.isfinite(snr) & (snr >= min_snr)
    return out


def selection_response(e: np.ndarray, selections: dict[str, np.ndarray],
                       step: float) -> np.ndarray:  # fmt: skip
    """The selection response ``R_S[i, j] = (<e_i>_{S(j+)} - <e_i>_{S(j-)}) / (2 step)``.

    Parameters
    ----------
    e : numpy.ndarray
        ``(n, 2)`` the unsheared images' shapes.
    selections : dict of numpy.ndarray
        ``(n,)`` bool, the rows selected with the quantities of the images ``1p, 1m, 2p,
        2m`` (:func:`metacal_selections`).
    step : float
        The images' shear ``delta``.

    Returns
    -------
    numpy.ndarray
        ``(2, 2)``; ``ValueError`` where a selection is empty.
    """
    e = np.asarray(e, dtype=float)
    R = np.empty((2, 2))
    for j, c in enumerate("12"):
        plus, minus = selections[f"{c}p"], selections[f"{c}m"]
        if not (plus.any() and minus.any()):
            raise ValueError("empty sample: a sheared image's selection holds no row")
        R[:, j] = (e[plus].mean(axis=0) - e[minus].mean(axis=0)) / (2.0 * step)
    return R


@dataclass(frozen=True)
class MetacalSample:
    """A catalogue's metacalibration inputs, read once for every group of its rows.

    Attributes
    ----------
    e : numpy.ndarray
        ``(n, 2)`` ``e1_mcal, e2_mcal``.
    R : numpy.ndarray
        ``(n, 2, 2)`` the measured responses ``R11 ... R22``.
    selections : dict of numpy.ndarray
        Each image's selection (:func:`metacal_selections`).
    step : float
        The images' shear ``delta``.
    """

    e: np.ndarray
    R: np.ndarray
    selections: dict[str, np.ndarray]
    step: float

    @classmethod
    def of(cls, table: Table, *, min_snr: float | None = None,
           step: float | None = None) -> MetacalSample:  # fmt: skip
        """The inputs of ``table``; ``min_snr`` defaults to its configuration's
        (``meta["config"].min_snr``; else 0, with a warning: a table read without
        :func:`pylensfit.read_catalogue` has lost it), ``step`` to
        ``meta["metacal_step"]``."""
        cfg = table.meta.get("config")
        if min_snr is None and cfg is None:
            warnings.warn("the table carries no configuration: no S/N cut (min_snr=0) in "
                          "the metacalibration's selection; read catalogues with "
                          "pylensfit.read_catalogue, or give min_snr", stacklevel=2)  # fmt: skip
        if min_snr is None:
            min_snr = float(cfg.min_snr) if cfg is not None else 0.0
        step = step if step is not None else table.meta.get(
            "metacal_step", None if cfg is None else cfg.metacal_step)
        if step is None or not step > 0:
            raise ValueError(f"the metacalibration's step must be given and > 0, got {step}")
        sel = metacal_selections(table, min_snr)
        e = np.column_stack([np.asarray(table["e1_mcal"], float),
                             np.asarray(table["e2_mcal"], float)])  # fmt: skip
        R = np.stack([np.column_stack([np.asarray(table[f"R{i}{j}"], float) for j in (1, 2)])
                      for i in (1, 2)], axis=1)  # fmt: skip
        return cls(e=e, R=R, selections=sel, step=float(step))

    def shear(self, rows: np.ndarray | None = None) -> MetacalShear:
        """The shear of the rows ``rows`` (a mask; default all) that the unsheared
        images select, with their selection response (module docstring)."""
        rows = np.ones(len(self.e), dtype=bool) if rows is None else np.asarray(rows, bool)
        sel = {t: s & rows for t, s in self.selections.items()}
        s0 = sel["noshear"]
        n = int(s0.sum())
        if n == 0:
            raise ValueError("empty sample: no row selected to estimate shear")
        withR = s0 & np.isfinite(self.R).all(axis=(1, 2))
        if not withR.any():
            raise ValueError("empty sample: no selected row with a measured response")
        R_gamma = self.R[withR].mean(axis=0)
        R_S = selection_response(self.e, sel, self.step)
        Rinv = np.linalg.inv(R_gamma + R_S)
        e = self.e[s0]
        g = Rinv @ e.mean(axis=0)
        C = np.cov(e.T) / n if n > 1 else np.full((2, 2), math.nan)
        err = np.sqrt(np.diag(Rinv @ C @ Rinv.T))
        return MetacalShear(g=g, g_err=err, R_gamma=R_gamma, R_S=R_S, n=n)

    def estimate(self, rows: np.ndarray) -> ShearEstimate:
        """:meth:`shear` of the rows ``rows``, as a :class:`ShearEstimate`."""
        return self.shear(rows).as_estimate()
