"""The ES-EKF's compiled (numba) loop (:func:`tcn_ahrs.filters.eskf.eskf`'s recursion), beside
the other classical filters' loops in :mod:`tcn_ahrs.filters.compiled` (the contract, the backend
choice and the parity test, ``tests/test_compiled.py``, are that module's). One sample is the
kernels of :mod:`tcn_ahrs.kernels.eskf`.
"""
from __future__ import annotations

import numpy as np

from ..kernels.eskf import gravity_update, heading_update, predict
from .compiled import _to_quat, njit, prange


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
