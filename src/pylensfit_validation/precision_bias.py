"""The precision mode's measurement of each block (the fits reduced to the shear sums)
and its bias tables: m and c per sample with jackknife errors and the shape controls."""

from __future__ import annotations

import math
import time
import warnings
from typing import Any

import numpy as np
from astropy.table import Table
from scipy.special import logsumexp

from pylensfit.calibration import CalibrationSample
from pylensfit.config import Config
from pylensfit.grid import DEFAULT_STENCIL, refined_grid
from pylensfit.likelihood import e_annuli, fit_stamps
from pylensfit.models import model_bank
from pylensfit.prior import Prior, mix_bulge_fractions
from pylensfit.runner import single_thread
from pylensfit.shear import (
    kernel_columns,
    moments_from_sums,
    sensitivity_from_sums,
    sheared_prior_columns,
    sums_with,
)

from .precision_render import (
    ESTIMATORS,
    N_QUANTITIES,
    QUANTITIES,
    PrecisionSpec,
    render_block,
    shear_sets,
)

__all__ = [
    "BIAS_COLUMNS",
    "JACKKNIFE_GALAXIES",
    "bias_table",
    "block_task",
    "measured_bulge_fraction",
    "psf_mean",
    "reduce_likelihoods",
    "reduce_renderings",
    "shape_controls",
    "shear_from_sums",
    "usable_fits",
]

# ----------------------------------------------------------------------------------------
# Per-rendering reduction: the 12 numbers the estimators need
# ----------------------------------------------------------------------------------------
def reduce_likelihoods(
    lnL: np.ndarray, egrid: np.ndarray, prior: Prior, g_nominal, *, refine: int = 4,
    stencil: int | None = None,
) -> np.ndarray:
    """The per-rendering quantities of every estimator, one pass over the posteriors.

    Parameters
    ----------
    lnL : numpy.ndarray
        ``(n, n_e)`` likelihoods on ``egrid`` (usable rows only).
    egrid : numpy.ndarray
        ``(n_e, 2)`` ellipticity grid.
    prior : Prior
        The (unsheared) prior.
    g_nominal : sequence of float
        ``(g1, g2)`` about which the fixed-point estimator is linearised.
    refine : int
        Integration refinement (as :func:`pylensfit.shear.shapes`).
    stencil : int, optional
        Points per axis of the interpolation onto the integration grid
        (:func:`pylensfit.grid.refine_lnL`; default :data:`pylensfit.grid.DEFAULT_STENCIL`).

    Returns
    -------
    numpy.ndarray
        ``(n, 12)``: ``<e1>, <e2>`` under ``P``; exact sensitivities ``sx1, sx2``; the
        paper's ``sp1, sp2``; ``<e1>, <e2>`` under ``P_gn`` (the prior sheared by
        ``g_nominal``) and their derivatives ``d<e_i>/dg_j`` there (``J11, J12, J21,
        J22``).
    """
    stencil = DEFAULT_STENCIL if stencil is None else int(stencil)
    grid = refined_grid(egrid, refine, stencil)
    K0 = kernel_columns(prior, grid)
    P, d1, d2 = sheared_prior_columns(prior, grid, np.asarray(g_nominal, float))
    e1, e2 = grid[:, 0], grid[:, 1]
    K1 = np.column_stack([P, e1 * P, e2 * P, d1, e1 * d1, e2 * d1, d2, e1 * d2, e2 * d2])
    S = sums_with(lnL, egrid, np.hstack([K0, K1]), refine, None, stencil)
    S0, S1 = S[:, :14], S[:, 14:]
    mom = moments_from_sums(S0)
    sx = sensitivity_from_sums(S0, "exact")
    sp = sensitivity_from_sums(S0, "paper")
    s0 = S1[:, 0]
    f1, f2 = S1[:, 1] / s0, S1[:, 2] / s0
    return np.column_stack([
        mom["e1"], mom["e2"], sx[0], sx[1], sp[0], sp[1], f1, f2,
        (S1[:, 4] - f1 * S1[:, 3]) / s0, (S1[:, 7] - f1 * S1[:, 6]) / s0,
        (S1[:, 5] - f2 * S1[:, 3]) / s0, (S1[:, 8] - f2 * S1[:, 6]) / s0,
    ])  # fmt: skip


