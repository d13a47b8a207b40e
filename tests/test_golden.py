"""Golden catalogues: ``measure`` on two fixed-seed fields and ``measure_stamps`` on
fixed-seed stamps give the numbers of ``tests/data/golden.npz`` (written by
``python tests/golden.py``), to float32 round-off. A change of the package's layout
changes none of them; a change of the method writes the file again, with the reason in
its commit."""

from __future__ import annotations

import numpy as np
import pytest

from golden import DATA, measured

pytestmark = pytest.mark.filterwarnings("ignore::pylensfit.calibration.CalibrationWarning")


def test_measure_and_measure_stamps_give_the_golden_numbers(tmp_path):
    want = np.load(DATA)
    got = measured(tmp_path)
    assert set(got) == set(want.files)
    for k in sorted(want.files):
        a, b = np.asarray(got[k]), want[k]
        assert a.shape == b.shape, k
        if k.endswith("flags"):
            np.testing.assert_array_equal(a, b, err_msg=k)
        else:
            np.testing.assert_allclose(a, b, rtol=2e-4, atol=2e-6, equal_nan=True,
                                       err_msg=k)  # fmt: skip
    n_gal = int(np.sum((want["cat_flags"] == 0) & (want["cat_weight"] > 0)))
    assert n_gal >= 100 and int(np.sum(want["stamps_weight"] > 0)) >= 100
