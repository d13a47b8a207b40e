"""The inputs of :func:`pylensfit.measure`: reading images, weights, masks and positions,
the saturated pixels, detection, and the up-front checks of the input files.
"""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from astropy.io import fits
from astropy.table import Table

from ..config import Config
from ..detection import detect, grow_mask, measure_background, saturation_level, saturation_mask
from ..psf import PSFError, PSFResult, psf_from_image
from ..psfmodel import ConstantPSF, PSFModel, read_psf_model

__all__ = [
    "InputError",
    "Image",
    "open_input",
    "read_image",
    "read_positions",
    "detect_objects",
    "value_at",
    "mask_saturated",
    "as_list",
    "check_inputs",
    "load_given",
    "read_given_psfs",
]

# the pipeline's one logger: its name predates the split into modules
log = logging.getLogger("pylensfit.pipeline")


class InputError(ValueError):
    """Bad input: a missing or unreadable file, an empty image, an empty catalogue."""


# ----------------------------------------------------------------------------------------
# Input
# ----------------------------------------------------------------------------------------
@dataclass
class Image:
    path: str
    data: np.ndarray
    header: fits.Header
    weight: np.ndarray | None
    bad: np.ndarray  # masked, zero-weight or non-finite pixels


@contextmanager
def open_input(path: str, what: str) -> Iterator[fits.HDUList]:
    """Open a FITS file; a missing or unreadable file is an :class:`InputError`."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{path}: {what} not found")
    with open(p, "rb") as fh:  # ours to close, whatever astropy makes of the content
        try:
            hdul = fits.open(fh, memmap=False)
            hdul.verify("exception")
        except Exception as err:  # astropy raises OSError, ValueError, VerifyError, ...
            # on one line: a verification report spans several, between boilerplate lines
            why = " ".join(ln.strip() for ln in str(err).splitlines() if ln.strip() and not
                           ln.startswith(("Verification reported errors", "Note: astropy")))
            if "SIMPLE" in why:  # astropy's hint is for its API, not for a user of ours
                why = "no SIMPLE card at its start: not a FITS file, or a damaged one"
            raise InputError(f"{path}: not a readable FITS file ({why})") from None
        with hdul:
            yield hdul


def _first_image(hdul: fits.HDUList, path: str, name: str | None = None) -> tuple:
    if name is not None:
        if name not in hdul:
            raise InputError(f"{path}: no HDU named {name}")
        hdus = [hdul[name]]
    else:
        hdus = [h for h in hdul if isinstance(h, (fits.PrimaryHDU, fits.ImageHDU))]
    for h in hdus:
        try:
            data = h.data
        except Exception as err:
            raise InputError(f"{path}: cannot read image data ({err})") from None
        if data is not None and data.ndim == 2:
            return np.asarray(data, dtype=np.float64), h.header
    raise InputError(f"{path}: no 2-D image in the file")


def read_image(path: str, weight: str | None = None, mask: str | None = None) -> Image:
    """Read an image, its weight map and mask (HDUs ``WEIGHT`` / ``MASK`` or files)."""
    with open_input(path, "image") as hdul:
        data, header = _first_image(hdul, path)
        w = _first_image(hdul, path, "WEIGHT")[0] if "WEIGHT" in hdul else None
        m = _first_image(hdul, path, "MASK")[0] if "MASK" in hdul else None
    if weight is not None:
        with open_input(weight, "weight map") as h:
            w = _first_image(h, weight)[0]
    if mask is not None:
        with open_input(mask, "mask") as h:
            m = _first_image(h, mask)[0]
    for arr, what in ((w, "weight map"), (m, "mask")):
        if arr is not None and arr.shape != data.shape:
            raise InputError(f"{path}: {what} shape {arr.shape} differs from the image's "
                             f"{data.shape}")  # fmt: skip
    finite = np.isfinite(data)
    if not finite.any():
        raise InputError(f"{path}: empty image (no finite pixel)")
    if np.nanmax(data) == np.nanmin(data):
        raise InputError(f"{path}: empty image (all pixels equal {np.nanmax(data):g})")
    bad = ~finite
    if w is not None:
        bad |= ~(np.isfinite(w) & (w > 0))
    if m is not None:
        bad |= np.nan_to_num(m) != 0
    if bad.all():
        raise InputError(f"{path}: every pixel is masked or has zero weight")
    return Image(path=path, data=data, header=header, weight=w, bad=bad)


def read_positions(path: str, image_path: str) -> Table:
    """An input catalogue: ``x, y`` (0-based) or SExtractor's ``X_IMAGE, Y_IMAGE``."""
    try:
        t = Table.read(path)
    except FileNotFoundError:
        raise InputError(f"{path}: input catalogue not found") from None
    except Exception as err:
        raise InputError(f"{path}: cannot read the input catalogue ({err})") from None
    if len(t) == 0:
        raise InputError(f"{path}: empty input catalogue (for {image_path})")
    names = {c.lower(): c for c in t.colnames}
    if "x" in names and "y" in names:
        x, y = t[names["x"]], t[names["y"]]
    elif "x_image" in names and "y_image" in names:
        x, y = t[names["x_image"]] - 1.0, t[names["y_image"]] - 1.0  # FITS 1-based
    else:
        raise InputError(f"{path}: input catalogue needs columns x, y (0-based) or "
                         "X_IMAGE, Y_IMAGE (1-based)")  # fmt: skip
    out = Table()
    try:
        out["x"] = np.asarray(x, dtype=float)
        out["y"] = np.asarray(y, dtype=float)
    except (TypeError, ValueError) as err:
        raise InputError(f"{path}: the input catalogue's positions are not numbers "
                         f"({err})") from None  # fmt: skip
    for c in t.colnames:
        if c not in out.colnames:
            out[c] = t[c]
    lost = ~(np.isfinite(out["x"]) & np.isfinite(out["y"]))
    if lost.any():
        log.warning("%s: %d row(s) without a finite position (rows %s): kept, flagged "
                    "BAD_POSITION and not measured", path, int(lost.sum()),
                    ", ".join(map(str, np.flatnonzero(lost)[:5])) + (", ..." if lost.sum() > 5
                                                                     else ""))  # fmt: skip
    return out


