"""The likelihood on the model grid on a JAX device (``Config.backend``): the same
stages as :func:`~pylensfit.likelihood.evaluate.evaluate_grid`, each block of galaxies
in one compiled call.

Per block, on the device: the windows' transforms and their centring on the peak of the
cross-correlation with a round model (:func:`~pylensfit.likelihood.windows.centre`), the
Fourier rows of the galaxies (phase ramp to the centres, PSF, frequency factors), the
folded matrix products with the coarse models, the centring pass's Laplace terms and
the move of the centres, the rows again at the new centres, the products with every
model (the bulge+disc fractions between the pure ones mixed from them), the Laplace
terms (position, the third-order refinement of the faint galaxies, amplitude, position
prior: :mod:`~pylensfit.likelihood.device_math`), the most likely model, and the sums
over size and over e. The host cuts and cleans the windows
(:func:`~pylensfit.likelihood.windows.prepare_window` with ``on_device``), sends each
block's pixels and receives its ``ln L`` rows, centres and transforms; the stamp tiers,
the finer e grid (``e_refine > 1``) and the rows of the result stay on the host.

The matrix products run in ``Config.dtype`` at the full precision of that type (no
TF32 on GPUs), the terms after them in float64, as the numba kernels do: the result
equals the CPU path's to float32 round-off in the products' sums, not bit for bit.
"""

from __future__ import annotations

from functools import cache
from typing import NamedTuple

import numpy as np

from .. import flags as flag_bits
from ..config import Config
from ..models import rfft_frequencies
from .bank import keep_last
from .evaluate import Grid, Products
from .priors import Weights
from .windows import Window, round_reference

# JAX and the device's arithmetic, imported on first use (:func:`_load_jax`): importing
# JAX takes about 1.5 s, which the CPU path (and every worker process) should not pay
jax = jnp = dm = None


def _load_jax() -> bool:
    """Import JAX and :mod:`~pylensfit.likelihood.device_math` (once); False without JAX
    (an optional dependency: pip install pylensfit[gpu])."""
    global jax, jnp, dm
    if jax is None:
        try:
            # deferred: the CPU path needs none of it (the comment above the function)
            import jax as jax_mod
            import jax.numpy as jnp_mod

            from . import device_math as dm_mod  # JAX at its top: deferred with it
        except ImportError:
            return False
        jax, jnp, dm = jax_mod, jnp_mod, dm_mod
    return True


def resolve_backend(cfg: Config) -> str:
    """``"cpu"`` or ``"jax"``: ``cfg.backend``, with ``"auto"`` the device path where
    JAX is installed and its default device is not the CPU (a GPU or TPU)."""
    if cfg.backend == "cpu":
        return "cpu"
    if cfg.backend == "jax":
        if not _load_jax():
            raise ImportError("Config(backend='jax') needs JAX: pip install 'pylensfit[gpu]' "
                              "(and jax[cuda12] for an NVIDIA GPU)")  # fmt: skip
        return "jax"
    return "jax" if _load_jax() and jax.default_backend() != "cpu" else "cpu"


class _Static(NamedTuple):
    """The block function's settings, fixed at compilation (hashable)."""

    n_base: int  # the folded columns read from the products, the mixed ones after them
    n_sub: int
    w_star: float
    b2: float
    max_step2: float
    amp: tuple
    cubic_snr: float
    rad2: float  # the square of the centring's search radius


def _x64():
    """A context in which JAX makes float64 arrays (``jax.enable_x64``; before JAX 0.8,
    ``jax.experimental.enable_x64``)."""
    ctx = getattr(jax, "enable_x64", None)
    if ctx is None:
        from jax.experimental import enable_x64 as ctx  # older JAX: the experimental name
    return ctx(True)


@cache
def _block_function():
    """The compiled block function (compiled again for each new shape or setting)."""
    return jax.jit(_block, static_argnames=("st",))


def _rows(D, xc, yc, a, q):
    """The galaxies' ``q`` rows ``h, grad h, Hess h`` (and the third derivatives) as
    ``(q, g, frequency)``, of :meth:`~pylensfit.likelihood.evaluate.Products.rows`."""
    kx, ky = a["kx"], a["ky"]
    ph = jnp.exp(1j * (kx[None] * xc[:, None] + ky[None] * yc[:, None]))
    Dp = D * ph * a["Pc"][None]
    r, i = Dp.real, Dp.imag
    out = [r, -kx * i, -ky * i, -kx * kx * r, -kx * ky * r, -ky * ky * r]
    if q == 10:
        out += [kx**3 * i, kx**2 * ky * i, kx * ky**2 * i, ky**3 * i]
    return jnp.stack(out)


