"""Reading any PSF model back: :func:`read_psf_model`."""

from __future__ import annotations

from pathlib import Path

from astropy.io import fits

from ..psf import PSFError, read_psf
from .base import ConstantPSF, PSFModel
from .piff_model import PiffPSF
from .polyio import POLY_KIND
from .polynomial import PolynomialPSF


def is_piff_fits(hdul) -> bool:
    return "PSF" in hdul and "PSF_WCS" in hdul and not hdul[0].header.get("PSFMODEL")


def read_psf_model(path: str | Path, **piff_options) -> PSFModel:
    """Read a PSF model: Piff's, a :class:`PolynomialPSF` or a constant PSF image.

    Parameters
    ----------
    path : str or Path
        A ``.piff`` file or a FITS file written by Piff (:class:`PiffPSF`); a file
        written by :meth:`PolynomialPSF.write` (:class:`PolynomialPSF`); a file written by
        :meth:`pylensfit.psf.PSFResult.write`, or any FITS file holding a 2-D PSF image
        (:class:`ConstantPSF`, through :func:`pylensfit.psf.read_psf`).
    **piff_options
        Keyword arguments of :class:`PiffPSF` (``size``, ``chipnum``, ...), for a Piff
        file only.

    Returns
    -------
    PSFModel

    Raises
    ------
    PSFError
        If the file cannot be read as any of them.
    PiffNotInstalledError
        For a Piff file when piff is not installed.
    """
    path = Path(path)
    if path.suffix.lower() == ".piff":
        return PiffPSF(path, **piff_options)
    try:
        with fits.open(path) as hdul:
            kind = str(hdul[0].header.get("PSFMODEL", "")).strip()
            piff_file = is_piff_fits(hdul)
    except (OSError, ValueError) as err:
        raise PSFError(f"{path}: not a readable PSF file ({err})") from None
    if piff_file:
        return PiffPSF(path, **piff_options)
    if piff_options:
        raise TypeError(f"options {sorted(piff_options)} apply to Piff files only")
    if kind == POLY_KIND:
        return PolynomialPSF.read(path)
    return ConstantPSF(read_psf(path))
