"""The one assemble step of both paths: fits and priors in, the catalogue's columns out.

:func:`pylensfit.measure_stamps` (postage stamps) and :func:`pylensfit.measure` (FITS
images) fit their objects in different ways (stamps given, or cut from images after
detection, PSF estimation and neighbour subtraction) but turn the fits into a table in
one way, :func:`assemble`: the bulge fractions mixed under their prior
(:func:`mix_lnL`), the posterior means, covariances and shear sensitivities
(:func:`pylensfit.shapes`), the flags completed (``FIT_FAILED`` where no shape,
``LOW_SNR``: :func:`flag_low_snr`), the inverse-variance weights
(:func:`pylensfit.weights.inverse_variance_weights`) of the usable galaxies
(:func:`usable_galaxies`). The columns carry the catalogue's names
(:data:`pylensfit.catalogue.COLUMNS`), in both paths: :func:`fit_columns` names a fit's
own (``model_SNratio``, ``model_flux``, ``scalelength``, ``stamp_size``, ...).

One difference is kept, by the caller's choice (``flagged``): the stamps table keeps the
shapes of flagged rows that were fitted (``flagged="keep"``: a stamp's user sees what its
fit gave), the catalogue keeps only those of the rows without a flag before the shapes
(``flagged="blank"``: NaN elsewhere, and the ``lnL`` of those rows NaN too where the
bulge fractions are mixed). Rows without a flag get the same numbers either way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import Config
from .flags import FLAGS
from .prior import mix_bulge_fractions
from .shear import shapes
from .skyframe import SkyFrame, covariance_to_sky, sensitivity_to_sky, to_sky
from .weights import inverse_variance_weights

__all__ = [
    "FIT_COLUMNS",
    "Assembled",
    "ObjectContext",
    "assemble",
    "fit_columns",
    "flag_low_snr",
    "mix_lnL",
    "usable_galaxies",
]

#: catalogue column -> attribute of :class:`~pylensfit.StampFits`: the columns a fit
#: gives (floats; ``stamp_size`` from ``StampFits.stamp`` is added by :func:`fit_columns`)
FIT_COLUMNS = {
    "model_flux": "flux",
    "model_SNratio": "snr",
    "scalelength": "r_best",
    "e1_best": "e1_best",
    "e2_best": "e2_best",
    "bulge_best": "bulge_best",
}

#: the shape columns of :func:`assemble`, as :func:`pylensfit.shapes` names them
SHAPE_COLUMNS = ("e1", "e2", "e1_var", "e2_var", "e12_cov", "sens1", "sens2")


def fit_columns(fits, stamp_size: int = 0) -> dict[str, np.ndarray]:
    """The catalogue's columns of a fit (:class:`~pylensfit.StampFits`): ``model_flux``,
    ``model_SNratio``, ``scalelength``, ``e1_best``, ``e2_best``, ``bulge_best`` (NaN for
    a model family of one bulge fraction) and ``stamp_size`` (``stamp_size`` where the
    fits do not say)."""
    n = len(fits)
    cols = {}
    for name, attr in FIT_COLUMNS.items():
        v = getattr(fits, attr)
        cols[name] = np.full(n, np.nan) if v is None else np.asarray(v, dtype=float)
    cols["stamp_size"] = (np.full(n, stamp_size, dtype=np.int32) if fits.stamp is None
                          else np.asarray(fits.stamp, dtype=np.int32))  # fmt: skip
    return cols


def usable_galaxies(flags, is_star, snr, min_snr: float) -> np.ndarray:
    """The rows that are galaxies to measure: no flag, not a point source, and a model
    S/N of at least ``min_snr`` (``Config.min_snr``: below it detections are mostly
    noise)."""
    snr = np.asarray(snr, dtype=float)
    return ((np.asarray(flags) == 0) & ~np.asarray(is_star, dtype=bool)
            & np.isfinite(snr) & (snr >= min_snr))  # fmt: skip


def flag_low_snr(flags, is_star, snr, min_snr: float) -> np.ndarray:
    """``flags`` with ``LOW_SNR`` set on the unflagged galaxies whose model S/N is below
    ``min_snr`` (or not finite)."""
    flags = np.asarray(flags, dtype=np.int32)
    low = (flags == 0) & ~np.asarray(is_star, dtype=bool) & ~(np.asarray(snr, float) >= min_snr)
    return flags | np.where(low, FLAGS["LOW_SNR"][0], 0).astype(np.int32)


def mix_lnL(lnL, lnL_bulge, lnL_star, bulge_weights, rows=None) -> np.ndarray:
    """``ln L(e)`` with the bulge fractions mixed under ``bulge_weights``
    (:func:`pylensfit.prior.mix_bulge_fractions`) on the rows ``rows`` (default: those
    whose ``lnL`` is finite), NaN on the others; ``lnL`` itself without marginalised
    fractions (``lnL_bulge`` None) or weights."""
    lnL = np.asarray(lnL)
    if lnL_bulge is None or bulge_weights is None:
        return lnL
    if len(bulge_weights) != lnL_bulge.shape[1]:
        raise ValueError(f"the priors hold {len(bulge_weights)} bulge weights, the "
                         f"fits {lnL_bulge.shape[1]} runs of the model family")  # fmt: skip
    if rows is None:
        rows = np.isfinite(lnL).all(axis=1)
    mixed = mix_bulge_fractions(lnL_bulge, np.asarray(lnL_star, dtype=float), bulge_weights)
    return np.where(np.asarray(rows, dtype=bool)[:, None], mixed, np.nan)


@dataclass(frozen=True)
class ObjectContext:
    """What :func:`assemble` needs of each object beside its likelihood.

    Attributes
    ----------
    flags : numpy.ndarray
        ``(n,)`` int32 flags so far (the fit's, the image's: stamp, saturation, PSF ...).
    not_galaxy : numpy.ndarray
        ``(n,)`` bool: a point source, or not measured (fitclass not 0).
    model_SNratio, model_flux, scalelength : numpy.ndarray
        ``(n,)`` the best model's S/N, flux (data units) and size (pixels).
    noise_sigma : numpy.ndarray or float
        Per-pixel noise (data units), per object or one for all.
    psf_sigma : numpy.ndarray or float
        The PSF's size (pixels, adaptive moments), per object or one for all.
    frame : SkyFrame, optional
        Each object's sky frame: the shapes are turned into it (the pixel frame's kept as
        ``e1_pix, e2_pix``) before the weights; None: the pixel frame (stamps).
    """

    flags: np.ndarray
    not_galaxy: np.ndarray
    model_SNratio: np.ndarray
    model_flux: np.ndarray
    scalelength: np.ndarray
    noise_sigma: np.ndarray | float
    psf_sigma: np.ndarray | float
    frame: SkyFrame | None = None


@dataclass(frozen=True)
class Assembled:
    """The result of :func:`assemble`.

    Attributes
    ----------
    columns : dict of numpy.ndarray
        ``e1, e2, e1_var, e2_var, e12_cov, sens1, sens2`` (the sky frame where the
        context has one, then also ``e1_pix, e2_pix``), ``weight`` and ``flags``, under
        the catalogue's names (:data:`pylensfit.catalogue.COLUMNS`).
    lnL : numpy.ndarray
        ``(n, n_e)`` the ``ln L(e)`` the shapes are of (the bulge fractions mixed).
    """

    columns: dict[str, np.ndarray]
    lnL: np.ndarray


def assemble(lnL, egrid, priors, config: Config, ctx: ObjectContext, *,
             lnL_bulge=None, lnL_star=None, flagged: str = "keep") -> Assembled:  # fmt: skip
    """The shapes, flags and weights of fitted objects under the priors.

    Parameters
    ----------
    lnL : numpy.ndarray
        ``(n, n_e)`` ``ln L(e)`` of the fits (NaN rows: not fitted).
    egrid : numpy.ndarray
        ``(n_e, 2)`` its ellipticity grid.
    priors : pylensfit.Priors
        The ellipticity prior and the bulge fractions' weights used (its
        ``ellipticity`` and ``bulge_weights``).
    config : Config
        ``sensitivity``, ``output_refine`` and ``min_snr`` used.
    ctx : ObjectContext
        Each object's flags, class, S/N, flux, size, noise and PSF size (and sky frame).
    lnL_bulge, lnL_star : numpy.ndarray, optional
        Each bulge fraction's ``ln L(e)`` and the point source's, to mix.
    flagged : {"keep", "blank"}
        ``"keep"``: every fitted row keeps its shapes (the stamps table); ``"blank"``:
        only the rows without a flag in ``ctx.flags`` (the catalogue; NaN elsewhere).

    Returns
    -------
    Assembled
        The columns and the mixed ``ln L(e)``.
    """
    if flagged not in ("keep", "blank"):
        raise ValueError(f"flagged must be 'keep' or 'blank', got {flagged!r}")
    lnL = np.asarray(lnL)
    f0 = np.asarray(ctx.flags, dtype=np.int32)
    measured = np.isfinite(lnL).all(axis=1)
    kept = measured if flagged == "keep" else measured & (f0 == 0)
    mixed = mix_lnL(lnL, lnL_bulge, lnL_star, priors.bulge_weights, kept)
    sh = shapes(mixed, egrid, priors.ellipticity, sensitivity=config.sensitivity,
                refine=config.output_refine)  # fmt: skip
    # a row of the catalogue without a finite shape is a failed fit, never one of flags 0
    failed = np.asarray(sh["flags"], dtype=np.int32)
    if flagged == "blank":
        failed = np.where(kept, failed, 0).astype(np.int32)
        kept = kept & (failed == 0)
    flags = flag_low_snr(f0 | failed, ctx.not_galaxy, ctx.model_SNratio, config.min_snr)
    cols: dict[str, np.ndarray] = {}
    for c in SHAPE_COLUMNS:
        v = np.asarray(sh[c], dtype=float)
        cols[c] = v if flagged == "keep" else np.where(kept, v, np.nan)
    if ctx.frame is not None:
        _to_sky(cols, ctx.frame)
    usable = usable_galaxies(flags, ctx.not_galaxy, ctx.model_SNratio, config.min_snr)
    n = len(flags)
    cols["weight"] = inverse_variance_weights(
        cols["e1"], cols["e2"], cols["sens1"], cols["sens2"], ctx.model_flux,
        np.broadcast_to(np.asarray(ctx.noise_sigma, dtype=float), (n,)), ctx.scalelength,
        ctx.psf_sigma, usable)  # fmt: skip
    cols["flags"] = flags
    return Assembled(columns=cols, lnL=mixed)


def _to_sky(cols: dict[str, np.ndarray], frame: SkyFrame) -> None:
    """The shape columns from the pixel frame to ``frame``, in place; the pixel frame's
    means kept as ``e1_pix, e2_pix``."""
    e1, e2 = cols["e1"], cols["e2"]
    cols["e1_pix"], cols["e2_pix"] = e1, e2
    cols["e1"], cols["e2"] = to_sky(e1, e2, frame)
    v = covariance_to_sky(cols["e1_var"], cols["e2_var"], cols["e12_cov"], frame)
    cols["e1_var"], cols["e2_var"], cols["e12_cov"] = v
    cols["sens1"], cols["sens2"] = sensitivity_to_sky(cols["sens1"], cols["sens2"], frame)