#: characters chi[c, h] of the square's group (FoldedBank), as signs
_CHI = ((1, 1, 1, 1), (1, -1, 1, -1), (1, 1, -1, -1), (1, -1, -1, 1))


def _products(R, a, G, dtype):
    """The folded products of the rows ``R`` with the four characters' banks ``G``, of
    :meth:`~pylensfit.likelihood.evaluate.Products.folded`: ``(4, q, g, n_cols)``."""
    Rf = R[..., a["idx"]]  # (q, g, 4, n_k0)
    out = []
    for ch in range(4):
        keep = a[f"keep{ch}"]
        Rk = Rf[..., keep]
        Fh = sum(s * Rk[:, :, h] for h, s in enumerate(_CHI[ch])) * a["coef"][keep]
        out.append(jnp.matmul(Fh.astype(dtype), G[ch], precision=jax.lax.Precision.HIGHEST))
    return jnp.stack(out)


def _members(P, a, n_base):
    """The four models of every column from the characters' products ``P`` (with ``a``
    the mixed columns made from their two base columns first; None: none), ``(q, 4, g,
    n_cols)`` in the products' precision (the Laplace terms read each row in float64)."""
    if a is not None and a["mix_a"].size:
        mixed = a["mix_fa"] * P[..., a["mix_a"]] + a["mix_fm"] * P[..., a["mix_b"]]
        P = jnp.concatenate([P[..., :n_base], mixed], axis=-1)
    p0, p1, p2, p3 = P[0], P[1], P[2], P[3]
    s02, s13, d02, d13 = p0 + p2, p1 + p3, p0 - p2, p1 - p3
    return jnp.stack([s02 + s13, s02 - s13, d02 + d13, d02 - d13], axis=1)


def _laplace(V, cm, gal, st, cubic_g):
    """``ln L`` of every (member, galaxy, column) and its ``h*``, ``X*``: the Laplace
    terms of :func:`~pylensfit.likelihood.laplace_nb.laplace_lnl`. ``cm`` ``(6, 4, 1,
    n_cols)``; ``gal`` ``(sigma, x0, y0)`` of shape ``(1, g, 1)``; ``cubic_g`` the
    galaxies fitted with the third-order expansion (None: none)."""
    sig, x0, y0 = gal
    x, y, hs, hess, ok = dm.position(V, cm, sig, st.max_step2)
    if cubic_g is not None:
        x, y, hs, hess = dm.cubic(V, (x, y, hs, hess), ok & cubic_g, st.max_step2)
    iss = 1.0 / (sig * cm[1])
    val, dl = dm.amplitude(hs * iss, cm[0], cm[5], iss, st.amp)
    detm, quad = dm.position_prior(-dl * iss, hess, x - x0, y - y0, st.b2)
    return val - 0.5 * jnp.log(detm) - 0.5 * quad, hs, x, y


