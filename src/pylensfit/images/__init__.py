"""From FITS images to a shear catalogue (paper sections 2.3-2.4 and 4).

:func:`measure` walks the whole path for each input image:

1. read the image, its weight (inverse variance) and mask maps and its WCS, and mask
   the saturated (``Config.saturation`` or the ``SATURATE`` card) and non-finite pixels;
2. measure the background and its rms and detect the objects with ``sep``
   (:mod:`pylensfit.detection`), or take the positions of an input catalogue;
3. select stars on the stellar locus (peak S/N above ``star_min_peak_snr``), stack them
   into a PSF (:func:`pylensfit.psf.stack_psf`) and co-add it with the PSFs of the
   separate star-field images;
4. cut a postage stamp about every object and flag those that cannot be fitted (edge,
   masked, saturated or NaN pixels, close pairs: :mod:`pylensfit.stamps`);
5. compute every object's ``ln L(e)`` grid (:func:`pylensfit.fit_stamps`), again with
   the neighbours' models and the sky's change taken out; an object whose model does not
   fit its stamp (a defect) is flagged ``DEFECT`` and left out of the others' stamps and
   the sky;
6. with ``Config.response = "metacal"``, metacalibrate every galaxy fitted on its
   largest stamp as its last fit saw it (:mod:`~pylensfit.images.metacal_rows`).

The images are independent and run in parallel: in a local process pool (``jobs``, one
BLAS and numba thread per worker) or on a dask.distributed cluster (``scheduler``).
Each finished image is written at once (atomically) to ``<output>.parts/``, so a run
that is killed and restarted does only the images that are missing. When all are done,
the prior is estimated from the galaxies of the run (unless one is given), the
posterior means, covariances and sensitivities computed from the stored grids, and the
catalogue written (:mod:`pylensfit.catalogue`). Every object that was detected has a
row; the ``flags`` column says why an object was not measured.

The parts, along the data flow: :mod:`~pylensfit.images.inputs` (reading the images,
weights, masks and positions; the up-front checks), :mod:`~pylensfit.images.image_psf`
(an image's PSF from its stars and the star fields; the PSF cells),
:mod:`~pylensfit.images.records` (the tasks and their typed results),
:mod:`~pylensfit.images.tiers` (an image's stamps and their tiers),
:mod:`~pylensfit.images.neighbours` (:func:`subtract_neighbours`, the method),
:mod:`~pylensfit.images.metacal_rows` (an image's metacalibration columns),
:mod:`~pylensfit.images.task` (one image's task and its rows),
:mod:`~pylensfit.images.parts` (resuming: task keys, part files, temporaries),
:mod:`~pylensfit.images.passes` (the recipe's glue: calibration and measuring passes,
the assembly of the rows), :mod:`~pylensfit.images.catalogue_io` (the catalogue's file),
:mod:`~pylensfit.images.run` (:func:`measure`) and
:mod:`~pylensfit.images.exposure_set` (:func:`measure_exposures`: the exposures of one
field, each galaxy fitted jointly on all of them). ``pylensfit.pipeline`` re-exports
the public names.
"""


from .catalogue_io import catalogue_frame, read_catalogue, write_catalogue
from .exposure_set import (
    ExposureSet,
    detection_coadd,
    jacobian_groups,
    measure_exposures,
    read_exposures,
    read_sky_positions,
)
from .image_psf import PSF_SUSPECT_CHI2, PSF_SUSPECT_PVALUE
from .inputs import InputError
from .neighbours import NeighbourScene, subtract_neighbours
from .records import ImageResult, PSFSummary
from .run import calibrate_images, measure

__all__ = [
    "ExposureSet",
    "InputError",
    "ImageResult",
    "NeighbourScene",
    "PSFSummary",
    "PSF_SUSPECT_CHI2",
    "PSF_SUSPECT_PVALUE",
    "calibrate_images",
    "catalogue_frame",
    "detection_coadd",
    "jacobian_groups",
    "measure",
    "measure_exposures",
    "read_exposures",
    "read_sky_positions",
    "read_catalogue",
    "subtract_neighbours",
    "write_catalogue",
]
