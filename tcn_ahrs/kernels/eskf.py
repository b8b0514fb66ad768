"""One sample of the ES-EKF (:func:`tcn_ahrs.filters.eskf.eskf`) for the compiled loop of
:mod:`tcn_ahrs.filters.compiled`: the prediction, the gravity-direction update and the
heading update, each in place on the run's small buffers (attitude rot (3, 3), bias (3,),
covariance P (6, 6)): no allocation, no BLAS call per 6x6 product.

Kernels for numba alone (the third kind in :mod:`tcn_ahrs.kernels`: they work on arrays in
place; the Python functions run without numba). The torch ``eskf`` is the independent
reference they are held to (``tests/test_compiled.py``, 1e-12) and the differentiable path.
"""
from __future__ import annotations

import math

from .quat import rodrigues_nb as rodrigues

try:
    import numba

    _jit = numba.njit(cache=True)
except ImportError:  # pragma: no cover - exercised only without numba
    def _jit(f):
        return f


@_jit
def solve_into(S, X, out, m):
    """out = S^-1 X for the m x m (m = 1 or 3) innovation covariance, by its adjugate."""
    if m == 1:
        for j in range(X.shape[1]):
            out[0, j] = X[0, j] / S[0, 0]
        return
    a, b, c = S[0, 0], S[0, 1], S[0, 2]
    d, e, f = S[1, 0], S[1, 1], S[1, 2]
    g, h, i = S[2, 0], S[2, 1], S[2, 2]
    A, B_, C = e * i - f * h, -(d * i - f * g), d * h - e * g
    det = a * A + b * B_ + c * C
    inv = ((A, -(b * i - c * h), b * f - c * e), (B_, a * i - c * g, -(a * f - c * d)),
           (C, -(a * h - b * g), a * e - b * d))
    for j in range(X.shape[1]):
        x0, x1, x2 = X[0, j], X[1, j], X[2, j]
        out[0, j] = (inv[0][0] * x0 + inv[0][1] * x1 + inv[0][2] * x2) / det
        out[1, j] = (inv[1][0] * x0 + inv[1][1] * x1 + inv[1][2] * x2) / det
        out[2, j] = (inv[2][0] * x0 + inv[2][1] * x1 + inv[2][2] * x2) / det


@_jit
def observe(rot, bias, P, r, H, R, m, plausible, thr, robust, n_iter, max_fading, w):
    """eskf._observe on the first m rows of r (3,), H (3, 6), R (3, 3): (robust inflation,
    Eqs. 39-42), Kalman update with the Joseph form, injection and reset, in place (rot, bias,
    P); w: the work buffers. Returns (gamma, lam_p, lam_r)."""
    HP, hph, S, SX, K, THt, T6, KR, G, rn, dx = w
    for i in range(m):
        for j in range(6):
            acc = 0.0
            for k in range(6):
                acc += H[i, k] * P[k, j]
            HP[i, j] = acc
    for i in range(m):
        for j in range(m):
            acc = 0.0
            for k in range(6):
                acc += HP[i, k] * H[j, k]
            hph[i, j] = acc
    gamma0, lam_p, lam_r = 0.0, 1.0, 1.0
    if robust:
        for it in range(n_iter + 1):
            for i in range(m):
                for j in range(m):
                    S[i, j] = lam_p * hph[i, j] + lam_r * R[i, j]
            for i in range(m):
                SX[i, 0] = r[i]
            solve_into(S, SX[:, :1], K[:m, :1], m)          # K used as scratch: S^-1 r
            g = 0.0
            for i in range(m):
                g += r[i] * K[i, 0]
            if it == 0:
                gamma0 = g
            if it == n_iter:
                break
            f = g / thr if g >= thr else 1.0
            if plausible:
                lam_p = min(lam_p * f, max_fading)
            else:
                lam_r = lam_r * f
    for i in range(6):
        for j in range(6):
            P[i, j] *= lam_p
    for i in range(m):
        for j in range(6):
            HP[i, j] *= lam_p
        for j in range(m):
            hph[i, j] *= lam_p
            S[i, j] = hph[i, j] + lam_r * R[i, j]
    # K^T = S^-1 H P  (m x 6)
    solve_into(S, HP[:m], SX[:m], m)
    for i in range(6):
        acc = 0.0
        for k in range(m):
            K[i, k] = SX[k, i]
            acc += SX[k, i] * r[k]
        dx[i] = acc
    # Joseph form P = (I - K H) P (I - K H)^T + K R K^T, using that H is zero outside the
    # attitude columns: T = P - K (H P); P = T - (T H^T) K^T
    for i in range(6):
        for j in range(6):
            acc = 0.0
            for k in range(m):
                acc += K[i, k] * HP[k, j]
            T6[i, j] = P[i, j] - acc
    for i in range(6):
        for k in range(m):
            THt[i, k] = T6[i, 0] * H[k, 0] + T6[i, 1] * H[k, 1] + T6[i, 2] * H[k, 2]
    for i in range(6):
        for j in range(6):
            acc = 0.0
            for k in range(m):
                acc += THt[i, k] * K[j, k]
            P[i, j] = T6[i, j] - acc
    for i in range(6):
        for j in range(m):
            acc = 0.0
            for k in range(m):
                acc += K[i, k] * lam_r * R[k, j]
            KR[i, j] = acc
    for i in range(6):
        for j in range(6):
            acc = 0.0
            for k in range(m):
                acc += KR[i, k] * K[j, k]
            P[i, j] += acc
    # injection and reset (eskf.correct)
    e00, e01, e02, e10, e11, e12, e20, e21, e22 = rodrigues(dx[0], dx[1], dx[2])
    for i in range(3):
        a0, a1, a2 = rot[i, 0], rot[i, 1], rot[i, 2]
        rn[i, 0] = a0 * e00 + a1 * e10 + a2 * e20
        rn[i, 1] = a0 * e01 + a1 * e11 + a2 * e21
        rn[i, 2] = a0 * e02 + a1 * e12 + a2 * e22
    for i in range(3):
        for j in range(3):
            rot[i, j] = rn[i, j]
        bias[i] += dx[3 + i]
    # P <- G P G^T with G = diag(M, I), M = I - [dtheta/2]x: only the attitude rows/columns change
    hx, hy, hz = 0.5 * dx[0], 0.5 * dx[1], 0.5 * dx[2]
    G[0, 0], G[0, 1], G[0, 2] = 1.0, hz, -hy
    G[1, 0], G[1, 1], G[1, 2] = -hz, 1.0, hx
    G[2, 0], G[2, 1], G[2, 2] = hy, -hx, 1.0
    for i in range(3):
        for j in range(6):
            T6[i, j] = G[i, 0] * P[0, j] + G[i, 1] * P[1, j] + G[i, 2] * P[2, j]
    for i in range(3, 6):
        for j in range(6):
            T6[i, j] = P[i, j]
    for i in range(6):
        for j in range(3):
            P[i, j] = T6[i, 0] * G[j, 0] + T6[i, 1] * G[j, 1] + T6[i, 2] * G[j, 2]
        for j in range(3, 6):
            P[i, j] = T6[i, j]
    for i in range(6):
        for j in range(i + 1, 6):
            a = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = a
            P[j, i] = a
    return gamma0, lam_p, lam_r


