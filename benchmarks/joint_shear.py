"""Shear bias and shear noise of the joint multi-exposure fit, beside one deep exposure
and the mean of single-exposure fits.

STEP2-like galaxies (the dithered simulation's population,
:mod:`pylensfit_validation.dither`: exponential, de Vaucouleurs and bulge+disc in turn,
sizes 0.24-0.7 arcsec, intrinsic shapes from the functional prior, S/N log-uniform in
``--snr`` (15-150 by default) in the deep exposure, half that in each of the K) are
rendered by GalSim, each with its 90-degree
rotated twin (``e_int -> -e_int``, its own noise), sheared by ``+g`` and ``-g`` (``g =
0.02``) on each component in turn, the same noise for ``+g`` and ``-g``:

* in K = 4 exposures, each with its own Moffat PSF (FWHM the mean's times 0.85, 0.95,
  1.05, 1.15; ellipticity up to 0.05), its WCS Jacobian (rotation up to 1 degree, the
  last a mirror image, scale 0.2" +-1 %), sub-pixel offsets and noise ``2 sigma`` (the
  four together as deep as one exposure of noise ``sigma``);
* in one exposure of noise ``sigma`` (the same depth), a round Moffat PSF of the mean
  FWHM, aligned, 0.2" pixels.

The priors come from an unsheared set of the same population (``2 --ngal`` other
galaxies): :func:`pylensfit.calibrate_exposures` for the joint fit,
:func:`pylensfit.calibrate` on the deep exposure for the deep fit and on exposure 0
for the single-exposure fits, on the co-add of its K exposures for the co-add fit.
Then:

* ``joint``: :func:`pylensfit.measure_exposure_stamps` on the four exposures;
* ``deep``: :func:`pylensfit.measure_stamps` on the deep exposure;
* ``single mean``: :func:`pylensfit.measure_stamps` on each exposure alone, the shapes
  and sensitivities turned into the sky frame (:func:`pylensfit.skyframe.to_sky`) and
  averaged per galaxy with the tables' weights;
* ``coadd``: :func:`pylensfit.measure_stamps` on the co-add of the K exposures
  (:func:`coadd`): each exposure's stamp resampled by a quintic spline onto one
  sky-aligned grid of 0.2" pixels (x to the west, y to the north: the package's sky
  frame ``(W, N)``, the deep exposure's grid), the galaxy at a random sub-pixel position
  of it, times the ratio of the pixels' areas (surface brightness kept), and summed
  with one inverse-variance weight per exposure (:func:`coadd_weights`, normalised to
  1). Its PSF is the same weighted sum of the exposures' PSF images resampled the same
  way about their centres: the co-add's exact PSF, up to the interpolation. The
  resampling correlates the noise; the fit assumes white noise of the co-add's per-pixel
  sigma, measured on co-adds of pure noise (:func:`coadd_sigma`).

The shear of a set is ``g_i = sum w e_i / sum w sens_i`` over the galaxies of positive
weight in both sets of a pair (the mean of their two weights). Printed per method:
``m_i = (g_i(+) - g_i(-)) / (2 g) - 1`` and ``c_i = (g_i(+) + g_i(-)) / 2`` with
bootstrap errors over the galaxies (twins kept together); ``sigma_g`` the shear error
per galaxy, ``sqrt(n)`` times the bootstrap error of ``g_i(+)`` (rms over the four sets:
the twins cancel the shape noise, so it is the measurement's noise); its ratio to the
deep exposure's (target <= 1.1); and the cost of the measurement per (galaxy, exposure)
(wall clock, the calibration not included; the co-add's resampling counted). Then the
paired differences of m between the joint fit and each other method: the difference on
the same galaxies, its error the standard deviation of the difference over the same
bootstrap resamplings, and the difference in units of that error. All fits with
``Config()`` on 48-pixel stamps (``--stamp``; ``max_stamp_size = 0``: no tiers); the joint fit is of
second order in position (``cubic_snr`` applies to the single fits only); every fit's
models are cut at the stamp's edge (``truncate_models``).

``--noise-twins``: every galaxy and its rotated twin are rendered again with their noise
negated (``-noise`` in every exposure and in the deep exposure, the same sub-pixel
offsets), which cancels the noise's first-order terms in m and c; the bootstrap keeps a
galaxy's four renderings together, and ``sigma_g`` is measured on the renderings of
independent noise (the noise twins left out).

``--psf-e E``: the PSF's leakage instead of m. The sets are unsheared (``g = 0``) and
every PSF (each exposure's, on top of its own ellipticity, the deep exposure's and so
the co-add's) is sheared by ``+E`` and ``-E`` on component 1, then on component 2, in
the sky frame (the PSF profile is in world coordinates, (W, N) arcsec, and
``drawImage(wcs=...)`` maps it onto each exposure's pixels); the same galaxies and
noise in the four sets, the priors those of the PSFs without ``E``. Printed in m's
place: ``alpha_i = (c_i(+E) - c_i(-E)) / (2 E)`` per method and the paired differences
of alpha; c is then the mean of the ``+E`` and ``-E`` sets' shears.

``--response metacal``: the joint fit and the deep exposure's fit are also
metacalibrated (``measure_exposure_stamps`` / ``measure_stamps(..., response="metacal")``,
the added noise fields from ``--metacal-seed``, the same for ``+g`` and ``-g``; not
negated in the noise twins), printed as ``joint mcal`` and ``deep mcal``: ``g_i = <e_i> /
<R_ii>`` over the galaxies whose five fits are usable in both sets of a pair
(unweighted), and their paired differences; the joint and deep rows' cost then includes
their metacalibration.

Usage::

    python benchmarks/joint_shear.py --ngal 300 --seed 1 --jobs 2   # ~6 min on 2 cores
    python benchmarks/joint_shear.py --ngal 400 --snr 10 15 --jobs 2  # the faint regime
    python benchmarks/joint_shear.py --ngal 150 --seed 1 --jobs 2 --noise-twins
    python benchmarks/joint_shear.py --ngal 150 --seed 2 --jobs 2 --psf-e 0.1 --noise-twins
    python benchmarks/joint_shear.py --ngal 300 --seed 6 --jobs 2 --noise-twins \
        --response metacal
"""

