"""Compiled (numba) per-sample loops of the classical filters, for inference and grid tuning.

The torch filters (:mod:`tcn_ahrs.filters.ecf`, ``mahony``, ``madgwick``, ``eskf``) stay the reference
and the differentiable path; their sequential loop is what costs (one Python iteration and ~40
tensor ops per sample). These kernels run the same recursion, written out on scalars, over
float64 numpy arrays (B runs x N samples, runs in parallel threads), and the torch functions
call them when nothing needs a gradient (``backend="auto"``); ``tests/test_compiled.py`` holds
the two equal to 1e-12. Everything that depends only on the measurements (normalised vectors,
gates, gain schedule) is still computed once, vectorised, by the torch function.

numba is optional (``pip install -e ".[fast]"``, in ``[dev]``): without it the torch loops run.
"""
from __future__ import annotations

import math

import numpy as np

from ..kernels.quat import matrix_to_quat_nb as _matrix_to_quat
from ..kernels.quat import qmul_nb as _qmul
from ..kernels.quat import qnormalize_nb as _qnorm
from ..kernels.quat import rodrigues_nb as _rodrigues9

try:
    import numba

    njit = numba.njit(cache=True, fastmath=False, parallel=True)
    prange = numba.prange
    AVAILABLE = True
except ImportError:  # pragma: no cover - the torch loops are used instead
    numba = None
    AVAILABLE = False

    def njit(f):
        return f

    prange = range


def available() -> bool:
    return AVAILABLE


@njit
def ecf_loop(a_hat, east_b, w_acc, w_mag, gyro, dt, r0, use_mag):
    """Eqs. 4-6 of :func:`tcn_ahrs.filters.ecf.ecf`: quat (B, N, 4) (as ``so3.matrix_to_quat`` of
    the attitudes) from r0 (B, 3, 3). The attitude is nine scalars (no array allocation in the
    loop); ``r <- r exp([(omega + e) dt] x)``."""
    B, N = gyro.shape[0], gyro.shape[1]
    out = np.empty((B, N, 4))
    for b in prange(B):
        r00, r01, r02 = r0[b, 0, 0], r0[b, 0, 1], r0[b, 0, 2]
        r10, r11, r12 = r0[b, 1, 0], r0[b, 1, 1], r0[b, 1, 2]
        r20, r21, r22 = r0[b, 2, 0], r0[b, 2, 1], r0[b, 2, 2]
        _to_quat(r00, r01, r02, r10, r11, r12, r20, r21, r22, out[b, 0])
        for k in range(1, N):
            ax, ay, az = a_hat[b, k, 0], a_hat[b, k, 1], a_hat[b, k, 2]
            wa = w_acc[b, k]
            ex = wa * (ay * r22 - az * r21)                     # a^ x C^T up (third row)
            ey = wa * (az * r20 - ax * r22)
            ez = wa * (ax * r21 - ay * r20)
            if use_mag:
                mx, my, mz = east_b[b, k, 0], east_b[b, k, 1], east_b[b, k, 2]
                wm = w_mag[b, k]
                ex += wm * (my * r02 - mz * r01)                # east^ x C^T east (first row)
                ey += wm * (mz * r00 - mx * r02)
                ez += wm * (mx * r01 - my * r00)
            d = dt[b, k]
            px, py, pz = (gyro[b, k, 0] + ex) * d, (gyro[b, k, 1] + ey) * d, (gyro[b, k, 2] + ez) * d
            e00, e01, e02, e10, e11, e12, e20, e21, e22 = _rodrigues9(px, py, pz)
            n00 = r00 * e00 + r01 * e10 + r02 * e20
            n01 = r00 * e01 + r01 * e11 + r02 * e21
            n02 = r00 * e02 + r01 * e12 + r02 * e22
            n10 = r10 * e00 + r11 * e10 + r12 * e20
            n11 = r10 * e01 + r11 * e11 + r12 * e21
            n12 = r10 * e02 + r11 * e12 + r12 * e22
            n20 = r20 * e00 + r21 * e10 + r22 * e20
            n21 = r20 * e01 + r21 * e11 + r22 * e21
            n22 = r20 * e02 + r21 * e12 + r22 * e22
            r00, r01, r02, r10, r11, r12, r20, r21, r22 = n00, n01, n02, n10, n11, n12, n20, n21, n22
            _to_quat(r00, r01, r02, r10, r11, r12, r20, r21, r22, out[b, k])
    return out


@numba.njit(cache=True) if AVAILABLE else (lambda f: f)
def _to_quat(m00, m01, m02, m10, m11, m12, m20, m21, m22, q):
    """:func:`tcn_ahrs.so3.matrix_to_quat` (Shepperd, w >= 0) of one matrix, into q (4,)."""
    q[0], q[1], q[2], q[3] = _matrix_to_quat(m00, m01, m02, m10, m11, m12, m20, m21, m22)


