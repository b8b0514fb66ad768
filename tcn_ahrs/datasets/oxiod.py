"""OxIOD (Chen et al., 2018): smartphone IMU + Vicon, official ``syn`` files.

Layout: ``<mode>/<dataN>/syn/imuK.csv`` and ``viK.csv`` (rows correspond one to one); the
recording name is ``<mode>/<dataN>/imuK`` (e.g. ``handheld/data1/imu2``).

``imuK.csv`` (no header, 16 columns in the published files; a 17th trailing column is
tolerated): time, attitude roll/pitch/yaw (the phone's own fusion, ignored), rotation rate
x/y/z (rad/s), gravity x/y/z (g), user acceleration x/y/z (g), magnetic field x/y/z (uT).
``viK.csv`` (no header, 9 columns): time, frame counter, translation x/y/z (m), rotation
**x,y,z,w** (Vicon order; converted to w,x,y,z).

Conversions (measured on the files, see the dataset README):
* time = row index / 100 Hz (the time column has lost its precision, e.g. ``1.4955e+11``);
* specific force = ``-9.81 * (gravity + user_acc)``: the phone's gravity+user acceleration
  points *down* at rest, the project's accelerometer convention reads +9.81 *up*;
* the Vicon world frame is gravity-aligned with z up (the accelerometer at rest, rotated by
  the ground truth, points along +z; checked in the tests), yaw arbitrary (not ENU north);
* **phone -> Vicon body frame**: the phone's sensor frame and the Vicon body frame differ by
  a constant rotation (~165-180 deg about the phone's z axis). :func:`estimate_body_from_phone`
  estimates it per file by solving Wahba's problem (Kabsch/SVD) between the phone gyro and
  the angular rate differentiated from the Vicon attitude, with outlier rejection (Vicon
  jumps) and a search over a small IMU/Vicon time lag (up to +/-``max_lag`` samples). The
  rotation is applied to gyro, accelerometer and magnetometer so the IMU is expressed in the
  Vicon body frame and the Vicon attitude is its ``nav_from_body``. ``meta`` keeps the
  rotation (``body_from_phone``), its angle and the lag (``vicon_lag_samples``). When
  ``align_lag`` is True the ground truth is shifted by that lag (samples that fall off the
  ends are masked);
* Vicon outliers (flips and jumps of up to 180 deg in one sample) are masked as invalid ground
  truth (:func:`tcn_ahrs.datasets._common.gt_outliers`: samples their ±10 neighbours, propagated
  by the gyro, contradict by > 5 deg; 2-70 per file, none on BROAD/EuRoC); ``meta`` counts them.
"""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np

from ..conventions import GRAVITY, quat_xyzw_to_wxyz
from ..sequence import DataError, ImuSequence
from ._common import body_rate_from_quat, check_finite, gt_outliers, read_numeric_csv

RATE = 100.0
IMU_NCOLS = (16, 17)
VI_NCOLS = (9,)


def list_recordings(root) -> List[str]:
    """Names ``<mode>/<dataN>/imuK`` of every ``syn/imuK.csv`` under ``root`` with a matching ``viK.csv``."""
    root = Path(root)
    out = []
    for p in root.rglob("syn/imu*.csv"):
        vi = p.with_name("vi" + p.name[3:])
        if vi.is_file():
            rel = p.parent.parent.relative_to(root).as_posix()
            out.append(f"{rel}/{p.stem}")
    return sorted(out)


def load_recording(root, name: str, **kwargs) -> ImuSequence:
    """Load ``root/<mode>/<dataN>/syn/imuK.csv`` + ``viK.csv`` for name ``<mode>/<dataN>/imuK``."""
    root = Path(root)
    parts = name.split("/")
    if len(parts) < 2 or not parts[-1].startswith("imu"):
        raise DataError(str(root), "recording", f"expected a name like 'handheld/data1/imu2', got {name!r}")
    folder = root.joinpath(*parts[:-1]) / "syn"
    k = parts[-1][3:]
    return load_files(folder / f"imu{k}.csv", folder / f"vi{k}.csv", name=name, **kwargs)


