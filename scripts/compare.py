#!/usr/bin/env python
"""Compare attitude estimators on one dataset: paper-style tables (tcn_ahrs/compare.py).

    python scripts/compare.py data=broad data.split=test tune=true
    python scripts/compare.py data=euroc data.split=val tune=true peers=true
    python scripts/compare.py data=broad ckpts='{"Proposed 9-axis": runs/x/checkpoints/best.ckpt}'

Writes results.json (metrics, tuned parameters and the recordings they were tuned on) and
results.md (Table 1/2 layout, BROAD total/heading/inclination, group averages, ablation) to
``out`` (default runs/compare/<data>/<time>; options in conf/compare.yaml).
"""
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tcn_ahrs.cli import check_overrides, user_errors  # noqa: E402


@hydra.main(version_base="1.3", config_path="../conf", config_name="compare")
@user_errors
def main(cfg: DictConfig) -> None:
    from tcn_ahrs.compare import compare_main

    compare_main(cfg)


if __name__ == "__main__":
    check_overrides("compare")  # a config error as one line with the nearest key (exit 2)
    main()
