"""Deployment export: self-contained TorchScript modules (batch and streaming) of a trained
:class:`~tcn_ahrs.model.ahrs.LearnedAHRS`.

Contract (also in the README and saved inside every exported file as ``metadata.json`` and as
the string returned by the module's ``metadata()`` method):

* ``python scripts/export.py ckpt=PATH out=FILE.pt [mode=batch|streaming|both]`` writes
  TorchScript that needs only ``torch`` to load and run (no ``tcn_ahrs`` import).
  ``mode=both`` (default) writes the batch module to ``FILE.pt`` and the streaming module to
  ``FILE_streaming.pt``.
* Inputs (the checkpoint's units and frames): raw IMU samples with channels
  gyro x,y,z [rad/s], accelerometer x,y,z [m/s^2, specific force: +9.81 along the body axis
  pointing up at rest] and, for 9-axis models, magnetometer x,y,z [uT]; all in the body
  (sensor) frame. Time step ``dt`` [s] = time since the previous sample. Initial attitude
  ``q0`` = Hamilton quaternion (w, x, y, z), ``nav_from_body``, navigation frame ENU.
* Batch module: ``quat, omega = m(imu (N, C), dt (float or (N,)), q0 (4,))`` ->
  attitude quaternions (N, 4) (w, x, y, z; w >= 0; nav_from_body, ENU; ``quat[0] == q0``)
  and corrected angular rate ω̂ (N, 3) [rad/s, body frame] (paper Eq. 22), float64.
  ``dt[0]`` is not used (the first rate sample does not move the attitude, Eq. 3).
* Streaming module: ``m.reset(q0)``; then per sample ``quat, omega = m.step(sample (C,), dt)``
  -> (4,), (3,) float64; the same numbers as the batch module, sample by sample (the
  ``dt`` of the first call after ``reset`` is not used). ``m.run(imu, dt, q0)`` = reset +
  step over a whole sequence in TorchScript. State: one ring buffer per convolution layer
  (``dilation * (kernel - 1)`` past inputs, zeros after ``reset`` = the batch model's causal
  zero padding), the ECF's pre-integrated attitude(s) C̃ (Eq. 25) and the integrated attitude.
* Input checks (every module): wrong shapes, a NaN/inf reading, or a time step after the first
  that is not finite and > 0 raise ``ValueError`` naming the input and the index; a streaming
  step checks before it changes any state, so after the error the module continues as if that
  sample had not been given (``reset(q0)`` also starts afresh).
* ``m.metadata()`` (and the ``metadata.json`` extra file) is JSON with: axes, channel names,
  variant, model config, the rate the model was trained at (``rate_hz``, null when the
  checkpoint does not record it), units, frames, quaternion order, receptive field, the input
  normalisation (included in the module), the tcn_ahrs version, the checkpoint's sha256.

Numerics: the TCN runs in float32 (``net_dtype``; BatchNorm folded into the convolutions,
dropout off), the calibration matrices, the ECF and the attitude integration in float64
(quaternions, blocked prefix-product scan). The parity bounds (batch vs streaming vs the eager
model; float64 networks vs eager float64) are the tolerances asserted in ``tests/test_export.py``
and ``tests/test_export_closed_loop.py``. ``net_dtype=bfloat16`` (batch module only, opt-in:
``export_checkpoint(..., mode="batch", net_dtype="bfloat16")``) runs the convolutions in bfloat16
(faster on AVX512-BF16 CPUs) and is NOT within those bounds (docs/performance.md).

Exported modules are frozen (:func:`torch.jit.freeze`, public methods kept): flags and
weights become constants. The streaming step folds the input normalisation into the first
layer and computes GELU as ``u (1 + erf(u))`` on sqrt(1/2)-scaled pre-activations (see
:meth:`StreamingAHRS._gelu_scaled`), identical math with fewer TorchScript ops.
"""
# No `from __future__ import annotations`: TorchScript reads the class-level attribute
# annotations (List[Tensor], ...) as real types.
import hashlib
import json
import math
import warnings
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Tuple, Union

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from . import __version__, so3
from .model.tcn import TCN, CausalConv1d, ConstantError

