"""What :meth:`PolynomialPSF.fit <pylensfit.psfmodel.PolynomialPSF.fit>` reports: the
per-star table, the held-out stars' residuals against the model fitted without them,
and the summary diagnostics."""

from __future__ import annotations

import numpy as np
from astropy.table import Table
from scipy.stats import chi2 as chi2_dist

from .basis import moments_many, n_terms
from .polyfit import Fit, FitOptions, Stars

TABLE_COLUMNS = ("x_cat", "y_cat", "x", "y", "flux", "snr", "correlation", "chi2", "used",
                 "reason", "heldout", "e1_star", "e2_star", "sigma_star", "e1_model",
                 "e2_model", "sigma_model")  # fmt: skip


def moment_noise(image: np.ndarray, rng: np.random.Generator, nu: float = 200.0,
                 n_real: int = 48) -> tuple[float, float]:  # fmt: skip
    """Noise of the adaptive moments of a star of this PSF, times its matched-filter S/N.

    Monte Carlo: ``n_real`` copies of ``image`` plus white noise at matched-filter S/N
    ``nu`` (the small-noise, linear regime). Returns ``k_e``, the standard deviation of
    each ellipticity component times the S/N, and ``k_s``, that of ``ln sigma``.
    """
    img = image / image.sum()
    noise = np.sqrt(np.sum(img * img)) / nu
    sims = img[None] + rng.normal(0.0, noise, (n_real,) + img.shape)
    sigma, e1, e2 = moments_many(sims)
    ok = np.isfinite(sigma) & np.isfinite(e1) & np.isfinite(e2)
    if ok.sum() < 4:
        return np.nan, np.nan
    k_e = nu * np.sqrt(0.5 * (np.var(e1[ok], ddof=1) + np.var(e2[ok], ddof=1)))
    return float(k_e), float(nu * np.std(np.log(sigma[ok]), ddof=1))


def heldout_summary(tab: Table, k_e: float, k_s: float) -> dict:
    """Residuals of the held-out stars (used in the final fit) against the first fit."""
    sel = np.asarray(tab["heldout"] & tab["used"])
    de1 = np.asarray(tab["e1_star"] - tab["e1_model"])[sel]
    de2 = np.asarray(tab["e2_star"] - tab["e2_model"])[sel]
    ds = np.asarray(tab["sigma_star"] / tab["sigma_model"] - 1.0)[sel]
    snr = np.asarray(tab["snr"])[sel]
    ok = np.isfinite(de1) & np.isfinite(de2) & np.isfinite(ds) & (snr > 0)
    de1, de2, ds, snr = de1[ok], de2[ok], ds[ok], snr[ok]
    if de1.size == 0:
        return {"heldout_n": 0}
    sig_e = k_e / snr
    noise_e = float(np.sqrt(np.mean(sig_e**2)))
    noise_s = float(np.sqrt(np.mean((k_s / snr) ** 2)))
    rms = {k: float(np.sqrt(np.mean(d**2))) for k, d in (("e1", de1), ("e2", de2), ("s", ds))}
    chi2 = float(np.mean(np.concatenate([de1, de2]) ** 2 / np.concatenate([sig_e, sig_e]) ** 2))
    return {
        "heldout_n": int(de1.size),
        "heldout_mean_de1": float(de1.mean()),
        "heldout_mean_de2": float(de2.mean()),
        "heldout_rms_de1": rms["e1"],
        "heldout_rms_de2": rms["e2"],
        "heldout_noise_de": noise_e,
        "heldout_excess_de1": float(np.sqrt(max(rms["e1"] ** 2 - noise_e**2, 0.0))),
        "heldout_excess_de2": float(np.sqrt(max(rms["e2"] ** 2 - noise_e**2, 0.0))),
        "heldout_chi2_de": chi2,
        "heldout_pvalue_de": float(chi2_dist.sf(2 * de1.size * chi2, 2 * de1.size)),
        "heldout_mean_dsigma": float(ds.mean()),
        "heldout_rms_dsigma": rms["s"],
        "heldout_noise_dsigma": noise_s,
        "heldout_excess_dsigma": float(np.sqrt(max(rms["s"] ** 2 - noise_s**2, 0.0))),
        "moment_noise_k_e": k_e,
        "moment_noise_k_sigma": k_s,
    }


def holdout_mask(used: np.ndarray, fraction: float, p: int, rng) -> np.ndarray:
    """A random ``fraction`` of the used stars, or none if the rest could not fit ``p`` terms."""
    hold = np.zeros(used.size, bool)
    pool = np.flatnonzero(used)
    k = int(round(fraction * pool.size))
    if k >= 1 and pool.size - k >= p + 1:
        hold[rng.choice(pool, k, replace=False)] = True
    return hold


def star_table(S: Stars, x, y, fit: Fit, model, model_h, hold) -> Table:
    """The per-candidate table of :meth:`PolynomialPSF.fit`."""
    n, k = S.n, S.idx
    col = {c: np.full(n, np.nan) for c in TABLE_COLUMNS if c not in ("used", "reason",
                                                                     "heldout")}  # fmt: skip
    col["x_cat"], col["y_cat"] = x.copy(), y.copy()
    xs, ys = S.ix + fit.X, S.iy + fit.Y
    img, sx, sy, _ = model._draw_centred(xs, ys)
    if model_h is not None and hold.any():
        img[hold] = model_h._draw(xs[hold], ys[hold])
    col["x"][k], col["y"][k] = xs + sx, ys + sy
    col["flux"][k], col["correlation"][k], col["chi2"][k] = fit.flux, fit.corr, fit.chi2
    col["snr"] = S.snr.copy()
    col["snr"][k] = np.where(np.isfinite(fit.snr), fit.snr, S.snr[k])
    col["sigma_star"][k], col["e1_star"][k], col["e2_star"][k] = moments_many(fit.unit)
    col["sigma_model"][k], col["e1_model"][k], col["e2_model"][k] = moments_many(img)
    reason = S.reason.copy()
    reason[k] = fit.why
    used = np.zeros(n, bool)
    used[k] = fit.used
    reason[used] = ""
    heldout = np.zeros(n, bool)
    heldout[k] = hold
    col["used"], col["heldout"] = used, heldout
    col["reason"] = np.array([str(r) for r in reason], dtype=str) if n else np.zeros(0, str)
    return Table({c: col[c] for c in TABLE_COLUMNS})


def fit_diagnostics(tab: Table, fit: Fit, order_requested: int, opts: FitOptions, source: str
                    ) -> dict:  # fmt: skip
    """The summary of a fit (:attr:`PolynomialPSF.diagnostics
    <pylensfit.psfmodel.PolynomialPSF.diagnostics>`), without the held-out check."""
    reason = np.asarray(tab["reason"], dtype=str)
    used = np.asarray(tab["used"], dtype=bool)
    chi2 = np.asarray(tab["chi2"], dtype=float)[used]
    return {
        "kind": "polynomial",
        "order": fit.order,
        "order_requested": order_requested,
        "n_terms": n_terms(fit.order),
        "n_stars": int(used.size),
        "n_used": int(used.sum()),
        "n_rejected": int((~used).sum()),
        "rejected": {r: int(np.sum(reason == r)) for r in sorted(set(reason.tolist())) if r},
        "n_heldout": int(np.sum(tab["heldout"])),
        "chi2_median": float(np.median(chi2)) if chi2.size else np.nan,
        "source": source,
        "options": opts.as_dict(),
    }

