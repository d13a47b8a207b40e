"""PSF stars selected on the stellar locus of size against magnitude: :func:`select_stars`."""

from __future__ import annotations

import logging

import numpy as np

from ..flags import flag_value
from .inputs import SEP_FLAGS

log = logging.getLogger("pylensfit.detection")

#: SEP flags that disqualify an object as a PSF star
STAR_BAD_SEP = (
    SEP_FLAGS["OBJ_MERGED"]
    | SEP_FLAGS["OBJ_TRUNC"]
    | SEP_FLAGS["OBJ_SINGU"]
    | SEP_FLAGS["APER_TRUNC"]
    | SEP_FLAGS["APER_HASMASKED"]
    | SEP_FLAGS["APER_ALLMASKED"]
)


def star_candidates(catalogue, min_peak_snr: float, saturation: float | None,
                    exclude_flags: int | None, position_order: int):  # fmt: skip
    """:func:`select_stars`' step 1: ``(cand, r_half, snr, pos)``, the candidates (bool),
    their half-light radii and S/N (every row), and the positions ``(x, y)`` where the
    locus centre may follow them (None otherwise)."""

    def col(name, default=None):
        try:
            return np.asarray(catalogue[name], dtype=np.float64)
        except (KeyError, ValueError):
            if default is None:
                raise ValueError(f"catalogue has no column {name!r}") from None
            return default

    r_half = col("r_half")
    k = len(r_half)
    flux = col("flux")
    peak_snr = col("peak_snr")
    snr = col("snr", np.full(k, np.inf))
    with np.errstate(invalid="ignore"):
        cand = np.isfinite(r_half) & (r_half > 0) & (flux > 0) & (peak_snr >= min_peak_snr)
    for name, bits in (("sep_flag", STAR_BAD_SEP), ("flags", exclude_flags)):
        if name == "flags" and bits is None:
            bits = flag_value("EDGE", "MASKED", "BAD_PIXELS")
        try:
            values = np.asarray(catalogue[name]).astype(np.int64)
        except (KeyError, ValueError):
            continue
        cand &= (values & int(bits)) == 0
    if saturation is not None:
        raw = col("peak") + col("background", np.zeros(k))
        cand &= raw < saturation - 1e-5 * abs(saturation)
    pos = None
    if position_order > 0:
        xy = [col(c, np.full(k, np.nan)) for c in ("x", "y")]
        if np.all(np.isfinite(xy[0][cand])) and np.all(np.isfinite(xy[1][cand])):
            pos = xy

    return cand, r_half, snr, pos


def select_stars(catalogue, *, min_peak_snr: float = 30.0, column: str | None = None,
                 saturation: float | None = None, nsigma: float = 3.0, window: float = 0.05,
                 min_width: float = 0.003, min_stars: int = 3, exclude_flags: int | None = None,
                 min_fraction: float = 0.25, position_order: int = 2) -> np.ndarray:  # fmt: skip
    """Select PSF stars on the stellar locus of size against magnitude.

    Point sources all have the PSF's size whatever their flux: the candidates (bright,
    unflagged, unsaturated) whose ``log10 r_half`` lies within ``nsigma`` of the locus, a
    band found at the small-size end and whose centre follows the PSF's size over the
    image, are the stars (the steps are those of :mod:`pylensfit.detection`).

    Parameters
    ----------
    catalogue : astropy.table.Table or mapping of arrays
        Output of :func:`detect` (``r_half``, ``flux``, ``peak_snr``, and if present
        ``snr``, ``sep_flag``, ``flags``, ``peak``, ``background``, ``x``, ``y``).
    min_peak_snr : float, optional
        Minimum peak signal-to-noise ratio. Default 30 (paper section 2.4).
    column : str, optional
        Name of a user-supplied star column (bool, or int where nonzero means star) that
        overrides the selection: its values are returned as a boolean array.
    saturation : float, optional
        Saturation level of the raw image (image units, background included).
    nsigma : float, optional
        Half-width of the band in sigmas. Default 3.
    window : float, optional
        Half-width in dex of the window that finds the locus. Default 0.05 (12%).
    min_width : float, optional
        Smallest intrinsic width of the locus in dex. Default 0.003 (0.7%).
    min_stars : int, optional
        Fewest candidates needed to define a locus; with fewer, nothing is selected (said
        in the log at INFO level). Default 3.
    exclude_flags : int, optional
        Bits of ``flags`` that disqualify a star; default EDGE | MASKED | BAD_PIXELS.
    min_fraction : float, optional
        In ``(0, 1]``: the smallest count, relative to the densest window's, of the
        window that finds the locus. Default 0.25: the stars are found below compact
        galaxies up to four times as dense in size; a clump of fewer objects below them
        (hot pixels, cosmic rays) is passed over.
    position_order : int, optional
        Highest total degree in ``(x, y)`` of the locus centre. Default 2; 0 for a
        centre constant over the image.

    Returns
    -------
    numpy.ndarray
        Boolean array, True for the selected stars.
    """
    if column is not None:
        return column_stars(catalogue, column)
    if not 0.0 < min_fraction <= 1.0:
        raise ValueError(f"min_fraction must be in (0, 1], got {min_fraction}")
    cand, r_half, snr, pos = star_candidates(catalogue, min_peak_snr, saturation,
                                             exclude_flags, position_order)  # fmt: skip
    sel = np.zeros(len(r_half), dtype=bool)
    idx = np.flatnonzero(cand)
    if len(idx) < max(int(min_stars), 1):  # info: a caller says what it does instead
        log.info(
            "select_stars: %d candidate(s) with peak S/N >= %g, fewer than min_stars=%d: "
            "no star selected", len(idx), min_peak_snr, min_stars,
        )
        return sel
    s = np.log10(r_half[idx])
    with np.errstate(divide="ignore", invalid="ignore"):
        noise = np.where(snr[idx] > 0, 0.434 / snr[idx], np.inf)
    noise = np.nan_to_num(noise, nan=np.inf)
    member = locus_window(s, window, min_fraction, int(min_stars))
    design = None if pos is None else locus_design(pos[0][idx], pos[1][idx], position_order)
    sel[idx[locus_members(s, noise, member, design, nsigma, min_width)]] = True
    return sel


