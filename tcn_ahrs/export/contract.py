"""The streaming input contract every runtime shares (the numba/TorchScript ones in
:mod:`tcn_ahrs.streaming`, the ONNX / torch.export loops of :mod:`tcn_ahrs.export.stateless`): one
sample or a chunk as checked float64 arrays (finite, within the physical ranges, steps finite,
> 0 and <= MAX_DT) and the start attitude, all checked before any state changes. It lives in
export, below the streaming runtimes that build on export's modules (no import cycle).
"""
from __future__ import annotations

from typing import Tuple

import numpy as np
import torch


def one_sample(stream, sample, dt) -> np.ndarray:
    """One sample as a checked (1, C) array; its dt stored in ``stream._dt1``."""
    x = np.asarray(sample, dtype=np.float64)
    if x.ndim != 1:
        raise ValueError(f"sample: expected shape ({stream.axes},), got {list(x.shape)}")
    x = x.reshape(1, -1)
    if x.shape[1] != stream.axes:
        raise ValueError(f"sample: expected {stream.axes} values, got {x.shape[1]}")
    stream._dt1[0] = dt
    stream._check(x, stream._dt1)
    return x


def checked_chunk(stream, samples, dt) -> Tuple[np.ndarray, np.ndarray]:
    """k samples as a checked (k, C) array and their (k,) steps."""
    xs = np.ascontiguousarray(np.asarray(samples, dtype=np.float64))
    if xs.ndim != 2 or xs.shape[1] != stream.axes:
        raise ValueError(f"samples: expected shape (k, {stream.axes}), got {list(xs.shape)}")
    dts = np.ascontiguousarray(np.broadcast_to(np.asarray(dt, dtype=np.float64), (xs.shape[0],)))
    stream._check(xs, dts)
    return xs, dts


def check_samples(xs: np.ndarray, dts: np.ndarray) -> None:
    """ValueError unless every reading is finite and within the physical ranges
    (:data:`tcn_ahrs.conventions.INPUT_RANGES`) and every (used) step is finite, >=
    :data:`~tcn_ahrs.conventions.MIN_DT` and <= :data:`~tcn_ahrs.conventions.MAX_DT` s."""
    from ..conventions import INPUT_LIMITS, INPUT_RANGES, MAX_DT, MIN_DT

    if not np.isfinite(xs).all():
        i = [int(v) for v in np.argwhere(~np.isfinite(xs))[0]]
        raise ValueError(f"sample: non-finite value at index {i} (expected finite readings: drop or "
                         "interpolate that sample)")
    limit = np.asarray(INPUT_LIMITS[:xs.shape[1]])
    if (np.abs(xs) > limit).any():
        i = [int(v) for v in np.argwhere(np.abs(xs) > limit)[0]]
        raise ValueError(f"sample: value {xs[i[0], i[1]]:.4g} at index {i} is beyond any sensor's range (|gyro| <= "
                         f"{INPUT_RANGES['gyro']:g} rad/s, |acc| <= {INPUT_RANGES['accel']:g} m/s^2, |mag| <= "
                         f"{INPUT_RANGES['mag']:g} uT per axis): a spike; drop or interpolate that sample")
    if dts.size and not (np.isfinite(dts).all() and (dts >= MIN_DT).all() and (dts <= MAX_DT).all()):
        raise ValueError(f"dt: expected finite time steps in [{MIN_DT:g}, {MAX_DT:g}] s since the previous sample, got "
                         f"{dts.tolist()}")


def check_quat0(q0) -> torch.Tensor:
    """q0 (w, x, y, z) as a unit float64 tensor; ValueError unless it is a non-zero finite quaternion."""
    q = torch.as_tensor(np.asarray(q0, dtype=np.float64)).reshape(-1)
    if q.numel() != 4 or not bool(torch.isfinite(q).all()) or float(q.norm()) == 0.0:
        raise ValueError(f"q0: expected a non-zero finite quaternion (w, x, y, z), got {q.tolist()}")
    return q / q.norm()
