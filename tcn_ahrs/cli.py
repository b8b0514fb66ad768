"""The scripts' error contract: a user error (bad data, config, checkpoint or path: every
``ValueError`` — :class:`~tcn_ahrs.sequence.DataError`, ``CheckpointError``, ``ExportError`` —
and ``OSError``) prints one line ``error: <message>`` on stderr and exits with status 2;
``HYDRA_FULL_ERROR=1`` shows the traceback instead. Anything else is a bug and keeps its traceback.
"""
from __future__ import annotations

import functools
import os
import sys

EXIT_USER_ERROR = 2


def user_errors(main):
    """Decorator for a script's Hydra task function (put it below ``@hydra.main``)."""

    @functools.wraps(main)
    def wrapper(*args, **kwargs):
        try:
            return main(*args, **kwargs)
        except (ValueError, OSError) as e:
            if os.environ.get("HYDRA_FULL_ERROR") == "1":
                raise
            print(f"error: {e}\n(HYDRA_FULL_ERROR=1 shows the traceback)", file=sys.stderr)
            raise SystemExit(EXIT_USER_ERROR) from None

    return wrapper
