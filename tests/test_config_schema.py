"""Every YAML under conf/ against its schema (tcn_ahrs/config/), both ways.

What is checked, per file kind:

* primary configs (train, crossval, evaluate, compare, benchmark, export, inspect_data,
  reproduce), composed with their defaults: no key the schema lacks (unknown), every schema field
  present (missing), every value of the declared type (``OmegaConf.structured`` merge of the
  resolved values), and each value equal to the schema's default — the YAML and the Python
  defaults are one set of numbers. Nested sections (``train.augment``, ``benchmark.lodo`` ...)
  the same way, recursively.
* ``model/*``: each option composed with train.yaml: keys both ways (``residual`` only where the
  option has it), types; ``model=ahrs`` also value by value against ``ModelConfig()``, and
  ``model=paper`` against it with :data:`~tcn_ahrs.config.model.PAPER_MODEL` on top.
* ``experiment/*`` and ``schedule/*`` (partial overrides by design): composed, then ``train:``/``eval:``/the top level
  and the model checked for unknown keys and types (missing keys cannot happen after the merge).
* ``paper/*``: keys both ways, types and every default against its class in
  :mod:`tcn_ahrs.config.papers`.
* ``data/*`` — looser, honestly: each dataset has keys of its own. A data config is checked
  against the schema of its kind (:func:`~tcn_ahrs.config.data.data_schema`: the recording-list
  datasets share one, rosbag/simulated/general* have their own): no unknown key, every field
  present, types. Its *values* (recording names, roots, splits) are not compared with anything
  (they are the data, not defaults). A multi-dataset config's ``parts`` are each checked as their
  own dataset.
* ``trainer/*``: keys are ``pytorch_lightning.Trainer`` arguments (its signature is the schema).
* ``callbacks/*``, ``logger/*``: every entry has an importable ``_target_`` whose signature takes
  the entry's arguments; the default options are instantiated (test_train runs them end to end).

Composition: every primary config x every option of each of its groups composes with Hydra's
compose API (``initialize_config_dir``), and every YAML file under conf/ is covered by one of the
checks above (a new file without a check fails :func:`test_every_yaml_file_is_checked`).
"""
from __future__ import annotations

import dataclasses
import importlib
import inspect
from typing import Any, Dict

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from tcn_ahrs.config import (CONF_DIR, BenchmarkConfig, CompareConfig, CrossvalConfig, EvaluateConfig, SearchConfig,
                             ExportConfig, InspectDataConfig, ModelConfig, ReproduceConfig, TrainScriptConfig,
                             check_types, defaults, keys)
from tcn_ahrs.config.data import data_schema
from tcn_ahrs.config.model import MODEL_OPTIONAL, PAPER_MODEL
from tcn_ahrs.config.papers import PAPERS
from tcn_ahrs.config.train import TRAIN_GROUPS

# primary config -> (schema of its top level, its config groups, keys that are groups/sections of others)
PRIMARY = {
    "train": (TrainScriptConfig, ("data", "model", "trainer", "callbacks", "logger", "experiment")),
    "crossval": (CrossvalConfig, ("data", "model", "trainer", "callbacks", "logger", "experiment")),
    "search": (SearchConfig, ("data", "model", "trainer", "callbacks", "logger", "experiment")),
    "evaluate": (EvaluateConfig, ("data",)),
    "compare": (CompareConfig, ("data",)),
    "benchmark": (BenchmarkConfig, ("data",)),
    "export": (ExportConfig, ()),
    "inspect_data": (InspectDataConfig, ("data",)),
    "reproduce": (ReproduceConfig, ("paper",)),
}
NOT_OWN = set(TRAIN_GROUPS) | {"paper"}  # checked by their own schemas below


def _compose(name, overrides=()):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(name, overrides=list(overrides))
    return OmegaConf.to_container(cfg, resolve=True)


def _options(group):
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


def _fields(schema) -> Dict[str, dataclasses.Field]:
    return {f.name: f for f in dataclasses.fields(schema)}


def _nested_schema(f: dataclasses.Field):
    """The dataclass of a field that is a section (None for a leaf)."""
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        v = f.default_factory()  # type: ignore[misc]
        if dataclasses.is_dataclass(v):
            return type(v)
    return None


