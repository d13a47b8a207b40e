"""Objects with another object inside their postage stamp: :func:`close_pairs`, and the
pipeline's rule on them, :func:`flag_close_pairs`."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def close_pairs(
    x, y, *, flux=None, stamp_size: int = 32, faint_ratio: float | None = None
) -> np.ndarray:
    """Objects with another detected object inside their postage stamp (paper section 2.3).

    Object ``i`` and ``j`` are a close pair when ``|x_i - x_j| < stamp_size / 2`` and
    ``|y_i - y_j| < stamp_size / 2``; the paper rejects every such object. With
    ``faint_ratio`` (the improvement the paper's conclusions suggest), an object is kept
    when every neighbour in its stamp is fainter than ``faint_ratio`` times its own flux;
    the faint neighbours themselves are still flagged. Pairs are found with a KD-tree in
    the Chebyshev metric, so the cost grows as ``N log N``.

    Parameters
    ----------
    x, y : array_like
        Object positions in pixels.
    flux : array_like, optional
        Object fluxes; required with ``faint_ratio``.
    stamp_size : int, optional
        Postage-stamp side in pixels. Default 32 (the paper's).
    faint_ratio : float, optional
        In ``(0, 1]``; None (default) flags every member of a pair.

    Returns
    -------
    numpy.ndarray
        Boolean array, True for objects to reject as close pairs.
    """
    x = np.asarray(x, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    if x.shape != y.shape:
        raise ValueError(f"x and y differ in length: {x.size} and {y.size}")
    k = x.size
    out = np.zeros(k, dtype=bool)
    if faint_ratio is not None:
        if flux is None:
            raise ValueError("faint_ratio needs the fluxes (flux=...)")
        if not 0 < faint_ratio <= 1:
            raise ValueError(f"faint_ratio must be in (0, 1], got {faint_ratio}")
        flux = np.asarray(flux, dtype=np.float64).ravel()
        if flux.size != k:
            raise ValueError(f"flux has {flux.size} values for {k} positions")
    if k < 2:
        return out
    half = stamp_size / 2.0
    ok = np.isfinite(x) & np.isfinite(y)
    pos = np.flatnonzero(ok)
    if pos.size < 2:
        return out
    tree = cKDTree(np.column_stack([x[pos], y[pos]]))
    pairs = tree.query_pairs(half, p=np.inf, output_type="ndarray")
    if pairs.size == 0:
        return out
    i, j = pos[pairs[:, 0]], pos[pairs[:, 1]]
    strict = (np.abs(x[i] - x[j]) < half) & (np.abs(y[i] - y[j]) < half)
    i, j = i[strict], j[strict]
    if faint_ratio is None:
        out[i] = True
        out[j] = True
        return out
    # i is spoiled by j unless j is fainter than faint_ratio * flux_i (NaN spoils)
    with np.errstate(invalid="ignore"):
        i_spoiled = ~(flux[j] < faint_ratio * flux[i])
        j_spoiled = ~(flux[i] < faint_ratio * flux[j])
    out[i[i_spoiled]] = True
    out[j[j_spoiled]] = True
    return out


def flag_close_pairs(x, y, flux, snr, *, stamp_size: int, min_snr: float,
                     faint_ratio: float | None = None) -> np.ndarray:  # fmt: skip
    """The pipeline's ``CLOSE_PAIR`` rule: a significant object (``snr >= min_snr``) is a
    close pair when another significant one lies inside its stamp (with ``faint_ratio``,
    one not that much fainter, :func:`close_pairs`); a fainter object (often a noise
    peak) when anything does.

    Parameters
    ----------
    x, y, flux, snr : array_like
        ``(n,)`` positions (pixels), fluxes and S/N (NaN: not significant).
    stamp_size : int
        Postage-stamp side, pixels.
    min_snr : float
        The S/N from which an object makes another a close pair.
    faint_ratio : float, optional
        As :func:`close_pairs`' (None or 0: every significant pair).

    Returns
    -------
    numpy.ndarray
        Boolean, True for the close pairs.
    """
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    flux = np.asarray(flux, dtype=float)
    pair = close_pairs(x, y, flux=flux, stamp_size=stamp_size)
    sig = np.nan_to_num(np.asarray(snr, dtype=float)) >= min_snr
    pair[sig] = close_pairs(x[sig], y[sig], flux=flux[sig], stamp_size=stamp_size,
                            faint_ratio=faint_ratio or None)  # fmt: skip
    return pair
