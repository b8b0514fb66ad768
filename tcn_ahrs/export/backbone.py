"""Exported modules of the residual model (``model.loop: backbone``, :mod:`tcn_ahrs.model.residual`).

The two networks run on the ring buffers of :class:`~tcn_ahrs.export.open_loop.StreamingAHRS`
(:func:`~tcn_ahrs.export.fused.fuse_residual`: BatchNorm folded, float32); their outputs become
the gyro residual and the trusts as in :class:`~tcn_ahrs.model.residual.BackboneLoop`, and the
backbone steps with the functions of :mod:`tcn_ahrs.kernels.backbone` read by TorchScript
(:func:`~tcn_ahrs.kernels.script_ops.script_kernel`: the kernel source compiled once more, no
restated math). The same contract and numbers as :class:`tcn_ahrs.streaming.BackboneStreaming`
(the numba runtime), which is ~10x faster; this module needs only torch.
"""
# No `from __future__ import annotations`: TorchScript reads the class-level attribute
# annotations (List[Tensor], ...) as real types.
import math
from typing import Any, List, Mapping, Tuple, Union

import torch
from torch import Tensor, nn

from ..kernels import backbone as K
from ..kernels.script_ops import script_kernel
from ..model.closed_loop_step import split_row
from .fused import fuse_residual
from .inputs import ExportError
from .open_loop import STREAMING_ATTRIBUTES, StreamingAHRS

_KS = script_kernel(K)
_coefficients, _gyro_update, _acc_update, _mag_update, _quat6, _quat9, qmul, _qrot = (
    _KS.coefficients, _KS.gyro_update, _KS.acc_update, _KS.mag_update, _KS.quat6, _KS.quat9, _KS.qmul, _KS.qrot)


