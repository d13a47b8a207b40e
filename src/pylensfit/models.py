"""Galaxy models in Fourier space and the model bank of the (e1, e2, r) grid.

Miller et al. (2007, arXiv:0708.2340), section 3, and Kitching et al. (2008,
arXiv:0802.1528), section 2.2 (docs: method, conventions, eq-shear-matrix and
eq-fourier-model).

Conventions
-----------
A model of ellipticity ``e`` and size ``r`` is a circular profile of scale ``r``
transformed by the area-preserving shear matrix of reduced shear ``g = e``::

    S(e) = [[1 + e1, e2], [e2, 1 - e1]] / sqrt(1 - |e|^2)      (det S = 1)

which is GalSim's ``Shear`` convention (``e1 > 0`` elongates along x). Its Fourier
transform is ``G(k) = F(|S(e)^T k| r)`` with ``F`` the transform of the circular
profile at unit scale, normalised to ``F(0) = 1`` (unit total flux):

* exponential disc, ``r`` = scale length: ``F(q) = (1 + q^2)^(-3/2)`` (analytic);
* de Vaucouleurs bulge, ``r`` = half-light radius: tabulated once from GalSim's
  Hankel transform (``galsim.DeVaucouleurs.kValue``), truncated at
  :data:`DEVAUC_TRUNCATION` = 8 half-light radii (the untruncated profile has 5.7 %
  of its flux beyond that; the truncation keeps the wings of large models from
  wrapping round a 32-pixel stamp), then interpolated with a cubic spline in
  ``ln(1 + q)`` for ``q <= 2000``;
* bulge + disc: ``F = f_b F_dev(q s) + (1 - f_b) F_exp(q)``, ``r`` = disc scale length,
  bulge half-light radius ``s r`` (``s`` = ``bulge_size_ratio``), both components with
  the same ellipticity.

The models are evaluated on the ``rfft2`` frequencies of an ``N x N`` stamp,
``k = 2 pi (f_x, f_y)`` in radians per pixel. So sampled, a model is periodic in real
space: a model wider than the stamp wraps its far wings round to the opposite side,
while the stamp of a galaxy cut from the sky holds only the galaxy. With
``Config.truncate_models`` (the default) the bank subtracts the transforms of those
wrapped wings (:func:`wrap_correction`), so that every model is the profile cut at the
stamp's edge, as the data are.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import fft as sfft
from scipy.optimize import brentq
from scipy.special import gamma, gammainc, gammaincinv

from ._kernels_nb import wrapped_wings
from ._util import (
    disk_cached,
    rfft_frequencies,  # re-exported: part of this module's API
)
from .bankruns import DISC_HLR, Run, bank_runs  # re-exported: part of this module's API
from .config import Config
from .grid import ellipticity_grid
from .psf import psf_transform

__all__ = [
    "DEVAUC_TRUNCATION",
    "MODEL_TYPES",
    "ModelBank",
    "fourier_profile",
    "frequency_rows",
    "half_light_radius",
    "model_bank",
    "radius_grid",
    "radius_weights",
    "render_models",
    "rfft_frequencies",
    "sheared_k",
    "wing_transforms",
    "wrap_correction",
]

#: Truncation radius of the de Vaucouleurs profile, in half-light radii.
DEVAUC_TRUNCATION = 8.0
#: Model families understood by :func:`fourier_profile`.
MODEL_TYPES = ("exponential", "devaucouleurs", "bulge+disc")

_Q_MAX_TABLE = 2000.0
#: copies of the stamp summed in each direction by :func:`wrap_correction`: models up to
#: about 7 stamps across (far beyond any galaxy that a stamp can measure) are exact
_WRAP_COPIES = 3


def _sersic_trunc(n: float) -> float:
    """Truncation radius (half-light radii) of a Sersic profile of index ``n`` of the model
    family: :data:`DEVAUC_TRUNCATION` above ``n = 2``, none (0) at or below, as the
    simulations draw them."""
    return DEVAUC_TRUNCATION if n > 2 else 0.0


@lru_cache(maxsize=16)
def _sersic_spline(n: float, trunc: float):
    """Spline of the transform of a Sersic profile of unit half-light radius (GalSim's
    Hankel transform, ``trunc`` half-light radii, 0: untruncated), uniform in ln(1 + q)."""
    import galsim  # galsim: heavy import, only to tabulate a profile's transform
    from scipy.interpolate import CubicSpline  # scipy.interpolate: start-up cost, with galsim

    if n == 4.0:
        prof = galsim.DeVaucouleurs(half_light_radius=1.0, trunc=trunc)
    else:
        prof = galsim.Sersic(n=n, half_light_radius=1.0, trunc=trunc)
    x = np.linspace(0.0, np.log1p(_Q_MAX_TABLE), 3001)
    q = np.expm1(x)
    f = np.array([prof.kValue(galsim.PositionD(float(qi), 0.0)).real for qi in q])
    return CubicSpline(x, f / f[0])


def _devauc_spline(trunc: float):
    """Spline of the de Vaucouleurs transform, tabulated uniformly in ln(1 + q)."""
    return _sersic_spline(4.0, trunc)


def _devauc_profile(q: np.ndarray) -> np.ndarray:
    return _devauc_spline(DEVAUC_TRUNCATION)(np.log1p(np.minimum(q, _Q_MAX_TABLE)))


def _component_transform(q: np.ndarray, n: float, h: float) -> np.ndarray:
    """Transform at ``q = |k| r`` of a unit-flux Sersic component of index ``n`` and
    half-light radius ``h r`` (``n = 1``: the exponential, analytic)."""
    if n == 1.0:
        x = q * (h / DISC_HLR)
        return (1.0 + x * x) ** -1.5
    return _sersic_spline(float(n), _sersic_trunc(n))(np.log1p(np.minimum(q * h, _Q_MAX_TABLE)))


def fourier_profile(
    q: np.ndarray,
    model: str = "devaucouleurs",
    *,
    bulge_fraction: float = 0.5,
    bulge_size_ratio: float = 0.6,
) -> np.ndarray:
    """Fourier transform ``F(q)`` of a circular profile at unit scale, ``F(0) = 1``.

    Parameters
    ----------
    q : array_like
        Dimensionless wavenumber ``|k| r`` (``k`` in radians per pixel, ``r`` in pixels).
    model : {"exponential", "devaucouleurs", "bulge+disc"}
        Profile family; see the module docstring for the meaning of the scale.
    bulge_fraction : float
        Bulge-to-total flux ratio of the ``"bulge+disc"`` model.
    bulge_size_ratio : float
        Bulge half-light radius over disc scale length for ``"bulge+disc"``.

    Returns
    -------
    numpy.ndarray
        ``F(q)``, float64, same shape as ``q``.
    """
    q = np.abs(np.asarray(q, dtype=float))
    if model == "exponential":
        return (1.0 + q * q) ** -1.5
    if model == "devaucouleurs":
        return _devauc_profile(q)
    if model == "bulge+disc":
        if not 0.0 <= bulge_fraction <= 1.0:
            raise ValueError(f"bulge_fraction must be in [0, 1], got {bulge_fraction}")
        if bulge_size_ratio <= 0:
            raise ValueError(f"bulge_size_ratio must be > 0, got {bulge_size_ratio}")
        return bulge_fraction * _devauc_profile(q * bulge_size_ratio) + (
            1.0 - bulge_fraction
        ) * (1.0 + q * q) ** -1.5
    raise ValueError(f"unknown model {model!r}; choose one of {MODEL_TYPES}")


def in_disc(kx, ky, k_max: float) -> np.ndarray:
    """``|k| <= k_max`` (with a relative tolerance of 1e-9 for the lattice points on it)."""
    return kx * kx + ky * ky <= k_max * k_max * (1 + 1e-9)


def frequency_rows(n: int, k_max: float = 0.0) -> np.ndarray | None:
    """The flattened ``rfft2`` frequencies of an ``n x n`` stamp with ``|k| <= k_max``.

    ``k_max = 0`` (or at least the corner's ``pi sqrt 2``): ``None``, all of them. The
    stamp tiers of :func:`pylensfit.likelihood.fit_stamps` fit a large galaxy on a stamp
    ``j`` times the base one with ``k_max = pi / j``: as many terms as the base stamp,
    where a galaxy that large has no signal left.
    """
    if not k_max or k_max >= np.pi * np.sqrt(2.0):
        return None
    kx, ky, _ = rfft_frequencies(n)
    return np.flatnonzero(in_disc(kx, ky, k_max).ravel())


def sheared_k(kx: np.ndarray, ky: np.ndarray, e1, e2) -> np.ndarray:
    """``|S(e)^T k|`` for the area-preserving shear ``S(e)`` (broadcasting)."""
    e1 = np.asarray(e1, dtype=float)
    e2 = np.asarray(e2, dtype=float)
    norm = 1.0 / np.sqrt(1.0 - e1 * e1 - e2 * e2)
    ux = ((1.0 + e1) * kx + e2 * ky) * norm
    uy = (e2 * kx + (1.0 - e1) * ky) * norm
    return np.hypot(ux, uy)


def _bulge_disc_transform(q: np.ndarray, bf: np.ndarray, bulge_size_ratio: float) -> np.ndarray:
    """``bf F_bulge(q bulge_size_ratio) + (1 - bf) F_disc(q)`` for ``(m, ...)``
    dimensionless wavenumbers ``q`` and one bulge fraction ``bf`` per model, each
    component evaluated only for the models that hold it: a pure disc's bulge term
    (``0 * F``) and a pure bulge's disc term are exactly 0, so the numbers are those of
    the sum over every model."""
    F = np.zeros_like(q)
    shape = (-1,) + (1,) * (q.ndim - 1)
    bulge, disc = bf != 0.0, bf != 1.0
    if bulge.any():
        F[bulge] = bf[bulge].reshape(shape) * fourier_profile(q[bulge] * bulge_size_ratio,
                                                              "devaucouleurs")  # fmt: skip
    if disc.any():
        F[disc] += (1.0 - bf[disc]).reshape(shape) * fourier_profile(q[disc], "exponential")
    return F


def _sheared_q(qx: np.ndarray, qy: np.ndarray, e1: np.ndarray, e2: np.ndarray,
               r: np.ndarray) -> np.ndarray:  # fmt: skip
    """``|S(e)^T q| r`` (:func:`sheared_k` times ``r``) for ``(m,)`` models, as the quadratic
    form of ``q``: ``(|q|^2 (1 + |e|^2) + 2 e1 (qx^2 - qy^2) + 4 e2 qx qy) / (1 - |e|^2)``,
    in fewer passes over the ``(m, ...)`` arrays."""
    a1, a2 = e1[:, None, None], e2[:, None, None]
    esq = a1 * a1 + a2 * a2
    r2 = (r * r)[:, None, None] / (1.0 - esq)
    q = qx * qx * ((1.0 + esq + 2.0 * a1) * r2)
    q += qx * qy * ((4.0 * a2) * r2)
    q += qy * qy * ((1.0 + esq - 2.0 * a1) * r2)
    return np.sqrt(q, out=q)


def _shift_phase(kx: np.ndarray, ky: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``exp(-i (kx x + ky y))`` ``(m, ny, nx)`` for ``(m,)`` centres on the separable grid of
    ``kx`` ``(nx,)`` and ``ky`` ``(ny,)``: one exponential per row and per column."""
    return (np.exp(-1j * np.multiply.outer(y, ky))[:, :, None]
            * np.exp(-1j * np.multiply.outer(x, kx))[:, None, :])  # fmt: skip


def render_models(
    n: int,
    psf: np.ndarray,
    x,
    y,
    e1,
    e2,
    r,
    flux,
    *,
    model: str = "exponential",
    bulge_fraction=0.5,
    bulge_size_ratio: float = 0.6,
    jacobian=None,
) -> np.ndarray:
    """Real-space images of PSF-convolved models on an ``n x n`` canvas.

    Each model is the profile of :func:`fourier_profile` (size ``r``, ellipticity ``e``,
    total flux ``flux``) convolved with ``psf``, centred at canvas pixel ``(x, y)``
    (0-based, pixel centres on integers), evaluated on the ``rfft2`` frequencies and
    transformed back: periodic on the canvas, so the canvas must be wide enough for the
    wings that matter. ``r = 0`` is a point source (the PSF itself).

    Parameters
    ----------
    n : int
        Canvas side in pixels.
    psf : numpy.ndarray
        2-D PSF image including the pixel response, centred on ``[s//2, s//2]``, or
        ``(m, s, s)``: one per model.
    x, y, e1, e2, r, flux : array_like
        ``(m,)`` centre (pixels), ellipticity, size (pixels; with ``jacobian``, arcsec)
        and flux of each model.
    model : {"exponential", "devaucouleurs", "bulge+disc"}
        Profile family.
    bulge_fraction : float or array_like
        Bulge fraction of each ``"bulge+disc"`` model.
    bulge_size_ratio : float
        Bulge half-light radius over disc scale length.
    jacobian : array_like, optional
        ``(2, 2)`` or ``(m, 2, 2)`` local WCS Jacobian ``d(x, y)/d(W, N)``, pixels per
        arcsec: the models are then sky-frame profiles (``e`` in the sky frame ``(W,
        N)``, ``r`` in arcsec) seen through it, the transform of ``m(J^-1 x) / |det J|``
        at ``k`` being ``M(J^T k)`` (:func:`pylensfit.joint.sky_frequencies`; the flux is
        kept). Default: the pixel frame.

    Returns
    -------
    numpy.ndarray
        ``(m, n, n)`` float64 images indexed ``[k, y, x]``.
    """
    x, y, e1, e2, r, flux = (np.atleast_1d(np.asarray(v, dtype=float)) for v in
                             (x, y, e1, e2, r, flux))  # fmt: skip
    m = x.size
    bf = np.broadcast_to(np.asarray(bulge_fraction, dtype=float), (m,))
    kx, ky, _ = rfft_frequencies(n)
    psf = np.asarray(psf, dtype=float)
    P = (psf_transform(psf, n)[None] if psf.ndim == 2
         else np.stack([psf_transform(p, n) for p in psf]))  # fmt: skip
    if jacobian is None:
        qx, qy = kx[None], ky[None]
    else:
        J = np.broadcast_to(np.asarray(jacobian, dtype=float), (m, 2, 2))[:, :, :, None, None]
        qx, qy = J[:, 0, 0] * kx + J[:, 1, 0] * ky, J[:, 0, 1] * kx + J[:, 1, 1] * ky
    q = _sheared_q(qx, qy, e1, e2, r)
    if model == "bulge+disc":
        F = _bulge_disc_transform(q, bf, bulge_size_ratio)
    else:
        F = fourier_profile(q, model)
    phase = _shift_phase(kx[0], ky[:, 0], x, y)
    phase *= P
    phase *= (flux[:, None, None] * F)
    return np.fft.irfft2(phase, s=(n, n))


@dataclass(frozen=True)
class ModelBank:
    """The PSF-independent model transforms ``G`` of every grid model on one stamp size.

    Attributes
    ----------
    G : numpy.ndarray
        ``(n_freq, n_models)`` real transforms on the ``rfft2`` frequencies (flattened
        row-major from ``(n, n // 2 + 1)``; only those of ``rows`` if given). Column
        ``ie * n_r + ir`` is ellipticity ``egrid[ie]``, radius ``radii[ir]`` and bulge
        fraction ``bulge[ir]``; the last column is the point source (r = 0).
    egrid : numpy.ndarray
        ``(n_e, 2)`` ellipticity cell centres.
    radii : numpy.ndarray
        ``(n_r,)`` model size in pixels of each column within an e cell, all > 0: the
        radius grid, repeated once per bulge fraction when those are marginalised
        (``n_sub`` consecutive sizes per fraction).
    n : int
        Stamp side in pixels.
    model : str
        Model family.
    bulge : numpy.ndarray or None
        Bulge fraction of each column within an e cell (``None``: one fixed fraction).
    bulge_size : numpy.ndarray or None
        Bulge half-light radius over disc scale length of each column within an e cell,
        where the bank has two bulge sizes (``None``: one, the configuration's).
    n_sub : int
        Sizes per bulge fraction (0: all of ``radii``).
    r_weights : numpy.ndarray or None
        Quadrature weight of each size of one run (:func:`radius_weights`).
    star_weight : float
        Quadrature weight of the point source.
    run_weights : numpy.ndarray or None
        Weight of each bulge fraction's sum over sizes: its half-light radius per unit
        ``r`` over that of the first fraction (:func:`half_light_radius`), so that the
        size prior is uniform in half-light radius whatever the fraction (``None``:
        one fraction).
    rows : numpy.ndarray or None
        The flattened ``rfft2`` frequencies that ``G`` holds, those with ``|k| <=
        k_max`` (:func:`frequency_rows`); ``None``: all of them.
    runs : tuple of Run
        The profile of each run of sizes (:func:`bank_runs`).
    """

    G: np.ndarray
    egrid: np.ndarray
    radii: np.ndarray
    n: int
    model: str
    bulge: np.ndarray | None = None
    n_sub: int = 0
    r_weights: np.ndarray | None = None
    star_weight: float = 1.0
    run_weights: np.ndarray | None = None
    rows: np.ndarray | None = None
    bulge_size: np.ndarray | None = None
    runs: tuple[Run, ...] = ()

    @property
    def n_sizes(self) -> int:
        """Length of one run of increasing radii (the r grid)."""
        return self.n_sub or self.radii.size

    @property
    def n_e(self) -> int:
        return self.egrid.shape[0]

    @property
    def n_r(self) -> int:
        return self.radii.size

    @property
    def n_models(self) -> int:
        return self.G.shape[1]


@lru_cache(maxsize=16)
def _sersic_b(n: float, trunc: float) -> float:
    """Sersic ``b`` of a profile of index ``n`` truncated at ``trunc`` half-light radii
    (0: untruncated, ``gammaincinv(2 n, 1/2)``).

    Chosen so that the truncated profile's half-light radius is 1, as GalSim's ``trunc``
    with ``flux_untruncated=False``.
    """
    if trunc <= 0:
        return float(gammaincinv(2.0 * n, 0.5))
    lo, hi = (5.0, 10.0) if n == 4.0 else (1e-6, 60.0)
    return float(brentq(lambda bb: gammainc(2 * n, bb) / gammainc(2 * n, bb * trunc ** (1 / n))
                        - 0.5, lo, hi))  # fmt: skip


def _enclosed(x, n: float, h: float):
    """Flux fraction within ``x`` (units of ``r``) of the Sersic component ``(n, h)``."""
    if n == 1.0:
        y = np.asarray(x) * (DISC_HLR / h)
        return 1.0 - (1.0 + y) * np.exp(-y)
    t = _sersic_trunc(n)
    b = _sersic_b(n, t)
    y = np.asarray(x) / h
    if t > 0:
        return gammainc(2 * n, b * np.minimum(y, t) ** (1 / n)) / gammainc(2 * n, b * t ** (1 / n))
    return gammainc(2 * n, b * y ** (1 / n))


@lru_cache(maxsize=128)
def run_half_light_radius(run: Run) -> float:
    """Half-light radius per unit ``r`` of a run's profile (:class:`Run`), by root finding
    on its components' enclosed-flux curves."""
    (na, ha), (nb, hb) = run.components
    f = float(run.fraction)
    if f == 0.0:
        return ha if na != 1.0 else half_light_radius("exponential")
    return float(brentq(lambda x: (1 - f) * _enclosed(x, na, ha) + f * _enclosed(x, nb, hb)
                        - 0.5, 1e-9, 1e3))  # fmt: skip


def wrap_correction(
    egrid: np.ndarray,
    radii: np.ndarray,
    fracs: np.ndarray,
    model: str,
    bulge_size_ratio: float,
    n: int,
    rows: np.ndarray | None = None,
    runs: tuple[Run, ...] | None = None,
) -> np.ndarray:
    """Transforms of the wings that the periodic Fourier models wrap into the stamp.

    A model evaluated on the ``rfft2`` frequencies of an ``n x n`` stamp is, in real
    space, the periodic sum of its copies ``m(x + j n)``: a model wider than the stamp
    brings its far wings back in on the opposite side. A stamp cut from the sky (or
    drawn by GalSim) holds only ``m(x)``. Subtracting these transforms from the bank
    makes each model the profile cut at the stamp's edge, as the data are. The
    wrapped flux is largest along the pixel axes (the nearest copies), so without the
    correction large models respond to shear differently along ``e1`` and ``e2``
    (``validate --precision``: galaxies of 1.4-2.5 PSF radii, m2 - m1 ~ +0.02 on a
    32-pixel stamp). The two pixel lines at ``+-n/2`` of an even stamp are one line of
    the periodic model; it is shared half and half so that the correction keeps the
    square's symmetries (:func:`pylensfit.likelihood.folded.folded_bank`).

    Parameters
    ----------
    egrid : numpy.ndarray
        ``(n_e, 2)`` ellipticities, closed under ``e1 -> -e1`` and ``e2 -> -e2``.
    radii : numpy.ndarray
        ``(n_r,)`` sizes of one run (one bulge fraction).
    fracs : numpy.ndarray
        Bulge fractions (``"bulge+disc"``; one value, ignored, for the other models).
    model : str
        Model family.
    bulge_size_ratio : float
        Bulge half-light radius over disc scale length (``"bulge+disc"``).
    n : int
        Stamp side.
    rows : numpy.ndarray, optional
        Only these of the flattened ``rfft2`` frequencies (:func:`frequency_rows`).
    runs : tuple of Run, optional
        The bank's runs (:func:`bank_runs`), in place of ``fracs`` and
        ``bulge_size_ratio``: each run's wings are mixed from its two components'.

    Returns
    -------
    numpy.ndarray
        ``(n * (n // 2 + 1), n_e * len(fracs) * n_r)`` (``len(runs)``) real transforms
        (``(len(rows), ...)`` with ``rows``), in the column order of :class:`ModelBank`
        (without the point source).
    """
    code = MODEL_TYPES.index(model)  # 0 exponential, 1 de Vaucouleurs, 2 bulge + disc
    eg = np.asarray(egrid, float)
    ie_rep = np.flatnonzero((eg[:, 0] > 0) & (eg[:, 1] > 0))
    rep = (eg[ie_rep, 0].copy(), eg[ie_rep, 1].copy(), np.asarray(radii, float))
    if runs is not None:
        w = _run_wings(rep, runs, n)
    else:
        w = _fraction_wings(rep, fracs, model, code, bulge_size_ratio, n)
    return _wing_transforms(eg, ie_rep, w, n, rows)


def wing_transforms(e1, e2, radii, model: str, runs, n: int) -> np.ndarray:
    """:func:`wrap_correction`'s transforms for any ellipticities, one cell at a time.

    Parameters
    ----------
    e1, e2 : array_like
        ``(m,)`` ellipticities in the stamp's pixel frame (not a grid closed under the
        square's symmetries: each is computed).
    radii : array_like
        ``(n_r,)`` sizes, pixels.
    model : str
        Model family.
    runs : sequence of tuple
        ``(bulge fraction, bulge size ratio)`` of each run (one, ignored, for the models
        other than ``"bulge+disc"``).
    n : int
        Stamp side.

    Returns
    -------
    numpy.ndarray
        ``(m, len(runs) * n_r, n, n // 2 + 1)`` real transforms on the ``rfft2``
        frequencies, phase-referenced to the stamp's centre (the bank's columns' order
        within an e cell: run, then size).
    """
    rep = (np.atleast_1d(np.asarray(e1, float)).copy(), np.atleast_1d(np.asarray(e2, float)).copy(),
           np.atleast_1d(np.asarray(radii, float)))  # fmt: skip
    code = MODEL_TYPES.index(model)
    sizes = list(dict.fromkeys(s for _, s in runs))
    parts = {s: _fraction_wings(rep, [f for f, t in runs if t == s], model, code, s, n)
             for s in sizes}  # one profile evaluation per component, per bulge size
    n_r = rep[2].size
    at = {s: 0 for s in sizes}
    cols = []
    for _, s in runs:  # the runs' order
        cols.append(parts[s][:, at[s] * n_r : (at[s] + 1) * n_r])
        at[s] += 1
    w = np.concatenate(cols, axis=1)
    out = np.zeros((*w.shape[:2], n, n // 2 + 1))
    live = np.flatnonzero(np.any(w != 0, axis=(0, 2, 3)))  # models that wrap
    if live.size:
        out[:, live] = sfft.rfft2(sfft.ifftshift(w[:, live].astype(float), axes=(2, 3)),
                                  workers=-1).real  # numpy's pocketfft, on every core
    return out


def _run_wings(rep: tuple, runs: tuple[Run, ...], n: int) -> np.ndarray:
    """The wrapped wings of every run at the representative ellipticities and sizes
    ``rep`` (``e1``, ``e2``, ``radii``), ``(n_rep, len(runs) * n_r, n, n)``: each run's
    are linear in its components' (one profile evaluation each)."""
    n_r = rep[2].size
    comp = {}
    for c in dict.fromkeys(cc for run in runs for cc in run.components):
        comp[c] = np.zeros((rep[0].size, n_r, n, n), dtype=np.float32)
        fr, profile = _wing_args(*c)
        wrapped_wings(*rep, fr, profile, int(n), _WRAP_COPIES, comp[c])
    return np.concatenate([(1.0 - run.fraction) * comp[run.components[0]]
                           + run.fraction * comp[run.components[1]] for run in runs],
                          axis=1)  # fmt: skip


def _fraction_wings(rep: tuple, fracs, model: str, code: int, bulge_size_ratio: float,
                    n: int) -> np.ndarray:  # fmt: skip
    """The wrapped wings of every bulge fraction of ``fracs`` (one of the other models) at
    the representative ellipticities and sizes ``rep``, ``(n_rep, n_fracs * n_r, n, n)``."""
    _, (_, _, b, norm, t, _) = _wing_args(4.0, 1.0)  # the de Vaucouleurs profile's
    fr = np.asarray(fracs, float) if model == "bulge+disc" else np.zeros(1)
    n_r = rep[2].size
    # the wings of a bulge+disc model are linear in its fraction: the pure disc's and
    # the pure bulge's make every fraction's (half the profile evaluations for three)
    base = np.array([0.0, 1.0]) if model == "bulge+disc" and fr.size > 2 else fr
    w = np.zeros((rep[0].size, base.size * n_r, n, n), dtype=np.float32)
    wrapped_wings(*rep, base, (code, float(bulge_size_ratio), b, norm, t, 0.25), int(n),
                  _WRAP_COPIES, w)  # fmt: skip
    if base is not fr:
        w0, w1 = w[:, :n_r], w[:, n_r:]
        w = np.concatenate([(1.0 - f) * w0 + f * w1 for f in fr], axis=1)
    return w


def _wing_transforms(eg: np.ndarray, ie_rep: np.ndarray, w: np.ndarray, n: int,
                     rows: np.ndarray | None) -> np.ndarray:  # fmt: skip
    """The transforms of the wings ``w`` of the representative cells ``ie_rep`` and of
    the other cells of ``eg``, their images under the square's symmetries
    (:func:`wrap_correction`'s result)."""
    per_e = w.shape[1]
    # the other cells by the square's symmetries: e2 -> -e2 is y -> -y, e1 -> -e1 is the
    # transposition x <-> y (on the periodic lattice of offsets from the centre n // 2)
    flip = (2 * (n // 2) - np.arange(n)) % n
    key = {(round(e1, 9), round(e2, 9)): k for k, (e1, e2) in enumerate(eg[ie_rep])}
    sel = np.arange(n * (n // 2 + 1)) if rows is None else np.asarray(rows)
    W = np.zeros((sel.size, eg.shape[0] * per_e))
    live = np.flatnonzero(np.any(w != 0, axis=(0, 2, 3)))
    if live.size == 0:
        return W
    for ie, (e1, e2) in enumerate(eg):
        img = w[key[(round(abs(e1), 9), round(abs(e2), 9))]][live]
        if e2 < 0:
            img = img[:, flip, :]
        if e1 < 0:
            img = np.swapaxes(img, 1, 2)
        tr = np.fft.rfft2(np.fft.ifftshift(img.astype(float), axes=(1, 2)))
        W[:, ie * per_e + live] = tr.real.reshape(live.size, -1)[:, sel].T
    return W


def _wing_args(n_s: float, h: float) -> tuple:
    """:func:`wrapped_wings`' ``fracs`` and ``profile`` (``(model_code, bsr, b_dev,
    norm_dev, trunc, inv_n)``) for the Sersic component ``(n_s, h)``: the exponential
    disc (code 0) or one Sersic component (code 3), untruncated ones cut where the flux
    beyond is below 1e-10."""
    if n_s == 1.0:
        if h != DISC_HLR:
            raise ValueError(f"an exponential component must be the disc, got size {h}")
        return np.zeros(1), (0, 1.0, 1.0, 1.0, 1.0, 1.0)
    t = _sersic_trunc(n_s)
    b = _sersic_b(n_s, t)
    frac_in = gammainc(2 * n_s, b * t ** (1 / n_s)) if t > 0 else 1.0
    norm = 2.0 * np.pi * n_s * gamma(2 * n_s) * frac_in / b ** (2 * n_s)
    cut = t if t > 0 else (gammaincinv(2 * n_s, 1.0 - 1e-10) / b) ** n_s
    return np.ones(1), (3, float(h), float(b), float(norm), float(cut), 1.0 / n_s)


@lru_cache(maxsize=64)
def half_light_radius(
    model: str = "devaucouleurs", *, bulge_fraction: float = 0.5, bulge_size_ratio: float = 0.6
) -> float:
    """Half-light radius of a model of unit size ``r`` (see the module docstring).

    1 for ``"devaucouleurs"`` (``r`` is its half-light radius, of the truncated profile as
    GalSim defines it), 1.678 for ``"exponential"`` (``r`` the scale length); for
    ``"bulge+disc"`` the radius enclosing half the light of the sum, found by root finding
    on the two enclosed-flux curves.
    """
    if model == "devaucouleurs":
        return 1.0
    if model == "exponential":
        return float(brentq(lambda x: _enclosed(x, 1.0, DISC_HLR) - 0.5, 1e-9, 1e3))
    if model == "bulge+disc":
        return run_half_light_radius(Run(float(bulge_fraction), float(bulge_size_ratio)))
    raise ValueError(f"unknown model {model!r}; choose one of {MODEL_TYPES}")


def radius_grid(r_min: float, r_max: float, r_step: float, r_rel_step: float = 0.0,
                r_floor: float = 0.0) -> np.ndarray:
    """Model sizes from ``r_min`` to ``r_max``, excluding 0 (the point source).

    With ``r_rel_step = 0`` the paper's uniform grid ``r_min, r_min + dr, ..., r_max``.
    With ``r_rel_step > 0`` no step exceeds ``r_rel_step * r`` either: below
    ``r_c = r_step / r_rel_step`` the sizes are geometric, ``r_c / (1 + r_rel_step)^k``,
    down to ``max(r_min, r_floor)`` (``r_floor = 0``: ``r_step / 2``); above it, uniform
    with step ``r_step``. A small galaxy's likelihood in ``r`` is as narrow in ``r`` as
    its size, so a uniform step samples it too coarsely (docs: method, eq-radius;
    ``validate --precision``).
    """
    if (r_step <= 0 or r_max <= 0 or r_min < 0 or r_max < r_min or r_rel_step < 0
            or r_floor < 0):
        raise ValueError(f"bad radius grid r_min={r_min}, r_max={r_max}, r_step={r_step}, "
                         f"r_rel_step={r_rel_step}, r_floor={r_floor}")  # fmt: skip
    if r_rel_step == 0:
        n = int(np.floor((r_max - r_min) / r_step + 1e-9)) + 1
        r = r_min + r_step * np.arange(n)
        return r[r > 0]
    r_c = r_step / r_rel_step
    floor = max(r_min, r_floor if r_floor > 0 else 0.5 * r_step)
    start = max(r_c, r_min)
    n_up = int(np.floor((r_max - start) / r_step + 1e-9)) + 1
    upper = start + r_step * np.arange(max(n_up, 0))
    n_down = 0
    if start > floor:
        n_down = int(np.floor(np.log(start / floor) / np.log1p(r_rel_step) + 1e-9))
    lower = start / (1.0 + r_rel_step) ** np.arange(n_down, 0, -1)
    r = np.concatenate([lower, upper])
    return r[(r > 0) & (r <= r_max * (1 + 1e-12))]


def radius_weights(radii: np.ndarray, r_min: float) -> tuple[np.ndarray, float]:
    """Quadrature weights of ``L(e) = int L(e, r) dr`` on the size grid.

    The weight of ``r_j`` is ``(r_{j+1} - r_{j-1}) / 2`` (``dr/dj`` by central
    differences, with ``r_0 = 0`` when the point source closes the grid and one-sided at
    the ends), so the sum is the trapezoid rule in the grid index ``j``; the point
    source gets ``r_1``. On the uniform grid every weight is ``dr``, as in the paper.

    Returns
    -------
    w : numpy.ndarray
        Weight of each size.
    w_star : float
        Weight of the point source (``r = 0``).
    """
    r = np.asarray(radii, dtype=float)
    if r.size == 1:
        return np.array([r[0] if r_min == 0 else 1.0]), float(r[0])
    ext = np.concatenate([[0.0 if r_min == 0 else 2 * r[0] - r[1]], r, [2 * r[-1] - r[-2]]])
    w = 0.5 * (ext[2:] - ext[:-2])
    return w, float(r[0])


def _bank_transforms(n: int, k_max: float, egrid: np.ndarray, radii: np.ndarray,
                     runs: tuple[Run, ...], model: str, bulge_size_ratio: float, dtype: str,
                     truncate: bool) -> np.ndarray:  # fmt: skip
    """:class:`ModelBank`'s ``G``: ``(n_freq, n_e * n_runs * n_r + 1)`` transforms of every
    model (ellipticity cell, run, size; the point source last) on the frequencies of
    :func:`frequency_rows` ``(n, k_max)``, less the wings the periodic models wrap into
    the stamp with ``truncate`` (:func:`wrap_correction`)."""
    fracs = np.array([run.fraction for run in runs])
    n_sub = radii.size
    kx, ky, _ = rfft_frequencies(n)
    rows = frequency_rows(n, k_max)
    kx = kx.ravel() if rows is None else kx.ravel()[rows]
    ky = ky.ravel() if rows is None else ky.ravel()[rows]
    n_freq = kx.size
    per_e = n_sub * len(runs)
    G = np.empty((n_freq, egrid.shape[0] * per_e + 1), dtype=dtype)
    mix = model == "bulge+disc" and len(runs) > 1
    comps = list(dict.fromkeys(c for run in runs for c in run.components))
    for ie, (e1, e2) in enumerate(egrid):  # one vectorised (freq x r) block per e and run
        ks = sheared_k(kx, ky, e1, e2)
        q = ks[:, None] * radii[None, :]
        if mix:  # each run's transform is linear in its two components' (exact)
            T = {c: _component_transform(q, *c) for c in comps}
        for ib, run in enumerate(runs):
            c0 = ie * per_e + ib * n_sub
            if mix:
                ca, cb = run.components
                G[:, c0 : c0 + n_sub] = run.fraction * T[cb] + (1.0 - run.fraction) * T[ca]
            else:
                G[:, c0 : c0 + n_sub] = fourier_profile(
                    q, model, bulge_fraction=run.fraction, bulge_size_ratio=bulge_size_ratio)
    G[:, -1] = 1.0
    if truncate:
        W = wrap_correction(egrid, radii, fracs, model, bulge_size_ratio, n, rows,
                            runs=runs if mix else None)  # fmt: skip
        G[:, :-1] -= W.astype(dtype)
        del W
    return G


@lru_cache(maxsize=8)
def _cached_bank(
    n: int,
    e_step: float,
    e_max: float,
    r_min: float,
    r_max: float,
    r_step: float,
    model: str,
    bulge_fraction: float,
    bulge_size_ratio: float,
    dtype: str,
    n_bulge: int = 1,
    r_rel_step: float = 0.0,
    truncate: bool = False,
    k_max: float = 0.0,
    bulge_size_ratio2: float = 0.0,
    sersic_ladder: tuple[float, ...] = (),
    r_floor: float = 0.0,
) -> ModelBank:
    egrid = ellipticity_grid(e_step, emax=e_max)
    radii = radius_grid(r_min, r_max, r_step, r_rel_step, r_floor)
    r_w, w_star = radius_weights(radii, r_min)
    runs = bank_runs(model, bulge_fraction, bulge_size_ratio, n_bulge, bulge_size_ratio2,
                     sersic_ladder)  # fmt: skip
    fracs = np.array([run.fraction for run in runs])
    n_sub = radii.size
    bulge = fracs if len(runs) == 1 else np.array([run.bulge_fraction for run in runs])
    rows = frequency_rows(n, k_max)
    key = (n, e_step, e_max, r_min, r_max, r_step, model, bulge_fraction, bulge_size_ratio,
           dtype, n_bulge, r_rel_step, truncate, k_max, bulge_size_ratio2, sersic_ladder,
           r_floor)  # fmt: skip
    G = disk_cached("model-bank", key, lambda: _bank_transforms(
        n, k_max, egrid, radii, runs, model, bulge_size_ratio, dtype, truncate))
    run_w = None
    if len(runs) > 1:
        hlr = np.array([run_half_light_radius(run) for run in runs])
        run_w = hlr / hlr[0]
    two = bulge_size_ratio2 > 0 or bool(sersic_ladder)
    return ModelBank(G=G, egrid=egrid, radii=np.tile(radii, len(runs)), n=n, model=model,
                     bulge=np.repeat(bulge, n_sub), n_sub=n_sub, r_weights=r_w,
                     star_weight=w_star, run_weights=run_w, rows=rows,
                     bulge_size=np.repeat([run.size for run in runs], n_sub) if two else None,
                     runs=runs)  # fmt: skip


def model_bank(config=None) -> ModelBank:
    """The model bank of a configuration (cached: built once per process).

    Parameters
    ----------
    config : pylensfit.Config, optional
        Grid and model settings; the paper's defaults if omitted.
    """
    cfg = config if config is not None else Config()
    return _cached_bank(
        cfg.stamp_size,
        cfg.e_step,
        cfg.e_max,
        cfg.r_min,
        cfg.r_max,
        cfg.r_step,
        cfg.model,
        cfg.bulge_fraction,
        cfg.bulge_size_ratio,
        cfg.dtype,
        int(cfg.n_bulge_fractions),
        float(cfg.r_rel_step),
        bool(cfg.truncate_models),
        float(cfg.k_max),
        float(cfg.bulge_size_ratio2),
        tuple(cfg.sersic_ladder),
        float(cfg.r_floor),
    )
