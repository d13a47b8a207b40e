""":func:`fit_stamps`: the stamps' tiers, then each window's stages, from the stamps to
their :class:`StampFits`."""

from __future__ import annotations

import numpy as np

from .._util import per_object
from ..config import Config
from ..prior import Prior, SizePrior
from .bank import MixedPSF, subset_psf
from .device import device_grid, resolve_backend
from .evaluate import evaluate_grid, products
from .folded import folded_bank
from .merge import merge_fits
from .priors import kernel_weights
from .refine import refined
from .results import assemble_fits
from .stampfits import StampFits
from .threads import one_blas_thread
from .tiers import stamp_tiers, tier_sizes, warn_small_stamps
from .windows import prepare_window


def fit_stamps(
    stamps: np.ndarray,
    psf: np.ndarray | MixedPSF,
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
    psf : numpy.ndarray or MixedPSF
        2-D PSF image including the pixel response, centred on ``[s//2, s//2]``, any size
        and normalisation; shared by all stamps of the call. Cut to each stamp size used,
        so give it as large as ``max_stamp_size`` for the tiers. Or a
        :class:`~pylensfit.likelihood.MixedPSF`: each stamp's PSF a weighted sum of a few
        PSF images, fitted exactly in one fit (the tier chosen with its heaviest image).
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
    ``jobs > 1`` and on a cluster's workers. With ``config.backend = "jax"`` the blocks
    run on a JAX device (:mod:`pylensfit.likelihood.device`), to round-off.
    """
    with one_blas_thread():
        return _fit_stamps(stamps, psf, noise_sigma, config, centres, size_prior,
                           size_marginal_prior, lnL_r_groups)  # fmt: skip


def _fit_stamps(stamps, psf, noise_sigma, config, centres, size_prior, size_marginal_prior,
                lnL_r_groups) -> StampFits:  # fmt: skip
    cfg = config if config is not None else Config()
    stamps = np.asarray(stamps, dtype=float)
    if stamps.ndim == 2:
        stamps = stamps[None]
    if stamps.ndim != 3 or stamps.shape[1] < 2 or stamps.shape[2] < 2:
        raise ValueError(f"stamps must have shape (n, N, N), got {stamps.shape}")
    n_gal = stamps.shape[0]
    if isinstance(psf, MixedPSF) and psf.n_stamps != n_gal:
        raise ValueError(f"MixedPSF has weights for {psf.n_stamps} stamps, not {n_gal}")
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
            warn_small_stamps(stamps.shape, cfg, sizes[-1], None)
        return _fit_window(stamps, psf, sigma, cfg, cx, cy, size_prior, size_marginal_prior,
                           lnL_r_groups)  # fmt: skip
    size, wanted = stamp_tiers(stamps, psf, sigma, cfg, cx, cy, sizes)
    if cfg.largest_stamp > sizes[-1]:
        short = int(np.count_nonzero(wanted > sizes[-1]))
        if short:
            warn_small_stamps(stamps.shape, cfg, sizes[-1], short)
    parts = []
    for t in np.unique(size):
        idx = np.flatnonzero(size == t)
        sub = cfg if t == cfg.stamp_size else cfg.replace(
            stamp_size=int(t), max_stamp_size=0, k_max=np.pi * cfg.stamp_size / t)  # fmt: skip
        parts.append((idx, _fit_window(stamps[idx], subset_psf(psf, idx), sigma[idx], sub,
                                       cx[idx], cy[idx],
                                       size_prior, size_marginal_prior,
                                       lnL_r_groups)))  # fmt: skip
    return merge_fits(parts, n_gal)


def _fit_window(stamps: np.ndarray, psf: np.ndarray | MixedPSF, sigma: np.ndarray, cfg: Config,
                cx: np.ndarray, cy: np.ndarray, size_prior: SizePrior | None,
                size_marginal_prior: Prior | None,
                lnL_r_groups: np.ndarray | None = None) -> StampFits:  # fmt: skip
    """:func:`fit_stamps` on ``cfg.stamp_size`` windows (one stamp size for all).

    The stages: the windows cleaned, transformed and centred (:func:`prepare_window`;
    on the device path transformed and centred by :func:`device_grid`),
    the kernel's priors (:func:`kernel_weights`), the likelihood on the model grid
    (:func:`evaluate_grid`, or :func:`device_grid` on a JAX device: ``cfg.backend``),
    the finer e grid (:func:`refined`) and the result
    (:func:`assemble_fits`).
    """
    # a PSF mixed per galaxy runs on the host (the device path holds one PSF per call)
    on_device = resolve_backend(cfg) == "jax" and not isinstance(psf, MixedPSF)
    win = prepare_window(stamps, psf, sigma, cfg, cx, cy, on_device=on_device)
    fb = folded_bank(cfg, win.bank)
    wts, fb_kept = kernel_weights(cfg, win.bank, fb, size_prior, size_marginal_prior,
                                  lnL_r_groups)  # fmt: skip
    # the buffer holds the products with every column of the bank, coarse ones included
    prod = products(win, cfg, fb_kept, fb.G[0].shape[1])
    if on_device:
        grid = device_grid(win, prod, wts, cfg)
    else:
        grid = evaluate_grid(win, prod, wts, cfg)
    egrid, lnle, lnleb = refined(win, prod, wts, grid, cfg, psf)
    return assemble_fits(win, wts, grid, egrid, lnle, lnleb, cfg)
