"""The population prior of the galaxies' sizes (half-light radius) and of point sources.

:class:`SizePrior` holds the density per unit ``ln h`` on a grid of knots and gives the
model bank's sizes their weights in the sum over ``r``
(:meth:`SizePrior.node_weights`); :mod:`pylensfit.prior.size_estimate` estimates it from
the data.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._util import json_kind, other_file_hint, read_json_entry
from ..models import half_light_radius, run_half_light_radius


def node_sizes(bank, config) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per size node of an e cell: ``r``, its quadrature weight and half-light radius."""
    n_b = bank.n_r // bank.n_sizes
    runs = config.bulge_runs
    if len(runs) != n_b:
        raise ValueError(f"the model bank has {n_b} runs of sizes, the configuration {len(runs)}")
    if n_b == 1:
        unit = np.array([half_light_radius(bank.model, bulge_fraction=float(runs[0].fraction),
                                           bulge_size_ratio=float(runs[0].size))])
    else:
        unit = np.array([run_half_light_radius(run) for run in runs])
    r = np.asarray(bank.radii, float)
    r_w = np.tile(np.asarray(bank.r_weights, float), n_b)
    return r, r_w, r * np.repeat(unit, bank.n_sizes)


def node_basis(h: np.ndarray, n_sizes: int, knots: np.ndarray) -> np.ndarray:
    """``(n_nodes, K)``: the mean of each knot's hat function over each node's hat.

    A density ``p`` linear between ``knots`` (0 outside, as :meth:`SizePrior.pdf`) is
    ``sum_k p_k hat_k``. Node ``j`` of a run of sizes (``n_sizes`` increasing ``h``)
    reads the prior as its mean ``pbar_j`` over a symmetric hat in ``ln h`` whose
    half-width is the node's spacing ``(ln h_{j+1} - ln h_{j-1}) / 2`` (the neighbour's
    spacing mirrored at the run's ends): ``p(h_j)`` to ``delta^2 p'' / 12`` where the
    prior is smooth, and the share of the node's hat inside where a box's edge cuts
    between nodes, so that the sum over the grid moves smoothly with the edge instead of
    in node-sized jumps.
    Row ``j`` holds ``int hat_k phi_j / int phi_j``; two-point Gauss-Legendre on every
    interval between the knots and the hat's corners is exact for these products of
    linear functions.
    """
    knots = np.asarray(knots, dtype=float)
    x = np.log(np.asarray(h, dtype=float))
    out = np.empty((x.size, knots.size))
    for s0 in range(0, x.size, n_sizes):
        c = x[s0 : s0 + n_sizes]
        if c.size > 1:
            ext = np.concatenate([[2 * c[0] - c[1]], c, [2 * c[-1] - c[-2]]])
            d = 0.5 * (ext[2:] - ext[:-2])
        else:
            d = np.array([0.05])
        # every function here is linear between these points
        b = np.unique(np.concatenate([c - d, c, c + d, knots]))
        mid, half = 0.5 * (b[1:] + b[:-1]), 0.5 * np.diff(b)
        t = np.concatenate([mid - half / np.sqrt(3.0), mid + half / np.sqrt(3.0)])
        wt = np.concatenate([half, half])
        phi = np.maximum(1.0 - np.abs(t[None] - c[:, None]) / d[:, None], 0.0) * wt
        # the knots' hats at t: two neighbours each, none outside the knots
        i = np.clip(np.searchsorted(knots, t) - 1, 0, knots.size - 2)
        f = (t - knots[i]) / (knots[i + 1] - knots[i])
        inside = (t >= knots[0]) & (t <= knots[-1])
        H = np.zeros((t.size, knots.size))
        H[np.arange(t.size), i] = np.where(inside, 1.0 - f, 0.0)
        H[np.arange(t.size), i + 1] = np.where(inside, f, 0.0)
        out[s0 : s0 + c.size] = phi @ H / d[:, None]
    return out


