"""From FITS images to a shear catalogue: the public names of :mod:`pylensfit.images`.

The pipeline's parts live in the subpackage :mod:`pylensfit.images`, one module per step
of the data flow; this module re-exports its public names so that
``from pylensfit.pipeline import measure`` keeps working.
"""

from .images import (
    PSF_SUSPECT_CHI2,
    PSF_SUSPECT_PVALUE,
    ImageResult,
    InputError,
    NeighbourScene,
    PSFSummary,
    calibrate_images,
    catalogue_frame,
    measure,
    measure_exposures,
    read_catalogue,
    subtract_neighbours,
    write_catalogue,
)

__all__ = [
    "InputError",
    "ImageResult",
    "NeighbourScene",
    "PSFSummary",
    "PSF_SUSPECT_CHI2",
    "PSF_SUSPECT_PVALUE",
    "calibrate_images",
    "catalogue_frame",
    "measure",
    "measure_exposures",
    "read_catalogue",
    "subtract_neighbours",
    "write_catalogue",
]
