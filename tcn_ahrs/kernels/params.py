"""A filter parameter written once: its default, unit, meaning and the range the family search
draws it from, in one dataclass field (``knob``); the families' knobs, defaults and search spaces
(:mod:`tcn_ahrs.estimators.families`) are read from the filters' parameter dataclasses
(:class:`~tcn_ahrs.kernels.backbone_layout.BackboneParams`, ``ECFParams``, ``MahonyParams``,
``MadgwickParams``), never restated.

``search``: ``(low, high)`` — log-uniform in the search; a list — one of its values; None — not
searched (a physical constant or a switch left at its default). ``grid``: the points the
estimator registry's tuning tries (``tcn-ahrs compare``'s tuned columns; the estimators'
``default_grid`` and ``tunable`` are read from it: :func:`tuning_grid`).
"""
from __future__ import annotations

from dataclasses import field, fields
from typing import Any, Dict, Optional


def knob(default: Any, unit: str, meaning: str, search: Optional[object] = None, grid: Optional[list] = None):
    """A dataclass field with its ``unit``, ``meaning``, ``search`` range and tuning ``grid`` in its metadata."""
    return field(default=default, metadata={"unit": unit, "meaning": meaning, "search": search, "grid": grid})


def tuning_grid(cls) -> Dict[str, list]:
    """{name: points} of the fields of ``cls`` the registry's tuning tries (in field order)."""
    return {f.name: list(f.metadata["grid"]) for f in fields(cls) if f.metadata.get("grid") is not None}


def searched(cls) -> Dict[str, object]:
    """{name: range} of the fields of ``cls`` the search draws (in field order)."""
    return {f.name: f.metadata["search"] for f in fields(cls) if f.metadata.get("search") is not None}


def suggest(trial, cls) -> Dict[str, float]:
    """One draw of every searched field of ``cls`` from an Optuna ``trial``."""
    out: Dict[str, float] = {}
    for name, rng in searched(cls).items():
        if isinstance(rng, list):
            out[name] = float(trial.suggest_categorical(name, rng))
        else:
            low, high = rng
            out[name] = trial.suggest_float(name, float(low), float(high), log=True)
    return out
