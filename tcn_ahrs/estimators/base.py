"""One interface for every attitude estimator, learned or classical.

An estimator runs on an :class:`~tcn_ahrs.sequence.ImuSequence` and returns one attitude per
sample (``nav_from_body`` quaternions, w,x,y,z, ENU) plus the internal signals worth
looking at (estimated gyro bias, rejection/gating flags, innovation statistics, ...).
The evaluation runner (:mod:`tcn_ahrs.evaluate`) takes any list of estimators.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Optional, Protocol, Tuple, runtime_checkable

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
    """What the evaluation runner (:func:`tcn_ahrs.evaluate.evaluate`) calls.

    Attributes:
        name:  column name (``ecf9d``, ``Raw IMU``, a checkpoint label).
        axes:  6 or 9 (optional; 6: the runner hands it the recording without magnetometer).
        heading_free: True for estimators with no heading reference (scored on inclination only).

    ``run(seq, init_quat, init_index)``: the caller says where and how the estimate starts —
    ``init_quat`` (4,) is the attitude at sample ``init_index`` (the runner: the first sample
    with valid ground truth, :func:`initial_state`), or ``None`` (the estimator initialises
    itself). Every estimator sees the whole recording; none reads its ground truth. The learned
    model starts its filter at ``init_index`` (its networks see the samples before, causally);
    the classical filters and raw integration apply ``init_quat`` at sample 0 — the samples
    before ``init_index`` have no ground truth and are never scored, and on the datasets where
    ``init_index > 0`` (BROAD) the sensor rests until then. ``run_batch(seqs, init_quats,
    init_indices)`` (optional) runs many recordings at once.
    """

    name: str

    def run(self, seq: ImuSequence, init_quat: Optional[np.ndarray] = None,
            init_index: int = 0) -> EstimatorOutput:
        ...


def initial_state(seq: ImuSequence) -> Tuple[int, Optional[np.ndarray]]:
    """``(index, attitude)``: the first sample with valid ground truth and its attitude, or
    ``(0, None)`` without ground truth. What the runner and the tuner hand to ``run``."""
    if seq.quat is None or not seq.quat_valid.any():
        return 0, None
    k = int(np.argmax(seq.quat_valid))
    return k, seq.quat[k].copy()


def initial_quat(seq: ImuSequence) -> Optional[np.ndarray]:
    """Ground-truth attitude at the first sample with valid ground truth, else ``None``
    (:func:`initial_state`'s attitude)."""
    return initial_state(seq)[1]