MODES = ("batch", "streaming", "both")
NET_DTYPES = (torch.float32, torch.float64, torch.bfloat16)
_SQRT_HALF = math.sqrt(0.5)
CHANNELS = {6: ["gyro_x", "gyro_y", "gyro_z", "acc_x", "acc_y", "acc_z"],
            9: ["gyro_x", "gyro_y", "gyro_z", "acc_x", "acc_y", "acc_z", "mag_x", "mag_y", "mag_z"]}


class ExportError(ValueError):
    """The model cannot be exported (a structure this exporter does not know)."""


# ============================================================ model -> fused parameters
def _fold_conv_bn(conv: nn.Conv1d, bn: nn.BatchNorm1d) -> Tuple[Tensor, Tensor]:
    """Eval-mode BatchNorm folded into the preceding convolution (float64):
    ``bn(conv(x)) = (W s) * x + (b - mu) s + beta`` with ``s = gamma / sqrt(var + eps)``."""
    w = conv.weight.detach().double()
    b = conv.bias.detach().double() if conv.bias is not None else torch.zeros(w.shape[0], dtype=torch.float64)
    var = bn.running_var.detach().double() if bn.running_var is not None else torch.ones_like(b)
    mean = bn.running_mean.detach().double() if bn.running_mean is not None else torch.zeros_like(b)
    gamma = bn.weight.detach().double() if bn.weight is not None else torch.ones_like(b)
    beta = bn.bias.detach().double() if bn.bias is not None else torch.zeros_like(b)
    s = gamma / torch.sqrt(var + bn.eps)
    return w * s[:, None, None], (b - mean) * s + beta


def _tcn_layers(net: TCN, where: str) -> List[Tuple[Tensor, Tensor, int]]:
    """[(weight (C_out, C_in, k), bias (C_out,), dilation)] of the dilated layers, BN folded."""
    mods = list(net.hidden)
    if len(mods) % 4:
        raise ExportError(f"{where}: expected (conv, BatchNorm, Dropout, GELU) blocks, got {mods}")
    out = []
    for i in range(0, len(mods), 4):
        conv, bn, drop, act = mods[i:i + 4]
        if not (isinstance(conv, CausalConv1d) and isinstance(bn, nn.BatchNorm1d)
                and isinstance(drop, nn.Dropout) and isinstance(act, nn.GELU)):
            raise ExportError(f"{where}: block {i // 4} is {[type(m).__name__ for m in mods[i:i + 4]]}, "
                              "expected [CausalConv1d, BatchNorm1d, Dropout, GELU]")
        if act.approximate != "none":
            raise ExportError(f"{where}: GELU(approximate={act.approximate!r}) not supported")
        c = conv.conv
        if c.stride[0] != 1 or c.groups != 1 or conv.left_pad != c.dilation[0] * (c.kernel_size[0] - 1):
            raise ExportError(f"{where}: block {i // 4}: only stride-1, ungrouped causal convolutions are supported")
        w, b = _fold_conv_bn(c, bn)
        out.append((w, b, int(c.dilation[0])))
    return out


