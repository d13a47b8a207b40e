"""Shared helpers: GalSim renderings with the pylensfit centring convention."""

import galsim
import numpy as np
import pytest

N = 32


def draw(obj, n=N, offset=(0.0, 0.0), flux=1.0):
    """Draw ``obj`` (with the pixel response) on ``n x n`` centred on element [n//2, n//2].

    GalSim centres an even-sized image on the half-integer ``true_center``; an extra
    half-pixel offset puts the profile centre on the integer element [n//2, n//2].
    """
    half = 0.5 if n % 2 == 0 else 0.0
    return obj.withFlux(flux).drawImage(
        nx=n, ny=n, scale=1.0, offset=(offset[0] + half, offset[1] + half)
    ).array


def galsim_model(model, r, e1=0.0, e2=0.0, bulge_fraction=0.5, bulge_size_ratio=0.6):
    """The pylensfit model of size ``r`` (pixels) and ellipticity ``e`` as a GalSim object."""
    from pylensfit.models import DEVAUC_TRUNCATION as T

    if model == "exponential":
        prof = galsim.Exponential(scale_radius=r)
    elif model == "devaucouleurs":
        prof = galsim.DeVaucouleurs(half_light_radius=r, trunc=T * r)
    else:
        rb = bulge_size_ratio * r
        prof = galsim.Add(
            galsim.DeVaucouleurs(half_light_radius=rb, trunc=T * rb).withFlux(bulge_fraction),
            galsim.Exponential(scale_radius=r).withFlux(1.0 - bulge_fraction),
        )
    return prof.shear(g1=e1, g2=e2)


PSFS = {
    "moffat_round": galsim.Moffat(beta=3.5, fwhm=3.0),
    "moffat_e1": galsim.Moffat(beta=3.5, fwhm=3.2).shear(g1=0.08, g2=0.0),
    "kolmogorov_e2": galsim.Kolmogorov(fwhm=3.5).shear(g1=-0.03, g2=0.07),
}


@pytest.fixture(scope="session")
def psfs():
    return PSFS


@pytest.fixture
def rng():
    return np.random.default_rng(20081208)
