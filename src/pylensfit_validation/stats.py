"""The statistics of the validation: m and c against the true shear, the quality factor
Q, the shear of twin pairs and groups, the truth's control variate, the spread of the
offsets over PSFs, the PSF leakage and the bins (Kitching et al. 2008, sections 4 and
5.1; docs: method, eq-m-c and eq-quality-factor)."""

from __future__ import annotations

import math
import os
from functools import lru_cache
from typing import Any

import numpy as np
from astropy.table import Table
from scipy.optimize import brentq

from pylensfit.shear import ShearEstimate

__all__ = [
    "BIN_LABELS",
    "DEFAULT_BINS",
    "MATCH_RADIUS",
    "MC_COLUMNS",
    "MORPHOLOGY_EDGES",
    "PSF_HELDOUT_TARGET",
    "TARGETS",
    "bin_index",
    "c_scatter",
    "controlled_estimate",
    "fit_m_c",
    "fit_m_c_cov",
    "group_members",
    "group_shear",
    "leakage_table",
    "mc_summary",
    "nanmean",
    "psf_leakage",
    "quality_factor",
    "quantile_edges",
    "read_truth",
    "shear_groups",
    "sky_columns",
    "truth_control_variate",
    "truth_terms",
    "twin_shear",
]


# ----------------------------------------------------------------------------------------
# Validation: m, c, sigma_c and Q (Kitching et al. 2008, sections 4 and 5.1; docs: method,
# eq-m-c and eq-quality-factor)
# ----------------------------------------------------------------------------------------
#: Targets: ``|<m>| <= 0.006`` (within its error), ``sigma_c <= 2e-4``, ``Q >= 100``.
TARGETS: dict[str, float] = {"m": 0.006, "sigma_c": 2e-4, "Q": 100.0}
#: The largest excess rms ellipticity residual (the model's, beyond the stars' noise)
#: of a varying PSF model on its held-out stars that the report calls met.
PSF_HELDOUT_TARGET = 1e-3

#: Default binnings of :func:`validate`: four bins (equal counts) of each quantity.
DEFAULT_BINS: dict[str, int] = {"mag": 4, "snr": 4, "size": 4}

BIN_LABELS = {
    "mag": "magnitude (measured, zeropoint 0)",
    "snr": "S/N (measured model_SNratio)",
    "size": "size r_true / PSF FWHM",
    "morphology": "morphology (STEP2: 0 Sersic, 1 bulge+disc, 2 knotty disc)",
}
#: The ``morphology`` bins that :func:`validate` adds on a STEP2-like set: one per kind.
MORPHOLOGY_EDGES = (-0.5, 0.5, 1.5, 2.5)
MATCH_RADIUS = 5.0  # px: detections farther than this from every truth object are unmatched


def fit_m_c_cov(g_true, g_meas, g_err) -> tuple[float, float, np.ndarray | None]:
    """``(m, c, cov)`` of the chi-square fit; ``m = nan`` and ``cov = None`` without leverage."""
    gt = np.asarray(g_true, dtype=float)
    d = np.asarray(g_meas, dtype=float) - gt
    w = 1.0 / np.asarray(g_err, dtype=float) ** 2
    A = np.column_stack([gt, np.ones_like(gt)])
    F = A.T @ (A * w[:, None])
    if np.linalg.cond(F) > 1e12:  # all g_true equal: only c is measured
        c = float(np.sum(w * d) / np.sum(w))
        return math.nan, c, None
    cov = np.linalg.inv(F)
    m, c = cov @ (A.T @ (w * d))
    return float(m), float(c), cov


def fit_m_c(g_true, g_meas, g_err) -> tuple[float, float, float, float]:
    """Chi-square fit of ``g_meas - g_true = m g_true + c``: ``(m, m_err, c, c_err)``.

    The model is linear, so the 1-sigma errors projected from the (m, c) chi-square grid
    (``delta chi^2 = 1``) are the square roots of the diagonal of the fit covariance.
    """
    m, c, cov = fit_m_c_cov(g_true, g_meas, g_err)
    if cov is None:
        w = 1.0 / np.asarray(g_err, dtype=float) ** 2
        return math.nan, math.nan, c, float(1.0 / math.sqrt(np.sum(w)))
    return m, float(math.sqrt(cov[0, 0])), c, float(math.sqrt(cov[1, 1]))


