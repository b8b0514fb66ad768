"""One interface for every attitude estimator, learned or classical.

An estimator runs on an :class:`~tcn_ahrs.sequence.ImuSequence` and returns one attitude per
sample (``nav_from_body`` quaternions, w,x,y,z, ENU) plus the internal signals worth
looking at (estimated gyro bias, rejection/gating flags, innovation statistics, ...).
The evaluation runner (:mod:`tcn_ahrs.evaluate`) takes any list of estimators.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Optional, Protocol, runtime_checkable

import numpy as np

from ..sequence import ImuSequence


@dataclass
class EstimatorOutput:
    """Result of running an estimator on one recording.

    quat:    (N, 4) estimated ``nav_from_body`` (w,x,y,z), ENU navigation frame.
    signals: name -> (N, ...) array, e.g. ``gyro_bias`` (N,3) rad/s, ``acc_rejected`` (N,) bool,
             ``mahalanobis_acc`` (N,) ...; free for each estimator, documented in its docstring.
    """

    quat: np.ndarray
    signals: Dict[str, np.ndarray] = field(default_factory=dict)


@runtime_checkable
class Estimator(Protocol):
    """Anything with a ``name`` and a ``run`` method.

    ``init_quat`` (4,) is the attitude at sample 0 when the caller knows it (e.g. ground truth
    at the first sample); estimators that can initialise themselves from the accelerometer
    and magnetometer may ignore it when it is ``None``.
    """

    name: str

    def run(self, seq: ImuSequence, init_quat: Optional[np.ndarray] = None) -> EstimatorOutput:
        ...


def initial_quat(seq: ImuSequence) -> Optional[np.ndarray]:
    """Ground-truth attitude at the first sample with valid ground truth, else ``None``.

    Estimators that need an initial attitude receive it at that sample; earlier samples
    (no ground truth) are not scored, so only the attitude from that sample on matters.
    """
    if seq.quat is None or not seq.quat_valid.any():
        return None
    return seq.quat[int(np.argmax(seq.quat_valid))].copy()
