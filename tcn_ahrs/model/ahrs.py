"""The learned AHRS: calibration (TCN) + open-loop ECF + integration on SO(3).

One model class; the variants of the paper and its ablations are flags (``conf/model/*.yaml``):

============== ===== ========= ======= ======= ============ =========
variant        axes  gyro net  acc net mag net acc/mag term ECF
============== ===== ========= ======= ======= ============ =========
ahrs9          9     tcn (9in) tcn     tcn     both         yes
ahrs6          6     tcn (6in) tcn     -       acc          yes
calib_imu      9/6   constant  const.  const.  both         yes
dig_like       9/6   tcn       none    none    none         no
no_mag_term    9     tcn       tcn     tcn     acc          yes
no_acc_term    9     tcn       tcn     tcn     mag          yes
no_ecf_terms   9     tcn       tcn     tcn     none         yes
gyro_only_input 9    tcn (3in) tcn     tcn     both         yes
============== ===== ========= ======= ======= ============ =========

Data flow (B windows of N samples; body frame; ENU ``nav_from_body``):
``imu (B,N,C) -> Calibration -> ω̂_gyr, ĝ, b̂ -> OpenLoopECF -> ω̂ (B,N,3) -> so3.integrate``.
The loss only needs ω̂ (increments, :mod:`tcn_ahrs.losses`); the absolute attitude
(Eq. 3) is :meth:`LearnedAHRS.attitude`.
"""
from __future__ import annotations

from typing import Any, Dict, Mapping, Optional

import torch
from torch import Tensor, nn

from .. import so3
from ..conventions import STATE_DTYPE
from ..filters.backbone import HEALTH_KEYS
from .calibration import Calibration
from .closed_loop import ClosedLoopFilter
from .open_loop import OpenLoopECF
from ..config import defaults, keys
from ..config.model import LOOPS, ClosedLoopConfig, ErrorScaleConfig, ModelConfig, ResidualConfig, TCNConfig
from .residual import RESIDUAL_KEYS, BackboneLoop, ResidualCalibration

# Every key a model config may have (a misspelt key is an error, see from_config): the fields of
# the schemas in tcn_ahrs/config/model.py, where each default is written once.
MODEL_KEYS = keys(ModelConfig)
CLOSED_LOOP_KEYS = keys(ClosedLoopConfig)
TCN_KEYS = keys(TCNConfig)
_D = ModelConfig()