def _both_ways(section: Dict[str, Any], schema, where: str, optional=frozenset(), values: bool = False) -> None:
    """Unknown keys, missing keys, types; with ``values`` each value equal to the default."""
    unknown = set(section) - keys(schema)
    assert not unknown, f"{where}: keys the schema {schema.__name__} lacks: {sorted(unknown)}"
    missing = keys(schema) - set(section) - set(optional)
    assert not missing, f"{where}: schema fields {schema.__name__} the YAML lacks: {sorted(missing)}"
    check_types(section, schema, where)
    want = defaults(schema)
    for name, f in _fields(schema).items():
        if name not in section:
            continue
        sub = _nested_schema(f)
        if sub is not None and isinstance(section[name], dict):
            _both_ways(section[name], sub, f"{where}.{name}", values=values)
        elif values:
            assert section[name] == want[name], (f"{where}.{name}: YAML {section[name]!r} != the schema's default "
                                                  f"{want[name]!r} (one default, written in tcn_ahrs/config/)")


def _no_unknown(section: Dict[str, Any], schema, where: str) -> None:
    """Unknown keys (recursively) and types only: partial YAML (experiments)."""
    unknown = set(section) - keys(schema)
    assert not unknown, f"{where}: keys the schema {schema.__name__} lacks: {sorted(unknown)}"
    check_types(section, schema, where)
    for name, f in _fields(schema).items():
        sub = _nested_schema(f)
        if sub is not None and isinstance(section.get(name), dict):
            _no_unknown(section[name], sub, f"{where}.{name}")


def _check_model(model: Dict[str, Any], where: str) -> None:
    optional = MODEL_OPTIONAL - ({"residual"} if model.get("loop") == "backbone" else set())
    _both_ways(model, ModelConfig, where, optional=optional)
    if model.get("loop") == "backbone":
        assert model.get("residual") is not None, f"{where}: loop backbone without a residual section"


def _check_data(data: Dict[str, Any], where: str) -> None:
    schema = data_schema(data["name"])
    _both_ways(data, schema, f"{where} ({schema.__name__})")
    for part, sub in (data.get("parts") or {}).items():
        _check_data(sub, f"{where}.parts.{part}")


def _check_trainer(trainer: Dict[str, Any], where: str) -> None:
    import pytorch_lightning as pl

    params = set(inspect.signature(pl.Trainer.__init__).parameters) - {"self"}
    unknown = set(trainer) - params
    assert not unknown, f"{where}: not pytorch_lightning.Trainer arguments: {sorted(unknown)}"


def _target(path: str):
    mod, _, name = path.rpartition(".")
    return getattr(importlib.import_module(mod), name)


def _check_targets(group: Dict[str, Any], where: str) -> None:
    assert group, f"{where}: empty"
    for key, spec in group.items():
        assert isinstance(spec, dict) and "_target_" in spec, f"{where}.{key}: no _target_"
        fn = _target(spec["_target_"])
        sig = inspect.signature(fn)
        takes_any = any(p.kind is p.VAR_KEYWORD for p in sig.parameters.values())
        args = set(spec) - {"_target_", "_partial_", "_recursive_", "_convert_", "_args_"}
        if not takes_any:
            unknown = args - set(sig.parameters)
            assert not unknown, f"{where}.{key}: {spec['_target_']} takes no {sorted(unknown)}"


def _check_primary(name: str, cfg: Dict[str, Any], values: bool) -> None:
    schema, _ = PRIMARY[name]
    own = {k: v for k, v in cfg.items() if k not in NOT_OWN}
    _both_ways(own, schema, f"{name}.yaml", values=values)
    if "model" in cfg:
        _check_model(cfg["model"], f"{name}.yaml model")
    if "data" in cfg:
        _check_data(cfg["data"], f"{name}.yaml data")
    if "trainer" in cfg:
        _check_trainer(cfg["trainer"], f"{name}.yaml trainer")
    for g in ("callbacks", "logger"):
        if g in cfg:
            _check_targets(cfg[g], f"{name}.yaml {g}")
    if "paper" in cfg:
        p = cfg["paper"]
        _both_ways(p, PAPERS[p["name"]], f"paper/{p['name']}.yaml", values=True)


# ------------------------------------------------------------------------------ the defaults
# a primary config's own values that are not the schema's defaults, and why
DATA_OVERRIDES = {"evaluate", "compare", "benchmark", "inspect_data"}  # set data.split only


@pytest.mark.parametrize("name", sorted(PRIMARY))
def test_primary_config_matches_its_schema_and_defaults(name):
    _check_primary(name, _compose(name), values=True)


