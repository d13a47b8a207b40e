"""Inverse-variance weights for the shear.

The catalogue's ``weight`` (its definition: :data:`pylensfit.catalogue.COLUMNS`) is,
for each usable galaxy, the weight that minimises the variance of the estimators
``sum w <e> / sum w sens`` (and of the fixed point): ``<sens> / Var(<e>)``, the mean
sensitivity over the variance of the posterior means (shape noise and measurement noise
together), both taken over the galaxies of its **class** of round signal-to-noise
``flux / (sigma sqrt(4 pi (r^2 + s_psf^2)))`` and size relative to the PSF, without the
galaxy itself (:func:`inverse_variance_weights`, :func:`class_weights`).

Why not the galaxy's own variance. A weight that depends on the galaxy's own
ellipticity biases the shear: the measurement variance of an elongated galaxy differs
from a round one's, and under a shear the galaxies aligned with it become more
elongated, so the weighted mean of ``e`` responds to the shear differently from the
mean (CFHTLenS and KiDS calibrated this weight bias with simulations). The class is
made of quantities that a shear leaves unchanged to first order (the flux, the
area-preserving model size ``r``, the noise and the PSF), and a galaxy's own shape is
left out of its class's moments, so the weight has no first-order response to the
shear.

Why not Miller et al. (2013)'s form. lensfit's survey version (CFHTLenS,
arXiv:1210.8201) weights by ``1 / (sigma_e^2 + sigma_pop^2)``, ``sigma_e^2`` the
likelihood's variance (:func:`lensfit_weights`), the inverse variance of a
likelihood-based ellipticity. A posterior mean is shrunk towards the prior as its noise
grows, and its sensitivity with it: for a Gaussian prior and likelihood
``<sens> / Var(<e>) = 1 / sigma_pop^2`` at every S/N, so equal weights are already the
best, and the class weights stay close to equal. On exponential discs of S/N 6-80
under a Moffat PSF (4,000 galaxies, ``Config.paper``) neither weight changed the
shear's error by more than 1%.
"""

from __future__ import annotations

import numpy as np

from .prior import Prior

__all__ = [
    "class_weights",
    "inverse_variance_weights",
    "likelihood_variance",
    "lensfit_weights",
    "shape_classes",
    "population_variance",
    "round_snr",
]


def likelihood_variance(lnL: np.ndarray, egrid: np.ndarray, e_max: float = 1.0,
                        block: int = 4096) -> np.ndarray:  # fmt: skip
    """Per-component variance of each likelihood row, corrected for the bounded range.

    Parameters
    ----------
    lnL : numpy.ndarray
        ``(n, n_e)`` log-likelihoods on ``egrid``.
    egrid : numpy.ndarray
        ``(n_e, 2)`` ellipticity cell centres (equal-area cells).
    e_max : float
        Largest ``|e|`` of the grid.

    Returns
    -------
    numpy.ndarray
        ``(n,)`` ``sigma_e^2 = v e_max^2 / (e_max^2 - 2 v)`` with ``v`` half the trace of
        the likelihood's covariance (NaN for a row without a finite maximum).
    """
    lnL = np.asarray(lnL)
    egrid = np.asarray(egrid, dtype=float)
    n = lnL.shape[0]
    v = np.full(n, np.nan)
    K = np.column_stack([np.ones(len(egrid)), egrid, (egrid**2).sum(axis=1)])
    for i in range(0, n, block):
        x = np.asarray(lnL[i : i + block], dtype=float)
        mx = np.max(np.where(np.isfinite(x), x, -np.inf), axis=1, initial=-np.inf)
        ok = np.isfinite(mx)
        L = np.exp(np.where(np.isfinite(x), x - np.where(ok, mx, 0.0)[:, None], -np.inf))
        S = L[ok] @ K
        m1, m2 = S[:, 1] / S[:, 0], S[:, 2] / S[:, 0]
        v[i : i + block][ok] = 0.5 * (S[:, 3] / S[:, 0] - m1 * m1 - m2 * m2)
    e2 = float(e_max) ** 2
    return v * e2 / np.maximum(e2 - 2 * v, 1e-6 * e2)


