"""Inverse-variance weights: the likelihood variance, the class weights and the weighted
shear estimators."""

import numpy as np
from astropy.table import Table

from pylensfit import Prior, estimate_shear
from pylensfit.grid import ellipticity_grid
from pylensfit.weights import (
    class_weights,
    lensfit_weights,
    likelihood_variance,
    population_variance,
)


def test_likelihood_variance_of_a_gaussian():
    egrid = ellipticity_grid(0.01, emax=1.0)
    c = np.array([[0.1, -0.2], [0.0, 0.0], [0.3, 0.3]])
    sig = np.array([0.03, 0.06, 0.1])
    d2 = ((egrid[None] - c[:, None]) ** 2).sum(axis=2)
    lnL = -0.5 * d2 / sig[:, None] ** 2
    v = sig**2
    np.testing.assert_allclose(likelihood_variance(lnL, egrid, 1.0), v / (1 - 2 * v),
                               rtol=2e-3)  # fmt: skip
    # a flat likelihood over the disc: v = 1/4, corrected to 1/2
    assert abs(likelihood_variance(np.zeros((1, len(egrid))), egrid, 1.0)[0] - 0.5) < 0.01


def test_population_variance_of_the_prior():
    p = Prior()
    e = p.sample(200_000, rng=np.random.default_rng(1))
    assert abs(population_variance(p) - 0.5 * np.mean((e**2).sum(axis=1))) < 0.002


def _toy(rng, n, g, posterior):
    """Gaussian shapes (sigma_pop 0.25) with noise 0.05-0.5 from the S/N; posterior means
    and sensitivities, or the noisy ellipticities themselves with sensitivity 1."""
    sp = 0.25
    snr0 = np.exp(rng.uniform(np.log(5), np.log(100), n))
    sn = 2.5 / snr0
    e = rng.normal(0, sp, (n, 2)) + np.asarray(g) + rng.normal(0, 1, (n, 2)) * sn[:, None]
    s = sp**2 / (sp**2 + sn**2) if posterior else np.ones(n)
    return e * (s[:, None] if posterior else 1.0), s, snr0, sn, sp


def test_class_weights_are_equal_for_posterior_means():
    rng = np.random.default_rng(3)
    e, s, snr0, *_ , sp = _toy(rng, 40_000, (0, 0), posterior=True)
    w = class_weights(e[:, 0], e[:, 1], s, s, snr0, np.ones_like(snr0), np.ones(len(s), bool))
    # <sens> / Var(<e>) = 1 / sigma_pop^2 at every S/N (the shrinkage cancels)
    np.testing.assert_allclose(w, 1 / sp**2, rtol=0.2)
    assert abs(np.median(w) * sp**2 - 1) < 0.03


def test_a_weight_does_not_depend_on_the_galaxys_own_shape():
    rng = np.random.default_rng(4)
    e, s, snr0, *_ = _toy(rng, 2000, (0, 0), posterior=True)
    use = np.ones(len(s), bool)
    w0 = class_weights(e[:, 0], e[:, 1], s, s, snr0, np.ones_like(snr0), use)
    e[7] = (0.9, -0.3)
    w1 = class_weights(e[:, 0], e[:, 1], s, s, snr0, np.ones_like(snr0), use)
    assert abs(w1[7] - w0[7]) < 1e-12 * w0[7] and np.any(np.abs(w1 - w0) > 1e-6 * w0)


def test_weights_cut_the_error_of_noisy_ellipticities_and_keep_the_shear():
    rng = np.random.default_rng(5)
    g = (0.03, -0.02)
    e, s, snr0, sn, sp = _toy(rng, 60_000, g, posterior=False)
    use = np.ones(len(s), bool)
    t = Table({"e1": e[:, 0], "e2": e[:, 1], "sens1": s, "sens2": s})
    t["weight"] = class_weights(t["e1"], t["e2"], s, s, snr0, np.ones_like(snr0), use)
    # the inverse variance of each class: 1 / (sigma_pop^2 + sigma_n^2)
    np.testing.assert_allclose(t["weight"], 1 / (sp**2 + sn**2), rtol=0.35)
    lf = lensfit_weights(sn**2, snr0, np.ones_like(snr0), sp**2, use)
    np.testing.assert_allclose(lf, 1 / (sp**2 + sn**2), rtol=0.35)
    a = estimate_shear(t, estimator="key2")
    b = estimate_shear(t, estimator="key2", weighted=True)
    assert b.g1_err < 0.93 * a.g1_err and b.g2_err < 0.93 * a.g2_err  # 0.906 here
    for est in (a, b):
        assert abs(est.g1 - g[0]) < 3 * est.g1_err and abs(est.g2 - g[1]) < 3 * est.g2_err
