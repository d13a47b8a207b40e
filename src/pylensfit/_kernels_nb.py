"""numba kernels of the low layers: the launch guard of the parallel kernels, and the
wings that a periodic model wraps into its stamp (:func:`pylensfit.models.wrap_correction`).

The likelihood's kernels live beside their Python in :mod:`pylensfit.likelihood`
(``amplitude_nb``, ``laplace_nb``, ``radius_nb``, ``grid_nb``); they launch through
:func:`one_launch_at_a_time` as well, and :mod:`pylensfit.shear` takes
:func:`launch_guard` around its own.
"""

from __future__ import annotations

import functools
import math
import os
import threading
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext

import numba
from numba import njit, prange

#: held around each launch of a parallel kernel while numba's threading layer is its
#: work queue (the fork-safe layer where TBB is absent, chosen by
#: :func:`pylensfit.likelihood.threads.fork_safe_threading`): that layer aborts the process
#: ("Concurrent access has been detected") when two threads launch kernels at once, as
#: the image tasks of a dask worker with several threads do
_LAUNCH_LOCK = threading.Lock()


def _renew_launch_lock() -> None:
    """A fresh lock in a forked child: a thread of the parent may have held the old one."""
    global _LAUNCH_LOCK
    _LAUNCH_LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_renew_launch_lock)


def launch_guard() -> AbstractContextManager:
    """The lock on the work queue (and before any layer has started, since this launch
    may start the work queue); a context that does nothing on TBB or OpenMP."""
    try:
        layer = numba.threading_layer()
    except ValueError:  # no parallel kernel has run yet
        return _LAUNCH_LOCK
    return _LAUNCH_LOCK if layer == "workqueue" else nullcontext()


def one_launch_at_a_time(kernel: Callable) -> Callable:
    """``kernel`` (a parallel numba dispatcher) called from Python under :func:`launch_guard`."""

    @functools.wraps(kernel, updated=())
    def launch(*args):
        with launch_guard():
            return kernel(*args)

    launch.kernel = kernel
    return launch


@njit(cache=True, fastmath={"contract", "arcp", "afn"}, inline="always")
def _profile_value(rr, model_code, fb, bsr, b_dev, norm_dev, trunc, inv_n):
    """Surface brightness of a unit-flux round profile of unit scale at radius ``rr``.

    ``model_code``: 0 exponential (scale length), 1 de Vaucouleurs (half-light radius,
    truncated at ``trunc``), 2 bulge + disc (disc scale length; bulge of fraction
    ``fb`` and half-light radius ``bsr``), 3 one Sersic component of half-light radius
    ``bsr``, ``exp(-b_dev x^inv_n) / norm_dev`` (``x`` in half-light radii) cut at
    ``trunc`` half-light radii.
    """
    if model_code == 3:
        x = rr / bsr
        if x <= trunc:
            return math.exp(-b_dev * x**inv_n) / (norm_dev * bsr * bsr)
        return 0.0
    v = 0.0
    if model_code != 1 and fb < 1.0:
        v += (1.0 - fb) * math.exp(-rr) / (2.0 * math.pi)
    if model_code == 1 or (model_code == 2 and fb > 0.0):
        s = 1.0 if model_code == 1 else bsr
        w = 1.0 if model_code == 1 else fb
        x = rr / s
        if x <= trunc:
            v += w * math.exp(-b_dev * x**0.25) / (norm_dev * s * s)
    return v


@njit(cache=True, inline="always")
def _stamp_share(a, i, shared):
    """The share of copy ``a`` (stamps away) that pixel line ``i`` of the stamp holds.

    The central copy is the stamp's own (1), except on an even stamp's first line, whose
    periodic image at ``+n/2`` (copy 1) it shares half and half; other copies wrap in (0).
    """
    if a == 0:
        return 0.5 if shared and i == 0 else 1.0
    if a == 1 and shared and i == 0:
        return 0.5
    return 0.0