class ResidualStreaming(StreamingAHRS):
    """The residual model one sample per call: ``reset(q0)``; ``step(sample (C,), dt)`` ->
    ``(quat (4,), omega (3,))`` float64 (omega = the gyro fed to the backbone minus its bias
    state); ``step_chunk(samples (k, C), dt)``; ``run(imu, dt, q0)`` = reset + one chunk.

    9 axes: the heading is referred to the field of the first sample after ``reset`` (the batch
    model's ``heading_ref`` "init"). The dt of the first sample IS used (the backbone integrates
    sample 0, as the batch model does). A non-finite reading or a dt that is not finite and > 0
    raises ValueError before any state changes."""

    __annotations__ = {**STREAMING_ATTRIBUTES,  # TorchScript's attribute types (open_loop.STREAMING_ATTRIBUTES)
                       "params": List[float], "bias0": List[float], "q_start": List[float], "m_conj": List[float],
                       "backbone_state": List[float], "coeff": List[float], "trust_scales": List[float],
                       "initial_state": List[float]}

    def __init__(self, model: nn.Module, metadata: Mapping[str, Any]):
        if getattr(model, "backbone", None) is None:
            raise ExportError("ResidualStreaming: the model has no backbone (model.loop must be 'backbone')")
        fused = fuse_residual(model)
        super().__init__(fused, metadata, torch.float32)
        cal, loop = model.calibration, model.backbone
        c = self.axes
        self.n_trust = 2 if c == 9 else 1
        # head rows: −(W h + b) = −[gyro net before tanh (3), trust logits]; the features arrive
        # as sqrt(2) GELU (the sqrt(1/2) folded into W)
        w = torch.cat([self.out_weight_f64[0:3], fused["trust_weight"][:self.n_trust] * math.sqrt(0.5)], 0)
        self.register_buffer("head_weight", w.contiguous())
        self.register_buffer("head_bias", torch.cat([fused["out_bias"][0:3], fused["trust_bias"][:self.n_trust]]).clone())
        self.register_buffer("head_matrix", torch.zeros(w.shape[0], c, dtype=torch.float64))
        self.use_backbone_mag = bool(loop.use_mag) and c == 9
        self.gyro_scale, self.gyro_clip = float(cal.gyro_scale), float(cal.gyro_clip)
        self.trust_max, self.trust_weight_knob = float(loop.trust_max), float(loop.trust_weight)
        self.trust_scales = [float(loop.acc_trust_scale), float(loop.mag_trust_scale), float(loop.bias_trust_scale)]
        self.bias_trust_power = float(loop.bias_trust_power)
        self.params = [float(v) for v in loop.params.vector()]
        self.bias0 = [float(v) for v in (loop.bias_prior * loop.bias_init.detach().double()).tolist()]
        self.q_start = [1.0, 0.0, 0.0, 0.0]
        self.m_conj = [1.0, 0.0, 0.0, 0.0]
        self.initial_state = [float(v) for v in K.initial_state(loop.params)]
        self.s_gq, self.s_bias = int(K.S_GQ), int(K.S_BIAS)
        self.backbone_state = [0.0] * K.N_STATE
        self.coeff = [0.0] * K.N_COEFF
        self.last_dt = -1.0

    @torch.jit.export
    def reset(self, q0: Tensor) -> None:
        """Start a new recording at attitude q0 (w, x, y, z), nav_from_body, ENU."""
        q: List[float] = self._q0(q0).tolist()
        self.q_start = q
        self.last_dt = -1.0  # coefficients recomputed at the first step
        self.t = 0
        self._reset_rings()

    def _start(self, raw: List[float]) -> None:
        """The backbone's state at the first sample (9D: in the magnetic frame of its field,
        :func:`tcn_ahrs.filters.common.magnetic_from_nav`)."""
        q = self.q_start
        self.m_conj = [1.0, 0.0, 0.0, 0.0]
        if self.use_backbone_mag:
            v0, v1, v2 = _qrot(q[0], q[1], q[2], q[3], raw[6], raw[7], raw[8])
            h = 0.5 * (0.5 * math.pi - math.atan2(v1, v0))
            ch, sh = math.cos(h), math.sin(h)
            w, x, y, z = qmul(ch, 0.0, 0.0, sh, q[0], q[1], q[2], q[3])
            q = [w, x, y, z]
            self.m_conj = [ch, 0.0, 0.0, -sh]
        s: List[float] = list(self.initial_state)
        n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        for i in range(4):
            s[self.s_gq + i] = q[i] / n
        for i in range(3):
            s[self.s_bias + i] = self.bias0[i]
        self.backbone_state = s

    def _filter(self, v: List[float], raw: List[float], dt: float) -> List[float]:
        """One sample: head output v (−[gyro net pre-tanh (3), trust logits]), the raw reading
        and its dt -> [quat w, x, y, z, omega x, y, z]; advances the backbone."""
        if self.t == 0:
            self._start(raw)
        trusts = [self.trust_scales[0], self.trust_scales[1], self.trust_scales[2]]
        for j in range(self.n_trust):
            tr = min(self.trust_max, 2.0 / (1.0 + math.exp(v[3 + j])))  # 2 σ(z) with z = −v
            trusts[j] = self.trust_scales[j] * (1.0 + self.trust_weight_knob * (tr - 1.0))
            if j == 0 and self.bias_trust_power > 0.0:  # the acc trust gating the bias update
                trusts[2] = self.trust_scales[2] * (tr / self.trust_max) ** self.bias_trust_power
        lim = self.gyro_clip
        gx = raw[0] - min(lim, max(-lim, self.gyro_scale * math.tanh(-v[0])))
        gy = raw[1] - min(lim, max(-lim, self.gyro_scale * math.tanh(-v[1])))
        gz = raw[2] - min(lim, max(-lim, self.gyro_scale * math.tanh(-v[2])))
        s, p, c = self.backbone_state, self.params, self.coeff
        if dt != self.last_dt:
            _coefficients(p, dt, c)
            self.last_dt = dt
        _gyro_update(s, p, c, gx, gy, gz)
        if raw[3] != 0.0 or raw[4] != 0.0 or raw[5] != 0.0:  # the batch loop skips [0 0 0], as VQF
            _acc_update(s, p, c, raw[3], raw[4], raw[5], trusts[0], trusts[2])
        if self.use_backbone_mag:
            if raw[6] != 0.0 or raw[7] != 0.0 or raw[8] != 0.0:
                _mag_update(s, p, c, raw[6], raw[7], raw[8], trusts[1])
            w, x, y, z = _quat9(s)
        else:
            w, x, y, z = _quat6(s)
        m = self.m_conj
        qw, qx, qy, qz = qmul(m[0], m[1], m[2], m[3], w, x, y, z)
        self.t += 1
        if qw < 0.0:  # w >= 0 representative, as the other exported modules
            qw, qx, qy, qz = -qw, -qx, -qy, -qz
        return [qw, qx, qy, qz, gx - s[self.s_bias], gy - s[self.s_bias + 1], gz - s[self.s_bias + 2]]

    def _check_dts(self, d: List[float]) -> None:
        for k in range(len(d)):  # every dt is used (the backbone integrates sample 0)
            if not (d[k] > 0.0 and d[k] <= self.max_dt):
                raise ValueError("dt: expected finite time steps in (0, " + self.max_dt_text + "] s, got " + str(d[k])
                                 + " at index " + str(k))

    @torch.jit.export
    def step(self, sample: Tensor, dt: Union[float, Tensor]) -> Tuple[Tensor, Tensor]:
        """sample (C,) raw IMU, dt [s] since the previous sample -> (quat (4,) w,x,y,z
        nav_from_body ENU, omega (3,) rad/s), float64."""
        dtf = self._begin_step(sample, dt)
        self._check_dts([dtf])
        x = sample.to(torch.float64)
        v: List[float] = self._head_step(sample, x, self.head_bias, self.head_weight, self.head_matrix).tolist()
        raw: List[float] = x.tolist()
        out = self._f64_tensor(self._filter(v, raw, dtf))
        return out[0:4], out[4:7]

    @torch.jit.export
    def step_chunk(self, samples: Tensor, dt: Union[float, Tensor]) -> Tuple[Tensor, Tensor]:
        """k samples (k, C), dt float or (k,) -> (quat (k, 4), omega (k, 3)) float64: what k
        calls of :meth:`step` return (one network pass for the k samples)."""
        self._check_imu(samples)
        n = samples.size(0)
        d: List[float] = self._dt(dt, n).tolist()
        self._check_dts(d)
        x = samples.to(torch.float64)
        head = torch.addmm(self.head_bias, self._errors_chunk(samples), self.head_weight.t()).neg()
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
        input is checked before the state is reset."""
        self._check_imu(imu)
        d: List[float] = self._dt(dt, imu.size(0)).tolist()
        self._check_dts(d)
        self._q0(q0)
        self.reset(q0)
        return self.step_chunk(imu, dt)


class ResidualBatch(ResidualStreaming):
    """The residual model, whole recording: ``forward(imu (N, C), dt float | (N,), q0 (4,)) ->
    (quat (N, 4), omega (N, 3))`` float64 (= :meth:`ResidualStreaming.run`)."""

    def forward(self, imu: Tensor, dt: Union[float, Tensor], q0: Tensor) -> Tuple[Tensor, Tensor]:  # type: ignore[override]
        return self.run(imu, dt, q0)
