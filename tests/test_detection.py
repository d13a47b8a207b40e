"""Detection on a GalSim field of known stars and galaxies (paper sections 2.3-2.4).

The field: 512 x 512 pixels of scale 1, sky 100, Gaussian noise sigma 5; 25 stars (Moffat
PSF, FWHM 3 px, peak S/N 30-1000) and 40 exponential galaxies (half-light radius 1-4 px,
|g| < 0.5, matched-filter S/N 20-200) on a jittered grid 50+ px apart, plus one faint
galaxy 12.2 px from a bright one: the deliberate close pair.
"""

import galsim
import numpy as np
import pytest
import sep
from scipy.spatial import cKDTree

from pylensfit.detection import (
    Background,
    close_pairs,
    detect,
    measure_background,
    select_stars,
)
from pylensfit.flags import flag_value

N = 512
SIGMA = 5.0
SKY = 100.0
PSF = galsim.Moffat(beta=3.5, fwhm=3.0)
N_STARS, N_GALS = 25, 40
PAIR_OFFSET = (10.0, 7.0)


def _stamp(obj, dx, dy, n=64):
    """``obj`` drawn with its centre at element [n//2 + dy, n//2 + dx] (conftest convention)."""
    return obj.drawImage(nx=n, ny=n, scale=1.0, offset=(dx + 0.5, dy + 0.5)).array


