"""The odometry paper's baselines: a total-state EKF and a UKF over the same state, the same IMU
propagation and the same measurements as the ES-EKF (:mod:`tcn_ahrs.nav.odometry`), run through
filterpy's ``ExtendedKalmanFilter`` and ``UnscentedKalmanFilter`` (Merwe scaled sigma points).

The paper took its EKF and UKF from ROS ``robot_localization``; here both are the textbook
filters on the ES-EKF's inputs, so the comparison isolates the filter formulation:

* State ``x = [p (3), v (3), e (3)]``: ENU position m, velocity m/s, and the attitude as ZYX
  Euler angles ``e = [roll, pitch, yaw]`` rad (``R = Rz(yaw) Ry(pitch) Rx(roll)``,
  ``nav_from_body``) — the minimal total-state attitude those filters carry, singular at
  ±90° pitch (a ground robot never gets there).
* Propagation with the IMU as input (Eq. 6's discretisation): ``a_n = R(e) a + g``,
  ``p += v dt + a_n dt^2/2``, ``v += a_n dt``, ``e += E(e)^-1 w dt`` (Euler-angle rates).
  ``F`` is its analytic Jacobian (tested against finite differences); ``Q`` puts the paper's
  ``sigma_a^2 dt^2`` on v and ``sigma_w^2 dt^2`` (through ``E^-1``) on e, like Eq. 10.
* Measurement ``z = [v_x, v_y, roll, pitch, yaw]`` from the wheels (Eqs. 21-22) and the
  magnetometer/accelerometer attitude, R as Eq. 13; angle residuals wrapped to (-pi, pi].
  While the encoders drop out only the angles update; while the magnetometer drops out the
  filters only predict (as the ES-EKF).

numpy float64, one run at a time (filterpy's loops are per sample and per sigma point).
"""
from __future__ import annotations

from typing import Dict, Optional

import numpy as np
from scipy.spatial.transform import Rotation

from ..conventions import GRAVITY
from .odometry import OdometryNoise

ANGLES = slice(6, 9)


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def _m(rows) -> np.ndarray:
    """Nested 3x3 lists of (...,) arrays -> (..., 3, 3) (of floats: one np.array, the EKF's case)."""
    if np.ndim(rows[0][0]) == 0:
        return np.array(rows, dtype=np.float64)
    return np.stack([np.stack(r, -1) for r in rows], -2)


def euler_matrix(e: np.ndarray):
    """``R = Rz(yaw) Ry(pitch) Rx(roll)`` (..., 3, 3) of e (..., 3) and its partial derivatives
    (..., 3, 3, 3) w.r.t. roll, pitch, yaw (last index)."""
    e = np.asarray(e, dtype=np.float64)
    (cr, cp, cy), (sr, sp, sy) = np.moveaxis(np.cos(e), -1, 0), np.moveaxis(np.sin(e), -1, 0)
    if e.ndim == 1:
        cr, cp, cy, sr, sp, sy = (float(c) for c in (cr, cp, cy, sr, sp, sy))
    o, z = np.ones_like(cr), np.zeros_like(cr)
    X, dX = _m([[o, z, z], [z, cr, -sr], [z, sr, cr]]), _m([[z, z, z], [z, -sr, -cr], [z, cr, -sr]])
    Y, dY = _m([[cp, z, sp], [z, o, z], [-sp, z, cp]]), _m([[-sp, z, cp], [z, z, z], [-cp, z, -sp]])
    Z, dZ = _m([[cy, -sy, z], [sy, cy, z], [z, z, o]]), _m([[-sy, -cy, z], [cy, -sy, z], [z, z, z]])
    return Z @ Y @ X, np.stack([Z @ Y @ dX, Z @ dY @ X, dZ @ Y @ X], -1)


def euler_rates(e: np.ndarray, w: np.ndarray):
    """ZYX Euler-angle rates ``E(e)^-1 w`` (..., 3) for body rates w (rad/s), and their Jacobian
    (..., 3, 3) w.r.t. e (the yaw column is zero)."""
    e = np.asarray(e, dtype=np.float64)
    sr, cr, tp, cp = np.sin(e[..., 0]), np.cos(e[..., 0]), np.tan(e[..., 1]), np.cos(e[..., 1])
    a, b = sr * w[1] + cr * w[2], cr * w[1] - sr * w[2]   # b = d a / d roll
    if e.ndim == 1:
        sr, cr, tp, cp, a, b = (float(c) for c in (sr, cr, tp, cp, a, b))
    z = np.zeros_like(a)
    rates = np.stack([w[0] + a * tp, b, a / cp], -1)
    J = _m([[b * tp, a / cp ** 2, z], [-a, z, z], [b / cp, a * tp / cp, z]])
    return rates, J


def euler_rate_matrix(e: np.ndarray) -> np.ndarray:
    """``E(e)^-1`` (3, 3): Euler-angle rates per body rate."""
    sr, cr, tp, cp = np.sin(e[0]), np.cos(e[0]), np.tan(e[1]), np.cos(e[1])
    return np.array([[1.0, sr * tp, cr * tp], [0.0, cr, -sr], [0.0, sr / cp, cr / cp]])


