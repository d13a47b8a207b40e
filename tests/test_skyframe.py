"""Shapes in the sky frame: the WCS's local Jacobian, checked with second moments and
with GalSim renderings made in world coordinates."""

import galsim
import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS

from pylensfit import Config, Prior, estimate_shear, measure
from pylensfit.skyframe import local_frame, shear_to_pixel, to_sky

SCALE = 0.2 / 3600.0  # deg / pixel


def _rot(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s], [s, c]])


def _jac(theta_deg=0.0, flip=False, dist=(0.0, 0.0)):
    """``d(W, N)/d(x, y)`` in degrees per pixel: rotation, distortion, flip."""
    g1, g2 = dist
    S = np.array([[1 + g1, g2], [g2, 1 - g1]]) / np.sqrt(1 - g1 * g1 - g2 * g2)
    F = np.diag([1.0, -1.0]) if flip else np.eye(2)
    return SCALE * _rot(np.radians(theta_deg)) @ S @ F


def _wcs(J, n=1024, ra0=150.0, dec0=2.0):
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [ra0, dec0]
    w.wcs.crpix = [n / 2 + 0.5, n / 2 + 0.5]
    w.wcs.cd = np.diag([-1.0, 1.0]) @ J  # (dRA cos dec, dDec) = (-dW, dN)
    return w


def _shape_of_moments(Q):
    """``(a - b)/(a + b)`` ellipticity of a second-moment matrix."""
    d = np.sqrt(np.linalg.det(Q))
    den = Q[0, 0] + Q[1, 1] + 2 * d
    return (Q[0, 0] - Q[1, 1]) / den, 2 * Q[0, 1] / den


def _moments_of_shape(e1, e2):
    S = np.array([[1 + e1, e2], [e2, 1 - e1]])
    return S @ S.T


def test_plain_wcs_is_the_pixel_frame():
    fr = local_frame(_wcs(_jac()), [512.0, 10.0], [512.0, 1000.0])
    assert not fr.flip.any() and fr.has_wcs.all()
    # the tangent plane's frame turns by ~1e-3 deg at 0.06 deg from its centre at dec 2
    assert np.all(np.abs(fr.angle) < 2e-3) and np.all(np.abs(fr.g1) < 1e-6)
    e1, e2 = to_sky(0.3, -0.2, fr)
    np.testing.assert_allclose([e1, e2], [[0.3, 0.3], [-0.2, -0.2]], atol=1e-4)


@pytest.mark.parametrize("theta,flip,dist", [(30.0, False, (0, 0)), (-70.0, True, (0, 0)),
                                             (110.0, True, (0.01, -0.02)),
                                             (0.0, False, (0.03, 0.01))])
def test_the_ellipse_maps_as_its_moments(theta, flip, dist):
    J = _jac(theta, flip, dist)
    fr = local_frame(_wcs(J), [512.0], [512.0])
    assert fr.flip[0] == flip
    for e in [(0.3, 0.1), (-0.05, 0.4), (0.0, -0.6)]:
        want = _shape_of_moments(J @ _moments_of_shape(*e) @ J.T)  # what the sky sees
        got = to_sky(np.array([e[0]]), np.array([e[1]]), fr)
        np.testing.assert_allclose([got[0][0], got[1][0]], want, atol=2e-6)
        back = shear_to_pixel(got[0], got[1], fr)
        np.testing.assert_allclose([back[0][0], back[1][0]], e, atol=1e-10)


def _world_field(path, J, g_sky, seed=3, n=768, spacing=32):
    """Galaxies sheared by ``g_sky`` in world coordinates (u, v) = (W, N), drawn by GalSim
    through the Jacobian; each galaxy and its 90-degree twin (in the world frame)."""
    rng = np.random.default_rng(seed)
    gw = galsim.JacobianWCS(*(J * 3600.0).ravel())  # dudx, dudy, dvdx, dvdy (arcsec)
    img = galsim.ImageF(n, n, wcs=gw)
    psf = galsim.Moffat(beta=3.5, fwhm=0.6)  # arcsec: round on the sky and on the pixels
    pos = np.arange(spacing, n - spacing + 1, spacing, dtype=float)
    xs, ys = np.meshgrid(pos, pos)
    xs, ys = xs.ravel(), ys.ravel()
    k = xs.size // 2
    e = rng.uniform(0.05, 0.45, k) * np.exp(2j * rng.uniform(0, np.pi, k))
    e = np.concatenate([e, -e])  # the 90-degree twins
    r = np.tile(rng.uniform(0.45, 0.7, k), 2)  # scale radius, arcsec
    for i in range(2 * k):
        gal = galsim.Exponential(scale_radius=r[i], flux=400.0).shear(g1=e[i].real,
                                                                       g2=e[i].imag)
        gal = galsim.Convolve(gal.shear(g1=g_sky[0], g2=g_sky[1]), psf)
        gal.drawImage(image=img, center=galsim.PositionD(xs[i] + 1, ys[i] + 1),
                      add_to_image=True)  # fmt: skip
    arr = img.array + np.random.default_rng(seed + 1).normal(0, 1.0, (n, n))
    hdr = _wcs(J, n).to_header()
    fits.PrimaryHDU(arr.astype(np.float32), header=hdr).writeto(path)
    pimg = psf.drawImage(nx=32, ny=32, wcs=gw.local(), offset=(0.5, 0.5)).array
    return pimg


@pytest.mark.parametrize("theta,flip", [(0.0, False), (35.0, True)])
def test_a_rotated_flipped_field_gives_the_sky_shear(tmp_path, theta, flip):
    g_sky = (0.05, -0.03)
    J = _jac(theta, flip)
    psf = _world_field(tmp_path / "f.fits", J, g_sky)
    cfg = Config.paper(model="exponential", r_max=6.0, r_step=0.3, min_snr=0.0)
    cat = measure([tmp_path / "f.fits"], psf=psf, config=cfg, prior=Prior(), progress=False)
    assert cat.meta["frame"] == "sky"
    use = (cat["flags"] == 0) & (cat["fitclass"] == 0)
    assert use.sum() > 400
    assert np.all(np.abs(cat["sky_angle"][use] - theta) < 0.01)
    assert np.all(cat["sky_flip"][use] == flip)
    # the pixel-frame shapes are the sky-frame ones taken back
    if theta:
        assert abs(np.mean(cat["e2_pix"][use]) - np.mean(cat["e2"][use])) > 0.02
    for est in ("fixed-point", "key2"):
        g = estimate_shear(cat, estimator=est)
        # the twins cancel the shape noise: a frame or sign error would be 0.05-0.1 off
        assert abs(g.g1 - g_sky[0]) < 0.008 and abs(g.g2 - g_sky[1]) < 0.008, (est, g)
