"""The closed loop on scalars as TorchScript runs it (:func:`scan_scalar`: the exported batch
and streaming modules); numba runs the same per-sample functions compiled
(:mod:`tcn_ahrs.model.closed_loop_compiled`: evaluation, CPU training, the streaming runtime).
The update itself is a kernel (:mod:`tcn_ahrs.kernels.closed_loop`; its names stay importable
from here); this module holds the loop over rows and the float64 round trip TorchScript needs.

:func:`tcn_ahrs.model.closed_loop.closed_loop_scan` is the same recursion on tensors — the
differentiable path that training backpropagates through. Its cost is ~25 tensor ops per
sample (≈ 90 µs per sample in TorchScript, ≈ 190 µs eager), which is what made the learned
AHRS slow in evaluation and export. Here the state is twelve floats (``nav_from_body`` row by
row, the gyro bias) and one update is ~150 scalar operations: compiled by numba it costs
≈ 0.1 µs, interpreted by TorchScript ≈ 4–5 µs. ``tests/test_closed_loop_step.py`` holds the
three equal (1e-12 rad).

Inputs per sample, in this order (:data:`ROW`): ω̂_gyr (3), â (3), east_b (3), the acc gain
k_acc τ_acc, the mag gain k_mag τ_mag, the rest gain, dt.
"""
# No `from __future__ import annotations`: TorchScript reads the annotations as real types.
from typing import List, Tuple

import torch
from torch import Tensor

from ..kernels.closed_loop import (closed_loop_update, east_reference_scalar, loop_inputs,  # noqa: F401 (re-exported)
                                   rest_update)
from ..kernels.quat import matrix_to_quat as matrix_to_quat_scalar  # noqa: F401 (re-exported: the kernel layer's)

# columns of one input row
ROW = ("gyro_x", "gyro_y", "gyro_z", "acc_unit_x", "acc_unit_y", "acc_unit_z", "east_x", "east_y",
       "east_z", "acc_gain", "mag_gain", "rest_gain", "dt")
# columns of one output row: C (row-major), b, w
OUT = 15


def split_float32(v: float) -> Tuple[float, float]:
    """v = hi + lo with hi exact in float32 (Dekker's split at 2^29 + 1) and lo exact to 2^-24 of
    itself: ``torch.tensor(hi) + torch.tensor(lo)`` is v to ~2^-48 relative, although TorchScript's
    ``torch.tensor(List[float], dtype=float64)`` rounds each value through float32."""
    c = 536870913.0 * v
    hi = c - (c - v)
    return hi, v - hi


def split_row(vals: List[float], out_hi: List[List[float]], out_lo: List[List[float]]) -> None:
    """Appends the :func:`split_float32` halves of ``vals`` as one row each to ``out_hi`` / ``out_lo``
    (then ``torch.tensor(out_hi) + torch.tensor(out_lo)`` is the float64 table, in TorchScript)."""
    hi: List[float] = []
    lo: List[float] = []
    for v in vals:
        h, l_ = split_float32(v)
        hi.append(h)
        lo.append(l_)
    out_hi.append(hi)
    out_lo.append(lo)


def scan_lists(state: List[float], east_ref: List[float], rows: List[List[float]], bias_gain: float,
               out_hi: List[List[float]], out_lo: List[List[float]]) -> List[float]:
    """The loop over ``rows`` (one :data:`ROW` list per sample) from ``state`` = C (9, row-major)
    + b (3); appends C, b, w of every sample (15 floats) to ``out_hi`` / ``out_lo`` as
    :func:`split_float32` halves; returns the last state. TorchScript-able (the exported modules'
    loop); the Python interpreter runs it too, slowly."""
    r00, r01, r02, r10, r11, r12 = state[0], state[1], state[2], state[3], state[4], state[5]
    r20, r21, r22, b0, b1, b2 = state[6], state[7], state[8], state[9], state[10], state[11]
    e0, e1, e2 = east_ref[0], east_ref[1], east_ref[2]
    for x in rows:
        (r00, r01, r02, r10, r11, r12, r20, r21, r22, b0, b1, b2, c0, c1, c2) = closed_loop_update(
            r00, r01, r02, r10, r11, r12, r20, r21, r22, b0, b1, b2, x[0], x[1], x[2], x[3], x[4], x[5],
            x[6], x[7], x[8], x[9], x[10], x[11], e0, e1, e2, x[12], bias_gain)
        split_row([r00, r01, r02, r10, r11, r12, r20, r21, r22, b0, b1, b2, c0, c1, c2], out_hi, out_lo)
    return [r00, r01, r02, r10, r11, r12, r20, r21, r22, b0, b1, b2]


def float64_tensor(vals: List[float]) -> Tensor:
    """List of floats -> float64 tensor, exact to ~1e-15 relative. (TorchScript's
    ``torch.tensor(List[float], dtype=float64)`` rounds through float32; the float32 residual adds
    back what it lost, leaving a 2^-48 relative error.)"""
    hi = torch.tensor(vals, dtype=torch.float64)
    rounded: List[float] = hi.tolist()
    return hi + torch.tensor([v - h for v, h in zip(vals, rounded)], dtype=torch.float64)


def scan_scalar(rot: Tensor, bias: Tensor, gyro: Tensor, acc_unit: Tensor, east_b: Tensor, acc_gain: Tensor,
                mag_gain: Tensor, rest_gain: Tensor, east_ref: Tensor, dt: Tensor, bias_gain: Tensor
                ) -> Tuple[Tensor, Tensor, Tensor]:
    """The same through :func:`scan_lists` (what TorchScript runs in the exported modules;
    batch entries one after the other). float64."""
    rows_t = torch.cat([gyro, acc_unit, east_b, acc_gain, mag_gain, rest_gain, dt], -1).to(torch.float64)
    state_t = torch.cat([rot.reshape(-1, 9), bias], -1).to(torch.float64)
    b, n = gyro.shape[0], gyro.shape[1]
    kb = float(bias_gain)
    outs: List[Tensor] = []
    for i in range(b):
        rows: List[List[float]] = rows_t[i, 1:].tolist()
        state: List[float] = state_t[i].tolist()
        hi: List[List[float]] = []
        lo: List[List[float]] = []
        ref: List[float] = east_ref[i].to(torch.float64).tolist()
        scan_lists(state, ref, rows, kb, hi, lo)
        first = torch.cat([state_t[i], torch.zeros(3, dtype=torch.float64)]).unsqueeze(0)
        if n > 1:
            first = torch.cat([first, torch.tensor(hi, dtype=torch.float64) + torch.tensor(lo, dtype=torch.float64)], 0)
        outs.append(first)
    o = torch.stack(outs, 0)
    return o[..., 0:9].reshape(b, n, 3, 3), o[..., 9:12], o[..., 12:15]