@dataclass(frozen=True)
class SizePrior:
    """Population prior of the galaxies' half-light radius, and of point sources.

    The paper sums ``L(e, r)`` over ``r`` with a uniform prior. A faint galaxy's
    likelihood in size is broad, and which sizes the sum weights moves its ``L(e)``: for
    de Vaucouleurs galaxies at S/N 10-20 fitted with their exact profile, the uniform
    prior gives ``m = -0.074 ± 0.021``, the estimated one ``-0.049 ± 0.021`` (400
    galaxies, paired, true ellipticity prior). This prior is estimated from the data
    (:func:`estimate_size_prior`), as the ellipticity prior is.

    Attributes
    ----------
    ln_h : numpy.ndarray
        ``(K,)`` evenly spaced knots in ``ln`` of the half-light radius (pixels).
    density : numpy.ndarray
        ``(K,)`` the density per unit ``ln h`` at the knots, linear between them and 0
        outside; integrates to ``1 - star``. Or ``(n_runs, K)``: one density per run of
        the model family (bulge fraction), each integrating to ``1 - star``, the size
        prior conditional on the run (:func:`estimate_size_prior` with ``per_run``); the
        runs' shares stay the bulge weights'.
    star : float
        Prior probability of a point source.
    smoothing : float, optional
        The EMS smoothing of the estimate (:func:`estimate_size_prior`), where known.
    """

    ln_h: np.ndarray
    density: np.ndarray
    star: float = 1e-6
    smoothing: float | None = None

    @property
    def per_run(self) -> bool:
        """Whether the prior holds one density per run of the model family."""
        return np.ndim(self.density) == 2

    def pdf(self, h) -> np.ndarray:
        """Density per unit ``ln h`` at half-light radii ``h`` (pixels); with one density
        per run, ``(n_runs,) + h.shape``."""
        with np.errstate(divide="ignore"):
            x = np.log(np.asarray(h, dtype=float))
        if self.per_run:
            return np.stack([np.interp(x, self.ln_h, d, left=0.0, right=0.0)
                             for d in self.density])  # fmt: skip
        return np.interp(x, self.ln_h, self.density, left=0.0, right=0.0)

    def marginal(self, weights=None) -> np.ndarray:
        """``(K,)`` the density over all runs, each weighted by ``weights`` (the bulge
        weights; equal by default); a single density as it is."""
        if not self.per_run:
            return np.asarray(self.density, dtype=float)
        d = np.asarray(self.density, dtype=float)
        w = np.full(d.shape[0], 1.0 / d.shape[0]) if weights is None else np.asarray(weights, float)
        if w.shape != (d.shape[0],):
            raise ValueError(f"{d.shape[0]} runs in the size prior, {w.size} weights")
        return (w / w.sum()) @ d

    def to_dict(self) -> dict[str, Any]:
        """JSON-able parameters (:meth:`from_dict` inverts it)."""
        return {"ln_h": [float(v) for v in self.ln_h],
                "density": np.asarray(self.density, dtype=float).tolist(),
                "star": float(self.star),
                **({} if self.smoothing is None
                   else {"smoothing": float(self.smoothing)})}  # fmt: skip

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "size prior dict") -> SizePrior:
        """The prior of :meth:`to_dict`.

        Parameters
        ----------
        d : dict
            ``ln_h`` and ``density``; optionally ``star`` and ``smoothing``.
        source : str
            What ``d`` came from (a file name), for the error message.

        Raises
        ------
        ValueError
            One line naming ``source`` if ``d`` is not a size prior.
        """
        what = f"{source}: not a size prior"
        if not isinstance(d, dict):
            raise ValueError(f"{what} (a JSON {json_kind(d)}; a size prior holds ln_h and "
                             "density)")  # fmt: skip
        missing = [k for k in ("ln_h", "density") if k not in d]
        if missing:
            raise ValueError(f"{what} (no entry {', '.join(map(repr, missing))}; a size prior "
                             f"holds ln_h and density{other_file_hint(d, {})})")  # fmt: skip
        try:
            ln_h = np.asarray(d["ln_h"], dtype=float)
            dens = np.asarray(d["density"], dtype=float)
            star = float(d.get("star", 1e-6))
            sm = d.get("smoothing")
            sm = None if sm is None else float(sm)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{what} ({err})") from None
        if ln_h.ndim != 1 or dens.ndim not in (1, 2) or dens.shape[-1] != ln_h.size \
                or ln_h.size < 2:
            raise ValueError(f"{what} (it needs ln_h and density (one row per run, or one) "
                             "of the same length >= 2)")  # fmt: skip
        if not (np.all(np.isfinite(ln_h)) and np.all(np.diff(ln_h) > 0)
                and np.all(np.isfinite(dens)) and np.all(dens >= 0)
                and np.all(dens.reshape(-1, ln_h.size).sum(axis=1) > 0)):
            raise ValueError(f"{what} (it needs increasing ln_h and a non-negative density)")
        if not 0 <= star < 1:
            raise ValueError(f"{what} (star must be in [0, 1), got {star:g})")
        return cls(ln_h=ln_h, density=dens, star=star, smoothing=sm)

    def save(self, path: str | Path) -> None:
        """Write the prior as JSON."""
        Path(path).write_text(json.dumps({"size_prior": self.to_dict()}, indent=1))

    @classmethod
    def load(cls, path: str | Path) -> SizePrior:
        """Read a prior written by :meth:`save`.

        Raises
        ------
        ValueError
            One line naming the file: unreadable, not JSON, or not a size prior.
        """
        d = read_json_entry(path, "size_prior", "size prior", {"priors": "priors", "B": "prior"})
        return cls.from_dict(d, source=str(path))

    def node_weights(self, bank, config) -> tuple[np.ndarray, float]:
        """Weights of the model bank's sizes and of the point source in the sum over r.

        Node ``j`` (size ``r_j``, quadrature weight ``w_j``, half-light radius ``h_j``)
        gets the prior mass ``w_j pbar_j / r_j`` (``d ln h = dr / r``), ``pbar_j`` the
        prior's average over the node's hat in ``ln h`` (:func:`node_basis`: ``p(h_j)``
        where the prior is smooth, the exact share of an edge that cuts between nodes).

        The tails, below ``config.size_prior_cut`` times the largest mass, are treated
        apart. Below the prior's mode the mass is floored there: sizes well under the
        PSF's are hard to tell apart, and what the prior holds there is the estimate's
        smoothing more than the data; those compact models keep a say in a bright
        galaxy's ``L(e)`` near ``|e| = 1``; without them (no floor and no tail cut,
        ``size_prior_cut=0``) ``m`` moves by less than 0.0005, paired
        (``benchmarks/studies/precision_ab.py --b size_prior_cut=0``). Above the mode
        the sizes are resolved, and the nodes in the tail get 0: the fit leaves them out
        of the sum over r and does not evaluate their models (a disc's largest sizes, a
        fifth of the bank in the precision mode).

        The floored nodes are summed on a coarser grid, every
        ``config.size_prior_floor_stride``-th size of the bank (the same sizes for every
        bulge fraction, so that a mixed fraction's columns are the pure ones' at the
        same size), each carrying the floor's mass of the floored nodes nearest to it:
        the total mass is unchanged, and the fit evaluates a third of those models with
        the default stride of three (in the precision mode 15 % of the models with the
        estimated size priors, a third with the population's own). The models there are
        compact and weigh 1e-4 of the prior's peak; the coarser sum moved the precision
        run's ``m`` by 1e-5 (``benchmarks/studies/precision_ab.py``). A bright galaxy
        far below the prior, whose size those models resolve, is the case it is not for.
        """
        r, r_w, h = node_sizes(bank, config)
        basis = node_basis(h, bank.n_sizes, self.ln_h)
        if self.per_run:
            n_b = bank.n_r // bank.n_sizes
            dens = np.asarray(self.density, dtype=float)
            if dens.shape[0] != n_b:
                raise ValueError(f"the size prior has {dens.shape[0]} runs, the model bank {n_b}")
            run = np.repeat(np.arange(n_b), bank.n_sizes)
            w = r_w * np.einsum("jk,jk->j", basis, dens[run]) / r
            mode = np.exp(self.ln_h[np.argmax(dens, axis=1)])[run]
            # each run's tails against its own largest mass
            top = w.reshape(n_b, bank.n_sizes).max(axis=1)[run]
        else:
            w = r_w * (basis @ self.density) / r
            mode = np.exp(self.ln_h[np.argmax(self.density)])
            top = w.max()
        if not w.max() > 0:
            raise ValueError("the size prior has no mass on the model bank's sizes")
        tail = config.size_prior_cut * top
        above = h > mode
        floored = ~above & (w < tail)
        w = np.where(above, np.where(w >= tail, w, 0.0), np.maximum(w, tail))
        stride = int(getattr(config, "size_prior_floor_stride", 1))
        if stride > 1 and floored.any():
            w = _thin_floor(w, floored, bank.n_sizes, stride)
        return w, float(max(self.star, 1e-12))


