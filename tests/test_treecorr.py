"""The catalogue's sign conventions against TreeCorr's: a tangential shear drawn on the
sky through a plain and a rotated, flipped WCS, measured by pylensfit and read by
TreeCorr with its defaults (no ``flip_g1``, ``flip_g2``)."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS

galsim = pytest.importorskip("galsim")
treecorr = pytest.importorskip("treecorr")

from pylensfit import Config, Prior, measure  # noqa: E402
from pylensfit.pipeline import write_catalogue  # noqa: E402

SCALE = 0.2 / 3600.0  # deg / pixel
N = 768  # field side (pixels)
SPACING = 30  # lattice pitch (pixels): 24 sites a row, twins side by side
G_T = 0.05  # tangential shear about the field's centre
RA0, DEC0 = 150.0, 2.0  # the field's centre (deg)
NG_BINS = dict(min_sep=10.0, max_sep=80.0, nbins=3, sep_units="arcsec")
# from above the twins' separation (6 arcsec), where they anticorrelate
GG_BINS = dict(min_sep=8.0, max_sep=60.0, nbins=4, sep_units="arcsec")


def _jac(theta_deg: float, flip: bool) -> np.ndarray:
    """``J = d(W, N)/d(x, y)`` (degrees per pixel): a rotation after an optional flip."""
    t = np.radians(theta_deg)
    rot = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    return SCALE * rot @ (np.diag([1.0, -1.0]) if flip else np.eye(2))


def _wcs(J: np.ndarray) -> WCS:
    """A TAN WCS centred on the field with ``CD = diag(-1, 1) J``: (dRA cos dec, dDec)
    = (-dW, dN)."""
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [RA0, DEC0]
    w.wcs.crpix = [N / 2 + 0.5, N / 2 + 0.5]
    w.wcs.cd = np.diag([-1.0, 1.0]) @ J
    return w


def _tangential_field(path, J: np.ndarray, seed: int = 3):
    """Exponential galaxies on a lattice under a tangential shear ``G_T`` about the
    centre, defined in world coordinates ``(u, v) = (W, N)`` and drawn through ``J`` by
    GalSim; each galaxy's 90-degree twin (in the world frame) is its right-hand
    neighbour. Returns the PSF image (round on the sky and on the pixels), the
    galaxies' RA, Dec (deg) and their complex sky-frame shears."""
    rng = np.random.default_rng(seed)
    gw = galsim.JacobianWCS(*(J * 3600.0).ravel())  # dudx, dudy, dvdx, dvdy (arcsec)
    img = galsim.ImageF(N, N, wcs=gw)
    psf = galsim.Moffat(beta=3.5, fwhm=0.6)  # arcsec
    pos = np.arange(SPACING, N - SPACING + 1, SPACING, dtype=float)
    xs, ys = (a.ravel() for a in np.meshgrid(pos, pos))  # 0-based pixels
    k = xs.size // 2
    e0 = rng.uniform(0.05, 0.3, k) * np.exp(2j * rng.uniform(0, np.pi, k))
    e = np.empty(2 * k, complex)
    e[0::2], e[1::2] = e0, -e0  # the twins: 24 sites a row, so neighbours in a row
    r = np.repeat(rng.uniform(0.45, 0.7, k), 2)  # scale radius, arcsec
    c = (N - 1) / 2.0  # CRPIX, 0-based
    dw, dn = (J * 3600.0) @ np.vstack([xs - c, ys - c])
    g = -G_T * np.exp(2j * np.arctan2(dn, dw))  # tangential: across the radius
    for i in range(2 * k):
        gal = galsim.Exponential(scale_radius=r[i], flux=400.0).shear(g1=e[i].real,
                                                                       g2=e[i].imag)
        gal = galsim.Convolve(gal.shear(g1=g[i].real, g2=g[i].imag), psf)
        ix, iy = int(xs[i]) + 1, int(ys[i]) + 1  # GalSim's 1-based pixel
        b = galsim.BoundsI(ix - 24, ix + 24, iy - 24, iy + 24) & img.bounds
        gal.drawImage(image=img[b], center=galsim.PositionD(ix, iy), add_to_image=True)
    arr = img.array + np.random.default_rng(seed + 1).normal(0, 1.0, (N, N))
    w = _wcs(J)
    fits.PrimaryHDU(arr.astype(np.float32), header=w.to_header()).writeto(path)
    ra, dec = w.all_pix2world(xs, ys, 0)
    pimg = psf.drawImage(nx=32, ny=32, wcs=gw.local(), offset=(0.5, 0.5)).array
    return pimg, ra, dec, g


