"""Every PSF pixel a polynomial in the position: :class:`PolynomialPSF`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from astropy.table import Table
from scipy.stats import f as f_dist

from .._util import per_object
from ..psf import PSFResult, StarChecks, psf_diagnostics
from ..psf.fourier import pad_to
from .base import PSFModel, sha1
from .basis import CHUNK, design, n_terms, phase, recentre
from .heldout import (
    TABLE_COLUMNS,
    fit_diagnostics,
    heldout_summary,
    holdout_mask,
    moment_noise,
    star_table,
)
from .polyfit import (
    Fit,
    FitOptions,
    Stars,
    check_fit_inputs,
    first_stage,
    fit_with_order,
    iterate,
    no_star_error,
)
from .polyio import read_polynomial, write_polynomial


class PolynomialPSF(PSFModel):
    """Every PSF pixel a polynomial in the position (lensfit's survey PSF, PSFEx's model).

    ``P(x, y) = sum_{i + j <= order} c_ij u^i v^j`` with ``u = (x - x0) / sx``,
    ``v = (y - y0) / sy``, ``x0, sx`` the centre and half-width of ``bounds`` (so
    ``u, v`` span ``[-1, 1]`` over them); drawn images are then re-centred by the
    convention (an exact Fourier shift, usually of a few hundredths of a pixel) and
    scaled to unit sum. Positions outside ``bounds`` extrapolate the polynomial.

    Usually made by :meth:`fit` or read by :func:`read_psf_model`.

    Parameters
    ----------
    coefs : numpy.ndarray
        ``(n_terms(order), size, size)`` coefficient images, in the order of the
        monomials ``u^i v^j`` by total degree ``d = i + j`` then by ``j``:
        ``1, u, v, u^2, uv, v^2, ...``.
    order : int
        Total degree of the polynomial.
    bounds : tuple of float
        ``(xmin, xmax, ymin, ymax)`` in 0-based image pixels.
    cov : numpy.ndarray, optional
        ``(p, p)`` covariance of the coefficients of a pixel per unit pixel variance of
        a unit-flux star (the inverse normal matrix of the fit; gives
        :attr:`PSFResult.pixel_noise` of :attr:`centre`).
    stars : astropy.table.Table, optional
        Per-star table of the fit (see :meth:`fit`).
    diagnostics : dict, optional
        Summary of the fit (see :meth:`fit`).
    centroid_sigma : float
        Width in pixels of the Gaussian of the centre convention.
    margin : int
        Padding in pixels of the Fourier re-centring.
    source : str
        Label of where the stars came from.

    Attributes
    ----------
    stars : astropy.table.Table or None
        For a model from :meth:`fit`, per candidate star: ``x_cat, y_cat``; the measured
        centre ``x, y`` in 0-based pixels, the convention of the drawn model; ``flux``,
        ``snr``, ``correlation``, ``chi2`` of the last check; ``used``; ``reason``;
        ``heldout``; adaptive moments ``e1_star, e2_star, sigma_star`` of the star and
        ``e1_model, e2_model, sigma_model`` of the model at its position, the held-out
        fit's for held-out stars, the final one's for the others.
    diagnostics : dict
        For a model from :meth:`fit`: ``order`` (used), ``order_requested``,
        ``n_terms``, ``n_stars`` (candidates), ``n_used``, ``n_rejected``, ``rejected``
        (count per reason), ``chi2_median`` (used stars), ``options``; and the held-out
        check, over the held-out stars that the final fit uses (so that contaminants of
        the list do not count; for a model that rejects many good stars this hides its
        worst misfits): ``n_heldout``, ``heldout_n``, ``heldout_mean_de1/2`` and
        ``heldout_rms_de1/2`` (star minus model ellipticity), ``heldout_noise_de`` (the
        rms expected from the stars' noise alone, ``k_e / snr`` per star with ``k_e``
        from a Monte Carlo of the moments of the model plus noise;
        ``moment_noise_k_e``), ``heldout_excess_de1/2`` (``sqrt(rms^2 - noise^2)``, 0
        if negative: the model's error), ``heldout_chi2_de`` (mean squared residual in
        units of the expected noise, about 1 for a model as good as the noise can
        tell), ``heldout_pvalue_de`` (the chance of a mean at least as large from the
        noise alone: the chi-square distribution of ``2 heldout_n`` degrees of
        freedom, the two components of each star), and the same for the relative size
        ``sigma_star / sigma_model - 1`` (``heldout_*_dsigma``). The noise of the
        held-out model itself is not counted.
    """

    def __init__(self, coefs, order: int, bounds, *, cov=None, stars: Table | None = None,
                 diagnostics: dict | None = None, centroid_sigma: float = 2.0,
                 margin: int = 4, source: str = ""):  # fmt: skip
        coefs = np.array(coefs, dtype=np.float64)
        order = int(order)
        if coefs.ndim != 3 or coefs.shape[0] != n_terms(order) or coefs.shape[1] != coefs.shape[2]:
            raise ValueError(f"coefs must have shape ({n_terms(order)}, size, size) for order "
                             f"{order}, got {coefs.shape}")  # fmt: skip
        b = np.asarray(bounds, dtype=float)
        if b.shape != (4,) or not np.all(np.isfinite(b)):
            raise ValueError(f"bounds must be (xmin, xmax, ymin, ymax), got {bounds!r}")
        self.coefs, self.order, self.bounds = coefs, order, tuple(float(t) for t in b)
        self.size = int(coefs.shape[-1])
        self.cov = None if cov is None else np.array(cov, dtype=np.float64)
        self.stars = stars
        self.diagnostics = dict(diagnostics or {})
        self.centroid_sigma, self.margin, self.source = float(centroid_sigma), int(margin), source
        self._centre: PSFResult | None = None
        self._ft: np.ndarray | None = None

    def __repr__(self) -> str:
        return (f"PolynomialPSF(order={self.order}, size={self.size}, bounds={self.bounds}, "
                f"n_used={self.diagnostics.get('n_used')})")  # fmt: skip

    # -- geometry -------------------------------------------------------------------
    @staticmethod
    def _scale(bounds) -> tuple[float, float, float, float]:
        xmin, xmax, ymin, ymax = bounds
        sx = 0.5 * (xmax - xmin) if xmax > xmin else 1.0
        sy = 0.5 * (ymax - ymin) if ymax > ymin else 1.0
        return 0.5 * (xmin + xmax), sx, 0.5 * (ymin + ymax), sy

    def uv(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Normalised coordinates ``(u, v)`` of 0-based image positions."""
        x0, sx, y0, sy = self._scale(self.bounds)
        return (np.asarray(x, dtype=float) - x0) / sx, (np.asarray(y, dtype=float) - y0) / sy

    # -- drawing ----------------------------------------------------------------------
    def _coef_ft(self) -> np.ndarray:
        """``(p, big * (big//2 + 1))`` phase-referenced transforms of the padded planes."""
        if self._ft is None:
            big = self.size + 2 * self.margin + 1
            F = np.fft.rfft2(pad_to(self.coefs, big)) * phase(big)[None]
            self._ft = F.reshape(len(F), -1)
        return self._ft

    def _draw_centred(self, x, y):
        """Drawn images, the re-centring shifts and the sums before normalisation.

        The polynomial is evaluated on the Fourier transforms of the (padded)
        coefficient planes, so a position costs one inverse FFT and a few Newton steps.
        """
        big = self.size + 2 * self.margin + 1
        Fc = self._coef_ft()
        parts = []
        for i in range(0, x.size, CHUNK):
            u, v = self.uv(x[i : i + CHUNK], y[i : i + CHUNK])
            D = (design(u, v, self.order) @ Fc).reshape(-1, big, big // 2 + 1)
            parts.append(recentre(D, self.size, self.centroid_sigma))
        if not parts:
            z = np.zeros(0)
            return np.zeros((0, self.size, self.size)), z, z, z
        return tuple(np.concatenate([p[k] for p in parts]) for k in range(4))

    def _draw(self, x, y):
        return self._draw_centred(x, y)[0]

    # -- summaries ------------------------------------------------------------------------
    @property
    def centre(self) -> PSFResult:
        """The model at the centre of :attr:`bounds`, with the fit's stars."""
        if self._centre is None:
            self._centre = self._centre_result()
        return self._centre

    def _centre_result(self) -> PSFResult:
        x0, _, y0, _ = self._scale(self.bounds)
        img, _, _, tot = self._draw_centred(np.array([x0]), np.array([y0]))
        noise = np.nan
        if self.cov is not None and self.cov.shape == (self.coefs.shape[0],) * 2:
            a = design(np.zeros(1), np.zeros(1), self.order)[0]
            noise = float(np.sqrt(max(a @ self.cov @ a, 0.0)) / tot[0])
        t = self.stars
        if t is None:
            t = Table({c: np.zeros(0) for c in TABLE_COLUMNS})
            t["used"] = np.zeros(0, bool)
            t["reason"] = np.zeros(0, dtype=str)
        cols = {
            c: np.asarray(t[c], dtype=float)
            for c in ("x_cat", "y_cat", "x", "y", "flux", "snr", "correlation", "chi2")
        }
        return PSFResult(image=img[0], used=np.asarray(t["used"], dtype=bool),
                         reason=np.array([str(r).strip() for r in t["reason"]], dtype=str),
                         pixel_noise=noise, source=self.source,
                         meta={"model": "polynomial", "order": self.order,
                               "position": (x0, y0)},
                         **cols, **psf_diagnostics(img[0]))  # fmt: skip

    @property
    def digest(self) -> str:
        return sha1("PolynomialPSF", self.coefs, self.order, np.array(self.bounds),
                    self.centroid_sigma, self.margin)  # fmt: skip

    # -- fitting --------------------------------------------------------------------------
    @classmethod
    def fit(cls, image: np.ndarray, x, y, *, noise_sigma, weight: np.ndarray | None = None,
            order: int = 2, size: int = 32, bounds=None, holdout: float = 0.2,
            clip: float | None = 2.0, n_iter: int = 3, seed: int = 0,
            min_stars_per_coefficient: float = 5.0, min_correlation: float = 0.9,
            model_error: float = 0.01, core_level: float = 0.01, max_shift: float = 2.0,
            min_snr: float = 10.0, centroid_sigma: float = 2.0, margin: int = 4,
            source: str = "image") -> PolynomialPSF:  # fmt: skip
        """Fit the per-pixel polynomial to star images, with outlier rejection and a
        held-out check (the steps are those of :mod:`pylensfit.psfmodel`).

        Parameters
        ----------
        image : numpy.ndarray
            2-D background-subtracted image indexed ``[y, x]``.
        x, y : array_like
            Catalogue positions of candidate stars, 0-based pixels.
        noise_sigma : float or array_like
            Per-pixel noise standard deviation, scalar or one per star (image units).
        weight : numpy.ndarray, optional
            Weight map; a star whose cutout holds a pixel of weight ``<= 0`` is rejected.
        order : int
            Total degree of the polynomial (2, quadratic, by default).
        size : int
            Side of the PSF images in pixels.
        bounds : tuple of float, optional
            ``(xmin, xmax, ymin, ymax)`` mapped onto ``u, v in [-1, 1]``; by default the
            image's extent ``(0, nx - 1, 0, ny - 1)``.
        holdout : float
            Fraction of the stars held out for the diagnostics (0 for none).
        clip : float or None
            Largest reduced chi-square of a star against the model (``max_chi2`` of
            :class:`~pylensfit.psf.StarChecks`); ``None`` disables the test.
        n_iter : int
            Number of fit / check passes.
        seed : int
            Seed of the held-out draw and of the Monte Carlo of the moments' noise.
        min_stars_per_coefficient : float
            Fewest usable stars per polynomial coefficient before the order is lowered.
        min_correlation, model_error, core_level, max_shift, min_snr, centroid_sigma, margin
            As in :func:`pylensfit.psf.stack_psf` (:class:`~pylensfit.psf.StarChecks`).
        source : str
            Label of the image, used in messages and stored.

        Returns
        -------
        PolynomialPSF
            The model, with the fit's :attr:`stars` and :attr:`diagnostics`.

        Raises
        ------
        PSFError
            If no usable star remains.
        ValueError
            For inconsistent arguments.
        """
        image, x, y, weight = check_fit_inputs(image, x, y, weight, size, order, holdout, n_iter)
        checks = StarChecks(min_correlation, clip, model_error, core_level, max_shift, min_snr,
                            centroid_sigma, int(margin))  # fmt: skip
        opts = FitOptions(checks, int(n_iter), min_stars_per_coefficient)
        S = first_stage(image, weight, x, y, per_object(noise_sigma, x.size, "noise_sigma"),
                        size, checks)  # fmt: skip
        if S.m == 0:
            raise no_star_error(S.reason, source)
        if bounds is None:
            bounds = (0.0, image.shape[1] - 1.0, 0.0, image.shape[0] - 1.0)
        x0, sx, y0, sy = cls._scale(bounds)
        uv = ((S.ix + S.X - x0) / sx, (S.iy + S.Y - y0) / sy)
        fit = fit_with_order(S, np.ones(S.m, bool), int(order), uv, opts, source)
        if not fit.used.any():
            raise no_star_error(S.reason, source, S.idx, fit.why)
        kw = {"centroid_sigma": centroid_sigma, "margin": margin, "source": source}
        model = cls(fit.coefs, fit.order, bounds, cov=fit.cov, **kw)
        rng = np.random.default_rng(seed)
        hold = holdout_mask(fit.used, holdout, n_terms(fit.order), rng)
        held = cls._heldout_model(S, fit, hold, uv, opts, bounds, kw)
        model.stars = star_table(S, x, y, fit, model, held, hold)
        k_e, k_s = moment_noise(model._draw(np.array([x0]), np.array([y0]))[0], rng)
        model.diagnostics = fit_diagnostics(model.stars, fit, int(order), opts, source)
        model.diagnostics.update(heldout_summary(model.stars, k_e, k_s))
        return model

    @classmethod
    def _heldout_model(cls, S: Stars, fit: Fit, hold: np.ndarray, uv, opts: FitOptions,
                       bounds, kw: dict) -> PolynomialPSF | None:  # fmt: skip
        """The model of ``fit``'s order fitted without the held-out stars ``hold``, or
        None (and ``hold`` cleared) if there are none or none of the rest survives."""
        model_h = None
        if hold.any():
            fit_h = iterate(S, fit.used & ~hold, fit.order, uv, opts)
            if fit_h.used.any():
                model_h = cls(fit_h.coefs, fit.order, bounds, cov=fit_h.cov, **kw)
        if model_h is None:
            hold[:] = False
        return model_h

    def variation(self) -> dict:
        """Whether the stars show the PSF varying over the field, beyond their noise.

        The used stars' measured adaptive-moment ellipticities ``e1_star``, ``e2_star``
        and ``ln sigma_star`` are each fitted, weighted by ``snr^2`` (their moments'
        noise goes as ``1 / snr``), by a constant and by the model's polynomial in
        ``(u, v)``. Each quantity's chi-square improvement, in units of the polynomial
        fit's residual variance (so that the noise's scale need not be known), is
        summed: an F statistic on ``q = 3 (n_terms - 1)`` and ``3 (n - n_terms)``
        degrees of freedom, ``n`` the stars.

        Returns
        -------
        dict
            ``vary_pvalue`` (the probability of an F at least this large for a PSF
            constant over the field: small when it varies; 1 for an order-0 model or
            too few stars to tell), ``vary_rms_de`` (rms over the stars of ``|e|``'s
            fitted variation about its mean, dimensionless), ``vary_rms_dsigma`` (the
            same for the size, relative) and ``vary_n`` (the stars).
        """
        out = {"vary_pvalue": 1.0, "vary_rms_de": 0.0, "vary_rms_dsigma": 0.0, "vary_n": 0}
        t, p = self.stars, n_terms(self.order)
        if t is None or self.order == 0:
            return out
        q = [np.asarray(t[c], dtype=float) for c in ("e1_star", "e2_star", "sigma_star")]
        snr = np.asarray(t["snr"], dtype=float)
        sel = (np.asarray(t["used"], bool) & np.isfinite(snr) & (snr > 0) & (q[2] > 0)
               & np.isfinite(q[0]) & np.isfinite(q[1]))  # fmt: skip
        n = int(sel.sum())
        out["vary_n"] = n
        if n < p + 5:
            return out
        u, v = self.uv(np.asarray(t["x"], float)[sel], np.asarray(t["y"], float)[sel])
        A = design(u, v, self.order)
        sw = snr[sel]
        stat, fitted = 0.0, []
        for y in (q[0][sel], q[1][sel], np.log(q[2][sel])):
            coef = np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)[0]
            model = A @ coef
            chi_poly = float(np.sum((sw * (y - model)) ** 2))
            mean = float(np.sum(sw**2 * y) / np.sum(sw**2))
            chi_const = float(np.sum((sw * (y - mean)) ** 2))
            stat += (chi_const - chi_poly) / max(chi_poly / (n - p), 1e-300)
            fitted.append(model - model.mean())
        dof = 3 * (p - 1)
        out["vary_pvalue"] = float(f_dist.sf(stat / dof, dof, 3 * (n - p)))
        out["vary_rms_de"] = float(np.sqrt(np.mean(fitted[0] ** 2 + fitted[1] ** 2)))
        out["vary_rms_dsigma"] = float(np.sqrt(np.mean(fitted[2] ** 2)))
        return out

    # -- files ----------------------------------------------------------------------------
    def write(self, path: str | Path, overwrite: bool = False) -> None:
        """Write as FITS, atomically.

        The primary HDU holds the ``(p, size, size)`` coefficient cube with header
        keywords ``PSFMODEL = 'POLYNOMIAL'``, ``ORDER``, ``XMIN``, ``XMAX``, ``YMIN``,
        ``YMAX`` (the bounds, 0-based pixels), ``CSIGMA``, ``MARGIN``, ``SOURCE``,
        ``N_USED``, ``N_REJ`` and ``DIAGS`` (:attr:`diagnostics` as JSON); the ``COVAR``
        image HDU the coefficients' covariance and the ``STARS`` table the stars.
        """
        write_polynomial(self, path, overwrite)

    @classmethod
    def read(cls, path: str | Path) -> PolynomialPSF:
        """Read a file written by :meth:`write`."""
        f = read_polynomial(path)
        return cls(f.coefs, f.order, f.bounds, cov=f.cov, stars=f.stars,
                   diagnostics=f.diagnostics, centroid_sigma=f.centroid_sigma,
                   margin=f.margin, source=f.source)  # fmt: skip
