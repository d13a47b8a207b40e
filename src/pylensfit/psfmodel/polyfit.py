"""The stages of :meth:`PolynomialPSF.fit <pylensfit.psfmodel.PolynomialPSF.fit>`: the
stars cut out and centred (:class:`Stars`), then the iterated per-pixel least-squares
fit, each candidate checked against the model without itself (:class:`Fit`)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .._util import newton_peak
from ..psf import PSFError
from ..psf.fourier import gaussian_image, gaussian_peak, pad_to, subpixel_shift
from ..psf.stars import REASONS, StarChecks, check_star_inputs, star_cutouts
from .basis import design, n_terms, phase

log = logging.getLogger("pylensfit.psfmodel")


@dataclass(frozen=True)
class FitOptions:
    """The settings of :meth:`PolynomialPSF.fit <pylensfit.psfmodel.PolynomialPSF.fit>`
    that its stages share: the stars' tests (``checks.max_chi2`` is the fit's ``clip``),
    the number of fit / check passes and the fewest stars per coefficient."""

    checks: StarChecks
    n_iter: int
    min_stars_per_coefficient: float

    def as_dict(self) -> dict:
        """The options by the fit's keyword names (``diagnostics["options"]``)."""
        c = self.checks
        return {"clip": c.max_chi2, "n_iter": self.n_iter, "min_correlation": c.min_correlation,
                "model_error": c.model_error, "core_level": c.core_level,
                "max_shift": c.max_shift, "min_snr": c.min_snr,
                "centroid_sigma": c.centroid_sigma, "margin": c.margin,
                "min_stars_per_coefficient": self.min_stars_per_coefficient}  # fmt: skip


def check_fit_inputs(image, x, y, weight, size, order, holdout, n_iter):
    """The checked image, positions and weight map of the fit (``ValueError`` for
    inconsistent arguments)."""
    image, x, y, weight = check_star_inputs(image, x, y, weight, size)
    if not (int(order) == order and order >= 0):
        raise ValueError(f"order must be a non-negative integer, got {order!r}")
    if not 0.0 <= holdout < 1.0:
        raise ValueError(f"holdout must be in [0, 1), got {holdout!r}")
    if n_iter < 0:
        raise ValueError(f"n_iter must be >= 0, got {n_iter}")
    return image, x, y, weight


def no_star_error(reason: np.ndarray, source: str, idx: np.ndarray | None = None,
                  why: np.ndarray | None = None) -> PSFError:  # fmt: skip
    """The error for no usable star, with the counts of the rejection reasons ``reason``
    (those of the stars ``idx`` replaced by ``why``, if given)."""
    if idx is not None:
        reason = reason.copy()
        reason[idx] = why
    counts = {r: int(np.count_nonzero(reason == r)) for r in set(reason.tolist()) if r}
    detail = ", ".join(f"{k}: {v}" for k, v in sorted(counts.items()))
    return PSFError(f"{source}: no usable PSF star among {reason.size} candidates "
                    f"({detail or 'none'})")  # fmt: skip


@dataclass
class Stars:
    """The candidate stars that passed the first stage, and the bookkeeping of all."""

    n: int  # number of candidates in the input list
    idx: np.ndarray  # (m,) index into the input list of each star kept
    ix: np.ndarray  # (m,) integer pixel of each cutout's centre
    iy: np.ndarray
    F0: np.ndarray  # (m, big, big//2+1) rfft2 of the cutouts
    D: np.ndarray  # F0 phase-referenced to the cutout centre
    x0: np.ndarray  # (m,) catalogue position relative to the cutout centre
    y0: np.ndarray
    X: np.ndarray  # (m,) stage-1 centre relative to the cutout centre
    Y: np.ndarray
    stars: np.ndarray  # (m, size, size) stars centred at (X, Y)
    amp: np.ndarray  # (m,) Gaussian-weighted flux
    sig: np.ndarray  # (m,) pixel noise
    reason: np.ndarray  # (n,) object: '' or the stage-1 rejection reason
    snr: np.ndarray  # (n,) Gaussian matched-filter S/N (NaN where not measured)

    @property
    def m(self) -> int:
        return int(self.idx.size)


