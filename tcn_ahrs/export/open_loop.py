"""Exported modules of the paper's open-loop model: :class:`BatchAHRS` (whole sequence) and
:class:`StreamingAHRS` (one sample per call, a ring buffer per convolution layer)."""
# No `from __future__ import annotations`: TorchScript reads the class-level attribute
# annotations (List[Tensor], ...) as real types.
import json
import math
from typing import Any, Dict, List, Mapping, Tuple, Union

import torch
import torch.nn.functional as F
from torch import Tensor

from .fused import gelu_scaled, hamilton_table, rows_up_east, acc_error_rows, mag_error_rows, quat_integrate, ring_convolutions
from ..kernels.quat import quat_step
from ..model.closed_loop_step import float64_tensor
from .inputs import ExportError, InputChecks

NET_DTYPES = (torch.float32, torch.float64, torch.bfloat16)
_SQRT_HALF = math.sqrt(0.5)


class BatchAHRS(InputChecks):
    """Whole-sequence learned AHRS (TorchScript-able). See the module docstring for the contract.

    ``forward(imu (N, C), dt float | (N,), q0 (4,)) -> (quat (N, 4), omega (N, 3))``, float64.
    """

    hidden_weights: List[Tensor]
    hidden_biases: List[Tensor]
    hidden_dilations: List[int]
    metadata_json: str

    def __init__(self, fused: Dict[str, Any], metadata: Mapping[str, Any], net_dtype: torch.dtype = torch.float32):
        super().__init__()
        if net_dtype not in NET_DTYPES:
            raise ExportError(f"net_dtype {net_dtype}: expected one of {NET_DTYPES}")
        self.axes = int(fused["axes"])
        self.groups = int(fused["groups"])
        self.has_ecf = bool(fused["ecf"])
        self.preintegration = str(fused["preintegration"])
        self.use_acc = bool(fused["use_acc"])
        self.use_mag = bool(fused["use_mag"])
        self.net_dtype = net_dtype
        f64 = torch.float64
        # normalisation and output layer: float32 (float64 for a float64 network); the
        # convolutions run in net_dtype (bfloat16: opt-in, batch only, see the module docstring)
        io_dtype = torch.float64 if net_dtype == torch.float64 else torch.float32
        self.io_dtype = io_dtype
        self.register_buffer("input_mean", fused["input_mean"].to(io_dtype))
        self.register_buffer("input_inv_std", (1.0 / fused["input_std"]).to(io_dtype))
        self.register_buffer("calib_matrix", fused["calib_matrix"].to(f64))
        self.register_buffer("out_bias", fused["out_bias"].to(f64))
        self.register_buffer("acc_gain", fused["acc_gain"].to(f64))
        self.register_buffer("mag_gain", fused["mag_gain"].to(f64))
        self.register_buffer("hamilton", hamilton_table())
        self.kernel_size = int(fused.get("kernel_size", 1))
        self.first_dilation = int(fused.get("first_dilation", 1))
        empty = torch.zeros(0, dtype=net_dtype)
        if self.groups > 0:
            self.register_buffer("first_weight", fused["first_weight"].to(net_dtype))
            self.register_buffer("first_bias", fused["first_bias"].to(net_dtype))
            self.register_buffer("out_weight", fused["out_weight"].to(io_dtype))
            self.hidden_weights = [w.to(net_dtype) for w, _, _ in fused["hidden"]]
            self.hidden_biases = [b.to(net_dtype) for _, b, _ in fused["hidden"]]
            self.hidden_dilations = [int(d) for _, _, d in fused["hidden"]]
        else:
            self.register_buffer("first_weight", empty)
            self.register_buffer("first_bias", empty)
            self.register_buffer("out_weight", torch.zeros(0, dtype=io_dtype))
            self.hidden_weights, self.hidden_biases, self.hidden_dilations = [], [], []
        self.metadata_json = json.dumps(dict(metadata), sort_keys=True)

    @torch.jit.export
    def metadata(self) -> str:
        """JSON: axes, variant, rate, units, frames, quaternion order, receptive field, ..."""
        return self.metadata_json

    # ------------------------------------------------------------------ pieces
    def errors(self, imu: Tensor) -> Tensor:
        """Learned error terms e = (ω̃, ã[, m̃]) (N, C) float64, from the stacked causal TCNs."""
        n = imu.size(0)
        if self.groups == 0:
            return self.out_bias.expand(n, self.axes)
        z = (imu.to(self.io_dtype) - self.input_mean) * self.input_inv_std  # (N, C)
        h = z.t().unsqueeze(0).to(self.net_dtype)  # (1, C, N)
        k1 = self.kernel_size - 1
        h = F.gelu(F.conv1d(F.pad(h, [k1 * self.first_dilation, 0]), self.first_weight, self.first_bias,
                            dilation=self.first_dilation))
        hs = h.chunk(self.groups, 1)
        for i in range(len(self.hidden_weights)):
            d = self.hidden_dilations[i]
            # one convolution per group (on CPU ~2x faster than a grouped convolution), kept
            # apart (no concatenation) until the output layer
            ws = self.hidden_weights[i].chunk(self.groups, 0)
            bs = self.hidden_biases[i].chunk(self.groups, 0)
            hs = [F.gelu(F.conv1d(F.pad(hs[j], [k1 * d, 0]), ws[j], bs[j], dilation=d))
                  for j in range(self.groups)]
        wo = self.out_weight.chunk(self.groups, 1)
        e = torch.mm(wo[0], hs[0][0].to(self.io_dtype))  # (C, N)
        for j in range(1, self.groups):
            e = torch.addmm(e, wo[j], hs[j][0].to(self.io_dtype))
        return e.t().to(torch.float64) + self.out_bias

    def _correction(self, q_prev: Tensor, acc: Tensor, mag: Tensor, acc_raw: Tensor) -> Tensor:
        """γ ⊙ e_acc + η ⊙ e_mag (Eqs. 22-24) against C̃ = C(q_prev), (N, 3) float64."""
        q = q_prev / torch.linalg.norm(q_prev, dim=1, keepdim=True)
        up, east = rows_up_east(q)
        corr = torch.zeros_like(acc)
        if self.use_acc:
            corr = corr + self.acc_gain * acc_error_rows(acc, up)
        if self.use_mag:
            corr = corr + self.mag_gain * mag_error_rows(mag, acc_raw, east)
        return corr

    def _previous(self, q0: Tensor, omega: Tensor, dt: Tensor) -> Tensor:
        """Pre-integrated attitude C̃_{k-1} (Eq. 25) for every sample k as (N, 4) quaternions
        (entry 0 = q0), as :func:`tcn_ahrs.model.open_loop.previous_attitude`."""
        q = quat_integrate(q0, omega, dt, self.hamilton)
        return torch.cat([q0.unsqueeze(0), q[:-1]], 0)

    def corrected_rate(self, imu: Tensor, dt: Tensor, q0: Tensor) -> Tensor:
        """ω̂ (N, 3) float64: calibration (Eqs. 12-14) + open-loop ECF (Eqs. 22-25).
        q0 (4,) unit quaternion, nav_from_body."""
        x = imu.to(torch.float64)
        cal = torch.addmm(self.errors(imu), x, self.calib_matrix.t(), beta=-1.0)  # M y − e
        gyro = cal[:, 0:3]
        if not self.has_ecf:
            return gyro
        acc = cal[:, 3:6]
        mag = cal[:, 6:9] if self.axes == 9 else acc
        base = x[:, 0:3] if self.preintegration == "raw" else gyro
        omega = gyro + self._correction(self._previous(q0, base, dt), acc, mag, x[:, 3:6])
        if self.preintegration == "two_pass":
            omega = gyro + self._correction(self._previous(q0, omega, dt), acc, mag, x[:, 3:6])
        return omega

    def forward(self, imu: Tensor, dt: Union[float, Tensor], q0: Tensor) -> Tuple[Tensor, Tensor]:
        """imu (N, C) raw, dt float or (N,) s, q0 (4,) -> quat (N, 4), omega (N, 3) (float64)."""
        self._check_imu(imu)
        n = imu.size(0)
        dtv = self._dt(dt, n)
        q0n = self._q0(q0)
        omega = self.corrected_rate(imu, dtv, q0n)
        q = quat_integrate(q0n, omega, dtv, self.hamilton)  # Eq. 3, float64 parallel prefix
        # unit norm and the w >= 0 representative in one multiply
        scale = torch.where(q[:, :1] < 0.0, -1.0, 1.0) / torch.linalg.norm(q, dim=1, keepdim=True)
        return q * scale, omega


