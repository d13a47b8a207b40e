"""The Markdown report of :func:`pylensfit_validation.validate.validate` and its
figures."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from astropy.table import Table

from .figures import pyplot_or_none
from .stats import BIN_LABELS, PSF_HELDOUT_TARGET, TARGETS
from .step import STEP2_KINDS

__all__ = [
    "nan_note",
    "write_report",
]


# -- report --------------------------------------------------------------------------------
def _ellipse(ax, m, c, m_err, c_err, rho, **kw) -> None:
    """The ``delta chi^2 = 1`` ellipse of a fit (its shadows are the 1-sigma errors)."""
    t = np.linspace(0, 2 * np.pi, 100)
    rho = 0.0 if not np.isfinite(rho) else rho
    x = m + m_err * np.cos(t)
    y = c + c_err * (rho * np.cos(t) + math.sqrt(max(1 - rho**2, 0.0)) * np.sin(t))
    ax.plot(x, y, **kw)


def _plot_mc_plane(res: Table, png: Path, plt) -> None:
    fits_ = res.meta["fits"]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for i, ax in zip((1, 2), axes, strict=True):
        t = fits_[(fits_["component"] == i) & (fits_["psf"] != "all")]
        shown = False
        for j, r in enumerate(t):
            col = f"C{j % 10}"
            if not np.isfinite(r["m"]):
                ax.axhline(r["c"], color=col, lw=0.8, ls=":", label=f"PSF {r['psf']} (c only)")
                continue
            ax.errorbar(r["m"], r["c"], xerr=r["m_err"], yerr=r["c_err"], fmt="o", ms=4,
                        color=col, label=f"PSF {r['psf']}")  # fmt: skip
            _ellipse(ax, r["m"], r["c"], r["m_err"], r["c_err"], r["rho"], color=col, lw=0.8)
            shown = True
        a = fits_[(fits_["component"] == i) & (fits_["psf"] == "all")]
        if len(a) and np.isfinite(a["m"][0]):
            ax.errorbar(a["m"][0], a["c"][0], xerr=a["m_err"][0], yerr=a["c_err"][0], fmt="*",
                        ms=10, color="k", label="all PSFs (joint fit)")  # fmt: skip
            shown = True
        if shown:
            ax.axvspan(-TARGETS["m"], TARGETS["m"], color="g", alpha=0.1, lw=0)
        ax.axhspan(-TARGETS["sigma_c"], TARGETS["sigma_c"], color="g", alpha=0.1, lw=0)
        ax.axhline(0, color="k", lw=0.5)
        ax.axvline(0, color="k", lw=0.5)
        ax.set_xlabel(f"m{i}")
        ax.set_ylabel(f"c{i}")
        ax.set_title(f"component {i}" + ("" if shown else " (g2 = 0: only c)"))
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)


def _plot_bins(res: Table, png: Path, plt) -> None:
    b = res.meta["bins"]
    kinds = list(dict.fromkeys(str(k) for k in b["kind"]))
    fig, axes = plt.subplots(len(kinds), 2, figsize=(10, 3.2 * len(kinds)), squeeze=False)
    for row, kind in zip(axes, kinds, strict=True):
        t = b[b["kind"] == kind]
        for j, p in enumerate(x for x in dict.fromkeys(t["psf"]) if x != "all"):
            u = t[t["psf"] == p]
            row[0].plot(u["center"], u["mean_m"], "-o", ms=3, lw=0.8, alpha=0.5, color=f"C{j}",
                        label=f"PSF {p}")  # fmt: skip
            row[1].plot(u["center"], u["mean_c"], "-o", ms=3, lw=0.8, alpha=0.5, color=f"C{j}")
        a = t[t["psf"] == "all"]
        row[0].errorbar(a["center"], a["mean_m"], yerr=a["mean_m_err"], fmt="-s", color="k",
                        lw=2, label="<m> over PSFs")  # fmt: skip
        row[1].errorbar(a["center"], a["c1"], yerr=a["c1_err"], fmt="-s", color="k", lw=2,
                        label="c1 (all PSFs)")  # fmt: skip
        row[1].errorbar(a["center"], a["c2"], yerr=a["c2_err"], fmt="--^", color="0.3", lw=2,
                        label="c2 (all PSFs)")  # fmt: skip
        for ax, what, tgt in ((row[0], "m", TARGETS["m"]), (row[1], "c", TARGETS["sigma_c"])):
            ax.axhspan(-tgt, tgt, color="g", alpha=0.1, lw=0)
            ax.axhline(0, color="k", lw=0.5)
            for x in res.meta["bin_edges"][kind][1:-1]:
                ax.axvline(x, color="0.8", lw=0.5)
            ax.set_xlabel(BIN_LABELS[kind])
            ax.set_ylabel(what)
            if kind == "snr":
                ax.set_xscale("log")
        row[0].legend(fontsize=7)
        row[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)


def _plot_prior(res: Table, png: Path, plt) -> None:
    pc = res.meta["prior_check"]
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(6, 6), sharex=True,
                                  gridspec_kw={"height_ratios": [2, 1]})  # fmt: skip
    mid = pc["mid"]
    ax.errorbar(mid, pc["density"], yerr=pc["density_err"], fmt="o", ms=3, color="k",
                label=f"truth |e_int| of the {pc['n']} prior-field galaxies")  # fmt: skip
    ax.step(pc["edges"], np.r_[pc["recovered"], pc["recovered"][-1]], where="post", color="C0",
            label=f"recovered {res.meta['prior']!r}")  # fmt: skip
    if pc["true"] is not None:
        ax.step(pc["edges"], np.r_[pc["true"], pc["true"][-1]], where="post", color="C1",
                ls="--", label="input functional form")  # fmt: skip
    ax.set_ylabel("P(|e|)")
    ax.legend(fontsize=7)
    rec = pc["recovered"]
    ax2.errorbar(mid, pc["density"] / rec - 1, yerr=pc["density_err"] / rec, fmt="o", ms=3,
                 color="k", label="truth histogram / recovered - 1")  # fmt: skip
    if pc["true"] is not None:
        ax2.plot(mid, pc["true"] / rec - 1, "--", color="C1", label="input / recovered - 1")
    ax2.axhline(0, color="k", lw=0.5)
    big = rec > 0.05 * rec.max()
    lim = max(0.25, float(np.max(np.abs(pc["density"][big] / rec[big] - 1))))
    ax2.set_ylim(-min(1.0, 1.2 * lim), min(1.0, 1.2 * lim))
    ax2.set_xlabel("|e|")
    ax2.set_ylabel("residual")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)


def _plot_residuals(est: Table, png: Path, plt, title: str) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for i, ax in zip((1, 2), axes, strict=True):
        for k in np.unique(est["psf"]):
            t = est[est["psf"] == k]
            ax.errorbar(t[f"g{i}_true"], t[f"g{i}"] - t[f"g{i}_true"], yerr=t[f"g{i}_err"],
                        fmt="o", ms=3, label=f"PSF {k}")  # fmt: skip
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(f"g{i} true")
        ax.set_title(f"component {i} ({title})")
    axes[0].set_ylabel("g measured - g true")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)


def _fmt_row(r) -> str:
    return (f"| {r['psf']} | {r['m1']:+.4f} +- {r['m1_err']:.4f} | {r['c1']:+.5f} +- "
            f"{r['c1_err']:.5f} | {r['m2']:+.4f} +- {r['m2_err']:.4f} | {r['c2']:+.5f} +- "
            f"{r['c2_err']:.5f} | {r['Q']:.0f} | {r['n_gal']} |")  # fmt: skip


_MC_HEAD = ["| PSF | m1 | c1 | m2 | c2 | Q | galaxies |", "|---|---|---|---|---|---|---|"]


def nan_note(res: Table) -> str:
    """Why a column of :func:`validate`'s table is NaN, in one line ("" if none is)."""
    notes = []
    for i in (1, 2):
        m = np.asarray(res[f"m{i}"], float)
        if m.size and np.all(np.isnan(m)):
            notes.append(f"m{i} = nan: every shear field of the set has the same g{i} (STEP1's "
                         f"are sheared along g1 only), so m{i} cannot be fitted; c{i} is the "
                         f"mean g{i} measured")  # fmt: skip
    return "; ".join(notes)


