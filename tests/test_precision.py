"""Paired precision mode: renderings, the streamed fixed point, the jackknife, a small run."""

from __future__ import annotations

import numpy as np
import pytest

from pylensfit import Config, ellipticity_grid, shear_fixed_point
from pylensfit.likelihood import fit_stamps
from pylensfit.models import model_bank
from pylensfit.prior import Prior, estimate_size_prior
from pylensfit_validation.precision import (
    PrecisionSpec,
    bias_table,
    default_config,
    population_prior,
    population_table,
    precision,
    reduce_likelihoods,
    reduce_renderings,
    reference_norm,
    render_block,
    shape_controls,
    shear_from_sums,
    spec_with,
)

galsim = pytest.importorskip("galsim")

EGRID = ellipticity_grid(0.1)
PRIOR = Prior(B=0.19, C=0.58, D=2.4)


def test_renderings_share_noise_and_are_reproducible():
    """+g and -g share a noise field, the rotated twin has its own; same seed, same pixels."""
    spec = PrecisionSpec(ngal=40, block_size=10, seed=4)
    noisy, psf, truth = render_block(spec, 1, 2)
    clean, _, _ = render_block(spec, 1, 2, noise=False)
    again, _, _ = render_block(spec, 1, 2)
    assert noisy.shape == (10, 4, 32, 32) and len(truth) == 10
    np.testing.assert_array_equal(noisy, again)
    n = noisy - clean
    np.testing.assert_allclose(n[:, 0], n[:, 2], atol=1e-4)
    np.testing.assert_allclose(n[:, 1], n[:, 3], atol=1e-4)
    assert np.std(n[:, 0] - n[:, 1]) > 1.0  # independent unit-variance fields
    # the shear changes the galaxy; the truth's S/N is that of the +g rendering
    assert np.all(np.abs(clean[:, 0] - clean[:, 2]).max(axis=(1, 2)) > 0)
    snr = np.sqrt((clean[:, 0].astype(float) ** 2).sum(axis=(1, 2))) / spec.noise_sigma
    np.testing.assert_allclose(snr, truth["snr"], rtol=1e-5)
    # the flux is the galaxy's own, whatever its shape, size and shear: every rendering
    # holds it (less what the 32-pixel stamp cuts off: 3% of a large de Vaucouleurs
    # galaxy's), and it is the drawn reference S/N over the PSF's reference norm, one
    # constant for all galaxies
    frac = clean.astype(float).sum(axis=(2, 3)) / np.asarray(truth["flux"])[:, None]
    assert frac.max() < 1.0005 and frac.min() > 0.95 and np.median(frac) > 0.995
    np.testing.assert_allclose(frac, np.repeat(frac[:, :1], 4, axis=1), rtol=2e-3)
    np.testing.assert_allclose(truth["flux"] * reference_norm(spec, 1) / spec.noise_sigma,
                               truth["snr_ref"], rtol=1e-9)  # fmt: skip
    # so the S/N differs from the reference S/N by the galaxy's size and shape
    ratio = np.asarray(truth["snr"]) / np.asarray(truth["snr_ref"])
    assert ratio.max() / ratio.min() > 1.3
    small = np.asarray(truth["size_ratio"]) < 0.8
    big = np.asarray(truth["size_ratio"]) > 1.6
    if small.any() and big.any():
        assert ratio[small].min() > ratio[big].max()
    assert abs(psf.sum() - 1) < 1e-6
    # the calibration sample is unsheared, one rendering per galaxy, other galaxies
    cal, _, ct = render_block(spec, 1, 2, calibration=True)
    assert cal.shape[1] == 1 and not np.allclose(ct["snr"], truth["snr"])


def test_noise_twins_are_the_renderings_with_their_noise_negated():
    """Renderings 4-7 hold the objects of 0-3 with the noise fields negated; 0-3 are the
    set without twins, pixel for pixel."""
    spec = PrecisionSpec(ngal=40, block_size=10, seed=4, noise_twins=True)
    noisy, _, truth = render_block(spec, 1, 2)
    clean, _, _ = render_block(spec, 1, 2, noise=False)
    plain, _, truth0 = render_block(spec_with(spec, noise_twins=False), 1, 2)
    assert noisy.shape == (10, 8, 32, 32)
    np.testing.assert_array_equal(noisy[:, :4], plain)
    np.testing.assert_array_equal(np.asarray(truth["e1_int"]), np.asarray(truth0["e1_int"]))
    np.testing.assert_array_equal(clean[:, 4:], clean[:, :4])
    # the mean of a rendering and its twin has no noise; half their difference is the
    # noise, one unit-variance field per (galaxy, rotation), shared by +g and -g
    np.testing.assert_allclose((noisy[:, :4] + noisy[:, 4:]) / 2, clean[:, :4], atol=2e-5)
    half = (noisy[:, :4] - noisy[:, 4:]) / 2
    np.testing.assert_allclose(half, noisy[:, :4] - clean[:, :4], atol=2e-5)
    assert abs(np.std(half) - spec.noise_sigma) < 0.02
    np.testing.assert_allclose(half[:, 0], half[:, 2], atol=1e-5)
    assert abs(np.corrcoef(half[:, 0].ravel(), half[:, 1].ravel())[0, 1]) < 0.03
    # the calibration sample has no twins
    assert render_block(spec, 1, 2, calibration=True)[0].shape[1] == 1


def test_rotated_twin_of_a_round_psf_is_the_rotated_image():
    """With a round PSF, the rotated +g galaxy is the -g galaxy turned by 90 degrees.

    A 90-degree turn maps a shear g to -g, so rendering 1 (rotated, +g) is rendering 2
    (-g) rotated: checked on the noise-free stamps about the stamp centre of an odd
    stamp, after undoing the sub-pixel offset with a GalSim rendering at zero offset.
    """
    spec = PrecisionSpec(ngal=8, block_size=8, seed=2, morphology_weights=(1, 0, 0, 0, 0))
    clean, _, t = render_block(spec, 0, 0, stamp_size=33, noise=False)
    import pylensfit_validation.precision as pp

    psf = pp.galsim_psf(spec.psfs[0])
    for a in range(len(t)):
        gal = galsim.Exponential(half_light_radius=float(t["r"][a])).shear(
            g1=float(t["e1_int"][a]), g2=float(t["e2_int"][a])
        )
        g = spec.g
        off = (float(t["dx"][a]), float(t["dy"][a]))
        rot = galsim.Convolve(gal.rotate(90 * galsim.degrees).shear(g1=g, g2=g), psf)
        minus = galsim.Convolve(gal.shear(g1=-g, g2=-g), psf)
        np.testing.assert_allclose(clean[a, 1], pp.draw_image(rot, 33, off) * t["flux"][a],
                                   atol=1e-4)
        # at zero offset the rotation identity is exact on the pixel grid
        r0, m0 = pp.draw_image(rot, 33), pp.draw_image(minus, 33)
        np.testing.assert_allclose(r0, np.rot90(m0), atol=1e-6 * r0.max())
        # On the mode's even stamp, with the offset turned with the galaxy, the +g
        # rendering turned by +90 degrees about element [N//2, N//2] is the turned
        # galaxy's -g rendering (rows and columns 1..N-1; row and column 0 have no
        # partner): the renderings' half of the argument that a round PSF's c is 0.
        plus = pp.draw_image(galsim.Convolve(gal.shear(g1=g, g2=g), psf), 32, off)
        turned = pp.draw_image(galsim.Convolve(gal.rotate(90 * galsim.degrees).shear(g1=-g, g2=-g),
                                          psf), 32, (-off[1], off[0]))  # fmt: skip
        np.testing.assert_allclose(np.rot90(plus[1:, 1:], k=-1), turned[1:, 1:],
                                   atol=1e-6 * plus.max())  # fmt: skip


