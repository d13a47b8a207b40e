"""Simulations with a PSF that varies over the field, and with a rotated or flipped WCS."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS

from pylensfit_validation.cli import simulate_main as main
from pylensfit_validation.simulate import (
    FieldSpec,
    _wcs,
    add_object,
    add_sky_and_noise,
    draw_population,
    field_psf,
    galaxy_profile,
    lensed_shapes,
    map_psf_model,
    pixel_to_sky_shear,
    psf_at,
    simulate_field,
    sky_to_pixel_shear,
    write_field,
)
from pylensfit_validation.step import _step2_galaxy
from pylensfit_validation.validation import (
    STEP2_KINDS,
    read_manifest,
    render_step2_field,
)

galsim = pytest.importorskip("galsim")

FRAMES = [(0.0, False), (30.0, False), (90.0, False), (0.0, True), (-65.0, True), (135.0, True)]


def _rot(deg: float) -> np.ndarray:
    t = np.deg2rad(deg)
    return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])


def _hsm(img: np.ndarray, x: float, y: float, half: int = 16):
    """HSM adaptive moments of the object at 0-based ``(x, y)`` of a sky-free image."""
    ix, iy = int(round(x)), int(round(y))
    cut = img[iy - half : iy + half + 1, ix - half : ix + half + 1].astype(np.float64)
    return galsim.hsm.FindAdaptiveMom(galsim.ImageD(cut, scale=1.0))


def _reference_simulate_field(spec: FieldSpec, seed: int) -> np.ndarray:
    """simulate_field's image drawn with one PSF object for every object."""
    rng = np.random.default_rng(seed)
    x, y, is_star, r, snr, star_snr, e_int = draw_population(spec, rng)
    e_int, _ = lensed_shapes(spec, e_int, is_star)
    psf = galsim.Moffat(beta=spec.psf_beta, fwhm=spec.psf_fwhm).shear(
        g1=spec.psf_e1, g2=spec.psf_e2
    )
    image = galsim.ImageF(spec.size, spec.size, scale=1.0)
    peak = psf.drawImage(nx=64, ny=64, scale=1.0).array.max()
    for i in range(x.size):
        if is_star[i]:
            obj, flux = psf, star_snr[i] * spec.noise_sigma / peak
        else:
            gal = galaxy_profile(spec.model, r[i], i).shear(g1=e_int[i, 0], g2=e_int[i, 1])
            obj = galsim.Convolve(gal.shear(g1=spec.g1, g2=spec.g2), psf)
            e0 = -e_int[i] if spec.rotate else e_int[i]
            ref = galsim.Convolve(galaxy_profile(spec.model, r[i], i).shear(g1=e0[0], g2=e0[1]),
                                  psf)  # fmt: skip
            arr = ref.drawImage(nx=64, ny=64, scale=1.0).array
            flux = snr[i] * spec.noise_sigma / np.sqrt((arr**2).sum())
        add_object(image, obj, flux, x[i], y[i])
    return add_sky_and_noise(image, spec, seed, None)[0]