def _best(lnl, extra, valid):
    """Per galaxy the largest ``ln L`` over the valid slots, its slot (the first in the
    kernel's order: column, then member) and ``extra``'s values there; ``lnl`` and
    ``extra`` ``(4, g, n_cols)``; returns ``ln L`` as ``(g, slot)`` too, the slots
    ``column * 4 + member``."""
    flat = jnp.where(valid, lnl, -jnp.inf).transpose(1, 2, 0).reshape(lnl.shape[1], -1)
    s = jnp.argmax(flat, axis=1)
    g = jnp.arange(flat.shape[0])
    pick = [e[s % 4, g, s // 4] for e in extra]
    return flat, s, flat[g, s], pick


def _block(a, pix, gal, st: _Static):
    """One block: the windows ``pix`` transformed and centred, the centring pass on the
    coarse models, then every model and the sums (see the module's docstring). ``gal``:
    ``(x0, y0, sigma)``."""
    x0, y0, sigma = gal
    D3, xc, yc, no_peak = dm.centre(pix, x0, y0, a, st.rad2)
    D = D3.reshape(pix.shape[0], -1)
    dtype = a["G0"].dtype
    sig = sigma[None, :, None]
    # pass 1: the coarse models' best peak moves the origin
    V = _members(_products(_rows(D, xc, yc, a, 6), a, [a[f"C{c}"] for c in range(4)], dtype),
                 None, 0)  # fmt: skip
    g0 = (sig, (x0 - xc)[None, :, None], (y0 - yc)[None, :, None])
    lnl, hs, x, y = _laplace(V, a["cm_c"], g0, st, None)
    s_m = jnp.broadcast_to(a["cm_c"][0], lnl.shape)
    _, s, _, (h_c, x_c, y_c, s_c) = _best(lnl, (hs, x, y, s_m), a["valid_c"])
    move = jnp.isfinite(x_c) & jnp.isfinite(y_c) & ~no_peak
    xc = xc + jnp.where(move, x_c, 0.0)
    yc = yc + jnp.where(move, y_c, 0.0)
    low = h_c / (sigma * jnp.sqrt(s_c)) < st.cubic_snr
    # pass 2: every model, the faint galaxies with the third-order expansion
    P = _products(_rows(D, xc, yc, a, 10), a, [a[f"G{c}"] for c in range(4)], dtype)
    V = _members(P, a, st.n_base)
    g1 = (sig, (x0 - xc)[None, :, None], (y0 - yc)[None, :, None])
    lnl, hs, x, y = _laplace(V, a["cm"], g1, st, low[None, :, None])
    flat, s, best, (hb, xb, yb) = _best(lnl, (hs, x, y), a["valid"])
    buf = flat[:, a["slot_of_model"]]
    sums = (a["node_w"], a["ln_w"], st.w_star, a["ln_pi"], a["e_wg"], st.n_sub)
    lnle, lnlb, lnlr = dm.collapse(buf, best, sums)
    return {"lnle": lnle, "lnlb": lnlb, "lnlr": lnlr, "best": a["model_of_slot"][s],
            "h": hb, "x": xb, "y": yb, "xc": xc, "yc": yc, "low": low, "D": D3,
            "no_peak": no_peak}  # fmt: skip


def _slot_tables(members: np.ndarray, models) -> tuple[np.ndarray, np.ndarray]:
    """Every (member, column) slot's model constants ``(6, 4, 1, n_cols)`` (``S, sqrt S,
    mxx, mxy, myy, ln S``; the padding's where the slot has no model, as
    :func:`~pylensfit.likelihood.tile_nb.tile_tables` pads) and which slots have one."""
    valid = members >= 0
    j = np.where(valid, members, 0)
    S = np.where(valid, models.S[j], 1.0)
    cm = np.stack([S, np.sqrt(S), np.where(valid, models.mxx[j], -1.0),
                   np.where(valid, models.mxy[j], 0.0), np.where(valid, models.myy[j], -1.0),
                   np.log(S)])  # fmt: skip
    return cm.transpose(0, 2, 1)[:, :, None, :], valid.T[:, None, :]


#: the device arrays of the last banks and PSFs
_ON_DEVICE: dict = {}


def _bank_arrays(win: Window, prod: Products) -> dict:
    """The bank's and the PSF's arrays on the device (cached while they recur)."""
    fb, pb = prod.fb, win.pb
    key = (id(fb), id(pb))
    hit = _ON_DEVICE.get(key)
    if hit is not None and hit[0] is fb and hit[1] is pb:
        return hit[2]
    members = fb.members
    n_models = win.bank.n_models
    cm, valid = _slot_tables(members, pb.models())
    cm_c, valid_c = _slot_tables(fb.coarse_members, pb.models(fb.coarse.cols))
    slot_of_model = np.zeros(n_models, dtype=np.int64)
    c, h = np.nonzero(members >= 0)
    slot_of_model[members[c, h]] = c * 4 + h
    dt = prod.dtype
    host = {"kx": prod.kxf, "ky": prod.kyf, "Pc": prod.Pc, "idx": fb.idx, "coef": fb.coef,
            "cm": cm, "valid": valid, "cm_c": cm_c, "valid_c": valid_c,
            "slot_of_model": slot_of_model, "model_of_slot": np.maximum(members, 0).ravel(),
            "mix_a": fb.mix_a, "mix_b": fb.mix_b,
            "mix_fa": (1.0 - fb.mix_f).astype(dt), "mix_fm": fb.mix_f.astype(dt)}  # fmt: skip
    for ch in range(4):
        host[f"keep{ch}"] = fb.keep[ch]
        host[f"G{ch}"] = fb.G[ch]
        host[f"C{ch}"] = fb.coarse_G[ch]
    arrays = {k: jnp.asarray(v) for k, v in host.items()}
    keep_last(_ON_DEVICE, key, (fb, pb, arrays), 2)
    return arrays


def _weights(wts: Weights, cfg: Config, n_base: int) -> tuple[dict, _Static]:
    """The sums' weights on the device and the block function's settings."""
    s = wts.sums
    with np.errstate(divide="ignore"):
        ln_w = np.log(s.node_w)
    n_grp = int(s.e_grp.max()) + 1
    e_wg = np.zeros((s.e_w.size, n_grp))
    e_wg[np.arange(s.e_w.size), s.e_grp] = s.e_w
    arrays = {"node_w": jnp.asarray(s.node_w, dtype=jnp.float64), "ln_w": jnp.asarray(ln_w),
              "ln_pi": jnp.asarray(s.ln_pi, dtype=jnp.float64), "e_wg": jnp.asarray(e_wg)}
    st = _Static(n_base=n_base, n_sub=int(s.n_sub), w_star=float(s.w_star), b2=float(wts.b2),
                 max_step2=float(cfg.max_newton_step) ** 2,
                 amp=tuple(float(v) for v in wts.amp), cubic_snr=float(cfg.cubic_snr),
                 rad2=max(cfg.max_offset, 0.75) ** 2)
    return arrays, st


def _centring(win: Window, cfg: Config) -> dict:
    """The centring's arrays on the device (:func:`~.device_math.centre`)."""
    n, c = win.n, win.c
    kx, ky, w = rfft_frequencies(n)
    host = {"phase": np.exp(1j * (kx * c + ky * c)),
            "ref": round_reference(win.pb.P.reshape(kx.shape), cfg),
            "off": ((np.arange(n) + c) % n - c).astype(float),
            "kx1": kx[0], "ky1": ky[:, 0], "w": w / n**2}  # fmt: skip
    return {k: jnp.asarray(v) for k, v in host.items()}


def _padded(v: np.ndarray, n: int, fill) -> np.ndarray:
    """``v`` padded to ``n`` rows with ``fill``."""
    if len(v) == n:
        return v
    return np.concatenate([v, np.full((n - len(v), *v.shape[1:]), fill, dtype=v.dtype)])


def device_grid(win: Window, prod: Products, wts: Weights, cfg: Config) -> Grid:
    """:func:`~pylensfit.likelihood.evaluate.evaluate_grid` on the JAX device: the same
    :class:`~pylensfit.likelihood.evaluate.Grid`, and ``win.xc``, ``win.yc`` moved as
    the centring pass moves them. Every block is sent before the first result is read
    (JAX dispatches asynchronously); the last one is padded to the block's size, so
    that one compilation serves all."""
    n_gal, bank = win.n_gal, win.bank
    grid = Grid(lnle=np.empty((n_gal, bank.n_e)), lnleb=np.empty((n_gal, bank.n_e, wts.n_b)),
                lnlr=np.empty((n_gal, wts.n_grp, bank.n_r + 1)),
                best=np.empty(n_gal, dtype=np.int64), hbest=np.empty(n_gal),
                xb=np.empty(n_gal), yb=np.empty(n_gal),
                cubic_g=np.zeros(n_gal, dtype=bool))  # fmt: skip
    n = max(min(cfg.block_size, n_gal), 1)
    fn = _block_function()
    with _x64():
        a = dict(_bank_arrays(win, prod))
        w, st = _weights(wts, cfg, prod.fb.members.shape[0] - prod.fb.mix_a.size)
        a.update(w)
        a.update(_centring(win, cfg))
        sent = []
        for s0 in range(0, n_gal, n):
            sl = slice(s0, min(s0 + n, n_gal))
            gal = tuple(jnp.asarray(_padded(v[sl], n, f))
                        for v, f in ((win.x0, 0.0), (win.y0, 0.0), (win.sigma, 1.0)))
            sent.append((sl, fn(a, jnp.asarray(_padded(win.pixels[sl], n, 0.0)), gal, st)))
        for sl, out in sent:
            _unpack(sl, {k: np.asarray(v)[: sl.stop - sl.start] for k, v in out.items()},
                    grid, win)  # fmt: skip
    win.flags[win.no_peak & ~win.bad] |= flag_bits.flag_value("NO_PEAK")
    return grid


def _unpack(sl: slice, res: dict, grid: Grid, win: Window) -> None:
    """A block's results ``res`` into ``grid`` and ``win`` (the transforms, centres and
    peaks that the host did not compute)."""
    grid.lnle[sl], grid.lnleb[sl], grid.lnlr[sl] = res["lnle"], res["lnlb"], res["lnlr"]
    grid.best[sl], grid.hbest[sl] = res["best"], res["h"]
    grid.xb[sl], grid.yb[sl], grid.cubic_g[sl] = res["x"], res["y"], res["low"]
    win.xc[sl], win.yc[sl], win.no_peak[sl], win.D[sl] = (res["xc"], res["yc"],
                                                          res["no_peak"], res["D"])  # fmt: skip
