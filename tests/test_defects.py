"""An unmasked bright defect (a saturated star, a bleed trail, a hot pixel) spoils no galaxy
far from it: its badly fitted model is flagged DEFECT and kept out of its neighbours' stamps
and out of the sky; saturated pixels are masked (SATURATED); a row's flags never contradict
its fitclass, weight and shape."""

import logging

import numpy as np
import pytest
from astropy.io import fits
from scipy.spatial import cKDTree

from conftest import check_catalogue_invariants
from pylensfit import Config, Prior, fit_stamps
from pylensfit.config import ConfigError
from pylensfit.detection import grow_mask, saturation_level, saturation_mask
from pylensfit.flags import flag_value
from pylensfit.pipeline import measure, read_catalogue
from pylensfit_validation.simulate import FieldSpec, simulate_field, write_field

CFG = Config.paper(model="exponential", r_max=6.0, r_step=0.3)
PRIOR = Prior()
SPEC = FieldSpec(size=512, star_fraction=0.0, psf_e1=0.0, psf_e2=0.0)
FAR = 3 * CFG.stamp_size  # px: no galaxy farther than this from a defect may change
DEFECT, SATURATED, MASKED = (flag_value(k) for k in ("DEFECT", "SATURATED", "MASKED"))


def _psf() -> np.ndarray:
    import galsim

    return galsim.Moffat(beta=SPEC.psf_beta, fwhm=SPEC.psf_fwhm).drawImage(
        nx=64, ny=64, scale=1.0).array


def _measure(path, tmp_path, config=CFG, name="cat"):
    out = tmp_path / f"{name}.fits"
    cat = measure([path], psf=_psf(), config=config, prior=PRIOR, output=out, progress=False)
    check_catalogue_invariants(cat)
    check_catalogue_invariants(read_catalogue(out))
    return cat


#: the field's seed and where the defects go: between galaxies (17 px from the nearest in
#: x or y, so no close pair: the defect is fitted and, before, its model was rendered into
#: its neighbours' stamps and the sky)
SEED, SPOT = 5, (300, 250)


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    """The simulated field (121 galaxies), its clean catalogue and the defects' spot."""
    d = tmp_path_factory.mktemp("defects")
    img, w, truth = simulate_field(SPEC, seed=SEED)
    cheb = np.maximum(np.abs(truth["x"] - SPOT[0]), np.abs(truth["y"] - SPOT[1]))
    assert cheb.min() > CFG.stamp_size / 2
    clean = d / "clean.fits"
    write_field(clean, img, w, SPEC)
    cat = _measure(clean, d, name="clean_cat")
    return d, np.asarray(img, dtype=np.float64), w, SPOT, cat


def _with(field, name, change, card=None):
    d, img, w, _, _ = field
    data = img.copy()
    change(data)
    p = d / f"{name}.fits"
    write_field(p, data.astype(np.float32), w, SPEC)
    if card is not None:
        with fits.open(p, mode="update") as h:
            h[0].header["SATURATE"] = card
    return p


def _compare(clean, cat, at) -> tuple[np.ndarray, np.ndarray]:
    """``(lost, moved)`` booleans over the clean catalogue's usable galaxies farther than
    FAR from ``at``: no usable row at the same detection any more, or e1 / e2 moved by
    more than 0.01."""
    dist, j = cKDTree(np.column_stack([cat["x_detect"], cat["y_detect"]])).query(
        np.column_stack([clean["x_detect"], clean["y_detect"]]), distance_upper_bound=1.0)
    far = np.hypot(clean["x_detect"] - at[0], clean["y_detect"] - at[1]) > FAR
    use = far & (np.asarray(clean["weight"]) > 0)
    found = np.isfinite(dist)
    j = np.where(found, j, 0)
    kept = found & (np.asarray(cat["weight"])[j] > 0)
    lost = use & ~kept
    de = np.fmax(np.abs(np.asarray(cat["e1"])[j] - clean["e1"]),
                 np.abs(np.asarray(cat["e2"])[j] - clean["e2"]))
    moved = use & kept & ~(de <= 0.01)
    assert use.sum() > 60  # most of the field is far from the defect
    return lost, moved


def _near(cat, at, radius):
    return np.hypot(cat["x_detect"] - at[0], cat["y_detect"] - at[1]) < radius


@pytest.mark.parametrize("kind", ["block 65000", "block 1e9", "pixel 1e30"])
def test_an_unmasked_defect_spoils_no_far_galaxy(field, tmp_path, kind):
    """A 10x10 block at 65,000 or 1e9 ADU or one pixel at 1e30, unmasked and without a
    SATURATE card. Before, the defect's model, rendered into its neighbours' stamps and
    the sky, lost 0 / 43 / 47 of the galaxies beyond three stamp widths (NO_PEAK) and
    moved 2 / 58 / 57 more by > 0.01 in e, up to 360 px away; now none at all (the two
    galaxies whose stamps hold the block are DEFECT), and the defect's rows are flagged."""
    *_, (x0, y0), clean = field

    def change(data):
        if kind.startswith("block"):
            data[y0 - 5 : y0 + 5, x0 - 5 : x0 + 5] = float(kind.split()[1])
        else:
            data[y0, x0] = 1e30

    cat = _measure(_with(field, kind.replace(" ", "_"), change), tmp_path)
    lost, moved = _compare(clean, cat, (x0, y0))
    assert lost.sum() == 0 and moved.sum() == 0, (lost.sum(), moved.sum())
    own = _near(cat, (x0, y0), 8)
    assert own.any(), "the defect is detected"
    assert (cat["flags"][own] != 0).all() and (cat["weight"][own] == 0).all()
    assert (cat["flags"][own] & DEFECT).any()


