"""The threads of the fit: numba's threading layer, chosen fork-safe at import, and one
BLAS thread around the matrix products (:func:`pylensfit.likelihood.fit_stamps`)."""

from __future__ import annotations

import os
from functools import lru_cache

import numba
from threadpoolctl import ThreadpoolController


def fork_safe_threading() -> None:
    """Have numba run the parallel kernels on a fork-safe threading layer.

    Where TBB is absent numba prefers GNU OpenMP, and a process that has run a parallel
    kernel on it cannot fork: each child of a ``multiprocessing`` fork pool that runs one
    is killed ("fork() called from a process already using GNU OpenMP"), and the pool
    starts another for ever. numba's ``forksafe`` is TBB where installed, else its work
    queue, which :mod:`pylensfit._kernels_nb` launches one kernel at a time (it is not
    thread-safe). :func:`fit_stamps` of 200 32-pixel stamps on two threads of a two-core
    machine already busy: work queue 0.26 s, TBB 0.25 s, GNU OpenMP 0.55 s (whose threads
    spin while they wait; 0.23 s with ``OMP_WAIT_POLICY=passive``).
    A layer chosen with ``NUMBA_THREADING_LAYER`` or ``numba.config`` is kept, and so is
    one that already runs (numba starts its layer at the first parallel kernel).
    """
    if (numba.config.THREADING_LAYER == "default"
            and not os.environ.get("NUMBA_THREADING_LAYER")
            and not os.environ.get("NUMBA_THREADING_LAYER_PRIORITY")):  # fmt: skip
        numba.config.THREADING_LAYER = "forksafe"


fork_safe_threading()


@lru_cache(maxsize=1)
def _blas_controller():
    return ThreadpoolController()


def one_blas_thread():
    """A context in which the BLAS libraries run on one thread (see :func:`fit_stamps`)."""
    return _blas_controller().limit(limits=1, user_api="blas")
