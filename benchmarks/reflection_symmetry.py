"""How far the fit is from covariant under the stamp's reflections: a bound on a round PSF's c.

Under the transpose (``x <-> y``), which maps ``(e1, e2) -> (-e1, e2)``, the stamp's
window (``[0, N)`` about element ``N // 2``), the e-grid, the priors, the precision
population and its noise are symmetric; under ``y -> -y``, which maps ``(e1, e2) ->
(e1, -e2)``, all of them are except the window's row 0. A fit covariant under both gives
a round PSF's ``c = 0`` in expectation, in both components. The script renders blocks
of the precision mode's population, fits each block's stamps as they are, transposed
and with their rows reflected about the centre (the PSF image with them), with the
precision mode's configuration and the population's ellipticity prior, and prints the
mean of the half-sums ``(e2 + e2R) / 2`` and ``(e1 + e1T) / 2`` (and their partners)
with their errors: each is what the fit's asymmetry adds to ``c``. ::

    python benchmarks/reflection_symmetry.py --psf round --blocks 4
    python benchmarks/reflection_symmetry.py --psf e=0.10 --noise-free
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from pylensfit.likelihood import fit_stamps
from pylensfit_validation.precision import (
    default_config,
    population_prior,
    reduce_renderings,
    render_block,
    spec_with,
)


def reflect_rows(a: np.ndarray) -> np.ndarray:
    """Rows reflected about element ``N // 2``; row 0 (no partner in the stamp) stays."""
    r = a.copy()
    r[..., 1:, :] = a[..., :0:-1, :]
    return r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--psf", default="round", help="one of the precision mode's PSFs")
    ap.add_argument("--blocks", type=int, default=4, help="blocks of 500 galaxies")
    ap.add_argument("--seed", type=int, default=99)
    ap.add_argument("--noise-free", action="store_true")
    a = ap.parse_args()
    spec = spec_with(seed=a.seed, psfs=[a.psf])
    cfg = default_config(spec)
    prior = population_prior(spec)
    keys = ("e1", "e2", "e1R", "e2R", "e1T", "e2T")
    out: dict[str, list] = {k: [] for k in keys}
    for b in range(a.blocks):
        t0 = time.perf_counter()
        st, psf, _ = render_block(spec, 0, b, stamp_size=cfg.largest_stamp, noise=not a.noise_free)
        n = st.shape[0]
        res = []
        for s, p in ((st, psf), (reflect_rows(st), reflect_rows(psf)),
                     (np.ascontiguousarray(st.swapaxes(-1, -2)), np.ascontiguousarray(psf.T))):
            f = fit_stamps(s.reshape(4 * n, *s.shape[2:]), p, spec.noise_sigma, config=cfg)
            res.append(reduce_renderings(f, prior, 0.0))  # the prior unsheared: symmetric
        good = res[0][1] & res[1][1] & res[2][1]
        for (Q, _), suf in zip(res, ("", "R", "T"), strict=True):
            out["e1" + suf].append(Q[..., 0][good])
            out["e2" + suf].append(Q[..., 1][good])
        print(f"block {b}: {good.sum()} renderings, {time.perf_counter() - t0:.0f} s", flush=True)
    o = {k: np.concatenate(v) for k, v in out.items()}
    print(f"PSF {a.psf}, {o['e1'].size} renderings, posterior mean rms {o['e1'].std():.3f} / "
          f"{o['e2'].std():.3f}{' (noise-free)' if a.noise_free else ''}")
    for name, d in (("y -> -y: (e2 + e2R) / 2", o["e2"] + o["e2R"]),
                    ("y -> -y: (e1 - e1R) / 2", o["e1"] - o["e1R"]),
                    ("x <-> y: (e1 + e1T) / 2", o["e1"] + o["e1T"]),
                    ("x <-> y: (e2 - e2T) / 2", o["e2"] - o["e2T"])):  # fmt: skip
        h = d / 2
        print(f"  {name}: mean {h.mean():+.1e} +- {h.std() / np.sqrt(h.size):.1e}, "
              f"rms {h.std():.1e}, max |.| {np.abs(h).max():.1e}")


if __name__ == "__main__":
    main()
