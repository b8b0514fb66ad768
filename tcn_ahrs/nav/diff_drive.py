"""Simulator of the odometry paper's experiment: a differential-drive robot (Jackal, the paper's
Table 1) driving a mine-corridor-like route, with IMU, wheel encoders and magnetometer.

Kinematics (planar, flat floor, per sample k at ``rate`` Hz): speed ``v_k`` and yaw rate
``w_k`` follow the route (straight corridor segments at cruise speed, turns at reduced speed,
smooth speed ramps); the state is integrated in the discretisation the filter's prediction
uses (Eq. 6), so a noise-free run is reproduced by :func:`tcn_ahrs.nav.odometry.predict` to
round-off (tested):

    R_k = R_{k-1} exp([0, 0, w_k] dt),   v_k = v_k [cos, sin, 0](yaw_k),
    a_k = R_{k-1}^T ((v_k - v_{k-1}) / dt + [0, 0, 9.81]),   p_k = p_{k-1} + (v_{k-1} + v_k) dt / 2.

Sensors: IMU with white noise (the paper's sigma_a, sigma_w) and a constant random bias per run;
wheel encoders as quantised wheel speeds (Eq. 22) with optional slip; a magnetometer seeing the
Earth's field plus local anomalies (steel in the mine) and white noise, turned into an attitude
with the accelerometer by TRIAD (:func:`tcn_ahrs.filters.triad_quat`). Seeded; any rate.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, List, Tuple

import numpy as np
import torch

from .. import so3
from ..conventions import GRAVITY
from ..filters.common import triad_quat
from .odometry import wheel_speeds


@dataclass(frozen=True)
class Robot:
    """The platform (the paper's Table 1): wheelbase L (m), speed limit (m/s)."""

    wheelbase: float = 0.262
    v_max: float = 0.62


@dataclass(frozen=True)
class Sensors:
    """Sensor errors. Noise stds per sample; biases drawn once per run (std); the encoder
    resolution in metres per tick turns into a speed quantum ``tick / dt``."""

    accel_noise: float = 0.005     # m/s^2 (Table 1)
    gyro_noise: float = 0.005      # rad/s (Table 1)
    accel_bias: float = 0.0        # m/s^2
    gyro_bias: float = 0.0         # rad/s
    mag_noise: float = 0.05        # uT
    encoder_tick: float = 1e-4     # m
    slip: float = 0.0              # relative wheel-speed error during slip bursts
    slip_fraction: float = 0.0     # share of samples inside slip bursts
    anomalies_per_100m: float = 0.0  # local magnetic anomalies (steel) along the route
    anomaly_ut: float = 10.0       # their peak field, uT


FIELD_UT = 50.0
DIP = math.radians(60.0)


def mine_route(rng: np.random.Generator, length: float) -> List[Tuple[float, float]]:
    """Corridor segments ``(straight metres, turn radians after it)`` adding up to ``length``:
    drifts of 20-60 m joined by turns of ±(45-90)°, as in a room-and-pillar mine."""
    segs, total = [], 0.0
    while total < length:
        s = float(min(rng.uniform(20.0, 60.0), length - total))
        segs.append((s, float(rng.choice([-1.0, 1.0]) * math.radians(rng.uniform(45.0, 90.0)))))
        total += s
    return segs


def _profile(segs, rate: float, cruise: float, turn_speed: float, turn_rate: float, ramp: float):
    """Speed and yaw-rate command per sample (piecewise, with speed ramps of ``ramp`` m/s^2)."""
    dt = 1.0 / rate
    v_cmd, w_cmd = [0.0] * int(2 * rate), [0.0] * int(2 * rate)  # 2 s at rest
    for straight, turn in segs:
        v_cmd += [cruise] * int(round(straight / cruise * rate))
        n_turn = int(round(abs(turn) / turn_rate * rate))
        v_cmd += [turn_speed] * n_turn
        w_cmd += [0.0] * (len(v_cmd) - n_turn - len(w_cmd)) + [math.copysign(turn_rate, turn)] * n_turn
    v_cmd += [0.0] * int(2 * rate)
    w_cmd += [0.0] * (len(v_cmd) - len(w_cmd))
    v = np.zeros(len(v_cmd))
    for k in range(1, len(v)):  # first-order speed ramp
        v[k] = v[k - 1] + float(np.clip(v_cmd[k] - v[k - 1], -ramp * dt, ramp * dt))
    return v, np.asarray(w_cmd)


def planar_motion(speed: np.ndarray, yaw_rate: np.ndarray, yaw0: float, rate: float, x0=(0.0, 0.0, 0.0)) -> Dict:
    """A body moving on a flat floor with forward speed ``speed`` (N,) m/s and yaw rate (N,)
    rad/s, integrated in the discretisation of the filters' prediction (Eq. 6 of the odometry
    paper; see the module docstring). Returns ``n``, ``dt``, ``time`` (N,), ``pos``, ``vel`` (N, 3)
    ENU, ``rot`` (N, 3, 3) nav_from_body, ``acc`` (N, 3) true specific force, ``gyro`` (N, 3)."""
    n, dt = len(speed), 1.0 / rate
    yaw = yaw0 + np.concatenate([[0.0], np.cumsum(yaw_rate[1:] * dt)])
    vel = np.stack([speed * np.cos(yaw), speed * np.sin(yaw), np.zeros(n)], -1)
    pos = np.zeros((n, 3)) + np.asarray(x0, dtype=np.float64)
    pos[1:] += np.cumsum(0.5 * (vel[1:] + vel[:-1]) * dt, 0)
    gyro = np.stack([np.zeros(n), np.zeros(n), yaw_rate], -1)
    r0 = so3.exp(torch.tensor([0.0, 0.0, yaw0], dtype=torch.float64))
    rot = so3.integrate(r0, torch.as_tensor(gyro), torch.full((n,), dt, dtype=torch.float64)).numpy()
    a_nav = np.zeros((n, 3))
    a_nav[1:] = (vel[1:] - vel[:-1]) / dt
    f_nav = a_nav + np.array([0.0, 0.0, GRAVITY])
    acc = np.zeros((n, 3))
    acc[1:] = np.einsum("nji,nj->ni", rot[:-1], f_nav[1:])  # R_{k-1}^T f_k (the filter's Eq. 6)
    acc[0] = rot[0].T @ f_nav[0]
    return {"n": n, "dt": dt, "time": np.arange(n) * dt, "pos": pos, "vel": vel, "rot": rot, "acc": acc, "gyro": gyro}


def simulate_drive(seed: int, rate: float = 50.0, length: float = 300.0, robot: Robot = Robot(),
                   sensors: Sensors = Sensors(), cruise: float = 0.5) -> Dict[str, np.ndarray]:
    """One run. Returns float64 arrays: ``time`` (N,), ``pos``, ``vel`` (N, 3) m, m/s ENU,
    ``quat`` (N, 4) nav_from_body, ``acc``, ``gyro``, ``mag`` (N, 3) body, ``v_left``,
    ``v_right`` (N,) m/s, ``mag_quat`` (N, 4) (TRIAD of acc and mag), ``slipping`` (N,) bool,
    ``accel_bias``, ``gyro_bias`` (3,) the run's constant IMU biases (m/s^2, rad/s)."""
    if cruise > robot.v_max:
        raise ValueError(f"cruise {cruise} m/s exceeds the robot's speed limit {robot.v_max} m/s")
    rng = np.random.default_rng(seed)
    segs = mine_route(rng, length)
    speed, yaw_rate = _profile(segs, rate, cruise, 0.5 * cruise, 0.5, 0.5)
    yaw0 = rng.uniform(-math.pi, math.pi)
    m = planar_motion(speed, yaw_rate, yaw0, rate)
    n, dt, pos, vel, rot, acc_true, gyro_true = (m[k] for k in ("n", "dt", "pos", "vel", "rot", "acc", "gyro"))
    accel_bias = sensors.accel_bias * rng.standard_normal(3)
    acc = acc_true + accel_bias + sensors.accel_noise * rng.standard_normal((n, 3))
    gyro_bias = sensors.gyro_bias * rng.standard_normal(3)
    gyro = gyro_true + gyro_bias + sensors.gyro_noise * rng.standard_normal((n, 3))
    m_nav = FIELD_UT * np.array([0.0, math.cos(DIP), -math.sin(DIP)])
    anomaly = np.zeros((n, 3))
    dist = np.concatenate([[0.0], np.cumsum(speed[1:] * dt)])
    n_anom = rng.poisson(sensors.anomalies_per_100m * length / 100.0) if sensors.anomalies_per_100m > 0 else 0
    for at in rng.uniform(0.0, dist[-1], n_anom):
        direction = rng.standard_normal(3)
        anomaly += (sensors.anomaly_ut * direction / np.linalg.norm(direction)) * np.exp(-0.5 * ((dist - at) / 2.0) ** 2)[:, None]
    mag = np.einsum("nji,nj->ni", rot, m_nav + anomaly) + sensors.mag_noise * rng.standard_normal((n, 3))
    v_l, v_r = wheel_speeds(torch.as_tensor(speed), torch.as_tensor(yaw_rate), robot.wheelbase)
    v_l, v_r = v_l.numpy(), v_r.numpy()
    slipping = np.zeros(n, dtype=bool)
    if sensors.slip_fraction > 0 and sensors.slip > 0:
        starts = rng.uniform(0, n, max(1, int(sensors.slip_fraction * n / rate)))
        for s in starts.astype(int):
            slipping[s:s + int(rate)] = True  # 1 s bursts
        v_l = np.where(slipping, v_l * (1.0 + sensors.slip), v_l)
        v_r = np.where(slipping, v_r * (1.0 + sensors.slip), v_r)
    quantum = sensors.encoder_tick / dt
    if quantum > 0:
        v_l, v_r = np.round(v_l / quantum) * quantum, np.round(v_r / quantum) * quantum
    mag_quat = triad_quat(torch.as_tensor(acc), torch.as_tensor(mag)).numpy()
    quat = so3.quat_positive(so3.matrix_to_quat(torch.as_tensor(rot))).numpy()
    return {"time": np.arange(n) * dt, "pos": pos, "vel": vel, "quat": quat, "acc": acc, "gyro": gyro,
            "mag": mag, "v_left": v_l, "v_right": v_r, "mag_quat": mag_quat, "slipping": slipping,
            "accel_bias": accel_bias, "gyro_bias": gyro_bias}
