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

Adaptive-robust variant after the paper ``adaptive-robust-ckf-uwb-imu`` (``../shared/papers``)
(Eqs. 39-42, Algorithm 1), per observation (gravity direction, then heading):

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

import functools
import math
from typing import Dict, Optional

import torch
from torch import Tensor

from .. import so3
from ..conventions import GRAVITY
from .common import converter_like, flatten_batch, normalize, unflatten


@functools.lru_cache(maxsize=64)
def chi2_threshold(alpha: float, dof: int) -> float:
    """Upper ``alpha`` quantile of the chi-square distribution (``Pr(gamma < thr) = 1 - alpha``)."""
    from scipy.stats import chi2

    return float(chi2.ppf(1.0 - alpha, dof))


def _sym(p: Tensor) -> Tensor:
    return 0.5 * (p + p.transpose(-1, -2))


def _robust_inflation(r, hph, rr, plausible, thr: float, n_iter: int, max_fading: float):
    """Algorithm 1 lines 3-9 for a batch of observations.

    Args: residual r (B, m), H P H^T (B, m, m), R (B, m, m), plausible (B,) bool, threshold.
    Returns: gamma0 (B,) before inflation, lam_p (B,) factor on P, lam_r (B,) factor on R.
    """
    lam_p = torch.ones_like(r[:, 0])
    lam_r = torch.ones_like(r[:, 0])
    gamma0 = None
    for it in range(n_iter + 1):
        s = lam_p[:, None, None] * hph + lam_r[:, None, None] * rr
        gamma = (r * torch.linalg.solve(s, r[..., None])[..., 0]).sum(-1)
        if it == 0:
            gamma0 = gamma
        if it == n_iter:
            break
        f = torch.where(gamma >= thr, gamma / thr, torch.ones_like(gamma))
        lam_p = torch.where(plausible, (lam_p * f).clamp(max=max_fading), lam_p)
        lam_r = torch.where(plausible, lam_r, lam_r * f)
    return gamma0, lam_p, lam_r


def _rolling_max(x: Tensor, w: int) -> Tensor:
    """Causal running maximum over the last ``w`` samples of (B, N)."""
    if w <= 1:
        return x
    xp = torch.nn.functional.pad(x[:, None], (w - 1, 0), value=float("-inf"))
    return torch.nn.functional.max_pool1d(xp, kernel_size=w, stride=1)[:, 0]


