"""The shear catalogue's schema, its generated tables, and FITS written atomically.

The catalogue is defined in one place: :data:`HDUS` (the file's HDUs), :data:`COLUMNS`
(the columns of its ``CATALOG`` HDU) and :data:`pylensfit.flags.FLAGS` (the bits of its
``flags`` column). :func:`pylensfit.write_catalogue` copies :data:`COLUMNS` into the
file's ``COLUMNS`` HDU (:func:`column_table`) and the flag bits into the primary
header's ``FLAGn`` cards (:func:`flag_cards`; :func:`header_flags` reads them back).
The README's tables are generated from the same definitions (:func:`markdown_hdus`,
:func:`markdown_columns`, :func:`markdown_flags`; :func:`update_readme` rewrites them,
``bash .ci/readme-tables`` runs it on README.md) and the documentation's at build time.

The output catalogue is a FITS file of the HDUs of :data:`HDUS`, in that order.
An HDU is written where the catalogue has its content (a catalogue of
:func:`pylensfit.measure` has every one but ``LNLB`` and ``SIZEPRI``, which depend on
the configuration). :func:`pylensfit.read_catalogue` reads them back. astropy's
``Table.read(path, hdu="CATALOG")`` reads the columns alone; without ``hdu=`` astropy
reads the same table, the first, and warns, as it does for every file of several tables.

Column names follow the KiDS lensfit catalogues where those have one (``e1``, ``e2``,
``weight``, ``fitclass``, ``model_SNratio``, ``pixel_SNratio``, ``PSF_e1``, ``PSF_e2``,
``ALPHA_J2000``, ``DELTA_J2000``), so that survey code reads ours unchanged.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable, Sequence
from pathlib import Path

from astropy.io import fits
from astropy.table import Table

from ._util import atomic_write
from .flags import FLAGS

__all__ = [
    "COLUMNS",
    "FITCLASS",
    "HDUS",
    "JOINT_COLUMNS",
    "METACAL_COLUMNS",
    "atomic_write",
    "column_table",
    "flag_cards",
    "header_flags",
    "markdown_columns",
    "markdown_flags",
    "markdown_hdus",
    "README_TABLES",
    "update_readme",
]

#: name -> contents of every HDU of the output catalogue, in the file's order (the module
#: docstring's list; an HDU is written where the catalogue has its content)
HDUS: dict[str, str] = {
    "PRIMARY": "no data; the header holds the provenance (PLFVERS, DATE, NOBJ), the "
               "ellipticity prior (PRIORFRM and its parameters, PRIORMTH), SENSTVTY, MODEL, "
               "EFRAME (the frame of e1, e2: sky, pixel or mixed) and one card per flag bit, "
               "FLAGn = its name for the bit of value n (FLAG1 = 'STAR'; a HIERARCH card from "
               "16384 on), the card's comment its meaning",
    "CATALOG": "one row per object that entered the pipeline, measured or flagged, with the "
               "columns of COLUMNS (those of the metacalibration with Config.response "
               "'metacal' only); the file's first table (extension 1)",
    "LNL": "(n_objects, n_e) float32 ln L(e) grids, row i for catalogue row i (each row's "
           "maximum 0, NaN for an object not measured), so that the prior can be estimated "
           "again, or per bin, without refitting",
    "EGRID": "the (n_e, 2) ellipticity cell centres of the LNL grids",
    "LNLB": "with the bulge fraction marginalised, (n_objects, n_b, n_e) float32, each "
            "fraction's ln L(e) on the scale of the lnL_star column, so that the prior over "
            "the fractions can be estimated again; header BULGEFR (the fractions), BULGEW "
            "(their weights in LNL, when estimated), BULGESZ and RUNS (each plane's profile) "
            "where the planes differ in size or profile",
    "SIZEPRI": "with a size prior, one row per knot (ln_h, and density, one per plane of "
               "LNLB); header STAR (the prior probability of a point source) and SMOOTH",
    "PRIORS": "every prior of the measurement, as JSON (the text of pylensfit.Priors.save)",
    "PSFS": "one row per input image: where its PSF came from (psf_source: given, a star "
            "field's or the image's stars, stacked or a polynomial model; note: why the "
            "image's own stars gave none), its PSF diagnostics (psf_n_used, psf_fwhm, "
            "psf_e1, ... of the PSF at the image's centre) and, for a PSF model fitted over "
            "the image, its check on held-out stars (the psf_heldout_* columns: the number "
            "of stars, the mean and rms of their residuals, the rms that their noise alone "
            "gives, their mean square over the noise's and its chi-square p-value, and "
            "psf_heldout_suspect, 1 where the check failed and the image's rows are flagged "
            "PSF_SUSPECT; NaN for a constant PSF)",
    "PSFIMG": "the (n_images, N, N) float32 PSF images, row for row of PSFS (zeros where the "
              "PSF failed)",
    "CONFIG": "the configuration, one row per setting (key, value as JSON)",
    "COLUMNS": "name, unit and description of every column of CATALOG (the table of COLUMNS)",
}

#: name -> (unit, description) of every column of the output catalogue.
# the module's documentation lists the HDUs from the same table
__doc__ = __doc__.replace(
    "in that order.\n",
    "in that order:\n\n" + "".join(f"* ``{k}``: {v}\n" for k, v in HDUS.items()) + "\n",
    1,
)

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
    "forced_SNratio": ("", "input catalogue rows: the best matched-filter S/N at the "
                       "catalogue position itself (round exponentials of half-light radius "
                       "0-4 px convolved with the PSF, no search over position: "
                       "pylensfit.forced.position_snr); below the threshold of "
                       "Config.forced_false_alarm the row is flagged LOW_SNR. NaN for "
                       "detected objects"),
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
    "weight": ("", "shear weight <sens> / Var(<e>) of a galaxy usable for shear (flags 0, "
               "fitclass 0): the mean of (sens1 + sens2) / 2 over the per-component variance "
               "of the posterior means e1, e2, both over the galaxies of its class of round "
               "S/N and size relative to the PSF (quantile bins, up to 10 x 4), leaving the "
               "galaxy itself out, so that it does not depend on the galaxy's own shape "
               "(pylensfit.weights.class_weights); 0 for every other row"),
    "fitclass": ("", "0 galaxy measured, 1 star (most likely r = 0), -1 not measured "
                 "(see flags)"),
    "is_star": ("", "most likely model size below Config.point_source_size (a point source)"),
    "e1_best": ("", "e1 of the single most likely model (grid cell), pixel frame"),
    "e2_best": ("", "e2 of the single most likely model (grid cell), pixel frame"),
    "bulge_best": ("", "bulge fraction of the single most likely model, with the bulge "
                   "fraction marginalised (Config.n_bulge_fractions > 1); NaN for a model "
                   "family of one fraction or an object not measured"),
    "psf_star": ("", "selected on the stellar locus as a PSF star of its image"),
    "refit_neighbours": ("", "measured in a second fit, with the neighbours' best-fit models "
                         "subtracted from its stamp (Config.subtract_neighbours)"),
    "PSF_e1": ("", "ellipticity e1 of the PSF used for this object (adaptive moments), "
                   "in the frame of e1"),
    "PSF_e2": ("", "ellipticity e2 of the PSF used for this object, frame of e1"),
    "flags": ("", "bit mask of reasons, see pylensfit.flags.FLAGS (0: measured, usable)"),
    "n_exposures": ("", "galaxies fitted jointly on their exposures "
                    "(pylensfit.measure_exposure_stamps): the number of exposures that "
                    "entered the fit (0: not measured)"),
    "exposures_used": ("", "galaxies fitted jointly on their exposures: bit mask, bit k "
                       "set where exposure k (ExposureStamps.exposure) entered the fit"),
    "lnL_star": ("", "bulge fraction marginalised: the point source's ln L on the scale of "
                 "the LNLB planes (each fraction's ln L(e), HDU LNLB), which lnL mixes with "
                 "the bulge-fraction prior (header BULGEW; uniform if absent)"),
    "e1_mcal": ("", "Config.response 'metacal': the posterior mean <e1> of the unsheared "
                "metacalibration image (deconvolved by the PSF, reconvolved with a slightly "
                "larger one, Config.metacal_reconvolution, its noise made isotropic; "
                "pylensfit.metacal), sky frame as e1; NaN where "
                "that image's fit is not usable"),
    "e2_mcal": ("", "Config.response 'metacal': <e2> of the unsheared metacalibration "
                "image, as e1_mcal"),
    "R11": ("", "Config.response 'metacal': the response d<e1>/dg1 measured on the galaxy "
            "itself, (<e1>(+delta) - <e1>(-delta)) / (2 delta) of its metacalibration "
            "images sheared by +-delta in g1 (Config.metacal_step), sky frame; NaN where a "
            "sheared image's fit is not usable"),
    "R12": ("", "Config.response 'metacal': the measured response d<e1>/dg2, as R11"),
    "R21": ("", "Config.response 'metacal': the measured response d<e2>/dg1, as R11"),
    "R22": ("", "Config.response 'metacal': the measured response d<e2>/dg2, as R11"),
    "mcal_snr_noshear": ("", "Config.response 'metacal': the matched-filter S/N of the most "
                         "likely model of the unsheared metacalibration image (its noise "
                         "sqrt(2) times the image's): the S/N of the selection"),
    "mcal_snr_1p": ("", "Config.response 'metacal': as mcal_snr_noshear, the image sheared "
                    "by +delta in g1 (for the selection response)"),
    "mcal_snr_1m": ("", "Config.response 'metacal': as mcal_snr_1p, sheared by -delta in g1"),
    "mcal_snr_2p": ("", "Config.response 'metacal': as mcal_snr_1p, sheared by +delta in g2"),
    "mcal_snr_2m": ("", "Config.response 'metacal': as mcal_snr_1p, sheared by -delta in g2"),
    "mcal_flags": ("", "Config.response 'metacal': bit mask of the metacalibration images "
                   "whose fit a selection leaves out, and of rows not metacalibrated "
                   "(pylensfit.flags.METACAL_FLAGS; 0: every image usable)"),
}

#: the columns of :data:`COLUMNS` that only a catalogue measured with ``Config.response =
#: "metacal"`` has (:func:`pylensfit.measure`); every other column but
#: :data:`JOINT_COLUMNS` is in every catalogue (``lnL_star`` where the bulge fraction is
#: marginalised)
METACAL_COLUMNS: tuple[str, ...] = (
    "e1_mcal", "e2_mcal", "R11", "R12", "R21", "R22", "mcal_snr_noshear", "mcal_snr_1p",
    "mcal_snr_1m", "mcal_snr_2p", "mcal_snr_2m", "mcal_flags")  # fmt: skip

#: the columns of :data:`COLUMNS` that only a table of galaxies fitted jointly on their
#: exposures has (:func:`pylensfit.measure_exposure_stamps`)
JOINT_COLUMNS: tuple[str, ...] = ("n_exposures", "exposures_used")

#: fitclass codes (KiDS-like)
FITCLASS = {"galaxy": 0, "star": 1, "not_measured": -1}


def column_table() -> Table:
    """:data:`COLUMNS` as a table: the catalogue's ``COLUMNS`` HDU.

    Returns
    -------
    astropy.table.Table
        One row per column of the ``CATALOG`` HDU, in its order: ``name``, ``unit``
        (empty for a number without a unit, a count or a label) and ``description``.
    """
    return Table(
        rows=[(k, u, d) for k, (u, d) in COLUMNS.items()], names=("name", "unit", "description")
    )


def _flag_keyword(value: int) -> str:
    """``FLAGn`` for the bit of value ``n``; a ``HIERARCH`` card beyond FITS' 8 characters."""
    key = f"FLAG{value}"
    return key if len(key) <= 8 else f"HIERARCH {key}"


