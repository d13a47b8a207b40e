"""``measure_exposures`` / ``pylensfit measure --exposures``: the exposures of one field
from FITS to a catalogue, each galaxy fitted jointly on every exposure that holds it.

A small dithered set (three exposures, each with its own pointing, rotation, pixel scale,
seeing, PSF ellipticity, noise, zero point and chip gap; one flipped) of bright galaxies,
PSFs from each exposure's star field."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.coordinates import SkyCoord
from astropy.io import fits
from astropy.table import Table

import pylensfit as plf
from pylensfit import Config, Priors, measure_exposures
from pylensfit.cli import main
from pylensfit.flags import FLAGS
from pylensfit_validation.dither import DitherSpec, read_dither, render_exposure, simulate_dither

pytest.importorskip("galsim")

SPEC = DitherSpec(n_exposures=3, ngal=25, snr_range=(200.0, 300.0), size_range=(0.3, 0.5),
                  spacing=10.0, star_field_size=160, g1=0.0, g2=0.0)
#: the defaults but for the models cut at each exposure's stamp edge: the wrapped wings
#: cost seconds per exposure and tier, and tests/test_joint_measure.py tests them
CFG = Config().replace(truncate_models=False)


@pytest.fixture(scope="module")
def dset(tmp_path_factory):
    return read_dither(simulate_dither(tmp_path_factory.mktemp("dx"), SPEC, seed=11))


def _files(s):
    k = range(len(s.exposures))
    return [str(s.path(i)) for i in k], [str(s.star_path(i)) for i in k]


@pytest.fixture(scope="module")
def from_truth(dset, tmp_path_factory):
    """The truth's positions as an input catalogue, with a row without a position and
    one off every exposure; the priors' defaults (no calibration: 25 galaxies)."""
    t = dset.truth
    ra = np.concatenate([t["ra"], [np.nan, t["ra"][0] + 1.0]])
    dec = np.concatenate([t["dec"], [np.nan, t["dec"][0]]])
    path = tmp_path_factory.mktemp("cat") / "positions.fits"
    Table({"ra": ra, "dec": dec}).write(path)
    exps, stars = _files(dset)
    return measure_exposures(exps, stars=stars, catalogue=str(path), priors=Priors(),
                             config=CFG), path  # fmt: skip


def test_every_position_leaves_a_row(from_truth, dset):
    cat, _ = from_truth
    n = len(dset.truth)
    assert len(cat) == n + 2
    assert cat["flags"][n] & FLAGS["BAD_POSITION"][0]
    assert cat["flags"][n + 1] & FLAGS["NOT_MEASURED"][0] and cat["n_exposures"][n + 1] == 0
    assert np.all(cat["weight"][n:] == 0) and np.all(np.isnan(cat["e1"][n:]))
    assert np.sum(cat["weight"][:n] > 0) >= n - 2
    assert cat.meta["frame"] == "sky" and len(cat.meta["exposures"]) == 3


def test_an_exposure_where_a_galaxy_is_on_the_gap_drops_out_alone(from_truth, dset):
    """The truth says which exposures have data at each galaxy's centre: the joint fit
    uses those exposures (``exposures_used``) and the galaxy is measured from them."""
    cat, _ = from_truth
    n = len(dset.truth)
    on = np.zeros((3, n), bool)
    for k in range(3):
        with fits.open(dset.path(k)) as h:
            on[k] = np.asarray(h["TRUTH"].data["on_data"], bool)
    used = np.asarray(cat["exposures_used"][:n])
    bits = np.array([(used >> k) & 1 for k in range(3)], bool)
    # an exposure used always has data at the centre; edge and gap cuts may drop more
    assert not np.any(bits & ~on)
    dropped = (on.sum(axis=0) < 3) & (on.sum(axis=0) > 0)
    assert dropped.any(), "the set should put a galaxy on a chip gap"
    assert np.all(cat["n_exposures"][:n] == bits.sum(axis=0))
    assert np.all(cat["weight"][:n][dropped & (bits.sum(axis=0) > 0)] > 0)


