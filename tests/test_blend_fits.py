"""Fits with several PSFs blended as with a PSF in between (likelihood.blend_fits)."""

import galsim
import numpy as np
import pytest

from conftest import draw
from pylensfit import Config, Prior, fit_stamps, shapes
from pylensfit.likelihood import blend_fits

CFG = Config.paper(model="exponential", r_max=6.0, r_step=0.3)


def _psf(e1):
    img = draw(galsim.Moffat(beta=3.5, fwhm=3.0).shear(g1=e1, g2=0.0))
    return img / img.sum()


@pytest.fixture(scope="module")
def stamps():
    """Noise-free galaxies under the PSF of e1 = 0.04, with a nominal noise of S/N ~ 40."""
    rng = np.random.default_rng(5)
    psf = galsim.Moffat(beta=3.5, fwhm=3.0).shear(g1=0.04, g2=0.0)
    out = []
    for _ in range(12):
        e1, e2 = rng.uniform(-0.4, 0.4, 2)
        gal = galsim.Exponential(half_light_radius=rng.uniform(1.5, 3.0)).shear(g1=e1, g2=e2)
        out.append(draw(galsim.Convolve(gal, psf), flux=400.0))
    return np.array(out, dtype=np.float32)


def _e(fits):
    sh = shapes(fits.lnL, fits.egrid, Prior())
    return np.column_stack([sh["e1"], sh["e2"]])


def test_blend_of_the_neighbouring_psfs_is_the_psf_between(stamps):
    """Galaxies under the PSF of e1 = 0.04 fitted with the PSFs of e1 = 0 and 0.08 and
    blended half and half give the shapes of the fits with the true PSF, to a small
    fraction of the error that either PSF alone leaves."""
    f0, f8, f4 = (fit_stamps(stamps, _psf(e), 1.0, config=CFG) for e in (0.0, 0.08, 0.04))
    blended = blend_fits([f0, f8], np.full((2, len(stamps)), 0.5))
    err_one = np.abs(_e(f0) - _e(f4))[:, 0].mean()
    err_blend = np.abs(_e(blended) - _e(f4))[:, 0].mean()
    assert err_one > 5e-3  # the wrong PSF shows: about -0.86 times its 0.04
    assert err_blend < 0.05 * err_one, (err_blend, err_one)
    # ln L: the mean of the two grids, shifted to a peak of 0
    assert np.allclose(np.nanmax(blended.lnL, axis=1), 0.0, atol=1e-5)
    assert np.all(blended.flags == (f0.flags | f8.flags))


def test_blend_weights(stamps):
    f0, f8 = (fit_stamps(stamps[:4], _psf(e), 1.0, config=CFG) for e in (0.0, 0.08))
    w = np.array([[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0]])
    b = blend_fits([f0, f8], w)
    for k, f in ((0, f0), (1, f8)):  # a weight of one is that PSF's fit
        np.testing.assert_allclose(b.lnL[k::2], f.lnL[k::2], atol=1e-5)
        np.testing.assert_allclose(b.flux[k::2], f.flux[k::2])
    assert blend_fits([f0], np.ones((1, 4))) is f0
    with pytest.raises(ValueError, match="shape"):
        blend_fits([f0, f8], np.ones((2, 3)) / 2)
    with pytest.raises(ValueError, match="sum to 1"):
        blend_fits([f0, f8], np.ones((2, 4)))
