"""The scripts' error contract: a user error (bad data, config, checkpoint or path: every
``ValueError`` — :class:`~tcn_ahrs.sequence.DataError`, ``CheckpointError``, ``ExportError`` —
and ``OSError``) prints one line ``error: <message>`` on stderr and exits with status 2;
``HYDRA_FULL_ERROR=1`` shows the traceback instead. Anything else is a bug and keeps its traceback.
"""
from __future__ import annotations

import functools
import os
import sys
import time
from pathlib import Path
from typing import Optional

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


def output_dir(explicit: Optional[str], fallback: Path) -> Path:
    """Where a script writes: ``explicit`` (``out=``/``run_dir=``), else Hydra's run directory
    of this job, else ``fallback/<date_time>`` (called outside Hydra, e.g. from a test)."""
    if explicit:
        return Path(str(explicit))
    try:
        from hydra.core.hydra_config import HydraConfig

        return Path(HydraConfig.get().runtime.output_dir)
    except Exception:  # noqa: BLE001 - no Hydra job
        return Path(fallback) / time.strftime("%Y-%m-%d_%H-%M-%S")