def quality_factor(g_true: np.ndarray, g_meas: np.ndarray, g_err: np.ndarray) -> float:
    """Paper's ``Q = 1000 sigma_stat^2 / <(g_meas - g_true)^2>`` over images and components.

    ``g_*`` are ``(n_images, 2)``; ``sigma_stat^2`` is the mean statistical variance of
    the images' estimates (``g_err^2``), the spread an unbiased method would show.
    """
    d2 = (np.asarray(g_meas) - np.asarray(g_true)) ** 2
    return float(1000.0 * np.mean(np.asarray(g_err) ** 2) / np.mean(d2))


def twin_shear(
    e_a: np.ndarray, e_b: np.ndarray, sens_a: np.ndarray, sens_b: np.ndarray
) -> ShearEstimate:
    """Shear of an image and its 90-degree-rotated twin, galaxy by galaxy (STEP2).

    Each galaxy ``a`` of the image is paired with its rotated counterpart ``b``; the
    intrinsic ellipticities cancel in ``e_a + e_b`` to first order in the shear
    (Kitching et al. 2008, section 4.2, after Massey et al. 2007). The pair's estimate
    is the mean shear over mean sensitivity (docs: method, eq-key2) over both images,
    ``g_i = sum_pairs (e_a,i + e_b,i) / sum_pairs (s_a,i + s_b,i)``, and its error comes
    from the scatter of the per-pair sums,
    ``std(e_a,i + e_b,i - g_i (s_a,i + s_b,i)) sqrt(N_pairs) / sum_pairs (s_a,i + s_b,i)``,
    so that it shows the cancellation (only measurement noise and the residual
    ``O(g e^2)`` terms remain). :func:`group_shear` is the same for groups of any size
    (twins and noise twins).

    Parameters
    ----------
    e_a, e_b : numpy.ndarray
        ``(n_pairs, 2)`` posterior mean ellipticities of the matched galaxies in the image
        and in its twin (row ``i`` of both is the same galaxy).
    sens_a, sens_b : numpy.ndarray
        ``(n_pairs, 2)`` their shear sensitivities ``d<e_i>/dg_i``.

    Returns
    -------
    ShearEstimate
        ``n`` is the number of pairs used (rows with any non-finite value are skipped).

    Raises
    ------
    ValueError
        On arrays of different shapes, no usable pair, or a non-positive summed sensitivity.
    """
    arrs = [np.asarray(a, dtype=float).reshape(-1, 2) for a in (e_a, e_b, sens_a, sens_b)]
    if len({a.shape for a in arrs}) != 1:
        raise ValueError("e_a, e_b, sens_a, sens_b must have the same (n_pairs, 2) shape")
    return group_shear(np.stack(arrs[:2], axis=1), np.stack(arrs[2:], axis=1))


def group_shear(e: np.ndarray, sens: np.ndarray) -> ShearEstimate:
    """Shear of a group of renderings of the same galaxies, summed galaxy by galaxy.

    A group is an image and its twins: the 90-degree-rotated one (the intrinsic shapes
    cancel) and, for a set simulated with noise twins, the two with their noise negated
    (the noise's first-order response cancels). The estimate is the mean shear over mean
    sensitivity (docs: method, eq-key2) over the whole group,
    ``g_i = sum_galaxies sum_members e_i / sum_galaxies sum_members s_i``, and its error
    comes from the scatter of the per-galaxy sums over the members,
    ``std(sum_members (e_i - g_i s_i)) sqrt(N) / sum s_i`` (the ratio estimator's), so
    that it shows the cancellations.

    Parameters
    ----------
    e : numpy.ndarray
        ``(n_galaxies, n_members, 2)`` posterior mean ellipticities; row ``i`` of every
        member is the same galaxy.
    sens : numpy.ndarray
        Their shear sensitivities ``d<e_i>/dg_i``, the same shape.

    Returns
    -------
    ShearEstimate
        ``n`` is the number of galaxies used (those with any non-finite value in any
        member are skipped).

    Raises
    ------
    ValueError
        On arrays of different or wrong shapes, no usable galaxy, or a non-positive summed
        sensitivity.
    """
    e, sens = np.asarray(e, dtype=float), np.asarray(sens, dtype=float)
    if e.shape != sens.shape or e.ndim != 3 or e.shape[2] != 2:
        raise ValueError("e and sens must have the same (n_galaxies, n_members, 2) shape, "
                         f"got {e.shape} and {sens.shape}")  # fmt: skip
    ok = np.all(np.isfinite(e), axis=(1, 2)) & np.all(np.isfinite(sens), axis=(1, 2))
    n = int(ok.sum())
    if n == 0:
        raise ValueError("no usable galaxy to estimate shear")
    esum, ssum = e[ok].sum(axis=1), sens[ok].sum(axis=1)
    out = []
    for i in range(2):
        s = float(ssum[:, i].sum())
        if not s > 0:
            raise ValueError(f"the sum of the group sensitivities (component {i + 1}) is {s}")
        g = float(esum[:, i].sum()) / s
        # the ratio estimator's error: the scatter of the residuals e - g s (at STEP's
        # shears of up to 0.1 the sensitivities' own scatter times g is most of std(e)
        # once the twins have cancelled the shapes and the noise)
        err = float(np.std(esum[:, i] - g * ssum[:, i], ddof=1)) * math.sqrt(n) / s if n > 1 \
            else math.nan
        out.append((g, err))
    return ShearEstimate(g1=out[0][0], g2=out[1][0], g1_err=out[0][1], g2_err=out[1][1], n=n)