def _reference_step2_field(spec: FieldSpec, seed: int) -> np.ndarray:
    """render_step2_field's image drawn with one PSF object for every object."""
    rng = np.random.default_rng(seed)
    x, y, is_star, r, snr, star_snr, e_int = draw_population(spec, rng)
    n_obj = x.size
    kinds = rng.choice(np.array(STEP2_KINDS), n_obj, p=[0.4, 0.3, 0.3])
    sersic_n = np.round(rng.uniform(0.5, 4.0, n_obj), 1)
    bulge_frac = rng.uniform(0.0, 0.5, n_obj)
    knot_frac = rng.uniform(0.2, 0.5, n_obj)
    n_knots = rng.integers(10, 60, n_obj)
    knot_seed = rng.integers(1, 2**31 - 1, n_obj)
    e_int, _ = lensed_shapes(spec, e_int, is_star)
    psf = galsim.Moffat(beta=spec.psf_beta, fwhm=spec.psf_fwhm).shear(
        g1=spec.psf_e1, g2=spec.psf_e2
    )
    image = galsim.ImageF(spec.size, spec.size, scale=1.0)
    peak = psf.drawImage(nx=64, ny=64, scale=1.0).array.max()
    for i in range(n_obj):
        if is_star[i]:
            obj, flux = psf, star_snr[i] * spec.noise_sigma / peak
        else:
            gal = _step2_galaxy(str(kinds[i]), r[i], sersic_n[i], bulge_frac[i], knot_frac[i],
                                int(n_knots[i]), int(knot_seed[i]))  # fmt: skip
            e0 = -e_int[i] if spec.rotate else e_int[i]
            gal = gal.shear(g1=e0[0], g2=e0[1])
            arr = galsim.Convolve(gal, psf).drawImage(nx=64, ny=64, scale=1.0).array
            flux = snr[i] * spec.noise_sigma / np.sqrt((arr**2).sum())
            if spec.rotate:
                gal = gal.rotate(90 * galsim.degrees)
            obj = galsim.Convolve(gal.shear(g1=spec.g1, g2=spec.g2), psf)
        add_object(image, obj, flux, x[i], y[i], 64)
    return add_sky_and_noise(image, spec, seed, None)[0]


@pytest.mark.parametrize("rotate", [False, True])
def test_constant_map_is_the_single_psf_rendering(rotate):
    spec = FieldSpec(size=200, model="mixed", g1=0.03, g2=-0.02, rotate=rotate)
    img, _, truth = simulate_field(spec, seed=11)
    assert np.array_equal(img, _reference_simulate_field(spec, 11))
    spec2 = FieldSpec(size=200, g1=0.04, g2=0.02, size_range=(1.5, 4.5), rotate=rotate)
    img2, _, _ = render_step2_field(spec2, seed=12)
    assert np.array_equal(img2, _reference_step2_field(spec2, 12))
    # the constant map's truth: the one PSF everywhere, its moments measured once
    assert np.all(truth["psf_fwhm"] == spec.psf_fwhm) and np.all(truth["psf_e1"] == spec.psf_e1)
    assert np.ptp(truth["psf_e1_obs"]) == 0 and np.ptp(truth["psf_sigma_obs"]) == 0
    assert np.array_equal(truth["e1_sky"], truth["e1"])  # the plain WCS: pixel = sky


def test_psf_at_the_survey_map():
    spec = FieldSpec(size=1000, psf_variation="survey", psf_e1=0.0, psf_e2=0.0)
    c = (spec.size - 1) / 2
    x, y = c + 500 * np.array([[0, 1, 0, 1, -1], [0, 0, 1, 1, -1]])
    fwhm, e1, e2 = psf_at(spec, x, y)
    assert fwhm[0] == spec.psf_fwhm and e1[0] == 0 and e2[0] == 0
    np.testing.assert_allclose(e1 + 1j * e2, [0, 0.04, -0.04, 0.08j, 0.08j], atol=1e-15)
    np.testing.assert_allclose(fwhm / spec.psf_fwhm, [1, 1.05, 1.05, 1.1, 0.9])
    p = field_psf(spec, 900.0, 120.0)
    f, a, b = psf_at(spec, 900.0, 120.0)
    ref = galsim.Moffat(beta=spec.psf_beta, fwhm=float(f)).shear(g1=float(a), g2=float(b))
    assert p == ref and field_psf(spec) == field_psf(replace(spec, psf_variation="none"))
    with pytest.raises(ValueError, match="psf_variation"):
        FieldSpec(psf_variation="wavy")