def _fit(text: str, room: int) -> str:
    """``text`` on one line, cut after a word to at most ``room`` characters (a cut text
    ends in "...")."""
    text = " ".join(text.split())
    if len(text) <= room:
        return text
    return text[: room - 3].rsplit(" ", 1)[0].rstrip(" ,;:(") + "..."


def flag_cards() -> list[fits.Card]:
    """The primary header's cards of the flag bits, one per bit of
    :data:`pylensfit.flags.FLAGS`.

    ``FLAGn = 'NAME'`` names the bit of value ``n`` (``FLAG1 = 'STAR'``); the card's
    comment is the bit's description, cut after a word to fit the 80-character card. A
    keyword longer than FITS' 8 characters (a bit of value 16384 or more) is written as a
    ``HIERARCH`` card, read back under the same name (``header["FLAG16384"]``).

    Returns
    -------
    list of astropy.io.fits.Card
        In the order of :data:`~pylensfit.flags.FLAGS`.
    """
    cards = []
    for name, (value, desc) in FLAGS.items():
        key = _flag_keyword(value)
        head = len(fits.Card(key, name, "x").image.rstrip()) - 1  # where the comment starts
        cards.append(fits.Card(key, name, _fit(desc, fits.Card.length - head)))
    return cards


def header_flags(header: fits.Header) -> dict[int, str]:
    """The flag bits that a catalogue's primary header names (its ``FLAGn`` cards).

    Parameters
    ----------
    header : astropy.io.fits.Header
        The primary header of a catalogue written by :func:`pylensfit.write_catalogue`.

    Returns
    -------
    dict of int to str
        Bit value -> flag name, by increasing value.
    """
    found = {}
    for key in header:
        m = re.fullmatch(r"FLAG(\d+)", key)
        if m:
            found[int(m.group(1))] = str(header[key])
    return dict(sorted(found.items()))


