"""Exported modules of the learned closed loop (the default model): the model's own
:class:`Calibration` and :class:`ClosedLoopFilter` modules scripted as they are."""
# No `from __future__ import annotations`: TorchScript reads the class-level attribute
# annotations (List[Tensor], ...) as real types.
import json
import math
from typing import Any, Dict, List, Mapping, Optional, Tuple, Union

import torch
from torch import Tensor, nn

from .. import so3
from ..kernels.closed_loop import (closed_loop_update, east_reference_scalar, gap_step, loop_inputs, repeat_count,
                                   rest_update)
from ..kernels.quat import matrix_to_quat as matrix_to_quat_scalar
from ..model.closed_loop_step import split_row
from ..model.closed_loop import frozen_window, window_samples
from .fused import fuse_model
from .inputs import ExportError, InputChecks
from .open_loop import STREAMING_ATTRIBUTES, StreamingAHRS


def rest_window(closed: nn.Module, metadata: Mapping[str, Any]) -> int:
    """The rest detector's window (samples) the exports run with: the one the model was trained
    with, or — when the checkpoint does not record it — the one for metadata's ``rate_hz``."""
    if int(closed.rest_window) > 0:
        return int(closed.rest_window)
    rate = metadata.get("rate_hz")
    if not rate:
        raise ExportError("closed-loop export: the rest window is unset and no rate_hz is known (pass rate=HZ)")
    return window_samples(closed.rest_time, float(rate))


class ClosedLoopBatch(InputChecks):
    """The learned closed loop, whole sequence: the model's own :class:`Calibration` and
    :class:`ClosedLoopFilter` modules scripted as they are (no restated math), run exactly as
    :meth:`LearnedAHRS.run_sequence` runs them in evaluation: networks in float32, rest
    detection, trust and the loop (:func:`tcn_ahrs.model.closed_loop.closed_loop_scan`) in float64.

    ``forward(imu (N, C), dt float | (N,), q0 (4,)) -> (quat (N, 4), omega (N, 3))``, float64;
    ``omega`` = the rate the loop applied, ω̂_gyr − b + w.
    """

    metadata_json: str

    def __init__(self, model: nn.Module, metadata: Mapping[str, Any]):
        super().__init__()
        import copy

        if model.closed is None:
            raise ExportError("ClosedLoopBatch: the model has no closed loop (model.loop=open)")
        self.axes = int(model.axes)
        self.calibration = copy.deepcopy(model.calibration).float().eval()
        self.closed = copy.deepcopy(model.closed).double().eval()
        self.closed.rest_window.fill_(rest_window(model.closed, metadata))
        self.metadata_json = json.dumps(dict(metadata), sort_keys=True)

    @torch.jit.export
    def metadata(self) -> str:
        return self.metadata_json

    def _run(self, x: Tensor, d: Tensor, rot: Tensor, bias: Tensor, east_ref: Optional[Tensor]) -> Dict[str, Tensor]:
        """x (1, N, C) float32, d (1, N) float32 -> the loop's dict (LearnedAHRS.filter_closed_loop)."""
        return self.closed.run(self.calibration(x), x, d, rot, bias, east_ref, 0, torch.float64)

    @staticmethod
    def _omega(out: Dict[str, Tensor]) -> Tensor:
        return out["gyro"][0].to(torch.float64) - out["gyro_bias"][0] + out["correction"][0]

    @staticmethod
    def _quat(rot: Tensor) -> Tensor:
        return so3.matrix_to_quat(rot)

    def forward(self, imu: Tensor, dt: Union[float, Tensor], q0: Tensor) -> Tuple[Tensor, Tensor]:
        self._check_imu(imu)
        n = imu.size(0)
        d = self._dt(dt, n, torch.float32)  # float32 as in evaluation (LearnedEstimator)
        rot0 = so3.quat_to_matrix(self._q0(q0)).unsqueeze(0)
        out = self._run(imu.to(torch.float32).unsqueeze(0), d.unsqueeze(0), rot0,
                        torch.zeros(1, 3, dtype=torch.float64), None)
        return self._quat(out["rot"][0]), self._omega(out)


