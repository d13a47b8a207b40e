"""Metacalibration in the image pipeline (``Config(response="metacal")``) and the
metacal estimator with the selection response (``pylensfit.shear.selection``).

The field: exponential galaxies sheared by a known ``g`` (sky frame, a WCS turned by 30
degrees), and its rotated twin (every galaxy turned by 90 degrees before the shear), so
that the shape noise cancels in the pair and the test's error is that of the pixel noise
alone.
"""

from __future__ import annotations

import numpy as np
import pytest
from astropy.table import Table

import pylensfit as plf
from pylensfit.catalogue import COLUMNS, JOINT_COLUMNS, METACAL_COLUMNS
from pylensfit.cli import main
from pylensfit.flags import METACAL_FLAGS
from pylensfit.images.catalogue_io import metacal_to_sky
from pylensfit.shear import MetacalSample, metacal_selections, selection_response, shear_table
from pylensfit.skyframe import SkyFrame, to_sky

pytestmark = pytest.mark.filterwarnings("ignore::pylensfit.calibration.CalibrationWarning")

G = (0.04, -0.02)
CFG = plf.Config(model="exponential", n_bulge_fractions=1, r_max=6.0, r_step=0.3)


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    """The two images, their PSF, and the metacal and model catalogues of both."""
    from pylensfit_validation.simulate import FieldSpec, field_psf, simulate_field, write_field

    d = tmp_path_factory.mktemp("mcal")
    paths = []
    for rot in (False, True):
        spec = FieldSpec(size=288, spacing=40.0, jitter=4.0, model="exponential", g1=G[0],
                         g2=G[1], star_fraction=0.0, rotate=rot, wcs_rotation_deg=30.0)
        img, w, truth = simulate_field(spec, seed=5)
        paths.append(d / f"field{int(rot)}.fits")
        write_field(paths[-1], img, w, spec, truth=truth)
    psf = field_psf(spec).drawImage(nx=32, ny=32, scale=1.0, use_true_center=False).array
    kw = {"priors": plf.Priors(), "psf": psf, "progress": False}
    out = d / "mcal.fits"
    mcal = plf.measure(paths, config=CFG.replace(response="metacal"), output=out, **kw)
    model = plf.measure(paths, config=CFG, **kw)
    return paths, kw, mcal, model, out


def test_the_metacal_columns_are_there_and_finite_and_nothing_else_changes(field):
    _, _, mcal, model, _ = field
    assert len(mcal) == len(model)  # rows in, rows out
    assert not set(METACAL_COLUMNS) & set(model.colnames)  # only with response="metacal"
    assert [c for c in mcal.colnames if c in COLUMNS] == [c for c in COLUMNS
                                                        if c not in ("lnL_star", *JOINT_COLUMNS)]
    for c in model.colnames:  # the other columns as a run without the metacalibration
        if c != "lnL":
            a, b = np.asarray(mcal[c]), np.asarray(model[c])
            assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), c
    gal = np.asarray(mcal["weight"]) > 0
    assert gal.sum() > 60
    ok = gal & (np.asarray(mcal["mcal_flags"]) == 0)
    assert ok.sum() >= 0.95 * gal.sum()
    for c in METACAL_COLUMNS:
        assert np.isfinite(np.asarray(mcal[c], dtype=float)[ok]).all(), c
    not_done = METACAL_FLAGS["NOT_METACALIBRATED"][0]
    assert ((np.asarray(mcal["mcal_flags"])[~np.isfinite(mcal["lnL"]).all(axis=1)]
             & not_done) != 0).all()  # fmt: skip
    # the unsheared image's S/N: the image's less its doubled noise variance's share
    ratio = np.asarray(mcal["mcal_snr_noshear"])[ok] / np.asarray(mcal["model_SNratio"])[ok]
    assert 0.6 < np.median(ratio) < 0.8
    assert mcal.meta["metacal_step"] == CFG.metacal_step


def test_the_metacal_shear_is_the_true_shear(field):
    _, _, mcal, _, _ = field
    r = MetacalSample.of(mcal, min_snr=0.0).shear()
    assert 0.85 < r.R_gamma[0, 0] < 1.1 and 0.85 < r.R_gamma[1, 1] < 1.1
    # the error of the pixel noise alone: the twins' shapes averaged pairwise (the same
    # objects at the same positions in both images)
    sel = MetacalSample.of(mcal, min_snr=0.0).selections["noshear"]
    idx = np.asarray(mcal["image_index"])
    a, b = (mcal[sel & (idx == k)] for k in (0, 1))
    d2 = ((np.asarray(a["x_detect"])[:, None] - np.asarray(b["x_detect"])[None]) ** 2
          + (np.asarray(a["y_detect"])[:, None] - np.asarray(b["y_detect"])[None]) ** 2)
    near = np.argmin(d2, axis=1)
    same = d2[np.arange(len(a)), near] < 1.0
    pa, pb = a[same], b[near[same]]
    assert len(pa) > 30
    pair = 0.5 * np.column_stack([pa["e1_mcal"] + pb["e1_mcal"], pa["e2_mcal"] + pb["e2_mcal"]])
    err = np.abs(np.linalg.inv(r.R_gamma + r.R_S)) @ (pair.std(axis=0, ddof=1)
                                                      / np.sqrt(len(pair)))  # fmt: skip
    assert np.all(err < 0.012)
    np.testing.assert_array_less(np.abs(r.g - np.array(G)), 3 * err)
    # per image as the other estimators; the table's "all" row is the sample's shear
    tab = shear_table(mcal, by="image", estimator="metacal", min_snr=0.0)
    assert list(tab["group"])[-1] == "all" and len(tab) == 3
    np.testing.assert_allclose([tab["g1"][-1], tab["g2"][-1]], r.g, rtol=1e-12)