@njit
def mahony_loop(a_hat, m_hat, gyro, dt, q0, k_p, k_i, bias0, use_mag, compat):
    """The recursion of :func:`tcn_ahrs.filters.mahony.mahony`: quat (B, N, 4), bias (B, N, 3)."""
    B, N = gyro.shape[0], gyro.shape[1]
    qs = np.empty((B, N, 4))
    bs = np.empty((B, N, 3))
    for b in prange(B):
        qw, qx, qy, qz = _qnorm(q0[b, 0], q0[b, 1], q0[b, 2], q0[b, 3])
        bx, by, bz = bias0[b, 0], bias0[b, 1], bias0[b, 2]
        qs[b, 0, 0], qs[b, 0, 1], qs[b, 0, 2], qs[b, 0, 3] = qw, qx, qy, qz
        bs[b, 0, 0], bs[b, 0, 1], bs[b, 0, 2] = bx, by, bz
        kp, ki = k_p[b], k_i[b]
        for k in range(1, N):
            w, x, y, z = _qnorm(qw, qx, qy, qz)                 # quat_to_matrix normalises
            r00, r01, r02 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
            r10, r11, r12 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
            r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
            ax, ay, az = a_hat[b, k, 0], a_hat[b, k, 1], a_hat[b, k, 2]
            ex, ey, ez = ay * r22 - az * r21, az * r20 - ax * r22, ax * r21 - ay * r20
            if use_mag:
                mx, my, mz = m_hat[b, k, 0], m_hat[b, k, 1], m_hat[b, k, 2]
                hx = r00 * mx + r01 * my + r02 * mz
                hy = r10 * mx + r11 * my + r12 * mz
                hz = r20 * mx + r21 * my + r22 * mz
                h_xy = math.sqrt(hx * hx + hy * hy)
                vx = r10 * h_xy + r20 * hz                      # R^T [0, |h_xy|, h_z]
                vy = r11 * h_xy + r21 * hz
                vz = r12 * h_xy + r22 * hz
                vn = max(math.sqrt(vx * vx + vy * vy + vz * vz), 1e-300)
                vx, vy, vz = vx / vn, vy / vn, vz / vn
                ex += my * vz - mz * vy
                ey += mz * vx - mx * vz
                ez += mx * vy - my * vx
            d = dt[b, k]
            bx -= ki * ex * d
            by -= ki * ey * d
            bz -= ki * ez * d
            ox, oy, oz = gyro[b, k, 0] - bx + kp * ex, gyro[b, k, 1] - by + kp * ey, gyro[b, k, 2] - bz + kp * ez
            if compat:
                dw, dx, dy, dz = _qmul(qw, qx, qy, qz, 0.0, ox, oy, oz)
                qw, qx, qy, qz = _qnorm(qw + 0.5 * dw * d, qx + 0.5 * dx * d, qy + 0.5 * dy * d, qz + 0.5 * dz * d)
            else:
                px, py, pz = ox * d, oy * d, oz * d
                t2 = px * px + py * py + pz * pz
                if t2 < 1e-6:
                    hs = 0.5 - t2 / 48.0 + t2 * t2 / 3840.0
                    cw = 1.0 - t2 / 8.0 + t2 * t2 / 384.0
                else:
                    t = math.sqrt(t2)
                    hs = math.sin(0.5 * t) / t
                    cw = math.cos(0.5 * t)
                qw, qx, qy, qz = _qnorm(*_qmul(qw, qx, qy, qz, cw, hs * px, hs * py, hs * pz))
            qs[b, k, 0], qs[b, k, 1], qs[b, k, 2], qs[b, k, 3] = qw, qx, qy, qz
            bs[b, k, 0], bs[b, k, 1], bs[b, k, 2] = bx, by, bz
    return qs, bs