def reduce_renderings(fits, prior: Prior, g: float, *, refine: int = 4,
                      bulge_weights: np.ndarray | None = None,
                      stencil: int | None = None, renderings: int = 4,
                      min_snr: float = 0.0):  # fmt: skip
    """:func:`reduce_likelihoods` of the fits of ``n`` galaxies' four (or eight) renderings.

    Parameters
    ----------
    fits : StampFits
        Fits of the ``R n`` stamps, galaxy by galaxy in the module's rendering order.
    prior : Prior
        The prior.
    g : float
        The applied shear per component (nominal shears ``+(g, g)`` for renderings 0-1,
        ``-(g, g)`` for 2-3).
    refine : int
        Integration refinement.
    bulge_weights : numpy.ndarray, optional
        Prior probabilities of the bulge fractions (:func:`~pylensfit.prior.
        estimate_bulge_weights`); the fits' uniform mixture if ``None``.
    stencil : int, optional
        As :func:`reduce_likelihoods`.
    renderings : int
        Renderings per galaxy ``R``: 4, or 8 with noise twins.
    min_snr : float
        Renderings whose best model's S/N is below this are not measured
        (``Config.min_snr``).

    Returns
    -------
    Q : numpy.ndarray
        ``(n, R, 12)`` per-rendering quantities (NaN where not measured).
    usable : numpy.ndarray
        ``(n, R)`` measured renderings.
    """
    plus, minus = shear_sets(renderings)
    R = int(renderings)
    ok = usable_fits(fits, min_snr)
    n = ok.size // R
    lnL = fits.lnL
    if bulge_weights is not None and fits.lnL_bulge is not None:
        lnL = mix_bulge_fractions(fits.lnL_bulge, fits.lnL_star, bulge_weights)
    Q = np.full((R * n, N_QUANTITIES), np.nan)
    for ks, gn in ((plus, (g, g)), (minus, (-g, -g))):  # the nominal shear of each set
        sel = np.zeros((n, R), bool)
        sel[:, list(ks)] = True
        sel = sel.ravel() & ok
        if np.any(sel):
            Q[sel] = reduce_likelihoods(lnL[sel], fits.egrid, prior, gn, refine=refine,
                                        stencil=stencil)  # fmt: skip
    return Q.reshape(n, R, N_QUANTITIES), ok.reshape(n, R)