# ----------------------------------------------------------------------------------------
# One image
# ----------------------------------------------------------------------------------------
#: where an input catalogue's row without a finite position is put (times its rank)
_NOWHERE = -1e7


def detect_objects(img: Image, cfg: Config, positions: Table | None):
    """Background-subtracted image, the object table (detections or input positions) and
    the :class:`~pylensfit.detection.Background`."""
    bkg = measure_background(img.data, mask=img.bad, weight=img.weight, box=cfg.background_box)
    det = detect(
        img.data, weight=img.weight, mask=img.bad, threshold=cfg.detect_threshold,
        min_area=cfg.detect_min_area, background=bkg, stamp_size=cfg.stamp_size,
    )  # fmt: skip
    sub = bkg.subtract(img.data)
    if positions is None:
        return sub, det, bkg
    # an input catalogue: its positions, with the detections' photometry where they match
    from scipy.spatial import cKDTree

    out = positions.copy()
    out["id"] = np.arange(1, len(out) + 1)
    # a row without a finite position: far off the image and from every other row, where
    # it is cut, paired and fitted with nothing (flagged BAD_POSITION by image_task)
    lost = ~(np.isfinite(out["x"]) & np.isfinite(out["y"]))
    out["no_position"] = lost
    out["x"][lost] = out["y"][lost] = _NOWHERE * np.arange(1, lost.sum() + 1)
    photometry = ("flux", "flux_err", "snr", "peak_snr", "r_half", "mag", "sep_flag")
    for c in photometry:
        out[c] = np.nan if c != "sep_flag" else 0
    rms = bkg.rms
    if len(det):
        d, j = cKDTree(np.column_stack([det["x"], det["y"]])).query(
            np.column_stack([out["x"], out["y"]]), distance_upper_bound=2.0
        )
        hit = np.isfinite(d)
        for c in photometry:
            out[c][hit] = det[c][j[hit]]
    out["noise_sigma"] = _noise_at(img, out["x"], out["y"], bkg, rms)
    return sub, out, bkg


def value_at(image: np.ndarray, x, y) -> np.ndarray:
    """``image`` at the pixels nearest ``(x, y)`` (clipped to the image)."""
    ix = np.clip(np.round(np.asarray(x)).astype(int), 0, image.shape[1] - 1)
    iy = np.clip(np.round(np.asarray(y)).astype(int), 0, image.shape[0] - 1)
    return np.asarray(image, dtype=float)[iy, ix]


