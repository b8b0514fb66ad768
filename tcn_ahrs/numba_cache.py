"""Where numba keeps the package's compiled kernels: one folder per version of the sources.

numba's on-disk cache (``cache=True``) checks only the file of the function it compiled, not the
files it inlined: a kernel in ``kernels/backbone.py`` compiled into the recording loop of
``filters/backbone.py`` kept running its old code after the kernel changed (measured: the
timestamp-jitter fix of the magnetometer's low-pass had no effect until ``__pycache__`` was
cleared). Keying the cache folder on every source file's size and modification time means a
changed source never meets a stale compiled function. ``NUMBA_CACHE_DIR`` set by the user wins.
"""
from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent


def sources_digest(root: Path = PACKAGE) -> str:
    """A short digest of every ``.py`` file under ``root``: path, size and modification time."""
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        st = p.stat()
        h.update(f"{p.relative_to(root)}:{st.st_size}:{st.st_mtime_ns};".encode())
    return h.hexdigest()[:16]


def cache_dir() -> Path:
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "tcn_ahrs" / "numba" / sources_digest()


def configure() -> None:
    """Point numba's cache at :func:`cache_dir` unless ``NUMBA_CACHE_DIR`` is set; works whether
    or not numba is already imported."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    path = str(cache_dir())
    os.environ["NUMBA_CACHE_DIR"] = path
    if "numba" in sys.modules:  # imported before us: its config was read already
        sys.modules["numba"].config.CACHE_DIR = path
