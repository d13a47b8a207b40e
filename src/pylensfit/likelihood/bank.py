"""The PSF's part of the model bank: each model's ``sum m^2`` and autocorrelation Hessian
under one PSF, cached over the last PSFs, or per pair of the PSFs that a per-galaxy PSF
is mixed from; the frequencies that the likelihood sums over."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from ..config import Config
from ..models import in_disc, rfft_frequencies
from ..psf import psf_transform
from .grid_nb import MixedModels, Models


@dataclass(frozen=True)
class PSFBank:
    """Per-PSF quantities: the PSF transform and the per-model sums that need no data."""

    P: np.ndarray  # (n_freq,) complex
    S: np.ndarray  # (n_models,) sum m^2
    mxx: np.ndarray  # (n_models,) Hessian of the model autocorrelation at 0
    mxy: np.ndarray
    myy: np.ndarray

    def models(self, cols: np.ndarray | None = None) -> Models:
        """The per-model sums of the models ``cols`` (default: all), the kernel's
        :class:`~pylensfit.likelihood.grid_nb.Models`."""
        if cols is None:
            return Models(self.S, self.mxx, self.mxy, self.myy)
        return Models(self.S[cols], self.mxx[cols], self.mxy[cols], self.myy[cols])


def interior(n: int, k_max: float = 0.0) -> np.ndarray:
    """``rfft2`` frequencies of an ``n x n`` stamp that are not Nyquist (``|j| < n/2``),
    and with ``k_max > 0`` no farther than ``k_max`` from the origin.

    The engine sums over these only. A Nyquist frequency stands for both ``+pi`` and
    ``-pi``, where neither an elliptical model nor a shift in position has one value:
    without it the likelihood is exactly covariant under the square's symmetries (a
    90-degree rotation of the data maps ``L(e)`` to ``L(-e)``), which
    :func:`folded_bank` uses. With the PSF at least Nyquist sampled the dropped
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


def keep_last(cache: dict, key, value, size: int, max_bytes: float | None = None) -> None:
    """Store ``value`` in ``cache``, dropping the oldest entries beyond ``size`` entries
    or, with ``max_bytes``, beyond that many bytes of arrays (:func:`array_bytes`; the
    newest entry is kept whatever its size)."""
    cache[key] = value
    while len(cache) > size:
        cache.pop(next(iter(cache)))
    if max_bytes is not None:
        sizes = {k: array_bytes(v) for k, v in cache.items()}
        total = sum(sizes.values())
        for k in list(cache)[:-1]:
            if total <= max_bytes:
                break
            total -= sizes[k]
            cache.pop(k)


def array_bytes(obj, seen: set | None = None) -> int:
    """The bytes of the numpy arrays that ``obj`` holds (in tuples, lists, dicts and
    dataclasses; each array counted once, a view as its base)."""
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return 0
    seen.add(id(obj))
    if isinstance(obj, np.ndarray):  # a view holds its base's memory
        return obj.nbytes if obj.base is None else array_bytes(obj.base, seen)
    if isinstance(obj, (tuple, list)):
        return sum(array_bytes(x, seen) for x in obj)
    if isinstance(obj, dict):
        return sum(array_bytes(x, seen) for x in obj.values())
    if hasattr(obj, "__dataclass_fields__"):
        return sum(array_bytes(getattr(obj, f), seen) for f in obj.__dataclass_fields__)
    return 0


#: the last PSFs' banks: a pipeline fits an image's galaxies with one PSF in several
#: calls (blocks, neighbour subtraction), or with one PSF per cell of a PSF over the
#: field (Config.psf_cells^2 per stamp tier, so 8 x 8 cells and two tiers need 128); a
#: precision block its renderings. An entry holds 4 floats per model (1.4 MB for
#: Config()'s 44,557 models).
_PSF_BANKS: dict = {}
_PSF_BANKS_KEPT = 144


def psf_bank(psf: np.ndarray, config: Config, bank) -> PSFBank:
    """:func:`_psf_bank_of` of the PSF image, reused while the same image and bank recur."""
    psf = np.ascontiguousarray(psf)
    key = (hashlib.blake2b(psf.tobytes(), digest_size=16).digest(), psf.shape, psf.dtype.str,
           config.stamp_size, float(config.k_max), id(bank))  # fmt: skip
    hit = _PSF_BANKS.get(key)
    if hit is not None and hit[0] is bank:
        return hit[1]
    pb = _psf_bank_of(psf, config, bank)
    keep_last(_PSF_BANKS, key, (bank, pb), _PSF_BANKS_KEPT)
    return pb


def _psf_bank_of(psf: np.ndarray, config: Config, bank) -> PSFBank:
    """The PSF's transform and each model's ``sum m^2`` and autocorrelation Hessian."""
    n = config.stamp_size
    P = psf_transform(psf, n)
    kx, ky, w = rfft_frequencies(n)
    p2 = (w * np.abs(P) ** 2 / n**2).ravel() * interior(n, config.k_max)
    kx = kx.ravel()
    ky = ky.ravel()
    W = np.stack([p2, -p2 * kx * kx, -p2 * kx * ky, -p2 * ky * ky])
    if bank.rows is not None:
        W = W[:, bank.rows]
    out = np.empty((4, bank.G.shape[1]))
    for c0 in range(0, bank.G.shape[1], 4096):  # in chunks: no bank-sized temporary
        out[:, c0 : c0 + 4096] = W @ np.square(bank.G[:, c0 : c0 + 4096], dtype=np.float64)
    return PSFBank(P=P.ravel(), S=out[0], mxx=out[1], mxy=out[2], myy=out[3])


