"""Error-state EKF for attitude + gyro bias, plain and adaptive-robust.

Plain filter after the paper ``es-ekf-imu-encoder-magnetometer`` (``../shared/papers``) (Eqs. 1-20),
reduced to attitude (that paper also carries position/velocity, which an AHRS does not
observe) and extended with the gyro bias (Sola, "Quaternion kinematics for the error-state
Kalman filter", 2017, Sec. 5-7, which the paper follows):

* nominal state ``q`` (nav_from_body, ENU) and gyro bias ``b`` (rad/s);
  error state ``dx = [dtheta (3, body frame: R_true = R exp([dtheta]x)), db (3)]``.
* prediction (Eqs. 6-7): ``q <- q (x) exp((omega - b) dt)``;
  ``P <- F P F^T + Q`` with ``F = [[exp(-[w dt]x), -I dt], [0, I]]`` (Eq. 8's attitude block
  ``R{w dt}^T``, Eq. 5) and ``Q = diag(sigma_g^2 dt I, sigma_bw^2 dt I)`` from the gyro noise
  density ``sigma_g`` (rad/s/sqrt(Hz)) and bias random walk ``sigma_bw`` (rad/s^2/sqrt(Hz));
  Eq. 10's ``sigma^2 dt^2`` with per-sample std ``sigma`` is the same as ``density^2 dt``.
* accelerometer update (gravity direction; 3-D): ``z = a/|a|``, ``h = R^T up``,
  ``H = [[h]x, 0]`` (``exp(-[dtheta]x) R^T up ~ h + [h]x dtheta``), ``R_a = sigma_a^2 I`` with
  ``sigma_a = accel_noise / sqrt(dt) / g`` (accel_noise in m/s^2/sqrt(Hz); the normalised
  direction has noise ~ sigma/g rad). The direction (not the raw vector) is used so an
  accelerometer scale error does not bias the tilt.
* magnetometer update (heading only; scalar): ``z = atan2(v_y, v_x)`` of ``v = R m`` (the field
  levelled with the filter's own tilt), predicted ``psi_ref`` = north (+pi/2, magnetic ENU),
  ``H = [-(R^T e_z)^T, 0]`` (a nav-frame error ``phi = R dtheta`` turns the levelled field by
  ``-phi_z``). Choice: the horizontal direction rather than the full normalised field, so
  that the magnetometer never tilts the attitude (magnetic disturbances and an uncertain
  dip angle only affect heading), as the ECF's east vector (paper Eq. 6) and Mahony/Madgwick's
  ``[0, |h_xy|, h_z]`` reference do. ``sigma_m = mag_noise / sqrt(dt) * |m| / |m_h|`` rad
  (mag_noise in rad/sqrt(Hz); the factor accounts for the heading of a steep field being
  less certain).
* Kalman gain Eq. 12, Joseph form Eq. 17, injection Eq. 16 (``q <- q (x) exp(dtheta)``,
  ``b <- b + db``), reset Eqs. 18-20 (``P <- G P G^T``, ``G = diag(I - [dtheta/2]x, I)``).

The loop is :func:`predict`, then per observation (:func:`gravity_observation`,
:func:`heading_observation`) the one Kalman update (:func:`tcn_ahrs.filters.kalman.kalman_update`)
and :func:`correct`.

Adaptive-robust variant after the paper ``adaptive-robust-ckf-uwb-imu`` (``../shared/papers``)
(Eqs. 39-42, Algorithm 1; :mod:`tcn_ahrs.filters.robust`), per observation (gravity direction,
then heading):

* ``gamma = r^T S^-1 r`` (Eq. 39), ``S = H P H^T + R``, compared with the chi-square quantile
  ``chi2.ppf(1 - alpha, dof)`` (Eq. 40; dof 3 for the gravity direction - conservative, as the
  radial component of a unit-vector residual is second order - and 1 for heading). With the
  default ``alpha = 0.001`` this is 16.27 (dof 3) and 10.83 (dof 1); the paper quotes 6.2 for
  dof 1 at alpha = 0.001, which is the 0.987 quantile (alpha ~ 0.013), not the 0.999 one:
  we compute the quantile from alpha with scipy.
* robustness factor (the paper's ``C_u < C_u,max`` test, Eq. 35-37, from a residual that does
  not depend on the state): for the accelerometer ``| |a| - g | < acc_norm_tol``; for the
  magnetometer ``| |m| - |m_ref| | < mag_norm_tol`` and ``|dip - dip_ref| < dip_tol`` (dip =
  angle between a and m). A *plausible* observation with ``gamma >= chi2`` means the state is
  abnormal: inflate the predicted covariance ``P <- (gamma/chi2) P`` (fading factor, Eq. 42);
  an *implausible* one is an outlier: ``R <- (gamma/chi2) R`` (Eq. 41). As in Algorithm 1's
  ``while`` loops the inflation is repeated (``n_iter`` times, a fixed count so that the
  batch needs no data-dependent control flow) until ``gamma < chi2``.

Signals: ``acc_gated``/``mag_gated`` (R inflated), ``mahalanobis_acc``/``mahalanobis_mag``
(gamma before inflation), ``fading`` (total P inflation factor applied at the sample, 1 = none),
``gyro_bias``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import torch
from torch import Tensor

from .. import so3
from ..conventions import GRAVITY
from ..kernels.params import knob
from .compiled import eskf_loop, use_compiled
from .common import converter_like, flatten_batch, normalize, unflatten
from .kalman import chi2_threshold, kalman_update, symmetrize
from .robust import robust_inflation, rolling_max

__all__ = ["eskf", "chi2_threshold", "predict", "gravity_observation", "heading_observation", "correct"]


def predict(rot: Tensor, bias: Tensor, P: Tensor, gyro: Tensor, dt: Tensor, q_rate: Tensor) -> Tuple[Tensor, Tensor]:
    """Prediction (Eqs. 6-8, 10): ``R <- R exp((omega - b) dt)``, ``P <- F P F^T + Q dt``.

    rot (B, 3, 3) nav_from_body, bias (B, 3) rad/s, P (B, 6, 6), gyro (B, 3) rad/s, dt (B, 1) s,
    q_rate (B, 6) = [sigma_g^2, sigma_bw^2] per axis (Q / dt). Returns (rot, P).
    """
    inc = so3.exp((gyro - bias) * dt)
    eye3 = torch.eye(3, dtype=P.dtype, device=P.device).expand_as(inc)
    zeros3 = torch.zeros_like(inc)
    F = torch.cat([torch.cat([inc.transpose(-1, -2), -eye3 * dt[..., None]], -1),
                   torch.cat([zeros3, eye3], -1)], -2)
    return rot @ inc, F @ P @ F.transpose(-1, -2) + torch.diag_embed(q_rate * dt)


def gravity_observation(rot: Tensor, acc_unit: Tensor) -> Tuple[Tensor, Tensor]:
    """Accelerometer as the gravity direction: residual ``a/|a| - R^T up`` (B, 3) and
    ``H = [[R^T up]x, 0]`` (B, 3, 6)."""
    h = rot[:, 2, :]  # R^T up
    return acc_unit - h, torch.cat([so3.hat(h), torch.zeros_like(rot)], -1)


def heading_observation(rot: Tensor, mag: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
    """Magnetometer as the heading of the levelled field: residual ``atan2(v_y, v_x) - pi/2``
    (wrapped, (B, 1)) of ``v = R m``, ``H = [-(R^T e_z)^T, 0]`` (B, 1, 6) and the factor
    ``|m|^2 / |m_h|^2`` (B,) on the heading variance (a steep field's heading is less certain)."""
    v = (rot @ mag[..., None])[..., 0]
    vh2 = (v[:, :2] ** 2).sum(-1).clamp_min(1e-12)
    r = torch.atan2(v[:, 1], v[:, 0]) - math.pi / 2
    r = torch.remainder(r + math.pi, 2 * math.pi) - math.pi
    H = torch.cat([-rot[:, 2:3, :], torch.zeros_like(rot[:, :1, :])], -1)
    return r[:, None], H, (v * v).sum(-1) / vh2


def correct(rot: Tensor, bias: Tensor, P: Tensor, dx: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
    """Injection (Eq. 16: ``R <- R exp(dtheta)``, ``b <- b + db``) and reset (Eqs. 19-20:
    ``P <- G P G^T``, ``G = diag(I - [dtheta/2]x, I)``)."""
    dth = dx[:, :3]
    eye3 = torch.eye(3, dtype=P.dtype, device=P.device).expand_as(rot)
    zeros3 = torch.zeros_like(rot)
    G = torch.cat([torch.cat([eye3 - so3.hat(0.5 * dth), zeros3], -1), torch.cat([zeros3, eye3], -1)], -2)
    return rot @ so3.exp(dth), bias + dx[:, 3:], symmetrize(G @ P @ G.transpose(-1, -2))


def _observe(rot, bias, P, r, H, R, plausible, thr: float, robust: bool, n_iter: int, max_fading: float):
    """One observation: (robust: gate and inflate, Eqs. 39-42), Kalman update (Eqs. 12, 15, 17),
    injection and reset. Returns rot, bias, P, gamma, lam_p, lam_r (the last three None unless
    robust)."""
    hph = H @ P @ H.transpose(-1, -2)
    gamma = lam_p = lam_r = None
    if robust:
        gamma, lam_p, lam_r = robust_inflation(r, hph, R, plausible, thr, n_iter, max_fading)
        P = lam_p[:, None, None] * P  # Eq. 42 (fading factor)
        R = lam_r[:, None, None] * R  # Eq. 41
        hph = lam_p[:, None, None] * hph
    dx, P = kalman_update(P, r, H, R, hph + R)
    rot, bias, P = correct(rot, bias, P, dx)
    return rot, bias, P, gamma, lam_p, lam_r


@dataclass
class ESEKFParams:
    """The ES-EKF's parameters, meaning, unit and default once: read by :func:`eskf` and the
    estimator registry (:class:`tcn_ahrs.estimators.classical.ESEKF`)."""

    gyro_noise: float = knob(1e-3, "rad/s/√Hz", "gyro white-noise density")
    bias_walk: float = knob(1e-5, "rad/s²/√Hz", "gyro bias random-walk density")
    accel_noise: float = knob(0.05, "m/s²/√Hz", "accelerometer measurement noise density",
                              grid=[0.01, 0.03, 0.1, 0.3])
    mag_noise: float = knob(0.05, "rad/√Hz", "the field direction's noise", grid=[0.01, 0.03, 0.1, 0.3])
    init_att_std: float = knob(0.1, "rad", "initial attitude uncertainty")
    init_bias_std: float = knob(0.01, "rad/s", "initial bias uncertainty")


@dataclass
class RobustESEKFParams(ESEKFParams):
    """The adaptive-robust ES-EKF's own parameters (ARCKF paper, Eqs. 39-42)."""

    alpha: float = 0.001  # significance level of the chi-square tests
    acc_norm_tol: float = 0.25  # m/s²
    mag_norm_tol: float = 3.0  # µT
    dip_tol: float = 0.05  # rad
    max_fading: float = 10.0
    n_iter: int = 3
    plausible_window: float = 0.2  # s


_ESKF = RobustESEKFParams()


def eskf(
    gyro: Tensor,
    accel: Tensor,
    dt: Tensor,
    q0: Tensor,
    mag: Optional[Tensor] = None,
    gyro_noise=_ESKF.gyro_noise,
    bias_walk=_ESKF.bias_walk,
    accel_noise=_ESKF.accel_noise,
    mag_noise=_ESKF.mag_noise,
    init_att_std=_ESKF.init_att_std,
    init_bias_std=_ESKF.init_bias_std,
    bias0: Optional[Tensor] = None,
    gravity: float = GRAVITY,
    robust: bool = False,
    alpha: float = _ESKF.alpha,
    acc_norm_tol=_ESKF.acc_norm_tol,
    mag_norm_tol=_ESKF.mag_norm_tol,
    dip_tol=_ESKF.dip_tol,
    mag_norm_ref=None,
    dip_ref=None,
    max_fading: float = _ESKF.max_fading,
    n_iter: int = _ESKF.n_iter,
    plausible_window: float = _ESKF.plausible_window,
    backend: str = "auto",
) -> Dict[str, Tensor]:
    """Run the (adaptive-robust) error-state EKF.

    Args:
        gyro, accel, mag: (..., N, 3) rad/s, m/s^2, uT (body); ``mag=None`` for 6-axis.
        dt:  (..., N) s, time step before each sample (``dt[..., 0]`` unused).
        q0:  (..., 4) initial nav_from_body (magnetic ENU when mag is used).
        gyro_noise:   gyro white-noise density, rad/s/sqrt(Hz) (default 1e-3).
        bias_walk:    gyro bias random-walk density, rad/s^2/sqrt(Hz) (default 1e-5).
        accel_noise:  accelerometer measurement noise density, m/s^2/sqrt(Hz) (default 0.05;
                      larger than the sensor's own ~2e-3 to cover normal body accelerations).
        mag_noise:    heading measurement noise density, rad/sqrt(Hz) (default 0.05).
        init_att_std: initial attitude std per axis, rad (default 0.1).
        init_bias_std: initial gyro-bias std per axis, rad/s (default 0.01).
        bias0:        (..., 3) initial gyro bias, rad/s (default 0).
        robust:       enable the adaptive-robust gating (see module docstring).
        alpha:        significance level of the chi-square tests (default 0.001).
        acc_norm_tol: | |a| - g | below which the accelerometer is plausible, m/s^2 (default 0.25).
        mag_norm_tol: | |m| - |m_ref| | below which the magnetometer is plausible, uT (default 3).
        dip_tol:      |dip - dip_ref| below which the magnetometer is plausible, rad (default 0.05).
        mag_norm_ref, dip_ref: (...,) reference field norm (uT) and dip (rad); default: the
                      first sample's.
        max_fading:   cap on the fading factor per observation and sample (default 10; keeps P
                      from exploding - linearisation breaks when the attitude std gets large).
        plausible_window: the plausibility tests must hold over this many seconds (default 0.2).
        n_iter:       inflation iterations (Algorithm 1's ``while``).
        backend:      ``"auto"``: the compiled loop (:mod:`tcn_ahrs.filters.compiled`) when nothing
                      needs a gradient and all is float64 on the CPU; ``"torch"`` / ``"numba"`` force one.
        Numeric parameters broadcast as batch tensors.
    Returns:
        ``quat`` (..., N, 4), ``gyro_bias`` (..., N, 3), ``att_std`` (..., N, 3) rad (sqrt of
        P's attitude diagonal); robust only: ``acc_gated``, ``mag_gated`` (..., N) bool,
        ``mahalanobis_acc``, ``mahalanobis_mag``, ``fading`` (..., N).
    """
    T = converter_like(gyro)
    gyro, accel, dt, q0, mag = T(gyro), T(accel), T(dt), T(q0), T(mag)
    bias0 = T(torch.zeros(3) if bias0 is None else bias0)
    names = ["gyro_noise", "bias_walk", "accel_noise", "mag_noise", "init_att_std", "init_bias_std",
             "acc_norm_tol", "mag_norm_tol", "dip_tol"]
    vals = [gyro_noise, bias_walk, accel_noise, mag_noise, init_att_std, init_bias_std,
            acc_norm_tol, mag_norm_tol, dip_tol]
    x, batch = _prepare(T, gyro, accel, dt, q0, mag, bias0, dict(zip(names, vals)), mag_norm_ref, dip_ref, gravity,
                        alpha, plausible_window)
    if use_compiled(backend, x.gyro, x.accel, x.dt, x.q0, x.mag, x.b, *x.p.values()):
        res = _run_compiled(x, robust, n_iter, max_fading)
    else:
        res = _run_torch(x, robust, n_iter, max_fading)
    return {k: unflatten(v, batch) for k, v in res.items()}


def _prepare(T, gyro, accel, dt, q0, mag, bias0, params, mag_norm_ref, dip_ref, gravity, alpha, plausible_window):
    """The filter's inputs flattened to one batch dimension, with everything that does not depend
    on the state computed up front: the per-sample measurement variances, the observations'
    plausibility (the robust filter's tests), the chi-square thresholds, the initial covariance
    and attitude. Returns (a namespace of them, the batch shape for :func:`unflatten`)."""
    from types import SimpleNamespace

    dtype, dev = gyro.dtype, gyro.device
    a_norm_all = torch.linalg.vector_norm(accel, dim=-1)
    if mag is not None:
        m_norm_all = torch.linalg.vector_norm(mag, dim=-1)
        dip_all = torch.acos(((normalize(accel) * normalize(mag)).sum(-1)).clamp(-1.0, 1.0))
        mag_norm_ref = m_norm_all[..., 0] if mag_norm_ref is None else T(mag_norm_ref)
        dip_ref = dip_all[..., 0] if dip_ref is None else T(dip_ref)
    else:
        m_norm_all = dip_all = None
        mag_norm_ref = dip_ref = torch.zeros((), dtype=dtype, device=dev)
    batch, flat = flatten_batch(
        [(gyro, 2), (accel, 2), (dt, 1), (q0, 1), (mag, 2), (bias0, 1), (a_norm_all, 1),
         (m_norm_all, 1), (dip_all, 1), (T(mag_norm_ref), 0), (T(dip_ref), 0)]
        + [(T(v), 0) for v in params.values()]
    )
    (gyro, accel, dt, q0, mag, b, a_norm_all, m_norm_all, dip_all, mag_norm_ref, dip_ref) = flat[:11]
    p_ = dict(zip(params, flat[11:]))
    B, n = gyro.shape[0], gyro.shape[1]
    x = SimpleNamespace(gyro=gyro, accel=accel, dt=dt, q0=q0, mag=mag, p=p_, B=B, n=n, dtype=dtype)
    x.a_hat = normalize(accel)
    var_g = p_["gyro_noise"] ** 2
    var_bw = p_["bias_walk"] ** 2
    # Per-sample measurement variances (noise density^2 / dt), vectorised up front.
    x.var_acc = (p_["accel_noise"][:, None] / gravity) ** 2 / dt
    # Robustness factors (state-independent plausibility of each observation), Eqs. 35-37 analogue.
    # An observation is plausible only if the test held over the last ``plausible_window`` seconds:
    # during vigorous motion |a| crosses g now and then while its direction is far from gravity,
    # and such a crossing must not be read as "observation fine, state abnormal" (fading).
    win = max(1, int(round(plausible_window / float(dt[:, 1:].median())))) if n > 1 else 1
    x.acc_plaus = rolling_max((a_norm_all - gravity).abs() / p_["acc_norm_tol"][:, None], win) < 1.0
    x.var_mag = x.mag_plaus = None
    if mag is not None:
        x.var_mag = p_["mag_noise"][:, None] ** 2 / dt
        mag_dev = torch.maximum((m_norm_all - mag_norm_ref[:, None]).abs() / p_["mag_norm_tol"][:, None],
                                (dip_all - dip_ref[:, None]).abs() / p_["dip_tol"][:, None])
        x.mag_plaus = rolling_max(mag_dev, win) < 1.0
    x.thr_acc = chi2_threshold(alpha, 3)
    x.thr_mag = chi2_threshold(alpha, 1)
    x.P = torch.diag_embed(torch.cat([(p_["init_att_std"] ** 2)[:, None].expand(B, 3),
                                      (p_["init_bias_std"] ** 2)[:, None].expand(B, 3)], -1))
    x.b = b.clone()
    x.qd_rate = torch.cat([var_g[:, None].expand(B, 3), var_bw[:, None].expand(B, 3)], -1)  # Q / dt (Eq. 10)
    # The nominal attitude is kept as a rotation matrix inside the loop (one exp per step
    # serves both the nominal propagation and F); quaternions are formed once at the end.
    x.rot = so3.quat_to_matrix(so3.quat_normalize(q0))
    return x, batch


def _run_compiled(x, robust: bool, n_iter: int, max_fading: float) -> Dict[str, Tensor]:
    """The recursion in the compiled loop (:func:`tcn_ahrs.filters.compiled.eskf_loop`)."""
    npy = lambda t: t.detach().contiguous().numpy()  # noqa: E731
    zb = torch.zeros(x.B, x.n, dtype=x.dtype)
    mag = x.mag
    quat, bs, var, sg = eskf_loop(
        npy(x.a_hat), npy(mag if mag is not None else torch.zeros_like(x.gyro)), npy(x.gyro), npy(x.dt), npy(x.rot),
        npy(x.b), npy(x.P), npy(x.qd_rate), npy(x.var_acc), npy(x.acc_plaus),
        npy(x.var_mag if mag is not None else zb), npy(x.mag_plaus if mag is not None else zb > 0),
        float(x.thr_acc), float(x.thr_mag), mag is not None, bool(robust), int(n_iter), float(max_fading))
    res = {"quat": torch.from_numpy(quat), "gyro_bias": torch.from_numpy(bs), "att_std": torch.from_numpy(var).sqrt()}
    if robust:
        sg = torch.from_numpy(sg)
        res.update(mahalanobis_acc=sg[0], acc_gated=sg[3] > 1.0, fading=sg[2])
        if mag is not None:
            res.update(mahalanobis_mag=sg[1], mag_gated=sg[4] > 1.0)
    return res


def _run_torch(x, robust: bool, n_iter: int, max_fading: float) -> Dict[str, Tensor]:
    """The recursion on tensors (autograd, CUDA): predict, the gravity observation, the heading
    observation, per sample."""
    rot, b, P, mag, B = x.rot, x.b, x.P, x.mag, x.B
    eye3 = torch.eye(3, dtype=x.dtype, device=x.gyro.device).expand(B, 3, 3)
    rots, bs, variances = [rot], [b], [torch.diagonal(P, dim1=-2, dim2=-1)[:, :3]]
    sig = {k: [] for k in ("mahalanobis_acc", "mahalanobis_mag", "fading", "acc_gated", "mag_gated")}
    for k in range(1, x.n):
        rot, P = predict(rot, b, P, x.gyro[:, k], x.dt[:, k, None], x.qd_rate)
        r, H = gravity_observation(rot, x.a_hat[:, k])
        Ra = eye3 * x.var_acc[:, k, None, None]
        rot, b, P, g_a, lp_a, lr_a = _observe(rot, b, P, r, H, Ra, x.acc_plaus[:, k], x.thr_acc, robust, n_iter,
                                              max_fading)
        if mag is not None:
            r, H, steep = heading_observation(rot, mag[:, k])
            Rm = (x.var_mag[:, k] * steep)[:, None, None]
            rot, b, P, g_m, lp_m, lr_m = _observe(rot, b, P, r, H, Rm, x.mag_plaus[:, k], x.thr_mag, robust, n_iter,
                                                  max_fading)
        rots.append(rot)
        bs.append(b)
        variances.append(torch.diagonal(P, dim1=-2, dim2=-1)[:, :3])
        if robust:
            sig["mahalanobis_acc"].append(g_a)
            sig["acc_gated"].append(lr_a > 1.0)
            fading = lp_a
            if mag is not None:
                sig["mahalanobis_mag"].append(g_m)
                sig["mag_gated"].append(lr_m > 1.0)
                fading = fading * lp_m
            sig["fading"].append(fading)
    res = {"quat": so3.matrix_to_quat(torch.stack(rots, 1)), "gyro_bias": torch.stack(bs, 1),
           "att_std": torch.sqrt(torch.stack(variances, 1))}
    if robust:
        names = ["mahalanobis_acc", "acc_gated", "fading"] + (["mahalanobis_mag", "mag_gated"] if mag is not None else [])
        for name in names:
            first = torch.ones(B, dtype=x.dtype, device=x.gyro.device) if name == "fading" else \
                torch.zeros(B, dtype=x.dtype, device=x.gyro.device)
            if name.endswith("gated"):
                first = first > 0.5
            res[name] = torch.stack([first] + sig[name], 1)
    return res
