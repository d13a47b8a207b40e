"""The model bank folded by the symmetries of the square pixel grid: four products over an
octant of frequencies for each orbit of four models, the bulge+disc fractions between the
pure ones mixed in the kernel, and the coarse sub-grid of the centring pass."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..config import Config
from ..models import ModelBank, in_disc
from .bank import keep_last
from .grid_nb import Columns


@dataclass(frozen=True)
class Coarse:
    """The coarse sub-grid of the centring pass: bank columns, e cells and sizes."""

    cols: np.ndarray
    n_e: int
    n_r: int


@dataclass(frozen=True)
class FoldedBank:
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
    coarse: Coarse  # the coarse sub-grid of the centring pass, closed under the symmetries
    coarse_G: tuple  # per character, its columns (all of them base columns)
    coarse_members: np.ndarray  # (n_cols_c, 4) as members, in the coarse models' numbering
    # columns c >= n_base are (1 - f) column a + f column b: a = mix_a[c - n_base], ...
    mix_a: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    mix_b: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    mix_f: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def columns(self) -> Columns:
        """Every column, the kernel's :class:`~pylensfit.likelihood.grid_nb.Columns`."""
        return Columns(self.members, self.mix_a, self.mix_b, self.mix_f)

    def coarse_columns(self) -> Columns:
        """The coarse sub-grid's columns (none mixed)."""
        return Columns(self.coarse_members, NO_MIX[0], NO_MIX[0], NO_MIX[1])


#: characters chi[c, h] of the group h = (1, s1, s2, s1 s2): (+-1)^(a i + b j)
CHI = np.array([[1, 1, 1, 1], [1, -1, 1, -1], [1, 1, -1, -1], [1, -1, -1, 1]], dtype=float)

_FOLDED: dict = {}
NO_MIX = (np.zeros(0, dtype=np.int64), np.zeros(0))


def folded_bank(config: Config, bank: ModelBank) -> FoldedBank:
    """The bank of ``config`` folded (cached: the last four banks)."""
    key = (config.stamp_size, config.e_step, config.e_max, config.r_min, config.r_max,
           config.r_step, config.model, config.bulge_fraction, config.bulge_size_ratio,
           config.dtype, int(config.n_bulge_fractions), float(config.r_rel_step),
           bool(config.truncate_models), float(config.k_max),
           float(config.bulge_size_ratio2), tuple(config.sersic_ladder),
           float(config.r_floor))  # fmt: skip
    fb = _FOLDED.get(key)
    if fb is not None and fb[0] is bank:
        return fb[1]
    idx, coef, keep = _octant(config.stamp_size, config.k_max)
    orbits = _Orbits.of(bank)
    G = _folded_transforms(bank, orbits, idx, keep, config.dtype)
    coarse, coarse_G, cmem = _coarse_grid(bank, orbits, G, config.e_step)
    perm, mix_a, mix_b, mix_f = mixed_columns(bank, orbits.ie_rep.size)
    members = orbits.members
    if mix_a.size:
        G = tuple(np.ascontiguousarray(g[:, perm[: perm.size - mix_a.size]]) for g in G)
        members = np.ascontiguousarray(members[perm])
    fb = FoldedBank(idx=idx, coef=coef, keep=keep, G=G, members=members, coarse=coarse,
                    coarse_G=coarse_G, coarse_members=cmem, mix_a=mix_a, mix_b=mix_b,
                    mix_f=mix_f)  # fmt: skip
    keep_last(_FOLDED, key, (bank, fb), 4)
    return fb


def _octant(n: int, k_max: float) -> tuple[np.ndarray, np.ndarray, tuple]:
    """The octant of an ``n x n`` stamp's frequencies, ``0 <= jy <= jx < n/2`` (within
    ``|k| <= k_max`` where ``k_max > 0``): the half-plane index of each point's four
    images, each point's orbit weight, and per character the points where it can be
    non-zero (:class:`FoldedBank`'s ``idx``, ``coef``, ``keep``)."""
    nh = n // 2 + 1
    jmax = (n - 1) // 2
    a, b = np.tril_indices(jmax + 1)  # octant 0 <= b <= a <= jmax
    if k_max > 0:  # the disc |k| <= k_max (the stamp tiers)
        inside = in_disc(a * (2 * np.pi / n), b * (2 * np.pi / n), k_max)
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
    return idx, coef, keep


@dataclass(frozen=True)
class _Orbits:
    """The bank's e cells in orbits of the square's symmetries, each represented by its
    cell with ``e1, e2 > 0``, and the models of every folded column."""

    rep: np.ndarray  # (n_e,) the cell represents its orbit
    ie_rep: np.ndarray  # the representatives' cells
    orb: np.ndarray  # (n_e,) the orbit of each cell
    h: np.ndarray  # (n_e,) the group element that maps the representative on the cell
    members: np.ndarray  # (n_orb * n_r + 1, 4) the model h . (representative) of a column

    @classmethod
    def of(cls, bank: ModelBank) -> _Orbits:
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
        return cls(rep=rep, ie_rep=ie_rep, orb=orb, h=h, members=members)


def _folded_transforms(bank: ModelBank, orbits: _Orbits, idx: np.ndarray, keep: tuple,
                       dtype) -> tuple:  # fmt: skip
    """Per character, the folded transforms of the representatives' columns (and the
    point source's) on the octant points where it can be non-zero."""
    n_r = bank.n_r
    rep_cols = np.append((orbits.ie_rep[:, None] * n_r + np.arange(n_r)[None, :]).ravel(),
                         bank.n_models - 1)  # fmt: skip
    Gr = bank.G[:, rep_cols]
    idx_g = idx
    if bank.rows is not None:  # the bank holds only the disc's frequencies
        pos = np.full(bank.n * (bank.n // 2 + 1), -1, dtype=np.int64)
        pos[bank.rows] = np.arange(bank.rows.size)
        idx_g = pos[idx]
        if (idx_g < 0).any():
            raise RuntimeError("the model bank lacks frequencies of the likelihood's sums")
    Gh = np.einsum("ch,hkm->ckm", CHI, Gr[idx_g].astype(np.float64))
    return tuple(np.ascontiguousarray(Gh[ch][keep[ch]], dtype=dtype) for ch in range(4))


def _coarse_grid(bank: ModelBank, orbits: _Orbits, G: tuple, e_step: float
                 ) -> tuple[Coarse, tuple, np.ndarray]:  # fmt: skip
    """The coarse sub-grid of the centring pass, its folded transforms (columns of ``G``)
    and the models of its columns: e cells at every other lattice step in both
    components (a set closed under e1 -> -e1, e2 -> -e2) and every 5th size."""
    eg, n_r, rep, orb, h = bank.egrid, bank.n_r, orbits.rep, orbits.orb, orbits.h
    lat = np.rint(np.abs(eg) / e_step - 0.5).astype(int)
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
    gcols = np.append((orb[rep_c][:, None] * n_r + ir_c[None, :]).ravel(),
                      orbits.ie_rep.size * n_r)  # fmt: skip
    coarse = Coarse(cols=ccols, n_e=n_ec, n_r=n_rc)
    return coarse, tuple(np.ascontiguousarray(g[:, gcols]) for g in G), cmem


def mixed_columns(bank, n_orb: int):
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


def active_columns(fb: FoldedBank, bank, active: np.ndarray) -> FoldedBank:
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
    keep_last(_ACTIVE, key, (fb, sub), 2)
    return sub
