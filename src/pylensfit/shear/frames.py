"""The sky frames of a catalogue's rows and of its images, for the shear estimators.

A catalogue of :func:`pylensfit.measure` gives its shapes in the sky frame
(:mod:`pylensfit.skyframe`); its ``lnL`` grids are in each image's pixel frame.
:func:`table_frame` reads each row's frame, :func:`group_frames` gives one frame per
image and :func:`rows_frame` selects rows of a frame.
"""

from __future__ import annotations

import numpy as np
from astropy.table import Table

from ..skyframe import SkyFrame, frame_of_table


def table_frame(table: Table) -> tuple[SkyFrame | None, np.ndarray | None]:
    """The sky frame of each row of a catalogue and the rows' images (``image_index``),
    or ``(None, None)`` for a table in the pixel frame (no frame columns, or the pixel
    frame everywhere)."""
    need = ("sky_angle", "sky_flip", "wcs_g1", "wcs_g2", "image_index")
    if not all(c in table.colnames for c in need):
        return None, None
    fr = frame_of_table(table)
    if fr.is_identity():
        return None, None
    return fr, np.asarray(table["image_index"])


def rows_frame(frame: SkyFrame, sel: np.ndarray) -> SkyFrame:
    """The rows ``sel`` (a mask or indices) of a frame of several rows."""
    return SkyFrame(angle=frame.angle[sel], flip=frame.flip[sel], g1=frame.g1[sel],
                    g2=frame.g2[sel], has_wcs=frame.has_wcs[sel])  # fmt: skip


def group_frames(frame: SkyFrame, groups: np.ndarray) -> tuple[SkyFrame, np.ndarray]:
    """One :class:`~pylensfit.skyframe.SkyFrame` per group (its rows' median rotation and
    mean distortion; the flip of its first row), and the group index of each row."""
    keys, inv = np.unique(np.asarray(groups), return_inverse=True)
    k = keys.size
    ang, g1, g2 = np.zeros(k), np.zeros(k), np.zeros(k)
    flip = np.zeros(k, dtype=bool)
    for i in range(k):  # one entry per image, not per galaxy
        sel = inv == i
        ang[i] = np.median(np.asarray(frame.angle)[sel])
        flip[i] = bool(np.asarray(frame.flip)[sel][0])
        g1[i] = np.mean(np.asarray(frame.g1)[sel])
        g2[i] = np.mean(np.asarray(frame.g2)[sel])
    return SkyFrame(angle=ang, flip=flip, g1=g1, g2=g2, has_wcs=np.ones(k, bool)), inv
