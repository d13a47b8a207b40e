"""The configuration: sections generated from the declarative tables, one validator
driven by them, the flat shortcut, YAML, the presets and the generated reference."""

from __future__ import annotations

import dataclasses
import math
import pickle
import re
import sys
from pathlib import Path

import pytest
import yaml

from pylensfit import Config, ConfigError
from pylensfit.config import PARAMS, PRESETS, SECTION_CLASSES, SECTIONS, Grid, Models, Stamps
from pylensfit.config.fields import in_bounds, parse_bounds
from pylensfit.config.validate import RULES

ALL = [(s.name, p) for s in SECTIONS for p in s.params]
IDS = [p.name for _, p in ALL]


def _outside(p):
    """A value of ``p``'s type outside its range, or None if its range is unbounded."""
    lo, hi, lo_open, hi_open = parse_bounds(p.bounds)
    if lo > -math.inf:
        v = lo if lo_open else lo - 1
    elif hi < math.inf:
        v = hi if hi_open else hi + 1
    else:
        return math.inf if hi_open else None
    return int(v) if p.type is int else float(v)


def test_every_parameter_is_declared_once_with_a_doc_and_a_valid_default():
    names = [p.name for _, p in ALL]
    assert len(names) == len(set(names)) == len(Config.describe()) == len(PARAMS)
    for _sec, p in ALL:
        assert p.doc.endswith(".") and len(p.doc) < 400, p.name
        assert not (p.choices and p.bounds), p.name
        if p.bounds:
            parse_bounds(p.bounds)
        assert not any(name == p.name for name in SECTION_CLASSES)
    Config()  # every default valid, and so every section's


@pytest.mark.parametrize(("section", "p"), ALL, ids=IDS)
def test_each_section_checks_its_fields_from_the_table(section, p):
    cls = SECTION_CLASSES[section]
    wrong = 3 if p.type is str else "x" if p.type is not bool else "perhaps"
    with pytest.raises(ConfigError, match=rf"'{p.name}' must be {re.escape(p.type_name)}"):
        Config(**{p.name: wrong})
    if p.type is not str:  # the section itself, made directly, checks the type too
        with pytest.raises(ConfigError, match=p.name):
            cls(**{p.name: "x"})
    if p.choices:
        with pytest.raises(ConfigError, match=rf"{p.name} must be one of "
                                              rf"{re.escape(p.allowed)}, got 'nope'"):
            cls(**{p.name: "nope"})
    if p.bounds:
        bad = _outside(p)
        if bad is not None:
            value = (bad,) if p.type is tuple else bad
            with pytest.raises(ConfigError, match=rf"{p.name} must (be|hold values) in "
                                                  rf"{re.escape(p.bounds)}"):
                cls(**{p.name: value})


def test_the_cross_field_rules_are_named_and_raise():
    assert {r.__name__ for rules in RULES.values() for r in rules} >= {
        "tiers_are_multiples", "sizes_ordered", "spline_prior_is_direct"}
    for bad, said in (({"r_min": 10.0}, "r_min < r_max"),
                      ({"prior_form": "spline", "prior_method": "em"}, "prior_method 'direct'"),
                      ({"amplitude_prior_min": 5.0, "amplitude_prior_max": 1.0},
                       "amplitude_prior_min"),
                      ({"bulge_size_ratio2": 0.6}, "must differ"),
                      ({"sersic_ladder": (2.0, 2.0)}, "distinct")):  # fmt: skip
        with pytest.raises(ConfigError, match=re.escape(said)):
            Config(**bad)
    with pytest.raises(ConfigError, match="multiple of stamp_size"):
        Stamps(max_stamp_size=48)  # a section made directly is not normalised
    with pytest.raises(ConfigError, match="needs model 'bulge\\+disc'"):
        Models(model="exponential")


def test_the_two_normalisations_are_those_documented():
    assert Config(stamp_size=48).max_stamp_size == 0  # 64 rounds down to 48: one stamp
    assert Config(max_stamp_size=100).max_stamp_size == 96
    assert "Rounded down" in PARAMS["max_stamp_size"].doc
    one = Config(model="exponential", n_bulge_fractions=3, sersic_ladder=(0.5, 2.0),
                 bulge_size_ratio2=1.0)  # fmt: skip
    assert (one.n_bulge_fractions, one.bulge_size_ratio2, one.sersic_ladder) == (1, 0.0, ())
    assert Config(sersic_ladder="0.5, 2, 4").sersic_ladder == (0.5, 2.0, 4.0)
    assert Config(sersic_ladder=[0.5, 2]).models.sersic_ladder == (0.5, 2.0)


@pytest.mark.parametrize("cfg", [Config(), Config.paper(), Config(e_step=0.05, r_max=8,
                                                                      saturation=6e4)])
def test_flat_and_sectioned_access_agree_for_every_field(cfg):
    for section, p in ALL:
        assert getattr(cfg, p.name) == getattr(getattr(cfg, section), p.name), p.name
    assert isinstance(cfg.r_max, float) and isinstance(cfg.stamp_size, int)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.e_step = 0.2  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.grid.e_step = 0.2  # type: ignore[misc]


