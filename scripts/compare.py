#!/usr/bin/env python
"""Compare attitude estimators on one dataset: paper-style tables (tcn_ahrs/experiments/compare.py).

    python scripts/compare.py data=broad data.split=test tune=true
    python scripts/compare.py data=euroc data.split=val tune=true peers=true
    python scripts/compare.py data=broad ckpts='{"Proposed 9-axis": runs/x/checkpoints/best.ckpt}'

Writes results.json (metrics, tuned parameters and the recordings they were tuned on) and
results.md (Table 1/2 layout, BROAD total/heading/inclination, group averages, ablation) to
``out`` (default runs/compare/<data>/<time>; options in conf/compare.yaml).

Same as ``tcn-ahrs compare ...`` (tcn_ahrs/cli.py); this file is kept for ``python scripts/compare.py``.
"""
import sys

from tcn_ahrs.cli import main

if __name__ == "__main__":
    main(["compare", *sys.argv[1:]])
