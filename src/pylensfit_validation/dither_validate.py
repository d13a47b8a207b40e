"""The joint fit of dithered exposures validated: shear bias from sets that differ only
by their shear, the same galaxies on one exposure beside it, each exposure's PSF
against its truth.

Sets written by :func:`pylensfit_validation.dither.simulate_dither` with the same seed
and spec but for the shear (``pylensfit simulate dither --seed S --shear G1 G2``) hold
the same galaxies, exposures and noise: their shear estimates differ by the response to
the shear, most of the shape noise and the noise cancels in ``m`` and ``c``.

Every set is measured with :func:`pylensfit.measure_exposures` under one set of priors,
estimated from the first set's own joint fits, and with :func:`pylensfit.measure` on one
of its exposures alone (its star field's PSF; priors from that exposure of the first
set). The shear of each set is :func:`pylensfit.estimate_shear` of every usable row,
nothing matched to the truth; with ``Config.response = "metacal"`` also the
metacalibration's (:class:`pylensfit.shear.MetacalSample`, the selection response of
the cuts included). ``m`` and ``c`` per component are the least-squares line
of the measured against the true shears; their errors are the jackknife over
``JACKKNIFE_SIDE^2`` cells of the sky, each cell left out of every set at once, so that
the shape noise and noise the sets share cancel in them as in ``m`` and ``c``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from astropy.table import Table

from pylensfit import Config, calibrate_images, estimate_shear, measure, measure_exposures
from pylensfit.calibration import calibrate_exposures
from pylensfit.exposures import cut_exposures
from pylensfit.images import read_exposures
from pylensfit.shear import MetacalSample

from .dither import DitherSet, read_dither
from .galaxies import PSFProfile

log = logging.getLogger(__name__)

__all__ = ["DitherValidation", "psf_residuals", "validate_dither"]


@dataclass
class DitherValidation:
    """The result of :func:`validate_dither`.

    Attributes
    ----------
    shears : astropy.table.Table
        One row per set and method: ``set``, ``method`` (``joint K``, ``exposure k``;
        each also as ``joint K mcal``, ``exposure k mcal``, the metacalibration's
        estimate with its selection response, where ``Config.response`` is "metacal"),
        the true ``g1_true, g2_true``, the estimates ``g1, g2`` with ``g1_err, g2_err``,
        ``n`` usable rows.
    bias : astropy.table.Table
        One row per method: ``m1, c1, m2, c2`` and their jackknife errors (NaN where
        the sets do not span two values of the component).
    psf : astropy.table.Table
        One row per exposure of the first set: the PSF used against the true one
        (:func:`psf_residuals`).
    """

    shears: Table
    bias: Table
    psf: Table


def psf_residuals(s: DitherSet, config: Config | None = None) -> Table:
    """Each exposure's PSF as the pipeline finds it (from its star field) against the
    true one: adaptive-moment ellipticity (pixel frame) and size differences.

    Returns
    -------
    astropy.table.Table
        ``exposure, e1_true, e2_true, de1, de2, dsigma`` (``dsigma``: relative size
        difference ``sigma / sigma_true - 1``).
    """
    # GalSim: the independent renderer of the true PSF and its moments
    import galsim

    cfg = config if config is not None else Config()
    eset = read_exposures([str(s.path(k)) for k in range(len(s.exposures))],
                          stars=[str(s.star_path(k)) for k in range(len(s.exposures))],
                          config=cfg)  # fmt: skip
    rows = []
    for k, (e, ex) in enumerate(zip(s.exposures, eset.exposures, strict=True)):
        img = ex.psf if isinstance(ex.psf, np.ndarray) else ex.psf.draw(
            np.array([ex.shape[1] / 2.0]), np.array([ex.shape[0] / 2.0]))[0]  # fmt: skip
        n = img.shape[0]
        true = PSFProfile("moffat", e.psf_fwhm, s.spec.psf_beta, e.psf_e1, e.psf_e2).galsim()
        ti = true.drawImage(nx=n, ny=n, scale=1.0)
        m = galsim.hsm.FindAdaptiveMom(galsim.ImageD(np.asarray(img, float)))
        mt = galsim.hsm.FindAdaptiveMom(ti)
        g, gt = m.observed_shape, mt.observed_shape
        rows.append((k, gt.g1, gt.g2, g.g1 - gt.g1, g.g2 - gt.g2,
                     m.moments_sigma / mt.moments_sigma - 1.0))  # fmt: skip
    return Table(rows=rows, names=("exposure", "e1_true", "e2_true", "de1", "de2", "dsigma"))


def _joint_priors(s: DitherSet, cfg: Config):
    """The priors of the first set's joint fits, at its truth positions."""
    eset = read_exposures([str(s.path(k)) for k in range(len(s.exposures))],
                          stars=[str(s.star_path(k)) for k in range(len(s.exposures))],
                          config=cfg)  # fmt: skip
    views = cut_exposures(eset.exposures, s.truth["ra"], s.truth["dec"], size=cfg.stamp_size)
    return calibrate_exposures(views, config=cfg)


#: the suffix of a method's name whose shear is the metacalibration's (``Config.response
#: = "metacal"``: ``<R_gamma + R_S>^-1 <e_mcal>``, the selection response included)
MCAL = " mcal"


def _estimator(method: str, cat: Table):
    """``rows -> ShearEstimate`` of one method's catalogue (``rows`` a mask)."""
    if method.endswith(MCAL):
        return MetacalSample.of(cat).estimate
    return lambda rows: estimate_shear(cat[rows])


def _shear_row(name: str, method: str, s: DitherSet, cat: Table) -> tuple:
    est = _estimator(method, cat)(np.ones(len(cat), bool))
    return (name, method, s.spec.g1, s.spec.g2, est.g1, est.g1_err, est.g2, est.g2_err, est.n)


