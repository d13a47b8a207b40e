"""Metacalibration's m and c on the unseen population, with noise twins and the full response.

The population, PSFs and renderings of ``benchmarks/unseen_paired.py`` (Sersic, knotty
discs, bulge+disc with rounder bulges; S/N 10-100 from ``dN/dS ~ S^-2``; 64-pixel
stamps; shear ``(+g, +g)`` and ``(-g, -g)``, ``g = 0.02``; each galaxy also turned by 90
degrees), and for each rendering its noise twin: the pixel noise and the
metacalibration's added noise field both negated, so that their first-order terms
cancel in m and c. Eight renderings per galaxy; the ``+g`` and ``-g`` ones share their
noise and added field.

Each rendering is metacalibrated by :func:`pylensfit.metacal.metacal_shapes` (the
posterior mean under the default ellipticity prior ``Prior()``, ``Config()`` on the
whole 64-pixel stamp, ``--reconvolution`` its PSF). The shear of each sign is
``<R>^-1 <e>`` with the full 2 x 2 mean response (the shear is on both components, and
``e_1``'s response to ``g_2`` does not cancel galaxy by galaxy; the diagonal alone is
printed too), then ``m_i = (g_i(+) - g_i(-)) / (2 g) - 1`` and ``c_i = (g_i(+) + g_i(-)) /
2``, with jackknife errors over 40 groups of galaxies, per kind and per true S/N.

Usage (``--part`` runs half of a PSF's galaxies, so that two processes share the work;
``--report`` combines the saved files)::

    NUMBA_NUM_THREADS=1 python benchmarks/studies/metacal_twins.py --ngal 1000 --psf 3 \\
        --seed 22 --part 0 --reconvolution round --save r0.npz      # 4 min, one core
    NUMBA_NUM_THREADS=1 python benchmarks/studies/metacal_twins.py --ngal 1000 --psf 3 \\
        --seed 22 --part 1 --reconvolution round --save r1.npz
    python benchmarks/studies/metacal_twins.py --report r0.npz r1.npz
    python benchmarks/studies/metacal_twins.py --paired d0.npz d1.npz -- r0.npz r1.npz
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import galsim
import numpy as np

import pylensfit as plf
from pylensfit.metacal import metacal_shapes

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import unseen_paired as U  # noqa: E402

G = 0.02
#: the eight renderings: (noise twin sign, turned by 90 degrees, sign of the shear)
RENDERINGS = [(tw, rot, sg) for tw in (1, -1) for rot in (0, 1) for sg in (1, -1)]
PLUS = np.array([sg > 0 for _, _, sg in RENDERINGS])


def render(n: int, ipsf: int, seed: int, part: int):
    """The stamps ``(n, 8, 64, 64)``, added noise fields, kinds and S/N of PSF ``ipsf``'s
    first ``n`` galaxies (half of them with ``part`` 0 or 1)."""
    pop = U.draw_population(n * len(U.PSFS), np.random.default_rng(seed), 25)
    sel = np.flatnonzero(pop.psf == ipsf)[:n]
    if part >= 0:
        sel = np.array_split(sel, 2)[part]
    psf, N = U.make_psf(ipsf), U.STAMP
    st = np.empty((sel.size, len(RENDERINGS), N, N))
    fl = np.empty_like(st)
    for j, i in enumerate(sel):
        p = pop.row(i)
        gal = U.make_galaxy(p)
        unit = U._draw(gal, psf, p)
        gal = gal.withFlux(p["snr"] * U.SIGMA / math.sqrt(float(np.sum(unit**2))))
        rng = np.random.default_rng([seed, 7, int(i)])
        noise, field = rng.normal(0, U.SIGMA, (2, N, N)), rng.standard_normal((2, N, N))
        for r, (tw, rot, sg) in enumerate(RENDERINGS):
            gr = gal.rotate(90 * galsim.degrees) if rot else gal
            st[j, r] = U._draw(gr.shear(g1=sg * G, g2=sg * G), psf, p) + tw * noise[rot]
            fl[j, r] = tw * field[rot]
    return st, fl, pop.kind[sel], pop.snr[sel]


def measure(a) -> None:
    st, fl, kind, snr = render(a.ngal, a.psf, a.seed, a.part)
    N = st.shape[-1]
    t0 = time.time()
    mc = metacal_shapes(st.reshape(-1, N, N), U.psf_image(a.psf).astype(float), U.SIGMA,
                        plf.Prior(), config=plf.Config(stamp_size=N, max_stamp_size=0),
                        noise_fields=fl.reshape(-1, N, N), reconvolution=a.reconvolution,
                        step=a.step)
    print(f"metacalibrated {st.shape[0] * st.shape[1]} renderings in {time.time() - t0:.0f} s")
    n_r = len(RENDERINGS)
    e = np.column_stack([mc["e1"], mc["e2"]]).reshape(-1, n_r, 2)
    R = np.stack([mc["R11"], mc["R12"], mc["R21"], mc["R22"]], 1).reshape(-1, n_r, 2, 2)
    np.savez(a.save, e=e, R=R, kind=kind, snr=snr)
    print(f"wrote {a.save}")


def _load(paths):
    d = [np.load(p) for p in paths]
    return tuple(np.concatenate([x[k] for x in d]) for k in ("e", "R", "kind", "snr"))


def _m_c(e, R, full: bool = True, w=None) -> np.ndarray:
    """``m1, m2, c1, c2`` of galaxies ``e, R`` (weights ``w`` per galaxy: a mix)."""
    ep, em = (np.average(e[:, s].mean(1), axis=0, weights=w) for s in (PLUS, ~PLUS))
    Rp, Rm = (np.average(R[:, s].mean(1), axis=0, weights=w) for s in (PLUS, ~PLUS))
    if full:
        gp, gm = np.linalg.solve(Rp, ep), np.linalg.solve(Rm, em)
    else:
        gp, gm = ep / np.diag(Rp), em / np.diag(Rm)
    return np.r_[(gp - gm) / (2 * G) - 1, (gp + gm) / 2]


def _jackknife(fn, n: int, groups: int = 40):
    full = fn(np.arange(n))
    parts = np.array_split(np.arange(n), groups)
    vals = np.array([fn(np.setdiff1d(np.arange(n), p)) for p in parts])
    return full, np.sqrt((groups - 1) / groups * ((vals - vals.mean(0)) ** 2).sum(0))


def _row(name: str, v, err) -> None:
    print(f"{name:20s} m1 {v[0]:+.4f} +- {err[0]:.4f}  m2 {v[1]:+.4f} +- {err[1]:.4f}  "
          f"c1 {v[2]:+.5f} +- {err[2]:.5f}  c2 {v[3]:+.5f} +- {err[3]:.5f}")


def report(paths, mixes=()) -> None:
    e, R, kind, snr = _load(paths)
    ok = np.isfinite(e).all((1, 2)) & np.isfinite(R).all((1, 2, 3))
    print(f"{ok.sum()} of {ok.size} galaxies with every rendering's five fits usable")
    e, R, kind, snr = e[ok], R[ok], kind[ok], snr[ok]
    _row("all", *_jackknife(lambda s: _m_c(e[s], R[s]), len(e)))
    _row("all, diagonal R", *_jackknife(lambda s: _m_c(e[s], R[s], False), len(e)))
    for k, name in enumerate(U.KINDS):
        i = np.flatnonzero(kind == k)
        _row(name, *_jackknife(lambda s, i=i: _m_c(e[i[s]], R[i[s]]), i.size))
    for lo, hi in ((10, 20), (20, 40), (40, 101)):
        i = np.flatnonzero((snr >= lo) & (snr < hi))
        _row(f"S/N {lo}-{hi}", *_jackknife(lambda s, i=i: _m_c(e[i[s]], R[i[s]]), i.size))
    for mix in mixes:
        # each kind's galaxies weighted so that the kinds' shares are the mix's
        share = np.asarray(mix, float) / np.sum(mix)
        w = share[kind] / np.bincount(kind, minlength=len(share))[kind]
        _row("mix " + ":".join(f"{v:g}" for v in mix),
             *_jackknife(lambda s, w=w: _m_c(e[s], R[s], w=w[s]), len(e)))


def paired(a_paths, b_paths) -> None:
    """The second set's mean ellipticity, m and c minus the first's over the galaxies
    usable in both (the same renderings under two settings), per kind."""
    ea, Ra, kind, _ = _load(a_paths)
    eb, Rb, _, _ = _load(b_paths)
    ok = (np.isfinite(ea).all((1, 2)) & np.isfinite(eb).all((1, 2))
          & np.isfinite(Ra).all((1, 2, 3)) & np.isfinite(Rb).all((1, 2, 3)))
    d = eb[ok].mean(1) - ea[ok].mean(1)
    print(f"mean R: {Ra[ok].mean((0, 1)).ravel().round(4)} -> "
          f"{Rb[ok].mean((0, 1)).ravel().round(4)}")
    for name, s in [("all", np.ones(ok.sum(), bool))] + [
            (k, kind[ok] == i) for i, k in enumerate(U.KINDS)]:  # fmt: skip
        err = d[s].std(0) / np.sqrt(s.sum())
        print(f"{name:12s} <e>: {ea[ok][s].mean((0, 1)).round(5)} -> "
              f"{eb[ok][s].mean((0, 1)).round(5)}; difference {d[s].mean(0).round(5)} +- "
              f"{err.round(5)}")
    ea, Ra, eb, Rb, kind = ea[ok], Ra[ok], eb[ok], Rb[ok], kind[ok]
    for name, i in [("all", np.arange(ok.sum()))] + [
            (k, np.flatnonzero(kind == j)) for j, k in enumerate(U.KINDS)]:  # fmt: skip
        _row(f"d {name}", *_jackknife(
            lambda s, i=i: _m_c(eb[i[s]], Rb[i[s]]) - _m_c(ea[i[s]], Ra[i[s]]), i.size))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ngal", type=int, default=1000, help="galaxies of the PSF")
    ap.add_argument("--psf", type=int, default=3, help="index into unseen_paired.PSFS")
    ap.add_argument("--seed", type=int, default=22)
    ap.add_argument("--part", type=int, default=-1, choices=(-1, 0, 1))
    ap.add_argument("--reconvolution", choices=("round", "dilate"), default="round")
    ap.add_argument("--step", type=float, default=0.01,
                    help="metacalibration's shear step delta (the dilation follows it)")
    ap.add_argument("--save", default="metacal_twins.npz")
    ap.add_argument("--report", nargs="+", metavar="NPZ")
    ap.add_argument("--mix", nargs=3, type=float, action="append", default=[],
                    metavar=("SERSIC", "KNOTTY", "BULGE_DISC"),
                    help="--report: also the kinds mixed in these proportions (repeatable)")
    ap.add_argument("--paired", nargs="+", metavar="NPZ",
                    help="A.npz ... -- B.npz ...: B's mean ellipticity minus A's")
    a, rest = ap.parse_known_args()
    if a.paired:
        paired(a.paired, [r for r in rest if r != "--"])
    elif a.report:
        report(a.report, a.mix)
    else:
        measure(a)


if __name__ == "__main__":
    main()
