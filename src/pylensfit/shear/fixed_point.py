"""The shear of a sample as a fixed point: the prior sheared until the posterior means
average to the shear (docs: method, eq-fixed-point).

:func:`shear_fixed_point` solves ``sum_a <e>_a(P_g) = N g`` by Newton steps, in the
pixel frame or, image by image, in the sky frame; :class:`ShearEstimate` is the result
of every shear estimator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..grid import DEFAULT_REFINE, refined_grid
from ..prior import Prior, usable_rows
from ..skyframe import SkyFrame, shear_to_pixel, spin2_matrix, to_sky
from .frames import group_frames, rows_frame
from .posterior import check_inputs
from .reduced import sheared_prior_columns
from .sums import sums_with


@dataclass(frozen=True)
class ShearEstimate:
    """Shear of a sample (docs: method, eq-key2 and eq-fixed-point).

    Attributes
    ----------
    g1, g2 : float
        Reduced shear estimates (dimensionless).
    g1_err, g2_err : float
        Their 1-sigma statistical errors, ``std(<e_i>) sqrt(N) / sum_a sens_i``.
    n : int
        Number of galaxies used.
    """

    g1: float
    g2: float
    g1_err: float
    g2_err: float
    n: int


def _fixed_point_terms(lnL, egrid, prior, grid, g, refine, block_size, w):
    """Posterior means ``(n, 2)`` under the prior sheared by ``g`` and the weighted sum
    of their Jacobians ``d<e_i>/dg_j`` (``(2, 2)``)."""
    P, d1, d2 = sheared_prior_columns(prior, grid, g)
    e1, e2 = grid[:, 0], grid[:, 1]
    K = np.column_stack([P, e1 * P, e2 * P, d1, e1 * d1, e2 * d1, d2, e1 * d2, e2 * d2])
    S = sums_with(lnL, egrid, K, refine, block_size)
    s0 = S[:, 0]
    m1, m2 = S[:, 1] / s0, S[:, 2] / s0
    # d<e_i>/dg_j = sum (e_i - <e_i>) L dP_g/dg_j / sum P_g L
    terms = ((S[:, 4] - m1 * S[:, 3]) / s0, (S[:, 7] - m1 * S[:, 6]) / s0,
             (S[:, 5] - m2 * S[:, 3]) / s0, (S[:, 8] - m2 * S[:, 6]) / s0)  # fmt: skip
    if w is None:
        jac = np.array([[np.sum(terms[0]), np.sum(terms[1])],
                        [np.sum(terms[2]), np.sum(terms[3])]])  # fmt: skip
    else:
        jac = np.array([[w @ terms[0], w @ terms[1]], [w @ terms[2], w @ terms[3]]])
    return np.column_stack([m1, m2]), jac


class _ImageFrames(NamedTuple):
    """The pixel frames of a sample's images, for the fixed point in the sky frame."""

    #: one frame per image (:func:`~pylensfit.shear.frames.group_frames`)
    frames: SkyFrame
    #: ``(n,)`` the image of each row
    index: np.ndarray
    #: ``(n_images, 2, 2)`` each image's spin-2 rotation (:func:`pylensfit.skyframe.spin2_matrix`)
    spin2: np.ndarray
    #: each row with its image's frame
    rows: SkyFrame


def _image_frames(frame: SkyFrame | None, groups: np.ndarray | None,
                  ok: np.ndarray) -> _ImageFrames | None:  # fmt: skip
    """The frames of the images ``groups`` of the rows ``ok``; None in the pixel frame."""
    if frame is None or frame.is_identity():
        return None
    if groups is None:
        raise ValueError("a sky frame needs the groups (images) that share a pixel frame")
    gf, inv = group_frames(frame, np.asarray(groups)[ok])
    return _ImageFrames(gf, inv, spin2_matrix(gf), rows_frame(gf, inv))


