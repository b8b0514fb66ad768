"""Per-device errors (scale, misalignment, biases) and magnetic disturbances."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...conventions import DEG
from .params import Environment, SensorErrorModel


# =============================================================================


@dataclass
class _Device:
    """Per-device constants drawn from ``device_seed`` (shared by every recording)."""

    k_gyro: np.ndarray
    k_acc: np.ndarray
    k_mag: np.ndarray
    gyro_bias: np.ndarray   # rad/s
    acc_bias: np.ndarray    # m/s^2
    hard_iron: np.ndarray   # uT
    gyro_g_sens: np.ndarray = None  # (3, 3) rad/s per g of specific force


def _k_matrix(rng, scale_std, mis_std) -> np.ndarray:
    k = np.eye(3) + np.diag(rng.normal(0.0, scale_std, 3))
    off = rng.normal(0.0, mis_std, (3, 3))
    np.fill_diagonal(off, 0.0)
    return k + off


def draw_device(device_seed: int, p: SensorErrorModel) -> _Device:
    rng = np.random.default_rng([int(device_seed), 0xDE71CE])
    k_gyro = _k_matrix(rng, p.gyro_scale_std, p.gyro_misalignment_std)
    k_acc = _k_matrix(rng, p.acc_scale_std, p.acc_misalignment_std)
    k_mag = _k_matrix(rng, p.mag_scale_std, p.mag_misalignment_std)
    lo, hi = p.gyro_bias_range_dps
    gyro_bias = rng.choice([-1.0, 1.0], 3) * rng.uniform(lo, hi, 3) * DEG
    acc_bias = rng.normal(0.0, p.acc_bias_std, 3)
    hard_iron = rng.normal(0.0, p.hard_iron_std_ut, 3)
    # drawn last, so a device without it reads the same numbers as before the parameter existed
    g_sens = rng.normal(0.0, p.gyro_g_sensitivity_dps * DEG, (3, 3)) if p.gyro_g_sensitivity_dps else np.zeros((3, 3))
    return _Device(k_gyro, k_acc, k_mag, gyro_bias, acc_bias, hard_iron, g_sens)


def bias_track(unit_normal: np.ndarray, dt: float, static: np.ndarray, rw: float) -> np.ndarray:
    """(N, 3) static bias plus a random walk starting at 0 (increments ``rw sqrt(dt) n_k``,
    from the (N, 3) standard normals ``unit_normal``)."""
    steps = unit_normal * (rw * math.sqrt(dt))
    steps[0] = 0.0
    return static + np.cumsum(steps, axis=0)


def mag_disturbance(rng, t: np.ndarray, env: Environment, not_before: float) -> np.ndarray:
    """(N, 3) transient external field in ENU (uT): dipole pass-bys
    ``peak * u * ((1 + x^2)^(-3/2) - c) / (1 - c)`` with ``x = (t - t_c)/tau``, cut at
    ``|x| = 3`` (``c = 10^(-3/2)`` keeps the field continuous)."""
    n = t.shape[0]
    d = np.zeros((n, 3))
    duration = float(t[-1] - t[0])
    count = int(round(env.mag_disturbances_per_minute * duration / 60.0))
    if count <= 0:
        return d
    cut = 10.0 ** -1.5
    for _ in range(count):
        tau = rng.uniform(*env.mag_disturbance_tau_s)
        peak = rng.uniform(*env.mag_disturbance_peak_ut)
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        # the whole pulse lies after ``not_before`` (when the recording is long enough)
        tc = rng.uniform(min(not_before + 3 * tau, t[-1]), t[-1])
        a, b = np.searchsorted(t, [tc - 3 * tau, tc + 3 * tau])
        x = (t[a:b] - tc) / tau
        shape = np.clip(((1.0 + x * x) ** -1.5 - cut) / (1.0 - cut), 0.0, None)
        d[a:b] += peak * shape[:, None] * u
    return d


# =============================================================================