from __future__ import annotations

import argparse
import time

import galsim
import numba
import numpy as np
from astropy.wcs import WCS
from scipy.ndimage import map_coordinates

import pylensfit as plf
from pylensfit.exposures import ExposureStamps
from pylensfit.prior import Prior
from pylensfit.skyframe import SkyFrame, local_frame, sensitivity_to_sky, to_sky
from pylensfit_validation.dither import DitherSpec
from pylensfit_validation.simulate import MIXED_KINDS, draw_shapes, galaxy_profile

N = 48  # stamp side, pixels
M = 31  # PSF image side
SCALE = 0.2  # arcsec per pixel
G = 0.02
K = 4
FWHM = 0.7  # arcsec, the mean PSF's
BETA = 3.5
SIGMA = 1.0  # the deep exposure's noise; each of the K has 2 SIGMA
ORDER = 5  # spline order of the co-add's resampling
#: ``--response metacal``: the added noise fields' seed (None: no metacalibration)
METACAL: dict = {"seed": None}


def exposures(rng: np.random.Generator) -> list[dict]:
    """The K exposures: Jacobian, PSF profile and image, noise, frame."""
    out = []
    for k, f in enumerate((0.85, 0.95, 1.05, 1.15)):
        a = np.radians(rng.uniform(-1.0, 1.0))
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        F = np.diag([-1.0, 1.0]) if k == K - 1 else np.eye(2)
        J = F @ R / (SCALE * (1 + rng.uniform(-0.01, 0.01)))
        e, t = rng.uniform(0.0, 0.05), rng.uniform(0, np.pi)
        out.append(exposure(J, galsim.Moffat(beta=BETA, fwhm=FWHM * f).shear(
            g1=e * np.cos(2 * t), g2=e * np.sin(2 * t)), 2 * SIGMA))  # fmt: skip
    return out


