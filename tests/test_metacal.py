"""Metacalibration images against GalSim's renderings and analytic responses."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.table import Table

from pylensfit.metacal import METACAL_TYPES, metacal_images, metacal_shapes, metacal_shear, response

galsim = pytest.importorskip("galsim")

N = 48
SHEARS = {"noshear": (0.0, 0.0), "1p": (0.01, 0.0), "1m": (-0.01, 0.0), "2p": (0.0, 0.01),
          "2m": (0.0, -0.01)}  # fmt: skip


def _draw(obj, method: str = "auto", n: int = N) -> np.ndarray:
    """``obj`` on ``n x n`` unit pixels, its origin at element ``[n//2, n//2]``."""
    return obj.drawImage(nx=n, ny=n, scale=1.0, offset=(0.5, 0.5), method=method).array


@pytest.mark.parametrize("centre", [(0.0, 0.0), (1.3, -0.7)])
def test_metacal_images_are_galsims_sheared_galaxy_with_the_dilated_psf(centre):
    """Each image is the galaxy sheared about its centre by +-delta and convolved with the
    PSF (pixel included) dilated by 1 + 2 delta, as GalSim renders it from the profiles:
    a Sersic galaxy off the stamp's centre, an elliptical Moffat PSF."""
    psf = galsim.Moffat(beta=3.5, fwhm=3.0).shear(g1=0.1, g2=-0.03)
    gal = galsim.Sersic(n=0.7, half_light_radius=2.5).shear(g1=0.2, g2=-0.1)
    img = _draw(galsim.Convolve(gal.shift(*centre), psf))
    mc = metacal_images(img, _draw(psf), 0.0, step=0.01,
                        centres=(N // 2 + centre[0], N // 2 + centre[1]))  # fmt: skip
    dil = galsim.Convolve(psf, galsim.Pixel(1.0)).dilate(1.02)
    for t in METACAL_TYPES:
        g1, g2 = SHEARS[t]
        ref = _draw(galsim.Convolve(gal.shear(g1=g1, g2=g2).shift(*centre), dil), "no_pixel")
        assert np.abs(mc.images[t] - ref).max() < 2e-5 * ref.max(), t
    ref_psf = _draw(dil, "no_pixel")
    # the Moffat's wings past the stamp differ (GalSim's dilated profile is not cut)
    np.testing.assert_allclose(mc.psf, ref_psf / ref_psf.sum(), atol=2e-3 * ref_psf.max())
    assert mc.noise_sigma == 0.0 and mc.step == 0.01


def test_the_operation_needs_the_galaxys_light_in_the_stamp():
    """Under a Kolmogorov PSF a de Vaucouleurs galaxy's sheared images match GalSim's true
    shear where the stamp holds its light (96 px), and not where the stamp cuts its wings
    and the PSF's (32 px: 0.6 % of the light in the edge rows): the shear of the cut image
    differs from the cut image of the sheared galaxy over the whole stamp, its core
    included (``benchmarks/studies/metacal_operation.py``)."""
    psf = galsim.Kolmogorov(fwhm=4.0).shear(g2=0.03)
    gal = galsim.DeVaucouleurs(half_light_radius=1.5).shear(g1=0.2, g2=-0.1)
    c = (0.3, -0.4)
    dil = galsim.Convolve(psf, galsim.Pixel(1.0)).dilate(1.02)
    err = {}
    for n in (32, 96):
        img = _draw(galsim.Convolve(gal.shift(*c), psf), n=n)
        mc = metacal_images(img, _draw(psf, n=n), 0.0, step=0.01, types=("1p", "1m"),
                            centres=(n // 2 + c[0], n // 2 + c[1]))  # fmt: skip
        ref = [_draw(galsim.Convolve(gal.shear(g1=s).shift(*c), dil), "no_pixel", n)
               for s in (0.01, -0.01)]  # fmt: skip
        core = slice(n // 2 - 8, n // 2 + 9)
        diff = (mc.images["1p"] - mc.images["1m"]) - (ref[0] - ref[1])
        err[n] = np.abs(diff[core, core]).max() / np.abs(ref[0] - ref[1]).max()
    assert err[96] < 2e-3
    assert err[32] > 0.05


def test_the_reconvolution_psf_dilation_can_be_given():
    """``dilation`` sets the reconvolution PSF's scale whatever the step (the same
    estimator for two steps), as GalSim renders it; one below ``1 + step`` (which would
    amplify the noise at some frequencies) is refused."""
    psf = galsim.Gaussian(sigma=1.4).shear(g1=0.05)
    gal = galsim.Exponential(half_light_radius=1.8).shear(g1=-0.2, g2=0.1)
    img = _draw(galsim.Convolve(gal, psf))
    for step in (0.01, 0.02):
        mc = metacal_images(img, _draw(psf), 0.0, step=step, dilation=1.05, types=("2m",))
        dil = galsim.Convolve(psf, galsim.Pixel(1.0)).dilate(1.05)
        ref = _draw(galsim.Convolve(gal.shear(g2=-step), dil), "no_pixel")
        assert np.abs(mc.images["2m"] - ref).max() < 2e-5 * ref.max()
    with pytest.raises(ValueError, match="dilation"):
        metacal_images(img, _draw(psf), 0.0, step=0.02, dilation=1.01)


def test_shear_about_another_point_moves_the_galaxy():
    """Without the galaxy's centre the shear is about the stamp's: the galaxy moves by
    delta times its offset, which GalSim's rendering of the moved galaxy shows."""
    psf = galsim.Gaussian(sigma=1.5)
    gal = galsim.Exponential(half_light_radius=2.0)
    c = np.array([3.0, 2.0])
    img = _draw(galsim.Convolve(gal.shift(*c), psf))
    mc = metacal_images(img, _draw(psf), 0.0, step=0.05, types=("1p",))
    S = np.array([[1.05, 0.0], [0.0, 0.95]]) / np.sqrt(1 - 0.05**2)
    dil = galsim.Convolve(psf, galsim.Pixel(1.0)).dilate(1.1)
    ref = _draw(galsim.Convolve(gal.shear(g1=0.05).shift(*(S @ c)), dil), "no_pixel")
    assert np.abs(mc.images["1p"] - ref).max() < 1e-5 * ref.max()


def _moments(img: np.ndarray) -> np.ndarray:
    """Unweighted (e1, e2) from the second moments of each image about its centroid."""
    y, x = np.mgrid[: img.shape[-2], : img.shape[-1]].astype(float)
    f = img.sum((-2, -1))
    xc, yc = (img * x).sum((-2, -1)) / f, (img * y).sum((-2, -1)) / f
    dx, dy = x - xc[..., None, None], y - yc[..., None, None]
    ixx, iyy = (img * dx * dx).sum((-2, -1)) / f, (img * dy * dy).sum((-2, -1)) / f
    ixy = (img * dx * dy).sum((-2, -1)) / f
    return np.stack([(ixx - iyy) / (ixx + iyy), 2 * ixy / (ixx + iyy)], -1)


def test_response_of_unweighted_moments_is_the_analytic_one():
    """Gaussian galaxy and Gaussian PSF: the second moments of the metacal images are
    ``S Sigma_g S + f^2 Sigma_p``, so the response of their ellipticity is known in closed
    form; :func:`response` of the images' ellipticities gives it (finite differences
    of the exact moments: to ``delta^2``)."""
    sg, sp, step = 2.0, 1.4, 0.01
    gal = galsim.Gaussian(sigma=sg).shear(g1=0.3, g2=0.2)
    psf = galsim.Gaussian(sigma=sp)
    img = _draw(galsim.Convolve(gal, psf))
    mc = metacal_images(img, _draw(psf), 0.0, step=step)
    e = {t: _moments(mc.images[t][None].astype(float)) for t in METACAL_TYPES}
    R = response(e, step)[0]

    def ell(d1: float, d2: float) -> np.ndarray:  # the metacal image's moments, analytic
        A = galsim.Shear(g1=d1, g2=d2).getMatrix()
        M = galsim.Shear(g1=0.3, g2=0.2).getMatrix()
        C = sg**2 * A @ M @ M.T @ A.T + (1 + 2 * step) ** 2 * (sp**2 + 1.0 / 12.0) * np.eye(2)
        return np.array([C[0, 0] - C[1, 1], 2 * C[0, 1]]) / (C[0, 0] + C[1, 1])

    h = 1e-4
    R_true = np.column_stack([(ell(h, 0) - ell(-h, 0)) / (2 * h),
                              (ell(0, h) - ell(0, -h)) / (2 * h)])  # fmt: skip
    np.testing.assert_allclose(R, R_true, atol=2e-3)
    np.testing.assert_allclose(e["noshear"][0], ell(0, 0), atol=1e-4)


def test_added_noise_cancels_the_anisotropy_of_the_sheared_noise():
    """Sheared and reconvolved, white noise becomes anisotropic (the correlation at one
    pixel along x differs from that along y); with the rotated field added it is the
    same along both axes, within its error. Paired noise fields give paired images."""
    rng = np.random.default_rng(3)
    noise = rng.standard_normal((300, 32, 32))
    psf = _draw(galsim.Gaussian(sigma=1.2), n=32)

    def aniso(img):
        cx = (img * np.roll(img, 1, -1)).mean() / img.var()
        cy = (img * np.roll(img, 1, -2)).mean() / img.var()
        return cx - cy

    data_only = metacal_images(noise, psf, 1.0, step=0.1, noise_fields=np.zeros_like(noise),
                               types=("1p",))  # fmt: skip
    fixed = metacal_images(noise, psf, 1.0, step=0.1, seed=5, types=("1p", "noshear"))
    err = 2.0 / np.sqrt(noise.size)
    # the kernel P_r(k) / P(S k) passes more high k_x than k_y: less correlated along x
    assert aniso(data_only.images["1p"]) < -10 * err
    assert abs(aniso(fixed.images["1p"])) < 3 * err
    assert fixed.noise_sigma == pytest.approx(np.sqrt(2.0))
    again = metacal_images(noise, psf, 1.0, step=0.1, seed=5, types=("1p",))
    np.testing.assert_array_equal(again.images["1p"], fixed.images["1p"])


def test_noise_power_of_the_unsheared_image_is_the_one_the_fits_assume_at_low_k():
    """The unsheared image's noise (the data's and the added field, deconvolved and
    reconvolved) has the power ``sigma^2 (|P_r(k) / P(k)|^2 + |P_r(R k) / P(R k)|^2)``
    (``R`` the 90-degree turn): twice the input variance at low frequencies, where the
    galaxies' signal is and where it equals the white ``noise_sigma^2`` the fits assume,
    and less towards Nyquist (the reconvolution PSF is wider)."""
    rng = np.random.default_rng(11)
    n, sig, m = 32, 1.7, 2000
    noise = rng.standard_normal((m, n, n)) * sig
    psf_obj = galsim.Gaussian(sigma=1.3).shear(g1=0.1)
    mc = metacal_images(noise, _draw(psf_obj, n=n), sig, seed=4, types=("noshear",))
    power = (np.abs(np.fft.rfft2(mc.images["noshear"].astype(float))) ** 2).mean(0) / n**2
    P = np.abs(np.fft.rfft2(np.fft.ifftshift(_draw(psf_obj, n=n))))
    Pr = np.abs(np.fft.rfft2(np.fft.ifftshift(mc.psf)))
    P, Pr = P / P[0, 0], Pr / Pr[0, 0]
    # |P| at the turned frequencies (kx, ky) -> (-ky, kx) on the rfft2 grid (|P| is even)
    kx, ky = np.fft.rfftfreq(n) * n, np.fft.fftfreq(n) * n
    iy = np.broadcast_to(np.rint(kx).astype(int)[None, :] % n, P.shape)
    ix = np.broadcast_to(np.abs(np.rint(ky)).astype(int)[:, None], P.shape)
    expected = sig**2 * ((Pr / P) ** 2 + (Pr[iy, ix] / P[iy, ix]) ** 2)
    k = np.hypot(*np.meshgrid(kx, ky))
    for sel in (k <= 2, (k > 4) & (k < 8), (k > 10) & (k < 15)):  # rings in units of 2 pi / n
        err = 4 / np.sqrt(m * sel.sum())  # 4 sigma of a mean of exponential variates
        assert power[sel].mean() == pytest.approx(expected[sel].mean(), rel=err)
    low = k <= 2  # where the fits' white level holds
    assert power[low].mean() == pytest.approx(mc.noise_sigma**2, rel=0.04)
    assert power[(k > 10) & (k < 15)].mean() < 0.8 * mc.noise_sigma**2


def test_bad_input_is_refused_with_a_clear_message():
    psf = np.ones((16, 16))
    with pytest.raises(ValueError, match="square stamps and a PSF of their size"):
        metacal_images(np.zeros((2, 16, 12)), psf, 0.0)
    with pytest.raises(ValueError, match="non-finite"):
        metacal_images(np.full((16, 16), np.nan), psf, 0.0)
    with pytest.raises(ValueError, match="noise_fields or a seed"):
        metacal_images(np.zeros((16, 16)), psf, 1.0)
    with pytest.raises(ValueError, match="unknown metacal types"):
        metacal_images(np.zeros((16, 16)), psf, 0.0, types=("3p",))
    with pytest.raises(ValueError, match="step"):
        metacal_images(np.zeros((16, 16)), psf, 0.0, step=0.0)


def test_metacal_response_is_the_fit_s_response_to_a_real_shear():
    """The response :func:`metacal_shapes` measures is that of lensfit's posterior mean
    to shearing the galaxy itself: noise-free Sersic galaxies (outside the fitted
    exponential family) 1.8 px off the stamp's centre, rendered by GalSim sheared by
    +-delta with the reconvolution PSF and fitted alike, give the same ``R`` per galaxy.
    Shearing about the stamp's centre instead moves the galaxy too, and at S/N 15 the
    position prior about the catalogue position makes the posterior mean respond to that."""
    from pylensfit import Config, Prior
    from pylensfit.likelihood import fit_stamps
    from pylensfit.shear import posterior_moments

    cfg = Config.paper(model="exponential", position_prior_sigma=0.3)
    prior = Prior(B=0.19, C=0.58, D=2.4)
    psf = galsim.Moffat(beta=3.5, fwhm=3.0).shear(g1=0.05)
    gals = [galsim.Sersic(n=0.6, half_light_radius=2.2).shear(g1=0.3, g2=-0.2),
            galsim.Sersic(n=2.5, half_light_radius=1.6).shear(g1=-0.1, g2=0.25)]  # fmt: skip
    shift = (1.4, -1.1)
    stamps = np.stack([_draw(galsim.Convolve(g.shift(*shift), psf)) for g in gals])
    sigma = np.sqrt((stamps[0] ** 2).sum()) / 15.0  # S/N 15: the position prior matters
    zeros = np.zeros_like(stamps)
    out = metacal_shapes(stamps, _draw(psf), sigma, prior, config=cfg, noise_fields=zeros,
                         position_prior_sigma=None)  # the fits' own prior, as below
    assert (out["flag"] == 0).all()
    dil = galsim.Convolve(psf, galsim.Pixel(1.0)).dilate(1.02)
    mc = metacal_images(stamps[0], _draw(psf), 0.0, types=("noshear",))

    def emean(imgs, cfg=cfg):
        f = fit_stamps(imgs, mc.psf, np.sqrt(2) * sigma, config=cfg)
        m = posterior_moments(f.lnL, f.egrid, prior, refine=cfg.output_refine)
        return np.column_stack([m["e1"], m["e2"]])

    ev = {t: emean(np.stack([_draw(galsim.Convolve(g.shear(g1=SHEARS[t][0], g2=SHEARS[t][1])
                                                   .shift(*shift), dil), "no_pixel")
                             for g in gals]))
          for t in ("1p", "1m", "2p", "2m")}  # fmt: skip
    R_true = response(ev, 0.01)
    R = np.array([[out["R11"], out["R12"]], [out["R21"], out["R22"]]]).transpose(2, 0, 1)
    np.testing.assert_allclose(R, R_true, atol=1e-3)
    assert np.abs(R_true[:, 0, 0] - 1).max() > 0.02  # not a trivial response of one
    stamp_centre = metacal_images(stamps, _draw(psf), 0.0, step=0.01, types=("1p", "1m"))
    e_sc = {t: emean(stamp_centre.images[t]) for t in ("1p", "1m")}
    R_sc = (e_sc["1p"][:, 0] - e_sc["1m"][:, 0]) / 0.02
    assert np.abs(R_sc - R_true[:, 0, 0]).max() > 0.02
    e = np.column_stack([out["e1"], out["e2"]])
    unsheared = np.stack([_draw(galsim.Convolve(g.shift(*shift), dil), "no_pixel") for g in gals])
    np.testing.assert_allclose(e, emean(unsheared), atol=1e-3)
    # by default the metacalibration images are fitted under a 2-pixel position prior
    wide = metacal_shapes(stamps, _draw(psf), sigma, prior, config=cfg, noise_fields=zeros)
    e_wide = np.column_stack([wide["e1"], wide["e2"]])
    np.testing.assert_allclose(e_wide, emean(unsheared, cfg.replace(position_prior_sigma=2.0)),
                               atol=1e-3)  # fmt: skip
    assert np.abs(e_wide - e).max() > 2e-3  # the prior matters at S/N 15


def test_metacal_response_does_not_depend_on_the_step():
    """The measured response is the derivative at zero shear: two steps (0.01, 0.02) under
    the same round reconvolution PSF (dilation 1.04) give the same ``R`` matrix of each
    noise-free galaxy outside the fitted family (Sersic, a disc with a knot, a
    de Vaucouleurs bulge in an exponential disc) under an elliptical PSF, to within the
    third-order term of the central difference, and the mean shear of a sheared set then
    differs by less than 1e-3 of itself (m within 1e-3); a response computed with the
    step of one image pair and the shear of another would be twice or half of it."""
    from pylensfit import Config, Prior

    cfg = Config.paper(model="exponential")
    psf = galsim.Moffat(beta=3.0, fwhm=3.0).shear(g1=0.06, g2=-0.04)
    disc = galsim.Exponential(half_light_radius=2.2)
    gals = [galsim.Sersic(n=2.5, half_light_radius=1.6).shear(g1=0.25, g2=0.1),
            (0.8 * disc + 0.2 * galsim.Gaussian(sigma=0.8).shift(1.5, -1.0)).shear(g2=-0.3),
            (0.4 * galsim.DeVaucouleurs(half_light_radius=0.8) + 0.6 * disc).shear(g1=-0.2)]
    stamps = np.stack([_draw(galsim.Convolve(x.shear(g1=0.02, g2=-0.01), psf)) for x in gals])
    sigma = np.sqrt((stamps[0] ** 2).sum()) / 40.0
    zeros = np.zeros_like(stamps)

    def measured(step):
        out = metacal_shapes(stamps, _draw(psf), sigma, Prior(), config=cfg, step=step,
                             noise_fields=zeros, dilation=1.04, reconvolution="round")
        assert (out["flag"] == 0).all()
        R = np.stack([[out[f"R{i}{j}"] for j in (1, 2)] for i in (1, 2)]).transpose(2, 0, 1)
        return out, R

    (a, Ra), (b, Rb) = measured(0.01), measured(0.02)
    np.testing.assert_allclose(a["e1"], b["e1"], atol=1e-12)  # the same unsheared image
    assert np.abs(Rb - Ra).max() < 2e-3, Rb - Ra
    assert np.abs(np.diagonal(Ra, axis1=1, axis2=2)).min() > 0.2
    Rm = Ra.mean(0)
    assert np.abs(Rb.mean(0) - Rm).max() < 1e-3 * np.abs(np.diag(Rm)).min(), (Ra, Rb)
    ga, gb = metacal_shear(a)[0], metacal_shear(b)[0]
    np.testing.assert_allclose(gb, ga, rtol=1e-3)


def test_metacal_shear_inverts_the_mean_response():
    R = np.array([[0.8, 0.05], [-0.02, 0.7]])
    g = np.array([0.03, -0.01])
    t = Table({"e1": [0.0, 0.0, 9.0], "e2": [0.0, 0.0, 9.0], "flag": [0, 0, 1]})
    e = R @ g
    t["e1"][:2], t["e2"][:2] = e[0] + np.array([0.1, -0.1]), e[1] + np.array([-0.2, 0.2])
    for i in range(2):
        for j in range(2):
            t[f"R{i + 1}{j + 1}"] = [R[i, j] + 0.1, R[i, j] - 0.1, 5.0]
    g_hat, R_hat = metacal_shear(t)
    np.testing.assert_allclose(g_hat, g, atol=1e-12)
    np.testing.assert_allclose(R_hat, R, atol=1e-12)
    t["flag"] = 1
    with pytest.raises(ValueError, match="no usable rows"):
        metacal_shear(t)


def test_one_noise_level_per_stamp_is_each_stamp_s_own():
    """With a noise level per stamp, each stamp's images are those of a call with its
    level alone (the added field scaled by it), and so is the level the fits assume."""
    rng = np.random.default_rng(8)
    stamps, fields = rng.standard_normal((2, 3, 24, 24))
    psf = _draw(galsim.Gaussian(sigma=1.3), n=24)
    sig = np.array([0.5, 2.0, 1.0])
    both = metacal_images(stamps, psf, sig, noise_fields=fields, types=("2m",))
    np.testing.assert_allclose(both.noise_sigma, np.sqrt(2) * sig)
    for k in range(3):
        one = metacal_images(stamps[k], psf, sig[k], noise_fields=fields[k], types=("2m",))
        np.testing.assert_allclose(both.images["2m"][k], one.images["2m"], atol=1e-5)
    with pytest.raises(ValueError, match="one per stamp"):
        metacal_images(stamps, psf, sig[:2], noise_fields=fields)


@pytest.mark.parametrize("reconvolution", ["round", "dilate"])
def test_measure_stamps_metacal_columns_are_the_galaxies_metacalibration(reconvolution):
    """``measure_stamps(response="metacal")`` adds the metacalibration of each stamp about
    its fitted centre (a PSF smaller than the stamps put on their grid), with its seeded
    noise fields and ``Config.metacal_reconvolution``'s PSF, fitted on the whole stamp:
    the columns are :func:`metacal_shapes`' for the same fields and a configuration of one
    stamp size, the stamps'."""
    import pylensfit as plf
    from pylensfit.psf import centre_on_stamp

    psf = galsim.Moffat(beta=3.5, fwhm=3.0)
    gals = [galsim.Sersic(n=0.6, half_light_radius=2.0).shear(g1=0.2, g2=-0.1),
            galsim.Exponential(half_light_radius=1.5).shear(g1=-0.1, g2=0.3),
            galsim.DeVaucouleurs(half_light_radius=1.2)]  # fmt: skip
    stamps = np.stack([_draw(galsim.Convolve(g, psf)) for g in gals])
    sigma = np.sqrt((stamps[0] ** 2).sum()) / 40.0
    stamps += np.random.default_rng(2).standard_normal(stamps.shape) * sigma
    psf_img = _draw(psf, n=25)
    priors = plf.Priors()
    cfg = plf.Config(max_stamp_size=0, metacal_reconvolution=reconvolution)
    t = plf.measure_stamps(stamps, psf_img, sigma, priors=priors, config=cfg,
                           response="metacal", seed=7)  # fmt: skip
    mc = metacal_shapes(stamps, centre_on_stamp(psf_img, N), sigma, priors.ellipticity,
                        config=priors.apply(cfg).replace(stamp_size=N), step=0.01,
                        centres=(t["x"], t["y"]), reconvolution=reconvolution,
                        noise_fields=np.random.default_rng([7, 0]).standard_normal(stamps.shape))
    assert (mc["flag"] == 0).all()
    for c in ("R11", "R12", "R21", "R22"):
        np.testing.assert_allclose(t[c], mc[c], rtol=1e-6)
    for i in (1, 2):
        np.testing.assert_allclose(t[f"e{i}_mcal"], mc[f"e{i}"], rtol=1e-6)
    assert t.meta["metacal_step"] == 0.01
    again = plf.measure_stamps(stamps, psf_img, sigma, priors=priors, config=cfg,
                               response="metacal", seed=7)  # fmt: skip
    np.testing.assert_array_equal(again["R11"], t["R11"])
    other = plf.measure_stamps(stamps, psf_img, sigma, priors=priors, config=cfg,
                               response="metacal", seed=8)  # fmt: skip
    assert not np.allclose(other["R11"], t["R11"])
    with pytest.raises(ValueError, match="response must be"):
        plf.measure_stamps(stamps, psf_img, sigma, priors=priors, response="moments")


def _wcs_draw(obj, wcs, method: str = "auto", n: int = N) -> np.ndarray:
    """``obj`` (sky coordinates) through ``wcs`` on ``n x n`` pixels, its origin at
    element ``[n//2, n//2]``."""
    return obj.drawImage(nx=n, ny=n, wcs=wcs, offset=(0.5, 0.5), method=method).array


#: GalSim's d(u, v)/d(x, y): a rotation by 30 degrees with a flip, and a sheared frame
JACOBIANS = {"rotated+flipped": (0.2 * np.cos(0.52), 0.2 * np.sin(0.52),
                                 0.2 * np.sin(0.52), -0.2 * np.cos(0.52)),
             "sheared": (0.21, 0.05, -0.03, 0.18)}  # fmt: skip


@pytest.mark.parametrize("name", sorted(JACOBIANS))
def test_sky_frame_shears_are_galsims_shear_of_the_sky_under_any_wcs(name):
    """With the pixels' Jacobian, each image is the galaxy sheared on the sky by +-delta
    and convolved with the dilated PSF (pixel included), as GalSim renders it through
    the same WCS (a rotation with a flip; a sheared, non-square pixel). Without it the
    shears are the pixel frame's, which under these WCSs is another shear: that image
    misses GalSim's by far more (the error of ngmix issue 72's kind)."""
    wcs = galsim.JacobianWCS(*JACOBIANS[name])
    J = np.linalg.inv(wcs.jacobian().getMatrix())  # d(x, y) / d(u, v)
    psf = galsim.Moffat(beta=3.5, fwhm=0.65).shear(g1=0.06, g2=0.05)
    gal = galsim.Sersic(n=0.8, half_light_radius=0.45).shear(g1=0.2, g2=-0.1)
    img = _wcs_draw(galsim.Convolve(gal, psf), wcs)
    psf_img = _wcs_draw(psf, wcs)
    sky = metacal_images(img, psf_img, 0.0, step=0.01, jacobian=J)
    pix = metacal_images(img, psf_img, 0.0, step=0.01, types=("1p", "2p"))
    dil = galsim.Convolve(psf, wcs.toWorld(galsim.Pixel(1.0))).dilate(1.02)
    for t in METACAL_TYPES:
        g1, g2 = SHEARS[t]
        ref = _wcs_draw(galsim.Convolve(gal.shear(g1=g1, g2=g2), dil), wcs, "no_pixel")
        assert np.abs(sky.images[t] - ref).max() < 2e-5 * ref.max(), t
        if t in pix.images:
            assert np.abs(pix.images[t] - ref).max() > 20 * 2e-5 * ref.max(), t


def test_round_reconvolution_is_round_on_the_sky_and_bounded_by_the_psf():
    """``reconvolution="round"``: for a PSF round on the sky (sampled without the square
    pixel's response), seen through a sheared WCS, it is that PSF dilated (the round PSF
    of the construction is the PSF itself); for an elliptical PSF it is round (adaptive
    moments, pixel frame = sky frame) where the dilated PSF keeps the PSF's ellipticity,
    and its transform nowhere exceeds the sheared PSF's, so no frequency's noise is
    amplified."""
    from pylensfit.metacal import round_reconvolution

    wcs = galsim.JacobianWCS(*JACOBIANS["sheared"])
    J = np.linalg.inv(wcs.jacobian().getMatrix())
    img = np.zeros((N, N))
    round_psf = galsim.Gaussian(fwhm=0.7)
    p_img = _wcs_draw(round_psf, wcs, "no_pixel")  # the pixel response is not round
    dil = metacal_images(img, p_img, 0.0, jacobian=J, types=("noshear",))
    rnd = metacal_images(img, p_img, 0.0, jacobian=J, types=("noshear",),
                         reconvolution="round")  # fmt: skip
    assert np.abs(rnd.psf - dil.psf).max() < 3e-3 * dil.psf.max()

    ell = _draw(galsim.Moffat(beta=3.5, fwhm=3.0).shear(g1=0.08, g2=0.06))
    e = {}
    for how in ("dilate", "round"):
        mc = metacal_images(img, ell, 0.0, types=("noshear",), reconvolution=how)
        m = galsim.hsm.FindAdaptiveMom(galsim.Image(mc.psf.astype(np.float64)))
        e[how] = np.hypot(m.observed_shape.g1, m.observed_shape.g2)
    assert e["dilate"] > 0.08 and e["round"] < 2e-3, e
    Pr = round_reconvolution(ell / ell.sum(), 1.02)
    for d1, d2 in ((0.01, 0), (-0.01, 0), (0, 0.01), (0, -0.01)):
        S = np.array([[1 + d1, d2], [d2, 1 - d1]]) / np.sqrt(1 - d1 * d1 - d2 * d2)
        kx, ky = np.meshgrid(2 * np.pi * np.fft.rfftfreq(N), 2 * np.pi * np.fft.fftfreq(N))
        qx, qy = S[0, 0] * kx + S[0, 1] * ky, S[1, 0] * kx + S[1, 1] * ky
        x1 = np.arange(N) - N // 2
        P = np.abs(np.einsum("yx,ijx,ijy->ij", ell / ell.sum(),
                             np.exp(-1j * qx[..., None] * x1), np.exp(-1j * qy[..., None] * x1)))
        assert np.all(Pr <= P * (1 + 1e-6))