def propagate(x: np.ndarray, acc: np.ndarray, gyro: np.ndarray, dt: float, gravity: float = GRAVITY) -> np.ndarray:
    """The process model f(x, u): one IMU step of the state (..., 9) (batched over sigma points)."""
    R, _ = euler_matrix(x[..., ANGLES])
    a_n = R @ acc - np.array([0.0, 0.0, gravity])
    rates, _ = euler_rates(x[..., ANGLES], gyro)
    return np.concatenate([x[..., 0:3] + x[..., 3:6] * dt + 0.5 * a_n * dt * dt, x[..., 3:6] + a_n * dt,
                           _wrap(x[..., 6:9] + rates * dt)], -1)


def jacobian(x: np.ndarray, acc: np.ndarray, gyro: np.ndarray, dt: float) -> np.ndarray:
    """Analytic ``F = d propagate / d x`` (9, 9)."""
    _, dR = euler_matrix(x[ANGLES])
    Ja = np.einsum("ijk,j->ik", dR, acc)              # d(R a)/d e
    _, Je = euler_rates(x[ANGLES], gyro)
    F = np.eye(9)
    F[0:3, 3:6] = np.eye(3) * dt
    F[0:3, 6:9] = 0.5 * Ja * dt * dt
    F[3:6, 6:9] = Ja * dt
    F[6:9, 6:9] += Je * dt
    return F


def process_noise(x: np.ndarray, dt: float, noise: OdometryNoise) -> np.ndarray:
    """Q (9, 9): Eq. 10's ``sigma_a^2 dt^2`` on v, ``sigma_w^2 dt^2`` mapped by ``E^-1`` on e."""
    Q = np.zeros((9, 9))
    Q[3:6, 3:6] = np.eye(3) * (noise.accel * dt) ** 2
    Einv = euler_rate_matrix(x[ANGLES])
    Q[6:9, 6:9] = Einv @ Einv.T * (noise.gyro * dt) ** 2
    return Q


