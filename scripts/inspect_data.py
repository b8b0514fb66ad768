#!/usr/bin/env python
"""Print a per-recording summary of a data split (duration, rate, axes, ground-truth coverage
and gaps, gyro mean at rest).

    python scripts/inspect_data.py data=broad data.split=all
    python scripts/inspect_data.py data=euroc data.root=/path/to/euroc data.split=train

Same as ``tcn-ahrs inspect ...`` (tcn_ahrs/cli.py); this file is kept for ``python scripts/inspect_data.py``.
"""
import sys

from tcn_ahrs.cli import main

if __name__ == "__main__":
    main(["inspect", *sys.argv[1:]])
