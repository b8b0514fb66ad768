"""Tuning of classical filter parameters on training recordings (grid search, batched).

The paper tunes its ECF baseline "on training sequences"; we do the same for every
classical estimator (:mod:`tcn_ahrs.estimators.classical`): the parameters each class tunes by
default are its ``tunable`` (with a ``default_grid``):

* ``ClosedLoopECF``: ``k_norm`` (1/s), ``a_min`` (m/s^2)
* ``Mahony``: ``k_p`` (1/s), ``k_i`` (1/s^2)
* ``Madgwick``: ``beta`` (rad/s)
* ``ESEKF`` / ``RobustESEKF``: ``accel_noise`` (m/s^2/sqrt(Hz)), ``mag_noise`` (rad/sqrt(Hz))

The loss is the project's AAE (:func:`tcn_ahrs.metrics.aae`, ground truth, scored samples,
aligned at the first scored sample), averaged over the recordings. All parameter
combinations of one recording run in ONE batched filter call (the time loop is shared), in
chunks of ``max_batch``.
"""
from __future__ import annotations

import itertools
import math
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from .estimators.base import initial_quat
from .estimators.classical import ClassicalEstimator
from .sequence import ImuSequence

MetricFn = Callable[[np.ndarray, np.ndarray, np.ndarray], float]


def _metric_fn(metric: Union[str, MetricFn]) -> MetricFn:
    if callable(metric):
        return metric
    from . import metrics

    try:
        fn = getattr(metrics, metric)
    except AttributeError:
        raise ValueError(f"unknown metric {metric!r}: expected a function of tcn_ahrs.metrics "
                         "(e.g. 'aae', 'aye') or a callable (q_gt, q_est, mask) -> float") from None
    return lambda q_gt, q_est, mask: fn(q_gt, q_est, mask)


def grid_combinations(grid: Mapping[str, Sequence]) -> List[Dict[str, float]]:
    """Cartesian product of ``grid`` (name -> values) as a list of dicts (first key slowest)."""
    keys = list(grid)
    for k in keys:
        if len(grid[k]) == 0:
            raise ValueError(f"grid entry {k!r} is empty")
    return [dict(zip(keys, vals)) for vals in itertools.product(*(grid[k] for k in keys))]


def evaluate_params(estimator: ClassicalEstimator, seq: ImuSequence, combos: Sequence[Mapping[str, float]],
                    metric: Union[str, MetricFn] = "aae", init: str = "gt", max_batch: int = 256) -> np.ndarray:
    """Metric of each parameter combination on one recording, (len(combos),), batched.

    ``init="gt"`` starts the filters at the ground-truth attitude of the first valid sample
    (:func:`tcn_ahrs.estimators.base.initial_quat`); ``"sensor"`` lets them initialise from the
    accelerometer/magnetometer (TRIAD).
    """
    if seq.quat is None:
        raise ValueError(f"{seq.source}: field 'quat': tuning needs ground truth, the recording has none")
    fn = _metric_fn(metric)
    q0 = initial_quat(seq) if init == "gt" else None
    if init not in ("gt", "sensor"):
        raise ValueError(f"init must be 'gt' or 'sensor', got {init!r}")
    mask = seq.scored()
    out = np.full(len(combos), np.nan)
    if not mask.any():
        return out
    n = len(seq)
    for start in range(0, len(combos), max_batch):
        chunk = combos[start:start + max_batch]
        params = {k: torch.tensor([c[k] for c in chunk], dtype=estimator.dtype) for k in chunk[0]}
        quat = estimator.run_params(seq, params, q0)["quat"].reshape(-1, n, 4).cpu().numpy()
        if quat.shape[0] == 1 and len(chunk) > 1:  # no parameter actually batched
            quat = np.repeat(quat, len(chunk), 0)
        for i in range(len(chunk)):
            out[start + i] = fn(seq.quat, quat[i], mask)
    return out