def fuse_model(model: nn.Module) -> Dict[str, Any]:
    """Read a :class:`LearnedAHRS` into the flat parameters the exported modules use.

    The (up to three) error TCNs share their architecture, so they are stacked as G groups:
    the first layer is one dense convolution over the normalised C-channel input (each net's
    weights embedded at the channels it reads, zeros elsewhere), the hidden layers are grouped
    convolutions, and the 1x1 output layers plus ``error_scale`` become one (C, G*C_last)
    matrix mapping to the C-channel error vector ``e`` (constant error terms go into its bias).
    The calibration is then ``x̂ = M y − e`` with ``M = blockdiag(R̂_gyr, R̂_acc, R̂_mag)``
    (Eqs. 12-14).
    """
    cal = model.calibration
    axes = int(cal.axes)
    sl = {"gyro": slice(0, 3), "acc": slice(3, 6), "mag": slice(6, 9)}
    inputs = {"gyro": list(range(axes)) if cal.gyro_input == "all" else [0, 1, 2],
              "acc": [3, 4, 5], "mag": [6, 7, 8]}
    nets = {"gyro": cal.gyro_error_net, "acc": cal.acc_error_net, "mag": cal.mag_error_net if axes == 9 else None}
    b_out = torch.zeros(axes, dtype=torch.float64)
    tcns: List[Tuple[str, List[Tuple[Tensor, Tensor, int]], Tensor, Tensor]] = []
    for s, net in nets.items():
        if net is None:
            continue
        scale = float(cal.error_scale[s])
        if isinstance(net, ConstantError):
            b_out[sl[s]] += scale * net.bias.detach().double()
        elif isinstance(net, TCN):
            layers = _tcn_layers(net, f"calibration.{s}_error_net")
            w_o = net.out.weight.detach().double()[:, :, 0] * scale  # (3, C_last)
            b_o = net.out.bias.detach().double() * scale
            tcns.append((s, layers, w_o, b_o))
        else:
            raise ExportError(f"calibration.{s}_error_net: unsupported module {type(net).__name__}")
    fused: Dict[str, Any] = {"axes": axes, "groups": len(tcns), "sensors": [t[0] for t in tcns]}
    if tcns:
        arch = [[(tuple(w.shape), d) for w, _, d in t[1][1:]] + [(t[1][0][0].shape[0], t[1][0][0].shape[2], t[1][0][2])]
                for t in tcns]
        if any(a != arch[0] for a in arch):
            raise ExportError(f"error TCNs of {fused['sensors']} differ in architecture; they must share "
                              "channels, kernel_size and dilations to be stacked")
        g = len(tcns)
        first = []
        for s, layers, _, _ in tcns:
            w0, _, _ = layers[0]
            full = torch.zeros(w0.shape[0], axes, w0.shape[2], dtype=torch.float64)
            full[:, inputs[s]] = w0
            first.append(full)
        fused["first_weight"] = torch.cat(first, 0)  # (G*C1, C, k)
        fused["first_bias"] = torch.cat([t[1][0][1] for t in tcns], 0)
        fused["first_dilation"] = tcns[0][1][0][2]
        fused["kernel_size"] = int(tcns[0][1][0][0].shape[2])
        fused["hidden"] = []  # [(weight (G*C_out, C_in, k) grouped, bias (G*C_out,), dilation)]
        for li in range(1, len(tcns[0][1])):
            fused["hidden"].append((torch.cat([t[1][li][0] for t in tcns], 0),
                                    torch.cat([t[1][li][1] for t in tcns], 0), tcns[0][1][li][2]))
        c_last = tcns[0][2].shape[1]
        w_out = torch.zeros(axes, g * c_last, dtype=torch.float64)
        for i, (s, _, w_o, b_o) in enumerate(tcns):
            w_out[sl[s], i * c_last:(i + 1) * c_last] = w_o
            b_out[sl[s]] += b_o
        fused["out_weight"] = w_out
    fused["out_bias"] = b_out
    m = torch.zeros(axes, axes, dtype=torch.float64)
    for s, mat in (("gyro", cal.gyro_matrix), ("acc", cal.acc_matrix), ("mag", cal.mag_matrix)):
        if mat is not None and axes >= sl[s].stop:
            m[sl[s], sl[s]] = mat.matrix.detach().double()
    fused["calib_matrix"] = m
    fused["input_mean"] = cal.input_mean.detach().double().clone()
    fused["input_std"] = cal.input_std.detach().double().clone()
    ecf = model.ecf
    fused["ecf"] = ecf is not None
    fused["preintegration"] = ecf.preintegration if ecf is not None else "none"
    fused["acc_gain"] = (ecf.acc_gain.detach().double().clone() if ecf is not None and ecf.acc_gain is not None
                         else torch.zeros(3, dtype=torch.float64))
    fused["mag_gain"] = (ecf.mag_gain.detach().double().clone() if ecf is not None and ecf.mag_gain is not None
                         and axes == 9 else torch.zeros(3, dtype=torch.float64))
    fused["use_acc"] = bool(ecf is not None and ecf.acc_gain is not None)
    fused["use_mag"] = bool(ecf is not None and ecf.mag_gain is not None and axes == 9)
    return fused


# ============================================================ float64 quaternion scans
def _hamilton_table() -> Tensor:
    """(16, 4) float64: ``p ⊗ q = (p ⊗_outer q).reshape(16) @ table`` (row 4 i + j holds the
    sign with which ``p_i q_j`` enters each component of the Hamilton product)."""
    e = torch.eye(4, dtype=torch.float64)
    return so3.quat_mul(e[:, None, :], e[None, :, :]).reshape(16, 4)


