"""Exposures of a field: local WCS Jacobians against closed forms and GalSim, GalSim
renderings through the Jacobian against renderings with the WCS, stamps and their
usable flags."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS

from pylensfit.exposures import (
    Exposure,
    StampFlag,
    cut_exposures,
    cut_stamps,
    flux_scale_from_zero_point,
    galaxy_views,
    local_jacobian,
    sky_offsets_to_world,
    sky_to_exposure_shear,
    sky_to_pixel,
)

galsim = pytest.importorskip("galsim")


def rot(deg: float) -> np.ndarray:
    t = np.radians(deg)
    return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])


def shear_matrix(g1: float, g2: float) -> np.ndarray:
    return np.array([[1 + g1, g2], [g2, 1 - g1]]) / np.sqrt(1 - g1 * g1 - g2 * g2)


def sky_cd(scale: float, angle: float = 0.0, flip: bool = False, g=(0.0, 0.0)) -> np.ndarray:
    """The CD matrix (degrees per pixel) of ``d(W, N)/d(x, y) = s R S F`` (arcsec)."""
    F = np.diag([1.0, -1.0 if flip else 1.0])
    return np.diag([-1.0, 1.0]) @ (scale / 3600.0 * rot(angle) @ shear_matrix(*g) @ F)


def tan_wcs(cd, crval=(150.0, 2.0), crpix=(50.5, 40.5)) -> WCS:
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = list(crval)
    w.wcs.crpix = list(crpix)
    w.wcs.cd = np.asarray(cd)
    return w


def _header(ctype: str, crval, cards: dict) -> fits.Header:
    h = fits.Header()
    h["NAXIS"], h["NAXIS1"], h["NAXIS2"] = 2, 2048, 4096
    h["CTYPE1"], h["CTYPE2"] = f"RA---{ctype}", f"DEC--{ctype}"
    h["CRVAL1"], h["CRVAL2"] = crval
    h["CRPIX1"], h["CRPIX2"] = 1024.5, 2048.5
    cd = sky_cd(0.187, angle=0.7, flip=ctype == "TPV")
    h["CD1_1"], h["CD1_2"], h["CD2_1"], h["CD2_2"] = cd.ravel()
    for k, v in cards.items():
        h[k] = v
    return h


def tpv_header() -> fits.Header:
    """A flipped, rotated TPV header (distortion polynomials in degrees, up to cubic)."""
    pv1 = {0: 0.0, 1: 1.0, 2: 0.0, 4: 2e-3, 5: -1e-3, 6: 5e-4, 7: -2e-2, 8: 1e-3, 9: -5e-3,
           10: 3e-3}  # fmt: skip
    pv2 = {0: 0.0, 1: 1.0, 2: 0.0, 4: -1e-3, 5: 2e-3, 6: 1e-3, 7: -1.5e-2, 8: 2e-3, 9: 1e-3,
           10: -4e-3}  # fmt: skip
    cards = {f"PV1_{k}": v for k, v in pv1.items()} | {f"PV2_{k}": v for k, v in pv2.items()}
    return _header("TPV", (35.0, -5.0), cards)


def sip_header() -> fits.Header:
    """A rotated TAN-SIP header (distortion polynomials in pixels, up to cubic)."""
    cards = {"A_ORDER": 3, "B_ORDER": 3, "A_2_0": 2e-6, "A_1_1": -1e-6, "A_0_2": 5e-7,
             "A_3_0": 1e-10, "A_1_2": -2e-10, "B_2_0": -1e-6, "B_1_1": 3e-6, "B_0_2": 1e-6,
             "B_0_3": 2e-10, "B_2_1": 1e-10}  # fmt: skip
    return _header("TAN-SIP", (150.0, 2.0), cards)


CASES = {
    "rotation 30": dict(scale=0.2, angle=30.0),
    "flip": dict(scale=0.2, flip=True),
    "shear": dict(scale=0.2, g=(0.05, -0.03)),
    "scale": dict(scale=0.187),
    "all": dict(scale=0.214, angle=-117.0, flip=True, g=(-0.02, 0.04)),
}


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("crval", [(150.0, 2.0), (0.0, -60.0)])
def test_jacobian_of_a_linear_wcs_is_its_cd_matrix_inverted(case, crval):
    """At the tangent point a TAN WCS is its CD matrix: ``J = (diag(-1, 1) CD)^-1``."""
    cd = sky_cd(**CASES[case])
    w = tan_wcs(cd, crval=crval)
    want = np.linalg.inv(np.diag([-1.0, 1.0]) @ cd * 3600.0)
    J = local_jacobian(w, np.full(3, crval[0]), np.full(3, crval[1]))
    assert J.shape == (3, 2, 2)
    assert np.abs(J - want).max() < 1e-8 * np.abs(want).max()
    assert np.sign(np.linalg.det(J[0])) == (-1 if CASES[case].get("flip") else 1)
    x, y = sky_to_pixel(w, crval[0], crval[1])
    assert np.allclose([x[0], y[0]], [49.5, 39.5], atol=1e-9)


def test_sky_offsets_follow_the_west_north_axes():
    ra, dec = sky_offsets_to_world([10.0, 10.0, 359.9999], [20.0, 20.0, 0.0], [36.0, 0.0, -3.6],
                                   [0.0, 36.0, 0.0])  # fmt: skip
    assert ra[0] < 10.0 and abs((10.0 - ra[0]) * np.cos(np.radians(20.0)) - 0.01) < 1e-9
    assert abs(ra[1] - 10.0) < 1e-12 and abs(dec[1] - 20.01) < 1e-9
    assert abs(ra[2] - 359.9999 - 0.001) < 1e-9 or abs(ra[2] - 0.0009) < 1e-9  # wraps east


@pytest.mark.parametrize("header", [tpv_header, sip_header], ids=["TPV", "SIP"])
def test_jacobian_matches_galsim_local_wcs_on_a_distorted_header(header):
    h = header()
    w = WCS(h)
    gw = galsim.FitsWCS(header=galsim.FitsHeader(header=h))
    rng = np.random.default_rng(3)
    x, y = rng.uniform(0, 2047, 20), rng.uniform(0, 4095, 20)
    ra, dec = w.all_pix2world(x, y, 0)
    px, py = sky_to_pixel(w, ra, dec)
    assert np.abs(px - x).max() < 1e-6 and np.abs(py - y).max() < 1e-6
    J = local_jacobian(w, ra, dec)
    lin = np.linalg.inv(np.diag([-1.0, 1.0]) @ w.wcs.cd * 3600.0)
    off = 0.0
    for i in range(x.size):
        pos = galsim.PositionD(x[i] + 1.0, y[i] + 1.0)
        local = gw.local(image_pos=pos).getMatrix()  # d(u, v)/d(x, y), arcsec per pixel
        assert np.abs(np.linalg.inv(J[i]) - local).max() < 1e-8 * np.abs(local).max()
        off = max(off, np.abs(J[i] - lin).max() / np.abs(lin).max())
        cpos = gw.toImage(galsim.CelestialCoord(ra[i] * galsim.degrees, dec[i] * galsim.degrees))
        assert abs(cpos.x - 1.0 - px[i]) < 1e-6 and abs(cpos.y - 1.0 - py[i]) < 1e-6
    assert off > 1e-4  # the distortion matters: the CD matrix alone is not J


def _render_three_ways(h: fits.Header, x: float, y: float, g: tuple[float, float]):
    """An exponential galaxy sheared by ``g`` in the sky frame at pixel ``(x, y)``: drawn
    by GalSim with the exposure's WCS, through ``J``, and as a round profile sheared by
    the pixel-frame shape of :func:`sky_to_exposure_shear`."""
    w = WCS(h)
    gw = galsim.FitsWCS(header=galsim.FitsHeader(header=h))
    ra, dec = w.all_pix2world([x], [y], 0)
    ex = Exposure(image=np.zeros((4096, 2048)), wcs=w)
    st = cut_stamps(ex, ra, dec, size=48)
    J = st.jacobian[0]
    hlr = 0.9  # arcsec
    sky = galsim.Exponential(half_light_radius=hlr).shear(g1=g[0], g2=g[1])
    bounds = galsim.BoundsI(int(st.x0[0]) + 1, int(st.x0[0]) + 48, int(st.y0[0]) + 1,
                            int(st.y0[0]) + 48)  # fmt: skip
    centre = galsim.PositionD(st.x[0] + 1.0, st.y[0] + 1.0)
    direct = sky.drawImage(image=galsim.ImageD(bounds, wcs=gw), center=centre).array
    through = sky.transform(*J.ravel()).withFlux(1.0)
    via_j = through.drawImage(image=galsim.ImageD(bounds, scale=1.0), center=centre).array
    e1, e2 = sky_to_exposure_shear([g[0]], [g[1]], st.frame)
    size = hlr * np.sqrt(abs(np.linalg.det(J)))
    pix = galsim.Exponential(half_light_radius=size).shear(g1=e1[0], g2=e2[0])
    via_e = pix.drawImage(image=galsim.ImageD(bounds, scale=1.0), center=centre).array
    return direct, via_j, via_e


@pytest.mark.parametrize("header", [tpv_header, sip_header], ids=["TPV", "SIP"])
def test_a_sky_frame_shape_rendered_through_J_is_the_galaxy_rendered_with_the_wcs(header):
    """GalSim's drawing with the exposure's WCS, with the profile carried to pixels
    through ``J``, and with the pixel-frame shape from the sky frame's agree to the
    precision of the two local Jacobians (1e-9)."""
    h = header()
    for x, y, g in [(100.3, 3900.7, (0.3, -0.2)), (1500.0, 2000.2, (-0.1, 0.45)),
                    (1900.6, 150.4, (0.0, 0.0))]:  # fmt: skip
        direct, via_j, via_e = _render_three_ways(h, x, y, g)
        peak = direct.max()
        assert abs(direct.sum() - 1.0) < 0.01
        assert np.abs(via_j - direct).max() < 1e-8 * peak  # measured: 6e-10 TPV, 2e-9 SIP
        assert np.abs(via_e - direct).max() < 1e-8 * peak


def test_sky_to_exposure_shear_is_the_ellipse_carried_through_J():
    """Against the shape of ``J S(g)``'s image of the unit circle, ``Q = M M^T``."""
    rng = np.random.default_rng(5)
    n = 50
    w = WCS(sip_header())
    ra, dec = w.all_pix2world(rng.uniform(0, 2047, n), rng.uniform(0, 4095, n), 0)
    st = cut_stamps(Exposure(image=np.zeros((4096, 2048)), wcs=w), ra, dec, size=16)
    g = rng.uniform(-0.6, 0.6, (n, 2)) * 0.7
    e1, e2 = sky_to_exposure_shear(g[:, 0], g[:, 1], st.frame)
    M = st.jacobian @ np.array([shear_matrix(*gi) for gi in g])
    Q = M @ np.transpose(M, (0, 2, 1))
    det = np.linalg.det(Q)
    den = Q[:, 0, 0] + Q[:, 1, 1] + 2 * np.sqrt(det)
    want = (Q[:, 0, 0] - Q[:, 1, 1]) / den, 2 * Q[:, 0, 1] / den
    assert np.abs(e1 - want[0]).max() < 1e-9 and np.abs(e2 - want[1]).max() < 1e-9


