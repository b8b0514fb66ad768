"""Learned residuals on the VQF-grade backbone (``model.loop: backbone``).

The backbone (:mod:`tcn_ahrs.kernels.backbone`) does the filtering; the networks only nudge it,
each nudge bounded and zero in the untrained model, so that the untrained model *is* the
backbone (tests/test_residual.py)::

    ω_in   = ω − clip(s_gyro · tanh(g_θ(x)), ±c_gyro)    gyro residual, |·| ≤ c_gyro per axis (rad/s)
    τ_acc  = c_acc · (1 + w (min(t_max, 2σ(z_acc(x))) − 1)),  τ_mag likewise,  τ_bias = c_bias
    q      = backbone(ω_in, a, m, dt; τ_acc, τ_mag, τ_bias)

``x`` is the raw IMU in fixed physical scales (rad/s, g, 50 µT): no statistics of one device's
training set, so a new device is read the same way. ``g_θ`` and ``z`` are two causal TCNs whose
output layers start at zero (ω_in = ω, τ = 1). ``c_gyro`` (applied in eval mode only; the network
learns within ``s_gyro``), ``w`` and the trust scales ``c`` are the recipe's inference knobs
(``conf/model/residual.yaml``: c_gyro 0 and w 0.5, chosen on BROAD's development folds; c = 1).
``c = 0`` everywhere turns the backbone into strapdown integration of the corrected gyro.

Training needs no gradient through the filter (the filter's tensor reading costs ~9 ms per
sample on a CPU): the gyro residual learns the ground-truth rotation increments (Eq. 28's loss,
as DIG), the trust logits learn whether each sample's accelerometer direction and magnetometer
heading agree with the ground truth (:func:`tcn_ahrs.losses.trust_labels`), so both learn physical
quantities, not a device's gains.
"""
from __future__ import annotations

from typing import Dict, Mapping, Optional

import numpy as np
import torch
from torch import Tensor, nn

from ..conventions import GRAVITY
from ..filters import backbone as bb
from ..config import keys
from ..config.model import ResidualConfig
from .tcn import TCN

FIELD_SCALE = 50.0  # µT: the Earth's field is 22–67 µT
RESIDUAL_KEYS = keys(ResidualConfig)  # model.residual's keys; meaning and defaults: tcn_ahrs/config/model.py
_R = ResidualConfig()


class ResidualCalibration(nn.Module):
    """The two networks: gyro residual (3 channels) and trust logits (acc, and mag for 9 axes).

    Same output keys as :class:`~tcn_ahrs.model.calibration.Calibration` (``gyro``, ``acc``,
    ``mag``, ``gyro_error``, ``acc_error``, ``mag_error``, ``acc_trust_logit``,
    ``mag_trust_logit``), so the training and evaluation code reads either. imu (B, N, C)."""

    def __init__(self, axes: int, tcn: Optional[Mapping] = None, gyro_scale: float = _R.gyro_scale,
                 gyro_clip: float = _R.gyro_clip):
        super().__init__()
        self.gyro_clip = float(gyro_clip)
        if axes not in (6, 9):
            raise ValueError(f"axes: expected 6 or 9, got {axes!r}")
        self.axes = int(axes)
        self.gyro_scale = float(gyro_scale)
        kw = dict(tcn or {})
        self.gyro_net = TCN(self.axes, 3, **kw)
        self.trust_net = TCN(self.axes, 2 if self.axes == 9 else 1, **kw)
        scale = [1.0, 1.0, 1.0] + [1.0 / GRAVITY] * 3 + ([1.0 / FIELD_SCALE] * 3 if self.axes == 9 else [])
        self.register_buffer("input_scale", torch.tensor(scale))

    @property
    def receptive_field(self) -> int:
        return max(int(self.gyro_net.receptive_field), int(self.trust_net.receptive_field))

    def set_input_stats(self, mean: Tensor, std: Tensor) -> None:
        """Not used: the inputs are read in fixed physical scales (device-independent)."""

    def set_gyro_bias(self, bias: Tensor) -> None:
        """Not used: the gyro bias is the backbone's state, not a learned constant."""

    def forward(self, imu: Tensor) -> Dict[str, Tensor]:
        if imu.shape[-1] != self.axes:
            raise ValueError(f"ResidualCalibration: expected {self.axes} IMU channels, got {imu.shape[-1]}")
        x = imu.to(self.input_scale.dtype) * self.input_scale  # the networks' dtype (float32)
        gyro_error = (self.gyro_scale * torch.tanh(self.gyro_net(x))).to(imu.dtype)
        if not self.training:
            # applied to the filter: at most gyro_clip per axis. The network learns the whole
            # increment error (bound gyro_scale); only its small part transfers to recordings it
            # never saw (BROAD fold 0, the development fold: unclipped AAE 1.99 / inclination 0.63,
            # clipped at 0.005 rad/s 2.07 / 0.52, VQF 2.85 / 0.52; trained at gyro_scale 0.005
            # instead: 3.38 / 0.55, a saturated tanh learns a sign)
            gyro_error = gyro_error.clamp(-self.gyro_clip, self.gyro_clip)
        z = self.trust_net(x)
        zero3 = torch.zeros_like(imu[..., 0:3])
        out = {"gyro_error": gyro_error, "gyro": imu[..., 0:3] - gyro_error, "acc": imu[..., 3:6],
               "acc_error": zero3, "acc_trust_logit": z[..., 0]}
        if self.axes == 9:
            out.update(mag=imu[..., 6:9], mag_error=zero3, mag_trust_logit=z[..., 1])
        return out


