"""Shapes in the sky frame: the local Jacobian of an image's WCS at each object.

The likelihood is computed in the pixel frame of each image. A survey combines
images of different orientations and correlates shears on the sky, so the catalogue
gives ``e1, e2`` in the **sky frame** that TreeCorr uses for RA/Dec catalogues: the
local frame with north up and west to the right, i.e. axes (W, N). In it ``e`` is
positive real for an object elongated east-west, negative real north-south, positive
imaginary along NW-SE and negative imaginary along NE-SW. TreeCorr reads the
catalogue's ``ALPHA_J2000``, ``DELTA_J2000``, ``e1``, ``e2`` with its defaults (no
``flip_g1`` or ``flip_g2``); a code in the IAU convention (x east, y north, position
angles from north through east) needs ``e2`` negated.

With the usual north-up, east-left WCS (``CD = [[-s, 0], [0, s]]``) the pixel frame
is the sky frame. In general the local Jacobian ``J = d(W, N)/d(x, y)`` at an object is
decomposed as ``J = a R(theta) S F``: ``F = diag(1, -1)`` when the WCS is a mirror
image (``det J < 0``), ``S`` the area-preserving shear matrix of a small reduced shear
``g_wcs`` (the WCS's distortion), ``R(theta)`` a rotation and ``a`` the pixel scale. A
pixel-frame ellipticity ``e`` is mapped exactly as the ellipse it describes::

    e -> conj(e) (if flipped) -> (e + g_wcs) / (1 + conj(g_wcs) e) -> e exp(2 i theta)

and the spin-2 second moments (covariance, sensitivities) by the rotation and flip.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from astropy.wcs import WCS, FITSFixedWarning

__all__ = [
    "SkyFrame",
    "local_frame",
    "pixel_frame",
    "to_sky",
    "covariance_to_sky",
    "frame_of_table",
    "jacobian_frame",
    "sensitivity_to_sky",
    "shear_to_pixel",
    "wcs_from_header",
]


@dataclass(frozen=True)
class SkyFrame:
    """The sky frame at each of ``n`` objects, relative to their image's pixel frame.

    Attributes
    ----------
    angle : numpy.ndarray
        ``(n,)`` rotation ``theta`` from the (flipped) pixel axes to the (W, N) axes, in
        degrees, counter-clockwise.
    flip : numpy.ndarray
        ``(n,)`` bool, the WCS is a mirror image (``det J < 0``).
    g1, g2 : numpy.ndarray
        ``(n,)`` the WCS's local distortion as a reduced shear, in the flipped pixel
        frame (0 for a conformal WCS).
    has_wcs : numpy.ndarray
        ``(n,)`` bool; where False the frame is the pixel frame (angle 0, no flip).
    """

    angle: np.ndarray
    flip: np.ndarray
    g1: np.ndarray
    g2: np.ndarray
    has_wcs: np.ndarray

    @property
    def n(self) -> int:
        """Number of objects."""
        return int(np.size(self.angle))

    def take(self, idx) -> SkyFrame:
        """The frames of the objects ``idx`` (an index array, boolean mask or slice)."""
        return SkyFrame(*(np.asarray(getattr(self, a))[idx]
                          for a in ("angle", "flip", "g1", "g2", "has_wcs")))  # fmt: skip

    def is_identity(self, tol: float = 1e-9) -> bool:
        """Whether the sky frame is the pixel frame everywhere (to ``tol``)."""
        return bool(not np.any(self.flip) and np.all(np.abs(np.radians(self.angle)) < tol)
                    and np.all(np.hypot(self.g1, self.g2) < tol))  # fmt: skip


def pixel_frame(n: int) -> SkyFrame:
    """The pixel frame for ``n`` objects (no WCS)."""
    z = np.zeros(n)
    return SkyFrame(angle=z, flip=np.zeros(n, bool), g1=z.copy(), g2=z.copy(),
                    has_wcs=np.zeros(n, bool))  # fmt: skip


def frame_of_table(table) -> SkyFrame:
    """The sky frame of each row of a catalogue, from its ``sky_angle``, ``sky_flip``,
    ``wcs_g1``, ``wcs_g2`` columns (the pixel frame for a table without them)."""
    if "sky_angle" not in table.colnames:
        return pixel_frame(len(table))
    col = lambda c: np.nan_to_num(np.asarray(table[c], dtype=float))  # noqa: E731
    has = (np.isfinite(np.asarray(table["ALPHA_J2000"], dtype=float))
           if "ALPHA_J2000" in table.colnames else np.ones(len(table), bool))  # fmt: skip
    return SkyFrame(angle=col("sky_angle"), flip=np.asarray(table["sky_flip"], dtype=bool),
                    g1=col("wcs_g1"), g2=col("wcs_g2"), has_wcs=has)


def wcs_from_header(header):
    """The celestial WCS of a FITS header, or None (no WCS or an unreadable one)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FITSFixedWarning)
        try:
            w = WCS(header, naxis=2)
        except Exception:
            return None
    return w if w.has_celestial else None


