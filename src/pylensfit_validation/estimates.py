"""A simulated set's catalogues, measured once and kept, matched to the truth, and the
shear estimates of its images and groups."""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
from pathlib import Path

import numpy as np
from astropy.table import Table
from scipy.spatial import cKDTree

from pylensfit import pipeline
from pylensfit.prior import (
    Prior,
    estimate_prior_binned,
)
from pylensfit.shear import ShearEstimate, estimate_shear, shear_fixed_point
from pylensfit.skyframe import SkyFrame, sensitivity_to_sky

from .simulate import (
    pixel_to_sky_shear,
)
from .stats import (
    MATCH_RADIUS,
    bin_index,
    controlled_estimate,
    fit_m_c,
    fit_m_c_cov,
    group_members,
    group_shear,
    nanmean,
    quality_factor,
    read_truth,
    shear_groups,
    sky_columns,
    truth_terms,
)
from .step import STEP2_KINDS

__all__ = [
    "BIN_COLUMNS",
    "bins_table",
    "check_frame",
    "matched_galaxies",
    "mc_rows",
    "measured_catalogues",
    "prior_check",
    "set_frame",
    "shapes_to_sky",
    "shear_estimates",
]

log = logging.getLogger(__name__)

# -- measured catalogues, kept under DIR/measured/ ----------------------------------------
#: the kept catalogues' version: one whose sidecar holds another is measured again. It
#: changes when the same configuration measures differently (3: the size prior estimated
#: from every measured galaxy; 4: the calibration recipe of :func:`pylensfit.calibrate`)
_MEASURE_VERSION = 4


def _ident(fields: list[dict], star: dict, cfg, priors=None, psf=None) -> dict:
    """What a kept catalogue was made from: the configuration, the fields' seeds, the
    priors given to the measurement (if any) and the PSF given to it (if any: a
    digest of its image or of its model file; otherwise it came from the star field)."""
    ids = []
    for f in [*fields, star]:
        # the manifest's entry, and the file as it is now (a set simulated again in the
        # same directory, with other parameters but the same seeds, is measured again)
        st = Path(f["path"]).stat() if f.get("path") else None
        ids.append({**{k: v for k, v in f.items() if k != "path"},
                    "bytes": st and st.st_size, "mtime_ns": st and st.st_mtime_ns})  # fmt: skip
    ident = {"version": _MEASURE_VERSION, "config": cfg.to_dict(), "fields": ids}
    if priors is not None:
        ident["priors"] = priors.to_dict()
    if isinstance(psf, Path):  # a PSF model file: its bytes
        ident["psf"] = hashlib.sha1(psf.read_bytes()).hexdigest()
    elif psf is not None:
        ident["psf"] = psf.digest
    return json.loads(json.dumps(ident))


def measured_catalogues(name: str, fields: list[dict], star: dict, cfg, mdir: Path, *, jobs: int,
              progress: bool, remeasure: bool, priors=None,
              psf=None) -> tuple[Table, bool]:  # fmt: skip
    """The catalogue of ``fields`` from ``mdir/<name>.fits``, measured unless kept.

    A kept catalogue is reused when its sidecar ``<name>.json`` records the same
    configuration, the same fields (names and seeds) and the same ``priors``.
    Otherwise the fields are measured with :func:`pylensfit.pipeline.measure`
    (``output=``: written atomically, resumable from its ``.parts`` folder; under
    ``priors``, a :class:`~pylensfit.Priors`, if given, else with the priors estimated
    from the fields by the calibration recipe) and the sidecar
    written after the catalogue. With ``psf`` (a :class:`~pylensfit.psf.PSFResult`, a
    :class:`~pylensfit.psfmodel.PSFModel` or the path of a PSF model file) the fields
    are measured with it instead of the star field's PSF.
    """
    cat_path, side = mdir / f"{name}.fits", mdir / f"{name}.json"
    ident = _ident(fields, star, cfg, priors, psf)
    if not remeasure and cat_path.exists() and side.exists():
        try:
            same = json.loads(side.read_text()) == ident
        except (OSError, ValueError):
            same = False
        if same:
            try:
                return pipeline.read_catalogue(cat_path), True
            except (OSError, ValueError) as err:  # a damaged file is remeasured
                log.warning("%s: unreadable kept catalogue (%s); measuring again", cat_path, err)
    mdir.mkdir(parents=True, exist_ok=True)
    side.unlink(missing_ok=True)
    pipeline.measure([f["path"] for f in fields], stars=[star["path"]] if psf is None else None,
                     psf=psf, config=cfg, priors=priors,
                     output=cat_path, overwrite=True, jobs=jobs, progress=progress)  # fmt: skip
    tmp = side.with_name(f".{side.name}.tmp")
    tmp.write_text(json.dumps(ident, indent=1))
    os.replace(tmp, side)
    return pipeline.read_catalogue(cat_path), False