def test_sections_given_whole_and_replace():
    cfg = Config(grid=Grid(e_step=0.05), models={"n_bulge_fractions": 5})
    assert cfg.e_step == 0.05 and cfg.n_bulge_fractions == 5
    assert Config(grid={"e_step": 0.2}, e_step=0.05).e_step == 0.05  # flat keywords win
    assert cfg.replace(grid=Grid()).e_step == 0.1
    assert cfg.replace(r_max=8.0).grid == Grid(e_step=0.05, r_max=8.0)
    assert cfg.replace(r_max=8.0) == Config(e_step=0.05, r_max=8.0, n_bulge_fractions=5)
    with pytest.raises(ConfigError, match=r"'e_stp' \(did you mean 'e_step'.*in section 'grid'"):
        Config(grid={"e_stp": 0.1})
    with pytest.raises(ConfigError, match="did you mean 'r_max'"):
        Config(r_mx=3.0)
    assert pickle.loads(pickle.dumps(cfg)) == cfg and hash(cfg) == hash(cfg.replace())
    assert repr(Config(e_step=0.05)) == "Config(e_step=0.05)"


def test_yaml_round_trip_and_the_flat_files_written_before(tmp_path):
    cfg = Config.paper(e_step=0.05, sersic_ladder=(), saturation=6e4)
    cfg.to_yaml(tmp_path / "c.yaml")
    data = yaml.safe_load((tmp_path / "c.yaml").read_text())
    assert list(data) == list(Config.describe())  # flat, section by section
    assert Config.from_yaml(tmp_path / "c.yaml") == cfg
    lad = Config(sersic_ladder=(0.5, 2.0, 4.0))
    lad.to_yaml(tmp_path / "l.yaml")
    assert Config.from_yaml(tmp_path / "l.yaml") == lad
    # a flat file of today's keys, in the order the single dataclass wrote them
    old = tmp_path / "old.yaml"
    old.write_text("stamp_size: 32\nmax_stamp_size: 64\ne_step: 0.05\nmodel: exponential\n"
                   "n_bulge_fractions: 3\nsersic_ladder: []\nsize_prior: flat\n"
                   "amplitude_prior_max: .inf\nsaturation: null\ntruncate_models: yes\n"
                   "dtype: float64\nmin_snr: 7\n")  # fmt: skip
    got = Config.from_yaml(old)
    assert (got.e_step, got.model, got.n_bulge_fractions, got.dtype, got.min_snr) == (
        0.05, "exponential", 1, "float64", 7.0)
    # a file of sections loads as well
    (tmp_path / "s.yaml").write_text("grid:\n  e_step: 0.05\npriors:\n  size_prior: flat\n")
    assert Config.from_yaml(tmp_path / "s.yaml") == Config(e_step=0.05, size_prior="flat")
    (tmp_path / "bad.yaml").write_text("grid:\n  e_step: 0.7\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: e_step must be in \(0, 0\.5\]"):
        Config.from_yaml(tmp_path / "bad.yaml")


def test_presets():
    assert set(PRESETS) == {"default", "paper"}
    assert Config.preset("default") == Config()
    paper = Config.paper()
    assert paper == Config.preset("paper") == Config.from_dict({"preset": "paper"})
    for key, value in PRESETS["paper"][0].items():
        assert getattr(paper, key) == value, key
    assert (paper.model, paper.largest_stamp, len(paper.bulge_runs)) == ("devaucouleurs", 32, 1)
    assert Config.paper(e_step=0.05).e_step == 0.05
    with pytest.raises(ConfigError, match="unknown preset"):
        Config.preset("nope")
    with pytest.raises(ConfigError, match="unknown preset"):
        Config.from_dict({"preset": "nope"})


def test_derived_properties():
    cfg = Config(e_step=0.1, e_refine=2)
    assert cfg.output_e_step == 0.05 and cfg.output_refine == 2 and cfg.largest_stamp == 64
    assert Config(max_stamp_size=0).largest_stamp == 32
    assert len(Config().bulge_runs) == 3 and Config().run_labels == ["0", "0.5", "1"]


def test_bounds():
    assert in_bounds(0.5, "(0, 0.5]") and not in_bounds(0.0, "(0, 0.5]")
    assert in_bounds(math.inf, "[0, inf]") and not in_bounds(math.inf, "[0, inf)")
    assert not in_bounds(math.nan, "(-inf, inf)")
    with pytest.raises(ValueError):
        parse_bounds("0..1")


def test_the_generated_reference_lists_every_field_once():
    sys.path.insert(0, str(Path(__file__).parents[1] / "docs" / "_ext"))
    plf_docs = pytest.importorskip("plf_docs")
    names = []
    for section in SECTIONS:
        rows = plf_docs.config_rows(section)
        names += [row[0][0].astext() for row in rows]
        for row, p in zip(rows, section.params, strict=True):
            assert row[1][0].astext() == p.type_name and row[2][0].astext() == repr(p.default)
    assert sorted(names) == sorted(Config.describe()) and len(names) == len(set(names))
