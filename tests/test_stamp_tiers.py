"""Stamp tiers on stamps smaller than ``Config.max_stamp_size``: their own side is the
largest tier, for the galaxies that need it only."""

from __future__ import annotations

import logging

import galsim
import numpy as np
import pytest

import pylensfit as plf
from pylensfit.likelihood import fit_stamps, tier_sizes
from pylensfit.shear import posterior_moments

MOFFAT = galsim.Moffat(beta=3.5, fwhm=3.0)


def _draw(obj, n: int) -> np.ndarray:
    """``obj`` on ``n x n`` pixels, centred on element ``[n//2, n//2]``."""
    return obj.drawImage(nx=n, ny=n, scale=1.0, offset=(0.5, 0.5)).array


def _ring(hlr: float, n: int, n_angles: int = 8, snr: float = 60.0) -> np.ndarray:
    """Noise-free exponentials of ``|e| = 0.3`` at ``n_angles`` position angles."""
    imgs = []
    for a in np.arange(n_angles) * np.pi / n_angles:
        z = 0.3 * np.exp(2j * a)
        gal = galsim.Exponential(half_light_radius=hlr).shear(g1=z.real, g2=z.imag)
        imgs.append(_draw(galsim.Convolve(gal, MOFFAT), n))
    imgs = np.array(imgs)
    return imgs * snr / np.sqrt((imgs[0] ** 2).sum())


def test_tier_sizes_follow_the_given_stamps():
    cfg = plf.Config()  # stamp_size 32, max_stamp_size 64
    assert tier_sizes(cfg, (48, 48)) == [32, 48]
    assert tier_sizes(cfg, (64, 64)) == [32, 64]
    assert tier_sizes(cfg, (128, 128)) == [32, 64]
    assert tier_sizes(cfg, (49, 47)) == [32, 46]
    assert tier_sizes(cfg, (32, 32)) == tier_sizes(cfg, (24, 24)) == [32]
    assert tier_sizes(cfg.replace(max_stamp_size=96), (80, 80)) == [32, 64, 80]
    assert tier_sizes(cfg.replace(max_stamp_size=0), (64, 64)) == [32]


def test_large_galaxies_use_the_whole_of_48_pixel_stamps(caplog):
    """On 48-pixel stamps (``max_stamp_size=64``) galaxies that need more than 32 pixels
    (``stamp_hlr_ratio`` of their convolved half-light radii) are fitted on 48, with no
    warning, the small ones on 32 as on their central 32 pixels alone. A large
    galaxy's posterior mean on 48 pixels is within 5e-5 of its fit on 64-pixel
    renderings; on 32 pixels it is 3e-4 away (measured: 1.8e-5 and 2.9e-4)."""
    cfg = plf.Config.paper(model="exponential", position_prior_sigma=0.01, max_stamp_size=64)
    psf = {n: _draw(MOFFAT, n) for n in (32, 48, 64)}
    moments = {}
    with caplog.at_level(logging.WARNING, logger="pylensfit"):
        for n in (32, 48, 64):
            stamps = np.concatenate([_ring(1.2, n, 2), _ring(3.5, n)])
            caplog.clear()  # (32-pixel stamps: the tiers cannot act, which it says)
            fits = fit_stamps(stamps, psf[n], 1.0, config=cfg)
            if n == 48:
                assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
                assert list(fits.stamp) == [32] * 2 + [48] * 8
                assert fits.meta["stamp_sizes"] == [32, 48]
                # the small ones: their fit on the central 32 x 32 pixels, as given
                small = fit_stamps(stamps[:2, 8:40, 8:40], psf[32], 1.0, config=cfg)
                np.testing.assert_allclose(fits.lnL[:2], small.lnL, atol=1e-4)
                np.testing.assert_allclose(fits.x[:2], small.x + 8, atol=1e-6)
            m = posterior_moments(fits.lnL[2:], fits.egrid, plf.Prior())
            moments[n] = np.column_stack([m["e1"], m["e2"]])
    d48 = np.abs(moments[48] - moments[64]).max()
    d32 = np.abs(moments[32] - moments[64]).max()
    assert d48 < 5e-5 and d32 > 2e-4, (d48, d32)


def test_galaxies_that_need_more_than_the_stamps_hold_are_counted(caplog):
    """A galaxy that needs more than 48 pixels, on 48-pixel stamps, is fitted on 48 and
    the warning counts it."""
    cfg = plf.Config.paper(model="exponential", max_stamp_size=64)
    stamps = np.concatenate([_ring(3.5, 48, 1), _ring(6.0, 48, 1)])
    with caplog.at_level(logging.WARNING, logger="pylensfit"):
        fits = fit_stamps(stamps, _draw(MOFFAT, 48), 1.0, config=cfg)
    assert list(fits.stamp) == [48, 48]
    said = " ".join(r.getMessage() for r in caplog.records)
    assert "1 galaxies need stamps larger than 48 px" in said


@pytest.mark.filterwarnings("ignore::pylensfit.CalibrationWarning")
def test_measure_stamps_records_the_tier(caplog):
    """``measure_stamps``' ``stamp`` column: the side each galaxy was fitted on."""
    rng = np.random.default_rng(4)
    stamps = np.concatenate([_ring(1.0, 48, 4), _ring(3.5, 48, 4)])
    stamps = stamps + rng.normal(size=stamps.shape)
    pr = plf.Priors()
    with caplog.at_level(logging.WARNING, logger="pylensfit"):
        t = plf.measure_stamps(stamps, _draw(MOFFAT, 48), 1.0, priors=pr)
    assert list(t["stamp_size"]) == [32] * 4 + [48] * 4
    assert "cannot act" not in caplog.text and "larger than" not in caplog.text