def test_survey_stars_follow_the_map():
    spec = FieldSpec(size=600, star_fraction=1.0, psf_variation="survey", psf_e1=0.02,
                     psf_e2=-0.01, star_peak_snr=(1e6, 1e6))  # fmt: skip
    img, _, t = simulate_field(spec, seed=4)
    img = img - spec.sky  # the noise (sigma 1) is 1e-6 of a star's peak
    mom = [_hsm(img, x, y) for x, y in zip(t["x"], t["y"], strict=True)]
    e = np.array([complex(m.observed_shape.g1, m.observed_shape.g2) for m in mom])
    sig = np.array([m.moments_sigma for m in mom])
    # the truth's adaptive moments of the pixel-convolved local PSF are the stars'
    e_truth = np.asarray(t["psf_e1_obs"]) + 1j * np.asarray(t["psf_e2_obs"])
    assert np.max(np.abs(e - e_truth)) < 1e-3
    assert np.max(np.abs(sig / t["psf_sigma_obs"] - 1)) < 1e-3
    # and they follow psf_at: the pixel dilutes e by a few per cent, the FWHM sets sigma
    e_map = np.asarray(t["psf_e1"]) + 1j * np.asarray(t["psf_e2"])
    assert np.ptp(e_map.real) > 0.05 and np.ptp(e_map.imag) > 0.1  # lattice to ~0.9 of the edge
    k = np.vdot(e_map, e).real / np.vdot(e_map, e_map).real
    assert 0.9 < k < 1.0 and np.max(np.abs(e - k * e_map)) < 2e-3
    corner = np.argmax(np.abs(e_map - (spec.psf_e1 + 1j * spec.psf_e2)))
    centre = np.argmin(np.hypot(t["x"] - 300, t["y"] - 300))
    assert abs(e[corner] - e[centre]) > 0.05  # 0.08 (0.88)^2, diluted
    ratio = sig / t["psf_fwhm"]
    assert np.ptp(t["psf_fwhm"]) > 0.5 and np.std(ratio) / np.mean(ratio) < 0.01


def test_map_psf_model_is_the_true_psf_over_the_field():
    # against GalSim's own rendering of the local PSF at random positions, with the
    # pixel response; PSF 3 of STEP2 (e = 0.12 at the centre, up to 0.2 in a corner)
    spec = FieldSpec(size=640, psf_variation="survey", psf_e1=0.12, psf_e2=0.0)
    model = map_psf_model(spec, size=48)
    rng = np.random.default_rng(3)
    x, y = rng.uniform(0, 639, 20), rng.uniform(0, 639, 20)
    drawn = model.draw(x, y)
    for xi, yi, img in zip(x, y, drawn, strict=True):
        ref = field_psf(spec, xi, yi).drawImage(nx=48, ny=48, scale=1.0,
                                                use_true_center=False).array  # fmt: skip
        ref /= ref.sum()
        assert np.max(np.abs(img - ref)) < 1e-4 * ref.max()
        a = galsim.hsm.FindAdaptiveMom(galsim.Image(img)).observed_shape
        b = galsim.hsm.FindAdaptiveMom(galsim.Image(ref)).observed_shape
        assert abs(a.g1 - b.g1) < 3e-5 and abs(a.g2 - b.g2) < 3e-5
    assert np.ptp(model.shape_at(x, y)[0]) > 0.05  # it does vary
    # a constant map is the one PSF everywhere
    const = map_psf_model(replace(spec, psf_variation="none"), size=48, order=2, grid=4)
    np.testing.assert_allclose(const.draw(5.0, 600.0), const.draw(320.0, 0.0), atol=1e-12)
    with pytest.raises(ValueError, match="grid"):
        map_psf_model(spec, order=5, grid=4)


