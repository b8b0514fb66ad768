"""data=rosbag: a ROS 2 and a ROS 1 bag written here (sensor_msgs/Imu, sensor_msgs/MagneticField,
geometry_msgs/PoseStamped) load like the generic format: same arrays, same checks."""
from pathlib import Path

import numpy as np
import pytest

from tcn_ahrs.datasets import load_split
from tcn_ahrs.datasets.simulate import simulate
from tcn_ahrs.sequence import DataError

rosbags = pytest.importorskip("rosbags")


def _write(path: Path, seq, ros1: bool, pose_every: int = 2):
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    Imu, Mag = T["sensor_msgs/msg/Imu"], T["sensor_msgs/msg/MagneticField"]
    Pose, PoseStamped, Point = T["geometry_msgs/msg/Pose"], T["geometry_msgs/msg/PoseStamped"], T["geometry_msgs/msg/Point"]
    cov = np.zeros(9)
    if ros1:
        from rosbags.rosbag1 import Writer

        writer, ser = Writer(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer

        writer, ser = Writer(path, version=9), ts.serialize_cdr

    def header(t, seq_no):
        stamp = Time(sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))
        return Header(seq=seq_no, stamp=stamp, frame_id="imu") if ros1 else Header(stamp=stamp, frame_id="imu")

    t0 = 1000.0
    with writer as w:
        ci = w.add_connection("/imu/data", Imu.__msgtype__, typestore=ts)
        cm = w.add_connection("/imu/mag", Mag.__msgtype__, typestore=ts)
        cp = w.add_connection("/vicon/body", PoseStamped.__msgtype__, typestore=ts)
        for k in range(len(seq)):
            t = t0 + seq.time[k]
            ns = int(round(t * 1e9))
            g, a, m = seq.gyro[k], seq.accel[k], seq.mag[k] * 1e-6
            msg = Imu(header=header(t, k), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=cov,
                      angular_velocity=V3(x=g[0], y=g[1], z=g[2]), angular_velocity_covariance=cov,
                      linear_acceleration=V3(x=a[0], y=a[1], z=a[2]), linear_acceleration_covariance=cov)
            w.write(ci, ns, ser(msg, Imu.__msgtype__))
            w.write(cm, ns, ser(Mag(header=header(t, k), magnetic_field=V3(x=m[0], y=m[1], z=m[2]),
                                    magnetic_field_covariance=cov), Mag.__msgtype__))
            if k % pose_every == 0 and not 300 <= k < 340:  # a 0.4 s tracking loss
                q = seq.quat[k]
                pose = Pose(position=Point(x=0.0, y=0.0, z=0.0), orientation=Q(x=q[1], y=q[2], z=q[3], w=q[0]))
                w.write(cp, ns, ser(PoseStamped(header=header(t, k), pose=pose), PoseStamped.__msgtype__))


@pytest.mark.parametrize("ros1", [False, True], ids=["ros2", "ros1"])
def test_bag_loads_like_the_recording_it_was_written_from(tmp_path, ros1):
    seq = simulate("slow_rotation", 8.0, 100.0, seed=5)
    name = "run1.bag" if ros1 else "run1"
    _write(tmp_path / name, seq, ros1)
    cfg = {"name": "rosbag", "root": str(tmp_path), "split": "all", "axes": 9,
           "topics": {"imu": "/imu/data", "mag": "/imu/mag", "pose": "/vicon/body"}, "declare": {}}
    (got,) = load_split(cfg)
    assert got.name == "run1" and len(got) == len(seq)
    np.testing.assert_allclose(got.time - got.time[0], seq.time - seq.time[0], atol=1e-6)
    np.testing.assert_allclose(got.gyro, seq.gyro, atol=1e-12)
    np.testing.assert_allclose(got.accel, seq.accel, atol=1e-12)
    np.testing.assert_allclose(got.mag, seq.mag, rtol=1e-9)
    # ground truth at every other sample: slerped in between, masked across the tracking loss
    assert not got.quat_valid[310:330].any() and got.quat_valid[:290].all()
    ok = got.quat_valid
    dot = np.abs(np.sum(got.quat[ok] * seq.quat[ok], axis=1))
    assert np.degrees(2 * np.arccos(np.clip(dot, -1, 1))).max() < 0.05


def test_a_missing_topic_names_what_the_bag_has(tmp_path):
    seq = simulate("slow_rotation", 3.0, 100.0, seed=6)
    _write(tmp_path / "r", seq, ros1=False)
    cfg = {"name": "rosbag", "root": str(tmp_path), "split": "all", "topics": {"imu": "/imu"}, "declare": {}}
    with pytest.raises(DataError, match=r"topic '/imu' not in the bag; it has \['/imu/data', '/imu/mag', '/vicon/body'\]"):
        load_split(cfg)