def population_variance(prior: Prior) -> float:
    """Per-component variance ``<|e|^2> / 2`` of the ellipticity prior (on its grid)."""
    p = prior.grid_pdf()
    e2 = (prior.egrid**2).sum(axis=1)
    return float(0.5 * np.sum(p * e2) / np.sum(p))


def round_snr(flux, noise_sigma, size, psf_sigma) -> np.ndarray:
    """The matched-filter S/N of a round Gaussian of the galaxy's flux and size.

    ``flux / (sigma sqrt(4 pi (size^2 + psf_sigma^2)))`` (flux in data units, ``sigma``
    per pixel, sizes in pixels): unchanged by a shear to first order, unlike the S/N
    of the elongated model.
    """
    s2 = np.asarray(size, dtype=float) ** 2 + np.asarray(psf_sigma, dtype=float) ** 2
    return np.asarray(flux, dtype=float) / (np.asarray(noise_sigma, dtype=float)
                                            * np.sqrt(4 * np.pi * s2))  # fmt: skip


def _bin_of(v: np.ndarray, edges: np.ndarray) -> np.ndarray:
    return np.clip(np.searchsorted(edges, v, side="right") - 1, 0, edges.size - 2)


def shape_classes(snr0: np.ndarray, size_ratio: np.ndarray, *, n_snr: int = 10,
                  n_size: int = 4, min_count: int = 100) -> np.ndarray:  # fmt: skip
    """Class of each galaxy: quantiles of ``log snr0``, then of ``log size_ratio`` within
    each (fewer classes on a small sample, at least ``min_count`` galaxies in each)."""
    n = snr0.size
    ns = int(max(1, min(n_snr, n // (min_count * n_size) or n // min_count)))
    nz = int(max(1, min(n_size, n // (min_count * ns))))
    ls, lz = np.log(snr0), np.log(size_ratio)
    sb = _bin_of(ls, np.quantile(ls, np.linspace(0, 1, ns + 1)))
    cls = np.empty(n, dtype=np.int64)
    for i in range(ns):  # a few tens of classes, not one per galaxy
        si = np.flatnonzero(sb == i)
        if si.size:
            cls[si] = i * nz + _bin_of(lz[si], np.quantile(lz[si], np.linspace(0, 1, nz + 1)))
    return cls


def _leave_one_out(v: np.ndarray, cls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and mean square of ``v`` over each row's class without the row itself."""
    k = int(cls.max()) + 1
    cnt = np.bincount(cls, minlength=k).astype(float)
    s1 = np.bincount(cls, weights=v, minlength=k)
    s2 = np.bincount(cls, weights=v * v, minlength=k)
    m = np.maximum(cnt[cls] - 1, 1)
    return (s1[cls] - v) / m, (s2[cls] - v * v) / m


def class_weights(e1, e2, sens1, sens2, snr0, size_ratio, usable, **classes) -> np.ndarray:
    """Weights ``<sens> / Var(<e>)`` of each galaxy's class, leave-one-out.

    For the estimators ``sum w <e> / sum w sens`` (and the fixed point), the weight
    that minimises the variance of the shear is the response over the variance of the
    posterior means; both are estimated over the galaxy's class of round S/N and size
    (:func:`shape_classes`) without the galaxy itself, so that the weight does not
    depend on the galaxy's own shape. Posterior means are shrunk towards the prior as
    their noise grows, and their response with them: for a Gaussian prior and
    likelihood ``<sens> / Var(<e>) = 1 / sigma_pop^2`` at every S/N, the equal weights.

    Returns
    -------
    numpy.ndarray
        ``(n,)`` weights (units ``1 / e^2``), 0 where not ``usable``.
    """
    usable = np.asarray(usable, dtype=bool)
    vals = [np.asarray(v, dtype=float) for v in (e1, e2, sens1, sens2, snr0, size_ratio)]
    ok = usable & np.logical_and.reduce([np.isfinite(v) for v in vals])
    ok &= (vals[4] > 0) & (vals[5] > 0)
    w = np.zeros(usable.size)
    idx = np.flatnonzero(ok)
    if idx.size < 3:
        w[usable] = 1.0
        return w
    e1, e2, s1, s2, snr0, ratio = (v[idx] for v in vals)
    cls = shape_classes(snr0, ratio, **classes)
    var = 0.0
    for e in (e1, e2):
        m, m2 = _leave_one_out(e, cls)
        var = var + 0.5 * (m2 - m * m)
    sens = 0.5 * (_leave_one_out(s1, cls)[0] + _leave_one_out(s2, cls)[0])
    good = (var > 0) & (sens > 0)
    w[idx] = np.where(good, sens / np.where(good, var, 1.0), np.nan)
    # a usable galaxy that cannot be classed (no flux or size) gets the median weight
    fill = np.nanmedian(w[idx]) if good.any() else 1.0
    w[usable & ~(w > 0)] = fill
    return w


def lensfit_weights(variance, snr0, size_ratio, sigma_pop2: float, usable,
                    **classes) -> np.ndarray:  # fmt: skip
    """Miller et al. (2013)'s form ``1 / (sigma_pop^2 + sigma_e^2)``, ``sigma_e^2`` the
    mean measurement variance (:func:`likelihood_variance`) of the galaxy's class
    (:func:`shape_classes`) without the galaxy itself; 0 where not ``usable``.

    The weight for likelihood-based ellipticities, not the catalogue's ``weight``. For
    posterior means with their sensitivities it gains little over equal weights (their
    noise is shrunk by the prior): :func:`class_weights` is the weight for those.

    Returns
    -------
    numpy.ndarray
        ``(n,)`` weights (units ``1 / e^2``), 0 where not ``usable``.
    """
    usable = np.asarray(usable, dtype=bool)
    variance, snr0, size_ratio = (np.asarray(v, dtype=float) for v in
                                  (variance, snr0, size_ratio))  # fmt: skip
    ok = usable & np.isfinite(variance) & (snr0 > 0) & (size_ratio > 0)
    w = np.zeros(usable.size)
    idx = np.flatnonzero(ok)
    if idx.size < 2:
        w[idx] = 1.0 / (sigma_pop2 + variance[idx])
        return w
    cls = shape_classes(snr0[idx], size_ratio[idx], **classes)
    w[idx] = 1.0 / (sigma_pop2 + _leave_one_out(variance[idx], cls)[0])
    return w


def inverse_variance_weights(e1, e2, sens1, sens2, flux, noise_sigma, size, psf_sigma,
                             usable) -> np.ndarray:  # fmt: skip
    """The catalogue's ``weight``: :func:`class_weights` of the rows ``usable``, in classes
    of round S/N (:func:`round_snr`) and size over the PSF's.

    Parameters
    ----------
    e1, e2, sens1, sens2 : array_like
        Posterior means and sensitivities per row.
    flux, noise_sigma, size, psf_sigma : array_like
        Per row: model flux (data units), noise per pixel, model size and PSF size
        (pixels).
    usable : numpy.ndarray
        Bool, the galaxies usable for shear.

    Returns
    -------
    numpy.ndarray
        ``(n,)`` weights ``<sens> / Var(<e>)`` of each row's class (units ``1 / e^2``), 0
        where not ``usable``; 1 for every usable row where fewer than 3 can be classed,
        and the median weight for a usable row without a weight of its own (no finite
        shape, no positive flux or size, or a class without a positive variance and
        sensitivity).
    """
    usable = np.asarray(usable, dtype=bool)
    size = np.asarray(size, dtype=float)
    psf_sigma = np.asarray(psf_sigma, dtype=float) * np.ones(usable.size)
    psf_sigma = np.where(np.isfinite(psf_sigma) & (psf_sigma > 0), psf_sigma, 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        snr0 = round_snr(flux, noise_sigma, size, psf_sigma)
        ratio = size / psf_sigma
    return class_weights(e1, e2, sens1, sens2, snr0, ratio, usable)
