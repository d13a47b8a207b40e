"""The result of a fit, :class:`StampFits`: one row per stamp, and its FITS file."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.table import Table

from .._util import atomic_write


@dataclass
class StampFits:
    """Result of :func:`fit_stamps`: one row per stamp.

    Attributes
    ----------
    egrid : numpy.ndarray
        ``(n_e, 2)`` ellipticity cell centres.
    lnL : numpy.ndarray
        ``(n, n_e)`` float32 ``ln L(e)`` summed over r, each row shifted so that its
        maximum is 0; NaN rows for stamps that could not be fitted (see ``flags``).
    lnL_peak : numpy.ndarray
        ``(n,)`` the shift removed from each row (the maximum of the unnormalised
        ``ln L(e)``, up to a constant common to all stamps of one noise level and stamp
        size).
    r_best : numpy.ndarray
        Most likely model size in pixels (marginal over the e grid); 0 for stars.
    flux : numpy.ndarray
        Amplitude of the most likely model (data units, total flux of the model).
    x, y : numpy.ndarray
        Fitted centre of the most likely model, in the pixels (0-based) of the stamps
        given to :func:`fit_stamps`.
    snr : numpy.ndarray
        Matched-filter signal-to-noise ``h* / (sigma sqrt S)`` of the most likely model.
    is_star : numpy.ndarray
        Boolean, most likely size is 0 or below ``Config.point_source_size``.
    flags : numpy.ndarray
        Bit mask, see :data:`pylensfit.flags.FLAGS`.
    e1_best, e2_best : numpy.ndarray
        Ellipticity of the most likely model (the maximum of ``L(e, r)``).
    lnL_bulge : numpy.ndarray or None
        With the bulge fraction marginalised (``n_bulge_fractions = n_b > 1``): ``(n, n_b,
        n_e)`` float32 ``ln L_k(e)`` of each fraction alone (sizes > 0, the sum over r
        weighted by the fraction's half-light radius per unit r relative to the pure
        disc's, ``ModelBank.run_weights``), shifted like ``lnL``. ``lnL`` is
        ``ln(sum_k L_k / n_b + L_star)``, a uniform prior over the fractions;
        :func:`pylensfit.prior.mix_bulge_fractions` gives it for any other.
    lnL_star : numpy.ndarray or None
        ``(n,)`` the point source's ``ln L`` (weighted as the ``r = 0`` end of the size
        integral), shifted like ``lnL``; ``None`` with one fraction.
    bulge_fractions : numpy.ndarray or None
        ``(n_b,)`` the bulge fraction of each run of ``lnL_bulge`` (with two bulge sizes,
        ``Config.bulge_size_ratio2``, the fractions above 0 twice).
    bulge_sizes : numpy.ndarray or None
        ``(n_b,)`` the bulge size (half-light radius / disc scale length) of each run,
        where there are two (``None``: one, the configuration's).
    bulge_best : numpy.ndarray or None
        Bulge fraction of the most likely model (the configuration's fixed fraction for
        a ``"bulge+disc"`` bank of one fraction; NaN for stars and failed fits). Not
        written by :meth:`write`.
    lnL_r : numpy.ndarray or None
        ``(n, n_r + 1)`` float32 ``ln`` of the likelihood of each size of the model
        bank, ``L(r) = sum_e P(e) L(e, r)`` with the ellipticity prior
        ``size_marginal_prior`` (every bulge fraction's run of sizes, then the point
        source; no size prior), shifted like ``lnL``: the data of
        :func:`pylensfit.prior.estimate_size_prior`. Not written by :meth:`write`.
    lnL_r_grouped : numpy.ndarray or None
        ``(n, n_groups, n_r + 1)`` float32 the sums of ``lnL_r`` over each group of e
        cells apart (``fit_stamps(lnL_r_groups=...)``; the point source in the last
        column of every group): ``lnL_r`` is their ``logsumexp`` over the groups. With
        the cells grouped by ``|e|`` (:func:`e_annuli`), ``L(r)`` under another prior
        that depends on ``|e|`` alone is a reweighting of the groups
        (:func:`reweight_lnL_r`), without a second fit. Not written by :meth:`write`.
    stamp : numpy.ndarray or None
        Side of the stamp each galaxy was fitted on (``Config.max_stamp_size``: large
        galaxies on larger stamps).
    """

    egrid: np.ndarray
    lnL: np.ndarray
    lnL_peak: np.ndarray
    r_best: np.ndarray
    flux: np.ndarray
    x: np.ndarray
    y: np.ndarray
    snr: np.ndarray
    is_star: np.ndarray
    flags: np.ndarray
    e1_best: np.ndarray
    e2_best: np.ndarray
    meta: dict = field(default_factory=dict)
    lnL_bulge: np.ndarray | None = None
    lnL_star: np.ndarray | None = None
    bulge_fractions: np.ndarray | None = None
    lnL_r: np.ndarray | None = None
    bulge_best: np.ndarray | None = None
    stamp: np.ndarray | None = None
    lnL_r_grouped: np.ndarray | None = None
    bulge_sizes: np.ndarray | None = None

    def __len__(self) -> int:
        return self.lnL.shape[0]

    _COLUMNS = ("r_best", "flux", "x", "y", "snr", "is_star", "flags", "e1_best", "e2_best",
                "lnL_peak")  # fmt: skip

    def to_table(self):
        """An :class:`astropy.table.Table` with one row per stamp, ``lnL`` a 2-D column."""
        t = Table({name: getattr(self, name) for name in self._COLUMNS})
        if self.stamp is not None:
            t["stamp"] = self.stamp
        t["lnL"] = self.lnL
        if self.lnL_bulge is not None:
            t["lnL_bulge"] = self.lnL_bulge
            t["lnL_star"] = self.lnL_star
            t.meta["BULGEFR"] = ",".join(f"{f:.6g}" for f in self.bulge_fractions)
            if self.bulge_sizes is not None:
                t.meta["BULGESZ"] = ",".join(f"{f:.6g}" for f in self.bulge_sizes)
        t.meta.update({k.upper()[:8]: v for k, v in self.meta.items()})
        return t

    def write(self, path: str | Path, *, overwrite: bool = False) -> None:
        """Write as FITS: the table in HDU 1, the ellipticity grid in HDU 2 (atomic)."""
        tab = fits.table_to_hdu(self.to_table())
        tab.name = "FITS"
        eg = fits.ImageHDU(self.egrid, name="EGRID")
        atomic_write(fits.HDUList([fits.PrimaryHDU(), tab, eg]), path, overwrite=overwrite)

    @classmethod
    def read(cls, path: str | Path) -> StampFits:
        """Read a file written by :meth:`write`."""
        with fits.open(path) as hdul:
            t = Table(hdul["FITS"].data)
            fracs = hdul["FITS"].header.get("BULGEFR")
            bsizes = hdul["FITS"].header.get("BULGESZ")
            egrid = np.array(hdul["EGRID"].data, dtype=float)
        kw = {name: np.asarray(t[name]) for name in cls._COLUMNS}
        if "stamp" in t.colnames:
            kw["stamp"] = np.asarray(t["stamp"])
        if "lnL_bulge" in t.colnames:
            kw["lnL_bulge"] = np.asarray(t["lnL_bulge"], dtype=np.float32)
            kw["lnL_star"] = np.asarray(t["lnL_star"], dtype=float)
            kw["bulge_fractions"] = np.array(str(fracs).split(","), dtype=float)
            if bsizes is not None:
                kw["bulge_sizes"] = np.array(str(bsizes).split(","), dtype=float)
        return cls(egrid=egrid, lnL=np.asarray(t["lnL"], dtype=np.float32), **kw)