class LearnedAHRS(nn.Module):
    """TCN calibration + differentiable open-loop ECF (paper Sec. 3).

    Args: see :data:`MODEL_KEYS`; ``variant`` is only a label saved with checkpoints.
    """

    def __init__(self, axes: int = 9, variant: str = _D.variant, gyro_net: str = _D.gyro_net,
                 acc_net: str = _D.acc_net, mag_net: str = _D.mag_net, gyro_input: str = _D.gyro_input,
                 use_acc_term: bool = _D.use_acc_term, use_mag_term: bool = _D.use_mag_term, ecf: bool = _D.ecf,
                 preintegration: str = _D.preintegration, init_gain: float = _D.init_gain,
                 error_scale: Optional[Mapping[str, float]] = None, tcn: Optional[Mapping] = None,
                 loop: str = _D.loop, trust: Optional[bool] = _D.trust,
                 closed_loop: Optional[Mapping[str, float]] = None,
                 residual: Optional[Mapping[str, Any]] = None):
        super().__init__()
        if loop not in LOOPS:
            raise ValueError(f"model config: loop {loop!r}: expected one of {LOOPS}")
        # unset sections: the schemas' defaults (tcn_ahrs/config/model.py), key by key
        tcn = {**defaults(TCNConfig), **dict(tcn or {})}
        error_scale = {**defaults(ErrorScaleConfig), **dict(error_scale or {})}
        self.axes = int(axes)
        self.variant = str(variant)
        self.loop = str(loop) if (ecf or loop == "backbone") else "open"
        trust = (self.loop == "closed") if trust is None else bool(trust)
        self.ecf = None
        self.closed = None
        self.backbone = None
        if self.loop == "backbone":  # learned residuals on the VQF-grade backbone (model/residual.py)
            res = dict(residual or {})
            bad = set(res) - RESIDUAL_KEYS
            if bad:
                raise ValueError(f"model.residual config: unknown key(s) {sorted(bad)}; "
                                 f"expected a subset of {sorted(RESIDUAL_KEYS)}")
            res = {**defaults(ResidualConfig), **res}
            self.calibration = ResidualCalibration(self.axes, dict(tcn or {}), float(res["gyro_scale"]),
                                                   float(res["gyro_clip"]))
            self.backbone = BackboneLoop(use_mag=use_mag_term and self.axes == 9,
                                         acc_trust_scale=float(res["acc_trust_scale"]),
                                         mag_trust_scale=float(res["mag_trust_scale"]),
                                         bias_trust_scale=float(res["bias_trust_scale"]),
                                         trust_max=float(res["trust_max"]),
                                         trust_weight=float(res["trust_weight"]),
                                         bias_prior=float(res["bias_prior"]),
                                         bias_trust_power=float(res["bias_trust_power"]),
                                         backbone=dict(res["backbone"] or {}))
            return
        self.calibration = Calibration(self.axes, gyro_net, acc_net, mag_net, gyro_input,
                                       dict(error_scale or {}), dict(tcn or {}), trust=trust)
        cl = dict(closed_loop or {})
        bad = set(cl) - CLOSED_LOOP_KEYS
        if bad:
            raise ValueError(f"model.closed_loop config: unknown key(s) {sorted(bad)}; "
                             f"expected a subset of {sorted(CLOSED_LOOP_KEYS)}")
        cl = {**defaults(ClosedLoopConfig), **cl}
        if ecf and self.loop == "open":
            self.ecf = OpenLoopECF(use_acc=use_acc_term, use_mag=use_mag_term and self.axes == 9,
                                   init_gain=init_gain, preintegration=preintegration)
        elif ecf:
            self.closed = ClosedLoopFilter(use_acc=use_acc_term, use_mag=use_mag_term and self.axes == 9,
                                           **{k: float(v) for k, v in cl.items()})

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], axes: Optional[int] = None) -> "LearnedAHRS":
        """Build from a (possibly OmegaConf) mapping; unknown keys raise ``ValueError``.
        ``axes`` (from the data) overrides ``cfg['axes']`` when ``cfg['axes']`` is None."""
        cfg = dict(cfg)
        unknown = set(cfg) - MODEL_KEYS
        if unknown:
            raise ValueError(f"model config: unknown key(s) {sorted(unknown)}; expected a subset of {sorted(MODEL_KEYS)}")
        tcn = dict(cfg.get("tcn") or {})
        bad = set(tcn) - TCN_KEYS
        if bad:
            raise ValueError(f"model.tcn config: unknown key(s) {sorted(bad)}; expected a subset of {sorted(TCN_KEYS)}")
        if cfg.get("closed_loop") is not None:
            cfg["closed_loop"] = dict(cfg["closed_loop"])
        if cfg.get("residual") is not None:
            cfg["residual"] = dict(cfg["residual"])
        for k in ("channels", "dilations"):
            if k in tcn:
                tcn[k] = list(tcn[k])
        cfg["tcn"] = tcn
        if cfg.get("error_scale") is not None:
            cfg["error_scale"] = dict(cfg["error_scale"])
        if cfg.get("axes") is None:
            if axes is None:
                raise ValueError("model config: 'axes' is unset and no data axes were given")
            cfg["axes"] = axes
        return cls(**cfg)

    @property
    def receptive_field(self) -> int:
        return self.calibration.receptive_field

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters() if p.requires_grad)

    def forward(self, imu: Tensor, dt: Tensor, r0: Tensor) -> Dict[str, Tensor]:
        """Corrected angular rate and intermediate signals.

        Args:
            imu: (B, N, C) raw gyro [rad/s], acc [m/s^2] (, mag [uT]), body frame.
            dt:  (B, N) time step before each sample, s.
            r0:  (B, 3, 3) ``nav_from_body`` at sample 0 (ground truth), needed by the ECF's
                 pre-integration (Eq. 25).
        Returns dict (B, N, 3): ``omega`` ω̂ (Eq. 22), ``gyro`` ω̂_gyr, ``gyro_error`` ω̃,
        ``acc_error`` ã, ``mag_error`` m̃ (9-axis), ``e_acc``/``e_mag`` when used.
        """
        if self.closed is not None:
            out = self._run_closed(imu, dt, r0, 0)
            out.pop("rot")
            return out
        cal = self.calibration(imu)
        out = dict(cal)
        if self.ecf is None:
            out["omega"] = cal["gyro"]
            return out
        omega, e_acc, e_mag = self.ecf(cal["gyro"], cal["acc"], cal.get("mag"), imu[..., 0:3],
                                       imu[..., 3:6], r0.to(imu.dtype), dt)
        out["omega"] = omega
        if e_acc is not None:
            out["e_acc"] = e_acc
        if e_mag is not None:
            out["e_mag"] = e_mag
        return out

    def filter_closed_loop(self, imu: Tensor, dt: Tensor, rot0: Tensor, bias0: Optional[Tensor] = None,
                           east_ref: Optional[Tensor] = None, context: int = 0,
                           dtype: Optional[torch.dtype] = None) -> Dict[str, Tensor]:
        """The closed loop (:mod:`tcn_ahrs.model.closed_loop`) over imu (B, N, C), dt (B, N).

        The calibration networks and the rest detector see every sample; the filter starts at
        sample ``context`` from rot0 (B, 3, 3) (``nav_from_body``) and bias0 (B, 3) (default 0), so
        the first ``context`` samples only warm the causal networks up (training chunks).
        ``dtype``: of the filter loop (default imu's; float64 for long recordings).
        Returns the calibration dict plus ``rot`` (B, N - context, 3, 3), ``gyro_bias``,
        ``correction`` (B, N - context, 3) and ``east_ref`` (B, 3)."""
        if self.closed is None:
            raise RuntimeError("filter_closed_loop: this model has no closed loop (model.loop=open)")
        if bias0 is None:
            bias0 = rot0.new_zeros(rot0.shape[:-2] + (3,))
        return self.closed.run(self.calibration(imu), imu, dt, rot0, bias0, east_ref, int(context),
                               imu.dtype if dtype is None else dtype)

    def run_sequence(self, imu: Tensor, dt: Tensor, r0: Tensor, start: int = 0,
                     reanchor: Optional[int] = None, heading_ref: str = "init") -> Dict[str, Tensor]:
        """A whole recording: the (causal) calibration sees every sample; the ECF and the
        integration start at sample ``start`` (first valid ground truth) from ``r0``.

        ``reanchor`` (samples, None = the paper's single open-loop pass): restart the open-loop
        ECF every ``reanchor`` samples from the model's *own* current attitude. The
        pre-integrated C̃ of Eq. 25 then never runs longer than a training window, so e_acc and
        e_mag keep describing the estimate on recordings of minutes (measured on BROAD's test
        trials: see README "Re-anchoring"). Still causal and fully parallel inside a segment.

        imu (1, N, C), dt (1, N), r0 (1, 3, 3). Returns the :meth:`forward` dict (entries before
        ``start``: raw-calibrated values, zero innovations) plus ``rot`` (1, N, 3, 3) in float64
        (samples before ``start`` hold r0).

        With the closed loop (``model.loop=closed``) the filter runs sample by sample in float64
        from ``r0`` at ``start``; ``reanchor`` does not apply (the loop never drifts from its
        own estimate). ``omega`` is then the applied rate ω̂_gyr − b + w. ``heading_ref``
        (backbone models, 9 axes): ``"init"`` the field at the start, ``"north"`` magnetic north."""
        if self.closed is not None:
            return self._run_closed(imu, dt, r0, start)
        if self.backbone is not None:
            return self._run_backbone(imu, dt, r0, start, heading_ref)
        cal = self.calibration(imu)
        out = dict(cal)
        omega = cal["gyro"].clone()
        n = imu.shape[1]
        r0d = r0.to(torch.float64)
        if self.ecf is None:
            segments = [(start, n - 1)]
        else:
            step = n if not reanchor else int(reanchor)
            segments = [(s, min(s + step, n - 1)) for s in range(start, max(n - 1, start + 1), step)]
        rot_parts = [r0d.unsqueeze(1).expand(-1, start + 1, 3, 3)]
        innov = {}
        r = r0d
        for s, e in segments:  # segments share their boundary sample (the anchor)
            sl = slice(s, e + 1)
            if self.ecf is not None:
                om, e_acc, e_mag = self.ecf(cal["gyro"][:, sl], cal["acc"][:, sl],
                                            cal["mag"][:, sl] if "mag" in cal else None,
                                            imu[:, sl, 0:3], imu[:, sl, 3:6], r.to(imu.dtype), dt[:, sl])
                omega[:, s + 1:e + 1] = om[:, 1:]
                if s == start:
                    omega[:, s] = om[:, 0]
                for name, val in (("e_acc", e_acc), ("e_mag", e_mag)):
                    if val is not None:
                        innov.setdefault(name, torch.zeros_like(omega))[:, s + 1:e + 1] = val[:, 1:]
                        if s == start:
                            innov[name][:, s] = val[:, 0]
            rot = self.attitude(omega[:, sl], dt[:, sl], r)
            rot_parts.append(rot[:, 1:])
            r = rot[:, -1]
        out.update(innov)
        out["omega"] = omega
        out["rot"] = torch.cat(rot_parts, 1)[:, :n]
        return out

    def _run_backbone(self, imu: Tensor, dt: Tensor, r0: Tensor, start: int,
                      heading_ref: str = "init") -> Dict[str, Tensor]:
        """The backbone with the learned residuals from sample ``start`` (batch of one)."""
        if imu.shape[0] != 1:
            raise ValueError("run_sequence with the backbone: one recording at a time (batch of one)")
        n = imu.shape[1]
        cal = self.calibration(imu)
        q0 = so3.matrix_to_quat(r0[0].to(torch.float64)).cpu().numpy()
        res = self.backbone.run(cal, imu, dt, q0, start, heading_ref)
        out = dict(cal)
        rot = so3.quat_to_matrix(res["quat"]).to(imu.device)[None]
        out["rot"] = torch.cat([r0.to(torch.float64).unsqueeze(1).expand(-1, start, 3, 3), rot], 1)[:, :n]
        out["omega"] = cal["gyro"]
        out["gyro_bias"] = res["gyro_bias"].to(imu.device)[None]
        out["rest"] = torch.cat([torch.zeros(start, dtype=torch.float64), res["rest"]])[None].to(imu.device)
        for k in HEALTH_KEYS:  # from `start` on; nothing flagged before
            out[k] = torch.cat([torch.zeros(start, dtype=torch.bool), res[k]])[None].to(imu.device)
        for k in ("acc_trust", "mag_trust"):
            out[k] = res[k].to(imu.device)
        return out

    def _run_closed(self, imu: Tensor, dt: Tensor, r0: Tensor, start: int) -> Dict[str, Tensor]:
        n = imu.shape[1]
        out = self.filter_closed_loop(imu, dt, r0.to(STATE_DTYPE), context=start, dtype=STATE_DTYPE)
        rot = out.pop("rot")
        rot = torch.cat([r0.to(torch.float64).unsqueeze(1).expand(-1, start, 3, 3), rot], 1)
        omega = out["gyro"].to(torch.float64).clone()
        omega[:, start:] = omega[:, start:] - out["gyro_bias"] + out["correction"]
        out["omega"] = omega.to(imu.dtype)
        out["rot"] = rot[:, :n]
        return out

    @staticmethod
    def attitude(omega: Tensor, dt: Tensor, r0: Tensor) -> Tensor:
        """Eq. 3: ``C_k = C_0 ∏ exp(ω̂ Δt)`` -> (B, N, 3, 3) (computed in r0's dtype; pass a
        float64 r0 for long sequences)."""
        return so3.integrate(r0, omega.to(r0.dtype), dt.to(r0.dtype))
