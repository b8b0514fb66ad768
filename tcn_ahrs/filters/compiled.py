"""Compiled (numba) per-sample loops of the classical filters, for inference and grid tuning.

The torch filters (:mod:`tcn_ahrs.filters.ecf`, ``mahony``, ``madgwick``, ``eskf``) stay the reference
and the differentiable path; their sequential loop is what costs (one Python iteration and ~40
tensor ops per sample). These loops run the same recursion over float64 numpy arrays (B runs x
N samples, runs in parallel threads), one sample at a time by the kernels of
:mod:`tcn_ahrs.kernels.classical` and :mod:`tcn_ahrs.kernels.eskf`, and the torch functions call
them when nothing needs a gradient (``backend="auto"``); ``tests/test_compiled.py`` holds the two
equal to 1e-12. Everything that depends only on the measurements (normalised vectors, gates, gain
schedule) is still computed once, vectorised, by the torch function.

numba is optional (``pip install -e ".[fast]"``, in ``[dev]``): without it the torch loops run.
"""
from __future__ import annotations

import numpy as np

from ..kernels.classical import ecf_step_nb as _ecf_step
from ..kernels.classical import madgwick_step_nb as _madgwick_step
from ..kernels.classical import mahony_step_nb as _mahony_step
from ..kernels.eskf import gravity_update, heading_update, predict
from ..kernels.quat import matrix_to_quat_nb as _matrix_to_quat
from ..kernels.quat import qnormalize_nb as _qnorm

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
    loop); one sample is :func:`~tcn_ahrs.kernels.classical.ecf_step`."""
    B, N = gyro.shape[0], gyro.shape[1]
    out = np.empty((B, N, 4))
    for b in prange(B):
        r00, r01, r02 = r0[b, 0, 0], r0[b, 0, 1], r0[b, 0, 2]
        r10, r11, r12 = r0[b, 1, 0], r0[b, 1, 1], r0[b, 1, 2]
        r20, r21, r22 = r0[b, 2, 0], r0[b, 2, 1], r0[b, 2, 2]
        _to_quat(r00, r01, r02, r10, r11, r12, r20, r21, r22, out[b, 0])
        for k in range(1, N):
            mx = my = mz = wm = 0.0
            if use_mag:
                mx, my, mz, wm = east_b[b, k, 0], east_b[b, k, 1], east_b[b, k, 2], w_mag[b, k]
            r00, r01, r02, r10, r11, r12, r20, r21, r22 = _ecf_step(
                r00, r01, r02, r10, r11, r12, r20, r21, r22, a_hat[b, k, 0], a_hat[b, k, 1], a_hat[b, k, 2],
                w_acc[b, k], mx, my, mz, wm, use_mag, gyro[b, k, 0], gyro[b, k, 1], gyro[b, k, 2], dt[b, k])
            _to_quat(r00, r01, r02, r10, r11, r12, r20, r21, r22, out[b, k])
    return out


@numba.njit(cache=True) if AVAILABLE else (lambda f: f)
def _to_quat(m00, m01, m02, m10, m11, m12, m20, m21, m22, q):
    """:func:`tcn_ahrs.so3.matrix_to_quat` (Shepperd, w >= 0) of one matrix, into q (4,)."""
    q[0], q[1], q[2], q[3] = _matrix_to_quat(m00, m01, m02, m10, m11, m12, m20, m21, m22)


@njit
def mahony_loop(a_hat, m_hat, gyro, dt, q0, k_p, k_i, bias0, use_mag, compat):
    """The recursion of :func:`tcn_ahrs.filters.mahony.mahony`: quat (B, N, 4), bias (B, N, 3);
    one sample is :func:`~tcn_ahrs.kernels.classical.mahony_step`."""
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
            mx = my = mz = 0.0
            if use_mag:
                mx, my, mz = m_hat[b, k, 0], m_hat[b, k, 1], m_hat[b, k, 2]
            qw, qx, qy, qz, bx, by, bz = _mahony_step(
                qw, qx, qy, qz, bx, by, bz, a_hat[b, k, 0], a_hat[b, k, 1], a_hat[b, k, 2], mx, my, mz, use_mag,
                gyro[b, k, 0], gyro[b, k, 1], gyro[b, k, 2], dt[b, k], kp, ki, compat)
            qs[b, k, 0], qs[b, k, 1], qs[b, k, 2], qs[b, k, 3] = qw, qx, qy, qz
            bs[b, k, 0], bs[b, k, 1], bs[b, k, 2] = bx, by, bz
    return qs, bs


@njit
def madgwick_loop(a_hat, m_hat, gyro, dt, q0, beta, use_mag):
    """The recursion of :func:`tcn_ahrs.filters.madgwick.madgwick` in its NWU frame: q0 (B, 4)
    already NWU; returns quat (B, N, 4) NWU; one sample is
    :func:`~tcn_ahrs.kernels.classical.madgwick_step`."""
    B, N = gyro.shape[0], gyro.shape[1]
    qs = np.empty((B, N, 4))
    for b in prange(B):
        qw, qx, qy, qz = q0[b, 0], q0[b, 1], q0[b, 2], q0[b, 3]
        qs[b, 0, 0], qs[b, 0, 1], qs[b, 0, 2], qs[b, 0, 3] = qw, qx, qy, qz
        be = beta[b]
        for k in range(1, N):
            mx = my = mz = 0.0
            if use_mag:
                mx, my, mz = m_hat[b, k, 0], m_hat[b, k, 1], m_hat[b, k, 2]
            qw, qx, qy, qz = _madgwick_step(qw, qx, qy, qz, a_hat[b, k, 0], a_hat[b, k, 1], a_hat[b, k, 2],
                                            mx, my, mz, use_mag, gyro[b, k, 0], gyro[b, k, 1], gyro[b, k, 2],
                                            dt[b, k], be)
            qs[b, k, 0], qs[b, k, 1], qs[b, k, 2], qs[b, k, 3] = qw, qx, qy, qz
    return qs


@njit
def eskf_loop(a_hat, mag, gyro, dt, rot0, bias0, P0, q_rate, var_acc, acc_plaus, var_mag, mag_plaus,
              thr_acc, thr_mag, use_mag, robust, n_iter, max_fading):
    """The recursion of :func:`tcn_ahrs.filters.eskf.eskf` (predict, gravity-direction update,
    heading update), in place on per-run buffers. Returns quat (B, N, 4), bias (B, N, 3),
    att_var (B, N, 3) and the robust signals (5, B, N): gamma_acc, gamma_mag, fading, lam_r_acc, lam_r_mag."""
    B, N = gyro.shape[0], gyro.shape[1]
    quat = np.empty((B, N, 4))
    bs = np.empty((B, N, 3))
    var = np.empty((B, N, 3))
    sig = np.zeros((5, B, N))
    for b in prange(B):
        rot = rot0[b].copy()
        bias = bias0[b].copy()
        P = P0[b].copy()
        T6 = np.zeros((6, 6))
        w = (np.zeros((3, 6)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 6)), np.zeros((6, 3)),
             np.zeros((6, 3)), T6, np.zeros((6, 3)), np.zeros((6, 6)), np.zeros((3, 3)), np.zeros(6))
        inc = np.zeros((3, 3))
        r = np.zeros(3)
        H = np.zeros((3, 6))
        R = np.zeros((3, 3))
        rn = np.zeros((3, 3))
        _to_quat(rot[0, 0], rot[0, 1], rot[0, 2], rot[1, 0], rot[1, 1], rot[1, 2], rot[2, 0], rot[2, 1], rot[2, 2],
                 quat[b, 0])
        bs[b, 0] = bias
        for i in range(3):
            var[b, 0, i] = P[i, i]
        sig[2, b, 0] = 1.0
        for k in range(1, N):
            predict(rot, bias, P, gyro[b, k, 0], gyro[b, k, 1], gyro[b, k, 2], dt[b, k], q_rate[b], inc, rn, T6)
            ga, lpa, lra = gravity_update(rot, bias, P, a_hat[b, k, 0], a_hat[b, k, 1], a_hat[b, k, 2], var_acc[b, k],
                                          acc_plaus[b, k], thr_acc, robust, n_iter, max_fading, r, H, R, w)
            fading = lpa
            if use_mag:
                gm, lpm, lrm = heading_update(rot, bias, P, mag[b, k, 0], mag[b, k, 1], mag[b, k, 2], var_mag[b, k],
                                              mag_plaus[b, k], thr_mag, robust, n_iter, max_fading, r, H, R, w)
                fading *= lpm
                sig[1, b, k], sig[4, b, k] = gm, lrm
            sig[0, b, k], sig[2, b, k], sig[3, b, k] = ga, fading, lra
            _to_quat(rot[0, 0], rot[0, 1], rot[0, 2], rot[1, 0], rot[1, 1], rot[1, 2], rot[2, 0], rot[2, 1],
                     rot[2, 2], quat[b, k])
            for i in range(3):
                bs[b, k, i] = bias[i]
                var[b, k, i] = P[i, i]
    return quat, bs, var, sig


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


__all__ = ["available", "use_compiled", "torch_loops", "ecf_loop", "mahony_loop", "madgwick_loop", "eskf_loop"]
