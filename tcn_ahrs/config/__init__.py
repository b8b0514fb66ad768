"""Typed schemas of every configuration: one dataclass per section, each field with its meaning,
unit and default written once (like VQF's parameter struct).

The YAML files under :data:`CONF_DIR` are what users run; these classes are what the code
checks them against and where the Python defaults come from (``AHRSModule``, ``LearnedAHRS``,
the speed benchmark). ``tests/test_config_schema.py`` checks both ways that every YAML and its
schema agree: the same keys, values of the declared types, and the same defaults.

The schemas are not registered in Hydra's ConfigStore: composition stays plain YAML, so the
scripts' override errors (``tcn_ahrs.cli.check_overrides``: exit 2 with the nearest key) are
unchanged; the entry points validate their sections with :func:`check_section`.

* :mod:`.model`   — ``model:`` (LearnedAHRS; closed loop, residual/backbone, TCN)
* :mod:`.train`   — ``train:`` (+ augment, noise), ``eval:``, train.yaml's top level, ``crossval:``
* :mod:`.scripts` — evaluate, compare, benchmark (transfer/lodo/finetune), export, inspect_data, reproduce
* :mod:`.speed`   — the speed benchmark's ``speed:`` section
* :mod:`.papers`  — each ``conf/paper/*.yaml``
* :mod:`.data`    — ``conf/data/*.yaml``: the common keys and each dataset's extras
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Dict, FrozenSet, Mapping

from ..conf import CONF_DIR  # the folder of the YAML configs, shipped inside the package (the one place naming it)


def conf_path(*parts: str) -> Path:
    """A path under :data:`CONF_DIR` (``conf_path("data", "broad.yaml")``)."""
    return CONF_DIR.joinpath(*parts)


def plain(cfg: Any) -> Any:
    """An OmegaConf node as plain Python containers (resolved); anything else unchanged."""
    from omegaconf import OmegaConf

    return OmegaConf.to_container(cfg, resolve=True) if OmegaConf.is_config(cfg) else cfg


def keys(schema) -> FrozenSet[str]:
    """The field names of a schema dataclass (the keys its YAML section may have)."""
    return frozenset(f.name for f in dataclasses.fields(schema))


def defaults(schema) -> Dict[str, Any]:
    """The schema's defaults as a plain dict (nested dataclasses as dicts)."""
    return dataclasses.asdict(schema())


def check_keys(section: Mapping, schema, where: str, extra=()) -> None:
    """``section``'s keys must be fields of ``schema`` (or in ``extra``): the message names the
    unknown keys and the expected set (the scripts' one-line error)."""
    allowed = set(keys(schema)) | set(extra)
    unknown = set(section) - allowed
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {sorted(unknown)}; expected a subset of {sorted(allowed)}")


def check_types(section: Mapping, schema, where: str) -> None:
    """``section`` merged into ``OmegaConf.structured(schema)``: a value of the wrong type (a
    string for a number, a scalar for a list) is a ``ValueError`` naming the key (``where``:
    the section's own dotted name, "" for a top level)."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    given = OmegaConf.create(plain(section))
    try:
        OmegaConf.merge(OmegaConf.structured(schema), given)
    except OmegaConfBaseException as e:
        key = getattr(e, "full_key", None) or ""
        msg = str(e).strip().splitlines()[0]
        name = ".".join(p for p in (where, key) if p)
        value = OmegaConf.select(given, key, default=None) if key else None
        raise ValueError(f"{name}: {msg}" + (f" (got {plain(value)!r})" if key else "")) from None


def check_section(section: Mapping, schema, where: str, extra=()) -> None:
    """Keys (:func:`check_keys`), then types (:func:`check_types`, ``extra`` keys excluded)."""
    check_keys(section, schema, where, extra)
    check_types({k: v for k, v in dict(section).items() if k not in set(extra)}, schema, where)


from .model import ClosedLoopConfig, ErrorScaleConfig, ModelConfig, ResidualConfig, TCNConfig  # noqa: E402
from .train import (AugmentConfig, CrossvalConfig, CrossvalSection, SearchConfig, SearchSection, EvalSection, NoiseConfig,  # noqa: E402
                    TrainConfig, TrainScriptConfig)
from .scripts import (BenchmarkConfig, CompareConfig, EvaluateConfig, ExportConfig,  # noqa: E402
                      InspectDataConfig, ReproduceConfig)

__all__ = ["CONF_DIR", "conf_path", "plain", "keys", "defaults", "check_keys", "check_types", "check_section",
           "ModelConfig", "TCNConfig", "ClosedLoopConfig", "ErrorScaleConfig", "ResidualConfig",
           "TrainConfig", "AugmentConfig", "NoiseConfig", "EvalSection", "TrainScriptConfig", "CrossvalSection",
           "SearchSection", "SearchConfig",
           "CrossvalConfig", "EvaluateConfig", "CompareConfig", "BenchmarkConfig", "ExportConfig",
           "InspectDataConfig", "ReproduceConfig"]
