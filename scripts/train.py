#!/usr/bin/env python
"""Train the learned AHRS, then evaluate it on held-out recordings.

    python scripts/train.py                                  # simulator, < 3 min on 2 CPU cores
    python scripts/train.py experiment=broad9_closed_loop data.fold=0 # real data with its schedule (fold 0 held out)
    python scripts/train.py experiment=broad9_open_loop                # the paper's open loop, 1800 epochs (GPU)
    python scripts/train.py resume=true run_dir=runs/broad/<that run>   # continue after a kill

Configuration: conf/train.yaml (+ groups data/ model/ trainer/ experiment/).

Same as ``tcn-ahrs train ...`` (tcn_ahrs/cli.py); this file is kept for ``python scripts/train.py``.
"""
import sys

from tcn_ahrs.cli import main

if __name__ == "__main__":
    main(["train", *sys.argv[1:]])
