"""The open-loop (paper) model restated for the exported modules: BatchNorm folded into the
convolutions (:func:`fuse_model`) and the float64 quaternion scans of the open-loop ECF."""
# No `from __future__ import annotations`: TorchScript reads the class-level attribute
# annotations (List[Tensor], ...) as real types.
from typing import Any, Dict, List, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .. import so3
from ..model.tcn import TCN, CausalConv1d, ConstantError
from .inputs import ExportError


def gelu_scaled(u: Tensor) -> Tensor:
    """``sqrt(2) * GELU(sqrt(2) u) = u (1 + erf(u))``: exact GELU in 2 ops (``F.gelu`` costs ~8 us
    per call on the streaming step's tiny tensors, erf + addcmul ~2 us); the sqrt(2) factors are
    folded into the adjacent layers' weights. The one copy: the streaming modules and the
    stateless step graphs call it."""
    return torch.addcmul(u, u, torch.erf(u))


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
    trust = bool(getattr(cal, "trust", False))
    # with trust, the magnetometer network also reads the accelerometer (Calibration.forward)
    inputs = {"gyro": list(range(axes)) if cal.gyro_input == "all" else [0, 1, 2],
              "acc": [3, 4, 5], "mag": [3, 4, 5, 6, 7, 8] if trust else [6, 7, 8]}
    trust_row = {"acc": 0, "mag": 1}
    nets = {"gyro": cal.gyro_error_net, "acc": cal.acc_error_net, "mag": cal.mag_error_net if axes == 9 else None}
    b_out = torch.zeros(axes, dtype=torch.float64)
    b_trust = torch.zeros(2, dtype=torch.float64)  # logits of the closed loop's acc / mag trust
    tcns: List[Tuple[str, List[Tuple[Tensor, Tensor, int]], Tensor, Tensor]] = []
    for s, net in nets.items():
        if net is None:
            continue
        scale = float(cal.error_scale[s])
        # output rows 0-2: the error term (times error_scale); row 3 (trust): the trust logit
        if isinstance(net, ConstantError):
            bias = net.bias.detach().double()
            b_out[sl[s]] += scale * bias[0:3]
            if bias.numel() > 3:
                b_trust[trust_row[s]] += bias[3]
        elif isinstance(net, TCN):
            layers = _tcn_layers(net, f"calibration.{s}_error_net")
            w_o = net.out.weight.detach().double()[:, :, 0].clone()  # (3 or 4, C_last)
            b_o = net.out.bias.detach().double().clone()
            w_o[0:3] *= scale
            b_o[0:3] *= scale
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
        w_trust = torch.zeros(2, g * c_last, dtype=torch.float64)
        for i, (s, _, w_o, b_o) in enumerate(tcns):
            w_out[sl[s], i * c_last:(i + 1) * c_last] = w_o[0:3]
            b_out[sl[s]] += b_o[0:3]
            if w_o.shape[0] > 3:
                w_trust[trust_row[s], i * c_last:(i + 1) * c_last] = w_o[3]
                b_trust[trust_row[s]] += b_o[3]
        fused["out_weight"] = w_out
        fused["trust_weight"] = w_trust
    fused["out_bias"] = b_out
    fused["trust_bias"] = b_trust
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
def hamilton_table() -> Tensor:
    """(16, 4) float64: ``p ⊗ q = (p ⊗_outer q).reshape(16) @ table`` (row 4 i + j holds the
    sign with which ``p_i q_j`` enters each component of the Hamilton product)."""
    e = torch.eye(4, dtype=torch.float64)
    return so3.quat_mul(e[:, None, :], e[None, :, :]).reshape(16, 4)


def qmul(a: Tensor, b: Tensor, table: Tensor) -> Tensor:
    """Row-wise Hamilton product of (M, 4) quaternions: one outer product + one matmul."""
    return torch.mm((a.unsqueeze(2) * b.unsqueeze(1)).reshape(-1, 16), table)