def truth_control_variate(r: np.ndarray, t: np.ndarray, t_pop: np.ndarray,
                          scale: float) -> tuple[float, float]:
    """The truth's shape noise as a control variate for one shear component of one image.

    A simulation knows each galaxy's true sheared ellipticity ``e_true`` (for a group of
    renderings, summed over its members), and ``t = e_true - g`` has expectation zero
    over an isotropic population of intrinsic shapes, exactly (``e_true = (e_s + g) /
    (1 + g* e_s)`` is analytic in ``e_s``, so its mean over the position angle is its
    value at ``e_s = 0``). Its sample mean over an image's population is pure sampling
    noise: for a single image, the shape noise itself; for a 90-degree twin pair, the
    second-order term ``-2 g* e_s^2`` that the rotation leaves, which makes c2 of a STEP1
    field at ``g1 = 0.1`` scatter 2.4 times as much as at ``g1 = 0``. The estimate
    ``g_hat`` (whatever the estimator) becomes ``g_hat - beta N <t>_pop / D``, where
    ``<t>_pop`` is the mean of ``t`` over **every** truth galaxy of the image (measured
    or not), ``N`` the measured truth galaxies, ``D`` the estimator's denominator
    (``sum s`` for the mean shear over mean sensitivity, eq-key2) and ``beta`` the
    regression slope of the residuals ``e - g s`` on ``t``. The galaxies lost to cuts
    and failed fits differ from the population only by their own ``t``: what a selection
    that responds to the shape does to the estimate stays in it; only the population's
    sampling noise goes. The error is that of
    ``sum (e - g s) - beta sum_measured (t - <t>)`` (the measurement's part) with the
    unmeasured galaxies' share of the population noise,
    ``beta^2 var(t) N (1 - N / N_pop)``.

    Parameters
    ----------
    r : numpy.ndarray
        ``(n,)`` the residuals ``e - g s`` of the galaxies in the estimate: posterior mean
        ellipticities less the shear times their sensitivities (group sums).
    t : numpy.ndarray
        ``(n,)`` their ``e_true - g`` (group sums); NaN for a row that is not a truth
        galaxy (a star fitted as a galaxy, a spurious detection).
    t_pop : numpy.ndarray
        ``(N_pop,)`` the same for every truth galaxy of the image (or group).
    scale : float
        ``1 / D``, the estimator's denominator.

    Returns
    -------
    delta, err : float
        The correction to subtract from the estimate, and the corrected estimate's error.
        ``delta = 0`` and the plain error where ``t`` does not vary (a twin pair at
        ``g = 0``, where the rotation cancels it exactly).
    """
    r = np.asarray(r, dtype=float)
    t = np.asarray(t, dtype=float)
    t_pop = np.asarray(t_pop, dtype=float)
    gal = np.isfinite(t)
    n, n_g = r.size, int(gal.sum())
    tc = t[gal] - t[gal].mean() if n_g else t[gal]
    den = float(np.sum(tc**2))
    beta = float(np.sum((r[gal] - r[gal].mean()) * tc) / den) if n_g > 2 and den > 1e-20 else 0.0
    z = r.copy()
    z[gal] -= beta * tc
    frac = min(n_g / t_pop.size, 1.0) if t_pop.size else 1.0
    var_pop = float(np.var(t_pop, ddof=1)) if t_pop.size > 1 else 0.0
    delta = beta * n_g * float(t_pop.mean()) * scale if t_pop.size else 0.0
    err = math.sqrt(n * float(np.var(z, ddof=1)) + beta**2 * var_pop * n_g * (1.0 - frac)) * scale
    return delta, err