def _qmul(a: Tensor, b: Tensor, table: Tensor) -> Tensor:
    """Row-wise Hamilton product of (M, 4) quaternions: one outer product + one matmul."""
    return torch.mm((a.unsqueeze(2) * b.unsqueeze(1)).reshape(-1, 16), table)


def _cumprod_hillis_steele(q: Tensor, table: Tensor) -> Tensor:
    """Inclusive prefix product of (N, 4) quaternions in ceil(log2 N) levels (O(N log N) work)."""
    n = q.size(0)
    p = q
    d = 1
    while d < n:
        p = torch.cat([p[:d], _qmul(p[:-d], p[d:], table)], 0)
        d *= 2
    return p


def quat_cumprod(q: Tensor, table: Tensor, block: int = 32) -> Tensor:
    """Inclusive cumulative Hamilton product ``P_k = q_0 ⊗ ... ⊗ q_k`` of (N, 4) float64
    quaternions (not renormalised: float64 round-off only; the caller normalises once).

    Blocked scan, O(N) work: the sequence is cut into B blocks of ``block`` samples; (1) the
    within-block prefixes of all blocks advance together, ``block - 1`` sequential products on
    (B, 4) rows; (2) the block totals are scanned (Hillis-Steele, log2 B levels); (3) each block
    is multiplied on the left by the product of all earlier blocks. A plain O(N log N)
    Hillis-Steele scan over 6000 samples costs ~13 levels x N products, 3x3 matrices
    (:func:`so3.cumprod_matrix`) ~4x more again; this is ~3 N products.
    ``table`` = :func:`_hamilton_table`."""
    n = q.size(0)
    if n <= 2 * block:
        return _cumprod_hillis_steele(q, table)
    nb = (n + block - 1) // block
    pad = nb * block - n
    if pad > 0:  # identity quaternions at the end change no prefix
        ident = torch.zeros(pad, 4, dtype=q.dtype, device=q.device)
        ident[:, 0] = 1.0
        q = torch.cat([q, ident], 0)
    x = q.view(nb, block, 4).transpose(0, 1).contiguous()  # (block, B, 4): step j of every block
    acc = x[0]
    steps = [acc]
    for j in range(1, block):
        acc = _qmul(acc, x[j], table)
        steps.append(acc)
    within = torch.stack(steps, 0)  # (block, B, 4) within-block prefixes
    before = _cumprod_hillis_steele(within[-1], table)[:-1]  # (B-1, 4): blocks 0..b-1
    later = _qmul(before.unsqueeze(0).expand(block, nb - 1, 4).reshape(-1, 4),
                  within[:, 1:].reshape(-1, 4), table).view(block, nb - 1, 4)
    out = torch.cat([within[:, :1], later], 1).transpose(0, 1).reshape(nb * block, 4)
    return out[:n]


def quat_integrate(q0: Tensor, omega: Tensor, dt: Tensor, table: Tensor) -> Tensor:
    """Eq. 3 with quaternions: ``q_k = q_0 ⊗ exp(ω_1 dt_1) ⊗ ... ⊗ exp(ω_k dt_k)`` (unnormalised
    by at most float64 round-off). q0 (4,), omega (N, 3), dt (N,) -> (N, 4) with entry 0 = q0."""
    inc = so3.quat_exp(omega[1:] * dt[1:, None])
    return quat_cumprod(torch.cat([q0.unsqueeze(0), inc], 0), table)