def _group_words(man: dict) -> str:
    """How a set's renderings are grouped for the estimates, in words."""
    rot = any(f["twin"] for f in man["fields"])
    neg = any(f.get("noise_twin") for f in man["fields"])
    parts = ["image"]
    if rot:
        parts.append("rotated twin")
    if neg:
        parts.append("noise twins")
    why = [w for w, on in (("shape noise", rot), ("the noise's first order", neg)) if on]
    return (" + ".join(parts) + " (matched galaxy by galaxy; " + " and ".join(why)
            + " cancel" + ("s" if len(why) == 1 else "")
            + "; every unmatched usable detection counted on its own)")


def _leakage_lines(lk: Table | None) -> list[str]:
    """The report's lines on the PSF leakage (``meta["leakage"]`` of :func:`validate`):
    one per PSF source, with all PSFs together and each PSF whose ellipticity varies."""
    if lk is None or not len(lk):
        return []

    def fit(r) -> str | None:
        if not (np.isfinite(r["alpha1"]) and np.isfinite(r["alpha2"])):
            return None
        return (f"alpha1 = {r['alpha1']:+.4f} +- {r['alpha1_err']:.4f}, alpha2 = "
                f"{r['alpha2']:+.4f} +- {r['alpha2_err']:.4f}")  # fmt: skip

    words = {"truth": "the true PSF (its adaptive-moment e at each galaxy)",
             "model": "the catalogue's model PSF (PSF_e1, PSF_e2)"}  # fmt: skip
    out = [""]
    for source, what in words.items():
        t = lk[lk["source"] == source]
        parts = [f"{'all PSFs' if r['psf'] == 'all' else 'PSF ' + r['psf']}: {fit(r)}"
                 for r in t if fit(r) is not None]  # fmt: skip
        out.append(f"- PSF leakage (g = c + alpha e_psf, sky frame) with {what}: "
                   + ("; ".join(parts) if parts else "not measured (the PSF's ellipticity "
                      "does not vary)") + ".")  # fmt: skip
    return out


