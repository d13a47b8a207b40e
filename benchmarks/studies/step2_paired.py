"""Paired +-g shear bias of the whole pipeline on STEP2-like fields.

STEP2's random shears and independent noise leave m with an error of about 0.015 per PSF
(0.006 over five PSFs from 100,000 galaxies). This benchmark renders STEP2-like fields
(`pylensfit_validation.validation.render_step2_field`: Sersic, bulge+disc and knotty galaxies on a
jittered lattice, stars, sky and noise) four times, as the precision mode renders its
stamps: sheared by +(g, g) and by -(g, g) with the same objects and the same noise
field, each with a 90-degree-rotated twin (its own noise). Every field goes through
`pylensfit.measure` (detection, the PSF from the star field and the image's own stars,
sky, neighbours, fits), and

    m_i = (g_hat_i(+g) - g_hat_i(-g)) / (2 g) - 1,   c_i = (g_hat_i(+g) + g_hat_i(-g)) / 2,

from the galaxies measured in all four renderings (eq. ``key2`` with the exact
sensitivity per rendering pair; the fixed point beside it), errors by jackknife over 50
groups of galaxies. The priors come from a zero-shear field of the same population
measured first (the ellipticity prior and the bulge-fraction weights estimated from it,
and its size prior given to the shear fields), as `pylensfit validate` takes them.

Oracles that take one part of the pipeline out (applied in the worker process that
measures each field):

* ``--true-psf``: the GalSim PSF (pixel included) in place of the stacked stars;
* ``--true-sky``: the true constant sky in place of SEP's and the re-measured one;
* ``--spacing 80``: isolated galaxies (the lattice pitch; STEP2's is 40 px);
* ``--config``: any configuration (e.g. ``stamp_size: 64`` or ``e_step: 0.05``).

``--compare B.yaml`` measures the same fields with a second configuration and prints m and
c of both on the galaxies both measure, and of B - A with its paired jackknife error:
the same galaxies and noise, so a change of a few 1e-3 is resolved where the errors of
each (about 0.004) are not.

::

    python benchmarks/studies/step2_paired.py --out /tmp/s2p --psf 0 --fields 2 --seed 1
    python benchmarks/studies/step2_paired.py --out /tmp/s2p --psf 0 --fields 2 --seed 1 --true-psf
    python benchmarks/studies/step2_paired.py --out /tmp/s2p --psf 0 --fields 2 --seed 1 \
        --compare five_fractions.yaml

Each configuration's catalogues are kept under ``OUT/<set>/<tag>/`` and reused; the
renderings under ``OUT/<set>/``. What it found: ``benchmarks/README.md``, "What the
studies found".
"""

from __future__ import annotations

import argparse
import hashlib
import json
import multiprocessing as mp
import time
from pathlib import Path

import numpy as np
from astropy.table import Table, vstack

G = 0.02
KINDS = ("sersic", "bulge+disc", "knots")


def _spec(psf: int, size: int, spacing: float, snr, g: float, rotate: bool):
    from pylensfit_validation.validation import STEP2_PSFS, spec_for

    return spec_for(STEP2_PSFS[psf], size=size, spacing=spacing, noise_sigma=1.0,
                     snr_range=tuple(snr), size_range=(1.5, 4.5), star_fraction=0.05,
                     pixel_scale_arcsec=0.2, model="bulge+disc", g1=g, g2=g,
                     rotate=rotate)  # fmt: skip


def _render(task) -> str:
    """Render one field (or the star field) unless it exists."""
    from pylensfit_validation.simulate import simulate_field, write_field
    from pylensfit_validation.validation import render_step2_field

    path, psf, size, spacing, snr, g, rotate, seed, noise_seed, stars = task
    if Path(path).exists():
        return path
    spec = _spec(psf, size, spacing, snr, g, rotate)
    if stars:
        from dataclasses import replace

        spec = replace(spec, star_fraction=1.0)
        img, w, truth = simulate_field(spec, seed=seed, noise_seed=noise_seed)
    else:
        img, w, truth = render_step2_field(spec, seed=seed, noise_seed=noise_seed)
    tmp = Path(path).with_name(f".{Path(path).name}.tmp.fits")
    write_field(tmp, img, w, spec, truth=truth)
    tmp.replace(path)
    return path


