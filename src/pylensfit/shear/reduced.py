"""The reduced-shear map (Kitching et al. 2008, section 2.1) on ellipticities and on a
population's density.

:func:`apply_shear` shears intrinsic ellipticities, ``e = (e_s + g) / (1 + g* e_s)``;
:func:`sheared_prior_columns` gives the density of a population after a shear ``g`` and
its derivatives in ``g``, the prior of the fixed-point estimator.
"""

from __future__ import annotations

import numpy as np

from ..prior import Prior


def apply_shear(
    e1: np.ndarray, e2: np.ndarray, g1: float, g2: float
) -> tuple[np.ndarray, np.ndarray]:
    """Shear intrinsic ellipticities: ``e = (e_s + g) / (1 + g* e_s)`` (paper section 2.1).

    Parameters
    ----------
    e1, e2 : array_like
        Intrinsic ellipticity components ``e_s`` (``|e_s| < 1``).
    g1, g2 : float
        Reduced shear components (``|g| < 1``).

    Returns
    -------
    tuple of numpy.ndarray
        The sheared ``(e1, e2)``.
    """
    es = np.asarray(e1, dtype=float) + 1j * np.asarray(e2, dtype=float)
    g = complex(g1, g2)
    e = (es + g) / (1.0 + np.conj(g) * es)
    return e.real, e.imag


def sheared_prior_columns(
    prior: Prior, grid: np.ndarray, g: np.ndarray, h: float = 1e-3
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``P_g`` on ``grid`` and its derivatives ``dP_g/dg_j`` (central differences).

    ``P_g(e) = P(e_s) |de_s/de|^2`` with ``e_s = (e - g)/(1 - g* e)``: the density of the
    population ``P`` after the reduced shear ``g`` (paper section 2.1); at ``g = 0`` its
    derivative is the exact sensitivity's ``dP_g/dg`` (docs: method, eq-sensitivity-exact).

    Parameters
    ----------
    prior : Prior
        The unsheared population density ``P``.
    grid : numpy.ndarray
        ``(n_e, 2)`` integration grid (:func:`refined_grid`).
    g : numpy.ndarray
        ``(g1, g2)``, the reduced shear.
    h : float
        Step of the central differences in ``g``.

    Returns
    -------
    P_g, dP_g1, dP_g2 : numpy.ndarray
        ``(n_e,)`` each: the sheared density and its derivatives with respect to
        ``g1`` and ``g2``.
    """
    e = grid[:, 0] + 1j * grid[:, 1]

    def dens(gc: complex) -> np.ndarray:
        den = 1.0 - np.conj(gc) * e
        es = (e - gc) / den
        jac = (1.0 - abs(gc) ** 2) ** 2 / np.abs(den) ** 4
        return prior.pdf(es.real, es.imag) * jac

    gc = complex(g[0], g[1])
    d1 = (dens(gc + h) - dens(gc - h)) / (2 * h)
    d2 = (dens(gc + 1j * h) - dens(gc - 1j * h)) / (2 * h)
    return dens(gc), d1, d2
