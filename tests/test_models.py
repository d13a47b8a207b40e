"""Fourier-space models against GalSim's independent real-space rendering."""

import galsim
import numpy as np
import pytest

from conftest import PSFS, N, draw, galsim_model
from pylensfit import models
from pylensfit.config import Config
from pylensfit.models import (
    fourier_profile,
    model_bank,
    radius_grid,
    radius_weights,
    render_models,
    rfft_frequencies,
    sheared_k,
    wrap_correction,
)
from pylensfit.psf import psf_transform


def render(model, r, e1, e2, psf_img, n=N, **kw):
    """pylensfit's PSF-convolved model drawn back to real space (unit flux) on n x n."""
    kx, ky, _ = rfft_frequencies(n)
    G = fourier_profile(sheared_k(kx, ky, e1, e2) * r, model, **kw)
    P = psf_transform(psf_img, n)
    c = n // 2
    return np.fft.irfft2(G * P * np.exp(-1j * (kx * c + ky * c)), s=(n, n))


# The comparison is made on 128 x 128 images so that the cyclic model does not wrap
# (on a 32-pixel stamp, up to 8% of a large model's flux wraps round: that is the stamp
# approximation of the paper, not a model error). What remains is the band-limit
# assumption (docs: method, conventions: G(k) P(k) equals the sampled convolution only if the
# pixelised PSF has no power above Nyquist). Measured residuals for these PSFs (FWHM
# >= 3 px) are below 3.2e-5 of the peak pixel, while an ellipticity wrong by 0.05, a
# wrong shear sign or a wrong size definition gives 1e-2 to 1e-1.
TOL = 2e-4
BIG = 128


@pytest.mark.parametrize("psf_name", list(PSFS))
@pytest.mark.parametrize("model", ["exponential", "devaucouleurs", "bulge+disc"])
@pytest.mark.parametrize("r,e1,e2", [(1.5, 0.3, -0.2), (3.0, -0.45, 0.1), (2.0, 0.0, 0.6)])
def test_model_matches_galsim(model, psf_name, r, e1, e2):
    psf = PSFS[psf_name]
    psf_img = draw(psf, n=BIG)
    ref = draw(galsim.Convolve(galsim_model(model, r, e1, e2), psf), n=BIG)
    ours = render(model, r, e1, e2, psf_img, n=BIG)
    assert np.abs(ours - ref).max() < TOL * ref.max()
    # and a model whose ellipticity is off by 0.05 fails the same tolerance
    wrong = render(model, r, e1 + 0.05, e2, psf_img, n=BIG)
    assert np.abs(wrong - ref).max() > 3 * TOL * ref.max()


