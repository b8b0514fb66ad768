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
    ``tau_mag`` s (heading), bias estimation at rest and in motion, magnetic disturbance rejection
    against the recording's own field. Any other :class:`~tcn_ahrs.kernels.backbone.BackboneParams`
    field can be set through ``extra`` (a dict). Signals: ``gyro_bias`` (N, 3) rad/s, ``rest``,
    ``mag_disturbed`` (N,)."""

    tau_acc: float = 3.0  # s
    tau_mag: float = 9.0  # s
    extra: object = None  # dict of further BackboneParams fields

    method: ClassVar[str] = "backbone"
    tunable: ClassVar[Sequence[str]] = ("tau_acc", "tau_mag")
    default_grid: ClassVar[Dict[str, list]] = {"tau_acc": [1.0, 3.0, 6.0], "tau_mag": [3.0, 9.0, 20.0]}

    def _filter(self, gyro, accel, dt, q0, mag, p):
        ta, tm = torch.as_tensor(p["tau_acc"]), torch.as_tensor(p["tau_mag"])
        shape = torch.broadcast_shapes(ta.shape, tm.shape, gyro.shape[:1])  # () / (R,) / (P, R)
        ta, tm = ta.expand(shape).reshape(-1), tm.expand(shape).reshape(-1)
        r = gyro.shape[0]
        n_sets = ta.numel() // r
        g, a, d, q = (x.cpu().numpy() for x in (gyro, accel, dt, q0))
        m = None if mag is None else mag.cpu().numpy()
        extra = dict(p.get("extra") or {})
        quat, bias, rest, dist = [], [], [], []
        for k in range(n_sets * r):
            i = k % r
            params = bb.BackboneParams.from_mapping({**extra, "tau_acc": float(ta[k]), "tau_mag": float(tm[k])})
            out = bb.run(g[i], a[i], None if m is None else m[i], d[i], params, q0=q[i])
            quat.append(out["quat"])
            bias.append(out["gyro_bias"])
            rest.append(out["rest"])
            dist.append(out["mag_disturbed"])
        lead = (n_sets, r) if len(shape) == 2 else (r,)
        t = lambda xs: torch.as_tensor(np.stack(xs)).reshape(lead + xs[0].shape).to(gyro.device)  # noqa: E731
        res = {"quat": t(quat).to(gyro.dtype), "gyro_bias": t(bias).to(gyro.dtype), "rest": t(rest)}
        if m is not None:
            res["mag_disturbed"] = t(dist)
        return res
