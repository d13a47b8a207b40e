"""A run killed and restarted writes the catalogue of a run never stopped, bit for bit."""

from pathlib import Path

import pytest
from astropy.io import fits

import pylensfit.images.passes as passes
from pylensfit import Config, Prior
from pylensfit.pipeline import measure
from pylensfit_validation.simulate import FieldSpec, simulate_field, write_field

CFG = Config.paper(model="exponential", r_max=6.0, r_step=0.3)
PRIOR = Prior()


def _field(path, seed, **kw):
    spec = FieldSpec(size=256, **kw)
    img, w, truth = simulate_field(spec, seed=seed)
    write_field(path, img, w, spec, truth=truth)


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    """Three small images and a star field; the first image has no star of its own, so
    its PSF is the star field's and its PSF note a long message naming it."""
    d = tmp_path_factory.mktemp("resume")
    _field(d / "no_stars_of_its_own_with_a_long_name.fits", seed=7, star_fraction=0.0)
    _field(d / "a.fits", seed=1, g1=0.03)
    _field(d / "b.fits", seed=2, g1=0.03)
    _field(d / "stars.fits", seed=3, star_fraction=1.0)
    return d, [d / "no_stars_of_its_own_with_a_long_name.fits", d / "a.fits", d / "b.fits"]


def _killed_at(monkeypatch, name: str) -> None:
    """Image tasks as they are, but a kill when the task of image ``name`` starts."""
    real = passes.image_task

    def task(t):
        if t.path.endswith(name):
            raise KeyboardInterrupt("killed")
        return real(t)

    monkeypatch.setattr(passes, "image_task", task)


def _date_masked(path) -> bytes:
    """The file's bytes with the primary header's ``DATE`` card blanked."""
    raw = bytearray(Path(path).read_bytes())
    with fits.open(path) as h:
        i = [c.keyword for c in h[0].header.cards].index("DATE")
    assert raw[80 * i : 80 * i + 8] == b"DATE    "
    raw[80 * i : 80 * (i + 1)] = b" " * 80
    return bytes(raw)


def test_resumed_catalogue_equals_an_uninterrupted_one(images, tmp_path, monkeypatch):
    d, imgs = images
    args = dict(stars=[d / "stars.fits"], config=CFG, prior=PRIOR, progress=False)
    ref = tmp_path / "ref.fits"
    measure(imgs, output=ref, **args)
    out = tmp_path / "run.fits"
    with monkeypatch.context() as mp:
        _killed_at(mp, "a.fits")  # after the first image
        with pytest.raises(KeyboardInterrupt):
            measure(imgs, output=out, **args)
    parts = sorted((tmp_path / "run.fits.parts").glob("*.fits"))
    assert [p.name.split("_", 1)[1].startswith("no_stars") for p in parts] == [True]
    cat = measure(imgs, output=out, **args)
    assert not (tmp_path / "run.fits.parts").exists()
    note = cat.meta["psfs"]["note"][0]
    assert len(note) > 68 and "no_stars_of_its_own_with_a_long_name.fits" in note
    diff = fits.FITSDiff(str(ref), str(out), ignore_keywords=["DATE"])
    assert diff.identical, diff.report()
    assert _date_masked(ref) == _date_masked(out)
