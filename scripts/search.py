#!/usr/bin/env python
"""The nested search over estimator families for one device (see conf/search.yaml).

    python scripts/search.py data=euroc data.axes=6                 # every outer fold, 3 seeds
    python scripts/search.py data=broad search.trials=10 search.seeds=[0]
    python scripts/search.py data=euroc data.axes=6 search.learned={closed_loop: runs/crossval/euroc_ahrs}

A killed search resumes: the Optuna studies live in search.db under the output folder.

Same as ``tcn-ahrs search ...`` (tcn_ahrs/cli.py); this file is kept for ``python scripts/search.py``.
"""
import sys

from tcn_ahrs.cli import main

if __name__ == "__main__":
    main(["search", *sys.argv[1:]])
