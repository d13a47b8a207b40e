"""The fit's result: every galaxy's ``ln L`` rows shifted to their maximum, the failed
fits and the stars flagged, the most likely model's parameters (:class:`StampFits`)."""

from __future__ import annotations

import numpy as np

from .. import flags as _flags
from ..config import Config
from .evaluate import Grid
from .merge import logsumexp_groups
from .priors import Weights
from .stampfits import StampFits
from .windows import Window


def _collapse_groups(lnlr: np.ndarray, n_r: int, n_grp: int
                     ) -> tuple[np.ndarray, np.ndarray | None]:  # fmt: skip
    """``ln L(r)`` summed over all e cells, and the groups apart where there are several."""
    if n_grp > 1:
        lnlr_grp = lnlr
        lnlr = lnlr[:, 0].copy()
        lnlr[:, :n_r] = logsumexp_groups(lnlr_grp[:, :, :n_r])
        return lnlr, lnlr_grp
    return lnlr[:, 0], None


def assemble_fits(win: Window, wts: Weights, grid: Grid, egrid: np.ndarray,
                  lnle: np.ndarray, lnleb: np.ndarray, cfg: Config) -> StampFits:  # fmt: skip
    """The :class:`StampFits`: every row shifted to its maximum, the failed fits and the
    stars flagged, the most likely model's parameters."""
    bank = win.bank
    lnlr, lnlr_grp = _collapse_groups(grid.lnlr, bank.n_r, wts.n_grp)
    peak, dead, rows = _shifted_rows(win, wts, (lnle, lnleb, lnlr, lnlr_grp))
    return StampFits(
        egrid=egrid.copy(),
        lnL_peak=np.where(dead, np.nan, peak),
        flags=win.flags,
        meta={"model": cfg.model, "e_step": cfg.output_e_step, "r_step": cfg.r_step,
              "r_max": cfg.r_max, "e_refine": int(cfg.e_refine)},  # fmt: skip
        bulge_fractions=None if wts.n_b == 1 else np.asarray(bank.bulge[:: bank.n_sizes], float),
        bulge_sizes=None if bank.bulge_size is None else np.asarray(
            bank.bulge_size[:: bank.n_sizes], float),
        stamp=np.full(win.n_gal, win.n),
        **rows,
        **_best_model(win, grid, lnlr, dead, cfg),
    )


def _shifted_rows(win: Window, wts: Weights, lnl: tuple) -> tuple[np.ndarray, np.ndarray, dict]:
    """Every ``ln L`` of the result (``lnl``: ``ln L(e)``, per bulge fraction, ``ln
    L(r)`` and per group of e cells) shifted by the maximum of ``ln L(e)``, in float32,
    NaN for the bad stamps and the failed fits (flagged ``FIT_FAILED``); returns the
    maxima, the dead rows and the rows by their :class:`StampFits` names."""
    lnle, lnleb, lnlr, lnlr_grp = lnl
    n_r, flags, bad = win.bank.n_r, win.flags, win.bad
    peak = lnle.max(axis=1)
    # a stamp of absurd values (a pixel at 1e30) gives ln L a range beyond float32's: -inf
    # cells in the returned rows, which no posterior can use; failed like a NaN row
    with np.errstate(over="ignore", invalid="ignore"):
        lnL = (lnle - peak[:, None]).astype(np.float32)
        failed = (~np.isfinite(peak) | ~np.isfinite(lnle).all(axis=1)
                  | ~np.isfinite(lnL).all(axis=1))  # fmt: skip
        flags[failed & ~bad] |= _flags.flag_value("FIT_FAILED")
        dead = bad | failed
        lnL[dead] = np.nan
        lnL_bulge = lnL_star = None
        if wts.n_b > 1:  # per bulge fraction, for a population prior over them
            lnL_bulge = np.moveaxis(lnleb - peak[:, None, None], 2, 1).astype(np.float32)
            lnL_bulge[dead] = np.nan
            lnL_star = np.where(dead, np.nan, lnlr[:, n_r] + np.log(wts.sums.w_star) - peak)
        lnL_r = (lnlr - peak[:, None]).astype(np.float32)
        lnL_r[dead] = np.nan
        if lnlr_grp is not None:
            lnlr_grp = (lnlr_grp - peak[:, None, None]).astype(np.float32)
            lnlr_grp[dead] = np.nan
    rows = {"lnL": lnL, "lnL_bulge": lnL_bulge, "lnL_star": lnL_star, "lnL_r": lnL_r,
            "lnL_r_grouped": lnlr_grp}  # fmt: skip
    return peak, dead, rows


def _best_model(win: Window, grid: Grid, lnlr: np.ndarray, dead: np.ndarray,
                cfg: Config) -> dict:  # fmt: skip
    """The most likely model's parameters by their :class:`StampFits` names (NaN for the
    dead rows), and the stars (most likely size 0 or below ``point_source_size``,
    flagged ``STAR``)."""
    bank, flags = win.bank, win.flags
    n_r = bank.n_r
    best, hbest, sigma = grid.best, grid.hbest, win.sigma
    ir_best = lnlr.argmax(axis=1)
    radii = np.append(bank.radii, 0.0)
    r_best = radii[ir_best]
    is_star = ((ir_best == n_r) | (r_best < cfg.point_source_size)) & ~dead
    flags[is_star] |= _flags.flag_value("STAR")
    S_best = win.model_S(best)
    ie_best = np.where(best == bank.n_models - 1, -1, best // max(n_r, 1))
    e_best = np.where(ie_best[:, None] >= 0, bank.egrid[np.maximum(ie_best, 0)], 0.0)
    nanif = np.where(dead, np.nan, 1.0)
    fracs = bank.bulge if bank.bulge is not None else np.full(n_r, cfg.bulge_fraction)
    bulge_best = np.where(ie_best >= 0, fracs[best % max(n_r, 1)], np.nan) * nanif
    c = win.c
    return {
        "r_best": r_best * nanif,
        "flux": hbest / S_best * nanif,
        "x": (c + win.xc + grid.xb + win.shift_x) * nanif,
        "y": (c + win.yc + grid.yb + win.shift_y) * nanif,
        "snr": hbest / (sigma * np.sqrt(S_best)) * nanif,
        "is_star": is_star,
        "e1_best": e_best[:, 0] * nanif,
        "e2_best": e_best[:, 1] * nanif,
        "bulge_best": bulge_best,
    }