def exposure(J: np.ndarray, psf, sigma: float) -> dict:
    """An exposure of Jacobian ``J`` (pixels per arcsec): its GalSim WCS, PSF image and
    sky frame (an astropy WCS of the same Jacobian)."""
    wcs = galsim.JacobianWCS(*np.linalg.inv(J).ravel())
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval, w.wcs.crpix = [150.0, 2.0], [N / 2 + 1, N / 2 + 1]
    w.wcs.cd = np.diag([-1.0, 1.0]) @ np.linalg.inv(J) / 3600.0  # (W, N) = (-dRA cos, dDec)
    return {"J": J, "wcs": wcs, "psf": psf, "sigma": sigma,
            "psf_img": psf.drawImage(nx=M, ny=M, wcs=wcs).array,
            "frame": local_frame(w, [N / 2], [N / 2])}  # fmt: skip


def population(n: int, rng: np.random.Generator, deep: dict, snr_range=None) -> dict:
    """``n`` galaxies: kind, size (arcsec), intrinsic shape, flux for an S/N log-uniform in
    ``snr_range`` in the deep exposure (default the dithered simulation's)."""
    spec = DitherSpec() if snr_range is None else DitherSpec(snr_range=tuple(snr_range))
    kinds = [MIXED_KINDS[i % len(MIXED_KINDS)] for i in range(n)]
    r = rng.uniform(*spec.size_range, n)
    e = draw_shapes(Prior(B=spec.prior_params[0], C=spec.prior_params[1],
                          D=spec.prior_params[2]), n, rng, spec.max_e)  # fmt: skip
    snr = np.exp(rng.uniform(*np.log(spec.snr_range), n))
    flux = np.empty(n)
    for i in range(n):  # GalSim renders one object at a time
        img = galsim.Convolve(galaxy_profile(kinds[i], r[i]).shear(g1=e[i, 0], g2=e[i, 1]),
                              deep["psf"]).drawImage(nx=N, ny=N, wcs=deep["wcs"]).array  # fmt: skip
        flux[i] = snr[i] * SIGMA / np.sqrt((img**2).sum())
    return {"kind": kinds, "r": r, "e": e, "flux": flux}


def render(pop: dict, ex: dict, g, sign: float, offsets, noise) -> np.ndarray:
    """``(n, N, N)`` stamps of the population (intrinsic shapes times ``sign``) sheared
    by ``g``, at the sub-pixel ``offsets`` (pixels), plus ``noise``."""
    out = np.empty((len(pop["r"]), N, N))
    for i in range(len(pop["r"])):
        gal = galaxy_profile(pop["kind"][i], pop["r"][i]).withFlux(pop["flux"][i])
        gal = gal.shear(g1=sign * pop["e"][i, 0], g2=sign * pop["e"][i, 1]).shear(g1=g[0], g2=g[1])
        out[i] = galsim.Convolve(gal, ex["psf"]).drawImage(
            nx=N, ny=N, wcs=ex["wcs"], offset=0.5 + offsets[i]).array  # fmt: skip
    return out + noise


def views(stamps: list, exps: list, offsets: list) -> list[ExposureStamps]:
    """In-memory :class:`ExposureStamps` of each exposure's stamps (no image: the
    galaxies' positions are their stamps' centres plus the offsets)."""
    n = stamps[0].shape[0]
    out = []
    for k, (s, ex, off) in enumerate(zip(stamps, exps, offsets, strict=True)):
        x, y = N // 2 + off[:, 0], N // 2 + off[:, 1]
        fr = ex["frame"]
        out.append(ExposureStamps(
            stamps=s, weights=np.full(s.shape, ex["sigma"] ** -2.0),
            noise_sigma=np.full(n, ex["sigma"]),
            psf=np.broadcast_to(ex["psf_img"], (n, M, M)), x=x, y=y,
            x0=np.zeros(n, np.int64), y0=np.zeros(n, np.int64),
            jacobian=np.broadcast_to(ex["J"], (n, 2, 2)),
            frame=repeat_frame(fr, n),
            flux_scale=1.0, flags=np.zeros(n, np.int64), exposure=k))  # fmt: skip
    return out


