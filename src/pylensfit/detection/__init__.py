"""Object detection, photometry, star selection and close-pair rejection (paper sections 2.3-2.4).

Detection uses SEP, the Source Extractor algorithms as a library (Bertin & Arnouts 1996;
Barbary 2016), as the paper used SExtractor to find galaxies and stars::

    bkg = measure_background(image, weight=weight)      # background and noise maps
    cat = detect(image, weight=weight, background=bkg)  # one row per object
    sub = bkg.subtract(image)                            # the image the catalogue measured
    stars = select_stars(cat)                            # stellar locus, peak S/N > 30
    pairs = close_pairs(cat["x"], cat["y"])              # another object in the stamp

Conventions: images are indexed ``[y, x]``; positions are 0-based with pixel centres at
integer values (pixel ``(x, y)`` is element ``[y, x]``), which is SEP's convention too. A
postage stamp of side ``n`` about ``(x, y)`` covers elements ``rint(y) - n//2`` to
``rint(y) - n//2 + n - 1`` (and the same in x), as in :mod:`pylensfit.likelihood`.

:func:`detect` measures each object on the background-subtracted image: the position is
the isophotal barycentre, refined by a Gaussian-windowed centroid (``windowed``);
``r_half`` is the radius enclosing half of the flux in a first circle of radius
``max(6 a, min_aperture)``; the flux is summed in a circle of radius
``aper_radius = clip(aperture * r_half, min_aperture, max_aperture)`` (5 r_half holds
> 99% of the flux of an exponential disc) and ``r_half`` is then re-measured as the radius
holding half of that flux. Masked and bad pixels count as 0 in the sums (no area
rescaling) and set ``APER_HASMASKED`` in ``sep_flag``. The aperture of a blended object
(``OBJ_MERGED``) holds some of its neighbours' light: its ``flux`` and ``r_half`` are
biased high; ``flux_iso`` is the deblended estimate. Every detection counts for the
``CLOSE_PAIR`` flag, including the noise peaks that a low ``threshold`` lets through
(about 50 in 512 x 512 pixels at 1.5 sigma).

Its catalogue has one row per object, with the columns (units in ``Table[col].unit``):
``id`` (1-based), ``x``, ``y`` (pix, 0-based), ``flux``, ``flux_err`` (image units,
aperture), ``flux_iso`` (image units, deblended isophotal footprint), ``snr``, ``mag``,
``peak`` (image units), ``peak_snr`` (peak over the noise sigma at the peak pixel), ``a``,
``b`` (pix), ``theta`` (rad, from +x towards +y), ``r_half``, ``aper_radius`` (pix),
``npix``, ``background``, ``bkg_rms`` (image units, background maps at the object),
``noise_sigma`` (image units: median of ``1/sqrt(weight)`` over the stamp's usable pixels
when a weight map is given, else ``bkg_rms``), ``sep_flag`` (:data:`SEP_FLAGS`), ``flags``
(:mod:`pylensfit.flags` bits EDGE, MASKED, BAD_PIXELS, CLOSE_PAIR of the ``stamp_size``
stamp).

:func:`select_stars` finds the PSF stars on the stellar locus. Point sources all have
the PSF's size whatever their flux, so in ``log10 r_half``
against magnitude they form a narrow horizontal band at the small-size end, while
galaxies spread over larger sizes. Compact galaxies convolved with the PSF are only
a little larger than it (0.1 dex for an exponential of half-light radius 0.45 times
the PSF's FWHM), and where they outnumber the stars their sizes may crowd more
densely than the stars'; where the PSF's size varies over the image (10 % is
common) the stars' band is as wide as that gap. The algorithm:

1. Candidates: finite ``r_half > 0`` and ``flux > 0``, ``peak_snr >= min_peak_snr``
   (paper section 2.4: stars of peak S/N > 30 make a good PSF), no SEP flag of
   blending, truncation, singular moments or masked aperture (``sep_flag``), none of
   ``exclude_flags`` in ``flags``, and, with ``saturation``, a raw peak
   ``peak + background`` below ``saturation`` (less a 1e-5 relative margin for the
   float32 rounding of SEP's peak).
2. Locus: windows ``[s, s + 2 window]`` of ``s = log10 r_half`` over the candidates;
   the first (smallest-size) window holding at least ``min_fraction`` of the
   densest window's count (and ``min_stars``), then the densest window that starts
   within ``2 window`` of it: the smallest-size clump of sizes, not the most
   populous one, which compact galaxies may make.
3. Band: an object lies on the locus when ``|s - c(x, y)| <= nsigma * sigma_i``, with
   ``sigma_i^2 = width^2 + (0.434 / snr_i)^2``: the measurement noise of
   ``log10 r_half`` (about ``0.434 / snr`` in simulations) added to an intrinsic width
   (pixelisation, what the centre does not follow) that is fitted so that the
   normalised deviations of the members have a robust (1.4826 MAD) sigma of 1, at
   least ``min_width``. The centre ``c`` is first the members' median, then (with
   ``x`` and ``y`` columns) a polynomial in the position of total degree up to
   ``position_order`` (as many terms as the members allow at 5 members a term),
   fitted to the members weighted by ``1 / sigma_i^2``: it follows the PSF's size
   over the image, so that the band is as narrow as the stars' noise and the compact
   galaxies, larger than the PSF where they are, fall outside it. Centre, width and
   membership are iterated from the window's members until stable.

The parts, along the computation: :mod:`~pylensfit.detection.inputs` (the maps as SEP
takes them, :data:`SEP_FLAGS`), :mod:`~pylensfit.detection.masks` (saturated pixels),
:mod:`~pylensfit.detection.background` (:func:`measure_background`),
:mod:`~pylensfit.detection.extraction` (:func:`detect`),
:mod:`~pylensfit.detection.measure` (the objects' positions, photometry and columns),
:mod:`~pylensfit.detection.pairs` (:func:`close_pairs`) and
:mod:`~pylensfit.detection.stars` (:func:`select_stars`).
"""

from . import inputs
from .background import Background, measure_background
from .extraction import detect
from .masks import grow_mask, saturation_level, saturation_mask
from .pairs import close_pairs, flag_close_pairs
from .stars import select_stars

#: SEP's object and aperture flags, name -> bit (the ``sep_flag`` column).
SEP_FLAGS = inputs.SEP_FLAGS

__all__ = [
    "Background",
    "close_pairs",
    "flag_close_pairs",
    "detect",
    "grow_mask",
    "measure_background",
    "saturation_level",
    "saturation_mask",
    "select_stars",
    "SEP_FLAGS",
]