def _measure(task) -> str:
    """Measure one field in a fresh worker, with the oracles (the sky's patch dies with it):
    the true PSF given to :func:`pylensfit.measure` (``psf=``) instead of the stacked one."""
    from pylensfit import Config, Prior, measure

    path, star, cfg_dict, size_prior, out, true_psf, true_sky = task
    psf = None if true_psf is None else np.asarray(true_psf).copy()
    if true_sky is not None:
        from sky_bias import patch_true_sky  # benchmarks/studies/ is the script's path

        patch_true_sky(true_sky)
    measure([path], stars=[star], config=Config.from_dict(cfg_dict), prior=Prior(), psf=psf,
            size_prior=size_prior, output=out, overwrite=True, progress=False)  # fmt: skip
    return out


def _true_psf_image(psf: int, n: int) -> np.ndarray:
    """The rendering's own PSF (`simulate.field_psf`) with the pixel, centred as a stacked one."""
    from pylensfit_validation.precision import draw_image
    from pylensfit_validation.simulate import field_psf

    img = draw_image(field_psf(_spec(psf, n, 40.0, (15.0, 150.0), 0.0, False)), n).astype(float)
    return img / img.sum()


def _jackknife(fn, n: int, groups: int = 50):
    """``fn(index)`` over all rows and its delete-one-group jackknife error."""
    idx = np.arange(n)
    grp = idx % groups
    full = fn(idx)
    reps = np.array([fn(idx[grp != q]) for q in range(groups)])
    err = np.sqrt((groups - 1) / groups * ((reps - reps.mean(0)) ** 2).sum(0))
    return full, err


def _measured(cfg, a, base, quads, star, true_psf, true_sky, ctx) -> Path:
    """Measure the prior field and every shear field with ``cfg`` (kept catalogues reused)."""
    from pylensfit import pipeline

    ident = json.dumps([cfg.to_dict(), a.true_psf, a.true_sky], sort_keys=True, default=str)
    mdir = base / hashlib.sha1(ident.encode()).hexdigest()[:10]
    mdir.mkdir(exist_ok=True)
    (mdir / "ident.json").write_text(ident)
    prior_cat = mdir / "prior.fits"
    with ctx.Pool(a.jobs, maxtasksperchild=1) as pool:
        if not prior_cat.exists():
            pool.apply(_measure, ((str(base / "prior.fits"), star, cfg.to_dict(), None,
                                   str(prior_cat), true_psf, true_sky),))  # fmt: skip
        sp = pipeline.read_catalogue(prior_cat).meta.get("size_prior")
        todo = [(str(base / n), star, cfg.to_dict(), sp, str(mdir / n), true_psf, true_sky)
                for q in quads for n in q if not (mdir / n).exists()]  # fmt: skip
        list(pool.imap_unordered(_measure, todo))
    return mdir


