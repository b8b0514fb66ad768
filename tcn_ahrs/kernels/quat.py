"""Quaternion and rotation-matrix algebra on scalars: the one copy every per-sample loop uses.

These are *typed scalar kernels* (the second kind in :mod:`tcn_ahrs.kernels`): plain Python on
floats with type annotations, so the same source is compiled by numba (the ``*_nb`` names
below: the classical filters' loops in :mod:`tcn_ahrs.filters.compiled`, the streaming runtime),
read by TorchScript (the exported closed-loop modules call :func:`matrix_to_quat` directly) and
run by the interpreter. Branches may depend on data where they do; :func:`qmul` and :func:`qrot`
have none, so the ops-table kernel :mod:`tcn_ahrs.kernels.backbone` takes them too (its torch
reading runs them on tensors; :mod:`tcn_ahrs.kernels.script_ops` includes their source).

Conventions as :mod:`tcn_ahrs.so3`: quaternions (w, x, y, z), Hamilton product, rotation
matrices row by row (m00, m01, ..., m22).
"""
# No `from __future__ import annotations`: TorchScript reads the annotations as real types.
import math
import types
from typing import Tuple


def matrix_to_quat(m00: float, m01: float, m02: float, m10: float, m11: float, m12: float,
                   m20: float, m21: float, m22: float) -> Tuple[float, float, float, float]:
    """:func:`tcn_ahrs.so3.matrix_to_quat` (Shepperd, unit, w >= 0) of one matrix, on scalars."""
    tr = m00 + m11 + m22
    d0, d1, d2, d3 = 1.0 + tr, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22
    best, dm = 0, d0
    if d1 > dm:
        best, dm = 1, d1
    if d2 > dm:
        best, dm = 2, d2
    if d3 > dm:
        best, dm = 3, d3
    s_ = 2.0 * math.sqrt(max(dm, 1e-12))
    if best == 0:
        w, x, y, z = 0.25 * s_, (m21 - m12) / s_, (m02 - m20) / s_, (m10 - m01) / s_
    elif best == 1:
        w, x, y, z = (m21 - m12) / s_, 0.25 * s_, (m01 + m10) / s_, (m02 + m20) / s_
    elif best == 2:
        w, x, y, z = (m02 - m20) / s_, (m01 + m10) / s_, 0.25 * s_, (m12 + m21) / s_
    else:
        w, x, y, z = (m10 - m01) / s_, (m02 + m20) / s_, (m12 + m21) / s_, 0.25 * s_
    n = max(math.sqrt(w * w + x * x + y * y + z * z), 1e-12)  # so3._eps for float64
    if w < 0.0:
        n = -n
    return w / n, x / n, y / n, z / n


def qmul(pw: float, px: float, py: float, pz: float, qw: float, qx: float, qy: float, qz: float
         ) -> Tuple[float, float, float, float]:
    """The Hamilton product p ⊗ q: the scalar reading of :func:`tcn_ahrs.so3.quat_mul` (the same
    expression; tests/test_so3.py holds them equal bit for bit)."""
    return (pw * qw - px * qx - py * qy - pz * qz, pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx, pw * qz + px * qy - py * qx + pz * qw)


def qrot(q0: float, q1: float, q2: float, q3: float, v0: float, v1: float, v2: float
         ) -> Tuple[float, float, float]:
    """q v q* for a unit quaternion q (w, x, y, z)."""
    x = (1 - 2 * q2 * q2 - 2 * q3 * q3) * v0 + 2 * v1 * (q2 * q1 - q0 * q3) + 2 * v2 * (q0 * q2 + q3 * q1)
    y = 2 * v0 * (q0 * q3 + q2 * q1) + v1 * (1 - 2 * q1 * q1 - 2 * q3 * q3) + 2 * v2 * (q2 * q3 - q1 * q0)
    z = 2 * v0 * (q3 * q1 - q0 * q2) + 2 * v1 * (q0 * q1 + q3 * q2) + v2 * (1 - 2 * q1 * q1 - 2 * q2 * q2)
    return x, y, z


