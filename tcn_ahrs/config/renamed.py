"""Old names of experiment configs and shipped models, kept working (README, "Renamed").

Until 2026-12 an experiment named only its data (``experiment=broad9`` was the paper's open loop,
``broad9_res`` the residual, ``broad9_cl`` the closed loop) and a shipped model only its device
(``checkpoints/euroc6.ckpt`` a closed loop, ``tumvi6.json`` a tuned ECF): the names did not say
what a file is. Now both name the family: ``<data>_open_loop``, ``_closed_loop``, ``_residual``
(``_ecf`` for a tuned ECF). An old name still works and is said once, with the new one.
"""
from __future__ import annotations

from typing import Dict, List, Tuple

# conf/experiment/<old>.yaml -> <new>.yaml
EXPERIMENTS: Dict[str, str] = {
    **{f"{d}": f"{d}_open_loop" for d in ("euroc6", "tumvi6", "oxiod9", "broad9")},
    **{f"{d}_cpu": f"{d}_open_loop_cpu" for d in ("euroc6", "tumvi6", "broad6", "broad9")},
    **{f"{d}_cl": f"{d}_closed_loop" for d in ("euroc6", "tumvi6", "oxiod9", "broad6", "broad9")},
    **{f"{d}_res": f"{d}_residual" for d in ("euroc6", "tumvi6", "oxiod9", "broad6", "broad9", "general6",
                                             "general9")},
    "euroc6_small": "euroc6_residual_small",
}

# checkpoints/<old>.ckpt or .json -> <new> (same suffix)
CHECKPOINTS: Dict[str, str] = {
    "euroc6": "euroc6_closed_loop", "euroc6_small": "euroc6_residual_small",
    "broad6": "broad6_residual", "broad9": "broad9_residual",
    "general6": "general6_residual", "general9": "general9_residual",
    "tumvi6": "tumvi6_ecf", "oxiod9": "oxiod9_ecf",
}


def experiment_overrides(args: List[str]) -> Tuple[List[str], List[str]]:
    """Command-line overrides with an old ``experiment=`` name replaced by its new one ->
    (overrides, notes to print)."""
    out, notes = [], []
    for a in args:
        key, eq, value = a.partition("=")
        if eq and key.lstrip("+~") == "experiment" and value in EXPERIMENTS:
            notes.append(f"note: experiment={value} is now experiment={EXPERIMENTS[value]} (README, \"Renamed\")")
            a = f"{key}={EXPERIMENTS[value]}"
        out.append(a)
    return out, notes


def experiment_name(name: str) -> str:
    """An experiment's current name (a recipe recorded under its old name reads as the new)."""
    return EXPERIMENTS.get(name, name)