def test_the_same_input_gives_the_same_metacal_columns(field):
    paths, kw, mcal, _, _ = field
    again = plf.measure(paths[:1], config=CFG.replace(response="metacal"), **kw)
    first = mcal[np.asarray(mcal["image_index"]) == 0]
    assert len(again) == len(first)
    for c in METACAL_COLUMNS:
        assert np.array_equal(np.asarray(again[c]), np.asarray(first[c]), equal_nan=True), c
    other = plf.measure(paths[:1], config=CFG.replace(response="metacal", metacal_seed=1), **kw)
    assert not np.array_equal(np.asarray(other["e1_mcal"]), np.asarray(first["e1_mcal"]),
                              equal_nan=True)  # fmt: skip


def test_a_resumed_run_gives_the_same_catalogue(field, tmp_path, monkeypatch):
    import pylensfit.images.passes as passes  # the image tasks, to kill one

    paths, kw, mcal, _, _ = field
    real, out = passes.image_task, tmp_path / "resumed.fits"

    def killed(t):
        if t.path.endswith("field1.fits"):
            raise KeyboardInterrupt("killed")
        return real(t)

    monkeypatch.setattr(passes, "image_task", killed)
    with pytest.raises(KeyboardInterrupt):
        plf.measure(paths, config=CFG.replace(response="metacal"), output=out, **kw)
    assert len(list((tmp_path / "resumed.fits.parts").glob("*field0*.fits"))) == 1
    monkeypatch.setattr(passes, "image_task", real)
    again = plf.measure(paths, config=CFG.replace(response="metacal"), output=out, **kw)
    assert len(again) == len(mcal)
    for c in (*METACAL_COLUMNS, "e1", "weight"):
        assert np.array_equal(np.asarray(again[c]), np.asarray(mcal[c]), equal_nan=True), c


def test_the_shear_command_gives_the_metacal_estimate(field, tmp_path, capsys):
    _, _, mcal, _, out = field
    back = plf.read_catalogue(out)
    assert set(METACAL_COLUMNS) <= set(back.colnames)
    t = tmp_path / "shear.ecsv"
    assert main(["shear", str(out), "--estimator", "metacal", "-o", str(t)]) == 0
    capsys.readouterr()
    tab = Table.read(t)
    r = MetacalSample.of(mcal).shear()  # the catalogue's own min_snr
    np.testing.assert_allclose([tab["g1"][-1], tab["g2"][-1]], r.g, rtol=1e-10)
    np.testing.assert_allclose([tab["g1_err"][-1], tab["g2_err"][-1]], r.g_err, rtol=1e-10)
    # a catalogue measured with response "metacal" gets that estimator by default, and says so
    d = tmp_path / "default.ecsv"
    assert main(["shear", str(out), "-o", str(d)]) == 0
    assert "--estimator fixed-point for the model's" in capsys.readouterr().out
    np.testing.assert_array_equal(Table.read(d)["g1"], tab["g1"])
    f = tmp_path / "model.ecsv"
    assert main(["shear", str(out), "--estimator", "fixed-point", "-o", str(f)]) == 0
    assert not np.allclose(Table.read(f)["g1"], tab["g1"])


def test_the_response_turns_to_the_sky_as_a_spin_2_tensor():
    rng = np.random.default_rng(1)
    n = 5
    R = rng.normal(1.0, 0.2, (n, 2, 2))
    g = rng.normal(0.0, 0.05, (n, 2))
    e = np.einsum("nij,nj->ni", R, g)  # pixel frame: e = R g
    frame = SkyFrame(angle=rng.uniform(-180, 180, n), flip=np.array([0, 1, 0, 1, 0], bool),
                     g1=np.zeros(n), g2=np.zeros(n), has_wcs=np.ones(n, bool))
    cat = Table({"e1_mcal": e[:, 0], "e2_mcal": e[:, 1]})
    for i in range(2):
        for j in range(2):
            cat[f"R{i + 1}{j + 1}"] = R[:, i, j]
    metacal_to_sky(cat, frame)
    gs = np.column_stack(to_sky(g[:, 0], g[:, 1], frame))
    Rs = np.stack([np.column_stack([cat[f"R{i}{j}"] for j in (1, 2)]) for i in (1, 2)], axis=1)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", Rs, gs),
                               np.column_stack([cat["e1_mcal"], cat["e2_mcal"]]), atol=1e-12)