def qmat(w: float, x: float, y: float, z: float
         ) -> Tuple[float, float, float, float, float, float, float, float, float]:
    """The rotation matrix of a unit quaternion (q v q* = R v), row by row: :func:`qrot`'s terms."""
    return (1 - 2 * y * y - 2 * z * z, 2 * (y * x - w * z), 2 * (w * y + z * x),
            2 * (w * z + y * x), 1 - 2 * x * x - 2 * z * z, 2 * (y * z - x * w),
            2 * (z * x - w * y), 2 * (w * x + z * y), 1 - 2 * x * x - 2 * y * y)


def qnormalize(w: float, x: float, y: float, z: float) -> Tuple[float, float, float, float]:
    """q / max(|q|, 1e-12) (so3._eps for float64)."""
    n = math.sqrt(w * w + x * x + y * y + z * z)
    n = max(n, 1e-12)
    return w / n, x / n, y / n, z / n


def quat_step(w: float, x: float, y: float, z: float, px: float, py: float, pz: float
              ) -> Tuple[float, float, float, float]:
    """``q ⊗ exp(φ)`` for the rotation vector φ = (px, py, pz) (ω dt), renormalised; below
    |φ|² = 1e-6 the half-angle series of :func:`tcn_ahrs.so3.quat_exp`."""
    t2 = px * px + py * py + pz * pz
    if t2 < 1e-6:
        hs = 0.5 - t2 / 48.0 + t2 * t2 / 3840.0
        cw = 1.0 - t2 / 8.0 + t2 * t2 / 384.0
    else:
        t = math.sqrt(t2)
        hs = math.sin(0.5 * t) / t
        cw = math.cos(0.5 * t)
    rw, rx, ry, rz = qmul(w, x, y, z, cw, hs * px, hs * py, hs * pz)
    return qnormalize(rw, rx, ry, rz)


def rodrigues(px: float, py: float, pz: float
              ) -> Tuple[float, float, float, float, float, float, float, float, float]:
    """:func:`tcn_ahrs.so3.exp` of the rotation vector (px, py, pz), ``E = I + A K + C K^2`` (the
    same small-angle series), as 9 scalars row by row."""
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


def mat3_mul_t(a00: float, a01: float, a02: float, a10: float, a11: float, a12: float, a20: float, a21: float,
               a22: float, b00: float, b01: float, b02: float, b10: float, b11: float, b12: float, b20: float,
               b21: float, b22: float) -> Tuple[float, float, float, float, float, float, float, float, float]:
    """A Bᵀ of two 3x3 matrices given row by row, row by row (the backbone's bias filter: P Hᵀ, K Aᵀ;
    A B as A (Bᵀ)ᵀ, B passed transposed)."""
    return (a00 * b00 + a01 * b01 + a02 * b02, a00 * b10 + a01 * b11 + a02 * b12, a00 * b20 + a01 * b21 + a02 * b22,
            a10 * b00 + a11 * b01 + a12 * b02, a10 * b10 + a11 * b11 + a12 * b12, a10 * b20 + a11 * b21 + a12 * b22,
            a20 * b00 + a21 * b01 + a22 * b02, a20 * b10 + a21 * b11 + a22 * b12, a20 * b20 + a21 * b21 + a22 * b22)


# numba's reading (the [fast] extra): compiled once for every loop of the project; without numba
# the ``*_nb`` names are the Python functions themselves
try:
    import numba

    matrix_to_quat_nb = numba.njit(cache=True, inline="always")(matrix_to_quat)
    qmul_nb = numba.njit(cache=True)(qmul)
    qnormalize_nb = numba.njit(cache=True)(qnormalize)
    rodrigues_nb = numba.njit(cache=True)(rodrigues)
    # quat_step calls qmul and qnormalize: compiled, it calls their compiled readings (the same
    # source, its globals pointed at them; TorchScript and the interpreter read the function itself)
    quat_step_nb = numba.njit(cache=True)(types.FunctionType(
        quat_step.__code__, {**globals(), "qmul": qmul_nb, "qnormalize": qnormalize_nb}, "quat_step"))
    NUMBA = True
except ImportError:  # pragma: no cover - exercised only without numba
    matrix_to_quat_nb, qmul_nb, qnormalize_nb, rodrigues_nb = matrix_to_quat, qmul, qnormalize, rodrigues
    quat_step_nb = quat_step
    NUMBA = False
