"""Writing and reading the catalogue's FITS file."""

from __future__ import annotations

import datetime
import json
import logging
import os

import numpy as np
from astropy.io import fits
from astropy.table import Table

from .._version import __version__
from ..calibration import Priors
from ..catalogue import atomic_write, column_table, flag_cards
from ..config import Config
from ..prior import Prior, SizePrior, SplinePrior
from ..skyframe import SkyFrame, frame_of_table, spin2_matrix, to_sky
from .inputs import InputError, open_input

__all__ = ["catalogue_frame", "psf_to_sky", "write_catalogue", "read_catalogue"]

# the pipeline's one logger: its name predates the split into modules
log = logging.getLogger("pylensfit.pipeline")


def catalogue_frame(cat: Table) -> SkyFrame:
    """The sky frame of each row of a :func:`measure` catalogue (its ``sky_angle``,
    ``sky_flip``, ``wcs_g1``, ``wcs_g2`` columns; the pixel frame where it has none)."""
    return frame_of_table(cat)


def psf_to_sky(cat: Table, frame: SkyFrame) -> None:
    """The PSF's ellipticity from the pixel frame to the sky frame (where
    :func:`pylensfit.assemble.assemble` turned the shapes), and the catalogue's frame in
    ``meta["frame"]``."""
    cat["PSF_e1"], cat["PSF_e2"] = to_sky(cat["PSF_e1"], cat["PSF_e2"], frame)
    cat.meta["frame"] = ("sky" if frame.has_wcs.all() and frame.n else
                         "pixel" if not frame.has_wcs.any() else "mixed")  # fmt: skip


def metacal_to_sky(cat: Table, frame: SkyFrame) -> None:
    """The metacalibration's ``e1_mcal, e2_mcal`` (as :func:`pylensfit.skyframe.to_sky`
    turns ``e1, e2``) and response ``R`` (a spin-2 tensor: ``M R M^T``, ``M`` the rotation
    and flip of :func:`pylensfit.skyframe.spin2_matrix`) from the pixel frame to the sky
    frame, where the catalogue has them."""
    if "e1_mcal" not in cat.colnames:
        return
    cat["e1_mcal"], cat["e2_mcal"] = to_sky(cat["e1_mcal"], cat["e2_mcal"], frame)
    M = spin2_matrix(frame)
    R = np.empty((len(cat), 2, 2))
    for i in range(2):
        for j in range(2):
            R[:, i, j] = np.asarray(cat[f"R{i + 1}{j + 1}"], dtype=float)
    R = M @ R @ np.transpose(M, (0, 2, 1))
    for i in range(2):
        for j in range(2):
            cat[f"R{i + 1}{j + 1}"] = R[:, i, j]


# ----------------------------------------------------------------------------------------
# Catalogue files
# ----------------------------------------------------------------------------------------
def _card(header, key: str, value: str, comment: str) -> None:
    """A string card, its comment left out where the value needs the card's room (a long
    value continues on CONTINUE cards)."""
    header[key] = (value, comment) if len(value) + len(comment) < 64 else value