#: characters that Markdown would read as markup in a table cell, and their escapes
_MARKDOWN_ESCAPES = {"\\": "\\\\", "|": "\\|", "<": "\\<", "*": "\\*"}


def _cell(text: str) -> str:
    """A Markdown table cell: one line, its markup characters escaped (``<e1>`` would be
    read as an HTML tag)."""
    return "".join(_MARKDOWN_ESCAPES.get(c, c) for c in " ".join(str(text).split()))


def _markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def markdown_hdus() -> str:
    """The Markdown table of the catalogue's HDUs (:data:`HDUS`): ``HDU``, ``contents``.

    Returns
    -------
    str
        The table's lines, without a final newline.
    """
    return _markdown_table(["HDU", "contents"], [(f"`{n}`", d) for n, d in HDUS.items()])


def markdown_columns() -> str:
    """The Markdown table of the catalogue's columns (:data:`COLUMNS`): ``column``,
    ``unit``, ``meaning``.

    Returns
    -------
    str
        The table's lines, without a final newline.
    """
    return _markdown_table(["column", "unit", "meaning"],
                           [(f"`{n}`", u, d) for n, (u, d) in COLUMNS.items()])  # fmt: skip


def markdown_flags() -> str:
    """The Markdown table of the flag bits (:data:`pylensfit.flags.FLAGS`): ``bit`` (its
    value), ``name``, ``meaning``.

    Returns
    -------
    str
        The table's lines, without a final newline.
    """
    return _markdown_table(["bit", "name", "meaning"],
                           [(str(v), f"`{n}`", d) for n, (v, d) in FLAGS.items()])  # fmt: skip


