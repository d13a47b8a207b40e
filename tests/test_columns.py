"""A written catalogue carries its schema: the COLUMNS HDU is pylensfit.catalogue.COLUMNS,
the primary header names every flag bit, the HDUs are those of HDUS in their order, and
astropy reads the CATALOG HDU without a warning when asked for it by name."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table
from astropy.utils.exceptions import AstropyUserWarning

from pylensfit import Config, Prior, measure, read_catalogue
from pylensfit import catalogue as catmod
from pylensfit import flags as flagmod
from pylensfit.catalogue import (
    COLUMNS,
    HDUS,
    JOINT_COLUMNS,
    METACAL_COLUMNS,
    flag_cards,
    header_flags,
)
from pylensfit.flags import FLAGS


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """A catalogue that ``measure`` wrote: a small simulated field with a WCS, bulge
    fraction marginalised over two values (so that ``LNLB`` and ``lnL_star`` are there)."""
    from pylensfit_validation.simulate import FieldSpec, simulate_field, write_field

    d = tmp_path_factory.mktemp("columns")
    spec = FieldSpec(size=160, spacing=32.0, jitter=4.0, model="exponential")
    img, w, truth = simulate_field(spec, seed=11, noise_seed=12)
    write_field(d / "field.fits", img, w, spec, truth=truth)
    yy, xx = np.mgrid[:33, :33] - 16
    psf = np.exp(-(xx**2 + yy**2) / (2 * 1.3**2))
    cfg = Config.paper(model="bulge+disc", n_bulge_fractions=2, r_max=6.0, r_step=0.3)
    out = d / "cat.fits"
    cat = measure([d / "field.fits"], psf=psf / psf.sum(), config=cfg, prior=Prior(),
                  progress=False, output=out)  # fmt: skip
    assert len(cat) > 10
    return out, cat


def test_columns_hdu_is_the_schema(written):
    path, _ = written
    with fits.open(path) as h:
        doc = h["COLUMNS"].data
        rows = [(str(n), str(u), str(d)) for n, u, d in
                zip(doc["name"], doc["unit"], doc["description"], strict=True)]  # fmt: skip
    assert rows == [(n, u, d) for n, (u, d) in COLUMNS.items()]


def test_catalog_hdu_has_every_column_of_the_schema_with_its_unit(written):
    path, _ = written
    with fits.open(path) as h:
        cols = h["CATALOG"].columns
        # no column undocumented, none missing (the metacalibration's: response "model")
        assert cols.names == [c for c in COLUMNS if c not in METACAL_COLUMNS + JOINT_COLUMNS]
        assert [c.unit or "" for c in cols] == [u for c, (u, _) in COLUMNS.items()
                                                if c not in METACAL_COLUMNS + JOINT_COLUMNS]


def test_header_names_every_flag_bit(written):
    path, _ = written
    hdr = fits.getheader(path)
    assert header_flags(hdr) == {v: n for n, (v, _) in FLAGS.items()}
    for name, (value, desc) in FLAGS.items():
        comment = hdr.comments[f"FLAG{value}"]
        assert comment, name
        # the bit's own description, cut after a word where the card has no more room
        assert desc == comment or (comment.endswith("...")
                                   and " ".join(desc.split()).startswith(comment[:-3]))


def test_hdus_are_those_of_the_schema_in_its_order(written):
    path, _ = written
    with fits.open(path) as h:
        names = [hdu.name for hdu in h]
    assert names[:4] == ["PRIMARY", "CATALOG", "LNL", "EGRID"]
    assert {"LNLB", "PRIORS", "PSFS", "PSFIMG", "CONFIG", "COLUMNS"} <= set(names)
    assert names == [n for n in HDUS if n in names], "an HDU not in HDUS, or out of order"
    # CATALOG is the first table, so that 'extension 1' (TreeCorr's ext=1) is the catalogue
    with fits.open(path) as h:
        tables = [i for i, hdu in enumerate(h) if isinstance(hdu, fits.BinTableHDU)]
    assert tables[0] == 1 and names[1] == "CATALOG"


def test_astropy_reads_the_catalog_hdu_by_name_without_a_warning(written):
    path, cat = written
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        t = Table.read(path, hdu="CATALOG")
    assert t.colnames == [c for c in COLUMNS if c not in METACAL_COLUMNS + JOINT_COLUMNS]
    assert np.array_equal(np.asarray(t["e1"]), np.asarray(cat["e1"]), equal_nan=True)
    # without hdu= astropy reads the same first table and warns, as for any file of
    # several tables (the README and the guide say so)
    with pytest.warns(AstropyUserWarning, match="multiple tables"):
        t0 = Table.read(path)
    assert t0.colnames == t.colnames and len(t0) == len(t)


def test_read_catalogue_reads_it_back(written):
    path, cat = written
    back = read_catalogue(path)
    assert [c for c in back.colnames if c in COLUMNS] == [
        c for c in COLUMNS if c not in METACAL_COLUMNS + JOINT_COLUMNS]
    assert np.array_equal(np.asarray(back["weight"]), np.asarray(cat["weight"]))


def test_a_new_flag_bit_gets_its_card_and_its_table_row(monkeypatch, tmp_path):
    """A bit added to FLAGS appears in the header cards and the generated tables with no
    other change; a value too long for an 8-character keyword takes a HIERARCH card."""
    bit = 2 * max(v for v, _ in flagmod.FLAGS.values())
    assert bit >= 16384  # FLAGn of more than 8 characters
    desc = "a reason added later, described at length " * 3
    monkeypatch.setitem(flagmod.FLAGS, "NEW_REASON", (bit, desc))
    hdr = fits.Header()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no 'card too long' or 'HIERARCH created' warning
        hdr.extend(flag_cards())
        fits.PrimaryHDU(header=hdr).writeto(tmp_path / "h.fits")
    back = fits.getheader(tmp_path / "h.fits")
    assert header_flags(back) == {v: n for n, (v, _) in flagmod.FLAGS.items()}
    assert header_flags(back)[bit] == "NEW_REASON"
    assert back.comments[f"FLAG{bit}"].endswith("...")
    assert f"| {bit} | `NEW_REASON` | a reason added later" in catmod.markdown_flags()


def test_update_readme_and_its_check(tmp_path, capsys):
    text = ("# x\n\n<!-- hdus:start -->\n<!-- hdus:end -->\n\ntext\n\n"
            "<!-- columns:start -->\nold\nrows\n<!-- columns:end -->\n"
            "<!-- flags:start -->\n<!-- flags:end -->\n")  # fmt: skip
    readme = tmp_path / "README.md"
    readme.write_text(text)
    assert catmod.main(["--check", str(readme)]) == 1
    assert readme.read_text() == text  # --check writes nothing
    assert catmod.main([str(readme)]) == 0
    new = readme.read_text()
    assert catmod.markdown_columns() in new and "old\nrows" not in new
    assert "\ntext\n" in new and new.startswith("# x\n")
    assert catmod.main(["--check", str(readme)]) == 0
    assert catmod.update_readme(new) == new
    with pytest.raises(ValueError, match="flags:start"):
        catmod.update_readme(re.sub(r"<!-- flags:end -->\n", "", new))
    capsys.readouterr()


def test_markdown_cells_escape_markup():
    """``<e1>`` would be read as an HTML tag, ``|`` would end the cell."""
    table = catmod.markdown_columns()
    row = next(ln for ln in table.splitlines() if ln.startswith("| `sens1` |"))
    assert r"d\<e1>/dg1" in row
    assert all(ln.count("|") - ln.count(r"\|") == 4 for ln in table.splitlines())
