"""The finer e grid (``Config.e_refine``): every galaxy's ``ln L(e)`` interpolated onto it,
and the bright galaxies' fitted again there, in a window about their peak."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..config import Config
from ..grid import ellipticity_grid, refine_lnL
from ..models import ModelBank, model_bank, rfft_frequencies
from .amplitude_nb import amplitude_table
from .bank import MixedPSF, PairBank, PSFBank, interior
from .evaluate import Grid, Products
from .folded import NO_MIX
from .grid_nb import Amplitude, Columns, Galaxies, Laplace, Outputs, laplace_grid_tab
from .pairs import window_bank
from .priors import Weights
from .windows import Window


def refined(win: Window, prod: Products, wts: Weights, grid: Grid, cfg: Config,
            psf: np.ndarray | MixedPSF) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The e grid returned, ``ln L(e)`` and per fraction on it: the bank's, or with
    ``cfg.e_refine > 1`` the finer grid, every galaxy interpolated and the narrow ones
    fitted again there (:func:`_refine_grid`; ``psf`` the window's PSF image, or its
    :class:`~pylensfit.likelihood.bank.MixedPSF`)."""
    if cfg.e_refine > 1:
        ok = ~win.bad & np.isfinite(grid.lnle).all(axis=1)
        return _refine_grid(cfg, psf, win, prod.rows, wts, grid, ok)
    return win.bank.egrid, grid.lnle, grid.lnleb


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