#: marker -> generator of each table that the README carries between the lines
#: ``<!-- marker:start -->`` and ``<!-- marker:end -->``
README_TABLES: dict[str, Callable[[], str]] = {
    "hdus": markdown_hdus,
    "columns": markdown_columns,
    "flags": markdown_flags,
}


def update_readme(text: str) -> str:
    """A README's text with each generated table (:data:`README_TABLES`) made anew.

    Parameters
    ----------
    text : str
        The README's Markdown.

    Returns
    -------
    str
        ``text`` with what lies between each pair of markers replaced by its table.

    Raises
    ------
    ValueError
        If a pair of markers is missing or appears more than once.
    """
    for marker, make in README_TABLES.items():
        pattern = re.compile(rf"(<!-- {marker}:start -->\n)(?:.*?\n)?(<!-- {marker}:end -->)",
                             re.S)  # fmt: skip
        text, n = pattern.subn(lambda m, make=make: f"{m.group(1)}{make()}\n{m.group(2)}", text)
        if n != 1:
            raise ValueError(f"the README needs one '<!-- {marker}:start -->' line and one "
                             f"'<!-- {marker}:end -->' line below it; found {n} pairs")
    return text


def main(argv: Sequence[str] | None = None) -> int:
    """Rewrite the generated tables of README files from the schema (``bash
    .ci/readme-tables``).

    Parameters
    ----------
    argv : sequence of str, optional
        ``[--check] README...`` (default: the command line). With ``--check`` nothing is
        written.

    Returns
    -------
    int
        The exit status: 1 under ``--check`` if a README's tables are out of date, else 0.
    """
    ap = argparse.ArgumentParser(prog="readme-tables", description="Rewrite the README's "
                                 "tables of the catalogue's HDUs, columns and flags.")
    ap.add_argument("readme", nargs="+", type=Path, help="README.md files")
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 if a README's tables are out of date")
    args = ap.parse_args(argv)
    stale = False
    for path in args.readme:
        text = path.read_text(encoding="utf-8")
        new = update_readme(text)
        if new != text:
            stale = True
            if args.check:
                print(f"{path}: its tables are out of date (bash .ci/readme-tables)")
            else:
                path.write_text(new, encoding="utf-8")
                print(f"{path}: tables rewritten")
    return int(stale and args.check)