def _cumprod_hillis_steele(q: Tensor, table: Tensor) -> Tensor:
    """Inclusive prefix product of (N, 4) quaternions in ceil(log2 N) levels (O(N log N) work)."""
    n = q.size(0)
    p = q
    d = 1
    while d < n:
        p = torch.cat([p[:d], qmul(p[:-d], p[d:], table)], 0)
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
    ``table`` = :func:`hamilton_table`."""
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
        acc = qmul(acc, x[j], table)
        steps.append(acc)
    within = torch.stack(steps, 0)  # (block, B, 4) within-block prefixes
    before = _cumprod_hillis_steele(within[-1], table)[:-1]  # (B-1, 4): blocks 0..b-1
    later = qmul(before.unsqueeze(0).expand(block, nb - 1, 4).reshape(-1, 4),
                  within[:, 1:].reshape(-1, 4), table).view(block, nb - 1, 4)
    out = torch.cat([within[:, :1], later], 1).transpose(0, 1).reshape(nb * block, 4)
    return out[:n]


def quat_integrate(q0: Tensor, omega: Tensor, dt: Tensor, table: Tensor) -> Tensor:
    """Eq. 3 with quaternions: ``q_k = q_0 ⊗ exp(ω_1 dt_1) ⊗ ... ⊗ exp(ω_k dt_k)`` (unnormalised
    by at most float64 round-off). q0 (4,), omega (N, 3), dt (N,) -> (N, 4) with entry 0 = q0."""
    inc = so3.quat_exp(omega[1:] * dt[1:, None])
    return quat_cumprod(torch.cat([q0.unsqueeze(0), inc], 0), table)


def rows_up_east(q: Tensor) -> Tuple[Tensor, Tensor]:
    """Rows of C(q) (nav_from_body, (N, 4) unit quaternions) the ECF uses: ``C^T e_up`` (third
    row) and ``C^T e_east`` (first row), each (N, 3)."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    up = torch.stack([2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)], 1)
    east = torch.stack([1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)], 1)
    return up, east


def _unit_rows(v: Tensor) -> Tensor:
    return v / torch.linalg.norm(v, dim=1, keepdim=True).clamp_min(1e-9)


def acc_error_rows(acc: Tensor, up: Tensor) -> Tensor:
    """Eq. 23 (as :func:`tcn_ahrs.model.open_loop.acc_error`): ``unit(ĝ) × (C̃^T e_up)``, (N, 3)."""
    return torch.linalg.cross(_unit_rows(acc), up, dim=1)


def mag_error_rows(mag: Tensor, acc_raw: Tensor, east: Tensor) -> Tensor:
    """Eq. 24 (as :func:`tcn_ahrs.model.open_loop.mag_error`): ``unit(b̂ × g') × (C̃^T e_east)``."""
    return torch.linalg.cross(_unit_rows(torch.linalg.cross(mag, acc_raw, dim=1)), east, dim=1)


# ============================================================ streaming networks over a chunk
def ring_convolutions(samples: Tensor, t0: int, rings: List[Tensor], weights: List[Tensor], biases: List[Tensor],
                      dilations: List[int], groups: int) -> Tensor:
    """The stacked networks over k new samples (k, C) at time t0 from their ring buffers: per
    layer one convolution over the buffer's history (in time order) followed by the chunk's
    inputs; the buffers (layer 0: (1, span, C) raw samples, then (G, span, C_in)) are updated in
    place as if the samples had been stepped one by one. weights (G*C_out, C_in, k) (layer 0:
    (G*C_1, C, k), one group), GELU as ``u (1 + erf(u))`` on scaled pre-activations (see
    :func:`~tcn_ahrs.export.fused.gelu_scaled`). Returns the last features (k, G*C_last) float64."""
    n = samples.size(0)
    h = samples.to(rings[0].dtype).unsqueeze(0)  # (1, n, C) time-major
    for i in range(len(rings)):
        buf = rings[i]
        span = buf.size(1)
        order = torch.remainder(torch.arange(t0 - span + 1, t0, dtype=torch.long), span)
        seq = torch.cat([buf.index_select(1, order), h], 1)  # (G_i, span - 1 + n, C_in)
        buf.index_copy_(1, torch.remainder(torch.arange(t0 + n - span, t0 + n, dtype=torch.long), span), seq[:, -span:])
        u = F.conv1d(seq.transpose(1, 2).reshape(1, -1, seq.size(1)), weights[i], biases[i], dilation=dilations[i],
                     groups=buf.size(0))
        h = torch.addcmul(u, u, torch.erf(u)).view(groups, -1, n).transpose(1, 2)
    return h.transpose(0, 1).reshape(n, -1).to(torch.float64)


