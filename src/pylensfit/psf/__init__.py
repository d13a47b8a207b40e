"""The PSF: from star images to the transform used by the likelihood engine.

The PSF image includes the pixel response (it is a star image), so the observed
model is ``M_k = G_k P_k`` on the stamp's DFT frequencies with no extra pixel factor.
This assumes that the PSF band-limits the data at the pixel Nyquist frequency
(paper section 2.4); aliasing of modes above Nyquist is not modelled.

:func:`stack_psf` estimates the PSF of an image from its stars (paper section 2.4):

1. A ``(size + 2 margin + 1)``-square cutout is taken about the nearest pixel of each
   catalogue position (odd, so that the Fourier shift has no ambiguous Nyquist mode; the
   margin takes the periodic wrap-around of the shift). Stars whose cutout leaves the
   image or holds non-finite or zero-weight pixels are rejected.
2. Each star is centred on the peak of its cross-correlation with a round Gaussian of
   ``centroid_sigma`` (the paper's "cross-correlation with a delta function", smoothed
   against noise) and moved there by an exact Fourier shift, i.e. the band-limited
   (sinc) interpolation that the paper performs on a 50x finer grid. Its amplitude is
   the Gaussian-weighted flux; stars below ``min_snr`` are dropped. The first stack is
   the pixel-wise median of the unit-flux stars (robust to a minority of contaminants).
3. ``n_iter`` times: each remaining star is re-centred on the maximum of its
   cross-correlation with the stack ``P`` (Newton steps on the Fourier series, so to a
   small fraction of a pixel), its flux is re-measured as ``<s, P> / <P, P>`` (unbiased
   for ``s = f P + noise``; its noise error correlates with the star's noise only along
   ``P``, so it changes the stack's normalisation, not its shape), and it is rejected if
   its normalised cross-correlation is below ``min_correlation`` or its reduced
   chi-square in the PSF core exceeds ``max_chi2`` (:class:`StarChecks`). The first pass
   compares with the median stack; later passes with the weighted stack of the other
   survivors (leave-one-out, so that a star's own noise cannot vouch for it). The stack
   is then remade from the survivors.
4. The final stack is shifted so that its Gaussian cross-correlation peaks on
   ``[size//2, size//2]`` and normalised to unit sum in the window.

The result estimates the band-limited part (``|k| < pi``) of the pixel-convolved PSF:
power above the pixel Nyquist frequency aliases with a phase that depends on each star's
sub-pixel position and averages away. For a Moffat of 3-pixel FWHM this differs from the
pixel-sampled PSF by 1.3e-3 of its peak (paper section 2.4).

The parts, along the computation: :mod:`~pylensfit.psf.transform` (:func:`psf_transform`,
the PSF on a stamp's frequencies), :mod:`~pylensfit.psf.stars` (the candidate stars'
inputs, cutouts, the tests they must pass, :class:`StarChecks`, and the rejection
:data:`REASONS`), :mod:`~pylensfit.psf.fourier` (exact
Fourier shifts and the Gaussian centre convention), :mod:`~pylensfit.psf.centring` (the
stages of the stack: centre, compare, reject), :mod:`~pylensfit.psf.stack`
(:func:`stack_psf`), :mod:`~pylensfit.psf.diagnostics` (:func:`psf_diagnostics`) and
:mod:`~pylensfit.psf.result` (:class:`PSFResult`, its files, :func:`combine_psfs`).
"""

from . import stars
from .diagnostics import psf_diagnostics
from .result import PSFResult, combine_psfs, psf_from_image, read_psf
from .stack import stack_psf
from .stars import StarChecks, check_star_inputs
from .transform import PSFError, centre_on_stamp, psf_transform

#: Rejection reasons written in :attr:`PSFResult.reason` (``''`` for a used star), by key.
REASONS = stars.REASONS

__all__ = [
    "REASONS",
    "PSFError",
    "PSFResult",
    "StarChecks",
    "centre_on_stamp",
    "check_star_inputs",
    "combine_psfs",
    "psf_diagnostics",
    "psf_from_image",
    "psf_transform",
    "read_psf",
    "stack_psf",
]
