"""Metacalibration of the joint fit: :func:`pylensfit.metacal.metacal_exposures`."""

from __future__ import annotations

import galsim
import numpy as np
import pytest

from pylensfit import Prior
from pylensfit.config import Config
from pylensfit.joint import fit_exposures
from pylensfit.metacal import (
    METACAL_TYPES,
    metacal_branches,
    metacal_exposures,
    metacal_fits,
    metacal_images,
    response,
)

N = 48
SCALE = 0.2  # arcsec per pixel
STEP = 0.01
SHEARS = {"noshear": (0.0, 0.0), "1p": (STEP, 0.0), "1m": (-STEP, 0.0), "2p": (0.0, STEP),
          "2m": (0.0, -STEP)}  # fmt: skip
#: the joint fit's options that the single fit shares (tests/test_joint.py), on 48 px
CFG = Config().replace(model="exponential", amplitude_prior="uniform", cubic_snr=0.0,
                       truncate_models=False, max_stamp_size=0, e_refine=1,
                       n_bulge_fractions=1, dtype="float64", r_min=0.0, r_max=8.0,
                       r_step=0.25, r_rel_step=0.0, stamp_size=N)  # fmt: skip
PRIOR = Prior(B=0.19, C=0.58, D=2.4)


def rotation(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


#: the exposures' J = d(x, y)/d(W, N), pixels per arcsec: rotated by 30 degrees, a mirror
#: image, a sheared WCS
JACOBIANS = np.stack([rotation(30.0), np.diag([-1.0, 1.0]) @ rotation(-65.0),
                      np.array([[1.06, 0.04], [0.04, 0.95]])]) / SCALE  # fmt: skip
PSFS = (galsim.Moffat(beta=3.5, fwhm=0.65),
        galsim.Moffat(beta=3.0, fwhm=0.7).shear(g1=0.05, g2=-0.03),
        galsim.Moffat(beta=3.5, fwhm=0.6).shear(g1=-0.04, g2=0.02))
#: noise-free galaxies outside the fitted exponential family, sky-frame shapes, arcsec
GALAXIES = (galsim.Sersic(n=0.7, half_light_radius=0.5, flux=600.0).shear(g1=0.3, g2=-0.15),
            galsim.Sersic(n=2.5, half_light_radius=0.4, flux=500.0).shear(g1=-0.1, g2=0.25))


def draw(obj, J: np.ndarray, method: str = "auto") -> np.ndarray:
    """``obj`` (sky coordinates, arcsec) through the WCS ``J`` on ``N x N`` pixels, its
    origin at element ``[N//2, N//2]`` (GalSim's ``JacobianWCS`` is ``J^-1``)."""
    wcs = galsim.JacobianWCS(*np.linalg.inv(J).ravel())
    return obj.drawImage(nx=N, ny=N, wcs=wcs, offset=(0.5, 0.5), method=method).array


def exposures(jacobians=JACOBIANS, psfs=PSFS, galaxies=GALAXIES):
    """``(K, n, N, N)`` stamps and ``(K, N, N)`` PSF images."""
    stamps = np.stack([[draw(galsim.Convolve(g, p), J) for g in galaxies]
                       for J, p in zip(jacobians, psfs, strict=True)])  # fmt: skip
    return stamps, np.stack([draw(p, J) for J, p in zip(jacobians, psfs, strict=True)])


def means(fits: dict) -> dict:
    return metacal_branches(fits, PRIOR, refine=CFG.output_refine, step=STEP)


@pytest.fixture(scope="module")
def sky_metacal():
    stamps, psf = exposures()
    sigma = np.sqrt((stamps[0, 0] ** 2).sum()) / 40.0  # the fits' assumed noise: S/N ~ 40
    fits = metacal_exposures(stamps, psf, sigma, JACOBIANS, offsets=(0.0, 0.0), config=CFG,
                             pixel_scale=SCALE, step=STEP, noise_fields=np.zeros_like(stamps))
    return stamps, psf, sigma, fits


def test_the_response_is_the_joint_fit_s_response_to_the_sky_s_shear(sky_metacal):
    """Each exposure's images are its stamp sheared on the sky by +-delta and convolved
    with its dilated PSF: GalSim's renderings of the galaxies sheared by +-delta on the
    sky, drawn through the three misaligned WCSs (rotated, mirror image, sheared) with
    each exposure's dilated PSF (pixel included), fitted jointly alike, give the same
    ``R`` (measured within 3e-5) and the same unsheared means. The pixel frame's shears
    (each exposure's stamp sheared in its own pixels: under a rotation or mirror another
    shear, ngmix issue 72's kind of error) give a response 0.5 off."""
    stamps, psf, sigma, fits = sky_metacal
    br = means(fits)
    assert all(br.usable[t].all() for t in METACAL_TYPES)
    assert (fits["noshear"].n_exposures == 3).all()
    dil = [galsim.Convolve(p, galsim.JacobianWCS(*np.linalg.inv(J).ravel())
                           .toWorld(galsim.Pixel(1.0))).dilate(1 + 2 * STEP)
           for J, p in zip(JACOBIANS, PSFS, strict=True)]  # fmt: skip
    kw = {"config": CFG.replace(position_prior_sigma=2.0), "pixel_scale": SCALE}
    psf_r = np.stack([draw(d, J, "no_pixel") for J, d in zip(JACOBIANS, dil, strict=True)])
    truth = {}
    for t in METACAL_TYPES:
        g1, g2 = SHEARS[t]
        # GalSim's images, drawn without the pixel: it is in the dilated PSF
        sheared = np.stack([[draw(galsim.Convolve(g.shear(g1=g1, g2=g2), d), J, "no_pixel")
                             for g in GALAXIES] for J, d in zip(JACOBIANS, dil, strict=True)])
        truth[t] = fit_exposures(sheared, psf_r, np.sqrt(2) * sigma, JACOBIANS, **kw)
    ref = means(truth)
    np.testing.assert_allclose(br.R, ref.R, atol=2e-4)  # measured 3e-5
    np.testing.assert_allclose(br.e["noshear"], ref.e["noshear"], atol=1e-5)
    assert np.abs(ref.R[:, 0, 0] - 1).max() > 0.05  # not a trivial response of one
    pix = {t: [] for t in METACAL_TYPES}
    for k in range(3):
        mc = metacal_images(stamps[k], psf[k], 0.0, step=STEP)  # no Jacobian: pixel frame
        for t in METACAL_TYPES:
            pix[t].append(mc.images[t])
    wrong = means({t: fit_exposures(np.stack(pix[t]), psf_r, np.sqrt(2) * sigma, JACOBIANS,
                                    **kw) for t in METACAL_TYPES})  # fmt: skip
    assert np.abs(wrong.R - ref.R).max() > 0.1


def test_one_aligned_exposure_is_the_single_fits_metacalibration():
    """K = 1 with J the identity (one reference pixel per pixel): the same images and
    fits as :func:`metacal_fits` on the stamps (``fit_stamps``), so the same means and
    response to float rounding; the added noise fields drawn from a seed, the same for
    the same seed."""
    J = np.eye(2)[None] / SCALE
    stamps, psf = exposures(jacobians=J, psfs=PSFS[:1])
    rng = np.random.default_rng(5)
    noisy = stamps + rng.normal(0.0, 2.0, stamps.shape)
    fields = np.random.default_rng(6).standard_normal(stamps.shape)
    joint = means(metacal_exposures(noisy, psf, 2.0, J, offsets=(0.05, -0.1), config=CFG,
                                    pixel_scale=SCALE, noise_fields=fields))  # fmt: skip
    single = means(metacal_fits(noisy[0], psf[0], 2.0, config=CFG, noise_fields=fields[0],
                                centres=(N // 2 + 0.25, N // 2 - 0.5)))  # fmt: skip
    for t in METACAL_TYPES:
        np.testing.assert_allclose(joint.e[t], single.e[t], atol=1e-6)  # measured 1e-8
    np.testing.assert_allclose(joint.R, single.R, atol=1e-5)
    seeded = [means(metacal_exposures(noisy, psf, 2.0, J, offsets=(0.05, -0.1), config=CFG,
                                      pixel_scale=SCALE, seed=s)).e["noshear"]
              for s in (1, 1, 2)]  # fmt: skip
    np.testing.assert_array_equal(seeded[0], seeded[1])
    assert np.abs(seeded[0] - seeded[2]).max() > 1e-3


def test_an_unusable_exposure_changes_nothing(sky_metacal):
    """An exposure flagged unusable for a galaxy (its stamp garbage) gives the
    metacalibration without it."""
    stamps, psf, sigma, _ = sky_metacal
    garbage = stamps.copy()
    garbage[1, 0] = np.nan
    usable = np.array([[True, True], [False, True], [True, True]])
    kw = {"offsets": (0.0, 0.0), "config": CFG, "pixel_scale": SCALE, "step": STEP}
    flagged = means(metacal_exposures(garbage, psf, sigma, JACOBIANS, usable=usable,
                                      noise_fields=np.zeros_like(stamps), **kw))  # fmt: skip
    keep = [0, 2]
    without = means(metacal_exposures(stamps[keep][:, :1], psf[keep], sigma, JACOBIANS[keep],
                                      noise_fields=np.zeros((2, 1, N, N)), **kw))  # fmt: skip
    np.testing.assert_allclose(flagged.R[:1], without.R, atol=1e-9)
    np.testing.assert_allclose(flagged.e["noshear"][:1], without.e["noshear"], atol=1e-9)
    assert np.isfinite(flagged.R).all()
    assert response(flagged.e, STEP).shape == (2, 2, 2)
