"""Stars among compact galaxies: the stellar locus, and a PSF model that fails its check.

The field (the issue's, scaled down): 640 x 640 pixels of 0.2" (a TAN WCS), a Moffat PSF
of FWHM 0.8" (4 px, beta 3.5) whose FWHM varies by +-10 % corner to corner and whose
ellipticity by up to 0.08 (``psf_variation="survey"``); about 220 exponential galaxies
of half-light radius 0.35-0.6" (1.75-3 px, so only 0.1-0.2 dex larger than the PSF once
convolved with it) at S/N 150, and about 45 stars of peak S/N 100-270 between them. The
compact galaxies outnumber the stars, and at one S/N and in a narrow range of sizes they
crowd more densely in size than the stars do.
"""

import logging

import numpy as np
import pytest
from astropy.table import Table
from scipy.spatial import cKDTree

from pylensfit import Config, Prior, measure
from pylensfit.detection import detect, select_stars
from pylensfit.flags import flag_value
from pylensfit.pipeline import PSF_SUSPECT_CHI2, PSF_SUSPECT_PVALUE
from pylensfit_validation.simulate import FieldSpec, simulate_field, write_field

SPEC = FieldSpec(size=640, spacing=36, jitter=6, psf_fwhm=4.0, psf_beta=3.5, psf_e1=0.0,
                 psf_e2=0.0, psf_variation="survey", star_fraction=0.2,
                 snr_range=(150.0, 150.0), size_range=(1.75 / 1.678, 3.0 / 1.678),
                 star_peak_snr=(100.0, 270.0), pixel_scale_arcsec=0.2)  # fmt: skip
#: the default PSF choice ("auto": the polynomial model where the stars show the PSF
#: varying), with a coarse exponential model bank to keep the fit short
CFG = Config.paper(model="exponential", r_max=6.0, r_step=0.3, min_snr=0.0).replace(
    psf_model="auto")


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    d = tmp_path_factory.mktemp("compact")
    img, w, truth = simulate_field(SPEC, seed=1)
    write_field(d / "f.fits", img, w, SPEC, truth=truth)
    return d, img, w, truth


def _truth_star(x, y, truth) -> np.ndarray:
    """Whether each position lies within 2 px of a true star (else a galaxy)."""
    d, j = cKDTree(np.column_stack([truth["x"], truth["y"]])).query(np.column_stack([x, y]))
    return np.asarray(truth["is_star"])[j] & (d < 2.0)


def _galaxies(cat, truth):
    """The true galaxies and their usable catalogue rows."""
    d, j = cKDTree(np.column_stack([cat["x"], cat["y"]])).query(
        np.column_stack([truth["x"], truth["y"]]))
    gal = ~np.asarray(truth["is_star"]) & (d < 2.0)
    c, t = cat[j[gal]], truth[gal]
    ok = (np.asarray(c["flags"]) == 0) & (np.asarray(c["fitclass"]) == 0)
    return c[ok], t[ok], gal.sum()


def test_locus_found_below_denser_compact_galaxies(field):
    _, img, w, truth = field
    cat = detect(img, weight=w)
    star = _truth_star(cat["x"], cat["y"], truth)
    bright = np.asarray(cat["peak_snr"]) >= 30
    # the field is a hard one: the densest 0.1 dex of sizes holds mostly galaxies (so the
    # densest window is not the locus), and galaxies outnumber the stars among the
    # candidates
    s = np.log10(np.asarray(cat["r_half"]))[bright]
    ss = np.sort(s)
    counts = np.searchsorted(ss, ss + 0.1, side="right") - np.arange(ss.size)
    k = int(np.argmax(counts))
    dense = (s >= ss[k]) & (s <= ss[k] + 0.1)
    assert star[bright][dense].mean() < 0.2, star[bright][dense].mean()
    assert (~star & bright).sum() > 2 * (star & bright).sum()
    sel = select_stars(cat)
    purity = star[sel].mean()
    completeness = sel[star & bright].mean()
    assert purity >= 0.99 and completeness >= 0.9, (purity, completeness, sel.sum())
    # a locus of a constant centre (the PSF's size varies by +-10 % over the image) is
    # wider, yet still clear of these galaxies
    flat = select_stars(cat, position_order=0)
    assert star[flat].mean() >= 0.99 and flat[star & bright].mean() >= 0.9