def read_truth(path: str | os.PathLike) -> Table:
    """The ``TRUTH`` table of a simulated field, read once per file version (matching the
    galaxies and the truth control read each field's; do not modify it)."""
    st = os.stat(path)
    return _truth_cached(os.fspath(path), st.st_mtime_ns, st.st_size)


@lru_cache(maxsize=256)
def _truth_cached(path: str, mtime_ns: int, size: int) -> Table:
    return Table.read(path, hdu="TRUTH")


def sky_columns(t: Table, a: str, b: str) -> tuple[str, str]:
    """The sky-frame columns ``a_sky, b_sky`` of a truth table, or the pixel-frame ``a, b``
    of a table without them (simulated with the plain WCS only, where the pixel frame
    is the sky frame)."""
    if f"{a}_sky" in t.colnames and f"{b}_sky" in t.colnames:
        return f"{a}_sky", f"{b}_sky"
    return a, b


def truth_terms(fields: dict[str, dict], names: list[str]) -> np.ndarray:
    """``(n_truth, 2)``: ``sum over the images names of (e_true - g)`` per truth object of a
    group's images (which share their truth rows); NaN for stars. ``e_true`` and ``g``
    in the sky frame (the truth's ``e1_sky, e2_sky``; the manifest's shears)."""
    out = None
    for name in names:
        f = fields[name]
        t = read_truth(f["path"])
        c1, c2 = sky_columns(t, "e1", "e2")
        d = np.column_stack([np.asarray(t[c1], float) - f["g1"],
                             np.asarray(t[c2], float) - f["g2"]])  # fmt: skip
        d[np.asarray(t["is_star"], bool)] = np.nan
        out = d if out is None else out + d
    return out


def controlled_estimate(res: tuple, e: np.ndarray, s: np.ndarray, t: np.ndarray, t_pop: np.ndarray,
                own_scale: bool = False) -> tuple:  # fmt: skip
    """``(g1, g1_err, g2, g2_err)`` of an estimate with :func:`truth_control_variate` applied
    (``e, s``: the ``(n, 2)`` ellipticities and sensitivities, group sums, it used). The
    estimator's denominator is ``sum s``, or with ``own_scale`` (a single image's fixed
    point, whose error is ``std(e) sqrt(n)`` over its Jacobian) the one its error gives."""
    out = list(res)
    ok = np.all(np.isfinite(e), axis=1) & np.all(np.isfinite(s), axis=1)
    e, s, t = e[ok], s[ok], t[ok]
    for i in range(2):
        g, err = res[2 * i], res[2 * i + 1]
        den = float(s[:, i].sum())
        if not (np.isfinite(g) and np.isfinite(err) and den > 0 and e.shape[0] > 2):
            continue
        scale = (err / (float(np.std(e[:, i], ddof=1)) * math.sqrt(e.shape[0])) if own_scale
                 else 1.0 / den)  # fmt: skip
        r = e[:, i] - (e[:, i].sum() / den) * s[:, i]
        pop = t_pop[:, i][np.isfinite(t_pop[:, i])]
        delta, err_c = truth_control_variate(r, t[:, i], pop, scale)
        out[2 * i], out[2 * i + 1] = g - delta, err_c
    return tuple(out)


def shear_groups(gal: Table, fields: dict[str, dict]) -> tuple[np.ndarray, np.ndarray]:
    """Each galaxy's group of renderings: an image with its rotated and noise twins.

    The members of a group are the shear fields of one PSF and shear (``(psf,
    shear_index)``): the image, its 90-degree twin and, for a set with noise twins, the
    two with the noise negated. A galaxy belongs to a group when all its members measured
    it (matched by truth index). Returns ``gid``, the group of each row (``-1``: none, or
    a set without twins), numbered consecutively, and ``base``, the file name of the
    group's first member (the unrotated image with the noise as drawn) per row.
    """
    n = len(gal)
    gid = np.full(n, -1, dtype=np.int64)
    base = np.full(n, "", dtype=object)
    images = np.asarray(gal["image"]).astype(str)
    tidx = np.asarray(gal["truth_index"])
    members: dict[tuple, list[dict]] = {}
    for f in fields.values():
        if f["role"] == "shear":
            members.setdefault((f["psf"], f["shear_index"]), []).append(f)
    nxt = 0
    for key in sorted(members):
        mem = sorted(members[key], key=lambda f: (bool(f["twin"]), bool(f.get("noise_twin"))))
        if len(mem) < 2:
            continue
        rows = [np.flatnonzero((images == f["file"]) & (tidx >= 0)) for f in mem]
        common = tidx[rows[0]]
        for r in rows[1:]:
            common = np.intersect1d(common, tidx[r])
        for r in rows:
            _, ir, ic = np.intersect1d(tidx[r], common, return_indices=True)
            gid[r[ir]] = nxt + ic
            base[r[ir]] = mem[0]["file"]
        nxt += common.size
    return gid, base


