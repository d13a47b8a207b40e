"""The calibration recipe's pieces: the position prior's width, the Priors object, the
fallbacks of a small sample, the presets and the default estimator."""

from __future__ import annotations

import numpy as np
import pytest

import pylensfit as plf
from pylensfit.calibration import estimate_position_sigma


def test_position_sigma_separates_the_catalogue_scatter_from_the_fit_error():
    rng = np.random.default_rng(1)
    n = 20000
    snr = 10 * rng.pareto(1.0, n) + 10
    fit = 2.0 / snr  # a fit error falling as 1 / S/N (px)
    # uniform sub-pixel offsets (a simulation's): the constant part, 1 / sqrt(12)
    dx = rng.uniform(-0.5, 0.5, n) + fit * rng.normal(size=n)
    dy = rng.uniform(-0.5, 0.5, n) + fit * rng.normal(size=n)
    sig, a = estimate_position_sigma(dx, dy, snr)
    assert sig == pytest.approx(12**-0.5, rel=0.03) and a == pytest.approx(4.0, rel=0.3)
    # a catalogue detected on the image: errors that fall with S/N only, which the fit's
    # share; no width is claimed from them (the configured, broad one is kept)
    dx, dy = (np.sqrt(2) * fit * rng.normal(size=n) for _ in range(2))
    sig, a = estimate_position_sigma(dx, dy, snr)
    assert sig is None and a == pytest.approx(8.0, rel=0.3)
    # an external catalogue's astrometric scatter of 0.05 px beside a fit error 2 / S/N
    # that dominates it at the median S/N is not resolved either; of 0.3 px it is
    for s0, want in ((0.05, None), (0.3, 0.3)):
        dx, dy = (s0 * rng.normal(size=n) + fit * rng.normal(size=n) for _ in range(2))
        sig, _ = estimate_position_sigma(dx, dy, snr)
        assert sig == (None if want is None else pytest.approx(want, rel=0.05))
    with pytest.raises(ValueError, match="too few"):
        estimate_position_sigma(dx[:5], dy[:5], snr[:5])


def test_priors_round_trip_and_apply(tmp_path):
    sp = plf.SizePrior(ln_h=np.linspace(-1, 2, 31), density=np.ones((3, 31)) / 3.0,
                       star=1e-4, smoothing=0.02)  # fmt: skip
    pr = plf.Priors(ellipticity=plf.Prior(B=0.2, C=0.5, D=2.0), bulge_weights=np.array(
        [0.5, 0.2, 0.3]), size=sp, flux_power=1.8, flux_range=(50.0, 2000.0),
        position_sigma=0.3, n_galaxies=1234, info={"flux_power_err": 0.01})  # fmt: skip
    pr.save(tmp_path / "p.json")
    back = plf.Priors.load(tmp_path / "p.json")
    assert back.ellipticity.params == pr.ellipticity.params
    np.testing.assert_array_equal(back.bulge_weights, pr.bulge_weights)
    np.testing.assert_array_equal(back.size.density, sp.density)
    assert (back.flux_power, back.flux_range, back.position_sigma, back.n_galaxies) == (
        1.8, (50.0, 2000.0), 0.3, 1234)
    assert "flux_power=1.800" in repr(back) and "position_sigma=0.300 px" in repr(back)
    cfg = back.apply(plf.Config())
    assert (cfg.amplitude_prior_power, cfg.amplitude_prior_min, cfg.amplitude_prior_max,
            cfg.position_prior_sigma) == (1.8, 50.0, 2000.0, 0.3)  # fmt: skip
    # the flux prior's settings only apply to a flux prior
    assert back.apply(plf.Config.paper()).amplitude_prior_power == 2.0
    (tmp_path / "bad.json").write_text('{"priors": {"ellipticity": {"B": 1}}}')
    with pytest.raises(ValueError, match="bad.json: malformed priors"):
        plf.Priors.load(tmp_path / "bad.json")
    (tmp_path / "nojson.json").write_text("not json")
    with pytest.raises(ValueError, match="nojson.json: not JSON"):
        plf.Priors.load(tmp_path / "nojson.json")


def test_small_sample_falls_back_to_the_defaults_with_a_warning():
    from test_readme import _stamps

    stamps, psf = _stamps(30)
    with pytest.warns(plf.CalibrationWarning) as rec:
        pr = plf.calibrate(stamps, psf, noise_sigma=1.0)
    said = " ".join(str(w.message) for w in rec)
    for what in ("ellipticity", "size", "flux power", "flux range"):
        assert f"the {what} prior falls back" in said
    assert pr.ellipticity.params == plf.Prior().params and pr.size is None
    assert pr.flux_range is None and pr.flux_power == 2.0
    assert set(pr.info["fallbacks"]) >= {"ellipticity", "size", "flux power", "flux range"}


def test_presets_and_the_paper_setup(tmp_path):
    c, p = plf.Config(), plf.Config.paper()
    assert (c.model, c.n_bulge_fractions, c.size_prior, c.amplitude_prior) == (
        "bulge+disc", 3, "estimated", "flux")
    assert (p.model, p.n_bulge_fractions, p.size_prior, p.amplitude_prior, p.r_step,
            p.max_stamp_size, p.min_snr) == ("devaucouleurs", 1, "flat", "uniform", 0.2, 0, 0.0)
    assert plf.Config.preset("paper", e_step=0.05).e_step == 0.05
    (tmp_path / "c.yaml").write_text("preset: paper\nr_max: 8.0\n")
    y = plf.Config.from_yaml(tmp_path / "c.yaml")
    assert y.model == "devaucouleurs" and y.r_max == 8.0
    with pytest.raises(plf.ConfigError, match="unknown preset"):
        plf.Config.preset("nope")
    with pytest.raises(plf.ConfigError, match="did you mean 'r_max'"):
        plf.Config.from_dict({"r_maxx": 3})


def test_estimate_shear_defaults_to_the_fixed_point():
    from pylensfit.shear import shear_fixed_point

    rng = np.random.default_rng(4)
    eg = plf.ellipticity_grid(0.1)
    pr = plf.Prior()
    e0 = rng.normal(0, 0.25, (400, 2)).clip(-0.8, 0.8) + 0.05
    lnL = (-0.5 * ((eg[None, :, 0] - e0[:, :1]) ** 2 + (eg[None, :, 1] - e0[:, 1:]) ** 2)
           / 0.1**2).astype(np.float32)  # fmt: skip
    t = plf.shapes(lnL, eg, pr)
    t["lnL"] = lnL
    t["weight"] = np.where(np.arange(400) < 380, 1.0, 0.0)  # the last 20 not used
    t.meta.update(prior=pr, egrid=eg, refine=4)
    g = plf.estimate_shear(t)
    ref = shear_fixed_point(lnL[:380], eg, pr, refine=4)
    assert (g.g1, g.g2, g.n) == (ref.g1, ref.g2, 380)
    assert plf.estimate_shear(t, estimator="key2").n == 380
    with pytest.raises(ValueError, match="estimator='key2'"):
        plf.estimate_shear(plf.shapes(lnL, eg, pr))
