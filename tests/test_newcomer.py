"""What a new user meets first: the commands of the README on a small fresh simulated
set, the permissions of the files written, a failed run's leftovers, the progress bar
within an image, and the README's TreeCorr recipe in a fresh environment."""

from __future__ import annotations

import os
import re
import stat
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from astropy.table import Table

import pylensfit as plf
from pylensfit import runner
from pylensfit.cli import main

ROOT = Path(__file__).resolve().parents[1]
# a small set's priors fall back to their defaults, each with a CalibrationWarning
pytestmark = pytest.mark.filterwarnings("ignore::pylensfit.calibration.CalibrationWarning")


@pytest.fixture
def umask_002():
    """A umask that neither the owner-only temporary files (0600) nor the usual default
    (022) give: files must come out 0664."""
    old = os.umask(0o002)
    try:
        yield 0o664
    finally:
        os.umask(old)


def _modes(folder: Path) -> dict[str, int]:
    return {p.relative_to(folder).as_posix(): stat.S_IMODE(p.stat().st_mode)
            for p in folder.rglob("*") if p.is_file()}  # fmt: skip


@pytest.fixture(scope="module")
def few_stars(tmp_path_factory):
    """``pylensfit simulate step1 --ngal 300 --seed 3``: 25 shear fields of 200 px, most
    of them with fewer bright stars than a PSF needs."""
    out = tmp_path_factory.mktemp("few") / "s1"
    assert main(["simulate", "step1", "--out", str(out), "--ngal", "300", "--seed", "3",
                 "--quiet"]) == 0  # fmt: skip
    return out


def test_headline_command_and_validate_on_a_few_star_set(few_stars, tmp_path, capsys):
    """The README's headline command on a field whose own stars are too few for a PSF,
    and ``validate`` on the whole set (every shear field measured with its star field),
    with the defaults: no error, and each catalogue says where its PSF came from."""
    out = tmp_path / "cat.fits"
    rc = main(["measure", str(few_stars / "psf1_g4.fits"), "--stars",
               str(few_stars / "psf1_stars.fits"), "-o", str(out), "-q"])  # fmt: skip
    assert rc == 0, capsys.readouterr().err
    psfs = Table.read(out, hdu="PSFS")
    assert list(psfs["psf_source"]) == ["stacked: 1 star field(s)"]
    assert "psf_min_stars" in psfs["note"][0]  # why the image's own stars gave none
    assert main(["validate", str(few_stars), "-q"]) == 0, capsys.readouterr().err
    shear = sorted((few_stars / "measured").glob("psf*_shear.fits"))
    assert len(shear) == 5
    sources = np.concatenate([np.asarray(Table.read(p, hdu="PSFS")["psf_source"])
                              for p in shear])  # fmt: skip
    assert sources.size == 25 and all("star field" in str(s) for s in sources), sources
    assert not list(few_stars.rglob("*.parts"))


def test_a_failed_run_leaves_no_parts_and_no_output(few_stars, tmp_path, monkeypatch):
    """An error in the second image's task: the error reaches the caller, and neither
    ``<output>.parts/`` nor the catalogue is left behind."""
    from pylensfit.images import passes

    task = passes.image_task

    def failing(t):
        if Path(t.path).name == "psf0_g1.fits":
            raise ValueError("a failure in the work")
        return task(t)

    monkeypatch.setattr(passes, "image_task", failing)
    out = tmp_path / "cat.fits"
    with pytest.raises(ValueError, match="a failure in the work"):
        plf.measure([few_stars / "psf0_g0.fits", few_stars / "psf0_g1.fits"],
                    stars=[few_stars / "psf0_stars.fits"], config=plf.Config.paper(),
                    output=out, progress=False)  # fmt: skip
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_written_files_have_the_umask_permissions(few_stars, tmp_path, umask_002):
    """Catalogues, simulated images and the demo's files get the user's umask (0664
    under umask 002), not the owner-only mode of a temporary file."""
    sim = tmp_path / "sim"
    assert main(["simulate", "step1", "--out", str(sim), "--ngal", "20", "--seed", "1",
                 "--quiet"]) == 0  # fmt: skip
    out = tmp_path / "cat" / "catalog.fits"
    plf.measure([few_stars / "psf0_g0.fits"], stars=[few_stars / "psf0_stars.fits"],
                config=plf.Config.paper(), output=out, progress=False)  # fmt: skip
    demo = tmp_path / "demo"
    main(["demo", "--size", "256", "--jobs", "1", "--outdir", str(demo)])
    modes = {**_modes(sim), **_modes(out.parent), **_modes(demo)}
    assert {"catalog.fits", "field_a.fits", "stars.fits", "psf0_g0.fits",
            "manifest.json"} <= set(modes)  # fmt: skip
    wrong = {k: oct(v) for k, v in modes.items() if v != umask_002}
    assert not wrong, wrong