def write_catalogue(cat: Table, path: str | os.PathLike, *, overwrite: bool = False) -> None:
    """Write a catalogue from :func:`measure` as FITS (see :mod:`pylensfit.catalogue`)."""
    plain = cat.copy(copy_data=False)
    lnL = np.asarray(plain["lnL"], dtype=np.float32)
    plain.remove_column("lnL")
    lnL_bulge = None
    if "lnL_bulge" in plain.colnames:
        lnL_bulge = np.asarray(plain["lnL_bulge"], dtype=np.float32)
        plain.remove_column("lnL_bulge")
    plain.meta.clear()
    for c in plain.colnames:  # documented in the COLUMNS HDU (FITS comments are too short)
        plain[c].description = None
    prior = cat.meta.get("prior")
    cfg = cat.meta.get("config")
    hdr = fits.Header()
    hdr["PLFVERS"] = (__version__, "pylensfit version")
    hdr["DATE"] = (datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                   "UTC time the catalogue was written")  # fmt: skip
    hdr["NOBJ"] = (len(cat), "objects (rows)")
    if prior is not None:
        for key, value, comment in prior.header_cards():
            hdr[key] = (value, comment)
        hdr["PRIORMTH"] = (prior.method, "how the prior was obtained")
    if cfg is not None:
        hdr["SENSTVTY"] = (cfg.sensitivity, "shear sensitivity formula")
        hdr["MODEL"] = (cfg.model, "galaxy model")
    frame = cat.meta.get("frame", "pixel")
    hdr["EFRAME"] = (frame, "frame of e1,e2: sky (W,N), pixel, mixed")
    hdr.extend(flag_cards())  # one card per bit (pylensfit.catalogue)
    hdr.add_comment("FLAGn: the name of the flags column's bit of value n")
    tab = fits.table_to_hdu(plain)
    tab.name = "CATALOG"
    hdus = [fits.PrimaryHDU(header=hdr), tab, fits.ImageHDU(lnL, name="LNL"),
            fits.ImageHDU(np.asarray(cat.meta["egrid"]), name="EGRID")]  # fmt: skip
    if lnL_bulge is not None:
        hb = fits.ImageHDU(lnL_bulge, name="LNLB")
        _card(hb.header, "BULGEFR", ",".join(f"{f:g}" for f in cat.meta["bulge_fractions"]),
              "bulge fractions of the LNLB planes")  # fmt: skip
        if cat.meta.get("bulge_sizes") is not None:
            _card(hb.header, "BULGESZ", ",".join(f"{f:g}" for f in cat.meta["bulge_sizes"]),
                  "bulge sizes (disc scale lengths)")  # fmt: skip
        if cat.meta.get("runs") is not None:
            _card(hb.header, "RUNS", ";".join(cat.meta["runs"]), "each plane's profile")
        w = cat.meta.get("bulge_weights")
        if w is not None:
            _card(hb.header, "BULGEW", ",".join(f"{v:.6g}" for v in w),
                  "their estimated prior weights")
        hdus.append(hb)
    sp = cat.meta.get("size_prior")
    if sp is not None:
        # one row per knot; a prior per run of the family has a density vector per row
        hs = fits.table_to_hdu(Table({"ln_h": sp.ln_h, "density": np.asarray(sp.density).T}))
        hs.name = "SIZEPRI"
        hs.header["STAR"] = (sp.star, "prior probability of a point source")
        if sp.smoothing is not None:
            hs.header["SMOOTH"] = (sp.smoothing, "EMS smoothing of the estimate")
        hdus.append(hs)
    pr = cat.meta.get("priors")
    if pr is not None:  # every prior of the measurement, as Priors.save writes them
        hp = fits.BinTableHDU(Table({"json": [json.dumps(pr.to_dict())]}))
        hp.name = "PRIORS"
        hdus.append(hp)
    if "psfs" in cat.meta:
        p = fits.table_to_hdu(cat.meta["psfs"])
        p.name = "PSFS"
        hdus += [p, fits.ImageHDU(np.asarray(cat.meta["psf_images"], dtype=np.float32),
                                  name="PSFIMG")]  # fmt: skip
    if cfg is not None:
        d = cfg.to_dict()
        c = fits.BinTableHDU(Table({"key": list(d), "value": [json.dumps(v) for v in d.values()]}))
        c.name = "CONFIG"
        hdus.append(c)
    doc = fits.table_to_hdu(column_table())
    doc.name = "COLUMNS"
    hdus.append(doc)
    atomic_write(fits.HDUList(hdus), path, overwrite=overwrite)


def _header_prior(hdr, egrid: np.ndarray) -> Prior | SplinePrior:
    """The ellipticity prior of a catalogue's primary header (its ``PRIORFRM`` form)."""
    method = hdr.get("PRIORMTH", "fixed")
    if hdr.get("PRIORFRM") == SplinePrior.form:
        n = len(SplinePrior().coef)
        return SplinePrior(coef=[hdr[f"PRIORS{j}"] for j in range(n)], egrid=egrid,
                           method=method)  # fmt: skip
    return Prior(B=hdr["PRIOR_B"], C=hdr["PRIOR_C"], D=hdr["PRIOR_D"], egrid=egrid,
                 method=method)  # fmt: skip


