"""Learned IMU calibration (paper Sec. 3.1-3.2, Eqs. 12-15, 20-21).

For each sensor s in {gyro, acc, mag}:  ``x̂_s = R̂_s y_s − e_s``  where ``R̂_s`` is a
trainable 3x3 matrix (scale factor + misalignment, initialised to the identity) and ``e_s``
an error term regressed by a causal TCN:

* gyro error  ω̃  (bias, Eq. 15) from all available sensors (6 or 9 inputs) — or from the
  gyro only (``gyro_input: gyro``, the paper's Fig. 10 ablation);
* acc error   ã   (external acceleration, Eq. 20) from the accelerometer;
* mag error   m̃   (magnetic disturbance, Eq. 21) from the magnetometer.

An error network can also be ``constant`` (a learned bias vector: the paper's "Calibrated IMU"
with the network input zeroed) or ``none`` (no error term).

Inputs are normalised with per-channel mean/std of the training set, kept as buffers so they
are saved in (and restored from) the checkpoint. All frames are the body frame; units rad/s,
m/s^2, uT. Shapes: imu (B, N, C) with C = 6 (gyro, acc) or 9 (gyro, acc, mag).
"""
from __future__ import annotations

from typing import Dict, Optional

import torch
from torch import Tensor, nn

from ..config import defaults
from ..config.model import ErrorScaleConfig
from .tcn import TCN, ConstantError

NET_KINDS = ("tcn", "constant", "none")


class SensorMatrix(nn.Module):
    """``R̂ = I + Δ`` with Δ trainable and initialised to zero (so weight decay pulls R̂ toward I,
    not toward the zero matrix)."""

    def __init__(self):
        super().__init__()
        self.delta = nn.Parameter(torch.zeros(3, 3))

    @property
    def matrix(self) -> Tensor:
        return torch.eye(3, dtype=self.delta.dtype, device=self.delta.device) + self.delta

    def forward(self, y: Tensor) -> Tensor:  # (B, N, 3) -> (B, N, 3):  R̂ y
        return y @ self.matrix.transpose(0, 1)


def _error_net(kind: str, in_channels: int, tcn_kwargs: dict, extra: int = 0) -> Optional[nn.Module]:
    """The error network of ``kind``: one of :data:`NET_KINDS`, or a network of one's own named
    by its import path (``gyro_net: my_pkg.my_nets.MyNet`` in a ``conf/model/<variant>.yaml``),
    built as ``MyNet(in_channels, out_channels, **model.tcn)``: a module mapping (B, N, in) to
    (B, N, out) causally, with an int ``receptive_field``."""
    if kind == "tcn":
        return TCN(in_channels, 3 + extra, **tcn_kwargs)
    if kind == "constant":
        return ConstantError(3 + extra)
    if kind == "none":
        return None
    if "." in kind:
        import importlib

        mod, _, cls = kind.rpartition(".")
        try:
            factory = getattr(importlib.import_module(mod), cls)
        except (ImportError, AttributeError) as e:
            raise ValueError(f"error network kind {kind!r}: cannot import it ({e})") from None
        return factory(in_channels, 3 + extra, **tcn_kwargs)
    raise ValueError(f"error network kind {kind!r}: expected one of {NET_KINDS} or an importable "
                     "'module.Class'")