@njit
def madgwick_loop(a_hat, m_hat, gyro, dt, q0, beta, use_mag):
    """The recursion of :func:`tcn_ahrs.filters.madgwick.madgwick` in its NWU frame: q0 (B, 4)
    already NWU; returns quat (B, N, 4) NWU."""
    B, N = gyro.shape[0], gyro.shape[1]
    qs = np.empty((B, N, 4))
    for b in prange(B):
        qw, qx, qy, qz = q0[b, 0], q0[b, 1], q0[b, 2], q0[b, 3]
        qs[b, 0, 0], qs[b, 0, 1], qs[b, 0, 2], qs[b, 0, 3] = qw, qx, qy, qz
        be = beta[b]
        for k in range(1, N):
            ax, ay, az = a_hat[b, k, 0], a_hat[b, k, 1], a_hat[b, k, 2]
            f0 = 2.0 * (qx * qz - qw * qy) - ax
            f1 = 2.0 * (qw * qx + qy * qz) - ay
            f2 = 2.0 * (0.5 - qx * qx - qy * qy) - az
            g0 = -2.0 * qy * f0 + 2.0 * qx * f1
            g1 = 2.0 * qz * f0 + 2.0 * qw * f1 - 4.0 * qx * f2
            g2 = -2.0 * qw * f0 + 2.0 * qz * f1 - 4.0 * qy * f2
            g3 = 2.0 * qx * f0 + 2.0 * qy * f1
            if use_mag:
                mx, my, mz = m_hat[b, k, 0], m_hat[b, k, 1], m_hat[b, k, 2]
                # h = R(q) m (quat_rotate)
                tx = 2.0 * (qy * mz - qz * my)
                ty = 2.0 * (qz * mx - qx * mz)
                tz = 2.0 * (qx * my - qy * mx)
                hx = mx + qw * tx + (qy * tz - qz * ty)
                hy = my + qw * ty + (qz * tx - qx * tz)
                hz = mz + qw * tz + (qx * ty - qy * tx)
                bxm = math.sqrt(hx * hx + hy * hy)
                bzm = hz
                f3 = 2.0 * bxm * (0.5 - qy * qy - qz * qz) + 2.0 * bzm * (qx * qz - qw * qy) - mx
                f4 = 2.0 * bxm * (qx * qy - qw * qz) + 2.0 * bzm * (qw * qx + qy * qz) - my
                f5 = 2.0 * bxm * (qw * qy + qx * qz) + 2.0 * bzm * (0.5 - qx * qx - qy * qy) - mz
                g0 += -2.0 * bzm * qy * f3 + (-2.0 * bxm * qz + 2.0 * bzm * qx) * f4 + 2.0 * bxm * qy * f5
                g1 += 2.0 * bzm * qz * f3 + (2.0 * bxm * qy + 2.0 * bzm * qw) * f4 + (2.0 * bxm * qz - 4.0 * bzm * qx) * f5
                g2 += (-4.0 * bxm * qy - 2.0 * bzm * qw) * f3 + (2.0 * bxm * qx + 2.0 * bzm * qz) * f4 + \
                    (2.0 * bxm * qw - 4.0 * bzm * qy) * f5
                g3 += (-4.0 * bxm * qz + 2.0 * bzm * qx) * f3 + (-2.0 * bxm * qw + 2.0 * bzm * qy) * f4 + 2.0 * bxm * qx * f5
            gn = max(math.sqrt(g0 * g0 + g1 * g1 + g2 * g2 + g3 * g3), 1e-300)
            g0, g1, g2, g3 = g0 / gn, g1 / gn, g2 / gn, g3 / gn
            dw, dx, dy, dz = _qmul(qw, qx, qy, qz, 0.0, gyro[b, k, 0], gyro[b, k, 1], gyro[b, k, 2])
            d = dt[b, k]
            qw, qx, qy, qz = _qnorm(qw + (0.5 * dw - be * g0) * d, qx + (0.5 * dx - be * g1) * d,
                                    qy + (0.5 * dy - be * g2) * d, qz + (0.5 * dz - be * g3) * d)
            qs[b, k, 0], qs[b, k, 1], qs[b, k, 2], qs[b, k, 3] = qw, qx, qy, qz
    return qs


class torch_loops:
    """Context manager: ``backend="auto"`` takes the torch loops inside (for side-by-side timing)."""

    def __enter__(self):
        global AVAILABLE
        self._saved, AVAILABLE = AVAILABLE, False
        return self

    def __exit__(self, *exc):
        global AVAILABLE
        AVAILABLE = self._saved


def use_compiled(backend: str, *tensors) -> bool:
    """``backend``: "torch", "numba" or "auto" (numba when available, every tensor on the CPU in
    float64 and none requiring a gradient)."""
    if backend == "torch":
        return False
    import torch

    ts = [t for t in tensors if isinstance(t, torch.Tensor)]
    if backend == "numba":
        if not AVAILABLE:
            raise ImportError("backend='numba' needs numba: pip install numba (or the [fast] extra)")
        bad = [t for t in ts if t.device.type != "cpu" or t.requires_grad]
        if bad:
            raise ValueError("backend='numba' runs on CPU tensors without gradients; got one on "
                             f"{bad[0].device} (requires_grad={bad[0].requires_grad}): use backend='torch' or 'auto'")
        return True
    if backend != "auto":
        raise ValueError(f"backend: expected 'auto', 'torch' or 'numba', got {backend!r}")
    return AVAILABLE and all(t.device.type == "cpu" and t.dtype == torch.float64 and not t.requires_grad for t in ts)


def __getattr__(name):
    # the ES-EKF's loop lives in :mod:`tcn_ahrs.filters.compiled_eskf` (imported on first use here:
    # that module builds on this one)
    if name == "eskf_loop":
        from .compiled_eskf import eskf_loop

        return eskf_loop
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["available", "use_compiled", "torch_loops", "ecf_loop", "mahony_loop", "madgwick_loop", "eskf_loop"]
