"""A PSF mixed per stamp from a few PSF images (likelihood.MixedPSF): one fit per stamp
with exactly the likelihood of its mixed PSF."""

from dataclasses import fields

import galsim
import numpy as np
import pytest

from conftest import draw
from pylensfit import Config
from pylensfit.likelihood import MixedPSF, fit_stamps

CFG = Config.paper(model="exponential", r_max=6.0, r_step=0.3)
#: the rows compared between fits: every per-galaxy number of the result
ROWS = ("lnL", "lnL_r", "lnL_peak", "flux", "x", "y", "snr", "r_best")


def _psf(e1: float, e2: float, fwhm: float, n: int = 32) -> np.ndarray:
    img = draw(galsim.Moffat(beta=3.5, fwhm=fwhm).shear(g1=e1, g2=e2), n=n)
    return img / img.sum()


def _corners(n: int = 32) -> np.ndarray:
    """Four PSFs as different as a cell's corners can be: |e| up to 0.06, FWHM +-8%."""
    return np.array([_psf(0.0, 0.0, 2.8, n), _psf(0.06, 0.0, 3.0, n), _psf(0.0, 0.05, 3.1, n),
                     _psf(-0.04, 0.03, 3.3, n)])  # fmt: skip


def _stamps(k: int, n: int = 32, seed: int = 1) -> np.ndarray:
    """``k`` noisy exponentials at S/N ~15-70 under a PSF between the corners', off
    centre by up to half a pixel."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(k):
        e1, e2 = rng.uniform(-0.4, 0.4, 2)
        gal = galsim.Exponential(half_light_radius=rng.uniform(1.5, 3.5)).shear(g1=e1, g2=e2)
        img = draw(galsim.Convolve(gal, galsim.Moffat(beta=3.5, fwhm=3.0)), n=n,
                   offset=tuple(rng.uniform(-0.5, 0.5, 2)), flux=rng.uniform(100.0, 600.0))
        out.append(img + rng.normal(0.0, 1.0, (n, n)))
    return np.array(out)


def _same_rows(a, b, rows: np.ndarray | slice, atol: float, rtol: float) -> None:
    for name in ROWS:
        np.testing.assert_allclose(np.asarray(getattr(a, name))[rows],
                                   np.asarray(getattr(b, name)), atol=atol, rtol=rtol,
                                   err_msg=name)  # fmt: skip
    np.testing.assert_array_equal(np.asarray(a.flags)[rows], np.asarray(b.flags))


@pytest.mark.parametrize("n", [32, 48])
def test_a_weight_of_one_is_that_psf(n):
    """Stamps each with one corner's weight 1 are fitted as with that corner's PSF image
    (on 48-pixel stamps with the stamp tiers, 32 and 48, as well); the same stamps in the
    same blocks, so only the per-model sums' float64 round-off differs."""
    cfg = CFG.replace(max_stamp_size=64)
    corners = _corners(n)
    stamps = _stamps(12, n)
    w = np.zeros((4, len(stamps)))
    w[np.arange(len(stamps)) % 4, np.arange(len(stamps))] = 1.0
    mixed = fit_stamps(stamps, MixedPSF(corners, w), 1.0, config=cfg)
    for c in range(4):
        one = fit_stamps(stamps, corners[c], 1.0, config=cfg)
        rows = np.flatnonzero(w[c] == 1.0)
        _same_rows(mixed, _take(one, rows), rows, atol=2e-4, rtol=1e-6)
    if n == 48:  # the large galaxies on the 48-pixel tier
        assert set(np.unique(mixed.stamp)) >= {32, 48}


def _take(fits, rows):
    """The rows ``rows`` of a StampFits (per-galaxy arrays only)."""
    out = {}
    for f in fields(fits):
        v = getattr(fits, f.name)
        per_galaxy = isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == len(fits)
        out[f.name] = v[rows] if per_galaxy and f.name != "egrid" else v
    return type(fits)(**out)


@pytest.mark.parametrize("model, e_refine", [("exponential", 1), ("exponential", 2),
                                             ("bulge+disc", 1)])  # fmt: skip