def _shapes(cfg, mdir: Path, base: Path, quads, psf: int) -> dict:
    """Per galaxy measured in all four renderings of its quadruple: its key (quadruple,
    truth index), posterior means ``E`` and sensitivities ``S`` (n, 4, 2) in the order
    +g, +g twin, -g, -g twin, its S/N, size and kind, and the fixed point's m."""
    from pylensfit import pipeline
    from pylensfit.prior import estimate_prior_and_bulge, mix_bulge_fractions
    from pylensfit.shear import shapes, shear_fixed_point
    from pylensfit_validation.validation import STEP2_PSFS, matched_galaxies

    fwhm = STEP2_PSFS[psf]["fwhm"]
    fields = {n: {"path": str(base / n)} for q in quads for n in q}
    fields["prior.fits"] = {"path": str(base / "prior.fits")}
    pcat = pipeline.read_catalogue(mdir / "prior.fits")
    pg = matched_galaxies(pcat, fields, psf, fwhm)
    egrid = np.asarray(pcat.meta["egrid"])
    prior, bw = estimate_prior_and_bulge(np.asarray(pg["lnL_bulge"]), np.asarray(pg["lnL_star"]),
                                         egrid, method=cfg.prior_method)  # fmt: skip
    lnL_q, info_q, keys = [], [], []
    for j, q in enumerate(quads):
        per = []
        for n in q:
            g = matched_galaxies(pipeline.read_catalogue(mdir / n), fields, psf, fwhm)
            per.append(g[(np.asarray(g["truth_index"]) >= 0) & ~np.asarray(g["truth_star"])])
        ti = np.array(sorted(set.intersection(*(set(np.asarray(g["truth_index"]).tolist())
                                                for g in per))), dtype=np.int64)  # fmt: skip
        sels = []
        for g in per:
            t_ = np.asarray(g["truth_index"])
            o_ = np.argsort(t_)
            sels.append(o_[np.searchsorted(t_[o_], ti)])
        lnL_q.append(np.stack([mix_bulge_fractions(np.asarray(g["lnL_bulge"])[s_],
                                                   np.asarray(g["lnL_star"])[s_], bw)
                               for g, s_ in zip(per, sels, strict=True)], axis=1))  # fmt: skip
        truth = Table.read(base / q[0], hdu="TRUTH")
        info_q.append(Table({
            "snr": np.mean([np.asarray(g["snr"])[s_] for g, s_ in zip(per, sels, strict=True)],
                           axis=0),
            "size": np.asarray(truth["r"])[ti] / fwhm,
            "kind": np.asarray(truth["kind"]).astype(str)[ti]}))  # fmt: skip
        keys.append(j * 10**7 + ti)
    lnL = np.concatenate(lnL_q)  # (n, 4, n_e): +g, +g twin, -g, -g twin
    n = lnL.shape[0]
    sh = shapes(lnL.reshape(n * 4, -1), egrid, prior, sensitivity=cfg.sensitivity,
                refine=cfg.integration_refine)  # fmt: skip
    fp = [shear_fixed_point(lnL[:, k].reshape(-1, lnL.shape[-1]), egrid, prior,
                            refine=cfg.integration_refine) for k in ((0, 1), (2, 3))]  # fmt: skip
    return {"key": np.concatenate(keys), "info": vstack(info_q),
            "E": np.column_stack([sh["e1"], sh["e2"]]).reshape(n, 4, 2),
            "S": np.column_stack([sh["sens1"], sh["sens2"]]).reshape(n, 4, 2),
            "m_fp": [(fp[0].g1 - fp[1].g1) / (2 * G) - 1, (fp[0].g2 - fp[1].g2) / (2 * G) - 1],
            "prior": prior, "bw": bw}  # fmt: skip


def _m_c(E, S, idx) -> np.ndarray:
    """m1, m2, c1, c2 of the galaxies ``idx`` (eq. ``key2`` per rendering pair)."""
    gp = (E[idx, 0] + E[idx, 1]).sum(0) / (S[idx, 0] + S[idx, 1]).sum(0)
    gm = (E[idx, 2] + E[idx, 3]).sum(0) / (S[idx, 2] + S[idx, 3]).sum(0)
    return np.concatenate([(gp - gm) / (2 * G) - 1, (gp + gm) / 2])


def _table(fn, info, title: str) -> None:
    """m and c of ``fn(idx)`` for all galaxies and by S/N, size and kind, with jackknife
    errors."""
    if title:
        print(title)
    print(f"{'sample':22s} {'m1':>8s} {'err':>7s} {'m2':>8s} {'err':>7s} {'c1':>9s} "
          f"{'c2':>9s} {'n':>6s}")  # fmt: skip

    def line(label, sel):
        idx = np.flatnonzero(sel)
        if idx.size < 100:
            return
        v, e = _jackknife(lambda i: fn(idx[i]), idx.size)
        print(f"{label:22s} {v[0]:+8.4f} {e[0]:7.4f} {v[1]:+8.4f} {e[1]:7.4f} {v[2]:+9.5f} "
              f"{v[3]:+9.5f} {idx.size:6d}")  # fmt: skip

    line("all", np.ones(len(info), bool))
    snr, rr = np.asarray(info["snr"]), np.asarray(info["size"])
    for lo, hi in ((0, 25), (25, 45), (45, 85), (85, np.inf)):
        line(f"S/N {lo:g}-{hi:g}", (snr >= lo) & (snr < hi))
    for lo, hi in ((0, 0.66), (0.66, 0.88), (0.88, 1.14), (1.14, np.inf)):
        line(f"r/FWHM {lo:g}-{hi:g}", (rr >= lo) & (rr < hi))
    for k in KINDS:
        line(f"kind {k}", np.asarray(info["kind"]) == k)