def group_members(gid: np.ndarray) -> np.ndarray:
    """``(n_groups, k)`` rows of each group's members from ``gid`` (every group of size k)."""
    use = np.flatnonzero(gid >= 0)
    if use.size == 0:
        return np.zeros((0, 1), dtype=np.int64)
    order = use[np.argsort(gid[use], kind="stable")]
    counts = np.bincount(gid[use])
    counts = counts[counts > 0]
    k = int(counts[0])
    if not np.all(counts == k):
        raise ValueError("groups of renderings of unequal size")
    return order.reshape(-1, k)


MC_COLUMNS = ("psf", "m1", "m1_err", "c1", "c1_err", "m2", "m2_err", "c2", "c2_err", "Q", "n_gal")


def nanmean(x) -> float:
    """Mean of the finite values (NaN, without a warning, when there is none)."""
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(x.mean()) if x.size else math.nan


def _nanstd(x) -> float:
    """Standard deviation of the finite values (NaN when there is none)."""
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(x.std()) if x.size else math.nan


def c_scatter(c: np.ndarray, c_err: np.ndarray, cl: float = 0.95) -> dict[str, float]:
    """The spread of one component of ``c`` over PSFs beyond what its errors give.

    With ``c_k = c0 + d_k + n_k``, ``d_k`` a PSF-dependent offset of spread ``sigma`` and
    ``n_k`` the fit's noise of standard deviation ``c_err[k]``, the statistic
    ``chi2(sigma) = sum_k (c_k - c_hat)^2 / (c_err_k^2 + sigma^2)`` (``c_hat`` the mean
    weighted by ``1 / (c_err_k^2 + sigma^2)``) follows a chi-square with ``n - 1``
    degrees of freedom. Returns ``chi2`` at ``sigma = 0`` with its ``dof`` and ``p``
    (the chance of a larger one from the errors alone), the estimate ``sigma_hat`` (the
    root of ``chi2(sigma) = n - 1``, 0 when ``chi2(0) < n - 1``) and the upper limit
    ``sigma_upper`` at confidence ``cl`` (the root of ``chi2(sigma)`` = its
    ``1 - cl`` quantile: larger spreads would give so small a ``chi2`` less often than
    ``1 - cl``; 0 when even ``sigma = 0`` does).
    """
    from scipy.stats import chi2 as chi2_dist  # scipy.stats: start-up cost (~0.4 s), only here

    c, e = np.asarray(c, dtype=float), np.asarray(c_err, dtype=float)
    ok = np.isfinite(c) & np.isfinite(e) & (e > 0)
    c, e = c[ok], e[ok]
    nan = {"chi2": math.nan, "dof": 0, "p": math.nan, "sigma_hat": math.nan,
           "sigma_upper": math.nan}  # fmt: skip
    if c.size < 2:
        return nan

    def chi2(sig: float) -> float:
        w = 1.0 / (e**2 + sig**2)
        return float(np.sum(w * (c - np.sum(w * c) / np.sum(w)) ** 2))

    dof = c.size - 1
    x0 = chi2(0.0)
    hi = 10.0 * (float(np.ptp(c)) + float(e.max()))  # chi2(hi) is far below any quantile

    def root(target: float) -> float:
        return 0.0 if x0 <= target else float(brentq(lambda s: chi2(s) - target, 0.0, hi))

    return {"chi2": x0, "dof": dof, "p": float(chi2_dist.sf(x0, dof)),
            "sigma_hat": root(float(dof)),
            "sigma_upper": root(float(chi2_dist.ppf(1.0 - cl, dof)))}  # fmt: skip


