"""Simulator of the polar INS/GNSS paper's experiments: an aircraft on a great circle at constant
speed with a navigation-grade IMU (200 Hz) and 1 Hz GNSS, seeded.

Truth (analytic, so the IMU is exact to round-off): a great circle of the sphere through the start
point, ``r(t) = |r_0| (cos theta a + sin theta b)``, ``theta = V t / |r_0|``, with ``a`` the start
direction and ``b`` the start heading's tangent; body axes forward (along the velocity), left,
up (geocentric radial, within 0.2 deg of the geodetic up), so ``omega_eb^b = [0, V / |r_0|, 0]``.
The IMU follows from the ECEF dynamics with the WGS-84 normal gravity the INS uses:
``f = C_e^b (r'' + 2 Omega x r' - g^e)``, ``omega_ib^b = C_e^b [0, 0, Omega] + omega_eb^b``. The
height varies slowly (a sphere over the ellipsoid: a few hundred metres per 1000 km at mid latitude).

Sensor errors (the paper's: gyro bias 0.01 deg/h, accelerometer bias 20 ug, GNSS < 10 m): constant
biases drawn per axis N(0, bias), white noise of the ARW / VRW of :class:`tcn_ahrs.nav.ins.InsNoise`,
GNSS white per ECEF axis.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict

import numpy as np

from . import earth
from .ins import InsNoise, preintegrate

UG = 1e-6 * 9.80665
DEG_PER_H = math.radians(1.0) / 3600.0


@dataclass(frozen=True)
class Flight:
    """A great-circle flight (angles in degrees, as a user states them)."""

    lat: float
    lon: float
    heading: float           # deg clockwise from north
    hours: float
    height: float = 10000.0  # m
    speed: float = 200.0     # m/s


@dataclass(frozen=True)
class ImuGrade:
    gyro_bias: float = 0.01 * DEG_PER_H        # rad/s (1 sigma per axis)
    accel_bias: float = 20.0 * UG              # m/s^2
    gyro_arw: float = InsNoise().gyro_arw      # rad/sqrt(s)
    accel_vrw: float = InsNoise().accel_vrw    # m/s/sqrt(s)
    rate: float = 200.0                        # Hz
    gnss_std: float = InsNoise().gnss_std      # m per ECEF axis
    gnss_rate: float = 1.0                     # Hz


def great_circle(flight: Flight, t: np.ndarray) -> Dict[str, np.ndarray]:
    """Truth at times t (N,): ``r_e``, ``v_e``, ``a_e`` (N, 3), ``C_be`` (N, 3, 3), ``w_eb_b`` (3,)."""
    L0, l0 = math.radians(flight.lat), math.radians(flight.lon)
    r0 = earth.ecef(np.array(L0), np.array(l0), np.array(flight.height))
    rad = float(np.linalg.norm(r0))
    a = r0 / rad
    C_en = earth.enu_from_ecef(np.array(L0), np.array(l0))
    north, east = C_en[1], C_en[0]
    north = north - (north @ a) * a
    north /= np.linalg.norm(north)
    psi = math.radians(flight.heading)
    b = math.cos(psi) * north + math.sin(psi) * east
    b /= np.linalg.norm(b)
    w = flight.speed / rad
    th = w * t
    c, s = np.cos(th)[:, None], np.sin(th)[:, None]
    up = c * a + s * b
    fwd = -s * a + c * b
    left = np.cross(up, fwd)
    return {"r_e": rad * up, "v_e": flight.speed * fwd, "a_e": -w * flight.speed * up,
            "C_be": np.stack([fwd, left, up], -1), "w_eb_b": np.array([0.0, w, 0.0])}


def ideal_imu(flight: Flight, t: np.ndarray) -> Dict[str, np.ndarray]:
    """Error-free gyro (rad/s) and specific force (m/s^2) in the body frame at times t, plus the truth."""
    tr = great_circle(flight, t)
    lat, lon, h = earth.geodetic(tr["r_e"])
    up = earth.enu_from_ecef(lat, lon)[:, 2]
    g_e = -earth.gravity(lat, h)[:, None] * up
    Om = np.array([0.0, 0.0, earth.OMEGA])
    f_e = tr["a_e"] + 2.0 * np.cross(Om, tr["v_e"]) - g_e
    C_eb = np.swapaxes(tr["C_be"], -1, -2)
    tr["acc"] = (C_eb @ f_e[..., None])[..., 0]
    tr["gyro"] = (C_eb @ Om) + tr["w_eb_b"]
    tr.update(lat=lat, lon=lon, h=h)
    return tr


def simulate_flight(flight: Flight, seed: int, nav_rate: float = 20.0, imu: ImuGrade = ImuGrade(),
                    chunk_s: float = 600.0) -> Dict[str, np.ndarray]:
    """IMU increments at ``nav_rate`` (from the 200 Hz samples, :func:`preintegrate`), GNSS, truth.
    Returns ``dtheta``, ``dv`` (K, 3), ``dt`` (nav period), ``gnss`` (K // gnss_every, 3) ECEF,
    ``gnss_every``, truth at the end of each nav step: ``r_e`` (K, 3), ``C_bn`` (K, 3, 3), ``lat``,
    ``lon``, ``h`` (K,), the start ``r0_e``, ``C_bn0``, ``v0_n``, and ``gyro_bias``, ``accel_bias`` (3,)."""
    rng = np.random.default_rng(seed)
    k = int(round(imu.rate / nav_rate))
    dt_imu = 1.0 / imu.rate
    n_total = int(round(flight.hours * 3600.0 * imu.rate)) // k * k
    gyro_bias = rng.standard_normal(3) * imu.gyro_bias
    accel_bias = rng.standard_normal(3) * imu.accel_bias
    per = max(int(chunk_s * imu.rate) // k * k, k)
    dth, dvs = [], []
    for start in range(0, n_total, per):
        n = min(per, n_total - start)
        t_mid = (start + np.arange(n) + 0.5) * dt_imu
        ideal = ideal_imu(flight, t_mid)
        gyro = ideal["gyro"] + gyro_bias + rng.standard_normal((n, 3)) * imu.gyro_arw / math.sqrt(dt_imu)
        acc = ideal["acc"] + accel_bias + rng.standard_normal((n, 3)) * imu.accel_vrw / math.sqrt(dt_imu)
        a, b = preintegrate(gyro, acc, dt_imu, k)
        dth.append(a)
        dvs.append(b)
    dtheta, dv = np.concatenate(dth), np.concatenate(dvs)
    K = dtheta.shape[0]
    dt = k * dt_imu
    t_nav = np.arange(0, K + 1) * dt
    truth = great_circle(flight, t_nav)
    lat, lon, h = earth.geodetic(truth["r_e"])
    C_en = earth.enu_from_ecef(lat, lon)
    C_bn = C_en @ truth["C_be"]
    v_n = (C_en @ truth["v_e"][..., None])[..., 0]
    gnss_every = int(round(nav_rate / imu.gnss_rate))
    g_idx = np.arange(gnss_every, K + 1, gnss_every)
    gnss = truth["r_e"][g_idx] + rng.standard_normal((len(g_idx), 3)) * imu.gnss_std
    return {"dtheta": dtheta, "dv": dv, "dt": dt, "gnss": gnss, "gnss_every": gnss_every,
            "r_e": truth["r_e"][1:], "C_bn": C_bn[1:], "v_n": v_n[1:], "lat": lat[1:], "lon": lon[1:], "h": h[1:],
            "r0_e": truth["r_e"][0], "C_bn0": C_bn[0], "v0_n": v_n[0], "lat0": lat[0], "lon0": lon[0], "h0": h[0],
            "gyro_bias": gyro_bias, "accel_bias": accel_bias, "flight": flight}


__all__ = ["Flight", "ImuGrade", "great_circle", "ideal_imu", "simulate_flight", "UG", "DEG_PER_H"]