def resample(img: np.ndarray, J: np.ndarray, centre_in, centre_out, size: int) -> np.ndarray:
    """An exposure's image ``img`` resampled onto ``size x size`` pixels of the sky grid
    (``SCALE`` arcsec, x to the west, y to the north) by a spline of order ``ORDER``:
    the grid's point ``centre_out`` (x, y) falls on ``img``'s point ``centre_in``,
    ``J`` the exposure's Jacobian (pixels per arcsec), the values times the ratio of the
    pixels' areas (the surface brightness kept)."""
    y, x = np.mgrid[:size, :size].astype(float)
    sky = SCALE * np.stack([x - centre_out[0], y - centre_out[1]])  # (W, N) arcsec
    p = np.tensordot(J, sky, axes=1) + np.asarray(centre_in, float)[:, None, None]
    area = SCALE**2 * abs(np.linalg.det(J))
    return area * map_coordinates(img, [p[1], p[0]], order=ORDER, mode="mirror")


def coadd_weights(exps: list) -> np.ndarray:
    """One inverse-variance weight per exposure (its noise in the sky grid's units),
    normalised to a sum of 1."""
    v = np.array([(SCALE**2 * abs(np.linalg.det(ex["J"])) * ex["sigma"]) ** 2 for ex in exps])
    return (1 / v) / (1 / v).sum()


