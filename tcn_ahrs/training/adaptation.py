"""Fine-tuning that never hurts: the fine-tuned model ships only when held-out evidence says it is
better than the model it started from; otherwise the starting model ships, and the run says why.

Why: fine-tuning on one or two recordings can fit what is not there. Self-supervised on TUM VI's
handheld rooms (2026-12-03), the rest loss took slow hand motion for the gyro's bias and the
heading error went 4.74 → 13.8°; with ground truth on two OxIOD recordings, 8.37 → 9.22°.

The evidence comes from the later parts of the user's recordings, which the fine-tuning never
trained on (``data.train_part``):

* with ground truth (``supervision="gt"``): mean AAE and inclination against it (the metrics
  module's one definition); adopted when it is better (:func:`tcn_ahrs.verdict.better`: a lower
  AAE and an inclination no higher, at the tables' 0.01° resolution);
* without (``supervision="self"``), two readings of the sensors' own consistency:
  - ``rest_drift_dps``: how fast the estimate turns while the device rests (°/s; rest as the device
    check reads it, from the signal's character, :func:`tcn_ahrs.device_check.rest_windows`) — the
    truth is zero, so this is heading and tilt drift measured without ground truth;
  - ``gravity_deg``: the mean angle between the estimate's up and the accelerometer where the
    specific force is gravity alone (:func:`tcn_ahrs.losses.self_labels` column 0) — inclination
    without ground truth.
  Adopted when the rest drift falls by at least ``MIN_GAIN`` and ``MIN_GAIN_DPS`` and the gravity angle rises by no
  more than ``GRAVITY_TOL_DEG``; no rest in the held-out parts is no evidence: the starting model stays.
"""
from __future__ import annotations

import math
from typing import Any, Dict, Optional, Sequence

import numpy as np
import torch

from .. import so3, verdict
from ..sequence import ImuSequence

MIN_GAIN = 0.1          # the rest drift must fall by 10 % (self-supervised)
MIN_GAIN_DPS = 0.01     # °/s, and by this much: below it (0.6° a minute) it is the evidence's noise
GRAVITY_TOL_DEG = 0.05  # °, how much the gravity angle may rise (self-supervised)


def rest_drift_dps(seq: ImuSequence, quat: np.ndarray) -> Optional[tuple]:
    """(mean turn rate of ``quat`` (N, 4) nav_from_body over the recording's rest stretches in °/s,
    seconds of rest) or None when it never rests."""
    from ..device_check import rest_windows, stretches

    rest, n, _, _ = rest_windows(seq.gyro, seq.accel, float(seq.rate))
    if not rest.any():
        return None
    q = torch.as_tensor(quat, dtype=torch.float64)
    turned, seconds = 0.0, 0.0
    for i, j in stretches(rest):  # each stretch of rest windows: the rotation from its first to its last sample
        a, b = i * n, j * n - 1
        rel = so3.quat_mul(so3.quat_conj(q[a]), q[b])
        turned += float(torch.linalg.norm(so3.quat_log(rel)))
        seconds += float(np.sum(seq.dt[a + 1:b + 1]))
    return math.degrees(turned) / max(seconds, 1e-9), seconds


def gravity_deg(seq: ImuSequence, quat: np.ndarray) -> Optional[float]:
    """Mean angle (°) between the estimate's up in the body frame and the measured specific force
    where it is gravity alone (:func:`~tcn_ahrs.losses.self_labels` column 0); None where it never is."""
    from ..losses import self_labels

    imu = torch.as_tensor(np.concatenate([seq.gyro, seq.accel], 1))
    ok = self_labels(imu, torch.as_tensor(seq.dt))[:, 0] > 0.5
    if not bool(ok.any()):
        return None
    r = so3.quat_to_matrix(torch.as_tensor(quat, dtype=torch.float64))[ok]  # nav_from_body
    up_body = r[:, 2, :]  # R^T e_z: the navigation frame's up seen in the body frame
    acc = imu[ok, 3:6]
    cos = (up_body * acc).sum(-1) / acc.norm(dim=-1).clamp_min(1e-9)
    return float(torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0))).mean())


def self_evidence(estimator, seqs: Sequence[ImuSequence]) -> Dict[str, Any]:
    """The two ground-truth-free readings (module docstring) of ``estimator`` on ``seqs``, each a
    time-weighted (rest) or plain (gravity) mean over the recordings that have it."""
    drift, rest_s, grav = 0.0, 0.0, []
    for s in seqs:
        q = estimator.run(s).quat
        d = rest_drift_dps(s, q)
        if d is not None:
            drift += d[0] * d[1]
            rest_s += d[1]
        g = gravity_deg(s, q)
        if g is not None:
            grav.append(g)
    return {"rest_drift_dps": drift / rest_s if rest_s > 0 else None, "rest_s": rest_s,
            "gravity_deg": float(np.mean(grav)) if grav else None}


def gt_evidence(estimator, seqs: Sequence[ImuSequence], axes: int) -> Dict[str, Any]:
    """Mean AAE and inclination (°) of ``estimator`` on the recordings with ground truth."""
    from ..estimators.base import initial_state
    from ..metrics import aae_and_inclination

    rows = []
    for s in seqs:
        if not s.has_gt:
            continue
        i0, q0 = initial_state(s)
        row = aae_and_inclination(s, estimator.run(s, q0, i0).quat, axes)
        if np.all(np.isfinite(row)):  # a part without scored samples says nothing
            rows.append(row)
    if not rows:
        return {"aae_deg": None, "inclination_deg": None}
    a = np.asarray(rows)
    return {"aae_deg": float(a[:, 0].mean()), "inclination_deg": float(a[:, 1].mean())}


def decide(before: Dict[str, Any], after: Dict[str, Any], supervision: str) -> tuple:
    """(adopt the fine-tuned model?, why in words) from the two evidence records."""
    if supervision == "gt":
        a0, a1 = before.get("aae_deg"), after.get("aae_deg")
        if a0 is None or a1 is None:
            return False, "no held-out part with ground truth: no evidence, the starting model is kept"
        i0, i1 = before["inclination_deg"], after["inclination_deg"]
        ok = verdict.better(a1, i1, a0, i0)
        return ok, (f"held-out parts: AAE {a0:.2f} → {a1:.2f}°, inclination {i0:.2f} → {i1:.2f}°: "
                    + ("better, the fine-tuned model ships" if ok else "not better, the starting model is kept"))
    d0, d1 = before.get("rest_drift_dps"), after.get("rest_drift_dps")
    if d0 is None or d1 is None:
        return False, ("the held-out parts never rest: no evidence without ground truth, "
                       "the starting model is kept")
    g0, g1 = before.get("gravity_deg"), after.get("gravity_deg")
    gravity_ok = g0 is None or g1 is None or g1 <= g0 + GRAVITY_TOL_DEG
    ok = d1 <= (1.0 - MIN_GAIN) * d0 and d0 - d1 >= MIN_GAIN_DPS and gravity_ok
    grav = "" if g0 is None or g1 is None else f", gravity angle {g0:.2f} → {g1:.2f}°"
    return ok, (f"held-out parts: drift at rest {d0:.3f} → {d1:.3f} °/s over {after['rest_s']:.0f} s{grav}: "
                + ("better, the fine-tuned model ships" if ok else "not better, the starting model is kept"))


def evidence(estimator, seqs: Sequence[ImuSequence], supervision: str, axes: int) -> Dict[str, Any]:
    return gt_evidence(estimator, seqs, axes) if supervision == "gt" else self_evidence(estimator, seqs)
