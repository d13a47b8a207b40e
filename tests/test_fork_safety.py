"""numba's parallel kernels and processes forked or threads started after them.

Each check runs in a fresh interpreter with a timeout: the failures it guards against
kill the process (GNU OpenMP in a forked child, the work queue launched from two threads)
or hang it (a fork pool respawning the workers that die).
"""

import os
import subprocess
import sys
import textwrap

import pytest

TIMEOUT = 120

_SETUP = """
import numpy as np

import pylensfit as plf

N = 32
y, x = np.mgrid[:N, :N] - N // 2
PSF = np.exp(-0.5 * (x**2 + y**2) / 1.5**2)
CFG = plf.Config(max_stamp_size=0)


def stamps(n, seed):
    rng = np.random.default_rng(seed)
    gal = 300.0 * np.exp(-0.5 * (x**2 / 2.5**2 + y**2 / 1.8**2))
    return gal[None] + rng.normal(size=(n, N, N))


def fit(seed):
    return float(plf.fit_stamps(stamps(2, seed), PSF, 1.0, config=CFG).flux[0])
"""


def _run(body: str) -> subprocess.CompletedProcess:
    """``body`` after the setup, in a fresh interpreter with two numba threads and the
    package's own choice of threading layer."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("NUMBA_THREADING_LAYER", "NUMBA_THREADING_LAYER_PRIORITY")}
    env["NUMBA_NUM_THREADS"] = "2"
    script = textwrap.dedent(_SETUP) + textwrap.dedent(body)
    try:
        return subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                              text=True, timeout=TIMEOUT)  # fmt: skip
    except subprocess.TimeoutExpired as err:
        pytest.fail(f"hung for {TIMEOUT} s; stderr:\n{err.stderr}")


@pytest.mark.skipif(sys.platform == "win32", reason="no fork start method")
def test_fork_pool_after_fit_stamps():
    """A fork pool after ``fit_stamps``: a trivial map, then one that fits in the children
    (what GNU OpenMP kills there, the pool starting new workers for ever). The children's
    fluxes are compared to 1e-12: their BLAS may split a product differently."""
    res = _run("""
        import multiprocessing as mp

        import numba


        def square(v):
            return v * v


        if __name__ == "__main__":
            before = fit(0)
            with mp.get_context("fork").Pool(2) as pool:
                assert pool.map(square, range(4)) == [0, 1, 4, 9]
                fluxes = pool.map(fit, [0, 0, 1])
            np.testing.assert_allclose(fluxes[:2], [before, before], rtol=1e-12)
            print("layer", numba.threading_layer())
    """)
    assert res.returncode == 0, res.stderr
    assert "layer omp" not in res.stdout


def test_threads_launch_kernels_at_once():
    """Four threads fitting at once (a dask worker's image tasks) on the chosen layer:
    the same fits as one thread, no abort.

    The fits use float64 products and the fluxes are compared to 1e-12, not bit for bit:
    BLAS may split a matrix product differently when several threads call it at once,
    which changes the last bits: 2e-14 of a flux in float64, but up to 1e-6 in the default
    float32 (6e-7 has been seen; this fit's float32 and float64 fluxes differ by 5e-7),
    a scale that could hide a race. A race on a shared buffer changes them by far more."""
    res = _run("""
        import threading

        CFG = plf.Config(max_stamp_size=0, dtype="float64")
        ref = fit(3)
        out = []
        threads = [threading.Thread(target=lambda: out.extend(fit(3) for _ in range(3)))
                   for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        np.testing.assert_allclose(out, [ref] * 12, rtol=1e-12)
    """)
    assert res.returncode == 0, res.stderr
