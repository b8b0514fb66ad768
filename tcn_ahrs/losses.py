"""Training loss on incremental rotations (paper Sec. 3.4, Eqs. 26-28).

``δC_{i,i+j} = C_i^T C_{i+j} = ∏_{k=i+1}^{i+j} exp(ω_k Δt_k)``                          (Eq. 26)
``L_j = Σ_i ρ(Log(δC_gt,i,i+j^T δĈ_i,i+j))``                                          (Eq. 27)
``L = L_16 + L_32``                                                                      (Eq. 28)

ρ is the Huber loss with δ = 0.005 rad, applied per component and divided by δ (PyTorch's
smooth-L1 with ``beta = δ``): the minimiser is the same as the paper's, the value reads as
"≈ |error| in rad" for large errors, and Adam is insensitive to the constant factor.

The predicted increments need no absolute attitude: for every start i the product of j
consecutive exponentials is built by doubling (``P_2k = P_k(i) P_k(i+k)``), i.e. log2(j)
batched matmuls over the whole window. The products are formed in float64 (the default
``dtype``): it costs little (3x3 matrices), and float32 round-off, although the doubling keeps it
small (~1e-7 rad after 4096 products; measured in tests/test_losses.py), would otherwise set a
floor under the residuals a well-trained model drives toward.
"""
from __future__ import annotations

import math
from typing import Optional, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from . import so3
from .conventions import LOSS_DTYPE


def window_products(rot: Tensor, j: int) -> Tensor:
    """Products of j consecutive matrices: rot (..., N, 3, 3) -> (..., N-j+1, 3, 3) with entry i
    = ``rot[i] rot[i+1] ... rot[i+j-1]``. Any j >= 1 (binary decomposition of j)."""
    if j < 1 or j > rot.shape[-3]:
        raise ValueError(f"window_products: j={j} must be in [1, N={rot.shape[-3]}]")
    result = None  # product of the first `done` factors, for every start
    done = 0
    power = rot  # products of `size` consecutive factors
    size = 1
    while True:
        if j & size:
            if result is None:
                result = power
            else:
                n = min(result.shape[-3], power.shape[-3] - done)
                result = result[..., :n, :, :] @ power[..., done:done + n, :, :]
            done += size
        if size * 2 > j:
            break
        power = power[..., :-size, :, :] @ power[..., size:, :, :]
        size *= 2
    n_out = rot.shape[-3] - j + 1
    return result[..., :n_out, :, :]


def predicted_increments(omega: Tensor, dt: Tensor, j: int, dtype=LOSS_DTYPE) -> Tensor:
    """δĈ_{i,i+j} for i = 0..N-1-j from body rates omega (B, N, 3), dt (B, N): sample k moves
    the attitude from k-1 to k, so the increment from i to i+j uses samples i+1..i+j.
    Returns (B, N-j, 3, 3) in ``dtype``."""
    inc = so3.exp(omega[..., 1:, :].to(dtype) * dt[..., 1:, None].to(dtype))
    return window_products(inc, j)


def true_increments(nav_from_body: Tensor, j: int) -> Tensor:
    """δC_gt,{i,i+j} = C_i^T C_{i+j}: (B, N, 3, 3) -> (B, N-j, 3, 3)."""
    return nav_from_body[..., :-j, :, :].transpose(-1, -2) @ nav_from_body[..., j:, :, :]


def increment_valid(valid: Tensor, j: int) -> Tensor:
    """(B, N) bool -> (B, N-j) bool: True where every sample i..i+j has valid ground truth
    (an increment touching an invalid sample is masked)."""
    bad = (~valid).to(torch.int32)
    c = torch.cat([torch.zeros_like(bad[..., :1]), bad.cumsum(-1)], -1)  # c[k] = #bad before k
    return (c[..., j + 1:] - c[..., :-j - 1]) == 0


def increment_loss(omega: Tensor, dt: Tensor, nav_from_body_gt: Tensor, valid: Tensor,
                   js: Sequence[int] = (16, 32), huber_delta: float = 0.005,
                   dtype=LOSS_DTYPE) -> Tensor:
    """Eq. 28: Σ_j mean over valid increments and components of Huber(Log(δC_gt^T δĈ))/δ.

    Args:
        omega: (B, N, 3) estimated body rate ω̂, rad/s.
        dt:    (B, N) s.
        nav_from_body_gt: (B, N, 3, 3) ground truth (rows where invalid may hold anything finite
            or NaN; they are masked).
        valid: (B, N) bool ground-truth validity.
    Returns a scalar in omega's dtype (0 if no increment is valid).
    """
    gt = torch.where(valid[..., None, None], nav_from_body_gt.to(dtype),
                     torch.eye(3, dtype=dtype, device=omega.device))
    total = omega.new_zeros(())
    for j in js:
        if omega.shape[-2] <= j:
            continue
        pred = predicted_increments(omega, dt, j, dtype)
        err = so3.log(true_increments(gt, j).transpose(-1, -2) @ pred)  # (B, N-j, 3)
        m = increment_valid(valid, j)
        if not bool(m.any()):
            continue
        per = F.smooth_l1_loss(err[m], torch.zeros_like(err[m]), beta=huber_delta, reduction="mean")
        total = total + per.to(omega.dtype)
    return total


