"""Where metacalibration's faint-end bias comes from: the response's variants, paired.

Exact exponential galaxies (the exponential model, the population's priors; other
kinds and models with ``--population``, ``--morphology-weights``, ``--model``) of the
precision mode's population, four renderings each (+-g, rotated by 90 degrees, the same
noise at +g and -g) and their antithetic twins (noise and added field negated), so that
lensfit's own bias is ~0 and the noise's first-order terms cancel. Each rendering is
metacalibrated, its noshear image measured (lensfit's posterior mean under the true
prior), and the response of that measurement to the true shear,
``R_true = (<e>(+g) - <e>(-g)) / 2g`` (the +g and -g renderings share their noise and
added field), is compared with the mean metacalibration response of variants of the
sheared images (all from the same renderings):

- ``mc``: ``pylensfit.metacal`` as it is (data and added field sheared);
- ``A``: the noise-free galaxy sheared, the noshear image's noise in all five images
  (the noise not sheared: what the noise's shear does is ``mc - A``);
- ``W``: the noise-free galaxy sheared and reconvolved, fresh white noise of the fits'
  level added (the same field in the five images): the fits' noise model exact;
- ``nofix``: no added field (the fits assume the input noise);
- ``step2``: ``mc`` with the shear ``--step2`` (give ``--mc-option dilation=F`` for the
  same reconvolution PSF, and so the same estimator, at both steps).

The images are sheared about each rendering's fitted centre (as ``metacal_shapes``
does), or about the galaxy's true centre with ``--about-true-centre``: in ``A`` the
galaxy alone is sheared, so a shear about the fitted centre moves it against its
unsheared noise by ``delta`` times the centre's error, which that noise made; in ``mc``
the noise moves with it.

``m = sum R_true / sum R - 1`` per component, with the jackknife error over groups of
galaxies, under five selections (none; a galaxy only if no fit is flagged, as
``metacal_shapes`` keeps it; each rendering on the data's flags; on the noshear image's,
without and with the selection response), by true S/N and kind; the paired differences
from the first variant (every usable fit)::

    nice -n 5 python benchmarks/studies/metacal_faint.py --ngal 2400 --seed 7 --jobs 2 \
        --block-size 50 --group 50 --variants mc --set max_stamp_size=0 --save F.npz
    nice -n 5 python benchmarks/studies/metacal_faint.py --ngal 1200 --seed 9 --jobs 2 \
        --variants mc step2 --step2 0.02 --mc-option dilation=1.04 --set max_stamp_size=0
    python benchmarks/studies/metacal_faint.py --report F.npz
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from pylensfit.likelihood import fit_stamps
from pylensfit.metacal import METACAL_TYPES, metacal_images
from pylensfit.prior import mix_bulge_fractions, usable_rows
from pylensfit.runner import run_tasks, single_thread, worker_pool
from pylensfit.shear import posterior_moments
from pylensfit_validation import precision as P

sys.path.insert(0, str(Path(__file__).resolve().parent))
from precision_ab import _kv  # noqa: E402

VARIANTS = ("mc", "A", "W", "nofix", "step2")


def _means(images, psf, sigma, cfg, size_prior, prior) -> np.ndarray:
    """Posterior mean and flags ``(n, 3)`` of each image (NaN where the fit is unusable)."""
    f = fit_stamps(images, psf, sigma, config=cfg, size_prior=size_prior)
    lnL = f.lnL if f.lnL_bulge is None else mix_bulge_fractions(f.lnL_bulge, f.lnL_star)
    good = usable_rows(lnL)
    mom = posterior_moments(np.where(good[:, None], lnL, 0.0), f.egrid, prior,
                            refine=cfg.output_refine)  # fmt: skip
    e = np.column_stack([mom["e1"], mom["e2"], np.asarray(f.flags, float)])
    e[~good, :2] = np.nan
    return e


def _variant_images(v, st, clean, psf, sig, fields, white, mc_kw):
    """The five images and the fits' noise level of variant ``v``."""
    if v == "mc":
        mc = metacal_images(st, psf, sig, noise_fields=fields, **mc_kw)
        return mc.images, mc.psf, mc.noise_sigma
    if v == "step2":
        kw = {k: x for k, x in mc_kw.items() if k != "step2"} | {"step": mc_kw["step2"]}
        mc = metacal_images(st, psf, sig, noise_fields=fields, **kw)
        return mc.images, mc.psf, mc.noise_sigma
    if v == "nofix":
        mc = metacal_images(st, psf, sig, noise_fields=0 * fields, **mc_kw)
        return mc.images, mc.psf, sig
    g = metacal_images(clean, psf, 0.0, **mc_kw)  # the galaxy alone
    if v == "A":
        mc = metacal_images(st, psf, sig, noise_fields=fields, types=("noshear",), **mc_kw)
        noise = mc.images["noshear"] - g.images["noshear"]
        return {t: g.images[t] + noise for t in METACAL_TYPES}, g.psf, mc.noise_sigma
    s2 = np.sqrt(2.0) * sig
    return {t: g.images[t] + s2 * white for t in METACAL_TYPES}, g.psf, s2


