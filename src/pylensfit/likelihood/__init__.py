"""The likelihood of every galaxy on the (e1, e2, r) grid, summed over r.

Miller et al. (2007, arXiv:0708.2340), section 3, and Kitching et al. (2008,
arXiv:0802.1528), section 2.2: the likelihood marginalised over the amplitude and over
the position (docs: method, eq-amplitude, eq-flux-prior, eq-position, eq-matrix-products
and eq-radius).

For a stamp ``d`` with constant noise ``sigma`` and a model ``A m(x - X)`` of unit flux:

* **amplitude** (uniform prior, ``A > 0``)::

      ln L(e, r, X) = h^2 / (2 sigma^2 S) + ln Phi(h / (sigma sqrt S)) - ln(S) / 2

  with ``h(X) = sum_x d(x) m(x - X)`` the cross-correlation and ``S = sum m^2``
  (Kitching et al. 2008, section 2.2; docs: method, eq-amplitude; the ``Phi`` term is
  the positive-flux prior, which keeps a negative cross-correlation from being read as a
  bright negative galaxy);
* **position**: the data are re-centred once per galaxy on the peak of their
  cross-correlation with a round model (found by FFT and refined by a parabola, then
  applied exactly by a Fourier phase ramp). ``h``, its gradient and Hessian at the
  re-centred origin are sums over frequencies, which for all galaxies and all models are
  six matrix products (folded by the symmetries of the square pixel grid into four
  products over an octant of frequencies for each orbit ``(+-e1, +-e2)`` of four models,
  a quarter of the operations: :class:`~pylensfit.likelihood.folded.FoldedBank`;
  Nyquist frequencies are left out, :func:`~pylensfit.likelihood.bank.interior`). One
  Newton step gives the peak ``X*``, ``h*``, and the Laplace approximation of the
  integral over ``X`` with a Gaussian prior of width ``b`` about the catalogue position
  ``X0`` is the 2-D form of the paper's likelihood marginalised
  over the position (section 2.2; docs: method, eq-position)::

      ln L(e, r) = l* - ln det(I + b^2 F) / 2 - (X* - X0)^T (F^-1 + b^2 I)^-1 (X* - X0) / 2

  with ``F = -(dl/dh) Hess h`` the curvature of ``l = ln L(e, r, X)`` in position;
* **size**: ``L(e) = int L(e, r) dr`` over ``r = r_min ... r_max`` (uniform prior), by
  the trapezoid rule on the size grid (:func:`pylensfit.models.radius_weights`);
  ``r = 0`` is the point source. An object whose most likely ``r`` (marginal over
  the e grid) is 0 is flagged as a star.

The modules follow the computation: :mod:`~pylensfit.likelihood.fit` (:func:`fit_stamps`,
each window's stages in order), :mod:`~pylensfit.likelihood.tiers` (the stamp side of each
galaxy), :mod:`~pylensfit.likelihood.windows` (the windows cut, cleaned, transformed and
centred), :mod:`~pylensfit.likelihood.bank` (the PSF's part of the model bank, cached;
:class:`MixedPSF`, a PSF mixed per stamp from a few), :mod:`~pylensfit.likelihood.pairs`
(that PSF's part per pair of its PSFs) and :mod:`~pylensfit.likelihood.folded` (the bank
folded by the square's symmetries),
:mod:`~pylensfit.likelihood.priors` (the kernel's priors and weights),
:mod:`~pylensfit.likelihood.evaluate` (the matrix products and the kernel's passes, block
by block), :mod:`~pylensfit.likelihood.refine` (the finer e grid of the bright
galaxies), :mod:`~pylensfit.likelihood.results` (the rows of the result),
:mod:`~pylensfit.likelihood.stampfits` (:class:`StampFits` and its file),
:mod:`~pylensfit.likelihood.merge` (fits merged, blended, reweighted) and
:mod:`~pylensfit.likelihood.threads` (numba's threading layer, one BLAS thread). The
numba kernels sit beside them: ``grid_nb`` (the kernel, its inputs as named tuples),
``tile_nb`` (a tile of models), ``laplace_nb`` (position), ``amplitude_nb`` (amplitude)
and ``radius_nb`` (the sum over size).
"""

# merge_fits, reweight_lnL_r and tier_sizes (as name: re-exported) serve other modules
# of the method, outside the public names as before
from .bank import MixedPSF
from .fit import fit_stamps
from .merge import blend_fits, e_annuli
from .merge import merge_fits as merge_fits
from .merge import reweight_lnL_r as reweight_lnL_r
from .stampfits import StampFits
from .tiers import tier_sizes as tier_sizes

__all__ = ["MixedPSF", "StampFits", "blend_fits", "e_annuli", "fit_stamps"]

# the result's class keeps its name, pylensfit.likelihood.StampFits: in the documentation
# (one entry, as pylensfit.StampFits's original) and in pickles
StampFits.__module__ = __name__
MixedPSF.__module__ = __name__
