"""Print a per-recording summary of a data split (duration, rate, axes, ground-truth coverage
and gaps, gyro mean at rest).

    python scripts/inspect_data.py data=broad data.split=all
    python scripts/inspect_data.py data=euroc data.root=/path/to/euroc data.split=train
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import hydra
from hydra.utils import to_absolute_path
from omegaconf import DictConfig, open_dict

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tcn_ahrs.cli import check_overrides, user_errors  # noqa: E402

from tcn_ahrs.datasets import format_summary_table, load_split, summarize  # noqa: E402


@hydra.main(version_base="1.3", config_path="../conf", config_name="inspect_data")
@user_errors
def main(cfg: DictConfig) -> None:
    data = cfg.data
    if data.get("root"):
        with open_dict(data):
            data.root = str(Path(to_absolute_path(str(data.root))).resolve())
    seqs = load_split(data)
    rows = [summarize(s, cfg.min_gap_s) for s in seqs]
    print(f"data={data.name} split={data.get('split', 'train')} root={data.get('root', '-')} "
          f"recordings={len(rows)}")
    print(format_summary_table(rows))
    if cfg.get("json"):
        Path(to_absolute_path(cfg.json)).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    check_overrides("inspect_data")  # a config error as one line with the nearest key (exit 2)
    main()