def _local_jacobian(w: WCS, x: float, y: float, h: float = 0.5) -> np.ndarray:
    """d(W, N)/d(x, y) of an astropy WCS at 0-based pixel ``(x, y)`` (degrees per pixel)."""
    ra0, dec0 = w.pixel_to_world_values(x, y)
    jac = np.empty((2, 2))
    for k, (dx, dy) in enumerate([(h, 0.0), (0.0, h)]):
        ra_p, dec_p = w.pixel_to_world_values(x + dx, y + dy)
        ra_m, dec_m = w.pixel_to_world_values(x - dx, y - dy)
        d_ra = ((ra_p - ra_m + 180.0) % 360.0 - 180.0) * np.cos(np.deg2rad(dec0))
        jac[:, k] = [-d_ra / (2 * h), (dec_p - dec_m) / (2 * h)]  # W = -RA cos(dec)
    return jac


@pytest.mark.parametrize("rot, flip", FRAMES)
def test_wcs_cd_matrix(rot, flip, tmp_path):
    spec = FieldSpec(size=64, wcs_rotation_deg=rot, wcs_flip=flip, pixel_scale_arcsec=0.2)
    s = 0.2 / 3600
    f = np.diag([1.0, -1.0 if flip else 1.0])
    np.testing.assert_allclose(_wcs(spec, 150.0, 2.0).wcs.cd, s * np.diag([-1, 1]) @ _rot(rot) @ f,
                               atol=1e-20)  # fmt: skip
    if rot == 0 and not flip:
        assert np.array_equal(_wcs(spec, 150.0, 2.0).wcs.cd, [[-s, 0.0], [0.0, s]])
    write_field(tmp_path / "f.fits", np.zeros((64, 64), np.float32), None, spec, dec0=-30.0)
    hdr = fits.getheader(tmp_path / "f.fits")
    assert hdr["SIMROT"] == rot and hdr["SIMFLIP"] == flip and hdr["SIMPSFV"] == "none"
    jac = _local_jacobian(WCS(hdr), 31.5, 31.5)
    np.testing.assert_allclose(jac, s * _rot(rot) @ f, atol=1e-6 * s)


def test_shear_conversion_round_trip():
    rng = np.random.default_rng(2)
    g1, g2 = rng.uniform(-0.5, 0.5, (2, 50))
    for rot, flip in FRAMES + [(17.0, False), (-123.0, True)]:
        p1, p2 = sky_to_pixel_shear(g1, g2, rot, flip)
        np.testing.assert_allclose(pixel_to_sky_shear(p1, p2, rot, flip), [g1, g2], atol=1e-15)
        np.testing.assert_allclose(np.hypot(p1, p2), np.hypot(g1, g2), atol=1e-15)
    # along pixel x is north-south on the sky for theta = 90 degrees
    np.testing.assert_allclose(pixel_to_sky_shear(0.2, 0.0, 90.0, False), (-0.2, 0.0), atol=1e-15)
    # flipped: the pixel diagonal x = y runs SW-NE on the sky (W = -N), e2 < 0
    np.testing.assert_allclose(pixel_to_sky_shear(0.0, 0.2, 0.0, True), (0.0, -0.2), atol=1e-15)


@pytest.mark.parametrize("rot, flip", FRAMES)
def test_shear_conversion_against_galsim_and_the_wcs(rot, flip):
    """A Gaussian rendered with g_pix has the sky frame's shape g_sky through the WCS."""
    spec = FieldSpec(size=64, wcs_rotation_deg=rot, wcs_flip=flip)
    jac = _local_jacobian(_wcs(spec, 150.0, 2.0), 31.5, 31.5)
    for g_sky in [(0.3, 0.0), (0.0, 0.3), (-0.12, 0.21)]:
        p1, p2 = sky_to_pixel_shear(*g_sky, rot, flip)
        img = galsim.Gaussian(sigma=3.0).shear(g1=float(p1), g2=float(p2)).drawImage(
            nx=64, ny=64, scale=1.0, method="no_pixel"
        )
        m = galsim.hsm.FindAdaptiveMom(img)
        a = m.observed_shape.getMatrix() * m.moments_sigma
        q = jac @ (a @ a.T) @ jac.T  # the moments in (W, N)
        chi = complex(q[0, 0] - q[1, 1], 2 * q[0, 1]) / (q[0, 0] + q[1, 1])
        g = chi / (1 + np.sqrt(1 - abs(chi) ** 2))
        assert abs(g - complex(*g_sky)) < 1e-5