def _flag_exposure():
    """A 100 x 80 exposure, sky 10, a zero-weight chip gap in columns 50-53, a masked
    pixel at (20, 60), a NaN pixel at (75, 20)."""
    ny, nx = 80, 100
    rng = np.random.default_rng(2)
    image = 10.0 + rng.normal(size=(ny, nx))
    image[20, 75] = np.nan
    weight = np.ones((ny, nx))
    weight[:, 50:54] = 0.0
    mask = np.zeros((ny, nx), bool)
    mask[60, 20] = True
    w = tan_wcs(sky_cd(0.2, angle=12.0))
    return Exposure(image=image, wcs=w, weight=weight, mask=mask, background=10.0, name="e")


def test_stamps_and_their_usable_flags():
    ex = _flag_exposure()
    #             usable      edge        off       gap centre   gap near   masked px  NaN px
    x = np.array([30.2, 3.0, -30.0, 51.4, 46.0, 20.4, 74.6, np.nan])
    y = np.array([30.0, 40.0, 40.0, 40.0, 40.0, 59.7, 20.0, 0.0])
    ra, dec = ex.wcs.all_pix2world(x, y, 0)
    st = cut_stamps(ex, ra, dec, size=12)
    F = StampFlag
    assert [StampFlag(int(f)) for f in st.flags] == [
        F(0), F.EDGE, F.OFF_IMAGE | F.EDGE, F.CENTRE_MASKED | F.MASKED, F.MASKED,
        F.CENTRE_MASKED | F.MASKED, F.BAD_PIXELS, F.OFF_IMAGE | F.EDGE | F.BAD_WCS]  # fmt: skip
    assert st.usable.tolist() == [True] + [False] * 7
    assert st.reasons(3) == ["CENTRE_MASKED", "MASKED"] and st.reasons(0) == []
    # the galaxy is at element [6, 6]; background subtracted; no data -> 0, weight 0
    assert (st.x0[0], st.y0[0]) == (24, 24)
    cx, cy = st.centres
    assert abs(cx[0] - 6.2) < 1e-6 and abs(cy[0] - 6.0) < 1e-6
    assert st.stamps[0][6, 6] == pytest.approx(ex.image[30, 30] - 10.0)
    assert np.all(st.weights[1][:, :3] == 0) and np.all(st.stamps[1][:, :3] == 0)
    assert np.all(st.weights[1][:, 3:] == 1)
    assert np.isfinite(st.stamps).all() and st.noise_sigma[0] == 1.0
    # a tolerance for masked pixels off the centre keeps the one beside the gap
    lax = cut_stamps(ex, ra, dec, size=12, max_masked_fraction=0.4)
    assert lax.flags[4] == 0 and lax.flags[3] == F.CENTRE_MASKED
    one = st[0]
    assert one.usable and one.centre == pytest.approx((6.2, 6.0), abs=1e-6)
    assert one.pixel_scale == pytest.approx(0.2, rel=1e-8)
    assert np.allclose(st.pixel_scale[:7], 0.2)