def attitude_loss(nav_from_body: Tensor, nav_from_body_gt: Tensor, valid: Tensor,
                  huber_delta: float = 0.01) -> Tensor:
    """Loss of a closed-loop estimate against ground truth: mean over valid samples and
    components of Huber(e)/δ with ``e = vee(C_gt^T Ĉ)`` (= sin θ · axis: the rotation error to
    first order, smooth at zero).

    nav_from_body (B, N, 3, 3) estimate; nav_from_body_gt (B, N, 3, 3); valid (B, N) bool.
    A scalar (0 if nothing is valid)."""
    if not bool(valid.any()):
        return nav_from_body.sum() * 0.0
    est = nav_from_body[valid]
    e = so3.vee(nav_from_body_gt[valid].to(est.dtype).transpose(-1, -2) @ est)
    return F.smooth_l1_loss(e, torch.zeros_like(e), beta=huber_delta, reduction="mean")


def trust_labels(imu: Tensor, nav_from_body: Tensor, valid: Tensor, acc_deg: float = 2.0,
                 mag_deg: float = 3.0, mag_norm: float = 0.1) -> Tensor:
    """Whether each sample's accelerometer and magnetometer can be trusted, judged against the
    ground truth (the targets of the backbone's trust logits, :mod:`tcn_ahrs.model.residual`).

    imu (N, C) raw (body frame; C = 6 or 9), nav_from_body (N, 3, 3) ground truth, valid (N,).
    Returns (N, 2) in {0., 1.}: column 0 = the measured specific force points within ``acc_deg``
    of the true up (R^T e_z); column 1 = the field's horizontal direction in the navigation frame
    lies within ``mag_deg`` of the recording's own prevailing direction and its norm within
    ``mag_norm`` (relative) of the recording's median (always 1 without a magnetometer). The
    prevailing direction is the circular mean over the samples near the first circular mean (a
    disturbance that lasts less than half the recording does not move it). Invalid samples: 0."""
    rot = nav_from_body.to(torch.float64)
    acc = imu[:, 3:6].to(torch.float64)
    up_b = rot[:, 2, :]  # R^T e_z = third row of R
    cos_a = (acc * up_b).sum(-1) / acc.norm(dim=-1).clamp_min(1e-9)
    acc_ok = cos_a > torch.cos(torch.tensor(acc_deg * torch.pi / 180.0, dtype=torch.float64))
    mag_ok = torch.ones_like(acc_ok)
    if imu.shape[-1] >= 9 and bool(valid.any()):
        m = (rot @ imu[:, 6:9].to(torch.float64).unsqueeze(-1)).squeeze(-1)
        head = torch.atan2(m[:, 0], m[:, 1])
        norm = m.norm(dim=-1)
        v = valid.bool()
        ref = torch.atan2(torch.sin(head[v]).mean(), torch.cos(head[v]).mean())
        near = v & (torch.remainder(head - ref + torch.pi, 2 * torch.pi) - torch.pi).abs().lt(torch.pi / 18)
        if bool(near.any()):
            ref = torch.atan2(torch.sin(head[near]).mean(), torch.cos(head[near]).mean())
        err = (torch.remainder(head - ref + torch.pi, 2 * torch.pi) - torch.pi).abs()
        med = norm[v].median()
        mag_ok = (err < mag_deg * torch.pi / 180.0) & ((norm / med - 1.0).abs() < mag_norm)
    out = torch.stack([acc_ok, mag_ok], -1).to(torch.float32)
    return out * valid.to(torch.float32).unsqueeze(-1)


def trust_loss(logits: Tensor, labels: Tensor, valid: Tensor) -> Tensor:
    """Binary cross-entropy of trust logits (B, N) against labels (B, N) on valid samples."""
    v = valid.to(logits.dtype)
    bce = F.binary_cross_entropy_with_logits(logits, labels.to(logits.dtype), reduction="none")
    return (bce * v).sum() / v.sum().clamp_min(1.0)


