"""The flexible ellipticity prior (a cubic B-spline in |e|): its density, its estimate
from likelihood grids, the shear under it, and its persistence.

The population here is a ring in ``|e|`` (few round galaxies, a mode at 0.4-0.5): a
shape outside the functional form of Kitching et al. (2008), whose estimate ends on a
bound of its parameters there.
"""

import numpy as np
import pytest
from astropy.table import Table
from scipy.stats import norm

from pylensfit import Config, ConfigError
from pylensfit.grid import DEFAULT_REFINE, ellipticity_grid
from pylensfit.pipeline import read_catalogue, write_catalogue
from pylensfit.prior import (
    Prior,
    RadialPrior,
    SplinePrior,
    estimate_prior,
    marginal_log_likelihood,
)
from pylensfit.shear import apply_shear, sensitivity_from_sums, shapes
from pylensfit.shear.posterior import all_sums

EGRID = ellipticity_grid(0.1)


def gaussian_lnL(e_obs, s, egrid=EGRID):
    """ln L_a(e) = -|e - e_obs_a|^2 / (2 s_a^2) on the grid, shifted to a maximum of 0."""
    d2 = (egrid[None, :, 0] - e_obs[:, :1]) ** 2 + (egrid[None, :, 1] - e_obs[:, 1:]) ** 2
    lnL = -d2 / (2.0 * s[:, None] ** 2)
    return lnL - lnL.max(axis=1, keepdims=True)


def ring(rng, n, mean, width):
    """``n`` complex ellipticities with ``|e| ~ N(mean, width)`` (clipped), random angles."""
    r = np.clip(rng.normal(mean, width, n), 0.02, 0.9)
    return r * np.exp(1j * rng.uniform(0.0, 2.0 * np.pi, n))


def noisy_sample(rng, e, smin=0.05, smax=0.3):
    s = rng.uniform(smin, smax, e.size)
    obs = np.column_stack([e.real, e.imag]) + s[:, None] * rng.standard_normal((e.size, 2))
    return gaussian_lnL(obs, s)