def test_offset_places_the_galaxies_about_the_stamp_centre():
    """``offset = 0`` centres every galaxy on element ``[n//2, n//2]`` (its noise-free
    centroid there, on an odd stamp that the cut leaves symmetric); the default spreads
    the centres over +-0.5 px, where the centroids follow the drawn offsets."""
    n = 33
    yy, xx = np.mgrid[:n, :n] - n // 2
    for off in (0.0, 0.5):
        spec = PrecisionSpec(ngal=20, block_size=20, seed=3, offset=off, snr_range=(100, 200),
                             size_ratio_range=(0.8, 1.2), morphology_weights=(1, 0, 0, 0, 0))
        clean, _, t = render_block(spec, 0, 0, stamp_size=n, noise=False)
        img = clean[:, 0].astype(float)
        cx = (img * xx).sum(axis=(1, 2)) / img.sum(axis=(1, 2))
        cy = (img * yy).sum(axis=(1, 2)) / img.sum(axis=(1, 2))
        tol = 1e-3 if off == 0 else 0.03  # the stamp's edge cuts an off-centre galaxy unevenly
        np.testing.assert_allclose(cx, t["dx"], atol=tol)
        np.testing.assert_allclose(cy, t["dy"], atol=tol)
        assert np.all(np.abs(t["dx"]) <= off) and (off == 0 or np.ptp(t["dx"]) > 0.5)
    with pytest.raises(ValueError, match="offset"):
        PrecisionSpec(offset=-1)


def test_gaussian_offsets_are_isotropic_with_the_square_variance():
    """``offset_shape="gaussian"`` draws isotropic offsets of variance ``offset^2 / 3`` per
    axis: their spin-4 moment ``<r^4 cos 4 phi> / <r^4>`` is zero (the square's is -0.42,
    aligned with the pixel axes); every other column of the truth is unchanged."""
    n = 40_000
    spin4 = {}
    tabs = {}
    for shape in ("square", "gaussian"):
        spec = PrecisionSpec(offset=0.5, offset_shape=shape, seed=4)
        t = population_table(spec, n, 2.0, np.random.default_rng(7), stratified=False)
        x, y = np.asarray(t["dx"]), np.asarray(t["dy"])
        np.testing.assert_allclose([x.var(), y.var()], 0.25 / 3, rtol=0.03)
        r4 = (x * x + y * y) ** 2
        spin4[shape] = np.mean(r4 * np.cos(4 * np.arctan2(y, x))) / np.mean(r4)
        tabs[shape] = t
    assert abs(spin4["gaussian"]) < 0.03
    assert spin4["square"] == pytest.approx(-0.42, abs=0.03)  # (2/80 - 6/144) / (2/80 + 2/144)
    for c in tabs["square"].colnames:
        if c not in ("dx", "dy"):
            np.testing.assert_array_equal(tabs["square"][c], tabs["gaussian"][c])
    with pytest.raises(ValueError, match="offset_shape"):
        PrecisionSpec(offset_shape="disc")


def test_calibration_sample_is_stratified_in_morphology_flux_and_size():
    """The calibration sample's morphologies come in proportion and, within each, its
    fluxes and sizes fill every one of ``n_k`` equal strata of their distributions once
    (the draws at random do not); the main sample is the same with the option on or off."""
    spec = PrecisionSpec(ngal=40, block_size=400, ncal=800, seed=3, snr_slope=2.0)
    w = np.asarray(spec.morphology_weights) / np.sum(spec.morphology_weights)
    lo, hi = spec.snr_range
    lr = np.log(spec.size_ratio_range)

    def strata(t):
        """For each morphology: whether the flux's and size's CDF values fill the strata."""
        out = []
        for k in range(w.size):
            s = np.asarray(t["morph"]) == k
            u = (lo**-1 - np.asarray(t["snr_ref"][s]) ** -1) / (lo**-1 - hi**-1)  # S^-2's CDF
            v = (np.log(np.asarray(t["size_ratio"][s])) - lr[0]) / (lr[1] - lr[0])
            full = np.arange(s.sum())
            out.append(all(np.array_equal(np.sort(np.floor(x * s.sum())), full) for x in (u, v)))
        return out

    _, _, t = render_block(spec, 0, 1, calibration=True, noise=False)
    np.testing.assert_array_equal(np.bincount(t["morph"], minlength=w.size), 400 * w)
    assert all(strata(t))
    rnd = spec_with(spec, stratified_calibration=False)
    _, _, t0 = render_block(rnd, 0, 1, calibration=True, noise=False)
    assert not any(strata(t0))
    assert not np.array_equal(np.bincount(t0["morph"], minlength=w.size), 400 * w)
    main = render_block(spec, 0, 0, stamp_size=24)
    main0 = render_block(rnd, 0, 0, stamp_size=24)
    np.testing.assert_array_equal(main[0], main0[0])
    for c in main[2].colnames:
        np.testing.assert_array_equal(main[2][c], main0[2][c])  # NaN where a column is unused


def _gaussian_lnL(e_obs, s):
    d2 = (EGRID[None, :, 0] - e_obs[:, :1]) ** 2 + (EGRID[None, :, 1] - e_obs[:, 1:]) ** 2
    return -d2 / (2.0 * s[:, None] ** 2)


def test_streamed_fixed_point_equals_the_iterated_one():
    """One Newton step from the nominal shear = shear_fixed_point iterated to convergence."""
    rng = np.random.default_rng(3)
    n = 4000
    g = np.array([0.03, -0.02])
    es = PRIOR.sample(n, rng=rng)
    es = es[:, 0] + 1j * es[:, 1]
    gc = complex(*g)
    e = (es + gc) / (1 + np.conj(gc) * es)
    s = rng.uniform(0.1, 0.25, n)
    e_obs = np.column_stack([e.real, e.imag]) + s[:, None] * rng.standard_normal((n, 2))
    lnL = _gaussian_lnL(e_obs, s)
    ref = shear_fixed_point(lnL, EGRID, PRIOR, refine=4)
    for gn in ([0.03, -0.02], [0.0, 0.0], [0.05, 0.0]):
        Q = reduce_likelihoods(lnL, EGRID, PRIOR, gn, refine=4)
        gh = shear_from_sums(Q.sum(axis=0), np.float64(n), np.array(gn), "fixed-point")
        tol = 2e-5 if gn == [0.03, -0.02] else 1e-3  # second order in (g_hat - g_n)
        assert np.max(np.abs(gh - [ref.g1, ref.g2])) < tol, (gn, gh, ref)
    # the key2 columns are those of shapes()
    from pylensfit import shapes

    t = shapes(lnL[:50], EGRID, PRIOR, refine=4)
    Q = reduce_likelihoods(lnL[:50], EGRID, PRIOR, (0.0, 0.0), refine=4)
    np.testing.assert_allclose(Q[:, 0], t["e1"], atol=1e-12)
    np.testing.assert_allclose(Q[:, 3], t["sens2"], atol=1e-12)
    tp = shapes(lnL[:50], EGRID, PRIOR, refine=4, sensitivity="paper")
    np.testing.assert_allclose(Q[:, 4], tp["sens1"], atol=1e-12)


