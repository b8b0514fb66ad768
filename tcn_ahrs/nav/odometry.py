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

Beyond the paper (both off by default, so the defaults are the paper's filter):

* ``estimate_biases``: six more error states, accelerometer and gyro bias ``[dba, dbg]``
  (random walks), entering as ``dv' -= R dba dt``, ``dtheta' -= dbg dt`` — the paper's filter
  has none, and a constant accelerometer bias then integrates into position error.
* ``mag_gate_alpha``: a Mahalanobis gate on the magnetometer attitude (as the robust attitude
  ES-EKF's, :mod:`tcn_ahrs.filters.robust`): steel in a mine bends the field by tens of degrees.
  Above the gate, the field's plausibility decides (:func:`mag_plausible`: norm and dip as at the
  start): a disturbed field is dropped (the wheel velocity then rotated by the filter's own
  heading), an undisturbed one means the state is off and inflates P — without that test a gate
  locks out for good once the heading has drifted past it.
* ``vel_z``: a zero-vertical-velocity row (``v_z = 0`` with std ``vel_z``) for a robot on a
  floor; the paper's Table 1 gives the z platform speed a std of 10000 m/s, i.e. no row. Without
  it nothing observes the vertical channel, and any vertical accelerometer error is integrated
  twice.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Sequence, Tuple

import torch
from torch import Tensor

from .. import so3
from ..conventions import GRAVITY
from ..filters.kalman import chi2_threshold, kalman_update, symmetrize
from ..filters.robust import robust_inflation


@dataclass(frozen=True)
class OdometryNoise:
    """Filter settings, defaults from the paper's Table 1 (Jackal) and Section 2.5.

    accel:   sigma_a, m/s^2 per sample (Eq. 10).
    gyro:    sigma_w, rad/s per sample (Eq. 10).
    vel:     sigma_v of the wheel velocity v_x, v_y, m/s (Eq. 13; Table 1's 0.001).
    att:     sigma_theta of the magnetometer attitude, rad (Eq. 13).
    init:    P_0 = init * I (Section 2.5: 0.01).
    vel_z:   std of a zero-vertical-velocity row, m/s; ``None`` = no row (the paper: 10000).
    mag_gate_alpha: false-alarm rate of a Mahalanobis gate on the magnetometer attitude
             (chi-square, 3 dof), with the ARCKF paper's Algorithm 1
             (:func:`tcn_ahrs.filters.robust.robust_inflation`): above the gate a plausible
             field inflates P, an implausible one drops the attitude rows. ``None`` = no gate.
    estimate_biases: add accelerometer and gyro bias error states (not in the paper).
    accel_bias_walk, gyro_bias_walk: their random walks, m/s^2/sqrt(s), rad/s/sqrt(s).
    accel_bias_init, gyro_bias_init: their initial stds, m/s^2, rad/s.
    """

    accel: float = 0.005
    gyro: float = 0.005
    vel: float = 0.001
    att: float = 0.005
    init: float = 0.01
    vel_z: Optional[float] = None
    mag_gate_alpha: Optional[float] = None
    estimate_biases: bool = False
    accel_bias_walk: float = 1e-4
    gyro_bias_walk: float = 1e-5
    accel_bias_init: float = 0.05
    gyro_bias_init: float = 0.005

    @property
    def dim(self) -> int:
        """Error-state size: 9 (the paper's dp, dv, dtheta) or 15 (with the biases)."""
        return 15 if self.estimate_biases else 9

    def initial_cov(self, batch: int, dtype=torch.float64, device=None) -> Tensor:
        """P_0 (B, dim, dim): ``init * I`` on dp, dv, dtheta, the bias stds squared on the biases."""
        d = [self.init] * 9
        if self.estimate_biases:
            d += [self.accel_bias_init ** 2] * 3 + [self.gyro_bias_init ** 2] * 3
        return torch.diag(torch.tensor(d, dtype=dtype, device=device)).repeat(batch, 1, 1)


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
            noise: OdometryNoise, gravity: float = GRAVITY,
            bias: Optional[Tensor] = None) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """One prediction step (Eqs. 6-10). p, v (B, 3); rot (B, 3, 3); P (B, d, d) with d =
    ``noise.dim``; acc, gyro (B, 3) body; dt (B,) s; bias (B, 6) ``[b_a, b_g]`` subtracted from
    acc and gyro (with ``noise.estimate_biases``). Returns (p, v, rot, P)."""
    if bias is not None:
        acc, gyro = acc - bias[:, :3], gyro - bias[:, 3:]
    g = torch.zeros_like(p)
    g[:, 2] = -gravity
    d = dt[:, None]
    a_nav = (rot @ acc[..., None])[..., 0] + g
    p_new = p + v * d + a_nav * (0.5 * d * d)
    v_new = v + a_nav * d
    inc = so3.exp(gyro * d)
    B, n = p.shape[0], noise.dim
    kw = dict(dtype=p.dtype, device=p.device)
    eye = torch.eye(3, **kw).expand(B, 3, 3)
    dd = d[..., None]
    ra = rot @ so3.hat(acc)
    F = torch.eye(n, **kw).repeat(B, 1, 1)
    F[:, 0:3, 3:6] = eye * dd
    F[:, 0:3, 6:9] = -0.5 * ra * dd * dd
    F[:, 3:6, 6:9] = -ra * dd
    F[:, 6:9, 6:9] = inc.transpose(-1, -2)
    q = torch.cat([torch.full((B, 3), noise.accel ** 2, **kw), torch.full((B, 3), noise.gyro ** 2, **kw)], -1) * (d * d)
    if noise.estimate_biases:
        F[:, 0:3, 9:12] = -0.5 * rot * dd * dd
        F[:, 3:6, 9:12] = -rot * dd
        F[:, 6:9, 12:15] = -eye * dd
        q = torch.cat([q, torch.full((B, 3), noise.accel_bias_walk ** 2, **kw) * d,
                       torch.full((B, 3), noise.gyro_bias_walk ** 2, **kw) * d], -1)
    Fi = torch.zeros(n, n - 3, **kw)  # noises on dv, dtheta (Eq. 9) and the bias walks
    Fi[3:, :] = torch.eye(n - 3, **kw)
    P_new = F @ P @ F.transpose(-1, -2) + Fi @ torch.diag_embed(q) @ Fi.T
    return p_new, v_new, rot @ inc, P_new


