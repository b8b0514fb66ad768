"""The VQF-grade backbone (:mod:`tcn_ahrs.filters.backbone`) as a classical estimator.

It is the filter the learned AHRS builds on (its residuals start at zero, so the untrained model
is this estimator), and the classical filter it must never be worse than. With VQF's defaults and
the same start it equals the ``vqf`` package (tests/test_backbone.py); unlike ``vqf`` it takes the
ground-truth initial attitude (``init_quat``, as every classical filter here) and per-sample time
steps (irregular recordings run as they are).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Dict, Sequence

import numpy as np
import torch

from ..filters import backbone as bb
from ..kernels.params import tuning_grid
from .classical import ClassicalEstimator
from .registry import register

_VQF = bb.BackboneParams()   # VQF's defaults


@register("backbone", "classical")
@dataclass
class Backbone(ClassicalEstimator):
    """VQF's structure and defaults (Laidig & Seel 2023): ``tau_acc`` s (inclination),
    ``tau_mag`` s (heading), bias estimation at rest and in motion (``bias_clip`` °/s), magnetic
    disturbance rejection against the recording's own field; the fields are
    :class:`~tcn_ahrs.kernels.backbone.BackboneParams`'s, any other one through ``extra`` (a dict). Signals: ``gyro_bias`` (N, 3) rad/s, ``rest``,
    ``mag_disturbed``, ``gyro_frozen``, ``acc_frozen``, ``gyro_clipped``, ``acc_clipped``, ``gap`` (N,)
    (sensor health, no ground truth)."""

    # the knobs an estimator sets directly (meaning, unit, default: BackboneParams's fields)
    tau_acc: float = _VQF.tau_acc
    tau_mag: float = _VQF.tau_mag
    motion_bias: float = _VQF.motion_bias
    rest_bias: float = _VQF.rest_bias
    bias_clip: float = _VQF.bias_clip
    mag_rejection: float = _VQF.mag_rejection
    extra: object = None  # dict of further BackboneParams fields

    method: ClassVar[str] = "backbone"
    default_grid: ClassVar[Dict[str, list]] = tuning_grid(bb.BackboneParams)
    tunable: ClassVar[Sequence[str]] = tuple(default_grid)

    def _filter(self, gyro, accel, dt, q0, mag, p):
        r = gyro.shape[0]
        names = [k for k in ("tau_acc", "tau_mag", "motion_bias", "rest_bias", "bias_clip", "mag_rejection")]
        vals = {k: torch.as_tensor(p[k]) for k in names}
        shape = torch.broadcast_shapes(*(v.shape for v in vals.values()), gyro.shape[:1])  # () / (R,) / (P, R)
        vals = {k: v.expand(shape).reshape(-1) for k, v in vals.items()}
        n_sets = vals["tau_acc"].numel() // r
        g, a, d, q = (x.cpu().numpy() for x in (gyro, accel, dt, q0))
        m = None if mag is None else mag.cpu().numpy()
        extra = dict(p.get("extra") or {})
        health = bb.HEALTH_KEYS
        quat, bias, rest, dist = [], [], [], []
        flags = {k: [] for k in health}
        for k in range(n_sets * r):
            i = k % r
            params = bb.BackboneParams.from_mapping({**extra, **{n: float(v[k]) for n, v in vals.items()}})
            out = bb.run(g[i], a[i], None if m is None else m[i], d[i], params, q0=q[i])
            quat.append(out["quat"])
            bias.append(out["gyro_bias"])
            rest.append(out["rest"])
            dist.append(out["mag_disturbed"])
            for name in health:
                flags[name].append(out[name])
        lead = (n_sets, r) if len(shape) == 2 else (r,)
        t = lambda xs: torch.as_tensor(np.stack(xs)).reshape(lead + xs[0].shape).to(gyro.device)  # noqa: E731
        res = {"quat": t(quat).to(gyro.dtype), "gyro_bias": t(bias).to(gyro.dtype), "rest": t(rest),
               **{name: t(v) for name, v in flags.items()}}
        if m is not None:
            res["mag_disturbed"] = t(dist)
        return res