def test_the_shapes_are_those_of_the_sky(from_truth, dset):
    """Bright galaxies: the sky-frame posterior means follow the true sheared shapes with
    slope ~1 on both components, through rotated, rescaled and flipped exposures (a
    shape left in an exposure's pixel frame gives slope ~-1 on e2 under the flip and a
    scatter of the rotation's)."""
    cat, _ = from_truth
    n = len(dset.truth)
    ok = np.asarray(cat["weight"][:n]) > 0
    for c in ("e1", "e2"):
        x, y = np.asarray(dset.truth[c])[ok], np.asarray(cat[c][:n])[ok]
        slope, icpt = np.polyfit(x, y, 1)
        assert 0.8 < slope < 1.2 and abs(icpt) < 0.03, (c, slope, icpt)
        assert np.median(np.abs(y - x)) < 0.06, c


def test_detection_on_the_coadd_finds_every_galaxy(dset, tmp_path):
    exps, stars = _files(dset)
    out = tmp_path / "cat.fits"
    # a high threshold: the test is of the co-add's path, not of fitting noise peaks
    cat = measure_exposures(exps, stars=stars, priors=Priors(),
                            config=CFG.replace(detect_threshold=4.0), output=out)  # fmt: skip
    t = dset.truth
    a = SkyCoord(cat["ALPHA_J2000"], cat["DELTA_J2000"], unit="deg")
    b = SkyCoord(t["ra"], t["dec"], unit="deg")
    _, sep, _ = b.match_to_catalog_sky(a)
    assert np.all(sep.arcsec < 0.3)
    back = plf.read_catalogue(out)
    assert len(back) == len(cat) and "n_exposures" in back.colnames


def test_the_command_line(dset, tmp_path, capsys, from_truth):
    exps, stars = _files(dset)
    _, positions = from_truth
    priors = tmp_path / "priors.json"
    Priors().save(priors)
    out = tmp_path / "cli.fits"
    CFG.to_yaml(tmp_path / "cfg.yaml")
    rc = main(["measure", "--exposures", *exps, "--stars", *stars, "--catalogues",
               str(positions), "--priors", str(priors), "--config", str(tmp_path / "cfg.yaml"),
               "-o", str(out)])  # fmt: skip
    assert rc == 0 and out.exists()
    assert "3 exposures" in capsys.readouterr().out
    rc = main(["measure", "--exposures", *exps, "--stars", stars[0], "-o",
               str(tmp_path / "x.fits")])  # fmt: skip
    err = capsys.readouterr().err
    assert rc != 0 and "1 star field(s) for 3 exposures" in err and "Traceback" not in err
    assert not (tmp_path / "x.fits").exists()


def _wcs(sip: float = 0.0):
    from astropy.wcs import WCS

    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"] if sip else ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [150.0, 2.0]
    w.wcs.crpix = [1024.0, 1024.0]
    w.wcs.cd = np.array([[-0.2, 0.01], [0.01, 0.2]]) / 3600.0
    if sip:
        from astropy.wcs import Sip

        a = np.zeros((3, 3))
        b = np.zeros((3, 3))
        a[2, 0] = b[0, 2] = sip  # x' = x + sip x^2: a scale change of 2 sip x
        w.sip = Sip(a, b, np.zeros((1, 1)), np.zeros((1, 1)), w.wcs.crpix)
    return w


def test_one_jacobian_per_group_within_the_tolerance():
    """A TAN field of 7 arcmin is one group; under a SIP distortion whose scale changes by
    4e-3 across it the groups hold Jacobians within the tolerance of their median."""
    from pylensfit.exposures import Exposure, local_jacobian
    from pylensfit.images import jacobian_groups

    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 2048, (400, 2))
    for sip, n_min in ((0.0, 1), (1e-6, 5)):
        w = _wcs(sip)
        ex = Exposure(image=np.zeros((2048, 2048), np.float32), wcs=w)
        sky = w.pixel_to_world(xy[:, 0], xy[:, 1])
        ra, dec = sky.ra.deg, sky.dec.deg
        g = jacobian_groups([ex, ex], ra, dec, 1e-4)
        assert (np.unique(g).size == 1) if sip == 0 else (np.unique(g).size >= n_min)
        J = local_jacobian(w, ra, dec)
        for lab in np.unique(g):
            Jg = J[g == lab]
            rel = Jg @ np.linalg.inv(np.median(Jg, axis=0)) - np.eye(2)
            assert np.abs(rel).max() < 1e-4 * 1.01


