"""Noise is not measured as galaxies: input positions on empty sky are flagged, and the
detections of a pure-noise image are at most 1 % usable."""

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from pylensfit import Config, Prior, measure
from pylensfit.flags import flag_value


def _psf(n: int = 48) -> np.ndarray:
    import galsim

    return galsim.Moffat(beta=3.5, fwhm=3.0).drawImage(nx=n, ny=n, scale=1.0).array


def _noise_image(path, size: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    img = (100.0 + rng.normal(size=(size, size))).astype(np.float32)
    fits.HDUList([fits.PrimaryHDU(img), fits.ImageHDU(np.ones_like(img), name="WEIGHT")]
                 ).writeto(path)  # fmt: skip


def _usable(cat) -> np.ndarray:
    return (np.asarray(cat["flags"]) == 0) & (np.asarray(cat["weight"]) > 0)


# the defaults' measurement (min_snr 5) in one pass under given priors, on a small grid
_CFG = dict(r_max=6.0, size_prior="flat", estimate_flux_prior=False,
            estimate_position_prior=False, amplitude_prior="uniform")  # fmt: skip


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_empty_sky_positions_are_flagged_low_snr(tmp_path):
    """60 input positions on pure noise: every row kept, none usable, each flagged
    LOW_SNR (or not measured for another reason); the default floor is what acts."""
    img = tmp_path / "sky.fits"
    _noise_image(img, 400, seed=21)
    rng = np.random.default_rng(22)
    gx, gy = np.meshgrid(40.0 + 40 * np.arange(8), 40.0 + 40 * np.arange(8))  # no pairs
    keep = rng.permutation(64)[:60]
    pos = Table({"x": gx.ravel()[keep] + rng.uniform(-2, 2, 60),
                 "y": gy.ravel()[keep] + rng.uniform(-2, 2, 60)})  # fmt: skip
    pos.write(tmp_path / "in.fits")
    cfg = Config(**_CFG)
    assert cfg.min_snr == Config().min_snr == 5.0
    cat = measure([img], catalogues=[tmp_path / "in.fits"], psf=_psf(), config=cfg,
                  prior=Prior(), progress=False)  # fmt: skip
    assert len(cat) == 60
    usable = _usable(cat)
    assert usable.sum() <= 1  # at most ~1 % of noise positions
    low = (np.asarray(cat["flags"]) & flag_value("LOW_SNR")) != 0
    assert low.sum() >= 40
    assert np.all(np.asarray(cat["weight"])[low] == 0)
    # without the floor the same rows would be usable galaxies: it is the floor that acts
    raw = measure([img], catalogues=[tmp_path / "in.fits"], psf=_psf(),
                  config=cfg.replace(min_snr=0.0), prior=Prior(), progress=False)  # fmt: skip
    assert _usable(raw).sum() >= 20


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_pure_noise_detections_are_at_most_one_percent_usable(tmp_path):
    paths = []
    for k in range(2):
        p = tmp_path / f"noise{k}.fits"
        _noise_image(p, 384, seed=30 + k)
        paths.append(p)
    cat = measure(paths, psf=_psf(), config=Config(**_CFG), prior=Prior(), progress=False)
    assert len(cat) > 100  # sep finds noise peaks at its default threshold
    assert _usable(cat).sum() <= 0.01 * len(cat) + 1
