"""Simulator of the ARCKF paper's experiment: a trolley at constant speed among four UWB beacons
on a 10 m x 5 m rectangle, with an x-IMU-like IMU (the paper's Table 1) and 2 Hz UWB ranges.

Routes (two laps each, as the paper's Fig. 8): ``rectangle`` (Route 1: 8 m x 3 m inside the
beacons, corners rounded to 0.5 m) and ``figure_eight`` (Route 2: two 2 m circles touching at the
centre). Motion: 2 s at rest (the filters' static initialisation), a 0.5 m/s^2 ramp to the
cruise speed, the route, a ramp down; integrated by :func:`tcn_ahrs.nav.diff_drive.planar_motion`
(the filters' discretisation).

Sensor errors: white noise of Table 1's densities (accelerometer 218 ug/sqrt(Hz), gyro
0.01 deg/s/sqrt(Hz)); constant zero-point offsets drawn uniformly within a fraction of Table 1's
(±50 mg, ±20 deg/s: the raw, uncalibrated limits; the paper's IMU was calibrated, so the
default draws within 10 % of them); ranges with white noise ``range_std``.

Outliers, as the paper injects them (the "dBW" of MATLAB's ``wgn``: variance ``10^(dBW/10)``):
``accel_outliers`` single IMU samples with white noise of 50 dBW (sigma 316 m/s^2) on every axis
(Route 1), and ``contaminated`` — a fraction of the ranges of beacons 2 and 4 (each) with white
noise of 20 dBW (sigma 10 m) (Route 2), optionally a positive NLOS bias instead (``nlos_bias``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from .diff_drive import planar_motion
from .odometry_baselines import euler_matrix

G0 = 9.80665


@dataclass(frozen=True)
class UwbSetup:
    """Geometry, rates and sensor errors (defaults: the paper's setting; heights our choice)."""

    beacons: Tuple[Tuple[float, float, float], ...] = ((0.0, 0.0, 2.0), (10.0, 0.0, 2.0), (10.0, 5.0, 2.0),
                                                       (0.0, 5.0, 2.0))
    tag_height: float = 0.8           # m
    speed: float = 0.5                # m/s, constant along the route
    imu_rate: float = 50.0            # Hz (not stated in the paper)
    uwb_rate: float = 2.0             # Hz (the paper's)
    range_std: float = 0.1            # m (the paper's sigma)
    accel_density: float = 218e-6 * G0   # m/s^2/sqrt(Hz) (Table 1)
    gyro_density: float = math.radians(0.01)  # rad/s/sqrt(Hz) (Table 1)
    accel_offset: float = 0.005 * G0  # m/s^2: offsets drawn uniformly within ± this (Table 1: 50 mg)
    gyro_offset: float = math.radians(2.0)  # rad/s (Table 1: 20 deg/s)


def _segments(route: str) -> List[Tuple[float, float]]:
    """(length m, curvature 1/m) of one lap."""
    if route == "rectangle":
        r, w, h = 0.5, 8.0, 3.0
        arc = (math.pi * r / 2.0, 1.0 / r)
        return [(w - 2 * r, 0.0), arc, (h - 2 * r, 0.0), arc, (w - 2 * r, 0.0), arc, (h - 2 * r, 0.0), arc]
    if route == "figure_eight":
        R = 2.0
        return [(2 * math.pi * R, 1.0 / R), (2 * math.pi * R, -1.0 / R)]
    raise ValueError(f"route: expected 'rectangle' or 'figure_eight', got {route!r}")


START = {"rectangle": ((1.5, 1.0), 0.0), "figure_eight": ((5.0, 2.5), math.pi / 2)}


def route_motion(route: str, setup: UwbSetup = UwbSetup(), laps: int = 2, rest_s: float = 2.0,
                 ramp: float = 0.5) -> Dict[str, np.ndarray]:
    """Noise-free motion along a route (see the module docstring): the output of
    :func:`planar_motion` plus ``laps`` and ``route``."""
    segs = _segments(route) * laps
    ends = np.cumsum([s for s, _ in segs])
    curv = np.array([c for _, c in segs])
    total, dt, vmax = float(ends[-1]), 1.0 / setup.imu_rate, setup.speed
    speed, s = [0.0] * int(rest_s * setup.imu_rate), 0.0
    v = 0.0
    while s < total - 1e-9:
        remaining = total - s
        if remaining <= v * v / (2 * ramp) + 1e-9:
            v = max(v - ramp * dt, 0.05)     # ramp down, never to a standstill before the end
        else:
            v = min(v + ramp * dt, vmax)
        step = min(v * dt, remaining)
        s += step
        speed.append(step / dt)
    speed += [0.0] * int(rest_s * setup.imu_rate / 2)
    speed = np.asarray(speed)
    dist = np.concatenate([[0.0], np.cumsum(speed[1:] * dt)])
    k = np.minimum(np.searchsorted(ends, dist - 0.5 * speed * dt, side="right"), len(segs) - 1)
    yaw_rate = curv[k] * speed
    (x0, y0), yaw0 = START[route]
    m = planar_motion(speed, yaw_rate, yaw0, setup.imu_rate, (x0, y0, setup.tag_height))
    m.update(route=route, laps=laps, speed=speed)
    return m


def simulate_uwb(route: str, seed: int, setup: UwbSetup = UwbSetup(), accel_outliers: int = 0,
                 accel_outlier_len: int = 1, contaminated: float = 0.0, contaminated_beacons: Sequence[int] = (1, 3),
                 nlos_bias: Optional[Tuple[float, float]] = None, laps: int = 2,
                 dropouts: Optional[Sequence[Tuple[int, float, float]]] = None) -> Dict[str, np.ndarray]:
    """One seeded run. ``accel_outliers``: that many 50 dBW accelerometer outliers spread over
    the route, each ``accel_outlier_len`` consecutive samples (1: the paper's; more: a burst); ``contaminated``: fraction of the ranges of ``contaminated_beacons``
    (0-based: the paper's beacons 2 and 4) with 20 dBW white noise, or with a positive bias drawn
    uniformly in ``nlos_bias`` (m) when given; ``dropouts``: (beacon, start s, duration s) with no
    range. Returns ``time``, ``pos``, ``vel`` (N, 3), ``rot`` (N, 3, 3), ``acc``, ``gyro`` (N, 3)
    measured, ``acc_true``, ``gyro_true``, ``ranges`` (N, n) (NaN between UWB epochs),
    ``range_outlier`` (N, n) bool, ``accel_outlier`` (N,) bool, ``accel_bias``, ``gyro_bias``
    (3,), ``beacons`` (n, 3), ``dt``."""
    rng = np.random.default_rng(seed)
    m = route_motion(route, setup, laps)
    n, dt = m["n"], m["dt"]
    beacons = np.asarray(setup.beacons, dtype=np.float64)
    accel_bias = rng.uniform(-1, 1, 3) * setup.accel_offset
    gyro_bias = rng.uniform(-1, 1, 3) * setup.gyro_offset
    acc = m["acc"] + accel_bias + setup.accel_density / math.sqrt(dt) * rng.standard_normal((n, 3))
    gyro = m["gyro"] + gyro_bias + setup.gyro_density / math.sqrt(dt) * rng.standard_normal((n, 3))
    accel_outlier = np.zeros(n, bool)
    if accel_outliers > 0:
        moving = np.flatnonzero(m["speed"] > 0.9 * setup.speed)
        at = moving[np.linspace(0, len(moving) - 1, accel_outliers + 2).astype(int)[1:-1]]
        at = np.unique(np.minimum((at[:, None] + np.arange(accel_outlier_len)[None]).ravel(), n - 1))
        acc[at] += math.sqrt(10 ** (50 / 10)) * rng.standard_normal((len(at), 3))
        accel_outlier[at] = True
    step = int(round(setup.imu_rate / setup.uwb_rate))
    epochs = np.arange(step, n, step)
    true_r = np.linalg.norm(m["pos"][epochs, None, :] - beacons[None], axis=-1)
    meas = true_r + setup.range_std * rng.standard_normal(true_r.shape)
    outl = np.zeros_like(meas, dtype=bool)
    if contaminated > 0:
        for b in contaminated_beacons:
            idx = rng.choice(len(epochs), int(round(contaminated * len(epochs))), replace=False)
            outl[idx, b] = True
            if nlos_bias is None:
                meas[idx, b] = np.abs(meas[idx, b] + math.sqrt(10 ** (20 / 10)) * rng.standard_normal(len(idx)))
            else:
                meas[idx, b] += rng.uniform(nlos_bias[0], nlos_bias[1], len(idx))
    if dropouts:
        t_ep = epochs * dt
        for b, start, dur in dropouts:
            meas[(t_ep >= start) & (t_ep < start + dur), b] = np.nan
    ranges = np.full((n, len(beacons)), np.nan)
    ranges[epochs] = meas
    range_outlier = np.zeros((n, len(beacons)), bool)
    range_outlier[epochs] = outl
    return {"time": m["time"], "pos": m["pos"], "vel": m["vel"], "rot": m["rot"], "acc": acc, "gyro": gyro,
            "acc_true": m["acc"], "gyro_true": m["gyro"], "ranges": ranges, "range_outlier": range_outlier,
            "accel_outlier": accel_outlier, "accel_bias": accel_bias, "gyro_bias": gyro_bias, "beacons": beacons,
            "dt": dt, "route": route}


def static_init(sim: Dict[str, np.ndarray], rest_s: float = 2.0, heading_error: float = 0.0) -> Dict[str, np.ndarray]:
    """The filters' start, as a user would get it: the trolley at rest for ``rest_s`` — tilt from
    the mean accelerometer, gyro bias from the mean gyro, heading the known start direction (+
    ``heading_error`` rad), position the known start point. Returns ``p0``, ``v0`` (3,), ``rot0``
    (3, 3), ``bias0`` (6,) = [b_a (0), b_g]."""
    k = int(rest_s / sim["dt"])
    a = sim["acc"][:k].mean(0)
    roll, pitch = math.atan2(a[1], a[2]), math.atan2(-a[0], math.hypot(a[1], a[2]))
    yaw = math.atan2(sim["rot"][0, 1, 0], sim["rot"][0, 0, 0]) + heading_error
    return {"p0": sim["pos"][0].copy(), "v0": np.zeros(3), "rot0": euler_matrix(np.array([roll, pitch, yaw]))[0],
            "bias0": np.concatenate([np.zeros(3), sim["gyro"][:k].mean(0)])}


__all__ = ["UwbSetup", "route_motion", "simulate_uwb", "static_init"]
