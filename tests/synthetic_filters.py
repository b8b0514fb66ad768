"""Synthetic recordings with exact ground truth for the classical-filter tests (test_filters,
test_tuning): a known attitude trajectory in ENU, specific force, field north and down."""
from __future__ import annotations

import numpy as np
import torch

from tcn_ahrs import so3
from tcn_ahrs.conventions import GRAVITY
from tcn_ahrs.sequence import ImuSequence

MAG_NAV = np.array([0.0, 20.0, -40.0])  # uT, ENU: north and down (dip ~63 deg)


def simulate(duration=20.0, rate=50.0, omega=None, bias=(0.0, 0.0, 0.0), acc_ext_nav=None, mag_dist_nav=None,
             gyro_std=0.005, acc_std=0.05, mag_std=0.3, seed=0, q_start=None):
    """Synthetic 9-axis recording with ground truth.

    omega: function t -> (N, 3) body rate (rad/s) or None (static). acc_ext_nav / mag_dist_nav:
    functions t -> (N, 3) external acceleration (m/s^2) / magnetic disturbance (uT) in nav.
    """
    rng = np.random.default_rng(seed)
    n = int(duration * rate)
    t = np.arange(n) / rate
    w = np.zeros((n, 3)) if omega is None else omega(t)
    r0 = torch.eye(3, dtype=torch.float64) if q_start is None else so3.quat_to_matrix(torch.as_tensor(q_start))
    rot = so3.integrate(r0, torch.as_tensor(w), torch.full((n,), 1.0 / rate, dtype=torch.float64)).numpy()
    f_nav = np.tile([0.0, 0.0, GRAVITY], (n, 1)) + (0 if acc_ext_nav is None else acc_ext_nav(t))
    m_nav = np.tile(MAG_NAV, (n, 1)) + (0 if mag_dist_nav is None else mag_dist_nav(t))
    accel = np.einsum("nji,nj->ni", rot, f_nav) + acc_std * rng.standard_normal((n, 3))
    mag = np.einsum("nji,nj->ni", rot, m_nav) + mag_std * rng.standard_normal((n, 3))
    gyro = w + np.asarray(bias) + gyro_std * rng.standard_normal((n, 3))
    quat = so3.matrix_to_quat(torch.as_tensor(rot)).numpy()
    return ImuSequence(name=f"sim{seed}", source=f"test simulate(seed={seed})", time=t, gyro=gyro, accel=accel,
                       mag=mag, quat=quat, rate=rate)


def wavy(t):
    return np.stack([0.6 * np.sin(0.7 * t), 0.4 * np.cos(1.1 * t), 0.5 * np.sin(0.3 * t + 1.0)], 1)