def self_labels(imu: Tensor, dt: Tensor, horizon_s: float = 0.2, acc_deg: float = 3.0, acc_norm: float = 0.03,
                mag_deg: float = 3.0, mag_norm: float = 0.1, rest_s: float = 0.5,
                rest_acc: float = 0.1, rest_gyro: float = 0.005, rest: Optional[Tensor] = None) -> Tensor:
    """Targets for self-supervised training (no motion capture): what the sensors say about
    themselves. imu (N, C) raw, body frame (C = 6 or 9), dt (N,) s. Returns (N, 3) in {0., 1.}:

    * column 0, the accelerometer is trustworthy: its norm is within ``acc_norm`` (relative) of
      g, and its direction ``horizon_s`` earlier, carried to now by the gyro's rotation, lies
      within ``acc_deg`` of its direction now (gravity is fixed in the navigation frame; a
      short horizon keeps the gyro's bias out: 0.08 rad/s over 0.2 s is 0.9°);
    * column 1, the magnetometer is (always 1 without one): its norm within ``mag_norm`` of the
      recording's median and its dip (angle to the specific force, on samples of column 0)
      within ``mag_deg`` of the median dip (a fixed field, a fixed dip);
    * column 2, at rest: the gyro's and the accelerometer's standard deviations over ``rest_s``
      below ``rest_gyro`` rad/s and ``rest_acc`` m/s² (the true rate is then zero, so the
      gyro reads its bias). ``rest`` (N,) bool, when given, replaces that rule (the data module
      passes the device check's, which judges rest by the signal's character:
      :func:`tcn_ahrs.device_check.rest_windows`; absolute thresholds took TUM VI's slow hand
      motion for rest and taught the network a bias that is not there)."""
    from .conventions import GRAVITY

    x = imu.to(torch.float64)
    d = dt.to(torch.float64)
    n = x.shape[0]
    rate = 1.0 / float(d[1:].median()) if n > 1 else 1.0
    acc, gyro = x[:, 3:6], x[:, 0:3]
    a_norm = acc.norm(dim=-1).clamp_min(1e-9)
    k = max(1, int(round(horizon_s * rate)))
    rot = so3.integrate(torch.eye(3, dtype=torch.float64), gyro, d)  # (N, 3, 3) world_from_body, up to a constant
    acc_ok = (a_norm / GRAVITY - 1.0).abs() < acc_norm
    if n > k:
        # the direction k samples ago, carried into today's body frame: R_t^T R_{t-k} a_{t-k}
        prev = (rot[k:].transpose(-1, -2) @ (rot[:-k] @ acc[:-k].unsqueeze(-1))).squeeze(-1)
        cos = (prev * acc[k:]).sum(-1) / (prev.norm(dim=-1).clamp_min(1e-9) * a_norm[k:])
        agree = torch.zeros(n, dtype=torch.bool)
        agree[k:] = cos > math.cos(math.radians(acc_deg))
        acc_ok = acc_ok & agree
    else:
        acc_ok = torch.zeros(n, dtype=torch.bool)
    mag_ok = torch.ones(n, dtype=torch.bool)
    if x.shape[1] >= 9:
        m = x[:, 6:9]
        m_norm = m.norm(dim=-1).clamp_min(1e-9)
        dip = torch.acos(((m * acc).sum(-1) / (m_norm * a_norm)).clamp(-1.0, 1.0))
        ref = dip[acc_ok].median() if bool(acc_ok.any()) else dip.median()
        mag_ok = ((m_norm / m_norm.median() - 1.0).abs() < mag_norm) & ((dip - ref).abs() < math.radians(mag_deg))
    w = max(3, int(rest_s * rate))
    if rest is not None:
        return torch.stack([acc_ok, mag_ok, torch.as_tensor(rest, dtype=torch.bool)], -1).to(torch.float32)
    rest = torch.zeros(n, dtype=torch.bool)
    if n >= w:
        def rolling_std(v: Tensor) -> Tensor:
            c = torch.cat([torch.zeros(1, 3, dtype=v.dtype), torch.cumsum(v, 0)])
            c2 = torch.cat([torch.zeros(1, 3, dtype=v.dtype), torch.cumsum(v * v, 0)])
            mean = (c[w:] - c[:-w]) / w
            return ((c2[w:] - c2[:-w]) / w - mean ** 2).clamp_min(0.0).sum(-1).sqrt()

        still = (rolling_std(gyro) < rest_gyro) & (rolling_std(acc) < rest_acc)  # window ending at sample i + w - 1
        rest[w - 1:] = still
    return torch.stack([acc_ok, mag_ok, rest], -1).to(torch.float32)


def rest_rate_loss(omega: Tensor, rest: Tensor, huber_delta: float = 0.005) -> Tensor:
    """Self-supervised gyro loss: at rest the true rate is zero, so the corrected rate omega
    (B, N, 3) rad/s should be (Huber, δ rad/s, divided by δ as :func:`increment_loss`) on the
    samples where ``rest`` (B, N) holds; 0 when none is at rest."""
    m = rest.bool()
    if not bool(m.any()):
        return omega.new_zeros(())
    e = omega[m]
    return F.smooth_l1_loss(e, torch.zeros_like(e), beta=huber_delta, reduction="mean") / huber_delta
