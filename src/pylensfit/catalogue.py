"""Catalogue input and output: the shear catalogue's columns, FITS written atomically.

The output catalogue is a FITS file:

* HDU ``CATALOG``: one row per object that entered the pipeline (:data:`COLUMNS`);
* HDU ``LNL``: ``(n_objects, n_e)`` float32 ``ln L(e)`` grids, row ``i`` for catalogue row
  ``i`` (each row's maximum is 0; NaN rows for objects not measured), so that the prior
  can be re-estimated, or estimated per bin, without refitting;
* HDU ``LNLB`` (bulge fraction marginalised): ``(n_objects, n_b, n_e)`` float32, each
  fraction's ``ln L(e)`` on the scale of the ``lnL_star`` column, so that the prior over
  the fractions can be (re-)estimated; header ``BULGEFR`` (the fractions) and ``BULGEW``
  (their weights in ``LNL``, when estimated);
* HDU ``EGRID``: the ``(n_e, 2)`` ellipticity cell centres;
* HDU ``PSFS``: one row per input image with its PSF diagnostics (``psf_n_used``,
  ``psf_fwhm``, ``psf_e1``, ... of the PSF at the image's centre and, for a PSF model
  fitted over the image, its held-out stars' ellipticity residuals ``psf_heldout_n``,
  ``psf_heldout_mean_de1/2``, ``psf_heldout_rms_de1/2``, ``psf_heldout_noise_de`` (the rms
  the stars' noise alone gives) and ``psf_heldout_excess_de1/2``, NaN for a constant
  PSF), and ``PSFIMG``, the ``(n_images, N, N)`` PSF images;
* HDU ``CONFIG``: the configuration (``key``, ``value`` as YAML text);
* the primary header: provenance (``PLFVERS``, date, number of images and objects, the
  prior's parameters).

Column names follow the KiDS lensfit catalogues where those have one (``e1``, ``e2``,
``weight``, ``fitclass``, ``model_SNratio``, ``pixel_SNratio``, ``PSF_e1``, ``PSF_e2``,
``ALPHA_J2000``, ``DELTA_J2000``), so that survey code reads ours unchanged.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from astropy.table import Table

__all__ = ["COLUMNS", "FITCLASS", "atomic_write", "column_table"]

#: name -> (unit, description) of every column of the output catalogue.
COLUMNS: dict[str, tuple[str, str]] = {
    "id": ("", "running object number in the catalogue (1-based)"),
    "image": ("", "input image file name (base name)"),
    "image_index": ("", "index of the input image in the run (0-based)"),
    "object_id": ("", "detection number within its image (1-based; input catalogue row)"),
    "x": ("pix", "x position in the image, 0-based (pixel centres at integers); fitted "
          "centre when measured, detection position otherwise"),
    "y": ("pix", "y position in the image, 0-based; as x"),
    "ALPHA_J2000": ("deg", "right ascension from the image WCS (float64; NaN without WCS)"),
    "DELTA_J2000": ("deg", "declination from the image WCS (float64; NaN without WCS)"),
    "x_detect": ("pix", "detection (catalogue) x position, 0-based"),
    "y_detect": ("pix", "detection (catalogue) y position, 0-based"),
    "mag": ("mag", "-2.5 log10(detection flux) + zeropoint (zeropoint 0 unless configured)"),
    "flux_aper": ("adu", "detection flux in a circular aperture of 5 r_half (sep)"),
    "flux_aper_err": ("adu", "its error"),
    "r_half": ("pix", "half-flux radius (sep)"),
    "sep_flag": ("", "sep extraction flags (deblended, blended, truncated, ...; see "
                 "pylensfit.detection.SEP_FLAGS)"),
    "pixel_SNratio": ("", "detection S/N: aperture flux over its error"),
    "noise_sigma": ("adu", "per-pixel noise standard deviation used in the fit"),
    "background": ("adu", "sky background subtracted at the object's position (measured "
                          "again less the fitted models: Config.model_background)"),
    "model_flux": ("adu", "amplitude of the most likely model (total flux)"),
    "model_SNratio": ("", "matched-filter S/N of the most likely model"),
    "scalelength": ("pix", "most likely model size r (marginal over e); 0 for a point "
                    "source; scale length (exponential, bulge+disc) or half-light radius "
                    "(de Vaucouleurs)"),
    "stamp_size": ("pix", "side of the postage stamp the object was fitted on: "
                   "Config.stamp_size, or for a large galaxy a larger tier up to "
                   "Config.max_stamp_size; 0 if not fitted"),
    "e1": ("", "posterior mean ellipticity <e1> (docs: method, eq-posterior), "
               "e = (a-b)/(a+b), in the sky frame (W, N) of TreeCorr: e1 > 0 east-west, "
               "e2 > 0 along NW-SE; the pixel frame for an image without a WCS"),
    "e2": ("", "posterior mean ellipticity <e2>, sky frame as e1"),
    "e1_var": ("", "posterior variance of e1 (sky frame)"),
    "e2_var": ("", "posterior variance of e2 (sky frame)"),
    "e12_cov": ("", "posterior covariance of e1 and e2 (sky frame)"),
    "sens1": ("", "shear sensitivity d<e1>/dg1 (exact by default: docs: method, "
                  "eq-sensitivity-exact), sky frame"),
    "sens2": ("", "shear sensitivity d<e2>/dg2, sky frame"),
    "e1_pix": ("", "<e1> in the image's pixel frame (x, y), as the LNL grids"),
    "e2_pix": ("", "<e2> in the image's pixel frame"),
    "sky_angle": ("deg", "rotation from the (flipped) pixel axes to the sky axes (W, N) "
                  "at the object, from the WCS's local Jacobian (0 without a WCS)"),
    "sky_flip": ("", "the WCS is a mirror image at the object (e2 changes sign first)"),
    "wcs_g1": ("", "the WCS's local distortion as a reduced shear g1 (flipped pixel frame)"),
    "wcs_g2": ("", "the WCS's local distortion g2"),
    "weight": ("", "inverse-variance weight 1/(sigma_pop^2 + sigma_e^2) of a galaxy usable "
               "for shear (Miller et al. 2013's form, sigma_e^2 the median measurement "
               "variance of galaxies of its round S/N and size: pylensfit.weights), 0 for "
               "every other row"),
    "fitclass": ("", "0 galaxy measured, 1 star (most likely r = 0), -1 not measured "
                 "(see flags)"),
    "is_star": ("", "most likely model size below Config.point_source_size (a point source)"),
    "e1_best": ("", "e1 of the single most likely model (grid cell), pixel frame"),
    "e2_best": ("", "e2 of the single most likely model (grid cell), pixel frame"),
    "psf_star": ("", "selected on the stellar locus as a PSF star of its image"),
    "refit_neighbours": ("", "measured in a second fit, with the neighbours' best-fit models "
                         "subtracted from its stamp (Config.subtract_neighbours)"),
    "PSF_e1": ("", "ellipticity e1 of the PSF used for this object (adaptive moments), "
                   "in the frame of e1"),
    "PSF_e2": ("", "ellipticity e2 of the PSF used for this object, frame of e1"),
    "flags": ("", "bit mask of reasons, see pylensfit.flags.FLAGS (0: measured, usable)"),
    "lnL_star": ("", "bulge fraction marginalised: the point source's ln L on the scale of "
                 "the LNLB planes (each fraction's ln L(e), HDU LNLB), which lnL mixes with "
                 "the bulge-fraction prior (header BULGEW; uniform if absent)"),
}

#: fitclass codes (KiDS-like)
FITCLASS = {"galaxy": 0, "star": 1, "not_measured": -1}


def column_table():
    """The documentation of :data:`COLUMNS` as an astropy Table (name, unit, description)."""
    return Table(
        rows=[(k, u, d) for k, (u, d) in COLUMNS.items()], names=("name", "unit", "description")
    )


def atomic_write(hdulist, path: str | Path, *, overwrite: bool = False) -> None:
    """Write an HDU list to ``path`` through a temporary file renamed when complete.

    A run killed while writing leaves no partial file under ``path``.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: output exists (pass overwrite=True to replace it)")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        hdulist.writeto(tmp, overwrite=True)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