def _jacobian(wcs, x: np.ndarray, y: np.ndarray, h: float = 0.5) -> np.ndarray:
    """``d(W, N)/d(x, y)`` in degrees per pixel, ``(n, 2, 2)``, by central differences."""
    pts = [(x + h, y), (x - h, y), (x, y + h), (x, y - h)]
    rd = [np.asarray(wcs.all_pix2world(px, py, 0), dtype=float) for px, py in pts]
    _, dec0 = np.asarray(wcs.all_pix2world(x, y, 0), dtype=float)
    cosd = np.cos(np.radians(dec0))

    def offsets(a, b):
        dra = (a[0] - b[0] + 180.0) % 360.0 - 180.0
        return -dra * cosd / (2 * h), (a[1] - b[1]) / (2 * h)  # west, north

    wx, nx = offsets(rd[0], rd[1])
    wy, ny = offsets(rd[2], rd[3])
    J = np.empty((x.size, 2, 2))
    J[:, 0, 0], J[:, 0, 1], J[:, 1, 0], J[:, 1, 1] = wx, wy, nx, ny
    return J


def jacobian_frame(jacobian) -> SkyFrame:
    """The sky frame of local Jacobians ``J = d(W, N)/d(x, y)`` (any units).

    ``J`` is decomposed as ``a R(theta) S F`` (module docstring); a Jacobian that is not
    finite or is singular gives the pixel frame.

    Parameters
    ----------
    jacobian : array_like
        ``(n, 2, 2)``.

    Returns
    -------
    SkyFrame
    """
    J = np.asarray(jacobian, dtype=float).reshape(-1, 2, 2)
    out = pixel_frame(J.shape[0])
    fin = np.isfinite(J).all(axis=(1, 2))
    J = np.where(fin[:, None, None], J, np.eye(2))
    det = np.linalg.det(J)
    good = fin & (det != 0)
    flip = det < 0
    K = J.copy()
    K[:, :, 1] *= np.where(flip, -1.0, 1.0)[:, None]  # K = J F: det K > 0
    # K = R(theta) P with P symmetric positive definite (polar decomposition)
    theta = np.arctan2(K[:, 1, 0] - K[:, 0, 1], K[:, 0, 0] + K[:, 1, 1])
    c, s = np.cos(theta), np.sin(theta)
    p00 = c * K[:, 0, 0] + s * K[:, 1, 0]
    p11 = -s * K[:, 0, 1] + c * K[:, 1, 1]
    p01 = 0.5 * (c * K[:, 0, 1] + s * K[:, 1, 1] - s * K[:, 0, 0] + c * K[:, 1, 0])
    tr = p00 + p11
    # P / (tr / 2) = [[1 + g1, g2], [g2, 1 - g1]] to first order; exactly, the reduced
    # shear g of P has |g| = (l1 - l2) / (l1 + l2) for its eigenvalues l1 >= l2
    g1, g2 = (p00 - p11) / tr, 2 * p01 / tr
    return SkyFrame(angle=np.where(good, np.degrees(theta), out.angle),
                    flip=np.where(good, flip, out.flip), g1=np.where(good, g1, out.g1),
                    g2=np.where(good, g2, out.g2), has_wcs=good)  # fmt: skip