def _wahba(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation R minimising sum |b_i - R a_i|^2 (Kabsch/SVD, det +1). a, b: (M, 3)."""
    h = a.T @ b
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1) + 1e-12)
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def estimate_body_from_phone(gyro_phone: np.ndarray, rate_vicon: np.ndarray, max_lag: int = 8,
                             min_rate: float = 0.3, max_rate: float = 15.0,
                             iterations: int = 3) -> Tuple[np.ndarray, int, float]:
    """Constant rotation ``body_from_phone`` with ``rate_vicon[k] ~ R @ gyro_phone[k + lag]``.

    gyro_phone: (N, 3) rad/s in the phone frame; rate_vicon: (N, 3) rad/s in the Vicon body frame
    (NaN where undefined). Uses samples where both rates are in ``[min_rate, max_rate]`` (turning
    enough to carry direction, and no Vicon jump), solves Wahba's problem, then re-solves on the
    samples whose residual angle is below 3x the median (robust to Vicon jumps and glitches).
    The lag (samples, |lag| <= max_lag) minimising the median residual angle is kept.

    Returns ``(R (3, 3), lag, median residual angle in degrees)``.
    """
    best = None
    n = gyro_phone.shape[0]
    for lag in range(-max_lag, max_lag + 1):
        lo, hi = max(0, -lag), min(n, n - lag)
        a = gyro_phone[lo + lag:hi + lag]
        b = rate_vicon[lo:hi]
        na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
        use = np.isfinite(nb) & (na > min_rate) & (na < max_rate) & (nb > min_rate) & (nb < max_rate)
        if use.sum() < 10:
            continue
        a_u, b_u = a[use], b[use]
        r = _wahba(a_u, b_u)
        for _ in range(iterations):
            ang = _angles_deg(a_u @ r.T, b_u)
            inl = ang < max(3.0 * np.median(ang), 2.0)
            r = _wahba(a_u[inl], b_u[inl])
        med = float(np.median(_angles_deg(a_u @ r.T, b_u)))
        if best is None or med < best[2]:
            best = (r, lag, med)
    if best is None:
        raise ValueError("not enough rotation to estimate the phone -> Vicon body rotation")
    return best


def load_files(imu_path, vi_path, name: Optional[str] = None, align_lag: bool = True,
               max_lag: int = 8) -> ImuSequence:
    """Load one pair of OxIOD ``syn`` files (see the module docstring for every conversion)."""
    imu_path, vi_path = Path(imu_path), Path(vi_path)
    _, imu, _ = read_numeric_csv(imu_path, header=False, ncols=IMU_NCOLS)
    _, vi, _ = read_numeric_csv(vi_path, header=False, ncols=VI_NCOLS)
    if imu.shape[0] != vi.shape[0]:
        raise DataError(str(vi_path), "rows", f"expected as many rows as {imu_path.name} ({imu.shape[0]}), "
                                              f"found {vi.shape[0]} (rows correspond one to one)")
    gyro_p = check_finite(imu_path, "rotation_rate (columns 5-7)", imu[:, 4:7])
    grav = check_finite(imu_path, "gravity (columns 8-10)", imu[:, 7:10])
    user = check_finite(imu_path, "user_acceleration (columns 11-13)", imu[:, 10:13])
    mag_p = check_finite(imu_path, "magnetic_field (columns 14-16)", imu[:, 13:16])
    # Phone API: gravity + user acceleration in g, pointing down at rest -> specific force up.
    acc_p = -GRAVITY * (grav + user)

    quat = quat_xyzw_to_wxyz(vi[:, 5:9])
    norm = np.linalg.norm(quat, axis=1)
    good = np.isfinite(norm) & (np.abs(norm - 1.0) < 0.05)  # zero/garbage rows = Vicon dropouts
    quat = np.where(good[:, None], quat / np.where(good, norm, 1.0)[:, None], np.nan)

    n = imu.shape[0]
    time = np.arange(n, dtype=np.float64) / RATE
    rate_vicon = body_rate_from_quat(quat, time, half_width=1)
    try:
        r, lag, resid = estimate_body_from_phone(gyro_p, rate_vicon, max_lag=max_lag)
    except ValueError as e:
        raise DataError(str(imu_path), "rotation_rate", f"could not estimate the phone -> Vicon body rotation: {e}") from None
    gyro, acc, mag = gyro_p @ r.T, acc_p @ r.T, mag_p @ r.T

    valid = good.copy()
    if align_lag and lag != 0:
        # rate_vicon[k] ~ gyro[k + lag]: the IMU sample k sees the attitude of Vicon row k - lag.
        shifted = np.full_like(quat, np.nan)
        sv = np.zeros(n, dtype=bool)
        if lag > 0:
            shifted[lag:], sv[lag:] = quat[:-lag], valid[:-lag]
        else:
            shifted[:lag], sv[:lag] = quat[-lag:], valid[-lag:]
        quat, valid = shifted, sv
    # Vicon flips and jumps (up to 180 deg in one sample): masked, not scored (nothing invented)
    outliers = gt_outliers(quat, valid, gyro, np.diff(time, prepend=time[0] - 1.0 / RATE))
    valid = valid & ~outliers
    quat = np.where(valid[:, None], quat, np.nan)
    angle = float(np.degrees(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))
    meta = {"gt_outliers_masked": int(outliers.sum()),"dataset": "oxiod", "imu_file": str(imu_path), "vicon_file": str(vi_path),
            "body_from_phone": r.tolist(), "body_from_phone_angle_deg": angle,
            "vicon_lag_samples": int(lag) if align_lag else 0, "estimated_lag_samples": int(lag),
            "gyro_vs_vicon_median_angle_deg": resid,
            "nav_frame": "Vicon world frame: gravity-aligned z-up; yaw arbitrary (not ENU north)"}
    return ImuSequence(name=name or imu_path.stem, source=str(imu_path), time=time, gyro=gyro, accel=acc,
                       mag=mag, quat=quat, quat_valid=valid, rate=RATE, meta=meta)