def coadd(stamps: list, exps: list, offsets: list, off_c: np.ndarray) -> np.ndarray:
    """``(n, N, N)`` co-add of the exposures' stamps: each galaxy, at ``N // 2 +
    offsets[k]`` in exposure k, resampled to ``N // 2 + off_c`` on the sky grid and
    summed with :func:`coadd_weights`."""
    w = coadd_weights(exps)
    out = np.zeros_like(stamps[0])
    for s, ex, off, wk in zip(stamps, exps, offsets, w, strict=True):
        for i in range(len(s)):
            out[i] += wk * resample(s[i], ex["J"], N // 2 + off[i], N // 2 + off_c[i], N)
    return out


def coadd_psf(exps: list) -> np.ndarray:
    """The co-add's PSF: the exposures' PSF images resampled about their centres and
    summed with the co-add's weights."""
    w = coadd_weights(exps)
    return sum(wk * resample(ex["psf_img"], ex["J"], (M // 2, M // 2), (M // 2, M // 2), M)
               for ex, wk in zip(exps, w, strict=True))  # fmt: skip


def coadd_sigma(exps: list, rng: np.random.Generator, n: int = 200) -> tuple[float, float]:
    """The co-add's per-pixel noise sigma, measured on ``n`` co-adds of pure noise (their
    pixels 4 or more from the edge), and the white-noise sum ``sqrt(sum (w_k a_k
    sigma_k)^2)`` it would be without the resampling's smoothing."""
    noise = [rng.normal(0, ex["sigma"], (n, N, N)) for ex in exps]
    offs = [rng.uniform(-0.5, 0.5, (n, 2)) for _ in range(len(exps) + 1)]
    c = coadd(noise, exps, offs[:-1], offs[-1])
    a = np.array([SCALE**2 * abs(np.linalg.det(ex["J"])) * ex["sigma"] for ex in exps])
    return float(c[:, 4:-4, 4:-4].std()), float(np.sqrt(((coadd_weights(exps) * a) ** 2).sum()))


def repeat_frame(frame: SkyFrame, n: int) -> SkyFrame:
    """One object's frame for ``n`` objects."""
    return SkyFrame(*(np.repeat(getattr(frame, a), n) for a in ("angle", "flip", "g1", "g2",
                                                                "has_wcs")))  # fmt: skip


def sky_shapes(t, frame) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A pixel-frame table's ``e1, e2, sens1, sens2`` in the sky frame."""
    fr = repeat_frame(frame, len(t))
    e1, e2 = to_sky(np.asarray(t["e1"]), np.asarray(t["e2"]), fr)
    s1, s2 = sensitivity_to_sky(np.asarray(t["sens1"]), np.asarray(t["sens2"]), fr)
    return e1, e2, s1, s2


def single_mean(tabs: list, exps: list) -> dict:
    """The per-exposure tables' sky-frame shapes averaged per galaxy with their weights."""
    w = np.stack([np.nan_to_num(np.asarray(t["weight"], float)) for t in tabs])
    sh = [sky_shapes(t, ex["frame"]) for t, ex in zip(tabs, exps, strict=True)]
    tot = w.sum(axis=0)
    out = {"weight": tot / len(tabs)}
    for j, c in enumerate(("e1", "e2", "sens1", "sens2")):
        v = np.stack([np.nan_to_num(s[j]) for s in sh])
        with np.errstate(invalid="ignore", divide="ignore"):
            out[c] = np.where(tot > 0, (w * v).sum(axis=0) / tot, np.nan)
    return out


def as_dict(t) -> dict:
    return {c: np.asarray(t[c], dtype=float) for c in ("e1", "e2", "sens1", "sens2", "weight")}


def metacal_dict(t) -> dict:
    """A table's metacalibration shapes and responses as ``as_dict``'s, weight 1 where
    all are finite."""
    out = {"e1": np.asarray(t["e1_mcal"], float), "e2": np.asarray(t["e2_mcal"], float),
           "sens1": np.asarray(t["R11"], float), "sens2": np.asarray(t["R22"], float)}
    out["weight"] = np.all([np.isfinite(v) for v in out.values()], axis=0).astype(float)
    return out


def bootstrap(n_base: int, rng: np.random.Generator, copies: int, n_boot: int = 300) -> np.ndarray:
    """``(n_boot, copies n_base)`` bootstrap counts over the base galaxies, each galaxy's
    ``copies`` renderings (twins, noise twins) kept together: one set of resamplings for
    every method (paired errors)."""
    boot = rng.multinomial(n_base, np.full(n_base, 1.0 / n_base), size=n_boot).astype(float)
    return np.tile(boot, copies)


def shear_stats(sets: dict, boot: np.ndarray, n_indep: int, step: float = G,
                name: str = "m") -> dict:  # fmt: skip
    """The slope (m or alpha), c and sigma_g of the four sets ``{(i, sign): shapes}``
    with their bootstrap errors over the resamplings ``boot``.

    Parameters
    ----------
    sets : dict
        The shapes of each set, ``(i, sign)`` for ``+-step`` on component ``i``.
    boot : numpy.ndarray
        The bootstrap counts, one column per rendering.
    n_indep : int
        The renderings of independent noise (the first ones: the noise twins excluded),
        on which ``sigma_g`` is measured.
    step : float
        The shear (or PSF ellipticity) of the sets.
    name : str
        ``"m"``: ``m_i = (g_i(+) - g_i(-)) / (2 step) - 1``; ``"alpha"``: the same
        without the ``- 1`` (the PSF's leakage).

    Returns
    -------
    dict
        ``name1, name2, c1, c2``: (value, error); ``name1_boot, name2_boot`` the
        resampled slopes (for the paired differences between methods); ``n`` the
        renderings used; ``sigma_g``.
    """
    res, sig = {}, []
    one = 1.0 if name == "m" else 0.0
    indep = boot * (np.arange(boot.shape[1]) < n_indep)
    for i in (0, 1):
        p, m = sets[(i, 1)], sets[(i, -1)]
        w = np.where((p["weight"] > 0) & (m["weight"] > 0), 0.5 * (p["weight"] + m["weight"]), 0.0)
        c, s, k = f"e{i + 1}", f"sens{i + 1}", f"{name}{i + 1}"
        gp = [np.nan_to_num(w * p[c]), np.nan_to_num(w * p[s])]
        gm = [np.nan_to_num(w * m[c]), np.nan_to_num(w * m[s])]
        est_p = (boot @ gp[0]) / (boot @ gp[1])
        est_m = (boot @ gm[0]) / (boot @ gm[1])
        gp0, gm0 = gp[0].sum() / gp[1].sum(), gm[0].sum() / gm[1].sum()
        res[f"{k}_boot"] = (est_p - est_m) / (2 * step) - one
        res[k] = ((gp0 - gm0) / (2 * step) - one, np.std(res[f"{k}_boot"]))
        res[f"c{i + 1}"] = (0.5 * (gp0 + gm0), np.std(0.5 * (est_p + est_m)))
        n_used = int((w[:n_indep] > 0).sum())
        for g in gp, gm:
            sig.append(np.std((indep @ g[0]) / (indep @ g[1])) * np.sqrt(n_used))
        res["n"] = int((w > 0).sum())
    res["sigma_g"] = float(np.sqrt(np.mean(np.square(sig))))
    return res


def main() -> None:
    global N
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--ngal", type=int, default=200, help="galaxies per set (each with a twin)")
    p.add_argument("--snr", type=float, nargs=2, metavar=("LO", "HI"),
                   default=DitherSpec().snr_range,
                   help="S/N range of the deep exposure (the K together)")  # fmt: skip
    p.add_argument("--noise-twins", action="store_true",
                   help="render every galaxy and twin again with its noise negated")  # fmt: skip
    p.add_argument("--psf-e", type=float, default=0.0, metavar="E",
                   help="measure the PSF leakage alpha: unsheared sets with a sky-frame PSF "
                        "ellipticity +-E shared by every exposure")  # fmt: skip
    p.add_argument("--stamp", type=int, default=N, help="stamp side, pixels")
    p.add_argument("--response", choices=("model", "metacal"), default="model",
                   help="also metacalibrate the joint and the deep fits")
    p.add_argument("--metacal-seed", type=int, default=0)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--jobs", type=int, default=2, help="threads of the fits' kernels")
    args = p.parse_args()
    N = args.stamp
    if args.response == "metacal":
        METACAL["seed"] = args.metacal_seed
    numba.set_num_threads(args.jobs)
    rng = np.random.default_rng(args.seed)
    cfg = plf.Config().replace(stamp_size=N, max_stamp_size=0)
    exps = exposures(rng)
    deep = exposure(np.eye(2) / SCALE, galsim.Moffat(beta=BETA, fwhm=FWHM), SIGMA)
    t0 = time.time()
    base = population(args.ngal, rng, deep, args.snr)
    cal = population(2 * args.ngal, rng, deep, args.snr)
    n = args.ngal
    # the calibration set: unsheared, no twins, the PSFs without --psf-e
    off_c = [rng.uniform(-0.5, 0.5, (2 * n, 2)) for _ in range(K + 1)]
    cal_st = [render(cal, ex, (0, 0), 1.0, o, rng.normal(0, ex["sigma"], (2 * n, N, N)))
              for ex, o in zip(exps + [deep], off_c, strict=True)]  # fmt: skip
    print(f"rendered the calibration set in {time.time() - t0:.0f} s")
    co = {"psf": coadd_psf(exps)}
    co["sigma"], white = coadd_sigma(exps, np.random.default_rng([args.seed, 1]))
    print(f"co-add: weights {np.round(coadd_weights(exps), 4)}, noise sigma {co['sigma']:.4f} "
          f"per pixel ({white:.4f} without the resampling's smoothing)")  # fmt: skip
    t0 = time.time()
    pri_j = plf.calibrate_exposures(views(cal_st[:K], exps, off_c[:K]), config=cfg)
    pri_d = plf.calibrate(cal_st[K], deep["psf_img"], SIGMA, config=cfg,
                          centres=tuple((N // 2 + off_c[K]).T))  # fmt: skip
    pri_s = plf.calibrate(cal_st[0], exps[0]["psf_img"], 2 * SIGMA, config=cfg,
                          centres=tuple((N // 2 + off_c[0]).T))  # fmt: skip
    pri_c = plf.calibrate(coadd(cal_st[:K], exps, off_c[:K], off_c[K]), co["psf"], co["sigma"],
                          config=cfg, centres=tuple((N // 2 + off_c[K]).T))  # fmt: skip
    print(f"calibrated in {time.time() - t0:.0f} s")
    print(f"S/N {args.snr[0]:g}-{args.snr[1]:g} in the deep exposure")
    run(base, n, (exps, deep, co), cfg, (pri_j, pri_d, pri_s, pri_c), rng,
        args.noise_twins, args.psf_e)  # fmt: skip


def with_psf_shear(ex: dict, e: tuple) -> dict:
    """The exposure ``ex`` with its PSF sheared by ``e`` (g1, g2) in the sky frame (the
    PSF profile is in world coordinates, (W, N) arcsec)."""
    return exposure(ex["J"], ex["psf"].shear(g1=e[0], g2=e[1]), ex["sigma"])


def setting(i: int, sign: int, frames: tuple, psf_e: float) -> tuple:
    """The shear and the exposures of the set ``(i, sign)``: ``g = sign G`` on component
    ``i`` or, with ``psf_e``, ``g = 0`` and a sky-frame PSF ellipticity ``sign psf_e``
    on component ``i`` added to every exposure's PSF, the deep exposure's and the
    co-add's."""
    step = sign * (psf_e if psf_e else G)
    v = (step, 0.0) if i == 0 else (0.0, step)
    if not psf_e:
        return v, frames
    exps, deep, co = frames
    exps = [with_psf_shear(ex, v) for ex in exps]
    co = {"psf": coadd_psf(exps), "sigma": co["sigma"]}
    return (0.0, 0.0), (exps, with_psf_shear(deep, v), co)


def measure(st: list, frames: tuple, off: list, cfg, priors: tuple, cost: dict) -> dict:
    """One set's stamps ``st`` (the K exposures', the deep exposure's) measured four ways;
    the time of each added to ``cost``."""
    exps, deep, co = frames
    pri_j, pri_d, pri_s, pri_c = priors
    out = {}
    mc = ({} if METACAL["seed"] is None else
          {"response": "metacal", "seed": METACAL["seed"]})  # fmt: skip
    t = time.time()
    tab = plf.measure_exposure_stamps(views(st[:K], exps, off[:K]), priors=pri_j, config=cfg,
                                      **mc)  # fmt: skip
    out["joint"] = as_dict(tab)
    if mc:
        out["joint mcal"] = metacal_dict(tab)
    cost["joint"] += time.time() - t
    t = time.time()
    tab = plf.measure_stamps(st[K], deep["psf_img"], SIGMA, priors=pri_d, config=cfg,
                             centres=tuple((N // 2 + off[K]).T), **mc)  # fmt: skip
    out["deep"] = as_dict(tab)
    if mc:
        out["deep mcal"] = metacal_dict(tab)
    cost["deep"] += time.time() - t
    t = time.time()
    tabs = [plf.measure_stamps(st[k], exps[k]["psf_img"], 2 * SIGMA, priors=pri_s,
                               config=cfg, centres=tuple((N // 2 + off[k]).T))
            for k in range(K)]  # fmt: skip
    cost["single mean"] += time.time() - t
    out["single mean"] = single_mean(tabs, exps)
    t = time.time()
    out["coadd"] = as_dict(plf.measure_stamps(
        coadd(st[:K], exps, off[:K], off[K]), co["psf"], co["sigma"], priors=pri_c,
        config=cfg, centres=tuple((N // 2 + off[K]).T)))  # fmt: skip
    cost["coadd"] += time.time() - t
    return out


def run(base, n, frames, cfg, priors, rng, noise_twins=False, psf_e=0.0) -> None:
    """Render the four sets (``+-g`` or, with ``psf_e``, the PSF's ``+-psf_e`` on each
    component), measure them four ways and print the tables."""
    copies = 4 if noise_twins else 2
    gals = {k: np.tile(base[k], copies) for k in ("r", "flux")}
    gals["kind"] = list(base["kind"]) * copies
    gals["e"] = np.tile(np.concatenate([base["e"], -base["e"]]), (copies // 2, 1))
    exps, deep = frames[:2]
    off = [np.tile(rng.uniform(-0.5, 0.5, (2 * n, 2)), (copies // 2, 1)) for _ in range(K + 1)]
    noise = [rng.normal(0, ex["sigma"], (2 * n, N, N)) for ex in exps + [deep]]
    if noise_twins:
        noise = [np.concatenate([nz, -nz]) for nz in noise]
    methods = ("joint", "deep", "single mean", "coadd")
    if METACAL["seed"] is not None:
        methods += ("joint mcal", "deep mcal")
    out = {m: {} for m in methods}
    cost = dict.fromkeys(out, 0.0)
    for i in (0, 1):
        for sign in (1, -1):
            g, fr = setting(i, sign, frames, psf_e)
            st = [render(gals, ex, g, 1.0, o, nz)
                  for ex, o, nz in zip(fr[0] + [fr[1]], off, noise, strict=True)]  # fmt: skip
            for m, shapes in measure(st, fr, off, cfg, priors, cost).items():
                out[m][(i, sign)] = shapes
    per = {"joint": K, "deep": 1, "single mean": K, "coadd": K, "joint mcal": K,
           "deep mcal": 1}  # the metacalibration's cost is in its fit's
    boot = bootstrap(n, np.random.default_rng(0), copies)
    name = "alpha" if psf_e else "m"
    stats = {m: shear_stats(out[m], boot, 2 * n, psf_e or G, name) for m in out}
    twins = "rotated twins and the noise twins of both" if noise_twins else "rotated twins"
    what = f"g = 0, PSF e = +-{psf_e} (sky frame)" if psf_e else f"g = {G}"
    head = f"{copies * n} renderings per set ({n} galaxies and their {twins}), {what}, K = {K}"
    report(stats, {m: 1e3 * cost[m] / (4 * copies * n * per[m]) for m in out}, head, name)


def report(stats: dict, ms: dict, head: str, name: str = "m") -> None:
    """Print each method's slope ``name`` (m or alpha), c, sigma_g and cost, then the
    joint fit's paired differences of the slope from the others."""
    sd = stats["deep"]["sigma_g"]
    k1, k2 = f"{name}1", f"{name}2"
    print(f"\n{head}\n")
    print(f"{'method':<12} {k1:>16} {k2:>16} {'c1':>18} {'c2':>18} {'n':>5} "
          f"{'sigma_g':>8} {'/deep':>6} {'ms/(gal,exp)':>13}")  # fmt: skip
    for m, s in stats.items():
        f = "  ".join(f"{s[k][0]:+.4f}+-{s[k][1]:.4f}" for k in (k1, k2, "c1", "c2"))
        print(f"{m:<12} {f}  {s['n']:>5} {s['sigma_g']:8.3f} {s['sigma_g'] / sd:6.3f} "
              f"{ms[m]:13.1f}")  # fmt: skip
    print(f"\npaired differences of {name} (the same galaxies and bootstrap resamplings)\n")
    w = len(name) + 7
    print(f"{'pair':<24} {'d' + k1:>16} {'d' + k1 + '/err':>{w}} {'d' + k2:>16} "
          f"{'d' + k2 + '/err':>{w}}")  # fmt: skip
    pairs = [("joint", o) for o in ("single mean", "coadd", "deep")]
    if "joint mcal" in stats:
        pairs += [("joint mcal", "deep mcal"), ("joint mcal", "joint")]
    for one, other in pairs:
        row = ""
        for k in (k1, k2):
            d = stats[one][k][0] - stats[other][k][0]
            e = float(np.std(stats[one][f"{k}_boot"] - stats[other][f"{k}_boot"]))
            row += f" {d:+.4f}+-{e:.4f} {d / e:+{w}.2f}"
        print(f"{one + ' - ' + other:<24}{row}")


if __name__ == "__main__":
    main()