def _diagnosis_lines(diag: dict[str, Any], pc: dict, has_bins: bool) -> list[str]:
    """The lines of the report's diagnosis: each target's state, and why any is not met."""
    lines: list[str] = []
    names = {"m": "|<m>| <= 0.006 (within error)", "sigma_c": "sigma_c <= 2e-4", "Q": "Q >= 100"}
    for k, label in names.items():
        lines.append(f"- **{label}**: {diag[k][0]} ({diag[k][1]}).")
    if "psf_heldout" in diag:
        lines.append(f"- **PSF model on held-out stars**: {diag['psf_heldout'][0]} "
                     f"({diag['psf_heldout'][1]}).")  # fmt: skip
    lines.append("")
    if diag["all_met"]:
        lines.append("All targets are met.")
    else:
        why = ["Where it falls short, the evidence below says why: "]
        if diag["bins_significant"]:
            sig = "; ".join(diag["bins_significant"])
            why.append(f"m departs from 0 by more than 2 sigma in {sig} (see m against "
                       "magnitude, S/N and size). ")  # fmt: skip
        elif has_bins:
            why.append("no bin of magnitude, S/N or size has m beyond 2 sigma of 0. ")
        if "psf_worst" in diag:
            why.append(f"The largest PSF-model ellipticity residual is "
                       f"{diag['psf_worst'][1]:.4f} (PSF {diag['psf_worst'][0]}); see the PSF "
                       "table. ")  # fmt: skip
        why.append(f"The recovered prior differs from the input functional form by "
                   f"{pc['rms_true']:.3f} rms (fractional, where P > 5% of its peak), and from "
                   f"the truth histogram by {pc['rms_hist']:.3f} against {pc['rms_poisson']:.3f} "
                   "expected from Poisson noise.")  # fmt: skip
        lines.append("".join(why))
    return lines