def local_frame(wcs, x, y) -> SkyFrame:
    """The sky frame at pixel positions ``x, y`` (0-based) of an image with ``wcs``.

    Parameters
    ----------
    wcs : astropy.wcs.WCS or None
        The image's celestial WCS (:func:`wcs_from_header`); None gives the pixel frame.
    x, y : array_like
        Positions in 0-based pixels; NaN positions get the pixel frame.

    Returns
    -------
    SkyFrame
    """
    x = np.atleast_1d(np.asarray(x, dtype=float))
    y = np.atleast_1d(np.asarray(y, dtype=float))
    out = pixel_frame(x.size)
    ok = np.isfinite(x) & np.isfinite(y)
    if wcs is None or not ok.any():
        return out
    fr = jacobian_frame(_jacobian(wcs, x[ok], y[ok]))
    idx = np.flatnonzero(ok)
    parts = []
    for a in ("angle", "flip", "g1", "g2", "has_wcs"):
        v = np.asarray(getattr(out, a)).copy()
        v[idx] = getattr(fr, a)
        parts.append(v)
    return SkyFrame(*parts)


def _phase(frame: SkyFrame) -> np.ndarray:
    return np.exp(2j * np.radians(np.asarray(frame.angle, dtype=float)))


def to_sky(e1, e2, frame: SkyFrame) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-frame ellipticities (or shears) ``e1, e2`` in the sky frame ``frame``.

    The exact map of the ellipse (module docstring): flip, the WCS's distortion as a
    reduced shear (Mobius composition), rotation by ``2 theta``.
    """
    e = np.asarray(e1, dtype=float) + 1j * np.asarray(e2, dtype=float)
    e = np.where(frame.flip, np.conj(e), e)
    g = np.asarray(frame.g1, dtype=float) + 1j * np.asarray(frame.g2, dtype=float)
    with np.errstate(invalid="ignore"):  # NaN shapes (objects not measured) stay NaN
        e = (e + g) / (1.0 + np.conj(g) * e) * _phase(frame)
    return e.real, e.imag


def shear_to_pixel(g1, g2, frame: SkyFrame) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of :func:`to_sky`: a sky-frame shear in each object's pixel frame."""
    e = (np.asarray(g1, dtype=float) + 1j * np.asarray(g2, dtype=float)) / _phase(frame)
    g = np.asarray(frame.g1, dtype=float) + 1j * np.asarray(frame.g2, dtype=float)
    with np.errstate(invalid="ignore"):
        e = (e - g) / (1.0 - np.conj(g) * e)
    e = np.where(frame.flip, np.conj(e), e)
    return e.real, e.imag


def spin2_matrix(frame: SkyFrame) -> np.ndarray:
    """``(n, 2, 2)`` linear map of spin-2 components, pixel to sky: ``R(2 theta) F``."""
    t = 2 * np.radians(np.asarray(frame.angle, dtype=float))
    c, s = np.cos(t), np.sin(t)
    f = np.where(frame.flip, -1.0, 1.0)
    M = np.empty((c.size, 2, 2))
    M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1] = c, -s * f, s, c * f
    return M


def covariance_to_sky(v11, v22, v12, frame: SkyFrame) -> tuple[np.ndarray, ...]:
    """A pixel-frame covariance of ``(e1, e2)`` in the sky frame: ``M C M^T``."""
    M = spin2_matrix(frame)
    C = np.empty((M.shape[0], 2, 2))
    C[:, 0, 0], C[:, 1, 1] = v11, v22
    C[:, 0, 1] = C[:, 1, 0] = v12
    out = M @ C @ np.transpose(M, (0, 2, 1))
    return out[:, 0, 0], out[:, 1, 1], out[:, 0, 1]


def sensitivity_to_sky(s1, s2, frame: SkyFrame) -> tuple[np.ndarray, np.ndarray]:
    """The diagonal shear responses ``d<e_i>/dg_i`` in the sky frame (``M R M^T``'s
    diagonal, the pixel-frame response ``R`` taken as diagonal)."""
    out = covariance_to_sky(s1, s2, np.zeros_like(np.asarray(s1, dtype=float)), frame)
    return out[0], out[1]