def test_measure_builds_the_psf_from_stars_only(field):
    d, _, _, truth = field
    cat = measure([str(d / "f.fits")], config=CFG, prior=Prior(), progress=False,
                  psf_dir=str(d / "psf"))  # fmt: skip
    p = cat.meta["psfs"][0]
    # the PSF model of the image's stars (written to psf_dir): they are stars, every one
    used = Table.read(d / "psf" / "f.psf.fits", hdu="STARS")
    used = used[np.asarray(used["used"], bool)]
    assert len(used) >= 30
    assert _truth_star(used["x"], used["y"], truth).mean() >= 0.99
    own = np.asarray(cat["psf_star"], bool)
    assert _truth_star(cat["x"][own], cat["y"][own], truth).mean() >= 0.99
    # its held-out stars agree with it to within their noise: the excess rms over the
    # noise is within its two-sigma floor (the rms^2 of n stars scatters by
    # rms^2 sqrt(2 / n)), and the check passes
    n = p["psf_heldout_n"]
    assert n >= 5
    for i in (1, 2):
        ex, rms = p[f"psf_heldout_excess_de{i}"], p[f"psf_heldout_rms_de{i}"]
        assert ex**2 <= 2 * rms**2 * np.sqrt(2 / n), (i, ex, rms, n)
    assert p["psf_heldout_chi2_de"] < 1 + 3 / np.sqrt(n)
    assert p["psf_heldout_suspect"] == 0
    assert not np.any(np.asarray(cat["flags"]) & flag_value("PSF_SUSPECT"))
    # the galaxies' shapes: median |e| that of the truth, sensitivity about 1
    c, t, n_gal = _galaxies(cat, truth)
    assert len(c) >= 0.9 * n_gal
    e_meas = np.median(np.hypot(c["e1_pix"], c["e2_pix"]))
    e_true = np.median(np.hypot(t["e1"], t["e2"]))
    assert abs(e_meas - e_true) < 0.05, (e_meas, e_true)
    assert abs(np.median(c["sens1"]) - 1.0) < 0.1


def test_a_psf_model_of_galaxies_is_flagged(field, caplog):
    d, _, _, truth = field
    # a star list of the most compact galaxies (what a locus taken at the densest sizes
    # gives on this field): the PSF model fitted to them fails its held-out check
    gal = ~np.asarray(truth["is_star"]) & (np.asarray(truth["r"]) < 1.3)
    t = Table({"x": truth["x"], "y": truth["y"], "psf_cand": gal})
    t.write(d / "cands.fits", overwrite=True)
    with caplog.at_level(logging.WARNING, logger="pylensfit.pipeline"):
        cat = measure([str(d / "f.fits")], catalogues=[str(d / "cands.fits")],
                      star_column="psf_cand", config=CFG, prior=Prior(), progress=False)
    p = cat.meta["psfs"][0]
    assert p["psf_heldout_suspect"] == 1
    assert p["psf_heldout_chi2_de"] > PSF_SUSPECT_CHI2
    assert p["psf_heldout_pvalue_de"] < PSF_SUSPECT_PVALUE
    warned = [r for r in caplog.records if "PSF_SUSPECT" in r.getMessage()]
    assert len(warned) == 1 and "f.fits" in warned[0].getMessage()
    # every row fitted with it is flagged: none is usable
    flags = np.asarray(cat["flags"])
    measured = np.asarray(cat["fitclass"]) >= 0
    assert measured.sum() > 100
    assert np.all(flags[measured] & flag_value("PSF_SUSPECT"))
    assert not np.any(np.asarray(cat["weight"]) > 0)