def matched_galaxies(cat: Table, fields: dict[str, dict], psf: int, psf_fwhm: float,
              sky: tuple[float, bool] = (0.0, False)) -> Table:  # fmt: skip
    """The usable galaxies of a catalogue, matched to the truth of their images.

    Every detection is matched to the nearest truth object within ``MATCH_RADIUS``
    pixels of its fitted centre (one detection per truth object: the nearest). Returns
    the rows with ``flags == 0``, ``fitclass == 0`` (galaxy) and a finite ``ln L`` grid,
    with ``psf``, ``truth_index`` (-1: unmatched), ``truth_star``, ``e1_int, e2_int``
    (sky frame), ``size`` (truth ``r`` over the FWHM of the PSF at the galaxy, the
    truth's ``psf_fwhm``, or ``psf_fwhm`` (pixels) for a truth without it; NaN when
    unmatched or matched to a star), ``morphology`` (the index in :data:`STEP2_KINDS`
    of a STEP2 galaxy's kind; NaN otherwise), ``mag``, ``snr`` (``model_SNratio``),
    ``psf_e1_true, psf_e2_true`` (the truth's adaptive-moment PSF ellipticity at the
    galaxy, ``psf_e1_obs, psf_e2_obs``, taken to the sky frame by ``sky``, the set's
    WCS rotation in degrees and flip; NaN when unmatched or without them),
    ``psf_e1_model, psf_e2_model`` (the catalogue's ``PSF_e1, PSF_e2``) and ``lnL``.
    """
    lnL = np.asarray(cat["lnL"])
    use = ((np.asarray(cat["flags"]) == 0) & (np.asarray(cat["fitclass"]) == 0)
           & np.isfinite(lnL).all(axis=1))  # fmt: skip
    g = cat[use]
    n = len(g)
    images = np.asarray(g["image"]).astype(str)
    tidx = np.full(n, -1, dtype=np.int64)
    tstar = np.zeros(n, dtype=bool)
    cols = ("r", "fwhm", "e1", "e2", "morph", "pe1", "pe2")
    v = {c: np.full(n, np.nan) for c in cols}
    for name in np.unique(images):
        truth = read_truth(fields[name]["path"])
        sel = np.flatnonzero(images == name)
        tree = cKDTree(np.column_stack([truth["x"], truth["y"]]))
        xy = np.column_stack([np.asarray(g["x"])[sel], np.asarray(g["y"])[sel]])
        d, j = tree.query(xy, distance_upper_bound=MATCH_RADIUS)
        idx = np.flatnonzero(np.isfinite(d))
        idx = idx[np.argsort(d[idx], kind="stable")]
        _, first = np.unique(j[idx], return_index=True)
        keep = idx[first]
        rows, jj = sel[keep], j[keep]
        tidx[rows] = jj
        tstar[rows] = np.asarray(truth["is_star"])[jj]
        v["r"][rows] = np.asarray(truth["r"])[jj]
        v["fwhm"][rows] = (np.asarray(truth["psf_fwhm"], float)[jj]
                           if "psf_fwhm" in truth.colnames else psf_fwhm)  # fmt: skip
        for k, c in zip(("e1", "e2"), sky_columns(truth, "e1_int", "e2_int"), strict=True):
            v[k][rows] = np.asarray(truth[c])[jj]
        if "psf_e1_obs" in truth.colnames and "psf_e2_obs" in truth.colnames:
            v["pe1"][rows], v["pe2"][rows] = pixel_to_sky_shear(
                np.asarray(truth["psf_e1_obs"], float)[jj],
                np.asarray(truth["psf_e2_obs"], float)[jj], *sky)
        if "kind" in truth.colnames:
            names, inv = np.unique(np.asarray(truth["kind"]).astype(str)[jj], return_inverse=True)
            code = np.array([STEP2_KINDS.index(k) if k in STEP2_KINDS else np.nan for k in names])
            v["morph"][rows] = code[inv]
    out = Table()
    out["psf"] = np.full(n, psf, dtype=np.int64)
    out["image"] = images
    out["truth_index"] = tidx
    out["truth_star"] = tstar
    out["e1_int"], out["e2_int"] = v["e1"], v["e2"]
    out["size"] = np.where(tstar, np.nan, v["r"] / v["fwhm"])
    out["morphology"] = np.where(tstar, np.nan, v["morph"])
    out["mag"] = np.asarray(g["mag"], dtype=float)
    out["snr"] = np.asarray(g["model_SNratio"], dtype=float)
    out["psf_e1_true"] = np.where(tstar, np.nan, v["pe1"])
    out["psf_e2_true"] = np.where(tstar, np.nan, v["pe2"])
    for i in (1, 2):
        out[f"psf_e{i}_model"] = (np.asarray(g[f"PSF_e{i}"], dtype=float)
                                  if f"PSF_e{i}" in g.colnames else np.full(n, np.nan))  # fmt: skip
    out["lnL"] = np.asarray(g["lnL"], dtype=np.float32)
    if "lnL_bulge" in g.colnames:  # each bulge fraction's L(e), for their prior
        out["lnL_bulge"] = np.asarray(g["lnL_bulge"], dtype=np.float32)
        out["lnL_star"] = np.asarray(g["lnL_star"], dtype=float)
    return out


