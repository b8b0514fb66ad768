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

from ..model.closed_loop_step import matrix_to_quat_scalar

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


if AVAILABLE:
    from ..model.closed_loop_compiled import matrix_to_quat_nb as _matrix_to_quat
else:  # pragma: no cover
    _matrix_to_quat = matrix_to_quat_scalar


@numba.njit(cache=True) if AVAILABLE else (lambda f: f)
def _to_quat(m00, m01, m02, m10, m11, m12, m20, m21, m22, q):
    """:func:`tcn_ahrs.so3.matrix_to_quat` (Shepperd, w >= 0) of one matrix, into q (4,)."""
    q[0], q[1], q[2], q[3] = _matrix_to_quat(m00, m01, m02, m10, m11, m12, m20, m21, m22)


@numba.njit(cache=True) if AVAILABLE else (lambda f: f)
def _qmul(pw, px, py, pz, qw, qx, qy, qz):
    return (pw * qw - px * qx - py * qy - pz * qz, pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx, pw * qz + px * qy - py * qx + pz * qw)


@numba.njit(cache=True) if AVAILABLE else (lambda f: f)
def _qnorm(w, x, y, z):
    n = math.sqrt(w * w + x * x + y * y + z * z)
    n = max(n, 1e-12)                                   # so3._eps for float64
    return w / n, x / n, y / n, z / n


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


# ---------------------------------------------------------------------------- ES-EKF
# Small dense helpers (loops on preallocated buffers: no allocation, no BLAS call per 6x6 product).

@numba.njit(cache=True) if AVAILABLE else (lambda f: f)
def _rodrigues9(px, py, pz):
    """so3.exp of (px, py, pz), ``E = I + A K + C K^2`` (same small-angle series), as 9 scalars
    row by row."""
    t2 = px * px + py * py + pz * pz
    if t2 < 1e-6:
        A = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        C = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
    else:
        t = math.sqrt(t2)
        A = math.sin(t) / t
        C = (1.0 - math.cos(t)) / t2
    return (1.0 + C * (-pz * pz - py * py), A * -pz + C * (py * px), A * py + C * (pz * px),
            A * pz + C * (px * py), 1.0 + C * (-pz * pz - px * px), A * -px + C * (pz * py),
            A * -py + C * (px * pz), A * px + C * (py * pz), 1.0 + C * (-py * py - px * px))


@numba.njit(cache=True) if AVAILABLE else (lambda f: f)
def _solve_into(S, X, out, m):
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


@numba.njit(cache=True) if AVAILABLE else (lambda f: f)
def _observe(rot, bias, P, r, H, R, m, plausible, thr, robust, n_iter, max_fading, w):
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
            _solve_into(S, SX[:, :1], K[:m, :1], m)          # K used as scratch: S^-1 r
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
    _solve_into(S, HP[:m], SX[:m], m)
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
    e00, e01, e02, e10, e11, e12, e20, e21, e22 = _rodrigues9(dx[0], dx[1], dx[2])
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
            d = dt[b, k]
            (inc[0, 0], inc[0, 1], inc[0, 2], inc[1, 0], inc[1, 1], inc[1, 2], inc[2, 0], inc[2, 1],
             inc[2, 2]) = _rodrigues9((gyro[b, k, 0] - bias[0]) * d, (gyro[b, k, 1] - bias[1]) * d,
                                      (gyro[b, k, 2] - bias[2]) * d)
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
                P[i, i] += q_rate[b, i] * d
            # gravity direction: r = a^ - R^T up, H = [[R^T up]x, 0]
            h0, h1, h2 = rot[2, 0], rot[2, 1], rot[2, 2]
            r[0], r[1], r[2] = a_hat[b, k, 0] - h0, a_hat[b, k, 1] - h1, a_hat[b, k, 2] - h2
            for i in range(3):
                for j in range(6):
                    H[i, j] = 0.0
                for j in range(3):
                    R[i, j] = var_acc[b, k] if i == j else 0.0
            H[0, 1], H[0, 2], H[1, 0], H[1, 2], H[2, 0], H[2, 1] = -h2, h1, h2, -h0, -h1, h0
            ga, lpa, lra = _observe(rot, bias, P, r, H, R, 3, acc_plaus[b, k], thr_acc, robust, n_iter, max_fading, w)
            fading = lpa
            if use_mag:
                mx, my, mz = mag[b, k, 0], mag[b, k, 1], mag[b, k, 2]
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
                R[0, 0] = var_mag[b, k] * ((v0 * v0 + v1 * v1 + v2 * v2) / vh2)
                gm, lpm, lrm = _observe(rot, bias, P, r, H, R, 1, mag_plaus[b, k], thr_mag, robust, n_iter,
                                        max_fading, w)
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
