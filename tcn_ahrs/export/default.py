"""The default of ``tcn-ahrs evaluate`` (no ``ckpt=``) as an exportable model: ``tcn-ahrs export
ckpt=default6`` / ``ckpt=default9`` (6 or 9 axes). It is the residual model with both networks off
(``gyro_clip`` 0, ``trust_weight`` 0: :func:`tcn_ahrs.export.c.runtime.live_networks`), so the
backbone alone with VQF's defaults and the causal device check
(:data:`tcn_ahrs.evaluate.main.DEFAULT_KNOBS`): the same kernel step that ``evaluate`` runs
(numba), compiled to C, and read as TorchScript. Its network weights are never read; they are
seeded so that two exports of the default are the same file."""
from __future__ import annotations

from pathlib import Path
from typing import Dict

import torch

DEFAULTS: Dict[str, int] = {"default6": 6, "default9": 9}
"""The names ``tcn-ahrs export ckpt=`` takes for the default, and their axes."""


def default_config(axes: int) -> Dict[str, object]:
    """The model config of the default for ``axes`` (a residual model whose networks are off)."""
    from ..evaluate.main import DEFAULT_KNOBS

    return {"variant": f"default{int(axes)}", "axes": int(axes), "loop": "backbone",
            "residual": {"gyro_clip": 0.0, "trust_weight": 0.0, "bias_prior": 0.0, "backbone": dict(DEFAULT_KNOBS)}}


def default_model(axes: int):
    """The default as a :class:`~tcn_ahrs.model.ahrs.LearnedAHRS` (eval mode)."""
    from ..model.ahrs import LearnedAHRS

    with torch.random.fork_rng():
        torch.manual_seed(0)
        return LearnedAHRS.from_config(default_config(axes)).eval()


def write_default_checkpoint(name: str, folder) -> Path:
    """``<folder>/<name>.ckpt``: the default (``name`` in :data:`DEFAULTS`) as a checkpoint the
    exporters read (atomic)."""
    from ..checkpoint import atomic_save, layout_meta

    axes = DEFAULTS[name]
    model = default_model(axes)
    path = Path(folder) / f"{name}.ckpt"
    atomic_save({"state_dict": {f"model.{k}": v for k, v in model.state_dict().items()},
                 "tcn_ahrs": layout_meta(default_config(axes), axes, "none (the default: no training)")}, path)
    return path