def _leakage_bins(e, s, x, w, n_bins: int) -> list[tuple]:
    """``(lo, hi, x_b, g_b, err_b, n_b)`` per bin of ``x`` (see :func:`psf_leakage`)."""
    u = np.unique(x)
    if u.size <= n_bins:  # one bin per value (a PSF constant over each image)
        idx, edges = np.searchsorted(u, x), np.column_stack([u, u])
    else:
        e_ = np.unique(np.quantile(x, np.linspace(0.0, 1.0, n_bins + 1)))
        idx, edges = bin_index(x, e_), np.column_stack([e_[:-1], e_[1:]])
    out = []
    for b in range(edges.shape[0]):
        sel = idx == b
        nb = int(sel.sum())
        sw = float(np.sum(w[sel] * s[sel]))
        if nb < 2 or not sw > 0:
            continue
        g = float(np.sum(w[sel] * e[sel])) / sw
        xb = float(np.sum(w[sel] * s[sel] * x[sel])) / sw
        var = nb / (nb - 1) * float(np.sum(w[sel] ** 2 * (e[sel] - g * s[sel]) ** 2))
        out.append((float(edges[b, 0]), float(edges[b, 1]), xb, g, math.sqrt(var) / sw, nb))
    return out


def _line_fit(x: np.ndarray, y: np.ndarray, err: np.ndarray,
              min_spread: float) -> tuple[float, ...]:  # fmt: skip
    """Weighted least squares ``y = c + a x``: ``(a, a_err, c, c_err, chi2, dof)``; ``a``
    NaN and ``c`` the weighted mean when ``x`` spans less than ``min_spread``."""
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(err) & (err > 0)
    x, y, w = x[ok], y[ok], 1.0 / err[ok] ** 2
    if x.size == 0:
        return (math.nan,) * 4 + (math.nan, 0)
    if x.size < 2 or not float(np.ptp(x)) >= min_spread:
        c = float(np.sum(w * y) / np.sum(w))
        return (math.nan, math.nan, c, float(1.0 / math.sqrt(np.sum(w))),
                float(np.sum(w * (y - c) ** 2)), int(x.size - 1))  # fmt: skip
    A = np.column_stack([np.ones_like(x), x])
    cov = np.linalg.inv(A.T @ (A * w[:, None]))
    c, a = cov @ (A.T @ (w * y))
    chi2 = float(np.sum(w * (y - c - a * x) ** 2))
    return (float(a), float(math.sqrt(cov[1, 1])), float(c), float(math.sqrt(cov[0, 0])), chi2,
            int(x.size - 2))  # fmt: skip