def test_defect_flagged_without_neighbour_subtraction(field, tmp_path):
    """With neither neighbours nor sky modelled the defect spoils nothing, and is still
    flagged: its model does not fit its stamp."""
    *_, (x0, y0), _ = field

    def change(data):
        data[y0 - 5 : y0 + 5, x0 - 5 : x0 + 5] = 65000.0

    cfg = CFG.replace(subtract_neighbours=False, model_background=False)
    cat = _measure(_with(field, "plain", change), tmp_path, config=cfg)
    own = _near(cat, (x0, y0), 8)
    assert own.any() and (cat["flags"][own] & DEFECT).all()
    assert (cat["weight"][own] == 0).all()


def _saturated_star(x0, y0, flux=3e7, level=60000.0):
    import galsim

    def change(data):
        star = galsim.Moffat(beta=SPEC.psf_beta, fwhm=SPEC.psf_fwhm).withFlux(flux).drawImage(
            nx=96, ny=96, scale=1.0, center=galsim.PositionD(x0 + 1, y0 + 1))
        b = star.bounds
        data[b.ymin - 1 : b.ymax, b.xmin - 1 : b.xmax] += star.array
        np.minimum(data, level, out=data)  # the detector's full well

    return change


@pytest.mark.parametrize("how", ["SATURATE card", "Config.saturation"])
def test_saturated_star_is_masked_and_flagged(field, tmp_path, how):
    """A star 40 times above the full well: with the level known (the image's SATURATE
    card, as SExtractor reads it, or Config.saturation) its core is masked before the
    detection and the fit; the rows on it are SATURATED (and MASKED), weight 0, and no
    galaxy far from it moves."""
    *_, (x0, y0), clean = field
    level = 60000.0
    by_card = how == "SATURATE card"
    p = _with(field, how.replace(" ", "_").replace(".", "_"), _saturated_star(x0, y0),
              card=level if by_card else None)  # fmt: skip
    cfg = CFG if by_card else CFG.replace(saturation=level)
    cat = _measure(p, tmp_path, config=cfg)
    on = _near(cat, (x0, y0), CFG.stamp_size / 2)
    assert on.any(), "the star's unmasked wings are detected"
    assert (cat["flags"][on] & SATURATED).all() and (cat["flags"][on] & MASKED).all()
    assert (cat["weight"][on] == 0).all()
    lost, moved = _compare(clean, cat, (x0, y0))
    assert lost.sum() == 0 and moved.sum() == 0, (lost.sum(), moved.sum())


def test_saturation_level_and_mask(caplog):
    hdr = fits.Header({"SATURATE": 5000.0})
    assert saturation_level(hdr) == 5000.0
    assert saturation_level(hdr, 100.0) == 100.0  # Config.saturation wins
    assert saturation_level(fits.Header()) is None
    with caplog.at_level(logging.WARNING, logger="pylensfit.detection"):
        assert saturation_level(fits.Header({"SATURATE": "lots"})) is None
    assert "SATURATE card 'lots'" in caplog.text
    img = np.zeros((20, 30))
    img[10, 15] = 7000.0
    img[2, 3] = np.nan  # masked apart, not a saturated pixel
    m = saturation_mask(img, 5000.0, grow=2)
    assert m.sum() == 25 and m[8:13, 13:18].all()
    assert not saturation_mask(img, None).any()
    assert saturation_mask(img, 5000.0, grow=0).sum() == 1
    g = grow_mask(~np.isfinite(img), 1)
    assert g.sum() == 9 and g[1:4, 2:5].all()
    corner = np.zeros((5, 5), dtype=bool)
    corner[0, 0] = True
    assert grow_mask(corner, 1).sum() == 4  # clipped at the edges


def test_config_checks_the_new_settings():
    for bad in ({"saturation": -1.0}, {"saturation": "high"}, {"saturation_grow": -1},
                {"max_reduced_chi2": 1.0}, {"max_residual_fraction": 0.0}):
        with pytest.raises(ConfigError):
            Config(**bad)
    assert Config.from_dict(Config(saturation=6e4).to_dict()).saturation == 6e4
    assert Config().saturation is None


def test_absurd_stamp_fails_the_fit_without_warnings():
    """A stamp 1e25 times a galaxy gives ln L a range beyond float32's: the row is
    FIT_FAILED with NaN ln L (it was flags 0 with -inf cells, so not measured)."""
    import galsim

    psf = galsim.Moffat(beta=3.5, fwhm=3.0)
    gal = galsim.Convolve(galsim.Exponential(scale_radius=2.0).shear(g1=0.2, g2=0.1), psf)
    stamp = gal.drawImage(nx=32, ny=32, scale=1.0).array
    p = psf.drawImage(nx=32, ny=32, scale=1.0).array
    f = fit_stamps(np.stack([1e3 * stamp, 1e25 * stamp]), p, 1.0, config=CFG)
    assert f.flags[0] == 0 and np.isfinite(f.lnL[0]).all()
    assert f.flags[1] & flag_value("FIT_FAILED") and np.isnan(f.lnL[1]).all()
