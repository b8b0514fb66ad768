"""Closed-loop Extended Complementary Filter (ECF), paper Section 2 (Eqs. 4-8).

Paper (tcn-ecf-ahrs, NED, accelerometer read as gravity) -> this code (ENU, specific force):

* Eq. 4 (discrete, as Eq. 3): ``C_k = C_{k-1} exp([(omega_k + K e_k) x] dt_k)``.
* Eq. 5: ``e_a = a/|a| x (C_{k-1}^T up)`` with ``up = [0, 0, 1]``. At rest the specific force
  points up, so measured and predicted vectors both point up and ``e_a`` is the rotation
  (body frame) that turns the prediction toward the measurement: the same sign as
  Mahony's ``v_meas x v_pred`` (the correction ``omega + K e`` rotates the estimate so the
  predicted vector follows the measured one; tested in ``tests/test_filters.py``).
* Eq. 6: the paper uses ``(a x m)/|a x m|`` vs ``[0, 1, 0]`` (east in NED, with ``a`` pointing
  down). In ENU with ``a`` pointing up, east is ``north x up``, i.e. the measured east
  direction is ``(m x a)/|m x a|`` and the reference ``C^T [1, 0, 0]``:
  ``e_m = (m x a)/|m x a| x (C_{k-1}^T east)``. Using the cross product with ``a`` removes the
  vertical (dip) component of the field, so ``e_m`` only corrects heading (to first order).
* Eq. 7: ``e = e_a + e_m`` if ``| |a| - g | < a_min`` and ``m_min < |m| < m_max``;
  ``e = e_a`` if only the accelerometer test passes; ``e = 0`` otherwise.
* Eq. 8: ``K`` ramps linearly from ``K_init`` at t = 0 to ``K_norm`` at ``t_init``.

The magnetometer reference is magnetic east; see :func:`tcn_ahrs.filters.common.magnetic_from_nav`
for running in another heading reference.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional

import torch
from torch import Tensor

from .. import so3
from ..kernels.params import knob
from ..conventions import GRAVITY
from .compiled import ecf_loop, use_compiled
from .common import converter_like, elapsed, field_gates, flatten_batch, gain_schedule, normalize, unflatten


@dataclass
class ECFParams:
    """The ECF's parameters, meaning, unit and default once: read by :func:`ecf`, the estimator
    registry (:class:`tcn_ahrs.estimators.classical.ECF`) and its tuning grid."""

    k_norm: float = knob(0.5, "1/s", "the steady-state correction gain (Eq. 8)", (0.01, 5.0),
                          grid=[0.05, 0.1, 0.2, 0.5, 1.0, 2.0])
    k_init: float = knob(10.0, "1/s", "the gain at the start, decaying to k_norm over t_init")
    t_init: float = knob(3.0, "s", "the start's length")
    a_min: float = knob(1.0, "m/s²", "the accelerometer used while | |a| - g | < a_min (Eq. 7)", (0.1, 5.0),
                         grid=[0.3, 1.0, 3.0])
    m_min: float = knob(20.0, "µT", "the magnetometer used while its norm lies in [m_min, m_max]")
    m_max: float = knob(70.0, "µT", "the magnetometer's largest norm used")


_ECF = ECFParams()


def ecf(
    gyro: Tensor,
    accel: Tensor,
    dt: Tensor,
    q0: Tensor,
    mag: Optional[Tensor] = None,
    k_norm=_ECF.k_norm,
    k_init=_ECF.k_init,
    t_init=_ECF.t_init,
    a_min=_ECF.a_min,
    m_min=_ECF.m_min,
    m_max=_ECF.m_max,
    gravity: float = GRAVITY,
    backend: str = "auto",
) -> Dict[str, Tensor]:
    """Run the closed-loop ECF.

    Args:
        gyro:  (..., N, 3) angular rate, body, rad/s. Sample k moves the attitude from k-1 to k.
        accel: (..., N, 3) specific force, body, m/s^2.
        dt:    (..., N) time step before each sample, s (``dt[..., 0]`` unused).
        q0:    (..., 4) attitude at sample 0 (nav_from_body, w,x,y,z, magnetic ENU when mag is used).
        mag:   (..., N, 3) magnetic field, body, uT, or None (6-axis: only ``e_a``).
        k_norm:  gain after the initialisation, 1/s (Eq. 8 ``K_norm``); default 0.5.
        k_init:  gain at t = 0, 1/s (``K_init``); default 10.
        t_init:  length of the gain ramp, s; default 3.
        a_min:   accelerometer rejection threshold on ``| |a| - g |``, m/s^2 (Eq. 7); default 1.0.
        m_min, m_max: accepted magnetic field norm range, uT (Eq. 7); default 20..70.
        gravity: ``|g|`` in m/s^2.
        backend: ``"auto"`` runs the loop compiled (:mod:`tcn_ahrs.filters.compiled`, numba) when
            nothing needs a gradient and all is float64 on the CPU; ``"torch"`` / ``"numba"`` force one.
        Parameters broadcast as batch tensors (scalars, (P,), ...).
    Returns:
        ``quat`` (..., N, 4); ``acc_used``, ``mag_used`` (..., N) bool (Eq. 7 decisions);
        ``gain`` (..., N) the scheduled K (1/s).
    """
    T = converter_like(gyro)
    gyro, accel, dt, q0, mag = T(gyro), T(accel), T(dt), T(q0), T(mag)
    params = [T(p) for p in (k_norm, k_init, t_init, a_min, m_min, m_max)]
    batch, flat = flatten_batch(
        [(gyro, 2), (accel, 2), (dt, 1), (q0, 1), (mag, 2)] + [(p, 0) for p in params]
    )
    gyro, accel, dt, q0, mag, k_norm, k_init, t_init, a_min, m_min, m_max = flat
    n = gyro.shape[1]

    # Everything that depends on the measurements only is computed once, vectorised.
    a_hat = normalize(accel)
    acc_ok, mag_ok = field_gates(accel, mag, a_min[:, None], m_min[:, None], m_max[:, None], gravity)  # Eq. 7
    gain = gain_schedule(elapsed(dt), k_norm, k_init, t_init)  # Eq. 8
    w_acc = gain * acc_ok
    if mag is not None:
        east_b = normalize(torch.cross(mag, accel, dim=-1))  # Eq. 6 in ENU: (m x a)/|m x a|
        w_mag = gain * mag_ok

    r = so3.quat_to_matrix(q0)
    if use_compiled(backend, gyro, accel, dt, q0, mag, w_acc, *params):
        z = torch.zeros_like(gyro)
        npy = lambda t: t.detach().contiguous().numpy()  # noqa: E731
        quat = torch.from_numpy(ecf_loop(npy(a_hat), npy(east_b if mag is not None else z), npy(w_acc.to(gyro.dtype)),
                                         npy(w_mag.to(gyro.dtype) if mag is not None else z[..., 0]), npy(gyro),
                                         npy(dt), npy(r), mag is not None))
        res = {"quat": quat, "acc_used": acc_ok, "mag_used": mag_ok, "gain": gain}
        return {k: unflatten(v, batch) for k, v in res.items()}
    out = [r]
    for k in range(1, n):
        # C^T up is the third row of C, C^T east the first row.
        e = w_acc[:, k, None] * torch.cross(a_hat[:, k], r[:, 2, :], dim=-1)  # Eq. 5
        if mag is not None:
            e = e + w_mag[:, k, None] * torch.cross(east_b[:, k], r[:, 0, :], dim=-1)  # Eq. 6
        r = r @ so3.exp((gyro[:, k] + e) * dt[:, k, None])  # Eq. 4 discretised as Eq. 3
        out.append(r)
    quat = so3.matrix_to_quat(torch.stack(out, 1))
    res = {"quat": quat, "acc_used": acc_ok, "mag_used": mag_ok, "gain": gain}
    return {k: unflatten(v, batch) for k, v in res.items()}
