"""Madgwick's gradient-descent orientation filter (6- and 9-axis).

S. Madgwick, "An efficient orientation filter for inertial and inertial/magnetic sensor
arrays", 2010, Eqs. 12-13 (gyro rate), 25-34 (gradient step), 45-46 (magnetic reference);
written exactly as the PyPI ``ahrs`` package (``ahrs.filters.Madgwick``, v0.4.0):

* ``q_dot = 0.5 q (x) [0, omega] - beta grad / |grad|``, ``grad = J^T f`` (Eqs. 33-34),
* ``f = R^T up - a^`` (6-axis) and ``f_b = R^T b - m^`` with ``b = [b_x, 0, b_z]`` built from the
  measured field rotated to nav (Eqs. 45-46), stacked for 9-axis,
* ``q_k = normalize(q + q_dot dt)`` (Eq. 13).

Convention finding: ahrs' Madgwick works in a **NWU** navigation frame (x north, y west,
z up: the accelerometer's specific force is compared with ``+z`` and the horizontal field
is put on ``+x``), unlike its Mahony (ENU, field on ``+y``). The filter is equivariant under
a constant rotation of the navigation frame (a left-multiplied unit quaternion commutes
with the additive step, the gradient and the normalisation), so we run the ahrs equations
in NWU internally and convert at the boundaries: results in ENU are those of ahrs up to
round-off (tested against ahrs in ``tests/test_filters.py``).

``beta`` (rad/s) is the gradient step on the unit quaternion per second, so the filter is
sampling-rate independent. ahrs defaults: 0.033 (6-axis) and 0.041 (9-axis).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional

import torch
from torch import Tensor

from .. import so3
from ..kernels.params import knob
from .compiled import madgwick_loop, use_compiled
from .common import converter_like, flatten_batch, normalize, nwu_from_enu_quat, unflatten

BETA_IMU = 0.033   # rad/s, ahrs's default with 6 axes
BETA_MARG = 0.041  # rad/s, ... and with 9


@dataclass
class MadgwickParams:
    """Madgwick's parameter, meaning, unit and default once: read by :func:`madgwick`, the estimator
    registry (:class:`tcn_ahrs.estimators.classical.Madgwick`) and the family search."""

    beta: Optional[float] = knob(None, "rad/s", "the gradient-descent gain; None: BETA_IMU with 6 axes, "
                                 "BETA_MARG with 9 (ahrs's defaults)", (1e-3, 0.5),
                                 grid=[0.005, 0.01, 0.02, 0.033, 0.05, 0.1, 0.2])

    @staticmethod
    def default_beta(axes: int) -> float:
        return BETA_MARG if axes == 9 else BETA_IMU


def _gradient_imu(q: Tensor, a: Tensor) -> Tensor:
    qw, qx, qy, qz = q.unbind(-1)
    f = torch.stack([2.0 * (qx * qz - qw * qy) - a[:, 0],
                     2.0 * (qw * qx + qy * qz) - a[:, 1],
                     2.0 * (0.5 - qx * qx - qy * qy) - a[:, 2]], -1)
    z = torch.zeros_like(qw)
    # J^T f written out (J is 3x4, Madgwick Eq. 26)
    j = torch.stack([torch.stack([-2.0 * qy, 2.0 * qz, -2.0 * qw, 2.0 * qx], -1),
                     torch.stack([2.0 * qx, 2.0 * qw, 2.0 * qz, 2.0 * qy], -1),
                     torch.stack([z, -4.0 * qx, -4.0 * qy, z], -1)], -2)
    return (j.transpose(-1, -2) @ f[..., None])[..., 0]


def _gradient_marg(q: Tensor, a: Tensor, m: Tensor) -> Tensor:
    h = so3.quat_rotate(q, m)  # field in the (NWU) nav frame, Eq. 45
    bx = torch.linalg.vector_norm(h[:, :2], dim=-1)  # Eq. 46
    bz = h[:, 2]
    qw, qx, qy, qz = q.unbind(-1)
    f = torch.stack([
        2.0 * (qx * qz - qw * qy) - a[:, 0],
        2.0 * (qw * qx + qy * qz) - a[:, 1],
        2.0 * (0.5 - qx * qx - qy * qy) - a[:, 2],
        2.0 * bx * (0.5 - qy * qy - qz * qz) + 2.0 * bz * (qx * qz - qw * qy) - m[:, 0],
        2.0 * bx * (qx * qy - qw * qz) + 2.0 * bz * (qw * qx + qy * qz) - m[:, 1],
        2.0 * bx * (qw * qy + qx * qz) + 2.0 * bz * (0.5 - qx * qx - qy * qy) - m[:, 2]], -1)
    z = torch.zeros_like(qw)
    j = torch.stack([
        torch.stack([-2.0 * qy, 2.0 * qz, -2.0 * qw, 2.0 * qx], -1),
        torch.stack([2.0 * qx, 2.0 * qw, 2.0 * qz, 2.0 * qy], -1),
        torch.stack([z, -4.0 * qx, -4.0 * qy, z], -1),
        torch.stack([-2.0 * bz * qy, 2.0 * bz * qz, -4.0 * bx * qy - 2.0 * bz * qw, -4.0 * bx * qz + 2.0 * bz * qx], -1),
        torch.stack([-2.0 * bx * qz + 2.0 * bz * qx, 2.0 * bx * qy + 2.0 * bz * qw, 2.0 * bx * qx + 2.0 * bz * qz,
                     -2.0 * bx * qw + 2.0 * bz * qy], -1),
        torch.stack([2.0 * bx * qy, 2.0 * bx * qz - 4.0 * bz * qx, 2.0 * bx * qw - 4.0 * bz * qy, 2.0 * bx * qx], -1),
    ], -2)
    return (j.transpose(-1, -2) @ f[..., None])[..., 0]


def madgwick(
    gyro: Tensor,
    accel: Tensor,
    dt: Tensor,
    q0: Tensor,
    mag: Optional[Tensor] = None,
    beta=None,
    backend: str = "auto",
) -> Dict[str, Tensor]:
    """Run the Madgwick filter.

    Args:
        gyro, accel, mag: (..., N, 3) rad/s, m/s^2, uT (body); ``mag=None`` for 6-axis.
        dt:  (..., N) s, time step before each sample (``dt[..., 0]`` unused).
        q0:  (..., 4) initial nav_from_body in ENU (magnetic ENU when mag is used).
        beta: gradient-descent gain, rad/s; default 0.033 (6-axis) / 0.041 (9-axis) as ahrs.
        backend: ``"auto"``: the compiled loop (:mod:`tcn_ahrs.filters.compiled`) when nothing needs a
            gradient and all is float64 on the CPU; ``"torch"`` / ``"numba"`` force one.
    Returns:
        ``quat`` (..., N, 4) nav_from_body, ENU.
    """
    if beta is None:
        beta = MadgwickParams.default_beta(6 if mag is None else 9)
    T = converter_like(gyro)
    gyro, accel, dt, q0, mag = T(gyro), T(accel), T(dt), T(q0), T(mag)
    dtype = gyro.dtype
    batch, flat = flatten_batch([(gyro, 2), (accel, 2), (dt, 1), (q0, 1), (mag, 2), (T(beta), 0)])
    gyro, accel, dt, q0, mag, beta = flat
    n = gyro.shape[1]
    a_hat = normalize(accel)
    m_hat = None if mag is None else normalize(mag)
    beta = beta[:, None]

    c = nwu_from_enu_quat(dtype, gyro.device)  # NWU_from_ENU
    q = so3.quat_normalize(so3.quat_mul(c, q0))
    if use_compiled(backend, gyro, accel, dt, q0, mag, beta):
        npy = lambda t: t.detach().contiguous().numpy()  # noqa: E731
        B = gyro.shape[0]
        qs = madgwick_loop(npy(a_hat), npy(m_hat if m_hat is not None else torch.zeros_like(gyro)), npy(gyro), npy(dt),
                           npy(q), npy(beta[:, 0].expand(B)), m_hat is not None)
        quat = so3.quat_mul(so3.quat_conj(c), torch.from_numpy(qs))
        return {"quat": unflatten(quat, batch)}
    qs = [q]
    zero = torch.zeros_like(q[:, :1])
    for k in range(1, n):
        grad = _gradient_imu(q, a_hat[:, k]) if m_hat is None else _gradient_marg(q, a_hat[:, k], m_hat[:, k])
        grad = normalize(grad)
        q_dot = 0.5 * so3.quat_mul(q, torch.cat([zero, gyro[:, k]], -1)) - beta * grad
        q = so3.quat_normalize(q + q_dot * dt[:, k, None])
        qs.append(q)
    quat = so3.quat_mul(so3.quat_conj(c), torch.stack(qs, 1))
    return {"quat": unflatten(quat, batch)}