def test_mixed_weights_are_the_mixed_psf(model, e_refine):
    """The exactness: each stamp's fit equals fit_stamps with the PSF image ``sum_c w_c
    psf_c`` given directly, in float64 products to the float32 of the returned rows
    (with e_refine = 2 the fine grid's refits too; bulge+disc with the fractions between
    the pure ones mixed in the kernel)."""
    cfg = CFG.replace(dtype="float64", e_refine=e_refine)
    if model == "bulge+disc":
        cfg = Config.paper(model="bulge+disc", n_bulge_fractions=3, r_max=6.0, r_step=0.3,
                           dtype="float64")  # fmt: skip
    corners = _corners()
    stamps = _stamps(8, seed=2)
    w = np.random.default_rng(3).dirichlet(np.ones(4), size=len(stamps)).T
    mixed = fit_stamps(stamps, MixedPSF(corners, w), 1.0, config=cfg)
    assert np.all(mixed.flags == 0)
    for i in range(len(stamps)):
        one = fit_stamps(stamps[i : i + 1], np.tensordot(w[:, i], corners, 1), 1.0,
                         config=cfg)  # fmt: skip
        _same_rows(mixed, one, slice(i, i + 1), atol=2e-4, rtol=1e-6)


def test_float32_products_agree_to_their_round_off():
    """In the default float32 products the mixed fit and the direct one differ by the
    products' round-off alone (which a stamp's neighbours in its block change as much)."""
    corners = _corners()
    stamps = _stamps(6, seed=4)
    w = np.random.default_rng(5).dirichlet(np.ones(4), size=len(stamps)).T
    mixed = fit_stamps(stamps, MixedPSF(corners, w), 1.0, config=CFG)
    for i in range(len(stamps)):
        one = fit_stamps(stamps[i : i + 1], np.tensordot(w[:, i], corners, 1), 1.0,
                         config=CFG)  # fmt: skip
        ok = np.isfinite(one.lnL[0]) & (one.lnL[0] > -50)
        np.testing.assert_allclose(mixed.lnL[i][ok], one.lnL[0][ok], atol=0.02)
        np.testing.assert_allclose(mixed.lnL_peak[i], one.lnL_peak[0], rtol=1e-5, atol=0.01)


def test_mixed_psf_checks_its_weights():
    corners = _corners()
    with pytest.raises(ValueError, match="sum to 1"):
        MixedPSF(corners, np.full((4, 3), 0.5))
    with pytest.raises(ValueError, match="images"):
        MixedPSF(corners, np.full((3, 2), 1.0 / 3))
    psf = MixedPSF(corners, np.full((4, 3), 0.25))
    assert psf.take(np.array([0, 2])).n_stamps == 2
    with pytest.raises(ValueError, match="3 stamps"):
        fit_stamps(_stamps(2), psf, 1.0, config=CFG)


@pytest.mark.parametrize("n", [32, 48])
def test_pair_sums_folded_by_the_square_are_the_sums(n):
    """The pair sums made over the octant with the characters' transforms of G^2 give,
    for a pair of one PSF with itself, that PSF's per-model sums over the half-plane
    (on the 48-pixel tier's disc of frequencies as well), to float64 round-off."""
    from pylensfit.likelihood.bank import psf_bank
    from pylensfit.likelihood.pairs import pair_bank
    from pylensfit.models import model_bank

    cfg = CFG if n == 32 else CFG.replace(stamp_size=48, max_stamp_size=0,
                                          k_max=np.pi * 32 / 48)  # fmt: skip
    bank = model_bank(cfg)
    corners = _corners(n)
    pb = pair_bank(corners, cfg, bank)
    for c in range(4):
        p = np.flatnonzero((pb.pair_a == c) & (pb.pair_b == c))[0]
        one = psf_bank(corners[c], cfg, bank)
        for name in ("S", "mxx", "mxy", "myy"):
            ref = getattr(one, name)
            np.testing.assert_allclose(getattr(pb, name)[p], ref, rtol=0,
                                       atol=1e-12 * np.abs(ref).max(), err_msg=name)  # fmt: skip