def _block(task: dict) -> dict:
    """Render one block, metacalibrate each rendering set with every variant, fit."""
    single_thread(True)
    spec, cfg, prior, sp = task["spec"], task["config"], task["prior"], task["size_prior"]
    b = task["block"]
    stamps, psf, truth = P.render_block(spec, 0, b, stamp_size=cfg.largest_stamp)
    clean = P.render_block(spec, 0, b, stamp_size=cfg.largest_stamp, noise=False)[0]
    n, N = stamps.shape[0], stamps.shape[-1]
    rng = np.random.default_rng([spec.seed, 17, b])
    nf = rng.standard_normal((n, 2, N, N))[:, [0, 1, 0, 1]].reshape(4 * n, N, N)
    wf = rng.standard_normal((n, 2, N, N))[:, [0, 1, 0, 1]].reshape(4 * n, N, N)
    flat, cl = stamps.reshape(4 * n, N, N).astype(float), clean.reshape(4 * n, N, N)
    sig = spec.noise_sigma
    mc_kw = {"step": task["step"], **task["mc_kw"]}
    step2 = mc_kw.pop("step2", None)
    out = {v: np.zeros((2, 5, 4 * n, 3)) for v in task["variants"]}
    flags0 = np.zeros((2, 4 * n))
    for a, sgn in enumerate((1.0, -1.0)):  # the antithetic twins
        st = cl + sgn * (flat - cl)
        f0 = fit_stamps(st, psf, sig, config=cfg, size_prior=sp)
        flags0[a] = f0.flags
        if task["true_centre"]:  # the renderings' own centres (each galaxy's offset)
            cen = tuple(np.repeat(N // 2 + np.asarray(truth[c], float), 4) for c in ("dx", "dy"))
        else:
            cen = (np.nan_to_num(f0.x, nan=N // 2), np.nan_to_num(f0.y, nan=N // 2))
        kw = dict(mc_kw, centres=cen)
        for v in task["variants"]:
            imgs, psf_r, s = _variant_images(v, st, cl, psf, sig, sgn * nf, sgn * wf,
                                             dict(kw, step2=step2) if v == "step2" else kw)
            for j, t in enumerate(METACAL_TYPES):
                out[v][a, j] = _means(imgs[t], psf_r, s, task["mc_config"], sp, prior)
    return {"block": b, "e": out, "flags0": flags0, "snr": np.asarray(truth["snr"], float),
            "morph": np.asarray(truth["morph"])}


def _selected_m(e, flags0, sel, step, g, grp):
    """m (2,) and its jackknife error of one variant's measurements under selection ``sel``.

    ``e``: ``(2, 5, n, 4, 3)`` (twin, type, galaxy, rendering, [e1, e2, flags]);
    ``flags0``: ``(2, n, 4)`` the first fit's flags. ``sel``:
    ``"none"`` every usable fit; ``"all"`` a galaxy only if none of its fits is flagged
    (``metacal_shapes``' rows); ``"noshear"`` each rendering on its noshear image's flags,
    with the selection response from the sheared images' flags (Sheldon & Huff 2017);
    ``"noshear-nors"`` the same without the selection response; ``"data"`` each rendering on
    the first fit's flags (the data's own), no selection response.
    """
    fin = np.isfinite(e[..., :2]).all(-1).all(1).all(0).all(-1)  # (n,) every fit usable
    fl = e[..., 2] != 0  # (2, 5, n, 4)
    if sel == "none":
        w = np.broadcast_to(fin[None, :, None], fl.shape[:1] + fl.shape[2:])
    elif sel == "all":
        ok = fin & ~fl.any((0, 1, 3)) & (flags0 == 0).all((0, 2))
        w = np.broadcast_to(ok[None, :, None], fl.shape[:1] + fl.shape[2:])
    elif sel == "data":
        w = fin[None, :, None] & (flags0 == 0)
    else:
        w = fin[None, :, None] & ~fl[:, 0]
    w = w.astype(float)
    ens = np.nan_to_num(e[:, 0, ..., :2])  # (2, n, 4, 2)
    ee = np.nan_to_num(e[..., :2])
    Rg = ((ee[:, 1] - ee[:, 2]) + (ee[:, 3] - ee[:, 4])) / (2 * step)  # response to (g, g)
    k = grp.max() + 1

    def gs(x):  # (2, n, 4, ...) -> per group sums (k, ...)
        x = np.moveaxis(x, 1, 0).reshape(x.shape[1], -1, *x.shape[3:]).sum(1)
        return np.stack([np.bincount(grp, c, k) for c in x.reshape(x.shape[0], -1).T], -1)

    sign = np.array([1.0, 1.0, -1.0, -1.0])[None, None, :]
    parts = {"Ep": gs((w * (sign > 0))[..., None] * ens), "Em": gs((w * (sign < 0))[..., None]
                                                                  * ens),  # fmt: skip
             "Np": gs(w * (sign > 0)), "Nm": gs(w * (sign < 0)), "Rg": gs(w[..., None] * Rg),
             "N": gs(w)}  # fmt: skip
    if sel == "noshear":
        for j, t in enumerate(("1p", "1m", "2p", "2m")):
            ws = (fin[None, :, None] & ~fl[:, 1 + j]).astype(float)
            parts["E" + t], parts["N" + t] = gs(ws[..., None] * ens), gs(ws)

    def m_of(P):  # from summed parts
        R = P["Rg"] / P["N"]
        if sel == "noshear":
            R = R + ((P["E1p"] / P["N1p"] - P["E1m"] / P["N1m"])
                     + (P["E2p"] / P["N2p"] - P["E2m"] / P["N2m"])) / (2 * step)  # fmt: skip
        return (P["Ep"] / P["Np"] - P["Em"] / P["Nm"]) / (2 * g * R) - 1

    with np.errstate(invalid="ignore", divide="ignore"):  # a group without a selected row
        full = m_of({key: v.sum(0) for key, v in parts.items()})
        jk = np.array([m_of({key: v.sum(0) - v[i] for key, v in parts.items()})
                       for i in range(k)])  # fmt: skip
    return full, np.sqrt((k - 1) / k * ((jk - jk.mean(0)) ** 2).sum(0)), w.mean()


SELECTIONS = ("none", "all", "data", "noshear-nors", "noshear")


def _report(es, flags0, snr, step, g, grp, morph=None) -> None:
    """m per variant and selection, and the paired differences between variants."""
    print("| variant | selection | kept | m1 | m2 |\n|---|---|---|---|---|")
    ms = {}
    for v, e in es.items():
        for sel in SELECTIONS:
            m, err, kept = _selected_m(e, flags0, sel, step[v], g, grp)
            ms[v, sel] = m
            print(f"| {v} | {sel} | {kept:.3f} | {m[0]:+.4f} ± {err[0]:.4f} | "
                  f"{m[1]:+.4f} ± {err[1]:.4f} |")
    print("true S/N percentiles 5, 50, 95:", np.round(np.percentile(snr, [5, 50, 95]), 1))
    k = grp.max() + 1
    for v in list(es)[1:]:  # paired with the first variant, every usable fit
        first = list(es)[0]

        def diff(keep, v=v, first=first):
            sub = np.flatnonzero(keep)
            one = np.zeros(sub.size, int)
            return (_selected_m(es[v][:, :, sub], flags0[:, sub], "none", step[v], g, one)[0]
                    - _selected_m(es[first][:, :, sub], flags0[:, sub], "none", step[first], g,
                                  one)[0])  # fmt: skip

        full = diff(np.ones(grp.size, bool))
        jk = np.array([diff(grp != i) for i in range(k)])
        err = np.sqrt((k - 1) / k * ((jk - jk.mean(0)) ** 2).sum(0))
        print(f"{v} - {first} (paired, every usable fit): {full[0]:+.4f} ± {err[0]:.4f} / "
              f"{full[1]:+.4f} ± {err[1]:.4f}")
    bins = [(f"S/N {lo}-{hi:g}", (snr >= lo) & (snr < hi))
            for lo, hi in ((0, 10), (10, 15), (15, 20), (20, np.inf))]  # by true S/N
    if morph is not None:
        bins += [(name, morph == j) for j, name in enumerate(P.MORPHOLOGIES)]
    for name, keep in bins:
        if keep.sum() < 2 * (grp == 0).sum():
            continue
        sub = np.flatnonzero(keep)
        gs = np.arange(sub.size) // max(1, (grp == 0).sum())
        for v, e in es.items():
            m, err, _ = _selected_m(e[:, :, sub], flags0[:, sub], "none", step[v], g, gs)
            print(f"{name}, {v} ({sub.size} galaxies, every usable fit): "
                  f"{m[0]:+.4f} ± {err[0]:.4f} / {m[1]:+.4f} ± {err[1]:.4f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ngal", type=int, default=400)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--population", default="aligned", help="PrecisionSpec.population")
    ap.add_argument("--morphology-weights", nargs=5, type=float, default=(1, 0, 0, 0, 0),
                    metavar="W", help="exponential, de Vaucouleurs, bulge+disc, Sersic, knots")
    ap.add_argument("--model", default="exponential",
                    help="the fits' model (bulge+disc: Config()'s, the fractions equally likely)")
    ap.add_argument("--snr", nargs=2, type=float, default=(10.0, 20.0),
                    help="the population's reference S/N range")
    ap.add_argument("--psf", default="round")
    ap.add_argument("--step", type=float, default=0.01)
    ap.add_argument("--g", type=float, default=0.02, help="the renderings' shear per component")
    ap.add_argument("--step2", type=float, default=0.02, help="the step of variant step2")
    ap.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=VARIANTS)
    ap.add_argument("--block-size", type=int, default=25)
    ap.add_argument("--group", type=int, default=25, help="galaxies per jackknife group")
    ap.add_argument("--mc-position-prior", type=float, default=2.0)
    ap.add_argument("--mc-option", nargs="*", default=[], metavar="KEY=VALUE",
                    help="extra metacal_images keywords (Python literals)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="changes to every fit's configuration (min_snr=0: no S/N cut)")
    ap.add_argument("--about-true-centre", action="store_true",
                    help="shear about each galaxy's true centre, not its fitted one")
    ap.add_argument("--save", default=None)
    ap.add_argument("--report", default=None, metavar="NPZ",
                    help="only report a run saved with --save")
    a = ap.parse_args()
    if a.report:
        d = np.load(a.report)
        es = {k[2:]: d[k] for k in d.files if k.startswith("e_")}
        steps = {v: float(d["step2"] if v == "step2" else d["step"]) for v in es}
        _report(es, d["flags0"], d["snr"], steps, float(d["g"]),
                np.arange(d["flags0"].shape[1]) // int(d["group"]),
                d["morph"] if "morph" in d.files else None)  # fmt: skip
        return
    mc_kw = _kv(a.mc_option) | {"step2": a.step2}
    spec = P.spec_with(P.PrecisionSpec(ngal=a.ngal, seed=a.seed, snr_range=tuple(a.snr),
                                       morphology_weights=tuple(a.morphology_weights),
                                       population=a.population, block_size=a.block_size,
                                       g=a.g),
                       psfs=[a.psf])  # fmt: skip
    cfg = P.default_config(spec).replace(model=a.model, **_kv(a.set))
    mcfg = cfg.replace(position_prior_sigma=a.mc_position_prior)
    prior, sp = P.population_prior(spec), P.population_size_prior(spec, 0)
    nb = -(-a.ngal // a.block_size)
    tasks = [{"spec": spec, "config": cfg, "mc_config": mcfg, "prior": prior, "size_prior": sp,
              "block": b, "step": a.step, "variants": a.variants, "mc_kw": mc_kw,
              "true_centre": a.about_true_centre}
             for b in range(nb)]  # fmt: skip
    t0 = time.perf_counter()
    res = {}
    with worker_pool(a.jobs) as pool:
        for t, r in run_tasks(_block, tasks, a.jobs, None, "metacal", True, pool):
            res[t["block"]] = r
    cat = [res[b] for b in range(nb)]
    snr = np.concatenate([r["snr"] for r in cat])
    morph = np.concatenate([r["morph"] for r in cat])
    print(f"{a.ngal} galaxies, {nb} blocks in {time.perf_counter() - t0:.0f} s; step {a.step}, "
          f"{a.psf} PSF, reference S/N {a.snr}, true S/N {np.percentile(snr, [5, 50, 95])}")
    es = {v: np.concatenate([r["e"][v] for r in cat], axis=2).reshape(2, 5, a.ngal, 4, 3)
          for v in a.variants}  # fmt: skip
    flags0 = np.concatenate([r["flags0"] for r in cat], axis=1).reshape(2, a.ngal, 4)
    grp = np.arange(a.ngal) // a.group
    _report(es, flags0, snr, {v: a.step2 if v == "step2" else a.step for v in es}, spec.g, grp,
            morph)
    if a.save:
        np.savez(a.save, snr=snr, morph=morph, flags0=flags0, step=a.step, step2=a.step2, g=spec.g,
                 group=a.group,
                 **{f"e_{v}": es[v] for v in a.variants})


if __name__ == "__main__":
    main()