def write_report(res: Table, man: dict, path: str | Path) -> list[Path]:
    """Write the Markdown report of :func:`validate` and its PNG figures beside it.

    Figures (``<stem>`` is the report's name without its suffix): ``<stem>.png``,
    ``g_meas - g_true`` against ``g_true`` per PSF (the fits' input: pairs for step2);
    ``<stem>_mc.png``, the (m, c) plane per PSF with ``delta chi^2 = 1`` ellipses;
    ``<stem>_bins.png``, m and c against magnitude, S/N and size; ``<stem>_prior.png``,
    the recovered prior against the truth's intrinsic ``|e|`` with the residual.

    Parameters
    ----------
    res : astropy.table.Table
        The output of :func:`validate`.
    man : dict
        The set's manifest (:func:`read_manifest`).
    path : str or pathlib.Path
        The Markdown file.

    Returns
    -------
    list of pathlib.Path
        The files written (the report first).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = res.meta
    stem = path.with_suffix("")
    pngs = {"resid": path.with_suffix(".png"), "mc": Path(f"{stem}_mc.png"),
            "bins": Path(f"{stem}_bins.png"), "prior": Path(f"{stem}_prior.png")}  # fmt: skip
    has_bins = meta.get("bins") is not None and len(meta["bins"]) > 0
    if not has_bins:
        del pngs["bins"]
    plt = pyplot_or_none(str(path))
    if plt is None:
        pngs = {}
    else:
        _plot_residuals(meta["estimates"], pngs["resid"], plt, meta["mode"])
        _plot_mc_plane(res, pngs["mc"], plt)
        if has_bins:
            _plot_bins(res, pngs["bins"], plt)
        _plot_prior(res, pngs["prior"], plt)

    def figure(key: str, alt: str) -> str:
        return f"![{alt}]({pngs[key].name})" if key in pngs else "(figure not drawn)"
    diag = meta["diagnosis"]
    pc = meta["prior_check"]
    n_est = len(meta["estimates"])
    lines = [f"# pylensfit validation: {man['kind']} ({man['dir']})", "",
             f"Estimator `{meta['estimator']}`; shear per "
             + (_group_words(man) if meta["mode"] == "pairs" else "image")
             + f", {n_est} estimates. Prior from the zero-shear fields: {meta['prior']!r}"
             + ("" if meta.get("bulge_weights") is None else
                "; bulge-fraction prior " + ", ".join(
                    f"{f}: {w:.3f}" for f, w in zip(
                        meta.get("bulge_runs") or [f"{f:g}" for f in np.linspace(
                            0, 1, len(meta["bulge_weights"]))], meta["bulge_weights"],
                        strict=True))) + "."
             + (" Fitted with the true PSFs, not the stars' (diagnostic)."
                if meta.get("psf_source") == "true" else "")
             + (" The truth's shape noise taken out of each estimate (a control variate "
                "of expectation zero: `validate --truth-control`); the bins without it."
                if meta.get("truth_control") else ""), "",
             f"<m> = {meta['mean_m']:+.4f} +- {meta['mean_m_err']:.4f} (the paper's mean of the "
             f"PSFs' errors: "
             f"+- {meta['mean_m_err_paper']:.4f}), sigma_c = {meta['sigma_c']:.2e} "
             f"(from the errors alone {meta['sigma_c_stat']:.2e}; the offsets' own spread "
             f"{meta.get('sigma_c_hat', math.nan):.1e}, < "
             f"{meta.get('sigma_c_upper', math.nan):.1e} at 95 %), Q = {res['Q'][-1]:.0f}", "",
             *_MC_HEAD]  # fmt: skip
    lines += [_fmt_row(r) for r in res]
    if nan_note(res):
        lines += ["", nan_note(res) + "."]
    lines += _leakage_lines(meta.get("leakage"))
    lines += ["", figure("resid", "g_meas - g_true"), "",
              "## Diagnosis", ""]  # fmt: skip
    lines += _diagnosis_lines(diag, pc, has_bins)
    lines += ["", "## m and c in the (m, c) plane", "",
              "1-sigma error bars and the delta chi^2 = 1 ellipse of each PSF's fit; the shaded "
              "bands are |m| <= 0.006 and |c| <= 2e-4.", "",
              figure("mc", "m-c plane"), ""]  # fmt: skip
    if meta.get("single") is not None and meta["mode"] == "pairs":
        lines += ["Single images (no twin cancellation), for comparison:", "", *_MC_HEAD]
        lines += [_fmt_row(r) for r in meta["single"]]
        lines.append("")
    if has_bins:
        b = meta["bins"]
        lines += ["## m and c per bin (a prior per bin, paper Table 2)", "",
                  "| quantity | bin | galaxies | prior galaxies | <m> | m1 | c1 | m2 | c2 | Q |",
                  "|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for r in b[b["psf"] == "all"]:
            fb = " (global prior)" if r["prior_fallback"] else ""
            span = (STEP2_KINDS[int(r["bin"])] if r["kind"] == "morphology"
                    else f"[{r['lo']:.3g}, {r['hi']:.3g})")  # fmt: skip
            lines.append(
                f"| {r['kind']} | {span} | {r['n_gal']} | "
                f"{r['n_prior']}{fb} | {r['mean_m']:+.4f} +- {r['mean_m_err']:.4f} | "
                f"{r['m1']:+.4f} +- {r['m1_err']:.4f} | {r['c1']:+.5f} +- {r['c1_err']:.5f} | "
                f"{r['m2']:+.4f} +- {r['m2_err']:.4f} | {r['c2']:+.5f} +- {r['c2_err']:.5f} | "
                f"{r['Q']:.0f} |"
            )
        lines += ["", "Faint lines: each PSF; bold: all PSFs.", "",
                  figure("bins", "m and c per bin"), ""]  # fmt: skip
    pcheck = meta["psf_check"]
    held = bool(len(pcheck)) and bool(np.any(np.asarray(pcheck["heldout_n"]) > 0))
    if len(pcheck):
        lines += ["## PSF models", "",
                  "Measured: the pipeline's PSF (stars, pixel included) averaged over the "
                  "shear images; true: GalSim's rendering of the input PSF with the pixel, "
                  "measured the same way (effective FWHM, adaptive-moment e).", "",
                  "| PSF | FWHM true | FWHM meas | e1 true | e1 meas | e2 true | e2 meas "
                  "| c1 | c2 |" + (" held-out stars | rms de1 / de2 | noise | excess de1 / de2 |"
                                   if held else ""),
                  "|---|---|---|---|---|---|---|---|---|" + ("---|---|---|---|"
                                                             if held else "")]  # fmt: skip
        cmap = {str(r["psf"]): r for r in res}
        for r in pcheck:
            c = cmap.get(str(r["psf"]))
            lines.append(
                f"| {r['psf']} | {r['fwhm_true']:.2f} | {r['fwhm_meas']:.2f} | "
                f"{r['e1_true']:+.4f} | {r['e1_meas']:+.4f} | {r['e2_true']:+.4f} | "
                f"{r['e2_meas']:+.4f} | {c['c1']:+.5f} | {c['c2']:+.5f} |"
                + (f" {r['heldout_n']} | {r['heldout_rms_de1']:.1e} / "
                   f"{r['heldout_rms_de2']:.1e} | {r['heldout_noise_de']:.1e} | "
                   f"{r['heldout_excess_de1']:.1e} / {r['heldout_excess_de2']:.1e} |"
                   if held else "")
            )
        if held:
            lines += ["", "Held-out stars: the PSF model's stars left out of its first fit "
                      "(pylensfit.psfmodel.PolynomialPSF), star minus model adaptive-moment "
                      "ellipticity over every image of the shear fields; noise: the rms "
                      "their own noise gives; excess: sqrt(rms^2 - noise^2), the model's "
                      f"error (target < {PSF_HELDOUT_TARGET:.0e})."]  # fmt: skip
        lines.append("")
    lines += ["## The prior", "",
              f"Recovered {meta['prior']!r} from the prior fields' galaxies against the truth "
              f"|e_int| of the {pc['n']} that were matched; fractional residual rms (where P > "
              f"5% of its peak): histogram {pc['rms_hist']:.3f} (Poisson {pc['rms_poisson']:.3f}),"
              f" input functional form {pc['rms_true']:.3f}.", "",
              figure("prior", "prior"), "",
              "Measured catalogues: " + ", ".join(
                  f"`{Path(v['path']).name}`" + (" (reused)" if v["reused"] else "")
                  for v in meta["measured"].values()), ""]  # fmt: skip
    path.write_text("\n".join(lines))
    return [path, *pngs.values()]
