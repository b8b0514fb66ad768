"""An exported file's self-description (``metadata.json``), shared by every export format: what the
model is, its units, frames and API, and which checkpoint (name, sha256) it came from."""
from __future__ import annotations

import hashlib
import warnings
from pathlib import Path
from typing import Any, Dict, Mapping, Optional

import torch
from torch import nn

from .. import __version__
from ..conventions import NETWORK_DTYPE

CHANNELS = {6: ["gyro_x", "gyro_y", "gyro_z", "acc_x", "acc_y", "acc_z"],
            9: ["gyro_x", "gyro_y", "gyro_z", "acc_x", "acc_y", "acc_z", "mag_x", "mag_y", "mag_z"]}


def file_sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _normalisation(cal: nn.Module) -> Dict[str, Any]:
    """The input normalisation folded into the networks: the training set's statistics, or the
    residual model's fixed physical scales (mean 0, std = 1 / scale)."""
    if hasattr(cal, "input_mean"):
        mean, std = list(cal.input_mean), list(cal.input_std)
    else:
        mean, std = [0.0] * len(cal.input_scale), list(1.0 / cal.input_scale)
    return {"included": True, "mean": [float(v) for v in mean], "std": [float(v) for v in std]}


def build_metadata(model: nn.Module, mode: str, meta: Optional[Mapping[str, Any]] = None,
                   net_dtype: torch.dtype = NETWORK_DTYPE) -> Dict[str, Any]:
    """The exported file's self-description (plain JSON types). ``meta`` adds or overrides
    entries (``rate_hz``, ``checkpoint``, ``checkpoint_sha256``, ``model_config``, ``data``)."""
    axes = int(model.axes)
    ecf = model.ecf
    backbone = getattr(model, "backbone", None) is not None
    md: Dict[str, Any] = {
        "format": "tcn-ahrs TorchScript export",
        "mode": mode,
        "tcn_ahrs_version": __version__,
        "torch_version": torch.__version__,
        "variant": str(getattr(model, "variant", "")),
        "axes": axes,
        "channels": CHANNELS[axes],
        "rate_hz": None,
        "receptive_field": int(model.receptive_field),
        "preintegration": ecf.preintegration if ecf is not None else "none",
        "ecf": ecf is not None,
        "loop": str(getattr(model, "loop", "open")),
        "units": {"gyro": "rad/s", "acc": "m/s^2 (specific force, +9.81 along the up axis at rest)",
                  "mag": "uT", "dt": "s", "omega": "rad/s"},
        "frames": {"imu": "body (sensor) frame", "attitude": "nav_from_body", "navigation": "ENU"},
        "quaternion_order": "wxyz",
        "quaternion_convention": "Hamilton, scalar first, w >= 0",
        "input_normalisation": _normalisation(model.calibration),
        "dtype": {"network": str(net_dtype).replace("torch.", ""), "calibration_ecf_integration": "float64"},
        "api": ({"forward": "quat (N,4), omega (N,3) = m(imu (N,C), dt float|(N,), q0 (4,))"} if mode == "batch" else
                {"reset": "m.reset(q0 (4,))",
                 "step": "quat (4,), omega (3,) = m.step(sample (C,), dt float)  (dt "
                         + ("used" if backbone else "unused") + " on the first call)",
                 "step_chunk": "quat (k,4), omega (k,3) = m.step_chunk(samples (k,C), dt float|(k,))  "
                               "(closed loop, backbone)",
                 "run": "quat (N,4), omega (N,3) = m.run(imu (N,C), dt float|(N,), q0 (4,))"}),
        "checkpoint": None,
        "checkpoint_sha256": None,
    }
    md.update(dict(meta or {}))
    return md


def checkpoint_export_meta(ckpt_path, ck_meta: Mapping[str, Any], rate_hz: Optional[float] = None):
    """The checkpoint's model (eval mode) and the entries :func:`build_metadata` adds for it
    (rate, checkpoint name and sha256, model config, data) - shared by every export format."""
    from ..checkpoint import model_from_checkpoint

    model = model_from_checkpoint(ckpt_path)
    rate = rate_hz if rate_hz is not None else ck_meta.get("rate_hz", (ck_meta.get("layout") or {}).get("rate_hz"))
    if rate is None:
        warnings.warn(f"{ckpt_path}: the checkpoint does not record the rate the model was trained at; "
                      "metadata rate_hz = null (pass rate=HZ to record it)")
    meta = {"rate_hz": None if rate is None else float(rate), "checkpoint": Path(ckpt_path).name,
            "checkpoint_sha256": file_sha256(ckpt_path), "model_config": ck_meta.get("model"),
            "data": ck_meta.get("data"), "rate_range_hz": (ck_meta.get("layout") or {}).get("rate_range_hz")}
    return model.eval(), meta
