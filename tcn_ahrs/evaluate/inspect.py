"""``tcn-ahrs inspect data=<name> [data.root=DIR] [data.split=all]``: a per-recording summary of a
data split (duration, rate, axes, ground-truth coverage and gaps, gyro mean at rest) and what the
sensors' health checks find in each (frozen, clipped, gaps: :func:`tcn_ahrs.health.recording_health`)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Dict, List


def inspect_main(cfg) -> List[Dict[str, Any]]:
    """Print the summary table of ``cfg.data``'s split; also write it as JSON to ``cfg.json``."""
    from hydra.utils import to_absolute_path
    from omegaconf import open_dict

    from ..datasets import format_summary_table, load_split, summarize

    data = cfg.data
    if data.get("root"):
        with open_dict(data):
            data.root = str(Path(to_absolute_path(str(data.root))).resolve())
    from ..health import recording_health

    seqs = load_split(data)
    rows = [summarize(s, cfg.min_gap_s) for s in seqs]
    print(f"data={data.name} split={data.get('split', 'train')} root={data.get('root', '-')} "
          f"recordings={len(rows)}")
    print(format_summary_table(rows))
    for seq, row in zip(seqs, rows):  # the sensors' health, as the backbone's checks read the stream
        row["health"] = recording_health(seq)
        print(f"health, {seq.name}: {'; '.join(row['health']) or 'no fault found'}")
    if cfg.get("json"):
        Path(to_absolute_path(cfg.json)).write_text(json.dumps(rows, indent=1))
    return rows
