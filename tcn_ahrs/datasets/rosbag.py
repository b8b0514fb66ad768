"""ROS 1 / ROS 2 bags (read with the pure-Python ``rosbags`` package, ``pip install -e .[ros]``).

Every ``*.bag`` file (ROS 1) and every folder holding a ``metadata.yaml`` (ROS 2) under ``root``
is a recording, named by its path relative to ``root`` (``*.bag`` without the suffix). Topics
come from the data config (``conf/data/rosbag.yaml``)::

    topics:
      imu: /imu/data            # sensor_msgs/Imu (required): angular_velocity rad/s,
                                #   linear_acceleration m/s^2 (specific force, REP 145)
      mag: /imu/mag             # sensor_msgs/MagneticField (Tesla), or null
      pose: /vicon/body         # geometry_msgs/PoseStamped, geometry_msgs/PoseWithCovarianceStamped
                                #   or nav_msgs/Odometry: ground-truth orientation, or null
    declare: {}                 # the generic format's declarations (nav_frame, gt_body_from_imu, ...)

Conversions (then the generic format's declarations and every plausibility check apply,
:func:`tcn_ahrs.datasets.generic.build`): time = each message's ``header.stamp`` (s); the
magnetic field T -> µT, linearly interpolated to the IMU stamps (IMU samples outside the
magnetometer's time span get the nearest reading); the pose orientation (x,y,z,w -> w,x,y,z)
slerped to the IMU stamps, masked (not invented) outside its span and across its gaps (> 0.1 s).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional

import numpy as np

from ..sequence import DataError, ImuSequence
from ._common import interpolate_quat

WANTS_CONFIG = True  # load_recording receives the data config (topics)
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped",
              "nav_msgs/msg/Odometry")


def list_recordings(root) -> List[str]:
    root = Path(root)
    bags = {p.relative_to(root).with_suffix("").as_posix() for p in root.rglob("*.bag") if p.is_file()}
    bags |= {p.parent.relative_to(root).as_posix() for p in root.rglob("metadata.yaml")}
    return sorted(bags)


def _reader():
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as e:
        raise ImportError("data=rosbag needs the 'rosbags' package: pip install -e .[ros]") from e
    return AnyReader, get_typestore(Stores.ROS2_HUMBLE)


def _stamp(msg) -> float:
    s = msg.header.stamp
    return float(s.sec) + 1e-9 * float(s.nanosec)


def load_recording(root, name: str, cfg: Optional[Mapping[str, Any]] = None) -> ImuSequence:
    from .generic import build

    root = Path(root)
    path = root / f"{name}.bag" if (root / f"{name}.bag").is_file() else root / name
    if not path.exists():
        raise DataError(str(root), "recording", f"expected a bag {name}.bag or a ROS 2 bag folder {name}/ here")
    cfg = dict(cfg or {})
    topics = dict(cfg.get("topics") or {})
    if not topics.get("imu"):
        raise DataError("data config", "topics.imu", "expected the sensor_msgs/Imu topic (e.g. /imu/data)")
    AnyReader, typestore = _reader()
    want = {k: topics.get(k) for k in ("imu", "mag", "pose") if topics.get(k)}
    rows: Dict[str, list] = {k: [] for k in want}
    with AnyReader([path], default_typestore=typestore) as reader:
        by_topic = {c.topic: c for c in reader.connections}
        for key, topic in want.items():
            if topic not in by_topic:
                raise DataError(str(path), f"topics.{key}", f"topic {topic!r} not in the bag; it has "
                                                         f"{sorted(by_topic)}")
            conn = by_topic[topic]
            if key == "pose" and conn.msgtype not in POSE_TYPES:
                raise DataError(str(path), "topics.pose", f"expected one of {POSE_TYPES}, got {conn.msgtype}")
        conns = [by_topic[t] for t in want.values()]
        key_of = {t: k for k, t in want.items()}
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            key = key_of[conn.topic]
            if key == "imu":
                w, a = msg.angular_velocity, msg.linear_acceleration
                rows[key].append((_stamp(msg), w.x, w.y, w.z, a.x, a.y, a.z))
            elif key == "mag":
                m = msg.magnetic_field
                rows[key].append((_stamp(msg), m.x, m.y, m.z))
            else:
                pose = msg.pose.pose if conn.msgtype != "geometry_msgs/msg/PoseStamped" else msg.pose
                o = pose.orientation
                rows[key].append((_stamp(msg), o.w, o.x, o.y, o.z))
    if len(rows["imu"]) < 2:
        raise DataError(str(path), "topics.imu", f"expected IMU messages on {want['imu']}, found {len(rows['imu'])}")
    imu = np.asarray(sorted(rows["imu"]), dtype=np.float64)
    t = imu[:, 0]
    arrays = {"t": t, "gyr": imu[:, 1:4], "acc": imu[:, 4:7], "mag": None, "quat": None, "score": None}
    if "mag" in rows:
        mag = np.asarray(sorted(rows["mag"]), dtype=np.float64)
        if mag.shape[0] < 1:
            raise DataError(str(path), "topics.mag", f"no messages on {want['mag']}")
        arrays["mag"] = 1e6 * np.stack([np.interp(t, mag[:, 0], mag[:, 1 + i]) for i in range(3)], 1)  # T -> µT
    if "pose" in rows and rows["pose"]:
        pose = np.asarray(sorted(rows["pose"]), dtype=np.float64)
        quat, valid = interpolate_quat(pose[:, 0], pose[:, 1:5], t, max_nearest_s=0.05, max_bracket_s=0.1)
        arrays["quat"] = np.where(valid[:, None], quat, np.nan)
    attrs = dict(cfg.get("declare") or {})
    return build(path, name, arrays, attrs, dataset="rosbag")