def _noise_at(img: Image, x, y, bkg, rms_map) -> np.ndarray:
    if img.weight is not None:
        w = value_at(img.weight, x, y)
        return np.where(w > 0, 1.0 / np.sqrt(np.where(w > 0, w, 1.0)), np.nan)
    if rms_map is not None:
        return value_at(rms_map, x, y)
    return np.full(np.shape(x), float(bkg.global_rms))


def mask_saturated(img: Image, cfg: Config) -> np.ndarray:
    """Mask what no galaxy model fits, before the background, the detection and the fit.

    The pixels at or above the saturation level (``cfg.saturation``, else the image's
    ``SATURATE`` card: :func:`~pylensfit.detection.saturation_level`) and the non-finite
    ones are added to ``img.bad`` (in place), each grown by ``cfg.saturation_grow`` px.

    Parameters
    ----------
    img : Image
        The image; its ``bad`` map is updated.
    cfg : Config

    Returns
    -------
    numpy.ndarray
        Boolean ``(ny, nx)``: the saturated pixels, grown (the ``SATURATED`` flag's map).

    Raises
    ------
    InputError
        If no pixel is left unmasked.
    """
    level = saturation_level(img.header, cfg.saturation)
    sat = saturation_mask(img.data, level, cfg.saturation_grow)
    img.bad |= sat | grow_mask(~np.isfinite(img.data), cfg.saturation_grow)
    if img.bad.all():
        why = "" if level is None else f" or at or above the saturation level {level:g}"
        raise InputError(f"{img.path}: every pixel is masked, has zero weight, is not "
                         f"finite or lies within {cfg.saturation_grow} px of such{why}")
    if sat.any():
        log.info("%s: %d pixels at or above the saturation level %g (grown by %d px) "
                 "masked", img.path, int(sat.sum()), level, cfg.saturation_grow)  # fmt: skip
    return sat


# ----------------------------------------------------------------------------------------
# The public entry point
# ----------------------------------------------------------------------------------------
def as_list(v, n: int, name: str) -> list:
    if v is None:
        return [None] * n
    if isinstance(v, (str, os.PathLike)):
        v = [v]
    v = [None if p is None else str(p) for p in v]
    if len(v) != n:
        raise InputError(f"{name}: {len(v)} given for {n} images")
    return v