def test_rotated_flipped_field_has_the_same_sky_truth():
    base = FieldSpec(size=240, g1=0.04, g2=-0.03, psf_e1=0.0, psf_e2=0.0)
    _, _, t0 = simulate_field(base, seed=9)
    for rot, flip in [(30.0, True), (90.0, False)]:
        _, _, t = simulate_field(replace(base, wcs_rotation_deg=rot, wcs_flip=flip), seed=9)
        assert np.array_equal(t["x"], t0["x"]) and np.array_equal(t["is_star"], t0["is_star"])
        for c in ("e1", "e2"):
            np.testing.assert_allclose(t[c + "_sky"], t0[c], atol=1e-14)
            np.testing.assert_allclose(t[c + "_int_sky"], t0[c + "_int"], atol=1e-14)
        assert np.max(np.abs(t["e1"] - t0["e1"])) > 0.1  # the pixel frame's shapes differ
        assert t.meta["wcs_rot"] == rot and t.meta["wcs_flip"] == flip
        assert t.meta["g1"] == base.g1  # the sky frame's shear


@pytest.mark.parametrize("twin", [False, True])
def test_step2_galaxy_is_the_same_on_the_sky_for_grid_symmetric_frames(twin):
    """One knotty galaxy at the centre: the frames that map pixels onto pixels give the
    plain field's image transposed, rotated or flipped about the galaxy (round PSF)."""
    spec = FieldSpec(size=81, jitter=0.0, star_fraction=0.0, g1=0.03, g2=0.05, psf_e1=0.0,
                     psf_e2=0.0, sky=0.0, snr_range=(1e9, 1e9), size_range=(3.0, 3.0),
                     rotate=twin)  # fmt: skip  # S/N 1e9: the noise (not transformed) is nil
    plain, _, t = render_step2_field(spec, seed=3)
    assert t["kind"][0] == "knots" and t["x"][0] == 40.0 and t["y"][0] == 40.0
    # (W, N) = Rot(theta) F (dx, dy): the pixel image is the sky's (the plain one) mapped back
    expect = {(90.0, True): plain.T, (90.0, False): np.rot90(plain, 1),
              (180.0, False): np.rot90(plain, 2), (0.0, True): plain[::-1]}  # fmt: skip
    for (rot, flip), ref in expect.items():
        img, _, _ = render_step2_field(replace(spec, wcs_rotation_deg=rot, wcs_flip=flip), seed=3)
        assert np.abs(img - ref).max() < 1e-4 * plain.max()  # GalSim FFTs: <= 1e-5
        assert np.abs(img - plain).max() > 0.1 * plain.max()


def test_rotated_flipped_step2_galaxies_have_the_sky_shapes():
    """HSM shapes of the galaxies agree in the sky frame at any angle (round PSF)."""
    base = FieldSpec(size=200, g1=0.03, g2=0.02, psf_e1=0.0, psf_e2=0.0, star_fraction=0.0,
                     snr_range=(1e5, 1e5), size_range=(2.0, 3.5), sky=0.0)  # fmt: skip
    img0, _, t0 = render_step2_field(base, seed=3)
    rot, flip = 30.0, True
    img, _, t = render_step2_field(replace(base, wcs_rotation_deg=rot, wcs_flip=flip), seed=3)
    assert np.array_equal(t["kind"], t0["kind"])
    for x, y in zip(t["x"], t["y"], strict=True):
        m0, m = _hsm(img0, x, y), _hsm(img, x, y)
        g1, g2 = pixel_to_sky_shear(m.observed_shape.g1, m.observed_shape.g2, rot, flip)
        # the pixels' square response and the sub-pixel phase: ~2e-3 at 30 degrees
        assert abs(complex(g1, g2) - complex(m0.observed_shape.g1, m0.observed_shape.g2)) < 5e-3
        assert abs(m.moments_sigma / m0.moments_sigma - 1) < 5e-3


