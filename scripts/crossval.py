#!/usr/bin/env python
"""Leave-recordings-out cross-validation of the learned AHRS (see conf/crossval.yaml).

    python scripts/crossval.py experiment=broad9_cl                 # every fold of data.folds
    python scripts/crossval.py experiment=broad9_cl crossval.folds=[0]
    python scripts/crossval.py data=euroc model=ahrs6 crossval.tune=true

A killed run resumes: each fold's training continues from its last.ckpt, finished folds are
reused (crossval.retrain=true trains them again).
"""
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tcn_ahrs.cli import check_overrides, user_errors  # noqa: E402


@hydra.main(version_base="1.3", config_path="../conf", config_name="crossval")
@user_errors
def main(cfg: DictConfig) -> None:
    from tcn_ahrs.crossval import crossval_main

    crossval_main(cfg)


if __name__ == "__main__":
    check_overrides("crossval")  # a config error as one line with the nearest key (exit 2)
    main()
