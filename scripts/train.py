#!/usr/bin/env python
"""Train the learned AHRS, then evaluate it on held-out recordings.

    python scripts/train.py                                  # simulator, < 3 min on 2 CPU cores
    python scripts/train.py experiment=broad9_cl data.fold=0 # real data with its schedule (fold 0 held out)
    python scripts/train.py experiment=broad9                # the paper's open loop, 1800 epochs (GPU)
    python scripts/train.py resume=true run_dir=runs/broad/<that run>   # continue after a kill

Configuration: conf/train.yaml (+ groups data/ model/ trainer/ experiment/).
"""
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tcn_ahrs.cli import check_overrides, user_errors  # noqa: E402


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
@user_errors
def main(cfg: DictConfig) -> None:
    from tcn_ahrs.train import train_main

    train_main(cfg)


if __name__ == "__main__":
    check_overrides("train")  # a config error as one line with the nearest key (exit 2)
    main()
