#!/usr/bin/env python
"""Export a trained checkpoint as self-contained TorchScript (batch and/or streaming).

    python scripts/export.py ckpt=runs/simulated/<run>/checkpoints/best.ckpt out=exports/ahrs9.pt
    python scripts/export.py ckpt=PATH out=FILE.pt mode=streaming rate=200
    python scripts/export.py ckpt=checkpoints/broad9.ckpt out=exports/broad9.onnx format=onnx
    python scripts/export.py ckpt=checkpoints/broad9.ckpt out=exports/broad9.pt2 format=export

Loading the result needs only torch:
    m = torch.jit.load("FILE.pt");  quat, omega = m(imu, dt, q0);  print(m.metadata())
    s = torch.jit.load("FILE_streaming.pt");  s.reset(q0);  quat, omega = s.step(sample, dt)

Configuration: conf/export.yaml; the contract is in tcn_ahrs/export.py's docstring.
"""
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tcn_ahrs.cli import check_overrides, user_errors  # noqa: E402

KEYS = {"ckpt", "out", "mode", "rate", "net_dtype", "overwrite", "format"}
FORMATS = ("torchscript", "onnx", "export")


@hydra.main(version_base="1.3", config_path="../conf", config_name="export")
@user_errors
def main(cfg: DictConfig) -> None:
    from tcn_ahrs.export import export_checkpoint, read_metadata

    unknown = set(cfg) - KEYS
    if unknown:
        raise ValueError(f"export: unknown key(s) {sorted(unknown)}; expected a subset of {sorted(KEYS)}")
    if not cfg.ckpt or not cfg.out:
        raise ValueError("export: pass ckpt=PATH (a checkpoint written by scripts/train.py) and out=FILE.pt")
    fmt = str(cfg.get("format", "torchscript"))
    if fmt not in FORMATS:
        raise ValueError(f"export: format={fmt!r}: expected one of {FORMATS}")
    rate = None if cfg.rate is None else float(cfg.rate)
    overwrite = bool(cfg.get("overwrite", False))
    if fmt == "torchscript":
        written = export_checkpoint(str(cfg.ckpt), str(cfg.out), str(cfg.mode), rate_hz=rate,
                                    net_dtype=str(cfg.net_dtype), overwrite=overwrite)
    else:
        if str(cfg.net_dtype) != "float32":
            raise ValueError(f"export: format={fmt} runs the networks in float32 (net_dtype=float32)")
        if fmt == "onnx":
            from tcn_ahrs.export.onnx_step import export_onnx as export_fn, read_onnx_metadata as read_metadata
        else:
            from tcn_ahrs.export.program import export_program as export_fn, read_program_metadata as read_metadata
        written = export_fn(str(cfg.ckpt), str(cfg.out), str(cfg.mode), rate_hz=rate, overwrite=overwrite)
    for mode, path in written.items():
        md = read_metadata(path)
        print(f"{mode}: {path}  ({md['variant']}, {md['axes']}-axis, preintegration {md['preintegration']}, "
              f"receptive field {md['receptive_field']}, rate "
              f"{'{:g}-{:g}'.format(*md['rate_range_hz']) if md.get('rate_range_hz') else md['rate_hz']} Hz, "
              f"checkpoint sha256 {md['checkpoint_sha256'][:12]}...)")


if __name__ == "__main__":
    check_overrides("export")  # a config error as one line with the nearest key (exit 2)
    main()