def tune_grid(
    estimator_cls,
    sequences: Sequence[ImuSequence],
    grid: Optional[Mapping[str, Sequence]] = None,
    metric: Union[str, MetricFn] = "aae",
    init: str = "gt",
    max_batch: int = 256,
    **fixed,
) -> Tuple[Dict[str, float], List[dict]]:
    """Grid search of a classical estimator's parameters on training recordings.

    Args:
        estimator_cls: a :class:`ClassicalEstimator` subclass (or an instance, whose other
            parameters are kept).
        sequences: training recordings with ground truth.
        grid: parameter name -> candidate values; default the class's ``default_grid``.
        metric: ``"aae"`` (default; :func:`tcn_ahrs.metrics.aae`), another metric name of
            :mod:`tcn_ahrs.metrics`, or a callable ``(q_gt, q_est, mask) -> float`` (lower is better).
        init: ``"gt"`` or ``"sensor"`` initial attitude (see :func:`evaluate_params`).
        max_batch: parameter sets per batched filter call.
        **fixed: other estimator fields (e.g. ``use_mag=False``).
    Returns:
        ``(best_params, table)``: the combination with the lowest mean metric over the
        recordings (recordings without scored samples are ignored), and one row per
        combination sorted best first: ``{"params": {...}, "score": mean, "per_sequence": {name: value}}``.
    """
    est = estimator_cls.with_params(**fixed) if isinstance(estimator_cls, ClassicalEstimator) else estimator_cls(**fixed)
    grid = dict(grid if grid is not None else type(est).default_grid)
    if not grid:
        raise ValueError(f"{type(est).__name__}: empty grid and no default_grid")
    names = set(est.param_names())
    bad = [k for k in grid if k not in names]
    if bad:
        raise ValueError(f"{type(est).__name__}: cannot tune {bad}; parameters are {sorted(names)}")
    if not sequences:
        raise ValueError("tune_grid needs at least one training recording")
    combos = grid_combinations(grid)
    scores = np.stack([evaluate_params(est, s, combos, metric, init, max_batch) for s in sequences], 1)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(scores)
        mean = np.where(valid.any(1), np.nansum(np.where(valid, scores, 0.0), 1) / np.maximum(valid.sum(1), 1), np.inf)
    order = np.argsort(mean, kind="stable")
    table = [{"params": dict(combos[i]), "score": float(mean[i]),
              "per_sequence": {s.name: float(scores[i, j]) for j, s in enumerate(sequences)}} for i in order]
    return dict(combos[order[0]]), table


def tune_gradient(
    estimator_cls,
    sequences: Sequence[ImuSequence],
    params: Sequence[str],
    steps: int = 20,
    lr: float = 0.1,
    window: Optional[int] = None,
    **fixed,
) -> Tuple[Dict[str, float], List[float]]:
    """Gradient descent on ``log(param)`` (positive parameters) through the differentiable filter.

    The loss is a smooth AAE surrogate: mean squared rotation angle (rad^2) between estimate
    and ground truth on scored samples (the first ``window`` samples of each recording if given,
    to keep the backward pass short). Returns the tuned parameters and the loss history.
    """
    from . import so3

    est = estimator_cls.with_params(**fixed) if isinstance(estimator_cls, ClassicalEstimator) else estimator_cls(**fixed)
    start = {k: float(getattr(est, k)) for k in params}
    logp = {k: torch.tensor(math.log(v), dtype=est.dtype, requires_grad=True) for k, v in start.items()}
    opt = torch.optim.Adam(list(logp.values()), lr=lr)
    history = []
    for _ in range(steps):
        opt.zero_grad()
        loss = 0.0
        for seq in sequences:
            s = seq if window is None else seq.slice(0, min(window, len(seq)))
            mask = torch.as_tensor(s.scored())
            if not bool(mask.any()):
                continue
            p = dict(est.params())
            p.update({k: torch.exp(v) for k, v in logp.items()})
            gyro, accel, dt, q0, mag, m_from_n = est._inputs(s, initial_quat(s))
            q = est._filter(gyro, accel, dt, q0, mag, p)["quat"]
            if m_from_n is not None:
                q = so3.quat_mul(so3.quat_conj(m_from_n), q)
            q_gt = torch.as_tensor(np.nan_to_num(s.quat), dtype=est.dtype)
            ang = so3.quat_log(so3.quat_mul(so3.quat_conj(q_gt[mask]), q[mask]))
            loss = loss + (ang * ang).sum(-1).mean() / len(sequences)
        loss.backward()
        opt.step()
        history.append(float(loss.detach()))
    return {k: float(torch.exp(v.detach())) for k, v in logp.items()}, history