def correct(p: Tensor, v: Tensor, rot: Tensor, P: Tensor, dx: Tensor,
            bias: Optional[Tensor] = None) -> Tuple[Tensor, ...]:
    """Injection (Eq. 16) and reset (Eqs. 18-20) of an error estimate dx (B, d). Returns
    (p, v, rot, P), plus the corrected bias (B, 6) when ``bias`` is given."""
    B, n = p.shape[0], P.shape[-1]
    dth = dx[:, 6:9]
    G = torch.eye(n, dtype=P.dtype, device=P.device).repeat(B, 1, 1)
    G[:, 6:9, 6:9] = G[:, 6:9, 6:9] - so3.hat(0.5 * dth)
    out = (p + dx[:, 0:3], v + dx[:, 3:6], rot @ so3.exp(dth), symmetrize(G @ P @ G.transpose(-1, -2)))
    return out if bias is None else out + (bias + dx[:, 9:15],)


def _rows(B: int, n: int, cols: Sequence[int], like: Tensor) -> Tensor:
    """H rows (B, len(cols), n) selecting the error-state components ``cols``."""
    H = like.new_zeros(B, len(cols), n)
    for i, c in enumerate(cols):
        H[:, i, c] = 1.0
    return H


def _observation(rot: Tensor, v: Tensor, vel_meas: Optional[Tensor], rot_meas: Optional[Tensor],
                 noise: OdometryNoise):
    """Residual r, H and R: the wheel velocity rows (with ``vel_meas``), the zero-vertical-velocity
    row (with ``noise.vel_z`` and ``vel_meas``), then the attitude rows (with ``rot_meas``);
    H of Eq. 14, R of Eq. 13."""
    B, n = v.shape[0], noise.dim
    res, cols, var = [], [], []
    if vel_meas is not None:
        res.append(vel_meas - v[:, :2])
        cols += [3, 4]
        var += [noise.vel ** 2] * 2
        if noise.vel_z is not None:
            res.append(-v[:, 2:3])
            cols.append(5)
            var.append(noise.vel_z ** 2)
    if rot_meas is not None:
        res.append(so3.log(rot.transpose(-1, -2) @ rot_meas))
        cols += [6, 7, 8]
        var += [noise.att ** 2] * 3
    R = torch.diag(torch.tensor(var, dtype=v.dtype, device=v.device)).expand(B, len(var), len(var))
    return torch.cat(res, -1), _rows(B, n, cols, v), R