def test_simulate_command_with_a_varying_psf_and_a_rotated_wcs(tmp_path):
    out = tmp_path / "s2"
    argv = ["step2", "--out", str(out), "--ngal", "40", "--size", "160", "--nshear", "1",
            "--psf-variation", "survey", "--wcs-rotation", "30", "--wcs-flip",
            "--quiet"]  # fmt: skip
    assert main(argv) == 0
    man = read_manifest(out)
    assert man["psf_variation"] == "survey" and man["wcs_rotation_deg"] == 30.0
    assert man["wcs_flip"] is True and man["fieldspec"]["psf_variation"] == "survey"
    for sf, f in zip(man["star_fields"], [f for f in man["fields"] if f["role"] == "prior"],
                     strict=True):  # fmt: skip
        ts, tg = Table.read(sf["path"], hdu="TRUTH"), Table.read(f["path"], hdu="TRUTH")
        p = sf["psf_params"]
        spec = FieldSpec(size=160, psf_fwhm=p["fwhm"], psf_beta=p["beta"], psf_e1=p["e1"],
                         psf_e2=p["e2"], psf_variation="survey")  # fmt: skip
        for t in (ts, tg):  # the star fields and the galaxy fields: one map
            fwhm, e1, e2 = psf_at(spec, t["x"], t["y"])
            assert np.array_equal(t["psf_e1"], e1) and np.array_equal(t["psf_fwhm"], fwhm)
        hdr = fits.getheader(sf["path"])
        assert hdr["SIMROT"] == 30.0 and hdr["SIMFLIP"] and hdr["SIMPSFV"] == "survey"
    with pytest.raises(ValueError, match="same PSF map"):
        main(["step2", "--out", str(tmp_path / "x"), "--star-field-size", "200", *argv[3:]])


@pytest.mark.parametrize("rot, flip", FRAMES)
def test_shear_positions_is_the_sky_shear_of_the_positions(rot, flip):
    """``shear_positions`` moves every object as the sky frame's shear maps its offset from
    the field's centre (through the WCS, whatever its rotation and flip), the shear GalSim
    applies to the shapes: the lattice's spacings change by at most ``|g|``, so no galaxy
    lands on a star; everything else stays as drawn."""
    g = (0.05, -0.03)
    spec = FieldSpec(size=400, g1=g[0], g2=g[1], wcs_rotation_deg=rot, wcs_flip=flip)
    x0, y0, star0, *rest0 = draw_population(spec, np.random.default_rng(5))
    x, y, star, *rest = draw_population(replace(spec, shear_positions=True),
                                        np.random.default_rng(5))  # fmt: skip
    assert np.array_equal(star, star0) and star.any() and (~star).any()
    for a, b in zip(rest, rest0, strict=True):
        assert np.array_equal(a, b)
    jac = _local_jacobian(_wcs(spec, 150.0, 2.0), 199.5, 199.5)  # pixels -> (W, N)
    c = (spec.size - 1) / 2.0
    u0 = jac @ np.vstack([x0 - c, y0 - c])
    u = jac @ np.vstack([x - c, y - c])
    S = np.array([[1 + g[0], g[1]], [g[1], 1 - g[0]]]) / np.sqrt(1 - g[0] ** 2 - g[1] ** 2)
    tol = 1e-9 * np.abs(u0).max()
    np.testing.assert_allclose(u, S @ u0, rtol=0, atol=tol)
    moved = np.hypot(x - x0, y - y0)
    assert moved.max() > 0.04 * c  # a real move: up to |g| times the distance from the centre
