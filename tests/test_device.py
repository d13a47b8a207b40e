"""The device path of the likelihood (``Config(backend="jax")``) against the CPU path, on
JAX's CPU backend: the same ``ln L`` grids and best models from the same stamps."""

import sys

import galsim
import numpy as np
import pytest

from conftest import PSFS, draw, galsim_model
from pylensfit import Config, fit_stamps
from pylensfit.likelihood import device

jax = pytest.importorskip("jax")

N_GAL = 11


def _stamps(model: str, snr=(10.0, 30.0), seed=7):
    """GalSim renderings of the bank's own profiles: ellipticities inside |e| < 0.6,
    sizes 1.5-3 px, S/N in ``snr``, centres within half a pixel; one stamp with a NaN
    pixel (flagged by both paths)."""
    rng = np.random.default_rng(seed)
    psf = PSFS["moffat_e1"]
    out = np.empty((N_GAL, 32, 32))
    for i in range(N_GAL):
        e = 0.6 * np.sqrt(rng.uniform()) * np.exp(2j * rng.uniform(0, np.pi))
        gal = galsim_model(model, rng.uniform(1.5, 3.0), e.real, e.imag)
        a = draw(galsim.Convolve(gal, psf), offset=tuple(rng.uniform(-0.5, 0.5, 2)))
        out[i] = a * rng.uniform(*snr) / np.sqrt((a * a).sum())
    out += rng.normal(size=out.shape)
    out[3, 5, 5] = np.nan
    return out, draw(psf)


def _posterior_means(fits, rows) -> np.ndarray:
    w = np.exp(fits.lnL[rows].astype(float))
    return (w @ fits.egrid) / w.sum(axis=1, keepdims=True)


def _both(stamps, psf, cfg):
    return (fit_stamps(stamps, psf, 1.0, config=cfg),
            fit_stamps(stamps, psf, 1.0, config=cfg.replace(backend="jax")))  # fmt: skip


def test_the_device_path_is_the_cpu_path_with_float64_products():
    """With float64 products the two paths sum the same terms to within float64
    round-off: every ``ln L`` row and the best model agree to 1e-8 (the centring pass,
    the third-order expansion of the faint galaxies, the power-law flux prior, the
    bulge+disc fractions mixed from the pure ones, blocks of 4 with the last one padded).
    One JAX compilation per configuration (about 10 s on a CPU): one configuration that
    holds every stage."""
    model = "bulge+disc"
    stamps, psf = _stamps(model)
    cfg = Config(model=model, max_stamp_size=0, dtype="float64", block_size=4)
    cpu, dev = _both(stamps, psf, cfg)
    assert (cpu.flags == dev.flags).all() and cpu.flags[3] != 0
    ok = cpu.flags == 0
    assert ok.sum() == N_GAL - 1
    for name in ("lnL", "lnL_r", "lnL_peak", "x", "y", "flux", "snr", "r_best", "e1_best",
                 "e2_best", "lnL_bulge", "lnL_star"):  # fmt: skip
        a, b = getattr(cpu, name), getattr(dev, name)
        if a is None:
            assert b is None
            continue
        a, b = np.asarray(a[ok], float), np.asarray(b[ok], float)
        fin = np.isfinite(a)
        assert (fin == np.isfinite(b)).all(), name
        np.testing.assert_allclose(b[fin], a[fin], rtol=1e-9, atol=1e-8, err_msg=name)


def test_float32_products_agree_to_their_round_off():
    """With the default float32 products the paths differ by the products' round-off
    (their sums run in another order): at S/N 10-30 the posterior means agree to 1e-5
    and the rows of ``ln L`` within 20 of their peak to 1e-3 (``ln L`` grows as S/N^2,
    and so does this difference: CPU float32 and float64 differ as much)."""
    stamps, psf = _stamps("exponential", seed=8)
    cfg = Config(model="exponential", max_stamp_size=0)
    cpu, dev = _both(stamps, psf, cfg)
    ok = cpu.flags == 0
    near = (cpu.lnL > -20) & ok[:, None]
    assert np.abs(dev.lnL - cpu.lnL)[near].max() < 1e-3
    assert np.abs(_posterior_means(dev, ok) - _posterior_means(cpu, ok)).max() < 1e-5
    assert (dev.r_best[ok] == cpu.r_best[ok]).all()
    np.testing.assert_allclose(dev.x[ok], cpu.x[ok], atol=1e-4)
    empty = fit_stamps(stamps[:0], psf, 1.0, config=cfg.replace(backend="jax"))
    assert empty.lnL.shape == (0, cpu.lnL.shape[1])


def test_the_backend_is_chosen_by_the_config(monkeypatch):
    """``cpu`` by default; ``auto`` is the device path only where JAX has a GPU or TPU;
    ``jax`` without JAX installed says how to install it."""
    assert Config().backend == "cpu"
    assert device.resolve_backend(Config()) == "cpu"
    auto = "cpu" if jax.default_backend() == "cpu" else "jax"
    assert device.resolve_backend(Config(backend="auto")) == auto
    assert device.resolve_backend(Config(backend="jax")) == "jax"
    # JAX absent: not imported yet, and its import fails
    monkeypatch.setattr(device, "jax", None)
    monkeypatch.setitem(sys.modules, "jax", None)
    with pytest.raises(ImportError, match="pylensfit\\[gpu\\]"):
        device.resolve_backend(Config(backend="jax"))
    assert device.resolve_backend(Config(backend="auto")) == "cpu"