def _thin_floor(w: np.ndarray, floored: np.ndarray, n_sizes: int, stride: int) -> np.ndarray:
    """:meth:`SizePrior.node_weights`' floored nodes on every ``stride``-th size.

    In each run of ``n_sizes`` sizes (a bulge fraction), the floored nodes at size
    index ``j`` with ``j % stride == stride - 1`` are kept; every other floored node
    gives its weight to the kept one nearest to it in the run (the larger on a tie) and
    gets 0. A run whose floored nodes include none of those indices keeps them all.
    """
    w = np.array(w, dtype=float)
    for run in range(w.size // n_sizes):
        seg = w[run * n_sizes:(run + 1) * n_sizes]  # a view
        f = np.flatnonzero(floored[run * n_sizes:(run + 1) * n_sizes])
        kept = f[f % stride == stride - 1]
        if kept.size == 0:
            continue
        pos = np.clip(np.searchsorted(kept, f), 1, kept.size)
        lo, hi = kept[pos - 1], kept[np.minimum(pos, kept.size - 1)]
        near = np.where(np.abs(f - lo) < np.abs(hi - f), lo, hi)  # ties: the larger size
        mass = np.zeros(n_sizes)
        np.add.at(mass, near, seg[f])
        seg[f] = 0.0
        seg[kept] = mass[kept]
    return w