def _synthetic_Q(n, m, c, sigma, rng):
    """Per-rendering quantities of galaxies with ``<e> = (1 + m) g + c + noise``.

    Sensitivities 1 and a zero prior response (``J = 0``), so every estimator reduces
    to the mean; the noise is shared by +g and -g as in the renderings.
    """
    g = 0.02
    Q = np.zeros((n, 4, 12))
    noise = sigma * rng.standard_normal((n, 2, 2))  # (galaxy, rotation, component)
    for k, sign in enumerate((1, 1, -1, -1)):
        e = sign * (1 + np.asarray(m)) * g + np.asarray(c) + noise[:, k % 2]
        Q[:, k, 0:2] = e
        Q[:, k, 6:8] = e
        Q[:, k, 2:6] = 1.0
    return Q, g


def test_bias_table_recovers_m_and_c_with_jackknife_errors():
    rng = np.random.default_rng(5)
    n, sigma = 20000, 0.3
    Q, g = _synthetic_Q(n, (0.01, -0.004), (2e-3, -1e-3), sigma, rng)
    usable = np.ones((n, 4), bool)
    blocks = np.arange(n) // 100
    t = bias_table(Q, usable, blocks, g)
    for r in t:
        # shared noise: m is exact whatever the noise; c carries the noise's mean
        assert abs(r["m1"] - 0.01) < 1e-9 and abs(r["m2"] + 0.004) < 1e-9
        assert r["m1_err"] < 1e-9
        expect = sigma / np.sqrt(2 * n)  # two independent noise fields per galaxy
        assert abs(r["c1"] - 2e-3) < 4 * expect and abs(r["c2"] + 1e-3) < 4 * expect
        assert 0.75 < r["c1_err"] / expect < 1.3
        assert r["n_gal"] == n and r["n_blocks"] == 200
    # a selection that drops +g renderings of positive-noise galaxies biases m when
    # each rendering is selected on its own, and not when the four go together
    noise_sign = Q[:, 0, 0] - (1.01 * g + 2e-3) > 0
    usable[noise_sign, 0] = False
    paired = bias_table(Q, usable, blocks, g)
    indep = bias_table(Q, usable, blocks, g, selection="independent")
    assert abs(paired["m1"][0] - 0.01) < 1e-9
    assert indep["m1"][0] < 0.01 - 1.0  # strong on purpose: half the +g upward noise gone
    assert paired["n_gal"][0] == n - noise_sign.sum()


def test_noise_twins_cancel_the_noise_to_first_order_in_c():
    """Eight renderings: the twins' negated noise cancels a response linear in the noise
    exactly (c and m exact) and keeps a quadratic one (a noise bias is not cancelled);
    the four renderings alone carry the noise in c."""
    rng = np.random.default_rng(8)
    n, sigma, q = 20000, 0.3, 0.2
    Q4, g = _synthetic_Q(n, (0.01, -0.004), (2e-3, -1e-3), sigma, rng)
    # the twins: e = signal + noise  ->  signal - noise
    signal = np.zeros((n, 4, 2))
    for k, sign in enumerate((1, 1, -1, -1)):
        signal[:, k] = sign * np.array([1.01, 0.996]) * g + np.array([2e-3, -1e-3])
    noise = Q4[:, :, 0:2] - signal
    Q = np.concatenate([Q4, Q4], axis=1)
    Q[:, 4:, 0:2] = Q[:, 4:, 6:8] = signal - noise
    blocks = np.arange(n) // 100
    t = bias_table(Q, np.ones((n, 8), bool), blocks, g)
    for r in t:
        for i, (m, c) in enumerate(((0.01, 2e-3), (-0.004, -1e-3)), start=1):
            assert abs(r[f"m{i}"] - m) < 1e-9 and abs(r[f"c{i}"] - c) < 1e-9, r
            assert r[f"m{i}_err"] < 1e-9 and r[f"c{i}_err"] < 1e-9
    t4 = bias_table(Q[:, :4], np.ones((n, 4), bool), blocks, g)
    assert np.all(t4["c1_err"] > 0.75 * sigma / np.sqrt(2 * n))
    # a quadratic response to the noise, q n^2 in both twins, survives: c moves by q sigma^2
    Qq = Q.copy()
    for sl in (slice(0, 2), slice(6, 8)):
        Qq[:, :4, sl] += q * noise**2
        Qq[:, 4:, sl] += q * noise**2
    tq = bias_table(Qq, np.ones((n, 8), bool), blocks, g)
    expect = q * sigma**2
    for r in tq[tq["estimator"] == "exact"]:
        assert abs(r["c1"] - 2e-3 - expect) < 4 * r["c1_err"] + 1e-9
        assert abs(r["c2"] + 1e-3 - expect) < 4 * r["c2_err"] + 1e-9
        assert abs(r["m1"] - 0.01) < 1e-9  # the same at +g and -g: m is untouched
    # renderings lost from a twin pair drop the galaxy in the paired selection
    usable = np.ones((n, 8), bool)
    usable[:10, 5] = False
    assert bias_table(Q, usable, blocks, g)["n_gal"][0] == n - 10
    with pytest.raises(ValueError, match="4 or 8 renderings"):
        bias_table(Q[:, :6], np.ones((n, 6), bool), blocks, g)


def test_fixed_point_is_unbiased_for_narrow_gaussian_likelihoods():
    """The estimator's end of the chain, where the likelihood is narrower than the grid.

    Galaxies of the population's prior, their four renderings sheared by +-(g, g) with
    the noise shared by +g and -g as in the precision mode, and a Gaussian ``L(e)`` of
    width 0.03 or 0.1 about each noisy sheared shape, on the default grid (``e_step``
    0.1: the narrower likelihood spans a third of a cell). With the population's prior
    the posterior is the exact one, so the fixed point's m is zero: measured within
    2e-5 +- 5e-5 and 3e-4 +- 4e-4 (10,000 galaxies). The paper's sensitivity is biased
    here, by +0.002 and +0.0065 (so the precision run's m at the bright end is not the
    estimator's or the grid's).
    """
    from pylensfit.shear import apply_shear
    from pylensfit_validation.simulate import draw_shapes

    rng = np.random.default_rng(3)
    n, g = 10000, 0.02
    e = draw_shapes(PRIOR, n, rng, 0.99)  # as the precision mode draws them
    for sigma, tol, paper_min in ((0.03, 2e-4, 1.5e-3), (0.1, 1e-3, 4e-3)):
        noise = sigma * rng.standard_normal((2, n, 2))
        Q = np.empty((n, 4, 12))
        for k, (gk, rot) in enumerate(((g, 1), (g, -1), (-g, 1), (-g, -1))):
            o1, o2 = apply_shear(rot * e[:, 0], rot * e[:, 1], gk, gk)
            Q[:, k] = reduce_likelihoods(
                _gaussian_lnL(np.column_stack([o1, o2]) + noise[k % 2], np.full(n, sigma)),
                EGRID, PRIOR, (gk, gk), refine=4)  # fmt: skip
        t = bias_table(Q, np.ones((n, 4), bool), np.arange(n) // 100, g,
                       controls=shape_controls(e[:, 0], e[:, 1]))  # fmt: skip
        fp, paper = t[t["estimator"] == "fixed-point"][0], t[t["estimator"] == "paper"][0]
        for c in ("m1", "m2"):
            assert abs(fp[c]) < max(tol, 3 * fp[c + "_err"]), (sigma, c, fp[c], fp[c + "_err"])
            assert paper[c] > paper_min, (sigma, c, paper[c])


