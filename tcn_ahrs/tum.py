"""The one TUM trajectory writer (the format ``evo`` reads): evaluation artefacts and the
navigation reproductions write their trajectories through it."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np


def write_tum(path, time: np.ndarray, quat: np.ndarray, pos: Optional[np.ndarray] = None) -> None:
    """The one TUM trajectory writer (read by ``evo``): one line ``t x y z qx qy qz qw`` per sample,
    attitude ``nav_from_body`` (w,x,y,z) reordered to scalar-last, positions ``pos`` (N, 3) m in
    the navigation frame (0 for an attitude-only estimate); a ``#`` header line."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    q = np.asarray(quat, dtype=np.float64)
    t = np.asarray(time, dtype=np.float64)
    xyz = np.zeros((len(t), 3)) if pos is None else np.asarray(pos, dtype=np.float64)
    data = np.column_stack([t, xyz, q[:, 1], q[:, 2], q[:, 3], q[:, 0]])
    np.savetxt(path, data, fmt=["%.9f"] + (["%d"] * 3 if pos is None else ["%.9f"] * 3) + ["%.9f"] * 4,
               header="t x y z qx qy qz qw", comments="# ")
