"""The run's checks and its data-driven starting points: ``train:`` values against their schema
(:class:`tcn_ahrs.config.TrainConfig`), the model's axes, the gyro at rest, and the residual
model's inference knobs chosen after training."""
from __future__ import annotations

import difflib
from pathlib import Path
from typing import Any, Dict, Mapping, Optional

import torch

from ..checkpoint import load_checkpoint
from ..config import AugmentConfig, NoiseConfig, TrainConfig, check_keys, keys
from ..config.train import numeric_ranges
from ..model.ahrs import LearnedAHRS
from ..validate import check_number

# Derived from the schemas (tcn_ahrs/config/train.py): the keys a section may have, and
# (type, lower bound, lower bound included, upper bound exclusive) of its numeric keys
TRAIN_KEYS = keys(TrainConfig)
AUGMENT_KEYS = keys(AugmentConfig)
NOISE_KEYS = keys(NoiseConfig)
TRAIN_VALUES = numeric_ranges(TrainConfig)
AUGMENT_VALUES = numeric_ranges(AugmentConfig)
NOISE_VALUES = numeric_ranges(NoiseConfig)
MONITORS = ("val/loss", "val/aae_deg")


def check_train_values(train: Mapping) -> None:
    """Every numeric ``train.*`` value in its range, and the noise levels >= 0 (key named)."""
    for k, (kind, low, low_ok, high) in TRAIN_VALUES.items():
        if train.get(k) is not None:
            check_number(train.get(k), f"train.{k}", kind, low, low_ok, high)
    noise = train.get("noise") or {}
    check_keys(noise, NoiseConfig, "train.noise")
    for k, v in noise.items():
        check_number(v, f"train.noise.{k}", float, 0.0)
    aug = train.get("augment") or {}
    check_keys(aug, AugmentConfig, "train.augment")
    for k, (kind, low, low_ok, high) in AUGMENT_VALUES.items():
        if aug.get(k) is not None:
            check_number(aug.get(k), f"train.augment.{k}", kind, low, low_ok, high)
    span = aug.get("rate_hz")
    if span is not None:
        span = list(span)
        if len(span) != 2 or not (0.0 < float(span[0]) <= float(span[1])):
            raise ValueError(f"train.augment.rate_hz: expected [low, high] Hz with 0 < low <= high, got {span}")
    if str(train.get("adopt_on", "recordings")) not in ("recordings", "parts"):
        raise ValueError(f"train.adopt_on: expected recordings or parts, got {train.get('adopt_on')!r}")
    if train.get("monitor") is not None and str(train.get("monitor")) not in MONITORS:
        near = difflib.get_close_matches(str(train.get("monitor")), MONITORS, n=1)
        raise ValueError(f"train.monitor: expected one of {list(MONITORS)} (the validation metrics logged), got "
                         f"{train.get('monitor')!r}" + (f" (did you mean {near[0]!r}?)" if near else ""))


def model_axes(cfg) -> int:
    """Model input axes: ``model.axes`` (default: ``data.axes``); a 9-axis model on 6-axis data is an error."""
    data_axes = int(cfg.data.get("axes", 9))
    axes = cfg.model.get("axes")
    axes = data_axes if axes is None else int(axes)
    if axes == 9 and data_axes == 6:
        raise ValueError(f"model '{cfg.model.get('variant')}' needs 9 axes but data '{cfg.data.name}' is "
                         "6-axis (data.axes=6): choose a 6-axis model (model=ahrs6) or data.axes=9")
    return axes


def choose_knobs_into_checkpoint(ckpt_path: str, val_seqs, run_dir: Path,
                                 grid: Optional[Mapping[str, Any]] = None, rule: str = "both") -> Dict[str, float]:
    """Choose the residual model's inference knobs (:func:`tcn_ahrs.tuning.knobs.select_residual_knobs`,
    over ``grid``, default its own) on ``val_seqs`` and write them into the checkpoint's model
    config (atomically; the checkpoint then IS the selected model); the table goes to
    ``run_dir/knobs.json``."""
    import json

    from ..checkpoint import atomic_save, model_from_checkpoint
    from ..tuning.knobs import select_residual_knobs

    model = model_from_checkpoint(ckpt_path)
    chosen, table = select_residual_knobs(model, val_seqs, grid=grid, rule=rule)
    ck = load_checkpoint(ckpt_path)
    for cfg in (ck["tcn_ahrs"]["model"], (ck.get("hyper_parameters") or {}).get("model_cfg")):
        if cfg is not None:
            cfg["residual"] = {**dict(cfg.get("residual") or {}), **chosen}
    atomic_save(ck, ckpt_path)
    (run_dir / "knobs.json").write_text(json.dumps({"chosen": chosen, "on": [s.name for s in val_seqs],
                                                     "table": table}, indent=1))
    ref = next(r for r in table if r["reference"])
    row = next(r for r in table if r["knobs"] == chosen)
    print(f"inference knobs chosen on the {len(val_seqs)} validation recordings: {chosen} (mean AAE "
          f"{row['aae_deg']:.2f} / inclination {row['inclination_deg']:.2f} deg; the tuned backbone "
          f"alone {ref['aae_deg']:.2f} / {ref['inclination_deg']:.2f}); table in {run_dir / 'knobs.json'}")
    return chosen


def rest_gyro_mean(model: LearnedAHRS, store) -> Optional[torch.Tensor]:
    """Mean raw gyro reading (3,) over the samples the model's rest detector flags in the
    training recordings (None when none is at rest)."""
    total, count = torch.zeros(3, dtype=torch.float64), 0
    for i in range(len(store.lengths)):
        s = store.sequence(i)
        rest = model.closed.rest(s["imu"][..., 0:3], s["imu"][..., 3:6], s["dt"])[0] > 0.5
        if bool(rest.any()):
            total += s["imu"][0, rest, 0:3].double().sum(0)
            count += int(rest.sum())
    return None if count == 0 else (total / count).float()
