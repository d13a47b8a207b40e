"""The realistic galaxy population of the STEP2-like sets (``FieldSpec.population``)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from pylensfit import cli
from pylensfit_validation.cli import simulate_main as main
from pylensfit_validation.galaxies import REALISTIC, draw_bulge_shapes
from pylensfit_validation.simulate import (
    FieldSpec,
    pixel_to_sky_shear,
    sky_to_pixel_shear,
    to_pixel_frame,
)
from pylensfit_validation.step import _step2_galaxy
from pylensfit_validation.validation import (
    read_manifest,
    render_step2_field,
    simulate_step,
)

galsim = pytest.importorskip("galsim")

#: one galaxy at the centre, noise nil (S/N 1e9), no sky, a round PSF
_ONE = FieldSpec(size=81, jitter=0.0, star_fraction=0.0, psf_e1=0.0, psf_e2=0.0, sky=0.0,
                 snr_range=(1e9, 1e9), size_range=(3.0, 3.0),
                 population="realistic")  # fmt: skip
#: a seed whose galaxy in ``_ONE`` is a bulge+disc (bulge fraction 0.41, misaligned by -56
#: degrees)
_ONE_SEED = 10


def _hsm(img: np.ndarray) -> galsim.hsm.ShapeData:
    return galsim.hsm.FindAdaptiveMom(galsim.ImageD(img.astype(np.float64), scale=1.0))


def _unweighted_g(img: np.ndarray) -> complex:
    """The reduced-shear ellipticity of the unweighted second moments of a pixelised
    profile, less the pixel's (``1/12`` on the diagonal)."""
    y, x = np.mgrid[: img.shape[0], : img.shape[1]]
    f = img.sum()
    cx, cy = (img * x).sum() / f, (img * y).sum() / f
    qxx = (img * (x - cx) ** 2).sum() / f - 1.0 / 12
    qyy = (img * (y - cy) ** 2).sum() / f - 1.0 / 12
    qxy = (img * (x - cx) * (y - cy)).sum() / f
    chi = complex(qxx - qyy, 2 * qxy) / (qxx + qyy)
    return chi / (1 + np.sqrt(1 - abs(chi) ** 2))


def test_aligned_is_the_default_and_realistic_keeps_the_objects():
    """The aligned population is the default; the realistic one draws after it, so it has
    the same objects, S/N, sizes, disc shapes and stars, and other galaxies' pixels."""
    spec = FieldSpec(size=200, g1=0.03, g2=-0.02, size_range=(1.5, 4.5), star_fraction=0.15)
    img0, _, t0 = render_step2_field(spec, seed=6)
    img_a, _, t_a = render_step2_field(replace(spec, population="aligned"), seed=6)
    img_r, _, t_r = render_step2_field(replace(spec, population="realistic"), seed=6)
    assert np.array_equal(img0, img_a) and t0.colnames == t_a.colnames
    for c in t0.colnames:
        assert np.array_equal(t0[c], t_a[c], equal_nan=t0[c].dtype.kind == "f")
    assert "misalign" not in t0.colnames and "bulge_size_ratio" not in t0.colnames
    assert "pop" not in t0.meta and t_r.meta["pop"] == "realistic"
    star = np.asarray(t0["is_star"])
    assert star.any() and len(t0) >= 16
    for c in ("x", "y", "is_star", "r", "snr", "e1_int", "e2_int", "e1", "e2", "kind",
              "n_knots"):  # fmt: skip
        assert np.array_equal(t_r[c], t0[c], equal_nan=t0[c].dtype.kind == "f"), c
    assert np.array_equal(t_r["bulge_frac"], t0["bulge_frac"], equal_nan=True)
    assert np.array_equal(t_r["flux"][star], t0["flux"][star])  # galaxies': their S/N's
    assert not np.allclose(img_r, img0)
    sersic = np.asarray(t0["kind"]) == "sersic"
    assert not np.array_equal(t_r["sersic_n"][sersic], t0["sersic_n"][sersic])
    no_bulge = star | sersic
    for c in ("misalign", "bulge_size_ratio"):
        assert np.isnan(t_r[c][no_bulge]).all() and np.isfinite(t_r[c][~no_bulge]).all()


