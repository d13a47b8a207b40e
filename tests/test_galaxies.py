"""The simulations' galaxy and PSF builders (pylensfit_validation.galaxies) against
GalSim's measures."""

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.special import gammainc, gammaincinv

from pylensfit.models import DEVAUC_TRUNCATION
from pylensfit_validation.galaxies import GalaxyProfile, PSFProfile, inner_shear

galsim = pytest.importorskip("galsim")

FINE = 0.1  # pixels per sample of the finely drawn images


def _fine(obj, n=500, scale=FINE):
    """``obj`` sampled (no pixel response) on ``n x n`` samples of ``scale`` pixels."""
    return obj.drawImage(nx=n, ny=n, scale=scale, method="no_pixel")


def _sersic_enclosed(n: float, hlr: float, trunc: float):
    """Enclosed-flux fraction ``F(R)`` of a Sersic profile truncated at ``trunc > 0`` whose
    truncated profile has half-light radius ``hlr`` (GalSim's convention), analytic."""
    b = gammaincinv(2 * n, 0.5)

    def untruncated(R, re):  # the untruncated profile of effective radius re
        return gammainc(2 * n, b * (R / re) ** (1 / n))

    re = brentq(lambda re: untruncated(hlr, re) - 0.5 * untruncated(trunc, re), 0.5 * hlr,
                5 * hlr)  # fmt: skip
    return lambda R: untruncated(np.minimum(R, trunc), re) / untruncated(trunc, re)


def _exponential_enclosed(scale_radius: float):
    return lambda R: 1.0 - (1.0 + R / scale_radius) * np.exp(-R / scale_radius)


@pytest.mark.parametrize(
    "size_kind, size, bulge_fraction, ratio",
    [("scale", 2.0, 0.5, 0.6), ("half_light", 3.0, 0.3, 0.5)],  # STEP1's, STEP2's
)
def test_bulge_disc_flux_split_and_half_light_radius(size_kind, size, bulge_fraction, ratio):
    p = GalaxyProfile("bulge+disc", size, size_kind=size_kind, bulge_fraction=bulge_fraction,
                      bulge_size_ratio=ratio)  # fmt: skip
    gal = p.galsim()
    bulge, disc = gal.obj_list
    assert isinstance(bulge, galsim.DeVaucouleurs) and isinstance(disc, galsim.Exponential)
    assert bulge.flux == pytest.approx(bulge_fraction)
    assert disc.flux == pytest.approx(1.0 - bulge_fraction)
    assert gal.flux == pytest.approx(1.0)
    rs = size if size_kind == "scale" else size / 1.6783469900166605
    assert disc.scale_radius == pytest.approx(rs)
    rb = ratio * size
    assert bulge.half_light_radius == pytest.approx(rb)
    assert bulge.trunc == pytest.approx(DEVAUC_TRUNCATION * rb)

    fb = _sersic_enclosed(4.0, rb, DEVAUC_TRUNCATION * rb)
    fd = _exponential_enclosed(rs)
    want = brentq(lambda R: bulge_fraction * fb(R) + (1 - bulge_fraction) * fd(R) - 0.5,
                  0.01, 10 * size)  # fmt: skip
    assert _fine(gal).calculateHLR() == pytest.approx(want, rel=0.02)


@pytest.mark.parametrize("n", [0.5, 1.5, 3.5])
def test_sersic_half_light_radius_and_truncation(n):
    gal = GalaxyProfile("sersic", 2.0, sersic_n=n).galsim()
    assert gal.trunc == (DEVAUC_TRUNCATION * 2.0 if n > 2 else 0.0)
    assert _fine(gal).calculateHLR() == pytest.approx(2.0, rel=0.02)


@pytest.mark.parametrize("kind", ["exponential", "devaucouleurs"])
def test_single_profiles_by_half_light_radius_and_by_model(kind):
    gal = GalaxyProfile(kind, 2.5).galsim()
    assert _fine(gal).calculateHLR() == pytest.approx(2.5, rel=0.02)
    model = GalaxyProfile.from_model(kind, 2.5).galsim()  # exponential: scale length
    want = 2.5 * (1.6783469900166605 if kind == "exponential" else 1.0)
    assert model.half_light_radius == pytest.approx(want)


def test_knots_flux_fraction_follow_the_disc_and_seed():
    p = GalaxyProfile("knots", 2.0, bulge_fraction=0.2, knot_fraction=0.3, n_knots=4000,
                      knot_seed=11)  # fmt: skip
    gal = p.galsim()
    bulge, disc, knots = gal.obj_list
    assert isinstance(knots, galsim.RandomKnots) and knots.npoints == 4000
    assert (bulge.flux, disc.flux, knots.flux) == pytest.approx((0.2, 0.8 * 0.7, 0.8 * 0.3))
    assert disc.half_light_radius == pytest.approx(2.0)
    # the knots are drawn from a profile of the disc's half-light radius
    assert np.median(np.hypot(*knots.points.T)) == pytest.approx(2.0, rel=0.06)
    psf = galsim.Gaussian(sigma=1.0)

    def img(seed):
        obj = galsim.Convolve(GalaxyProfile("knots", 2.0, knot_fraction=0.3, n_knots=30,
                                            knot_seed=seed).galsim(), psf)  # fmt: skip
        return obj.drawImage(nx=32, ny=32, scale=1.0).array

    a = img(5)
    assert a.sum() == pytest.approx(1.0, abs=0.01)
    assert np.array_equal(a, img(5)) and not np.array_equal(a, img(6))


