"""The image tasks and their typed results: what one image's task takes and gives back."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..calibration import Priors
from ..config import Config
from ..prior import SizePrior
from ..psf import PSFResult
from ..psfmodel import PSFModel

__all__ = [
    "StarfieldTask",
    "ImageTask",
    "PSFSummary",
    "ImageResult",
    "PSF_KEYS",
    "HELDOUT_KEYS",
    "psf_summary",
]


@dataclass(frozen=True)
class StarfieldTask:
    """One star-field image to build a PSF from (a task of :func:`starfield_task`)."""

    path: str
    index: int
    config: Config
    single_thread: bool = False  # set by the runner on its workers


@dataclass(frozen=True)
class ImageTask:
    """One image to measure (a task of :func:`image_task`)."""

    path: str
    index: int
    config: Config
    weight: str | None = None  # the image's weight and mask files
    mask: str | None = None
    catalogue: str | None = None  # an input catalogue instead of detection
    star_psfs: tuple = ()  # the star fields' PSFs (PSFResult or PSFModel)
    star_column: str | None = None
    psf_dir: str | None = None
    psf: PSFResult | PSFModel | None = None  # a given PSF: no stars stacked
    size_prior: SizePrior | None = None
    keep_lnL_r: bool | str = False  # keep L(r): True, or "annuli" (per ring of |e|)
    size_marginal_prior: Any = None
    # the measurement's priors, with Config.response "metacal": the metacalibration's
    # posterior means need them in the image's task (images/metacal_rows.py)
    metacal_priors: Priors | None = None
    single_thread: bool = False  # set by the runner on its workers


@dataclass(frozen=True)
class PSFSummary:
    """An image's PSF as the catalogue keeps it (its ``PSFS`` and ``PSFIMG`` HDUs).

    Attributes
    ----------
    numbers : dict of float
        The PSF's diagnostics at the image's centre (``PSF_KEYS``: ``n_used``,
        ``fwhm``, ``sigma``, ...) and a varying model's held-out check
        (``HELDOUT_KEYS``, NaN for a constant PSF).
    image : numpy.ndarray
        The PSF image at the image's centre.
    """

    numbers: dict[str, float]
    image: np.ndarray

    def get(self, key: str) -> float:
        """The number ``key`` (NaN if not kept)."""
        return self.numbers.get(key, math.nan)

    @property
    def sigma(self) -> float:
        """The PSF's size (pixels, adaptive moments)."""
        return self.get("sigma")


@dataclass(frozen=True)
class ImageResult:
    """One image measured: what :func:`image_task` hands the run, a part file keeps
    (:func:`write_part`, :func:`_read_part`) and :func:`assemble_results` reads.

    Attributes
    ----------
    index : int
        The image's index in the run.
    path : str
        The image file.
    rows : dict of numpy.ndarray
        The image's catalogue columns before the shapes (:func:`_image_rows`), one
        entry per object, under the names of :data:`pylensfit.catalogue.COLUMNS`.
    lnL : numpy.ndarray
        ``(n, n_e)`` float32 ``ln L(e)`` of each object (NaN: not measured).
    egrid : numpy.ndarray
        ``(n_e, 2)`` the ellipticity grid of ``lnL``.
    lnL_bulge : numpy.ndarray or None
        ``(n, n_b, n_e)`` each bulge fraction's ``ln L(e)`` (marginalised fractions).
    lnL_r : numpy.ndarray or None
        ``L(r)`` (per ring of ``|e|``) where a calibration pass keeps it.
    psf : PSFSummary or None
        The image's PSF (None: it failed).
    psf_note : str
        Why the image's own stars gave no PSF ("" if they did).
    psf_source : str
        Where the PSF came from, in words.
    timing : dict of float
        Seconds per stage (``read+detect``, ``psf``, ``stamps``, ``fit``).
    """

    index: int
    path: str
    rows: dict[str, np.ndarray]
    lnL: np.ndarray
    egrid: np.ndarray
    lnL_bulge: np.ndarray | None = None
    lnL_r: np.ndarray | None = None
    psf: PSFSummary | None = None
    psf_note: str = ""
    psf_source: str = ""
    timing: dict[str, float] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.lnL.shape[0])


PSF_KEYS = ("n_used", "n_rejected", "fwhm", "sigma", "e1", "e2")
#: A varying PSF model's check on its held-out stars (:class:`PolynomialPSF`'s
#: ``diagnostics``), kept per image in the catalogue's ``PSFS`` HDU (NaN otherwise).
HELDOUT_KEYS = ("heldout_n", "heldout_mean_de1", "heldout_mean_de2", "heldout_rms_de1",
                 "heldout_rms_de2", "heldout_noise_de", "heldout_excess_de1",
                 "heldout_excess_de2", "heldout_chi2_de", "heldout_pvalue_de",
                 "heldout_suspect")  # fmt: skip


def psf_summary(psf: PSFResult, model: PSFModel | None = None) -> PSFSummary:
    """The PSF's numbers for the catalogue: the PSF at the image's centre and, for a
    model fitted over the image, its held-out stars' residuals (NaN if it has none)."""
    d = {k: float(getattr(psf, k)) for k in PSF_KEYS}
    d["n_used"], d["n_rejected"] = int(psf.n_used), int(psf.n_rejected)
    diag = {} if model is None else model.diagnostics
    d.update({k: float(diag.get(k, math.nan)) for k in HELDOUT_KEYS})
    return PSFSummary(numbers=d, image=np.asarray(psf.image, dtype=float))