@dataclass(frozen=True)
class MixedPSF:
    """Every stamp with its own PSF, a weighted sum of a few PSF images: stamp ``i``'s
    PSF is ``sum_c weights[c, i] P_c``, with ``P_c`` the transform of ``images[c]``
    normalised to unit flux on the stamp (:func:`pylensfit.psf.psf_transform`). With the
    PSFs at the corners of a galaxy's cell and its position's bilinear weights, the PSF
    interpolated at the galaxy (``Config.psf_interpolation = "fourier"``).

    The likelihood with such a PSF is exact in one fit per stamp: the data enter the
    sums as ``D conj(P)``, one vector per stamp, and every model's ``sum m^2`` and
    autocorrelation Hessian are quadratic in the PSF, sums over the pairs of images
    (:class:`PairBank`) weighted by ``w_c w_c'``.

    Parameters
    ----------
    images : numpy.ndarray
        ``(K, N, N)`` PSF images, each centred on ``[N//2, N//2]`` with the pixel
        response, any normalisation.
    weights : numpy.ndarray
        ``(K, n)`` each stamp's weight of each image, >= 0, summing to 1 over the images.
    """

    images: np.ndarray
    weights: np.ndarray

    def __post_init__(self) -> None:
        images = np.asarray(self.images, dtype=float)
        w = np.asarray(self.weights, dtype=float)
        if images.ndim != 3 or w.ndim != 2 or w.shape[0] != images.shape[0]:
            raise ValueError(f"MixedPSF: images (K, N, N) and weights (K, n), got "
                             f"{images.shape} and {w.shape}")  # fmt: skip
        if w.size and (np.any(~(w >= 0)) or not np.allclose(w.sum(axis=0), 1.0)):
            raise ValueError("MixedPSF: weights must be >= 0 and sum to 1 over the images")
        object.__setattr__(self, "images", images)
        object.__setattr__(self, "weights", w)

    @property
    def n_stamps(self) -> int:
        """The number of stamps the weights are for."""
        return self.weights.shape[1]

    @property
    def nearest(self) -> np.ndarray:
        """``(n,)`` each stamp's heaviest image."""
        return np.argmax(self.weights, axis=0)

    def take(self, idx: np.ndarray | slice) -> MixedPSF:
        """The same images with the weights of the stamps ``idx``."""
        return MixedPSF(self.images, self.weights[:, idx])


def subset_psf(psf, idx: np.ndarray | slice):
    """``psf`` for the stamps ``idx``: a PSF image as it is, a :class:`MixedPSF` with
    those stamps' weights."""
    return psf.take(idx) if isinstance(psf, MixedPSF) else psf


@dataclass(frozen=True)
class PairBank:
    """The per-model sums of :class:`PSFBank` per pair ``(a, b)`` of ``K`` PSFs:
    ``S_ab(j) = Re sum_k |M_j(k)|^2 P_a(k) conj(P_b(k))`` (and the Hessian terms with
    their ``-k k^T``), for ``a <= b``. Under the PSF ``sum_c w_c P_c`` every sum is
    ``sum_{a <= b} w_a w_b (2 - [a = b]) S_ab(j)``, exactly (:meth:`pair_weights`).
    Made by :func:`pylensfit.likelihood.pairs.pair_bank`."""

    P: np.ndarray  # (K, n_freq) complex, the PSFs' transforms
    S: np.ndarray  # (n_pairs, n_models)
    mxx: np.ndarray
    mxy: np.ndarray
    myy: np.ndarray
    pair_a: np.ndarray  # (n_pairs,) the pairs' PSFs, a <= b
    pair_b: np.ndarray

    def pair_weights(self, weights: np.ndarray) -> np.ndarray:
        """``(n, n_pairs)`` the pairs' weights ``w_a w_b (2 - [a = b])`` of stamps whose
        PSF weights are ``weights`` ``(K, n)``."""
        a, b = self.pair_a, self.pair_b
        wp = weights[a] * weights[b] * np.where(a == b, 1.0, 2.0)[:, None]
        return np.ascontiguousarray(wp.T)

    def models(self, wp: np.ndarray, cols: np.ndarray | None = None) -> MixedModels:
        """The kernel's :class:`~pylensfit.likelihood.grid_nb.MixedModels` of the models
        ``cols`` (default: all) for galaxies of pair weights ``wp`` ``(n, n_pairs)``."""
        sums = (self.S, self.mxx, self.mxy, self.myy)
        if cols is not None:
            sums = tuple(np.ascontiguousarray(v[:, cols]) for v in sums)
        return MixedModels(*sums, np.ascontiguousarray(wp))

    def galaxy_models(self, wp: np.ndarray, cols: np.ndarray) -> Models:
        """One galaxy's :class:`~pylensfit.likelihood.grid_nb.Models` of the models
        ``cols``, its pair weights ``wp`` ``(n_pairs,)``."""
        return Models(*(wp @ v[:, cols] for v in (self.S, self.mxx, self.mxy, self.myy)))

    def S_of(self, wp: np.ndarray, j: np.ndarray) -> np.ndarray:
        """``(n,)`` each galaxy's ``sum m^2`` of its model ``j[g]`` (pair weights ``wp``)."""
        return np.einsum("gp,pg->g", wp, self.S[:, j])
