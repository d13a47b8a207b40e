"""``pylensfit validate --dither``: two small dithered sets of one seed that differ by
their shear, through the joint fit and one exposure alone."""

from __future__ import annotations

import numpy as np
import pytest

from pylensfit import Config
from pylensfit.cli import main
from pylensfit_validation.dither import DitherSpec, simulate_dither
from pylensfit_validation.dither_validate import validate_dither

pytest.importorskip("galsim")

SPEC = dict(n_exposures=2, ngal=16, snr_range=(200.0, 300.0), size_range=(0.3, 0.5),
            spacing=10.0, star_field_size=160)  # fmt: skip


@pytest.fixture(scope="module")
def paired(tmp_path_factory):
    d = tmp_path_factory.mktemp("dv")
    return [simulate_dither(d / name, DitherSpec(g1=g, g2=-g, **SPEC), seed=4)
            for name, g in (("p", 0.05), ("m", -0.05))]  # fmt: skip


@pytest.mark.filterwarnings("ignore::pylensfit.CalibrationWarning")
def test_paired_sets_give_m_and_c_with_errors_of_the_pair(paired, tmp_path):
    """Bright galaxies: m near zero; the jackknife leaves each sky cell out of both
    sets at once, so the error is that of the pair's difference, well below what the
    sets' shape noise gives alone (about 0.25 / sqrt(16) / 0.05 = 1.25 in m). With
    ``response="metacal"`` each catalogue's metacalibration estimate is a method too."""
    # the models not cut at the stamps' edges (seconds per exposure and tier)
    cfg = Config(truncate_models=False, response="metacal")
    res = validate_dither(paired, out=tmp_path, config=cfg)
    assert list(res.shears["method"]) == ["joint 2", "joint 2 mcal", "exposure 0",
                                          "exposure 0 mcal"] * 2  # fmt: skip
    assert list(res.bias["method"]) == ["joint 2", "joint 2 mcal", "exposure 0",
                                        "exposure 0 mcal"]  # fmt: skip
    assert np.all(res.bias["n"] >= 2 * 14)
    # 16 galaxies do not measure the metacalibration's m (one galaxy crossing a cut moves
    # the selection response by ~e / (16 * 2 step)); its per-set shears, which the same
    # shape noise dominates, are the model's
    sh = res.shears
    for name in ("p", "m"):
        joint = sh[(sh["set"] == name) & (sh["method"] == "joint 2")][0]
        mcal = sh[(sh["set"] == name) & (sh["method"] == "joint 2 mcal")][0]
        assert abs(mcal["g1"] - joint["g1"]) < 0.02 and abs(mcal["g2"] - joint["g2"]) < 0.02
    for row in res.bias[[not m.endswith("mcal") for m in res.bias["method"]]]:
        for c in ("m1", "m2"):
            assert 0 < row[c + "_err"] < 0.15, (row["method"], c)
            assert abs(row[c]) < 3 * row[c + "_err"] + 0.02, (row["method"], c)
        for c in ("c1", "c2"):  # the 16 galaxies' shape noise, which +g and -g share
            assert abs(row[c]) < 0.2, (row["method"], c)
    # the PSF stacked from each star field is the true one (GalSim's), in shape and size
    assert np.all(np.abs(res.psf["de1"]) < 2e-3) and np.all(np.abs(res.psf["de2"]) < 2e-3)
    assert np.all(np.abs(res.psf["dsigma"]) < 5e-3)
    assert (tmp_path / "p_joint.fits").exists() and (tmp_path / "m_exp0.fits").exists()


def test_the_command_needs_a_set(capsys, tmp_path):
    rc = main(["validate", "--dither", str(tmp_path / "missing")])
    err = capsys.readouterr().err
    assert rc != 0 and "missing" in err and "Traceback" not in err
