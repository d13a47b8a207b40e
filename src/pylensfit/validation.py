"""STEP1- and STEP2-like validation sets simulated with GalSim (paper sections 4-5).

``simulate_step("step1", out)`` writes a STEP1-like set: bulge + disc galaxies
(de Vaucouleurs bulge, exponential disc), five PSFs (round, elliptical along ``e1``,
elliptical along ``e2``, larger, and a diagonal one with a broader wing), ``g1`` in
{0, 0.005, 0.01, 0.05, 0.1} with ``g2 = 0``, pixel 0.206 arcsec.

``simulate_step("step2", out)`` writes a STEP2-like set: complex morphologies (Sersic
profiles of varied index, bulge + disc, discs with star-forming knots), a random shear
``|g| <= 0.06`` per image in both components, each image with a twin whose galaxies are
rotated by 90 degrees before the shear (the same objects and shear, independent noise),
five PSFs of which two are highly elliptical, pixel 0.2 arcsec.

Both sets have a zero-shear field per PSF (role ``"prior"``) from which the ellipticity
prior is estimated, as in the paper, and a star-only field per PSF from which the PSF is
modelled. Every field carries its truth table in a ``TRUTH`` extension (columns as in
:func:`pylensfit.simulate.simulate_field`); ``manifest.json`` lists the fields.

Conventions are those of :mod:`pylensfit.simulate`: sizes in pixels, numpy ``(x, y)``
0-based is GalSim ``(x + 1, y + 1)``, ``e = (a - b) / (a + b)`` and a shear ``g`` maps
``e_s`` to ``(e_s + g) / (1 + g* e_s)``.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path

import numpy as np
from astropy.table import Table

from .prior import Prior
from .simulate import (
    FieldSpec,
    _add_object,
    _add_sky_and_noise,
    _psf,
    _truth_table,
    draw_population,
    simulate_field,
    write_field,
)

__all__ = [
    "STEP1_PSFS",
    "STEP2_PSFS",
    "STEP1_SHEARS",
    "simulate_step",
    "read_manifest",
    "render_step2_field",
    "main",
]

#: STEP1-like PSFs: Moffat ``(fwhm [px], beta, e1, e2)``; pixel 0.206 arcsec.
STEP1_PSFS: tuple[dict, ...] = (
    {"fwhm": 3.0, "beta": 3.5, "e1": 0.0, "e2": 0.0},  # round
    {"fwhm": 3.0, "beta": 3.5, "e1": 0.05, "e2": 0.0},  # elliptical along e1
    {"fwhm": 3.0, "beta": 3.5, "e1": 0.0, "e2": 0.05},  # elliptical along e2
    {"fwhm": 4.5, "beta": 3.5, "e1": 0.0, "e2": 0.0},  # larger
    {"fwhm": 3.5, "beta": 2.5, "e1": -0.03, "e2": 0.03},  # diagonal, broad wings
)

#: STEP2-like PSFs, two of them highly elliptical; pixel 0.2 arcsec.
STEP2_PSFS: tuple[dict, ...] = (
    {"fwhm": 3.0, "beta": 3.5, "e1": 0.0, "e2": 0.0},  # round
    {"fwhm": 3.0, "beta": 3.5, "e1": 0.04, "e2": -0.02},  # mildly elliptical
    {"fwhm": 4.5, "beta": 3.0, "e1": 0.01, "e2": 0.01},  # larger
    {"fwhm": 3.0, "beta": 3.5, "e1": 0.12, "e2": 0.0},  # highly elliptical along e1
    {"fwhm": 3.5, "beta": 3.0, "e1": -0.07, "e2": 0.10},  # highly elliptical, diagonal
)

#: STEP1 input shears ``g1`` (``g2 = 0``).
STEP1_SHEARS: tuple[float, ...] = (0.0, 0.005, 0.01, 0.05, 0.1)

_PIXEL = {"step1": 0.206, "step2": 0.2}
_STAMP = 64


def _spec_for(psf: dict, **kw) -> FieldSpec:
    return FieldSpec(
        psf_fwhm=psf["fwhm"], psf_beta=psf["beta"], psf_e1=psf["e1"], psf_e2=psf["e2"], **kw
    )


def _step2_galaxy(
    kind: str, r: float, n: float, bulge_frac: float, knot_frac: float, n_knots: int, knot_seed: int
):
    """Round (before the intrinsic shear) unit-flux STEP2-like galaxy of half-light radius r."""
    import galsim

    from .models import DEVAUC_TRUNCATION as T

    if kind == "sersic":
        trunc = T * r if n > 2.0 else 0.0
        return galsim.Sersic(n=n, half_light_radius=r, trunc=trunc)
    rb = 0.5 * r
    bulge = galsim.DeVaucouleurs(half_light_radius=rb, trunc=T * rb).withFlux(bulge_frac)
    disc_flux = 1.0 - bulge_frac
    if kind == "bulge+disc":
        return galsim.Add(bulge, galsim.Exponential(half_light_radius=r).withFlux(disc_flux))
    if kind == "knots":  # disc with star-forming knots that follow it
        knots = galsim.RandomKnots(
            n_knots,
            half_light_radius=r,
            flux=knot_frac * disc_flux,
            rng=galsim.BaseDeviate(knot_seed),
        )
        disc = galsim.Exponential(half_light_radius=r).withFlux((1 - knot_frac) * disc_flux)
        return galsim.Add(bulge, disc, knots)
    raise ValueError(f"unknown step2 galaxy kind {kind!r}")


def render_step2_field(
    spec: FieldSpec, *, seed: int, noise_seed: int | None = None
) -> tuple[np.ndarray, np.ndarray, Table]:
    """Render a STEP2-like field: complex morphologies, sheared, with stars and noise.

    The lattice, stars, fluxes, intrinsic ellipticities and noise follow
    :func:`pylensfit.simulate.simulate_field`; the galaxies are a mix of Sersic profiles
    (index 0.5-4), bulge + disc, and discs with star-forming knots
    (``galsim.RandomKnots``). ``spec.size_range`` is the range of half-light radii (px).

    Parameters
    ----------
    spec : FieldSpec
        What to simulate (``spec.model`` is ignored). With ``spec.rotate`` each galaxy,
        knots included, is rotated by 90 degrees after its intrinsic shear and before the
        lensing shear: the twin of the field with the same ``seed``.
    seed : int
        Seed of the objects.
    noise_seed : int, optional
        Seed of the noise (default: derived from ``seed``).

    Returns
    -------
    image : numpy.ndarray
        ``(size, size)`` float32, sky included, with Gaussian noise.
    weight : numpy.ndarray
        Inverse-variance map.
    truth : astropy.table.Table
        As :func:`pylensfit.simulate.simulate_field`, plus ``kind`` (galaxy type),
        ``sersic_n``, ``bulge_frac``, ``n_knots``; ``r`` is the half-light radius.
        ``e1_int, e2_int`` are the (rotated, for a twin) intrinsic shears of the profile.
    """
    import galsim

    rng = np.random.default_rng(seed)
    n = int(spec.size)
    x, y, is_star, r, snr, star_snr, e_int = draw_population(spec, rng)
    n_obj = x.size
    kinds = rng.choice(np.array(["sersic", "bulge+disc", "knots"]), n_obj, p=[0.4, 0.3, 0.3])
    sersic_n = np.round(rng.uniform(0.5, 4.0, n_obj), 1)  # quantised: GalSim caches by n
    bulge_frac = rng.uniform(0.0, 0.5, n_obj)
    knot_frac = rng.uniform(0.2, 0.5, n_obj)
    n_knots = rng.integers(10, 60, n_obj)
    knot_seed = rng.integers(1, 2**31 - 1, n_obj)
    if spec.rotate:
        e_int = -e_int  # a 90-degree rotation of an ellipse flips e
    es = e_int[:, 0] + 1j * e_int[:, 1]
    g = complex(spec.g1, spec.g2)
    e_obs = (es + g) / (1 + np.conj(g) * es)
    e_obs[is_star] = 0.0

    psf = _psf(spec)
    image = galsim.ImageF(n, n, scale=1.0)  # bounds 1..n: numpy (x, y) is galsim (x+1, y+1)
    flux = np.empty(n_obj)
    psf_peak = psf.drawImage(nx=_STAMP, ny=_STAMP, scale=1.0).array.max()
    for i in range(n_obj):
        if is_star[i]:
            obj = psf
            flux[i] = star_snr[i] * spec.noise_sigma / psf_peak
        else:
            gal = _step2_galaxy(
                str(kinds[i]),
                r[i],
                sersic_n[i],
                bulge_frac[i],
                knot_frac[i],
                int(n_knots[i]),
                int(knot_seed[i]),
            )
            # intrinsic shape: the unrotated ellipse (so that both twins get the same flux)
            e0 = -e_int[i] if spec.rotate else e_int[i]
            gal = gal.shear(g1=e0[0], g2=e0[1])
            norm = galsim.Convolve(gal.shear(g1=spec.g1, g2=spec.g2), psf)
            arr = norm.drawImage(nx=_STAMP, ny=_STAMP, scale=1.0).array
            flux[i] = snr[i] * spec.noise_sigma / np.sqrt((arr**2).sum())
            if spec.rotate:
                gal = gal.rotate(90 * galsim.degrees)
            obj = galsim.Convolve(gal.shear(g1=spec.g1, g2=spec.g2), psf)
        _add_object(image, obj, flux[i], x[i], y[i], _STAMP)
    arr, weight = _add_sky_and_noise(image, spec, seed, noise_seed)
    truth = _truth_table(x, y, is_star, flux, r, e_int, e_obs, snr)
    truth["kind"] = np.where(is_star, "star", kinds)
    truth["sersic_n"] = np.where(is_star | (kinds != "sersic"), np.nan, sersic_n)
    truth["bulge_frac"] = np.where(is_star | (kinds == "sersic"), np.nan, bulge_frac)
    truth["n_knots"] = np.where(~is_star & (kinds == "knots"), n_knots, 0)
    truth.meta.update(
        {
            "g1": spec.g1,
            "g2": spec.g2,
            "model": "step2",
            "noise": spec.noise_sigma,
            "psf_fwhm": spec.psf_fwhm,
            "psf_e1": spec.psf_e1,
            "psf_e2": spec.psf_e2,
            "seed": seed,
            "rotate": spec.rotate,
        }
    )
    return arr, weight, truth


def _field_size(ngal: int, n_fields: int, spacing: float, star_fraction: float) -> int:
    """Field size (px) giving about ``ngal / n_fields`` galaxies on the lattice."""
    per_field = max(ngal / n_fields, 1.0) / max(1.0 - star_fraction, 1e-3)
    m = max(round(math.sqrt(per_field)), 1)
    return int(math.ceil((m + 1) * spacing))  # simulate_field puts m points on (m+1)*spacing


def _step2_shears(n_shear: int, gmax: float, rng: np.random.Generator) -> list[tuple]:
    """Random shears, uniform in the disc ``|g| <= gmax``, both components nonzero."""
    out = []
    while len(out) < n_shear:
        g1, g2 = rng.uniform(-gmax, gmax, 2)
        if math.hypot(g1, g2) <= gmax and abs(g1) > 1e-3 and abs(g2) > 1e-3:
            out.append((float(g1), float(g2)))
    return out


def simulate_step(
    kind: str,
    out: str | Path,
    *,
    ngal: int = 20000,
    seed: int = 1,
    noise_sigma: float = 1.0,
    field_size: int | None = None,
    n_shear: int | None = None,
    gmax: float = 0.06,
    spacing: float = 40.0,
    star_fraction: float = 0.05,
    snr_range: tuple[float, float] = (15.0, 150.0),
    size_range: tuple[float, float] | None = None,
    star_field_size: int | None = None,
    psfs: tuple[dict, ...] | None = None,
) -> Path:
    """Simulate a STEP1- or STEP2-like validation set with GalSim.

    Parameters
    ----------
    kind : {"step1", "step2"}
        Which set (see the module docstring).
    out : str or pathlib.Path
        Output directory (created).
    ngal : int
        Total number of galaxies over the shear fields (twins included); sets the field
        size from the lattice ``spacing`` unless ``field_size`` is given.
    seed : int
        Master seed; every field's object and noise seeds derive from it (in the manifest).
    noise_sigma : float
        Gaussian noise per pixel (the S/N range is relative to it).
    field_size : int, optional
        Field size in pixels (overrides the one derived from ``ngal``).
    n_shear : int, optional
        Number of shear values per PSF: step1 takes the first ``n_shear`` of
        ``STEP1_SHEARS`` (default all 5); step2 draws ``n_shear`` random shears (default
        4), shared by all PSFs, each with a rotated twin.
    gmax : float
        Largest ``|g|`` of the step2 shears.
    spacing : float
        Lattice pitch (px).
    star_fraction : float
        Fraction of the lattice points that are stars in the galaxy fields.
    snr_range : tuple of float
        Range of galaxy matched-filter S/N (log-uniform).
    size_range : tuple of float, optional
        Galaxy size range (px): scale length of the disc for step1 (default (1.2, 3.5)),
        half-light radius for step2 (default (1.5, 4.5)).
    star_field_size : int, optional
        Size of the star-only fields (default: ``field_size``).
    psfs : tuple of dict, optional
        PSFs as ``{"fwhm", "beta", "e1", "e2"}`` (default ``STEP1_PSFS``/``STEP2_PSFS``).

    Returns
    -------
    pathlib.Path
        The output directory, holding ``psf{k}_g{j}.fits`` (shear fields),
        ``psf{k}_g{j}_rot.fits`` (step2 twins), ``psf{k}_prior.fits`` (zero shear),
        ``psf{k}_stars.fits`` (stars only) and ``manifest.json``.
    """
    if kind not in _PIXEL:
        raise ValueError(f"kind must be 'step1' or 'step2', not {kind!r}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    psfs = tuple(psfs) if psfs is not None else (STEP1_PSFS if kind == "step1" else STEP2_PSFS)
    rng = np.random.default_rng(seed)
    if kind == "step1":
        shears = [(g, 0.0) for g in STEP1_SHEARS[: (n_shear or len(STEP1_SHEARS))]]
        twins = (False,)
        size_range = size_range or (1.2, 3.5)
    else:
        shears = _step2_shears(n_shear or 4, gmax, rng)
        twins = (False, True)
        size_range = size_range or (1.5, 4.5)
    n_fields = len(psfs) * len(shears) * len(twins)
    size = int(field_size) if field_size else _field_size(ngal, n_fields, spacing, star_fraction)
    star_size = int(star_field_size) if star_field_size else size
    pixel = _PIXEL[kind]
    render = simulate_field if kind == "step1" else render_step2_field
    common = dict(
        size=size,
        spacing=spacing,
        noise_sigma=noise_sigma,
        snr_range=snr_range,
        size_range=size_range,
        star_fraction=star_fraction,
        pixel_scale_arcsec=pixel,
        model="bulge+disc",
    )

    def seeds() -> tuple[int, int]:
        s = rng.integers(1, 2**31 - 1, 2)
        return int(s[0]), int(s[1])

    fields = []
    star_files = []
    for k, psf in enumerate(psfs):
        star_file = f"psf{k}_stars.fits"
        s_obj, s_noise = seeds()
        sspec = _spec_for(psf, **{**common, "size": star_size, "star_fraction": 1.0})
        img, w, truth = simulate_field(sspec, seed=s_obj, noise_seed=s_noise)
        write_field(out / star_file, img, w, sspec, truth=truth)
        star_files.append(
            {
                "file": star_file,
                "psf": k,
                "psf_params": dict(psf),
                "seed": s_obj,
                "noise_seed": s_noise,
                "n_star": len(truth),
            }
        )
        jobs = [("prior", None, 0.0, 0.0, False)]
        jobs += [("shear", j, g1, g2, t) for j, (g1, g2) in enumerate(shears) for t in twins]
        obj_seed = {}
        for role, j, g1, g2, twin in jobs:
            if role == "prior":
                name = f"psf{k}_prior.fits"
            else:
                name = f"psf{k}_g{j}" + ("_rot" if twin else "") + ".fits"
            s_obj, s_noise = seeds()
            if twin:
                s_obj = obj_seed[j]  # the same objects, rotated; independent noise
            else:
                obj_seed[j] = s_obj
            spec = _spec_for(psf, **common, g1=g1, g2=g2, rotate=twin)
            img, w, truth = render(spec, seed=s_obj, noise_seed=s_noise)
            write_field(out / name, img, w, spec, truth=truth)
            n_gal = int((~np.asarray(truth["is_star"])).sum())
            fields.append(
                {
                    "file": name,
                    "role": role,
                    "psf": k,
                    "psf_params": dict(psf),
                    "g1": g1,
                    "g2": g2,
                    "shear_index": j,
                    "twin": twin,
                    "star_file": star_file,
                    "seed": s_obj,
                    "noise_seed": s_noise,
                    "n_gal": n_gal,
                    "n_obj": len(truth),
                }
            )
    manifest = {
        "kind": kind,
        "pixel_scale_arcsec": pixel,
        "ngal": ngal,
        "ngal_shear_fields": sum(f["n_gal"] for f in fields if f["role"] == "shear"),
        "seed": seed,
        "noise_sigma": noise_sigma,
        "field_size": size,
        "star_field_size": star_size,
        "psfs": [dict(p) for p in psfs],
        "shears": [list(s) for s in shears],
        "fieldspec": {k: v for k, v in asdict(FieldSpec(**common)).items() if k not in ("extra",)},
        "star_fields": star_files,
        "fields": fields,
    }
    manifest["fieldspec"]["model"] = "bulge+disc" if kind == "step1" else "step2"
    with open(out / "manifest.json", "w") as fh:
        json.dump(manifest, fh, indent=1, default=list)
    return out


def read_manifest(directory: str | Path) -> dict:
    """Read the ``manifest.json`` of a validation set written by :func:`simulate_step`.

    Parameters
    ----------
    directory : str or pathlib.Path
        The set's directory.

    Returns
    -------
    dict
        The manifest, with ``"dir"`` (the directory) added and every field's and star
        field's ``"path"`` (absolute path of its FITS file).
    """
    directory = Path(directory)
    with open(directory / "manifest.json") as fh:
        man = json.load(fh)
    man["dir"] = str(directory)
    for f in man["fields"] + man["star_fields"]:
        f["path"] = str(directory / f["file"])
    return man


def main(argv: list[str] | None = None) -> int:
    """``pylensfit simulate step1|step2 --out DIR [--ngal N] [--seed S] [--noise SIGMA]``.

    Standalone entry point (``python -m pylensfit.validation ...``), for the CLI to wire in.

    Parameters
    ----------
    argv : list of str, optional
        Arguments (default ``sys.argv[1:]``).

    Returns
    -------
    int
        Exit status.
    """
    import argparse

    p = argparse.ArgumentParser(
        prog="pylensfit simulate", description="simulate a STEP1/STEP2-like validation set"
    )
    p.add_argument("kind", choices=["step1", "step2"])
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--ngal", type=int, default=20000, help="galaxies over the shear fields")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--noise", type=float, default=1.0, help="noise sigma per pixel")
    p.add_argument("--size", type=int, default=None, help="field size (px)")
    p.add_argument("--nshear", type=int, default=None, help="shear values per PSF")
    a = p.parse_args(argv)
    d = simulate_step(
        a.kind,
        a.out,
        ngal=a.ngal,
        seed=a.seed,
        noise_sigma=a.noise,
        field_size=a.size,
        n_shear=a.nshear,
    )
    man = read_manifest(d)
    print(
        f"{a.kind}: {len(man['fields'])} fields of {man['field_size']} px, "
        f"{man['ngal_shear_fields']} galaxies in shear fields, "
        f"{len(man['star_fields'])} star fields -> {d}"
    )
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())


# ----------------------------------------------------------------------------------------
# Validation: m, c, sigma_c and Q (paper section 5, DESIGN.md section 5)
# ----------------------------------------------------------------------------------------
def fit_m_c(g_true, g_meas, g_err) -> tuple[float, float, float, float]:
    """Chi-square fit of ``g_meas - g_true = m g_true + c``: ``(m, m_err, c, c_err)``.

    The model is linear, so the 1-sigma errors projected from the (m, c) chi-square grid
    (``delta chi^2 = 1``) are the square roots of the diagonal of the fit covariance.
    """
    gt = np.asarray(g_true, dtype=float)
    d = np.asarray(g_meas, dtype=float) - gt
    w = 1.0 / np.asarray(g_err, dtype=float) ** 2
    A = np.column_stack([gt, np.ones_like(gt)])
    F = A.T @ (A * w[:, None])
    if np.linalg.cond(F) > 1e12:  # all g_true equal: only c is measured
        c = float(np.sum(w * d) / np.sum(w))
        return math.nan, math.nan, c, float(1.0 / math.sqrt(np.sum(w)))
    cov = np.linalg.inv(F)
    m, c = cov @ (A.T @ (w * d))
    return float(m), float(math.sqrt(cov[0, 0])), float(c), float(math.sqrt(cov[1, 1]))


def quality_factor(g_true: np.ndarray, g_meas: np.ndarray, g_err: np.ndarray) -> float:
    """Paper's ``Q = 1000 sigma_stat^2 / <(g_meas - g_true)^2>`` over images and components.

    ``g_*`` are ``(n_images, 2)``; ``sigma_stat^2`` is the mean statistical variance of
    the images' estimates (``g_err^2``), the spread an unbiased method would show.
    """
    d2 = (np.asarray(g_meas) - np.asarray(g_true)) ** 2
    return float(1000.0 * np.mean(np.asarray(g_err) ** 2) / np.mean(d2))


def validate(
    directory: str | Path,
    *,
    config=None,
    jobs: int = 1,
    estimator: str = "key2",
    report: str | Path | None = None,
    progress: bool = True,
):
    """Run the pipeline on a simulated set and measure m, c, sigma_c and Q per PSF.

    The prior is estimated from the zero-shear fields of all PSFs (as in the paper), then
    each PSF's shear fields are measured with its own star field, the shear of every
    image estimated (``estimator``: eq. ``key2`` or the sheared-prior fixed point), and
    ``g_meas - g_true = m g_true + c`` fitted per PSF and component.

    Returns
    -------
    astropy.table.Table
        One row per PSF and a last row ``all``: ``m1, m1_err, c1, c1_err, m2, m2_err, c2,
        c2_err, Q, n_gal``; ``meta`` holds ``<m>``, ``sigma_c``, the global Q, the prior,
        and the per-image table.
    """
    from astropy.table import Table

    from .config import Config
    from .pipeline import measure
    from .prior import estimate_prior
    from .shear import shear_table

    man = read_manifest(directory)
    cfg = config if config is not None else Config(model="bulge+disc")
    by_psf: dict[int, list] = {}
    for f in man["fields"]:
        by_psf.setdefault(int(f["psf"]), []).append(f)
    stars = {int(s["psf"]): s["path"] for s in man["star_fields"]}
    # the prior, from the zero-shear fields
    lnls = []
    for k, fields in sorted(by_psf.items()):
        pf = [f["path"] for f in fields if f["role"] == "prior"]
        if not pf:
            continue
        cat = measure(pf, stars=[stars[k]], config=cfg, prior=Prior(), jobs=jobs,
                      progress=progress)  # fmt: skip
        gal = (np.asarray(cat["flags"]) == 0) & (np.asarray(cat["fitclass"]) == 0)
        lnls.append(np.asarray(cat["lnL"])[gal])
        egrid = cat.meta["egrid"]
    prior = estimate_prior(np.concatenate(lnls), egrid, method=cfg.prior_method)
    per_image = []
    for k, fields in sorted(by_psf.items()):
        sf = [f for f in fields if f["role"] == "shear"]
        cat = measure([f["path"] for f in sf], stars=[stars[k]], config=cfg, prior=prior,
                      jobs=jobs, progress=progress)  # fmt: skip
        tab = shear_table(cat, by="image", estimator=estimator, prior=prior,
                          egrid=cat.meta["egrid"], refine=cfg.integration_refine)  # fmt: skip
        truth = {Path(f["path"]).name: f for f in sf}
        for row in tab[:-1]:
            f = truth[str(row["group"]).split("=", 1)[1]]
            per_image.append((k, f["file"], f["g1"], f["g2"], row["g1"], row["g1_err"],
                              row["g2"], row["g2_err"], row["n"]))  # fmt: skip
    img = Table(rows=per_image, names=("psf", "file", "g1_true", "g2_true", "g1", "g1_err",
                                       "g2", "g2_err", "n"))  # fmt: skip
    rows = []
    for k in [*sorted(by_psf), "all"]:
        sel = np.ones(len(img), bool) if k == "all" else np.asarray(img["psf"]) == k
        t = img[sel]
        res = []
        for i in (1, 2):
            res += fit_m_c(t[f"g{i}_true"], t[f"g{i}"], t[f"g{i}_err"])
        gt = np.column_stack([t["g1_true"], t["g2_true"]])
        gm = np.column_stack([t["g1"], t["g2"]])
        ge = np.column_stack([t["g1_err"], t["g2_err"]])
        rows.append((str(k), *res, quality_factor(gt, gm, ge), int(np.sum(t["n"]))))
    out = Table(rows=rows, names=("psf", "m1", "m1_err", "c1", "c1_err", "m2", "m2_err",
                                  "c2", "c2_err", "Q", "n_gal"))  # fmt: skip
    per = out[:-1]
    ms = np.concatenate([per["m1"], per["m2"]])
    out.meta["mean_m"] = float(np.nanmean(ms))
    out.meta["sigma_c"] = float(math.hypot(np.std(per["c1"]), np.std(per["c2"])))
    out.meta["prior"] = prior
    out.meta["images"] = img
    if report is not None:
        _write_report(out, img, man, Path(report))
    return out


def _write_report(res, img, man, path: Path) -> None:
    """A Markdown report with a plot of g_meas - g_true against g_true per PSF."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for i, ax in zip((1, 2), axes, strict=True):
        for k in np.unique(img["psf"]):
            t = img[img["psf"] == k]
            ax.errorbar(t[f"g{i}_true"], t[f"g{i}"] - t[f"g{i}_true"], yerr=t[f"g{i}_err"],
                        fmt="o", ms=3, label=f"PSF {k}")  # fmt: skip
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(f"g{i} true")
        ax.set_title(f"component {i}")
    axes[0].set_ylabel("g measured - g true")
    axes[1].legend(fontsize=7)
    png = path.with_suffix(".png")
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
    lines = [f"# pylensfit validation: {man['kind']} ({man['dir']})", "",
             f"<m> = {res.meta['mean_m']:+.4f}, sigma_c = {res.meta['sigma_c']:.2e}, "
             f"prior {res.meta['prior']!r}", "",
             "| PSF | m1 | c1 | m2 | c2 | Q | galaxies |",
             "|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in res:
        lines.append(
            f"| {r['psf']} | {r['m1']:+.4f} +- {r['m1_err']:.4f} | {r['c1']:+.5f} +- "
            f"{r['c1_err']:.5f} | {r['m2']:+.4f} +- {r['m2_err']:.4f} | {r['c2']:+.5f} +- "
            f"{r['c2_err']:.5f} | {r['Q']:.0f} | {r['n_gal']} |"
        )
    lines += ["", f"![g_meas - g_true]({png.name})", ""]
    path.write_text("\n".join(lines))
