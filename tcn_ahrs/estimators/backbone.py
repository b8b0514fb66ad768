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
from .classical import ClassicalEstimator
from .registry import register


@register("backbone", "classical")
@dataclass
class Backbone(ClassicalEstimator):
    """VQF's structure and defaults (Laidig & Seel 2023): ``tau_acc`` s (inclination),
    ``tau_mag`` s (heading), bias estimation at rest and in motion (``bias_clip`` °/s), magnetic
    disturbance rejection against the recording's own field; the fields are
    :class:`~tcn_ahrs.kernels.backbone.BackboneParams`'s, any other one through ``extra`` (a dict). Signals: ``gyro_bias`` (N, 3) rad/s, ``rest``,
    ``mag_disturbed``, ``gyro_frozen``, ``acc_frozen``, ``gyro_clipped``, ``acc_clipped``, ``gap`` (N,)
    (sensor health, no ground truth)."""

    tau_acc: float = 3.0  # s
    tau_mag: float = 9.0  # s
    motion_bias: float = 1.0  # 1: bias estimation in motion, 0: off
    rest_bias: float = 1.0  # 1: rest detection and bias estimation at rest, 0: off
    bias_clip: float = 2.0  # deg/s, bound of the bias estimate
    mag_rejection: float = 1.0  # 1: magnetic disturbance rejection, 0: off
    extra: object = None  # dict of further BackboneParams fields

    method: ClassVar[str] = "backbone"
    tunable: ClassVar[Sequence[str]] = ("tau_acc", "tau_mag", "motion_bias", "bias_clip")
    default_grid: ClassVar[Dict[str, list]] = {"tau_acc": [1.0, 3.0, 10.0], "tau_mag": [3.0, 9.0, 20.0],
                                               "motion_bias": [1.0, 0.0], "bias_clip": [2.0, 8.0]}

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
