"""An image's metacalibration columns (``Config.response = "metacal"``): each galaxy's
response measured on itself, with what a selection of each sheared branch cuts on.

Every galaxy fitted without a flag (``STAR`` aside: the branches decide for themselves)
whose largest stamp (``Config.largest_stamp``) lies in the image without bad pixels is
metacalibrated (:func:`pylensfit.metacal.metacal_fits`) on that stamp as its last fit saw
it, the neighbours' light and the sky's change taken out, about its fitted centre, with
the PSF the fit used: the image's, or, where the PSF varies, its cell's (the PSFs of its
cell's corners, the fits blended with its position's weights as the fit blends them,
:func:`pylensfit.likelihood.blend_fits`). The posterior means are those of the
measurement's priors (:func:`pylensfit.metacal.metacal_branches`). Each galaxy's added
noise field is drawn from ``(Config.metacal_seed, image index, row)``, and the
operation's matrix products run on one BLAS thread (a product's sums in one order): the
same input gives the same columns, bit for bit, in one run or a resumed one, in this
process or in workers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from threadpoolctl import threadpool_limits

from .. import flags as _flags
from ..calibration import Priors
from ..config import Config
from ..likelihood import blend_fits
from ..metacal import METACAL_TYPES, metacal_branches, metacal_fits
from ..psf import PSFResult, centre_on_stamp
from .image_psf import CellPSFs

__all__ = ["METACAL_BLOCK", "MetacalInputs", "empty_columns", "metacal_columns",
           "noise_fields", "store_branches"]

#: galaxies metacalibrated at a time (bounded memory: five images and their fits each)
METACAL_BLOCK = 256


@dataclass(frozen=True)
class MetacalInputs:
    """What :func:`metacal_columns` needs of one image's fits.

    Attributes
    ----------
    stamps : numpy.ndarray
        ``(n, N, N)`` every object's largest stamp (``N = Config.largest_stamp``),
        background subtracted, as it was cut.
    taken_out : numpy.ndarray or None
        ``(n, N, N)`` the light its last fit took out of it (the neighbours' models and
        the sky's change; zero where it was not refitted), or None for none.
    full : numpy.ndarray
        ``(n,)`` bool: the stamp lies in the image without bad pixels.
    cx, cy : numpy.ndarray
        ``(n,)`` the fitted centres in the stamps' pixels (element ``[y, x]``).
    noise : numpy.ndarray
        ``(n,)`` the per-pixel noise sigma (data units).
    todo : numpy.ndarray
        ``(n,)`` bool: the rows to metacalibrate (fitted, no flag but ``STAR``).
    """

    stamps: np.ndarray
    taken_out: np.ndarray | None
    full: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    noise: np.ndarray
    todo: np.ndarray


def noise_fields(seed: int, image_index: int, rows: np.ndarray, side: int) -> np.ndarray:
    """``(len(rows), side, side)`` unit-variance noise fields, each drawn from its own
    generator seeded by ``(seed, image_index, row)``: independent of the blocks."""
    out = np.empty((len(rows), side, side))
    for k, r in enumerate(rows):
        out[k] = np.random.default_rng([int(seed), int(image_index), int(r)]).standard_normal(
            (side, side))
    return out


def empty_columns(n: int) -> dict[str, np.ndarray]:
    """The metacalibration columns of ``n`` rows, none metacalibrated (NaN,
    ``NOT_METACALIBRATED``)."""
    cols = {c: np.full(n, np.nan) for c in ("e1_mcal", "e2_mcal", "R11", "R12", "R21", "R22")}
    cols.update({f"mcal_snr_{t}": np.full(n, np.nan) for t in METACAL_TYPES})
    cols["mcal_flags"] = np.full(n, _flags.METACAL_FLAGS["NOT_METACALIBRATED"][0], np.int32)
    return cols


def _psf_groups(rows: np.ndarray, psf: PSFResult, cells: CellPSFs | None):
    """``(rows, PSF images, weights (k, len(rows)))`` per group of ``rows`` fitted with
    the same PSFs: all of them with the image's PSF, or one group per cell."""
    if cells is None:
        return [(rows, [psf.image], np.ones((1, rows.size)))]
    out = []
    for c in np.unique(cells.cell[rows]):
        r = rows[cells.cell[rows] == c]
        out.append((r, [cells.images[k] for k in cells.nodes[:, r[0]]], cells.weights[:, r]))
    return out


def metacal_columns(inp: MetacalInputs, cfg: Config, priors: Priors, image_index: int,
                    psf: PSFResult | None, cells: CellPSFs | None) -> dict[str, np.ndarray]:
    """The metacalibration columns of an image's rows (the module docstring).

    Parameters
    ----------
    inp : MetacalInputs
        The image's stamps, fits and rows to metacalibrate.
    cfg : Config
        The measurement's configuration (``metacal_step``, ``metacal_seed``).
    priors : Priors
        The measurement's priors: the size prior of the fits, the ellipticity prior and
        bulge-fraction weights of the posterior means.
    image_index : int
        The image's index in the run (of the noise fields' seeds).
    psf, cells
        The image's PSF and, where it varies, its cells' (None: no PSF, nothing done).

    Returns
    -------
    dict of numpy.ndarray
        ``e1_mcal, e2_mcal, R11, R12, R21, R22``, ``mcal_snr_<type>`` per type of
        :data:`pylensfit.metacal.METACAL_TYPES` and ``mcal_flags``
        (:data:`pylensfit.flags.METACAL_FLAGS`), one entry per row, in the pixel frame.
    """
    n, side = inp.todo.size, inp.stamps.shape[-1]
    cols = empty_columns(n)
    rows = np.flatnonzero(inp.todo & inp.full & np.isfinite(inp.cx) & np.isfinite(inp.cy)
                          & np.isfinite(inp.noise) & (inp.noise > 0))  # fmt: skip
    if psf is None or not rows.size:
        return cols
    mcfg = cfg.replace(stamp_size=side, max_stamp_size=0)  # the whole stamp, one tier
    with threadpool_limits(limits=1, user_api="blas"):  # the same bits in any worker
        for grp, images, weights in _psf_groups(rows, psf, cells):
            _metacal_group(cols, inp, grp, images, weights, mcfg, priors, image_index)
    return cols


def _metacal_group(cols: dict[str, np.ndarray], inp: MetacalInputs, grp: np.ndarray,
                   images: list, weights: np.ndarray, mcfg: Config, priors: Priors,
                   image_index: int) -> None:  # fmt: skip
    """Metacalibrate the rows ``grp`` fitted with the PSF ``images`` (blended with
    ``weights``) in blocks, into ``cols``."""
    side = inp.stamps.shape[-1]
    for s0 in range(0, grp.size, METACAL_BLOCK):
        r, w = grp[s0 : s0 + METACAL_BLOCK], weights[:, s0 : s0 + METACAL_BLOCK]
        data = inp.stamps[r] if inp.taken_out is None else inp.stamps[r] - inp.taken_out[r]
        fields = noise_fields(mcfg.metacal_seed, image_index, r, side)
        per_psf = [metacal_fits(data, centre_on_stamp(p, side), inp.noise[r], config=mcfg,
                                size_prior=priors.size, step=mcfg.metacal_step,
                                noise_fields=fields, centres=(inp.cx[r], inp.cy[r]),
                                reconvolution=mcfg.metacal_reconvolution)
                   for p in images]  # fmt: skip
        fits = {t: per_psf[0][t] if len(per_psf) == 1 else
                blend_fits([f[t] for f in per_psf], w) for t in METACAL_TYPES}  # fmt: skip
        store_branches(cols, r, metacal_branches(fits, priors.ellipticity,
                                         bulge_weights=priors.bulge_weights,
                                         refine=mcfg.output_refine,
                                         step=mcfg.metacal_step))


def store_branches(cols: dict[str, np.ndarray], r: np.ndarray, br) -> None:
    """Write the branches ``br`` (:class:`pylensfit.metacal.MetacalBranches`) of rows
    ``r`` into ``cols`` (:func:`empty_columns`)."""
    cols["e1_mcal"][r], cols["e2_mcal"][r] = br.e["noshear"][:, 0], br.e["noshear"][:, 1]
    R = br.R
    for i in range(2):
        for j in range(2):
            cols[f"R{i + 1}{j + 1}"][r] = R[:, i, j]
    fl = np.zeros(r.size, dtype=np.int32)
    for t in METACAL_TYPES:
        cols[f"mcal_snr_{t}"][r] = br.snr[t]
        fl |= np.where(br.usable[t], 0, _flags.METACAL_FLAGS[t][0]).astype(np.int32)
    cols["mcal_flags"][r] = fl
