"""A filter parameter written once: its default, unit, meaning and the range the family search
draws it from, in one dataclass field (``knob``); the families' knobs, defaults and search spaces
(:mod:`tcn_ahrs.estimators.families`) are read from the filters' parameter dataclasses
(:class:`~tcn_ahrs.kernels.backbone_layout.BackboneParams`, ``ECFParams``, ``MahonyParams``,
``MadgwickParams``), never restated.

``search``: ``(low, high)`` — log-uniform in the search; a list — one of its values; None — not
searched (a physical constant or a switch left at its default).
"""
from __future__ import annotations

from dataclasses import field, fields
from typing import Any, Dict, Optional


def knob(default: Any, unit: str, meaning: str, search: Optional[object] = None):
    """A dataclass field with its ``unit``, ``meaning`` and ``search`` range in its metadata."""
    return field(default=default, metadata={"unit": unit, "meaning": meaning, "search": search})


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