def column_stars(catalogue, column: str) -> np.ndarray:
    """The stars of a user-supplied column (bool, or int where nonzero means star)."""
    try:
        values = np.asarray(catalogue[column])
    except (KeyError, ValueError, IndexError):
        raise ValueError(f"star column {column!r} not in the catalogue") from None
    if values.dtype == bool:
        return values.copy()
    if np.issubdtype(values.dtype, np.integer):
        return values != 0
    raise ValueError(f"star column {column!r} must be bool or int, got {values.dtype}")


def locus_members(s: np.ndarray, noise: np.ndarray, member: np.ndarray,
                  design: np.ndarray | None, nsigma: float, min_width: float
                  ) -> np.ndarray:  # fmt: skip
    """The candidates on the locus (:func:`select_stars`, step 3): centre, width and
    membership iterated from the window's ``member`` until stable; ``s`` is
    ``log10 r_half``, ``noise`` its measurement noise and ``design`` the monomials of the
    positions (None: a centre constant over the image)."""
    centre = np.full(s.size, np.median(s[member]))
    settled = design is None  # the centre a polynomial in the position, where one is
    for _ in range(30):
        width = locus_width(s[member] - centre[member], noise[member], min_width)
        new = np.abs(s - centre) <= nsigma * np.hypot(width, noise)
        if not new.any() or (settled and np.array_equal(new, member)):
            break
        member = new
        if design is not None:
            centre = locus_centre(s, design, member, np.hypot(width, noise))
            settled = True
        else:
            centre[:] = np.median(s[member])
    return member


def locus_window(s: np.ndarray, window: float, min_fraction: float, min_stars: int
                  ) -> np.ndarray:  # fmt: skip
    """The members of the window ``[s0, s0 + 2 window]`` that finds the stellar locus
    (:func:`select_stars`, step 2)."""
    ss = np.sort(s)
    counts = np.searchsorted(ss, ss + 2 * window, side="right") - np.arange(ss.size)
    need = min(int(counts.max()), max(min_stars, min_fraction * counts.max()))
    first = ss[np.flatnonzero(counts >= need)[0]]
    near = np.flatnonzero((ss >= first) & (ss <= first + 2 * window))
    start = ss[near[np.argmax(counts[near])]]
    return (s >= start) & (s <= start + 2 * window)


def locus_design(x: np.ndarray, y: np.ndarray, order: int) -> np.ndarray:
    """``(n, p)`` monomials ``u^i v^j``, ``i + j <= order``, of the positions scaled to
    ``[-1, 1]`` over their range."""
    u = [(q - 0.5 * (q.max() + q.min())) / max(0.5 * np.ptp(q), 1.0) for q in (x, y)]
    return np.column_stack([u[0] ** i * u[1] ** (d - i)
                            for d in range(order + 1) for i in range(d, -1, -1)])  # fmt: skip


def locus_centre(s: np.ndarray, design: np.ndarray, member: np.ndarray, sigma: np.ndarray
                  ) -> np.ndarray:  # fmt: skip
    """The locus centre at every candidate: a polynomial in the position fitted to the
    members weighted by ``1 / sigma^2``, of the highest degree with 5 members a term
    (the members' median with fewer than 15)."""
    n = int(member.sum())
    p = design.shape[1]
    order = int(round((np.sqrt(8 * p + 1) - 3) / 2))  # p = (order + 1)(order + 2) / 2
    while order > 0 and n < 5 * (order + 1) * (order + 2) // 2:
        order -= 1
    if order == 0:
        return np.full(s.size, np.median(s[member]))
    p = (order + 1) * (order + 2) // 2
    w = 1.0 / sigma[member]
    coef = np.linalg.lstsq(design[member, :p] * w[:, None], s[member] * w, rcond=None)[0]
    return design[:, :p] @ coef


def locus_width(dev: np.ndarray, noise: np.ndarray, floor: float) -> float:
    """Smallest intrinsic width ``w >= floor`` with robust sigma of ``dev / hypot(w, noise)``
    at most 1 (the robust sigma falls as ``w`` grows, so bisect)."""

    def rsig(w):
        return 1.4826 * np.median(np.abs(dev) / np.hypot(w, noise))

    if rsig(floor) <= 1.0:
        return float(floor)
    lo, hi = floor, max(floor, 1.4826 * float(np.median(np.abs(dev))))
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if rsig(mid) <= 1.0 else (mid, hi)
    return float(hi)