def check_frame(cat: Table, sky: tuple[float, bool], name: str) -> None:
    """Raise ``ValueError`` when a catalogue's sky frame (its ``sky_angle``, ``sky_flip``
    columns, from the images' WCS) is not the set's (``sky``: the manifest's WCS
    rotation in degrees and its flip), to 0.1 degree: the comparison with the truth
    takes the shapes to the sky frame with the manifest's."""
    if "sky_angle" not in cat.colnames or "sky_flip" not in cat.colnames or not len(cat):
        return
    ang = np.asarray(cat["sky_angle"], dtype=float)
    ok = np.isfinite(ang)
    if "flags" in cat.colnames:  # the measured rows (a position: the WCS's frame)
        ok &= np.asarray(cat["flags"]) == 0
    if "ALPHA_J2000" in cat.colnames:
        ok &= np.isfinite(np.asarray(cat["ALPHA_J2000"], dtype=float))
    if not ok.any():
        return
    # spin-2 quantities see the angle modulo 180 degrees
    dev = (ang[ok] - sky[0] + 90.0) % 180.0 - 90.0
    flip = np.asarray(cat["sky_flip"], dtype=bool)[ok]
    if np.max(np.abs(dev)) > 0.1 or np.any(flip != bool(sky[1])):
        raise ValueError(
            f"{name}: the catalogue's sky frame (rotation {np.median(ang[ok]):.3f} deg, "
            f"flipped {bool(np.median(flip))}) is not the manifest's ({sky[0]:g} deg, "
            f"flipped {bool(sky[1])}): the images' WCS disagrees with the set")


def set_frame(man: dict) -> tuple[float, bool]:
    """The set's WCS rotation (degrees) and flip, from its manifest (plain by default)."""
    return float(man.get("wcs_rotation_deg") or 0.0), bool(man.get("wcs_flip", False))


def _frame_of(n: int, sky: tuple[float, bool]) -> SkyFrame | None:
    """The sky frame of ``n`` rows of a set's images (all share the WCS rotation and
    flip ``sky``), or None for the plain WCS, whose pixel frame is the sky frame."""
    rot, flip = float(sky[0]), bool(sky[1])
    if rot == 0.0 and not flip:
        return None
    return SkyFrame(angle=np.full(n, rot), flip=np.full(n, flip), g1=np.zeros(n),
                    g2=np.zeros(n), has_wcs=np.ones(n, bool))  # fmt: skip


