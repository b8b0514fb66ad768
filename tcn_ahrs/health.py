"""What the sensor-health checks found in one run, in words a person reads (``tcn-ahrs evaluate``
prints them per recording and writes them to results.json).

The flags are an estimator's signals (the backbone's: :class:`tcn_ahrs.estimators.backbone.Backbone`,
no ground truth read): ``gyro_frozen`` / ``acc_frozen`` (three readings repeating exactly: not
integrated / not trusted), ``gyro_clipped`` / ``acc_clipped`` (a reading pinned at the sensor's
range), ``gap`` (a step far longer than the recording's rate). Pure function of arrays.
"""
from __future__ import annotations

from typing import Dict, List, Mapping, Optional

import numpy as np

from .device_check import stretches

HEALTH_FLAGS: Dict[str, str] = {
    "gyro_frozen": "gyro frozen",
    "acc_frozen": "accelerometer frozen",
    "gyro_clipped": "gyro clipped",
    "acc_clipped": "accelerometer clipped",
    "gap": "gap",
    "mag_frozen": "magnetometer frozen",
}
"""Signal name -> what it is called in the report."""


def health_report(time: np.ndarray, signals: Optional[Mapping[str, object]], most: int = 3) -> Optional[List[str]]:
    """Per flag of :data:`HEALTH_FLAGS` set anywhere, one phrase ("gyro frozen 5.0 s from 6.7 s",
    "accelerometer clipped on 412 samples from 3.2 s", "gap 0.50 s at 10.0 s"); [] when the
    checks ran and found nothing; None when the estimator reports no health flags.
    ``time`` (N,) s; ``signals``: the estimator's (N,) flags."""
    if not signals or not any(k in signals for k in HEALTH_FLAGS):
        return None
    t = np.asarray(time, dtype=np.float64)
    t0 = float(t[0]) if t.size else 0.0
    out: List[str] = []
    for key, what in HEALTH_FLAGS.items():
        if key not in signals or signals[key] is None:
            continue
        mask = np.asarray(signals[key]).reshape(-1)[: t.size] > 0.5
        if not mask.any():
            continue
        runs = stretches(mask)
        if key == "gap":
            steps = np.diff(t, prepend=t[0])
            parts = [f"{steps[a]:.2f} s at {t[a] - t0:.1f} s" for a, _ in runs[:most]]
        elif key.endswith("_clipped"):
            parts = [f"on {int(mask.sum())} samples from {t[runs[0][0]] - t0:.1f} s"]
        else:
            parts = [f"{t[b - 1] - t[a] + (t[1] - t[0] if t.size > 1 else 0.0):.1f} s from {t[a] - t0:.1f} s"
                     for a, b in runs[:most]]
        more = f" (+{len(runs) - most} more)" if not key.endswith("_clipped") and len(runs) > most else ""
        out.append(f"{what} " + ", ".join(parts) + more)
    return out


def recording_health(seq) -> List[str]:
    """What the backbone's health checks (VQF's defaults) find in one recording's own readings (no
    ground truth): :func:`health_report`'s phrases (``tcn-ahrs inspect`` prints them)."""
    from .filters import backbone as bb

    out = bb.run(seq.gyro, seq.accel, seq.mag, seq.dt, bb.BackboneParams())
    return health_report(seq.time, {k: out[k] for k in bb.HEALTH_KEYS}) or []