def fuse_residual(model: nn.Module) -> Dict[str, Any]:
    """The residual model's two networks (:class:`~tcn_ahrs.model.residual.ResidualCalibration`)
    in :func:`fuse_model`'s layout, so the streaming ring buffers (:class:`StreamingAHRS`,
    :func:`ring_convolutions`) run them: groups = [gyro net, trust net], the fixed physical input
    scale as the normalisation (mean 0, std 1/scale), ``out_weight`` rows 0-2 = the gyro net's
    output *before* its tanh (the caller applies ``gyro_scale · tanh``), ``trust_weight`` rows =
    the acc (and mag) trust logits; no calibration matrix, no ECF."""
    cal = model.calibration
    axes = int(cal.axes)
    nets = [("gyro", cal.gyro_net), ("trust", cal.trust_net)]
    layers = {s: _tcn_layers(net, f"calibration.{s}_net") for s, net in nets}
    arch = [[(tuple(w.shape), d) for w, _, d in layers[s]] for s, _ in nets]
    if arch[0][1:] != arch[1][1:] or arch[0][0][0][0] != arch[1][0][0][0]:
        raise ExportError("residual model: the gyro and trust networks must share channels, kernel_size and dilations")
    c_last = cal.gyro_net.out.weight.shape[1]
    w_out = torch.zeros(axes, 2 * c_last, dtype=torch.float64)
    w_trust = torch.zeros(2, 2 * c_last, dtype=torch.float64)
    b_out = torch.zeros(axes, dtype=torch.float64)
    b_trust = torch.zeros(2, dtype=torch.float64)
    w_out[0:3, :c_last] = cal.gyro_net.out.weight.detach().double()[:, :, 0]
    b_out[0:3] = cal.gyro_net.out.bias.detach().double()
    n_trust = cal.trust_net.out.weight.shape[0]
    w_trust[:n_trust, c_last:] = cal.trust_net.out.weight.detach().double()[:, :, 0]
    b_trust[:n_trust] = cal.trust_net.out.bias.detach().double()
    return {
        "axes": axes, "groups": 2, "sensors": ["gyro", "trust"],
        "first_weight": torch.cat([layers["gyro"][0][0], layers["trust"][0][0]], 0),
        "first_bias": torch.cat([layers["gyro"][0][1], layers["trust"][0][1]], 0),
        "first_dilation": layers["gyro"][0][2], "kernel_size": int(layers["gyro"][0][0].shape[2]),
        "hidden": [(torch.cat([layers["gyro"][i][0], layers["trust"][i][0]], 0),
                    torch.cat([layers["gyro"][i][1], layers["trust"][i][1]], 0), layers["gyro"][i][2])
                   for i in range(1, len(layers["gyro"]))],
        "out_weight": w_out, "trust_weight": w_trust, "out_bias": b_out, "trust_bias": b_trust,
        "calib_matrix": torch.zeros(axes, axes, dtype=torch.float64),
        "input_mean": torch.zeros(axes, dtype=torch.float64),
        "input_std": 1.0 / cal.input_scale.detach().double(),
        "ecf": False, "preintegration": "none", "acc_gain": torch.zeros(3, dtype=torch.float64),
        "mag_gain": torch.zeros(3, dtype=torch.float64), "use_acc": False, "use_mag": False,
    }
