"""PSF models that vary across the field.

:func:`pylensfit.psf.stack_psf` gives one PSF per image. Real surveys need the PSF at
each galaxy's position: lensfit's survey version (Miller et al. 2013, CFHTLenS,
arXiv:1210.8201) models every pixel of the PSF as a polynomial in the position,
fitted to the stars, as PSFEx does. This package provides:

* :class:`PSFModel`, the interface: ``draw(x, y)``, ``shape_at(x, y)``, ``centre``,
  ``diagnostics``, ``digest``, ``write``;
* :class:`ConstantPSF`, one :class:`~pylensfit.psf.PSFResult` everywhere;
* :class:`PolynomialPSF`, the per-pixel polynomial fitted to the stars
  (:meth:`PolynomialPSF.fit`), with outlier rejection and held-out diagnostics;
* :class:`PiffPSF`, a model fitted by Piff (optional dependency), and
  :func:`fit_piff`, which fits one to an image's stars with Piff;
* :func:`read_psf_model`, which reads any of them back.

Every drawn image follows the convention of :mod:`pylensfit.psf`: ``(size, size)``,
unit sum, pixel response included, centred on element ``[size//2, size//2]`` defined
as the peak of its cross-correlation with a round Gaussian of ``centroid_sigma``.
Positions are 0-based image pixels with pixel centres on integers, ``x`` indexing the
columns (arrays are ``[y, x]``).

:meth:`PolynomialPSF.fit` fits the model in four steps:

1. Cutouts, centring on the Gaussian cross-correlation peak (exact Fourier shift) and
   the S/N cut, as in :func:`pylensfit.psf.stack_psf` (whose rejection reasons,
   :data:`pylensfit.psf.REASONS`, are recorded).
2. ``n_iter`` passes: the unit-flux stars are fitted, every pixel at once, by weighted
   least squares (weights ``flux^2 / sigma^2``, the inverse variance of their pixels)
   with monomials ``u^i v^j``, ``i + j <= order``; then every candidate is compared with
   the model at its own position without itself (leave-one-out, through its leverage):
   re-centred on the cross-correlation with it, its flux measured as
   ``<s, P> / <P, P>``, and rejected (for this pass; a later pass may take it back) if it
   moved more than ``max_shift``, has non-positive flux, a noise-debiased correlation
   below ``min_correlation`` or a reduced chi-square in the PSF core above ``clip`` (the
   tests of ``stack_psf``, :class:`pylensfit.psf.StarChecks`). The model is refitted to
   the survivors.
3. If fewer than ``min_stars_per_coefficient`` stars per coefficient are usable, the
   order is lowered (a warning is logged), down to 0: the inverse-variance stack of
   ``stack_psf``.
4. Held-out check: a fraction ``holdout`` of the usable stars (drawn with
   ``numpy.random.default_rng(seed)``) is left out of a second fit of the same order,
   and the adaptive moments of each held-out star are compared with those of that model
   at its position (:attr:`PolynomialPSF.diagnostics`, keys ``heldout_*``). The returned
   model is the fit to all stars.

The parts, along the computation: :mod:`~pylensfit.psfmodel.basis` (the monomials, the
re-centring of drawn images), :mod:`~pylensfit.psfmodel.base` (:class:`PSFModel`,
:class:`ConstantPSF`), :mod:`~pylensfit.psfmodel.polyfit` (the stages of the fit),
:mod:`~pylensfit.psfmodel.heldout` (the per-star table and the held-out check),
:mod:`~pylensfit.psfmodel.polynomial` (:class:`PolynomialPSF`),
:mod:`~pylensfit.psfmodel.polyio` (its file), :mod:`~pylensfit.psfmodel.piff_model`
(:class:`PiffPSF`, :func:`fit_piff`) and :mod:`~pylensfit.psfmodel.read`
(:func:`read_psf_model`).
"""

from .base import ConstantPSF, PSFModel
from .basis import n_terms
from .piff_model import PiffNotInstalledError, PiffPSF, fit_piff
from .polynomial import PolynomialPSF
from .read import read_psf_model

__all__ = [
    "ConstantPSF",
    "PSFModel",
    "PiffNotInstalledError",
    "PiffPSF",
    "PolynomialPSF",
    "fit_piff",
    "n_terms",
    "read_psf_model",
]