@pytest.mark.parametrize("kind, fwhm", [("moffat", 3.0), ("kolmogorov", 4.0)])
def test_psf_fwhm_and_ellipticity(kind, fwhm):
    assert _fine(PSFProfile(kind, fwhm).galsim(), 400).calculateFWHM() == pytest.approx(
        fwhm, rel=0.01
    )
    psf = PSFProfile(kind, fwhm, beta=2.5, e1=0.06, e2=-0.04).galsim()
    mom = galsim.hsm.FindAdaptiveMom(_fine(psf, 128, 0.25))
    assert (mom.observed_shape.g1, mom.observed_shape.g2) == pytest.approx((0.06, -0.04), abs=1e-4)


def test_asymmetric_psf_lobe():
    p = PSFProfile.from_dict({"name": "asymmetric", "kind": "asymmetric", "fwhm": 3.0,
                              "beta": 3.5, "e1": 0.0, "e2": 0.0, "lobe_flux": 0.2,
                              "lobe_shift": 1.0})  # fmt: skip
    img = _fine(p.galsim(), 400).array.astype(float)
    y, x = (np.indices(img.shape) - (img.shape[0] - 1) / 2) * FINE
    assert img.sum() == pytest.approx(1.0, abs=0.01)
    assert (x * img).sum() / img.sum() == pytest.approx(0.2 * 1.0, abs=0.01)
    assert (y * img).sum() / img.sum() == pytest.approx(0.0, abs=1e-6)


def test_from_dict_and_errors():
    kol = PSFProfile.from_dict({"kind": "kolmogorov", "fwhm": 4.0, "e1": 0.0, "e2": 0.03})
    assert (kol.kind, kol.fwhm, kol.e2) == ("kolmogorov", 4.0, 0.03)
    assert PSFProfile.from_dict({"fwhm": 3.0, "beta": 3.0, "e1": 0.1, "e2": 0.0}).kind == "moffat"
    with pytest.raises(KeyError):
        PSFProfile.from_dict({"fwhm": 3.0, "e1": 0.0, "e2": 0.0})  # a Moffat needs beta
    with pytest.raises(ValueError, match="unknown PSF kind"):
        PSFProfile("airy", 3.0)
    with pytest.raises(ValueError, match="unknown galaxy kind"):
        GalaxyProfile("spiral", 2.0)
    with pytest.raises(ValueError, match="half-light radius"):
        GalaxyProfile("devaucouleurs", 2.0, size_kind="scale")
    with pytest.raises(ValueError, match="size must be > 0"):
        GalaxyProfile("exponential", 0.0)
    with pytest.raises(ValueError, match="unknown model"):
        GalaxyProfile.from_model("sersic", 2.0)
    with pytest.raises(ValueError, match="bulge_shear"):
        GalaxyProfile("bulge+disc", 2.0, bulge_shear=(0.8, 0.7))


def test_inner_shear_ends_a_component_at_its_target_shape():
    """GalSim's adaptive moments of a Gaussian sheared by ``inner_shear(outer, target)``
    and then by ``outer`` give ``target``; the naive ``target - outer`` does not."""
    rng = np.random.default_rng(4)
    outer = rng.uniform(-0.35, 0.35, (5, 2))
    target = rng.uniform(-0.35, 0.35, (5, 2))
    b1, b2 = inner_shear(outer, target)
    for o, t, g1, g2 in zip(outer, target, b1, b2, strict=True):
        obj = galsim.Gaussian(sigma=6.0).shear(g1=g1, g2=g2).shear(g1=o[0], g2=o[1])
        shape = _fine(obj, n=160, scale=1.0).FindAdaptiveMom().observed_shape
        assert shape.g1 == pytest.approx(t[0], abs=1e-5)
        assert shape.g2 == pytest.approx(t[1], abs=1e-5)
        naive = galsim.Gaussian(sigma=6.0).shear(g1=t[0] - o[0], g2=t[1] - o[1])
        nshape = _fine(naive.shear(g1=o[0], g2=o[1]), n=160, scale=1.0).FindAdaptiveMom()
        assert np.hypot(nshape.observed_shape.g1 - t[0], nshape.observed_shape.g2 - t[1]) > 1e-3


def test_bulge_with_its_own_shape_inside_a_round_disc():
    """A bulge+disc galaxy whose bulge has its own shear: the sum of a sheared bulge and
    a round disc, pixel for pixel, with the flux split unchanged."""
    prof = GalaxyProfile("bulge+disc", 3.0, bulge_fraction=0.4, bulge_shear=(0.3, -0.2))
    img = _fine(prof.galsim(), n=200, scale=0.25).array
    bulge = galsim.DeVaucouleurs(half_light_radius=1.5, trunc=DEVAUC_TRUNCATION * 1.5)
    ref = galsim.Add(bulge.withFlux(0.4).shear(g1=0.3, g2=-0.2),
                     galsim.Exponential(half_light_radius=3.0).withFlux(0.6))  # fmt: skip
    np.testing.assert_allclose(img, _fine(ref, n=200, scale=0.25).array, rtol=0, atol=1e-9)
    round_ = _fine(GalaxyProfile("bulge+disc", 3.0, bulge_fraction=0.4).galsim(), n=200,
                   scale=0.25).FindAdaptiveMom().observed_shape  # fmt: skip
    shaped = galsim.Image(img, scale=0.25).FindAdaptiveMom().observed_shape
    assert abs(round_.g1) < 1e-4 and shaped.g1 > 0.02 and shaped.g2 < -0.01
