"""SO(3) math in pure torch: batched, float32/float64, TorchScript-compatible.

Conventions (see :mod:`tcn_ahrs.conventions`): quaternions are Hamilton ``(w, x, y, z)``;
a rotation ``R`` maps body-frame vectors to the navigation frame; rotation vectors ``phi``
(axis * angle, radians) relate to matrices by ``R = exp(hat(phi))``.

Shapes: ``(..., 3)`` rotation vectors, ``(..., 3, 3)`` matrices, ``(..., 4)`` quaternions;
any number of leading batch dimensions.
"""
from __future__ import annotations

import math
from typing import Tuple

import torch
from torch import Tensor

# Below an angle of 1e-3 rad (squared: 1e-6, written inline for TorchScript) Taylor series
# replace the closed forms; the truncated terms (~theta^6) are below float64 round-off.


def _eps(x: Tensor) -> float:
    return 1e-12 if x.dtype == torch.float64 else 1e-6


def hat(phi: Tensor) -> Tensor:
    """(..., 3) -> (..., 3, 3) skew-symmetric matrix with ``hat(a) @ b == cross(a, b)``."""
    x, y, z = phi[..., 0], phi[..., 1], phi[..., 2]
    o = torch.zeros_like(x)
    return torch.stack(
        [torch.stack([o, -z, y], -1), torch.stack([z, o, -x], -1), torch.stack([-y, x, o], -1)], -2
    )


def vee(m: Tensor) -> Tensor:
    """(..., 3, 3) -> (..., 3): inverse of :func:`hat` (uses the antisymmetric part)."""
    return 0.5 * torch.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1
    )


def _sinc_terms(theta2: Tensor) -> Tuple[Tensor, Tensor]:
    """A = sin(t)/t and B = (1 - cos(t))/t^2 from t^2, stable (and differentiable) at t -> 0."""
    small = theta2 < 1e-6
    t2s = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2s)
    a = torch.where(small, 1.0 - theta2 / 6.0 + theta2 * theta2 / 120.0, torch.sin(t) / t)
    b = torch.where(small, 0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0, (1.0 - torch.cos(t)) / t2s)
    return a, b


def exp(phi: Tensor) -> Tensor:
    """Rotation vector (..., 3) -> rotation matrix (..., 3, 3) (Rodrigues' formula)."""
    theta2 = (phi * phi).sum(-1)
    a, b = _sinc_terms(theta2)
    k = hat(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def log(r: Tensor) -> Tensor:
    """Rotation matrix (..., 3, 3) -> rotation vector (..., 3) with angle in [0, pi].

    Goes through the quaternion (Shepperd's method picks the best-conditioned branch), then
    :func:`quat_log`, which is stable near 0 and near pi, including its gradient.
    """
    return quat_log(matrix_to_quat(r))


def quat_normalize(q: Tensor) -> Tensor:
    """(..., 4) -> unit quaternion."""
    return q / torch.sqrt((q * q).sum(-1, keepdim=True)).clamp_min(_eps(q))


def quat_positive(q: Tensor) -> Tensor:
    """Pick the representative with ``w >= 0`` (q and -q are the same rotation)."""
    return torch.where(q[..., :1] < 0, -q, q)


def quat_conj(q: Tensor) -> Tensor:
    """(..., 4) -> conjugate (the inverse rotation for unit quaternions)."""
    return torch.cat([q[..., :1], -q[..., 1:]], -1)


def quat_mul(p: Tensor, q: Tensor) -> Tensor:
    """Hamilton product ``p * q`` of (..., 4) quaternions (broadcasting); as rotations: ``R(p) @ R(q)``."""
    pw, px, py, pz = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return torch.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        -1,
    )


def quat_rotate(q: Tensor, v: Tensor) -> Tensor:
    """Rotate (..., 3) vectors by (..., 4) unit quaternions: ``R(q) @ v``."""
    u = q[..., 1:]
    w = q[..., :1]
    t = 2.0 * torch.cross(u, v, dim=-1)
    return v + w * t + torch.cross(u, t, dim=-1)


