"""The README's examples run as written, on small simulated data."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", README.read_text(), flags=re.S)


def _stamps(n: int, seed: int = 3):
    """``n`` exponential and de Vaucouleurs galaxies on 64-pixel stamps, S/N ~ 20-80."""
    import galsim

    rng = np.random.default_rng(seed)
    psf = galsim.Moffat(beta=3.5, fwhm=3.0)
    out = np.empty((n, 64, 64))
    for k in range(n):
        r = rng.uniform(1.0, 2.5)
        gal = (galsim.Exponential(half_light_radius=r) if k % 2 else
               galsim.DeVaucouleurs(half_light_radius=r, trunc=8 * r))
        e = rng.normal(0, 0.2, 2).clip(-0.6, 0.6)
        img = galsim.Convolve(gal.shear(g1=e[0], g2=e[1]), psf).drawImage(
            nx=64, ny=64, scale=1.0, offset=rng.uniform(-0.5, 0.5, 2)).array
        out[k] = img * rng.uniform(20, 80) / np.sqrt((img**2).sum())
    out += rng.normal(size=out.shape)
    return out, psf.drawImage(nx=64, ny=64, scale=1.0).array


def _fields(d: Path) -> None:
    from pylensfit_validation.simulate import FieldSpec, simulate_field, write_field

    spec = FieldSpec(size=320, spacing=32.0, jitter=4.0, model="mixed", g1=0.03)
    img, w, truth = simulate_field(spec, seed=11, noise_seed=12)
    write_field(d / "field.fits", img, w, spec, truth=truth)
    stars = FieldSpec(size=256, star_fraction=1.0)
    img, w, _ = simulate_field(stars, seed=13)
    write_field(d / "starfield.fits", img, w, stars)


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_python_example_runs_as_written(tmp_path, monkeypatch):
    (code,) = [b for b in _blocks("python") if "plf.calibrate(" in b]
    _fields(tmp_path)
    stamps, psf = _stamps(150)
    monkeypatch.chdir(tmp_path)
    ns = {"stamps": stamps, "psf": psf}
    exec(compile(code, str(README), "exec"), ns)
    import pylensfit as plf

    assert isinstance(ns["priors"], plf.Priors)
    t = ns["table"]
    assert {"e1", "e2", "sens1", "sens2", "weight", "flags"} <= set(t.colnames)
    assert ns["usable"].sum() > 120
    g = ns["g"]
    assert abs(g.g1) < 5 * g.g1_err and abs(g.g2) < 5 * g.g2_err  # unsheared stamps
    assert (tmp_path / "priors.json").exists() and (tmp_path / "catalog.fits").exists()
    assert ns["cfg"].model == "devaucouleurs"


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_cli_quick_start_runs_as_written(tmp_path, monkeypatch, capsys):
    """The 'Quick start' shell lines of the README (measure, then shear) on small fields."""
    from pylensfit.cli import main

    (block,) = [b for b in _blocks("bash") if "pylensfit measure field.fits" in b]
    _fields(tmp_path)
    monkeypatch.chdir(tmp_path)
    lines = [ln.split("#")[0].strip() for ln in block.splitlines()]
    cmds = [ln for ln in lines if ln.startswith("pylensfit ")]
    assert cmds
    for cmd in cmds:
        assert main(shlex.split(cmd)[1:]) == 0, cmd
    out = capsys.readouterr().out
    assert "g1" in out and (tmp_path / "catalog.fits").exists()


# ---------------------------------------------------------------------------------------
# The README's catalogue section: its tables are the catalogue's schema
# ---------------------------------------------------------------------------------------
def _generated(marker: str) -> list[list[str]]:
    """The cells of the README's table between ``<!-- marker:start/end -->``, unescaped,
    without the header and separator rows."""
    text = README.read_text()
    m = re.search(rf"<!-- {marker}:start -->\n(.*?)<!-- {marker}:end -->", text, flags=re.S)
    assert m, f"README.md has no <!-- {marker}:start --> ... <!-- {marker}:end --> table"
    rows = []
    for line in m.group(1).strip().splitlines()[2:]:
        cells = re.split(r"(?<!\\)\|", line.strip())[1:-1]
        rows.append([re.sub(r"\\(.)", r"\1", c.strip()) for c in cells])
    return rows


def test_readme_tables_are_the_generated_ones():
    """The committed README carries the tables that the schema generates (after a change to
    COLUMNS, FLAGS or HDUS: bash .ci/readme-tables)."""
    from pylensfit.catalogue import update_readme

    text = README.read_text()
    assert update_readme(text) == text, "README.md's tables are stale: bash .ci/readme-tables"


def test_readme_columns_flags_and_hdus_are_the_schema():
    from pylensfit.catalogue import COLUMNS, HDUS
    from pylensfit.flags import FLAGS

    cols = {n.strip("`"): (u, d) for n, u, d in _generated("columns")}
    assert list(cols) == list(COLUMNS)
    assert cols == {n: (u, " ".join(d.split())) for n, (u, d) in COLUMNS.items()}
    bits = {n.strip("`"): (int(b), d) for b, n, d in _generated("flags")}
    assert bits == {n: (v, " ".join(d.split())) for n, (v, d) in FLAGS.items()}
    hdus = {n.strip("`"): d for n, d in _generated("hdus")}
    assert list(hdus) == list(HDUS)
    assert hdus == {n: " ".join(d.split()) for n, d in HDUS.items()}
    # the one definition of the weight: the README's prose defers to its row
    assert "`weight` (its row below)" in README.read_text()


def test_catalogue_docstring_lists_every_hdu_as_the_schema():
    """pylensfit.catalogue's module docstring lists the HDUs of HDUS, in order, each with
    the description of HDUS."""
    from pylensfit import catalogue

    doc = " ".join(catalogue.__doc__.split())
    listed = re.findall(r"\* ``([A-Z]+)``: ", doc)
    assert listed == list(catalogue.HDUS)
    for name, desc in catalogue.HDUS.items():
        assert f"* ``{name}``: {' '.join(desc.split())}" in doc, name


def test_readme_states_fit_piffs_default_order():
    import inspect

    from pylensfit.psfmodel import fit_piff

    order = inspect.signature(fit_piff).parameters["order"].default
    text = " ".join(README.read_text().split())
    assert f"where the function's default is `order={order}`" in text