def test_default_model_is_the_schema_default_and_paper_is_paper_model():
    want = defaults(ModelConfig)
    for option, over in (("ahrs", {}), ("paper", PAPER_MODEL)):
        model = _compose("train", [f"model={option}"])["model"]
        exp = {**want, **over}
        for k, v in model.items():
            if k in ("variant", "axes"):  # follow data.axes (interpolations)
                continue
            assert v == exp[k], f"model={option}: {k} = {v!r} in YAML, {exp[k]!r} in tcn_ahrs/config/model.py"


# ------------------------------------------------------------------- every group option composes
def _cases():
    for name, (_, groups) in PRIMARY.items():
        for g in groups:
            for opt in _options(g):
                yield name, g, opt


@pytest.mark.parametrize("name,group,option", list(_cases()))
def test_every_group_option_composes_and_matches_its_schema(name, group, option):
    cfg = _compose(name, [f"{group}={option}"])
    if group == "experiment":  # partial overrides: unknown keys and types only
        schema, _ = PRIMARY[name]
        _no_unknown({k: v for k, v in cfg.items() if k not in NOT_OWN}, schema, f"experiment/{option}.yaml")
        _check_model(cfg["model"], f"experiment/{option}.yaml model")
        _check_data(cfg["data"], f"experiment/{option}.yaml data")
    else:
        _check_primary(name, cfg, values=False)


@pytest.mark.parametrize("option", _options("schedule"))
def test_every_schedule_composes_and_matches_the_train_schema(option):
    """schedule/* (an experiment's training schedule, used by experiments through their defaults
    list): partial overrides like the experiments: unknown keys and types."""
    for name in ("train", "crossval"):
        cfg = _compose(name, [f"+schedule={option}"])
        schema, _ = PRIMARY[name]
        _no_unknown({k: v for k, v in cfg.items() if k not in NOT_OWN}, schema, f"schedule/{option}.yaml")
        _check_model(cfg["model"], f"schedule/{option}.yaml model")


def test_every_yaml_file_is_checked():
    groups = {g for _, gs in PRIMARY.values() for g in gs} | {"schedule"}
    covered = {f"{n}.yaml" for n in PRIMARY} | {f"{g}/{o}.yaml" for g in groups for o in _options(g)}
    covered |= {f"search/learn/{r}.yaml" for r in _learned_recipes_checked()}
    every = {p.relative_to(CONF_DIR).as_posix() for p in CONF_DIR.rglob("*.yaml")}
    assert every <= covered, f"YAML under conf/ no schema check covers: {sorted(every - covered)}"


def _learned_recipes_checked():
    """Every recipe of conf/search/learn/ read through its schema (LearnRecipe) and its overrides
    composed with conf/train.yaml (9 and 6 axes): a misspelt key fails here, not in a search."""
    from tcn_ahrs.checkpoints import SHIPPED_DIR
    from tcn_ahrs.experiments.lodo import compose_train
    from tcn_ahrs.experiments.search.learn import load_recipes

    recipes = load_recipes()
    for recipe, (_, overrides) in recipes.items():
        for axes, data in ((9, "broad"), (6, "euroc")):
            compose_train([o.format(axes=axes, shipped=SHIPPED_DIR) for o in overrides] + [f"data={data}"])
    return recipes


def test_a_learned_recipe_with_a_misspelt_key_is_refused(tmp_path, monkeypatch):
    from tcn_ahrs.experiments.search import learn

    (tmp_path / "search" / "learn").mkdir(parents=True)
    (tmp_path / "search" / "learn" / "x.yaml").write_text("name: x\noverides: [train.epochs=1]\n")
    monkeypatch.setattr("tcn_ahrs.conf.CONF_DIR", tmp_path)
    with pytest.raises(ValueError, match=r"x.yaml: unknown key\(s\) \['overides'\]"):
        learn.load_recipes()


def test_paper_schemas_and_reproduce_modules_agree():
    from tcn_ahrs.reproduce import papers

    assert set(PAPERS) == set(_options("paper")) == set(papers())


# ------------------------------------------------------------------------- the checks do check
def test_schema_checks_catch_unknown_missing_and_wrong_types():
    from tcn_ahrs.config import TrainConfig, check_section

    train = _compose("train")["train"]
    with pytest.raises(AssertionError, match="lacks"):
        _both_ways({**train, "learning_rate": 0.1}, TrainConfig, "train")
    with pytest.raises(AssertionError, match="YAML lacks"):
        _both_ways({k: v for k, v in train.items() if k != "lr"}, TrainConfig, "train")
    with pytest.raises(ValueError, match="train.lr"):
        check_types({**train, "lr": "fast"}, TrainConfig, "train")
    with pytest.raises(ValueError, match="train.loss_js"):
        check_types({**train, "loss_js": 16}, TrainConfig, "train")
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['learning_rate'\]; expected a subset of"):
        check_section({**train, "learning_rate": 0.1}, TrainConfig, "train")
    with pytest.raises(AssertionError, match="default"):
        _both_ways({**train, "lr": 0.5}, TrainConfig, "train", values=True)