def shapes_to_sky(e: np.ndarray, s: np.ndarray, sky: tuple[float, bool]) -> tuple[np.ndarray, ...]:
    """Pixel-frame ``(n, 2)`` ellipticities and sensitivities in the set's sky frame, as
    the truth's ``e1_sky, e2_sky`` (:func:`pylensfit_validation.simulate.pixel_to_sky_shear`; the
    sensitivities as :func:`pylensfit.skyframe.sensitivity_to_sky`)."""
    fr = _frame_of(e.shape[0], sky)
    if fr is None:
        return e, s
    e1, e2 = pixel_to_sky_shear(e[:, 0], e[:, 1], *sky)
    s1, s2 = sensitivity_to_sky(s[:, 0], s[:, 1], fr)
    return np.column_stack([e1, e2]), np.column_stack([s1, s2])


def _fixed_point(lnL: np.ndarray, egrid: np.ndarray, prior: Prior, refine: int,
                 sky: tuple[float, bool]) -> ShearEstimate:  # fmt: skip
    """:func:`pylensfit.shear_fixed_point` giving the sky-frame shear of a set's images
    (one pixel frame, that of the WCS rotation and flip ``sky``)."""
    fr = _frame_of(lnL.shape[0], sky)
    if fr is None:
        return shear_fixed_point(lnL, egrid, prior, refine=refine)
    return shear_fixed_point(lnL, egrid, prior, refine=refine, frame=fr,
                             groups=np.zeros(lnL.shape[0], dtype=np.int64))  # fmt: skip


_EST_NAMES = ("psf", "file", "g1_true", "g2_true", "g1", "g1_err", "g2", "g2_err", "n", "n_pair")


def shear_estimates(gal: Table, e: np.ndarray, s: np.ndarray, fields: dict[str, dict], *,
                     pairs: bool, estimator: str, prior: Prior, egrid: np.ndarray,
                     refine: int, truth_control: bool = False,
                     sky: tuple[float, bool] = (0.0, False)) -> Table:  # fmt: skip
    """One shear estimate per image (``pairs=False``) or per image + twin pair, with the
    truth's shape noise taken out (:func:`truth_control_variate`) if ``truth_control``.
    ``e, s`` and the estimates are in the sky frame of the set (``sky``: its WCS
    rotation, degrees, and flip)."""
    images = np.asarray(gal["image"]).astype(str)
    lnL = np.asarray(gal["lnL"])
    rows = []
    nan4 = (math.nan,) * 4
    if not pairs:
        for name in np.unique(images):
            f = fields[name]
            sel = images == name
            try:
                if estimator == "fixed-point":
                    est = _fixed_point(lnL[sel], egrid, prior, refine, sky)
                else:
                    t = Table({"e1": e[sel, 0], "e2": e[sel, 1], "sens1": s[sel, 0],
                               "sens2": s[sel, 1]})  # fmt: skip
                    est = estimate_shear(t)
                res = (est.g1, est.g1_err, est.g2, est.g2_err)
                if truth_control:
                    t_all = truth_terms(fields, [name])
                    tix = np.asarray(gal["truth_index"])[sel]
                    t = np.full((tix.size, 2), np.nan)
                    t[tix >= 0] = t_all[tix[tix >= 0]]
                    res = controlled_estimate(res, e[sel], s[sel], t, t_all,
                                      own_scale=estimator == "fixed-point")
            except ValueError:
                res = nan4
            rows.append((f["psf"], f["file"], f["g1"], f["g2"], *res, int(sel.sum()), 0))
    else:
        gid, base = shear_groups(gal, fields)
        members = group_members(gid)
        members_base = base[members[:, 0]]
        group_files: dict[tuple, list[str]] = {}
        for g in fields.values():
            if g["role"] == "shear":
                group_files.setdefault((g["psf"], g["shear_index"]), []).append(g["file"])
        for name in np.unique(images):
            f = fields[name]
            if f["twin"] or f.get("noise_twin"):
                continue
            rows_k = members[members_base == name]
            # every usable detection of the group's images counts, as in a survey: the
            # galaxies that all members measured are summed over the members (their shape
            # noise and noise cancel), the others (unmatched detections, galaxies that a
            # member missed) are units of their own
            in_group = np.flatnonzero(np.isin(images, group_files[(f["psf"], f["shear_index"])]))
            left = np.setdiff1d(in_group, rows_k.ravel())
            e_u = np.concatenate([e[rows_k].sum(axis=1), e[left]])[:, None, :]
            s_u = np.concatenate([s[rows_k].sum(axis=1), s[left]])[:, None, :]
            try:
                est = group_shear(e_u, s_u)
                res = (est.g1, est.g1_err, est.g2, est.g2_err)
                if estimator == "fixed-point":  # the group together; error from the sums
                    fp = _fixed_point(lnL[in_group], egrid, prior, refine, sky)
                    res = (fp.g1, est.g1_err, fp.g2, est.g2_err)
                if truth_control and len(rows_k):
                    names = sorted({str(images[r]) for r in rows_k[0]})
                    t_all = truth_terms(fields, names)
                    t = np.full((e_u.shape[0], 2), np.nan)
                    t[: len(rows_k)] = t_all[np.asarray(gal["truth_index"])[rows_k[:, 0]]]
                    res = controlled_estimate(res, e_u[:, 0], s_u[:, 0], t, t_all)
            except ValueError:
                res = nan4
            rows.append((f["psf"], f["file"], f["g1"], f["g2"], *res, in_group.size,
                         rows_k.shape[0]))  # fmt: skip
    if not rows:
        return Table(names=_EST_NAMES, dtype=(int, str, *[float] * 6, int, int))
    return Table(rows=rows, names=_EST_NAMES)


