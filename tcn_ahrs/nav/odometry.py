"""Error-state EKF for a ground robot without GNSS: IMU propagation, wheel-encoder velocity and
magnetometer attitude corrections (paper ``es-ekf-imu-encoder-magnetometer``; equation numbers
are the paper's). Batched over B runs, float64, pure torch.

Nominal state: position ``p`` (B, 3) m and velocity ``v`` (B, 3) m/s in ENU, attitude ``R``
(B, 3, 3) ``nav_from_body``. Error state ``dx = [dp, dv, dtheta]`` (9), ``dtheta`` in the body
frame (``R_true = R exp([dtheta]x)``, the injection of Eq. 16).

* Prediction (Eqs. 6-10), specific force ``a`` and rate ``w`` of the IMU::

      p <- p + v dt + (R a + g) dt^2 / 2,   v <- v + (R a + g) dt,   R <- R exp(w dt)
      P <- F_x P F_x^T + F_i Q_i F_i^T,     Q_i = diag(sigma_a^2 dt^2 I, sigma_w^2 dt^2 I)

  with ``g = [0, 0, -9.81]`` and ``F_x`` the Jacobian of the error kinematics (Eq. 5/8):
  ``dp' = dp + dv dt - R [a]x dtheta dt^2/2``, ``dv' = dv - R [a]x dtheta dt``,
  ``dtheta' = exp(w dt)^T dtheta``; ``F_i`` puts the noises on dv and dtheta (Eq. 9).
* Measurement (Eqs. 11-14): the horizontal velocity from the wheels rotated by the magnetometer
  heading, ``[v_x, v_y] = (v_L + v_R)/2 [cos, sin](theta_m)`` (Eqs. 21-22), and the attitude
  the magnetometer (with the accelerometer's tilt) gives. The paper's H = diag(0,0,0,1,1,0,1,1,1)
  observes exactly these five components; here they are the five rows of H (the zero rows carry
  no information). The attitude residual is ``Log(R^T R_meas)`` — the body-frame angle error the
  injection uses — rather than a difference of Euler angles, which wraps at ±180° and is
  singular at ±90° pitch.
* Gain Eq. 12, update Eq. 15, Joseph form Eq. 17 (:func:`tcn_ahrs.filters.kalman.kalman_update`),
  injection Eq. 16, reset Eqs. 18-20 (``G = diag(I, I, I - [dtheta/2]x)``).
* While the encoders drop out only the attitude rows update; while the magnetometer drops out
  the filter only predicts (the velocity of Eq. 21 needs the magnetometer's heading) — the paper's
  "otherwise it continues propagation".
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import torch
from torch import Tensor

from .. import so3
from ..conventions import GRAVITY
from ..filters.kalman import kalman_update, symmetrize


@dataclass(frozen=True)
class OdometryNoise:
    """Noise settings, defaults from the paper's Table 1 (Jackal) and Section 2.5.

    accel:   sigma_a, m/s^2 per sample (Eq. 10).
    gyro:    sigma_w, rad/s per sample (Eq. 10).
    vel:     sigma_v of the wheel velocity v_x, v_y, m/s (Eq. 13; Table 1's 0.001).
    att:     sigma_theta of the magnetometer attitude, rad (Eq. 13).
    init:    P_0 = init * I_9 (Section 2.5: 0.01).
    """

    accel: float = 0.005
    gyro: float = 0.005
    vel: float = 0.001
    att: float = 0.005
    init: float = 0.01


def wheel_speeds(v: Tensor, omega: Tensor, wheelbase: float) -> Tuple[Tensor, Tensor]:
    """Left and right wheel speeds of a differential drive, Eq. 22:
    ``v_L = v - omega L / 2``, ``v_R = v + omega L / 2`` (m/s)."""
    return v - omega * wheelbase / 2.0, v + omega * wheelbase / 2.0


def wheel_velocity(v_left: Tensor, v_right: Tensor, heading: Tensor) -> Tensor:
    """Horizontal ENU velocity (..., 2) from the wheel speeds and the heading theta_m (rad,
    counter-clockwise from east = the body x axis' yaw), Eq. 21."""
    v = 0.5 * (v_left + v_right)
    return torch.stack([v * torch.cos(heading), v * torch.sin(heading)], -1)


def predict(p: Tensor, v: Tensor, rot: Tensor, P: Tensor, acc: Tensor, gyro: Tensor, dt: Tensor,
            noise: OdometryNoise, gravity: float = GRAVITY) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """One prediction step (Eqs. 6-10). p, v (B, 3); rot (B, 3, 3); P (B, 9, 9); acc, gyro (B, 3)
    body; dt (B,) s. Returns (p, v, rot, P)."""
    g = torch.zeros_like(p)
    g[:, 2] = -gravity
    d = dt[:, None]
    a_nav = (rot @ acc[..., None])[..., 0] + g
    p_new = p + v * d + a_nav * (0.5 * d * d)
    v_new = v + a_nav * d
    inc = so3.exp(gyro * d)
    B = p.shape[0]
    eye = torch.eye(3, dtype=p.dtype, device=p.device).expand(B, 3, 3)
    zero = torch.zeros_like(eye)
    ra = rot @ so3.hat(acc)
    dd = d[..., None]
    F = torch.cat([torch.cat([eye, eye * dd, -0.5 * ra * dd * dd], -1),
                   torch.cat([zero, eye, -ra * dd], -1),
                   torch.cat([zero, zero, inc.transpose(-1, -2)], -1)], -2)
    q = torch.cat([torch.full((B, 3), noise.accel ** 2, dtype=p.dtype, device=p.device),
                   torch.full((B, 3), noise.gyro ** 2, dtype=p.dtype, device=p.device)], -1) * (d * d)
    Fi = torch.cat([torch.zeros(3, 6, dtype=p.dtype, device=p.device),
                    torch.eye(6, dtype=p.dtype, device=p.device)], 0)  # (9, 6), Eq. 9
    P_new = F @ P @ F.transpose(-1, -2) + Fi @ torch.diag_embed(q) @ Fi.T
    return p_new, v_new, rot @ inc, P_new


def correct(p: Tensor, v: Tensor, rot: Tensor, P: Tensor, dx: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Injection (Eq. 16) and reset (Eqs. 18-20) of an error estimate dx (B, 9)."""
    B = p.shape[0]
    dth = dx[:, 6:9]
    G = torch.eye(9, dtype=P.dtype, device=P.device).repeat(B, 1, 1)
    G[:, 6:9, 6:9] = G[:, 6:9, 6:9] - so3.hat(0.5 * dth)
    return p + dx[:, 0:3], v + dx[:, 3:6], rot @ so3.exp(dth), symmetrize(G @ P @ G.transpose(-1, -2))


def _observation(rot: Tensor, v: Tensor, vel_meas: Optional[Tensor], rot_meas: Tensor, noise: OdometryNoise):
    """Residual r, H and R of the attitude rows (and, with vel_meas, the velocity rows first)."""
    B = v.shape[0]
    r_att = so3.log(rot.transpose(-1, -2) @ rot_meas)
    H_att = torch.zeros(B, 3, 9, dtype=v.dtype, device=v.device)
    H_att[:, :, 6:9] = torch.eye(3, dtype=v.dtype, device=v.device)
    var = [torch.full((B, 3), noise.att ** 2, dtype=v.dtype, device=v.device)]
    if vel_meas is None:
        return r_att, H_att, torch.diag_embed(var[0])
    H_vel = torch.zeros(B, 2, 9, dtype=v.dtype, device=v.device)
    H_vel[:, 0, 3] = 1.0
    H_vel[:, 1, 4] = 1.0
    var.insert(0, torch.full((B, 2), noise.vel ** 2, dtype=v.dtype, device=v.device))
    r = torch.cat([vel_meas - v[:, :2], r_att], -1)
    return r, torch.cat([H_vel, H_att], 1), torch.diag_embed(torch.cat(var, -1))


def odometry_eskf(acc: Tensor, gyro: Tensor, dt: Tensor, v_left: Tensor, v_right: Tensor, mag_quat: Tensor,
                  p0: Tensor, v0: Tensor, q0: Tensor, encoders_ok: Optional[Tensor] = None,
                  mag_ok: Optional[Tensor] = None, noise: OdometryNoise = OdometryNoise(),
                  gravity: float = GRAVITY) -> Dict[str, Tensor]:
    """Run the filter over B runs of N samples.

    Args:
        acc, gyro: (B, N, 3) specific force m/s^2, rate rad/s (body).
        dt: (B, N) s, step before each sample (``dt[:, 0]`` unused).
        v_left, v_right: (B, N) wheel speeds, m/s.
        mag_quat: (B, N, 4) attitude from the magnetometer and accelerometer (w,x,y,z,
            nav_from_body; e.g. :func:`tcn_ahrs.filters.triad_quat` per sample).
        p0, v0: (B, 3) initial position m and velocity m/s; q0: (B, 4) initial attitude.
        encoders_ok, mag_ok: (B, N) bool availability (default: always).
        noise: :class:`OdometryNoise`.
    Returns:
        ``pos`` (B, N, 3), ``vel`` (B, N, 3), ``quat`` (B, N, 4), ``pos_std`` (B, N, 3) (sqrt of
        P's position diagonal); entry 0 = the initial state.
    """
    B, n = acc.shape[0], acc.shape[1]
    ones = torch.ones(B, n, dtype=torch.bool, device=acc.device)
    enc_ok = ones if encoders_ok is None else encoders_ok.bool()
    m_ok = ones if mag_ok is None else mag_ok.bool()
    rot_meas = so3.quat_to_matrix(so3.quat_normalize(mag_quat))
    heading = torch.atan2(rot_meas[..., 1, 0], rot_meas[..., 0, 0])  # yaw of the body x axis
    vel_meas = wheel_velocity(v_left, v_right, heading)
    p, v = p0.clone(), v0.clone()
    rot = so3.quat_to_matrix(so3.quat_normalize(q0))
    P = torch.eye(9, dtype=acc.dtype, device=acc.device).repeat(B, 1, 1) * noise.init
    ps, vs, rs, stds = [p], [v], [rot], [torch.diagonal(P, dim1=-2, dim2=-1)[:, :3].sqrt()]
    for k in range(1, n):
        p, v, rot, P = predict(p, v, rot, P, acc[:, k], gyro[:, k], dt[:, k], noise, gravity)
        # both rows where encoders and magnetometer report, attitude only where just the magnetometer;
        # each update is computed only when some run of the batch needs it (the common case: one)
        both = (enc_ok[:, k] & m_ok[:, k])[:, None]
        att = (m_ok[:, k] & ~enc_ok[:, k])[:, None]
        dx, P_new = p.new_zeros(B, 9), P
        if bool(att.any()):
            r, H, R = _observation(rot, v, None, rot_meas[:, k], noise)
            dx_att, P_att = kalman_update(P, r, H, R)
            dx = torch.where(att, dx_att, dx)
            P_new = torch.where(att[..., None], P_att, P_new)
        if bool(both.any()):
            r, H, R = _observation(rot, v, vel_meas[:, k], rot_meas[:, k], noise)
            dx_full, P_full = kalman_update(P, r, H, R)
            dx = torch.where(both, dx_full, dx)
            P_new = torch.where(both[..., None], P_full, P_new)
        P = P_new
        p, v, rot, P = correct(p, v, rot, P, dx)
        ps.append(p)
        vs.append(v)
        rs.append(rot)
        stds.append(torch.diagonal(P, dim1=-2, dim2=-1)[:, :3].clamp_min(0).sqrt())
    return {"pos": torch.stack(ps, 1), "vel": torch.stack(vs, 1),
            "quat": so3.quat_positive(so3.matrix_to_quat(torch.stack(rs, 1))), "pos_std": torch.stack(stds, 1)}
