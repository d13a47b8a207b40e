"""The stages of :func:`~pylensfit.psf.stack_psf`: cut the stars out, centre them on a
Gaussian, then re-centre, compare and reject them against the stack, pass by pass.

The candidates' bookkeeping (:class:`Candidates`, with their diagnostics in a
:class:`StarRecord`) and the centred stars (:class:`Centred`) travel between the stages;
each comparison with the stack gives a :class:`Check`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .._util import newton_peak, rfft_frequencies
from .fourier import gaussian_image, gaussian_peak, pad_to, subpixel_shift
from .stars import REASONS, StarChecks, star_cutouts
from .transform import PSFError


@dataclass
class StarRecord:
    """Per-candidate diagnostics of :func:`stack_psf` (NaN until measured), ``(n,)`` each."""

    x: np.ndarray
    y: np.ndarray
    flux: np.ndarray
    snr: np.ndarray
    correlation: np.ndarray
    chi2: np.ndarray

    @classmethod
    def empty(cls, n: int) -> StarRecord:
        """All-NaN diagnostics for ``n`` candidates."""
        return cls(*(np.full(n, np.nan) for _ in range(6)))


@dataclass
class Candidates:
    """The candidate stars of :func:`stack_psf`: why each is rejected, and which have cutouts.

    ``reason`` has one entry per candidate (``''`` while in play); ``idx`` indexes the
    ``m`` candidates with a usable cutout, which all the ``(m,)`` arrays follow.
    """

    n: int
    source: str
    reason: np.ndarray
    idx: np.ndarray
    ix: np.ndarray
    iy: np.ndarray
    sig: np.ndarray
    record: StarRecord

    @property
    def m(self) -> int:
        """Number of candidates with a usable cutout."""
        return int(self.idx.size)

    def reject(self, mask: np.ndarray, why: str) -> None:
        """Reject the cutout stars of ``mask`` (``(m,)``) still in play, for ``why``."""
        self.reason[self.idx[mask & (self.reason[self.idx] == "")]] = why

    def used_now(self) -> np.ndarray:
        """``(m,)`` boolean, the cutout stars still in play."""
        return self.reason[self.idx] == ""

    def error(self) -> PSFError:
        """The error for no usable star, with the counts of the rejection reasons."""
        reason = self.reason
        counts = {r: int(np.count_nonzero(reason == r)) for r in set(reason.tolist()) if r}
        detail = ", ".join(f"{k}: {v}" for k, v in sorted(counts.items()))
        return PSFError(
            f"{self.source}: no usable PSF star among {self.n} candidates ({detail or 'none'})"
        )


@dataclass
class Centred:
    """The cutout stars' Fourier transforms, centres and unit-flux images (``(m, ...)``)."""

    phase: np.ndarray
    F0: np.ndarray
    D: np.ndarray
    x0: np.ndarray
    y0: np.ndarray
    X: np.ndarray
    Y: np.ndarray
    unit: np.ndarray
    var_unit: np.ndarray

    def median_stack(self, use: np.ndarray) -> tuple[np.ndarray, float]:
        """Pixel-wise median of the unit-flux stars of ``use`` and its per-pixel variance."""
        med = np.median(self.unit[use], axis=0)
        var = 0.5 * np.pi * self.var_unit[use].mean() / use.sum()
        return med, var

    def mean_parts(self, use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Inverse-variance weighted sum of the unit-flux stars of ``use``, and the weights."""
        wts = np.where(use, 1.0 / self.var_unit, 0.0)
        return np.einsum("i,ijk->jk", wts, self.unit), wts


class Reference(NamedTuple):
    """Each cutout star's unit-sum reference stack, ``(m, size, size)``, its per-pixel
    variance ``(m,)``, and the common stack that delimits the chi-square core."""

    refs: np.ndarray
    var: np.ndarray
    common: np.ndarray


@dataclass
class Check:
    """One comparison of the cutout stars with their reference stacks (``(m,)`` each)."""

    X: np.ndarray
    Y: np.ndarray
    stars: np.ndarray
    sp: np.ndarray
    pp: np.ndarray
    flux: np.ndarray
    correlation: np.ndarray
    chi2: np.ndarray


def cut_stars(
    image: np.ndarray,
    weight: np.ndarray | None,
    x: np.ndarray,
    y: np.ndarray,
    sigma_all: np.ndarray,
    big: int,
    source: str,
) -> tuple[Candidates, np.ndarray]:
    """Cut the candidates out and reject those without a usable cutout or noise level.

    Returns the candidates and the ``(m, big, big)`` cutouts; raises :class:`PSFError`
    if none is usable.
    """
    n = x.size
    stamps, idx, ix, iy, reason = star_cutouts(image, weight, x, y, big)
    bad_sig = ~(np.isfinite(sigma_all) & (sigma_all > 0))
    reason[(reason == "") & bad_sig] = REASONS["noise"]
    keep = reason[idx] == ""
    stamps, idx = stamps[keep], idx[keep]
    cand = Candidates(
        n=n, source=source, reason=reason, idx=idx, ix=ix, iy=iy, sig=sigma_all[idx],
        record=StarRecord.empty(n),
    )  # fmt: skip
    if cand.m == 0:
        raise cand.error()
    return cand, stamps


def centre_on_gaussian(
    cand: Candidates, stamps: np.ndarray, x: np.ndarray, y: np.ndarray, size: int,
    checks: StarChecks,
) -> Centred:  # fmt: skip
    """Stage 1: centre on the Gaussian cross-correlation peak, Gaussian-weighted flux.

    Rejects stars without a peak, too far from the catalogue, below ``min_snr`` or of
    non-positive flux; raises :class:`PSFError` if none remains.
    """
    idx, big = cand.idx, stamps.shape[-1]
    kx, ky, _ = rfft_frequencies(big)
    phase = np.exp(1j * (kx * (big // 2) + ky * (big // 2)))
    F0 = np.fft.rfft2(stamps)
    D = F0 * phase[None]
    x0 = x[idx] - cand.ix[idx]
    y0 = y[idx] - cand.iy[idx]
    X, Y, ok = gaussian_peak(D, checks.centroid_sigma, x0, y0, max(checks.max_shift, 1.0))
    cand.reject(~ok, REASONS["peak"])
    cand.reject(np.hypot(X - x0, Y - y0) > checks.max_shift, REASONS["shift"])
    stars = subpixel_shift(F0, X, Y, big, size)
    G = gaussian_image(size, checks.centroid_sigma)
    amp = np.einsum("ijk,jk->i", stars, G) / np.sum(G * G)
    snr = amp * np.sqrt(np.sum(G * G)) / cand.sig
    cand.record.snr[idx] = snr  # replaced by the PSF-matched S/N at each check
    cand.reject(~(snr >= checks.min_snr), REASONS["snr"])
    cand.reject(~(amp > 0), REASONS["flux"])
    if not cand.used_now().any():
        raise cand.error()
    safe_amp = np.where(amp > 0, amp, 1.0)
    unit = stars / safe_amp[:, None, None]
    var_unit = (cand.sig / safe_amp) ** 2  # per-pixel variance of each unit-flux star
    return Centred(phase=phase, F0=F0, D=D, x0=x0, y0=y0, X=X, Y=Y, unit=unit,
                   var_unit=var_unit)  # fmt: skip


def reference_stacks(cen: Centred, used: np.ndarray, median: bool) -> Reference:
    """Each star's unit-sum reference: the median stack, or the leave-one-out weighted
    stack of the other ``used`` stars."""
    m, size = cen.unit.shape[0], cen.unit.shape[-1]
    if median:
        med, var = cen.median_stack(used)
        refs = np.broadcast_to(med, (m, size, size))
        var_ref = np.full(m, var)
        common = med
    else:
        num, wts = cen.mean_parts(used)
        W = wts.sum()
        w_loo = W - wts
        alone = ~(w_loo > 0)
        w_loo = np.where(alone, W, w_loo)
        refs = (num[None] - np.where(alone, 0.0, wts)[:, None, None] * cen.unit) / w_loo[
            :, None, None
        ]
        var_ref = 1.0 / w_loo
        common = num / W
    tot = refs.sum(axis=(1, 2))
    refs = refs / tot[:, None, None]
    var_ref = var_ref / tot**2
    return Reference(refs, var_ref, common)


def compare_with_stack(cen: Centred, sig: np.ndarray, ref: Reference, checks: StarChecks
                       ) -> Check:  # fmt: skip
    """Re-centre each star on its cross-correlation with its reference; measure its flux,
    noise-debiased correlation and core chi-square against it."""
    refs, var_ref, common = ref
    size, big = refs.shape[-1], cen.D.shape[-2]
    npix = size * size
    # re-centre each star on its cross-correlation with the reference
    R = np.fft.rfft2(pad_to(refs, big)) * cen.phase[None]
    Xn, Yn, okn = newton_peak(cen.D, R, cen.X, cen.Y)
    Xn = np.where(okn, Xn, cen.X)
    Yn = np.where(okn, Yn, cen.Y)
    st = subpixel_shift(cen.F0, Xn, Yn, big, size)
    sp = np.einsum("ijk,ijk->i", st, refs)
    pp = np.einsum("ijk,ijk->i", refs, refs)
    ss = np.einsum("ijk,ijk->i", st, st)
    f = sp / pp
    tiny = 1e-300
    corr = sp / np.sqrt(
        np.maximum(ss - npix * sig**2, tiny) * np.maximum(pp - npix * var_ref, tiny)
    )
    core = common >= checks.core_level * common.max()
    resid = st - f[:, None, None] * refs
    var_pix = (
        sig[:, None, None] ** 2
        + (f**2 * var_ref)[:, None, None]
        + (checks.model_error * f[:, None, None] * refs) ** 2
    )
    chi2 = np.sum(np.where(core[None], resid**2 / var_pix, 0.0), axis=(1, 2)) / max(
        int(core.sum()) - 3, 1
    )
    return Check(X=Xn, Y=Yn, stars=st, sp=sp, pp=pp, flux=f, correlation=corr, chi2=chi2)


def refine_pass(cand: Candidates, cen: Centred, median: bool, checks: StarChecks) -> None:
    """One re-centre / reject / re-stack pass against the median (``median``) or the
    leave-one-out stack; updates ``cand`` and ``cen``, raises :class:`PSFError` if no
    star remains."""
    used = cand.used_now()
    chk = compare_with_stack(cen, cand.sig, reference_stacks(cen, used, median), checks)
    f, corr, chi2 = chk.flux, chk.correlation, chk.chi2
    # record this check for the stars still in play, then reject
    active = used
    idx, sig, rec = cand.idx, cand.sig, cand.record
    cen.X = np.where(active, chk.X, cen.X)
    cen.Y = np.where(active, chk.Y, cen.Y)
    rec.flux[idx[active]] = f[active]
    rec.correlation[idx[active]] = corr[active]
    rec.chi2[idx[active]] = chi2[active]
    rec.snr[idx[active]] = (chk.sp / (sig * np.sqrt(chk.pp)))[active]
    cand.reject(active & (np.hypot(cen.X - cen.x0, cen.Y - cen.y0) > checks.max_shift),
                REASONS["shift"])  # fmt: skip
    cand.reject(active & ~(f > 0), REASONS["flux"])
    cand.reject(active & ~(corr >= checks.min_correlation), REASONS["correlation"])
    if checks.max_chi2 is not None:
        cand.reject(active & ~(chi2 <= checks.max_chi2), REASONS["chi2"])
    if not cand.used_now().any():
        raise cand.error()
    fa = np.where(f > 0, f, 1.0)
    cen.unit = np.where(active[:, None, None], chk.stars / fa[:, None, None], cen.unit)
    cen.var_unit = np.where(active, (sig / fa) ** 2, cen.var_unit)
