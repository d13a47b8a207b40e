"""Bad input is answered in one line naming the file or option and the problem: no
traceback, no output left behind."""

import subprocess
import sys

import numpy as np
import pytest
import yaml
from astropy.io import fits
from astropy.table import Table

from pylensfit import Config, Prior, Priors, SizePrior, ellipticity_grid
from pylensfit.cli import main
from pylensfit.flags import flag_value
from pylensfit.pipeline import read_catalogue, write_catalogue


def _run(capsys, argv):
    """``main(argv)``: its exit status and everything it printed."""
    capsys.readouterr()
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse
        code = exc.code
    out = capsys.readouterr()
    return code, out.out + out.err


def _one_line(code, text, *needles):
    """A failure told in one line that holds every one of ``needles``."""
    assert code not in (0, None), text
    assert "Traceback" not in text
    lines = text.strip().splitlines()
    assert len(lines) == 1, text
    for n in needles:
        assert str(n) in lines[0], (n, lines[0])
    return lines[0]


@pytest.fixture
def catalogue(tmp_path):
    """A small catalogue as ``pylensfit measure`` writes it (40 galaxies, Gaussian ln L)."""
    eg = ellipticity_grid(0.1)
    rng = np.random.default_rng(3)
    n = 40
    e0 = rng.normal(0, 0.25, (n, 2))
    lnL = -0.5 * ((eg[None, :, 0] - e0[:, :1]) ** 2 + (eg[None, :, 1] - e0[:, 1:]) ** 2) / 0.01
    t = Table({"x": rng.uniform(0, 100, n), "y": rng.uniform(0, 100, n),
               "image": ["a.fits"] * n, "flags": np.zeros(n, np.int32),
               "fitclass": np.zeros(n, np.int16), "weight": np.ones(n),
               "mag": rng.uniform(20, 24, n), "lnL": lnL.astype(np.float32)})  # fmt: skip
    t.meta["egrid"] = eg
    t.meta["prior"] = Prior(egrid=eg)
    path = tmp_path / "cat.fits"
    write_catalogue(t, path)
    return path, t


def _without(t, column, path):
    c = t.copy()
    c.remove_column(column)
    c.meta.update(t.meta)
    write_catalogue(c, path)
    return path