def _rows_up_east(q: Tensor) -> Tuple[Tensor, Tensor]:
    """Rows of C(q) (nav_from_body, (N, 4) unit quaternions) the ECF uses: ``C^T e_up`` (third
    row) and ``C^T e_east`` (first row), each (N, 3)."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    up = torch.stack([2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)], 1)
    east = torch.stack([1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)], 1)
    return up, east


def _unit_rows(v: Tensor) -> Tensor:
    return v / torch.linalg.norm(v, dim=1, keepdim=True).clamp_min(1e-9)


def acc_error_rows(acc: Tensor, up: Tensor) -> Tensor:
    """Eq. 23 (as :func:`tcn_ahrs.model.ecf.acc_error`): ``unit(ĝ) × (C̃^T e_up)``, (N, 3)."""
    return torch.linalg.cross(_unit_rows(acc), up, dim=1)


def mag_error_rows(mag: Tensor, acc_raw: Tensor, east: Tensor) -> Tensor:
    """Eq. 24 (as :func:`tcn_ahrs.model.ecf.mag_error`): ``unit(b̂ × g') × (C̃^T e_east)``."""
    return torch.linalg.cross(_unit_rows(torch.linalg.cross(mag, acc_raw, dim=1)), east, dim=1)


# ===================================================================== batch module
class _Inputs(nn.Module):
    """Input checks shared by every exported module (``self.axes`` set by the subclass)."""

    def _check_imu(self, imu: Tensor):
        if imu.dim() != 2 or imu.size(1) != self.axes:
            raise ValueError("imu: expected shape (N, " + str(self.axes) + ") [gyro rad/s, acc m/s^2"
                             + (", mag uT" if self.axes == 9 else "") + "], got " + str(list(imu.shape)))
        if imu.size(0) < 1:
            raise ValueError("imu: expected at least one sample")
        self._check_finite(imu, "imu")

    def _check_finite(self, x: Tensor, what: str):
        """Raise on NaN/inf, naming the first bad entry (one NaN would otherwise spread through
        the networks' receptive field and the filter state into every later output)."""
        bad = torch.logical_not(torch.isfinite(x))
        if bool(bad.any()):
            where: List[int] = torch.nonzero(bad)[0].tolist()
            raise ValueError(what + ": non-finite value at index " + str(where)
                             + " (expected finite readings: drop or interpolate that sample)")

    def _check_step(self, dt: float, first: bool):
        """dt of a step after the first must be finite and > 0 s (the first is not used)."""
        if not first and not (dt > 0.0 and math.isfinite(dt)):
            raise ValueError("dt: expected a finite time step > 0 s since the previous sample, got "
                             + str(dt))

    def _q0(self, q0: Tensor) -> Tensor:
        if q0.numel() != 4:
            raise ValueError("q0: expected 4 values (w, x, y, z), got shape " + str(list(q0.shape)))
        q = q0.reshape(4).to(torch.float64)
        n = float(torch.linalg.norm(q))
        if not (n > 0.0 and math.isfinite(n)):
            raise ValueError("q0: expected a non-zero finite quaternion (w, x, y, z)")
        return q / n

    def _dt(self, dt: Union[float, Tensor], n: int, dtype: torch.dtype = torch.float64) -> Tensor:
        if isinstance(dt, Tensor):
            d = dt.to(dtype)
            if d.dim() == 0:
                d = d.expand(n)
            elif d.dim() != 1 or d.size(0) != n:
                raise ValueError("dt: expected a float or shape (" + str(n) + ",), got " + str(list(d.shape)))
        else:
            d = torch.full([n], float(dt), dtype=dtype)
        # dt[0] is not used (Eq. 3); every later step must be a finite positive time
        later = d[1:]
        bad = torch.logical_not(torch.isfinite(later) & (later > 0))
        if bool(bad.any()):
            k = int(torch.nonzero(bad)[0, 0]) + 1
            raise ValueError("dt: expected finite time steps > 0 s after sample 0, got " + str(float(d[k]))
                             + " at index " + str(k))
        return d


class BatchAHRS(_Inputs):
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
        self.register_buffer("hamilton", _hamilton_table())
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
        up, east = _rows_up_east(q)
        corr = torch.zeros_like(acc)
        if self.use_acc:
            corr = corr + self.acc_gain * acc_error_rows(acc, up)
        if self.use_mag:
            corr = corr + self.mag_gain * mag_error_rows(mag, acc_raw, east)
        return corr

    def _previous(self, q0: Tensor, omega: Tensor, dt: Tensor) -> Tensor:
        """Pre-integrated attitude C̃_{k-1} (Eq. 25) for every sample k as (N, 4) quaternions
        (entry 0 = q0), as :func:`tcn_ahrs.model.ecf.previous_attitude`."""
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

    hidden_weights: List[Tensor]  # (TorchScript reads only this class's own annotations)
    hidden_biases: List[Tensor]
    hidden_dilations: List[int]
    metadata_json: str
    ring_buffers: List[Tensor]
    spans: List[int]
    tap_index: List[Tensor]
    tap_offsets: List[int]
    acc_gain_list: List[float]
    mag_gain_list: List[float]
    step_weights: List[Tensor]
    step_biases: List[Tensor]
    q_pre: List[float]
    q_pre2: List[float]
    q_att: List[float]

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
            # GELU as 2 ops (see _gelu_scaled): outputs scaled by 1/sqrt(2), inputs by the
            # same factor again (the previous layer emits sqrt(2) * GELU), in float64
            w_f, b_f = fused_hidden_f64[len(self.spans) - 1]
            self.step_weights.append((w_f.reshape(g, c_out, c_in, k).permute(0, 3, 2, 1).reshape(g, k * c_in, c_out) * 0.5)
                                     .to(net_dtype).contiguous())
            self.step_biases.append((b_f.reshape(g, 1, c_out) * _SQRT_HALF).to(net_dtype).contiguous())
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
        if self.groups > 0:
            # raw-sample buffer: the mean normalises to the batch model's zero padding
            self.first_buffer.copy_(self.input_mean.expand_as(self.first_buffer))
        for buf in self.ring_buffers:
            buf.zero_()

    # ---------------------------------------------------------- scalar SO(3) helpers
    @staticmethod
    def _quat_step(q: List[float], wx: float, wy: float, wz: float, dt: float) -> List[float]:
        """``q ⊗ exp(ω dt)``, renormalised (same Taylor threshold as :func:`so3.quat_exp`)."""
        px, py, pz = wx * dt, wy * dt, wz * dt
        t2 = px * px + py * py + pz * pz
        if t2 < 1e-6:
            hs = 0.5 - t2 / 48.0 + t2 * t2 / 3840.0
            ew = 1.0 - t2 / 8.0 + t2 * t2 / 384.0
        else:
            th = math.sqrt(t2)
            hs = math.sin(0.5 * th) / th
            ew = math.cos(0.5 * th)
        ex, ey, ez = hs * px, hs * py, hs * pz
        w, x, y, z = q[0], q[1], q[2], q[3]
        rw = w * ew - x * ex - y * ey - z * ez
        rx = w * ex + x * ew + y * ez - z * ey
        ry = w * ey - x * ez + y * ew + z * ex
        rz = w * ez + x * ey - y * ex + z * ew
        n = math.sqrt(rw * rw + rx * rx + ry * ry + rz * rz)
        return [rw / n, rx / n, ry / n, rz / n]

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
    @staticmethod
    def _gelu_scaled(u: Tensor) -> Tensor:
        """``sqrt(2) * GELU(sqrt(2) u) = u (1 + erf(u))``: exact GELU in 2 ops (``F.gelu`` costs
        ~8 us per call on these tiny tensors, erf + addcmul ~2 us); the sqrt(2) factors are
        folded into the adjacent layers' weights."""
        return torch.addcmul(u, u, torch.erf(u))

    def _errors_step(self, sample: Tensor) -> Tensor:
        """Hidden features of the last layer, flat (G*C_last,) float64, for the newest sample
        (advances the ring buffers). Only called when the model has error TCNs."""
        span = self.first_span
        p = self.t % span
        buf = self.first_buffer
        buf.select(0, p).copy_(sample)  # (copy_ converts the dtype)
        taps = buf.index_select(0, self.tap_index[self.tap_offsets[0] + p]).view(1, -1)
        g = self.groups
        h = self._gelu_scaled(torch.addmm(self.first_bias_step, taps, self.first_weight_t)).view(g, 1, -1)
        for i in range(len(self.ring_buffers)):
            span = self.spans[i]
            p = self.t % span
            buf = self.ring_buffers[i]
            buf.narrow(1, p, 1).copy_(h)
            taps = buf.index_select(1, self.tap_index[self.tap_offsets[i + 1] + p]).view(g, 1, -1)
            h = self._gelu_scaled(torch.baddbmm(self.step_biases[i], taps, self.step_weights[i]))
        return h.view(-1).to(torch.float64)

    @staticmethod
    def _f64_tensor(vals: List[float]) -> Tensor:
        """List of floats -> float64 tensor to ~1e-15 relative. (TorchScript's
        ``torch.tensor(List[float], dtype=float64)`` rounds through float32; the float32
        residual adds back what it lost, leaving a 2^-48 relative error.)"""
        hi = torch.tensor(vals, dtype=torch.float64)
        hl: List[float] = hi.tolist()
        return hi + torch.tensor([v - h for v, h in zip(vals, hl)], dtype=torch.float64)

    @torch.jit.export
    def step(self, sample: Tensor, dt: Union[float, Tensor]) -> Tuple[Tensor, Tensor]:
        """sample (C,) raw IMU, dt [s] since the previous sample (unused on the first call after
        reset) -> (quat (4,) w,x,y,z nav_from_body ENU, omega (3,) rad/s), float64."""
        if sample.dim() != 1 or sample.size(0) != self.axes:
            raise ValueError("sample: expected shape (" + str(self.axes) + ",), got " + str(list(sample.shape)))
        dtf = float(dt.item()) if isinstance(dt, Tensor) else float(dt)
        # checked before any state changes: after an error the module goes on as if the sample
        # had not been given (or reset() starts afresh)
        self._check_finite(sample, "sample")
        self._check_step(dtf, self.t == 0)
        x = sample.to(torch.float64)
        if self.groups > 0:
            # M y − (W_o h + b_o) (Eqs. 12-14): two fused multiply-adds in float64
            cal_t = torch.addmv(torch.addmv(self.out_bias, self.out_weight_f64, self._errors_step(sample)),
                                self.calib_matrix, x, beta=-1.0)
        else:
            cal_t = torch.addmv(self.out_bias, self.calib_matrix, x, beta=-1.0)
        cal: List[float] = cal_t.tolist()
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


# ======================================================================= export API
# ============================================================ closed loop (default model)
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


def file_sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def build_metadata(model: nn.Module, mode: str, meta: Optional[Mapping[str, Any]] = None,
                   net_dtype: torch.dtype = torch.float32) -> Dict[str, Any]:
    """The exported file's self-description (plain JSON types). ``meta`` adds or overrides
    entries (``rate_hz``, ``checkpoint``, ``checkpoint_sha256``, ``model_config``, ``data``)."""
    axes = int(model.axes)
    ecf = model.ecf
    md: Dict[str, Any] = {
        "format": "tcn-ahrs TorchScript export",
        "mode": mode,
        "tcn_ahrs_version": __version__,
        "torch_version": torch.__version__,
        "variant": str(getattr(model, "variant", "")),
        "axes": axes,
        "channels": CHANNELS[axes],
        "rate_hz": None,
        "receptive_field": int(model.receptive_field),
        "preintegration": ecf.preintegration if ecf is not None else "none",
        "ecf": ecf is not None,
        "loop": str(getattr(model, "loop", "open")),
        "units": {"gyro": "rad/s", "acc": "m/s^2 (specific force, +9.81 along the up axis at rest)",
                  "mag": "uT", "dt": "s", "omega": "rad/s"},
        "frames": {"imu": "body (sensor) frame", "attitude": "nav_from_body", "navigation": "ENU"},
        "quaternion_order": "wxyz",
        "quaternion_convention": "Hamilton, scalar first, w >= 0",
        "input_normalisation": {
            "included": True,
            "mean": [float(v) for v in model.calibration.input_mean],
            "std": [float(v) for v in model.calibration.input_std]},
        "dtype": {"network": str(net_dtype).replace("torch.", ""), "calibration_ecf_integration": "float64"},
        "api": ({"forward": "quat (N,4), omega (N,3) = m(imu (N,C), dt float|(N,), q0 (4,))"} if mode == "batch" else
                {"reset": "m.reset(q0 (4,))",
                 "step": "quat (4,), omega (3,) = m.step(sample (C,), dt float)  (dt unused on the first call)",
                 "run": "quat (N,4), omega (N,3) = m.run(imu (N,C), dt float|(N,), q0 (4,))"}),
        "checkpoint": None,
        "checkpoint_sha256": None,
    }
    md.update(dict(meta or {}))
    return md


def _script(module: nn.Module, freeze: bool = True):
    """TorchScript ``module`` (eval mode). ``freeze``: :func:`torch.jit.freeze` it, keeping the
    public methods: attributes that are never mutated (flags, weights, layer lists) become
    constants, dead branches go, and the per-sample ``step`` runs ~8% faster."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # torch.jit.script is deprecated in 2.13
        scripted = torch.jit.script(module.eval())
        if not freeze:
            return scripted
        keep = [n for n in ("metadata", "errors", "corrected_rate", "reset", "step", "run") if scripted._c._has_method(n)]
        return torch.jit.freeze(scripted, preserved_attrs=keep)


def _export(cls, model: nn.Module, path, meta, net_dtype: torch.dtype, mode: str):
    model = model.eval()
    md = build_metadata(model, mode, meta, net_dtype)
    if getattr(model, "closed", None) is not None:
        if net_dtype != torch.float32:
            raise ExportError("the closed-loop export runs its networks in float32 (net_dtype=float32)")
        cls = ClosedLoopStreaming if mode == "streaming" else ClosedLoopBatch
        module = cls(model, md).eval()
    else:
        module = cls(fuse_model(model), md, net_dtype).eval()
    scripted = _script(module)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    torch.jit.save(scripted, str(tmp), _extra_files={"metadata.json": scripted.metadata()})
    tmp.replace(path)
    return scripted


def export_batch(model: nn.Module, path, meta: Optional[Mapping[str, Any]] = None,
                 net_dtype: torch.dtype = torch.float32):
    """Script ``model`` (a :class:`LearnedAHRS`, eval mode) as a :class:`BatchAHRS` and save it
    to ``path`` (with ``metadata.json``). Returns the scripted module."""
    return _export(BatchAHRS, model, path, meta, net_dtype, "batch")


def export_streaming(model: nn.Module, path, meta: Optional[Mapping[str, Any]] = None,
                     net_dtype: torch.dtype = torch.float32):
    """Script ``model`` as a :class:`StreamingAHRS` and save it to ``path``. Returns the module."""
    return _export(StreamingAHRS, model, path, meta, net_dtype, "streaming")


def streaming_path(out) -> Path:
    """Where ``mode=both`` writes the streaming module: ``FILE.pt`` -> ``FILE_streaming.pt``."""
    out = Path(out)
    return out.with_name(f"{out.stem}_streaming{out.suffix or '.pt'}")


def export_checkpoint(ckpt_path, out_path, mode: str = "both", rate_hz: Optional[float] = None,
                      net_dtype: Union[str, torch.dtype] = "float32") -> Dict[str, str]:
    """Load a checkpoint (``weights_only=True``, :func:`tcn_ahrs.checkpoint.model_from_checkpoint`)
    and export it. Returns {"batch": path, "streaming": path} (the ones written).

    Raises :class:`tcn_ahrs.checkpoint.CheckpointError` for a missing, corrupt or foreign file."""
    from .checkpoint import checkpoint_meta, load_checkpoint, model_from_checkpoint

    if mode not in MODES:
        raise ValueError(f"export mode {mode!r}: expected one of {MODES}")
    if isinstance(net_dtype, str):
        if net_dtype not in ("float32", "float64", "bfloat16"):
            raise ValueError(f"net_dtype {net_dtype!r}: expected 'float32', 'float64' or 'bfloat16'")
        net_dtype = getattr(torch, net_dtype)
    if net_dtype == torch.bfloat16 and mode != "batch":
        raise ValueError(f"net_dtype bfloat16 is for mode=batch only (got mode={mode})")
    model = model_from_checkpoint(ckpt_path)
    ck_meta = checkpoint_meta(load_checkpoint(ckpt_path), ckpt_path)
    rate = rate_hz if rate_hz is not None else ck_meta.get("rate_hz", (ck_meta.get("layout") or {}).get("rate_hz"))
    if rate is None:
        warnings.warn(f"{ckpt_path}: the checkpoint does not record the rate the model was trained at; "
                      "metadata rate_hz = null (pass rate=HZ to record it)")
    meta = {"rate_hz": None if rate is None else float(rate), "checkpoint": Path(ckpt_path).name,
            "checkpoint_sha256": file_sha256(ckpt_path), "model_config": ck_meta.get("model"),
            "data": ck_meta.get("data")}
    written: Dict[str, str] = {}
    if mode in ("batch", "both"):
        export_batch(model, out_path, meta, net_dtype)
        written["batch"] = str(out_path)
    if mode in ("streaming", "both"):
        sp = Path(out_path) if mode == "streaming" else streaming_path(out_path)
        export_streaming(model, sp, meta, net_dtype)
        written["streaming"] = str(sp)
    return written


def read_metadata(path) -> Dict[str, Any]:
    """The ``metadata.json`` of an exported file (only torch needed)."""
    extra = {"metadata.json": ""}
    torch.jit.load(str(path), _extra_files=extra)
    return json.loads(extra["metadata.json"])