def measured_bulge_fraction(fits, prior: Prior,
                            bulge_weights: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """Each stamp's posterior mean bulge fraction, an observed quantity to bin on.

    ``sum_k f_k p(k | data)`` with ``p(k | data)`` proportional to
    ``pi_k sum_e P(e) L_k(e)`` on the fits' ellipticity grid (the point source left
    out): the bulge fraction that the data and the priors give, not the truth's.

    Parameters
    ----------
    fits : StampFits
        Fits with the bulge fraction marginalised (``lnL_bulge``, ``bulge_fractions``).
    prior : Prior
        The ellipticity prior ``P(e)``.
    bulge_weights : numpy.ndarray, optional
        Prior probabilities ``pi_k`` of the fractions (uniform if ``None``).

    Returns
    -------
    numpy.ndarray
        ``(n,)`` posterior mean bulge fractions in ``[0, 1]`` (NaN where not measured).
    """
    lb = np.asarray(fits.lnL_bulge, dtype=float)
    n_b = lb.shape[1]
    w = np.full(n_b, 1.0 / n_b) if bulge_weights is None else np.asarray(bulge_weights, float)
    eg = np.asarray(fits.egrid, dtype=float)
    with np.errstate(divide="ignore"):
        lnp = np.log(prior.pdf(eg[:, 0], eg[:, 1]))
        lnw = np.log(w / w.sum())
    a = logsumexp(lb + lnp[None, None, :], axis=2) + lnw[None, :]
    with np.errstate(invalid="ignore"):
        post = np.exp(a - logsumexp(a, axis=1, keepdims=True))
    return post @ np.asarray(fits.bulge_fractions, dtype=float)


def usable_fits(fits, min_snr: float = 0.0) -> np.ndarray:
    """Measured galaxies: no flag, not a point source, S/N at least ``min_snr``."""
    snr = np.asarray(fits.snr, dtype=float)
    return (np.asarray(fits.flags) == 0) & ~np.asarray(fits.is_star) & ~(snr < min_snr)


def block_task(task: dict[str, Any]) -> dict[str, Any]:
    """Render, fit and reduce one block (runs in a worker)."""
    single_thread(task.get("single_thread", False))
    spec: PrecisionSpec = task["spec"]
    cfg: Config = task["config"]
    t0 = time.perf_counter()
    stamps, psf, truth = render_block(spec, task["psf"], task["block"],
                                      stamp_size=cfg.largest_stamp,
                                      calibration=task["calibration"],
                                      noise=task.get("noise", True))  # fmt: skip
    t1 = time.perf_counter()
    n, nr = stamps.shape[:2]
    groups = None
    if task.get("keep_lnL_r") == "annuli":  # L(r) per |e|, for any prior of |e| later

        groups = e_annuli(model_bank(cfg).egrid)
    fits = fit_stamps(stamps.reshape(n * nr, *stamps.shape[2:]), psf, spec.noise_sigma,
                      config=cfg, size_prior=task.get("size_prior"),
                      size_marginal_prior=task.get("size_marginal_prior"),
                      lnL_r_groups=groups)  # fmt: skip
    t2 = time.perf_counter()
    ok = usable_fits(fits, cfg.min_snr)
    res: dict[str, Any] = {"block": task["block"], "psf": task["psf"], "truth": truth,
                           "render_s": t1 - t0, "fit_s": t2 - t1}  # fmt: skip
    if task["calibration"]:
        c = stamps.shape[-1] // 2  # the catalogue position: the stamp's centre
        res["sample"] = CalibrationSample.from_fits(fits, ok, c, c, group=task["psf"])
        if task.get("keep_lnL_r") and task.get("keep_lnL_r") != "annuli":
            res["lnL_r"] = fits.lnL_r[ok]
        return res
    Q, usable = reduce_renderings(fits, task["prior"], spec.g, refine=cfg.output_refine,
                                  bulge_weights=task.get("bulge_weights"),
                                  stencil=task.get("stencil"), renderings=nr,
                                  min_snr=cfg.min_snr)  # fmt: skip
    res["Q"] = Q.astype(np.float32)
    res["usable"] = usable
    if fits.lnL_bulge is not None:  # averaged over the renderings: even in the shear
        bf = measured_bulge_fraction(fits, task["prior"], task.get("bulge_weights"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a galaxy never measured
            res["bulge_meas"] = np.nanmean(np.where(usable, bf.reshape(n, nr), np.nan),
                                           axis=1).astype(np.float32)  # fmt: skip
    res["r_best"] = fits.r_best.reshape(n, nr)[:, 0].astype(np.float32)
    res["snr_meas"] = fits.snr.reshape(n, nr)[:, 0].astype(np.float32)
    res["stamp"] = fits.stamp.reshape(n, nr)[:, 0].astype(np.int16)
    res["reduce_s"] = time.perf_counter() - t2
    return res


# ----------------------------------------------------------------------------------------
# Estimators and the jackknife
# ----------------------------------------------------------------------------------------
def shear_from_sums(T: np.ndarray, N: np.ndarray, gn: np.ndarray, estimator: str):
    """``(..., 2)`` shear from summed quantities ``T (..., 12)`` of ``N (...)`` renderings."""
    ix = {q: i for i, q in enumerate(QUANTITIES)}
    if estimator in ("exact", "paper"):
        s = "sx" if estimator == "exact" else "sp"
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.stack([T[..., ix["e1"]] / T[..., ix[f"{s}1"]],
                             T[..., ix["e2"]] / T[..., ix[f"{s}2"]]], axis=-1)  # fmt: skip
    # one Newton step of f(g) = sum <e>(P_g) - N g from g_nominal
    f1 = T[..., ix["fe1"]] - N * gn[0]
    f2 = T[..., ix["fe2"]] - N * gn[1]
    a, b = T[..., ix["J11"]] - N, T[..., ix["J12"]]
    c, d = T[..., ix["J21"]], T[..., ix["J22"]] - N
    with np.errstate(invalid="ignore", divide="ignore"):
        det = a * d - b * c
        return np.stack([gn[0] - (d * f1 - b * f2) / det, gn[1] - (a * f2 - c * f1) / det],
                        axis=-1)  # fmt: skip


def bias_table(
    Q: np.ndarray,
    usable: np.ndarray,
    blocks: np.ndarray,
    g: float,
    *,
    groups: dict[str, np.ndarray] | None = None,
    selection: str = "paired",
    controls: np.ndarray | None = None,
) -> Table:
    """m and c with jackknife errors for every estimator and group of galaxies.

    Parameters
    ----------
    Q : numpy.ndarray
        ``(n_gal, R, 12)`` per-rendering quantities (:func:`reduce_likelihoods`), in the
        rendering order of the module table: ``R = 4``, or 8 with the noise twins.
    usable : numpy.ndarray
        ``(n_gal, R)`` measured renderings.
    blocks : numpy.ndarray
        ``(n_gal,)`` jackknife block of each galaxy.
    g : float
        The applied shear per component (``+-(g, g)``).
    groups : dict of str to numpy.ndarray, optional
        Named boolean ``(n_gal,)`` masks; default one group ``all``.
    selection : {"paired", "independent"}
        ``paired``: a galaxy counts only if all its renderings are measured;
        ``independent``: each rendering counts on its own.
    controls : numpy.ndarray, optional
        ``(n_gal, k)`` control variates: per-galaxy quantities whose population mean is
        known to be zero and which correlate with the galaxies' response, such as the
        spin-4 parts of the intrinsic ellipticity (:func:`shape_controls`). Each of m1,
        m2, c1, c2 then becomes ``v - beta . xbar`` (``xbar`` the controls' mean over the
        measured renderings), with ``beta`` regressed from the blocks' jackknife
        pseudo-values. This removes the shape noise that 90-degree twins leave (the
        response's ``cos 4 theta`` terms) without changing the expectation; the errors
        are the jackknife of the corrected values. Groups of fewer than 20 blocks are
        left uncorrected (``beta`` would be noise).

    Returns
    -------
    astropy.table.Table
        One row per group and estimator: ``group, estimator, m1, m1_err, m2, m2_err, c1,
        c1_err, c2, c2_err, n_gal, n_blocks`` and ``controlled`` (whether the controls
        were applied); errors are delete-one-block jackknife.
    """
    Q = np.nan_to_num(np.asarray(Q, float))
    usable = np.asarray(usable, bool)
    sets = shear_sets(Q.shape[1])
    if selection == "paired":
        w = np.repeat(usable.all(axis=1, keepdims=True), Q.shape[1], axis=1)
    elif selection == "independent":
        w = usable
    else:
        raise ValueError(f"selection must be 'paired' or 'independent', got {selection!r}")
    ub, bidx = np.unique(np.asarray(blocks), return_inverse=True)
    nb = ub.size
    groups = groups if groups is not None else {"all": np.ones(len(Q), bool)}
    X = None if controls is None else np.asarray(controls, float).reshape(len(Q), -1)
    rows = []
    gvec = np.array([g, g])
    for name, mask in groups.items():
        mask = np.asarray(mask, bool)
        n_gal = int((mask & w.any(axis=1)).sum())
        # per block sums of the + and - renderings: (2, nb, 12) and (2, nb)
        T = np.zeros((2, nb, N_QUANTITIES))
        N = np.zeros((2, nb))
        for s, ks in enumerate(sets):
            ww = w[:, ks] & mask[:, None]
            qs = np.einsum("ak,akq->aq", ww, Q[:, ks])
            for q in range(N_QUANTITIES):
                T[s, :, q] = np.bincount(bidx, weights=qs[:, q], minlength=nb)
            N[s] = np.bincount(bidx, weights=ww.sum(axis=1), minlength=nb)
        used = N.sum(axis=0) > 0
        tot_T, tot_N = T.sum(axis=1), N.sum(axis=1)
        # full sample first, then leave-one-block-out (only blocks with galaxies)
        TT = np.concatenate([tot_T[:, None], tot_T[:, None] - T[:, used]], axis=1)
        NN = np.concatenate([tot_N[:, None], tot_N[:, None] - N[:, used]], axis=1)
        k = int(used.sum())
        xbar = None
        if X is not None and k >= _MIN_CONTROL_BLOCKS:
            # the controls' mean over the measured renderings, full and leave-one-out
            wx = (w & mask[:, None]).sum(axis=1).astype(float)
            SX = np.stack([np.bincount(bidx, weights=wx * X[:, j], minlength=nb)
                           for j in range(X.shape[1])], axis=1)[used]  # fmt: skip
            SW = np.bincount(bidx, weights=wx, minlength=nb)[used]
            with np.errstate(invalid="ignore", divide="ignore"):
                xbar = np.concatenate([SX.sum(0)[None] / SW.sum(),
                                       (SX.sum(0) - SX) / (SW.sum() - SW)[:, None]])  # fmt: skip
        for est in ESTIMATORS:
            gp = shear_from_sums(TT[0], NN[0], gvec, est)
            gm = shear_from_sums(TT[1], NN[1], -gvec, est)
            m = (gp - gm) / (2 * g) - 1.0
            c = (gp + gm) / 2.0
            row: dict[str, Any] = {"group": name, "estimator": est, "controlled": xbar is not None}
            for i in (0, 1):
                for key, v in (("m", m[:, i]), ("c", c[:, i])):
                    if xbar is not None:
                        v, applied = _controlled(v, xbar, k)
                        row["controlled"] &= applied
                    row[f"{key}{i + 1}"] = float(v[0])
                    jk = v[1:]
                    row[f"{key}{i + 1}_err"] = (
                        float(math.sqrt((k - 1) / k * np.sum((jk - jk.mean()) ** 2)))
                        if k > 1 else math.nan
                    )  # fmt: skip
            row["n_gal"] = n_gal
            row["n_blocks"] = k
            rows.append(row)
    return Table(rows=[[r[k] for k in BIAS_COLUMNS] for r in rows], names=BIAS_COLUMNS)


#: Columns of :func:`bias_table`.
BIAS_COLUMNS = ["group", "estimator", "m1", "m1_err", "m2", "m2_err", "c1", "c1_err", "c2",
                 "c2_err", "n_gal", "n_blocks", "controlled"]  # fmt: skip


def psf_mean(per_psf: Table) -> Table:
    """The unweighted mean over PSFs of each estimator's m and c, errors combined.

    The blocks go to the PSFs in turn, so the PSFs' shares of the sample are fixed by
    design; the jackknife of the ``all`` group counts as noise the change of those
    shares when a block is left out, which this mean does not have.
    """
    rows = []
    for est in dict.fromkeys(per_psf["estimator"]):
        t = per_psf[per_psf["estimator"] == est]
        k = len(t)
        row: dict[str, Any] = {"group": "mean of PSFs", "estimator": est}
        for q in ("m1", "m2", "c1", "c2"):
            row[q] = float(np.mean(t[q]))
            row[f"{q}_err"] = float(np.sqrt(np.sum(np.asarray(t[f"{q}_err"]) ** 2)) / k)
        row["n_gal"] = int(np.sum(t["n_gal"]))
        row["n_blocks"] = int(np.sum(t["n_blocks"]))
        row["controlled"] = bool(np.all(t["controlled"]))
        rows.append(row)
    out = Table(rows=[[r[n] for n in BIAS_COLUMNS] for r in rows], names=BIAS_COLUMNS)
    out["breakdown"] = "all"
    return out


#: Galaxies per jackknife group of :func:`precision`.
JACKKNIFE_GALAXIES = 100

#: Fewest jackknife blocks for which :func:`bias_table` applies control variates.
_MIN_CONTROL_BLOCKS = 20


def _controlled(v: np.ndarray, xbar: np.ndarray, k: int) -> np.ndarray:
    """Control-variate correction of a statistic and its ``k`` leave-one-out values.

    ``v`` is ``(1 + k,)``: the full-sample value, then the delete-one-block values;
    ``xbar`` is ``(1 + k, n_c)``, the controls' means over the same samples. ``beta`` is
    the least-squares slope of the blocks' jackknife pseudo-values of ``v`` on those of
    ``xbar``; the result is ``v - xbar . beta`` for every sample, and whether it was
    applied (not where a value is not finite: ``v`` is returned as it is).
    """
    ok = np.isfinite(v).all() and np.isfinite(xbar).all()
    if not ok:
        return v, False
    pv = k * v[0] - (k - 1) * v[1:]
    px = k * xbar[0] - (k - 1) * xbar[1:]
    A = px - px.mean(axis=0)
    beta = np.linalg.lstsq(A, pv - pv.mean(), rcond=None)[0]
    return v - xbar @ beta, True


def shape_controls(e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """Control variates of the precision mode: the spin-4 parts of the intrinsic shape.

    A galaxy's response to a shear depends on its intrinsic ellipticity's orientation
    through ``Re(e^2) = e1^2 - e2^2`` and ``Im(e^2) = 2 e1 e2`` (``e' = e + g - conj(g)
    e^2`` to first order), which its 90-degree twin (``e -> -e``) does not cancel. Over
    an isotropic population both have mean zero exactly, so :func:`bias_table` can
    regress them out of m and c.

    Parameters
    ----------
    e1, e2 : numpy.ndarray
        Intrinsic ellipticities (unrotated rendering).

    Returns
    -------
    numpy.ndarray
        ``(n, 2)``: ``e1^2 - e2^2`` and ``2 e1 e2``.
    """
    e1 = np.asarray(e1, float)
    e2 = np.asarray(e2, float)
    return np.stack([e1 * e1 - e2 * e2, 2.0 * e1 * e2], axis=1)
