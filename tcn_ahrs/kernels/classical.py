"""One sample of the classical filters (ECF, Mahony, Madgwick) on scalars: the steps the compiled
loops of :mod:`tcn_ahrs.filters.compiled` run, one run after the other over float64 arrays.

Scalar kernels for numba (see :mod:`tcn_ahrs.kernels`): Python on floats that numba compiles as
it is (the ``*_nb`` names below; the Python functions run without numba). They branch on data and call
the quaternion kernels of :mod:`tcn_ahrs.kernels.quat`. The torch filters
(:mod:`tcn_ahrs.filters.ecf`, ``mahony``, ``madgwick``) are the independent reference these are
held to (``tests/test_compiled.py``, 1e-12) and the differentiable path. Inputs are what the
torch function computed once, vectorised: unit vectors, gates, gains.
"""
from __future__ import annotations

import math

from .quat import qmul_nb as qmul
from .quat import qnormalize_nb as qnormalize
from .quat import quat_step_nb as quat_step
from .quat import rodrigues_nb as rodrigues


def ecf_weights(ax, ay, az, mx, my, mz, use_mag, t, k_norm, k_init, t_init, a_min, m_min, m_max, gravity):
    """Eqs. 5-8 of :func:`tcn_ahrs.filters.ecf.ecf` for one sample's readings (the torch filter
    computes them vectorised over the recording: ``normalize``, ``field_gates``,
    ``gain_schedule``): the unit specific force a^, the measured east (m x a)/|m x a| (Eq. 6 in
    ENU) and the two terms' weights, the gain K(t) of Eq. 8 where the Eq. 7 tests pass, else 0
    (``t``: seconds since sample 0). The C runtime's reading (export/c/classical.py)."""
    an = math.sqrt(ax * ax + ay * ay + az * az)
    na = max(an, 1e-30)  # a zero reading stays zero (1e-300 would be 0 in a float build)
    tt = max(t_init, 1e-12)
    gain = k_norm + (tt - t) / tt * (k_init - k_norm) if t < t_init else k_norm
    acc_ok = an - gravity < a_min and gravity - an < a_min
    wa = gain if acc_ok else 0.0
    ex, ey, ez, wm = 0.0, 0.0, 0.0, 0.0
    if use_mag:
        mn = math.sqrt(mx * mx + my * my + mz * mz)
        cx, cy, cz = my * az - mz * ay, mz * ax - mx * az, mx * ay - my * ax
        nc = max(math.sqrt(cx * cx + cy * cy + cz * cz), 1e-30)
        ex, ey, ez = cx / nc, cy / nc, cz / nc
        wm = gain if acc_ok and mn > m_min and mn < m_max else 0.0
    return ax / na, ay / na, az / na, ex, ey, ez, wa, wm


def ecf_step(r00, r01, r02, r10, r11, r12, r20, r21, r22, ax, ay, az, wa, mx, my, mz, wm, use_mag, gx, gy, gz, dt):
    """Eqs. 4-6 of :func:`tcn_ahrs.filters.ecf.ecf`: the attitude r (nav_from_body, row by row)
    after one sample: ``r <- r exp([(omega + e) dt] x)``, e = wa a^ x C^T up + wm east^ x C^T east
    (the magnetometer term only with ``use_mag``)."""
    ex = wa * (ay * r22 - az * r21)                     # a^ x C^T up (third row)
    ey = wa * (az * r20 - ax * r22)
    ez = wa * (ax * r21 - ay * r20)
    if use_mag:
        ex += wm * (my * r02 - mz * r01)                # east^ x C^T east (first row)
        ey += wm * (mz * r00 - mx * r02)
        ez += wm * (mx * r01 - my * r00)
    px, py, pz = (gx + ex) * dt, (gy + ey) * dt, (gz + ez) * dt
    e00, e01, e02, e10, e11, e12, e20, e21, e22 = rodrigues(px, py, pz)
    n00 = r00 * e00 + r01 * e10 + r02 * e20
    n01 = r00 * e01 + r01 * e11 + r02 * e21
    n02 = r00 * e02 + r01 * e12 + r02 * e22
    n10 = r10 * e00 + r11 * e10 + r12 * e20
    n11 = r10 * e01 + r11 * e11 + r12 * e21
    n12 = r10 * e02 + r11 * e12 + r12 * e22
    n20 = r20 * e00 + r21 * e10 + r22 * e20
    n21 = r20 * e01 + r21 * e11 + r22 * e21
    n22 = r20 * e02 + r21 * e12 + r22 * e22
    return n00, n01, n02, n10, n11, n12, n20, n21, n22


def mahony_step(qw, qx, qy, qz, bx, by, bz, ax, ay, az, mx, my, mz, use_mag, gx, gy, gz, d, kp, ki, compat):
    """One sample of :func:`tcn_ahrs.filters.mahony.mahony`: (q, b) -> (q', b') (8 floats)."""
    w, x, y, z = qnormalize(qw, qx, qy, qz)                 # quat_to_matrix normalises
    r00, r01, r02 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    r10, r11, r12 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    ex, ey, ez = ay * r22 - az * r21, az * r20 - ax * r22, ax * r21 - ay * r20
    if use_mag:
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
    bx -= ki * ex * d
    by -= ki * ey * d
    bz -= ki * ez * d
    ox, oy, oz = gx - bx + kp * ex, gy - by + kp * ey, gz - bz + kp * ez
    if compat:
        dw, dx, dy, dz = qmul(qw, qx, qy, qz, 0.0, ox, oy, oz)
        qw, qx, qy, qz = qnormalize(qw + 0.5 * dw * d, qx + 0.5 * dx * d, qy + 0.5 * dy * d, qz + 0.5 * dz * d)
    else:
        qw, qx, qy, qz = quat_step(qw, qx, qy, qz, ox * d, oy * d, oz * d)
    return qw, qx, qy, qz, bx, by, bz


def madgwick_step(qw, qx, qy, qz, ax, ay, az, mx, my, mz, use_mag, gx, gy, gz, d, be):
    """One sample of :func:`tcn_ahrs.filters.madgwick.madgwick` in its NWU frame: q -> q'."""
    f0 = 2.0 * (qx * qz - qw * qy) - ax
    f1 = 2.0 * (qw * qx + qy * qz) - ay
    f2 = 2.0 * (0.5 - qx * qx - qy * qy) - az
    g0 = -2.0 * qy * f0 + 2.0 * qx * f1
    g1 = 2.0 * qz * f0 + 2.0 * qw * f1 - 4.0 * qx * f2
    g2 = -2.0 * qw * f0 + 2.0 * qz * f1 - 4.0 * qy * f2
    g3 = 2.0 * qx * f0 + 2.0 * qy * f1
    if use_mag:
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
    dw, dx, dy, dz = qmul(qw, qx, qy, qz, 0.0, gx, gy, gz)
    return qnormalize(qw + (0.5 * dw - be * g0) * d, qx + (0.5 * dx - be * g1) * d,
                      qy + (0.5 * dy - be * g2) * d, qz + (0.5 * dz - be * g3) * d)


# numba's reading (the [fast] extra); without numba the ``*_nb`` names are the Python functions
try:
    import numba

    ecf_step_nb = numba.njit(cache=True)(ecf_step)
    mahony_step_nb = numba.njit(cache=True)(mahony_step)
    madgwick_step_nb = numba.njit(cache=True)(madgwick_step)
except ImportError:  # pragma: no cover - exercised only without numba
    ecf_step_nb, mahony_step_nb, madgwick_step_nb = ecf_step, mahony_step, madgwick_step
