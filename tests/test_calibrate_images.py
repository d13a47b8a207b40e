"""Calibrate once on a sample of the images, measure every image in one pass: the
recipe driven pass by pass (:class:`pylensfit.calibration.Recipe`), the sample's draw,
:func:`pylensfit.calibrate_images`, ``measure(priors=...)`` and ``pylensfit calibrate``."""

import numpy as np
import pytest

import pylensfit as plf
import pylensfit.images.passes as passes
from pylensfit.calibration import CalibrationSample, Recipe, run_recipe
from pylensfit.cli import main
from pylensfit.images.sample import draw_sample
from pylensfit_validation.simulate import FieldSpec, simulate_field, write_field

CFG = plf.Config.paper(model="exponential", r_max=6.0, r_step=0.3)


def test_the_sample_is_whole_images_drawn_with_the_seed():
    counts = np.array([40, 10, 30, 20, 50])
    assert draw_sample(counts, 0, 1).tolist() == [0, 1, 2, 3, 4]  # 0: every image
    assert draw_sample(counts, 150, 1).tolist() == [0, 1, 2, 3, 4]  # all reach no more
    a = draw_sample(counts, 60, 7)
    assert a.tolist() == draw_sample(counts, 60, 7).tolist()  # the seed draws it again
    assert np.all(np.diff(a) > 0) and counts[a].sum() >= 60
    order = np.random.default_rng(7).permutation(counts.size)
    n = int(np.searchsorted(np.cumsum(counts[order]), 60)) + 1
    assert a.tolist() == sorted(order[:n].tolist())
    draws = {tuple(draw_sample(counts, 60, s)) for s in range(20)}
    assert len(draws) > 1  # another seed, another sample


def _sample(n: int = 400, seed: int = 1) -> CalibrationSample:
    flux = 100.0 * (1.0 + np.random.default_rng(seed).pareto(1.5, n))
    return CalibrationSample(egrid=np.zeros((4, 2)), lnL=np.zeros((n, 4)), flux=flux,
                             flux_err=flux / 20.0, snr=np.full(n, 20.0), dx=np.zeros(n),
                             dy=np.zeros(n), group=np.zeros(n, int))  # fmt: skip


def test_the_recipe_asks_for_its_passes_and_is_fed_them():
    """The caller drives the recipe: each pass it asks for, fitted and fed back, until it
    asks for none; the priors are those of :func:`run_recipe` given the same passes."""
    cfg = plf.Config(size_prior="flat", bulge_prior="uniform", estimate_position_prior=False)
    recipe = Recipe(cfg, prior=plf.Prior())
    with pytest.raises(RuntimeError, match="not fitted yet"):
        recipe.priors  # noqa: B018
    asked = []
    while recipe.next_pass is not None:
        step = recipe.next_pass
        asked.append(step)
        assert step.configs[0].amplitude_prior == "flux" and step.size_priors == (None,)
        recipe.feed(_sample())
    # the ellipticity prior given and no other prior but the flux's to estimate: the
    # flux prior's power and limits from the one pass, with no pass under them
    assert [s.label for s in asked] == ["calibration"]
    assert recipe.priors[0].flux_range is not None and recipe.priors[0].flux_power > 0
    with pytest.raises(RuntimeError, match="no pass left"):
        recipe.feed(_sample())
    again = run_recipe(lambda *a: _sample(), cfg, prior=plf.Prior())[0]
    assert recipe.priors[0].to_dict() == again.to_dict()


@pytest.fixture(scope="module")
def fields(tmp_path_factory):
    d = tmp_path_factory.mktemp("calfields")
    for name, seed, kw in (("a", 1, {}), ("b", 2, {}), ("stars", 3, {"star_fraction": 1.0})):
        spec = FieldSpec(size=512, g1=0.03, **kw)
        img, w, truth = simulate_field(spec, seed=seed)
        write_field(d / f"{name}.fits", img, w, spec, truth=truth)
    return d


def _counted(monkeypatch) -> list:
    """The images measured, as :func:`measure` hands them to the image task."""
    calls, task = [], passes.image_task

    def counting(t):
        calls.append(t.path)
        return task(t)

    monkeypatch.setattr(passes, "image_task", counting)
    return calls


def test_calibrate_once_then_measure_in_one_pass(fields, tmp_path, monkeypatch):
    """``calibrate_images`` on a sample of one image of two (drawn again by its seed),
    saved and read back identical; ``measure`` under them fits each image once and gives
    the catalogue of the same Priors object, and that of ``measure`` calibrating on the
    same sample itself."""
    images, stars = [fields / "a.fits", fields / "b.fits"], [fields / "stars.fits"]
    pri = plf.calibrate_images(images, stars=stars, config=CFG, sample=1, seed=4,
                               progress=False)  # fmt: skip
    assert len(pri.info["sample_images"]) == 1 and pri.info["images"] == 2
    assert pri.n_galaxies >= 50
    again = plf.calibrate_images(images, stars=stars, config=CFG, sample=1, seed=4,
                                 progress=False)  # fmt: skip
    assert again.to_dict() == pri.to_dict()
    path = tmp_path / "priors.json"
    pri.save(path)
    assert plf.Priors.load(path).to_dict() == pri.to_dict()
    calls = _counted(monkeypatch)
    from_file = plf.measure(images, stars=stars, config=CFG, priors=path, progress=False)
    assert sorted(calls) == sorted(map(str, images))  # one measuring pass
    given = plf.measure(images, stars=stars, config=CFG, priors=pri, progress=False)
    own = plf.measure(images, stars=stars, progress=False,
                      config=CFG.replace(calibration_sample=1, calibration_seed=4))
    assert own.meta["priors"].to_dict() == pri.to_dict()
    for cat in (given, own):
        for c in ("e1", "e2", "e1_var", "sens1", "weight", "flags"):
            np.testing.assert_array_equal(np.asarray(cat[c]), np.asarray(from_file[c]), c)


def test_cli_calibrate_and_measure_with_its_priors(fields, tmp_path, capsys):
    """``pylensfit calibrate`` writes the priors that ``measure --priors`` reads; a bad
    priors file or an existing output is one line naming it, and writes nothing."""
    cfg = tmp_path / "cfg.yaml"
    CFG.to_yaml(cfg)
    a, b, stars = (str(fields / f"{n}.fits") for n in ("a", "b", "stars"))
    out = tmp_path / "priors.json"
    assert main(["calibrate", a, b, "--stars", stars, "--config", str(cfg), "--sample", "0",
                 "-o", str(out), "-q"]) == 0  # fmt: skip
    said = capsys.readouterr().out
    assert said.startswith(f"{out}: Priors(") and "from 2 of 2 images" in said
    assert plf.Priors.load(out).info["sample_images"] == [a, b]
    capsys.readouterr()
    assert main(["calibrate", a, "--config", str(cfg), "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{out}: output exists" in err
    bad = tmp_path / "bad.json"
    bad.write_text('{"priors": [1, 2]}')
    cat = tmp_path / "cat.fits"
    assert main(["measure", a, "--priors", str(bad), "-o", str(cat)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{bad}: not a priors file" in err and not cat.exists()
    assert main(["calibrate", a, "--sample", "-1", "-o", str(tmp_path / "p.json")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "calibration_sample" in err
