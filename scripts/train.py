#!/usr/bin/env python
"""Train the learned AHRS, then evaluate it on held-out recordings.

    python scripts/train.py                          # simulator, a few minutes on a CPU
    python scripts/train.py data=broad data.root=../shared/datasets/broad
    python scripts/train.py experiment=broad9        # the paper's 1800 epochs
    python scripts/train.py model=dig_like trainer=gpu
    python scripts/train.py resume=true hydra.run.dir=runs/simulated/<that run>

Configuration: conf/train.yaml (+ groups data/ model/ trainer/ experiment/).
"""
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tcn_ahrs.cli import user_errors  # noqa: E402


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
@user_errors
def main(cfg: DictConfig) -> None:
    from tcn_ahrs.train import train_main

    train_main(cfg)


if __name__ == "__main__":
    main()
