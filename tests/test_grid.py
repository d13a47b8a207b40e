import numpy as np
import pytest

from pylensfit import ellipticity_grid
from pylensfit.grid import grid_step


def test_paper_grid_is_cell_centres_inside_unit_circle():
    g = ellipticity_grid(0.1)
    # 20 x 20 cells minus the corners outside |e| < 1
    assert g.shape[0] < 400
    assert np.all(np.hypot(g[:, 0], g[:, 1]) < 1)
    # never a point at e = 0; nearest points are (+-0.05, +-0.05)
    assert np.min(np.hypot(g[:, 0], g[:, 1])) == pytest.approx(np.hypot(0.05, 0.05))
    # point-symmetric and symmetric under e1 <-> e2 (needed for rotation invariance)
    s = {tuple(np.round(p, 9)) for p in g}
    assert {tuple(np.round(-p, 9)) for p in g} == s
    assert {tuple(np.round(p[::-1], 9)) for p in g} == s
    assert grid_step(g) == pytest.approx(0.1)


def test_grid_count_matches_area():
    # number of cells ~ pi / step^2 for a fine grid
    g = ellipticity_grid(0.02)
    assert abs(g.shape[0] * 0.02**2 - np.pi) < 0.02


def test_bad_step():
    with pytest.raises(ValueError, match="step"):
        ellipticity_grid(0.0)
