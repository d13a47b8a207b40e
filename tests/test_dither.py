"""Dithered simulations: a small set written, read back, and every galaxy where its
truth position says in every exposure."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS

from pylensfit.exposures import Exposure, StampFlag, cut_stamps, flux_scale_from_zero_point
from pylensfit_validation.cli import simulate_main
from pylensfit_validation.dither import DitherSpec, read_dither, simulate_dither

galsim = pytest.importorskip("galsim")

#: bright, small and well apart: a centroid's noise of ~0.01 px, no neighbour's light
SPEC = DitherSpec(n_exposures=3, ngal=6, snr_range=(300.0, 400.0), size_range=(0.24, 0.45),
                  spacing=16.0, star_field_size=96)


@pytest.fixture(scope="module")
def dither_set(tmp_path_factory):
    return read_dither(simulate_dither(tmp_path_factory.mktemp("dither"), SPEC, seed=3))


def test_a_small_set_is_written_and_reads_back(dither_set):
    s = dither_set
    assert s.spec == SPEC and s.seed == 3 and len(s.exposures) == 3
    assert len(s.truth) == 6
    for c in ("ra", "dec", "e1_int", "e2_int", "e1", "e2", "g1", "g2", "r", "flux", "model"):
        assert c in s.truth.colnames
    assert len({e.psf_fwhm for e in s.exposures}) == 3
    assert all(abs(e.psf_fwhm / SPEC.psf_fwhm - 1) <= 0.15 for e in s.exposures)
    assert all(abs(e.rotation) <= 1.0 and abs(e.offset_w) <= 30 for e in s.exposures)
    assert sum(e.flip for e in s.exposures) == 1
    for k, e in enumerate(s.exposures):
        with fits.open(s.path(k)) as h:
            assert h[0].header["MAGZP"] == e.zero_point and h[0].header["SIMFLIP"] == e.flip
            assert h[0].data.shape == (SPEC.image_size,) * 2
            gap = h["WEIGHT"].data[:, SPEC.image_size // 2]
            assert np.all(gap == 0) and np.all(h[0].data[:, SPEC.image_size // 2] == 0)
            assert len(h["TRUTH"].data) == 6
        with fits.open(s.star_path(k)) as h:
            assert h[0].header["SIMROT"] == e.rotation and np.all(h["TRUTH"].data["is_star"])
            cd = WCS(h[0].header).pixel_scale_matrix
            assert cd[0, 0] == pytest.approx(exposure_cd11(e), rel=1e-9)


def exposure_cd11(e) -> float:
    t = np.radians(e.rotation)
    return -e.pixel_scale / 3600.0 * np.cos(t)


def test_the_truth_positions_land_on_the_galaxies_in_every_exposure(dither_set):
    """The adaptive-moment centroid of every galaxy in every exposure is within 0.1 px
    of its truth sky position through the exposure's WCS (measured: within 0.03 px)."""
    s = dither_set
    measured = 0
    for k, e in enumerate(s.exposures):
        ex = Exposure.from_fits(s.path(k), reference_zero_point=SPEC.zero_point)
        assert ex.flux_scale == pytest.approx(flux_scale_from_zero_point(e.zero_point, 30.0))
        st = cut_stamps(ex, s.truth["ra"], s.truth["dec"], size=40)
        with fits.open(s.path(k)) as h:
            on = np.asarray(h["TRUTH"].data["on_data"], bool)
        assert np.all(st.flags[~on] & StampFlag.CENTRE_MASKED)
        cx, cy = st.centres
        for i in np.flatnonzero(st.usable):
            mom = galsim.hsm.FindAdaptiveMom(galsim.ImageD(st.stamps[i]))
            c = mom.moments_centroid
            assert abs(c.x - 1.0 - cx[i]) < 0.1 and abs(c.y - 1.0 - cy[i]) < 0.1, (k, i)
            measured += 1
    assert measured >= 12  # of 18: a galaxy in a chip gap, or beside one, is left out


def test_the_set_is_deterministic(dither_set, tmp_path):
    again = read_dither(simulate_dither(tmp_path / "a", SPEC, seed=3))
    other = read_dither(simulate_dither(tmp_path / "b", SPEC, seed=4))
    with fits.open(dither_set.path(1)) as a, fits.open(again.path(1)) as b:
        assert np.array_equal(a[0].data, b[0].data)
    assert np.array_equal(again.truth["ra"], dither_set.truth["ra"])
    assert not np.array_equal(other.truth["e1_int"], dither_set.truth["e1_int"])


def test_simulate_dither_from_the_command_line(tmp_path, capsys):
    assert simulate_main(["dither", "--exposures", "3", "--ngal", "4", "--seed", "2",
                          "--star-field-size", "64", "--out", str(tmp_path)]) == 0  # fmt: skip
    s = read_dither(tmp_path)
    assert len(s.exposures) == 3 and len(s.truth) == 4
    assert "3 exposures" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        simulate_main(["step1", "--exposures", "3", "--out", str(tmp_path / "x")])