def _image_shapes(path: str, what: str) -> dict[str, tuple[int, ...]]:
    """The shapes of a FITS file's first 2-D image (key ``""``) and of its ``WEIGHT`` and
    ``MASK`` HDUs, from the headers: :func:`measure` opens every input this way before
    any work starts, so that a damaged file is reported at once, on one line naming it.

    Raises
    ------
    InputError
        A file that cannot be opened or is truncated (an HDU's data or header cut short:
        astropy reads what is there with a warning, and would leave the rest out or fail
        when the image's task runs), or one without a 2-D image.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # astropy's truncation warnings: reported below
        with open_input(path, what) as hdul:
            n = len(hdul)  # every header read
            size = hdul.fileinfo(0)["file"].size  # 0 where unknown: a compressed file
            end = 0
            for i in range(n):
                info = hdul.fileinfo(i)
                end = info["datLoc"] + info["datSpan"]
                if size and end > size:
                    raise InputError(f"{path}: truncated {what} file ({size} bytes, HDU {i} "
                                     f"ends at byte {end})")  # fmt: skip
                if not size:  # compressed: its data must be read to know it is all there
                    try:
                        _ = hdul[i].data
                    except Exception as err:
                        raise InputError(f"{path}: cannot read HDU {i} of the {what} file "
                                         f"({type(err).__name__}: {err})") from None  # fmt: skip
            if size and size > end and _not_blank(path, end):
                raise InputError(f"{path}: truncated {what} file ({size - end} bytes after "
                                 f"HDU {n - 1} are not a whole HDU)")  # fmt: skip
            shapes = {}
            for h in hdul:
                if (isinstance(h, (fits.PrimaryHDU, fits.ImageHDU)) and len(h.shape) == 2
                        and min(h.shape) > 0):  # fmt: skip
                    shapes.setdefault("", tuple(h.shape))
            for name in ("WEIGHT", "MASK"):
                if name in hdul:
                    h = hdul[name]
                    shapes[name] = tuple(h.shape) if isinstance(
                        h, (fits.PrimaryHDU, fits.ImageHDU)) else ()  # fmt: skip
    if "" not in shapes:
        raise InputError(f"{path}: no 2-D image in the file")
    return shapes


def _not_blank(path: str, start: int) -> bool:
    """Whether the bytes of ``path`` from ``start`` on are not all zeros or blanks (the
    padding some writers leave after the last HDU, which astropy reads past)."""
    with open(path, "rb") as fh:
        fh.seek(start)
        while chunk := fh.read(1 << 16):
            if chunk.strip(b"\0 "):
                return True
    return False


def check_inputs(images: list[str], weights: list, masks: list, stars: list[str]) -> None:
    """Open every input image, weight map, mask and star field before any work starts
    (:func:`_image_shapes`), and refuse an image given twice (its rows would be
    duplicated): one line naming the file and the problem."""
    first: dict[Any, str] = {}
    for p in images:
        st = os.stat(p)
        key = (st.st_dev, st.st_ino) if st.st_ino else os.path.normcase(os.path.realpath(p))
        if key in first:
            also = "" if first[key] == p else f" (the same file as {first[key]})"
            raise InputError(f"{p}: image given twice{also}; each image must be given once")
        first[key] = p
    for p, w, m in zip(images, weights, masks, strict=True):
        shapes = _image_shapes(p, "image")
        # a weight or mask file given replaces the image's own HDU (as read_image reads)
        for f, name, what in ((w, "WEIGHT", "weight map"), (m, "MASK", "mask")):
            if f is not None:
                shape = _image_shapes(f, what)[""]
            elif name in shapes:
                shape = shapes[name]
            else:
                continue
            if len(shape) != 2:
                raise InputError(f"{p}: its {name} HDU is not a 2-D image")
            if shape != shapes[""]:
                raise InputError(f"{f or p}: {what} shape {shape} differs from the image's "
                                 f"{shapes['']}" + (f" ({p})" if f else ""))  # fmt: skip
    for p in stars:
        _image_shapes(p, "star field")


def load_given(obj, cls, what: str):
    """``obj`` as it is, or read with ``cls.load`` if a path: one line naming the file if
    it is missing or not a ``what`` file."""
    if not isinstance(obj, (str, os.PathLike)):
        return obj
    if not Path(obj).exists():
        raise InputError(f"{obj}: file not found")
    try:
        return cls.load(obj)
    except (ValueError, KeyError, TypeError, AttributeError) as err:
        msg = str(err)
        raise InputError(msg if msg.startswith(str(obj)) else
                         f"{obj}: not a {what} file ({type(err).__name__}: {msg})") from None


def read_given_psfs(psf, images: list[str]) -> list[PSFResult | PSFModel] | None:
    """``measure``'s ``psf=`` as one :class:`PSFResult` (a constant PSF) or
    :class:`~pylensfit.psfmodel.PSFModel` (a PSF over the field, e.g. Piff's) per image
    (``None``: not given)."""
    if psf is None:
        return None
    single = isinstance(psf, (PSFResult, PSFModel, str, os.PathLike)) or (
        isinstance(psf, np.ndarray) and psf.ndim == 2)
    items = [psf] * len(images) if single else list(psf)
    if len(items) != len(images):
        raise InputError(f"psf: {len(items)} PSF(s) given for {len(images)} image(s)")
    out, cache = [], {}
    for item, img in zip(items, images, strict=True):
        if isinstance(item, ConstantPSF):
            item = item.psf
        if isinstance(item, (PSFResult, PSFModel)):
            out.append(item)
            continue
        key = str(item) if isinstance(item, (str, os.PathLike)) else id(item)
        if key not in cache:
            try:
                if isinstance(item, (str, os.PathLike)):
                    if not Path(item).exists():
                        raise InputError(f"{item}: PSF file not found")
                    model = read_psf_model(item)
                    cache[key] = model.psf if isinstance(model, ConstantPSF) else model
                else:
                    cache[key] = psf_from_image(item, source="psf=")
            except (PSFError, ImportError) as err:  # ImportError: piff not installed
                raise InputError(f"the PSF for {img}: {err}") from None
        out.append(cache[key])
    return out