def test_render_models_places_each_model_as_galsim_does():
    """Several models at once, off-centre and with their own bulge fractions and fluxes.

    A sub-pixel shift applied as a phase to the pixelised PSF adds to the band-limit error
    (measured: 2.2e-4 of the peak for a point source 0.1-0.3 px off a pixel centre), so
    the tolerance is 5e-4 here; a position off by 0.1 px gives ~10x that.
    """
    tol = 5e-4
    psf = PSFS["moffat_e1"]
    psf_img = draw(psf, n=BIG)
    x = np.array([60.3, 70.0, 50.8])
    y = np.array([64.6, 55.2, 71.1])
    e1, e2 = np.array([0.3, -0.1, 0.0]), np.array([-0.2, 0.4, 0.0])
    r, flux = np.array([2.0, 3.0, 0.0]), np.array([100.0, 40.0, 25.0])
    bf = np.array([0.3, 0.8, 0.5])
    ours = render_models(BIG, psf_img, x, y, e1, e2, r, flux, model="bulge+disc",
                         bulge_fraction=bf)  # fmt: skip
    for k in range(3):
        gal = galsim_model("bulge+disc", r[k], e1[k], e2[k], bulge_fraction=bf[k]) if r[k] else \
            galsim.DeltaFunction()
        off = (x[k] - BIG // 2, y[k] - BIG // 2)
        ref = draw(galsim.Convolve(gal, psf), n=BIG, offset=off, flux=flux[k])
        assert np.abs(ours[k] - ref).max() < tol * ref.max()
        assert ours[k].sum() == pytest.approx(flux[k], rel=1e-9)
    # a position off by 0.1 pixel fails the same tolerance
    moved = render_models(BIG, psf_img, x[:1] + 0.1, y[:1], e1[:1], e2[:1], r[:1], flux[:1],
                          model="bulge+disc", bulge_fraction=bf[:1])  # fmt: skip
    assert np.abs(moved[0] - ours[0]).max() > 3 * tol * ours[0].max()


def test_render_models_through_a_jacobian_is_galsims_sky_profile_in_the_pixels():
    """Sky-frame models (``e`` in the (W, N) frame, ``r`` in arcsec) seen through a
    rotated, sheared, mirror-image Jacobian, each with its own PSF image: GalSim's
    ``JacobianWCS.toImage`` of the same sky profile, convolved with the pixel-frame PSF.
    The same models without the mirror fail the tolerance."""
    tol = 5e-4
    a = np.radians(33.0)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    J = np.diag([1.0, -1.0]) @ rot @ np.array([[1.03, 0.02], [0.02, 0.97]]) / 0.2
    wcs = galsim.JacobianWCS(*np.linalg.inv(J).ravel())  # d(u, v)/d(x, y), (u, v) = (W, N)
    psfs = [PSFS["moffat_e1"], PSFS["kolmogorov_e2"]]
    psf_imgs = np.stack([draw(p, n=BIG) for p in psfs])
    x, y = np.array([60.3, 70.6]), np.array([64.6, 55.2])
    e1, e2, r = np.array([0.3, -0.1]), np.array([-0.2, 0.4]), np.array([0.4, 0.6])
    flux = np.array([100.0, 40.0])
    ours = render_models(BIG, psf_imgs, x, y, e1, e2, r, flux, model="exponential",
                         jacobian=J)  # fmt: skip
    mirror = render_models(BIG, psf_imgs, x, y, e1, e2, r, flux, model="exponential",
                           jacobian=np.diag([1.0, -1.0]) @ J)  # fmt: skip
    for k in range(2):
        gal = wcs.toImage(galsim_model("exponential", r[k], e1[k], e2[k]))
        ref = draw(galsim.Convolve(gal, psfs[k]), n=BIG, flux=flux[k],
                   offset=(x[k] - BIG // 2, y[k] - BIG // 2))  # fmt: skip
        assert np.abs(ours[k] - ref).max() < tol * ref.max()
        assert ours[k].sum() == pytest.approx(flux[k], rel=1e-9)
        assert np.abs(mirror[k] - ref).max() > 3 * tol * ref.max()


def test_shear_convention_distinguishes_e1_sign():
    """A wrong sign or axis of the shear would fail the comparison above; check it does."""
    psf_img = draw(PSFS["moffat_round"], n=BIG)
    ref = draw(
        galsim.Convolve(galsim_model("exponential", 2.0, 0.3, 0.0), PSFS["moffat_round"]), n=BIG
    )
    wrong = render("exponential", 2.0, -0.3, 0.0, psf_img, n=BIG)
    assert np.abs(wrong - ref).max() > 10 * TOL * ref.max()


def test_exponential_transform_is_analytic():
    q = np.linspace(0, 20, 200)
    assert np.allclose(fourier_profile(q, "exponential"), (1 + q**2) ** -1.5)


def test_devaucouleurs_table_against_hankel_transform():
    """The tabulated de Vaucouleurs transform against direct numerical Hankel integration."""
    from scipy.integrate import quad
    from scipy.optimize import brentq
    from scipy.special import j0

    from pylensfit.models import DEVAUC_TRUNCATION as T

    pts = [1e-3, 1e-2, 0.1, 1]

    def enclosed(r0, rmax):
        return quad(lambda r: np.exp(-((r / r0) ** 0.25)) * r, 0, rmax, limit=400, points=pts)[0]

    # the half-light radius is that of the profile truncated at T half-light radii
    r0 = brentq(lambda r0: enclosed(r0, 1.0) - 0.5 * enclosed(r0, T), 1e-6, 1e-2)
    prof = lambda r: np.exp(-((r / r0) ** 0.25))  # noqa: E731
    norm = quad(lambda r: prof(r) * r, 0, T, limit=400, points=[1e-3, 1e-2, 0.1, 1])[0]
    for q in [0.3, 1.0, 3.0, 10.0]:
        val = quad(lambda r, q=q: prof(r) * j0(q * r) * r, 0, T, limit=800,
                   points=[1e-3, 1e-2, 0.1, 1])[0] / norm  # fmt: skip
        assert fourier_profile(q, "devaucouleurs") == pytest.approx(val, rel=2e-4, abs=1e-6)


@pytest.mark.parametrize("model", ["exponential", "devaucouleurs", "bulge+disc"])
@pytest.mark.parametrize("r,e1,e2", [(3.0, 0.35, -0.25), (2.0, -0.65, 0.05), (5.0, 0.05, 0.05)])
def test_truncated_model_matches_galsim_on_the_stamp(model, r, e1, e2):
    """On a 32-pixel stamp the corrected model is the profile cut at the stamp's edge.

    GalSim draws the PSF-convolved galaxy on the stamp itself (no wrapping). The
    periodic model carries 5-15 % of extra flux wrapped round from the far side and
    misses by 1-5 % of the peak inside the stamp; with the wrapped wings subtracted
    (models.wrap_correction) the interior (3 px from the edges) agrees to 3e-3 of the
    peak. On the edge lines the PSF blurs light across the cut, which the periodic
    convolution takes from the opposite edge: the whole-stamp rms stays at ~1e-2.
    """
    n = N
    psf = PSFS["moffat_round"]
    psf_img = draw(psf, n=n)
    ref = draw(galsim.Convolve(galsim_model(model, r, e1, e2), psf), n=n)
    periodic = render(model, r, e1, e2, psf_img, n=n)
    eg = np.array([[abs(e1) * s1, abs(e2) * s2] for s1 in (1, -1) for s2 in (1, -1)])
    ie = int(np.flatnonzero((eg[:, 0] == e1) & (eg[:, 1] == e2))[0])
    W = wrap_correction(eg, np.array([r]), np.array([0.5]), model, 0.6, n)[:, ie]
    kx, ky, _ = rfft_frequencies(n)
    c = n // 2
    P = psf_transform(psf_img, n)
    corr = np.fft.irfft2(W.reshape(kx.shape) * P * np.exp(-1j * (kx * c + ky * c)), s=(n, n))
    ours = periodic - corr
    inner = (slice(3, -3), slice(3, -3))
    peak = ref.max()
    assert np.abs(ours - ref)[inner].max() < 3e-3 * peak
    assert np.abs(periodic - ref)[inner].max() > 3 * 3e-3 * peak
    assert abs(ours.sum() - ref.sum()) < 0.2 * abs(periodic.sum() - ref.sum())


def test_bank_layout_and_point_source():
    cfg = Config.paper(model="exponential", e_step=0.2, r_step=1.0, r_max=4.0,
                       truncate_models=False)
    bank = model_bank(cfg)
    assert bank.G.shape == (N * (N // 2 + 1), bank.n_e * bank.n_r + 1)
    assert np.all(bank.G[:, -1] == 1.0)  # point source
    assert np.allclose(bank.G[0, :], 1.0)  # unit flux, k = 0 first
    kx, ky, _ = rfft_frequencies(N)
    ie, ir = 5, 2
    e1, e2 = bank.egrid[ie]
    col = bank.G[:, ie * bank.n_r + ir]
    expect = fourier_profile(sheared_k(kx, ky, e1, e2) * bank.radii[ir], "exponential").ravel()
    assert np.allclose(col, expect, rtol=1e-6)
    # the default bank: the same models less their wrapped wings (small models unchanged)
    cut = model_bank(cfg.replace(truncate_models=True))
    ie = int(np.argmin(np.hypot(*(bank.egrid - 0.1).T)))  # r = 1 px, e = (0.1, 0.1)
    assert np.allclose(cut.G[:, ie * bank.n_r], bank.G[:, ie * bank.n_r], atol=1e-6)
    assert np.all(cut.G[0, :-1] <= bank.G[0, :-1] + 1e-7)  # flux cut at the stamp's edge


def test_paper_grid_size():
    bank = model_bank(Config.paper(model="exponential", r_rel_step=0.0))
    assert bank.n_r == 50 and bank.radii[0] == pytest.approx(0.2)
    assert bank.radii[-1] == pytest.approx(10.0)
    assert bank.n_models == 316 * 50 + 1
    np.testing.assert_allclose(bank.r_weights, 0.2)  # the paper's sum times dr
    assert bank.star_weight == pytest.approx(0.2)


def test_relative_size_grid():
    """No step exceeds r_rel_step * r or r_step; uniform (the paper's) above r_step / r_rel_step."""
    r = radius_grid(0.0, 10.0, 0.2, 0.1)
    steps = np.diff(r)
    assert np.all(steps <= 0.2 + 1e-9) and np.all(steps <= 0.1 * r[1:] + 1e-9)
    assert 0.1 <= r[0] < 0.11 and r[-1] == pytest.approx(10.0)
    np.testing.assert_allclose(r[r >= 2.0 - 1e-9], np.arange(2.0, 10.0 + 1e-9, 0.2))
    assert radius_grid(0.5, 10.0, 0.2, 0.1)[0] >= 0.5


@pytest.mark.parametrize("r_rel_step", [0.0, 0.1])
def test_radius_weights_integrate(r_rel_step):
    """sum_j w_j f(r_j) + w_star f(0) is the integral over r, on either grid."""
    r = radius_grid(0.0, 10.0, 0.2, r_rel_step)
    w, w_star = radius_weights(r, 0.0)
    # integral 1 (5e-4 beyond 10 px); the trapezoid rule's error, (dr^2/12) f'(0), is 3.3e-3
    f = lambda x: x * np.exp(-x)  # noqa: E731
    total = w_star * f(0.0) + np.sum(w * f(r))
    assert total == pytest.approx(1.0 - 11 * np.exp(-10), rel=4e-3 if r_rel_step == 0 else 1e-3)
    # a peak at a small size, as narrow as the galaxy is small: the uniform grid's sum
    # swings by tens of per cent with the peak's position between two sizes, the relative
    # grid's by 1e-6 (its offset, 1.5e-3, is dr/dj's central difference, q^2 / 6)
    errs = []
    for d in np.linspace(0.0, 0.2, 9):
        g = np.exp(-0.5 * ((r - 0.5 - d) / 0.08) ** 2)
        errs.append(np.sum(w * g) / (0.08 * np.sqrt(2 * np.pi)) - 1)
    if r_rel_step:
        assert np.max(np.abs(errs)) < 2.5e-3 and np.ptp(errs) < 1e-4
    else:
        assert np.ptp(errs) > 0.05


def _ladder_galsim(run, r, e1, e2):
    """A run of the model bank (:class:`pylensfit.models.Run`) as a GalSim object."""
    from pylensfit.models import DEVAUC_TRUNCATION as T

    def comp(n, h):
        if n == 1.0:
            return galsim.Exponential(half_light_radius=h * r)
        return galsim.Sersic(n=n, half_light_radius=h * r, trunc=T * h * r if n > 2 else 0.0)

    (na, ha), (nb, hb) = run.components
    f = run.fraction
    parts = [c.withFlux(w) for c, w in ((comp(na, ha), 1 - f), (comp(nb, hb), f)) if w > 0]
    return galsim.Add(parts).shear(g1=e1, g2=e2)


def test_sersic_ladder_bank_columns_match_galsim_on_the_stamp():
    """The Sersic ladder's runs (``Config.sersic_ladder``): each column of the bank,
    the stamp-edge wrap correction included, is GalSim's profile of that run (Sersic n =
    0.5, 2, 4 of the disc's half-light radius, untruncated at n <= 2, and the half-and-half
    mixtures of adjacent indices) cut at the stamp's edge, to 3e-3 of the peak inside the
    stamp (as the one-profile models, test_truncated_model_matches_galsim_on_the_stamp);
    adjacent runs differ by more than five times that; a run's half-light radius is the
    disc's; bad ladders are rejected."""
    from pylensfit.models import DISC_HLR, Run, run_half_light_radius

    cfg = Config.paper(model="bulge+disc", n_bulge_fractions=3, e_step=0.2,
                 sersic_ladder=(0.5, 2, 4))  # fmt: skip
    bank = model_bank(cfg)
    runs = cfg.bulge_runs
    assert bank.runs == runs
    assert [run.label() for run in runs] == ["0", "0.5", "1", "Sersic 0.5", "Sersic 0.5+1",
                                             "Sersic 1+2", "Sersic 2", "Sersic 2+4",
                                             "Sersic 4"]  # fmt: skip
    assert runs[4] == Run(0.5, DISC_HLR, 1.0, 0.5)
    for run in runs[3:]:
        assert run_half_light_radius(run) == pytest.approx(DISC_HLR, rel=1e-9)
    assert np.isnan(bank.bulge[3 * bank.n_sizes :]).all()
    psf = PSFS["moffat_round"]
    psf_img = draw(psf)
    P = psf_transform(psf_img, N)
    kx, ky, _ = rfft_frequencies(N)
    c = N // 2
    ie = int(np.flatnonzero(np.isclose(bank.egrid, [0.3, -0.1]).all(axis=1))[0])
    inner = (slice(3, -3), slice(3, -3))
    for r in (1.0, 3.0):  # the largest's wings wrap round the 32-pixel stamp
        ir = int(np.argmin(np.abs(bank.radii[: bank.n_sizes] - r)))
        r = bank.radii[ir]
        ours = []
        for k, run in enumerate(runs):
            col = bank.G[:, ie * bank.n_r + k * bank.n_sizes + ir].reshape(kx.shape)
            img = np.fft.irfft2(col * P * np.exp(-1j * (kx * c + ky * c)), s=(N, N))
            ref = draw(galsim.Convolve(_ladder_galsim(run, r, 0.3, -0.1), psf))
            assert np.abs(img - ref)[inner].max() < 3e-3 * ref.max(), (run, r)
            ours.append(img)
        for a, b in zip(ours[3:-1], ours[4:], strict=True):
            assert np.abs(a - b)[inner].max() > 5 * 3e-3 * a.max()
    for bad in ({"sersic_ladder": (1.0, 2.0)}, {"sersic_ladder": (2.0, 2.0)},
                {"sersic_ladder": (9.0,)}, {"sersic_ladder": (2.0,), "n_bulge_fractions": 1}):
        with pytest.raises(ValueError, match="sersic_ladder"):
            cfg.replace(**bad)


def test_size_grid_floor():
    """r_floor moves the geometric grid's smallest size and leaves the sizes above it."""
    base = radius_grid(0.0, 10.0, 0.4, 0.1)
    low = radius_grid(0.0, 10.0, 0.4, 0.1, r_floor=0.05)
    assert 0.2 <= base[0] < 0.22 and 0.05 <= low[0] < 0.055
    np.testing.assert_allclose(low[-base.size:], base)
    assert np.all(np.diff(low) <= 0.1 * low[1:] + 1e-9)


def test_render_models_bulge_disc_mixture_is_the_full_sum_bit_for_bit():
    """Each component of the bulge+disc mixture is evaluated only for the models that
    hold it (a pure disc's or a pure bulge's other term is exactly 0): the images are
    those of ``bf F_bulge + (1 - bf) F_disc`` summed over every model, to the last bit,
    point sources included; the rendered images are those of that sum to round-off."""
    rng = np.random.default_rng(7)
    m, n = 30, 64
    x, y = rng.uniform(28, 36, m), rng.uniform(28, 36, m)
    e1, e2 = rng.uniform(-0.4, 0.4, m), rng.uniform(-0.4, 0.4, m)
    r = rng.uniform(0.0, 4.0, m)
    r[:3] = 0.0
    flux = rng.uniform(10.0, 1000.0, m)
    bf = rng.choice([0.0, 0.5, 1.0, 0.3], m)
    psf_img = PSFS["moffat_e1"].drawImage(nx=32, ny=32, scale=1.0).array
    kx, ky, _ = rfft_frequencies(n)
    q = sheared_k(kx[None], ky[None], e1[:, None, None], e2[:, None, None]) * r[:, None, None]
    F = (bf[:, None, None] * fourier_profile(q * 0.6, "devaucouleurs")
         + (1.0 - bf[:, None, None]) * fourier_profile(q, "exponential"))  # fmt: skip
    phase = np.exp(-1j * (kx[None] * x[:, None, None] + ky[None] * y[:, None, None]))
    want = np.fft.irfft2(flux[:, None, None] * F * psf_transform(psf_img, n)[None] * phase,
                         s=(n, n))  # fmt: skip
    assert np.array_equal(models._bulge_disc_transform(q, bf, 0.6), F)
    # render_models shifts and shears with other sums (separable phase, the quadratic
    # form of k): the same images to round-off
    got = render_models(n, psf_img, x, y, e1, e2, r, flux, model="bulge+disc",
                        bulge_fraction=bf, bulge_size_ratio=0.6)  # fmt: skip
    assert np.max(np.abs(got - want)) <= 1e-13 * np.max(np.abs(want))


def test_model_bank_read_back_from_the_disk_cache_is_the_built_one(tmp_path, monkeypatch):
    """A bank built once is kept on disk (PYLENSFIT_CACHE_DIR) and read back by the next
    process bit for bit; a damaged file is built again, and "off" keeps nothing."""
    cfg = Config(model="bulge+disc", n_bulge_fractions=3, e_step=0.25, r_max=3.0,
                 stamp_size=16, max_stamp_size=0)  # fmt: skip
    monkeypatch.setenv("PYLENSFIT_CACHE_DIR", "off")
    models._cached_bank.cache_clear()
    built = np.array(model_bank(cfg).G)
    assert not list(tmp_path.glob("*"))
    monkeypatch.setenv("PYLENSFIT_CACHE_DIR", str(tmp_path))
    for _ in range(2):  # written, then read (the in-process cache cleared: a new process)
        models._cached_bank.cache_clear()
        G = model_bank(cfg).G
        assert G.dtype == built.dtype and G.tobytes() == built.tobytes()
        assert not G.flags.writeable
    (f,) = tmp_path.glob("model-bank-*.npy")
    f.write_bytes(f.read_bytes()[:100])  # a damaged file
    models._cached_bank.cache_clear()
    assert model_bank(cfg).G.tobytes() == built.tobytes()
    assert np.load(f).tobytes() == built.tobytes()  # written again whole
    models._cached_bank.cache_clear()