@njit(parallel=True, cache=True)
def _wrapped_wings_nb(e1s, e2s, radii, fracs, profile, n, max_copies, out):
    """The wings that a periodic model wraps into an ``n x n`` stamp.

    A model evaluated on the stamp's discrete frequencies is the periodic sum of its
    copies ``m(x + j n)``; a stamp cut from the sky holds only ``m(x)`` (docs: method,
    eq-fourier-model, ``Config.truncate_models``). For each ellipticity
    ``(e1s[i], e2s[i])``, bulge fraction ``fracs[b]`` and size ``radii[j]`` (column
    ``b * len(radii) + j``), ``out[i, col]`` receives the sum of the copies ``j != 0``
    on the stamp's pixels (offsets ``-n/2 ... n/2 - 1`` from the centre, ``[iy, ix]``),
    with the two pixel lines at ``+-n/2`` (one periodic line) shared half and half,
    which keeps the square's symmetries. Pixel-centre values: the wings are smooth on
    the pixel scale. Columns without wings beyond the stamp stay zero. ``profile`` is
    ``(model_code, bsr, b_dev, norm_dev, trunc, inv_n)`` of :func:`_profile_value`.
    """
    model_code, bsr, b_dev, norm_dev, trunc, inv_n = profile
    n_e = e1s.size
    n_r = radii.size
    n_b = fracs.size
    h = n // 2
    shared = n % 2 == 0  # an even stamp's first line is at -n/2, its copy at +n/2
    for t in prange(n_e * n_b * n_r):
        i = t // (n_b * n_r)
        col = t % (n_b * n_r)
        fb = fracs[col // n_r]
        r = radii[col % n_r]
        e1 = e1s[i]
        e2 = e2s[i]
        ee = math.sqrt(e1 * e1 + e2 * e2)
        inv = 1.0 / math.sqrt(1.0 - ee * ee)
        stretch = math.sqrt((1.0 + ee) / (1.0 - ee))
        # the model's extent: 25 scale lengths of the disc (a fraction 4e-10 of its flux
        # beyond), the bulge's truncation radius
        ext = 0.0
        if model_code == 3:
            ext = trunc * bsr
        elif model_code != 1 and fb < 1.0:
            ext = 25.0
        if model_code == 1 or (model_code == 2 and fb > 0.0):
            s = 1.0 if model_code == 1 else bsr
            ext = max(ext, trunc * s)
        ext *= r * stretch
        if ext <= h:
            continue
        kmax = min(int(math.ceil(ext / n + 0.5)), max_copies)
        for iy in range(n):
            py = iy - h
            for ix in range(n):
                px = ix - h
                # the profile is point-symmetric and, off the shared lines, so is the
                # set of copies kept: the pixel at -p has the value of p
                my = 2 * h - iy
                mx = 2 * h - ix
                off_shared = not shared or (ix > 0 and iy > 0)  # then -p is in the stamp
                if off_shared and (my < iy or (my == iy and mx < ix)):
                    out[i, col, iy, ix] = out[i, col, my, mx]
                    continue
                acc = 0.0
                for a in range(-kmax, kmax + 1):
                    x = px + a * n
                    inx = _stamp_share(a, ix, shared)
                    if abs(x) > ext + 1.0:
                        continue
                    for b in range(-kmax, kmax + 1):
                        y = py + b * n
                        iny = _stamp_share(b, iy, shared)
                        keep = 1.0 - inx * iny
                        if keep == 0.0 or abs(y) > ext + 1.0:
                            continue
                        ux = ((1.0 - e1) * x - e2 * y) * inv
                        uy = (-e2 * x + (1.0 + e1) * y) * inv
                        rr = math.sqrt(ux * ux + uy * uy) / r
                        acc += keep * _profile_value(rr, model_code, fb, bsr, b_dev,
                                                     norm_dev, trunc, inv_n) / (r * r)  # fmt: skip
                out[i, col, iy, ix] = acc


wrapped_wings = one_launch_at_a_time(_wrapped_wings_nb)


@njit(cache=True)
def add_patches_nb(canvas, patches, ix0, iy0):
    """Add ``(m, M, M)`` ``patches`` into the 2-D ``canvas`` in place, element ``[0, 0]``
    of patch ``k`` on pixel ``(ix0[k], iy0[k])``, pixels outside the canvas dropped.

    One patch after the other, row by row: the order in which ``numpy.add.at`` adds the
    same elements, so that the sums are the same to the last bit (overlapping patches
    add up).
    """
    ny, nx = canvas.shape
    m, my, mx = patches.shape
    for k in range(m):
        for i in range(my):
            r = iy0[k] + i
            if r < 0 or r >= ny:
                continue
            for j in range(mx):
                c = ix0[k] + j
                if 0 <= c < nx:
                    canvas[r, c] += patches[k, i, j]
