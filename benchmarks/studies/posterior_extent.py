"""How much of the model grid a galaxy's likelihood occupies: the ceiling of adaptive
sampling.

Adaptive sampling (lensfit's survey version) evaluates each galaxy's likelihood finely
only where it is not negligible. Its gain is bounded by the part of the grid that is not
negligible: this study measures that part exactly. Each galaxy's joint ``ln L(e, r)``
(every e cell, every size node of every bulge fraction) is read from
:func:`pylensfit.fit_stamps` with one group of e cells per cell
(``lnL_r_groups = arange(n_e)``: ``StampFits.lnL_r_grouped`` is then ``e_w(e) L(e, r)``,
and ``ln e_w`` is taken off again), on the stamps of ``bench_likelihood.py`` (32 x 32,
S/N 10-100 log-uniform, half-light radius 1.5-4 px, Moffat PSF), with ``Config()``'s
bulge+disc grid. Printed, for thresholds ``T`` (e-folds under the galaxy's peak), by S/N
and for two S/N distributions (the simulated one, and a survey-like ``dN/dS ~ S^-2.5``
from the same galaxies reweighted), the fraction of the grid above ``peak - T``:

- ``models``: (e cell, size) pairs, the kernel's work if every model could be skipped
  one by one;
- ``columns``: (orbit of four e cells, size) columns with any member above, the kernel's
  work when a folded column (:class:`pylensfit.likelihood.folded.FoldedBank`) is skipped
  whole, and the matrix products' if they could be cut per galaxy;
- ``sizes``: size nodes with any e cell above (pruning sizes only, as a block of
  galaxies sharing one set of columns would).

The fit's time is the kernel's (about 70 %) plus the products' (about 25 %); the ceiling
of the speed-up is ``1 / (0.25 + 0.70 f + 0.05)`` with ``f`` the kernel's fraction.

Usage::

    python benchmarks/studies/posterior_extent.py --ngal 1000 --seed 1   # 2 min
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench_likelihood import simulate  # noqa: E402

BINS = ((10.0, 20.0), (20.0, 40.0), (40.0, 100.0))


def joint_lnL(stamps: np.ndarray, psf: np.ndarray, cfg) -> tuple[np.ndarray, np.ndarray]:
    """``(n, n_e, n_r)`` joint ``ln L(e, r)`` relative to each galaxy's peak, and the e
    grid."""
    import pylensfit as plf
    from pylensfit.models import model_bank
    from pylensfit.prior import Prior

    bank = model_bank(cfg)
    eg = bank.egrid
    e_w = Prior().pdf(eg[:, 0], eg[:, 1])
    e_w = e_w / e_w.sum()
    out = []
    for s0 in range(0, len(stamps), 200):
        f = plf.fit_stamps(stamps[s0 : s0 + 200], psf, 1.0, config=cfg,
                           lnL_r_groups=np.arange(eg.shape[0]))  # fmt: skip
        g = np.asarray(f.lnL_r_grouped, dtype=float)[:, :, :-1] - np.log(e_w)[None, :, None]
        out.append(g - g.max(axis=(1, 2), keepdims=True))
    return np.concatenate(out), eg


def fractions(lnl: np.ndarray, eg: np.ndarray, T: float) -> dict[str, np.ndarray]:
    """Per galaxy, the fractions of models, columns and sizes above ``-T``."""
    above = lnl > -T  # (n, n_e, n_r)
    key = np.round(np.abs(eg), 6)
    _, orbit = np.unique(key, axis=0, return_inverse=True)
    n_orb = orbit.max() + 1
    cols = np.zeros((lnl.shape[0], n_orb, lnl.shape[2]), dtype=bool)
    for o in range(n_orb):
        cols[:, o] = above[:, orbit == o].any(axis=1)
    return {"models": above.mean(axis=(1, 2)), "columns": cols.mean(axis=(1, 2)),
            "sizes": above.any(axis=1).mean(axis=1)}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ngal", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--thresholds", type=float, nargs="+", default=[15.0, 25.0, 40.0])
    args = ap.parse_args(argv)
    import pylensfit as plf

    cfg = plf.Config(max_stamp_size=0)
    _, snr, stamps, psf = simulate(args.ngal, args.seed, "exponential")
    lnl, eg = joint_lnL(stamps, psf, cfg)
    print(f"{args.ngal} galaxies, {lnl.shape[1]} e cells x {lnl.shape[2]} sizes "
          f"({cfg.model}, {cfg.n_bulge_fractions} fractions)")  # fmt: skip
    survey = snr**-1.5  # log-uniform dN/dlnS = const -> dN/dS ~ S^-2.5
    head = " ".join(f"S/N {a:.0f}-{b:.0f}" for a, b in BINS)
    print(f"{'T':>4} {'kind':8} {head}  simulated  survey-like  fit speed-up ceiling")
    for T in args.thresholds:
        fr = fractions(lnl, eg, T)
        for kind, f in fr.items():
            per = " ".join(f"{f[(snr >= a) & (snr < b)].mean():9.3f}" for a, b in BINS)
            sim, sv = f.mean(), np.average(f, weights=survey)
            print(f"{T:4.0f} {kind:8} {per}  {sim:9.3f}  {sv:11.3f}  "
                  f"{1 / (0.30 + 0.70 * sv):.2f}x")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