def psf_leakage(e1, e2, sens1, sens2, psf_e1, psf_e2, *, n_bins: int = 8, weights=None,
                min_spread: float = 1e-4) -> dict[str, Any]:  # fmt: skip
    """PSF leakage: the mean shear against the PSF's ellipticity, ``g_i = c_i + alpha_i e_psf,i``.

    For each component ``i`` the galaxies are binned by the ellipticity of the PSF at
    their position, ``e_psf,i`` (``n_bins`` bins of equal counts, or one bin per
    distinct value when there are no more than ``n_bins``, as for a PSF constant over
    each image). A bin's shear is the mean shear over mean sensitivity (docs: method,
    eq-key2), ``g_b = sum w e_i / sum w s_i``, with the error from the scatter of its
    galaxies, ``sqrt(n_b / (n_b - 1) sum w^2 (e_i - g_b s_i)^2) / sum w s_i``, at the
    sensitivity-weighted mean PSF ellipticity ``x_b = sum w s_i e_psf,i / sum w s_i``
    (for ``e_i = s_i (c_i + alpha_i e_psf,i)`` plus noise, ``g_b = c_i + alpha_i x_b``
    exactly). ``c_i, alpha_i`` are the weighted least-squares fit of ``g_b`` on ``x_b``
    (weights ``1 / err_b^2``), with the errors of its covariance.

    Parameters
    ----------
    e1, e2 : array_like
        ``(n,)`` ellipticities, or their residuals ``e - s g`` from a known shear ``g``,
        in the frame of ``psf_e1, psf_e2`` (dimensionless).
    sens1, sens2 : array_like
        ``(n,)`` shear sensitivities ``d<e_i>/dg_i``.
    psf_e1, psf_e2 : array_like
        ``(n,)`` the PSF's ellipticity at each galaxy (dimensionless).
    n_bins : int
        Bins per component.
    weights : array_like, optional
        ``(n,)`` per-galaxy weights (default 1, e.g. the catalogue's inverse-variance
        ``weight``); rows with a weight of 0 or any non-finite value are skipped.
    min_spread : float
        Least range of the bins' PSF ellipticities ``x_b`` for ``alpha`` to be fitted
        (dimensionless); below it only ``c`` is (a PSF constant over the sample, to
        rounding or to the ~1e-7 that the WCS's local frame moves it by).

    Returns
    -------
    dict
        ``alpha1, alpha1_err, c1, c1_err`` and the same for component 2
        (dimensionless; ``alpha`` NaN where the bins' PSF ellipticities span less than
        ``min_spread``, ``c`` then the sample's mean shear), ``chi2_1, dof_1, chi2_2,
        dof_2`` of the fits, ``n1, n2`` (galaxies used) and ``bins``, a table with one
        row per component and bin: ``component``, ``bin``, ``lo, hi`` (the bin's range of
        ``e_psf``), ``psf_e`` (``x_b``), ``g``, ``g_err``, ``n``.
    """
    e = [np.asarray(a, dtype=float).ravel() for a in (e1, e2)]
    s = [np.asarray(a, dtype=float).ravel() for a in (sens1, sens2)]
    x = [np.asarray(a, dtype=float).ravel() for a in (psf_e1, psf_e2)]
    n = e[0].size
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float).ravel()
    if any(a.size != n for a in (*e, *s, *x, w)):
        raise ValueError("e1, e2, sens1, sens2, psf_e1, psf_e2 and weights must have one "
                         "value per galaxy")  # fmt: skip
    if int(n_bins) < 1:
        raise ValueError(f"n_bins must be at least 1, got {n_bins}")
    out: dict[str, Any] = {}
    rows = []
    for i in (0, 1):
        ok = (np.isfinite(e[i]) & np.isfinite(s[i]) & np.isfinite(x[i]) & np.isfinite(w)
              & (w > 0))  # fmt: skip
        b = _leakage_bins(e[i][ok], s[i][ok], x[i][ok], w[ok], int(n_bins))
        arr = np.array([r[2:5] for r in b], dtype=float).reshape(-1, 3)
        a, ae, c, ce, chi2, dof = _line_fit(arr[:, 0], arr[:, 1], arr[:, 2], min_spread)
        k = i + 1
        out.update({f"alpha{k}": a, f"alpha{k}_err": ae, f"c{k}": c, f"c{k}_err": ce,
                    f"chi2_{k}": chi2, f"dof_{k}": dof, f"n{k}": int(ok.sum())})  # fmt: skip
        rows += [(k, j, *r) for j, r in enumerate(b)]
    out["bins"] = Table(rows=rows, names=("component", "bin", "lo", "hi", "psf_e", "g", "g_err",
                                          "n"),
                        dtype=(int, int, float, float, float, float, float, int))  # fmt: skip
    return out


_LEAK_NAMES = ("psf", "source", "alpha1", "alpha1_err", "alpha2", "alpha2_err", "c1", "c1_err",
               "c2", "c2_err", "n")  # fmt: skip


def leakage_table(gal: Table, e: np.ndarray, s: np.ndarray, fields: dict[str, dict],
                   psfs: list[int], pairs: bool, n_bins: int = 8) -> Table:  # fmt: skip
    """:func:`psf_leakage` per PSF and for all PSFs together (``psf == "all"``), with the
    truth's PSF (``source == "truth"``: its ellipticity at each galaxy) and with the
    catalogue's model PSF (``"model"``).

    The galaxies matched to the truth enter with their residuals from their image's
    shear, ``e - s g`` (``e, s``: the ``(n, 2)`` sky-frame shapes and sensitivities of
    ``gal``'s rows; ``g`` the manifest's), so that images of different shears combine;
    for a set with twins, the members of each group are summed (their shape noise
    cancels) at the members' mean PSF ellipticity, and the galaxies outside the groups
    are left out. ``n`` counts the galaxies (or groups) used.
    """
    names, inv = np.unique(np.asarray(gal["image"]).astype(str), return_inverse=True)
    g = np.array([[fields[m]["g1"], fields[m]["g2"]] for m in names], float).reshape(-1, 2)
    r = e - s * g[inv]
    matched = (np.asarray(gal["truth_index"]) >= 0) & ~np.asarray(gal["truth_star"], bool)
    if pairs:
        mem = group_members(shear_groups(gal, fields)[0])
        mem = mem[matched[mem].all(axis=1)]
    else:
        mem = np.flatnonzero(matched)[:, None]
    R, S = r[mem].sum(axis=1), s[mem].sum(axis=1)
    psf_of = np.asarray(gal["psf"])[mem[:, 0]]
    rows = []
    for source, col in (("truth", "true"), ("model", "model")):
        P = np.column_stack([np.asarray(gal[f"psf_e{i}_{col}"], float)[mem].mean(axis=1)
                             for i in (1, 2)])  # fmt: skip
        for k in [*psfs, "all"]:
            sel = np.ones(len(R), bool) if k == "all" else psf_of == k
            res = psf_leakage(R[sel, 0], R[sel, 1], S[sel, 0], S[sel, 1], P[sel, 0], P[sel, 1],
                              n_bins=n_bins)  # fmt: skip
            rows.append((str(k), source, *(res[q] for q in _LEAK_NAMES[2:-1]),
                         min(res["n1"], res["n2"])))  # fmt: skip
    return Table(rows=rows, names=_LEAK_NAMES,
                 dtype=(str, str, *[float] * 8, int))  # fmt: skip