def test_views_of_a_galaxy_over_its_exposures():
    ex = _flag_exposure()
    shifted = Exposure(image=ex.image, wcs=tan_wcs(sky_cd(0.2), crpix=(80.5, 40.5)),
                       weight=ex.weight, background=10.0, flux_scale=2.0)  # fmt: skip
    ra, dec = ex.wcs.all_pix2world([30.0, 46.0], [30.0, 40.0], 0)
    sets = cut_exposures([ex, shifted], ra, dec, size=12)
    assert [s.exposure for s in sets] == [0, 1]
    views = galaxy_views(sets, 0)
    assert [v.exposure for v in views] == [0, 1] and views[1].flux_scale == 2.0
    assert [v.exposure for v in galaxy_views(sets, 1)] == [1]  # beside the gap in exposure 0
    assert len(galaxy_views(sets, 1, usable_only=False)) == 2


class _PSF:
    """A PSF source: a Gaussian of sigma 1.5 px, NaN right of x = 90."""

    def draw(self, x, y):
        g = np.exp(-0.5 * (np.arange(-7, 8) / 1.5) ** 2)
        img = np.outer(g, g) / np.outer(g, g).sum()
        out = np.repeat(img[None], np.size(x), 0)
        out[np.asarray(x) > 90] = np.nan
        return out