def read_catalogue(path: str | os.PathLike) -> Table:
    """Read a catalogue written by :func:`write_catalogue` (``lnL`` as a 2-D column).

    Raises
    ------
    InputError
        One line naming the file: not a pylensfit catalogue (an HDU missing, ``LNL`` and
        ``EGRID`` of inconsistent shapes) or a header card or HDU that cannot be read.
    """
    with open_input(str(path), "catalogue") as h:
        for need in ("CATALOG", "LNL", "EGRID"):
            if need not in h:
                raise InputError(f"{path}: not a pylensfit catalogue (no {need} HDU)")
        cat = _guarded(path, "CATALOG", lambda: Table(h["CATALOG"].data))
        lnL = _guarded(path, "LNL", lambda: np.array(h["LNL"].data, dtype=np.float32))
        egrid = _guarded(path, "EGRID", lambda: np.array(h["EGRID"].data, dtype=float))
        if lnL.ndim != 2 or lnL.shape[0] != len(cat):
            raise InputError(f"{path}: LNL has shape {lnL.shape} for {len(cat)} objects "
                             "(one row of ln L per object)")  # fmt: skip
        if egrid.shape != (lnL.shape[1], 2) or not np.isfinite(egrid).all():
            raise InputError(f"{path}: EGRID has shape {egrid.shape}; LNL's "
                             f"{lnL.shape[1]} columns need ({lnL.shape[1]}, 2) finite "
                             "ellipticities")  # fmt: skip
        cat["lnL"] = lnL
        cat.meta["egrid"] = egrid
        for hdu, read in _HDU_READERS:
            if hdu == "PRIMARY" or hdu in h:
                _guarded(path, hdu, lambda read=read, hdu=hdu: read(h, hdu, cat, path))
    return cat


def _guarded(path, hdu: str, read):
    """``read()``; an error reading it as one line naming the file and the HDU."""
    try:
        return read()
    except InputError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as err:
        msg = err.args[0] if isinstance(err, KeyError) and err.args else err
        raise InputError(f"{path}: cannot read HDU {hdu} ({type(err).__name__}: "
                         f"{msg})") from None  # fmt: skip


def _read_bulge(h, hdu: str, cat: Table, path) -> None:
    hb = h[hdu]
    cat["lnL_bulge"] = np.array(hb.data, dtype=np.float32)
    cat.meta["bulge_fractions"] = np.array(hb.header["BULGEFR"].split(","), float)
    if "BULGESZ" in hb.header:
        cat.meta["bulge_sizes"] = np.array(hb.header["BULGESZ"].split(","), float)
    if "RUNS" in hb.header:
        cat.meta["runs"] = hb.header["RUNS"].split(";")
    w = hb.header.get("BULGEW")
    cat.meta["bulge_weights"] = None if w is None else np.array(w.split(","), float)


def _read_primary(h, hdu: str, cat: Table, path) -> None:
    hdr = h[0].header
    cat.meta["frame"] = str(hdr.get("EFRAME", "pixel"))
    if "PRIOR_B" in hdr or hdr.get("PRIORFRM") == SplinePrior.form:
        cat.meta["prior"] = _header_prior(hdr, cat.meta["egrid"])


def _read_size_prior(h, hdu: str, cat: Table, path) -> None:
    hs = h[hdu]
    cat.meta["size_prior"] = SizePrior(ln_h=np.array(hs.data["ln_h"], dtype=float),
                                       density=np.array(hs.data["density"], float).T,
                                       star=float(hs.header["STAR"]),
                                       smoothing=hs.header.get("SMOOTH"))  # fmt: skip


def _read_priors(h, hdu: str, cat: Table, path) -> None:
    try:
        cat.meta["priors"] = Priors.from_dict(json.loads(str(h[hdu].data["json"][0])),
                                              source=f"{path} PRIORS")  # fmt: skip
    except ValueError as err:
        log.warning("%s: the PRIORS HDU cannot be read (%s); left out", path, err)


def _read_psfs(h, hdu: str, cat: Table, path) -> None:
    if hdu == "PSFS":
        cat.meta["psfs"] = Table(h[hdu].data)
    else:
        cat.meta["psf_images"] = np.array(h[hdu].data, dtype=float)


def _read_config(h, hdu: str, cat: Table, path) -> None:
    t = h[hdu].data
    vals = {str(k): json.loads(str(v)) for k, v in zip(t["key"], t["value"], strict=True)}
    known = set(Config.describe())
    extra = sorted(set(vals) - known)
    if extra:  # written by another version: read what this one knows
        log.warning("%s: configuration key(s) %s unknown to this version are left out", path,
                    extra)  # fmt: skip
    try:
        cat.meta["config"] = Config.from_dict({k: v for k, v in vals.items() if k in known})
    except ValueError as err:
        log.warning("%s: its configuration cannot be read (%s); left out", path, err)


#: the optional HDUs of a catalogue and their readers, in the order they are read
_HDU_READERS = (("LNLB", _read_bulge), ("PRIMARY", _read_primary),
                ("SIZEPRI", _read_size_prior), ("PRIORS", _read_priors),
                ("PSFS", _read_psfs), ("PSFIMG", _read_psfs), ("CONFIG", _read_config))