def mc_rows(est: Table, psfs: list[int]) -> tuple[list[tuple], list[tuple]]:
    """Per PSF and ``all``: the fit rows, and ``(psf, component, m, c, m_err, c_err, rho)``."""
    rows, fits_ = [], []
    vals = np.column_stack([np.asarray(est[c], float) for c in ("g1", "g2", "g1_err", "g2_err")])
    finite = np.all(np.isfinite(vals), axis=1) & np.all(vals[:, 2:] > 0, axis=1)
    for k in [*psfs, "all"]:
        sel = finite & (np.ones(len(est), bool) if k == "all" else np.asarray(est["psf"]) == k)
        t = est[sel]
        res: list[float] = []
        for i in (1, 2):
            if len(t) == 0:
                res += [math.nan] * 4
                continue
            m, c, cov = fit_m_c_cov(t[f"g{i}_true"], t[f"g{i}"], t[f"g{i}_err"])
            m_, m_err, c_, c_err = fit_m_c(t[f"g{i}_true"], t[f"g{i}"], t[f"g{i}_err"])
            res += [m_, m_err, c_, c_err]
            rho = math.nan if cov is None else float(cov[0, 1] / math.sqrt(cov[0, 0] * cov[1, 1]))
            fits_.append((str(k), i, m_, m_err, c_, c_err, rho))
        if len(t):
            gt = np.column_stack([t["g1_true"], t["g2_true"]])
            gm = np.column_stack([t["g1"], t["g2"]])
            ge = np.column_stack([t["g1_err"], t["g2_err"]])
            q = quality_factor(gt, gm, ge)
        else:
            q = math.nan
        rows.append((str(k), *res, q, int(np.sum(t["n"]))))
    return rows, fits_


BIN_COLUMNS = ("kind", "bin", "lo", "hi", "center", "psf", "n_gal", "n_used", "n_prior",
              "prior_fallback",
              "m1", "m1_err", "c1", "c1_err", "m2", "m2_err", "c2", "c2_err", "Q", "mean_m",
              "mean_m_err", "mean_c", "mean_c_err")  # fmt: skip


