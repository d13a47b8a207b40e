"""Small helpers shared by the modules of the package.

Array checks (:func:`per_object`, :func:`check_egrid`, :func:`check_lnL`), the
``rfft2`` frequency grid and a Fourier-series peak finder shared by the PSF and
likelihood stages (:func:`rfft_frequencies`, :func:`newton_peak`), and the reading and
writing of the package's JSON files (:func:`read_json`, :func:`jsonable`,
:func:`json_kind`, :func:`other_file_hint`), the atomic write of every file the
package writes (:func:`atomic_write_with`), and the on-disk cache of arrays that take
long to build (:func:`disk_cached`).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "atomic_write",
    "atomic_write_with",
    "check_egrid",
    "check_lnL",
    "disk_cached",
    "json_kind",
    "jsonable",
    "newton_peak",
    "other_file_hint",
    "per_object",
    "read_json",
    "rfft_frequencies",
]


# ----------------------------------------------------------------------------------------
# Array checks
# ----------------------------------------------------------------------------------------
def per_object(value, n: int, name: str) -> np.ndarray:
    """A scalar or ``(n,)`` array as a fresh float ``(n,)`` array; wrong shapes raise."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        return np.full(n, float(arr))
    if arr.shape != (n,):
        raise ValueError(f"{name} must be a scalar or have shape ({n},), got {arr.shape}")
    return arr.copy()


def check_egrid(egrid: np.ndarray) -> np.ndarray:
    """An ellipticity grid as a float ``(n_e, 2)`` array, checked.

    Parameters
    ----------
    egrid : array_like
        Grid points ``(e1, e2)``.

    Returns
    -------
    numpy.ndarray
        ``egrid`` as float (not copied when it already is).

    Raises
    ------
    ValueError
        If the shape is not ``(n_e, 2)`` with ``n_e >= 2``, a value is not finite, or a
        point lies on or outside ``|e| = 1``.
    """
    egrid = np.asarray(egrid, dtype=float)
    if egrid.ndim != 2 or egrid.shape[1] != 2 or egrid.shape[0] < 2:
        raise ValueError(f"ellipticity grid must have shape (n_e, 2), got {egrid.shape}")
    if not np.all(np.isfinite(egrid)):
        raise ValueError("ellipticity grid contains non-finite values")
    if np.any(np.hypot(egrid[:, 0], egrid[:, 1]) >= 1.0):
        raise ValueError("ellipticity grid points must lie inside |e| < 1")
    return egrid


def check_lnL(lnL: np.ndarray, egrid: np.ndarray) -> np.ndarray:
    """Likelihood rows ``lnL (n_gal, n_e)`` on the grid ``egrid``, checked.

    Parameters
    ----------
    lnL : array_like
        ``ln L`` of each galaxy at each grid point.
    egrid : numpy.ndarray
        The ``(n_e, 2)`` grid (as returned by :func:`check_egrid`).

    Returns
    -------
    numpy.ndarray
        ``lnL``, cast to float if it is not of a floating type.

    Raises
    ------
    ValueError
        If ``lnL`` is not 2-D or its columns do not match the grid's points.
    """
    lnL = np.asarray(lnL)
    if lnL.ndim != 2:
        raise ValueError(f"lnL must be a 2-D array (n_gal, n_e), got {lnL.ndim} dimension(s)")
    if lnL.shape[1] != egrid.shape[0]:
        raise ValueError(
            f"lnL has {lnL.shape[1]} columns but the ellipticity grid has {egrid.shape[0]} "
            "points: each row must be ln L on that grid"
        )
    if not np.issubdtype(lnL.dtype, np.floating):
        lnL = lnL.astype(float)
    return lnL