def test_realistic_population_ranges():
    """Misaligned bulges (30 degrees rms for bulge+disc, 10 for knotty discs), bulges of
    their own size, Sersic indices log-uniform over 0.3-6."""
    spec = FieldSpec(size=320, spacing=20.0, jitter=0.0, star_fraction=0.0,
                     size_range=(1.5, 2.0), population="realistic")  # fmt: skip
    _, _, t = render_step2_field(spec, seed=2)
    kind = np.asarray(t["kind"])
    mis = np.asarray(t["misalign"], float)
    bd, kn = kind == "bulge+disc", kind == "knots"
    assert bd.sum() >= 50 and kn.sum() >= 50
    assert 20 < np.sqrt(np.mean(mis[bd] ** 2)) < 40
    assert 5 < np.sqrt(np.mean(mis[kn] ** 2)) < 15
    assert np.abs(mis[bd | kn]).max() <= 90 and np.isnan(mis[kind == "sersic"]).all()
    ratio = np.asarray(t["bulge_size_ratio"], float)[bd | kn]
    lo, hi = REALISTIC["bulge_size_ratio"]
    assert lo <= ratio.min() and ratio.max() <= hi and np.ptp(ratio) > 0.3
    n = np.asarray(t["sersic_n"], float)[kind == "sersic"]
    assert n.min() < 0.5 and n.max() > 4 and n.min() >= 0.3 and n.max() <= 6
    np.testing.assert_allclose(n, np.round(n, 1), atol=1e-12)  # quantised


def test_realistic_twin_is_the_rotated_original():
    """The twin's truth: the same galaxies and bulges, their intrinsic shapes negated."""
    spec = FieldSpec(size=160, star_fraction=0.1, g1=0.02, g2=0.04, wcs_rotation_deg=30.0,
                     wcs_flip=True, population="realistic")  # fmt: skip
    _, _, t = render_step2_field(spec, seed=8)
    _, _, tw = render_step2_field(replace(spec, rotate=True), seed=8)
    for c in ("e1_int", "e2_int", "e1_int_sky", "e2_int_sky"):
        np.testing.assert_allclose(tw[c], -t[c], atol=1e-15)
    for c in ("misalign", "bulge_size_ratio", "sersic_n", "snr", "flux"):
        np.testing.assert_allclose(tw[c], t[c], rtol=1e-6)


@pytest.mark.parametrize("rot, flip", [(0.0, False), (30.0, True)])
def test_realistic_twin_moments_are_rotated(rot, flip):
    """A bright bulge+disc galaxy with a misaligned bulge and its twin (no lensing shear,
    round PSF): the adaptive moments go e -> -e, the size unchanged."""
    spec = replace(_ONE, wcs_rotation_deg=rot, wcs_flip=flip)
    img, _, t = render_step2_field(spec, seed=_ONE_SEED)
    twin, _, _ = render_step2_field(replace(spec, rotate=True), seed=_ONE_SEED)
    assert t["kind"][0] == "bulge+disc" and abs(t["misalign"][0]) > 30
    m, mt = _hsm(img), _hsm(twin)
    g, gt = m.observed_shape, mt.observed_shape
    assert abs(g.g1) + abs(g.g2) > 0.1
    assert abs(gt.g1 + g.g1) < 1e-3 and abs(gt.g2 + g.g2) < 1e-3
    assert abs(mt.moments_sigma / m.moments_sigma - 1) < 1e-3


@pytest.mark.parametrize("twin", [False, True])
def test_realistic_galaxy_is_the_same_on_the_sky_for_grid_symmetric_frames(twin):
    """The bulges' shapes are the sky frame's: the frames that map pixels onto pixels
    give the plain field's image transposed, rotated or flipped about the galaxy."""
    spec = replace(_ONE, g1=0.03, g2=0.05, rotate=twin)
    plain, _, t = render_step2_field(spec, seed=_ONE_SEED)
    assert t["kind"][0] == "bulge+disc" and t["x"][0] == 40.0 and t["y"][0] == 40.0
    expect = {(90.0, True): plain.T, (90.0, False): np.rot90(plain, 1),
              (180.0, False): np.rot90(plain, 2), (0.0, True): plain[::-1]}  # fmt: skip
    for (rot, flip), ref in expect.items():
        img, _, tf = render_step2_field(replace(spec, wcs_rotation_deg=rot, wcs_flip=flip),
                                        seed=_ONE_SEED)  # fmt: skip
        assert tf["misalign"][0] == t["misalign"][0]
        assert np.abs(img - ref).max() < 1e-4 * plain.max()
        if rot != 180.0:  # a bulge+disc galaxy is symmetric under a half turn
            assert np.abs(img - plain).max() > 0.03 * plain.max()