def main(argv=None) -> int:
    from pylensfit.config import Config
    from pylensfit_validation.validation import STEP2_PSFS, step_config

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True, help="work directory (renderings, catalogues)")
    ap.add_argument("--psf", type=int, default=0, help="index into STEP2_PSFS")
    ap.add_argument("--fields", type=int, default=2, help="field quadruples (+-g, twins)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument(
        "--size",
        type=int,
        default=0,
        help="field side in px (default: about 2,500 galaxies a field)",
    )
    ap.add_argument("--spacing", type=float, default=40.0, help="lattice pitch (px)")
    ap.add_argument("--snr", type=float, nargs=2, default=(15.0, 150.0))
    ap.add_argument("--config", help="YAML configuration (default: validate's)")
    ap.add_argument("--compare", help="a second YAML configuration: m and c of both on the "
                    "galaxies both measure, and of their difference with its paired error")
    ap.add_argument("--true-psf", action="store_true")
    ap.add_argument("--true-sky", action="store_true")
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args(argv)
    t0 = time.time()
    size = a.size or int(round(52 * a.spacing))
    base = Path(a.out) / (f"psf{a.psf}_s{a.seed}_sp{a.spacing:g}_n{size}"
                          f"_snr{a.snr[0]:g}-{a.snr[1]:g}")  # fmt: skip
    base.mkdir(parents=True, exist_ok=True)
    cfg = Config.from_yaml(a.config) if a.config else step_config()
    cfgs = [cfg] + ([Config.from_yaml(a.compare)] if a.compare else [])
    rng = np.random.default_rng([a.seed, a.psf])
    geo = (a.psf, size, a.spacing, list(a.snr))
    s = [int(v) for v in rng.integers(1, 2**31 - 1, 4)]
    renders = [
        (str(base / "stars.fits"), *geo, 0.0, False, s[0], s[1], True),
        (str(base / "prior.fits"), *geo, 0.0, False, s[2], s[3], False),
    ]
    quads = []
    for j in range(a.fields):
        s_obj, na, nb = (int(v) for v in rng.integers(1, 2**31 - 1, 3))
        names = []
        for sg, tg in ((1, "p"), (-1, "m")):
            for rot, ns in ((False, na), (True, nb)):
                name = f"f{j}_{tg}{'_rot' if rot else ''}.fits"
                renders.append((str(base / name), *geo, sg * G, rot, s_obj, ns, False))
                names.append(name)
        quads.append(names)
    ctx = mp.get_context("spawn")  # no fork: GalSim and numba threads in the parent
    with ctx.Pool(a.jobs) as pool:
        list(pool.imap_unordered(_render, renders))
    t_render = time.time() - t0
    true_psf = _true_psf_image(a.psf, cfg.stamp_size).tolist() if a.true_psf else None
    true_sky = 50.0 if a.true_sky else None  # FieldSpec's sky
    star = str(base / "stars.fits")
    mdirs = [_measured(c, a, base, quads, star, true_psf, true_sky, ctx) for c in cfgs]
    t_measure = time.time() - t0 - t_render
    res = [_shapes(c, d, base, quads, a.psf) for c, d in zip(cfgs, mdirs, strict=True)]
    print(f"PSF {a.psf} {STEP2_PSFS[a.psf]}, {a.fields} field quadruple(s) of {size} px, "
          f"spacing {a.spacing:g}, S/N {a.snr[0]:g}-{a.snr[1]:g}; true PSF {a.true_psf}, "
          f"true sky {a.true_sky}; render {t_render:.0f} s, measure {t_measure:.0f} s")  # fmt: skip
    for name, r, d in zip("AB", res, mdirs, strict=False):
        label = name + " " if a.compare else ""
        print(f"{label}catalogues {d}: prior {r['prior']}, bulge weights "
              f"{np.round(r['bw'], 3).tolist()}; fixed point m1 {r['m_fp'][0]:+.4f}, "
              f"m2 {r['m_fp'][1]:+.4f}")  # fmt: skip
    if not a.compare:
        r = res[0]
        _table(lambda i: _m_c(r["E"], r["S"], i), r["info"], "")
        return 0
    # the galaxies that both configurations measure in all four renderings
    common = np.intersect1d(res[0]["key"], res[1]["key"])
    sel = [np.searchsorted(r["key"], common) for r in res]
    E = [r["E"][s_] for r, s_ in zip(res, sel, strict=True)]
    S = [r["S"][s_] for r, s_ in zip(res, sel, strict=True)]
    info = res[0]["info"][sel[0]]
    for k, title in ((0, f"A ({a.config or 'validate'})"), (1, f"B ({a.compare})")):
        _table(lambda i, k=k: _m_c(E[k], S[k], i), info, title)
    _table(lambda i: _m_c(E[1], S[1], i) - _m_c(E[0], S[0], i), info, "B - A (paired)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
