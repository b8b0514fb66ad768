"""EuRoC MAV (Burri et al., IJRR 2016), official "ASL" layout.

``<seq>/mav0/imu0/data.csv``: ``#timestamp [ns], w_RS_S_x/y/z [rad s^-1], a_RS_S_x/y/z [m s^-2]``
(200 Hz, ADIS16448, 6-axis, specific force: +9.81 up at rest, already the project convention).
``<seq>/mav0/state_groundtruth_estimate0/data.csv``: ``#timestamp, p_RS_R_*, q_RS_w/x/y/z, [v, b_w, b_a]``
(8 or 17 columns). Columns are read **by header name** (spelling variants: ``#timestamp`` with or
without `` [ns]``, spaces after commas), never by position.

Frames: ``q_RS`` maps the IMU body frame S to the world frame R, i.e. ``nav_from_body``. R is
gravity-aligned with z up, but its **yaw is arbitrary** (not east/north): heading has no
absolute meaning on EuRoC (no magnetometer either), so compare headings only after aligning
the initial yaw (AAE/AYE with alignment are fine; absolute heading metrics are not).

Loading: nanoseconds -> seconds relative to the first kept IMU sample (``meta["t0_ns"]`` keeps
the absolute stamp), IMU cropped to the ground truth's time span (ground truth starts 1-2.4 s
later and ends ~1 s earlier), ground-truth orientation slerped to the IMU stamps; samples
whose nearest ground-truth sample is more than ``max_nearest_s`` away (or whose bracketing
ground-truth samples are more than ``max_bracket_s`` apart) are masked.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Dict, List, Sequence

import numpy as np

from ..sequence import DataError, ImuSequence
from ._common import check_finite, check_increasing, interpolate_quat, read_numeric_csv

GYRO_COLS = ("w_RS_S_x", "w_RS_S_y", "w_RS_S_z")
ACC_COLS = ("a_RS_S_x", "a_RS_S_y", "a_RS_S_z")
QUAT_COLS = ("q_RS_w", "q_RS_x", "q_RS_y", "q_RS_z")
GT_DIR = "state_groundtruth_estimate0"

# At 200 Hz: a few samples. Ground truth is 200 Hz and continuous; this only guards gaps.
MAX_NEAREST_S = 0.015
MAX_BRACKET_S = 0.030


def column_key(header_cell: str) -> str:
    """Normalise an ASL header cell: ``'#timestamp [ns]'`` -> ``'timestamp'``, ``' q_RS_w []'`` -> ``'q_RS_w'``."""
    c = header_cell.strip().lstrip("#").strip()
    c = re.sub(r"\s*\[.*\]\s*$", "", c)
    return c.strip()


def read_asl_csv(path, required: Sequence[str]) -> Dict[str, np.ndarray]:
    """Read an ASL csv into {normalised column name: values}; ``timestamp`` is int64 ns.

    Raises DataError naming the file and the first missing required column.
    """
    path = Path(path)
    names, values, stamps = read_numeric_csv(path, header=True, int_first_column=True)
    keys = [column_key(c) for c in names]
    cols = {k: values[:, i] for i, k in enumerate(keys)}
    if keys and keys[0] != "timestamp" and "timestamp" not in cols:
        raise DataError(str(path), "timestamp", f"expected a '#timestamp [ns]' column first, header is {names}")
    cols["timestamp"] = stamps if keys[0] == "timestamp" else np.round(cols["timestamp"]).astype(np.int64)
    for k in required:
        if k not in cols:
            raise DataError(str(path), k, f"expected a column named '{k}'; header has {names}")
    return cols


def list_recordings(root) -> List[str]:
    """Sequence folders under ``root`` that hold ``mav0/imu0/data.csv``, sorted."""
    root = Path(root)
    return sorted(p.parent.parent.parent.name for p in root.glob("*/mav0/imu0/data.csv"))


def load_recording(root, name: str, **kwargs) -> ImuSequence:
    """Load sequence folder ``root/name`` (see :func:`load_asl`)."""
    return load_asl(Path(root) / name, gt_dir=GT_DIR, name=name, dataset="euroc", **kwargs)


def load_asl(seq_dir, gt_dir: str, name: str, dataset: str, max_nearest_s: float = MAX_NEAREST_S,
             max_bracket_s: float = MAX_BRACKET_S) -> ImuSequence:
    """Load an ASL-format sequence folder (EuRoC, TUM VI): IMU + ground-truth orientation.

    Crops the IMU to the ground truth's time span and slerps the ground truth to the IMU stamps
    (masking gaps, see :func:`~tcn_ahrs.datasets._common.interpolate_quat`).
    """
    seq_dir = Path(seq_dir)
    imu_path = seq_dir / "mav0" / "imu0" / "data.csv"
    gt_path = seq_dir / "mav0" / gt_dir / "data.csv"
    if not imu_path.is_file():
        raise DataError(str(imu_path), "file", f"expected the IMU file of sequence '{name}', found nothing there")
    imu = read_asl_csv(imu_path, ("timestamp",) + GYRO_COLS + ACC_COLS)
    t_imu_ns = imu["timestamp"]
    check_increasing(imu_path, "timestamp", t_imu_ns.astype(np.float64))
    for c in GYRO_COLS + ACC_COLS:
        check_finite(imu_path, c, imu[c])
    gyro = np.stack([imu[c] for c in GYRO_COLS], axis=1)
    accel = np.stack([imu[c] for c in ACC_COLS], axis=1)

    if not gt_path.is_file():
        raise DataError(str(gt_path), "file", f"expected the ground-truth file of sequence '{name}', found nothing there")
    gt = read_asl_csv(gt_path, ("timestamp",) + QUAT_COLS)
    t_gt_ns = gt["timestamp"]
    check_increasing(gt_path, "timestamp", t_gt_ns.astype(np.float64))
    q_gt = np.stack([gt[c] for c in QUAT_COLS], axis=1)  # NaN rows (if any) count as absent

    # Crop the IMU to the ground truth's span (ground truth starts later and ends earlier).
    keep = (t_imu_ns >= t_gt_ns[0]) & (t_imu_ns <= t_gt_ns[-1])
    if keep.sum() < 2:
        raise DataError(str(gt_path), "timestamp", f"expected ground truth overlapping the IMU's time span "
                                                   f"({t_imu_ns[0]}..{t_imu_ns[-1]} ns), got {t_gt_ns[0]}..{t_gt_ns[-1]} ns")
    t0_ns = int(t_imu_ns[keep][0])
    t = (t_imu_ns[keep] - t0_ns) * 1e-9
    t_gt = (t_gt_ns - t0_ns) * 1e-9
    quat, valid = interpolate_quat(t_gt, q_gt, t, max_nearest_s, max_bracket_s)
    meta = {"dataset": dataset, "t0_ns": t0_ns, "imu_file": str(imu_path), "gt_file": str(gt_path),
            "cropped_start_s": float((t0_ns - t_imu_ns[0]) * 1e-9),
            "cropped_end_s": float((t_imu_ns[-1] - t_imu_ns[keep][-1]) * 1e-9),
            "nav_frame": "gravity-aligned z-up world frame of the ground truth; yaw arbitrary (not ENU north)"}
    rate = float(np.round(1.0 / np.median(np.diff(t)), 3))
    return ImuSequence(name=name, source=str(seq_dir), time=t, gyro=gyro[keep], accel=accel[keep], mag=None,
                       quat=quat, quat_valid=valid, rate=rate, meta=meta)