@pytest.mark.parametrize("rot, flip", [(0.0, False), (30.0, True)])
def test_bulge_ends_misaligned_on_the_sky(rot, flip):
    """render_step2_field's construction of a bulge (a bulge fraction of 1): its own
    shear in the sky frame, the pixel frame, the disc's intrinsic shape, the twin's
    rotation. On the sky the bulge ends misaligned with its disc by ``misalign``, less
    elongated, and the twin's bulge is the original's rotated by 90 degrees."""
    e_sky = np.array([[0.35, -0.2]])
    size_ratio, b1, b2, dphi = draw_bulge_shapes([True], [False], e_sky,
                                                 np.random.default_rng(4))  # fmt: skip
    spec = FieldSpec(wcs_rotation_deg=rot, wcs_flip=flip)
    e0 = sky_to_pixel_shear(e_sky[0, 0], e_sky[0, 1], rot, flip)
    out = []
    for twin in (False, True):
        gal = _step2_galaxy("bulge+disc", 4.0, 1.0, 1.0, 0.3, 10, 1,
                            bulge_size_ratio=float(size_ratio[0]),
                            bulge_shear=(float(b1[0]), float(b2[0])))  # fmt: skip
        gal = to_pixel_frame(gal, spec).shear(g1=float(e0[0]), g2=float(e0[1]))
        if twin:
            gal = gal.rotate((-90 if flip else 90) * galsim.degrees)
        g = _unweighted_g(gal.drawImage(nx=128, ny=128, scale=1.0).array)
        out.append(complex(*pixel_to_sky_shear(g.real, g.imag, rot, flip)))
    g, gt = out
    assert abs(gt + g) < 1e-5
    ed = complex(*e_sky[0])
    pa = np.rad2deg(0.5 * (np.angle(g) - np.angle(ed)))
    assert abs(pa - dphi[0]) < 0.1 and abs(dphi[0]) > 10
    lo, hi = REALISTIC["bulge+disc e_ratio"]
    assert lo <= abs(g) / abs(ed) <= hi + 1e-3


def test_the_population_is_checked(tmp_path, capsys):
    with pytest.raises(ValueError, match="population must be one of"):
        FieldSpec(population="spiral")
    with pytest.raises(ValueError, match="population must be one of"):
        simulate_step("step2", tmp_path / "a", population="spiral")
    with pytest.raises(ValueError, match="step1 set's galaxies"):
        simulate_step("step1", tmp_path / "b", population="realistic")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    with pytest.raises(SystemExit) as err:
        main(["step2", "--out", str(tmp_path / "c"), "--population", "spiral"])
    assert err.value.code == 2
    assert "invalid choice: 'spiral'" in capsys.readouterr().err.splitlines()[-1]
    rc = cli.main(["simulate", "step1", "--out", str(tmp_path / "d"), "--population",
                   "realistic", "--quiet"])  # fmt: skip
    lines = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(lines) == 1 and "population must be 'aligned'" in lines[0]


def test_simulate_command_records_the_population(tmp_path):
    """``pylensfit simulate step2 --population realistic``: the manifest records it, and
    a field rendered again from the manifest is the file's."""
    out = tmp_path / "s2"
    assert cli.main(["simulate", "step2", "--out", str(out), "--ngal", "40", "--size",
                     "120", "--nshear", "1", "--population", "realistic", "--quiet"]) == 0
    man = read_manifest(out)
    assert man["population"] == "realistic" and man["fieldspec"]["population"] == "realistic"
    f = next(f for f in man["fields"] if f["twin"] and f["psf"] == 3)
    fs = {k: tuple(v) if isinstance(v, list) else v for k, v in man["fieldspec"].items()}
    p = f["psf_params"]
    spec = FieldSpec(**{**fs, "psf_fwhm": p["fwhm"], "psf_beta": p["beta"], "psf_e1": p["e1"],
                        "psf_e2": p["e2"], "g1": f["g1"], "g2": f["g2"], "rotate": f["twin"]})
    img, _, truth = render_step2_field(spec, seed=f["seed"], noise_seed=f["noise_seed"])
    assert np.array_equal(img, fits.getdata(f["path"]))
    t = Table.read(f["path"], hdu="TRUTH")
    assert np.array_equal(t["misalign"], truth["misalign"], equal_nan=True)
    assert t.meta["POP"] == "realistic"
    simulate_step("step2", tmp_path / "a", ngal=8, field_size=80, n_shear=1,
                  psfs=(man["psfs"][0],))  # fmt: skip
    assert read_manifest(tmp_path / "a")["population"] == "aligned"  # the default, recorded
