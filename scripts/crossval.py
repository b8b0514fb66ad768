#!/usr/bin/env python
"""Leave-recordings-out cross-validation of the learned AHRS (see conf/crossval.yaml).

    python scripts/crossval.py experiment=broad9_closed_loop                 # every fold of data.folds
    python scripts/crossval.py experiment=broad9_closed_loop crossval.folds=[0]
    python scripts/crossval.py data=euroc model=ahrs6 crossval.tune=true

A killed run resumes: each fold's training continues from its last.ckpt, finished folds are
reused (crossval.retrain=true trains them again).

Same as ``tcn-ahrs crossval ...`` (tcn_ahrs/cli.py); this file is kept for ``python scripts/crossval.py``.
"""
import sys

from tcn_ahrs.cli import main

if __name__ == "__main__":
    main(["crossval", *sys.argv[1:]])