def test_the_object_bar_moves_within_an_image(few_stars, monkeypatch):
    """On a terminal, ``measure`` shows a second bar counting the objects fitted, fed
    from within each image's task: it ends with every object planned done."""
    import io

    from tqdm import tqdm

    bars = []

    class OnATerminal(tqdm):
        def __init__(self, *args, **kwargs):
            if kwargs.get("disable") is None:  # None: on a terminal only; here, one
                kwargs["disable"] = False
            super().__init__(*args, file=io.StringIO(), **kwargs)
            bars.append(self)

    monkeypatch.setattr(runner, "tqdm", OnATerminal)
    cat = plf.measure([few_stars / "psf2_g0.fits"], stars=[few_stars / "psf2_stars.fits"],
                      config=plf.Config.paper(), progress=True)  # fmt: skip
    objects = [b for b in bars if getattr(b, "desc", "").endswith(": objects")]
    assert objects, [getattr(b, "desc", "") for b in bars]
    fitted = int(np.sum(cat["fitclass"] >= 0))
    assert all(b.total == b.n >= fitted > 0 for b in objects)  # every pass's bar
    # no second bar where the tasks report no objects (the star fields)
    assert not [b for b in bars if getattr(b, "desc", "") == "star fields: objects"]


def _readme_block(after: str, lang: str) -> str:
    """The first ``lang`` code block of the README after the text ``after``."""
    text = (ROOT / "README.md").read_text()
    i = text.index(after)
    m = re.search(rf"```{lang}\n(.*?)```", text[i:], flags=re.S)
    assert m, f"no {lang} block after {after!r}"
    return m.group(1)


def test_readme_treecorr_recipe_in_a_fresh_environment(few_stars, tmp_path):
    """The README's TreeCorr recipe, as written, in a virtual environment made by the
    README's install line plus the extra that the README names for it."""
    text = (ROOT / "README.md").read_text()
    extra = re.search(r'pip install "\.\[(\w+)\]"`?\)?:?\n*```python\nimport treecorr', text)
    assert extra, "the README names no extra before its TreeCorr recipe"
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    subprocess.run([str(py), "-m", "pip", "install", "-q", f"{ROOT}[{extra.group(1)}]"],
                   check=True, capture_output=True)  # fmt: skip
    work = tmp_path / "work"
    plf.measure([few_stars / "psf0_g0.fits", few_stars / "psf0_g1.fits"],
                stars=[few_stars / "psf0_stars.fits"], config=plf.Config.paper(),
                output=work / "catalog.fits", progress=False)  # fmt: skip
    recipe = _readme_block("TreeCorr reads FITS files", "python")
    run = subprocess.run([str(py), "-c", textwrap.dedent(recipe)], cwd=work,
                         capture_output=True, text=True)  # fmt: skip
    assert run.returncode == 0, run.stderr
    printed = run.stdout[run.stdout.rindex("[", 0, run.stdout.rindex("[")):]  # xi+, xi-
    xip = np.array(printed.split("]")[0].strip("[ \n").split(), float)
    assert xip.size == 5 and np.isfinite(xip).any(), run.stdout
