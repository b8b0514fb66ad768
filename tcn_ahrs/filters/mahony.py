"""Mahony's explicit complementary filter with integral gyro-bias estimation.

R. Mahony, T. Hamel, J.-M. Pflimlin, "Nonlinear Complementary Filters on the Special
Orthogonal Group", IEEE TAC 53(5), 2008, Eq. 32 (explicit CF), written as in the PyPI
``ahrs`` package (``ahrs.filters.Mahony``, v0.4.0), whose navigation frame for Mahony is
ENU-like (x east, y north, z up; it compares the normalised specific force with
``R^T [0, 0, 1]`` and the field with ``R^T [0, |h_xy|, h_z]``, north along +y) - the same as ours:

* ``v_a = R^T up``, ``h = R m^``, ``v_m = R^T [0, |h_xy|, h_z] / |.|``
  (the reference field is the measured one, rotated to nav and turned to magnetic north,
  so the magnetometer's dip never affects the tilt),
* ``omega_mes = a^ x v_a + m^ x v_m``   (measured x predicted, as ECF Eq. 5),
* ``b_k = b_{k-1} - k_I omega_mes dt``  (integral term; bias updated before it is used),
* ``Omega = omega - b_k + k_P omega_mes``,
* ``compat=True``: ``q_k = normalize(q + 0.5 q (x) [0, Omega] dt)`` (ahrs, first-order);
  ``compat=False`` (default): ``q_k = q (x) exp(Omega dt)`` (exact for a constant rate).

Units: ``k_P`` 1/s, ``k_I`` 1/s^2, so the filter behaves the same at any sampling rate.
Quirk of ahrs not reproduced: it skips a sample whose gyro reading is exactly zero.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional

import torch
from torch import Tensor

from .. import so3
from ..kernels.params import knob
from .compiled import mahony_loop, use_compiled
from .common import converter_like, flatten_batch, normalize, unflatten


@dataclass
class MahonyParams:
    """Mahony's parameters, meaning, unit and default once: read by :func:`mahony` and the
    estimator registry (:class:`tcn_ahrs.estimators.classical.Mahony`)."""

    k_p: float = knob(1.0, "1/s", "the proportional gain", (0.01, 10.0), grid=[0.1, 0.3, 1.0, 3.0])
    k_i: float = knob(0.3, "1/s²", "the integral (gyro bias) gain", (1e-4, 1.0), grid=[0.0, 0.01, 0.1, 0.3])
    compat: bool = knob(False, "flag", "``ahrs.filters.Mahony``'s update order, for the cross-check")


_MAHONY = MahonyParams()


def mahony(
    gyro: Tensor,
    accel: Tensor,
    dt: Tensor,
    q0: Tensor,
    mag: Optional[Tensor] = None,
    k_p=_MAHONY.k_p,
    k_i=_MAHONY.k_i,
    bias0: Optional[Tensor] = None,
    compat: bool = _MAHONY.compat,
    backend: str = "auto",
) -> Dict[str, Tensor]:
    """Run the Mahony filter.

    Args:
        gyro, accel, mag: (..., N, 3) rad/s, m/s^2, uT (body); ``mag=None`` for 6-axis.
        dt:   (..., N) s, time step before each sample (``dt[..., 0]`` unused).
        q0:   (..., 4) initial nav_from_body (magnetic ENU when mag is used).
        k_p:  proportional gain, 1/s (default 1.0, as ahrs).
        k_i:  integral gain, 1/s^2 (default 0.3, as ahrs); 0 disables bias estimation.
        bias0: (..., 3) initial gyro bias, rad/s (default 0).
        compat: integrate like ahrs (first-order + normalisation) instead of the exponential map.
        backend: ``"auto"``: the compiled loop (:mod:`tcn_ahrs.filters.compiled`) when nothing needs a
            gradient and all is float64 on the CPU; ``"torch"`` / ``"numba"`` force one.
    Returns:
        ``quat`` (..., N, 4); ``gyro_bias`` (..., N, 3) rad/s (the bias estimate after sample k).
    """
    T = converter_like(gyro)
    gyro, accel, dt, q0, mag = T(gyro), T(accel), T(dt), T(q0), T(mag)
    bias0 = T(torch.zeros(3) if bias0 is None else bias0)
    batch, flat = flatten_batch(
        [(gyro, 2), (accel, 2), (dt, 1), (q0, 1), (mag, 2), (bias0, 1), (T(k_p), 0), (T(k_i), 0)]
    )
    gyro, accel, dt, q0, mag, b, k_p, k_i = flat
    n = gyro.shape[1]
    a_hat = normalize(accel)
    m_hat = None if mag is None else normalize(mag)
    k_p, k_i = k_p[:, None], k_i[:, None]

    if use_compiled(backend, gyro, accel, dt, q0, mag, b, k_p, k_i):
        npy = lambda t: t.detach().contiguous().numpy()  # noqa: E731
        B = gyro.shape[0]
        qs, bs = mahony_loop(npy(a_hat), npy(m_hat if m_hat is not None else torch.zeros_like(gyro)), npy(gyro), npy(dt),
                             npy(q0), npy(k_p[:, 0].expand(B)), npy(k_i[:, 0].expand(B)), npy(b), m_hat is not None,
                             bool(compat))
        res = {"quat": torch.from_numpy(qs), "gyro_bias": torch.from_numpy(bs)}
        return {k: unflatten(v, batch) for k, v in res.items()}
    q = so3.quat_normalize(q0)
    b = b.clone()
    qs, bs = [q], [b]
    zero = torch.zeros_like(q[:, :1])
    for k in range(1, n):
        r = so3.quat_to_matrix(q)
        w = torch.cross(a_hat[:, k], r[:, 2, :], dim=-1)  # a^ x R^T up
        if m_hat is not None:
            h = (r @ m_hat[:, k, :, None])[..., 0]  # field in nav
            ref = torch.stack([torch.zeros_like(h[:, 0]), torch.linalg.vector_norm(h[:, :2], dim=-1), h[:, 2]], -1)
            v_m = normalize((r.transpose(-1, -2) @ ref[..., None])[..., 0])
            w = w + torch.cross(m_hat[:, k], v_m, dim=-1)
        d = dt[:, k, None]
        b = b - k_i * w * d
        omega = gyro[:, k] - b + k_p * w
        if compat:
            q = so3.quat_normalize(q + 0.5 * so3.quat_mul(q, torch.cat([zero, omega], -1)) * d)
        else:
            q = so3.quat_normalize(so3.quat_mul(q, so3.quat_exp(omega * d)))
        qs.append(q)
        bs.append(b)
    res = {"quat": torch.stack(qs, 1), "gyro_bias": torch.stack(bs, 1)}
    return {k: unflatten(v, batch) for k, v in res.items()}
