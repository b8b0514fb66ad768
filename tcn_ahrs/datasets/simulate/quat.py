"""Quaternion helpers in numpy (float64), an independent oracle of :mod:`tcn_ahrs.so3` (torch):
the same formulas, tested against it (``tests/test_simulate.py``); the simulator is I/O-side
numpy and must generate > 1 M samples/s."""
from __future__ import annotations

import math

import numpy as np



# =============================================================================
# Quaternion helpers in numpy (float64; the same formulas as tcn_ahrs.so3, which is torch):
# the simulator is I/O-side numpy and must generate > 1 M samples/s.
# =============================================================================


def qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) quaternions (w,x,y,z); as rotations ``R(p) @ R(q)``."""
    pw, px, py, pz = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([pw * qw - px * qx - py * qy - pz * qz,
                     pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy - px * qz + py * qw + pz * qx,
                     pw * qz + px * qy - py * qx + pz * qw], -1)


def qconj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def qexp(phi: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) -> unit quaternions (..., 4) (closed form, Taylor near 0)."""
    theta2 = np.sum(phi * phi, -1, keepdims=True)
    theta = np.sqrt(theta2)
    small = theta2 < 1e-6
    with np.errstate(invalid="ignore", divide="ignore"):
        half_sinc = np.where(small, 0.5 - theta2 / 48.0 + theta2 * theta2 / 3840.0,
                             np.sin(0.5 * theta) / np.where(small, 1.0, theta))
    w = np.where(small, 1.0 - theta2 / 8.0 + theta2 * theta2 / 384.0, np.cos(0.5 * theta))
    return np.concatenate([w, half_sinc * phi], -1)


def qlog(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) -> rotation vectors (..., 3), angle in [0, pi]."""
    q = np.where(q[..., :1] < 0, -q, q)
    w, v = q[..., :1], q[..., 1:]
    n = np.sqrt(np.sum(v * v, -1, keepdims=True))
    small = n < 1e-3
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(small, 2.0 / w * (1.0 - n * n / (3.0 * w * w)),
                         2.0 * np.arctan2(n, w) / np.where(small, 1.0, n))
    return scale * v


def quat_about_z(yaw: np.ndarray) -> np.ndarray:
    """Rotation about the z axis by ``yaw`` (...,) -> (..., 4)."""
    yaw = np.asarray(yaw, dtype=np.float64)
    z = np.zeros_like(yaw)
    return np.stack([np.cos(0.5 * yaw), z, z, np.sin(0.5 * yaw)], -1)


def qmatrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (N, 4) -> rotation matrices (N, 3, 3)."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r = np.empty((q.shape[0], 3, 3))
    r[:, 0, 0] = 1 - 2 * (y * y + z * z)
    r[:, 0, 1] = 2 * (x * y - w * z)
    r[:, 0, 2] = 2 * (x * z + w * y)
    r[:, 1, 0] = 2 * (x * y + w * z)
    r[:, 1, 1] = 1 - 2 * (x * x + z * z)
    r[:, 1, 2] = 2 * (y * z - w * x)
    r[:, 2, 0] = 2 * (x * z - w * y)
    r[:, 2, 1] = 2 * (y * z + w * x)
    r[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def to_body(r: np.ndarray, v_nav: np.ndarray) -> np.ndarray:
    """``R^T v`` for (N,3,3) nav_from_body and (N,3) or (3,) navigation vectors -> (N,3)."""
    if v_nav.ndim == 1:
        return v_nav[0] * r[:, 0, :] + v_nav[1] * r[:, 1, :] + v_nav[2] * r[:, 2, :]
    return v_nav[:, 0:1] * r[:, 0, :] + v_nav[:, 1:2] * r[:, 1, :] + v_nav[:, 2:3] * r[:, 2, :]


def cumprod_quat(q: np.ndarray) -> np.ndarray:
    """Inclusive cumulative Hamilton product ``P_k = q_0 q_1 ... q_k`` of (N, 4) quaternions.

    Vectorised chunked scan (numpy): the sequence is cut into C chunks of length L ~ sqrt(N);
    the L in-chunk steps each multiply all C chunks at once, the chunk totals are scanned the
    same way (recursively) and applied to their chunks. O(N) work, O(sqrt N) Python steps;
    round-off grows like O(sqrt N) products (1e-13 for 1e6 samples).
    """
    n = q.shape[0]
    if n <= 64:
        out = q.copy()
        for k in range(1, n):
            out[k] = qmul(out[k - 1], out[k])
        return out / np.linalg.norm(out, axis=1, keepdims=True)
    chunk = int(math.ceil(math.sqrt(n)))
    count = int(math.ceil(n / chunk))
    pad = count * chunk - n
    qq = np.concatenate([q, np.tile([1.0, 0.0, 0.0, 0.0], (pad, 1))]) if pad else q
    # components as (4, L, C): step l touches the contiguous rows c[:, l, :]
    c = np.ascontiguousarray(qq.reshape(count, chunk, 4).transpose(2, 1, 0))
    w, x, y, z = c[0], c[1], c[2], c[3]
    for l in range(1, chunk):
        pw, px, py, pz = w[l - 1], x[l - 1], y[l - 1], z[l - 1]
        qw, qx, qy, qz = w[l].copy(), x[l].copy(), y[l].copy(), z[l].copy()
        w[l] = pw * qw - px * qx - py * qy - pz * qz
        x[l] = pw * qx + px * qw + py * qz - pz * qy
        y[l] = pw * qy - px * qz + py * qw + pz * qx
        z[l] = pw * qz + px * qy - py * qx + pz * qw
    totals = np.stack([w[-1], x[-1], y[-1], z[-1]], -1)  # (C, 4)
    prefix = cumprod_quat(totals)
    before = np.concatenate([[[1.0, 0.0, 0.0, 0.0]], prefix[:-1]])  # exclusive prefix (C, 4)
    out = qmul(before[None, :, :], c.transpose(1, 2, 0))  # (L, C, 4)
    out = out.transpose(1, 0, 2).reshape(count * chunk, 4)[:n]
    return out / np.linalg.norm(out, axis=1, keepdims=True)


# =============================================================================