class BackboneLoop(nn.Module):
    """The backbone with the trust scales: runs a whole recording (numba, float64, no gradient)
    from a given attitude. ``backbone``: :class:`~tcn_ahrs.kernels.backbone.BackboneParams` fields."""

    def __init__(self, use_mag: bool, acc_trust_scale: float = _R.acc_trust_scale,
                 mag_trust_scale: float = _R.mag_trust_scale, bias_trust_scale: float = _R.bias_trust_scale,
                 trust_max: float = _R.trust_max, trust_weight: float = _R.trust_weight,
                 backbone: Optional[Mapping[str, float]] = None, bias_prior: float = _R.bias_prior,
                 bias_trust_power: float = _R.bias_trust_power):
        super().__init__()
        self.trust_max = float(trust_max)
        self.trust_weight = float(trust_weight)
        self.use_mag = bool(use_mag)
        self.acc_trust_scale = float(acc_trust_scale)
        self.mag_trust_scale = float(mag_trust_scale)
        self.bias_trust_scale = float(bias_trust_scale)
        self.bias_prior = float(bias_prior)  # multiplies bias_init: 0 = VQF's zero start
        self.bias_trust_power = float(bias_trust_power)  # the acc trust gating the bias update (config)
        self.params = bb.BackboneParams.from_mapping(dict(backbone or {}))
        # the bias estimate's starting point (rad/s): the training recordings' estimated gyro bias
        # (train.init_gyro_bias), a prior the backbone keeps estimating from (zero: VQF's start)
        self.register_buffer("bias_init", torch.zeros(3, dtype=torch.float64))

    def trusts(self, cal: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """(B, N) trusts from the calibration's logits (2σ(z): 1 at z = 0) times the scales."""
        def network(z: Tensor) -> Tensor:  # the network's own trust, 2 σ(z) clipped
            return torch.clamp(2.0 * torch.sigmoid(z.double()), max=self.trust_max)

        def trust(t: Tensor, scale: float) -> Tensor:
            return scale * (1.0 + self.trust_weight * (t - 1.0))  # how far the network moves it from 1

        t_acc = network(cal["acc_trust_logit"])
        acc = trust(t_acc, self.acc_trust_scale)
        mag = (trust(network(cal["mag_trust_logit"]), self.mag_trust_scale) if "mag_trust_logit" in cal
               else torch.ones_like(acc))
        bias = torch.full_like(acc, self.bias_trust_scale)
        if self.bias_trust_power > 0.0:  # the network's accelerometer trust, before the knobs
            bias = self.bias_trust_scale * (t_acc / self.trust_max) ** self.bias_trust_power
        return {"acc_trust": acc, "mag_trust": mag, "bias_trust": bias}

    @torch.no_grad()
    def run(self, cal: Dict[str, Tensor], imu: Tensor, dt: Tensor, q0: np.ndarray, start: int,
            heading_ref: str = "init") -> Dict[str, Tensor]:
        """One recording (batch of one): cal from :class:`ResidualCalibration`, raw imu (1, N, C),
        dt (1, N), q0 (4,) ``nav_from_body`` at sample ``start``. The filter starts at ``start``
        (the networks saw the samples before). 9 axes: heading is referred to the field at the
        start (the classical filters' ``heading_ref="init"``), so any motion-capture yaw works;
        ``heading_ref="north"``: to magnetic north (ground truth referred to it: BROAD).
        Returns ``quat`` (N - start, 4), ``gyro_bias`` (N - start, 3), ``rest`` (N - start,) and
        the trusts (1, N)."""
        from ..filters.common import magnetic_from_nav
        from .. import so3

        tr = self.trusts(cal)
        g = cal["gyro"][0, start:].double().cpu().numpy()
        a = imu[0, start:, 3:6].double().cpu().numpy()
        d = dt[0, start:].double().cpu().numpy()
        m = imu[0, start:, 6:9].double().cpu().numpy() if (self.use_mag and imu.shape[-1] >= 9) else None
        q = np.asarray(q0, dtype=np.float64)
        m_from_n = None
        if m is not None and heading_ref == "init":
            m_from_n = magnetic_from_nav(torch.as_tensor(q), torch.as_tensor(m[0]))
            q = so3.quat_mul(m_from_n, torch.as_tensor(q)).numpy()
        out = bb.run(g, a, m, d, self.params, q0=q, acc_trust=tr["acc_trust"][0, start:].cpu().numpy(),
                     mag_trust=tr["mag_trust"][0, start:].cpu().numpy(),
                     bias_trust=tr["bias_trust"][0, start:].cpu().numpy(), bias0=self.bias_prior * self.bias_init.cpu().numpy())
        quat = torch.as_tensor(out["quat"])
        if m_from_n is not None:
            quat = so3.quat_mul(so3.quat_conj(m_from_n).expand_as(quat), quat)
        res = {"quat": quat, "gyro_bias": torch.as_tensor(out["gyro_bias"]),
               "rest": torch.as_tensor(out["rest"], dtype=torch.float64)}
        # the sensors' health flags (frozen, clipped, gap), as the backbone estimator returns them
        res.update({k: torch.as_tensor(out[k]) for k in bb.HEALTH_KEYS})
        res.update(tr)
        return res
