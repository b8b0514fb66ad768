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

Changes to Algorithm 1, each a :class:`UwbParams` field, each measured (``python
scripts/reproduce.py paper=uwb_arckf`` runs the printed version beside ours): the fading factor
on position and velocity only (``fading_states``; on all of P the biases and the attitude are
kicked through the inflated cross-covariances and runs diverge), an iterated range update
(``n_relinearise``), a floor constraint (``height_std``: four coplanar beacons leave the height
ambiguous) and trust only where the epoch had >= 4 ranges to accuse a bad one.

Beyond the paper: ``huber`` (a Huber M-estimator update, the second robust baseline: each
beacon's R divided by its Huber weight of the normalised innovation), ``imu_gate`` (the same
chi-square test on the accelerometer samples), missing ranges (beacon dropouts: NaN ranges are
left out of that epoch) and 3-D beacons (no floor constraint: ``tag_height=None``).
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
    fading_states: Eq. 42's fading factor inflates the first this many error states (15: the
        whole P, the paper's -- it diverges on our 50 dBW accelerometer outliers, its bias and
        attitude states kicked through the inflated cross-covariances; 6 (default): position and velocity, ``P <- D P D`` with ``D = diag(sqrt(lam) I_6,
        I_9)``, which keeps P positive definite and leaves attitude and biases as they were).
    n_relinearise: passes of the range update, each linearised at the last pass's position (1:
        the paper's single linearisation; 3 (default): an iterated EKF, for the metres of error an
        outlier leaves at 3-10 m from the beacons).
    imu_gate: the same chi-square test on the IMU side (beyond the paper): each accelerometer
        sample against the last accepted one, ``gamma = |a_k - a_ref|^2 / (2 accel_noise^2 +
        (imu_gate_jerk dt)^2)`` against chi-square(3) at ``gate_alpha``; a rejected sample is
        replaced by ``a_ref`` (the prediction then coasts on the last good specific force).
    imu_gate_jerk: m/s^3, the motion's plausible jerk in that test.
    imu_gate_max_hold: after this many rejections in a row the next sample is accepted (the
        reference is stale, not every new sample an outlier: a gate must not lock out).
    diverged_m: a run whose position leaves the beacons by more than this (or turns non-finite)
        is marked ``diverged`` and its output NaN from there (the other runs of the batch go on).
    height_std: std (m) of a floor constraint, the known tag height as one more observation per
        UWB epoch (None: off). Not in the paper, whose trolley and results are 2-D: with four
        coplanar beacons the height is observed only through the 1.2 m beacon-tag offset and
        is ambiguous (mirror about the beacon plane), so one 50 dBW accelerometer outlier
        (a 6 m/s velocity jump) sends the plain filter to the mirror solution and it diverges.
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
    height_std: Optional[float] = 0.05
    fading_states: int = 6
    n_relinearise: int = 3
    diverged_m: float = 1e3
    imu_gate: bool = False
    imu_gate_jerk: float = 10.0
    imu_gate_max_hold: int = 25
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
    iteratively reweighted Gauss-Newton from ``x0`` (the filter's prediction). The local minimum
    near the prediction, not the global one: with four ranges and two unknowns the global L1
    minimum passes exactly through two ranges and may pick a bad one (measured: starting from
    every leave-one-out closed-form fix and keeping the lowest cost tripled the ARCKF's RMSE at
    3 % contaminated ranges, 0.17 -> 0.53 m). beacons (n, 2) m; ranges (B, n) horizontal
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


def _fade(P: Tensor, lam: Tensor, k: int) -> Tensor:
    """Eq. 42's ``P <- lam P`` on the first k error states: ``D P D``, ``D = diag(sqrt(lam) I_k, I)``."""
    if k >= P.shape[-1]:
        return P * lam[:, None, None]
    d = torch.ones(P.shape[:-1], dtype=P.dtype, device=P.device)
    d[:, :k] = lam.sqrt()[:, None]
    return d[:, :, None] * P * d[:, None, :]


def uwb_update(p: Tensor, v: Tensor, rot: Tensor, bias: Tensor, P: Tensor, beacons: Tensor, ranges: Tensor,
               params: UwbParams, cu: Optional[Tensor] = None, trusted: Optional[Tensor] = None,
               height: Optional[float] = None) -> Dict[str, Tensor]:
    """One UWB epoch: ranges (B, n) (NaN = missing), the robustness factors ``cu`` (B, n) and
    ``trusted`` (B, n) bool (C_u < C_u,max) for Algorithm 1; ``height`` the floor constraint's
    tag height (with ``params.height_std``; not gated). Returns the corrected state and
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
            P = _fade(P, lam_p, params.fading_states)   # Eq. 42, before the next beacon's test
            lam_total = lam_total * lam_p
            scale = torch.where(valid[:, i], lam_r, scale)
        elif params.huber:
            u = (Z[:, i] / (hph[:, 0, 0] + Ri[:, 0, 0]).sqrt()).abs()
            scale = torch.where(u > params.huber_k, u / params.huber_k, scale)  # R / w, w = k/|u|
        r_scale.append(scale)
    r_scale = torch.stack(r_scale, -1)
    var = var * r_scale
    r_filled = torch.where(valid, ranges, torch.zeros_like(ranges))
    var = torch.where(valid, var, torch.ones_like(var))
    floor = height is not None and params.height_std is not None
    if floor:
        var = torch.cat([var, var.new_full((B, 1), params.height_std ** 2)], 1)
    R = torch.diag_embed(var)
    P_prior = P
    dx = p.new_zeros(B, 15)
    for _ in range(max(params.n_relinearise, 1)):
        # iterated EKF (Gauss-Newton on the ranges): relinearise at the updated position,
        # dx = K_j (Z_j + H_j dx_j); one pass is the paper's (and the standard) update
        Zj, Hj = range_rows(p + dx[:, :3], beacons, r_filled)
        Zj = Zj + (Hj @ dx[..., None])[..., 0]
        # missing ranges: a zero row with a unit variance adds nothing
        Hj = torch.where(valid[..., None], Hj, torch.zeros_like(Hj))
        Zj = torch.where(valid, Zj, torch.zeros_like(Zj))
        if floor:
            Hz = Hj.new_zeros(B, 1, 15)
            Hz[:, 0, 2] = 1.0
            Hj, Zj = torch.cat([Hj, Hz], 1), torch.cat([Zj, height - p[:, 2:3]], 1)
        dx, P = kalman_update(P_prior, Zj, Hj, R)
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
        tag_height: the tag's known height above the floor (m): the trilateration's horizontal
            ranges and the floor constraint (``params.height_std``); None: the estimate's height,
            no constraint.
    Returns:
        ``pos`` (B, N, 3), ``quat`` (B, N, 4), ``bias`` (B, N, 6), ``pos_std`` (B, N, 3) and per UWB
        epoch (E epochs): ``epoch_index`` (E,), ``gamma``, ``cu``, ``at_threshold``, ``r_scale`` (the
        R inflations) (B, E, n), ``lam_p`` (B, E) (the fading factor); ``diverged`` (B,) bool; ``imu_rejected`` (B, N) bool
        (the IMU gate's rejections).
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
    rec = {"epoch_index": [], "gamma": [], "cu": [], "at_threshold": [], "lam_p": [], "r_scale": []}
    diverged = torch.zeros(B, dtype=torch.bool)
    centre = beacons.mean(0)
    state0 = (p.clone(), v.clone(), rot.clone(), bias.clone(), P.clone())
    acc_ref = acc[:, 0]
    held = torch.zeros(B, dtype=torch.long)
    imu_rejected = torch.zeros(B, N, dtype=torch.bool)
    diverged_step = torch.full((B,), N, dtype=torch.long)
    if params.imu_gate:
        imu_thr = chi2_threshold(params.gate_alpha, 3)
        imu_var = 2.0 * noise.accel ** 2 + (params.imu_gate_jerk * dt) ** 2
    for k in range(1, N):
        a_k = acc[:, k]
        if params.imu_gate:
            bad = (((a_k - acc_ref) ** 2).sum(-1) / imu_var > imu_thr) & (held < params.imu_gate_max_hold)
            imu_rejected[:, k] = bad
            held = torch.where(bad, held + 1, torch.zeros_like(held))
            a_k = torch.where(bad[:, None], acc_ref, a_k)
            acc_ref = a_k
        p, v, rot, P = predict(p, v, rot, P, a_k, gyro[:, k], dts, noise, gravity, bias)
        lost = ~torch.isfinite(P).flatten(1).all(1) | ~torch.isfinite(p).all(1) | \
            ((p - centre).norm(dim=-1) > params.diverged_m)
        if bool(lost.any()):
            # a diverged run restarts from its initial state so that its batch's solves stay
            # finite; its output is NaN from here
            diverged_step = torch.where(lost & ~diverged, torch.full_like(diverged_step, k), diverged_step)
            diverged = diverged | lost
            acc_ref = torch.where(lost[:, None], acc[:, k], acc_ref)
            p, v, rot, bias, P = (torch.where(lost.view(-1, *[1] * (x.dim() - 1)), x0, x)
                                  for x, x0 in zip((p, v, rot, bias, P), state0))
        if bool(epoch[k]):
            r = ranges[:, k]
            valid = torch.isfinite(r)
            dz = beacons[None, :, 2] - (p[:, 2:3] if tag_height is None else tag_height)
            r_h = torch.sqrt((torch.where(valid, r, torch.zeros_like(r)) ** 2 - dz ** 2).clamp_min(0.0))
            _, res = trilaterate(beacons[:, :2], r_h, valid, p[:, :2])
            cu, cmax, at = robustness_factor(res, torch.where(valid, r, torch.zeros_like(r)), valid, params.cu_sigma)
            # a range is trusted (a large gamma then blames the state) only where the epoch's
            # geometry could have accused it: >= 4 ranges for the 2 unknowns (with 3 the L1 fit
            # passes exactly through two of them, whichever is bad); else a large gamma blames the range
            trusted = ~at & (valid.sum(-1, keepdim=True) >= 4)
            out = uwb_update(p, v, rot, bias, P, beacons, r, params, cu, trusted, tag_height)
            p, v, rot, bias, P = out["p"], out["v"], out["rot"], out["bias"], out["P"]
            rec["epoch_index"].append(k)
            rec["gamma"].append(out["gamma"])
            rec["cu"].append(cu)
            rec["at_threshold"].append(at)
            rec["lam_p"].append(out["lam_p"])
            rec["r_scale"].append(out["r_scale"])
        nan = torch.full_like(p, float("nan"))
        pos.append(torch.where(diverged[:, None], nan, p))
        quat.append(rot)
        biases.append(bias)
        stds.append(P.diagonal(dim1=-2, dim2=-1)[:, :3].clamp_min(0).sqrt())
    res = {"pos": torch.stack(pos, 1), "quat": so3.quat_positive(so3.matrix_to_quat(torch.stack(quat, 1))),
           "bias": torch.stack(biases, 1), "pos_std": torch.stack(stds, 1),
           "epoch_index": torch.tensor(rec["epoch_index"], dtype=torch.long)}
    for key in ("gamma", "cu", "at_threshold", "lam_p", "r_scale"):
        res[key] = torch.stack(rec[key], 1) if rec[key] else torch.zeros(B, 0)
    # everything of a diverged run from its divergence on is NaN (False for flags): the restart
    # only kept the batch's algebra finite
    after = torch.arange(N)[None, :] >= diverged_step[:, None]                     # (B, N)
    for key in ("quat", "bias", "pos_std"):
        res[key] = torch.where(after[..., None], torch.full_like(res[key], float("nan")), res[key])
    if len(rec["epoch_index"]):
        ep_after = res["epoch_index"][None, :] >= diverged_step[:, None]           # (B, E)
        for key in ("gamma", "cu", "r_scale"):
            res[key] = torch.where(ep_after[..., None], torch.full_like(res[key], float("nan")), res[key])
        res["lam_p"] = torch.where(ep_after, torch.full_like(res["lam_p"], float("nan")), res["lam_p"])
        res["at_threshold"] = res["at_threshold"] & ~ep_after[..., None]
    res["diverged"] = diverged
    res["imu_rejected"] = imu_rejected
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
