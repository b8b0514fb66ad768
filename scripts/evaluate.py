#!/usr/bin/env python
"""Evaluate a trained checkpoint (+ Raw IMU and optional classical baselines) with the runner.

    python scripts/evaluate.py ckpt=runs/simulated/<run>/checkpoints/best.ckpt
    python scripts/evaluate.py ckpt=PATH data=broad data.split=test baselines=[ecf]
    python scripts/evaluate.py ckpt=PATH data=generic data.root=DIR data.split=all out=DIR

Writes results.json, results.md, plots and TUM trajectories to ``out`` (conf/evaluate.yaml).

Same as ``tcn-ahrs evaluate ...`` (tcn_ahrs/cli.py); this file is kept for ``python scripts/evaluate.py``.
"""
import sys

from tcn_ahrs.cli import main

if __name__ == "__main__":
    main(["evaluate", *sys.argv[1:]])
