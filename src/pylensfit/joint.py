"""The likelihood of a galaxy on all of its exposures at once, on a sky-frame (e, r) grid.

Each galaxy is seen in ``K`` exposures (:mod:`pylensfit.exposures`), each with its own
stamp ``d_k``, PSF ``P_k``, noise ``sigma_k``, photometric scale ``f_k`` (counts per unit
of the common flux) and local WCS Jacobian ``J_k = d(x, y)/d(W, N)`` (pixels per
arcsec). One model of the sky, ``A m(u - X)`` (flux ``A``, sky offset ``X`` in arcsec,
shape ``e`` and size ``r`` in the sky frame), is seen in exposure ``k`` as
``A f_k m(J_k^-1 (x - c_k) - X) / |det J_k|`` convolved with ``P_k`` (``c_k`` the
catalogue position in the stamp): its transform on the stamp's frequencies ``k`` is
``M_sky(J_k^T k) P_k(k)``, with the phase ``exp(-i (J_k^T k) . X)`` of the shared offset.
So every exposure is a sky-frame stamp sampled at the frequencies ``q = J_k^T k``
(radians per arcsec), and the sky-frame model ``G(q) = F(|S(e)^T q| r)`` of
:mod:`pylensfit.models` is evaluated there once per exposure.

With ``h_k(X) = sum_x d_k(x) m_k(x - c_k - J_k X)`` and ``S_k = sum_x m_k^2``, the
chi-square of all exposures is quadratic in ``A`` with ``H = sum_k f_k h_k / sigma_k^2``
and ``Q = sum_k f_k^2 S_k / sigma_k^2``:

* **amplitude** (uniform prior, ``A > 0``), marginalised once over the sum::

      ln L(e, r, X) = H^2 / (2 Q) + ln Phi(H / sqrt Q) - ln(Q) / 2

  which for one exposure is :func:`pylensfit.likelihood.fit_stamps`'s
  ``h^2 / (2 sigma^2 S) + ln Phi(h / (sigma sqrt S)) - ln(S) / 2`` up to ``ln sigma``;
  the configuration's power law (``Config.amplitude_prior`` ``"snr"`` or ``"flux"``, its
  bounds on the flux ``A`` in the common flux unit) is the single fit's integral with
  the S/N ``H / sqrt Q`` and ``Q`` for ``S / sigma^2``;
* **position**: ``H`` and its gradient and Hessian in the sky offset ``X`` are sums over
  every exposure's frequencies of ``Re(D'_k) G``, ``-q Im(D'_k) G`` and ``-q q^T Re(D'_k)
  G`` with ``D'_k = f_k D_k conj(P_k) / sigma_k^2`` (the data re-centred on the catalogue
  position by a phase ramp): matrix products of the block's rows with each exposure's
  bank, summed over the exposures; ``Q`` and the expected Hessian likewise from
  ``f_k^2 |P_k|^2 / sigma_k^2``. Each exposure's products are folded by the symmetries
  of the square pixel grid that its Jacobian keeps as symmetries of the model grid
  (:func:`lattice_symmetries`): all four where ``J`` maps the pixel axes onto the sky's
  axes or diagonals (a quarter of the operations, as the single fit's), the quarter turn
  ``e -> -e`` for any rotation or mirror image times a scale (half), none for a sheared
  ``J``; the exposures of one kind are summed in one matrix product, and the kernel
  reads each model's products from its folded column (those of a bulge+disc fraction
  between 0 and 1 mixed from the pure disc's and the pure bulge's columns, as the
  single fit's: the products are linear in the model). One Newton step gives ``X*`` and
  ``H*``, and the Laplace approximation with the Gaussian position prior of width ``b``
  (arcsec) about the catalogue position is that of the single-exposure fit::

      ln L(e, r) = l* - ln det(I + b^2 F) / 2 - X*^T (F^-1 + b^2 I)^-1 X* / 2,
      F = -(dl/dH) Hess H;

* **size and bulge fraction**: ``L(e) = sum_b pi_b sum_r w_r L(e, r) + w_* L_*``, the
  radius weights of :func:`pylensfit.models.radius_weights` or those of a size prior
  (:meth:`pylensfit.prior.SizePrior.node_weights`, in reference pixels; the single
  fit's correction of a peak narrower than the r grid), a uniform prior over the bulge
  fractions, the point source (``r = 0``) once; ``L(r) = sum_e P(e) L(e, r)`` kept as
  the single fit keeps it, for the size prior's estimate.

Sizes and lengths in the configuration (``r_min``, ``r_max``, ``r_step``,
``position_prior_sigma``, ``max_offset``, ``centring_scale``, ``max_newton_step``) are
read in units of a reference pixel scale (``pixel_scale``, arcsec): with one exposure of
``J = I`` the fit is :func:`pylensfit.likelihood.fit_stamps`'s.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace

import numpy as np
from threadpoolctl import threadpool_limits

from . import flags as _flags
from .bankruns import bank_runs
from .config import Config
from .exposures import ExposureStamps
from .grid import ellipticity_grid
from .joint_nb import Folds, Norms, laplace_grid, unfold
from .likelihood.amplitude_nb import AMP_UNIFORM, amplitude_table
from .likelihood.bank import keep_last
from .likelihood.grid_nb import Galaxies, Laplace, Outputs, Sums
from .likelihood.merge import logsumexp_groups
from .likelihood.priors import amplitude_prior, e_groups
from .models import (
    ModelBank,
    fourier_profile,
    half_light_radius,
    in_disc,
    radius_grid,
    radius_weights,
    rfft_frequencies,
    sheared_k,
    wing_transforms,
)
from .prior import Prior, SizePrior
from .psf import psf_transform
from .skyframe import jacobian_frame, shear_to_pixel

__all__ = ["JointFits", "ViewArrays", "first_exposure", "fit_exposures", "fit_views",
           "lattice_symmetries", "pixel_cells", "sky_frequencies"]

#: e cells evaluated together when a bank is built (memory of one chunk ~ n_freq x 16 x n_r)
_E_CHUNK = 16


def first_exposure(used: np.ndarray, none: int = -1) -> np.ndarray:
    """Each galaxy's first used exposure: the lowest set bit of its ``exposures_used``.

    Parameters
    ----------
    used : numpy.ndarray
        ``(n,)`` integer bit masks (bit ``k``: exposure ``k`` entered the fit).
    none : int
        The value where no bit is set.

    Returns
    -------
    numpy.ndarray
        ``(n,)`` int64 exposure indices.
    """
    used = np.asarray(used, np.int64)
    low = np.maximum(used & -used, 1)
    return np.where(used > 0, np.log2(low).round().astype(np.int64), none)


@dataclass
class JointFits:
    """Result of :func:`fit_exposures`: one row per galaxy.

    Attributes
    ----------
    egrid : numpy.ndarray
        ``(n_e, 2)`` sky-frame ellipticity cell centres.
    lnL : numpy.ndarray
        ``(n, n_e)`` float32 ``ln L(e)`` of all usable exposures together, each row
        shifted so that its maximum is 0; NaN for galaxies without a usable exposure.
    lnL_peak : numpy.ndarray
        ``(n,)`` the shift removed from each row.
    n_exposures : numpy.ndarray
        ``(n,)`` int, the exposures that entered each galaxy's fit.
    r_best : numpy.ndarray
        Size of the most likely model, arcsec (0 for the point source).
    flux : numpy.ndarray
        Amplitude of the most likely model, in the common flux unit (``H* / Q``).
    x, y : numpy.ndarray
        Sky offset ``(W, N)`` of the most likely model's centre from the catalogue
        position, arcsec (west, north).
    snr : numpy.ndarray
        Matched-filter S/N of the most likely model, ``H* / sqrt Q``, all exposures.
    e1_best, e2_best : numpy.ndarray
        Sky-frame ellipticity of the most likely model.
    flags : numpy.ndarray
        Bit mask, :data:`pylensfit.flags.FLAGS` (``NOT_MEASURED``: no usable exposure;
        ``NO_PEAK``: no positive cross-correlation peak; ``FIT_FAILED``).
    lnL_bulge : numpy.ndarray or None
        With several bulge fractions, ``(n, n_b, n_e)`` float32 ``ln L_b(e)`` of each
        fraction alone (sizes > 0), shifted like ``lnL``.
    lnL_star : numpy.ndarray or None
        ``(n,)`` the point source's weighted ``ln L``, shifted like ``lnL``, with several
        fractions.
    bulge_fractions : numpy.ndarray or None
        ``(n_b,)`` the fraction of each run of ``lnL_bulge``.
    pixel_scale : float
        The reference pixel scale, arcsec, in which the configuration's sizes were read.
    meta : dict
        The model family and grid steps.
    lnL_r : numpy.ndarray or None
        ``(n, n_r + 1)`` float32 ``ln L(r) = ln sum_e P(e) L(e, r)`` of every size node
        (each run's sizes, then the point source), ``P`` the ellipticity prior
        ``Prior()``, shifted like ``lnL``: :attr:`pylensfit.StampFits.lnL_r`'s meaning.
    lnL_r_grouped : numpy.ndarray or None
        ``(n, n_groups, n_r + 1)`` float32 the sums of ``lnL_r`` over each group of e
        cells apart (``fit_exposures(lnL_r_groups=...)``), shifted like ``lnL``, for
        :func:`pylensfit.prior.estimate_size_prior` (through
        :func:`pylensfit.likelihood.reweight_lnL_r`); None without groups.
    radii : numpy.ndarray or None
        ``(n_r,)`` the size of each node of ``lnL_r``, arcsec.
    r_marginal : numpy.ndarray or None
        ``(n,)`` the size of the largest ``L(r)``, arcsec (0 for the point source):
        :attr:`pylensfit.StampFits.r_best`'s meaning (marginal over e).
    is_star : numpy.ndarray or None
        ``(n,)`` bool: ``r_marginal`` is 0 or below ``Config.point_source_size``
        reference pixels (:attr:`pylensfit.StampFits.is_star`'s meaning).
    bulge_best : numpy.ndarray or None
        ``(n,)`` the bulge fraction of the most likely model (NaN for the point source).
    exposures_used : numpy.ndarray or None
        ``(n,)`` int64 bit mask: bit ``k`` set where exposure ``k`` entered the fit.
    """

    egrid: np.ndarray
    lnL: np.ndarray
    lnL_peak: np.ndarray
    n_exposures: np.ndarray
    r_best: np.ndarray
    flux: np.ndarray
    x: np.ndarray
    y: np.ndarray
    snr: np.ndarray
    e1_best: np.ndarray
    e2_best: np.ndarray
    flags: np.ndarray
    lnL_bulge: np.ndarray | None = None
    lnL_star: np.ndarray | None = None
    bulge_fractions: np.ndarray | None = None
    pixel_scale: float = 1.0
    meta: dict = field(default_factory=dict)
    lnL_r: np.ndarray | None = None
    lnL_r_grouped: np.ndarray | None = None
    radii: np.ndarray | None = None
    r_marginal: np.ndarray | None = None
    is_star: np.ndarray | None = None
    bulge_best: np.ndarray | None = None
    exposures_used: np.ndarray | None = None

    def __len__(self) -> int:
        return self.lnL.shape[0]

    #: the attributes that all galaxies share (every other one has a row per galaxy)
    _SHARED = ("egrid", "bulge_fractions", "pixel_scale", "meta", "radii")

    def take(self, rows) -> JointFits:
        """The galaxies ``rows`` (an index array, boolean mask or slice) alone."""
        per = [f.name for f in fields(self) if f.name not in self._SHARED]
        return replace(self, **{a: None if getattr(self, a) is None else
                                np.asarray(getattr(self, a))[rows] for a in per})  # fmt: skip


@dataclass(frozen=True)
class _Columns:
    """The model grid's columns: e cells, runs of sizes (arcsec), their weights and the
    priors of the sums (size prior, e cells' weights in ``L(r)`` and their groups, the
    amplitude prior)."""

    egrid: np.ndarray  # (n_e, 2)
    radii: np.ndarray  # (n_sub,) arcsec, one run
    runs: tuple  # (fraction, bulge size ratio) per run
    node_w: np.ndarray  # (n_b * n_sub,) weight of each size node in the sum over r
    w_star: float
    model: str
    e_w: np.ndarray  # (n_e,) the e cells' weights in L(r), summing to 1
    e_grp: np.ndarray  # (n_e,) int: the group of each e cell in L(r)
    amp: tuple  # the amplitude prior and its table, joint_nb.laplace_grid's ``amp``
    truncate: bool = False  # the models cut at each exposure's stamp edge (truncate_models)

    @property
    def n_e(self) -> int:
        return self.egrid.shape[0]

    @property
    def n_sub(self) -> int:
        return self.radii.size

    @property
    def n_b(self) -> int:
        return len(self.runs)

    @property
    def n_grp(self) -> int:
        return int(self.e_grp.max()) + 1

    @property
    def n_cols(self) -> int:
        return self.n_e * self.n_b * self.n_sub + 1

    def sums(self) -> Sums:
        """The weights of the sum over r (the runs of sizes equally likely a priori),
        the kernel's :class:`~pylensfit.likelihood.grid_nb.Sums`."""
        return Sums(self.node_w, self.w_star, np.full(self.n_b, -np.log(self.n_b)),
                    self.e_w, self.e_grp, self.n_sub)  # fmt: skip

    def kept(self) -> np.ndarray | None:
        """The models within the size prior's support (the point source always), a set
        closed under the symmetries (all e cells of a size); None: all of them."""
        if (self.node_w > 0).all():
            return None
        per_e = self.n_b * self.n_sub
        on = np.flatnonzero(self.node_w > 0)
        return np.append((np.arange(self.n_e)[:, None] * per_e + on[None, :]).ravel(),
                         self.n_cols - 1)  # fmt: skip

    def uniform(self) -> float:
        """1.0 for the uniform amplitude prior, else 0.0 (``joint_nb.laplace_grid``)."""
        return float(self.amp[0] == AMP_UNIFORM)


def _size_weights(cfg: Config, radii: np.ndarray, runs: tuple, size_prior: SizePrior | None
                  ) -> tuple[np.ndarray, float]:  # fmt: skip
    """The weight of every size node (``radii`` in reference pixels, one run) and of the
    point source: the quadrature weights of the flat prior, uniform in half-light radius
    for every run, or ``size_prior``'s (:meth:`pylensfit.prior.SizePrior.node_weights`,
    on the reference pixels' grid of :func:`pylensfit.models.model_bank`)."""
    r_w, w_star = radius_weights(radii, cfg.r_min)
    run_w = np.ones(len(runs))
    if len(runs) > 1:
        hlr = np.array([half_light_radius("bulge+disc", bulge_fraction=f, bulge_size_ratio=s)
                        for f, s in runs])  # fmt: skip
        run_w = hlr / hlr[0]
    if size_prior is None:
        node_w = np.tile(np.asarray(r_w, float), len(runs)) * np.repeat(run_w, radii.size)
        return node_w, float(w_star)
    # the bank's sizes alone (no transforms): what SizePrior.node_weights reads of it
    grid = ModelBank(G=np.empty((0, 0)), egrid=np.empty((0, 2)), radii=np.tile(radii, len(runs)),
                     n=int(cfg.stamp_size), model=cfg.model, n_sub=radii.size,
                     r_weights=np.asarray(r_w, float), star_weight=float(w_star),
                     run_weights=run_w if len(runs) > 1 else None)  # fmt: skip
    node_w, w_star = size_prior.node_weights(grid, cfg)
    return np.asarray(node_w, dtype=float), float(w_star)


def _columns(cfg: Config, scale: float, size_prior: SizePrior | None = None,
             lnL_r_groups: np.ndarray | None = None) -> _Columns:  # fmt: skip
    """The configuration's grid with its sizes in arcsec (``scale`` arcsec per pixel),
    the size prior's weights, the e cells' weights in ``L(r)`` (the ellipticity prior
    ``Prior()``, as :func:`pylensfit.likelihood.fit_stamps`'s default) and groups, and the
    configuration's amplitude prior."""
    if cfg.sersic_ladder or cfg.bulge_size_ratio2 > 0:
        raise ValueError("fit_exposures: the Sersic ladder and a second bulge size are not "
                         "supported; use one bulge size")  # fmt: skip
    egrid = ellipticity_grid(cfg.e_step, emax=cfg.e_max)
    radii = radius_grid(cfg.r_min, cfg.r_max, cfg.r_step, cfg.r_rel_step, cfg.r_floor)
    runs = tuple((float(r.fraction), float(r.size)) for r in bank_runs(
        cfg.model, cfg.bulge_fraction, cfg.bulge_size_ratio, int(cfg.n_bulge_fractions)))
    node_w, w_star = _size_weights(cfg, radii, runs, size_prior)
    e_w = Prior().pdf(egrid[:, 0], egrid[:, 1])
    amp = amplitude_prior(cfg)
    return _Columns(egrid=egrid, radii=radii * scale, runs=runs, node_w=node_w,
                    w_star=w_star, model=cfg.model, e_w=e_w / e_w.sum(),
                    e_grp=e_groups(lnL_r_groups, egrid.shape[0]),
                    amp=(*amp, *amplitude_table(amp.power)),
                    truncate=bool(cfg.truncate_models))  # fmt: skip


def _interior(n: int, k_max: float = 0.0) -> np.ndarray:
    """Flattened ``rfft2`` indices of an ``n x n`` stamp that are not Nyquist (``|j| <
    n/2``) and, with ``k_max > 0``, within ``|k| <= k_max`` (the stamp tiers): the
    frequencies the single-exposure fit sums over."""
    kx, ky, _ = rfft_frequencies(n)
    jmax = (n - 1) // 2
    jx = np.rint(kx * n / (2 * np.pi)).astype(int)
    jy = np.rint(ky * n / (2 * np.pi)).astype(int)
    on = (np.abs(jx) <= jmax) & (np.abs(jy) <= jmax)
    if k_max > 0:
        on &= in_disc(kx, ky, k_max)
    return np.flatnonzero(on.ravel())


def sky_frequencies(jacobian: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``q = J^T k`` of every ``rfft2`` frequency of an ``n x n`` stamp, radians per arcsec.

    A sky-frame profile ``m(u)`` seen through ``J`` is ``m(J^-1 x) / |det J|`` in the
    pixels, whose transform at the pixel frequency ``k`` is ``M(J^T k)``.

    Parameters
    ----------
    jacobian : numpy.ndarray
        ``(2, 2)`` local WCS Jacobian ``J = d(x, y)/d(W, N)``, pixels per arcsec.
    n : int
        Stamp side, pixels.

    Returns
    -------
    qx, qy : numpy.ndarray
        ``(n, n // 2 + 1)`` the ``W`` and ``N`` components of ``J^T k``, radians per
        arcsec, on the grid of :func:`pylensfit.models.rfft_frequencies`.
    """
    kx, ky, _ = rfft_frequencies(n)
    J = np.asarray(jacobian, dtype=float)
    return J[0, 0] * kx + J[1, 0] * ky, J[0, 1] * kx + J[1, 1] * ky


def _bank_chunks(cols: _Columns, qx: np.ndarray, qy: np.ndarray):
    """The sky-frame model transforms at the frequencies ``q``, a few e cells at a time:
    yields ``(j0, G)``, ``G`` the ``(n_freq, n)`` float64 columns ``j0 .. j0 + n`` of the
    grid (cell ``ie``'s runs of sizes at ``ie * n_b * n_sub``), the point source last
    (its own chunk)."""
    n_f, per_e = qx.size, cols.n_b * cols.n_sub
    for e0 in range(0, cols.n_e, _E_CHUNK):  # vectorised blocks of (freq x e x r)
        eg = cols.egrid[e0 : e0 + _E_CHUNK]
        ks = sheared_k(qx[:, None], qy[:, None], eg[None, :, 0], eg[None, :, 1])
        q = ks[:, :, None] * cols.radii[None, None, :]
        blk = np.empty((n_f, eg.shape[0], cols.n_b, cols.n_sub))
        for ib, prof in enumerate(_run_profiles(cols, q)):
            blk[:, :, ib] = prof
        yield e0 * per_e, blk.reshape(n_f, -1)
    yield cols.n_e * per_e, np.ones((n_f, 1))


def _run_profiles(cols: _Columns, q: np.ndarray) -> list[np.ndarray]:
    """:func:`pylensfit.models.fourier_profile` at ``q`` of each run: the bulge+disc
    runs' ``f B + (1 - f) D`` with the bulge's ``B`` evaluated once per bulge size and
    the disc's ``D`` once."""
    if cols.model != "bulge+disc":
        return [fourier_profile(q, cols.model, bulge_fraction=f, bulge_size_ratio=s)
                for f, s in cols.runs]  # fmt: skip
    disc = fourier_profile(q, "exponential")
    bulge = {s: fourier_profile(q * s, "devaucouleurs") for s in {s for _, s in cols.runs}}
    return [f * bulge[s] + (1.0 - f) * disc for f, s in cols.runs]


#: the square pixel grid's symmetries ``h = 1, s1, s2, s1 s2`` (modulo ``k -> -k``) as
#: matrices on the frequencies ``(kx, ky)``: ``s1`` flips ``ky``, ``s2`` swaps the axes.
#: The same matrices on the sky frequencies map a model ``(e1, e2)`` to ``(e1, -e2)``,
#: ``(-e1, e2)``, ``(-e1, -e2)`` (``G_{s e}(q) = G_e(s q)``,
#: :class:`pylensfit.likelihood.folded.FoldedBank`), the signs :data:`_E_SIGNS`
_SYMMETRIES = np.array([[[1, 0], [0, 1]], [[1, 0], [0, -1]], [[0, 1], [1, 0]],
                        [[0, 1], [-1, 0]]])  # fmt: skip
_E_SIGNS = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]])
#: the characters of the group, ``chi_c(h) = (-1)^{popcount(c & h)}``
_CHI = np.array([[(-1) ** bin(c & h).count("1") for h in range(4)] for c in range(4)], float)


def lattice_symmetries(jacobian: np.ndarray, tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """The square pixel grid's symmetries that an exposure's Jacobian keeps as symmetries
    of the sky-frame model grid.

    A symmetry ``h`` of the pixel frequencies (:data:`_SYMMETRIES`) is seen on the sky as
    ``J^T h J^-T``; where that is (up to sign) one of the same matrices ``s``, the model
    ``e`` seen at ``h k`` is the model ``s e`` seen at ``k``, and the exposure's products
    fold by ``h`` as the single fit's do. Every Jacobian keeps ``h = 1``; a rotation (or
    a mirror image) times a scale keeps the quarter turn ``s1 s2`` (``e -> -e``); one
    that maps the pixel axes onto the sky's axes or diagonals
    keeps all four.

    Parameters
    ----------
    jacobian : numpy.ndarray
        ``(2, 2)`` ``J = d(x, y)/d(W, N)``, pixels per arcsec (invertible).
    tol : float
        Tolerance on the entries of ``J^T h J^-T`` (dimensionless).

    Returns
    -------
    h, s : numpy.ndarray
        The kept symmetries (indices into :data:`_SYMMETRIES`, a subgroup, ``h[0] = 0``)
        and the model symmetry ``s`` that each is on the sky.
    """
    Jt = np.asarray(jacobian, dtype=float).T
    hs, ss = [0], [0]
    for h, M in enumerate(_SYMMETRIES[1:], start=1):
        on_sky = Jt @ M @ np.linalg.inv(Jt)
        for s, S in enumerate(_SYMMETRIES):
            if np.abs(on_sky - S).max() < tol or np.abs(on_sky + S).max() < tol:
                hs.append(h)
                ss.append(s)
                break
    return np.array(hs), np.array(ss)


#: the column subsets of the folded banks last used (all, the centring pass's, the size
#: prior's), per exposure
_SUBSETS: dict = {}
_SUBSETS_KEPT = 24
#: the most bytes of arrays that the banks and their subsets keep, each (a Config() bank
#: of 48-pixel stamps holds about 0.2 GB)
_CACHE_BYTES = 1.5e9


@dataclass(frozen=True)
class _Fold:
    """One exposure's bank folded by the lattice symmetries ``H`` its Jacobian keeps.

    On the interior frequencies modulo ``+-H`` (orbit representatives ``k0``), the
    characters ``chi`` of ``H`` split each product ``h_e = sum_k f(k) G_e(k)`` into
    ``h_{s(g) e} = sum_chi chi(g) A_chi[e]``, ``A_chi[e] = sum_k0 w(k0) fhat_chi(k0)
    Ghat_chi,e(k0)`` with ``fhat_chi(k0) = sum_h chi(h) f(h k0)`` (likewise ``Ghat``) and
    ``w = |orbit| / |H|^2``: ``|H|`` products over ``1 / |H|`` of the frequencies, for
    the ``|H|`` models ``s(g) e``, as :class:`pylensfit.likelihood.folded.FoldedBank`
    does for ``H`` the whole group. ``|H| = 1`` is the half-plane, unfolded.
    """

    idx: np.ndarray  # (n_h, n_k0) position of h k0 (or -h k0) in the exposure's sel
    w: np.ndarray  # (n_k0,) orbit weights
    chi: np.ndarray  # (n_h, n_h) characters of H: chi[c, slot of h]
    keep: tuple  # per character, the k0 where it can be non-zero
    G: tuple  # per character, (len(keep), n_base) folded transforms of the base columns
    G2: tuple  # per character, (len(keep), n_fc) those of the squared transforms (norms)
    members: np.ndarray  # (n_fc, n_h) the model s(h) e of folded column c, slot h
    kind: tuple  # (H, s): exposures of one kind have the same folded columns
    mix: tuple  # (base, a, b, f), (n_fc,) each: _mixed_columns

    def columns(self, cols: np.ndarray | None, n_cols: int) -> tuple:
        """The products' transforms, ``G2``, ``members`` and the mixing of the models
        ``cols`` (a set closed under the symmetries; None: all), the members numbered in
        ``cols`` (kept for later calls: the last :data:`_SUBSETS_KEPT`).

        ``G`` holds the base columns that the folded columns of ``cols`` read, in their
        order; the folded column ``i``'s products are ``(1 - f[i])`` times those of
        ``G``'s column ``a[i]`` plus ``f[i]`` times those of ``b[i]``: the third tuple,
        ``(a, b, f)``.
        """
        key = (id(self), n_cols, None if cols is None else cols.tobytes())
        hit = _SUBSETS.get(key)
        if hit is not None and hit[0] is self:
            return hit[1]
        out = self._subset(cols, n_cols)
        keep_last(_SUBSETS, key, (self, out), _SUBSETS_KEPT, _CACHE_BYTES)
        return out

    def _subset(self, cols: np.ndarray | None, n_cols: int) -> tuple:
        if cols is None:
            fc, mem, G2 = np.arange(self.members.shape[0]), self.members, self.G2
        else:
            pos = np.full(n_cols, -1, dtype=np.int64)
            pos[cols] = np.arange(cols.size)
            fc = np.flatnonzero(pos[self.members[:, 0]] >= 0)
            mem = np.ascontiguousarray(np.where(self.members[fc] >= 0, pos[self.members[fc]],
                                                -1))  # fmt: skip
            G2 = tuple(g[:, fc] for g in self.G2)
        a, b, f = (x[fc] for x in self.mix[1:])
        direct = np.union1d(a, b)  # the base columns read, in the order of G's
        on = self.mix[0][direct]
        G = (self.G if direct.size == self.G[0].shape[1]
             else tuple(np.ascontiguousarray(g[:, on]) for g in self.G))  # fmt: skip
        return G, G2, mem, (np.searchsorted(direct, a), np.searchsorted(direct, b), f)


def _mixed_columns(cols: _Columns, n_rep: int) -> tuple[np.ndarray, ...]:
    """The folded columns (``n_rep`` cells' runs of sizes, then the point source) as mixes
    of the base columns: the bulge+disc fractions between 0 and 1 are ``(1 - f)`` times
    the pure disc's transform plus ``f`` times the pure bulge's (of the same bulge size),
    and so are their products with the data (the single fit's
    :func:`pylensfit.likelihood.folded.mixed_columns`). Returns, per folded column, its
    place among the base columns (-1: mixed), the two base columns it reads (its own
    where not mixed; folded columns' numbers) and its ``f`` (0 where not mixed)."""
    per_e = cols.n_b * cols.n_sub
    n_fc = n_rep * per_e + 1
    a = np.arange(n_fc)
    b, f = a.copy(), np.zeros(n_fc)
    ends = {(fr, sz): ib for ib, (fr, sz) in enumerate(cols.runs) if fr in (0.0, 1.0)}
    if cols.model == "bulge+disc":
        for ib, (fr, sz) in enumerate(cols.runs):
            if 0.0 < fr < 1.0 and (0.0, sz) in ends and (1.0, sz) in ends:
                j = (np.arange(n_rep)[:, None] * per_e + ib * cols.n_sub
                     + np.arange(cols.n_sub)[None, :]).ravel()  # fmt: skip
                a[j] = j + (ends[(0.0, sz)] - ib) * cols.n_sub
                b[j] = j + (ends[(1.0, sz)] - ib) * cols.n_sub
                f[j] = fr
    is_base = f == 0.0
    base = np.where(is_base, np.cumsum(is_base) - 1, -1)
    return base, a, b, f


def _frequency_orbits(n: int, H: np.ndarray,
                      k_max: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The interior frequencies of an ``n x n`` stamp (within ``|k| <= k_max`` where it
    is positive) modulo ``+-H``: each orbit's representative ``k0`` (integer ``(jx,
    jy)``, ``(n_k0, 2)``), its images ``h k0`` (``(n_h, n_k0, 2)``) and the orbit's size."""
    jmax = (n - 1) // 2
    jy, jx = np.mgrid[-jmax : jmax + 1, -jmax : jmax + 1]
    pts = np.stack([jx.ravel(), jy.ravel()], axis=1)
    if k_max > 0:  # the symmetries keep |k|: the disc is a union of orbits
        pts = pts[in_disc(2 * np.pi / n * pts[:, 0], 2 * np.pi / n * pts[:, 1], k_max)]
    key = lambda p: (p[..., 1] + jmax) * (2 * jmax + 1) + p[..., 0] + jmax  # noqa: E731
    imgs = np.einsum("hab,pb->hpa", _SYMMETRIES[H], pts)
    both = np.concatenate([key(imgs), key(-imgs)])  # (2 n_h, n_pts) the orbit's keys
    rep = both.min(axis=0) == key(pts)
    size = np.array([np.unique(both[:, i]).size for i in np.flatnonzero(rep)])
    return pts[rep], imgs[:, rep], size


def _sel_positions(n: int, sel: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Position in ``sel`` (flattened ``rfft2`` indices) of the frequencies ``k`` (integer
    ``(..., 2)``), or of ``-k`` where ``k`` lies in the other half-plane."""
    flip = k[..., 0] < 0
    k = np.where(flip[..., None], -k, k)
    flat = (k[..., 1] % n) * (n // 2 + 1) + k[..., 0]
    pos = np.full(n * (n // 2 + 1), -1, dtype=np.int64)
    pos[sel] = np.arange(sel.size)
    return pos[flat]


def _model_orbits(cols: _Columns, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The e cells in orbits of the model symmetries ``S``: the representatives (the
    first cell of each orbit) and, per slot, the cell of ``s e`` for each of them."""
    eg = cols.egrid
    cell = {(round(a, 9), round(b, 9)): i for i, (a, b) in enumerate(eg)}
    img = np.array([[cell[(round(a * sa, 9), round(b * sb, 9))] for a, b in eg]
                    for sa, sb in _E_SIGNS[S]])  # fmt: skip
    rep = np.flatnonzero(img.min(axis=0) == np.arange(eg.shape[0]))
    return rep, img[:, rep]


def pixel_cells(egrid: np.ndarray, jacobian: np.ndarray) -> tuple[np.ndarray, float]:
    """The sky-frame models seen through a Jacobian as pixel-frame models.

    The sky profile ``f(|S(e)^-1 u| / r)`` is ``f(|S(e)^-1 J^-1 x| / r)`` in the pixels:
    the pixel-frame model of ellipticity ``e'``, the exact map of the ellipse into the
    frame of ``J^-1 = d(W, N)/d(x, y)`` (:func:`pylensfit.skyframe.shear_to_pixel` of
    :func:`pylensfit.skyframe.jacobian_frame`), and size ``r sqrt|det J|``.

    Parameters
    ----------
    egrid : numpy.ndarray
        ``(n_e, 2)`` sky-frame ellipticities.
    jacobian : numpy.ndarray
        ``(2, 2)`` ``J = d(x, y)/d(W, N)``, pixels per arcsec.

    Returns
    -------
    e : numpy.ndarray
        ``(n_e, 2)`` pixel-frame ellipticities.
    scale : float
        Pixels per arcsec of the sizes, ``sqrt|det J|``.
    """
    J = np.asarray(jacobian, float)
    e1, e2 = shear_to_pixel(*np.asarray(egrid, float).T, jacobian_frame(np.linalg.inv(J)))
    return np.stack([e1, e2], axis=-1), float(np.sqrt(abs(np.linalg.det(J))))


def _wings(cols: _Columns, J: np.ndarray, n: int, imgs: np.ndarray):
    """Where ``cols.truncate``, the function ``(e0, e1) -> (n_rows, (e1 - e0) * per_e)``
    of the wrapped wings' transforms (:func:`pylensfit.models.wing_transforms`) of the
    cells ``e0 .. e1`` of ``cols`` seen through ``J`` on ``n``-pixel stamps, at the
    integer frequencies ``imgs`` (``(..., 2)``, rows in their order); else None."""
    if not cols.truncate:
        return None
    e_pix, scale = pixel_cells(cols.egrid, J)
    k = imgs.reshape(-1, 2)
    flip = k[:, 0] < 0
    jx, jy = np.where(flip, -k[:, 0], k[:, 0]), np.where(flip, -k[:, 1], k[:, 1]) % n
    runs = cols.runs if cols.model == "bulge+disc" else cols.runs[:1]

    def wings(e0: int, e1: int) -> np.ndarray:
        W = wing_transforms(e_pix[e0:e1, 0], e_pix[e0:e1, 1], cols.radii * scale,
                            cols.model, runs, n)  # fmt: skip
        return W[:, :, jy, jx].transpose(2, 0, 1).reshape(k.shape[0], -1)

    return wings


def _fold(cols: _Columns, J: np.ndarray, n: int, sel: np.ndarray, dtype,
          k_max: float = 0.0) -> _Fold:  # fmt: skip
    """The exposure's bank folded by the symmetries its Jacobian keeps."""
    H, S = lattice_symmetries(J)
    k0, imgs, size = _frequency_orbits(n, H, k_max)
    chi = _CHI[np.unique(_CHI[:, H], axis=0, return_index=True)[1]][:, H]
    stab = (imgs == k0[None]).all(-1) | (imgs == -k0[None]).all(-1)  # (n_h, n_k0)
    keep = tuple(np.flatnonzero(~(stab & (c[:, None] < 0)).any(axis=0)) for c in chi)
    rep, img = _model_orbits(cols, S)
    q = 2 * np.pi / n * imgs.reshape(-1, 2) @ np.asarray(J, dtype=float)  # J^T k per row
    per_e = cols.n_b * cols.n_sub
    members = (img.T[:, None, :] * per_e + np.arange(per_e)[None, :, None]).reshape(-1, H.size)
    members = np.vstack([members, np.r_[cols.n_cols - 1, np.full(H.size - 1, -1)]])
    mix = _mixed_columns(cols, rep.size)
    rcols = replace(cols, egrid=cols.egrid[rep])
    G, G2 = _fold_transforms(rcols, q, chi, keep, mix[0], dtype, _wings(rcols, J, n, imgs))
    return _Fold(idx=_sel_positions(n, sel, imgs), w=size / H.size**2, chi=chi, keep=keep,
                 G=G, G2=G2, members=np.ascontiguousarray(members, dtype=np.int64),
                 kind=(tuple(H), tuple(S)), mix=mix)  # fmt: skip


def _fold_transforms(cols: _Columns, q: np.ndarray, chi: np.ndarray, keep: tuple,
                     base: np.ndarray, dtype, wings=None) -> tuple[tuple, tuple]:  # fmt: skip
    """Per character ``chi[c]``, the folded transforms ``sum_h chi[c, h] G(h k0)`` of the
    base columns (``base >= 0``) and those of the squares of every column, on its
    ``keep[c]``, in ``dtype``; ``q`` the sky frequencies of the images ``h k0``
    (``(n_h * n_k0, 2)``), ``cols`` the representatives' grid; a chunk of e cells at a
    time."""
    n_h = chi.shape[1]
    G = tuple(np.empty((kp.size, int((base >= 0).sum())), dtype=dtype) for kp in keep)
    G2 = tuple(np.empty((kp.size, base.size), dtype=dtype) for kp in keep)
    per_e = cols.n_b * cols.n_sub
    for j0, blk in _bank_chunks(cols, q[:, 0], q[:, 1]):
        j1 = j0 + blk.shape[1]
        if wings is not None and j0 < cols.n_e * per_e:  # the models cut at the stamp's edge
            blk = blk - wings(j0 // per_e, j1 // per_e)
        on = np.flatnonzero(base[j0:j1] >= 0)
        b0 = base[j0 + on[0]] if on.size else 0
        blk = blk.reshape(n_h, -1, blk.shape[1])
        for c, kp, g, g2 in zip(chi, keep, G, G2, strict=True):
            Gk = blk[:, kp]
            g[:, b0 : b0 + on.size] = np.einsum("h,hkc->kc", c, Gk[..., on])
            g2[:, j0:j1] = np.einsum("h,hkc->kc", c, Gk * Gk)
    return G, G2


@dataclass(frozen=True)
class _Exposure:
    """One exposure's part of the block: its folded bank and its frequencies."""

    fold: _Fold
    qx: np.ndarray  # (n_f,) sky frequencies of the interior half-plane
    qy: np.ndarray
    coef: np.ndarray  # (n_f,) 1 / n^2
    herm: np.ndarray  # (n_f,) Hermitian weight: 2, or 1 on the ky axis
    sel: np.ndarray  # (n_f,) their flattened rfft2 indices


#: the last exposures' banks (an exposure's galaxies come in several calls or blocks)
_BANKS: dict = {}
_BANKS_KEPT = 8


def _exposure(cols: _Columns, J: np.ndarray, n: int, dtype, k_max: float = 0.0) -> _Exposure:
    """The bank of the exposure of Jacobian ``J`` on ``n x n`` stamps, the frequencies
    ``|k| <= k_max`` where it is positive (cached: the last ``_BANKS_KEPT``)."""
    key = (np.asarray(J, dtype=float).tobytes(), n, np.dtype(dtype).str, cols.model, cols.runs,
           cols.egrid.tobytes(), cols.radii.tobytes(), float(k_max), cols.truncate)  # fmt: skip
    hit = _BANKS.get(key)
    if hit is None:
        sel = _interior(n, k_max)
        qx, qy = (a.ravel()[sel] for a in sky_frequencies(J, n))
        _, _, w = rfft_frequencies(n)
        hit = _Exposure(fold=_fold(cols, J, n, sel, dtype, k_max), qx=qx, qy=qy,
                        coef=np.full(sel.size, 1.0 / n**2), herm=w.ravel()[sel],
                        sel=sel)  # fmt: skip
        keep_last(_BANKS, key, hit, _BANKS_KEPT, _CACHE_BYTES)
    return hit


@dataclass(frozen=True)
class _Inputs:
    """The checked inputs, broadcast to ``(K, n, ...)``."""

    stamps: np.ndarray  # (K, n, N, N)
    P: np.ndarray  # (K, n_psf, N, N // 2 + 1) PSF transforms, n_psf 1 or n
    sigma: np.ndarray  # (K, n)
    fscale: np.ndarray  # (K, n)
    usable: np.ndarray  # (K, n)
    cx: np.ndarray  # (K, n) catalogue positions in the stamps, pixels
    cy: np.ndarray
    J: np.ndarray  # (K, 2, 2)


def _psf_transforms(psf, K: int, n_gal: int, N: int) -> tuple[np.ndarray, np.ndarray]:
    """The PSF transforms, ``(K, 1 or n, N, N // 2 + 1)``, and which are finite: one per
    exposure where each exposure's galaxies are given the same image (the models' norms
    then one product per exposure, not per galaxy)."""
    psf = np.asarray(psf, dtype=float)
    if psf.ndim == 2:
        psf = np.broadcast_to(psf, (K, *psf.shape))
    if psf.ndim == 4 and n_gal > 0 and psf.shape[:2] == (K, n_gal) and np.array_equal(
            psf, np.broadcast_to(psf[:, :1], psf.shape)):  # fmt: skip
        psf = psf[:, 0]
    if psf.ndim not in (3, 4) or psf.shape[0] != K or (psf.ndim == 4 and psf.shape[1] != n_gal):
        raise ValueError(f"psf must be (s, s), (K, s, s) or (K, n, s, s) for K={K}, n={n_gal}; "
                         f"got {psf.shape}")  # fmt: skip
    flat = psf.reshape(-1, *psf.shape[-2:])
    ok = np.all(np.isfinite(flat), axis=(1, 2)) & (flat.sum(axis=(1, 2)) > 0)
    P = np.zeros((flat.shape[0], N, N // 2 + 1), dtype=complex)
    for i in np.flatnonzero(ok):  # one transform per distinct PSF image given
        P[i] = psf_transform(flat[i], N)
    shape = (K, 1 if psf.ndim == 3 else n_gal, N, N // 2 + 1)
    return P.reshape(shape), ok.reshape(shape[:2])


def _per(value, K: int, n: int, name: str) -> np.ndarray:
    """A scalar, ``(K,)`` or ``(K, n)`` value as ``(K, n)`` floats."""
    a = np.asarray(value, dtype=float)
    if a.ndim == 1 and a.size == K:
        a = a[:, None]
    try:
        return np.array(np.broadcast_to(a, (K, n)))
    except ValueError:
        raise ValueError(f"{name} must be a scalar, (K,) or (K, n) = ({K}, {n}), "
                         f"got shape {a.shape}") from None


def _inputs(stamps, psf, noise_sigma, jacobian, flux_scale, usable, centres) -> _Inputs:
    stamps = np.asarray(stamps, dtype=float)
    if stamps.ndim == 3:
        stamps = stamps[None]
    if stamps.ndim != 4 or stamps.shape[2] != stamps.shape[3]:
        raise ValueError(f"stamps must be (K, n, N, N), got {stamps.shape}")
    K, n_gal, N = stamps.shape[:3]
    J = np.asarray(jacobian, dtype=float).reshape(-1, 2, 2)
    if J.shape[0] != K:
        raise ValueError(f"jacobian must be (K, 2, 2) for K={K}, got {np.shape(jacobian)}")
    P, psf_ok = _psf_transforms(psf, K, n_gal, N)
    sigma = _per(noise_sigma, K, n_gal, "noise_sigma")
    fscale = _per(flux_scale, K, n_gal, "flux_scale")
    use = np.ones((K, n_gal), bool) if usable is None else np.array(
        np.broadcast_to(np.asarray(usable, dtype=bool), (K, n_gal)))  # fmt: skip
    if centres is None:
        cx = cy = np.full((K, n_gal), float(N // 2))
    else:
        cx, cy = (_per(c, K, n_gal, "centres") for c in centres)
    det = np.linalg.det(J)
    use &= (np.isfinite(stamps).all(axis=(2, 3)) & np.isfinite(sigma) & (sigma > 0)
            & np.isfinite(fscale) & (fscale > 0) & np.isfinite(cx) & np.isfinite(cy)
            & psf_ok & (np.isfinite(det) & (det != 0))[:, None])  # fmt: skip
    stamps = np.where(use[:, :, None, None], np.nan_to_num(stamps), 0.0)
    return _Inputs(stamps=stamps, P=P, sigma=np.where(use, sigma, 1.0),
                   fscale=np.where(use, fscale, 0.0), usable=use, cx=np.where(use, cx, 0.0),
                   cy=np.where(use, cy, 0.0), J=J)  # fmt: skip


@dataclass(frozen=True)
class _Block:
    """One block's data rows, per exposure: ``D'`` at the catalogue position and the
    norm weights."""

    D: list  # per exposure, (m, n_f) complex: f D conj(P) coef / sigma^2
    W: list  # per exposure, (1 or m, n_f) real: |P|^2 coef, one row per PSF
    w2: list  # per exposure, (m,) f^2 / sigma^2


def _block(inp: _Inputs, exps: list[_Exposure], sl: slice) -> _Block:
    N = inp.stamps.shape[-1]
    kx, ky, _ = rfft_frequencies(N)
    D, W, w2 = [], [], []
    for k, ex in enumerate(exps):
        ph = np.exp(1j * (kx.ravel()[ex.sel][None] * inp.cx[k, sl, None]
                          + ky.ravel()[ex.sel][None] * inp.cy[k, sl, None]))  # fmt: skip
        F = np.fft.rfft2(inp.stamps[k, sl]).reshape(-1, N * (N // 2 + 1))[:, ex.sel]
        P = inp.P[k].reshape(inp.P.shape[1], -1)[:, ex.sel]
        P = P[sl] if P.shape[0] > 1 else P
        wt = inp.fscale[k, sl] / inp.sigma[k, sl] ** 2
        D.append(F * ph * np.conj(P) * (ex.coef * wt[:, None]))
        W.append(np.abs(P) ** 2 * ex.coef)
        w2.append(wt * inp.fscale[k, sl])
    return _Block(D=D, W=W, w2=w2)


def _rows(D: np.ndarray, ex: _Exposure, xc: np.ndarray, yc: np.ndarray) -> np.ndarray:
    """``(6, m, n_f)``: the rows of ``H``, its gradient and Hessian at the origin
    ``(xc, yc)`` (sky offsets, arcsec)."""
    Dp = D * np.exp(1j * (ex.qx[None] * xc[:, None] + ex.qy[None] * yc[:, None]))
    r, i = Dp.real, Dp.imag
    qx, qy = ex.qx, ex.qy
    return np.stack([r, -qx * i, -qy * i, -qx * qx * r, -qx * qy * r, -qy * qy * r])


def _folded(folds: list[_Fold], Rs: list[np.ndarray], Gs: list[tuple], out: np.ndarray) -> None:
    """The products of the rows ``Rs`` (each ``(rows, n_f)``, on its exposure's
    frequencies) with the folded transforms ``Gs`` (one per character), ``sum_e (fhat_chi
    R_e) Ghat_chi,e``, summed over exposures of one kind (``folds``) as one matrix
    product over all of their frequencies, into ``out`` (``(n_chi, rows, n_fc)``)."""
    for c in range(len(Gs[0])):
        F = np.concatenate([np.einsum("h,rhk->rk", f.chi[c], R[:, f.idx[:, f.keep[c]]])
                            * f.w[f.keep[c]] for f, R in zip(folds, Rs, strict=True)],
                           axis=1)  # fmt: skip
        G = Gs[0][c] if len(Gs) == 1 else np.concatenate([g[c] for g in Gs])
        np.matmul(F.astype(G.dtype), G, out=out[c])


def _places(members: np.ndarray, c: int) -> tuple[np.ndarray, np.ndarray]:
    """The folded column and the slot of each of the ``c`` models of ``members``."""
    f, h = np.nonzero(members >= 0)
    col, slot = np.zeros(c, dtype=np.int64), np.zeros(c, dtype=np.int64)
    col[members[f, h]] = f
    slot[members[f, h]] = h
    return col, slot


def _norms(blk: _Block, exps: list[_Exposure], parts: list[tuple], c: int) -> Norms:
    """The models' norms per exposure (:class:`~pylensfit.joint_nb.Norms`: ``Q`` and the
    expected Hessian per unit weight, one product per exposure and PSF, unfolded)."""
    S = np.zeros((len(exps), 4 * blk.W[0].shape[0], c))
    for k, (W, ex, (_, G2, members, _)) in enumerate(zip(blk.W, exps, parts, strict=True)):
        q = np.stack([W, -W * ex.qx * ex.qx, -W * ex.qx * ex.qy, -W * ex.qy * ex.qy])
        q = q.reshape(-1, q.shape[-1])
        Sf = np.empty((len(G2), q.shape[0], G2[0].shape[1]), dtype=G2[0].dtype)
        _folded([ex.fold], [q], [G2], Sf)
        unfold(Sf, ex.fold.chi, members, S[k])
    return Norms(S.reshape(len(exps), 4, -1, c), np.stack(blk.w2))


def _products(blk: _Block, exps: list[_Exposure], xc, yc, cols=None) -> tuple[Folds, Norms]:
    """The products of ``H`` and its derivatives with the exposures' folded banks
    (:class:`~pylensfit.joint_nb.Folds`, the rows ``q * m + g``), summed over the
    exposures of each kind (the same folded columns), and the models' norms per
    exposure (:func:`_norms`) (``cols``: those models only, a set closed under the
    symmetries)."""
    m = xc.size
    n_cols = exps[0].fold.members.max() + 1
    c = n_cols if cols is None else cols.size
    parts = [ex.fold.columns(cols, n_cols) for ex in exps]
    kinds = list(dict.fromkeys(ex.fold.kind for ex in exps))
    groups = [[k for k, ex in enumerate(exps) if ex.fold.kind == kind] for kind in kinds]
    sizes = np.array([[len(parts[g[0]][0]), parts[g[0]][0][0].shape[1]] for g in groups])
    n_k = len(groups)
    off = np.zeros((n_k, 4), dtype=np.int64)
    off[:, :] = np.r_[0, np.cumsum(sizes.prod(1) * 6 * m)[:-1]][:, None]
    off += np.arange(4)[None, :] * sizes[:, 1:] * 6 * m
    P = np.empty(int((sizes.prod(1) * 6 * m).sum()), dtype=parts[0][0][0].dtype)
    sgn, col = np.zeros((n_k, 4, c)), np.zeros((n_k, 2, c), dtype=np.int64)
    frac = np.zeros((n_k, c))
    for i, g in enumerate(groups):
        (n_chi, n_fc), fold = sizes[i], exps[g[0]].fold
        view = P[off[i, 0] : off[i, 0] + n_chi * 6 * m * n_fc].reshape(n_chi, 6 * m, n_fc)
        Rs = [_rows(blk.D[k], exps[k], xc, yc).reshape(6 * m, -1) for k in g]
        _folded([exps[k].fold for k in g], Rs, [parts[k][0] for k in g], view)
        fcol, slot = _places(parts[g[0]][2], c)
        a, b, f = parts[g[0]][3]
        col[i, 0], col[i, 1], frac[i] = a[fcol], b[fcol], f[fcol]
        sgn[i, :n_chi] = fold.chi[:, slot]
    folds = Folds(P, off, sizes[:, 1].copy(), sizes[:, 0].copy(), sgn, col, frac)
    return folds, _norms(blk, exps, parts, c)


def _laplace(folds: Folds, norms: Norms, x0, y0, sums: Sums, cols: _Columns, full, cfg: Config,
             scale: float) -> Outputs:  # fmt: skip
    """``ln L(e)``, ``ln L_b(e)`` per run, ``ln L(r)`` per group of e cells and the most
    likely model's ``H*``, ``X*`` (from the origin; arcsec) of the block, the models
    (``full``: their places in the grid of ``sums``) marginalised over the amplitude
    (``cols.amp``) and the position (module docstring) and summed over r with ``sums``
    (:func:`pylensfit.joint_nb.laplace_grid`: the single-exposure fit's Newton step,
    expected-Hessian fallback, amplitude integral, position prior and sum over r, on the
    sums over the exposures). ``x0, y0``: the catalogue position from the origin,
    arcsec."""
    m = np.asarray(x0).size
    n_e, n_r = sums.e_w.size, sums.node_w.size
    out = Outputs.empty(m, n_e, n_r // sums.n_sub, int(sums.e_grp.max()) + 1, n_r)
    out.h[:] = out.x[:] = out.y[:] = np.nan
    gals = Galaxies(np.ones(m), np.ascontiguousarray(x0, dtype=float),
                    np.ascontiguousarray(y0, dtype=float))  # fmt: skip
    pos = Laplace((cfg.position_prior_sigma * scale) ** 2, cfg.max_newton_step * scale, False)
    models = (cols.uniform(), np.ascontiguousarray(full, dtype=np.int64))
    laplace_grid(folds, norms, gals, sums, cols.amp, pos, models, out)
    return out


def _round_centre(inp: _Inputs, blk: _Block, exps: list[_Exposure], sl: slice, cfg: Config,
                  scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The peak of the joint cross-correlation with a round exponential (``centring_scale``
    reference pixels): each exposure's integer-pixel peak within ``max_offset`` taken to
    the sky and averaged with its weight, then Newton steps on the joint series."""
    m = sl.stop - sl.start
    N = inp.stamps.shape[-1]
    num, den = np.zeros((2, m)), np.zeros(m)
    off = (np.arange(N) + N // 2) % N - N // 2
    rad = max(cfg.max_offset, 0.75)
    near = off[None, :] ** 2 + off[:, None] ** 2 <= rad * rad
    refs = []
    for k, ex in enumerate(exps):
        qx, qy = sky_frequencies(inp.J[k], N)
        ref = fourier_profile(np.hypot(qx, qy) * cfg.centring_scale * scale, "exponential")
        refs.append(ref.ravel()[ex.sel] * ex.herm)  # the half-plane's sums: the plane's
        full = np.zeros((m, N * (N // 2 + 1)), dtype=complex)
        full[:, ex.sel] = blk.D[k] / ex.coef
        cc = np.fft.irfft2(full.reshape(m, N, -1) * ref, s=(N, N))
        cc = np.where(near, cc, -np.inf).reshape(m, -1)
        iy, ix = np.unravel_index(cc.argmax(axis=1), (N, N))
        v = np.maximum(cc.max(axis=1), 0.0)
        sky = np.linalg.solve(inp.J[k], np.stack([off[ix], off[iy]]))  # pixels to arcsec
        num += v * sky
        den += v
    with np.errstate(invalid="ignore", divide="ignore"):
        xc, yc = np.where(den > 0, num / den, 0.0)
    for _ in range(3):
        h = sum((_rows(D, ex, xc, yc) * r).sum(-1) for D, ex, r in zip(blk.D, exps, refs,
                                                                      strict=True))  # fmt: skip
        det = h[3] * h[5] - h[4] ** 2
        with np.errstate(invalid="ignore", divide="ignore"):
            sx = np.where(det > 0, (h[4] * h[2] - h[5] * h[1]) / det, 0.0)
            sy = np.where(det > 0, (h[4] * h[1] - h[3] * h[2]) / det, 0.0)
        step_ok = (h[3] < 0) & (det > 0) & (np.hypot(sx, sy) < scale)
        xc, yc = xc + np.where(step_ok, sx, 0.0), yc + np.where(step_ok, sy, 0.0)
    return xc, yc, ~(den > 0)


def _coarse_columns(cols: _Columns, e_step: float) -> tuple[np.ndarray, Sums]:
    """The centring pass's models, the single fit's: the e cells at every other lattice
    step in both components, every 5th size from the third, the point source; and the
    (unused but for their shape) weights of their sums over r."""
    lat = np.rint(np.abs(cols.egrid) / e_step - 0.5).astype(int)
    ie = np.flatnonzero((lat % 2 == 0).all(axis=1))
    n_r = cols.n_b * cols.n_sub
    ir = np.arange(min(2, n_r - 1), n_r, 5)
    sums = Sums(np.ones(ir.size), 1.0, np.zeros(1), np.full(ie.size, 1.0 / ie.size),
                np.zeros(ie.size, dtype=np.int64), ir.size)  # fmt: skip
    return np.append((ie[:, None] * n_r + ir[None, :]).ravel(), cols.n_cols - 1), sums


def _fit_block(inp: _Inputs, exps: list[_Exposure], cols: _Columns, cfg: Config,
               scale: float, sl: slice) -> dict:  # fmt: skip
    """Every model for the block's galaxies: centring, the coarse pass that moves the
    origin to the best round model's peak, then the whole grid."""
    blk = _block(inp, exps, sl)
    xc, yc, no_peak = _round_centre(inp, blk, exps, sl, cfg, scale)
    cc, sums_c = _coarse_columns(cols, cfg.e_step)
    out = _laplace(*_products(blk, exps, xc, yc, cc), -xc, -yc, sums_c, cols,
                   np.arange(cc.size), cfg, scale)  # fmt: skip
    xc = xc + np.nan_to_num(out.x)
    yc = yc + np.nan_to_num(out.y)
    kept = cols.kept()  # the sizes of weight 0 in no sum: their models not evaluated
    folds, norms = _products(blk, exps, xc, yc, kept)
    full = np.arange(cols.n_cols) if kept is None else kept
    out = _laplace(folds, norms, -xc, -yc, cols.sums(), cols, full, cfg, scale)
    g = np.arange(out.best.size)
    p = g if norms.S.shape[2] > 1 else 0
    Q = (norms.w2 * norms.S[:, 0, p, out.best].astype(np.float64)).sum(axis=0)
    return {"lnle": out.lnle, "lnlb": out.lnlb, "star": out.lnlr[:, 0, -1] + np.log(cols.w_star),
            "best": full[out.best], "no_peak": no_peak, "h": out.h, "Q": Q, "x": xc + out.x,
            "y": yc + out.y, "lnlr": out.lnlr}  # fmt: skip


def fit_exposures(
    stamps: np.ndarray,
    psf: np.ndarray,
    noise_sigma,
    jacobian: np.ndarray,
    *,
    flux_scale=1.0,
    usable: np.ndarray | None = None,
    centres: tuple[np.ndarray, np.ndarray] | None = None,
    config: Config | None = None,
    pixel_scale: float | None = None,
    size_prior: SizePrior | None = None,
    lnL_r_groups: np.ndarray | None = None,
) -> JointFits:
    """The likelihood ``L(e)`` of each galaxy from all of its exposures together.

    One sky-frame (e, r) grid serves every exposure (its models at ``J_k^T k``); flux and
    position are shared and marginalised once over the sum of the exposures (module
    docstring). One bank per Jacobian (folded, :func:`lattice_symmetries`; the last eight
    kept), the products by blocks of ``config.block_size`` galaxies.

    Parameters
    ----------
    stamps : numpy.ndarray
        ``(K, n, N, N)`` background-subtracted stamps, counts, indexed ``[exposure,
        galaxy, y, x]`` (``(n, N, N)``: one exposure).
    psf : numpy.ndarray
        The PSF images including the pixel response, centred on element ``[s//2, s//2]``:
        ``(s, s)`` for all, ``(K, s, s)`` one per exposure or ``(K, n, s, s)`` one per
        galaxy and exposure (any normalisation; where each exposure's images are all the
        same, read as one per exposure).
    noise_sigma : float or array_like
        Per-pixel noise, counts: a scalar, ``(K,)`` or ``(K, n)``.
    jacobian : numpy.ndarray
        ``(K, 2, 2)`` local WCS Jacobian ``J = d(x, y)/d(W, N)`` of each exposure,
        pixels per arcsec (:func:`pylensfit.exposures.local_jacobian`), one for the
        galaxies of the call.
    flux_scale : float or array_like
        Counts per unit of the common flux, scalar, ``(K,)`` or ``(K, n)``.
    usable : numpy.ndarray, optional
        ``(K, n)`` bool: the exposures that hold each galaxy (default all). Exposures with
        non-finite pixels, a bad noise, flux scale or PSF drop out as well.
    centres : tuple of numpy.ndarray, optional
        ``(x, y)``, each ``(K, n)`` (or ``(K,)``), the catalogue position in each stamp,
        0-based pixels (default the stamp's element ``[N//2, N//2]``): the centre of
        the position prior, mapped to the common sky position.
    config : Config, optional
        Grid, model and marginalisation settings (``e_step``, ``e_max``, the size grid,
        ``model``, ``n_bulge_fractions``, ``position_prior_sigma``, ``max_offset``,
        ``centring_scale``, ``max_newton_step``, ``block_size``, ``dtype``, the
        amplitude prior and flux bounds in the common flux unit, ``k_max`` of a stamp
        tier, ``truncate_models``: the wrapped wings of each cell's pixel-frame model,
        :func:`pixel_cells`, subtracted), lengths in reference pixels of ``pixel_scale``
        arcsec. The position expansion is of second order (``cubic_snr = 0``).
    pixel_scale : float, optional
        Arcsec per reference pixel (default: the median of ``1 / sqrt|det J_k|``).
    size_prior : pylensfit.prior.SizePrior, optional
        Prior of the half-light radius (reference pixels) in the sum over r, as
        :func:`pylensfit.likelihood.fit_stamps`'s (default flat; the models of sizes of
        weight 0 are not evaluated).
    lnL_r_groups : numpy.ndarray, optional
        ``(n_e,)`` integer group of each e cell: keep ``L(r)`` per group as well
        (``JointFits.lnL_r_grouped``; :func:`pylensfit.likelihood.e_annuli`).

    Returns
    -------
    JointFits
        One row per galaxy; ``n_exposures`` says how many exposures each used.

    Notes
    -----
    The stamps are fitted whole (``config.stamp_size`` is not read). The matrix products
    run on one BLAS thread, as :func:`pylensfit.likelihood.fit_stamps`'s (the result does
    not depend on the thread count); the Laplace terms on numba's, one galaxy each.
    """
    cfg = config if config is not None else Config()
    inp = _inputs(stamps, psf, noise_sigma, jacobian, flux_scale, usable, centres)
    scale = float(pixel_scale if pixel_scale is not None
                  else np.median(1.0 / np.sqrt(np.abs(np.linalg.det(inp.J)))))  # fmt: skip
    return _fit(inp, _columns(cfg, scale, size_prior, lnL_r_groups), cfg, scale)


def _fit(inp: _Inputs, cols: _Columns, cfg: Config, scale: float) -> JointFits:
    """:func:`fit_exposures` of the checked inputs, block by block, on one BLAS thread."""
    K, n_gal, N = inp.stamps.shape[:3]
    good = np.isfinite(np.linalg.det(inp.J)) & (np.linalg.det(inp.J) != 0)
    eye = np.eye(2) / scale
    exps = [_exposure(cols, inp.J[k] if good[k] else eye, N, np.dtype(cfg.dtype), cfg.k_max)
            for k in range(K)]
    with threadpool_limits(limits=1, user_api="blas"):  # as fit_stamps: the same bits anywhere
        parts = [_fit_block(inp, exps, cols, cfg, scale, slice(s, min(s + cfg.block_size,
                                                                     n_gal)))
                 for s in range(0, n_gal, cfg.block_size)]  # fmt: skip
    return _assemble(parts, inp, cols, cfg, scale)


def _size_rows(lnlr: np.ndarray, peak: np.ndarray, dead: np.ndarray, cols: _Columns,
               cfg: Config, scale: float) -> dict:  # fmt: skip
    """``ln L(r)`` (all e cells, and per group where there are several) shifted like ``ln
    L(e)``, the size of its maximum (arcsec) and the point sources, as the single fit's
    (:func:`pylensfit.likelihood.fit_stamps`)."""
    n_r = cols.n_b * cols.n_sub
    grouped = None
    total = lnlr[:, 0].copy()
    if lnlr.shape[1] > 1:
        total[:, :n_r] = logsumexp_groups(lnlr[:, :, :n_r])
        with np.errstate(invalid="ignore", over="ignore"):
            grouped = (lnlr - peak[:, None, None]).astype(np.float32)
        grouped[dead] = np.nan
    with np.errstate(invalid="ignore", over="ignore"):
        lnL_r = (total - peak[:, None]).astype(np.float32)
    lnL_r[dead] = np.nan
    radii = np.tile(cols.radii, cols.n_b)
    ir = np.where(dead, n_r, np.nan_to_num(total, nan=-np.inf).argmax(axis=1))
    r = np.append(radii, 0.0)[ir]
    is_star = ((ir == n_r) | (r < cfg.point_source_size * scale)) & ~dead
    return {"lnL_r": lnL_r, "lnL_r_grouped": grouped, "radii": radii,
            "r_marginal": np.where(dead, np.nan, r), "is_star": is_star}  # fmt: skip


def _assemble(parts: list[dict], inp: _Inputs, cols: _Columns, cfg: Config,
              scale: float) -> JointFits:  # fmt: skip
    """The :class:`JointFits` of the blocks' results."""
    cat = {k: np.concatenate([p[k] for p in parts]) if parts else np.zeros(0)
           for k in ("lnle", "lnlb", "star", "best", "no_peak", "h", "Q", "x", "y")}  # fmt: skip
    n_gal = inp.stamps.shape[1]
    n_r = cols.n_b * cols.n_sub
    lnlr = (np.concatenate([p["lnlr"] for p in parts]) if parts
            else np.zeros((0, cols.n_grp, n_r + 1)))  # fmt: skip
    lnle = cat["lnle"].reshape(n_gal, cols.n_e)
    n_exp = inp.usable.sum(axis=0)
    flags = np.zeros(n_gal, dtype=np.int32)
    flags[n_exp == 0] |= _flags.flag_value("NOT_MEASURED")
    flags[cat["no_peak"].astype(bool) & (n_exp > 0)] |= _flags.flag_value("NO_PEAK")
    with np.errstate(invalid="ignore", over="ignore"):
        peak = lnle.max(axis=1) if n_gal else np.zeros(0)
        failed = ~np.isfinite(lnle).all(axis=1) & (n_exp > 0)
    flags[failed] |= _flags.flag_value("FIT_FAILED")
    dead = (n_exp == 0) | failed
    nan = np.where(dead, np.nan, 1.0)
    lnL = np.where(dead[:, None], np.nan, lnle - peak[:, None]).astype(np.float32)
    best = cat["best"].astype(np.int64)
    per_e = cols.n_b * cols.n_sub
    star = best == cols.n_cols - 1
    ie = np.where(star, 0, best // per_e)
    r = np.where(star, 0.0, cols.radii[best % cols.n_sub])
    e = np.where(star[:, None], 0.0, cols.egrid[ie])
    multi = cols.n_b > 1
    fracs = np.array([f for f, _ in cols.runs]) if multi else np.array([cfg.bulge_fraction])
    lnlb = cat["lnlb"].reshape(n_gal, cols.n_e, cols.n_b)
    return JointFits(
        egrid=cols.egrid.copy(), lnL=lnL, lnL_peak=peak * nan, n_exposures=n_exp,
        r_best=r * nan, flux=cat["h"] / cat["Q"] * nan, x=cat["x"] * nan, y=cat["y"] * nan,
        snr=cat["h"] / np.sqrt(cat["Q"]) * nan, e1_best=e[:, 0] * nan, e2_best=e[:, 1] * nan,
        flags=flags,
        lnL_bulge=(np.moveaxis(lnlb - peak[:, None, None], 2, 1) * nan[:, None, None]
                   ).astype(np.float32) if multi else None,
        lnL_star=(cat["star"] - peak) * nan if multi else None,
        bulge_fractions=fracs if multi else None,
        pixel_scale=scale,
        meta={"model": cfg.model, "e_step": cfg.e_step, "r_step": cfg.r_step * scale},
        bulge_best=np.where(star, np.nan, fracs[(best % per_e) // cols.n_sub % fracs.size]) * nan,
        exposures_used=(inp.usable.astype(np.int64)
                        << np.arange(inp.usable.shape[0], dtype=np.int64)[:, None]).sum(axis=0),
        **_size_rows(lnlr, peak, dead, cols, cfg, scale),
    )  # fmt: skip


def fit_views(views: Sequence[ExposureStamps], *, config: Config | None = None,
              pixel_scale: float | None = None, size_prior: SizePrior | None = None,
              lnL_r_groups: np.ndarray | None = None) -> JointFits:  # fmt: skip
    """:func:`fit_exposures` of the galaxies' views cut from their exposures.

    Parameters
    ----------
    views : sequence of pylensfit.exposures.ExposureStamps
        One per exposure (:func:`pylensfit.exposures.cut_exposures`), each with its PSF
        at the galaxies; galaxy ``i`` is element ``i`` of each.
    config : Config, optional
        As :func:`fit_exposures`.
    pixel_scale, size_prior, lnL_r_groups : optional
        As :func:`fit_exposures`.

    Returns
    -------
    JointFits
        The exposures flagged for a galaxy (:attr:`ExposureStamps.usable`) leave its fit.
        Each exposure's Jacobian is the median of its galaxies' (the call's galaxies
        should lie within a region where it varies little: 1e-3 of it changes a model's
        ellipticity by about 1e-3).
    """
    if any(v.psf is None for v in views):
        raise ValueError("fit_views needs each exposure's PSF at the galaxies (ExposureStamps.psf)")
    a = ViewArrays.of(views)
    return fit_exposures(a.stamps, a.psf, a.noise_sigma, a.jacobian, flux_scale=a.flux_scale,
                         usable=a.usable, centres=a.centres, config=config,
                         pixel_scale=pixel_scale, size_prior=size_prior,
                         lnL_r_groups=lnL_r_groups)  # fmt: skip


@dataclass(frozen=True)
class ViewArrays:
    """The galaxies' views in ``K`` exposures stacked as :func:`fit_exposures`' arguments.

    Attributes
    ----------
    stamps : numpy.ndarray
        ``(K, n, N, N)``.
    psf : numpy.ndarray
        ``(K, n, s, s)`` each galaxy's PSF in each exposure.
    noise_sigma, flux_scale : numpy.ndarray
        ``(K, n)`` and ``(K,)``.
    jacobian : numpy.ndarray
        ``(K, 2, 2)`` each exposure's Jacobian, the median of its galaxies'.
    usable : numpy.ndarray
        ``(K, n)`` bool.
    centres : tuple of numpy.ndarray
        ``(x, y)``, each ``(K, n)``, the catalogue positions in the stamps.
    """

    stamps: np.ndarray
    psf: np.ndarray
    noise_sigma: np.ndarray
    jacobian: np.ndarray
    flux_scale: np.ndarray
    usable: np.ndarray
    centres: tuple[np.ndarray, np.ndarray]

    @classmethod
    def of(cls, views: Sequence[ExposureStamps]) -> ViewArrays:
        """The arrays of ``views`` (:func:`fit_views`)."""
        return cls(stamps=np.stack([v.stamps for v in views]),
                   psf=np.stack([v.psf for v in views]),
                   noise_sigma=np.stack([v.noise_sigma for v in views]),
                   jacobian=np.stack([np.nanmedian(v.jacobian, axis=0) for v in views]),
                   flux_scale=np.array([v.flux_scale for v in views]),
                   usable=np.stack([v.usable for v in views]),
                   centres=(np.stack([v.centres[0] for v in views]),
                            np.stack([v.centres[1] for v in views])))  # fmt: skip

    def take(self, rows: np.ndarray) -> ViewArrays:
        """The galaxies ``rows`` alone."""
        return ViewArrays(stamps=self.stamps[:, rows], psf=self.psf[:, rows],
                          noise_sigma=self.noise_sigma[:, rows], jacobian=self.jacobian,
                          flux_scale=self.flux_scale, usable=self.usable[:, rows],
                          centres=(self.centres[0][:, rows], self.centres[1][:, rows]))  # fmt: skip
