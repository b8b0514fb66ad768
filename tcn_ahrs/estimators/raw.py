"""Raw IMU: strapdown integration of the raw gyroscope (the paper's "Raw IMU" baseline)."""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from .. import so3
from ..sequence import ImuSequence
from .base import EstimatorOutput
from .registry import register


@register("raw", "raw")
class RawIntegration:
    """Integrates the raw gyro from ``init_quat`` at sample 0 (identity if ``None``), float64:
    ``R_k = R_0 exp(w_1 dt_1) ... exp(w_k dt_k)`` (paper Eq. 3, :func:`tcn_ahrs.so3.integrate`),
    with ``dt_k = t_k - t_{k-1}`` (real time steps, so gaps in the IMU stream are bridged).

    Uses neither accelerometer nor magnetometer: attitude drifts with the gyro bias.
    Output signals: none.
    """

    name = "Raw IMU"

    def __init__(self, axes: Optional[int] = None):
        pass  # ``axes`` is accepted for the registry's uniform factory; the gyro alone is used
    def run(self, seq: ImuSequence, init_quat: Optional[np.ndarray] = None,
            init_index: int = 0) -> EstimatorOutput:
        if init_quat is None:
            q0 = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
        else:
            q0 = torch.as_tensor(np.asarray(init_quat, dtype=np.float64).reshape(-1))
            if q0.shape != (4,) or not torch.isfinite(q0).all() or torch.linalg.norm(q0) < 0.5:
                raise ValueError(f"init_quat: expected a finite unit quaternion (w,x,y,z) of shape (4,), "
                                 f"got {np.asarray(init_quat)!r}")
        r0 = so3.quat_to_matrix(so3.quat_normalize(q0))
        omega = torch.as_tensor(seq.gyro, dtype=torch.float64)
        dt = torch.as_tensor(seq.dt, dtype=torch.float64)
        with torch.no_grad():
            rot = so3.integrate(r0, omega, dt)
            quat = so3.matrix_to_quat(rot)
        return EstimatorOutput(quat=quat.numpy(), signals={})
