"""The per-model sums of a PSF mixed per galaxy, per pair of its PSFs
(:class:`~pylensfit.likelihood.bank.PairBank`), folded by the square's symmetries; the
PSF's part of the bank for either kind of PSF."""

from __future__ import annotations

import hashlib

import numpy as np

from ..config import Config
from ..models import rfft_frequencies
from ..psf import psf_transform
from .bank import MixedPSF, PairBank, PSFBank, keep_last, psf_bank
from .folded import CHI, FoldedBank, folded_bank

#: the last pair banks: a pipeline fits a cell's galaxies in several calls (blocks, stamp
#: tiers); an entry holds 40 floats per model for four PSFs (18 MB for Config()'s bank)
_PAIR_BANKS: dict = {}
_PAIR_BANKS_KEPT = 4


def pair_bank(images: np.ndarray, config: Config, bank) -> PairBank:
    """:class:`~pylensfit.likelihood.bank.PairBank` of the PSF images ``(K, N, N)``,
    reused while they recur.

    Every sum is ``sum_k W(k) G_j(k)^2`` over the half-plane of frequencies, ``W`` one
    of ``Re(P_a conj(P_b))`` times ``1, -kx^2, -kx ky, -ky^2``. The square's symmetries
    map a model's ``G^2`` on its orbit's as they map ``G`` (:class:`FoldedBank`), so the
    sums of the four models of an orbit are four products over the octant of
    frequencies with the characters' transforms of ``G^2`` of its representative
    (:func:`_folded_sums`): a quarter of the operations of the sums over the half-plane.
    """
    images = np.ascontiguousarray(images)
    key = (hashlib.blake2b(images.tobytes(), digest_size=16).digest(), images.shape,
           images.dtype.str, config.stamp_size, float(config.k_max), id(bank))  # fmt: skip
    hit = _PAIR_BANKS.get(key)
    if hit is not None and hit[0] is bank:
        return hit[1]
    n = config.stamp_size
    P = np.stack([psf_transform(im, n).ravel() for im in images])
    kx, ky, _ = rfft_frequencies(n)
    kx, ky = kx.ravel(), ky.ravel()
    a, b = np.triu_indices(len(images))
    q = (P[a] * np.conj(P[b])).real  # (n_pairs, n_freq)
    W = np.concatenate([q, -q * kx * kx, -q * kx * ky, -q * ky * ky])
    out = _folded_sums(W, folded_bank(config, bank), bank)
    S, mxx, mxy, myy = (np.ascontiguousarray(v) for v in np.split(out, 4))
    pb = PairBank(P=P, S=S, mxx=mxx, mxy=mxy, myy=myy, pair_a=a, pair_b=b)
    keep_last(_PAIR_BANKS, key, (bank, pb), _PAIR_BANKS_KEPT)
    return pb


#: the last banks' characters' transforms of G^2 (PSF-independent, float64: 63 MB for
#: Config()'s bank): a pipeline's cells share the bank of each stamp tier
_G2HAT: dict = {}
_G2HAT_KEPT = 2


def _g2hat(fb: FoldedBank, bank) -> tuple[tuple, np.ndarray]:
    """Per character ``chi``, ``(len(keep_chi), n_cols)`` ``sum_h chi(h) G_e(h k0)^2`` of
    each column's representative model ``e`` at the octant points ``k0`` where ``chi``
    can be non-zero, and the model order: model ``j`` is item ``order[j]`` of the
    ``(4, n_cols)`` flattened models ``h . e`` of the columns (cached: the last two
    folded banks)."""
    hit = _G2HAT.get(id(fb))
    if hit is not None and hit[0] is fb:
        return hit[1]
    rep = fb.members[:, 0]  # each column's model with e1, e2 > 0 (and the point source)
    idx_g = fb.idx
    if bank.rows is not None:  # the bank holds only the disc's frequencies
        pos = np.full(bank.n * (bank.n // 2 + 1), -1, dtype=np.int64)
        pos[bank.rows] = np.arange(bank.rows.size)
        idx_g = pos[fb.idx]
    out = tuple(np.empty((k.size, rep.size)) for k in fb.keep)
    for c0 in range(0, rep.size, 2048):  # in chunks: no bank-sized temporary
        G2 = np.square(bank.G[:, rep[c0 : c0 + 2048]][idx_g], dtype=np.float64)
        for ch in range(4):
            out[ch][:, c0 : c0 + 2048] = np.einsum("h,hkc->kc", CHI[ch], G2[:, fb.keep[ch]])
    M = fb.members.T.ravel()  # (4 n_cols,) the model h . e of each (h, column), or -1
    live = np.flatnonzero(M >= 0)
    order = live[np.argsort(M[live])]
    keep_last(_G2HAT, id(fb), (fb, (out, order)), _G2HAT_KEPT)
    return out, order


def _folded_sums(W: np.ndarray, fb: FoldedBank, bank) -> np.ndarray:
    """``(n_rows, n_models)`` the sums ``sum_k w(k) W_i(k) G_j(k)^2 / n^2`` over the
    interior half-plane (Hermitian weights ``w``) of every row ``W_i`` ``(n_rows,
    n_freq)``, an even function of ``k``, and every model ``j``: per column of ``fb``
    (an orbit of four models and a size), ``A_chi = sum_k0 c(k0) What_chi(k0)
    G2hat_chi(k0)`` per character (:func:`_g2hat`) and the model ``h . e`` ``sum_chi
    chi(h) A_chi``."""
    g2, order = _g2hat(fb, bank)
    Wh = W[:, fb.idx]  # (n_rows, 4, n_k0)
    A = np.stack([(np.einsum("h,rhk->rk", CHI[ch], Wh[:, :, fb.keep[ch]])
                   * fb.coef[fb.keep[ch]]) @ g2[ch] for ch in range(4)])  # fmt: skip
    n_rows = W.shape[0]
    B = (CHI.T @ A.reshape(4, -1)).reshape(4, n_rows, -1)  # (h, row, column)
    return np.take(B.transpose(1, 0, 2).reshape(n_rows, -1), order, axis=1)


def window_bank(psf, config: Config, bank) -> PSFBank | PairBank:
    """The PSF's part of ``bank``: :func:`~pylensfit.likelihood.bank.psf_bank` of a PSF
    image, :func:`pair_bank` of a :class:`~pylensfit.likelihood.bank.MixedPSF`'s images."""
    if isinstance(psf, MixedPSF):
        return pair_bank(psf.images, config, bank)
    return psf_bank(psf, config, bank)