def first_stage(image, weight, x, y, sigma_all, size, checks: StarChecks) -> Stars:
    """Cutouts, Gaussian centring and S/N cut, as the first stage of ``stack_psf``."""
    big = checks.cutout_side(size)
    stamps, idx, ix, iy, reason = star_cutouts(image, weight, x, y, big)
    bad_sig = ~(np.isfinite(sigma_all) & (sigma_all > 0))
    reason[(reason == "") & bad_sig] = REASONS["noise"]
    keep = reason[idx] == ""
    stamps, idx = stamps[keep], idx[keep]
    if idx.size == 0:
        z, zi = np.zeros(0), np.zeros(0, np.int64)
        e = np.zeros((0, big, big // 2 + 1), complex)
        return Stars(n=x.size, idx=zi, ix=zi, iy=zi, F0=e, D=e, x0=z, y0=z, X=z, Y=z,
                     stars=np.zeros((0, size, size)), amp=z, sig=z, reason=reason,
                     snr=np.full(x.size, np.nan))  # fmt: skip
    sig = sigma_all[idx]
    F0 = np.fft.rfft2(stamps)
    D = F0 * phase(big)[None]
    x0, y0 = x[idx] - ix[idx], y[idx] - iy[idx]
    max_shift = checks.max_shift
    X, Y, ok = gaussian_peak(D, checks.centroid_sigma, x0, y0, max(max_shift, 1.0))
    stars = subpixel_shift(F0, X, Y, big, size)
    G = gaussian_image(size, checks.centroid_sigma)
    amp = np.einsum("ijk,jk->i", stars, G) / np.sum(G * G)
    snr_k = amp * np.sqrt(np.sum(G * G)) / sig
    snr = np.full(x.size, np.nan)
    snr[idx] = snr_k
    why = np.full(idx.size, "", dtype=object)
    for mask, r in ((~ok, "peak"), (np.hypot(X - x0, Y - y0) > max_shift, "shift"),
                    (~(snr_k >= checks.min_snr), "snr"), (~(amp > 0), "flux")):  # fmt: skip
        why[mask & (why == "")] = REASONS[r]
    reason[idx] = why
    k = why == ""
    return Stars(n=x.size, idx=idx[k], ix=ix[idx[k]], iy=iy[idx[k]], F0=F0[k], D=D[k],
                 x0=x0[k], y0=y0[k], X=X[k], Y=Y[k], stars=stars[k], amp=amp[k], sig=sig[k],
                 reason=reason, snr=snr)  # fmt: skip


@dataclass
class Fit:
    """One iterated polynomial fit to a subset of the stars."""

    order: int
    coefs: np.ndarray  # (p, size, size)
    cov: np.ndarray  # (p, p): (A^T W A)^-1, the covariance of the coefficients per pixel
    used: np.ndarray  # (m,) in the final solve
    why: np.ndarray  # (m,) object: '' or the last check's rejection (for candidates)
    X: np.ndarray  # (m,) centres relative to the cutout centre
    Y: np.ndarray
    unit: np.ndarray  # (m, size, size) unit-flux stars centred on (X, Y)
    flux: np.ndarray  # (m,) NaN for stars never checked
    snr: np.ndarray
    corr: np.ndarray
    chi2: np.ndarray


def solve(A: np.ndarray, w: np.ndarray, Y: np.ndarray):
    """Weighted least squares for all pixels at once: ``coefs (p, npix)``, ``cov (p, p)``."""
    Aw = A * w[:, None]
    cov = np.linalg.pinv(A.T @ Aw, hermitian=True)
    return cov @ (Aw.T @ Y), cov


def references(A, w, unit, used, coefs, cov):
    """The model at each star's position, independent of the star, and its pixel variance.

    Stars in the fit get the leave-one-out prediction ``y - (y - yhat) / (1 - h)`` (``h``
    the star's leverage) with variance ``q / (1 - h)``, ``q = a^T cov a``; the others the
    prediction ``yhat`` with variance ``q``.
    """
    m, size = unit.shape[0], unit.shape[-1]
    y = unit.reshape(m, -1)
    yhat = A @ coefs
    q = np.einsum("ip,pq,iq->i", A, cov, A)
    h = np.where(used, w * q, 0.0)
    loo = used & (1.0 - h > 1e-6)  # a star alone in its part of the model: no LOO
    one_h = np.where(loo, 1.0 - h, 1.0)
    ref = np.where(loo[:, None], y - (y - yhat) / one_h[:, None], yhat)
    var = q / one_h
    return ref.reshape(m, size, size), var


class StarCheck(NamedTuple):
    """One comparison of stars with their references, ``(m,)`` each but ``stars``: the
    new centres ``X, Y`` (pixels from the cutout centres), the re-centred stars
    ``(m, size, size)``, their flux, matched-filter S/N, noise-debiased correlation and
    core reduced chi-square."""

    X: np.ndarray
    Y: np.ndarray
    stars: np.ndarray
    flux: np.ndarray
    snr: np.ndarray
    corr: np.ndarray
    chi2: np.ndarray


def check_stars(S: Stars, ref, var_ref, X, Y, checks: StarChecks) -> StarCheck:
    """Re-centre the stars on their references and measure flux, S/N, correlation, chi2."""
    big, size = S.D.shape[-2], ref.shape[-1]
    npix = size * size
    tot = ref.sum(axis=(1, 2))
    good = tot > 0
    tot = np.where(good, tot, 1.0)
    ref = ref / tot[:, None, None]
    var_ref = var_ref / tot**2
    R = np.fft.rfft2(pad_to(ref, big)) * phase(big)[None]
    Xn, Yn, ok = newton_peak(S.D, R, X, Y)
    Xn, Yn = np.where(ok, Xn, X), np.where(ok, Yn, Y)
    st = subpixel_shift(S.F0, Xn, Yn, big, size)
    sp = np.einsum("ijk,ijk->i", st, ref)
    pp = np.einsum("ijk,ijk->i", ref, ref)
    ss = np.einsum("ijk,ijk->i", st, st)
    sig = S.sig
    f = np.where(good, sp / pp, np.nan)
    tiny = 1e-300
    corr = sp / np.sqrt(
        np.maximum(ss - npix * sig**2, tiny) * np.maximum(pp - npix * var_ref, tiny)
    )
    core = ref >= checks.core_level * ref.max(axis=(1, 2))[:, None, None]
    resid = st - f[:, None, None] * ref
    var_pix = (sig[:, None, None] ** 2 + (f**2 * var_ref)[:, None, None]
               + (checks.model_error * f[:, None, None] * ref) ** 2)  # fmt: skip
    dof = np.maximum(core.sum(axis=(1, 2)) - 3, 1)
    chi2 = np.sum(np.where(core, resid**2 / var_pix, 0.0), axis=(1, 2)) / dof
    snr = sp / (sig * np.sqrt(pp))
    return StarCheck(Xn, Yn, st, f, snr, corr, chi2)


def verdict(S: Stars, chk: StarCheck, checks: StarChecks) -> np.ndarray:
    """Rejection reason of each star after a check (``''`` for a star kept)."""
    X, Y, f, corr, chi2 = chk.X, chk.Y, chk.flux, chk.corr, chk.chi2
    why = np.full(S.m, "", dtype=object)
    clip = checks.max_chi2
    tests = [(np.hypot(X - S.x0, Y - S.y0) > checks.max_shift, "shift"), (~(f > 0), "flux"),
             (~(corr >= checks.min_correlation), "correlation")]  # fmt: skip
    if clip is not None:
        tests.append((~(chi2 <= clip), "chi2"))
    for mask, r in tests:
        why[mask & (why == "")] = REASONS[r]
    return why


def iterate(S: Stars, cand: np.ndarray, order: int, uv, opts: FitOptions) -> Fit:
    """Fit, check every candidate against the model at its position, refit, ``n_iter`` times.

    Every candidate is checked at every pass against the model without it, so a star
    rejected early (e.g. next to a contaminant that pulled the first fit) comes back
    when the model no longer disagrees with it.
    """
    m, size = S.m, S.stars.shape[-1]
    u, v = uv
    A = design(u, v, order)
    safe = np.where(S.amp > 0, S.amp, 1.0)
    unit = S.stars / safe[:, None, None]
    var_unit = (S.sig / safe) ** 2
    X, Y = S.X.copy(), S.Y.copy()
    used = cand.copy()
    nan = np.full(m, np.nan)
    flux, snr, corr, chi2 = nan.copy(), nan.copy(), nan.copy(), nan.copy()
    why = np.full(m, "", dtype=object)
    c = cand
    Sc = subset(S, c)
    for _ in range(opts.n_iter):
        if not used.any():
            break
        w = np.where(used, 1.0 / var_unit, 0.0)
        coefs, cov = solve(A[used], w[used], unit[used].reshape(int(used.sum()), -1))
        ref, var_ref = references(A, w, unit, used, coefs, cov)
        chk = check_stars(Sc, ref[c], var_ref[c], X[c], Y[c], opts.checks)
        f = chk.flux
        X[c], Y[c], flux[c], snr[c], corr[c], chi2[c] = chk.X, chk.Y, f, chk.snr, chk.corr, chk.chi2
        why[c] = verdict(Sc, chk, opts.checks)
        fa = np.where(f > 0, f, 1.0)
        unit[c] = np.where((f > 0)[:, None, None], chk.stars / fa[:, None, None], unit[c])
        var_unit[c] = np.where(f > 0, (S.sig[c] / fa) ** 2, var_unit[c])
        used = cand & (why == "")
    if not used.any():
        return Fit(order, np.zeros((n_terms(order), size, size)), np.zeros((1, 1)), used, why,
                   X, Y, unit, flux, snr, corr, chi2)  # fmt: skip
    w = 1.0 / var_unit[used]
    coefs, cov = solve(A[used], w, unit[used].reshape(int(used.sum()), -1))
    return Fit(order, coefs.reshape(-1, size, size), cov, used, why, X, Y, unit, flux, snr,
               corr, chi2)  # fmt: skip


def subset(S: Stars, mask: np.ndarray) -> Stars:
    """The stars of ``mask`` (the per-candidate bookkeeping is shared)."""
    pick = {k: getattr(S, k)[mask] for k in ("idx", "ix", "iy", "F0", "D", "x0", "y0", "X",
                                             "Y", "stars", "amp", "sig")}  # fmt: skip
    return Stars(n=S.n, reason=S.reason, snr=S.snr, **pick)


def affordable_order(n_stars: int, order: int, per_coef: float) -> int:
    """The highest order ``<= order`` with at least ``per_coef`` stars per coefficient."""
    while order > 0 and n_stars < per_coef * n_terms(order):
        order -= 1
    return order


def fit_with_order(S: Stars, cand: np.ndarray, order: int, uv, opts: FitOptions, what: str
                   ) -> Fit:  # fmt: skip
    """:func:`iterate`, lowering the order (with a warning) while too few stars survive."""
    per_coef = opts.min_stars_per_coefficient
    want = order
    n_used = int(cand.sum())
    order = affordable_order(n_used, order, per_coef)
    while True:
        fit = iterate(S, cand, order, uv, opts)
        n_used = int(fit.used.sum())
        lower = affordable_order(n_used, order, per_coef)
        if lower == order or n_used == 0:
            break
        order = lower
    if order < want:
        log.warning("%s: %d usable stars (%d candidates) for a PSF of order %d (%d "
                    "coefficients, at least %g stars each): order lowered to %d", what,
                    n_used, int(cand.sum()), want, n_terms(want), per_coef, order)  # fmt: skip
    return fit
