"""Checkpoints: atomic writes, safe loading, and a layout check before use.

* :class:`AtomicCheckpointIO` — Lightning CheckpointIO that writes to a temporary file in the
  same folder and ``os.replace``-s it over the target, so a crash mid-write never leaves a
  truncated ``last.ckpt``/best checkpoint; loads with ``torch.load(weights_only=True)``.
* :func:`load_checkpoint` — ``weights_only=True`` loading with clear errors.
* Each checkpoint carries ``checkpoint["tcn_ahrs"] = {"model": <model config>, "layout":
  {"axes": 6|9, "channels": [...]}, "data": <data name>}`` and, trained by ``tcn-ahrs train``, the
  ``"recipe"`` {command, overrides} that made it (plain types only, so safe loading works);
  :func:`check_layout` refuses a checkpoint whose layout differs from the data's.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Sequence

import torch
from pytorch_lightning.plugins.io import TorchCheckpointIO

from .app import staged_files
from .config.model import ModelConfig
from .model.ahrs import LearnedAHRS

CHANNELS = {6: ["gyro_x", "gyro_y", "gyro_z", "acc_x", "acc_y", "acc_z"],
            9: ["gyro_x", "gyro_y", "gyro_z", "acc_x", "acc_y", "acc_z", "mag_x", "mag_y", "mag_z"]}


class CheckpointError(ValueError):
    """A checkpoint that cannot be used (missing, unreadable, or for another data layout)."""


def atomic_save(obj: Any, path) -> None:
    """``torch.save`` to ``path`` atomically (:func:`~tcn_ahrs.app.staged_files`, flushed to disk)."""
    def write(_, tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            torch.save(obj, fh)
            fh.flush()
            os.fsync(fh.fileno())

    staged_files({"checkpoint": Path(path)}, write)


def load_checkpoint(path, map_location="cpu") -> Dict[str, Any]:
    """Load a checkpoint dict with ``weights_only=True`` (no arbitrary code from the file)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint file not found")
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(4)
    if head[:2] != b"PK" and head[:1] != b"\x80":  # torch.save: a zip archive (or a legacy pickle)
        what = "an empty file" if size == 0 else f"a {size}-byte file starting with {head!r}"
        raise CheckpointError(f"{path}: not a checkpoint ({what}; expected a .ckpt written by "
                              "scripts/train.py, a zip archive or pickle from torch.save)")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # truncated archives, disallowed types
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"{path}: cannot load this checkpoint safely (torch.load with "
                              f"weights_only=True: {first}); is it complete and written by scripts/train.py?") from e


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning CheckpointIO with atomic saves and ``weights_only=True`` loads."""

    def save_checkpoint(self, checkpoint, path, storage_options=None) -> None:
        atomic_save(checkpoint, path)

    def load_checkpoint(self, path, map_location=None, weights_only=None):
        return load_checkpoint(path, map_location=map_location or "cpu")


def layout_meta(model_cfg: Mapping, axes: int, data_name: str = "",
                rate_hz: Optional[float] = None, rate_range_hz: Optional[Sequence[float]] = None,
                device_check: bool = False) -> Dict[str, Any]:
    """The record stored with every checkpoint: model config, input layout, training data and
    rate; ``rate_range_hz`` (low, high): the rates it was trained at (random resampling), so
    any recording in that range is its own; ``device_check``: it learned on recordings with their
    gyro bias at rest subtracted (:mod:`tcn_ahrs.device_check`), so it is given them so."""
    layout = {"axes": int(axes), "channels": list(CHANNELS[int(axes)]),
              "rate_hz": None if rate_hz is None else float(rate_hz)}
    if rate_range_hz:
        layout["rate_range_hz"] = [float(rate_range_hz[0]), float(rate_range_hz[1])]
    if device_check:
        layout["device_check"] = True
    model = dict(model_cfg)
    # the loop always recorded: a record without one is read as a pre-closed-loop checkpoint
    # (checkpoint_meta), while the default is the closed loop
    model.setdefault("loop", ModelConfig.loop)
    return {"model": model, "layout": layout, "data": str(data_name)}


def checkpoint_meta(ckpt: Mapping, path="checkpoint") -> Dict[str, Any]:
    meta = ckpt.get("tcn_ahrs")
    if not isinstance(meta, Mapping) or "layout" not in meta or "model" not in meta:
        raise CheckpointError(f"{path}: not a tcn-ahrs checkpoint (no 'tcn_ahrs' model/layout record)")
    meta = dict(meta)
    if isinstance(meta["model"], Mapping) and "loop" not in meta["model"]:
        # written before the closed loop existed (checkpoints/paper/*): the open loop, the model's
        # only loop then (today's default is the closed loop, tcn_ahrs/config/model.py)
        meta["model"] = {**dict(meta["model"]), "loop": "open"}
    return meta


def networks_off(path) -> bool:
    """Whether a residual checkpoint's inference knobs switch both networks off (``gyro_clip`` 0 and
    ``trust_weight`` 0): it runs as the backbone with its knobs, and is called that (the search's
    release, the transfer tables, the model cards)."""
    if path is None:
        return False
    res = (checkpoint_meta(load_checkpoint(str(path)), str(path))["model"] or {}).get("residual")
    return bool(res) and float(res.get("gyro_clip", 1.0)) == 0.0 and float(res.get("trust_weight", 1.0)) == 0.0


def check_layout(ckpt: Mapping, axes: int, path="checkpoint", data_axes: Optional[int] = None) -> None:
    """Raise :class:`CheckpointError` unless the checkpoint was trained for ``axes``-axis input.
    ``data_axes``: the most the dataset can provide (6: it has no magnetometer), so the advice
    names only what can work."""
    meta = checkpoint_meta(ckpt, path)
    got = int(meta["layout"]["axes"])
    if got != int(axes):
        variant = meta["model"].get("variant", "?")
        head = (f"{path}: checkpoint of model variant '{variant}' expects {got}-axis input "
                f"({', '.join(meta['layout']['channels'])}) but the data provides {axes} axes; ")
        if got > int(axes) and data_axes is not None and int(data_axes) < got:
            raise CheckpointError(head + "this dataset has no magnetometer: use a 6-axis checkpoint "
                                  "(e.g. checkpoints/general6_residual.ckpt)")
        raise CheckpointError(head + f"use a {axes}-axis checkpoint, or evaluate this one with data.axes={got}"
                              + (" (drops the magnetometer)" if got == 6 else ""))


def model_from_checkpoint(path, axes: Optional[int] = None, map_location="cpu") -> LearnedAHRS:
    """Build the :class:`LearnedAHRS` stored in a checkpoint (Lightning or plain); with ``axes``
    the layout is checked first."""
    ckpt = load_checkpoint(path, map_location)
    meta = checkpoint_meta(ckpt, path)
    if axes is not None:
        check_layout(ckpt, axes, path)
    model = LearnedAHRS.from_config(meta["model"], axes=int(meta["layout"]["axes"]))
    state = ckpt.get("state_dict", ckpt.get("model_state"))
    if state is None:
        raise CheckpointError(f"{path}: no 'state_dict' in checkpoint")
    # the weight average (train.ema_decay) is the model when present; "model." the raw weights
    prefix = "ema_model." if any(k.startswith("ema_model.") for k in state) else "model."
    state = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)} or dict(state)
    if model.closed is not None and "closed.rest_window" not in state:
        # written before the rest window was stored: it was the median step of the data, i.e. the
        # training rate recorded with the checkpoint (0: keep deriving it from the data)
        rate = (meta.get("layout") or {}).get("rate_hz") or meta.get("rate_hz")
        if rate:
            model.closed.set_rate(float(rate))
        state["closed.rest_window"] = model.closed.rest_window.clone()
    try:
        model.load_state_dict(state)
    except RuntimeError as e:
        raise CheckpointError(f"{path}: weights do not match the model config stored with them: {e}") from e
    for name, t in list(model.named_parameters()) + list(model.named_buffers()):
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise CheckpointError(f"{path}: weight '{name}' holds NaN/inf values (a diverged training run?): "
                                  "use an earlier checkpoint of the run (e.g. best.ckpt) or train again")
    rate = (meta.get("layout") or {}).get("rate_hz") or meta.get("rate_hz")
    model.trained_rate_hz = None if not rate else float(rate)  # checked against the data by LearnedEstimator
    span = (meta.get("layout") or {}).get("rate_range_hz")
    model.trained_rate_range = None if not span else (float(span[0]), float(span[1]))
    model.eval()
    return model


def release_checkpoint(src, dst) -> Dict[str, Any]:
    """Write the small, inference-only copy of a training checkpoint that ``checkpoints/``
    ships: the model weights (incl. the input statistics and BatchNorm buffers) and the
    ``tcn_ahrs`` record, without optimiser state (which would triple the size). The result
    loads with :func:`model_from_checkpoint` like the original. Returns the record."""
    ckpt = load_checkpoint(src)
    meta = checkpoint_meta(ckpt, src)
    model = model_from_checkpoint(src)  # validates that the weights fit the stored config
    slim = {"state_dict": {f"model.{k}": v.clone() for k, v in model.state_dict().items()},
            "tcn_ahrs": meta, "epoch": ckpt.get("epoch"), "global_step": ckpt.get("global_step")}
    atomic_save(slim, dst)
    return meta