#: sky cells per side of the jackknife of m and c
JACKKNIFE_SIDE = 4


def _line(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """``m, c`` of the least-squares line ``y - x = m x + c`` (NaN without two ``x``)."""
    if np.unique(np.round(x, 12)).size < 2:
        return np.nan, np.nan
    m, c = np.polyfit(x, y - x, 1)
    return float(m), float(c)


def _cells(cats: list[Table], side: int) -> list[np.ndarray]:
    """Each row's jackknife cell: ``side x side`` cells of RA and Dec over all rows."""
    ra = np.concatenate([np.asarray(c["ALPHA_J2000"], float) for c in cats])
    dec = np.concatenate([np.asarray(c["DELTA_J2000"], float) for c in cats])
    ok = np.isfinite(ra) & np.isfinite(dec)
    er = np.quantile(ra[ok], np.linspace(0, 1, side + 1)[1:-1])
    ed = np.quantile(dec[ok], np.linspace(0, 1, side + 1)[1:-1])
    return [np.searchsorted(er, np.asarray(c["ALPHA_J2000"], float)) * side
            + np.searchsorted(ed, np.asarray(c["DELTA_J2000"], float)) for c in cats]  # fmt: skip


def _bias(method: str, sets: list[DitherSet], cats: list[Table]) -> tuple:
    """``m1, m1_err, c1, c1_err, m2, ...`` of one method's catalogues of the sets: the
    line through their shears, its error the jackknife over cells of the sky (each cell
    left out of every set at once, so that what the sets share cancels)."""
    cells = _cells(cats, JACKKNIFE_SIDE)
    g1t = np.array([s.spec.g1 for s in sets])
    g2t = np.array([s.spec.g2 for s in sets])
    fns = [_estimator(method, c) for c in cats]
    out, n = [], 0
    for drop in range(-1, JACKKNIFE_SIDE**2):  # -1: no cell left out, every row
        est = [fn(cl != drop) for fn, cl in zip(fns, cells, strict=True)]
        if drop == -1:
            n = sum(e.n for e in est)
        out.append(_line(g1t, np.array([e.g1 for e in est]))
                   + _line(g2t, np.array([e.g2 for e in est])))  # fmt: skip
    v = np.array(out)
    k = len(v) - 1
    err = np.sqrt((k - 1) / k * ((v[1:] - v[1:].mean(0)) ** 2).sum(0))
    m1, c1, m2, c2 = v[0]
    return method, m1, err[0], c1, err[1], m2, err[2], c2, err[3], int(n)


def _methods(name: str, cfg: Config) -> list[str]:
    """A catalogue's shear estimators: the model's, and the metacalibration's where
    ``cfg.response`` is ``"metacal"``."""
    return [name] + ([name + MCAL] if cfg.response == "metacal" else [])


def validate_dither(directories: Sequence[str | Path], *, config: Config | None = None,
                    exposure: int | None = 0, out: str | Path | None = None,
                    ) -> DitherValidation:  # fmt: skip
    """Shear bias of the joint fit on dithered sets that differ by their shear, the same
    galaxies on one exposure beside it, and each exposure's PSF against its truth.

    Parameters
    ----------
    directories : sequence of str or pathlib.Path
        Sets of one seed and spec, differing only by the shear (module docstring).
    config : Config, optional
        Settings (default ``Config()``).
    exposure : int or None
        The exposure measured alone beside the joint fit (None: none).
    out : str or pathlib.Path, optional
        Directory for the catalogues (``<set>_joint.fits``, ``<set>_exp<k>.fits``).

    Returns
    -------
    DitherValidation
        The shears per set and method, ``m`` and ``c`` per method, the PSF residuals.
    """
    cfg = config if config is not None else Config()
    sets = [read_dither(d) for d in directories]
    priors = _joint_priors(sets[0], cfg)
    single = None
    if exposure is not None:
        single = calibrate_images([str(sets[0].path(exposure))],
                                  stars=[str(sets[0].star_path(exposure))], config=cfg,
                                  progress=False)  # fmt: skip
    rows = []
    cats: dict[str, list[Table]] = {}
    for s in sets:
        name = s.directory.name
        paths = [str(s.path(k)) for k in range(len(s.exposures))]
        stars = [str(s.star_path(k)) for k in range(len(s.exposures))]
        o = None if out is None else Path(out) / f"{name}_joint.fits"
        cat = measure_exposures(paths, stars=stars, priors=priors, config=cfg, output=o,
                                overwrite=True)  # fmt: skip
        for method in _methods(f"joint {len(paths)}", cfg):
            rows.append(_shear_row(name, method, s, cat))
            cats.setdefault(method, []).append(cat)
        if single is not None:
            o = None if out is None else Path(out) / f"{name}_exp{exposure}.fits"
            one = measure([paths[exposure]], stars=[stars[exposure]], priors=single,
                          config=cfg, output=o, overwrite=True, progress=False)  # fmt: skip
            for method in _methods(f"exposure {exposure}", cfg):
                rows.append(_shear_row(name, method, s, one))
                cats.setdefault(method, []).append(one)
    shears = Table(rows=rows, names=("set", "method", "g1_true", "g2_true", "g1", "g1_err",
                                     "g2", "g2_err", "n"))  # fmt: skip
    bias = Table(rows=[_bias(k, sets, v) for k, v in cats.items()],
                 names=("method", "m1", "m1_err", "c1", "c1_err", "m2", "m2_err", "c2",
                        "c2_err", "n"))  # fmt: skip
    return DitherValidation(shears=shears, bias=bias, psf=psf_residuals(sets[0], cfg))