def _residual_z(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z residual (..., m), the last three (angles) wrapped; broadcasts over sigma points."""
    y = np.subtract(a, b)
    y[..., -3:] = _wrap(y[..., -3:])
    return y


def _residual_x(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """State residual (..., 9), the Euler angles wrapped; broadcasts over sigma points."""
    y = np.subtract(a, b)
    y[..., ANGLES] = _wrap(y[..., ANGLES])
    return y


def unscented_transform(sigmas: np.ndarray, Wm: np.ndarray, Wc: np.ndarray, noise_cov=None, mean_fn=None,
                        residual_fn=None):
    """filterpy's ``unscented_transform`` with the residual applied to all sigma points at once
    (filterpy loops over them in Python when the residual is not ``np.subtract``); the same
    mean and covariance (tested)."""
    x = Wm @ sigmas if mean_fn is None else mean_fn(sigmas, Wm)
    y = (residual_fn or np.subtract)(sigmas, x[None, :])
    P = y.T @ (Wc[:, None] * y)
    return x, (P if noise_cov is None else P + noise_cov)


def _mean_angles(sigmas: np.ndarray, weights: np.ndarray, cols) -> np.ndarray:
    """Weighted mean of sigma points with the angle columns averaged on the circle."""
    m = weights @ sigmas
    m[cols] = np.arctan2(weights @ np.sin(sigmas[:, cols]), weights @ np.cos(sigmas[:, cols]))
    return m


def _measurement(vel_meas: Optional[np.ndarray], euler_meas: np.ndarray, noise: OdometryNoise):
    """(z, H, R) of one update: velocity rows (with vel_meas) and the three angle rows."""
    if vel_meas is None:
        H = np.zeros((3, 9))
        H[:, 6:9] = np.eye(3)
        return euler_meas, H, np.eye(3) * noise.att ** 2
    H = np.zeros((5, 9))
    H[0, 3] = H[1, 4] = 1.0
    H[2:, 6:9] = np.eye(3)
    return np.concatenate([vel_meas, euler_meas]), H, np.diag([noise.vel ** 2] * 2 + [noise.att ** 2] * 3)


def to_euler(quat: np.ndarray) -> np.ndarray:
    """(N, 4) w,x,y,z nav_from_body -> (N, 3) [roll, pitch, yaw] (ZYX), via scipy."""
    q = np.asarray(quat, dtype=np.float64)
    return Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_euler("ZYX")[:, ::-1].copy()


def from_euler(euler: np.ndarray) -> np.ndarray:
    """(N, 3) [roll, pitch, yaw] -> (N, 4) w,x,y,z, via scipy."""
    q = Rotation.from_euler("ZYX", np.asarray(euler)[:, ::-1]).as_quat()[:, [3, 0, 1, 2]]
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def odometry_filter(kind: str, acc: np.ndarray, gyro: np.ndarray, dt: np.ndarray, v_left: np.ndarray,
                    v_right: np.ndarray, mag_quat: np.ndarray, p0: np.ndarray, v0: np.ndarray, q0: np.ndarray,
                    encoders_ok: Optional[np.ndarray] = None, mag_ok: Optional[np.ndarray] = None,
                    noise: OdometryNoise = OdometryNoise(), gravity: float = GRAVITY,
                    ukf_alpha: float = 1e-3) -> Dict[str, np.ndarray]:
    """Run filterpy's EKF (``kind="ekf"``) or UKF (``"ukf"``) over one run of N samples.

    Inputs as :func:`tcn_ahrs.nav.odometry.odometry_eskf` for one run (no batch axis, numpy):
    acc, gyro (N, 3); dt, v_left, v_right (N,); mag_quat (N, 4); p0, v0 (3,); q0 (4,);
    encoders_ok, mag_ok (N,) bool. ``noise``'s bias and ``vel_z`` options are ES-EKF extensions
    and must be off. Returns ``pos``, ``vel`` (N, 3), ``quat`` (N, 4), ``pos_std`` (N, 3).
    """
    if kind not in ("ekf", "ukf"):
        raise ValueError(f"kind: expected 'ekf' or 'ukf', got {kind!r}")
    if noise.estimate_biases or noise.vel_z is not None:
        raise ValueError("noise: the EKF/UKF baselines carry the paper's state only "
                         "(estimate_biases=False, vel_z=None)")
    from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter

    n = len(acc)
    enc_ok = np.ones(n, bool) if encoders_ok is None else np.asarray(encoders_ok, bool)
    m_ok = np.ones(n, bool) if mag_ok is None else np.asarray(mag_ok, bool)
    euler_meas = to_euler(mag_quat)
    speed = 0.5 * (np.asarray(v_left) + np.asarray(v_right))
    vel_meas = speed[:, None] * np.stack([np.cos(euler_meas[:, 2]), np.sin(euler_meas[:, 2])], -1)  # Eq. 21
    x0 = np.concatenate([p0, v0, to_euler(np.asarray(q0)[None])[0]])
    if kind == "ekf":
        class _EKF(ExtendedKalmanFilter):
            def predict_x(self, u):  # filterpy's hook for a nonlinear process model
                self.x = propagate(self.x, *u)

        f = _EKF(dim_x=9, dim_z=5)
    else:
        class _UKF(UnscentedKalmanFilter):
            # filterpy's UKF with its three per-sigma-point Python loops vectorised (same math)
            def compute_process_sigmas(self, dt, fx=None, **fx_args):
                self.sigmas_f = propagate(self.points_fn.sigma_points(self.x, self.P), fx_args["a"], fx_args["w"], dt,
                                          gravity)

            def cross_variance(self, x, z, sigmas_f, sigmas_h):
                return _residual_x(sigmas_f, x[None]).T @ (self.Wc[:, None] * _residual_z(sigmas_h, z[None]))

        points = MerweScaledSigmaPoints(9, alpha=ukf_alpha, beta=2.0, kappa=0.0, subtract=_residual_x)
        f = _UKF(dim_x=9, dim_z=5, dt=float(dt[1]) if n > 1 else 0.0,
                                  hx=lambda x, H: H @ x, fx=lambda x, step, a, w: propagate(x, a, w, step, gravity),
                                  points=points, residual_x=_residual_x, residual_z=_residual_z,
                                  x_mean_fn=lambda s, w: _mean_angles(s, w, ANGLES),
                                  z_mean_fn=lambda s, w: _mean_angles(s, w, slice(-3, None)))
    f.x = x0.copy()
    f.P = np.eye(9) * noise.init
    pos, vel, eul, std = (np.empty((n, 3)) for _ in range(4))
    pos[0], vel[0], eul[0], std[0] = x0[0:3], x0[3:6], x0[6:9], np.sqrt(np.diag(f.P)[:3])
    for k in range(1, n):
        step = float(dt[k])
        f.Q = process_noise(f.x, step, noise)
        if kind == "ekf":
            f.F = jacobian(f.x, acc[k], gyro[k], step)
            f.predict(u=(acc[k], gyro[k], step, gravity))
        else:
            f.predict(dt=step, UT=unscented_transform, a=acc[k], w=gyro[k])
        if m_ok[k]:
            z, H, R = _measurement(vel_meas[k] if enc_ok[k] else None, euler_meas[k], noise)
            if kind == "ekf":
                f.update(z, HJacobian=lambda x, H=H: H, Hx=lambda x, H=H: H @ x, R=R, residual=_residual_z)
            else:
                f.update(z, R=R, UT=unscented_transform, hx=lambda x, H=H: H @ x)
            f.x[ANGLES] = _wrap(f.x[ANGLES])
        pos[k], vel[k], eul[k] = f.x[0:3], f.x[3:6], f.x[6:9]
        std[k] = np.sqrt(np.clip(np.diag(f.P)[:3], 0.0, None))
    return {"pos": pos, "vel": vel, "quat": from_euler(eul), "pos_std": std}
