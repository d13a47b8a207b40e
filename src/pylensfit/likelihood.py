"""The likelihood of every galaxy on the (e1, e2, r) grid, summed over r.

Miller et al. (2007, arXiv:0708.2340), section 3, and Kitching et al. (2008,
arXiv:0802.1528), section 2.2: the likelihood marginalised over the amplitude and over
the position (docs: method, eq-amplitude, eq-flux-prior, eq-position, eq-matrix-products
and eq-radius).

For a stamp ``d`` with constant noise ``sigma`` and a model ``A m(x - X)`` of unit flux:

* **amplitude** (uniform prior, ``A > 0``)::

      ln L(e, r, X) = h^2 / (2 sigma^2 S) + ln Phi(h / (sigma sqrt S)) - ln(S) / 2

  with ``h(X) = sum_x d(x) m(x - X)`` the cross-correlation and ``S = sum m^2``
  (Kitching et al. 2008, section 2.2; docs: method, eq-amplitude; the ``Phi`` term is
  the positive-flux prior, which keeps a negative cross-correlation from being read as a
  bright negative galaxy);
* **position**: the data are re-centred once per galaxy on the peak of their
  cross-correlation with a round model (found by FFT and refined by a parabola, then
  applied exactly by a Fourier phase ramp). ``h``, its gradient and Hessian at the
  re-centred origin are sums over frequencies, which for all galaxies and all models are
  six matrix products (folded by the symmetries of the square pixel grid into four
  products over an octant of frequencies for each orbit ``(+-e1, +-e2)`` of four models,
  a quarter of the operations: :class:`_FoldedBank`; Nyquist frequencies are left out,
  :func:`_interior`). One Newton step gives the peak ``X*``, ``h*``, and the Laplace
  approximation of the integral over ``X`` with a Gaussian prior of width ``b`` about
  the catalogue position ``X0`` is the 2-D form of the paper's likelihood marginalised
  over the position (section 2.2; docs: method, eq-position)::

      ln L(e, r) = l* - ln det(I + b^2 F) / 2 - (X* - X0)^T (F^-1 + b^2 I)^-1 (X* - X0) / 2

  with ``F = -(dl/dh) Hess h`` the curvature of ``l = ln L(e, r, X)`` in position;
* **size**: ``L(e) = int L(e, r) dr`` over ``r = r_min ... r_max`` (uniform prior), by
  the trapezoid rule on the size grid (:func:`pylensfit.models.radius_weights`);
  ``r = 0`` is the point source. An object whose most likely ``r`` (marginal over
  the e grid) is 0 is flagged as a star.
"""

from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import dataclass, field, fields, replace
from functools import lru_cache
from pathlib import Path

import numba
import numpy as np
from astropy.io import fits
from astropy.table import Table
from threadpoolctl import ThreadpoolController

from . import flags as _flags
from ._kernels_nb import AMP_UNIFORM, amplitude_table, laplace_grid, laplace_grid_tab
from ._util import atomic_write, newton_peak, per_object
from .config import Config
from .grid import ellipticity_grid, refine_lnL
from .models import (
    ModelBank,
    fourier_profile,
    half_light_radius,
    in_disc,
    model_bank,
    rfft_frequencies,
)
from .prior import Prior, SizePrior
from .psf import psf_transform

__all__ = ["StampFits", "blend_fits", "e_annuli", "fit_stamps"]


def _fork_safe_threading() -> None:
    """Have numba run the parallel kernels on a fork-safe threading layer.

    Where TBB is absent numba prefers GNU OpenMP, and a process that has run a parallel
    kernel on it cannot fork: each child of a ``multiprocessing`` fork pool that runs one
    is killed ("fork() called from a process already using GNU OpenMP"), and the pool
    starts another for ever. numba's ``forksafe`` is TBB where installed, else its work
    queue, which :mod:`pylensfit._kernels_nb` launches one kernel at a time (it is not
    thread-safe). :func:`fit_stamps` of 200 32-pixel stamps on two threads of a two-core
    machine already busy: work queue 0.26 s, TBB 0.25 s, GNU OpenMP 0.55 s (whose threads
    spin while they wait; 0.23 s with ``OMP_WAIT_POLICY=passive``).
    A layer chosen with ``NUMBA_THREADING_LAYER`` or ``numba.config`` is kept, and so is
    one that already runs (numba starts its layer at the first parallel kernel).
    """
    if (numba.config.THREADING_LAYER == "default"
            and not os.environ.get("NUMBA_THREADING_LAYER")
            and not os.environ.get("NUMBA_THREADING_LAYER_PRIORITY")):  # fmt: skip
        numba.config.THREADING_LAYER = "forksafe"


_fork_safe_threading()


@dataclass
class StampFits:
    """Result of :func:`fit_stamps`: one row per stamp.

    Attributes
    ----------
    egrid : numpy.ndarray
        ``(n_e, 2)`` ellipticity cell centres.
    lnL : numpy.ndarray
        ``(n, n_e)`` float32 ``ln L(e)`` summed over r, each row shifted so that its
        maximum is 0; NaN rows for stamps that could not be fitted (see ``flags``).
    lnL_peak : numpy.ndarray
        ``(n,)`` the shift removed from each row (the maximum of the unnormalised
        ``ln L(e)``, up to a constant common to all stamps of one noise level and stamp
        size).
    r_best : numpy.ndarray
        Most likely model size in pixels (marginal over the e grid); 0 for stars.
    flux : numpy.ndarray
        Amplitude of the most likely model (data units, total flux of the model).
    x, y : numpy.ndarray
        Fitted centre of the most likely model, in the pixels (0-based) of the stamps
        given to :func:`fit_stamps`.
    snr : numpy.ndarray
        Matched-filter signal-to-noise ``h* / (sigma sqrt S)`` of the most likely model.
    is_star : numpy.ndarray
        Boolean, most likely size is 0 or below ``Config.point_source_size``.
    flags : numpy.ndarray
        Bit mask, see :data:`pylensfit.flags.FLAGS`.
    e1_best, e2_best : numpy.ndarray
        Ellipticity of the most likely model (the maximum of ``L(e, r)``).
    lnL_bulge : numpy.ndarray or None
        With the bulge fraction marginalised (``n_bulge_fractions = n_b > 1``): ``(n, n_b,
        n_e)`` float32 ``ln L_k(e)`` of each fraction alone (sizes > 0, the sum over r
        weighted by the fraction's half-light radius per unit r relative to the pure
        disc's, ``ModelBank.run_weights``), shifted like ``lnL``. ``lnL`` is
        ``ln(sum_k L_k / n_b + L_star)``, a uniform prior over the fractions;
        :func:`pylensfit.prior.mix_bulge_fractions` gives it for any other.
    lnL_star : numpy.ndarray or None
        ``(n,)`` the point source's ``ln L`` (weighted as the ``r = 0`` end of the size
        integral), shifted like ``lnL``; ``None`` with one fraction.
    bulge_fractions : numpy.ndarray or None
        ``(n_b,)`` the bulge fraction of each run of ``lnL_bulge`` (with two bulge sizes,
        ``Config.bulge_size_ratio2``, the fractions above 0 twice).
    bulge_sizes : numpy.ndarray or None
        ``(n_b,)`` the bulge size (half-light radius / disc scale length) of each run,
        where there are two (``None``: one, the configuration's).
    bulge_best : numpy.ndarray or None
        Bulge fraction of the most likely model (the configuration's fixed fraction for
        a ``"bulge+disc"`` bank of one fraction; NaN for stars and failed fits). Not
        written by :meth:`write`.
    lnL_r : numpy.ndarray or None
        ``(n, n_r + 1)`` float32 ``ln`` of the likelihood of each size of the model
        bank, ``L(r) = sum_e P(e) L(e, r)`` with the ellipticity prior
        ``size_marginal_prior`` (every bulge fraction's run of sizes, then the point
        source; no size prior), shifted like ``lnL``: the data of
        :func:`pylensfit.prior.estimate_size_prior`. Not written by :meth:`write`.
    lnL_r_grouped : numpy.ndarray or None
        ``(n, n_groups, n_r + 1)`` float32 the sums of ``lnL_r`` over each group of e
        cells apart (``fit_stamps(lnL_r_groups=...)``; the point source in the last
        column of every group): ``lnL_r`` is their ``logsumexp`` over the groups. With
        the cells grouped by ``|e|`` (:func:`e_annuli`), ``L(r)`` under another prior
        that depends on ``|e|`` alone is a reweighting of the groups
        (:func:`reweight_lnL_r`), without a second fit. Not written by :meth:`write`.
    stamp : numpy.ndarray or None
        Side of the stamp each galaxy was fitted on (``Config.max_stamp_size``: large
        galaxies on larger stamps).
    """

    egrid: np.ndarray
    lnL: np.ndarray
    lnL_peak: np.ndarray
    r_best: np.ndarray
    flux: np.ndarray
    x: np.ndarray
    y: np.ndarray
    snr: np.ndarray
    is_star: np.ndarray
    flags: np.ndarray
    e1_best: np.ndarray
    e2_best: np.ndarray
    meta: dict = field(default_factory=dict)
    lnL_bulge: np.ndarray | None = None
    lnL_star: np.ndarray | None = None
    bulge_fractions: np.ndarray | None = None
    lnL_r: np.ndarray | None = None
    bulge_best: np.ndarray | None = None
    stamp: np.ndarray | None = None
    lnL_r_grouped: np.ndarray | None = None
    bulge_sizes: np.ndarray | None = None

    def __len__(self) -> int:
        return self.lnL.shape[0]

    _COLUMNS = ("r_best", "flux", "x", "y", "snr", "is_star", "flags", "e1_best", "e2_best",
                "lnL_peak")  # fmt: skip

    def to_table(self):
        """An :class:`astropy.table.Table` with one row per stamp, ``lnL`` a 2-D column."""
        t = Table({name: getattr(self, name) for name in self._COLUMNS})
        if self.stamp is not None:
            t["stamp"] = self.stamp
        t["lnL"] = self.lnL
        if self.lnL_bulge is not None:
            t["lnL_bulge"] = self.lnL_bulge
            t["lnL_star"] = self.lnL_star
            t.meta["BULGEFR"] = ",".join(f"{f:.6g}" for f in self.bulge_fractions)
            if self.bulge_sizes is not None:
                t.meta["BULGESZ"] = ",".join(f"{f:.6g}" for f in self.bulge_sizes)
        t.meta.update({k.upper()[:8]: v for k, v in self.meta.items()})
        return t

    def write(self, path: str | Path, *, overwrite: bool = False) -> None:
        """Write as FITS: the table in HDU 1, the ellipticity grid in HDU 2 (atomic)."""
        tab = fits.table_to_hdu(self.to_table())
        tab.name = "FITS"
        eg = fits.ImageHDU(self.egrid, name="EGRID")
        atomic_write(fits.HDUList([fits.PrimaryHDU(), tab, eg]), path, overwrite=overwrite)

    @classmethod
    def read(cls, path: str | Path) -> StampFits:
        """Read a file written by :meth:`write`."""
        with fits.open(path) as hdul:
            t = Table(hdul["FITS"].data)
            fracs = hdul["FITS"].header.get("BULGEFR")
            bsizes = hdul["FITS"].header.get("BULGESZ")
            egrid = np.array(hdul["EGRID"].data, dtype=float)
        kw = {name: np.asarray(t[name]) for name in cls._COLUMNS}
        if "stamp" in t.colnames:
            kw["stamp"] = np.asarray(t["stamp"])
        if "lnL_bulge" in t.colnames:
            kw["lnL_bulge"] = np.asarray(t["lnL_bulge"], dtype=np.float32)
            kw["lnL_star"] = np.asarray(t["lnL_star"], dtype=float)
            kw["bulge_fractions"] = np.array(str(fracs).split(","), dtype=float)
            if bsizes is not None:
                kw["bulge_sizes"] = np.array(str(bsizes).split(","), dtype=float)
        return cls(egrid=egrid, lnL=np.asarray(t["lnL"], dtype=np.float32), **kw)