def quat_to_matrix(q: Tensor) -> Tensor:
    """Unit quaternion (..., 4) (w,x,y,z) -> rotation matrix (..., 3, 3)."""
    q = quat_normalize(q)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quat(r: Tensor) -> Tensor:
    """Rotation matrix (..., 3, 3) -> unit quaternion (..., 4) with ``w >= 0``.

    Shepperd's method: of the four candidate formulas, use the one whose square root has
    the largest argument, so the result (and its gradient) is well conditioned everywhere.
    """
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    m01, m02, m10 = r[..., 0, 1], r[..., 0, 2], r[..., 1, 0]
    m12, m20, m21 = r[..., 1, 2], r[..., 2, 0], r[..., 2, 1]
    tr = m00 + m11 + m22
    # 4*w^2, 4*x^2, 4*y^2, 4*z^2
    d = torch.stack([1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = d.argmax(-1, keepdim=True)
    s = 2.0 * torch.sqrt(d.clamp_min(_eps(r)))  # s_i = 4 * |q_i|
    sw, sx, sy, sz = s[..., 0], s[..., 1], s[..., 2], s[..., 3]
    cand = torch.stack(
        [
            torch.stack([0.25 * sw, (m21 - m12) / sw, (m02 - m20) / sw, (m10 - m01) / sw], -1),
            torch.stack([(m21 - m12) / sx, 0.25 * sx, (m01 + m10) / sx, (m02 + m20) / sx], -1),
            torch.stack([(m02 - m20) / sy, (m01 + m10) / sy, 0.25 * sy, (m12 + m21) / sy], -1),
            torch.stack([(m10 - m01) / sz, (m02 + m20) / sz, (m12 + m21) / sz, 0.25 * sz], -1),
        ],
        -2,
    )  # (..., 4 candidates, 4 components)
    shape = list(best.shape[:-1])
    idx = best.unsqueeze(-1).expand(shape + [1, 4])
    q = torch.gather(cand, -2, idx).squeeze(-2)
    return quat_positive(quat_normalize(q))


def quat_exp(phi: Tensor) -> Tensor:
    """Rotation vector (..., 3) -> unit quaternion (..., 4)."""
    theta2 = (phi * phi).sum(-1, keepdim=True)
    small = theta2 < 1e-6
    t2s = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2s)
    # sin(t/2)/t and cos(t/2) with Taylor expansions near 0
    half_sinc = torch.where(small, 0.5 - theta2 / 48.0 + theta2 * theta2 / 3840.0, torch.sin(0.5 * t) / t)
    w = torch.where(small, 1.0 - theta2 / 8.0 + theta2 * theta2 / 384.0, torch.cos(0.5 * t))
    return torch.cat([w, half_sinc * phi], -1)


def quat_log(q: Tensor) -> Tensor:
    """Unit quaternion (..., 4) -> rotation vector (..., 3) with angle in [0, pi].

    ``phi = 2 atan2(|v|, w) v / |v|`` on the ``w >= 0`` representative: atan2 keeps full
    precision near pi (where acos would not), and near 0 a Taylor series keeps the
    gradient finite.
    """
    q = quat_positive(q)
    w = q[..., :1]
    v = q[..., 1:]
    n2 = (v * v).sum(-1, keepdim=True)
    small = n2 < 1e-6
    n = torch.sqrt(torch.where(small, torch.ones_like(n2), n2))
    ws = torch.where(small, w, torch.ones_like(w))  # w ~ 1 where used; avoid 1/0 elsewhere
    # 2 atan2(n, w)/n ; for small n: 2/w (1 - n^2/(3 w^2))
    scale_big = 2.0 * torch.atan2(n, w) / n
    scale_small = 2.0 / ws * (1.0 - n2 / (3.0 * ws * ws))
    return torch.where(small, scale_small, scale_big) * v


def quat_slerp(q0: Tensor, q1: Tensor, t: Tensor) -> Tensor:
    """Spherical linear interpolation between unit quaternions (..., 4) at fractions t (...)
    (shortest path): ``q0 * exp(t * log(q0^-1 q1))``."""
    d = quat_mul(quat_conj(q0), q1)
    phi = quat_log(d)
    return quat_mul(q0, quat_exp(t.unsqueeze(-1) * phi))


def matrix_to_euler(r: Tensor) -> Tensor:
    """Rotation matrix (..., 3, 3) -> (..., 3) roll, pitch, yaw in radians
    (intrinsic z-y'-x'': ``R = Rz(yaw) Ry(pitch) Rx(roll)``)."""
    roll = torch.atan2(r[..., 2, 1], r[..., 2, 2])
    pitch = torch.asin((-r[..., 2, 0]).clamp(-1.0, 1.0))
    yaw = torch.atan2(r[..., 1, 0], r[..., 0, 0])
    return torch.stack([roll, pitch, yaw], -1)


def quat_to_euler(q: Tensor) -> Tensor:
    """Unit quaternion (..., 4) -> (..., 3) roll, pitch, yaw (see :func:`matrix_to_euler`)."""
    return matrix_to_euler(quat_to_matrix(q))


def yaw(r: Tensor) -> Tensor:
    """Heading (..., ) of rotation matrices (..., 3, 3): angle of the body x axis projected on the
    horizontal plane (z-y'-x'' yaw), radians."""
    return torch.atan2(r[..., 1, 0], r[..., 0, 0])


def wrap_angle(a: Tensor) -> Tensor:
    """Wrap angles to (-pi, pi]."""
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


def cumprod_matrix(r: Tensor, dim: int = -3) -> Tensor:
    """Inclusive cumulative product ``P_k = R_0 R_1 ... R_k`` of (..., N, 3, 3) matrices along
    the sequence dimension (``-3``), in ceil(log2 N) parallel steps (Hillis-Steele scan).

    Each step is one batched matmul over the whole sequence, so on a GPU the depth is
    O(log N) instead of O(N). Work is O(N log N); round-off grows like O(log N) products.
    """
    assert dim == -3, "the sequence dimension must be the third from last"
    n = r.shape[-3]
    p = r
    d = 1
    while d < n:
        p = torch.cat([p[..., :d, :, :], p[..., :-d, :, :] @ p[..., d:, :, :]], -3)
        d *= 2
    return p


def cumprod_quat(q: Tensor) -> Tensor:
    """Inclusive cumulative Hamilton product of (..., N, 4) quaternions along dim -2 in
    O(log N) parallel steps (renormalised after each step)."""
    n = q.shape[-2]
    p = q
    d = 1
    while d < n:
        p = torch.cat([p[..., :d, :], quat_normalize(quat_mul(p[..., :-d, :], p[..., d:, :]))], -2)
        d *= 2
    return p


def cumprod_matrix_sequential(r: Tensor) -> Tensor:
    """Reference O(N) sequential cumulative product of (..., N, 3, 3) (for tests and tiny N)."""
    out = [r[..., 0, :, :]]
    for k in range(1, r.shape[-3]):
        out.append(out[-1] @ r[..., k, :, :])
    return torch.stack(out, -3)


def integrate(r0: Tensor, omega: Tensor, dt: Tensor) -> Tensor:
    """Strapdown integration (paper Eq. 3): ``R_k = R_0 exp(w_1 dt_1) ... exp(w_k dt_k)``.

    Args:
        r0:    (..., 3, 3) initial ``nav_from_body``.
        omega: (..., N, 3) body angular rate, rad/s; sample k moves the attitude from k-1 to k.
        dt:    (..., N) or broadcastable time steps, s.
    Returns:
        (..., N, 3, 3) with ``R[..., 0] = r0`` (the first rate sample is not applied).
    """
    inc = exp(omega[..., 1:, :] * dt[..., 1:, None])
    first = r0.unsqueeze(-3)
    prod = cumprod_matrix(torch.cat([first, inc], -3))
    return prod
