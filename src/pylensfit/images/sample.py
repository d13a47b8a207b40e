"""The calibration sample: the images that the calibration recipe runs on.

A survey estimates its priors once, on a sample of its galaxies, and measures every
image in one pass under them. The sample is made of whole images, drawn at random
(``Config.calibration_seed``) until their objects reach ``Config.calibration_sample``:
each galaxy of the sample is fitted exactly as the measurement fits it (the image's own
detection, PSF, neighbours subtracted and sky), so that the likelihoods the priors are
estimated from are those the priors are applied to. A subset of each image's detections
would leave the others unfitted, their light in the sample's stamps where the
measurement subtracts it. The images' objects are counted first: each image read and
its objects detected (or its input catalogue read), which costs a small part of a fit.
"""

from __future__ import annotations

import logging

import numpy as np

from .inputs import detect_objects, read_image, read_positions
from .records import ImageTask

__all__ = ["count_task", "draw_sample", "sample_tasks"]

# the pipeline's one logger: its name predates the split into modules
log = logging.getLogger("pylensfit.pipeline")


def count_task(task: ImageTask) -> int:
    """The objects of one image: its input catalogue's rows, or its detections."""
    if task.catalogue:
        return len(read_positions(task.catalogue, task.path))
    img = read_image(task.path, task.weight, task.mask)
    return len(detect_objects(img, task.config, None)[1])


def draw_sample(counts: np.ndarray, size: int, seed: int) -> np.ndarray:
    """The images of the calibration sample, in their given order.

    Parameters
    ----------
    counts : numpy.ndarray
        ``(n_images,)`` objects per image.
    size : int
        Objects wanted; 0: every image.
    seed : int
        Seed of the draw.

    Returns
    -------
    numpy.ndarray
        Sorted indices of the images drawn: in a random order (``seed``), the fewest
        whose objects reach ``size`` (every image where they do not).
    """
    counts = np.asarray(counts, dtype=np.int64)
    if size <= 0 or counts.sum() <= size:
        return np.arange(counts.size)
    order = np.random.default_rng(seed).permutation(counts.size)
    n = int(np.searchsorted(np.cumsum(counts[order]), size)) + 1
    return np.sort(order[:n])


def sample_tasks(tasks: list[ImageTask], size: int, seed: int, workers) -> list[ImageTask]:
    """The tasks of the calibration sample (:func:`draw_sample`); every task without
    counting where there is one image or ``size`` is 0.

    ``workers`` is the :class:`~pylensfit.images.passes.Workers` that count the objects.
    """
    if size <= 0 or len(tasks) <= 1:
        return list(tasks)
    counts = np.zeros(len(tasks), dtype=np.int64)
    pos = {t.index: k for k, t in enumerate(tasks)}
    for t, n in workers.run(count_task, tasks, "counting objects"):
        counts[pos[t.index]] = n
    chosen = draw_sample(counts, size, seed)
    log.info("calibration sample: %d of %d images, %d of %d objects (seed %d)", chosen.size,
             len(tasks), int(counts[chosen].sum()), int(counts.sum()), seed)  # fmt: skip
    return [tasks[k] for k in chosen]