def eskf(
    gyro: Tensor,
    accel: Tensor,
    dt: Tensor,
    q0: Tensor,
    mag: Optional[Tensor] = None,
    gyro_noise=1e-3,
    bias_walk=1e-5,
    accel_noise=0.05,
    mag_noise=0.05,
    init_att_std=0.1,
    init_bias_std=0.01,
    bias0: Optional[Tensor] = None,
    gravity: float = GRAVITY,
    robust: bool = False,
    alpha: float = 0.001,
    acc_norm_tol=0.25,
    mag_norm_tol=3.0,
    dip_tol=0.05,
    mag_norm_ref=None,
    dip_ref=None,
    max_fading: float = 10.0,
    n_iter: int = 3,
    plausible_window: float = 0.2,
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
        Numeric parameters broadcast as batch tensors.
    Returns:
        ``quat`` (..., N, 4), ``gyro_bias`` (..., N, 3), ``att_std`` (..., N, 3) rad (sqrt of
        P's attitude diagonal); robust only: ``acc_gated``, ``mag_gated`` (..., N) bool,
        ``mahalanobis_acc``, ``mahalanobis_mag``, ``fading`` (..., N).
    """
    T = converter_like(gyro)
    gyro, accel, dt, q0, mag = T(gyro), T(accel), T(dt), T(q0), T(mag)
    dtype, dev = gyro.dtype, gyro.device
    bias0 = T(torch.zeros(3) if bias0 is None else bias0)
    a_norm_all = torch.linalg.vector_norm(accel, dim=-1)
    if mag is not None:
        m_norm_all = torch.linalg.vector_norm(mag, dim=-1)
        dip_all = torch.acos(((normalize(accel) * normalize(mag)).sum(-1)).clamp(-1.0, 1.0))
        mag_norm_ref = m_norm_all[..., 0] if mag_norm_ref is None else T(mag_norm_ref)
        dip_ref = dip_all[..., 0] if dip_ref is None else T(dip_ref)
    else:
        m_norm_all = dip_all = None
        mag_norm_ref = dip_ref = torch.zeros((), dtype=dtype, device=dev)
    names = ["gyro_noise", "bias_walk", "accel_noise", "mag_noise", "init_att_std", "init_bias_std",
             "acc_norm_tol", "mag_norm_tol", "dip_tol"]
    vals = [gyro_noise, bias_walk, accel_noise, mag_noise, init_att_std, init_bias_std,
            acc_norm_tol, mag_norm_tol, dip_tol]
    batch, flat = flatten_batch(
        [(gyro, 2), (accel, 2), (dt, 1), (q0, 1), (mag, 2), (bias0, 1), (a_norm_all, 1),
         (m_norm_all, 1), (dip_all, 1), (T(mag_norm_ref), 0), (T(dip_ref), 0)]
        + [(T(v), 0) for v in vals]
    )
    (gyro, accel, dt, q0, mag, b, a_norm_all, m_norm_all, dip_all, mag_norm_ref, dip_ref) = flat[:11]
    p_ = dict(zip(names, flat[11:]))
    B, n = gyro.shape[0], gyro.shape[1]
    eye3 = torch.eye(3, dtype=dtype, device=gyro.device).expand(B, 3, 3)
    eye6 = torch.eye(6, dtype=dtype, device=gyro.device).expand(B, 6, 6)
    zeros3 = torch.zeros(B, 3, 3, dtype=dtype, device=gyro.device)

    a_hat = normalize(accel)
    var_g = p_["gyro_noise"] ** 2
    var_bw = p_["bias_walk"] ** 2
    # Per-sample measurement variances (noise density^2 / dt), vectorised up front.
    var_acc = (p_["accel_noise"][:, None] / gravity) ** 2 / dt
    # Robustness factors (state-independent plausibility of each observation), Eqs. 35-37 analogue.
    # An observation is plausible only if the test held over the last ``plausible_window`` seconds:
    # during vigorous motion |a| crosses g now and then while its direction is far from gravity,
    # and such a crossing must not be read as "observation fine, state abnormal" (fading).
    win = max(1, int(round(plausible_window / float(dt[:, 1:].median())))) if n > 1 else 1
    acc_plaus = _rolling_max((a_norm_all - gravity).abs() / p_["acc_norm_tol"][:, None], win) < 1.0
    if mag is not None:
        var_mag = p_["mag_noise"][:, None] ** 2 / dt
        mag_dev = torch.maximum((m_norm_all - mag_norm_ref[:, None]).abs() / p_["mag_norm_tol"][:, None],
                                (dip_all - dip_ref[:, None]).abs() / p_["dip_tol"][:, None])
        mag_plaus = _rolling_max(mag_dev, win) < 1.0
    thr_acc = chi2_threshold(alpha, 3)
    thr_mag = chi2_threshold(alpha, 1)

    P = torch.diag_embed(torch.cat([(p_["init_att_std"] ** 2)[:, None].expand(B, 3),
                                    (p_["init_bias_std"] ** 2)[:, None].expand(B, 3)], -1))
    q = so3.quat_normalize(q0)
    b = b.clone()
    qd_rate = torch.cat([var_g[:, None].expand(B, 3), var_bw[:, None].expand(B, 3)], -1)  # Q / dt (Eq. 10)

    def update(rot, b, P, r, H, Rm, plausible, thr):
        """One Kalman update with error injection and reset; returns new rot, b, P and signals."""
        hph = H @ P @ H.transpose(-1, -2)
        if robust:
            gamma, lam_p, lam_r = _robust_inflation(r, hph, Rm, plausible, thr, n_iter, max_fading)
            P = lam_p[:, None, None] * P  # Eq. 42 (fading factor)
            Rm = lam_r[:, None, None] * Rm  # Eq. 41
            hph = lam_p[:, None, None] * hph
        else:
            gamma = lam_p = lam_r = None
        S = hph + Rm
        if S.shape[-1] == 1:
            K = (P @ H.transpose(-1, -2)) / S  # Eq. 12, scalar observation
        else:
            K = torch.linalg.solve(S, H @ P).transpose(-1, -2)  # Eq. 12 (S symmetric)
        dx = (K @ r[..., None])[..., 0]  # Eq. 15
        IKH = eye6 - K @ H
        P = IKH @ P @ IKH.transpose(-1, -2) + K @ Rm @ K.transpose(-1, -2)  # Eq. 17 (Joseph)
        dth = dx[:, :3]
        rot = rot @ so3.exp(dth)  # Eq. 16: q <- q (x) q{dtheta}
        b = b + dx[:, 3:]
        G = torch.cat([torch.cat([eye3 - so3.hat(0.5 * dth), zeros3], -1), eye_bottom], -2)  # Eq. 20
        P = _sym(G @ P @ G.transpose(-1, -2))  # Eq. 19
        return rot, b, P, gamma, lam_p, lam_r

    eye_bottom = torch.cat([zeros3, eye3], -1)
    zeros13 = torch.zeros(B, 1, 3, dtype=dtype, device=gyro.device)
    # The nominal attitude is kept as a rotation matrix inside the loop (one exp per step
    # serves both the nominal propagation and F); quaternions are formed once at the end.
    rot = so3.quat_to_matrix(q)
    rots, bs, variances = [rot], [b], [torch.diagonal(P, dim1=-2, dim2=-1)[:, :3]]
    sig = {k: [] for k in ("mahalanobis_acc", "mahalanobis_mag", "fading", "acc_gated", "mag_gated")}
    for k in range(1, n):
        d = dt[:, k, None]
        # --- prediction (Eqs. 6-8, 10)
        w = gyro[:, k] - b
        inc = so3.exp(w * d)
        rot = rot @ inc
        F = torch.cat([torch.cat([inc.transpose(-1, -2), -eye3 * d[..., None]], -1), eye_bottom], -2)
        P = F @ P @ F.transpose(-1, -2) + torch.diag_embed(qd_rate * d)
        # --- accelerometer: gravity direction
        h = rot[:, 2, :]  # R^T up
        r = a_hat[:, k] - h
        H = torch.cat([so3.hat(h), zeros3], -1)
        Ra = eye3 * var_acc[:, k, None, None]
        rot, b, P, g_a, lp_a, lr_a = update(rot, b, P, r, H, Ra, acc_plaus[:, k], thr_acc)
        # --- magnetometer: heading of the levelled field
        if mag is not None:
            v = (rot @ mag[:, k, :, None])[..., 0]
            vh2 = (v[:, :2] ** 2).sum(-1).clamp_min(1e-12)
            r = torch.atan2(v[:, 1], v[:, 0]) - math.pi / 2
            r = torch.remainder(r + math.pi, 2 * math.pi) - math.pi
            H = torch.cat([-rot[:, 2:3, :], zeros13], -1)  # (B, 1, 6)
            Rm = (var_mag[:, k] * (v * v).sum(-1) / vh2)[:, None, None]
            rot, b, P, g_m, lp_m, lr_m = update(rot, b, P, r[:, None], H, Rm, mag_plaus[:, k], thr_mag)
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
            first = torch.ones(B, dtype=dtype, device=gyro.device) if name == "fading" else torch.zeros(B, dtype=dtype, device=gyro.device)
            if name.endswith("gated"):
                first = first > 0.5
            res[name] = torch.stack([first] + sig[name], 1)
    return {k: unflatten(v, batch) for k, v in res.items()}
