"""Fits put together: disjoint subsets merged, fits with several PSFs blended, and
``ln L(r)`` reweighted to another ellipticity prior by the groups of equal ``|e|``."""

from __future__ import annotations

from dataclasses import fields

import numpy as np

from ..prior import Prior
from .stampfits import StampFits


def merge_fits(parts: list[tuple[np.ndarray, StampFits]], n_gal: int) -> StampFits:
    """One :class:`StampFits` from fits of disjoint subsets of ``n_gal`` galaxies.

    Parameters
    ----------
    parts : list of (numpy.ndarray, StampFits)
        ``(index, fits)``: the galaxies' positions in the merged result (integer
        indices or a boolean mask of length ``n_gal``) and their fits, all made with the
        same ellipticity grid and model bank.
    n_gal : int
        Number of galaxies in the merged result; every one must be in exactly one part.

    Returns
    -------
    StampFits
        Per-galaxy arrays filled from the parts; the grid, bank and ``meta`` from the
        first part, with ``meta["stamp_sizes"]`` the stamp sizes of the merged set.
    """
    first = parts[0][1]
    out = {}
    for f in fields(StampFits):
        v0 = getattr(first, f.name)
        if f.name in ("egrid", "meta", "bulge_fractions", "bulge_sizes"):
            out[f.name] = v0
        elif isinstance(v0, np.ndarray):
            arr = np.empty((n_gal, *v0.shape[1:]), dtype=v0.dtype)
            for idx, fit in parts:
                arr[idx] = getattr(fit, f.name)
            out[f.name] = arr
        else:
            out[f.name] = v0
    out["meta"] = dict(first.meta, stamp_sizes=sorted({int(v) for v in out["stamp"]}))
    return StampFits(**out)


#: :class:`StampFits` fields that are ``ln L`` shifted by ``lnL_peak``: blended in ``ln L``.
_SHIFTED = ("lnL", "lnL_bulge", "lnL_star", "lnL_r", "lnL_r_grouped")
#: Fields blended as weighted means (the best model's numbers).
_AVERAGED = ("r_best", "flux", "x", "y", "snr", "e1_best", "e2_best")


def blend_fits(fits_list: list[StampFits], weights: np.ndarray) -> StampFits:
    """The fits of the same stamps with several PSFs, blended as with a PSF in between.

    For a galaxy whose PSF is ``P = sum_c w_c P_c`` (weights summing to 1, e.g. the
    bilinear weights of the PSFs at the corners of the galaxy's cell), the likelihood
    is, to first order in the differences between the ``P_c``, ``ln L = sum_c w_c ln
    L_c``: the mean of the corners' ``ln L`` grids, whose peak sits at the weighted mean
    of the corners' peaks. Every ``ln L`` of the fits (``lnL``, ``lnL_bulge``,
    ``lnL_star``, ``lnL_r``, ``lnL_r_grouped``) is blended so, with the shifts
    ``lnL_peak`` restored and the result shifted again to a maximum of 0; the best
    model's numbers (size, flux, centre, S/N, ellipticity) are the weighted means, the
    point-source decision and the best bulge fraction those of the heaviest PSF, the
    flags the union of all.

    Parameters
    ----------
    fits_list : list of StampFits
        Fits of the same ``n`` stamps, one per PSF, on the same ellipticity grid and
        model bank.
    weights : numpy.ndarray
        ``(len(fits_list), n)`` each stamp's weight of each PSF, >= 0, summing to 1 over
        the PSFs.

    Returns
    -------
    StampFits
        The blended fits; ``meta`` and the grid from the first.
    """
    w = np.asarray(weights, dtype=np.float64)
    k = len(fits_list)
    if k == 0 or w.shape != (k, len(fits_list[0])):
        raise ValueError(f"weights must have shape ({k}, n_stamps), got {w.shape}")
    if np.any(w < 0) or not np.allclose(w.sum(0), 1.0):
        raise ValueError("weights must be >= 0 and sum to 1 over the PSFs")
    if k == 1:
        return fits_list[0]
    first = fits_list[0]
    peak = np.stack([np.asarray(f.lnL_peak, np.float64) for f in fits_list])
    out = {f.name: getattr(first, f.name) for f in fields(StampFits)}

    def wsum(name: str, shift: bool) -> np.ndarray:
        tot = 0.0
        for c, f in enumerate(fits_list):
            v = np.asarray(getattr(f, name), np.float64)
            wc = w[c].reshape((-1,) + (1,) * (v.ndim - 1))
            pc = peak[c].reshape(wc.shape) if shift else 0.0
            tot = tot + wc * (v + pc)
        return tot

    lnL = wsum("lnL", True)
    new_peak = np.max(lnL, axis=1)
    out["lnL_peak"] = new_peak.astype(first.lnL_peak.dtype)
    for name in _SHIFTED:
        if getattr(first, name) is None:
            continue
        v = lnL if name == "lnL" else wsum(name, True)
        shift = new_peak.reshape((-1,) + (1,) * (v.ndim - 1))
        out[name] = (v - shift).astype(np.float32)
    for name in _AVERAGED:
        out[name] = wsum(name, False).astype(np.asarray(getattr(first, name)).dtype)
    heavy = np.argmax(w, axis=0)
    cols = np.arange(w.shape[1])
    for name in ("is_star", "bulge_best"):
        if getattr(first, name) is not None:
            out[name] = np.stack([np.asarray(getattr(f, name)) for f in fits_list])[heavy, cols]
    flags = np.zeros_like(np.asarray(first.flags))
    for f in fits_list:
        flags |= np.asarray(f.flags)
    out["flags"] = flags
    return StampFits(**out)


