"""The likelihood on the model grid: the window's matrix products with the folded bank,
and the kernel's two passes on each block of galaxies (the centring pass on the coarse
models, then every model)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import Config
from .folded import CHI, FoldedBank
from .grid_nb import Laplace, Outputs, laplace_grid, laplace_grid_mixed
from .priors import Weights
from .windows import Window


@dataclass(frozen=True)
class Products:
    """The window's Fourier rows and their matrix products with the folded model bank."""

    win: Window
    fb: FoldedBank  # with the columns of the sizes that the size prior keeps
    kxf: np.ndarray  # (n_freq,) frequencies
    kyf: np.ndarray
    Pc: np.ndarray  # (n_freq,) conjugate PSF transform, or (n_gal, n_freq) one per galaxy
    dtype: np.dtype
    store: np.ndarray  # one buffer for every block's products: the pages are mapped once

    def rows(self, sl: slice | np.ndarray, cubic: bool) -> np.ndarray:
        """h, grad h, Hess h (and third derivatives) as ``(q * m, frequency)`` rows."""
        kxf, kyf, win = self.kxf, self.kyf, self.win
        ph = np.exp(1j * (kxf[None] * win.xc[sl, None] + kyf[None] * win.yc[sl, None]))
        Pc = self.Pc[None] if self.Pc.ndim == 1 else self.Pc[sl]
        Dp = win.D[sl].reshape(-1, kxf.size) * ph * Pc
        r, i = Dp.real, Dp.imag
        out = [r, -kxf * i, -kyf * i, -kxf * kxf * r, -kxf * kyf * r, -kyf * kyf * r]
        if cubic:
            out += [kxf**3 * i, kxf**2 * kyf * i, kxf * kyf**2 * i, kyf**3 * i]
        return np.concatenate(out, axis=0)

    def folded(self, sl: slice | np.ndarray, cubic: bool, Gf: tuple | None = None
               ) -> np.ndarray:  # fmt: skip
        """The products with every model (or the coarse ones), folded by the square's
        symmetries (FoldedBank)."""
        fb = self.fb
        Gf = fb.G if Gf is None else Gf
        R = self.rows(sl, cubic)[:, fb.idx]  # (q m, 4, octant)
        nc = Gf[0].shape[1]
        out = self.store[: 4 * R.shape[0] * nc].reshape(4, R.shape[0], nc)
        for ch in range(4):
            Fh = np.einsum("h,rhk->rk", CHI[ch], R[:, :, fb.keep[ch]])
            Fh *= fb.coef[fb.keep[ch]]
            np.matmul(Fh.astype(self.dtype), Gf[ch], out=out[ch])
        return out


def products(win: Window, cfg: Config, fb: FoldedBank, n_cols: int) -> Products:
    """The products of ``win`` with ``fb``'s columns, in a buffer for ``n_cols`` columns."""
    dtype = np.dtype(cfg.dtype)
    store = np.empty(4 * 10 * min(cfg.block_size, win.n_gal) * n_cols, dtype=dtype)
    return Products(win=win, fb=fb, kxf=win.kx.ravel(), kyf=win.ky.ravel(),
                    Pc=win.conj_psf(), dtype=dtype, store=store)  # fmt: skip


@dataclass(frozen=True)
class Grid:
    """The kernel's results for every galaxy of the window (filled block by block)."""

    lnle: np.ndarray  # (n_gal, n_e) ln L(e)
    lnleb: np.ndarray  # (n_gal, n_e, n_b) per bulge fraction
    lnlr: np.ndarray  # (n_gal, n_grp, n_r + 1) ln L(r) per group of e cells
    best: np.ndarray  # (n_gal,) the most likely model
    hbest: np.ndarray  # its h*
    xb: np.ndarray  # its peak, from the origin (xc, yc)
    yb: np.ndarray
    cubic_g: np.ndarray  # fitted with the third-order expansion in position


def _kernel(win: Window):
    """The kernel for ``win``'s PSF: one PSF, or one per galaxy (its sums per model mixed
    per galaxy)."""
    return laplace_grid if win.wp is None else laplace_grid_mixed


def _recentre_block(win: Window, prod: Products, wts: Weights, cfg: Config,
                    sl: slice) -> np.ndarray:  # fmt: skip
    """Pass 1 on a block, on a coarse subset of models (the folded bank's): move the
    origin to the peak of the most likely model, so that the Laplace step of every model
    near it is short.

    Returns the faint galaxies (S/N of that model below ``cfg.cubic_snr``), whose models'
    peaks spread over a good fraction of a pixel: pass 2 fits them with the third-order
    expansion in position.
    """
    fb = prod.fb
    m = sl.stop - sl.start
    out = Outputs.empty(m, fb.coarse.n_e, 1, 1, fb.coarse.n_r)
    cols = fb.coarse.cols
    _kernel(win)(prod.folded(sl, False, fb.coarse_G), fb.coarse_columns(),
                 win.models(cols, sl), win.galaxies(sl), wts.sums_c, wts.amp,
                 Laplace(wts.b2, cfg.max_newton_step, False), out)  # fmt: skip
    move = np.isfinite(out.x) & np.isfinite(out.y) & ~win.no_peak[sl]
    win.xc[sl] += np.where(move, out.x, 0.0)
    win.yc[sl] += np.where(move, out.y, 0.0)
    snr_c = out.h / (win.sigma[sl] * np.sqrt(win.model_S(cols[out.best], sl)))
    return snr_c < cfg.cubic_snr


def _fit_block(win: Window, prod: Products, wts: Weights, cfg: Config, grid: Grid,
               idx: np.ndarray, cubic: bool) -> None:  # fmt: skip
    """Pass 2 on the galaxies ``idx`` of a block: every model, into ``grid``."""
    bank = win.bank
    out = Outputs.empty(idx.size, bank.n_e, wts.n_b, wts.n_grp, bank.n_r)
    _kernel(win)(prod.folded(idx, cubic), prod.fb.columns(), win.models(sel=idx),
                 win.galaxies(idx), wts.sums, wts.amp,
                 Laplace(wts.b2, cfg.max_newton_step, cubic), out)  # fmt: skip
    (grid.lnle[idx], grid.lnleb[idx], grid.lnlr[idx], grid.best[idx], grid.hbest[idx],
     grid.xb[idx], grid.yb[idx]) = out  # fmt: skip


def evaluate_grid(win: Window, prod: Products, wts: Weights, cfg: Config) -> Grid:
    """The likelihood of every galaxy on the model grid, block by block: the centring
    pass on the coarse models (:func:`_recentre_block`), then every model
    (:func:`_fit_block`), the faint galaxies and the others apart."""
    n_gal, bank = win.n_gal, win.bank
    grid = Grid(lnle=np.empty((n_gal, bank.n_e)), lnleb=np.empty((n_gal, bank.n_e, wts.n_b)),
                lnlr=np.empty((n_gal, wts.n_grp, bank.n_r + 1)),
                best=np.empty(n_gal, dtype=np.int64), hbest=np.empty(n_gal),
                xb=np.empty(n_gal), yb=np.empty(n_gal),
                cubic_g=np.zeros(n_gal, dtype=bool))  # fmt: skip
    for s0 in range(0, n_gal, cfg.block_size):
        sl = slice(s0, min(s0 + cfg.block_size, n_gal))
        low = _recentre_block(win, prod, wts, cfg, sl)
        grid.cubic_g[sl] = low
        for sel, cubic in ((np.flatnonzero(low), True), (np.flatnonzero(~low), False)):
            if sel.size == 0:
                continue
            _fit_block(win, prod, wts, cfg, grid, sel + s0, cubic)
    return grid