@dataclass(frozen=True)
class _PSFBank:
    """Per-PSF quantities: the PSF transform and the per-model sums that need no data."""

    P: np.ndarray  # (n_freq,) complex
    S: np.ndarray  # (n_models,) sum m^2
    mxx: np.ndarray  # (n_models,) Hessian of the model autocorrelation at 0
    mxy: np.ndarray
    myy: np.ndarray


def _interior(n: int, k_max: float = 0.0) -> np.ndarray:
    """``rfft2`` frequencies of an ``n x n`` stamp that are not Nyquist (``|j| < n/2``),
    and with ``k_max > 0`` no farther than ``k_max`` from the origin.

    The engine sums over these only. A Nyquist frequency stands for both ``+pi`` and
    ``-pi``, where neither an elliptical model nor a shift in position has one value:
    without it the likelihood is exactly covariant under the square's symmetries (a
    90-degree rotation of the data maps ``L(e)`` to ``L(-e)``), which
    :func:`_folded_bank` uses. With the PSF at least Nyquist sampled the dropped
    frequencies carry a negligible part of the signal. The disc ``|k| <= k_max`` keeps
    those symmetries; under white noise the Fourier terms are independent, so the sum
    over a subset is the exact likelihood of that part of the data.
    """
    kx, ky, _ = rfft_frequencies(n)
    jmax = (n - 1) // 2
    jx = np.rint(kx * n / (2 * np.pi)).astype(int)
    jy = np.rint(ky * n / (2 * np.pi)).astype(int)
    keep = (np.abs(jx) <= jmax) & (np.abs(jy) <= jmax)
    if k_max > 0:
        keep &= in_disc(kx, ky, k_max)
    return keep.ravel()


@dataclass(frozen=True)
class _Coarse:
    """The coarse sub-grid of the centring pass: bank columns, e cells and sizes."""

    cols: np.ndarray
    n_e: int
    n_r: int


@dataclass(frozen=True)
class _FoldedBank:
    """The model bank folded by the symmetries of the square pixel grid.

    The reflections ``s1: (kx, ky) -> (kx, -ky)`` and ``s2: (kx, ky) -> (ky, kx)`` map
    a model of ellipticity ``(e1, e2)`` to ``(e1, -e2)`` and ``(-e1, e2)``:
    ``G_{s e}(k) = G_e(s k)``. On the frequencies modulo these and ``k -> -k`` (an
    octant, ``0 <= jy <= jx < n/2``), the four characters ``chi`` of the group
    ``{1, s1, s2, s1 s2}`` split every sum ``h_e = sum_k f(k) G_e(k)`` of the engine
    into ``h_{g e} = sum_chi chi(g) A_chi[e]`` with ``A_chi = sum_k0 c(k0)/4 fhat_chi(k0)
    Ghat_chi,e(k0)``: four products over an octant for the four models ``(+-e1, +-e2)``
    instead of one product over the half-plane per model, a quarter of the operations,
    exactly (docs: method, eq-matrix-products).

    A bulge+disc bank's fractions between 0 and 1 are linear in the two ends' transforms
    (:func:`pylensfit.models.model_bank`), and so are their products: ``G`` holds the
    pure disc's and the pure bulge's columns (and the point source's), and the kernel
    mixes the others from them (``mix_a``, ``mix_b``, ``mix_f``): a third fewer
    operations in the matrix products for three fractions.
    """

    idx: np.ndarray  # (4, n_k0) half-plane index of h k0 for h = 1, s1, s2, s1 s2
    coef: np.ndarray  # (n_k0,) orbit weight c(k0) / 4 / n^2
    keep: tuple  # per character, the octant points where it can be non-zero
    G: tuple  # per character, (len(keep), n_base) folded transforms of the base columns
    members: np.ndarray  # (n_cols, 4) model with h . (representative) in column c, or -1
    coarse: _Coarse  # the coarse sub-grid of the centring pass, closed under the symmetries
    coarse_G: tuple  # per character, its columns (all of them base columns)
    coarse_members: np.ndarray  # (n_cols_c, 4) as members, in the coarse models' numbering
    # columns c >= n_base are (1 - f) column a + f column b: a = mix_a[c - n_base], ...
    mix_a: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    mix_b: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    mix_f: np.ndarray = field(default_factory=lambda: np.zeros(0))


#: characters chi[c, h] of the group h = (1, s1, s2, s1 s2): (+-1)^(a i + b j)
_CHI = np.array([[1, 1, 1, 1], [1, -1, 1, -1], [1, 1, -1, -1], [1, -1, -1, 1]], dtype=float)

_FOLDED: dict = {}
_NO_MIX = (np.zeros(0, dtype=np.int64), np.zeros(0))


