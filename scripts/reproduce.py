#!/usr/bin/env python
"""Reproduce a navigation paper's experiment (tcn_ahrs/reproduce/<paper>.py).

    python scripts/reproduce.py paper=es_ekf_odometry
    python scripts/reproduce.py paper=es_ekf_odometry paper.seeds=20 'paper.scenarios=[paper]'

Prints the paper's table with its numbers beside ours; writes results.json, results.md, TUM
trajectories and plots to ``out`` (default runs/reproduce/<paper>/<time>; conf/paper/<paper>.yaml).

Same as ``tcn-ahrs reproduce ...`` (tcn_ahrs/cli.py); this file is kept for ``python scripts/reproduce.py``.
"""
import sys

from tcn_ahrs.cli import main

if __name__ == "__main__":
    main(["reproduce", *sys.argv[1:]])