def test_shape_controls_remove_the_twins_shape_noise_without_bias():
    """Control variates: same expectation as the plain estimate, several times less noise.

    Galaxies respond to the shear ``(g, g)`` as ``e' = e + g - conj(g) e^2`` does, times
    ``1 + m`` and times an extra per-galaxy factor that the controls cannot predict, so
    the 90-degree twins leave the ``Re(e^2)``, ``Im(e^2)`` terms in m. Over 150 populations,
    the controlled m must average to the true m, its jackknife error must match its
    scatter, and that scatter must be well below the plain estimate's.
    """
    rng = np.random.default_rng(11)
    n, g, m_true = 4000, 0.02, np.array([0.01, -0.004])
    blocks = np.arange(n) // 100
    usable = np.ones((n, 4), bool)
    raw, cv, cv_err = [], [], []
    for _ in range(150):
        e = PRIOR.sample(n, rng=rng)
        x = shape_controls(e[:, 0], e[:, 1])
        u, v = x[:, 0], x[:, 1]
        extra = 1.0 + 0.1 * rng.standard_normal(n)
        resp = np.stack([1.0 - u - v, 1.0 + u - v], axis=1) * extra[:, None]
        Q = np.zeros((n, 4, 12))
        noise = 0.3 * rng.standard_normal((n, 2, 2))
        for k, sign in enumerate((1, 1, -1, -1)):
            ek = sign * (1 + m_true) * g * resp + noise[:, k % 2]
            Q[:, k, 0:2] = ek
            Q[:, k, 6:8] = ek
            Q[:, k, 2:6] = 1.0
        t0 = bias_table(Q, usable, blocks, g)
        t1 = bias_table(Q, usable, blocks, g, controls=x)
        assert not t0["controlled"][0] and t1["controlled"][0]
        r0, r1 = t0[t0["estimator"] == "exact"][0], t1[t1["estimator"] == "exact"][0]
        raw.append([r0["m1"], r0["m2"]])
        cv.append([r1["m1"], r1["m2"]])
        cv_err.append([r1["m1_err"], r1["m2_err"]])
    raw, cv, cv_err = map(np.asarray, (raw, cv, cv_err))
    sd_raw, sd_cv = raw.std(axis=0), cv.std(axis=0)
    assert np.all(np.abs(cv.mean(axis=0) - m_true) < 3 * sd_cv / np.sqrt(len(cv)))
    assert np.all(np.abs(raw.mean(axis=0) - m_true) < 3 * sd_raw / np.sqrt(len(raw)))
    assert np.all(sd_cv < 0.5 * sd_raw), (sd_cv, sd_raw)
    assert np.all(np.abs(cv_err.mean(axis=0) / sd_cv - 1) < 0.25), (cv_err.mean(0), sd_cv)
    # too few blocks for a regression: left as it was
    few = bias_table(Q, usable, np.arange(n) // 400, g, controls=x)
    plain = bias_table(Q, usable, np.arange(n) // 400, g)
    assert not few["controlled"][0] and few["m1"][0] == plain["m1"][0]


def test_small_precision_run_bright_exponentials():
    """End to end: bright exponential discs fitted with the exponential model.

    200 galaxies (800 renderings), round PSF, S/N 40-80, sizes 1-2.5 PSF radii; the
    paired design leaves an error of ~0.01 on m from this many galaxies. m must be
    within 4 jackknife sigma + 0.01 of 0 for the fixed point and the exact response,
    c within 4 sigma (a round PSF), and the paper's sensitivity, which is biased by the
    order of the likelihood width over the prior width, is reported alongside.
    """
    spec = spec_with(ngal=200, block_size=20, ncal=600, seed=11, psfs=["round"],
                     snr_range=(40.0, 80.0), size_ratio_range=(1.0, 2.5),
                     morphology_weights=(1, 0, 0, 0, 0))  # fmt: skip
    res = precision(spec, config=Config.paper(model="exponential"), progress=False)
    allrows = res[res["breakdown"] == "all"]
    assert set(allrows["estimator"]) == {"fixed-point", "exact", "paper"}
    for r in allrows:
        assert r["n_gal"] >= 190 and r["n_blocks"] == 10
        assert np.isfinite(r["m1_err"]) and r["m1_err"] > 0
        if r["estimator"] != "paper":
            for i in (1, 2):
                assert abs(r[f"m{i}"]) < 4 * r[f"m{i}_err"] + 0.01, r
                assert abs(r[f"c{i}"]) < 4 * r[f"c{i}_err"] + 1e-3, r
    assert res.meta["fp_step"] < 0.01
    assert set(res["breakdown"]) >= {"psf", "snr", "size", "morphology", "bulge_frac"}


def test_precision_run_with_noise_twins():
    """End to end with noise twins: the run's `no noise twins` rows are, to rounding, the
    same galaxies measured by a run without twins, and the twins shrink c's errors."""
    kw = dict(ngal=200, block_size=20, ncal=600, seed=11, psfs=["round"],
              snr_range=(15.0, 40.0), size_ratio_range=(1.0, 2.5),
              morphology_weights=(1, 0, 0, 0, 0))  # fmt: skip
    cfg = Config.paper(model="exponential")
    res = precision(spec_with(**kw, noise_twins=True), config=cfg, progress=False)
    ref = precision(spec_with(**kw), config=cfg, progress=False)
    assert res.meta["timing"]["renderings_per_s"] == pytest.approx(
        8 * res.meta["timing"]["galaxies_per_s"])
    twins = res[(res["breakdown"] == "all") & (res["group"] == "all")]
    plain = res[res["breakdown"] == "no noise twins"]
    base = ref[(ref["breakdown"] == "all") & (ref["group"] == "all")]
    assert list(plain["estimator"]) == list(base["estimator"])
    # (the fits run in batches of 8 stamps per galaxy instead of 4: float32 rounding)
    for q in ("m1", "m2", "c1", "c2", "m1_err", "c1_err"):
        np.testing.assert_allclose(plain[q], base[q], rtol=0, atol=2e-6)
    for r in twins:
        assert r["n_gal"] >= 190
        for i in (1, 2):
            assert abs(r[f"m{i}"]) < 4 * r[f"m{i}_err"] + 0.01, r
            assert abs(r[f"c{i}"]) < 4 * r[f"c{i}_err"] + 1e-3, r
    # c's error: the noise cancelled to first order (S/N 15-40: about three times smaller)
    assert np.all(twins["c1_err"] < 0.6 * plain["c1_err"])
    assert np.all(twins["c2_err"] < 0.6 * plain["c2_err"])


def _reflect_rows(a: np.ndarray) -> np.ndarray:
    """Rows reflected about element ``N // 2`` (``y -> -y`` about the galaxies' centre);
    row 0, which has no partner in the stamp, stays."""
    r = a.copy()
    r[..., 1:, :] = a[..., :0:-1, :]
    return r


def test_fit_is_covariant_under_the_stamps_reflections():
    """c = 0 for a round PSF by symmetry, if the fit treats x and y alike.

    The stamp's window (``[0, N)`` about element ``N // 2``), the e-grid and the priors
    are symmetric under the transpose, which maps ``(e1, e2) -> (-e1, e2)``, and, up to
    the window's row 0, under ``y -> -y``, which maps ``(e1, e2) -> (e1, -e2)``; the
    precision population and its noise are too. A fit that is covariant under
    both gives a round PSF's ``c = 0`` in expectation (both components), so its error
    bounds what any run could measure of it. Noisy renderings of the precision mix
    under the e=0.10 PSF (symmetric under ``y -> -y``; transposed with the data), fitted
    with the precision mode's configuration (bulge+disc, 64-pixel tiers, flux and
    position priors): the transposed stamps' posterior means are the originals' mapped
    to rounding (2e-8 in float64), the reflected ones' to the one unpaired row (medians
    of 1e-4 here; a mean of (-0.3 +- 1.1)e-5 over 8,000 renderings under the round
    PSF). The default centre moved by a quarter pixel in y breaks the transpose by 0.04,
    by 0.1 px along both axes the reflection's median by 8e-4.
    """
    spec = PrecisionSpec(ngal=40, block_size=40, seed=5)
    # in float64: float32 rounds the transposed products differently, which moves one
    # rendering of these 160 by 6e-5 (the others by 1e-6 or less)
    cfg = default_config(spec).replace(dtype="float64")
    prior = population_prior(spec)
    st, psf, _ = render_block(spec, 1, 0, stamp_size=cfg.largest_stamp)
    n = st.shape[0]

    def posterior(stamps, psf_img):
        f = fit_stamps(stamps.reshape(4 * n, *stamps.shape[2:]), psf_img, spec.noise_sigma,
                       config=cfg)  # fmt: skip
        Q, ok = reduce_renderings(f, prior, 0.0)
        assert ok.mean() > 0.95
        return Q, ok

    Q, ok = posterior(st, psf)
    QT, okT = posterior(np.ascontiguousarray(st.swapaxes(-1, -2)), np.ascontiguousarray(psf.T))
    QR, okR = posterior(_reflect_rows(st), _reflect_rows(psf))
    assert np.array_equal(ok, okT)
    e1, e2, s1, s2 = (Q[..., i][ok] for i in range(4))
    assert np.std(e1) > 0.1 and np.std(e2) > 0.1  # shapes that a wrong map would not hide
    # transpose: x <-> y, exact up to rounding (2e-8 measured)
    np.testing.assert_allclose(QT[..., 0][ok], -e1, atol=1e-6)
    np.testing.assert_allclose(QT[..., 1][ok], e2, atol=1e-6)
    np.testing.assert_allclose(QT[..., 2][ok], s1, atol=1e-6)
    np.testing.assert_allclose(QT[..., 3][ok], s2, atol=1e-6)
    # y -> -y: row 0's noise is the only unpaired datum
    both = ok & okR
    d2 = QR[..., 1][both] + Q[..., 1][both]
    d1 = QR[..., 0][both] - Q[..., 0][both]
    assert np.median(np.abs(d2)) < 3e-4 and np.median(np.abs(d1)) < 3e-4
    assert abs(np.mean(d2)) < 2e-4 and abs(np.mean(d1)) < 2e-4


def test_estimated_bulge_prior_finds_a_disc_population():
    """Exponential discs fitted with the bulge+disc model, fractions 0, 0.5, 1 marginalised.

    The bulge-fraction prior estimated from the calibration sample puts nearly all its
    weight on the pure disc (with the size prior uniform in half-light radius for every
    fraction), and m is then as for the exact model. (Uniform weights give m ~ +0.02 on
    such a population at S/N 10-200, ``benchmarks/studies/exact_model_bias.py``.)
    """
    spec = spec_with(ngal=200, block_size=20, ncal=600, seed=11, psfs=["round"],
                     snr_range=(40.0, 80.0), size_ratio_range=(1.0, 2.5),
                     morphology_weights=(1, 0, 0, 0, 0))  # fmt: skip
    cfg = Config.paper(model="bulge+disc", n_bulge_fractions=3)
    res = precision(spec, config=cfg, progress=False, prior=Prior(B=0.19, C=0.58, D=2.4))
    bp = res.meta["bulge_prior"]
    assert bp["method"] == "estimated" and bp["fractions"] == [0.0, 0.5, 1.0]
    assert abs(sum(bp["weights"]) - 1) < 1e-9 and bp["weights"][0] > 0.9, bp
    r = res[(res["breakdown"] == "all") & (res["estimator"] == "fixed-point")][0]
    for i in (1, 2):
        assert abs(r[f"m{i}"]) < 4 * r[f"m{i}_err"] + 0.01, r
    with pytest.raises(ValueError, match="bulge_prior"):
        Config.paper(model="bulge+disc", n_bulge_fractions=3, bulge_prior="flat")


def test_two_bulge_sizes_in_the_precision_mode(tmp_path):
    """A family with two bulge sizes (``bulge_size_ratio2``): the calibration estimates one
    weight per run (five), nearly all of it on the pure disc for a population of discs,
    and the meta and the report name each run's fraction and bulge size."""
    spec = spec_with(ngal=40, block_size=20, ncal=400, seed=11, psfs=["round"],
                     snr_range=(40.0, 80.0), size_ratio_range=(1.0, 2.5),
                     morphology_weights=(1, 0, 0, 0, 0))  # fmt: skip
    cfg = Config.paper(model="bulge+disc", n_bulge_fractions=3, bulge_size_ratio2=1.2)
    res = precision(spec, config=cfg, progress=False, prior=Prior(B=0.19, C=0.58, D=2.4))
    bp = res.meta["bulge_prior"]
    assert bp["fractions"] == [0.0, 0.5, 1.0, 0.5, 1.0]
    assert bp["sizes"] == [0.6, 0.6, 0.6, 1.2, 1.2]
    assert len(bp["weights"]) == 5 and abs(sum(bp["weights"]) - 1) < 1e-9
    assert bp["weights"][0] > 0.8, bp
    assert res.meta["config"]["bulge_size_ratio2"] == 1.2
    from pylensfit_validation.precision import write_report

    write_report(res, tmp_path / "report.md")
    text = (tmp_path / "report.md").read_text()
    assert "0.5 (bulge 1.2)" in text and "bulges of 0.6 and 1.2 disc scale lengths" in text
    with pytest.raises(ValueError, match="bulge_weights"):
        precision(spec, config=cfg, prior=Prior(B=0.19, C=0.58, D=2.4),
                  bulge_weights=(1, 0, 0), progress=False)  # fmt: skip


def test_sersic_ladder_in_the_precision_mode(tmp_path):
    """The Sersic ladder beside the bulge+disc runs (``sersic_ladder``): the calibration
    estimates one weight per run (nine), most of it on the pure disc for a population of
    exponential discs, and the meta and the report name each run's profile."""
    spec = spec_with(ngal=40, block_size=20, ncal=400, seed=11, psfs=["round"],
                     snr_range=(40.0, 80.0), size_ratio_range=(1.0, 2.5),
                     morphology_weights=(1, 0, 0, 0, 0))  # fmt: skip
    cfg = Config.paper(model="bulge+disc", n_bulge_fractions=3, sersic_ladder=(0.5, 2, 4))
    res = precision(spec, config=cfg, progress=False, prior=Prior(B=0.19, C=0.58, D=2.4))
    bp = res.meta["bulge_prior"]
    assert bp["labels"] == ["0", "0.5 (bulge 0.6)", "1 (bulge 0.6)", "Sersic 0.5",
                            "Sersic 0.5+1", "Sersic 1+2", "Sersic 2", "Sersic 2+4",
                            "Sersic 4"]  # fmt: skip
    assert len(bp["weights"]) == 9 and abs(sum(bp["weights"]) - 1) < 1e-9
    assert bp["weights"][0] == max(bp["weights"]) and bp["weights"][0] > 0.5, bp
    assert res.meta["config"]["sersic_ladder"] == [0.5, 2.0, 4.0]
    from pylensfit_validation.precision import write_report

    write_report(res, tmp_path / "report.md")
    assert "Sersic 2+4: " in (tmp_path / "report.md").read_text()


def test_flux_prior_bounds_are_estimated_from_the_calibration_fluxes(tmp_path):
    """With ``flux_bounds=True``, ``precision`` bounds the flux prior at each PSF's flux
    range as the calibration galaxies' fluxes and errors give it: within 3 errors (and
    10 %) of the population's limits for exponentials fitted as such, the faint one
    measured from galaxies at S/N 5-20, and the report says so; with
    ``flux_bounds=False`` the prior is unbounded."""
    from pylensfit_validation.precision import reference_norm, write_report

    spec = spec_with(ngal=20, block_size=20, ncal=1000, seed=4, psfs=["round"],
                     snr_range=(10.0, 200.0), size_ratio_range=(0.5, 1.5),
                     morphology_weights=(1, 0, 0, 0, 0))  # fmt: skip
    cfg = Config.paper(model="exponential", amplitude_prior="flux", estimate_flux_prior=True,
                       max_stamp_size=64)
    res = precision(spec, config=cfg, progress=False, prior=Prior(B=0.19, C=0.58, D=2.4),
                    flux_bounds=True)  # fmt: skip
    (b,) = res.meta["flux_bounds"]
    ref = spec.noise_sigma / reference_norm(spec, 0, 64)
    assert b["true"] == pytest.approx([10.0 * ref, 200.0 * ref])
    for k, key in enumerate(("lo", "hi")):
        assert abs(b[key] - b["true"][k]) < 3 * b[f"{key}_err"] + 1e-9, b
        assert abs(b[key] / b["true"][k] - 1) < 0.1, b
    assert 0 < b["lo_err"] < 0.05 * b["lo"]
    # the best model's flux scatters more than its fixed-model error (the size that
    # fits best moves with the noise), and the scale fitted with the limits says so
    assert b["error_scale"] > 1.1, b
    write_report(res, tmp_path / "r.md")
    text = (tmp_path / "r.md").read_text()
    assert "within each PSF's flux range as estimated" in text
    assert f"the errors' scale {b['error_scale']:.2f}" in text
    res0 = precision(spec_with(spec, ncal=200), config=cfg, progress=False,
                     prior=Prior(B=0.19, C=0.58, D=2.4), flux_bounds=False)  # fmt: skip
    assert res0.meta["flux_bounds"] is None


def test_flux_bounds_size_prior_is_estimated_under_the_bounded_flux_prior():
    """With ``flux_bounds=True`` and the size prior to estimate, the size prior comes
    from fits under the bounded flux prior the later passes use: the same as a run
    given those bounds and that power from the start (whose own bounds the default
    ``flux_bounds=True`` keeps). (Estimated from the unbounded
    first pass instead, it came out 10 % small and gave m = +0.009 with the bounds;
    ``benchmarks/studies/precision_priors.py --estimate-flux-bounds``.)"""
    spec = spec_with(ngal=10, block_size=100, ncal=300, seed=6, psfs=["round"],
                     morphology_weights=(1, 0, 0, 0, 0))  # fmt: skip
    cfg = Config.paper(model="exponential", amplitude_prior="flux", estimate_flux_prior=True,
                       size_prior="estimated", max_stamp_size=64)  # fmt: skip
    pri = Prior(B=0.19, C=0.58, D=2.4)
    res = precision(spec, config=cfg, progress=False, prior=pri, flux_bounds=True)
    (b,) = res.meta["flux_bounds"]
    beta = res.meta["flux_slope"]["value"]
    given = precision(spec, config=cfg.replace(amplitude_prior_min=b["lo"],
                                               amplitude_prior_max=b["hi"]),
                      progress=False, prior=pri, flux_slope=beta)  # fmt: skip
    assert given.meta["flux_bounds"] is None
    (sp,), (sp_given,) = res.meta["size_prior"], given.meta["size_prior"]
    np.testing.assert_allclose(sp["density"], sp_given["density"], rtol=1e-9, atol=1e-12)
    # and not the size prior of the unbounded fits
    free = precision(spec, config=cfg, progress=False, prior=pri, flux_slope=beta,
                     flux_bounds=False)  # fmt: skip
    (sp_free,) = free.meta["size_prior"]
    assert np.max(np.abs(np.asarray(sp_free["density"]) - sp["density"])) > 1e-3 * max(
        sp["density"])


def test_cli_precision_writes_report(tmp_path, capsys):
    from astropy.table import Table

    from pylensfit.cli import main

    rep = tmp_path / "prec" / "report.md"
    args = ["validate", "--precision", "--ngal", "16", "--ncal", "80", "--block-size", "4",
            "--psf", "round", "e=0.10", "--seed", "3", "--report", str(rep), "-q",
            "--true-prior"]  # fmt: skip
    # the flux range (estimated by default) needs 50 calibration galaxies per PSF: said
    # before any fit, with the remedy
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "flux_bounds needs at least 50 calibration galaxies per PSF" in err
    assert "spec.ncal = 80 gives 40" in err and not rep.exists()
    args[args.index("--ncal") + 1] = "160"
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "fixed-point" in out and "e=0.10" in out
    text = rep.read_text()
    assert "## psf" in text and "## snr" in text and "report_snr.png" in text
    assert (tmp_path / "prec" / "report_morphology.png").stat().st_size > 0
    tab = Table.read(rep.with_suffix(".ecsv"))
    assert set(tab["breakdown"]) >= {"all", "psf", "snr", "size", "selection", "no controls"}
    assert "## no controls" in text and "| cv |" in text
    # the mean of the two PSFs' m and c, their errors combined in quadrature
    fp = tab[tab["estimator"] == "fixed-point"]
    mean = fp[fp["group"] == "mean of PSFs"][0]
    per = fp[fp["breakdown"] == "psf"]
    assert len(per) == 2 and mean["breakdown"] == "all"
    assert abs(mean["m1"] - np.mean(per["m1"])) < 1e-12
    assert abs(mean["c2_err"] - np.hypot(*per["c2_err"]) / 2) < 1e-12
    # morphology per PSF: every galaxy of each PSF in one of its morphologies' groups
    pm = fp[fp["breakdown"] == "psf_morphology"]
    for name, n in zip(per["group"], per["n_gal"], strict=True):
        assert sum(r["n_gal"] for r in pm if r["group"].startswith(name + " ")) == n
    assert "## psf_morphology" in text
    # the Sersic galaxies by index: every one in a bin, no other galaxy in any
    sn = fp[fp["breakdown"] == "sersic_n"]
    (ns,) = fp[(fp["breakdown"] == "morphology") & (fp["group"] == "sersic")]["n_gal"]
    assert ns > 0 and sum(sn["n_gal"]) == ns and "## sersic_n" in text
    assert tab.meta["spec"]["ngal"] == 16
    # --true-prior: no calibration sample, the population's own prior
    assert "Prior given: B=0.190, C=0.580, D=2.400" in text and tab.meta["prior"]["given"]
    # the default model marginalises the bulge fraction, its prior from the calibration set
    assert "Bulge-fraction prior estimated from the calibration sample: 0: " in text
    assert abs(sum(tab.meta["bulge_prior"]["weights"]) - 1) < 1e-9
    # and the size prior, estimated from the calibration set too
    # one per PSF: the population's sizes are drawn relative to the PSF's
    assert "Size prior estimated from the calibration sample (one per PSF)" in text
    assert "(the true centres: uniform within ±0.5 px along both axes)" in text
    sps = tab.meta["size_prior"]
    assert [sp["psf"] for sp in sps] == ["round", "e=0.10"] and tab.meta["size_prior_per_psf"]
    # each with the smoothing it was estimated with, in the report too
    assert [sp["smoothing"] for sp in sps] == [0.25, 0.25] and "smoothing 0.25)" in text
    assert not np.array_equal(sps[0]["density"], sps[1]["density"])
    for sp in sps:
        # one density per bulge fraction (default_config's size_prior_per_run), each the
        # sizes' distribution given the fraction, and their mixture for the report
        dens = np.asarray(sp["density"])
        assert dens.shape == (3, len(sp["ln_h"]))
        for row in (*dens, sp["marginal"]):
            assert abs(np.trapezoid(row, sp["ln_h"]) + sp["star"] - 1) < 0.02
    # the default amplitude prior is a power law in the flux, its power the counts' slope
    # measured on the calibration sample's fluxes (drawn with power 2), and the fits use it
    fs = tab.meta["flux_slope"]
    assert fs["estimated"] and 0 < fs["error"] < 0.5
    assert abs(fs["value"] - 2.0) < 4 * fs["error"]
    # large galaxies go to larger stamps (default_config: up to 64 pixels)
    assert tab.meta["config"]["max_stamp_size"] == 64
    assert set(tab.meta["stamps"]) <= {32, 64} and sum(tab.meta["stamps"].values()) == 16
    assert "Stamps (the +g rendering's" in text
    assert tab.meta["config"]["amplitude_prior"] == "flux"
    assert tab.meta["config"]["amplitude_prior_power"] == fs["value"] != 2.0
    assert "estimated from the calibration sample's fluxes" in text
    # and bounded by default at each PSF's flux range as the calibration sample gives it
    assert [b["psf"] for b in tab.meta["flux_bounds"]] == ["round", "e=0.10"]
    assert all(0 < b["lo"] < b["hi"] for b in tab.meta["flux_bounds"])
    assert "within each PSF's flux range as estimated" in text
    # a directory or a mode is required
    with pytest.raises(SystemExit):
        main(["validate"])


def test_estimated_size_prior_recovers_the_population_sizes():
    """Faint de Vaucouleurs galaxies (S/N 10-20) fitted with their own profile: the size
    prior deconvolved from their L(r) matches the simulated half-light radii.

    L(r) is marginalised over e with the ellipticity prior; with a uniform weight over
    the e cells instead, elongated models' preference for small sizes took the median
    15% low (measured: 1.49 px for 1.76 px). The largest galaxies (above the 84th
    percentile) lose their wings to the 32-pixel stamp and come out ~10% small.
    """
    spec = spec_with(ngal=800, ncal=800, block_size=400, seed=4, psfs=["round"],
                     snr_range=(10.0, 20.0), size_ratio_range=(0.5, 2.5),
                     morphology_weights=(0, 1, 0, 0, 0))  # fmt: skip
    cfg = Config.paper(model="devaucouleurs")
    prior = Prior(B=0.19, C=0.58, D=2.4)
    L, h = [], []
    for b in range(2):
        st, psf, t = render_block(spec, 0, b, calibration=True)
        f = fit_stamps(st[:, 0], psf, 1.0, config=cfg, size_marginal_prior=prior)
        ok = (f.flags == 0) & ~f.is_star
        L.append(f.lnL_r[ok])
        h.append(np.asarray(t["r"])[ok])
    sp = estimate_size_prior(np.concatenate(L), model_bank(cfg), cfg)
    h = np.concatenate(h)
    cdf = np.cumsum(sp.density) / np.sum(sp.density)
    q = np.array([0.16, 0.5])
    # measured: 1.09 / 1.75 px against 1.03 / 1.76 px
    np.testing.assert_allclose(np.exp(np.interp(q, cdf, sp.ln_h)), np.quantile(h, q), rtol=0.07)
    assert sp.star < 1e-3


def test_given_size_and_bulge_priors_replace_the_estimates(monkeypatch):
    """``precision(size_prior=, bulge_weights=)``: the population's own size prior
    covers exactly the sizes that ``render_block`` draws, and given priors are used
    as they are (no calibration pass), recorded as given, and change the result."""
    from pylensfit_validation.precision import population_size_prior

    spec = spec_with(ngal=40, block_size=20, ncal=400, seed=3, psfs=["round"],
                     snr_range=(20.0, 40.0), morphology_weights=(1, 0, 0, 0, 0))  # fmt: skip
    sp = population_size_prior(spec, 0)
    _, _, t = render_block(spec, 0, 0, calibration=True, noise=False)
    lnr = np.log(np.asarray(t["r"]))
    lo, hi = sp.ln_h[1], sp.ln_h[-2]
    assert np.all((lnr >= lo) & (lnr <= hi))
    # log-uniform: the drawn sizes fill the support evenly (20 galaxies: loose)
    assert abs(np.mean((lnr - lo) / (hi - lo)) - 0.5) < 0.15
    assert hi - lo == pytest.approx(np.log(spec.size_ratio_range[1] / spec.size_ratio_range[0]))
    cfg = Config.paper(model="bulge+disc", n_bulge_fractions=3, size_prior="estimated")
    prior = Prior(B=0.19, C=0.58, D=2.4)

    def estimated(*args, **kw):
        raise AssertionError("a given prior was estimated")

    import pylensfit.prior as prior_module

    for name in ("estimate_prior", "estimate_prior_and_bulge", "estimate_bulge_weights",
                 "estimate_size_prior"):  # fmt: skip
        monkeypatch.setattr(prior_module, name, estimated)
    runs = {}
    for w in ((2, 0, 0), (0, 0, 1)):
        res = precision(spec, config=cfg, prior=prior, size_prior=sp, bulge_weights=w,
                        progress=False)  # fmt: skip
        assert res.meta["size_prior_given"]
        assert res.meta["size_prior"][0]["density"] == sp.density.tolist()
        bp = res.meta["bulge_prior"]
        assert bp["method"] == "given"
        np.testing.assert_allclose(bp["weights"], np.asarray(w) / sum(w))
        runs[w] = res[(res["breakdown"] == "all") & (res["estimator"] == "fixed-point")][0]
    # the same renderings fitted as discs and as de Vaucouleurs galaxies differ
    assert abs(runs[(2, 0, 0)]["m1"] - runs[(0, 0, 1)]["m1"]) > 1e-3
    with pytest.raises(ValueError, match="bulge_weights"):
        precision(spec, config=cfg, prior=prior, bulge_weights=(1, 1), progress=False)
    with pytest.raises(ValueError, match="size_prior"):
        precision(spec, config=cfg, prior=prior, size_prior=[sp, sp], progress=False)
    # priors to estimate and no calibration sample: a clear error, not an empty estimate
    with pytest.raises(ValueError, match="ncal is 0"):
        precision(spec_with(spec, ncal=0), config=cfg, size_prior=sp, bulge_weights=w,
                  progress=False)  # fmt: skip


def test_cli_precision_e_refine_reaches_the_configuration(monkeypatch):
    """``validate --precision --e-refine 2`` fits with the precision mode's own configuration
    refined (and a given one refined alike); ``--noise-twins`` reaches the spec."""
    import pylensfit_validation.precision as prec
    from pylensfit.cli import main

    seen = {}

    def fake(spec, *, config=None, **kw):
        seen["config"] = config
        seen["spec"] = spec
        raise SystemExit(0)

    monkeypatch.setattr(prec, "precision", fake)
    with pytest.raises(SystemExit):
        main(["validate", "--precision", "--ngal", "16", "--e-refine", "2", "-q"])
    spec = prec.spec_with(ngal=16)
    assert seen["config"] == prec.default_config(spec).replace(e_refine=2)
    with pytest.raises(SystemExit):
        main(["validate", "--precision", "--ngal", "16", "-q"])
    assert seen["config"] is None  # the mode's default, unrefined
    assert not seen["spec"].noise_twins
    with pytest.raises(SystemExit):
        main(["validate", "--precision", "--ngal", "16", "--noise-twins", "-q"])
    assert seen["spec"].noise_twins and seen["spec"].ngal == 16


def testbreakdowns_take_a_table_or_a_dict_and_bin_sersic_indices():
    """``breakdowns`` (the report's bins, also used by ``benchmarks/studies/precision_ab.py``
    on a dict of columns): the Sersic-index bins hold the Sersic galaxies and only them,
    each once; without Sersic galaxies there is no such breakdown."""
    from astropy.table import Table

    from pylensfit_validation.precision import PRECISION_PSFS, SERSIC_EDGES, breakdowns

    n = 7
    cols = {"snr": np.full(n, 20.0), "size_ratio": np.full(n, 1.2),
            "bulge_frac": np.array([0, 1, np.nan, np.nan, np.nan, 0.3, np.nan]),
            "morph": np.array([0, 1, 3, 3, 3, 2, 3]),
            "sersic_n": np.array([np.nan, np.nan, 0.5, 1.2, 4.0, np.nan, 2.5]),
            "psf": np.zeros(n, int)}  # fmt: skip
    for gal in (cols, Table(cols)):
        b = breakdowns(gal, PRECISION_PSFS[:1])
        counts = np.sum([v for v in b["sersic_n"].values()], axis=0)
        np.testing.assert_array_equal(counts, np.isfinite(cols["sersic_n"]).astype(int))
        assert len(b["sersic_n"]) == len(SERSIC_EDGES) - 1
        assert b["sersic_n"]["2.5-4"].sum() == 2  # 2.5 and the top edge, 4
    none = dict(cols, sersic_n=np.full(n, np.nan))
    assert "sersic_n" not in breakdowns(none, PRECISION_PSFS[:1])


def test_realistic_population_misaligns_the_bulges_and_keeps_the_rest():
    """``population="realistic"``: the same galaxies, fluxes, disc shapes and noise as the
    aligned population; only the bulges (their sizes, own shapes and misalignment, rms
    30 degrees for bulge+disc) and the Sersic indices (0.3-6) differ, and each bulge
    ends at its drawn position angle and within 0.2-1 of its disc's ellipticity."""
    kw = dict(ngal=400, block_size=400, ncal=40, psfs=["round"], seed=9)
    al, _, ta = render_block(spec_with(**kw), 0, 0)
    re, _, tr = render_block(spec_with(**kw, population="realistic"), 0, 0)
    for c in ("morph", "snr_ref", "r", "e1_int", "e2_int", "bulge_frac", "dx", "dy"):
        np.testing.assert_array_equal(ta[c], tr[c])
    name = np.asarray(("exponential", "devaucouleurs", "bulge+disc", "sersic", "knots"))[
        np.asarray(tr["morph"])]  # fmt: skip
    same = (name == "exponential") | (name == "devaucouleurs")
    np.testing.assert_array_equal(al[same], re[same])  # same renderings, same noise
    bd = name == "bulge+disc"
    assert not np.array_equal(al[bd], re[bd])
    assert np.all(ta["misalign"][bd] == 0) and np.isnan(tr["misalign"][same]).all()
    assert 22 < np.sqrt(np.mean(np.asarray(tr["misalign"][bd]) ** 2)) < 38
    sn = np.asarray(tr["sersic_n"])[name == "sersic"]
    assert sn.min() < 0.5 and sn.max() > 4.0 and sn.min() >= 0.3 and sn.max() <= 6.0
    # the bulge's final shape: GalSim's shear matrices of the intrinsic shape after its own
    for row in tr[bd][:20]:
        a = (galsim.Shear(g1=row["e1_int"], g2=row["e2_int"]).getMatrix()
             @ galsim.Shear(g1=row["bulge_g1"], g2=row["bulge_g2"]).getMatrix())  # fmt: skip
        q = a @ a.T
        d = complex(q[0, 0] - q[1, 1], 2 * q[0, 1]) / (q[0, 0] + q[1, 1])
        eb = d / (1 + np.sqrt(1 - abs(d) ** 2))
        ed = complex(row["e1_int"], row["e2_int"])
        assert 0.2 - 1e-9 <= abs(eb) / abs(ed) <= 1 + 1e-9
        dphi = np.rad2deg(np.angle(eb / ed)) / 2
        assert dphi == pytest.approx(row["misalign"], abs=1e-6)
    with pytest.raises(ValueError, match="population"):
        spec_with(population="cosmos")


def test_spec_checks_its_morphologies_and_snr_range():
    assert spec_with(morphology_weights=(1, 0, 0, 0, 0)).morphology_weights == (1, 0, 0, 0, 0)
    for bad in ((1, 0, 0, 0, -1), (0, 0, 0, 0, 0), (1, 0, 0, 0, np.nan)):
        with pytest.raises(ValueError, match="morphology_weights"):
            spec_with(morphology_weights=bad)
    for bad in ((20.0, 10.0), (0.0, 10.0)):
        with pytest.raises(ValueError, match="snr_range"):
            spec_with(snr_range=bad)


def test_realistic_precision_run_reports_m_by_misalignment(tmp_path):
    """A small run of the realistic population: the misalignment and the wide Sersic
    breakdowns are in the table, the population in the report."""
    spec = spec_with(ngal=120, block_size=40, ncal=200, seed=5, psfs=["round"],
                     population="realistic", snr_range=(40.0, 80.0),
                     morphology_weights=(0, 0, 1, 1, 0))  # fmt: skip
    res = precision(spec, config=Config.paper(model="exponential"), progress=False,
                    prior=PRIOR, report=tmp_path / "r.md")  # fmt: skip
    groups = set(res["group"][res["breakdown"] == "misalign"])
    assert groups <= {"0-10", "10-20", "20-40", "40-90"} and len(groups) >= 3
    assert "0.3-0.5" in set(res["group"][res["breakdown"] == "sersic_n"]) or "4-6" in set(
        res["group"][res["breakdown"] == "sersic_n"])  # fmt: skip
    assert "realistic population" in (tmp_path / "r.md").read_text()


def test_breakdown_by_the_measured_bulge_fraction():
    """Exponentials and de Vaucouleurs galaxies at S/N 40-80 fitted with the fraction
    marginalised: the posterior mean bulge fraction puts the discs in the lowest bin and
    the bulges in the highest (an observed quantity, the breakdown conditional on the
    data)."""
    spec = spec_with(ngal=120, block_size=40, ncal=300, seed=13, psfs=["round"],
                     snr_range=(40.0, 80.0), size_ratio_range=(1.0, 2.5),
                     morphology_weights=(1, 1, 0, 0, 0))  # fmt: skip
    cfg = Config.paper(model="bulge+disc", n_bulge_fractions=3)
    res = precision(spec, config=cfg, progress=False, prior=PRIOR)

    def counts(breakdown):
        t = res[(res["breakdown"] == breakdown) & (res["estimator"] == "fixed-point")]
        return {str(g): int(c) for g, c in zip(t["group"], t["n_gal"], strict=True) if c}

    true, meas = counts("morphology"), counts("bulge_frac_meas")
    assert set(true) == {"exponential", "devaucouleurs"} and sum(meas.values()) == 120
    # most of each kind in its end bin, and not in the other's
    assert true["exponential"] * 0.75 <= meas.get("0-0.2", 0) <= true["exponential"] + 5, meas
    assert true["devaucouleurs"] * 0.75 <= meas.get("0.8-1", 0) <= true["devaucouleurs"] + 5