def _folded_bank(config: Config, bank) -> _FoldedBank:
    key = (config.stamp_size, config.e_step, config.e_max, config.r_min, config.r_max,
           config.r_step, config.model, config.bulge_fraction, config.bulge_size_ratio,
           config.dtype, int(config.n_bulge_fractions), float(config.r_rel_step),
           bool(config.truncate_models), float(config.k_max),
           float(config.bulge_size_ratio2), tuple(config.sersic_ladder),
           float(config.r_floor))  # fmt: skip
    fb = _FOLDED.get(key)
    if fb is not None and fb[0] is bank:
        return fb[1]
    n = config.stamp_size
    nh = n // 2 + 1
    jmax = (n - 1) // 2
    a, b = np.tril_indices(jmax + 1)  # octant 0 <= b <= a <= jmax
    if config.k_max > 0:  # the disc |k| <= k_max (the stamp tiers)
        inside = in_disc(a * (2 * np.pi / n), b * (2 * np.pi / n), config.k_max)
        a, b = a[inside], b[inside]

    def half(jx, jy):
        neg = jx < 0
        jx = np.where(neg, -jx, jx)
        jy = np.where(neg, -jy, jy)
        return (jy % n) * nh + jx

    idx = np.stack([half(a, b), half(a, -b), half(b, a), half(b, -a)])
    c = np.where((a == 0) & (b == 0), 0.25, np.where((b == 0) | (a == b), 1.0, 2.0))
    coef = c / 4.0 / n**2
    keep = tuple(np.flatnonzero(~((bool(al) & (b == 0)) | (bool(be) & (a == b))))
                 for al, be in ((0, 0), (1, 0), (0, 1), (1, 1)))  # fmt: skip
    eg = bank.egrid
    rep = (eg[:, 0] > 0) & (eg[:, 1] > 0)
    ie_rep = np.flatnonzero(rep)
    key_rep = {(round(e1, 9), round(e2, 9)): o for o, (e1, e2) in enumerate(eg[ie_rep])}
    orb = np.array([key_rep[(round(abs(e1), 9), round(abs(e2), 9))] for e1, e2 in eg])
    h = (eg[:, 1] < 0).astype(int) + 2 * (eg[:, 0] < 0)  # s1 flips e2, s2 flips e1
    n_r = bank.n_r
    members = np.full((ie_rep.size * n_r + 1, 4), -1, dtype=np.int64)
    j = np.arange(bank.n_models - 1)
    members[orb[j // n_r] * n_r + j % n_r, h[j // n_r]] = j
    members[-1, 0] = bank.n_models - 1  # the point source, its own image
    rep_cols = np.append((ie_rep[:, None] * n_r + np.arange(n_r)[None, :]).ravel(),
                         bank.n_models - 1)  # fmt: skip
    Gr = bank.G[:, rep_cols]
    idx_g = idx
    if bank.rows is not None:  # the bank holds only the disc's frequencies
        pos = np.full(n * nh, -1, dtype=np.int64)
        pos[bank.rows] = np.arange(bank.rows.size)
        idx_g = pos[idx]
        if (idx_g < 0).any():
            raise RuntimeError("the model bank lacks frequencies of the likelihood's sums")
    Gh = np.einsum("ch,hkm->ckm", _CHI, Gr[idx_g].astype(np.float64))
    G = tuple(np.ascontiguousarray(Gh[ch][keep[ch]], dtype=config.dtype) for ch in range(4))
    # the coarse sub-grid: e cells at every other lattice step in both components (a set
    # closed under e1 -> -e1, e2 -> -e2) and every 5th size
    lat = np.rint(np.abs(eg) / config.e_step - 0.5).astype(int)
    ie_c = np.flatnonzero((lat % 2 == 0).all(axis=1))
    ir_c = np.arange(min(2, n_r - 1), n_r, 5)
    n_ec, n_rc = ie_c.size, ir_c.size
    ccols = np.append((ie_c[:, None] * n_r + ir_c[None, :]).ravel(), bank.n_models - 1)
    rep_c = ie_c[rep[ie_c]]
    oc = {o: k for k, o in enumerate(orb[rep_c])}  # full orbit number -> coarse one
    cmem = np.full((rep_c.size * n_rc + 1, 4), -1, dtype=np.int64)
    jc = np.arange(n_ec * n_rc)
    ie_j = ie_c[jc // n_rc]
    cmem[np.array([oc[o] for o in orb[ie_j]]) * n_rc + jc % n_rc, h[ie_j]] = jc
    cmem[-1, 0] = n_ec * n_rc
    gcols = np.append((orb[rep_c][:, None] * n_r + ir_c[None, :]).ravel(), ie_rep.size * n_r)
    coarse = _Coarse(cols=ccols, n_e=n_ec, n_r=n_rc)
    coarse_G = tuple(np.ascontiguousarray(g[:, gcols]) for g in G)
    perm, mix_a, mix_b, mix_f = _mixed_columns(bank, ie_rep.size)
    if mix_a.size:
        G = tuple(np.ascontiguousarray(g[:, perm[: perm.size - mix_a.size]]) for g in G)
        members = np.ascontiguousarray(members[perm])
    fb = _FoldedBank(idx=idx, coef=coef, keep=keep, G=G, members=members, coarse=coarse,
                     coarse_G=coarse_G, coarse_members=cmem, mix_a=mix_a, mix_b=mix_b,
                     mix_f=mix_f)  # fmt: skip
    _keep(_FOLDED, key, (bank, fb), 4)
    return fb


def _mixed_columns(bank, n_orb: int):
    """The folded bank's column order with the mixed runs last.

    Returns ``perm`` (new column -> old, the old order ``orbit * n_r + ir`` and the
    point source last), and for the mixed columns (``perm[n_base:]``) the base columns
    ``a`` and ``b`` (the pure runs of the run's two components, :class:`~pylensfit.models.Run`)
    and the fraction ``f``: column ``(1 - f) a + f b``. No mixed columns (``perm`` the
    identity) unless the bank is bulge+disc with runs between pure ones (the fractions 0
    and 1 and others between; the Sersic ladder's half-and-half mixtures).
    """
    n_r = bank.n_r
    n_old = n_orb * n_r + 1
    none = (np.arange(n_old), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    runs = tuple(bank.runs)
    if bank.model != "bulge+disc" or len(runs) < 2:
        return none
    n_sub = bank.n_sizes
    pure = {}  # component -> its pure run
    for k, run in enumerate(runs):
        if run.fraction in (0.0, 1.0):
            pure.setdefault(run.components[int(run.fraction)], k)
    ends = np.array([k for k, run in enumerate(runs) if run.fraction in (0.0, 1.0)])
    mid = np.array([k for k, run in enumerate(runs) if run.fraction not in (0.0, 1.0)], int)
    if mid.size == 0 or any(c not in pure for k in mid for c in runs[k].components):
        return none
    orb = np.arange(n_orb)[:, None, None]
    size = np.arange(n_sub)[None, None, :]
    ends_c = orb * n_r + ends[None, :, None] * n_sub + size
    mids_c = orb * n_r + mid[None, :, None] * n_sub + size
    perm = np.concatenate([ends_c.ravel(), [n_orb * n_r], mids_c.ravel()])
    pos = np.empty(n_old, dtype=np.int64)
    pos[perm] = np.arange(n_old)
    run_a = np.array([pure[runs[k].components[0]] for k in mid])
    run_b = np.array([pure[runs[k].components[1]] for k in mid])
    shape = (n_orb, mid.size, n_sub)
    mix_a = pos[np.broadcast_to(orb * n_r + run_a[None, :, None] * n_sub + size, shape).ravel()]
    mix_b = pos[np.broadcast_to(orb * n_r + run_b[None, :, None] * n_sub + size, shape).ravel()]
    fr = np.array([runs[k].fraction for k in mid])
    mix_f = np.broadcast_to(fr[None, :, None], shape).ravel().copy()
    return perm, mix_a, mix_b, mix_f


_ACTIVE: dict = {}


def _active_columns(fb: _FoldedBank, bank, active: np.ndarray) -> _FoldedBank:
    """``fb`` with the columns of the sizes ``active`` (``(n_r,)`` bool) only.

    The columns of the sizes left out are dropped from the matrix products and from the
    kernel's loop (``members``), except the pure fractions' columns that an active mixed
    column is made from: those stay in ``G`` after the active base columns, read only
    through ``mix_a`` and ``mix_b``. The coarse sub-grid is unchanged.
    """
    key = (id(fb), active.tobytes())
    hit = _ACTIVE.get(key)
    if hit is not None and hit[0] is fb:
        return hit[1]
    n_r = bank.n_r
    n_mix = fb.mix_a.size
    n_base = fb.members.shape[0] - n_mix
    j = fb.members.max(axis=1)  # any model of the column: all share its size
    keep = np.where(j == bank.n_models - 1, True, active[j % n_r])
    kb = np.flatnonzero(keep[:n_base])
    km = np.flatnonzero(keep[n_base:])
    feed = np.setdiff1d(np.union1d(fb.mix_a[km], fb.mix_b[km]), kb)
    order = np.concatenate([kb, feed])  # new prod column -> old
    pos = np.full(n_base, -1, dtype=np.int64)
    pos[order] = np.arange(order.size)
    sub = replace(
        fb,
        G=tuple(np.ascontiguousarray(g[:, order]) for g in fb.G),
        members=np.ascontiguousarray(np.concatenate([fb.members[kb], fb.members[n_base + km]])),
        mix_a=pos[fb.mix_a[km]], mix_b=pos[fb.mix_b[km]], mix_f=fb.mix_f[km].copy(),
    )  # fmt: skip
    _keep(_ACTIVE, key, (fb, sub), 2)
    return sub


def _keep(cache: dict, key, value, size: int) -> None:
    """Store ``value`` in ``cache``, dropping the oldest entry beyond ``size``."""
    if len(cache) >= size:
        cache.pop(next(iter(cache)))
    cache[key] = value


#: the last PSFs' banks: a pipeline fits an image's galaxies with one PSF in several
#: calls (blocks, neighbour subtraction), or with one PSF per cell of a PSF over the
#: field (Config.psf_cells^2 per stamp tier, so 8 x 8 cells and two tiers need 128); a
#: precision block its renderings. An entry holds 4 floats per model (1.4 MB for
#: Config()'s 44,557 models).
_PSF_BANKS: dict = {}
_PSF_BANKS_KEPT = 144


def _psf_bank(psf: np.ndarray, config: Config, bank) -> _PSFBank:
    """:func:`_psf_bank_of` of the PSF image, reused while the same image and bank recur."""
    psf = np.ascontiguousarray(psf)
    key = (hashlib.blake2b(psf.tobytes(), digest_size=16).digest(), psf.shape, psf.dtype.str,
           config.stamp_size, float(config.k_max), id(bank))  # fmt: skip
    hit = _PSF_BANKS.get(key)
    if hit is not None and hit[0] is bank:
        return hit[1]
    pb = _psf_bank_of(psf, config, bank)
    _keep(_PSF_BANKS, key, (bank, pb), _PSF_BANKS_KEPT)
    return pb


def _psf_bank_of(psf: np.ndarray, config: Config, bank) -> _PSFBank:
    """The PSF's transform and each model's ``sum m^2`` and autocorrelation Hessian."""
    n = config.stamp_size
    P = psf_transform(psf, n)
    kx, ky, w = rfft_frequencies(n)
    p2 = (w * np.abs(P) ** 2 / n**2).ravel() * _interior(n, config.k_max)
    kx = kx.ravel()
    ky = ky.ravel()
    W = np.stack([p2, -p2 * kx * kx, -p2 * kx * ky, -p2 * ky * ky])
    if bank.rows is not None:
        W = W[:, bank.rows]
    out = np.empty((4, bank.G.shape[1]))
    for c0 in range(0, bank.G.shape[1], 4096):  # in chunks: no bank-sized temporary
        out[:, c0 : c0 + 4096] = W @ np.square(bank.G[:, c0 : c0 + 4096], dtype=np.float64)
    return _PSFBank(P=P.ravel(), S=out[0], mxx=out[1], mxy=out[2], myy=out[3])


def _cut_stamps(stamps: np.ndarray, n: int, cx: np.ndarray, cy: np.ndarray):
    """Cut ``n x n`` windows centred on round(c) (zero padded); return them and new centres."""
    k, ny, nx = stamps.shape
    if ny == n and nx == n:
        return stamps, cx, cy
    ix = np.rint(cx).astype(int) - n // 2
    iy = np.rint(cy).astype(int) - n // 2
    inside = k and ix.min() >= 0 and iy.min() >= 0 and ix.max() + n <= nx and iy.max() + n <= ny
    # zeros about the stamps only where a window reaches beyond them (the copy is a
    # good part of a precision block's time)
    pad = 0 if inside else n
    padded = np.pad(stamps, ((0, 0), (pad, pad), (pad, pad))) if pad else stamps
    rows = (iy[:, None] + pad + np.arange(n)[None, :]).clip(0, ny + 2 * pad - 1)
    cols = (ix[:, None] + pad + np.arange(n)[None, :]).clip(0, nx + 2 * pad - 1)
    out = padded[np.arange(k)[:, None, None], rows[:, :, None], cols[:, None, :]]
    return out, cx - ix, cy - iy


def _centre(D: np.ndarray, P: np.ndarray, config: Config, x0: np.ndarray, y0: np.ndarray):
    """Integer-then-parabola peak of the cross-correlation with a round model.

    ``D`` is phase-referenced to the stamp centre ``n//2``; ``x0, y0`` are catalogue
    offsets from it. Returns the offsets of the peak and a flag for "no positive peak".
    """
    n = config.stamp_size
    kx, ky, _ = rfft_frequencies(n)
    ref = fourier_profile(np.hypot(kx, ky) * config.centring_scale, "exponential") * P
    cc = np.fft.irfft2(D * np.conj(ref)[None], s=(n, n))  # cc[g, iy, ix] = h(X=(ix, iy))
    off = (np.arange(n) + n // 2) % n - n // 2
    rad = max(config.max_offset, 0.75)
    d2 = (off[None, None, :] - x0[:, None, None]) ** 2 + (
        off[None, :, None] - y0[:, None, None]
    ) ** 2
    masked = np.where(d2 <= rad * rad, cc, -np.inf)
    flat = masked.reshape(len(D), -1).argmax(axis=1)
    iy, ix = np.unravel_index(flat, (n, n))
    g = np.arange(len(D))
    v0 = cc[g, iy, ix]

    def parabola(vm, vp):
        den = vm - 2 * v0 + vp
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.where(den < 0, 0.5 * (vm - vp) / den, 0.0)
        return np.clip(step, -0.5, 0.5)

    dx = parabola(cc[g, iy, (ix - 1) % n], cc[g, iy, (ix + 1) % n])
    dy = parabola(cc[g, (iy - 1) % n, ix], cc[g, (iy + 1) % n, ix])
    xc = off[ix] + dx
    yc = off[iy] + dy
    # Newton iterations on the exact (Fourier-interpolated) cross-correlation: every
    # model's Laplace step then starts from a fraction of its own peak width
    xc, yc, _ = newton_peak(D, ref, xc, yc, n_steps=3)
    no_peak = ~(v0 > 0)
    xc = np.where(no_peak, x0, xc)
    yc = np.where(no_peak, y0, yc)
    return xc, yc, no_peak


def fit_stamps(
    stamps: np.ndarray,
    psf: np.ndarray,
    noise_sigma,
    *,
    config: Config | None = None,
    centres: tuple[np.ndarray, np.ndarray] | None = None,
    size_prior=None,
    size_marginal_prior=None,
    lnL_r_groups: np.ndarray | None = None,
) -> StampFits:
    """Likelihood ``L(e)`` of every stamp on the ellipticity grid, and the best model.

    With ``config.max_stamp_size`` larger than ``config.stamp_size`` (and stamps larger
    than the base stamp), each galaxy is fitted on the smallest stamp ``j * stamp_size``
    that is ``stamp_hlr_ratio`` of its PSF-convolved half-light radii wide (measured
    with round exponentials first), with the Fourier terms ``|k| <= pi / j`` only: as
    many as on the base stamp, and all that a galaxy that large has signal in. Stamps
    smaller than ``max_stamp_size`` give their own side as the largest tier
    (:func:`tier_sizes`: 48-pixel stamps fit the galaxies that need more than 32 pixels
    on 48, ``j = 1.5``). On one stamp, the
    light that the PSF scatters across the edge makes large galaxies respond to shear
    differently along the pixel axes and the diagonals (``benchmarks/studies/stamp_edge.py``).

    Parameters
    ----------
    stamps : numpy.ndarray
        ``(n, N, N)`` (or one ``(N, N)``) background-subtracted images indexed
        ``[k, y, x]``, each galaxy near element ``[N//2, N//2]`` unless ``centres`` is
        given. ``N`` may differ from ``config.stamp_size``: a window of that size (or of
        a larger tier) is cut about each centre (zero padded outside the input; a tier's
        window never leaves the input).
    psf : numpy.ndarray
        2-D PSF image including the pixel response, centred on ``[s//2, s//2]``, any size
        and normalisation; shared by all stamps of the call. Cut to each stamp size used,
        so give it as large as ``max_stamp_size`` for the tiers.
    noise_sigma : float or numpy.ndarray
        Per-pixel noise standard deviation, scalar or one per stamp.
    config : Config, optional
        Grid, model and marginalisation settings (default ``Config()``; the priors it
        estimates are applied with :meth:`pylensfit.Priors.apply` and ``size_prior=``).
    centres : tuple of numpy.ndarray, optional
        Catalogue positions ``(x, y)`` in stamp pixels (0-based), the centres of the
        position prior.
    size_prior : pylensfit.prior.SizePrior, optional
        Prior of the half-light radius in the sum over r (and of the point source);
        default the paper's, uniform in r (in half-light radius for every bulge fraction).
    size_marginal_prior : pylensfit.prior.Prior, optional
        The ellipticity prior with which ``StampFits.lnL_r`` is marginalised over e,
        ``L(r) = sum_e P(e) L(e, r)``, the likelihood of the size that
        :func:`pylensfit.prior.estimate_size_prior` deconvolves (default ``Prior()``, the
        functional form with the STEP-like parameters). A uniform weight over e cells
        favours the small sizes that elongated models prefer: it estimated the sizes of
        exponential discs ~6% small.
    lnL_r_groups : numpy.ndarray, optional
        ``(n_e,)`` integer group (0, 1, ...) of each cell of the ellipticity grid: keep
        the sum over e of ``L(r)`` per group as well (``StampFits.lnL_r_grouped``; for
        the groups of equal ``|e|``, :func:`e_annuli`).

    Returns
    -------
    StampFits
        One row per stamp. Stamps with non-finite pixels or a bad noise value are
        flagged and get NaN ``lnL``; they never raise.

    Notes
    -----
    The matrix products run on one BLAS thread whatever the caller's setting (the
    compiled kernels keep their threads, each galaxy on one of them): a threaded
    float32 ``sgemm`` sums in another order, and ``ln L`` would depend on the machine's
    thread count by about 1e-4, which the sky measured again less the models can carry
    much further. So the result is the same bit for bit in a serial run, under
    ``jobs > 1`` and on a cluster's workers.
    """
    with _one_blas_thread():
        return _fit_stamps(stamps, psf, noise_sigma, config, centres, size_prior,
                           size_marginal_prior, lnL_r_groups)  # fmt: skip


@lru_cache(maxsize=1)
def _blas_controller():
    return ThreadpoolController()


def _one_blas_thread():
    """A context in which the BLAS libraries run on one thread (see :func:`fit_stamps`)."""
    return _blas_controller().limit(limits=1, user_api="blas")


def _fit_stamps(stamps, psf, noise_sigma, config, centres, size_prior, size_marginal_prior,
                lnL_r_groups) -> StampFits:  # fmt: skip
    cfg = config if config is not None else Config()
    stamps = np.asarray(stamps, dtype=float)
    if stamps.ndim == 2:
        stamps = stamps[None]
    if stamps.ndim != 3 or stamps.shape[1] < 2 or stamps.shape[2] < 2:
        raise ValueError(f"stamps must have shape (n, N, N), got {stamps.shape}")
    n_gal = stamps.shape[0]
    sigma = per_object(noise_sigma, n_gal, "noise_sigma")
    if centres is None:
        cx = np.full(n_gal, stamps.shape[2] // 2, dtype=float)
        cy = np.full(n_gal, stamps.shape[1] // 2, dtype=float)
    else:
        cx = per_object(centres[0], n_gal, "centres[0]")
        cy = per_object(centres[1], n_gal, "centres[1]")
    sizes = tier_sizes(cfg, stamps.shape[1:])
    if len(sizes) <= 1 or n_gal == 0:
        if n_gal and cfg.largest_stamp > sizes[-1]:
            _warn_small_stamps(stamps.shape, cfg, sizes[-1], None)
        return _fit_window(stamps, psf, sigma, cfg, cx, cy, size_prior, size_marginal_prior,
                           lnL_r_groups)  # fmt: skip
    size, wanted = _stamp_tiers(stamps, psf, sigma, cfg, cx, cy, sizes)
    if cfg.largest_stamp > sizes[-1]:
        short = int(np.count_nonzero(wanted > sizes[-1]))
        if short:
            _warn_small_stamps(stamps.shape, cfg, sizes[-1], short)
    parts = []
    for t in np.unique(size):
        idx = np.flatnonzero(size == t)
        sub = cfg if t == cfg.stamp_size else cfg.replace(
            stamp_size=int(t), max_stamp_size=0, k_max=np.pi * cfg.stamp_size / t)  # fmt: skip
        parts.append((idx, _fit_window(stamps[idx], psf, sigma[idx], sub, cx[idx], cy[idx],
                                       size_prior, size_marginal_prior,
                                       lnL_r_groups)))  # fmt: skip
    return merge_fits(parts, n_gal)


def tier_sizes(config: Config, shape: tuple[int, ...]) -> list[int]:
    """The stamp sides of the tiers that stamps of ``shape`` (``(ny, nx)``) allow.

    The multiples of ``config.stamp_size`` up to ``config.largest_stamp`` that the
    stamps hold, and above them the stamps' own side (rounded down to an even number)
    where it is smaller than ``largest_stamp``: 48-pixel stamps give ``[32, 48]`` under
    the default ``max_stamp_size=64``, 64-pixel ones ``[32, 64]``.

    Parameters
    ----------
    config : Config
        ``stamp_size`` (the base tier) and ``max_stamp_size`` (the largest).
    shape : tuple of int
        The given stamps' sides.

    Returns
    -------
    list of int
        Increasing stamp sides; ``[config.stamp_size]`` alone where there are no tiers or
        the stamps hold no more than the base stamp.
    """
    n0 = config.stamp_size
    top = min(config.largest_stamp, *(int(v) for v in shape))
    sizes = list(range(n0, top + 1, n0)) or [n0]
    top -= top % 2
    if top > sizes[-1]:
        sizes.append(top)
    return sizes


def _warn_small_stamps(shape: tuple[int, ...], cfg: Config, top: int,
                       n_short: int | None) -> None:  # fmt: skip
    """Log that the given stamps are smaller than ``cfg.largest_stamp``: ``n_short``
    galaxies wanted a larger stamp than ``top``, the largest side they allow (None: the
    stamps allow no tier above the base stamp)."""
    log = logging.getLogger(__name__)
    if n_short is None:
        log.warning("stamps of %dx%d px: max_stamp_size=%d cannot act, the largest galaxies "
                    "are fitted on %d-pixel stamps (give stamps of %d px)", shape[1],
                    shape[2], cfg.largest_stamp, top, cfg.largest_stamp)  # fmt: skip
    else:
        log.warning("stamps of %dx%d px: %d galaxies need stamps larger than %d px and are "
                    "fitted on %d (max_stamp_size=%d: give stamps of %d px)", shape[1],
                    shape[2], n_short, top, top, cfg.largest_stamp,
                    cfg.largest_stamp)  # fmt: skip


def _stamp_tiers(stamps, psf, sigma, cfg: Config, cx, cy,
                 sizes: list[int]) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The stamp side of every stamp, one of ``sizes`` (:func:`tier_sizes`), and the side
    each galaxy needs (pixels, at least ``stamp_size``).

    Each galaxy's size is that of the round exponential of largest matched-filter S/N
    on the largest tier's window (half-light radii 0.1-12 px, about the centre that a
    fit on the base stamp starts from), its PSF-convolved half-light radius ``R``
    measured on the convolved model's image. It needs ``stamp_hlr_ratio * R``; its side
    is the smallest of ``sizes`` at least that (the largest where none is), at most what
    the given stamp holds about the galaxy; stamps without a positive peak get the base
    side.
    """
    n0 = cfg.stamp_size
    nw = sizes[-1]
    kx, ky, w = rfft_frequencies(nw)
    c = nw // 2
    P = psf_transform(psf, nw)
    # the centre from the base stamp's window about the same pixel (a quarter of the
    # largest window's cost: two thirds of this function's time were the centring)
    kx0, ky0, _ = rfft_frequencies(n0)
    c0 = n0 // 2
    P0 = psf_transform(psf, n0)
    ccfg = cfg.replace(max_stamp_size=0, k_max=0.0)
    # round exponentials (and their convolved half-light radii, from their images)
    M = fourier_profile(np.hypot(kx, ky).ravel()[:, None] * np.geomspace(0.1, 12.0, 24)[None]
                        / half_light_radius("exponential"), "exponential") * P.ravel()[:, None]
    wt = w.ravel() * _interior(nw)
    S = (wt[:, None] * np.abs(M) ** 2).sum(axis=0)
    img = np.fft.irfft2(M.T.reshape(-1, *kx.shape) * np.exp(-1j * (kx * c + ky * c)),
                        s=(nw, nw)).reshape(M.shape[1], -1)  # fmt: skip
    rad = np.hypot(*(np.mgrid[:nw, :nw] - c)).ravel()
    order = np.argsort(rad)
    cum = np.cumsum(img[:, order], axis=1)
    hlr = rad[order][np.argmax(cum >= 0.5 * cum[:, -1:], axis=1)]
    wanted = np.full(len(stamps), n0, dtype=int)
    step = 4 * cfg.block_size
    for s0 in range(0, len(stamps), step):
        sl = slice(s0, min(s0 + step, len(stamps)))
        win, wx, wy = _cut_stamps(np.nan_to_num(stamps[sl], nan=0.0, posinf=0.0, neginf=0.0),
                                  nw, cx[sl], cy[sl])  # fmt: skip
        D = np.fft.rfft2(win) * np.exp(1j * (kx * c + ky * c))[None]
        D0 = (np.fft.rfft2(win[:, c - c0:c - c0 + n0, c - c0:c - c0 + n0])
              * np.exp(1j * (kx0 * c0 + ky0 * c0))[None])  # fmt: skip
        xc, yc, no_peak = _centre(D0, P0, ccfg, wx - c, wy - c)
        # the phase ramp, separable: one exp per row and per column of the frequencies
        ph = (np.exp(1j * ky[:, 0][None, :, None] * yc[:, None, None])
              * np.exp(1j * kx[0][None, None, :] * xc[:, None, None]))  # fmt: skip
        ph = ph.reshape(len(D), -1)
        h = ((D.reshape(len(D), -1) * ph * wt) @ np.conj(M)).real
        best = np.argmax(h / np.sqrt(S), axis=1)
        need = np.ceil(cfg.stamp_hlr_ratio * hlr[best]).astype(int)
        ok = ~no_peak & (h[np.arange(len(D)), best] > 0) & np.isfinite(sigma[sl])
        wanted[sl] = np.where(ok, np.maximum(need, n0), n0)
    side = np.asarray(sizes)
    size = side[np.minimum(np.searchsorted(side, wanted), side.size - 1)]
    # no window beyond the given stamps: n <= 2 min(ic, N - ic) along both axes
    ix, iy = np.rint(cx).astype(int), np.rint(cy).astype(int)
    room = np.minimum.reduce([ix, stamps.shape[2] - ix, iy, stamps.shape[1] - iy])
    fits_in = side[np.maximum(np.searchsorted(side, 2 * room, side="right") - 1, 0)]
    return np.minimum(size, fits_in), wanted


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
    out[:, :-1] = _logsumexp_groups(L[:, :, :-1] + lnw[None, :, None])
    return out.astype(np.float32)


def _logsumexp_groups(a: np.ndarray) -> np.ndarray:
    """``log sum exp`` over axis 1 of ``(n, n_groups, m)`` (``-inf`` where all are)."""
    top = np.max(a, axis=1)
    safe = np.where(np.isfinite(top), top, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.log(np.sum(np.exp(a - safe[:, None]), axis=1)) + safe


@dataclass
class _Window:
    """One stamp size's galaxies cleaned, transformed and centred: what every stage reads.

    ``xc, yc`` (the origin of the expansion in position, offsets from the centre pixel
    ``c``) are moved in place by the centring pass (:func:`_recentre_block`), and
    ``flags`` gains bits in place.
    """

    n_gal: int
    n: int  # stamp side
    c: int  # centre pixel, n // 2
    bank: ModelBank
    pb: _PSFBank
    sigma: np.ndarray  # (n_gal,) noise, 1 for the bad stamps
    flags: np.ndarray  # (n_gal,) int32 bit mask
    bad: np.ndarray  # (n_gal,) bad pixels or bad noise
    shift_x: np.ndarray  # window origin in the input stamps
    shift_y: np.ndarray
    x0: np.ndarray  # catalogue positions, offsets from the centre pixel
    y0: np.ndarray
    kx: np.ndarray  # rfft2 frequencies of the window
    ky: np.ndarray
    D: np.ndarray  # (n_gal, n, n // 2 + 1) transforms, phase-referenced to the centre
    xc: np.ndarray
    yc: np.ndarray
    no_peak: np.ndarray  # no positive peak of the cross-correlation


def _clean_stamps(stamps: np.ndarray, sigma: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Flag the stamps with non-finite pixels or a bad noise value and neutralise them.

    Returns the stamps and the noise (the bad ones zeros and 1), the flags and the bad
    stamps' mask.
    """
    flags = np.zeros(stamps.shape[0], dtype=np.int32)
    bad_pix = ~np.isfinite(stamps).all(axis=(1, 2))
    bad_sig = ~(np.isfinite(sigma) & (sigma > 0))
    flags[bad_pix] |= _flags.flag_value("BAD_PIXELS")
    flags[bad_sig] |= _flags.flag_value("BAD_NOISE")
    bad = bad_pix | bad_sig
    if bad.any():
        stamps = np.where(bad[:, None, None], 0.0, stamps)
        stamps = np.nan_to_num(stamps, nan=0.0, posinf=0.0, neginf=0.0)
        sigma = np.where(bad, 1.0, sigma)
    return stamps, sigma, flags, bad


def _prepare_window(stamps: np.ndarray, psf: np.ndarray, sigma: np.ndarray, cfg: Config,
                    cx: np.ndarray, cy: np.ndarray) -> _Window:  # fmt: skip
    """Cut and clean the windows, their transforms, the PSF bank and the centres."""
    n_gal = stamps.shape[0]
    n = cfg.stamp_size
    bank = model_bank(cfg)
    pb = _psf_bank(psf, cfg, bank)
    cx_in, cy_in = cx, cy
    stamps, cx, cy = _cut_stamps(stamps, n, cx, cy)
    stamps, sigma, flags, bad = _clean_stamps(stamps, sigma)
    kx, ky, _ = rfft_frequencies(n)
    c = n // 2
    x0 = cx - c
    y0 = cy - c
    D = np.fft.rfft2(stamps) * np.exp(1j * (kx * c + ky * c))[None]
    xc, yc, no_peak = _centre(D, pb.P.reshape(kx.shape), cfg, x0, y0)
    flags[no_peak & ~bad] |= _flags.flag_value("NO_PEAK")
    return _Window(n_gal=n_gal, n=n, c=c, bank=bank, pb=pb, sigma=sigma, flags=flags, bad=bad,
                   shift_x=cx_in - cx, shift_y=cy_in - cy, x0=x0, y0=y0, kx=kx, ky=ky, D=D,
                   xc=xc, yc=yc, no_peak=no_peak)  # fmt: skip


@dataclass(frozen=True)
class _Products:
    """The window's Fourier rows and their matrix products with the folded model bank."""

    win: _Window
    fb: _FoldedBank  # with the columns of the sizes that the size prior keeps
    kxf: np.ndarray  # (n_freq,) frequencies
    kyf: np.ndarray
    Pc: np.ndarray  # (n_freq,) conjugate PSF transform
    dtype: np.dtype
    store: np.ndarray  # one buffer for every block's products: the pages are mapped once

    def rows(self, sl: slice | np.ndarray, cubic: bool) -> np.ndarray:
        """h, grad h, Hess h (and third derivatives) as ``(q * m, frequency)`` rows."""
        kxf, kyf, win = self.kxf, self.kyf, self.win
        ph = np.exp(1j * (kxf[None] * win.xc[sl, None] + kyf[None] * win.yc[sl, None]))
        Dp = win.D[sl].reshape(-1, kxf.size) * ph * self.Pc[None]
        r, i = Dp.real, Dp.imag
        out = [r, -kxf * i, -kyf * i, -kxf * kxf * r, -kxf * kyf * r, -kyf * kyf * r]
        if cubic:
            out += [kxf**3 * i, kxf**2 * kyf * i, kxf * kyf**2 * i, kyf**3 * i]
        return np.concatenate(out, axis=0)

    def folded(self, sl: slice | np.ndarray, cubic: bool, Gf: tuple | None = None
               ) -> np.ndarray:  # fmt: skip
        """The products with every model (or the coarse ones), folded by the square's
        symmetries (_FoldedBank)."""
        fb = self.fb
        Gf = fb.G if Gf is None else Gf
        R = self.rows(sl, cubic)[:, fb.idx]  # (q m, 4, octant)
        nc = Gf[0].shape[1]
        out = self.store[: 4 * R.shape[0] * nc].reshape(4, R.shape[0], nc)
        for ch in range(4):
            Fh = np.einsum("h,rhk->rk", _CHI[ch], R[:, :, fb.keep[ch]])
            Fh *= fb.coef[fb.keep[ch]]
            np.matmul(Fh.astype(self.dtype), Gf[ch], out=out[ch])
        return out


def _products(win: _Window, cfg: Config, fb: _FoldedBank, n_cols: int) -> _Products:
    """The products of ``win`` with ``fb``'s columns, in a buffer for ``n_cols`` columns."""
    dtype = np.dtype(cfg.dtype)
    store = np.empty(4 * 10 * min(cfg.block_size, win.n_gal) * n_cols, dtype=dtype)
    return _Products(win=win, fb=fb, kxf=win.kx.ravel(), kyf=win.ky.ravel(),
                     Pc=np.conj(win.pb.P), dtype=dtype, store=store)  # fmt: skip


@dataclass(frozen=True)
class _Weights:
    """The priors and weights that the likelihood kernel applies, and the e cells' groups."""

    n_b: int  # bulge fractions, a uniform prior over them here
    ln_pi: np.ndarray  # (n_b,) ln prior of each fraction
    node_w: np.ndarray  # (n_r,) weight of each size node (size prior, trapezoid rule)
    w_star: float  # the point source's weight
    e_w: np.ndarray  # (n_e,) the e cells' weights in lnL_r (size_marginal_prior)
    e_grp: np.ndarray  # (n_e,) group of each e cell in lnL_r
    n_grp: int
    amp: tuple[float, float, float, float]  # amplitude prior: power, ln S power, limits
    b2: float  # variance of the position prior
    e_w_c: np.ndarray  # the centring pass's weights of its e cells
    rw_c: np.ndarray  # and of its sizes


def _size_weights(cfg: Config, bank: ModelBank, fb: _FoldedBank, size_prior: SizePrior | None,
                  n_b: int) -> tuple[np.ndarray, float, _FoldedBank]:  # fmt: skip
    """The weight of every size node and of the point source, and ``fb`` without the
    columns of the sizes outside the size prior (no models to evaluate)."""
    if size_prior is None:
        run_w = bank.run_weights if bank.run_weights is not None else np.ones(n_b)
        node_w = np.tile(np.asarray(bank.r_weights, float), n_b) * np.repeat(run_w, bank.n_sizes)
        w_star = float(bank.star_weight)
    else:
        node_w, w_star = size_prior.node_weights(bank, cfg)
        if not (node_w > 0).all():
            fb = _active_columns(fb, bank, node_w > 0)
    return node_w, w_star, fb


def _e_groups(lnL_r_groups: np.ndarray | None, n_e: int) -> np.ndarray:
    """The checked group of every e cell in ``lnL_r`` (all in group 0 by default)."""
    if lnL_r_groups is None:
        return np.zeros(n_e, dtype=np.int64)
    e_grp = np.asarray(lnL_r_groups)
    if e_grp.shape != (n_e,) or e_grp.dtype.kind not in "iu" or e_grp.min() < 0:
        raise ValueError(f"lnL_r_groups needs {n_e} non-negative integers (one per e "
                         f"cell), got shape {e_grp.shape}, dtype {e_grp.dtype}")  # fmt: skip
    return e_grp.astype(np.int64)


def _amplitude_prior(cfg: Config) -> tuple[float, float, float, float]:
    """The kernel's amplitude prior: its power (:data:`~pylensfit._kernels_nb.AMP_UNIFORM`
    for the uniform prior; any finite power is a power law), the power of ``S`` in ``ln
    L``, its limits."""
    uniform = cfg.amplitude_prior == "uniform"
    amp_pow = AMP_UNIFORM if uniform else float(cfg.amplitude_prior_power)
    amp_lns = amp_pow - 1.0 if cfg.amplitude_prior == "flux" else 0.0
    flux_prior = cfg.amplitude_prior == "flux"
    amp_lo = float(cfg.amplitude_prior_min) if flux_prior else 0.0
    amp_hi = float(cfg.amplitude_prior_max) if flux_prior else np.inf
    return amp_pow, amp_lns, amp_lo, amp_hi


def _kernel_weights(cfg: Config, bank: ModelBank, fb: _FoldedBank, size_prior: SizePrior | None,
                    size_marginal_prior: Prior | None, lnL_r_groups: np.ndarray | None
                    ) -> tuple[_Weights, _FoldedBank]:  # fmt: skip
    """The kernel's priors and weights, and the folded bank of the sizes they keep."""
    coarse = fb.coarse
    n_b = bank.n_r // bank.n_sizes
    ln_pi = np.full(n_b, -np.log(n_b))
    node_w, w_star, fb = _size_weights(cfg, bank, fb, size_prior, n_b)
    mp = size_marginal_prior if size_marginal_prior is not None else Prior()
    e_w = mp.pdf(bank.egrid[:, 0], bank.egrid[:, 1])
    e_w = e_w / e_w.sum()
    e_w_c = np.full(coarse.n_e, 1.0 / coarse.n_e)
    e_grp = _e_groups(lnL_r_groups, bank.n_e)
    amp = _amplitude_prior(cfg)
    r_w = np.asarray(bank.r_weights, dtype=float)
    rw_c = np.tile(r_w, bank.n_r // bank.n_sizes)[coarse.cols[:-1] % bank.n_r][: coarse.n_r]
    wts = _Weights(n_b=n_b, ln_pi=ln_pi, node_w=node_w, w_star=w_star, e_w=e_w, e_grp=e_grp,
                   n_grp=int(e_grp.max()) + 1, amp=amp, b2=cfg.position_prior_sigma**2,
                   e_w_c=e_w_c, rw_c=rw_c)  # fmt: skip
    return wts, fb


@dataclass(frozen=True)
class _Grid:
    """The kernel's results for every galaxy of the window (filled block by block)."""

    lnle: np.ndarray  # (n_gal, n_e) ln L(e)
    lnleb: np.ndarray  # (n_gal, n_e, n_b) per bulge fraction
    lnlr: np.ndarray  # (n_gal, n_grp, n_r + 1) ln L(r) per group of e cells
    best: np.ndarray  # (n_gal,) the most likely model
    hbest: np.ndarray  # its h*
    xb: np.ndarray  # its peak, from the origin (xc, yc)
    yb: np.ndarray
    cubic_g: np.ndarray  # fitted with the third-order expansion in position


def _recentre_block(win: _Window, prod: _Products, wts: _Weights, cfg: Config, sl: slice,
                    coarse_psf: tuple) -> np.ndarray:  # fmt: skip
    """Pass 1 on a block, on a coarse subset of models: move the origin to the peak of the
    most likely model, so that the Laplace step of every model near it is short.

    Returns the faint galaxies (S/N of that model below ``cfg.cubic_snr``), whose models'
    peaks spread over a good fraction of a pixel: pass 2 fits them with the third-order
    expansion in position.
    """
    fb = prod.fb
    coarse = fb.coarse
    m = sl.stop - sl.start
    S_c, mxx_c, mxy_c, myy_c = coarse_psf
    tmp = (np.empty((m, coarse.n_e)), np.empty((m, coarse.n_e, 1)),
           np.empty((m, 1, coarse.n_r + 1)), np.empty(m, dtype=np.int64), np.empty(m),
           np.empty(m), np.empty(m))  # fmt: skip
    laplace_grid(
        prod.folded(sl, False, fb.coarse_G), fb.coarse_members, _NO_MIX[0],
        _NO_MIX[0], _NO_MIX[1], m, coarse.n_e,
        coarse.n_r, coarse.n_r, S_c, mxx_c, mxy_c, myy_c, win.sigma[sl],
        win.x0[sl] - win.xc[sl], win.y0[sl] - win.yc[sl], wts.b2, cfg.max_newton_step,
        wts.rw_c, win.bank.star_weight, np.zeros(1), wts.e_w_c,
        np.zeros(coarse.n_e, dtype=np.int64), *wts.amp, False,
        *tmp,
    )  # fmt: skip
    step_x, step_y = tmp[5], tmp[6]
    move = np.isfinite(step_x) & np.isfinite(step_y) & ~win.no_peak[sl]
    win.xc[sl] += np.where(move, step_x, 0.0)
    win.yc[sl] += np.where(move, step_y, 0.0)
    snr_c = tmp[4] / (win.sigma[sl] * np.sqrt(S_c[tmp[3]]))
    return snr_c < cfg.cubic_snr


def _fit_block(win: _Window, prod: _Products, wts: _Weights, cfg: Config, grid: _Grid,
               idx: np.ndarray, cubic: bool) -> None:  # fmt: skip
    """Pass 2 on the galaxies ``idx`` of a block: every model, into ``grid``."""
    bank, pb, fb = win.bank, win.pb, prod.fb
    n_e, n_r, k = bank.n_e, bank.n_r, idx.size
    out = (np.empty((k, n_e)), np.empty((k, n_e, wts.n_b)),
           np.empty((k, wts.n_grp, n_r + 1)), np.empty(k, dtype=np.int64),
           np.empty(k), np.empty(k), np.empty(k))  # fmt: skip
    laplace_grid(
        prod.folded(idx, cubic), fb.members, fb.mix_a, fb.mix_b, fb.mix_f,
        k, n_e, n_r, bank.n_sizes,
        pb.S, pb.mxx, pb.mxy, pb.myy,
        win.sigma[idx], win.x0[idx] - win.xc[idx], win.y0[idx] - win.yc[idx], wts.b2,
        cfg.max_newton_step, wts.node_w, wts.w_star, wts.ln_pi, wts.e_w, wts.e_grp,
        *wts.amp, cubic,
        *out,
    )  # fmt: skip
    (grid.lnle[idx], grid.lnleb[idx], grid.lnlr[idx], grid.best[idx], grid.hbest[idx],
     grid.xb[idx], grid.yb[idx]) = out  # fmt: skip


def _evaluate_grid(win: _Window, prod: _Products, wts: _Weights, cfg: Config) -> _Grid:
    """The likelihood of every galaxy on the model grid, block by block: the centring
    pass on the coarse models (:func:`_recentre_block`), then every model
    (:func:`_fit_block`), the faint galaxies and the others apart."""
    n_gal, bank, pb = win.n_gal, win.bank, win.pb
    grid = _Grid(lnle=np.empty((n_gal, bank.n_e)), lnleb=np.empty((n_gal, bank.n_e, wts.n_b)),
                 lnlr=np.empty((n_gal, wts.n_grp, bank.n_r + 1)),
                 best=np.empty(n_gal, dtype=np.int64), hbest=np.empty(n_gal),
                 xb=np.empty(n_gal), yb=np.empty(n_gal),
                 cubic_g=np.zeros(n_gal, dtype=bool))  # fmt: skip
    # the PSF bank's values at the coarse models, once for every block
    coarse_psf = tuple(a[prod.fb.coarse.cols] for a in (pb.S, pb.mxx, pb.mxy, pb.myy))
    for s0 in range(0, n_gal, cfg.block_size):
        sl = slice(s0, min(s0 + cfg.block_size, n_gal))
        low = _recentre_block(win, prod, wts, cfg, sl, coarse_psf)
        grid.cubic_g[sl] = low
        for sel, cubic in ((np.flatnonzero(low), True), (np.flatnonzero(~low), False)):
            if sel.size == 0:
                continue
            _fit_block(win, prod, wts, cfg, grid, sel + s0, cubic)
    return grid


@dataclass(frozen=True)
class _RefineKernel:
    """Per-galaxy inputs and priors of the kernel that :func:`_refine_grid` runs again."""

    sigma: np.ndarray  # (n_gal,) noise
    x0: np.ndarray  # (n_gal,) catalogue positions from the origin of the expansion
    y0: np.ndarray
    b2: float
    node_w: np.ndarray
    w_star: float
    ln_pi: np.ndarray
    amp: tuple[float, float, float, float]


def _refined(win: _Window, prod: _Products, wts: _Weights, grid: _Grid, cfg: Config,
             psf: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The e grid returned, ``ln L(e)`` and per fraction on it: the bank's, or with
    ``cfg.e_refine > 1`` the finer grid, every galaxy interpolated and the narrow ones
    fitted again there (:func:`_refine_grid`)."""
    if cfg.e_refine > 1:
        ok = ~win.bad & np.isfinite(grid.lnle).all(axis=1)
        kern = _RefineKernel(sigma=win.sigma, x0=win.x0 - win.xc, y0=win.y0 - win.yc,
                             b2=wts.b2, node_w=wts.node_w, w_star=wts.w_star,
                             ln_pi=wts.ln_pi, amp=wts.amp)  # fmt: skip
        return _refine_grid(cfg, psf, win.bank, grid.lnle, grid.lnleb, ok, grid.cubic_g,
                            prod.rows, kern)  # fmt: skip
    return win.bank.egrid, grid.lnle, grid.lnleb


def _collapse_groups(lnlr: np.ndarray, n_r: int, n_grp: int
                     ) -> tuple[np.ndarray, np.ndarray | None]:  # fmt: skip
    """``ln L(r)`` summed over all e cells, and the groups apart where there are several."""
    if n_grp > 1:
        lnlr_grp = lnlr
        lnlr = lnlr[:, 0].copy()
        lnlr[:, :n_r] = _logsumexp_groups(lnlr_grp[:, :, :n_r])
        return lnlr, lnlr_grp
    return lnlr[:, 0], None


def _assemble_fits(win: _Window, wts: _Weights, grid: _Grid, egrid: np.ndarray,
                   lnle: np.ndarray, lnleb: np.ndarray, cfg: Config) -> StampFits:  # fmt: skip
    """The :class:`StampFits`: every row shifted to its maximum, the failed fits and the
    stars flagged, the most likely model's parameters."""
    bank, pb, flags, bad = win.bank, win.pb, win.flags, win.bad
    n_r, n_b, w_star = bank.n_r, wts.n_b, wts.w_star
    best, hbest, sigma = grid.best, grid.hbest, win.sigma
    lnlr, lnlr_grp = _collapse_groups(grid.lnlr, n_r, wts.n_grp)
    peak = lnle.max(axis=1)
    # a stamp of absurd values (a pixel at 1e30) gives ln L a range beyond float32's: -inf
    # cells in the returned rows, which no posterior can use; failed like a NaN row
    with np.errstate(over="ignore", invalid="ignore"):
        lnL = (lnle - peak[:, None]).astype(np.float32)
        failed = (~np.isfinite(peak) | ~np.isfinite(lnle).all(axis=1)
                  | ~np.isfinite(lnL).all(axis=1))  # fmt: skip
        flags[failed & ~bad] |= _flags.flag_value("FIT_FAILED")
        dead = bad | failed
        lnL[dead] = np.nan
        lnL_bulge = lnL_star = None
        if n_b > 1:  # per bulge fraction, for a population prior over them
            lnL_bulge = np.moveaxis(lnleb - peak[:, None, None], 2, 1).astype(np.float32)
            lnL_bulge[dead] = np.nan
            lnL_star = np.where(dead, np.nan, lnlr[:, n_r] + np.log(w_star) - peak)
        lnL_r = (lnlr - peak[:, None]).astype(np.float32)
        lnL_r[dead] = np.nan
        if lnlr_grp is not None:
            lnlr_grp = (lnlr_grp - peak[:, None, None]).astype(np.float32)
            lnlr_grp[dead] = np.nan

    ir_best = lnlr.argmax(axis=1)
    radii = np.append(bank.radii, 0.0)
    r_best = radii[ir_best]
    is_star = ((ir_best == n_r) | (r_best < cfg.point_source_size)) & ~dead
    flags[is_star] |= _flags.flag_value("STAR")
    S_best = pb.S[best]
    ie_best = np.where(best == bank.n_models - 1, -1, best // max(n_r, 1))
    e_best = np.where(ie_best[:, None] >= 0, bank.egrid[np.maximum(ie_best, 0)], 0.0)
    nanif = np.where(dead, np.nan, 1.0)
    fracs = bank.bulge if bank.bulge is not None else np.full(n_r, cfg.bulge_fraction)
    bulge_best = np.where(ie_best >= 0, fracs[best % max(n_r, 1)], np.nan) * nanif
    c = win.c
    return StampFits(
        egrid=egrid.copy(),
        lnL=lnL,
        lnL_peak=np.where(dead, np.nan, peak),
        r_best=r_best * nanif,
        flux=hbest / S_best * nanif,
        x=(c + win.xc + grid.xb + win.shift_x) * nanif,
        y=(c + win.yc + grid.yb + win.shift_y) * nanif,
        snr=hbest / (sigma * np.sqrt(S_best)) * nanif,
        is_star=is_star,
        flags=flags,
        e1_best=e_best[:, 0] * nanif,
        e2_best=e_best[:, 1] * nanif,
        meta={"model": cfg.model, "e_step": cfg.output_e_step, "r_step": cfg.r_step,
              "r_max": cfg.r_max, "e_refine": int(cfg.e_refine)},  # fmt: skip
        lnL_bulge=lnL_bulge,
        lnL_star=lnL_star,
        bulge_fractions=None if n_b == 1 else np.asarray(bank.bulge[:: bank.n_sizes], float),
        bulge_sizes=None if bank.bulge_size is None else np.asarray(
            bank.bulge_size[:: bank.n_sizes], float),
        lnL_r=lnL_r,
        bulge_best=bulge_best,
        stamp=np.full(win.n_gal, win.n),
        lnL_r_grouped=lnlr_grp,
    )


def _fit_window(stamps: np.ndarray, psf: np.ndarray, sigma: np.ndarray, cfg: Config,
                cx: np.ndarray, cy: np.ndarray, size_prior: SizePrior | None,
                size_marginal_prior: Prior | None,
                lnL_r_groups: np.ndarray | None = None) -> StampFits:  # fmt: skip
    """:func:`fit_stamps` on ``cfg.stamp_size`` windows (one stamp size for all).

    The stages: the windows cleaned, transformed and centred (:func:`_prepare_window`),
    the kernel's priors (:func:`_kernel_weights`), the likelihood on the model grid
    (:func:`_evaluate_grid`), the finer e grid (:func:`_refined`) and the result
    (:func:`_assemble_fits`).
    """
    win = _prepare_window(stamps, psf, sigma, cfg, cx, cy)
    fb = _folded_bank(cfg, win.bank)
    wts, fb_kept = _kernel_weights(cfg, win.bank, fb, size_prior, size_marginal_prior,
                                   lnL_r_groups)  # fmt: skip
    # the buffer holds the products with every column of the bank, coarse ones included
    prod = _products(win, cfg, fb_kept, fb.G[0].shape[1])
    grid = _evaluate_grid(win, prod, wts, cfg)
    egrid, lnle, lnleb = _refined(win, prod, wts, grid, cfg, psf)
    return _assemble_fits(win, wts, grid, egrid, lnle, lnleb, cfg)


@lru_cache(maxsize=4)
def _fine_lattice(step: float, e_max: float, k: int):
    """Index maps between the grid of ``step`` and the finer one of ``step / k``: the
    coarse cells' lattice coordinates, each fine cell's coarse parent (``n_e``: none), its
    3 x 3 fine neighbours (``n_f``: none) and its segment (fine row, coarse column)."""
    coarse = ellipticity_grid(step, emax=e_max)
    fine = ellipticity_grid(step / k, emax=e_max)
    lat = np.rint(coarse / step - 0.5).astype(np.int64)
    flat = np.rint(fine / (step / k) - 0.5).astype(np.int64)
    n_e, n_f = len(lat), len(flat)
    c_of = {(int(a), int(b)): i for i, (a, b) in enumerate(lat)}
    f_of = {(int(a), int(b)): i for i, (a, b) in enumerate(flat)}
    parent = np.array([c_of.get((int(a) // k, int(b) // k), n_e) for a, b in flat])
    nbr = np.array([[f_of.get((int(a) + da, int(b) + db), n_f) for da in (-1, 0, 1)
                     for db in (-1, 0, 1)] for a, b in flat])  # fmt: skip
    seg_of = (flat[:, 1] - flat[:, 1].min()) * (n_f + 1) + flat[:, 0] // k
    return lat, parent, nbr, seg_of


def _refine_grid(cfg: Config, psf, bank, lnle, lnleb, ok, cubic_g, rows_fn,
                 kern: _RefineKernel):
    """``ln L(e)`` on the finer grid of ``cfg.e_refine`` (adaptive refinement).

    Every usable galaxy's ``ln L`` (and each bulge fraction's) is interpolated from the
    ``e_step`` grid onto the cells ``e_step / e_refine`` (:func:`pylensfit.shear.
    refine_lnL`, the quintic that the Bayesian integrals use). A galaxy whose ``e_step``
    cells within ``refine_lnl`` of the maximum all lie within ``h`` cells of its peak cell
    (in either component), with ``(h + 1/2) e_step + e_step / e_refine <= refine_width``,
    is then evaluated again, exactly, on the fine cells of those coarse cells and on the
    fine cells next to them: the likelihood that the coarse grid samples too sparsely is
    computed where it matters, at the cost of the window's models only. Elsewhere its
    values stay interpolated (``exp(-12)`` or less of the peak; the emulation of
    ``benchmarks/studies/egrid_refinement.py`` found interpolated values outside a
    window of 4-6 sigma as good as exact ones).

    The window's products are the unfolded ones (a window has none of the square's
    symmetries): the half-plane of frequencies with the Hermitian weights. They are made
    per segment, the fine cells of one fine row within one coarse cell (adjacent columns
    of the fine bank: a view, no copy), for every galaxy whose window meets it at once;
    each galaxy's window then goes through the kernel with its own models.

    Returns the fine grid, ``ln L(e)`` ``(n, n_f)`` and per fraction ``(n, n_f, n_b)``
    (NaN for unusable rows), on the scale of ``lnle``.
    """
    k = int(cfg.e_refine)
    cfg_f = cfg.replace(e_step=cfg.output_e_step, e_refine=1)
    bank_f = model_bank(cfg_f)
    fine = bank_f.egrid
    n_gal, n_e = lnle.shape
    n_b = lnleb.shape[2]
    n_r = bank.n_r
    n_f = fine.shape[0]
    lnle_f = np.full((n_gal, n_f), np.nan)
    lnleb_f = np.full((n_gal, n_f, n_b), np.nan)
    g_ok = np.flatnonzero(ok)
    if g_ok.size == 0:
        return fine, lnle_f, lnleb_f

    def interpolated(x):  # rows of ln L on the e_step grid, each to its own maximum
        top = x.max(axis=1)
        out = np.full((x.shape[0], n_f), -np.inf)
        live = np.isfinite(top)
        if live.any():
            xi, grid = refine_lnL(x[live] - top[live, None], bank.egrid, refine=k)
            if grid.shape != fine.shape or not np.allclose(grid, fine):
                raise RuntimeError("the refined e grid is not the fine model bank's")
            out[live] = xi + top[live, None]
        return out

    lnle_f[g_ok] = interpolated(lnle[g_ok])
    xb = np.moveaxis(lnleb[g_ok], 2, 1).reshape(-1, n_e)
    lnleb_f[g_ok] = np.moveaxis(interpolated(xb).reshape(g_ok.size, n_b, n_f), 1, 2)

    # the windows: the coarse cells within refine_lnl of the maximum, as their fine
    # cells, and the fine cells next to those
    step, fstep = cfg.e_step, cfg.output_e_step
    lat, parent, nbr, seg_of = _fine_lattice(step, cfg.e_max, k)
    x = lnle[g_ok]
    pk = np.argmax(x, axis=1)
    near = x >= (x[np.arange(g_ok.size), pk] - cfg.refine_lnl)[:, None]
    reach = np.where(near, np.abs(lat[None, :, :] - lat[pk][:, None, :]).max(axis=2), 0)
    go = (reach.max(axis=1) + 0.5) * step + fstep <= cfg.refine_width * (1 + 1e-9)
    if not go.any():
        return fine, lnle_f, lnleb_f
    gal = g_ok[go]
    near_f = np.zeros((gal.size, n_f + 1), dtype=bool)
    near_f[:, :n_f] = np.pad(near[go], ((0, 0), (0, 1)))[:, parent]
    window = near_f[:, nbr].any(axis=2)  # (n_go, n_f)

    pb_f = _psf_bank(psf, cfg_f, bank_f)
    n = cfg.stamp_size
    _, _, w = rfft_frequencies(n)
    wk = w.ravel() * _interior(n, cfg.k_max) / n**2
    if bank_f.rows is not None:
        wk = wk[bank_f.rows]
    G = bank_f.G
    dtype = np.dtype(cfg.dtype)
    node_w = kern.node_w
    live_r = node_w > 0
    table = amplitude_table(kern.amp[0])
    # segments (seg_of): the fine cells of one fine row within one coarse column
    # (adjacent columns of the bank), one product each for every galaxy that needs it
    for cubic in (False, True):
        sel = np.flatnonzero(cubic_g[gal] == cubic)
        for c0 in range(0, sel.size, 128):
            part = sel[c0 : c0 + 128]
            idx = gal[part]
            R = rows_fn(idx, cubic)
            if bank_f.rows is not None:
                R = R[:, bank_f.rows]
            q = R.shape[0] // idx.size
            R = (R * wk).astype(dtype).reshape(q, idx.size, -1)
            star = R @ G[:, -1]  # (q, n_g)
            gi, cells = np.nonzero(window[part])  # galaxy-major pairs
            bounds = np.searchsorted(gi, np.arange(idx.size + 1))
            B = np.empty((q, gi.size, n_r), dtype=dtype)
            seg = seg_of[cells]
            order = np.argsort(seg, kind="stable")
            for grp in np.split(order, np.flatnonzero(np.diff(seg[order])) + 1):
                gu, ui = np.unique(gi[grp], return_inverse=True)
                f0, f1 = int(cells[grp].min()), int(cells[grp].max()) + 1
                out = (R[:, gu, :].reshape(q * gu.size, -1) @ G[:, f0 * n_r : f1 * n_r])
                B[:, grp, :] = out.reshape(q, gu.size, f1 - f0, n_r)[:, ui, cells[grp] - f0, :]
            for a, g in enumerate(idx):
                win = cells[bounds[a] : bounds[a + 1]]
                nw = win.size
                prod = np.concatenate([B[:, bounds[a] : bounds[a + 1], :].reshape(q, -1),
                                       star[:, a : a + 1]], axis=1)[None]  # fmt: skip
                j = np.arange(nw * n_r + 1, dtype=np.int64)
                j[:-1][~np.tile(live_r, nw)] = -1
                gid = np.append((win[:, None] * n_r + np.arange(n_r)[None, :]).ravel(),
                                bank_f.n_models - 1)  # fmt: skip
                res = (np.empty((1, nw)), np.empty((1, nw, n_b)), np.empty((1, 1, n_r + 1)),
                       np.empty(1, dtype=np.int64), *np.empty((3, 1)))
                laplace_grid_tab(
                    np.ascontiguousarray(prod), j[:, None], _NO_MIX[0], _NO_MIX[0], _NO_MIX[1],
                    1, nw, n_r, bank.n_sizes, pb_f.S[gid], pb_f.mxx[gid], pb_f.mxy[gid],
                    pb_f.myy[gid], kern.sigma[g : g + 1], kern.x0[g : g + 1],
                    kern.y0[g : g + 1], kern.b2, cfg.max_newton_step, node_w,
                    kern.w_star, kern.ln_pi, np.full(nw, 1.0 / nw),
                    np.zeros(nw, dtype=np.int64), *kern.amp, cubic, *table, *res,
                )  # fmt: skip
                lnle_f[g, win] = res[0][0]
                lnleb_f[g, win, :] = res[1][0]
    return fine, lnle_f, lnleb_f