def mc_summary(per: Table) -> dict[str, float]:
    """``<m>`` over PSFs and components, its errors, ``sigma_c``, its statistical floor and
    the spread of ``c`` beyond the errors (:func:`c_scatter`)."""
    ms = np.concatenate([per["m1"], per["m2"]]).astype(float)
    me = np.concatenate([per["m1_err"], per["m2_err"]]).astype(float)
    ok = np.isfinite(ms) & np.isfinite(me)
    c1, c2 = np.asarray(per["c1"], float), np.asarray(per["c2"], float)
    e1, e2 = np.asarray(per["c1_err"], float), np.asarray(per["c2_err"], float)
    return {
        "mean_m": float(np.mean(ms[ok])) if ok.any() else math.nan,
        # error of the mean of the PSFs' m (independent fits)
        "mean_m_err": float(math.sqrt(np.sum(me[ok] ** 2)) / ok.sum()) if ok.any() else math.nan,
        # the paper's error of <m> (Kitching et al. 2008, section 4.2): the PSFs' mean error
        "mean_m_err_paper": float(np.mean(me[ok])) if ok.any() else math.nan,
        "sigma_c": float(math.hypot(_nanstd(c1), _nanstd(c2))),
        # what sigma_c would be from the fits' errors alone
        "sigma_c_stat": float(np.hypot(np.sqrt(nanmean(e1**2)), np.sqrt(nanmean(e2**2)))),
        "mean_c1": nanmean(c1),
        "mean_c2": nanmean(c2),
        **_intrinsic_sigma_c(c1, e1, c2, e2),
    }


def _intrinsic_sigma_c(c1, e1, c2, e2) -> dict[str, float]:
    """``sigma_c`` of the offsets alone, the noise taken out (:func:`c_scatter` per
    component, combined as the paper's ``sqrt(sigma_c1^2 + sigma_c2^2)``)."""
    a, b = c_scatter(c1, e1), c_scatter(c2, e2)
    return {"sigma_c_hat": float(math.hypot(a["sigma_hat"], b["sigma_hat"])),
            "sigma_c_upper": float(math.hypot(a["sigma_upper"], b["sigma_upper"])),
            "c1_chi2": a["chi2"], "c2_chi2": b["chi2"], "c_dof": a["dof"],
            "c1_p": a["p"], "c2_p": b["p"]}  # fmt: skip


def quantile_edges(values: np.ndarray, spec, extra: np.ndarray) -> np.ndarray:
    """Edges from ``spec`` (a number of equal-count bins of ``values``, or the edges)."""
    if np.ndim(spec) == 0:
        n = int(spec)
        v = values[np.isfinite(values)]
        if n < 1 or v.size == 0:
            return np.array([])
        edges = np.quantile(v, np.linspace(0.0, 1.0, n + 1))
        allv = np.concatenate([v, extra[np.isfinite(extra)]])
        edges[0], edges[-1] = min(edges[0], allv.min()), max(edges[-1], allv.max())
        return np.unique(edges)
    edges = np.asarray(spec, dtype=float)
    if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
        raise ValueError(f"bin edges must increase, got {list(edges)}")
    return edges


def bin_index(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Bin of each value, ``edges[i] <= v < edges[i+1]`` (last bin closed); ``-1`` outside.

    The same convention as :class:`pylensfit.prior.BinnedPrior`, so that a galaxy's prior
    and its shear bin agree.
    """
    values = np.asarray(values, dtype=float)
    edges = np.asarray(edges, dtype=float)
    idx = np.searchsorted(edges, values, side="right") - 1
    idx[values == edges[-1]] = edges.size - 2
    idx[(idx < 0) | (idx >= edges.size - 1) | ~np.isfinite(values)] = -1
    return idx