def test_derived_key_sets_are_the_schemas():
    from tcn_ahrs.experiments.compare import BENCHMARK_KEYS, COMPARE_KEYS
    from tcn_ahrs.config import AugmentConfig, ClosedLoopConfig, ResidualConfig, TCNConfig, TrainConfig
    from tcn_ahrs.config.data import GenericDeclarations
    from tcn_ahrs.datasets.generic import ATTR_KEYS
    from tcn_ahrs.evaluate.main import EVAL_KEYS
    from tcn_ahrs.model.ahrs import CLOSED_LOOP_KEYS, MODEL_KEYS, TCN_KEYS
    from tcn_ahrs.model.residual import RESIDUAL_KEYS
    from tcn_ahrs.training.run import AUGMENT_KEYS, TRAIN_KEYS

    assert TRAIN_KEYS == keys(TrainConfig) and AUGMENT_KEYS == keys(AugmentConfig)
    assert EVAL_KEYS == keys(EvaluateConfig)
    assert COMPARE_KEYS == keys(CompareConfig) and BENCHMARK_KEYS == keys(BenchmarkConfig)
    assert MODEL_KEYS == keys(ModelConfig) and CLOSED_LOOP_KEYS == keys(ClosedLoopConfig)
    assert TCN_KEYS == keys(TCNConfig) and RESIDUAL_KEYS == keys(ResidualConfig)
    assert set(ATTR_KEYS) == keys(GenericDeclarations)


def test_class_defaults_are_the_schema_defaults():
    """The Python classes take their defaults from the schemas (no second set of numbers)."""
    from tcn_ahrs.config import ClosedLoopConfig, TrainConfig
    from tcn_ahrs.model.ahrs import LearnedAHRS
    from tcn_ahrs.model.closed_loop import ClosedLoopFilter
    from tcn_ahrs.training.run import AHRSModule

    t = TrainConfig()
    sig = inspect.signature(AHRSModule.__init__).parameters
    for k in ("lr", "weight_decay", "epochs", "window", "huber_delta", "stream_chunks", "attitude_delta",
              "ema_decay", "supervision"):
        assert sig[k].default == getattr(t, k), k
    assert list(sig["loss_js"].default) == t.loss_js
    m = ModelConfig()
    sig = inspect.signature(LearnedAHRS.__init__).parameters
    for k in ("gyro_net", "acc_net", "mag_net", "gyro_input", "use_acc_term", "use_mag_term", "ecf",
              "preintegration", "init_gain", "loop", "trust"):
        assert sig[k].default == getattr(m, k), k
    cl = ClosedLoopConfig()
    sig = inspect.signature(ClosedLoopFilter.__init__).parameters
    for f in dataclasses.fields(ClosedLoopConfig):
        assert sig[f.name].default == getattr(cl, f.name), f.name
    model = LearnedAHRS(axes=9)
    assert model.loop == "closed" and model.calibration.gyro_error_net is not None


def test_train_main_checks_types_and_group_entries_before_any_work():
    """scripts/train.py's checks (tcn_ahrs.training.run.check_config): wrong types and misspelt
    callbacks/logger arguments are one-line ValueErrors naming the key (exit 2 in the scripts)."""
    from hydra import compose as _c

    from tcn_ahrs.training.run import check_config

    def cfg(*over):
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            return _c("train", overrides=list(over))

    check_config(cfg())
    with pytest.raises(ValueError, match=r"^train\.loss_js: .*got 16"):
        check_config(cfg("train.loss_js=16"))
    with pytest.raises(ValueError, match=r"^eval\.plots: "):
        check_config(cfg("eval.plots=maybe"))
    with pytest.raises(ValueError, match=r"^eval: unknown key\(s\) \['splt'\]"):
        check_config(cfg("+eval.splt=val"))
    with pytest.raises(ValueError, match=r"callbacks\.best: .*takes no argument\(s\) \['monitr'\]"):
        check_config(cfg("+callbacks.best.monitr=x"))
    with pytest.raises(ValueError, match=r"logger\.csv: _target_ 'no_such_module\.Logger' does not import"):
        check_config(cfg("logger.csv._target_=no_such_module.Logger"))