def test_psf_at_each_galaxy_and_a_failed_one():
    ex = _flag_exposure()
    src = Exposure(image=ex.image, wcs=ex.wcs, background=10.0, noise_sigma=1.1, psf=_PSF())
    ra, dec = ex.wcs.all_pix2world([30.0, 94.0], [30.0, 30.0], 0)
    st = cut_stamps(src, ra, dec, size=8)
    assert st.psf.shape == (2, 15, 15) and st.noise_sigma.tolist() == [1.1, 1.1]
    assert st.flags[0] == 0 and st.flags[1] == StampFlag.PSF_FAILED
    fixed = Exposure(image=ex.image, wcs=ex.wcs, psf=np.ones((5, 5)) / 25)
    assert cut_stamps(fixed, ra, dec, size=8).psf.shape == (2, 5, 5)
    with pytest.raises(ValueError, match="draw"):
        Exposure(image=ex.image, wcs=ex.wcs, psf=np.ones(5))


def test_an_exposure_read_from_fits(tmp_path):
    ex = _flag_exposure()
    hdr = ex.wcs.to_header()
    hdr["MAGZP"] = 30.5
    image = np.nan_to_num(ex.image, nan=10.0)
    fits.HDUList([fits.PrimaryHDU(image, header=hdr),
                  fits.ImageHDU(ex.weight / 4.0, name="WEIGHT")]).writeto(tmp_path / "e.fits")
    got = Exposure.from_fits(tmp_path / "e.fits", reference_zero_point=30.0)
    assert got.shape == (80, 100) and got.name == "e.fits"
    assert got.flux_scale == pytest.approx(flux_scale_from_zero_point(30.5, 30.0))
    assert got.flux_scale == pytest.approx(10**0.2)
    assert abs(got.background - 10.0) < 0.1 and got.noise_sigma is None
    assert np.allclose(got.wcs.pixel_scale_matrix, ex.wcs.pixel_scale_matrix)
    st = cut_stamps(got, *ex.wcs.all_pix2world([30.0], [30.0], 0), size=8)
    assert st.noise_sigma[0] == pytest.approx(2.0)
    plain = Exposure.from_fits(tmp_path / "e.fits", weight=None)
    assert plain.flux_scale == 1.0 and 0.8 < plain.noise_sigma < 1.2