def _refine_grid(cfg: Config, psf: np.ndarray | MixedPSF, win: Window, rows_fn, wts: Weights,
                 grid: Grid, ok: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """``ln L(e)`` on the finer grid of ``cfg.e_refine`` (adaptive refinement).

    Every usable galaxy's (``ok``) ``ln L`` (and each bulge fraction's) is interpolated
    from the ``e_step`` grid onto the cells ``e_step / e_refine``
    (:func:`pylensfit.grid.refine_lnL`, the quintic that the Bayesian integrals use). A
    galaxy whose ``e_step`` cells within ``refine_lnl`` of the maximum all lie within
    ``h`` cells of its peak cell (in either component), with ``(h + 1/2) e_step + e_step
    / e_refine <= refine_width``, is then evaluated again, exactly, on the fine cells of
    those coarse cells and on the fine cells next to them: the likelihood that the coarse
    grid samples too sparsely is computed where it matters, at the cost of the window's
    models only. Elsewhere its values stay interpolated (``exp(-12)`` or less of the
    peak; the emulation of ``benchmarks/studies/egrid_refinement.py`` found interpolated
    values outside a window of 4-6 sigma as good as exact ones).

    The window's products are the unfolded ones (a window has none of the square's
    symmetries): the half-plane of frequencies with the Hermitian weights. They are made
    per segment, the fine cells of one fine row within one coarse cell (adjacent columns
    of the fine bank: a view, no copy), for every galaxy whose window meets it at once
    (:func:`_segment_products`); each galaxy's window then goes through the kernel with
    its own models (:func:`_fit_cells`).

    Returns the fine grid, ``ln L(e)`` ``(n, n_f)`` and per fraction ``(n, n_f, n_b)``
    (NaN for unusable rows), on the scale of ``grid.lnle``.
    """
    k = int(cfg.e_refine)
    cfg_f = cfg.replace(e_step=cfg.output_e_step, e_refine=1)
    bank_f = model_bank(cfg_f)
    fine = bank_f.egrid
    lnle, lnleb = grid.lnle, grid.lnleb
    (n_gal, n_e), n_b, n_f = lnle.shape, lnleb.shape[2], fine.shape[0]
    out = (np.full((n_gal, n_f), np.nan), np.full((n_gal, n_f, n_b), np.nan))
    g_ok = np.flatnonzero(ok)
    if g_ok.size == 0:
        return fine, *out
    out[0][g_ok] = _interpolated(lnle[g_ok], win.bank.egrid, fine, k)
    xb = np.moveaxis(lnleb[g_ok], 2, 1).reshape(-1, n_e)
    out[1][g_ok] = np.moveaxis(_interpolated(xb, win.bank.egrid, fine, k)
                               .reshape(g_ok.size, n_b, n_f), 1, 2)  # fmt: skip
    go, window = _windows(cfg, lnle[g_ok], k)
    if not go.any():
        return fine, *out
    gal = g_ok[go]
    fb = _FineBank.of(cfg, cfg_f, bank_f, psf, wts.amp)
    gals = win.galaxies(slice(None))
    for cubic in (False, True):
        sel = np.flatnonzero(grid.cubic_g[gal] == cubic)
        lap = Laplace(wts.b2, cfg.max_newton_step, cubic)
        for c0 in range(0, sel.size, 128):
            part = sel[c0 : c0 + 128]
            idx = gal[part]
            R = rows_fn(idx, cubic)
            if fb.bank.rows is not None:
                R = R[:, fb.bank.rows]
            q = R.shape[0] // idx.size
            R = (R * fb.wk).astype(fb.dtype).reshape(q, idx.size, -1)
            segs = _segment_products(R, window[part], fb)
            _fit_cells(idx, segs, fb, (gals, wts, lap, win.wp), out)
    return fine, *out


def _interpolated(x: np.ndarray, egrid: np.ndarray, fine: np.ndarray, k: int) -> np.ndarray:
    """Rows ``x`` of ``ln L`` on the grid ``egrid``, each interpolated to the finer
    grid ``fine`` (``k`` times finer) relative to its own maximum."""
    top = x.max(axis=1)
    out = np.full((x.shape[0], fine.shape[0]), -np.inf)
    live = np.isfinite(top)
    if live.any():
        xi, grid = refine_lnL(x[live] - top[live, None], egrid, refine=k)
        if grid.shape != fine.shape or not np.allclose(grid, fine):
            raise RuntimeError("the refined e grid is not the fine model bank's")
        out[live] = xi + top[live, None]
    return out


def _windows(cfg: Config, x: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Which galaxies of the ``ln L`` rows ``x`` are fitted again, and their windows
    ``(n_go, n_f)``: the coarse cells within ``refine_lnl`` of the maximum, as their fine
    cells, and the fine cells next to those."""
    step, fstep = cfg.e_step, cfg.output_e_step
    lat, parent, nbr, _ = _fine_lattice(step, cfg.e_max, k)
    n_f = parent.size
    pk = np.argmax(x, axis=1)
    near = x >= (x[np.arange(x.shape[0]), pk] - cfg.refine_lnl)[:, None]
    reach = np.where(near, np.abs(lat[None, :, :] - lat[pk][:, None, :]).max(axis=2), 0)
    go = (reach.max(axis=1) + 0.5) * step + fstep <= cfg.refine_width * (1 + 1e-9)
    near_f = np.zeros((int(go.sum()), n_f + 1), dtype=bool)
    near_f[:, :n_f] = np.pad(near[go], ((0, 0), (0, 1)))[:, parent]
    return go, near_f[:, nbr].any(axis=2)


@dataclass(frozen=True)
class _FineBank:
    """The finer grid's model bank and what its products and the kernel need."""

    bank: ModelBank
    pb: PSFBank | PairBank
    wk: np.ndarray  # the frequencies' Hermitian weights (interior, / n^2)
    dtype: np.dtype
    seg_of: np.ndarray  # (n_f,) the segment of each fine cell (:func:`_fine_lattice`)
    table: tuple  # the amplitude prior's table

    @classmethod
    def of(cls, cfg: Config, cfg_f: Config, bank_f: ModelBank, psf: np.ndarray | MixedPSF,
           amp: Amplitude) -> _FineBank:  # fmt: skip
        """The fine bank ``bank_f`` of ``cfg_f`` under ``psf`` (its pair sums for a
        :class:`~pylensfit.likelihood.bank.MixedPSF`), for the fits of ``cfg`` with the
        amplitude prior ``amp``."""
        n = cfg.stamp_size
        _, _, w = rfft_frequencies(n)
        wk = w.ravel() * interior(n, cfg.k_max) / n**2
        if bank_f.rows is not None:
            wk = wk[bank_f.rows]
        return cls(bank=bank_f, pb=window_bank(psf, cfg_f, bank_f), wk=wk,
                   dtype=np.dtype(cfg.dtype),
                   seg_of=_fine_lattice(cfg.e_step, cfg.e_max, int(cfg.e_refine))[3],
                   table=amplitude_table(amp.power))  # fmt: skip


def _segment_products(R: np.ndarray, window: np.ndarray, fb: _FineBank) -> tuple:
    """The products of the weighted rows ``R`` ``(q, n_g, n_freq)`` of ``n_g`` galaxies
    with the fine cells of their windows ``(n_g, n_f)``: the point source's ``(q, n_g)``,
    the (galaxy-major) cells, each galaxy's bounds in them, and the products ``(q,
    n_pairs, n_r)``, a segment at a time."""
    G, n_r = fb.bank.G, fb.bank.n_r
    q = R.shape[0]
    star = R @ G[:, -1]  # (q, n_g)
    gi, cells = np.nonzero(window)  # galaxy-major pairs
    bounds = np.searchsorted(gi, np.arange(R.shape[1] + 1))
    B = np.empty((q, gi.size, n_r), dtype=fb.dtype)
    seg = fb.seg_of[cells]
    order = np.argsort(seg, kind="stable")
    for grp in np.split(order, np.flatnonzero(np.diff(seg[order])) + 1):
        gu, ui = np.unique(gi[grp], return_inverse=True)
        f0, f1 = int(cells[grp].min()), int(cells[grp].max()) + 1
        out = (R[:, gu, :].reshape(q * gu.size, -1) @ G[:, f0 * n_r : f1 * n_r])
        B[:, grp, :] = out.reshape(q, gu.size, f1 - f0, n_r)[:, ui, cells[grp] - f0, :]
    return star, cells, bounds, B


def _fit_cells(idx: np.ndarray, segs: tuple, fb: _FineBank, kern: tuple, out: tuple) -> None:
    """The kernel on each galaxy ``idx[a]``'s window of fine cells (``segs``:
    :func:`_segment_products`), with the window's galaxies, weights, Laplace settings and
    pair weights (None: one PSF) ``kern``; into ``out = (ln L(e), ln L_k(e))`` on the
    fine grid."""
    star, cells, bounds, B = segs
    gals, wts, lap, wp = kern
    n_r, q = fb.bank.n_r, B.shape[0]
    live_r = wts.sums.node_w > 0
    no_mix = (NO_MIX[0], NO_MIX[0], NO_MIX[1])
    for a, g in enumerate(idx):
        cw = cells[bounds[a] : bounds[a + 1]]
        nw = cw.size
        prod = np.concatenate([B[:, bounds[a] : bounds[a + 1], :].reshape(q, -1),
                               star[:, a : a + 1]], axis=1)[None]  # fmt: skip
        j = np.arange(nw * n_r + 1, dtype=np.int64)
        j[:-1][~np.tile(live_r, nw)] = -1
        gid = np.append((cw[:, None] * n_r + np.arange(n_r)[None, :]).ravel(),
                        fb.bank.n_models - 1)  # fmt: skip
        models = fb.pb.models(gid) if wp is None else fb.pb.galaxy_models(wp[g], gid)
        res = Outputs.empty(1, nw, wts.n_b, 1, n_r)
        sums = wts.sums._replace(e_w=np.full(nw, 1.0 / nw), e_grp=np.zeros(nw, dtype=np.int64))
        laplace_grid_tab(np.ascontiguousarray(prod), Columns(j[:, None], *no_mix),
                         models, Galaxies(*(v[g : g + 1] for v in gals)), sums,
                         wts.amp, fb.table, lap, res)  # fmt: skip
        out[0][g, cw] = res.lnle[0]
        out[1][g, cw, :] = res.lnlb[0]