# ================================================================= streaming module
STREAMING_ATTRIBUTES = {
    "hidden_weights": List[Tensor], "hidden_biases": List[Tensor], "hidden_dilations": List[int], "metadata_json": str,
    "ring_buffers": List[Tensor], "spans": List[int], "tap_index": List[Tensor], "tap_offsets": List[int],
    "acc_gain_list": List[float], "mag_gain_list": List[float], "step_weights": List[Tensor],
    "step_biases": List[Tensor], "chunk_weights": List[Tensor], "chunk_biases": List[Tensor], "q_pre": List[float],
    "q_pre2": List[float], "q_att": List[float]}
"""The streaming modules' TorchScript-typed attributes (a class's own ``__annotations__``)."""


class StreamingAHRS(BatchAHRS):
    """One sample per call (TorchScript-able). ``reset(q0)``, ``step(sample (C,), dt)`` ->
    ``(quat (4,), omega (3,))``; ``forward`` = ``step``; ``run(imu, dt, q0)`` = reset + steps.

    Convolution state: layer l keeps a ring buffer of ``L_l = dilation_l * (kernel - 1) + 1``
    inputs (the current one plus dilation*(kernel-1) past ones), time-major. Each input is
    written once, at row ``p = t mod L_l``; the ``kernel`` taps of sample t, oldest first, are
    rows ``(p + 1 + j * dilation) mod L_l``, read with one ``index_select`` through an index
    precomputed for every phase p. The first layer's buffer holds the raw samples (the input
    normalisation is folded into its weights, so ``reset`` fills it with the normalisation
    mean = the batch model's zero padding of the normalised input). ECF state: quaternions of
    the pre-integrated attitude(s) C̃ (Eq. 25; a second one for ``two_pass``) and of the output
    attitude (Eq. 3), float64 scalars.

    Speed: the step is bound by per-op dispatch (~0.5-1 us per TorchScript tensor op), not by
    arithmetic, so it uses as few tensor ops as possible (~30 per sample).
    """

    # the attributes TorchScript types; it reads only a class's own __annotations__, so each
    # streaming subclass starts its own from this one dict (STREAMING_ATTRIBUTES), not a copy
    __annotations__ = dict(STREAMING_ATTRIBUTES)

    def __init__(self, fused: Dict[str, Any], metadata: Mapping[str, Any], net_dtype: torch.dtype = torch.float32):
        if net_dtype == torch.bfloat16:
            raise ExportError("net_dtype bfloat16 is for the batch module only (a per-sample bfloat16 "
                              "matrix-vector product is not faster on CPU and loses precision)")
        super().__init__(fused, metadata, net_dtype)
        k = self.kernel_size
        self.t = 0
        self.first_span = self.first_dilation * (k - 1) + 1
        g = self.groups
        self.tap_index, self.tap_offsets = [], []

        def add_taps(span: int, dilation: int) -> None:
            # per phase p: rows of the taps, oldest first
            self.tap_offsets.append(len(self.tap_index))
            for p in range(span):
                self.tap_index.append(torch.tensor([(p + 1 + j * dilation) % span for j in range(k)],
                                                   dtype=torch.long))

        if g > 0:
            mean = fused["input_mean"].double()
            inv_std = 1.0 / fused["input_std"].double()
            w0 = fused["first_weight"].double() * inv_std[None, :, None]  # (G*C1, C, k), Eq. 12 normalisation folded
            b0 = fused["first_bias"].double() - (w0 * mean[None, :, None]).sum((1, 2))
            # (k*C, G*C1) in (tap, channel) row order: taps (k, C) flattened times this matrix
            self.register_buffer("first_weight_t", (w0.permute(2, 1, 0).reshape(k * self.axes, -1) * _SQRT_HALF)
                                 .to(net_dtype).contiguous())
            self.register_buffer("first_bias_step", (b0.reshape(1, -1) * _SQRT_HALF).to(net_dtype))
            self.register_buffer("first_buffer", torch.zeros(self.first_span, self.axes, dtype=net_dtype))
            add_taps(self.first_span, self.first_dilation)
        else:
            for name in ("first_weight_t", "first_bias_step", "first_buffer"):
                self.register_buffer(name, torch.zeros(0, dtype=net_dtype))
        self.ring_buffers, self.spans, self.step_weights, self.step_biases = [], [], [], []
        fused_hidden_f64 = [(w.double(), b.double()) for w, b, _ in fused.get("hidden", [])]
        for w, b, d in zip(self.hidden_weights, self.hidden_biases, self.hidden_dilations):
            c_out, c_in = w.shape[0] // g, w.shape[1]
            span = d * (k - 1) + 1
            self.spans.append(span)
            # time-major buffer (G, L, C_in): writing one input is one (G, 1, C_in) copy and the
            # gathered taps (G, k, C_in) are contiguous
            self.ring_buffers.append(torch.zeros(g, span, c_in, dtype=net_dtype))
            add_taps(span, d)
            # (G, k*C_in, C_out) with the taps' (tap, channel) order: the per-sample product is a
            # (1, k*C_in) row times this matrix (a batched row-vector product is far faster
            # on CPU than a batched matrix times a one-column matrix)
            # GELU as 2 ops (see fused.gelu_scaled): outputs scaled by 1/sqrt(2), inputs by the
            # same factor again (the previous layer emits sqrt(2) * GELU), in float64
            w_f, b_f = fused_hidden_f64[len(self.spans) - 1]
            self.step_weights.append((w_f.reshape(g, c_out, c_in, k).permute(0, 3, 2, 1).reshape(g, k * c_in, c_out) * 0.5)
                                     .to(net_dtype).contiguous())
            self.step_biases.append((b_f.reshape(g, 1, c_out) * _SQRT_HALF).to(net_dtype).contiguous())
        # the same weights as convolutions over a chunk of samples (_errors_chunk): (G*C_out, C_in, k)
        self.chunk_weights, self.chunk_biases = [], []
        if g > 0:
            c1 = self.first_weight_t.shape[1]
            self.chunk_weights.append(self.first_weight_t.reshape(k, self.axes, c1).permute(2, 1, 0).clone())
            self.chunk_biases.append(self.first_bias_step.reshape(-1).clone())
        for w_s, b_s in zip(self.step_weights, self.step_biases):
            c_out = w_s.shape[2]
            self.chunk_weights.append(w_s.reshape(g, k, -1, c_out).permute(0, 3, 2, 1).reshape(g * c_out, -1, k)
                                      .clone())
            self.chunk_biases.append(b_s.reshape(-1).clone())
        # e = W_o h + b_o in float64, subtracted from M y in one addmv (Eqs. 12-14); the last
        # layer's features arrive as sqrt(2) * GELU
        self.register_buffer("out_weight_f64", fused["out_weight"].double() * _SQRT_HALF if g > 0
                             else torch.zeros(0, dtype=torch.float64))
        self.acc_gain_list = [float(v) for v in self.acc_gain]
        self.mag_gain_list = [float(v) for v in self.mag_gain]
        q = [1.0, 0.0, 0.0, 0.0]
        self.q_pre, self.q_pre2, self.q_att = list(q), list(q), list(q)

    @torch.jit.export
    def reset(self, q0: Tensor) -> None:
        """Start a new sequence at attitude q0 (w, x, y, z), nav_from_body, ENU."""
        q: List[float] = self._q0(q0).tolist()
        self.q_pre = list(q)
        self.q_pre2 = list(q)
        self.q_att = list(q)
        self.t = 0
        self._reset_rings()

    def _reset_rings(self) -> None:
        """The networks' state after ``reset``: the batch model's causal zero padding."""
        if self.groups > 0:
            # raw-sample buffer: the mean normalises to the batch model's zero padding
            self.first_buffer.copy_(self.input_mean.expand_as(self.first_buffer))
        for buf in self.ring_buffers:
            buf.zero_()

    # ---------------------------------------------------------- scalar SO(3) helpers
    @staticmethod
    def _quat_step(q: List[float], wx: float, wy: float, wz: float, dt: float) -> List[float]:
        """``q ⊗ exp(ω dt)``, renormalised (:func:`tcn_ahrs.kernels.quat.quat_step`)."""
        w, x, y, z = quat_step(q[0], q[1], q[2], q[3], wx * dt, wy * dt, wz * dt)
        return [w, x, y, z]

    def _corr(self, q: List[float], cal: List[float], raw: List[float]) -> List[float]:
        """γ ⊙ e_acc + η ⊙ e_mag (Eqs. 22-24) against C̃ = C(q), scalar float64 arithmetic."""
        w, x, y, z = q[0], q[1], q[2], q[3]
        cx, cy, cz = 0.0, 0.0, 0.0
        if self.use_acc:
            # Eq. 23: unit(ĝ) × (C̃^T e_up); C̃^T e_up = third row of C̃
            ux, uy, uz = 2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)
            ax, ay, az = cal[3], cal[4], cal[5]
            n = max(math.sqrt(ax * ax + ay * ay + az * az), 1e-9)
            ax, ay, az = ax / n, ay / n, az / n
            cx += self.acc_gain_list[0] * (ay * uz - az * uy)
            cy += self.acc_gain_list[1] * (az * ux - ax * uz)
            cz += self.acc_gain_list[2] * (ax * uy - ay * ux)
        if self.use_mag:
            # Eq. 24: unit(b̂ × g'_raw) × (C̃^T e_east); C̃^T e_east = first row of C̃
            vx, vy, vz = 1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)
            mx, my, mz = cal[6], cal[7], cal[8]
            gx, gy, gz = raw[3], raw[4], raw[5]
            ex, ey, ez = my * gz - mz * gy, mz * gx - mx * gz, mx * gy - my * gx
            n = max(math.sqrt(ex * ex + ey * ey + ez * ez), 1e-9)
            ex, ey, ez = ex / n, ey / n, ez / n
            cx += self.mag_gain_list[0] * (ey * vz - ez * vy)
            cy += self.mag_gain_list[1] * (ez * vx - ex * vz)
            cz += self.mag_gain_list[2] * (ex * vy - ey * vx)
        return [cx, cy, cz]

    # ----------------------------------------------------------------------- step
    def _errors_step(self, sample: Tensor) -> Tensor:
        """Hidden features of the last layer, flat (G*C_last,) float64, for the newest sample
        (advances the ring buffers). Only called when the model has error TCNs."""
        span = self.first_span
        p = self.t % span
        buf = self.first_buffer
        buf.select(0, p).copy_(sample)  # (copy_ converts the dtype)
        taps = buf.index_select(0, self.tap_index[self.tap_offsets[0] + p]).view(1, -1)
        g = self.groups
        h = gelu_scaled(torch.addmm(self.first_bias_step, taps, self.first_weight_t)).view(g, 1, -1)
        for i in range(len(self.ring_buffers)):
            span = self.spans[i]
            p = self.t % span
            buf = self.ring_buffers[i]
            buf.narrow(1, p, 1).copy_(h)
            taps = buf.index_select(1, self.tap_index[self.tap_offsets[i + 1] + p]).view(g, 1, -1)
            h = gelu_scaled(torch.baddbmm(self.step_biases[i], taps, self.step_weights[i]))
        return h.view(-1).to(torch.float64)

    def _errors_chunk(self, samples: Tensor) -> Tensor:
        """:meth:`_errors_step` for k samples (k, C) at once: (k, G*C_last) float64
        (:func:`ring_convolutions` over this module's ring buffers, which end as if the samples
        had been stepped one by one)."""
        rings = [self.first_buffer.unsqueeze(0)] + self.ring_buffers
        return ring_convolutions(samples, self.t, rings, self.chunk_weights, self.chunk_biases,
                                 [self.first_dilation] + self.hidden_dilations, self.groups)

    @staticmethod
    def _f64_tensor(vals: List[float]) -> Tensor:
        """List of floats -> float64 tensor to ~1e-15 relative. (TorchScript's
        ``torch.tensor(List[float], dtype=float64)`` rounds through float32; the float32
        residual adds back what it lost, leaving a 2^-48 relative error.)"""
        return float64_tensor(vals)

    def _begin_step(self, sample: Tensor, dt: Union[float, Tensor]) -> float:
        """Checks one sample (C,) and its dt *before any state changes* (after an error the module
        goes on as if the sample had not been given, or reset() starts afresh) -> dt as a float."""
        if sample.dim() != 1 or sample.size(0) != self.axes:
            raise ValueError("sample: expected shape (" + str(self.axes) + ",), got " + str(list(sample.shape)))
        dtf = float(dt.item()) if isinstance(dt, Tensor) else float(dt)
        self._check_finite(sample, "sample")
        self._check_step(dtf, self.t == 0)
        return dtf

    def _head_step(self, sample: Tensor, x: Tensor, bias: Tensor, weight: Tensor, matrix: Tensor) -> Tensor:
        """``M y − (W h + b)`` for the newest sample (advances the ring buffers): the calibration
        (Eqs. 12-14) as two fused multiply-adds in float64; y = x the raw sample in float64."""
        if self.groups > 0:
            return torch.addmv(torch.addmv(bias, weight, self._errors_step(sample)), matrix, x, beta=-1.0)
        return torch.addmv(bias, matrix, x, beta=-1.0)

    @torch.jit.export
    def step(self, sample: Tensor, dt: Union[float, Tensor]) -> Tuple[Tensor, Tensor]:
        """sample (C,) raw IMU, dt [s] since the previous sample (unused on the first call after
        reset) -> (quat (4,) w,x,y,z nav_from_body ENU, omega (3,) rad/s), float64."""
        dtf = self._begin_step(sample, dt)
        x = sample.to(torch.float64)
        cal: List[float] = self._head_step(sample, x, self.out_bias, self.out_weight_f64, self.calib_matrix).tolist()
        raw: List[float] = x.tolist()
        gx, gy, gz = cal[0], cal[1], cal[2]
        ox, oy, oz = gx, gy, gz
        first = self.t == 0
        if self.has_ecf:
            c = self._corr(self.q_pre, cal, raw)
            o1x, o1y, o1z = gx + c[0], gy + c[1], gz + c[2]
            ox, oy, oz = o1x, o1y, o1z
            if self.preintegration == "two_pass":
                c2 = self._corr(self.q_pre2, cal, raw)
                ox, oy, oz = gx + c2[0], gy + c2[1], gz + c2[2]
                if not first:
                    self.q_pre2 = self._quat_step(self.q_pre2, o1x, o1y, o1z, dtf)
            if not first:
                if self.preintegration == "raw":
                    self.q_pre = self._quat_step(self.q_pre, raw[0], raw[1], raw[2], dtf)
                else:
                    self.q_pre = self._quat_step(self.q_pre, gx, gy, gz, dtf)
        if not first:
            self.q_att = self._quat_step(self.q_att, ox, oy, oz, dtf)
        self.t += 1
        q = self.q_att
        sign = -1.0 if q[0] < 0.0 else 1.0  # w >= 0 representative, as the batch module
        out = self._f64_tensor([sign * q[0], sign * q[1], sign * q[2], sign * q[3], ox, oy, oz])
        return out[0:4], out[4:7]

    def forward(self, sample: Tensor, dt: Union[float, Tensor]) -> Tuple[Tensor, Tensor]:  # type: ignore[override]
        return self.step(sample, dt)

    @torch.jit.export
    def run(self, imu: Tensor, dt: Union[float, Tensor], q0: Tensor) -> Tuple[Tensor, Tensor]:
        """reset(q0), then step through imu (N, C) -> quat (N, 4), omega (N, 3) (float64)."""
        self._check_imu(imu)
        n = imu.size(0)
        dtv: List[float] = self._dt(dt, n).tolist()
        self.reset(q0)
        quat = torch.empty(n, 4, dtype=torch.float64)
        omega = torch.empty(n, 3, dtype=torch.float64)
        for k in range(n):
            q, w = self.step(imu[k], dtv[k])
            quat[k] = q
            omega[k] = w
        return quat, omega