def test_bad_prior_files(catalogue, tmp_path, capsys):
    img = tmp_path / "img.fits"
    fits.PrimaryHDU(np.random.default_rng(1).normal(size=(64, 64))).writeto(img)
    out = tmp_path / "out.fits"
    wrong = tmp_path / "wrong.json"
    wrong.write_text('{"B": 0.2, "c": 0.5}')
    listed = tmp_path / "list.json"
    listed.write_text("[0.2, 0.5, 2.4]")
    text = tmp_path / "text.json"
    text.write_text("B = 0.2\n")
    cases = [(wrong, "not an ellipticity prior", "'C'"), (listed, "JSON list", ""),
             (text, "not JSON", "")]  # fmt: skip
    for path, problem, detail in cases:
        code, said = _run(capsys, ["measure", img, "--prior", path, "-o", out])
        _one_line(code, said, path.name, problem, detail)
        with pytest.raises(ValueError, match=f"{path.name}: .*{problem}"):
            Prior.load(path)
    for option, cls in (("--size-prior", SizePrior), ("--priors", Priors)):
        for path in (wrong, listed, text):
            code, said = _run(capsys, ["measure", img, option, path, "-o", out])
            _one_line(code, said, path.name, "not ")
            with pytest.raises(ValueError, match=path.name):
                cls.load(path)
    assert not out.exists()
    # `shear --prior` reads it too
    code, said = _run(capsys, ["shear", catalogue[0], "--prior", wrong])
    _one_line(code, said, "wrong.json", "not an ellipticity prior")
    # a real process: stderr holds that line and nothing else
    res = subprocess.run([sys.executable, "-m", "pylensfit.cli", "measure", str(img),
                          "--prior", str(listed), "-o", str(out)],
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert res.returncode == 1 and res.stdout == ""
    _one_line(1, res.stderr, "pylensfit: error: ", "list.json", "JSON list")
    assert not out.exists()


def test_catalogues_without_the_columns(catalogue, tmp_path, capsys):
    path, t = catalogue
    prior = tmp_path / "prior.json"
    foreign = tmp_path / "foreign.fits"
    Table({"ra": [1.0, 2.0], "dec": [3.0, 4.0]}).write(foreign)
    no_flags = _without(t, "flags", tmp_path / "no_flags.fits")
    no_image = _without(t, "image", tmp_path / "no_image.fits")
    no_lnl = tmp_path / "no_lnl.fits"
    with fits.open(path) as h:
        fits.HDUList([h[i].copy() for i in range(len(h)) if h[i].name != "LNL"]).writeto(no_lnl)
    for bad, need in ((foreign, "CATALOG"), (no_flags, "flags"), (no_lnl, "LNL")):
        for cmd in (["prior", bad, "-o", prior], ["shear", bad, "-o", tmp_path / "g.ecsv"]):
            code, said = _run(capsys, cmd)
            _one_line(code, said, bad.name, need)
    code, said = _run(capsys, ["shear", no_image])
    _one_line(code, said, "no_image.fits", "no column image")
    # a second catalogue that lacks one is named, not the first
    code, said = _run(capsys, ["prior", path, no_flags, "-o", prior])
    _one_line(code, said, "no_flags.fits", "flags")
    assert not prior.exists() and not (tmp_path / "g.ecsv").exists()
    # and the catalogue itself is good
    code, said = _run(capsys, ["shear", path, "--no-per-image"])
    assert code == 0


def test_bin_by_mistakes(catalogue, tmp_path, capsys):
    path, _ = catalogue
    out = tmp_path / "g.ecsv"
    for spec, problem in (("nosuchcol:1,2", "no column 'nosuchcol'"),
                          ("image:1,2", "cat.fits is not numeric"),
                          ("lnL:1,2", "one number per row")):  # fmt: skip
        code, said = _run(capsys, ["shear", path, "--bin-by", spec, "-o", out])
        assert code == 1
        _one_line(code, said, "--bin-by", problem)
    code, said = _run(capsys, ["shear", path, "--bin-by", "mags:20,22", "-o", out])
    _one_line(code, said, "--bin-by", "closest: mag")
    for spec, problem in (("mag:5", "two edges"), ("mag:24,20", "increase"),
                          ("mag:nan,22", "finite"), ("mag", "COLUMN:EDGE")):  # fmt: skip
        code, said = _run(capsys, ["shear", path, "--bin-by", spec, "-o", out])
        assert code == 2  # argparse
        _one_line(code, said, "argument --bin-by", problem)
    assert not out.exists()
    assert _run(capsys, ["shear", path, "--bin-by", "mag:20,22,24", "-o", out])[0] == 0


def test_broken_catalogue_files(catalogue, tmp_path, capsys):
    path, _ = catalogue
    with fits.open(path) as h:
        h["EGRID"].data = h["EGRID"].data[:-4]
        h.writeto(tmp_path / "egrid.fits")
    with fits.open(path) as h:
        h[0].header["PRIOR_C"] = "abc"
        h.writeto(tmp_path / "card.fits")
    raw = bytearray(path.read_bytes())
    at = raw.find(b"PRIOR_B =")
    raw[at : at + 17] = b"PRIOR_B = 1.2.3.4"
    (tmp_path / "raw.fits").write_bytes(bytes(raw))
    for name, problem in (("egrid.fits", "EGRID has shape"), ("card.fits", "HDU PRIMARY"),
                          ("raw.fits", "'PRIOR_B' is not FITS standard")):  # fmt: skip
        for cmd in (["prior", tmp_path / name, "-o", tmp_path / "p.json"],
                    ["shear", tmp_path / name]):  # fmt: skip
            code, said = _run(capsys, cmd)
            _one_line(code, said, name, problem)
        with pytest.raises(ValueError, match=f"{name}: .*{problem}"):
            read_catalogue(tmp_path / name)
    assert not (tmp_path / "p.json").exists()


def test_unknown_configuration_key_is_one_short_line(tmp_path, capsys):
    img = tmp_path / "img.fits"
    fits.PrimaryHDU(np.zeros((8, 8))).writeto(img)
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("stamp_sise: 48\n")
    code, said = _run(capsys, ["measure", img, "--config", cfg, "-o", tmp_path / "o.fits"])
    line = _one_line(code, said, "cfg.yaml", "'stamp_sise'", "'stamp_size'", "pylensfit config")
    assert len(line) - len(str(cfg)) < 160  # the message, less the file's path
    # a file of another program's keys: a few named, the rest counted
    many = tmp_path / "many.yaml"
    many.write_text(yaml.safe_dump({f"{k}_other": v for k, v in Config().to_dict().items()}))
    code, said = _run(capsys, ["measure", img, "--config", many, "-o", tmp_path / "o.fits"])
    line = _one_line(code, said, "many.yaml", "unknown configuration keys", "more",
                     "pylensfit config")  # fmt: skip
    assert len(line) - len(str(many)) < 200
    assert not (tmp_path / "o.fits").exists()


def test_a_whole_stamp_size_and_a_positive_number_of_jobs(tmp_path, capsys):
    img = tmp_path / "img.fits"
    fits.PrimaryHDU(np.zeros((8, 8))).writeto(img)
    out = tmp_path / "o.fits"
    for text, shown in (("stamp_size: 32.7\n", "32.7"), ("stamp_size: true\n", "True")):
        cfg = tmp_path / "cfg.yaml"
        cfg.write_text(text)
        code, said = _run(capsys, ["measure", img, "--config", cfg, "-o", out])
        _one_line(code, said, "cfg.yaml", "'stamp_size' must be int", shown)
    for jobs in ("0", "-3", "two"):
        code, said = _run(capsys, ["measure", img, "--jobs", jobs, "-o", out])
        assert code == 2
        _one_line(code, said, "argument --jobs", jobs)
    assert not out.exists()


def test_a_nan_position_is_kept_and_flagged(tmp_path, capsys):
    """An input catalogue's row without a finite position: the run goes on, the row is
    kept (NaN position) and flagged BAD_POSITION, the others are measured."""
    from pylensfit_validation.simulate import FieldSpec, field_psf, simulate_field, write_field

    spec = FieldSpec(size=192, model="exponential", star_fraction=0.0, snr_range=(40, 80))
    img, w, truth = simulate_field(spec, seed=5)
    write_field(tmp_path / "f.fits", img, w, spec, truth=truth)
    psf = field_psf(spec).drawImage(nx=48, ny=48, scale=1.0, use_true_center=False).array
    fits.PrimaryHDU(psf).writeto(tmp_path / "psf.fits")
    incat = Table({"x": np.array(truth["x"], float), "y": np.array(truth["y"], float)})
    incat["x"][1] = np.nan
    incat["y"][3] = np.inf
    incat.write(tmp_path / "in.fits")
    Config.paper(model="exponential", r_max=6.0, r_step=0.3).to_yaml(tmp_path / "cfg.yaml")
    Prior().save(tmp_path / "prior.json")
    out = tmp_path / "cat.fits"
    code, said = _run(capsys, ["measure", tmp_path / "f.fits", "--catalogues",
                               tmp_path / "in.fits", "--psf", tmp_path / "psf.fits",
                               "--config", tmp_path / "cfg.yaml", "--prior",
                               tmp_path / "prior.json", "-o", out, "-q"])  # fmt: skip
    assert code == 0, said
    cat = read_catalogue(out)
    assert len(cat) == len(incat)
    lost = np.zeros(len(cat), bool)
    lost[[1, 3]] = True
    assert np.all(cat["flags"][lost] == flag_value("BAD_POSITION"))
    assert np.all(cat["fitclass"][lost] == -1)
    for c in ("x", "y", "x_detect", "y_detect", "ALPHA_J2000", "noise_sigma"):
        assert np.all(np.isnan(cat[c][lost])), c
    assert not np.any(cat["flags"][~lost] & flag_value("BAD_POSITION"))
    assert np.all(np.isfinite(cat["x"][~lost]))
    assert np.sum((cat["flags"] == 0) & ~lost) >= 3