class ClosedLoopStreaming(StreamingAHRS):
    """The closed loop one sample per call: ``reset(q0)``; ``step(sample (C,), dt)`` ->
    ``(quat (4,), omega (3,))``; ``step_chunk(samples (k, C), dt)`` -> ``(quat (k, 4), omega (k, 3))``
    (the same numbers as k calls of ``step``, one network pass for the k samples); ``run(imu, dt,
    q0)`` = reset + one chunk.

    State: one ring buffer per convolution layer (the stacked, BatchNorm-folded networks of
    :func:`~tcn_ahrs.export.fused.fuse_model`, read through :class:`StreamingAHRS`), the rest
    detector's running sums over its window with the index of the last unsteady sample, and the
    filter's twelve floats (attitude, gyro bias) plus the heading reference. The per-sample filter
    update is :func:`~tcn_ahrs.kernels.closed_loop.closed_loop_update`, the function the
    batch module's loop and the library's compiled loop run.
    """

    __annotations__ = {**STREAMING_ATTRIBUTES,  # TorchScript's attribute types (open_loop.STREAMING_ATTRIBUTES)
                       "state": List[float], "east_ref": List[float], "rest_ring": List[float],
                       "rest_sums": List[float], "last_reading": List[float], "last_gyro": List[float]}

    def __init__(self, model: nn.Module, metadata: Mapping[str, Any]):
        if model.closed is None:
            raise ExportError("ClosedLoopStreaming: the model has no closed loop (model.loop=open)")
        fused = fuse_model(model)
        super().__init__(fused, metadata, torch.float32)
        closed = model.closed
        self.window = rest_window(closed, metadata)
        self.use_acc = bool(closed.use_acc)
        self.use_mag = bool(closed.use_mag) and self.axes == 9
        self.k_acc = float(closed.log_acc_gain.detach().exp())
        self.k_mag = float(closed.log_mag_gain.detach().exp())
        self.k_bias = float(closed.log_bias_gain.detach().exp())
        self.rest_tc = float(closed.log_rest_tc.detach().exp())
        self.rest_gyro, self.rest_acc = float(closed.rest_gyro), float(closed.rest_acc)
        self.acc_reject, self.gravity = float(closed.acc_reject), float(closed.gravity)
        self.mag_min, self.mag_max = float(closed.mag_min), float(closed.mag_max)
        # head: [M y − e ; −trust logits] = addmv(addmv(b, W, h), M, y, beta=−1) in float64 (Eqs. 12-14)
        c = self.axes
        w_err = self.out_weight_f64 if self.groups > 0 else torch.zeros(c, 0, dtype=torch.float64)
        w_trust = (fused["trust_weight"] * math.sqrt(0.5) if self.groups > 0 else torch.zeros(2, 0, dtype=torch.float64))
        self.register_buffer("head_weight", torch.cat([w_err, w_trust], 0).contiguous())
        self.register_buffer("head_bias", torch.cat([fused["out_bias"], fused["trust_bias"]], 0).clone())
        self.register_buffer("head_matrix", torch.cat([fused["calib_matrix"], torch.zeros(2, c, dtype=torch.float64)], 0))
        self.state = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
        self.east_ref = [0.0, 0.0, 0.0]
        self.rest_ring = [0.0] * (6 * self.window)
        self.rest_sums = [0.0] * 6
        self.last_unsteady_gyro = -self.window - 1
        self.last_unsteady_acc = -self.window - 1
        # sensor health (the batch module's frozen_detector): the last gyro and acc reading and
        # how many samples each has repeated
        self.frozen_window = frozen_window(self.window, float(closed.rest_time))
        self.last_reading = [0.0] * 6
        self.gyro_repeats = 0
        self.acc_repeats = 0
        self.gap_factor = float(closed.gap_factor)
        self.typical_step = 0.0
        self.last_gyro = [0.0] * 3

    @torch.jit.export
    def reset(self, q0: Tensor) -> None:
        """Start a new recording at attitude q0 (w, x, y, z), nav_from_body, ENU."""
        rot: List[float] = so3.quat_to_matrix(self._q0(q0)).reshape(9).tolist()
        self.state = rot + [0.0, 0.0, 0.0]
        self.east_ref = [0.0, 0.0, 0.0]
        # built by a loop, not as the literal `[0.0] * n`: TorchScript pools constant lists, and
        # this one is written in place (a pooled constant would carry the old recording's values)
        ring: List[float] = []
        for _ in range(6 * self.window):
            ring.append(0.0)
        self.rest_ring = ring
        self.rest_sums = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]  # replaced, never written in place
        self.last_unsteady_gyro = -self.window - 1
        self.last_unsteady_acc = -self.window - 1
        self.last_reading = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]  # replaced, never written in place
        self.gyro_repeats = 0
        self.acc_repeats = 0
        self.typical_step = 0.0
        self.last_gyro = [0.0, 0.0, 0.0]  # replaced, never written in place
        self.t = 0
        self._reset_rings()

    def _filter(self, v: List[float], raw: List[float], dt: float) -> List[float]:
        """One sample through the rest detector and the closed loop. v = head output (calibrated
        C channels, then the negated acc / mag trust logits), raw the reading. Returns
        [quat w, x, y, z, omega x, y, z] and advances the state."""
        c = self.axes
        t = self.t
        w = self.window
        g0, g1, g2, r3, r4, r5 = raw[0], raw[1], raw[2], raw[3], raw[4], raw[5]
        ring = self.rest_ring
        base = 6 * (t % w)
        o0, o1, o2, o3, o4, o5 = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        if t >= w:  # the reading that leaves the rest window
            o0, o1, o2, o3, o4, o5 = ring[base], ring[base + 1], ring[base + 2], ring[base + 3], ring[base + 4], ring[base + 5]
        ring[base], ring[base + 1], ring[base + 2], ring[base + 3], ring[base + 4], ring[base + 5] = g0, g1, g2, r3, r4, r5
        q = self.rest_sums
        s0, s1, s2, s3, s4, s5, self.last_unsteady_gyro, self.last_unsteady_acc, rest = rest_update(
            q[0], q[1], q[2], q[3], q[4], q[5], g0, g1, g2, r3, r4, r5, o0, o1, o2, o3, o4, o5, t, w,
            self.last_unsteady_gyro, self.last_unsteady_acc, self.rest_gyro, self.rest_acc)
        self.rest_sums = [s0, s1, s2, s3, s4, s5]
        # sensor health: a frozen gyro is not integrated (dt held at 0), a frozen accelerometer
        # not trusted (nor the measured east built from it)
        p = self.last_reading
        self.gyro_repeats = repeat_count(p[0], p[1], p[2], g0, g1, g2, self.gyro_repeats, t)
        self.acc_repeats = repeat_count(p[3], p[4], p[5], r3, r4, r5, self.acc_repeats, t)
        self.last_reading = [g0, g1, g2, r3, r4, r5]
        gyro_ok = 0.0 if self.gyro_repeats >= self.frozen_window - 1 else 1.0
        acc_ok = 0.0 if self.acc_repeats >= self.frozen_window - 1 else 1.0
        rest = rest * gyro_ok * acc_ok
        bx, by, bz, field = 0.0, 0.0, 0.0, 0.0
        if c == 9:
            bx, by, bz = v[6], v[7], v[8]
            field = math.sqrt(raw[6] * raw[6] + raw[7] * raw[7] + raw[8] * raw[8])
        ux, uy, uz, mx, my, mz, ka, km = loop_inputs(
            v[3], v[4], v[5], bx, by, bz, r3, r4, r5, field, -v[c], -v[c + 1], self.use_acc, self.use_mag,
            self.k_acc, self.k_mag, self.acc_reject, self.gravity, self.mag_min, self.mag_max)
        ka, km = ka * acc_ok, km * acc_ok
        s = self.state
        gx, gy, gz = v[0], v[1], v[2]
        if t > 0:  # a gap (samples lost): the rate over it is the mean of the readings either side
            self.typical_step, gap = gap_step(self.typical_step, dt, self.gap_factor)
            if gap > 0.5:
                gx, gy, gz = 0.5 * (gx + self.last_gyro[0]), 0.5 * (gy + self.last_gyro[1]), 0.5 * (gz + self.last_gyro[2])
        self.last_gyro = [v[0], v[1], v[2]]
        dt = dt * gyro_ok
        if t == 0:
            if self.use_mag:
                e0, e1, e2 = east_reference_scalar(s[0], s[1], s[2], s[3], s[4], s[5], mx, my, mz)
                self.east_ref = [e0, e1, e2]
            out = s
            c0, c1, c2 = 0.0, 0.0, 0.0
        else:
            er = self.east_ref
            out_t = closed_loop_update(s[0], s[1], s[2], s[3], s[4], s[5], s[6], s[7], s[8], s[9], s[10], s[11],
                                       gx, gy, gz, ux, uy, uz, mx, my, mz, ka, km,
                                       min(1.0, rest * dt / self.rest_tc), er[0], er[1], er[2], dt, self.k_bias)
            out = [out_t[0], out_t[1], out_t[2], out_t[3], out_t[4], out_t[5], out_t[6], out_t[7], out_t[8],
                   out_t[9], out_t[10], out_t[11]]
            c0, c1, c2 = out_t[12], out_t[13], out_t[14]
            self.state = out
        self.t = t + 1
        qw, qx, qy, qz = matrix_to_quat_scalar(out[0], out[1], out[2], out[3], out[4], out[5], out[6], out[7], out[8])
        return [qw, qx, qy, qz, v[0] - out[9] + c0, v[1] - out[10] + c1, v[2] - out[11] + c2]

    @torch.jit.export
    def step(self, sample: Tensor, dt: Union[float, Tensor]) -> Tuple[Tensor, Tensor]:
        """sample (C,) raw IMU, dt [s] since the previous sample (unused on the first call after
        reset) -> (quat (4,) w,x,y,z nav_from_body ENU, omega (3,) rad/s), float64."""
        dtf = self._begin_step(sample, dt)
        x = sample.to(torch.float64)
        v: List[float] = self._head_step(sample, x, self.head_bias, self.head_weight, self.head_matrix).tolist()
        raw: List[float] = x.tolist()
        out = self._f64_tensor(self._filter(v, raw, dtf))
        return out[0:4], out[4:7]

    @torch.jit.export
    def step_chunk(self, samples: Tensor, dt: Union[float, Tensor]) -> Tuple[Tensor, Tensor]:
        """k samples (k, C) at once, dt float or (k,) (the first entry unused right after reset)
        -> (quat (k, 4), omega (k, 3)) float64: what k calls of :meth:`step` return."""
        self._check_imu(samples)
        n = samples.size(0)
        d: List[float] = self._dt(dt, n).tolist()
        self._check_step(d[0], self.t == 0)
        x = samples.to(torch.float64)
        if self.groups > 0:
            head = torch.addmm(torch.addmm(self.head_bias, self._errors_chunk(samples), self.head_weight.t()),
                               x, self.head_matrix.t(), beta=-1.0)
        else:
            head = torch.addmm(self.head_bias.expand(n, -1), x, self.head_matrix.t(), beta=-1.0)
        vs: List[List[float]] = head.tolist()
        raws: List[List[float]] = x.tolist()
        hi: List[List[float]] = []
        lo: List[List[float]] = []
        for k in range(n):
            split_row(self._filter(vs[k], raws[k], d[k]), hi, lo)
        out = torch.tensor(hi, dtype=torch.float64) + torch.tensor(lo, dtype=torch.float64)
        return out[:, 0:4], out[:, 4:7]

    def forward(self, sample: Tensor, dt: Union[float, Tensor]) -> Tuple[Tensor, Tensor]:  # type: ignore[override]
        return self.step(sample, dt)

    @torch.jit.export
    def run(self, imu: Tensor, dt: Union[float, Tensor], q0: Tensor) -> Tuple[Tensor, Tensor]:
        """reset(q0), then imu (N, C) as one chunk -> quat (N, 4), omega (N, 3) (float64). Every
        input is checked before the state is reset (after an error the module goes on as before)."""
        self._check_imu(imu)
        d = self._dt(dt, imu.size(0))
        self._q0(q0)
        self.reset(q0)
        return self.step_chunk(imu, d)
