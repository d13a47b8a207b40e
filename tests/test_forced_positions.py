"""Forced positions: an input catalogue's position on blank sky is not a galaxy.

The S/N at the catalogue position itself (``pylensfit.forced``) is a standard normal
variable on pure noise, so its threshold has a known false-alarm probability; in the
pipeline it flags blank positions ``LOW_SNR`` and keeps the galaxies.
"""

import galsim
import numpy as np
import pytest
from astropy.table import Table
from scipy.stats import norm

from pylensfit import Config, ConfigError, Prior, measure
from pylensfit.flags import flag_value
from pylensfit.forced import (
    FORCED_HALF_LIGHT_RADII,
    false_alarm_threshold,
    forced_threshold,
    position_snr,
)
from pylensfit_validation.simulate import FieldSpec, simulate_field, write_field

N = 32
PSF = galsim.Moffat(beta=3.5, fwhm=3.0)


def _psf_image(n: int = 48) -> np.ndarray:
    """The PSF centred on element ``[n//2, n//2]``."""
    return PSF.drawImage(nx=n, ny=n, scale=1.0, offset=(0.5, 0.5)).array


def _draw(obj, x: float, y: float, n: int = N) -> np.ndarray:
    """``obj`` on ``n x n`` pixels, its centre at pixel ``(x, y)`` (0-based)."""
    return obj.drawImage(nx=n, ny=n, scale=1.0, offset=(x - n // 2 + 0.5, y - n // 2 + 0.5)).array


def test_threshold_is_the_bonferroni_bound():
    k = len(FORCED_HALF_LIGHT_RADII)
    assert false_alarm_threshold(1e-3) == pytest.approx(norm.isf(1e-3 / k), rel=1e-12)
    assert false_alarm_threshold(0.05, n_filters=1) == pytest.approx(1.6449, abs=1e-4)
    for bad in (0.0, 1.0, -0.1, 2.0):
        with pytest.raises(ValueError):
            false_alarm_threshold(bad)
    assert forced_threshold(Config()) == pytest.approx(false_alarm_threshold(1e-3))
    # the cut is off where every fitted galaxy is used, or where asked
    assert forced_threshold(Config(min_snr=0.0)) is None
    assert forced_threshold(Config(forced_false_alarm=1.0)) is None
    assert forced_threshold(Config.paper()) is None
    for bad in (0.0, 1.5):
        with pytest.raises(ConfigError, match="forced_false_alarm"):
            Config(forced_false_alarm=bad)


def test_position_snr_is_the_matched_filter_at_the_position():
    """On a noiseless galaxy the filter of its own profile at its own position gives its
    S/N exactly (sub-pixel position included); the same filter elsewhere, the pixel sum
    of the galaxy times the filter moved there."""
    gal = galsim.Convolve(galsim.Exponential(half_light_radius=2.0), PSF)
    d = _draw(gal, 16.3, 15.6)
    d *= 20.0 / np.sqrt((d**2).sum())  # S/N 20 at sigma 1
    psf = _psf_image()
    own = position_snr(d, psf, 1.0, ([16.3], [15.6]), half_light_radii=(2.0,))
    assert own[0] == pytest.approx(20.0, rel=1e-4)
    # at sigma 2, half of it
    half = position_snr(d, psf, 2.0, ([16.3], [15.6]), half_light_radii=(2.0,))
    assert half[0] == pytest.approx(10.0, rel=1e-4)
    xs = np.array([13.3, 16.3, 18.8, 16.3])
    ys = np.array([15.6, 12.1, 15.6, 17.6])
    got = position_snr(np.repeat(d[None], xs.size, axis=0), psf, 1.0, (xs, ys),
                       half_light_radii=(2.0,))  # fmt: skip
    want = []
    for x, y in zip(xs, ys, strict=True):
        m = _draw(gal, x, y)
        want.append((d * m).sum() / np.sqrt((m**2).sum()))
    np.testing.assert_allclose(got, want, rtol=1e-4)
    assert np.all(got < 0.9 * own[0])  # off the galaxy: less
    # the best of the bank: at least the best single filter's
    both = position_snr(d, psf, 1.0, ([16.3], [15.6]))
    assert 0.95 * 20.0 < both[0] <= 20.0 + 1e-6
    # a non-finite pixel, a bad noise value or position: NaN, no raise
    bad = np.repeat(d[None], 3, axis=0)
    bad[0, 3, 3] = np.nan
    out = position_snr(bad, psf, np.array([1.0, 0.0, 1.0]), ([16.3, 16.3, np.nan],
                                                             [15.6, 15.6, 15.6]))  # fmt: skip
    assert np.isnan(out).all()


def test_false_alarm_probability_on_pure_noise():
    """Each filter's S/N at a fixed position is a standard normal variable on white
    noise; the best of the bank exceeds the threshold of false-alarm probability a at
    most a of the time (the bound is conservative: the filters are correlated)."""
    rng = np.random.default_rng(5)
    n_st = 6000
    stamps = rng.normal(scale=3.0, size=(n_st, N, N))
    cx, cy = rng.uniform(12, 20, n_st), rng.uniform(12, 20, n_st)
    psf = _psf_image()
    for r in FORCED_HALF_LIGHT_RADII:
        v = position_snr(stamps, psf, 3.0, (cx, cy), half_light_radii=(r,))
        assert abs(v.mean()) < 0.05 and abs(v.std() - 1.0) < 0.04, (r, v.mean(), v.std())
    best = position_snr(stamps, psf, 3.0, (cx, cy))
    for a in (0.2, 0.05, 0.01):
        rate = np.mean(best >= false_alarm_threshold(a))
        assert a / 4 < rate <= a + 2.5 * np.sqrt(a / n_st), (a, rate)


def _field_with_blanks(tmp_path, seed: int):
    """A 512-px field of exponential galaxies of S/N 6-60 on a 48-px lattice, and an
    input catalogue: their true positions, then one blank position in each of the
    lattice's cells (no row within a stamp's half-width of another)."""
    spec = FieldSpec(size=512, spacing=48.0, jitter=4.0, star_fraction=0.0, psf_e1=0.0,
                     psf_e2=0.0, snr_range=(6.0, 60.0))  # fmt: skip
    img, w, truth = simulate_field(spec, seed=seed, noise_seed=seed + 7)
    image = tmp_path / "field.fits"
    write_field(image, img, w, spec, truth=truth)
    rng = np.random.default_rng(seed + 100)
    g = np.arange(72.0, 464.0, 48.0)
    bx, by = (v.ravel() + rng.uniform(-2.0, 2.0, v.size) for v in np.meshgrid(g, g))
    pos = Table({"x": np.r_[truth["x"], bx], "y": np.r_[truth["y"], by]})
    pos.write(tmp_path / "positions.fits")
    blank = np.r_[np.zeros(len(truth), bool), np.ones(bx.size, bool)]
    snr = np.r_[np.asarray(truth["snr"], float), np.full(bx.size, np.nan)]
    return image, tmp_path / "positions.fits", blank, snr


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_blank_positions_are_not_measured_as_galaxies(tmp_path):
    """The true positions of a simulated field plus 81 blank ones: at most 5 % of the
    blank positions usable (the best model's S/N alone leaves more than 5 % of them
    above min_snr), every galaxy of S/N >= 10 usable."""
    image, cat_path, blank, snr = _field_with_blanks(tmp_path, seed=2)
    cfg = Config(r_max=6.0, size_prior="flat", estimate_flux_prior=False,
                 estimate_position_prior=False, amplitude_prior="uniform")  # fmt: skip
    cat = measure([image], catalogues=[cat_path], psf=_psf_image(), config=cfg, prior=Prior(),
                  progress=False)  # fmt: skip
    assert len(cat) == blank.size
    flags = np.asarray(cat["flags"])
    usable = (flags == 0) & (np.asarray(cat["weight"]) > 0)
    bright = ~blank & (snr >= 10)
    assert bright.sum() > 50 and blank.sum() == 81
    assert usable[blank].mean() <= 0.05
    assert usable[bright].all()
    fs = np.asarray(cat["forced_SNratio"], dtype=float)
    assert np.isfinite(fs).all()
    u = forced_threshold(cfg)
    assert np.all(fs[bright] >= u)
    # round filters at the true position: 0.5-1 of the galaxy's own matched-filter S/N
    ratio = fs[bright] / snr[bright]
    assert ratio.min() > 0.5 and 0.85 < np.median(ratio) < 1.05
    # what the best model's S/N alone would keep: the rows the cut flagged LOW_SNR whose
    # model S/N is above min_snr
    low = flag_value("LOW_SNR")
    galaxy = np.asarray(cat["fitclass"]) == 0
    snr_fit = np.asarray(cat["model_SNratio"], dtype=float)
    by_cut = galaxy & (flags == low) & (snr_fit >= cfg.min_snr)
    assert np.all(fs[by_cut] < u)
    alone = usable | by_cut
    assert alone[blank].mean() > 0.1  # the look-elsewhere effect the cut removes
    assert alone[bright].all()
    # the same run without the cut: those rows come back usable
    raw = measure([image], catalogues=[cat_path], psf=_psf_image(),
                  config=cfg.replace(forced_false_alarm=1.0), prior=Prior(),
                  progress=False)  # fmt: skip
    raw_usable = (np.asarray(raw["flags"]) == 0) & (np.asarray(raw["weight"]) > 0)
    np.testing.assert_array_equal(raw_usable, alone)
