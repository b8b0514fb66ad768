"""Exported modules of the learned closed loop (the default model): the model's own
:class:`Calibration` and :class:`ClosedLoopFilter` modules scripted as they are."""
# No `from __future__ import annotations`: TorchScript reads the class-level attribute
# annotations (List[Tensor], ...) as real types.
import json
from typing import Any, Dict, List, Mapping, Optional, Tuple, Union

import torch
from torch import Tensor, nn

from .. import so3
from .inputs import ExportError, _Inputs


class ClosedLoopBatch(_Inputs):
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
        if int(self.closed.rest_window) <= 0:
            rate = metadata.get("rate_hz")
            if not rate:
                raise ExportError("closed-loop export: the rest window is unset and no rate_hz is known "
                                  "(pass rate=HZ)")
            self.closed.set_rate(float(rate))
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


class ClosedLoopStreaming(ClosedLoopBatch):
    """The closed loop one sample per call: ``reset(q0)``; ``step(sample (C,), dt)`` ->
    ``(quat (4,), omega (3,))``; ``run(imu, dt, q0)`` = reset + steps.

    State: the last ``L = max(receptive field, 2 · rest window − 1)`` raw samples (what the
    causal networks and the rest detector at the newest sample depend on), the attitude, the
    bias state and the heading reference. Each step runs the same calibration and the same loop
    code as the batch module, on that history (the calibration over all L samples: correct, but
    ~L times the per-sample work of a ring-buffer network — the speed issue's to fuse).
    """

    def __init__(self, model: nn.Module, metadata: Mapping[str, Any]):
        super().__init__(model, metadata)
        w = int(self.closed.rest_window)
        self.history = int(max(int(model.receptive_field), 2 * w - 1))
        self.register_buffer("buf", torch.zeros(self.history, self.axes, dtype=torch.float32))
        self.register_buffer("buf_dt", torch.zeros(self.history, dtype=torch.float32))
        self.register_buffer("rot", torch.eye(3, dtype=torch.float64).unsqueeze(0))
        self.register_buffer("bias", torch.zeros(1, 3, dtype=torch.float64))
        self.register_buffer("east_ref", torch.zeros(1, 3, dtype=torch.float64))
        self.count = 0

    @torch.jit.export
    def reset(self, q0: Tensor) -> None:
        self.rot = so3.quat_to_matrix(self._q0(q0)).unsqueeze(0)
        self.bias = torch.zeros(1, 3, dtype=torch.float64)
        self.east_ref = torch.zeros(1, 3, dtype=torch.float64)
        self.buf = torch.zeros(self.history, self.axes, dtype=torch.float32)
        self.buf_dt = torch.zeros(self.history, dtype=torch.float32)
        self.count = 0

    @torch.jit.export
    def step(self, sample: Tensor, dt: float) -> Tuple[Tensor, Tensor]:
        if sample.numel() != self.axes:
            raise ValueError("sample: expected " + str(self.axes) + " values, got " + str(sample.numel()))
        self._check_finite(sample, "sample")  # before any state changes (see StreamingAHRS.step)
        self._check_step(dt, self.count == 0)
        self.buf = torch.cat([self.buf[1:], sample.reshape(1, self.axes).to(torch.float32)], 0)
        self.buf_dt = torch.cat([self.buf_dt[1:], torch.full([1], dt, dtype=torch.float32)], 0)
        self.count += 1
        m = min(self.count, self.history)  # fewer than `history` samples: all of them, as batch
        x = self.buf[self.history - m:].unsqueeze(0)
        d = self.buf_dt[self.history - m:].unsqueeze(0)
        if self.count == 1:
            out = self._run(x, d, self.rot, self.bias, None)  # the initial state; sets east_ref
            self.east_ref = out["east_ref"]
            return self._quat(self.rot[0]), self._omega(out)[0]
        # the filter over the last two samples from the carried state (entry 0 = the state), the
        # networks and the rest detector over the whole history: one call of the batch code
        res = self.closed.run(self.calibration(x), x, d, self.rot, self.bias, self.east_ref, m - 2, torch.float64)
        self.rot = res["rot"][:, 1]
        self.bias = res["gyro_bias"][:, 1]
        omega = res["gyro"][0, m - 1].to(torch.float64) - res["gyro_bias"][0, 1] + res["correction"][0, 1]
        return self._quat(self.rot[0]), omega

    def forward(self, sample: Tensor, dt: float) -> Tuple[Tensor, Tensor]:  # type: ignore[override]
        return self.step(sample, dt)

    @torch.jit.export
    def run(self, imu: Tensor, dt: Union[float, Tensor], q0: Tensor) -> Tuple[Tensor, Tensor]:
        self._check_imu(imu)
        n = imu.size(0)
        d = self._dt(dt, n, torch.float32)
        self.reset(q0)
        qs: List[Tensor] = []
        ws: List[Tensor] = []
        for k in range(n):
            q, w = self.step(imu[k], float(d[k]))
            qs.append(q)
            ws.append(w)
        return torch.stack(qs, 0), torch.stack(ws, 0)
