"""Numerical convergence of the grid sampling (paper section 2.3, Figure 2).

Kitching et al. (2008, section "Numerical Convergence", Figure 2) show the ensemble
averages that enter the shear estimate -- the mean ellipticity ``<e_i>``, the
"variance in ellipticity" ``<e_i^2>`` and the shear sensitivity ``d<e_i>/dg_i``, per
component -- as functions of the numerical parameters of the code: the ellipticity grid
spacing ``de``, the size grid step ``dr``, the largest size ``r_max``, and a constant
offset of every catalogue position. Each parameter is varied in turn while the others
keep the paper's values (``de = 0.1``, ``dr = 0.2`` px, ``r_max = 10`` px, no offset).

:func:`convergence` reproduces that study on a GalSim sample whose truth is known:

* one fixed sample of galaxies is rendered once (:func:`render_sample`): intrinsic
  ellipticities drawn from the functional prior (:class:`~pylensfit.prior.Prior`),
  log-uniform sizes and matched-filter S/N, a Moffat PSF, random sub-pixel centres,
  Gaussian noise; each galaxy on a stamp twice the fitting stamp so that an offset
  catalogue position can cut a window in which the galaxy sits off-centre, as in a
  real extraction about a misplaced position;
* the same stamps (and the same noise) are fitted by :func:`~pylensfit.fit_stamps` under
  every setting; the catalogue offset is applied along ``+x`` through ``centres``;
* per galaxy the posterior means and sensitivities come from
  :func:`~pylensfit.shapes` with the **true** functional prior (the one the
  ellipticities were drawn from, normalised on each setting's grid), so that the study
  isolates the numerics from prior estimation;
* per setting: the sample means of ``<e_i>_a``, of ``<e_i>_a^2`` (the paper's
  ``<e_i^2>``, the variance of the ensemble of posterior means about zero) and of the
  sensitivities (exact response, the default, and the paper's: docs: method,
  eq-partial), with standard errors ``std / sqrt(n)``; and their change against the
  finest setting of the same parameter, from paired per-galaxy differences (same
  galaxies, same noise), whose errors are much smaller than those of the means
  themselves.

``<e_i^2>`` here is the mean square of the per-galaxy posterior means (what the paper
plots), not the posterior second moment.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from astropy.table import Table
from tqdm.auto import tqdm

from pylensfit.config import Config
from pylensfit.flags import BAD, flag_value
from pylensfit.likelihood import fit_stamps
from pylensfit.prior import Prior
from pylensfit.shear import shapes, shear_sensitivity

from .galaxies import GalaxyProfile, PSFProfile
from .simulate import draw_shapes

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_DES",
    "DEFAULT_DRS",
    "DEFAULT_OFFSETS",
    "DEFAULT_PSF",
    "DEFAULT_R_MAXS",
    "PARAMETERS",
    "QUANTITIES",
    "ConvergenceSample",
    "convergence",
    "convergence_table",
    "measure_setting",
    "plot_convergence",
    "render_sample",
    "write_convergence",
]

#: Default PSF: a round Moffat (FWHM in px), STEP1 PSF 0 of :mod:`pylensfit_validation.validation`.
DEFAULT_PSF: Mapping[str, float] = {"fwhm": 3.0, "beta": 3.5, "e1": 0.0, "e2": 0.0}
#: Default ellipticity grid spacings ``de``.
DEFAULT_DES: tuple[float, ...] = (0.05, 0.075, 0.1, 0.15, 0.2, 0.3)
#: Default size grid steps ``dr`` (px).
DEFAULT_DRS: tuple[float, ...] = (0.1, 0.2, 0.4, 0.8, 1.6)
#: Default largest model sizes ``r_max`` (px).
DEFAULT_R_MAXS: tuple[float, ...] = (2.0, 3.0, 5.0, 7.5, 10.0, 15.0)
#: Default catalogue position offsets (px, along +x).
DEFAULT_OFFSETS: tuple[float, ...] = (0.0, 1.0, 2.0, 4.0, 8.0, 12.0)

#: Varied parameters: table name -> (Config field or ``None`` for the offset, label,
#: which end of the range is the finest setting).
PARAMETERS: dict[str, tuple[str | None, str, str]] = {
    "de": ("e_step", r"$\Delta e$", "min"),
    "dr": ("r_step", r"$\Delta r$ [px]", "min"),
    "r_max": ("r_max", r"$r_{\max}$ [px]", "max"),
    "offset": (None, "catalogue offset [px]", "min"),
}

#: Per-setting quantities: sample means of ``<e_i>``, ``<e_i>^2``, the exact and the
#: paper's sensitivities.
QUANTITIES: tuple[str, ...] = (
    "e1", "e2", "e1sq", "e2sq", "sens1", "sens2", "sens1_paper", "sens2_paper",
)  # fmt: skip
#: Quantities with a relative change (``rel_*``): those whose reference is not ~0.
_RELATIVE: tuple[str, ...] = ("e1sq", "e2sq", "sens1", "sens2", "sens1_paper", "sens2_paper")


@dataclass(frozen=True)
class ConvergenceSample:
    """A rendered sample of galaxies with its truth (see :func:`render_sample`).

    Attributes
    ----------
    stamps : numpy.ndarray
        ``(n, 2N, 2N)`` float64 images, ``N = stamp_size``, background free.
    psf_image : numpy.ndarray
        ``(N, N)`` unit-flux PSF image including the pixel, centred on ``[N//2, N//2]``.
    noise_sigma : float
        Per-pixel noise standard deviation (also when no noise was added).
    x, y : numpy.ndarray
        True galaxy centres in stamp pixels (0-based, ``x`` the column).
    e : numpy.ndarray
        ``(n, 2)`` intrinsic ellipticities (GalSim reduced shear of the profile).
    r : numpy.ndarray
        Sizes in px (half-light radius for de Vaucouleurs, scale length for the exponential
        and the disc of bulge+disc: the meaning of ``r`` in the model grid).
    snr : numpy.ndarray
        Matched-filter S/N of the noise-free galaxy with the true profile.
    model : str
        Galaxy profile, the same family as the fitted model.
    prior : Prior
        The functional prior the ellipticities were drawn from (when drawn).
    stamp_size : int
        ``N``, the fitting stamp side.
    noisy : bool
        Whether Gaussian noise was added.
    """

    stamps: np.ndarray
    psf_image: np.ndarray
    noise_sigma: float
    x: np.ndarray
    y: np.ndarray
    e: np.ndarray
    r: np.ndarray
    snr: np.ndarray
    model: str
    prior: Prior
    stamp_size: int
    noisy: bool

    def __len__(self) -> int:
        return self.stamps.shape[0]


def render_sample(
    ngal: int = 1000,
    *,
    seed: int = 1,
    snr: tuple[float, float] = (10.0, 50.0),
    sizes: tuple[float, float] = (1.0, 3.0),
    psf: Mapping[str, float] | None = None,
    model: str = "devaucouleurs",
    prior: Prior | None = None,
    e: np.ndarray | None = None,
    noise: bool = True,
    stamp_size: int = 32,
    noise_sigma: float = 1.0,
) -> ConvergenceSample:
    """Render a fixed sample of PSF-convolved galaxies with GalSim, once.

    Parameters
    ----------
    ngal : int
        Number of galaxies.
    seed : int
        Seed of everything random (shapes, sizes, S/N, sub-pixel centres, noise): the same
        seed gives the same sample.
    snr : tuple of float
        Range of the matched-filter S/N, drawn log-uniformly (a single value for
        ``snr[0] == snr[1]``).
    sizes : tuple of float
        Range of the galaxy size ``r`` in px, drawn log-uniformly (its meaning is the
        model grid's, see :attr:`ConvergenceSample.r`).
    psf : mapping, optional
        Moffat PSF ``{"fwhm": px, "beta": ..., "e1": ..., "e2": ...}``, or any PSF of
        :meth:`pylensfit_validation.galaxies.PSFProfile.from_dict`; default :data:`DEFAULT_PSF`.
    model : str
        ``"devaucouleurs"``, ``"exponential"`` or ``"bulge+disc"`` (with the default
        :class:`~pylensfit.Config` bulge fraction and size ratio):
        :meth:`pylensfit_validation.galaxies.GalaxyProfile.from_model`.
    prior : Prior, optional
        Functional prior of the intrinsic ellipticities (default ``Prior()``, the
        STEP-like B, C, D = 0.19, 0.58, 2.4); draws with ``|e| > 0.99`` are redrawn.
    e : numpy.ndarray, optional
        ``(ngal, 2)`` intrinsic ellipticities to use instead of prior draws.
    noise : bool
        Add Gaussian noise of ``noise_sigma`` (``False``: noise-free stamps whose
        likelihood width is still set by ``snr``).
    stamp_size : int
        The fitting stamp side ``N``; galaxies are rendered on ``2N x 2N`` stamps.
    noise_sigma : float
        Noise per pixel (the flux scale).

    Returns
    -------
    ConvergenceSample
    """
    import galsim  # galsim: heavy import, only for rendering

    ngal = int(ngal)
    if ngal < 1:
        raise ValueError(f"ngal must be >= 1, got {ngal}")
    psf = dict(DEFAULT_PSF if psf is None else psf)
    prior = Prior() if prior is None else prior
    rng = np.random.default_rng(seed)
    if e is None:
        e = draw_shapes(prior, ngal, rng, 0.99)
    else:
        e = np.asarray(e, dtype=float).reshape(ngal, 2)
        if np.any(np.hypot(*e.T) >= 1.0):
            raise ValueError("intrinsic ellipticities must have |e| < 1")
    lo, hi = np.log(np.asarray(sizes, dtype=float))
    r = np.exp(rng.uniform(lo, hi, ngal))
    lo, hi = np.log(np.asarray(snr, dtype=float))
    s = np.exp(rng.uniform(lo, hi, ngal))
    dxy = rng.uniform(-0.5, 0.5, (ngal, 2))
    big = 2 * int(stamp_size)
    c = big // 2

    gpsf = PSFProfile.from_dict(psf).galsim()
    n = int(stamp_size)
    psf_image = gpsf.drawImage(nx=n, ny=n, scale=1.0, offset=(0.5, 0.5)).array.astype(float)
    stamps = np.empty((ngal, big, big))
    for i in range(ngal):  # GalSim renders one object at a time
        # r as the model bank's; bulge+disc: Config's bulge fraction 0.5, size ratio 0.6
        gal = GalaxyProfile.from_model(model, r[i]).galsim().shear(g1=e[i, 0], g2=e[i, 1])
        stamps[i] = (
            galsim.Convolve(gal, gpsf)
            .drawImage(nx=big, ny=big, scale=1.0, offset=(0.5 + dxy[i, 0], 0.5 + dxy[i, 1]))
            .array
        )
    norm = np.sqrt(np.einsum("kij,kij->k", stamps, stamps))
    stamps *= (s * noise_sigma / norm)[:, None, None]
    if noise:
        stamps += rng.normal(scale=noise_sigma, size=stamps.shape)
    return ConvergenceSample(
        stamps=stamps, psf_image=psf_image, noise_sigma=float(noise_sigma),
        x=c + dxy[:, 0], y=c + dxy[:, 1], e=e, r=r, snr=s, model=model, prior=prior,
        stamp_size=n, noisy=bool(noise),
    )  # fmt: skip


def measure_setting(
    sample: ConvergenceSample,
    config: Config,
    *,
    offset: float = 0.0,
    prior: Prior | None = None,
    refine: int | None = None,
) -> dict[str, np.ndarray]:
    """Fit every galaxy of ``sample`` under one setting; per-galaxy quantities.

    Parameters
    ----------
    sample : ConvergenceSample
        The rendered galaxies.
    config : Config
        Grid and model settings (``config.stamp_size`` must be ``sample.stamp_size``).
    offset : float
        Catalogue position offset in px, along ``+x``, passed to
        :func:`~pylensfit.fit_stamps` through ``centres``.
    prior : Prior, optional
        Functional prior of the posterior (default ``sample.prior``, the true one); it is
        renormalised on the setting's ellipticity grid.
    refine : int, optional
        Integration-grid refinement of :func:`~pylensfit.shapes` (default
        ``config.integration_refine``; 1 integrates on the model grid, as the paper).

    Returns
    -------
    dict of numpy.ndarray
        ``e1, e2`` (posterior means), ``e1sq, e2sq`` (their squares), ``sens1, sens2``
        (exact response), ``sens1_paper, sens2_paper`` (the paper's, eq-partial), ``flags`` (the
        fit's), ``usable`` (no flag of :data:`pylensfit.flags.BAD` -- ``STAR`` is one,
        ``NO_PEAK`` is not -- and finite values), and the 0-d arrays ``fit_time``
        (seconds) and ``refine`` (the refinement used: 1 when the grid is too coarse to
        refine).
    """
    if config.stamp_size != sample.stamp_size:
        raise ValueError(
            f"config.stamp_size {config.stamp_size} != sample stamp size {sample.stamp_size}"
        )
    refine = config.output_refine if refine is None else int(refine)
    t0 = time.perf_counter()
    fits = fit_stamps(
        sample.stamps, sample.psf_image, sample.noise_sigma, config=config,
        centres=(sample.x + float(offset), sample.y),
    )  # fmt: skip
    fit_time = time.perf_counter() - t0
    p = sample.prior if prior is None else prior
    pr = p.on_grid(fits.egrid)
    try:
        sh = shapes(fits.lnL, fits.egrid, pr, sensitivity="exact", refine=refine)
    except ValueError:
        if refine == 1:
            raise
        refine = 1  # a grid too coarse to refine (de >~ 0.4): integrate on the grid itself
        sh = shapes(fits.lnL, fits.egrid, pr, sensitivity="exact", refine=refine)
    sp1, sp2 = shear_sensitivity(fits.lnL, fits.egrid, pr, method="paper", refine=refine)
    out = {
        "e1": np.asarray(sh["e1"], dtype=float),
        "e2": np.asarray(sh["e2"], dtype=float),
        "sens1": np.asarray(sh["sens1"], dtype=float),
        "sens2": np.asarray(sh["sens2"], dtype=float),
        "sens1_paper": np.asarray(sp1, dtype=float),
        "sens2_paper": np.asarray(sp2, dtype=float),
    }
    out["e1sq"] = out["e1"] ** 2
    out["e2sq"] = out["e2"] ** 2
    finite = np.all(np.isfinite(np.column_stack([out[q] for q in QUANTITIES])), axis=1)
    out["flags"] = np.asarray(fits.flags) | np.asarray(sh["flags"])
    out["usable"] = finite & ((out["flags"] & BAD) == 0)
    out["fit_time"] = np.asarray(fit_time)
    out["refine"] = np.asarray(refine)
    return out


def _mean_err(v: np.ndarray) -> tuple[float, float]:
    n = v.size
    if n == 0:
        return math.nan, math.nan
    return float(v.mean()), (float(v.std(ddof=1) / math.sqrt(n)) if n > 1 else math.nan)


def _settings(
    des: Sequence[float], drs: Sequence[float], r_maxs: Sequence[float],
    offsets: Sequence[float],
) -> list[tuple[str, float]]:  # fmt: skip
    vals = {"de": des, "dr": drs, "r_max": r_maxs, "offset": offsets}
    return [(p, float(v)) for p in PARAMETERS for v in vals[p]]


def convergence_table(
    sample: ConvergenceSample,
    *,
    config: Config | None = None,
    des: Sequence[float] = DEFAULT_DES,
    drs: Sequence[float] = DEFAULT_DRS,
    r_maxs: Sequence[float] = DEFAULT_R_MAXS,
    offsets: Sequence[float] = DEFAULT_OFFSETS,
    prior: Prior | None = None,
    refine: int | None = None,
    progress: bool = True,
) -> Table:
    """The convergence table of a rendered sample (see :func:`convergence`).

    Parameters
    ----------
    sample : ConvergenceSample
        From :func:`render_sample`.
    config : Config, optional
        The base settings about which one parameter at a time is varied (default
        ``Config(model=sample.model, stamp_size=sample.stamp_size)``, the paper's grid).
    des, drs, r_maxs, offsets : sequence of float
        Values of ``e_step``, ``r_step`` (px), ``r_max`` (px) and of the catalogue offset
        (px, along ``+x``). An empty sequence skips that parameter.
    prior : Prior, optional
        Posterior prior (default: the sample's true prior).
    refine : int, optional
        Integration refinement of :func:`~pylensfit.shapes` (default
        ``config.integration_refine``).
    progress : bool
        Show a progress bar (tqdm, on stderr).

    Returns
    -------
    astropy.table.Table
        Described in :func:`convergence`.
    """
    base = config if config is not None else Config.paper(
        model=sample.model, stamp_size=sample.stamp_size
    )  # fmt: skip
    settings = _settings(des, drs, r_maxs, offsets)
    if not settings:
        raise ValueError("no setting to run: every parameter list is empty")
    cache: dict[tuple, dict[str, np.ndarray]] = {}
    per: list[dict[str, np.ndarray]] = []
    for name, value in tqdm(settings, desc="convergence", disable=not progress):
        field = PARAMETERS[name][0]
        cfg = base if field is None else base.replace(**{field: value})
        off = value if field is None else 0.0
        key = (cfg.e_step, cfg.r_step, cfg.r_max, off)
        if key not in cache:
            cache[key] = measure_setting(sample, cfg, offset=off, prior=prior, refine=refine)
        per.append(cache[key])

    rows = []
    star, no_peak = flag_value("STAR"), flag_value("NO_PEAK")
    for name in PARAMETERS:
        idx = [i for i, (p, _) in enumerate(settings) if p == name]
        if not idx:
            continue
        vals = np.array([settings[i][1] for i in idx])
        finest = PARAMETERS[name][2]
        if name == "offset":
            i_ref = idx[int(np.argmin(np.abs(vals)))]
        else:
            i_ref = idx[int(np.argmin(vals) if finest == "min" else np.argmax(vals))]
        ref = per[i_ref]
        for i in idx:
            m = per[i]
            use = m["usable"]
            both = use & ref["usable"]
            row: dict[str, object] = {
                "parameter": name, "value": settings[i][1], "reference": i == i_ref,
                "n_used": int(use.sum()), "n_star": int(np.count_nonzero(m["flags"] & star)),
                "n_bad": int(np.count_nonzero(~use)), "n_paired": int(both.sum()),
                "n_no_peak": int(np.count_nonzero(m["flags"] & no_peak)),
                "fit_time": float(m["fit_time"]), "refine": int(m["refine"]),
            }  # fmt: skip
            for q in QUANTITIES:
                row[q], row[f"{q}_err"] = _mean_err(m[q][use])
            for q in QUANTITIES:
                d, de = _mean_err(m[q][both] - ref[q][both])
                row[f"d_{q}"], row[f"d_{q}_err"] = d, de
                if q in _RELATIVE:
                    r0 = float(ref[q][both].mean()) if both.any() else math.nan
                    row[f"rel_{q}"] = d / r0 if r0 else math.nan
                    row[f"rel_{q}_err"] = de / abs(r0) if r0 else math.nan
            rows.append(row)
    t = Table(rows=rows)
    t["parameter"] = t["parameter"].astype(str)
    t.meta.update(
        {
            "description": "lensfit numerical convergence (Kitching et al. 2008, Figure 2)",
            "ngal": len(sample),
            "model": base.model,
            "noisy": sample.noisy,
            "snr_range": [float(sample.snr.min()), float(sample.snr.max())],
            "size_range": [float(sample.r.min()), float(sample.r.max())],
            "prior": {"B": (prior or sample.prior).B, "C": (prior or sample.prior).C,
                      "D": (prior or sample.prior).D},
            "refine": base.output_refine if refine is None else int(refine),
            "base": {"e_step": base.e_step, "r_step": base.r_step, "r_max": base.r_max,
                     "stamp_size": base.stamp_size},
            "offset_direction": "+x",
        }
    )  # fmt: skip
    return t


def convergence(
    out: str | Path | None = None,
    *,
    ngal: int = 1000,
    seed: int = 1,
    snr: tuple[float, float] = (10.0, 50.0),
    sizes: tuple[float, float] = (1.0, 3.0),
    psf: Mapping[str, float] | None = None,
    model: str = "devaucouleurs",
    des: Sequence[float] = DEFAULT_DES,
    drs: Sequence[float] = DEFAULT_DRS,
    r_maxs: Sequence[float] = DEFAULT_R_MAXS,
    offsets: Sequence[float] = DEFAULT_OFFSETS,
    prior: Prior | None = None,
    refine: int | None = None,
    config: Config | None = None,
    progress: bool = True,
) -> Table:
    """Convergence of ``<e>``, ``<e^2>`` and the sensitivity with the grid (paper Fig. 2).

    Renders one sample of galaxies (:func:`render_sample`) and fits the same stamps under
    every setting, one parameter varied at a time about ``config`` (the paper's
    ``de = 0.1``, ``dr = 0.2`` px, ``r_max = 10`` px, no offset): the ellipticity grid
    spacing ``de``, the size step ``dr``, the largest size ``r_max``, and a constant
    offset of every catalogue position along ``+x``. The posterior uses the **true**
    functional prior, the one the intrinsic ellipticities were drawn from.

    The default run (1,000 de Vaucouleurs galaxies of S/N 10-50 and half-light radius
    1-3 px; 23 rows, 20 distinct fits, the paper's setting being shared by the four
    panels) took 112 s on 2 busy cores (load ~4); the fits cost time roughly as
    ``1/de^2`` and ``r_max / dr``, and linearly in ``ngal``.

    Parameters
    ----------
    out : str or pathlib.Path, optional
        Directory to write ``convergence.png`` (Figure 2's layout: one panel per
        parameter, ``<e_i>``, ``<e_i^2>`` and sensitivity/10 for both components, with
        standard errors; below, the paired changes against the finest setting),
        ``convergence.ecsv`` (the full table) and ``convergence.md`` (a summary).
    ngal : int
        Number of galaxies. The standard error of ``<e_i>`` is ~``0.25/sqrt(ngal)``;
        changes against the finest setting are paired and far more precise.
    seed : int
        Seed of the sample (the run is deterministic given the seed).
    snr, sizes, psf, model
        The sample: log-uniform matched-filter S/N range, log-uniform size range (px),
        Moffat PSF (:data:`DEFAULT_PSF`), galaxy profile (also the fitted model).
    des, drs, r_maxs, offsets : sequence of float
        Values of each parameter (:data:`DEFAULT_DES`, :data:`DEFAULT_DRS`,
        :data:`DEFAULT_R_MAXS`, :data:`DEFAULT_OFFSETS`); empty skips a parameter.
    prior : Prior, optional
        Functional prior of the intrinsic ellipticities and of the posterior (default
        ``Prior()``: B, C, D = 0.19, 0.58, 2.4).
    refine : int, optional
        Integration-grid refinement of :func:`~pylensfit.shapes` (default
        ``config.integration_refine`` = 4; ``refine=1`` integrates on the model grid as
        the paper did, which makes the ``de`` dependence stronger).
    config : Config, optional
        Base settings (default ``Config.paper(model=model)``, the paper's grid); when
        given, its ``model`` and ``stamp_size`` are also those of the rendered sample
        (``model`` is ignored).
    progress : bool
        Show a progress bar.

    Returns
    -------
    astropy.table.Table
        One row per (parameter, value), in the order de, dr, r_max, offset. Columns:
        ``parameter`` (``"de"``, ``"dr"``, ``"r_max"``, ``"offset"``), ``value``,
        ``reference`` (the finest value of that parameter: smallest ``de``, ``dr``,
        offset; largest ``r_max``), ``n_used`` (galaxies with no bad flag, stars
        excluded, finite results), ``n_star``, ``n_bad``, ``n_paired`` (usable here and
        at the reference), ``fit_time`` (s); for every quantity ``q`` of
        :data:`QUANTITIES` (``e1, e2``: mean posterior ellipticity; ``e1sq, e2sq``: mean
        square of the posterior means, the paper's ``<e_i^2>``; ``sens1, sens2``: mean
        exact sensitivity; ``sens1_paper, sens2_paper``: the paper's, eq-partial) the mean ``q``
        and its standard error ``q_err`` over the usable galaxies, the paired change
        ``d_q`` against the reference and its error ``d_q_err`` (over galaxies usable in
        both), and for all but ``e1, e2`` the relative change ``rel_q = d_q / q_ref`` with
        ``rel_q_err``. ``meta`` records the sample and settings.
    """
    t0 = time.perf_counter()
    base = config if config is not None else Config.paper(model=model)
    sample = render_sample(
        ngal, seed=seed, snr=snr, sizes=sizes, psf=psf, model=base.model, prior=prior,
        stamp_size=base.stamp_size,
    )  # fmt: skip
    t = convergence_table(
        sample, config=base, des=des, drs=drs, r_maxs=r_maxs, offsets=offsets,
        refine=refine, progress=progress,
    )  # fmt: skip
    t.meta["seed"] = int(seed)
    t.meta["psf"] = dict(DEFAULT_PSF if psf is None else psf)
    t.meta["run_time"] = round(time.perf_counter() - t0, 1)
    if out is not None:
        write_convergence(t, out)
    return t


def write_convergence(table: Table, out: str | Path) -> dict[str, Path]:
    """Write ``convergence.{png,ecsv,md}`` into the directory ``out``.

    Returns
    -------
    dict of pathlib.Path
        ``{"png": ..., "ecsv": ..., "md": ...}``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {k: out / f"convergence.{k}" for k in ("png", "ecsv", "md")}
    table.write(paths["ecsv"], format="ascii.ecsv", overwrite=True)
    drawn = plot_convergence(table, paths["png"])
    if not drawn:
        del paths["png"]
    paths["md"].write_text(_markdown(table, paths["png"].name if drawn else None))
    return paths


def _fmt(v: float, e: float, nd: int = 4) -> str:
    return f"{v:+.{nd}f} ± {e:.{nd}f}" if np.isfinite(v) else "—"


def _markdown(t: Table, png: str | None) -> str:
    m = t.meta
    lines = [
        "# lensfit numerical convergence (Kitching et al. 2008, Figure 2)",
        "",
        f"{m.get('ngal')} {m.get('model')} galaxies, S/N {m['snr_range'][0]:.0f}-"
        f"{m['snr_range'][1]:.0f}, sizes {m['size_range'][0]:.2f}-{m['size_range'][1]:.2f} px, "
        f"seed {m.get('seed', '-')}, PSF {m.get('psf', '-')}; true prior {m['prior']}; "
        f"integration refine {m['refine']}; run time {m.get('run_time', '-')} s.",
        "One parameter varied at a time about de = {e_step}, dr = {r_step} px, "
        "r_max = {r_max} px, no offset (offset along +x).".format(**m["base"]),
        "`<e_i^2>` is the mean square of the posterior means; sens is the exact response,"
        " sens_paper the paper's (Kitching et al. 2008, arXiv:0802.1528, section 2.1)."
        " Δ: paired change against the finest value (*).",
        "",
        "| parameter | value | n | <e1> | <e2> | <e1^2> | <e2^2> | sens1 | sens2 "
        "| sens1_paper | Δ<e1> | Δ<e2> | Δ<e1^2>/<e1^2> | Δsens1/sens1 | fit s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in t:
        star = "*" if r["reference"] else ""
        lines.append(
            f"| {r['parameter']} | {r['value']:g}{star} | {r['n_used']} "
            f"| {_fmt(r['e1'], r['e1_err'])} | {_fmt(r['e2'], r['e2_err'])} "
            f"| {r['e1sq']:.4f} | {r['e2sq']:.4f} | {r['sens1']:.4f} | {r['sens2']:.4f} "
            f"| {r['sens1_paper']:.4f} | {_fmt(r['d_e1'], r['d_e1_err'])} "
            f"| {_fmt(r['d_e2'], r['d_e2_err'])} "
            f"| {_fmt(r['rel_e1sq'], r['rel_e1sq_err'], 3)} "
            f"| {_fmt(r['rel_sens1'], r['rel_sens1_err'], 3)} | {r['fit_time']:.1f} |"
        )
    lines += ["", f"![convergence]({png})" if png else "(figure not drawn)", ""]
    return "\n".join(lines)


def plot_convergence(table: Table, path: str | Path) -> bool:
    """Figure 2 of the paper from a :func:`convergence` table, as a PNG.

    Returns False, drawing nothing, when matplotlib (the ``[plots]`` extra) is not
    installed.

    Top row, one panel per parameter: ``<e_i>`` (black), ``<e_i^2>`` (green) and the
    exact sensitivity divided by 10 (red, the paper's scaling), component 1 solid and 2
    dashed, with standard errors. Bottom row: the paired changes against the finest
    value (sensitivity unscaled), with their errors.
    """
    try:
        # the optional [plots] extra; a heavy import, only for plots
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        log.warning("%s: matplotlib is not installed, so the figure is not drawn "
                    "(pip install 'pylensfit[plots]')", path)
        return False

    names = [p for p in PARAMETERS if np.any(table["parameter"] == p)]
    fig = Figure(figsize=(3.6 * len(names), 6.4))
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, len(names), squeeze=False, sharex="col")
    series = (
        ("e{}", "k", r"$\langle e_{i}\rangle$", 1.0),
        ("e{}sq", "g", r"$\langle e_{i}^2\rangle$", 1.0),
        ("sens{}", "r", r"$\partial\langle e_{i}\rangle/\partial g_{i}$ /10", 0.1),
    )
    for j, name in enumerate(names):
        t = table[table["parameter"] == name]
        t = t[np.argsort(t["value"])]
        x = np.asarray(t["value"], dtype=float)
        for top, ax in ((True, axes[0, j]), (False, axes[1, j])):
            for fmt, color, label, scale in series:
                for comp, ls in ((1, "-"), (2, "--")):
                    q = fmt.format(comp)
                    col = q if top else f"d_{q}"
                    s = scale if top else 1.0
                    ax.errorbar(
                        x, s * np.asarray(t[col]), yerr=s * np.asarray(t[f"{col}_err"]),
                        color=color, ls=ls, marker="o", ms=3, capsize=2,
                        label=label.replace("{i}", str(comp)) if j == 0 else None,
                    )  # fmt: skip
            ax.axhline(0.0, color="0.6", lw=0.5)
            ref = x[np.asarray(t["reference"], dtype=bool)]
            for v in ref:
                ax.axvline(v, color="0.8", lw=0.8, ls=":")
        axes[1, j].set_xlabel(PARAMETERS[name][1])
        axes[0, j].set_title(name)
    axes[0, 0].set_ylabel("value")
    axes[1, 0].set_ylabel("change vs finest (paired)")
    axes[0, 0].legend(fontsize=6, ncol=2)
    m = table.meta
    fig.suptitle(
        f"lensfit convergence: {m.get('ngal')} {m.get('model')} galaxies, "
        f"refine {m.get('refine')}", fontsize=9,
    )  # fmt: skip
    fig.tight_layout()
    fig.savefig(str(path), dpi=110)
    return True
