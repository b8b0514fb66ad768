"""TUM VI (Schubert et al., IROS 2018), official 512_16 export, ASL layout.

``<seq>/mav0/imu0/data.csv`` (~200 Hz, BMI160, 6-axis, already calibrated by the dataset's
authors) and ``<seq>/mav0/mocap0/data.csv`` (120 Hz OptiTrack pose of the IMU frame,
``q_RS`` w,x,y,z = ``nav_from_body``). Read with the same ASL reader as EuRoC
(:func:`tcn_ahrs.datasets.euroc.load_asl`).

Frames: the mocap world frame is gravity-aligned with z up (checked in the tests: the
accelerometer at rest, rotated by the ground truth, points along +z); its yaw is arbitrary
(not ENU north): compare headings only after aligning the initial yaw.

Gaps: the motion capture loses tracking (room1: 9 gaps > 50 ms, room3: 31, room5: 3). An IMU
sample gets ground truth only if a mocap sample lies within ``max_nearest_s`` (default 10 ms)
and the two mocap samples bracketing it are at most ``max_bracket_s`` (default 25 ms, i.e.
up to two missing mocap frames) apart; everything else is masked, never bridged.
"""
from __future__ import annotations

from pathlib import Path
from typing import List

from ..sequence import ImuSequence
from .euroc import load_asl

GT_DIR = "mocap0"
MAX_NEAREST_S = 0.010
MAX_BRACKET_S = 0.025


def list_recordings(root) -> List[str]:
    """Sequence folders under ``root`` holding both ``mav0/imu0`` and ``mav0/mocap0`` data, sorted."""
    root = Path(root)
    return sorted(p.parent.parent.parent.name for p in root.glob("*/mav0/imu0/data.csv")
                  if (p.parent.parent / GT_DIR / "data.csv").is_file())


def load_recording(root, name: str, max_nearest_s: float = MAX_NEAREST_S,
                   max_bracket_s: float = MAX_BRACKET_S) -> ImuSequence:
    """Load sequence folder ``root/name`` (e.g. ``dataset-room1_512_16``)."""
    return load_asl(Path(root) / name, gt_dir=GT_DIR, name=name, dataset="tumvi",
                    max_nearest_s=max_nearest_s, max_bracket_s=max_bracket_s)