def test_bad_inputs_are_one_line_and_leave_no_output(dset, tmp_path, capsys):
    exps, stars = _files(dset)
    nowcs = tmp_path / "nowcs.fits"
    fits.PrimaryHDU(np.ones((64, 64), np.float32)).writeto(nowcs)
    badcat = tmp_path / "xy.fits"
    Table({"x": [1.0], "y": [2.0]}).write(badcat)
    out = tmp_path / "o.fits"
    cases = [
        ([*exps[:2], str(tmp_path / "gone.fits"), "--stars", *stars], "gone.fits: exposure "
         "not found"),
        ([*exps[:2], str(nowcs), "--psf", str(nowcs)], "nowcs.fits: no celestial WCS"),
        ([*exps, "--stars", *stars, "--catalogues", str(badcat)], "needs columns ra, dec"),
    ]  # fmt: skip
    for args, says in cases:
        rc = main(["measure", "--exposures", *args, "-o", str(out)])
        err = capsys.readouterr().err
        assert rc != 0 and says in err and "Traceback" not in err, err
        assert len(err.strip().splitlines()) == 1, err
        assert not out.exists()


def test_the_neighbours_are_taken_out_of_every_exposure(tmp_path):
    """Galaxies 6" apart (their neighbours outside the 48-px stamps, their wings inside):
    each even galaxy is measured with its odd neighbours present, and alone (the same
    exposures and noise rendered without the odd galaxies). With the neighbours' models
    rendered into each exposure through its WCS and PSF and taken out, the shapes are
    those of the galaxies alone to a few 1e-3; without, several times further off (all
    on the base stamp, ``max_stamp_size = 0``). With the stamp tiers, the galaxies alone
    that need more than 32 px and have no neighbour within 64 px are fitted on 64; the
    others are not."""
    spec = DitherSpec(n_exposures=3, ngal=25, snr_range=(200.0, 300.0), size_range=(0.4, 0.7),
                      spacing=6.0, jitter=0.3, star_field_size=160, g1=0.0, g2=0.0)  # fmt: skip
    s = read_dither(simulate_dither(tmp_path / "crowded", spec, seed=11))
    exps, stars = _files(s)
    keep = np.arange(len(s.truth)) % 2 == 0  # a checkerboard of the 5 x 5 lattice
    alone = []
    for k, path in enumerate(exps):
        img = render_exposure(spec, s.exposures[k], s.truth[keep])[0]
        with fits.open(path) as h:
            h[0].data = img
            alone.append(str(tmp_path / f"alone{k}.fits"))
            h.writeto(alone[-1])
    pos = {}
    for name, sel in (("all", np.ones(len(s.truth), bool)), ("alone", keep)):
        pos[name] = str(tmp_path / f"{name}.fits")
        Table({"ra": s.truth["ra"][sel], "dec": s.truth["dec"][sel]}).write(pos[name])
    base = CFG.replace(max_stamp_size=0)
    ref = measure_exposures(alone, stars=stars, catalogue=pos["alone"], priors=Priors(),
                            config=base)  # fmt: skip
    rms = {}
    for sub in (False, True):
        cat = measure_exposures(exps, stars=stars, catalogue=pos["all"], priors=Priors(),
                                config=base.replace(subtract_neighbours=sub))[keep]  # fmt: skip
        d = np.concatenate([np.asarray(cat[c]) - np.asarray(ref[c]) for c in ("e1", "e2")])
        rms[sub] = float(np.sqrt(np.mean(d**2)))
        assert np.all(cat["flags"] == 0)
    assert rms[True] < 0.003  # measured 0.0015
    assert rms[True] < 0.4 * rms[False]  # measured 0.0056 without
    tiers = measure_exposures(alone, stars=stars, catalogue=pos["alone"], priors=Priors(),
                              config=CFG)  # fmt: skip
    # the checkerboard's galaxies are 8.5" apart diagonally: within 64 px of each other
    # but at the set's edge
    assert np.all(tiers["stamp_size"] >= 32) and np.sum(tiers["stamp_size"] == 64) >= 1
    crowded = measure_exposures(exps, stars=stars, catalogue=pos["all"], priors=Priors(),
                                config=CFG)  # fmt: skip
    assert np.all(crowded["stamp_size"] == 32)


