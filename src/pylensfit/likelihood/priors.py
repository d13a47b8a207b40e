"""The priors and weights that the likelihood kernel applies: the size prior's weights
of the sizes, the bulge fractions', the e cells' in ``L(r)``, the amplitude prior and
the position prior."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import Config
from ..models import ModelBank
from ..prior import Prior, SizePrior
from .amplitude_nb import AMP_UNIFORM
from .folded import FoldedBank, active_columns
from .grid_nb import Amplitude, Sums


@dataclass(frozen=True)
class Weights:
    """The priors and weights that the likelihood kernel applies."""

    n_b: int  # bulge fractions, a uniform prior over them here
    n_grp: int  # groups of e cells in lnL_r
    #: the weights of the sums over r and e (size prior and trapezoid rule, the bulge
    #: fractions' prior, the e cells' weights in lnL_r, size_marginal_prior, and groups)
    sums: Sums
    #: the centring pass's: its sizes' quadrature weights, its e cells alike, one group
    sums_c: Sums
    amp: Amplitude  # the amplitude prior
    b2: float  # variance of the position prior


def _size_weights(cfg: Config, bank: ModelBank, fb: FoldedBank, size_prior: SizePrior | None,
                  n_b: int) -> tuple[np.ndarray, float, FoldedBank]:  # fmt: skip
    """The weight of every size node and of the point source, and ``fb`` without the
    columns of the sizes outside the size prior (no models to evaluate)."""
    if size_prior is None:
        run_w = bank.run_weights if bank.run_weights is not None else np.ones(n_b)
        node_w = np.tile(np.asarray(bank.r_weights, float), n_b) * np.repeat(run_w, bank.n_sizes)
        w_star = float(bank.star_weight)
    else:
        node_w, w_star = size_prior.node_weights(bank, cfg)
        if not (node_w > 0).all():
            fb = active_columns(fb, bank, node_w > 0)
    return node_w, w_star, fb


def e_groups(lnL_r_groups: np.ndarray | None, n_e: int) -> np.ndarray:
    """The checked group of every e cell in ``lnL_r`` (all in group 0 by default)."""
    if lnL_r_groups is None:
        return np.zeros(n_e, dtype=np.int64)
    e_grp = np.asarray(lnL_r_groups)
    if e_grp.shape != (n_e,) or e_grp.dtype.kind not in "iu" or e_grp.min() < 0:
        raise ValueError(f"lnL_r_groups needs {n_e} non-negative integers (one per e "
                         f"cell), got shape {e_grp.shape}, dtype {e_grp.dtype}")  # fmt: skip
    return e_grp.astype(np.int64)


def amplitude_prior(cfg: Config) -> Amplitude:
    """The kernel's amplitude prior: its power
    (:data:`~pylensfit.likelihood.amplitude_nb.AMP_UNIFORM` for the uniform prior; any
    finite power is a power law), the power of ``S`` in ``ln L``, its limits."""
    uniform = cfg.amplitude_prior == "uniform"
    amp_pow = AMP_UNIFORM if uniform else float(cfg.amplitude_prior_power)
    amp_lns = amp_pow - 1.0 if cfg.amplitude_prior == "flux" else 0.0
    flux_prior = cfg.amplitude_prior == "flux"
    amp_lo = float(cfg.amplitude_prior_min) if flux_prior else 0.0
    amp_hi = float(cfg.amplitude_prior_max) if flux_prior else np.inf
    return Amplitude(amp_pow, amp_lns, amp_lo, amp_hi)


def kernel_weights(cfg: Config, bank: ModelBank, fb: FoldedBank, size_prior: SizePrior | None,
                   size_marginal_prior: Prior | None, lnL_r_groups: np.ndarray | None
                   ) -> tuple[Weights, FoldedBank]:  # fmt: skip
    """The kernel's priors and weights, and the folded bank of the sizes they keep."""
    coarse = fb.coarse
    n_b = bank.n_r // bank.n_sizes
    ln_pi = np.full(n_b, -np.log(n_b))
    node_w, w_star, fb = _size_weights(cfg, bank, fb, size_prior, n_b)
    mp = size_marginal_prior if size_marginal_prior is not None else Prior()
    e_w = mp.pdf(bank.egrid[:, 0], bank.egrid[:, 1])
    e_w = e_w / e_w.sum()
    e_grp = e_groups(lnL_r_groups, bank.n_e)
    r_w = np.asarray(bank.r_weights, dtype=float)
    rw_c = np.tile(r_w, bank.n_r // bank.n_sizes)[coarse.cols[:-1] % bank.n_r][: coarse.n_r]
    sums_c = Sums(rw_c, bank.star_weight, np.zeros(1), np.full(coarse.n_e, 1.0 / coarse.n_e),
                  np.zeros(coarse.n_e, dtype=np.int64), coarse.n_r)  # fmt: skip
    wts = Weights(n_b=n_b, n_grp=int(e_grp.max()) + 1,
                  sums=Sums(node_w, w_star, ln_pi, e_w, e_grp, bank.n_sizes), sums_c=sums_c,
                  amp=amplitude_prior(cfg), b2=cfg.position_prior_sigma**2)  # fmt: skip
    return wts, fb
