"""UWB/IMU positioning robust to NLOS outliers: the adaptive-robust complementary Kalman filter
(ARCKF) of ``../shared/papers/adaptive-robust-ckf-uwb-imu.txt`` (equation numbers are the
paper's), batched over B runs, float64, pure torch.

Complementary (error-state) filter, 15 states ``[dp, dv, dtheta, db_a, db_g]``:

* Prediction at the IMU rate (Eqs. 1-11, 13-28): the strapdown mechanisation and the error
  covariance of :func:`tcn_ahrs.nav.odometry.predict` with its bias states — the same math as
  the odometry ES-EKF, written once. Differences from the paper's printing, all
  parametrisation: the attitude error is body-frame (``R_true = R exp([dtheta]x)``) rather than
  the n-frame ``epsilon`` (equivalent: ``epsilon = R dtheta``; the range rows do not touch it), the
  biases are ordered ``[b_a, b_g]`` (the paper's G/Q of Eqs. 25-27 already are, its state vector
  is not), every error is ``true - estimate`` (the paper mixes both signs between Eqs. 8-10,
  29 and 30), and Q per step is ``sigma^2 dt^2`` on dv/dtheta and ``U dt`` on the bias walks
  (Eq. 28 prints no dt; Table 2's values are then per-second densities).
* Range rows (Eqs. 29-32): ``Z_i = r_i - ||S_i - p||``, ``H_i = -(S_i - p)^T / ||S_i - p||`` on dp
  (the derivative of Eq. 29; Eq. 30 prints the opposite sign), ``R_i = sigma_s^2 C_u,i`` (Eq. 38).
* Robustness factor (Eqs. 33-37): the per-beacon residual ``dr_i`` of a trilateration of this
  epoch's ranges alone (Eq. 33's L1 fit in the horizontal plane, :func:`trilaterate`),
  ``C_u,i = min(exp|dr_i|, C_u,max)``, ``C_u,max = exp(f(d) + 3 sigma)``,
  ``f(d) = 0.4 (1.10 - exp(-0.17 d))``; fewer than 3 ranges: ``C_u = 1``.
* Algorithm 1 (Eqs. 39-42): per beacon ``gamma_i = Z_i^2 / (H_i P H_i^T + R_i)`` against the
  chi-square(1) threshold; ``C_u,i < C_u,max`` (a trusted range): the state is off, P is
  inflated by ``gamma/chi2`` (fading factor, Eq. 42); else an outlier, its ``R_i`` is (Eq. 41);
  the paper's ``while`` loops run ``n_iter`` times (:func:`tcn_ahrs.filters.robust.robust_inflation`;
  they converge to ``gamma = chi2`` and never exit exactly), beacon by beacon, so a P inflation
  carries into the next beacon's test; then one Joseph update with every beacon.
* Threshold: the paper prints chi2 = 6.2 "for alpha = 0.001"; the chi-square(1) quantile at
  alpha = 0.001 is 10.83 (6.2 is alpha = 0.0128). ``gate_alpha`` takes the quantile from
  scipy, ``gate_threshold`` a number; the experiment reports both.

Beyond the paper: ``huber`` (a Huber M-estimator update, the second robust baseline: each
beacon's R divided by its Huber weight of the normalised innovation), and missing ranges
(beacon dropouts: NaN ranges are left out of that epoch).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import torch
from torch import Tensor

from .. import so3
from ..conventions import GRAVITY
from ..filters.kalman import chi2_threshold, kalman_update
from ..filters.robust import robust_inflation
from .odometry import OdometryNoise, correct, predict

G0 = 9.80665  # m/s^2 per g (Table 2's units)


@dataclass(frozen=True)
class UwbParams:
    """Filter settings; defaults from the paper (Table 2, Eqs. 36-42).

    accel_noise, gyro_noise: sqrt(N_a), sqrt(N_g), m/s^2 and rad/s (Table 2: 0.1 g, 0.2 rad/s).
    noise_per_sample: read N_a, N_g as per-sample variances (True) or as densities per Hz.
    accel_bias_walk, gyro_bias_walk: sqrt(U_a), sqrt(U_g) per sqrt(s) (Table 2: 0.01 g, 0.02 rad/s).
    range_std: sigma_s of Eq. 38, m (the paper's sigma = 0.1 m of Eq. 37).
    cu_sigma: sigma of the C_u,max threshold, Eq. 37, m.
    robust: Algorithm 1 on (False: the plain CKF, R_i = sigma_s^2).
    gate_alpha / gate_threshold: the chi-square(1) test (threshold wins when set).
    n_iter: inflation rounds of Algorithm 1's while loops.
    max_fading: cap on the product of one epoch's P inflations (not in the paper: uncapped, a
        range a trilateration failed to flag inflates the whole P by its gamma/chi2 and the
        filter diverges within seconds).
    huber: Huber M-estimator update instead of Algorithm 1 (with robust=False); huber_k its tuning constant.
    init_pos, init_vel, init_att, init_accel_bias, init_gyro_bias: P_0 stds (m, m/s, rad, m/s^2, rad/s).
    """

    accel_noise: float = 0.1 * G0
    gyro_noise: float = 0.2
    accel_bias_walk: float = 0.01 * G0
    gyro_bias_walk: float = 0.02
    noise_per_sample: bool = True
    range_std: float = 0.1
    cu_sigma: float = 0.1
    robust: bool = True
    gate_alpha: float = 0.001
    gate_threshold: Optional[float] = None
    n_iter: int = 3
    max_fading: float = 100.0
    huber: bool = False
    huber_k: float = 1.345
    init_pos: float = 0.3
    init_vel: float = 0.05
    init_att: float = 0.05
    init_accel_bias: float = 0.5
    init_gyro_bias: float = 0.01

    @property
    def threshold(self) -> float:
        return float(self.gate_threshold) if self.gate_threshold is not None else chi2_threshold(self.gate_alpha, 1)

    def odometry_noise(self, dt: float) -> OdometryNoise:
        """The shared prediction's settings for an IMU period dt. ``noise_per_sample``: Table 2's
        N_a, N_g are per-sample variances of the IMU's noise (:func:`odometry.predict` puts
        ``sigma^2 dt^2`` on dv and dtheta); else densities, per-sample ``sqrt(N / dt)``."""
        scale = 1.0 if self.noise_per_sample else dt ** -0.5
        return OdometryNoise(accel=self.accel_noise * scale, gyro=self.gyro_noise * scale,
                             accel_bias_walk=self.accel_bias_walk, gyro_bias_walk=self.gyro_bias_walk,
                             estimate_biases=True)

    def initial_cov(self, batch: int, dtype=torch.float64) -> Tensor:
        d = [self.init_pos ** 2] * 3 + [self.init_vel ** 2] * 3 + [self.init_att ** 2] * 3 + \
            [self.init_accel_bias ** 2] * 3 + [self.init_gyro_bias ** 2] * 3
        return torch.diag(torch.tensor(d, dtype=dtype)).repeat(batch, 1, 1)


PLAIN = UwbParams(robust=False)


def ranging_error(d: Tensor) -> Tensor:
    """f(d) = 0.4 (1.10 - exp(-0.17 d)), the expected UWB ranging error at range d (m), Eq. 36."""
    return 0.4 * (1.10 - torch.exp(-0.17 * d))


def cu_max(d: Tensor, sigma: float = 0.1) -> Tensor:
    """Threshold of the robustness factor, Eq. 37: exp(f(d) + 3 sigma)."""
    return torch.exp(ranging_error(d) + 3.0 * sigma)


def trilaterate(beacons: Tensor, ranges: Tensor, valid: Tensor, x0: Tensor, n_iter: int = 30,
                eps: float = 1e-4) -> Tuple[Tensor, Tensor]:
    """Eq. 33-34: the horizontal position minimising ``sum_i | ||x - S_i|| - r_i |`` (L1), by
    iteratively reweighted Gauss-Newton from ``x0``. beacons (n, 2) m; ranges (B, n) horizontal
    ranges; valid (B, n) bool; x0 (B, 2). Returns (x (B, 2), residuals ``r_i - ||x - S_i||`` (B, n),
    zero where invalid)."""
    x = x0.clone()
    w_valid = valid.to(x.dtype)
    r = torch.where(valid, ranges, torch.zeros_like(ranges))
    for _ in range(n_iter):
        diff = x[:, None, :] - beacons[None]            # (B, n, 2)
        dist = diff.norm(dim=-1).clamp_min(1e-9)
        res = dist - r
        J = diff / dist[..., None]                      # d dist / d x
        w = w_valid / res.abs().clamp_min(eps)          # IRLS weights of the L1 cost
        JtW = J.transpose(-1, -2) * w[:, None, :]
        A = JtW @ J + 1e-9 * torch.eye(2, dtype=x.dtype)
        step = torch.linalg.solve(A, (JtW @ res[..., None]))[..., 0]
        x = x - step
    dist = (x[:, None, :] - beacons[None]).norm(dim=-1)
    return x, torch.where(valid, r - dist, torch.zeros_like(r))


def robustness_factor(residual: Tensor, d: Tensor, valid: Tensor, sigma: float = 0.1) -> Tuple[Tensor, Tensor, Tensor]:
    """Eq. 35 with Eq. 37: (C_u (B, n), C_u,max (B, n), at_threshold (B, n) bool). Epochs with fewer
    than 3 valid ranges get C_u = 1 (no residual to judge by)."""
    cmax = cu_max(d, sigma)
    cu = torch.exp(residual.abs())
    at = (cu >= cmax) & valid
    cu = torch.minimum(cu, cmax)
    few = valid.sum(-1, keepdim=True) < 3
    cu = torch.where(few | ~valid, torch.ones_like(cu), cu)
    at = at & ~few
    return cu, cmax, at


def range_rows(p: Tensor, beacons: Tensor, ranges: Tensor) -> Tuple[Tensor, Tensor]:
    """Eqs. 29-31 linearised at the predicted position: Z (B, n) = r - ||S - p||, H (B, n, 15)
    with ``-(S - p)^T / ||S - p||`` on dp."""
    diff = beacons[None] - p[:, None, :]               # (B, n, 3)
    dist = diff.norm(dim=-1).clamp_min(1e-9)
    H = p.new_zeros(p.shape[0], beacons.shape[0], 15)
    H[..., 0:3] = -diff / dist[..., None]
    return ranges - dist, H


def uwb_update(p: Tensor, v: Tensor, rot: Tensor, bias: Tensor, P: Tensor, beacons: Tensor, ranges: Tensor,
               params: UwbParams, cu: Optional[Tensor] = None, trusted: Optional[Tensor] = None) -> Dict[str, Tensor]:
    """One UWB epoch: ranges (B, n) (NaN = missing), the robustness factors ``cu`` (B, n) and
    ``trusted`` (B, n) bool (C_u < C_u,max) for Algorithm 1. Returns the corrected state and
    covariance and the per-beacon ``gamma`` (B, n) (NaN where missing), ``lam_p`` (B,) the total
    fading factor, ``r_scale`` (B, n) the R inflations."""
    B, n = ranges.shape
    valid = torch.isfinite(ranges)
    Z, H = range_rows(p, beacons, torch.where(valid, ranges, torch.zeros_like(ranges)))
    var = torch.full((B, n), params.range_std ** 2, dtype=p.dtype, device=p.device)
    if params.robust and cu is not None:
        var = var * cu
    thr = params.threshold
    gammas, r_scale = [], []
    lam_total = torch.ones(B, dtype=p.dtype, device=p.device)
    P = P.clone()
    for i in range(n):
        hph = (H[:, i:i + 1] @ P @ H[:, i:i + 1].transpose(-1, -2))
        Ri = var[:, i, None, None]
        gamma = (Z[:, i] ** 2 / (hph[:, 0, 0] + Ri[:, 0, 0]))
        gammas.append(torch.where(valid[:, i], gamma, torch.full_like(gamma, float("nan"))))
        scale = torch.ones_like(gamma)
        if params.robust:
            plaus = trusted[:, i] if trusted is not None else torch.ones_like(valid[:, i])
            _, lam_p, lam_r = robust_inflation(Z[:, i:i + 1], hph, Ri, plaus, thr, params.n_iter, params.max_fading)
            lam_p = torch.where(valid[:, i], lam_p, torch.ones_like(lam_p))
            lam_p = torch.minimum(lam_p, params.max_fading / lam_total)
            P = P * lam_p[:, None, None]        # Eq. 42 on the whole prior, before the next beacon
            lam_total = lam_total * lam_p
            scale = torch.where(valid[:, i], lam_r, scale)
        elif params.huber:
            u = (Z[:, i] / (hph[:, 0, 0] + Ri[:, 0, 0]).sqrt()).abs()
            scale = torch.where(u > params.huber_k, u / params.huber_k, scale)  # R / w, w = k/|u|
        r_scale.append(scale)
    r_scale = torch.stack(r_scale, -1)
    var = var * r_scale
    # missing ranges: a zero row with a unit variance adds nothing
    H = torch.where(valid[..., None], H, torch.zeros_like(H))
    Z = torch.where(valid, Z, torch.zeros_like(Z))
    var = torch.where(valid, var, torch.ones_like(var))
    dx, P = kalman_update(P, Z, H, torch.diag_embed(var))
    p, v, rot, P, bias = correct(p, v, rot, P, dx, bias)
    return {"p": p, "v": v, "rot": rot, "bias": bias, "P": P, "gamma": torch.stack(gammas, -1),
            "lam_p": lam_total, "r_scale": r_scale}


def arckf(acc: Tensor, gyro: Tensor, dt: float, ranges: Tensor, beacons: Tensor, p0: Tensor, v0: Tensor, q0: Tensor,
          params: UwbParams = UwbParams(), bias0: Optional[Tensor] = None, tag_height: Optional[float] = None,
          gravity: float = GRAVITY) -> Dict[str, Tensor]:
    """Run the filter over B runs.

    Args:
        acc, gyro: (B, N, 3) IMU at a constant period ``dt`` s (body; specific force, rad/s).
        ranges: (B, N, n) UWB ranges to the n beacons in m, NaN where no range arrived (the UWB
            epochs: rows with any finite range).
        beacons: (n, 3) beacon positions, ENU m.
        p0, v0: (B, 3); q0: (B, 4) initial pose; bias0: (B, 6) initial ``[b_a, b_g]``.
        params: :class:`UwbParams` (``PLAIN`` for the CKF).
        tag_height: height of the tag for the trilateration's horizontal ranges (default: the
            estimate's height at that epoch).
    Returns:
        ``pos`` (B, N, 3), ``quat`` (B, N, 4), ``bias`` (B, N, 6), ``pos_std`` (B, N, 3) and per UWB
        epoch (E epochs): ``epoch_index`` (E,), ``gamma``, ``cu``, ``at_threshold`` (B, E, n),
        ``lam_p`` (B, E).
    """
    B, N = acc.shape[:2]
    noise = params.odometry_noise(dt)
    p, v = p0.clone(), v0.clone()
    rot = so3.quat_to_matrix(so3.quat_normalize(q0))
    bias = acc.new_zeros(B, 6) if bias0 is None else bias0.clone()
    P = params.initial_cov(B, acc.dtype)
    dts = torch.full((B,), float(dt), dtype=acc.dtype)
    epoch = torch.isfinite(ranges).any(-1).any(0)        # (N,): a UWB epoch in any run
    pos, quat, biases, stds = [p], [rot], [bias], [P.diagonal(dim1=-2, dim2=-1)[:, :3].sqrt()]
    rec = {"epoch_index": [], "gamma": [], "cu": [], "at_threshold": [], "lam_p": []}
    for k in range(1, N):
        p, v, rot, P = predict(p, v, rot, P, acc[:, k], gyro[:, k], dts, noise, gravity, bias)
        if bool(epoch[k]):
            r = ranges[:, k]
            valid = torch.isfinite(r)
            dz = beacons[None, :, 2] - (p[:, 2:3] if tag_height is None else tag_height)
            r_h = torch.sqrt((torch.where(valid, r, torch.zeros_like(r)) ** 2 - dz ** 2).clamp_min(0.0))
            _, res = trilaterate(beacons[:, :2], r_h, valid, p[:, :2])
            cu, cmax, at = robustness_factor(res, torch.where(valid, r, torch.zeros_like(r)), valid, params.cu_sigma)
            out = uwb_update(p, v, rot, bias, P, beacons, r, params, cu, ~at)
            p, v, rot, bias, P = out["p"], out["v"], out["rot"], out["bias"], out["P"]
            rec["epoch_index"].append(k)
            rec["gamma"].append(out["gamma"])
            rec["cu"].append(cu)
            rec["at_threshold"].append(at)
            rec["lam_p"].append(out["lam_p"])
        pos.append(p)
        quat.append(rot)
        biases.append(bias)
        stds.append(P.diagonal(dim1=-2, dim2=-1)[:, :3].clamp_min(0).sqrt())
    res = {"pos": torch.stack(pos, 1), "quat": so3.quat_positive(so3.matrix_to_quat(torch.stack(quat, 1))),
           "bias": torch.stack(biases, 1), "pos_std": torch.stack(stds, 1),
           "epoch_index": torch.tensor(rec["epoch_index"], dtype=torch.long)}
    for key in ("gamma", "cu", "at_threshold", "lam_p"):
        res[key] = torch.stack(rec[key], 1) if rec[key] else torch.zeros(B, 0)
    return res


def posterior_crlb(acc: Tensor, gyro: Tensor, rot: Tensor, dt: float, pos: Tensor, epochs: Tensor, beacons: Tensor,
                   accel_noise: float, gyro_noise: float, range_std: float, P0: Tensor) -> Tensor:
    """Posterior Cramér-Rao bound of the horizontal position (Eqs. 43-44, Tichavsky et al.):
    ``J_{k+1} = H^T R^-1 H + (Q_k + Phi_k J_k^-1 Phi_k^T)^-1`` (the paper's Eq. 44 with its
    misprints fixed: J_{k+1} on the left, the discrete Phi), along the TRUE trajectory with the
    TRUE noise (white IMU noise of the given per-sample stds, constant biases, range std).
    acc, gyro (N, 3); rot (N, 3, 3); pos (N, 3); epochs (N,) bool (ranges at that sample); P0
    (15, 15). Returns (N,) ``sqrt(trace of the horizontal block of J^-1)``, m."""
    noise = OdometryNoise(accel=accel_noise, gyro=gyro_noise, accel_bias_walk=0.0, gyro_bias_walk=0.0,
                          estimate_biases=True)
    Jinv = P0[None].clone()
    out = [Jinv[0, :2, :2].trace().sqrt()]
    dts = torch.full((1,), float(dt), dtype=acc.dtype)
    for k in range(1, acc.shape[0]):
        # covariance form of the information recursion: the prediction is P = Phi P Phi^T + Q
        _, _, _, Jinv = predict(pos[k - 1:k], pos.new_zeros(1, 3), rot[k - 1:k], Jinv, acc[k:k + 1], gyro[k:k + 1],
                                dts, noise)
        if bool(epochs[k]):
            _, H = range_rows(pos[k:k + 1], beacons, pos.new_zeros(1, beacons.shape[0]))
            J = torch.linalg.inv(Jinv) + H.transpose(-1, -2) @ H / range_std ** 2
            Jinv = torch.linalg.inv(J)
            Jinv = 0.5 * (Jinv + Jinv.transpose(-1, -2))
        out.append(Jinv[0, :2, :2].trace().clamp_min(0).sqrt())
    return torch.stack(out)


__all__ = ["UwbParams", "PLAIN", "ranging_error", "cu_max", "trilaterate", "robustness_factor", "range_rows",
           "uwb_update", "arckf", "posterior_crlb"]
