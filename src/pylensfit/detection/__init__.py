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

The parts, along the computation: :mod:`~pylensfit.detection.inputs` (the maps as SEP
takes them, :data:`SEP_FLAGS`), :mod:`~pylensfit.detection.masks` (saturated pixels),
:mod:`~pylensfit.detection.background` (:func:`measure_background`),
:mod:`~pylensfit.detection.extraction` (:func:`detect`),
:mod:`~pylensfit.detection.measure` (the objects' positions, photometry and columns),
:mod:`~pylensfit.detection.pairs` (:func:`close_pairs`) and
:mod:`~pylensfit.detection.stars` (:func:`select_stars`).
"""

from .background import Background, measure_background
from .extraction import detect
from .inputs import SEP_FLAGS
from .masks import grow_mask, saturation_level, saturation_mask
from .pairs import close_pairs
from .stars import select_stars

__all__ = [
    "Background",
    "close_pairs",
    "detect",
    "grow_mask",
    "measure_background",
    "saturation_level",
    "saturation_mask",
    "select_stars",
    "SEP_FLAGS",
]