def bins_table(kind, edges, pg, sg, e_s_of, psfs, fields, pairs, estimator, egrid, cfg,
                min_count, sky=(0.0, False)) -> list[tuple]:  # fmt: skip
    """Rows of ``meta["bins"]`` for one binned quantity (see :func:`validate`)."""
    vp, vs = np.asarray(pg[kind], float), np.asarray(sg["_bin_" + kind], float)
    okp = np.isfinite(vp)
    bp = estimate_prior_binned(np.asarray(pg["lnL"])[okp], egrid, vp[okp], edges,
                               min_count=min_count, method=cfg.prior_method)  # fmt: skip
    idx = bin_index(vs, edges)
    rows = []
    for b in range(edges.size - 1):
        prior_b = bp.prior_for_bin(b)
        sel = idx == b
        sub = sg[sel]
        e, s = e_s_of(sub, prior_b)
        est = shear_estimates(sub, e, s, fields, pairs=pairs, estimator=estimator,
                               prior=prior_b, egrid=egrid, refine=cfg.output_refine,
                               sky=sky)  # fmt: skip
        mc, _ = mc_rows(est, psfs)
        center = float(np.median(vs[sel])) if sel.any() else 0.5 * (edges[b] + edges[b + 1])
        for row in mc:
            # <m> over the components (and, for "all", over the PSFs as well, as the paper)
            use = mc[:-1] if row[0] == "all" else [row]
            ms = np.array([v for r in use for v in (r[1], r[5])], float)
            mes = np.array([v for r in use for v in (r[2], r[6])], float)
            ok = np.isfinite(ms) & np.isfinite(mes)
            mm = float(ms[ok].mean()) if ok.any() else math.nan
            mme = float(math.sqrt(np.sum(mes[ok] ** 2)) / ok.sum()) if ok.any() else math.nan
            mc_ = nanmean([row[3], row[7]])
            mce = 0.5 * math.hypot(row[4], row[8])
            sp = np.asarray(sub["psf"])
            n_bin = len(sub) if row[0] == "all" else int(np.sum(sp == int(row[0])))
            rows.append((kind, b, float(edges[b]), float(edges[b + 1]), center, row[0], n_bin,
                         row[10], int(bp.counts[b]), bool(bp.fallback[b]), *row[1:10], mm, mme,
                         mc_, mce))  # fmt: skip
    return rows


def prior_check(prior: Prior, e_int: np.ndarray, true_params, n_bins: int = 20) -> dict:
    """The recovered prior against the truth: histogram of ``|e_int|`` and residuals.

    Returns the histogram (``edges``, ``counts``, ``density``, ``density_err``), the
    recovered and true radial densities at the bin centres (``recovered``, ``true``;
    ``2 pi |e| P(|e|)``), and the fractional residual rms where the recovered density
    exceeds 5% of its peak: of the histogram (``rms_hist``, with its Poisson expectation
    ``rms_poisson``) and of the true functional form (``rms_true``, noise free).
    """
    a = np.hypot(e_int[:, 0], e_int[:, 1])
    a = a[np.isfinite(a)]
    edges = np.linspace(0.0, 1.0, n_bins + 1)
    counts, _ = np.histogram(a, edges)
    width = np.diff(edges)
    n = max(a.size, 1)
    dens = counts / (n * width)
    dens_err = np.sqrt(np.maximum(counts, 1)) / (n * width)
    mid = 0.5 * (edges[1:] + edges[:-1])
    fine = np.linspace(0.0, 1.0, 2001)
    rec_f = prior.radial_pdf(fine[:-1] + 2.5e-4)

    def binned(p: np.ndarray) -> np.ndarray:  # bin averages of a density on the fine grid
        return p.reshape(n_bins, -1).mean(axis=1)

    rec = binned(rec_f)
    out = {"edges": edges, "mid": mid, "counts": counts, "density": dens,
           "density_err": dens_err, "recovered": rec, "n": int(a.size)}  # fmt: skip
    use = rec > 0.05 * rec.max()
    frac = dens[use] / rec[use] - 1
    out["rms_hist"] = float(np.sqrt(np.mean(frac**2)))
    out["rms_poisson"] = float(np.sqrt(np.mean(1.0 / np.maximum(counts[use], 1))))
    out["true"] = None
    out["rms_true"] = math.nan
    if true_params is not None:
        tp = Prior(B=true_params[0], C=true_params[1], D=true_params[2], egrid=prior.egrid)
        tr = binned(tp.radial_pdf(fine[:-1] + 2.5e-4))
        out["true"] = tr
        out["rms_true"] = float(np.sqrt(np.mean((tr[use] / rec[use] - 1) ** 2)))
    return out