@dataclass(frozen=True)
class _FixedPoint:
    """The equation ``f(g) = sum_a w_a (<e>_a(P_g) - g) = 0`` of :func:`shear_fixed_point`
    on its usable rows: the posterior means, the Jacobian, the residual and the errors."""

    lnL: np.ndarray
    egrid: np.ndarray
    prior: Prior
    #: the integration grid (:func:`pylensfit.grid.refined_grid`) and its refinement
    grid: np.ndarray
    refine: int
    block_size: int | None
    #: ``(n,)`` the weights, None for 1
    w: np.ndarray | None
    images: _ImageFrames | None

    @property
    def n(self) -> int:
        """Rows used."""
        return int(self.lnL.shape[0])

    @property
    def wsum(self) -> float:
        """The sum of the weights."""
        return float(self.n if self.w is None else self.w.sum())

    def terms(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(n, 2)`` posterior means under the prior sheared by ``g`` (sky frame where
        there is one) and the ``(2, 2)`` Jacobian of ``f``."""
        if self.images is None:
            m, jac = _fixed_point_terms(self.lnL, self.egrid, self.prior, self.grid, g,
                                        self.refine, self.block_size, self.w)  # fmt: skip
        else:
            m, jac = self._sky_terms(g)
        return m, jac - self.wsum * np.eye(2)

    def _sky_terms(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`terms` image by image: each image's prior sheared by ``g`` in its pixel
        frame, its means and Jacobian taken to the sky frame."""
        im = self.images
        m, jac = np.empty((self.n, 2)), np.zeros((2, 2))
        gp1, gp2 = shear_to_pixel(np.full(im.frames.n, g[0]), np.full(im.frames.n, g[1]),
                                  im.frames)  # fmt: skip
        for k in range(im.frames.n):  # one prior per image (pixel frame)
            sel = im.index == k
            if not sel.any():
                continue
            w = None if self.w is None else self.w[sel]
            mk, jk = _fixed_point_terms(self.lnL[sel], self.egrid, self.prior, self.grid,
                                        np.array([gp1[k], gp2[k]]), self.refine,
                                        self.block_size, w)  # fmt: skip
            m[sel, 0], m[sel, 1] = to_sky(mk[:, 0], mk[:, 1], rows_frame(im.rows, sel))
            jac += im.spin2[k] @ jk @ im.spin2[k].T
        return m, jac

    def residual(self, m: np.ndarray, g: np.ndarray) -> np.ndarray:
        """``f(g)`` from the posterior means ``m`` at ``g``."""
        w = self.w
        return (np.array([m[:, 0].sum(), m[:, 1].sum()]) if w is None else w @ m) - self.wsum * g

    def errors(self, m: np.ndarray, jac: np.ndarray, g: np.ndarray) -> tuple[float, float]:
        """The 1-sigma errors of ``g`` (:func:`shear_fixed_point`'s Returns)."""
        n, w = self.n, self.w
        if w is None:
            err = [float(np.std(m[:, i], ddof=1)) * math.sqrt(n) / abs(jac[i, i]) if n > 1
                   else math.nan for i in range(2)]  # fmt: skip
        else:
            err = [float(np.sqrt(np.sum(w**2 * (m[:, i] - g[i]) ** 2))) / abs(jac[i, i])
                   if n > 1 else math.nan for i in range(2)]  # fmt: skip
        return err[0], err[1]


def _usable(lnL: np.ndarray, weights: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """The usable rows of ``lnL`` (of positive weight) and their weights."""
    ok = usable_rows(lnL)
    w = None
    if weights is not None:
        w = np.asarray(weights, dtype=float)
        if w.shape != (lnL.shape[0],):
            raise ValueError(f"weights must have shape ({lnL.shape[0]},), got {w.shape}")
        ok &= np.isfinite(w) & (w > 0)
    if not ok.any():
        raise ValueError("empty sample: no usable likelihood row to estimate shear")
    return ok, None if w is None else w[ok]


def shear_fixed_point(
    lnL: np.ndarray,
    egrid: np.ndarray,
    prior: Prior,
    *,
    refine: int = DEFAULT_REFINE,
    n_iter: int = 4,
    block_size: int | None = None,
    weights: np.ndarray | None = None,
    frame=None,
    groups: np.ndarray | None = None,
) -> ShearEstimate:
    """Shear of a sample as the fixed point ``sum_a <e>_a(P_g) = N g`` (all orders in g).

    The paper's mean shear over mean sensitivity (Kitching et al. 2008, arXiv:0802.1528,
    section 3.3; docs: method, eq-key2) divides by sensitivities computed at ``g = 0``
    on data that are sheared; for a noise-free ring ``<e> = g`` and ``<e^2> = g^2``
    exactly, so the summed exact sensitivity is ``N (1 - |g|^2)`` and the estimate is
    high by a factor ``1 + |g|^2`` (``m ~ +0.006`` at ``g = 0.1`` for likelihood widths
    0.05-0.1). Here the prior itself is sheared: with ``P_g`` the density of the
    population ``P`` after a shear ``g``, the posterior mean under the true population
    averages to the population mean ``g`` exactly, so ``g`` solves
    ``f(g) = sum_a <e>_a(P_g) - N g = 0``, found by Newton steps from ``g = 0`` with the
    Jacobian ``sum_a d<e>_a/dg - N`` (the prior's share of the exact response; the first
    step is eq-key2 with the data part of the sensitivity replaced by its expectation,
    1).

    With ``weights`` ``w_a`` it solves ``sum_a w_a (<e>_a(P_g) - g) = 0``. With a sky
    ``frame`` per row and the ``groups`` (images) that share a pixel frame, ``g`` is the
    sky-frame shear: each group's prior is sheared by ``g`` taken to its pixel frame
    (:func:`pylensfit.skyframe.shear_to_pixel`) and its posterior means are taken to the
    sky frame (:func:`pylensfit.skyframe.to_sky`) before they are summed.

    Parameters
    ----------
    lnL, egrid, prior, refine, block_size
        As in :func:`shapes` (rows that are unusable are skipped).
    n_iter : int
        Newton steps (3 reach 1e-7 in g).
    weights : numpy.ndarray, optional
        ``(n_gal,)`` per-galaxy weights (rows of weight 0 are skipped; default 1).
    frame : pylensfit.skyframe.SkyFrame, optional
        The sky frame of each row (default: the pixel frame).
    groups : numpy.ndarray, optional
        ``(n_gal,)`` labels of the rows that share a pixel frame (e.g. the catalogue's
        ``image_index``); needed with ``frame``.

    Returns
    -------
    ShearEstimate
        ``g1, g2`` and their errors, ``std_a(<e_i>_a) sqrt(N) / |sum_a d<e_i>/dg_i - N|``
        (weighted: ``sqrt(sum_a w_a^2 (<e_i>_a - g_i)^2) / |sum_a w_a (d<e_i>/dg_i - 1)|``).
    """
    lnL, egrid = check_inputs(lnL, egrid, prior, refine=refine)
    ok, w = _usable(lnL, weights)
    problem = _FixedPoint(lnL=lnL[ok], egrid=egrid, prior=prior,
                          grid=refined_grid(egrid, int(refine)), refine=int(refine),
                          block_size=block_size, w=w,
                          images=_image_frames(frame, groups, ok))  # fmt: skip
    g = np.zeros(2)
    for _ in range(n_iter):
        m, jac = problem.terms(g)
        g = g - np.linalg.solve(jac, problem.residual(m, g))
    g1_err, g2_err = problem.errors(m, jac, g)
    return ShearEstimate(g1=float(g[0]), g2=float(g[1]), g1_err=g1_err, g2_err=g2_err,
                         n=problem.n)  # fmt: skip
