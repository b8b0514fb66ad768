"""The numerics tests' tolerances, in one table, by dtype and by kind of quantity.

Why one table: a tolerance says what the test claims ("this is round-off", "this is a
well-conditioned angle", "these are two implementations of one filter"), so the same claim gets
the same number everywhere, and a float32 variant of a float64 test takes its number from the
same row instead of a guess.

``TOL[dtype][kind] = (rtol, atol)``; :func:`tol` returns ``dict(rtol=..., atol=...)`` for
``torch.testing.assert_close`` / ``np.testing.assert_allclose`` (``dtype``: a torch or numpy
dtype, or ``"float32"`` / ``"float64"``). The named constants below are the ``atol`` of a row, for
``pytest.approx(x, abs=...)`` and ``err.max() < ...``.

Machine epsilon: float64 2.2e-16, float32 1.2e-7. Each value is the worst error seen on the
tests' inputs times a margin of roughly 10-100, never looser than the literal it replaced.

Kinds (all absolute errors on O(1) quantities unless said otherwise):

``exact``       an identity evaluated in a handful of flops (hat/vee, cross products, the
                quaternion product, conjugates): a few ulp -> 1e-13 / 1e-6.
``rotation``    entries of rotation matrices / unit quaternions after exp, quat<->matrix,
                one product, rotating a vector: tens of ulp -> 1e-12 / 1e-5.
``scan``        cumulative products of up to ~1000 rotations (parallel scan vs sequential,
                renormalised quaternion scan): round-off grows like O(log N) to O(N) products
                -> 1e-11 / 1e-4.
``integrate``   200 sequential strapdown steps against scipy's own composition (two different
                round-off paths accumulate) and slerp (log, scale, exp) -> 1e-10 / 1e-4.
``angle``       rotation vectors / Euler angles in radians out of ``log``, ``atan2``, ``asin``:
                near an angle of pi the axis is recovered from a vector part of size
                ~cos(theta/2), losing digits -> 1e-9 / 1e-4 (float32: the angle's own round-off
                near pi, see test_so3.test_float32_accuracy).
``deg``         a well-conditioned attitude error in degrees from float64 quaternions
                (acos/atan2 away from 0) -> 1e-9 deg; float32 quaternions in: 1e-3 deg.
``deg_small``   an error that should be ~0 deg computed from a small angle's residue (atan2 of
                two small components after a heading removal) -> 1e-7 deg.
``deg_zero``    an error that should be 0 deg through acos/sqrt of a quantity near 1 (loses
                half the digits: sqrt(eps) = 1.5e-8 rad = 8.5e-7 deg) -> 1e-6 deg.
``parity``      one algorithm implemented twice (our Kalman update vs filterpy, the compiled
                kernels vs the TorchScript reference, batched vs single runs) in float64
                -> rtol 1e-10, atol 1e-12.
``lib_parity``  our classical filter vs a PyPI library's (``ahrs``) over a whole recording:
                the library re-normalises and integrates in its own order -> 1e-6 (quaternion
                entries).

Literals that are not round-off (a paper's printed value +- its printed digits, a physics
bound such as "bias within 1.5e-3 rad/s after 20 s", a rational approximation's published
error bound) stay in their tests: they are facts of the scenario, not of the dtype.
"""
from __future__ import annotations

from typing import Dict, Tuple, Union

import numpy as np
import torch

F64, F32 = torch.float64, torch.float32

TOL: Dict[torch.dtype, Dict[str, Tuple[float, float]]] = {
    F64: {
        "exact": (0.0, 1e-13),
        "rotation": (0.0, 1e-12),
        "scan": (0.0, 1e-11),
        "integrate": (0.0, 1e-10),
        "angle": (0.0, 1e-9),
        "deg": (0.0, 1e-9),
        "deg_small": (0.0, 1e-7),
        "deg_zero": (0.0, 1e-6),
        "parity": (1e-10, 1e-12),
        "lib_parity": (0.0, 1e-6),
    },
    F32: {
        "exact": (0.0, 1e-6),
        "rotation": (0.0, 1e-5),
        "scan": (0.0, 1e-4),
        "integrate": (0.0, 1e-4),
        "angle": (0.0, 1e-4),
        "deg": (0.0, 1e-3),
    },
}

# relative tolerances of scalar float64 results (pytest.approx(rel=...)):
REL_F64 = 1e-12      # one formula evaluated two ways (a Mahalanobis distance vs np.linalg.solve)
REL_METRIC_F64 = 1e-9  # an RMS of thousands of angles vs its numpy formula (summation order)

# the atol of each row, for pytest.approx(abs=...) and ``err.max() < ...``
EXACT_F64 = TOL[F64]["exact"][1]
ROTATION_F64 = TOL[F64]["rotation"][1]
SCAN_F64 = TOL[F64]["scan"][1]
INTEGRATE_F64 = TOL[F64]["integrate"][1]
ANGLE_F64 = TOL[F64]["angle"][1]
DEG_F64 = TOL[F64]["deg"][1]
DEG_SMALL_F64 = TOL[F64]["deg_small"][1]
DEG_ZERO_F64 = TOL[F64]["deg_zero"][1]
PARITY_F64 = TOL[F64]["parity"]
LIB_PARITY_F64 = TOL[F64]["lib_parity"][1]
EXACT_F32 = TOL[F32]["exact"][1]
ROTATION_F32 = TOL[F32]["rotation"][1]
ANGLE_F32 = TOL[F32]["angle"][1]
DEG_F32 = TOL[F32]["deg"][1]

DTypeLike = Union[torch.dtype, np.dtype, str, type]


def _dtype(dtype: DTypeLike) -> torch.dtype:
    if isinstance(dtype, torch.dtype):
        return dtype
    name = np.dtype(dtype).name
    return {"float64": F64, "float32": F32}[name]


def tol(dtype: DTypeLike, kind: str) -> Dict[str, float]:
    """``dict(rtol=, atol=)`` of ``kind`` at ``dtype`` (KeyError: no such row: add one, with why)."""
    rtol, atol = TOL[_dtype(dtype)][kind]
    return {"rtol": rtol, "atol": atol}


def atol(dtype: DTypeLike, kind: str) -> float:
    return TOL[_dtype(dtype)][kind][1]
