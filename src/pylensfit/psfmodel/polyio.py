"""The FITS file of a :class:`~pylensfit.psfmodel.PolynomialPSF`: written and read."""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import numpy as np
from astropy.io import fits
from astropy.table import Table

from .._util import atomic_write, jsonable
from ..psf import PSFError
from .basis import exponents

#: ``PSFMODEL`` header value of a file written by :meth:`PolynomialPSF.write`.
POLY_KIND = "POLYNOMIAL"


class PolynomialFile(NamedTuple):
    """What a polynomial PSF's file holds: the arguments of ``PolynomialPSF``."""

    coefs: np.ndarray
    order: int
    bounds: tuple[float, float, float, float]
    cov: np.ndarray | None
    stars: Table | None
    diagnostics: dict
    centroid_sigma: float
    margin: int
    source: str


def write_polynomial(model: PolynomialFile, path: str | Path, overwrite: bool) -> None:
    """Write ``model`` (a ``PolynomialPSF`` or a :class:`PolynomialFile`) as FITS,
    atomically (the layout: :meth:`PolynomialPSF.write
    <pylensfit.psfmodel.PolynomialPSF.write>`)."""
    prim = fits.PrimaryHDU(model.coefs)
    hdr = prim.header
    hdr["PSFMODEL"] = (POLY_KIND, "pylensfit per-pixel polynomial PSF")
    hdr["ORDER"] = (model.order, "total degree in u=(x-x0)/sx, v=(y-y0)/sy")
    for key, val in zip(("XMIN", "XMAX", "YMIN", "YMAX"), model.bounds, strict=True):
        hdr[key] = (val, "bounds mapped on [-1, 1], 0-based pixels")
    hdr["CSIGMA"] = (model.centroid_sigma, "centre convention Gaussian sigma [pixel]")
    hdr["MARGIN"] = (model.margin, "padding of the Fourier re-centring [pixel]")
    # string cards carry no comment: a long value would have it truncated (a warning)
    hdr["SOURCE"] = str(model.source)
    hdr["TERMS"] = " ".join(f"u{i}v{j}" for i, j in exponents(model.order))
    for key, name in (("N_USED", "n_used"), ("N_REJ", "n_rejected")):
        if name in model.diagnostics:
            hdr[key] = int(model.diagnostics[name])
    hdr["DIAGS"] = json.dumps(jsonable(model.diagnostics), sort_keys=True)
    hdus = [prim]
    if model.cov is not None:
        hdus.append(fits.ImageHDU(model.cov, name="COVAR"))
    if model.stars is not None:
        tab = fits.table_to_hdu(model.stars)
        tab.name = "STARS"
        hdus.append(tab)
    atomic_write(fits.HDUList(hdus), path, overwrite=overwrite)


def read_polynomial(path: str | Path) -> PolynomialFile:
    """The contents of a file written by :func:`write_polynomial` (:class:`PSFError` for
    another file)."""
    with fits.open(path) as hdul:
        hdr = hdul[0].header
        if str(hdr.get("PSFMODEL", "")).strip() != POLY_KIND:
            raise PSFError(f"{path}: not a PolynomialPSF file (no PSFMODEL = {POLY_KIND!r})")
        coefs = np.array(hdul[0].data, dtype=np.float64)
        cov = np.array(hdul["COVAR"].data, dtype=np.float64) if "COVAR" in hdul else None
        stars = None
        if "STARS" in hdul:
            data = hdul["STARS"].data
            stars = Table({c: np.array(data[c]) for c in data.names})
        bounds = tuple(float(hdr[k]) for k in ("XMIN", "XMAX", "YMIN", "YMAX"))
        diags = json.loads(hdr.get("DIAGS", "{}"))
        csigma, margin = float(hdr.get("CSIGMA", 2.0)), int(hdr.get("MARGIN", 4))
        source, order = str(hdr.get("SOURCE", "")), int(hdr["ORDER"])
    if stars is not None:
        stars["reason"] = np.array([str(r).strip() for r in stars["reason"]], dtype=str)
        for c in ("used", "heldout"):
            stars[c] = np.asarray(stars[c], dtype=bool)
    return PolynomialFile(coefs, order, bounds, cov, stars, diags, csigma, margin, source)