def e_annuli(egrid: np.ndarray) -> np.ndarray:
    """The group of every ellipticity cell by its ``|e|`` (``fit_stamps(lnL_r_groups=)``).

    Cells of equal ``|e|`` (to 1e-9) share a group, numbered by increasing ``|e|``:
    36 groups for the 316 cells of ``e_step = 0.1``. A prior that depends on ``|e|``
    alone, as the functional form does (:class:`pylensfit.prior.Prior`), is constant
    on each group.
    """
    ee = np.round(np.hypot(egrid[:, 0], egrid[:, 1]), 9)
    return np.unique(ee, return_inverse=True)[1].astype(np.int64).reshape(-1)


def reweight_lnL_r(lnL_r_grouped: np.ndarray, egrid: np.ndarray, groups: np.ndarray,
                   prior_from, prior_to) -> np.ndarray:  # fmt: skip
    """``L(r) = sum_e P_to(e) L(e, r)`` from fits that kept ``sum_e P_from(e) L(e, r)``
    per group of equal ``|e|`` (:func:`e_annuli`).

    Parameters
    ----------
    lnL_r_grouped : numpy.ndarray
        ``(n, n_groups, n_r + 1)`` ``StampFits.lnL_r_grouped`` of fits with
        ``size_marginal_prior=prior_from`` (``None``: the default ``Prior()``) and
        ``lnL_r_groups=groups``.
    egrid : numpy.ndarray
        ``(n_e, 2)`` the fits' ellipticity grid.
    groups : numpy.ndarray
        ``(n_e,)`` the cells' groups (:func:`e_annuli`).
    prior_from, prior_to : pylensfit.prior.Prior or None
        Priors that depend on ``|e|`` alone (checked: each must be constant on every
        group, to 1e-9 relative).

    Returns
    -------
    numpy.ndarray
        ``(n, n_r + 1)`` float32, what ``StampFits.lnL_r`` of the same fits with
        ``size_marginal_prior=prior_to`` holds (to float32 rounding), shifted alike.
    """
    def cell_weights(p):
        w = (p if p is not None else Prior()).pdf(egrid[:, 0], egrid[:, 1])
        return w / w.sum()

    groups = np.asarray(groups)
    w_from, w_to = cell_weights(prior_from), cell_weights(prior_to)
    n_grp = int(groups.max()) + 1
    ratio = np.zeros(n_grp)
    for w in (w_from, w_to):
        lo = np.full(n_grp, np.inf)
        hi = np.zeros(n_grp)
        np.minimum.at(lo, groups, w)
        np.maximum.at(hi, groups, w)
        if np.any(hi - lo > 1e-9 * hi):
            raise ValueError("reweight_lnL_r: a prior is not constant on a group of e cells "
                             "(it depends on more than |e|, or the groups are not annuli)")
    ratio[groups] = w_to / np.where(w_from > 0, w_from, np.nan)
    L = np.asarray(lnL_r_grouped, dtype=float)
    with np.errstate(divide="ignore"):
        lnw = np.log(ratio)
    out = L[:, 0].copy()
    out[:, :-1] = logsumexp_groups(L[:, :, :-1] + lnw[None, :, None])
    return out.astype(np.float32)


def logsumexp_groups(a: np.ndarray) -> np.ndarray:
    """``log sum exp`` over axis 1 of ``(n, n_groups, m)`` (``-inf`` where all are)."""
    top = np.max(a, axis=1)
    safe = np.where(np.isfinite(top), top, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.log(np.sum(np.exp(a - safe[:, None]), axis=1)) + safe