def test_a_cosmic_ray_on_a_galaxy_drops_that_exposure_alone(dset, from_truth, tmp_path):
    """Cosmic rays (3-pixel tracks of 50 sigma) 2 px from the centres of nine galaxies in
    exposure 0: masked (``Config.cosmic_rays``), those galaxies are fitted on the other
    two exposures, near their shapes from all three; every other galaxy keeps its
    exposures. Unmasked, the same hits pull the nine shapes far off."""
    clean, path = from_truth
    n = len(dset.truth)
    exps, stars = _files(dset)
    hit = np.arange(0, n, 3)
    with fits.open(exps[0]) as h:
        tr = h["TRUTH"].data
        hit = hit[np.asarray(tr["on_data"], bool)[hit]]
        img = h[0].data.astype(np.float32)
        sigma = 1.0 / np.sqrt(np.median(h["WEIGHT"].data[h["WEIGHT"].data > 0]))
        for i in hit:
            x, y = int(round(tr["x"][i])) + 2, int(round(tr["y"][i]))
            img[y, x : x + 3] += 50.0 * sigma
        h[0].data = img
        exps = [str(tmp_path / "cr0.fits"), *exps[1:]]
        h.writeto(exps[0])
    de = {}
    for on in (True, False):
        cat = measure_exposures(exps, stars=stars, catalogue=str(path), priors=Priors(),
                                config=CFG.replace(cosmic_rays=on))[:n]  # fmt: skip
        de[on] = np.hypot(cat["e1"] - clean["e1"][:n], cat["e2"] - clean["e2"][:n])
        if on:
            used = np.asarray(cat["exposures_used"])
            assert np.all(used[hit] & 1 == 0) and np.all(cat["weight"][hit] > 0)
            rest = np.setdiff1d(np.arange(n), hit)
            assert np.array_equal(used[rest], np.asarray(clean["exposures_used"][:n])[rest])
            assert np.nanmax(de[on][rest]) < 1e-3
    assert np.median(de[True][hit]) < 0.005  # measured 0.0005
    assert np.median(de[False][hit]) > 5 * np.median(de[True][hit])  # measured 0.022


def test_metacal_columns_of_the_joint_fit(from_truth, dset, tmp_path, capsys):
    """``Config.response = "metacal"``: every measured galaxy metacalibrated on all its
    exposures, the single-image pipeline's columns (sky frame); every other column as
    the measurement without it; the same numbers again for the same seed; ``shear
    --estimator metacal`` reads the catalogue."""
    cat, positions = from_truth
    exps, stars = _files(dset)
    out = tmp_path / "mcal.fits"
    mc = measure_exposures(exps, stars=stars, catalogue=str(positions), priors=Priors(),
                           config=CFG.replace(response="metacal"), output=out)  # fmt: skip
    assert len(mc) == len(cat)
    for c in cat.colnames:
        np.testing.assert_array_equal(np.asarray(mc[c]), np.asarray(cat[c]), err_msg=c)
    n = len(dset.truth)
    ok = np.asarray(cat["weight"][:n]) > 0
    mflags = np.asarray(mc["mcal_flags"])
    assert (mflags[:n][ok] == 0).mean() > 0.9 and (mflags[n:] != 0).all()
    good = np.flatnonzero(mflags == 0)
    R = np.array([[mc["R11"], mc["R12"]], [mc["R21"], mc["R22"]]], float)[:, :, good]
    assert np.isfinite(R).all()
    assert 0.3 < np.median(R[0, 0]) < 1.2 and 0.3 < np.median(R[1, 1]) < 1.2
    assert np.median(np.abs(R[0, 1])) < 0.1
    # at S/N 200-300 the unsheared image's mean is the measurement's, in the sky frame
    for c in ("e1", "e2"):
        d = np.asarray(mc[c + "_mcal"])[good] - np.asarray(mc[c])[good]
        assert np.median(np.abs(d)) < 0.03, c
    assert (np.asarray(mc["mcal_snr_noshear"])[good] > 50).all()
    again = measure_exposures(exps, stars=stars, catalogue=str(positions), priors=Priors(),
                              config=CFG.replace(response="metacal"))  # fmt: skip
    np.testing.assert_array_equal(np.asarray(again["R11"]), np.asarray(mc["R11"]))
    assert main(["shear", str(out), "--estimator", "metacal"]) == 0
    assert "g1" in capsys.readouterr().out
