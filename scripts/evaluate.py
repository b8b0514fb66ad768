#!/usr/bin/env python
"""Evaluate a trained checkpoint (+ Raw IMU and optional classical baselines) with the runner.

    python scripts/evaluate.py ckpt=runs/simulated/<run>/checkpoints/best.ckpt
    python scripts/evaluate.py ckpt=PATH data=broad data.split=test baselines=[ecf]
    python scripts/evaluate.py ckpt=PATH data=generic data.root=DIR data.split=all out=DIR

Writes results.json, results.md, plots and TUM trajectories to ``out`` (conf/evaluate.yaml).
"""
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tcn_ahrs.cli import check_overrides, user_errors  # noqa: E402


@hydra.main(version_base="1.3", config_path="../conf", config_name="evaluate")
@user_errors
def main(cfg: DictConfig) -> None:
    from tcn_ahrs.evaluate.main import evaluate_main

    evaluate_main(cfg)


if __name__ == "__main__":
    check_overrides("evaluate")  # a config error as one line with the nearest key (exit 2)
    main()
