"""One schema, one assemble step: ``measure_stamps`` on stamps and ``measure`` on an image
give the same columns (the stamps table's a subset of the catalogue's, same names, units
and meanings) and, on the same galaxies seen through the same pixels, the same numbers.

The image is a lattice of well-separated GalSim galaxies with white noise; ``measure``
reads it with a constant weight map, a given PSF image (``psf=``) and forced positions
(an input catalogue), under one given :class:`~pylensfit.Priors`, with the neighbours'
subtraction and the sky's second measurement off (``Config(subtract_neighbours=False,
model_background=False)``: both change the pixels of a refit, which a stamp has no
neighbours or sky for). The stamps are cut from the same image less the same background
(:func:`pylensfit.detection.measure_background` with the pipeline's arguments) at the
same positions, with the PSF as ``measure`` keeps it (unit sum) and the weight map's
noise.

What may differ, by the method: the catalogue's ``x, y`` are image pixels, the stamps'
stamp pixels (their offsets from the catalogue positions, ``x - x_detect``, agree); a
flagged row keeps its shapes in the stamps table and is NaN in the catalogue (none is
flagged here).
"""

from __future__ import annotations

import galsim
import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

import pylensfit as plf
from pylensfit.calibration.stamps import STAMP_COLUMNS
from pylensfit.catalogue import COLUMNS
from pylensfit.detection import measure_background
from pylensfit.psf import psf_from_image
from pylensfit.stamps import cut_stamps

pytestmark = pytest.mark.filterwarnings("ignore::pylensfit.calibration.CalibrationWarning")

SIGMA = 1.0
SIDE = 64  # the largest stamp (Config().largest_stamp): every galaxy fitted on one tier
PSF = galsim.Moffat(beta=3.5, fwhm=3.0).shear(g1=0.02, g2=-0.01)


def _image(seed: int = 11) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A field of 5 x 5 exponentials 60 px apart, 40 px from the edges, S/N ~ 30-80."""
    rng = np.random.default_rng(seed)
    n = 5 * 60 + 20
    img = galsim.ImageF(n, n, scale=1.0)
    xs, ys = [], []
    for i in range(5):
        for j in range(5):
            x, y = 40.0 + 60 * i + rng.uniform(-0.5, 0.5), 40.0 + 60 * j + rng.uniform(-0.5, 0.5)
            e = rng.uniform(0, 0.4) * np.exp(2j * rng.uniform(0, np.pi))
            gal = galsim.Exponential(half_light_radius=rng.uniform(1.2, 2.5))
            gal = gal.withFlux(rng.uniform(400, 1200)).shear(g1=e.real, g2=e.imag)
            st = galsim.Convolve(gal, PSF).drawImage(nx=48, ny=48, scale=1.0,
                                                     center=galsim.PositionD(x + 1, y + 1))
            b = st.bounds & img.bounds
            img[b] += st[b]
            xs.append(x)
            ys.append(y)
    img.addNoise(galsim.GaussianNoise(galsim.BaseDeviate(seed), sigma=SIGMA))
    return img.array.astype(np.float32), np.array(xs), np.array(ys)


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("one_schema")
    data, x, y = _image()
    weight = np.full(data.shape, 1.0 / SIGMA**2, dtype=np.float32)
    path = tmp / "field.fits"
    fits.HDUList([fits.PrimaryHDU(data), fits.ImageHDU(weight, name="WEIGHT")]).writeto(path)
    cat_path = tmp / "positions.fits"
    Table({"x": x, "y": y}).write(cat_path)
    psf_img = PSF.drawImage(nx=32, ny=32, scale=1.0, offset=(0.5, 0.5)).array
    cfg = plf.Config(subtract_neighbours=False, model_background=False)
    assert cfg.largest_stamp == SIDE
    bkg = measure_background(data.astype(float), mask=np.zeros(data.shape, bool),
                             weight=weight, box=cfg.background_box)  # fmt: skip
    stamps, cx, cy, sflags = cut_stamps(bkg.subtract(data), x, y, SIDE)
    assert not sflags.any()
    psf = psf_from_image(psf_img).image  # as measure keeps a given PSF image
    # one set of priors for both paths, the bulge fractions mixed under uneven weights
    runs = len(cfg.bulge_runs)
    assert runs > 1
    priors = plf.Priors(bulge_weights=np.linspace(1.0, 2.0, runs) / np.linspace(1.0, 2.0,
                                                                                 runs).sum())
    cat = plf.measure([path], catalogues=[cat_path], psf=psf_img, priors=priors,
                      config=cfg, progress=False)  # fmt: skip
    tab = plf.measure_stamps(stamps, psf, SIGMA, priors=priors, config=cfg, centres=(cx, cy))
    return cat, tab


def test_the_stamps_columns_are_catalogue_columns(both):
    cat, tab = both
    assert set(STAMP_COLUMNS) <= set(COLUMNS)
    named = [c for c in tab.colnames if c != "lnL"]
    assert named == list(STAMP_COLUMNS)
    assert set(tab.colnames) <= set(cat.colnames)
    for c in named:  # same units and descriptions
        assert (tab[c].unit, tab[c].description) == (cat[c].unit, cat[c].description), c
    for old in ("snr", "flux", "r_best", "stamp"):
        assert old not in tab.colnames


def test_both_paths_give_the_same_numbers(both):
    cat, tab = both
    assert len(cat) == len(tab) == 25
    np.testing.assert_array_equal(cat["flags"], tab["flags"])
    ok = np.asarray(tab["flags"]) == 0
    assert ok.sum() >= 20
    np.testing.assert_array_equal(cat["fitclass"], tab["fitclass"])
    np.testing.assert_array_equal(cat["stamp_size"], tab["stamp_size"])
    for c in ("e1", "e2", "e1_var", "e2_var", "e12_cov", "sens1", "sens2", "model_SNratio",
              "model_flux", "scalelength", "e1_best", "e2_best", "noise_sigma", "weight"):
        np.testing.assert_allclose(np.asarray(cat[c])[ok], np.asarray(tab[c])[ok], rtol=2e-5,
                                   atol=1e-7, err_msg=c)  # fmt: skip
    for a, b in (("x", "x_detect"), ("y", "y_detect")):  # image vs stamp pixels
        np.testing.assert_allclose(np.asarray(cat[a] - cat[b])[ok],
                                   np.asarray(tab[a] - tab[b])[ok], atol=1e-6)  # fmt: skip
    np.testing.assert_allclose(np.asarray(cat["lnL"])[ok], np.asarray(tab["lnL"])[ok],
                               rtol=1e-5, atol=1e-4)  # fmt: skip