@_jit
def predict(rot, bias, P, gx, gy, gz, d, q_rate, inc, rn, T6):
    """Strapdown by the bias-corrected gyro over d and P <- F P F^T + Q d (q_rate (6,)); inc, rn,
    T6: work buffers."""
    (inc[0, 0], inc[0, 1], inc[0, 2], inc[1, 0], inc[1, 1], inc[1, 2], inc[2, 0], inc[2, 1],
     inc[2, 2]) = rodrigues((gx - bias[0]) * d, (gy - bias[1]) * d, (gz - bias[2]) * d)
    for i in range(3):
        for j in range(3):
            rn[i, j] = rot[i, 0] * inc[0, j] + rot[i, 1] * inc[1, j] + rot[i, 2] * inc[2, j]
    for i in range(3):
        for j in range(3):
            rot[i, j] = rn[i, j]
    # P <- F P F^T, F = [[A, -dt I], [0, I]], A = inc^T, by blocks: rows 0-2 of F P ...
    for i in range(3):
        for j in range(6):
            T6[i, j] = inc[0, i] * P[0, j] + inc[1, i] * P[1, j] + inc[2, i] * P[2, j] - d * P[3 + i, j]
    for i in range(3, 6):
        for j in range(6):
            T6[i, j] = P[i, j]
    # ... then (F P) F^T: columns 0-2 change, 3-5 are (F P)'s
    for i in range(6):
        for j in range(3):
            P[i, j] = T6[i, 0] * inc[0, j] + T6[i, 1] * inc[1, j] + T6[i, 2] * inc[2, j] - d * T6[i, 3 + j]
        for j in range(3, 6):
            P[i, j] = T6[i, j]
    for i in range(6):
        P[i, i] += q_rate[i] * d


@_jit
def gravity_update(rot, bias, P, ax, ay, az, var_a, plausible, thr, robust, n_iter, max_fading, r, H, R, w):
    """The gravity-direction update (:func:`observe` on 3 rows); returns (gamma, lam_p, lam_r)."""
    # gravity direction: r = a^ - R^T up, H = [[R^T up]x, 0]
    h0, h1, h2 = rot[2, 0], rot[2, 1], rot[2, 2]
    r[0], r[1], r[2] = ax - h0, ay - h1, az - h2
    for i in range(3):
        for j in range(6):
            H[i, j] = 0.0
        for j in range(3):
            R[i, j] = var_a if i == j else 0.0
    H[0, 1], H[0, 2], H[1, 0], H[1, 2], H[2, 0], H[2, 1] = -h2, h1, h2, -h0, -h1, h0
    return observe(rot, bias, P, r, H, R, 3, plausible, thr, robust, n_iter, max_fading, w)


@_jit
def heading_update(rot, bias, P, mx, my, mz, var_m, plausible, thr, robust, n_iter, max_fading, r, H, R, w):
    """The heading update from the field (mx, my, mz) (:func:`observe` on 1 row); returns
    (gamma, lam_p, lam_r)."""
    v0 = rot[0, 0] * mx + rot[0, 1] * my + rot[0, 2] * mz
    v1 = rot[1, 0] * mx + rot[1, 1] * my + rot[1, 2] * mz
    v2 = rot[2, 0] * mx + rot[2, 1] * my + rot[2, 2] * mz
    vh2 = max(v0 * v0 + v1 * v1, 1e-12)
    rr = math.atan2(v1, v0) - math.pi / 2
    rr = (rr + math.pi) - 2 * math.pi * math.floor((rr + math.pi) / (2 * math.pi)) - math.pi
    r[0] = rr
    for j in range(6):
        H[0, j] = 0.0
    H[0, 0], H[0, 1], H[0, 2] = -rot[2, 0], -rot[2, 1], -rot[2, 2]
    R[0, 0] = var_m * ((v0 * v0 + v1 * v1 + v2 * v2) / vh2)
    return observe(rot, bias, P, r, H, R, 1, plausible, thr, robust, n_iter, max_fading, w)