def _add(img, obj, x, y, n=64):
    ix, iy = int(np.rint(x)), int(np.rint(y))
    arr = _stamp(obj, x - ix, y - iy, n)
    img[iy - n // 2 : iy - n // 2 + n, ix - n // 2 : ix - n // 2 + n] += arr
    return arr


def make_field(seed=20081208):
    """Noise-free image and truth: positions, fluxes, kinds, S/N and centroid bounds."""
    rng = np.random.default_rng(seed)
    img = np.zeros((N, N))
    cells = np.array(
        [(x, y) for y in np.linspace(40, N - 40, 8) for x in np.linspace(40, N - 40, 9)]
    )
    cells = cells[rng.permutation(len(cells))[: N_STARS + N_GALS]]
    rows = []
    for k, (cx, cy) in enumerate(cells):
        x, y = cx + rng.uniform(-5, 5), cy + rng.uniform(-5, 5)
        if k < N_STARS:
            peak_snr = np.exp(rng.uniform(np.log(30), np.log(1000)))
            unit = _stamp(PSF, x - np.rint(x), y - np.rint(y))
            flux = peak_snr * SIGMA / unit.max()
            obj, snr = PSF.withFlux(flux), np.nan
        else:
            rh = 2.0 if k == N_STARS else rng.uniform(1.0, 4.0)  # k == N_STARS: in the pair
            g = galsim.Exponential(half_light_radius=rh).shear(
                g=rng.uniform(0, 0.5), beta=rng.uniform(0, np.pi) * galsim.radians
            )
            gal = galsim.Convolve(g, PSF)
            snr = 150.0 if k == N_STARS else np.exp(rng.uniform(np.log(20), np.log(200)))
            unit = _stamp(gal, x - np.rint(x), y - np.rint(y))
            flux = snr * SIGMA / np.sqrt((unit**2).sum())
            obj = gal.withFlux(flux)
        arr = _add(img, obj, x, y)
        rows.append((x, y, flux, k < N_STARS, snr, arr.max() / SIGMA))
    # the close pair: a faint compact galaxy 12.2 px from the bright galaxy number N_STARS
    x0, y0 = rows[N_STARS][:2]
    x, y = x0 + PAIR_OFFSET[0], y0 + PAIR_OFFSET[1]
    comp = galsim.Convolve(galsim.Exponential(half_light_radius=1.0), PSF)
    unit = _stamp(comp, x - np.rint(x), y - np.rint(y))
    flux = 25.0 * SIGMA / np.sqrt((unit**2).sum())
    arr = _add(img, comp.withFlux(flux), x, y)
    rows.append((x, y, flux, False, 25.0, arr.max() / SIGMA))
    truth = {
        name: np.array([r[i] for r in rows])
        for i, name in enumerate(["x", "y", "flux", "star", "snr", "peak_snr"])
    }
    truth["pair"] = np.zeros(len(rows), dtype=bool)
    truth["pair"][[N_STARS, len(rows) - 1]] = True
    # Cramer-Rao bound of each position per axis (noise SIGMA, the object's own profile)
    gy, gx = np.gradient(img)
    sx, sy = [], []
    for x, y in zip(truth["x"], truth["y"], strict=True):
        sl = (slice(int(y) - 24, int(y) + 25), slice(int(x) - 24, int(x) + 25))
        sx.append(SIGMA / np.sqrt((gx[sl] ** 2).sum()))
        sy.append(SIGMA / np.sqrt((gy[sl] ** 2).sum()))
    truth["sx"], truth["sy"] = np.array(sx), np.array(sy)
    return img, truth


def match(cat, truth, max_dist=2.0):
    """Index of the nearest detection of each true object, and the distance."""
    d, i = cKDTree(np.column_stack([cat["x"], cat["y"]])).query(
        np.column_stack([truth["x"], truth["y"]])
    )
    assert np.all(d < max_dist), f"objects not detected: {np.flatnonzero(d >= max_dist)}"
    return i, d


@pytest.fixture(scope="module")
def field():
    return make_field()


@pytest.fixture(scope="module")
def image(field):
    img, _ = field
    return img + SKY + np.random.default_rng(7).normal(0.0, SIGMA, img.shape)


@pytest.fixture(scope="module")
def cat(image):
    return detect(image)


# --------------------------------------------------------------------------------------
# background


def test_background_and_rms_recovered(field, image):
    img, _ = field
    bkg = measure_background(image)
    assert isinstance(bkg, Background)
    assert bkg.back.shape == bkg.rms.shape == image.shape
    # sky 100 to 0.02 sigma globally, 0.2 sigma anywhere but the extrapolated corners
    assert abs(bkg.global_back - SKY) < 0.1
    assert np.percentile(np.abs(bkg.back - SKY), 99) < 1.0
    # rms 5 to 1.5% globally (SEP's clipped sigma alone is 1.6% low), 5% in the map
    assert abs(bkg.global_rms / SIGMA - 1) < 0.015
    assert np.percentile(np.abs(bkg.rms / SIGMA - 1), 99) < 0.05
    raw = measure_background(image, rescale_rms=False)
    assert -0.03 < raw.global_rms / SIGMA - 1 < -0.005
    # the bias the objects' wings put in the background: masking them removes most of it
    noise_only = image - img
    induced = measure_background(image).global_back - measure_background(noise_only).global_back
    plain = (
        measure_background(image, mask_sources=False).global_back
        - measure_background(noise_only, mask_sources=False).global_back
    )
    # (over field and noise seeds: plain 0.08 to 0.17, masked -0.05 to 0.04)
    assert plain > 0.06
    assert abs(induced) < 0.07 and induced < plain - 0.05
    sub = bkg.subtract(image)
    np.testing.assert_allclose(sub, image - bkg.back)


def test_background_with_everything_masked_falls_back_to_the_unmasked_estimate(image, caplog):
    """A source mask that leaves no box half free must not give a background of 0.

    SEP returns 0 when every box is discarded; the masked estimate is then dropped (with
    a warning) and the unmasked one kept, which sits within 0.3 sigma of the sky here.
    """
    with caplog.at_level("WARNING", logger="pylensfit.detection"):
        bkg = measure_background(image, source_radius=200.0)
    assert "no 64 x 64 background box half free" in caplog.text
    plain = measure_background(image, mask_sources=False)
    assert abs(bkg.global_back - SKY) < 0.3 * SIGMA
    np.testing.assert_allclose(bkg.back, plain.back)


def test_pure_noise_gives_few_detections():
    noise = SKY + np.random.default_rng(3).normal(0.0, SIGMA, (N, N))
    cat5 = detect(noise, threshold=5.0)
    assert len(cat5) <= 2
    cat3 = detect(noise, threshold=3.0)
    assert len(cat3) <= 10
    assert abs(cat5.meta["BKGRMS"] / SIGMA - 1) < 0.015
    assert abs(cat5.meta["BKG"] - SKY) < 0.05


# --------------------------------------------------------------------------------------
# positions, fluxes, peaks


def test_every_object_detected_at_the_cramer_rao_precision(cat, field):
    _, truth = field
    i, d = match(cat, truth)
    assert len(set(i)) == len(i)  # the close pair is deblended into two detections
    # per-axis errors in units of the Cramer-Rao bound: unit scatter, no outlier
    z = np.concatenate([(cat["x"][i] - truth["x"]) / truth["sx"],
                        (cat["y"][i] - truth["y"]) / truth["sy"]])  # fmt: skip
    iso = np.tile(~truth["pair"], 2)
    assert np.abs(z[iso]).max() < 4.5
    assert 0.8 < z[iso].std() < 1.25
    star, gal = truth["star"], ~truth["star"] & ~truth["pair"]
    assert d[star].max() < 0.1
    assert d[gal & (truth["snr"] >= 50)].max() < 0.4
    assert d[gal & (truth["snr"] >= 100)].max() < 0.2
    assert np.all(cat["id"] == np.arange(1, len(cat) + 1))


def test_flux_within_errors(cat, field):
    _, truth = field
    i, _ = match(cat, truth)
    c = cat[i]
    iso = ~truth["pair"]
    pull = (c["flux"] - truth["flux"]) / c["flux_err"]
    assert np.mean(np.abs(pull[iso]) < 4) >= 0.95
    assert -0.7 < np.median(pull[iso]) < 0.5
    bright = truth["star"] & (truth["peak_snr"] > 300)
    np.testing.assert_allclose(c["flux"][bright], truth["flux"][bright], rtol=0.02)
    merged = (c["sep_flag"][iso] & sep.OBJ_MERGED) != 0
    assert merged.mean() <= 0.1  # deblended from a noise peak at most
    np.testing.assert_allclose(c["snr"], c["flux"] / c["flux_err"])
    np.testing.assert_allclose(c["mag"], -2.5 * np.log10(c["flux"]))
    assert np.all(c["r_half"] > 1.5) and np.all(c["npix"] >= 5)
    # local background and noise at each object
    assert np.all(np.abs(c["background"] - SKY) < 1.0)
    assert np.median(np.abs(c["background"] - SKY)) < 0.15
    np.testing.assert_allclose(c["bkg_rms"], SIGMA, rtol=0.05)
    assert abs(np.median(c["bkg_rms"]) / SIGMA - 1) < 0.015
    np.testing.assert_array_equal(c["noise_sigma"], c["bkg_rms"])


def test_zeropoint(image, cat):
    zp = detect(image, zeropoint=25.0)
    np.testing.assert_allclose(zp["mag"], cat["mag"] + 25.0)
    assert zp.meta["ZP"] == 25.0 and cat.meta["ZP"] == 0.0


def test_peak_snr_of_stars(cat, field):
    _, truth = field
    i, _ = match(cat, truth)
    s = truth["star"]
    meas, true = cat["peak_snr"][i][s], truth["peak_snr"][s]
    assert np.all(np.abs(meas - true) < 5 + 0.02 * true)
    np.testing.assert_allclose(cat["peak_snr"], cat["peak"] / cat["bkg_rms"], rtol=0.02)


# --------------------------------------------------------------------------------------
# stars


def test_select_stars_purity_and_completeness(cat, field):
    _, truth = field
    i, _ = match(cat, truth)
    sel = select_stars(cat)
    is_star = np.zeros(len(cat), dtype=bool)
    is_star[i[truth["star"]]] = True
    bright = truth["star"] & (truth["peak_snr"] >= 40)
    completeness = sel[i[bright]].mean()
    purity = is_star[sel].mean()
    assert completeness >= 0.9 and purity >= 0.9, (completeness, purity)
    assert np.all(cat["peak_snr"][sel] >= 30)
    assert not sel[i[~truth["star"]]].any()  # no galaxy, not even the compact ones
    strict = select_stars(cat, min_peak_snr=200)
    assert strict.sum() >= 5 and np.all(cat["peak_snr"][strict] >= 200)
    assert np.all(sel[strict])


def test_select_stars_column_override(cat):
    flagged = cat.copy()
    user = np.zeros(len(cat), dtype=bool)
    user[::7] = True
    flagged["is_star"] = user
    flagged["class"] = user.astype(int) * 3
    np.testing.assert_array_equal(select_stars(flagged, column="is_star"), user)
    np.testing.assert_array_equal(select_stars(flagged, column="class"), user)
    with pytest.raises(ValueError, match="not in the catalogue"):
        select_stars(cat, column="nope")


def test_select_stars_rejects_saturated(field, image):
    _, truth = field
    level = SKY + 1000.0
    clipped = np.minimum(image, level)
    cat = detect(clipped)
    i, _ = match(cat, truth)
    saturated = truth["star"] & (truth["peak_snr"] * SIGMA > 1000.0 + 3 * SIGMA)
    unsaturated = truth["star"] & (truth["peak_snr"] * SIGMA < 1000.0 - 3 * SIGMA)
    assert saturated.sum() >= 3
    sel = select_stars(cat, saturation=level)
    assert not sel[i[saturated]].any()
    assert sel[i[unsaturated & (truth["peak_snr"] >= 40)]].mean() >= 0.9


def test_select_stars_needs_candidates(cat, caplog):
    with caplog.at_level("INFO", logger="pylensfit.detection"):
        sel = select_stars(cat, min_peak_snr=1e6)
    assert "fewer than min_stars" in caplog.text
    assert not sel.any()


# --------------------------------------------------------------------------------------
# close pairs


def test_close_pair_flagged_and_faint_ratio(cat, field):
    _, truth = field
    i, _ = match(cat, truth)
    x, y, flux = cat["x"][i], cat["y"][i], cat["flux_iso"][i]
    pairs = close_pairs(x, y, stamp_size=32)
    np.testing.assert_array_equal(pairs, truth["pair"])
    # with faint_ratio the bright member is kept (not flagged), its faint neighbour is not
    flagged = close_pairs(x, y, flux=flux, stamp_size=32, faint_ratio=0.3)
    bright, faint = N_STARS, len(truth["x"]) - 1
    assert flux[faint] < 0.3 * flux[bright]
    assert not flagged[bright] and flagged[faint]
    assert flagged.sum() == 1
    # detect() sets the CLOSE_PAIR bit on both members
    assert np.all(cat["flags"][i[truth["pair"]]] & flag_value("CLOSE_PAIR"))
    # a small stamp separates them
    assert not close_pairs(x, y, stamp_size=16).any()


def test_close_pairs_geometry_against_brute_force():
    # square stamp (Chebyshev metric), strict inequality
    x = np.array([0.0, 15.9, 100.0, 110.0, 200.0, 215.0, 300.0, 316.0])
    y = np.array([0.0, 0.0, 0.0, 20.0, 0.0, 15.0, 0.0, 0.0])
    np.testing.assert_array_equal(close_pairs(x, y, stamp_size=32), [1, 1, 0, 0, 1, 1, 0, 0])
    rng = np.random.default_rng(1)
    x, y = rng.uniform(0, 400, (2, 400))
    flux = rng.lognormal(5, 1.5, 400)
    dx = np.abs(x[:, None] - x[None, :]) < 16
    dy = np.abs(y[:, None] - y[None, :]) < 16
    near = dx & dy & ~np.eye(400, dtype=bool)
    np.testing.assert_array_equal(close_pairs(x, y), near.any(axis=1))
    spoil = near & ~(flux[None, :] < 0.2 * flux[:, None])  # neighbour j not faint enough
    got = close_pairs(x, y, flux=flux, faint_ratio=0.2)
    np.testing.assert_array_equal(got, spoil.any(axis=1))
    assert got.sum() < near.any(axis=1).sum()
    with pytest.raises(ValueError, match="flux"):
        close_pairs(x, y, faint_ratio=0.2)
    assert close_pairs([], []).shape == (0,)


# --------------------------------------------------------------------------------------
# weight maps, masks, bad pixels, input types


def test_noise_sigma_from_weight_map(field):
    img, truth = field
    sigma = np.where(np.arange(N)[None, :] < N // 2, SIGMA, 2 * SIGMA) * np.ones((N, 1))
    noisy = img + SKY + np.random.default_rng(11).normal(size=img.shape) * sigma
    weight = 1.0 / sigma**2
    weight[:, 5:9] = 0.0  # a zero-weight column strip, like a bad column
    cat = detect(noisy, weight=weight)
    local_snr = (
        np.where(truth["star"], truth["peak_snr"], truth["snr"])
        * SIGMA
        / sigma[0, np.rint(truth["x"]).astype(int)]
    )
    ok = local_snr >= 20
    i, _ = match(cat, {k: v[ok] for k, v in truth.items()})
    c = cat[i]
    x = truth["x"][ok]
    expect = np.where(x < N // 2, SIGMA, 2 * SIGMA)
    clear = np.abs(np.rint(x) - N // 2) > 17
    assert clear.sum() > 40
    np.testing.assert_allclose(c["noise_sigma"][clear], expect[clear], rtol=1e-6)
    far = np.abs(x - N // 2) > 100
    np.testing.assert_allclose(c["bkg_rms"][far], expect[far], rtol=0.1)
    # flux errors follow the local noise
    ratio = np.median(c["flux_err"][far & (x > N // 2)] / c["aper_radius"][far & (x > N // 2)])
    ratio /= np.median(c["flux_err"][far & (x < N // 2)] / c["aper_radius"][far & (x < N // 2)])
    assert 1.8 < ratio < 2.2
    assert not np.any((cat["x"] > 4.5) & (cat["x"] < 8.5))


def _stamp_overlaps(x, y, block, n=32):
    """Whether the n x n stamps about (x, y) (module convention) overlap a [y, x] block."""
    ix, iy = np.rint(x).astype(int) - n // 2, np.rint(y).astype(int) - n // 2
    return (
        (ix < block[1].stop)
        & (ix + n > block[1].start)
        & (iy < block[0].stop)
        & (iy + n > block[0].start)
    )


def _inside(x, y, block):
    """Whether (x, y) lies on a pixel of the [y, x] block (pixel centres at integers)."""
    ix, iy = np.rint(x), np.rint(y)
    return (
        (ix >= block[1].start)
        & (ix < block[1].stop)
        & (iy >= block[0].start)
        & (iy < block[0].stop)
    )


def test_masked_and_nan_regions(field, image):
    _, truth = field
    # a masked block of garbage and a NaN block, each reaching into a bright star's stamp
    # (13 to 23 px from the star: the star's light there is < 0.1 sigma)
    bright = np.flatnonzero(truth["star"] & (truth["peak_snr"] > 100))[:2]
    blocks = []
    for k in bright:
        cx, cy = int(np.rint(truth["x"][k])) + 18, int(np.rint(truth["y"][k]))
        blocks.append((slice(cy - 5, cy + 6), slice(cx - 5, cx + 6)))
    mblock, nblock = blocks
    data = image.copy()
    mask = np.zeros(data.shape, dtype=np.int16)
    data[mblock] = 1e5  # garbage that would be a bright object were it not masked
    mask[mblock] = 1
    data[nblock] = np.nan

    bkg = measure_background(data, mask=mask)
    assert np.all(np.isfinite(bkg.back)) and np.all(np.isfinite(bkg.rms))
    assert abs(bkg.global_back - SKY) < 0.1 and bkg.bad[mblock].all() and bkg.bad[nblock].all()
    cat = detect(data, mask=mask)
    assert not np.any(_inside(cat["x"], cat["y"], mblock))
    assert not np.any(_inside(cat["x"], cat["y"], nblock))
    match(cat, truth)  # every object still found
    # the stamps that reach the blocks, and only those, are flagged
    masked = (cat["flags"] & flag_value("MASKED")) != 0
    bad = (cat["flags"] & flag_value("BAD_PIXELS")) != 0
    np.testing.assert_array_equal(masked, _stamp_overlaps(cat["x"], cat["y"], mblock))
    np.testing.assert_array_equal(bad, _stamp_overlaps(cat["x"], cat["y"], nblock))
    i, _ = match(cat, truth)
    assert masked[i[bright[0]]] and bad[i[bright[1]]]
    # without the mask the garbage block is detected
    unmasked = detect(np.where(np.isfinite(data), data, SKY))
    assert np.any(_inside(unmasked["x"], unmasked["y"], mblock))


def test_big_endian_input(image):
    little = detect(image.astype("<f4"))
    big = detect(image.astype(">f4"))
    assert len(big) == len(little) > 60
    for name in ("x", "y", "flux", "r_half", "noise_sigma"):
        np.testing.assert_array_equal(big[name], little[name])
    b = measure_background(image.astype(">f8"))
    assert abs(b.global_back - SKY) < 0.1


def test_empty_image_and_bad_input(cat):
    empty = detect(np.zeros((64, 64)))
    assert len(empty) == 0 and empty.colnames == cat.colnames
    for name in cat.colnames:
        assert empty[name].dtype == cat[name].dtype
    with pytest.raises(ValueError, match="2-D"):
        detect(np.zeros(100))
    with pytest.raises(ValueError, match="2-D"):
        detect(np.zeros((3, 32, 32)))
    with pytest.raises(ValueError, match="finite"):
        detect(np.full((32, 32), np.nan))
    with pytest.raises(ValueError, match="finite"):
        measure_background(np.full((32, 32), np.inf))
    with pytest.raises(ValueError, match="shape"):
        detect(np.zeros((32, 32)), weight=np.ones((32, 31)))
    edge = detect(np.pad(np.ones((5, 5)) * 50, ((0, 40), (0, 40))) + np.random.default_rng(
        0).normal(0, 1, (45, 45)), threshold=5)  # fmt: skip
    assert len(edge) == 1 and edge["flags"][0] & flag_value("EDGE")


def test_sep_limits_are_raised_when_hit(image):
    old = sep.get_extract_pixstack()
    sep.set_extract_pixstack(500)
    try:
        small = detect(image)
        assert sep.get_extract_pixstack() == 500  # restored after the call
    finally:
        sep.set_extract_pixstack(old)
    ref = detect(image)
    assert len(small) == len(ref)
    np.testing.assert_array_equal(small["x"], ref["x"])
