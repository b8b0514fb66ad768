"""The one place for the project's conventions, and converters from the others.

Everything inside ``tcn_ahrs`` uses exactly these conventions; loaders convert the
publishers' conventions to them (and nowhere else does any conversion happen).

* **Quaternions** are Hamilton quaternions stored as ``(w, x, y, z)`` (scalar first).
* **Rotations map body to navigation**: an attitude ``nav_from_body`` (quaternion or
  3x3 matrix ``R``) maps a vector expressed in the sensor (body, b-) frame to the
  navigation (n-) frame: ``v_nav = R @ v_body``.
* **Navigation frame is ENU**: x east, y north, z up.
* **Accelerometer** reads specific force: at rest it reads ``+GRAVITY`` (9.81 m/s^2) along
  the body axis that points up, i.e. ``accel = R.T @ [0, 0, +9.81]``.
* **Magnetometer** reads the local field in microtesla; in ENU the field points north
  and (on the northern hemisphere) down.
* **Units**: rad/s, m/s^2, microtesla (uT), seconds.
* **Euler angles** (for reporting only): roll, pitch, yaw of the intrinsic z-y'-x''
  sequence, ``R = Rz(yaw) Ry(pitch) Rx(roll)``; yaw is counter-clockwise from east
  (ENU), in radians.
"""
from __future__ import annotations

import numpy as np
import torch

GRAVITY = 9.81
"""Magnitude of gravity in m/s^2 used for plausibility checks and simulation."""

UP_NAV = np.array([0.0, 0.0, 1.0])
"""Direction the accelerometer points at rest, in the navigation (ENU) frame."""

EAST_NAV = np.array([1.0, 0.0, 0.0])
NORTH_NAV = np.array([0.0, 1.0, 0.0])

DEG = np.pi / 180.0

# ---------------------------------------------------------------- physical input ranges
# A reading beyond these is no MEMS measurement but a fault (a spike, a wrong unit, a garbled
# packet): refused by the loader (file, field, sample) and by every streaming runtime before any
# state changes, because one integrated 1e30 turns every later output into NaN. Each bound sits
# well above what IMUs measure: gyros to ±4000 °/s (70 rad/s), accelerometers to ±400 g for
# impacts, magnetometers to ±4900 µT; steps up to one second (an AHRS needs more than 1 Hz).
MAX_GYRO = 100.0    # rad/s, per axis
MAX_ACCEL = 4000.0  # m/s², per axis
MAX_MAG = 10000.0   # µT, per axis
MAX_DT = 1.0        # s, one time step
MIN_DT = 1e-5       # s, one time step: 100 kHz, above any MEMS IMU's rate. Shorter steps are clock faults
                    # (duplicated or garbled stamps); the C runtime's float filter turned its bias NaN for good
                    # at dt <= 1e-14 s, so every runtime refuses them (Python, ONNX/torch.export loaders, C)
INPUT_RANGES = {"gyro": MAX_GYRO, "accel": MAX_ACCEL, "mag": MAX_MAG}
INPUT_LIMITS = (MAX_GYRO,) * 3 + (MAX_ACCEL,) * 3 + (MAX_MAG,) * 3
"""The same per channel of a raw sample (gyro x,y,z, acc x,y,z, mag x,y,z)."""

# ---------------------------------------------------------------- numerics: one float policy
# Where precision matters is where values are multiplied or summed over many samples: attitude and
# position integration (products of 10^4-10^6 rotations) and the loss's rotation increments.
# The networks' inputs and outputs are O(1) and tolerate float32, which halves their cost.
STORAGE_DTYPE = np.float64
"""Recordings (:class:`~tcn_ahrs.sequence.ImuSequence` arrays, ground truth) as loaded and stored."""
STATE_DTYPE = torch.float64
"""Every filter state and integration: classical filters, raw integration, the learned closed loop
at evaluation and export, the navigation filters."""
NETWORK_DTYPE = torch.float32
"""The TCNs, in training and inference (the export's ``net_dtype`` default)."""
LOSS_DTYPE = torch.float64
"""Products of rotation increments inside the training losses (Eq. 28)."""

# ---------------------------------------------------------------------------
# Quaternion component order
# ---------------------------------------------------------------------------


def quat_xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    """Reorder quaternions from scalar-last ``(x,y,z,w)`` (scipy, ROS, Vicon) to ``(w,x,y,z)``."""
    q = np.asarray(q)
    return np.concatenate([q[..., 3:4], q[..., 0:3]], axis=-1)


def quat_wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """Reorder quaternions from ``(w,x,y,z)`` to scalar-last ``(x,y,z,w)``."""
    q = np.asarray(q)
    return np.concatenate([q[..., 1:4], q[..., 0:1]], axis=-1)


# ---------------------------------------------------------------------------
# Navigation frames
# ---------------------------------------------------------------------------

# Rotation matrices that map a vector given in the named frame into ENU.
_ENU_FROM = {
    "ENU": np.eye(3),
    # NED: x north, y east, z down  ->  ENU: (e, n, u) = (y, x, -z)
    "NED": np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
    # NWU: x north, y west, z up  ->  ENU: (e, n, u) = (-y, x, z)
    "NWU": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
}


def enu_from_frame(frame: str) -> np.ndarray:
    """3x3 matrix mapping vectors in navigation frame ``frame`` (ENU, NED or NWU) to ENU."""
    try:
        return _ENU_FROM[frame.upper()].copy()
    except KeyError:
        raise ValueError(f"unknown navigation frame {frame!r}; expected one of {sorted(_ENU_FROM)}") from None


def nav_matrices_to_enu(nav_from_body: np.ndarray, frame: str) -> np.ndarray:
    """Re-express attitudes ``frame_from_body`` (..., 3, 3) as ``enu_from_body``."""
    return enu_from_frame(frame) @ np.asarray(nav_from_body)


def nav_vectors_to_enu(v: np.ndarray, frame: str) -> np.ndarray:
    """Re-express navigation-frame vectors (..., 3) given in ``frame`` in ENU."""
    return np.asarray(v) @ enu_from_frame(frame).T


# ---------------------------------------------------------------------------
# Units
# ---------------------------------------------------------------------------


def deg_to_rad(x):
    """deg/s -> rad/s (or deg -> rad)."""
    return np.asarray(x) * DEG


def rad_to_deg(x):
    """rad/s -> deg/s (or rad -> deg)."""
    return np.asarray(x) / DEG


def g_to_mps2(x):
    """Specific force in units of g -> m/s^2."""
    return np.asarray(x) * GRAVITY


def mps2_to_g(x):
    """Specific force in m/s^2 -> units of g."""
    return np.asarray(x) / GRAVITY


def gauss_to_ut(x):
    """Magnetic field in Gauss -> microtesla (1 G = 100 uT)."""
    return np.asarray(x) * 100.0


def nt_to_ut(x):
    """Magnetic field in nanotesla -> microtesla."""
    return np.asarray(x) * 1e-3


def accel_down_to_up(x):
    """Accelerometers that read -g along the up axis at rest (gravity, not specific force)."""
    return -np.asarray(x)