def _yaw(rot: Tensor) -> Tensor:
    """Heading of the body x axis (rad, counter-clockwise from east)."""
    return torch.atan2(rot[..., 1, 0], rot[..., 0, 0])


def mag_plausible(acc: Tensor, mag: Tensor, rate: float, ref_seconds: float = 2.0, norm_tol: float = 1.5,
                  dip_tol_deg: float = 2.0) -> Tensor:
    """(B, N) bool: the magnetic field looks like the Earth's — its norm (uT) and dip (the angle
    to the accelerometer's up) within ``norm_tol`` and ``dip_tol_deg`` of their medians over the
    first ``ref_seconds`` (the robot at rest before it drives). acc, mag (B, N, 3) body."""
    norm = mag.norm(dim=-1)
    cos_dip = (acc * mag).sum(-1) / (acc.norm(dim=-1) * norm).clamp_min(1e-12)
    dip = torch.rad2deg(torch.asin(cos_dip.clamp(-1.0, 1.0)))
    k = max(1, int(ref_seconds * rate))
    return ((norm - norm[:, :k].median(1, keepdim=True).values).abs() < norm_tol) & \
        ((dip - dip[:, :k].median(1, keepdim=True).values).abs() < dip_tol_deg)


def odometry_eskf(acc: Tensor, gyro: Tensor, dt: Tensor, v_left: Tensor, v_right: Tensor, mag_quat: Tensor,
                  p0: Tensor, v0: Tensor, q0: Tensor, encoders_ok: Optional[Tensor] = None,
                  mag_ok: Optional[Tensor] = None, noise: OdometryNoise = OdometryNoise(),
                  gravity: float = GRAVITY, mag_field_ok: Optional[Tensor] = None) -> Dict[str, Tensor]:
    """Run the filter over B runs of N samples.

    Args:
        acc, gyro: (B, N, 3) specific force m/s^2, rate rad/s (body).
        dt: (B, N) s, step before each sample (``dt[:, 0]`` unused).
        v_left, v_right: (B, N) wheel speeds, m/s.
        mag_quat: (B, N, 4) attitude from the magnetometer and accelerometer (w,x,y,z,
            nav_from_body; e.g. :func:`tcn_ahrs.filters.triad_quat` per sample).
        p0, v0: (B, 3) initial position m and velocity m/s; q0: (B, 4) initial attitude.
        encoders_ok, mag_ok: (B, N) bool availability (default: always). Rows per sample: wheel
            velocity (and ``vel_z``) where both report, attitude alone where only the
            magnetometer does, nothing where it drops out (Eq. 21 needs its heading).
        noise: :class:`OdometryNoise`.
        mag_field_ok: (B, N) bool, the field plausible (:func:`mag_plausible`); only used by the
            gate (default: never plausible, i.e. every gated sample is dropped).
    Returns:
        ``pos`` (B, N, 3), ``vel`` (B, N, 3), ``quat`` (B, N, 4), ``pos_std`` (B, N, 3) (sqrt of
        P's position diagonal); entry 0 = the initial state; with ``noise.estimate_biases`` also
        ``bias`` (B, N, 6), the estimated ``[b_a, b_g]`` (m/s^2, rad/s); with
        ``noise.mag_gate_alpha`` also ``mag_rejected`` (B, N) bool (the attitude R inflated).
    """
    B, n = acc.shape[0], acc.shape[1]
    ones = torch.ones(B, n, dtype=torch.bool, device=acc.device)
    enc_ok = ones if encoders_ok is None else encoders_ok.bool()
    m_ok = ones if mag_ok is None else mag_ok.bool()
    rot_meas = so3.quat_to_matrix(so3.quat_normalize(mag_quat))
    vel_meas = wheel_velocity(v_left, v_right, _yaw(rot_meas))
    gate = None if noise.mag_gate_alpha is None else chi2_threshold(noise.mag_gate_alpha, 3)
    plausible = ~ones if mag_field_ok is None else mag_field_ok.bool()
    p, v = p0.clone(), v0.clone()
    rot = so3.quat_to_matrix(so3.quat_normalize(q0))
    P = noise.initial_cov(B, acc.dtype, acc.device)
    bias = acc.new_zeros(B, 6) if noise.estimate_biases else None
    ps, vs, rs, stds, bs = [p], [v], [rot], [torch.diagonal(P, dim1=-2, dim2=-1)[:, :3].sqrt()], [bias]
    rejected = [torch.zeros(B, dtype=torch.bool, device=acc.device)]
    for k in range(1, n):
        p, v, rot, P = predict(p, v, rot, P, acc[:, k], gyro[:, k], dt[:, k], noise, gravity, bias)
        # row set per run: "both" (velocity + attitude), "att" (encoders out), "vel" (attitude
        # gated: the velocity rotated by the filter's own heading), or none (magnetometer out);
        # each update is computed only when some run of the batch needs it (the common case: one)
        use_mag = m_ok[:, k]
        flagged = torch.zeros_like(use_mag)
        if gate is not None:
            # Algorithm 1 of the ARCKF paper: gamma above the gate and a plausible field (norm and
            # dip as at the start) -> the state is off: inflate P (lam_p); an implausible field
            # (steel nearby) -> an outlier: drop the attitude rows, rotate the wheel velocity by
            # the filter's own heading
            r, H, R = _observation(rot, v, None, rot_meas[:, k], noise)
            hph = H @ P @ H.transpose(-1, -2)
            plaus = plausible[:, k]
            gamma, lam_p, _ = robust_inflation(r, hph, R, plaus, gate, 3, 1e6)
            flagged = (gamma > gate) & ~plaus & use_mag
            rejected.append(flagged)
            use_mag = use_mag & ~flagged
            P = P.clone()
            P[:, 6:9, 6:9] = P[:, 6:9, 6:9] * lam_p[:, None, None]
        sets = {"both": enc_ok[:, k] & use_mag, "att": use_mag & ~enc_ok[:, k], "vel": enc_ok[:, k] & flagged}
        dx, P_new = p.new_zeros(B, noise.dim), P
        for name, mask in sets.items():
            if not bool(mask.any()):
                continue
            vm = {"both": vel_meas[:, k], "att": None,
                  "vel": wheel_velocity(v_left[:, k], v_right[:, k], _yaw(rot))}[name]
            r, H, R = _observation(rot, v, vm, None if name == "vel" else rot_meas[:, k], noise)
            dx_s, P_s = kalman_update(P, r, H, R)
            dx = torch.where(mask[:, None], dx_s, dx)
            P_new = torch.where(mask[:, None, None], P_s, P_new)
        if bias is None:
            p, v, rot, P = correct(p, v, rot, P_new, dx)
        else:
            p, v, rot, P, bias = correct(p, v, rot, P_new, dx, bias)
            bs.append(bias)
        ps.append(p)
        vs.append(v)
        rs.append(rot)
        stds.append(torch.diagonal(P, dim1=-2, dim2=-1)[:, :3].clamp_min(0).sqrt())
    out = {"pos": torch.stack(ps, 1), "vel": torch.stack(vs, 1),
           "quat": so3.quat_positive(so3.matrix_to_quat(torch.stack(rs, 1))), "pos_std": torch.stack(stds, 1)}
    if bias is not None:
        out["bias"] = torch.stack(bs, 1)
    if gate is not None:
        out["mag_rejected"] = torch.stack(rejected, 1)
    return out
