#!/usr/bin/env python
"""Reproduce a navigation paper's experiment (tcn_ahrs/reproduce/<paper>.py).

    python scripts/reproduce.py paper=es_ekf_odometry
    python scripts/reproduce.py paper=es_ekf_odometry paper.seeds=20 'paper.scenarios=[paper]'

Prints the paper's table with its numbers beside ours; writes results.json, results.md, TUM
trajectories and plots to ``out`` (default runs/reproduce/<paper>/<time>; conf/paper/<paper>.yaml).
"""
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tcn_ahrs.cli import check_overrides, user_errors  # noqa: E402


@hydra.main(version_base="1.3", config_path="../conf", config_name="reproduce")
@user_errors
def main(cfg: DictConfig) -> None:
    from tcn_ahrs.cli import output_dir
    from tcn_ahrs.reproduce import run

    paper = OmegaConf.to_container(cfg.paper, resolve=True)
    run(str(paper["name"]), paper, output_dir(cfg.get("out"), Path("runs/reproduce") / str(paper["name"])))


if __name__ == "__main__":
    check_overrides("reproduce")  # a config error as one line with the nearest key (exit 2)
    main()