class Calibration(nn.Module):
    __jit_unused_properties__ = ["receptive_field"]

    """Calibration of the raw IMU readings (Eqs. 12-14) with learned error terms.

    Args:
        axes:        6 (gyro, acc) or 9 (gyro, acc, mag).
        gyro_net, acc_net, mag_net: "tcn" | "constant" | "none" | an importable "module.Class" (:func:`_error_net`).
        gyro_input:  "all" (Eq. 15: every sensor feeds the gyro network) or "gyro".
        error_scale: multiplies each network's output (a dimensionless O(1) output maps to a
                     physical error of this size: rad/s, m/s^2, uT); keeps the first Adam steps
                     (lr 0.01) from producing errors far beyond the sensors' real ones.
        tcn:         keyword arguments of :class:`~tcn_ahrs.model.tcn.TCN`.
    """

    def __init__(self, axes: int = 9, gyro_net: str = "tcn", acc_net: str = "tcn",
                 mag_net: str = "tcn", gyro_input: str = "all",
                 error_scale: Optional[Dict[str, float]] = None, tcn: Optional[dict] = None,
                 trust: bool = False):
        super().__init__()
        if axes not in (6, 9):
            raise ValueError(f"axes: expected 6 or 9, got {axes!r}")
        if gyro_input not in ("all", "gyro"):
            raise ValueError(f"gyro_input: expected 'all' or 'gyro', got {gyro_input!r}")
        self.axes = axes
        self.gyro_input = gyro_input
        tcn_kwargs = dict(tcn or {})
        scale = defaults(ErrorScaleConfig)  # tcn_ahrs/config/model.py
        scale.update(error_scale or {})
        self.error_scale = scale
        self.register_buffer("input_mean", torch.zeros(axes))
        self.register_buffer("input_std", torch.ones(axes))
        self.gyro_matrix = SensorMatrix()
        self.acc_matrix = SensorMatrix()
        self.mag_matrix = SensorMatrix() if axes == 9 else None
        # trust: the accelerometer and magnetometer networks output a fourth channel, the logit of
        # the closed-loop filter's per-sample trust in that sensor; the magnetometer network then
        # also sees the accelerometer (a disturbed field shows in its norm *and* its dip angle).
        self.trust = bool(trust)
        extra = 1 if self.trust else 0
        self.gyro_error_net = _error_net(gyro_net, axes if gyro_input == "all" else 3, tcn_kwargs)
        self.acc_error_net = _error_net(acc_net, 3, tcn_kwargs, extra)
        self.mag_error_net = (_error_net(mag_net, 6 if self.trust else 3, tcn_kwargs, extra)
                              if axes == 9 else None)

    @torch.no_grad()
    def set_input_stats(self, mean: Tensor, std: Tensor) -> None:
        """Store the training set's per-channel mean/std (C,) used to normalise network inputs."""
        mean = torch.as_tensor(mean, dtype=self.input_mean.dtype).reshape(-1)
        std = torch.as_tensor(std, dtype=self.input_std.dtype).reshape(-1)
        if mean.numel() != self.axes or std.numel() != self.axes:
            raise ValueError(f"input statistics: expected {self.axes} channels, got {mean.numel()}/{std.numel()}")
        self.input_mean.copy_(mean)
        self.input_std.copy_(std.clamp_min(1e-6))

    @torch.no_grad()
    def set_gyro_bias(self, bias: Tensor) -> None:
        """Start the gyro error term at a constant ``bias`` (3,) rad/s (the output layer's bias;
        its weights stay as they are): ω̂_gyr = R̂ y − bias for an untrained network."""
        net = self.gyro_error_net
        if net is None:
            return
        b = torch.as_tensor(bias, dtype=torch.float32).reshape(3) / float(self.error_scale["gyro"])
        if isinstance(net, ConstantError):
            net.bias[0:3] = b
        elif isinstance(getattr(net, "out", None), nn.Module):  # TCN (and networks of one's own with an output layer)
            net.out.bias[0:3] = b

    @property
    def receptive_field(self) -> int:
        nets = [n for n in (self.gyro_error_net, self.acc_error_net, self.mag_error_net) if n is not None]
        return max([int(n.receptive_field) for n in nets] + [1])

    def forward(self, imu: Tensor) -> Dict[str, Tensor]:
        """imu (B, N, C) raw readings -> dict of (B, N, 3):

        ``gyro`` ω̂_gyr (Eq. 12), ``acc`` ĝ (Eq. 13), ``mag`` b̂ (Eq. 14, 9-axis only), the
        error terms ``gyro_error`` ω̃, ``acc_error`` ã, ``mag_error`` m̃, and (B, N) trust logits
        ``acc_trust_logit``, ``mag_trust_logit`` (zero unless ``trust``).
        """
        if imu.shape[-1] != self.axes:
            raise ValueError("Calibration: expected " + str(self.axes) + " IMU channels, got " + str(imu.shape[-1]))
        # written out per network (no helper taking a module): this forward is scripted as is
        # by the TorchScript export
        z = (imu - self.input_mean) / self.input_std
        zero3 = torch.zeros_like(imu[..., 0:3])
        zero1 = torch.zeros_like(imu[..., 0])
        out: Dict[str, Tensor] = {}
        gyro_error = zero3
        if self.gyro_error_net is not None:
            gyro_error = self.error_scale["gyro"] * self.gyro_error_net(z if self.gyro_input == "all" else z[..., 0:3])
        acc_error, acc_logit = zero3, zero1
        if self.acc_error_net is not None:
            y = self.acc_error_net(z[..., 3:6])
            acc_error = self.error_scale["acc"] * y[..., 0:3]
            if self.trust:
                acc_logit = y[..., 3]
        out["gyro_error"] = gyro_error
        out["acc_error"] = acc_error
        out["acc_trust_logit"] = acc_logit
        out["gyro"] = self.gyro_matrix(imu[..., 0:3]) - gyro_error
        out["acc"] = self.acc_matrix(imu[..., 3:6]) - acc_error
        mag_matrix = self.mag_matrix
        if mag_matrix is not None:
            mag_error, mag_logit = zero3, zero1
            if self.mag_error_net is not None:
                y = self.mag_error_net(z[..., 3:9] if self.trust else z[..., 6:9])
                mag_error = self.error_scale["mag"] * y[..., 0:3]
                if self.trust:
                    mag_logit = y[..., 3]
            out["mag_error"] = mag_error
            out["mag_trust_logit"] = mag_logit
            out["mag"] = mag_matrix(imu[..., 6:9]) - mag_error
        return out