# ----------------------------------------------------------------------------------------
# Fourier grids
# ----------------------------------------------------------------------------------------
def rfft_frequencies(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Angular frequencies and Hermitian weights of ``numpy.fft.rfft2`` on ``n x n``.

    Returns
    -------
    kx, ky, w : numpy.ndarray
        Arrays of shape ``(n, n // 2 + 1)``: ``kx``, ``ky`` in radians per pixel and the
        weight ``w`` (1 or 2) with which each half-plane frequency stands for the full
        plane in a sum of an even function of ``k``.
    """
    kx1 = 2 * np.pi * np.fft.rfftfreq(n)
    ky1 = 2 * np.pi * np.fft.fftfreq(n)
    kx, ky = np.meshgrid(kx1, ky1, indexing="xy")
    w = np.full(kx.shape, 2.0)
    w[:, 0] = 1.0
    if n % 2 == 0:
        w[:, -1] = 1.0
    return kx, ky, w


def newton_peak(D: np.ndarray, R: np.ndarray, X: np.ndarray, Y: np.ndarray, n_steps: int = 6):
    """Maximise ``h(X) = sum_x s(x + X) r(x)`` by Newton steps on its Fourier series.

    ``D`` and ``R`` are ``rfft2`` transforms phase-referenced to the centre of the
    (odd) ``big x big`` frame. Steps longer than a pixel or at a point of non-negative
    curvature are refused. Returns the peak and whether the curvature there is negative.
    """
    big = D.shape[-2]
    kx, ky, w = rfft_frequencies(big)
    kx1, ky1 = kx[0], ky[:, 0]  # kx varies along the columns, ky along the rows
    base = D * np.conj(R) * (w / big**2)
    X = X.astype(float)
    Y = Y.astype(float)
    for _ in range(n_steps):
        # the phase ramp is separable: one exp per row and per column, not per frequency
        ex = np.exp(1j * kx1[None, :] * X[:, None])
        ey = np.exp(1j * ky1[None, :] * Y[:, None])
        Dp = base * ey[:, :, None] * ex[:, None, :]
        re, im = Dp.real, Dp.imag
        re_x = re @ kx1  # (n, rows): sums over the columns weighted by kx
        gx = -(im @ kx1).sum(axis=1)
        hxx = -(re @ (kx1 * kx1)).sum(axis=1)
        gy = -(im.sum(axis=2) @ ky1)
        hyy = -(re.sum(axis=2) @ (ky1 * ky1))
        hxy = -(re_x @ ky1)
        det = hxx * hyy - hxy * hxy
        good = (hxx < 0) & (det > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            sx = np.where(good, (hxy * gy - hyy * gx) / det, 0.0)
            sy = np.where(good, (hxy * gx - hxx * gy) / det, 0.0)
        ok = good & (np.hypot(sx, sy) < 1.0)
        X = np.where(ok, X + sx, X)
        Y = np.where(ok, Y + sy, Y)
    return X, Y, good


# ----------------------------------------------------------------------------------------
# JSON files
# ----------------------------------------------------------------------------------------
def json_kind(obj: Any) -> str:
    """The JSON name of ``obj``'s type (``"list"``, ``"number"``, ...).

    Parameters
    ----------
    obj : object
        A value decoded from JSON.

    Returns
    -------
    str
        ``"list"``, ``"string"``, ``"null"``, ``"number"`` or ``"boolean"``; the Python
        type's name for anything else.
    """
    if isinstance(obj, list):
        return "list"
    if isinstance(obj, str):
        return "string"
    if obj is None:
        return "null"
    if isinstance(obj, (bool, int, float)):
        return "number" if not isinstance(obj, bool) else "boolean"
    return type(obj).__name__


def other_file_hint(d: dict, kinds: dict[str, str]) -> str:
    """What a JSON object holds, for an error message about a file of the wrong kind.

    Parameters
    ----------
    d : dict
        The decoded JSON object.
    kinds : dict
        Entry name -> the kind of file that holds it (``{"priors": "priors"}``).

    Returns
    -------
    str
        ``"; it holds 'priors': a priors file?"`` where ``d`` holds the entry of one of
        ``kinds``; else the first entries it holds, or ``"; it is empty"``.
    """
    for key, kind in kinds.items():
        if key in d:
            return f"; it holds {key!r}: a {kind} file?"
    keys = ", ".join(repr(str(k)) for k in list(d)[:4]) + (", ..." if len(d) > 4 else "")
    return f"; it holds {keys}" if d else "; it is empty"


def read_json(path: str | Path) -> Any:
    """The content of the JSON file ``path``.

    Parameters
    ----------
    path : str or pathlib.Path
        The file.

    Returns
    -------
    object
        The decoded content.

    Raises
    ------
    ValueError
        One line naming the file: it cannot be read, or it is not JSON.
    """
    try:
        text = Path(path).read_text()
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not JSON (not a text file)") from None
    except OSError as err:
        raise ValueError(f"{path}: cannot read ({err.strerror or err})") from None
    if not text.strip():
        raise ValueError(f"{path}: not JSON (empty file)")
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not JSON ({err.msg} at line {err.lineno} column "
                         f"{err.colno})") from None  # fmt: skip


def jsonable(obj: Any) -> Any:
    """``obj`` with numpy arrays and scalars made Python lists and numbers, for JSON.

    Parameters
    ----------
    obj : object
        Nested dicts, lists and tuples of numbers, strings and numpy values.

    Returns
    -------
    object
        The same structure with string keys, lists for tuples and arrays, and ``None``
        for non-finite floats (JSON has no infinity or NaN).
    """
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None  # JSON has no infinity
    return obj


def read_json_entry(path: str | Path, key: str, what: str, others: dict[str, str]) -> Any:
    """The entry ``key`` of the JSON object in the file ``path``.

    Parameters
    ----------
    path : str or pathlib.Path
        The file.
    key : str
        The entry that a file of this kind holds (``"priors"``).
    what : str
        The kind of file, for the message (``"priors"``).
    others : dict
        Entry name -> the kind of file that holds it, to say which file it may be instead.

    Returns
    -------
    object
        ``content[key]``.

    Raises
    ------
    ValueError
        One line naming the file: unreadable, not JSON, or without the entry.
    """
    d = read_json(path)
    if not isinstance(d, dict) or key not in d:
        detail = (f"a JSON {json_kind(d)}" if not isinstance(d, dict)
                  else f"no {key!r} entry" + other_file_hint(d, others))  # fmt: skip
        raise ValueError(f"{path}: not a {what} file ({detail})")
    return d[key]


# ----------------------------------------------------------------------------------------
# Files
# ----------------------------------------------------------------------------------------
def new_file_mode() -> int:
    """The permissions a new file gets under the process's umask (``0o666 & ~umask``).

    Read from ``/proc/self/status`` where the kernel reports it (no change of the
    process-wide umask, so safe under threads), else by setting and restoring it.
    """
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


def atomic_write_with(write: Callable[[str], None], path: str | Path, *,
                      overwrite: bool = False) -> None:  # fmt: skip
    """Write ``path`` through a temporary file beside it, renamed when complete.

    ``write(tmp)`` writes the content to the temporary file's name. A run killed while
    writing leaves no partial file under ``path``; the file gets the permissions of the
    user's umask (a temporary file is created readable by its owner only).

    Raises
    ------
    FileExistsError
        If ``path`` exists and ``overwrite`` is false.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: output exists (pass overwrite=True to replace it)")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, new_file_mode())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write(hdulist, path: str | Path, *, overwrite: bool = False) -> None:
    """Write a FITS HDU list to ``path`` through a temporary file renamed when complete
    (:func:`atomic_write_with`): a run killed while writing leaves no partial file under
    ``path``, and the file gets the permissions of the user's umask.

    Raises
    ------
    FileExistsError
        If ``path`` exists and ``overwrite`` is false.
    """
    atomic_write_with(lambda tmp: hdulist.writeto(tmp, overwrite=True), path,
                      overwrite=overwrite)  # fmt: skip


# ----------------------------------------------------------------------------------------
# The on-disk cache of built arrays
# ----------------------------------------------------------------------------------------
#: environment variable naming the folder of :func:`disk_cached`'s arrays; empty or
#: ``"off"``: no cache on disk
CACHE_ENV = "PYLENSFIT_CACHE_DIR"
#: the most bytes :func:`disk_cached` keeps: the least recently used arrays go first
CACHE_MAX_BYTES = 2 * 2**30


def cache_dir() -> Path | None:
    """The folder of :func:`disk_cached`'s arrays: ``$PYLENSFIT_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/pylensfit`` (``~/.cache/pylensfit``); ``None`` where the variable
    is set empty or to ``"off"``."""
    given = os.environ.get(CACHE_ENV)
    if given is not None:
        return None if given.strip() in ("", "off", "0") else Path(given).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join("~", ".cache")
    return Path(base).expanduser() / "pylensfit"


_SOURCE_DIGEST: list[str] = []


def _source_digest() -> str:
    """A digest of every source file of the package and of the versions of the
    libraries that compute with it: a cached array is reused only by the same code."""
    if not _SOURCE_DIGEST:
        h = hashlib.sha256()
        for f in sorted(Path(__file__).resolve().parent.rglob("*.py")):
            h.update(f.as_posix().encode() + b"\0" + f.read_bytes())
        for mod in ("numpy", "scipy", "numba"):
            h.update(f"{mod} {getattr(sys.modules.get(mod), '__version__', '')}".encode())
        _SOURCE_DIGEST.append(h.hexdigest())
    return _SOURCE_DIGEST[0]


def disk_cached(name: str, key: tuple, build: Callable[[], np.ndarray]) -> np.ndarray:
    """``build()``, kept on disk under :func:`cache_dir` for the next process to read.

    An array that takes seconds to build (a model bank: 10-40 s per process and stamp
    tier, paid again by every worker of a pool) is read back instead, the same to the
    last bit: the file is keyed by ``name``, ``repr(key)`` and a digest of the package's
    source and of the numpy, scipy and numba versions. Written atomically (a reader sees
    a whole file or none); a file that cannot be read is built again, and a folder that
    cannot be written leaves the array uncached. The least recently used files go once
    the folder holds more than :data:`CACHE_MAX_BYTES`.

    Parameters
    ----------
    name : str
        What the array is (a file-name prefix).
    key : tuple
        Everything the array depends on besides the package's code (its ``repr`` is
        hashed).
    build : callable
        Builds the array.

    Returns
    -------
    numpy.ndarray
        The array, read-only.
    """
    folder = cache_dir()
    path = None
    if folder is not None:
        digest = hashlib.sha256(f"{name}\0{key!r}\0{_source_digest()}".encode()).hexdigest()
        path = folder / f"{name}-{digest[:32]}.npy"
        try:
            out = np.load(path, allow_pickle=False)
            os.utime(path)  # recently used
            out.setflags(write=False)
            return out
        except (OSError, ValueError, EOFError):
            pass
    out = build()
    if path is not None:
        try:
            atomic_write_with(lambda tmp: _save_npy(tmp, out), path, overwrite=True)
            _evict(folder, CACHE_MAX_BYTES)
        except OSError:
            pass
    out.setflags(write=False)
    return out


def _save_npy(path: str, array: np.ndarray) -> None:
    """``array`` in ``.npy`` format at ``path`` exactly (no suffix added)."""
    with open(path, "wb") as fh:
        np.save(fh, array, allow_pickle=False)


def _evict(folder: Path, max_bytes: int) -> None:
    """Delete the least recently used ``.npy`` files of ``folder`` beyond ``max_bytes``."""
    files = []
    for f in folder.glob("*.npy"):
        try:
            st = f.stat()
        except OSError:
            continue
        files.append((st.st_mtime, st.st_size, f))
    total = sum(s for _, s, _ in files)
    for _, size, f in sorted(files, key=lambda t: t[0]):
        if total <= max_bytes:
            break
        try:
            f.unlink()
            total -= size
        except OSError:
            pass