def _branch(e_int: np.ndarray, gamma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A synthetic measurement of galaxies of intrinsic shapes ``e_int`` under the shear
    ``gamma``: the shape ``e = e_int + 0.8 gamma`` and an S/N ``20 + 25 |e|^2`` (the more
    elongated the brighter: isotropic, so that ``<e> = 0`` without shear, but a galaxy
    sheared along its shape passes a cut more often)."""
    e = e_int + 0.8 * np.asarray(gamma)
    return e, 20.0 + 25.0 * np.sum(e * e, axis=1)


def _selected_sample(e_int: np.ndarray, g: np.ndarray, step: float) -> Table:
    """The metacalibration columns of :func:`_branch` under the shear ``g``."""
    n = len(e_int)
    t = Table()
    for typ, d in {"noshear": (0, 0), "1p": (step, 0), "1m": (-step, 0), "2p": (0, step),
                   "2m": (0, -step)}.items():  # fmt: skip
        e, snr = _branch(e_int, g + np.array(d))
        if typ == "noshear":
            t["e1_mcal"], t["e2_mcal"] = e[:, 0], e[:, 1]
        t[f"mcal_snr_{typ}"] = snr
    for i in range(2):
        for j in range(2):
            t[f"R{i + 1}{j + 1}"] = np.full(n, 0.8 if i == j else 0.0)
    t["mcal_flags"] = np.zeros(n, dtype=np.int32)
    t["flags"] = np.zeros(n, dtype=np.int32)
    return t


def test_the_selection_response_corrects_the_bias_of_a_cut():
    g, step = np.array([0.03, -0.02]), 0.01
    e_int = np.random.default_rng(3).normal(0.0, 0.25, (1_000_000, 2))
    t = _selected_sample(e_int, g, step)
    cut = float(np.median(t["mcal_snr_noshear"]))  # a hard cut at the sample's median
    s = MetacalSample.of(t, min_snr=cut, step=step)
    r = s.shear()
    np.testing.assert_allclose(r.R_gamma, 0.8 * np.eye(2), atol=1e-9)
    # the sample's true response: its mean shape under the shears g +- h, each selected
    # with its own S/N
    h, true = 0.005, np.empty((2, 2))
    for j in range(2):
        mean = []
        for sgn in (1, -1):
            e, snr = _branch(e_int, g + sgn * h * np.eye(2)[j])
            mean.append(e[snr >= cut].mean(axis=0))
        true[:, j] = (mean[0] - mean[1]) / (2 * h)
    assert true[0, 0] > 0.9 and true[1, 1] > 0.9  # the cut adds to 0.8
    np.testing.assert_allclose(r.R_gamma + r.R_S, true, atol=0.012)
    np.testing.assert_allclose(r.g, g, atol=4 * r.g_err.max())
    sel = s.selections["noshear"]
    biased = np.linalg.solve(r.R_gamma, [np.mean(t["e1_mcal"][sel]), np.mean(t["e2_mcal"][sel])])
    assert np.all(np.abs(biased - g) > 10 * r.g_err)  # without R_S: far off
    # the same sample without a cut: no selection response
    r0 = MetacalSample.of(t, min_snr=0.0, step=step).shear()
    assert abs(r0.R_S).max() < 1e-9


def test_a_table_without_its_configuration_is_cut_at_no_snr_with_a_warning():
    """A catalogue read without ``pylensfit.read_catalogue`` (``Table.read``) has lost its
    configuration, and with it ``Config.min_snr``: the selection then cuts nowhere, which
    it says, and a given ``min_snr`` is used silently."""
    t = _selected_sample(np.zeros((10, 2)), np.zeros(2), 0.01)
    t["mcal_snr_noshear"][0] = 1.0
    with pytest.warns(UserWarning, match="no S/N cut"):
        s = MetacalSample.of(t, step=0.01)
    assert s.selections["noshear"].all()
    assert not MetacalSample.of(t, step=0.01, min_snr=2.0).selections["noshear"][0]


def test_each_branch_selects_on_its_own_quantities():
    t = _selected_sample(np.zeros((10, 2)), np.zeros(2), 0.01)
    t["mcal_flags"][0] = METACAL_FLAGS["1p"][0]
    t["mcal_flags"][1] = METACAL_FLAGS["NOT_METACALIBRATED"][0]
    t["flags"][2] = plf.flags.flag_value("STAR", "LOW_SNR")  # the unsheared fit's decisions
    t["flags"][3] = plf.flags.flag_value("CLOSE_PAIR")
    t["mcal_snr_2m"][4] = 1.0
    sel = metacal_selections(t, min_snr=2.0)
    assert sel["noshear"].tolist() == [True, False, True, False] + [True] * 6
    assert sel["1p"].tolist() == [False, False, True, False] + [True] * 6
    assert sel["2m"].tolist() == [True, False, True, False, False] + [True] * 5
    with pytest.raises(ValueError, match="empty sample"):
        selection_response(np.zeros((10, 2)), {**sel, "1m": np.zeros(10, bool)}, 0.01)
    with pytest.raises(ValueError, match="metacalibration column"):
        metacal_selections(Table({"e1": [0.0]}), 0.0)