@pytest.fixture(scope="module", params=[(0.0, False), (35.0, True)], ids=["plain", "rot35flip"])
def measured(request, tmp_path_factory):
    """The field measured, its catalogue written and read by TreeCorr as the guide says,
    with the weighted mean sensitivity and a catalogue of the true shears."""
    theta, flip = request.param
    d = tmp_path_factory.mktemp("treecorr")
    psf, ra, dec, g = _tangential_field(d / "field.fits", _jac(theta, flip))
    cfg = Config.paper(model="exponential", r_max=6.0, r_step=0.3, min_snr=0.0)
    cat = measure([d / "field.fits"], psf=psf, config=cfg, prior=Prior(), progress=False)
    assert cat.meta["frame"] == "sky"
    write_catalogue(cat, d / "cat.fits")
    # the exact call of the guide (docs/guide.rst): TreeCorr's defaults otherwise
    src = treecorr.Catalog(str(d / "cat.fits"), ra_col="ALPHA_J2000", dec_col="DELTA_J2000",
                           ra_units="deg", dec_units="deg", g1_col="e1", g2_col="e2",
                           w_col="weight", ext=1)  # fmt: skip
    w = np.asarray(cat["weight"], float)
    use = (w > 0) & np.isfinite(cat["e1"]) & np.isfinite(cat["e2"])
    assert use.sum() > 500
    s = 0.5 * (np.asarray(cat["sens1"]) + np.asarray(cat["sens2"]))
    sens = float(np.sum(w[use] * s[use]) / np.sum(w[use]))
    true = treecorr.Catalog(ra=ra, dec=dec, ra_units="deg", dec_units="deg", g1=g.real,
                            g2=g.imag)  # fmt: skip
    return {"src": src, "true": true, "sens": sens, "theta": theta, "flip": flip}


def test_tangential_shear_about_the_centre(measured):
    """NG with a lens at the centre: the tangential shear over the mean sensitivity is
    +0.05 and the cross shear 0. A sign error in e1 or e2 (or a frame left pixel under
    the rotated, flipped WCS) would give ~0 or -0.05, at 7 sigma or more."""
    lens = treecorr.Catalog(ra=[RA0], dec=[DEC0], ra_units="deg", dec_units="deg")
    ng = treecorr.NGCorrelation(**NG_BINS)
    ng.process(lens, measured["src"])
    s = measured["sens"]
    gt, gx, err = ng.xi / s, ng.xi_im / s, np.sqrt(ng.varxi) / s
    assert np.all(ng.npairs > 20) and 0.85 < s < 1.0
    iv = 1.0 / err**2
    gt_all, gx_all = np.sum(iv * gt) / iv.sum(), np.sum(iv * gx) / iv.sum()
    err_all = iv.sum() ** -0.5
    assert np.all(np.abs(gt - G_T) < 3 * err), (gt, err)
    assert abs(gt_all - G_T) < 3 * err_all and err_all < 0.01, (gt_all, err_all)
    assert abs(gx_all) < 3 * err_all, (gx_all, err_all)


def test_shear_correlation_is_positive_at_small_separations(measured):
    """GG: xi+ over the squared mean sensitivity is positive at the two smallest
    separations (8-21 arcsec) and agrees with the xi+ of the true shears there."""
    gg = treecorr.GGCorrelation(**GG_BINS)
    gg.process(measured["src"])
    gt = treecorr.GGCorrelation(**GG_BINS)
    gt.process(measured["true"])
    s2 = measured["sens"] ** 2
    xip, err = gg.xip / s2, np.sqrt(gg.varxip) / s2
    assert np.all(xip[:2] > 2 * err[:2]), (xip, err)
    assert np.all(np.abs(xip[:3] - gt.xip[:3]) < 3 * err[:3]), (xip, gt.xip, err)