def test_density_gradient_and_normalisation():
    coef = [0.3, 1.0, 2.0, 1.5, 0.0, -1.0, -3.0, -6.0]
    p = SplinePrior(coef=coef, egrid=EGRID)
    assert np.sum(p.grid_pdf()) * p.step**2 == pytest.approx(1.0, rel=1e-12)
    rng = np.random.default_rng(0)
    e = rng.uniform(-0.6, 0.6, (50, 2))
    h = 1e-6
    g1, g2 = p.grad(e[:, 0], e[:, 1])
    f1 = (p.pdf(e[:, 0] + h, e[:, 1]) - p.pdf(e[:, 0] - h, e[:, 1])) / (2 * h)
    f2 = (p.pdf(e[:, 0], e[:, 1] + h) - p.pdf(e[:, 0], e[:, 1] - h)) / (2 * h)
    np.testing.assert_allclose(g1, f1, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(g2, f2, rtol=1e-6, atol=1e-8)
    assert p.pdf(1.0, 0.0) == 0.0 and p.pdf(0.7, 0.8) == 0.0
    # a constant added to every coefficient is the same prior
    q = SplinePrior(coef=np.asarray(coef) + 5.0, egrid=EGRID)
    np.testing.assert_allclose(q.grid_pdf(), p.grid_pdf(), rtol=1e-12)
    # the default is close to the functional prior's STEP-like defaults
    r = np.linspace(0.05, 0.85, 30)
    ratio = SplinePrior().pdf(r, 0 * r) / Prior().pdf(r, 0 * r)
    assert np.all(np.abs(ratio - 1) < 0.05)


def test_spline_follows_a_population_the_functional_form_cannot():
    """20,000 noisy likelihoods of a ring population: the spline's |e| density is within
    15 % of the truth where it exceeds a fifth of its peak, with the higher marginal
    likelihood; the functional form ends on a bound and misses the truth by far more."""
    rng = np.random.default_rng(1)
    lnL = noisy_sample(rng, ring(rng, 20_000, 0.45, 0.12))
    ps = estimate_prior(lnL, EGRID, form="spline")
    pf = estimate_prior(lnL, EGRID)
    assert ps.info["at_bound"] == [] and ps.info["converged"]
    assert pf.info["at_bound"]
    assert marginal_log_likelihood(lnL, EGRID, ps) > marginal_log_likelihood(lnL, EGRID, pf) + 100
    r = np.linspace(0.05, 0.85, 17)
    truth = norm.pdf(r, 0.45, 0.12)
    big = truth > 0.2 * truth.max()
    err_s = np.abs(ps.radial_pdf(r) / truth - 1)[big]
    err_f = np.abs(pf.radial_pdf(r) / truth - 1)[big]
    print(err_s.max(), err_f.max())
    assert err_s.max() < 0.15 and err_f.max() > 0.3


def test_shear_under_the_spline_prior_is_unbiased_where_the_functional_is_not():
    """Known shear g1 = +-0.02 on a narrow ring population (|e| ~ 0.5 +- 0.08) in rings of
    four with the noise rotated alike, each prior estimated from 20,000 unsheared
    galaxies of the same population: with the exact sensitivity the spline prior gives
    |m| <= 3e-3 (seeds 7-9: -0.0010, +0.0021, -0.0016), the functional form m of 0.007
    to 0.014 in size."""
    rng = np.random.default_rng(9)
    cal = noisy_sample(rng, ring(rng, 20_000, 0.5, 0.08))
    priors = {"spline": estimate_prior(cal, EGRID, form="spline"),
              "functional": estimate_prior(cal, EGRID)}  # fmt: skip
    n = 10_000
    base = ring(rng, n, 0.5, 0.08)
    s0 = rng.uniform(0.05, 0.3, n)
    n0 = s0 * (rng.standard_normal(n) + 1j * rng.standard_normal(n))
    rot = np.array([1, 1j, -1, -1j])
    es, noise, s = (base[:, None] * rot).ravel(), (n0[:, None] * rot).ravel(), np.repeat(s0, 4)
    m = {}
    for name, prior in priors.items():
        g_hat = []
        for g in (0.02, -0.02):
            e1, e2 = apply_shear(es.real, es.imag, g, 0.0)
            lnL = gaussian_lnL(np.column_stack([e1 + noise.real, e2 + noise.imag]), s)
            S, _ = all_sums(lnL, EGRID, prior, DEFAULT_REFINE, None, None)
            sens = sensitivity_from_sums(S, "exact")[0]
            g_hat.append(np.sum(S[:, 1] / S[:, 0]) / np.sum(sens))
        m[name] = (g_hat[0] - g_hat[1]) / 0.04 - 1
    print("m with each prior:", m)
    assert abs(m["spline"]) <= 3e-3
    assert abs(m["functional"]) > 5e-3


def test_persistence(tmp_path):
    p = SplinePrior(coef=[0.1, 1.0, 2.0, 1.5, 0.0, -1.0, -3.0, -6.0], egrid=EGRID,
                    method="direct", info={"n_used": 5})  # fmt: skip
    path = tmp_path / "prior.json"
    p.save(path)
    for q in (RadialPrior.load(path), SplinePrior.load(path)):
        assert isinstance(q, SplinePrior)
        np.testing.assert_allclose(q.grid_pdf(), p.grid_pdf(), rtol=1e-12)
    with pytest.raises(ValueError, match="prior.json: not an ellipticity prior of form "
                                         "'functional'"):  # fmt: skip
        Prior.load(path)
    assert isinstance(RadialPrior.from_dict(Prior().to_dict()), Prior)
    with pytest.raises(ValueError, match="no entry 'coef'"):
        RadialPrior.from_dict({"form": "spline", "step": 0.1})
    # through a catalogue's header, and into shapes
    rng = np.random.default_rng(3)
    n = 30
    e0 = rng.normal(0, 0.25, (n, 2))
    lnL = gaussian_lnL(e0, np.full(n, 0.1)).astype(np.float32)
    t = Table({"x": rng.uniform(0, 100, n), "y": rng.uniform(0, 100, n),
               "image": ["a.fits"] * n, "flags": np.zeros(n, np.int32),
               "fitclass": np.zeros(n, np.int16), "weight": np.ones(n), "lnL": lnL})  # fmt: skip
    t.meta.update(egrid=EGRID, prior=p)
    write_catalogue(t, tmp_path / "cat.fits")
    back = read_catalogue(tmp_path / "cat.fits").meta["prior"]
    assert isinstance(back, SplinePrior) and back.method == "direct"
    np.testing.assert_allclose(back.grid_pdf(), p.grid_pdf(), rtol=1e-6)
    sh = shapes(lnL, EGRID, back)
    assert sh.meta["prior"]["form"] == "spline" and np.all(np.isfinite(sh["e1"]))


def test_config_form_and_method():
    assert Config.paper().prior_form == "functional"
    with pytest.raises(ConfigError, match="prior_method 'direct'"):
        Config(prior_form="spline", prior_method="em")
    with pytest.raises(ConfigError, match="prior_form must be"):
        Config(prior_form="histogram")
    with pytest.raises(ValueError, match="method 'direct' only"):
        estimate_prior(np.zeros((3, len(EGRID))), EGRID, form="spline", method="em")
