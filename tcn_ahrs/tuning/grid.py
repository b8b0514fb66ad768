"""Tuning of classical filter parameters on training recordings (grid search, batched).

The paper tunes its ECF baseline "on training sequences"; we do the same for every
classical estimator (:mod:`tcn_ahrs.estimators.classical`): the parameters each class tunes by
default are its ``tunable`` (with a ``default_grid``):

* ``ClosedLoopECF``: ``k_norm`` (1/s), ``a_min`` (m/s^2)
* ``Mahony``: ``k_p`` (1/s), ``k_i`` (1/s^2)
* ``Madgwick``: ``beta`` (rad/s)
* ``ESEKF`` / ``RobustESEKF``: ``accel_noise`` (m/s^2/sqrt(Hz)), ``mag_noise`` (rad/sqrt(Hz))

The loss is the project's AAE scored as every table scores it (:func:`tcn_ahrs.metrics.scored_metric`,
the yardstick of :mod:`tcn_ahrs.metrics`), averaged over the recordings. All recordings x all
parameter points run in ONE batched filter call (the time loop is shared), in chunks of
``max_batch``; :func:`tune_method` tunes any registered method by name (the PyPI peers one run
per point).
"""
from __future__ import annotations

import math
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from ..estimators.base import initial_quat
from ..estimators.registry import grid_combinations  # noqa: F401  (re-exported: tuning.grid_combinations)
from ..estimators.classical import ClassicalEstimator
from ..sequence import ImuSequence

MetricFn = Callable[[np.ndarray, np.ndarray, np.ndarray], float]


def _metric_fn(metric: Union[str, MetricFn]) -> Callable:
    """``fn(seq, quat, axes) -> float``: a metric name is scored by the yardstick of every table
    (:func:`tcn_ahrs.metrics.scored_metric`: settling time, heading alignment, 9-axis on magnetic
    north unaligned); a callable ``(q_gt, q_est, mask)`` gets the recording's scored samples."""
    if callable(metric):
        return lambda seq, quat, axes: metric(seq.quat, quat, seq.scored())
    from .. import metrics

    if f"{metric}_deg" not in metrics.metric_keys():
        raise ValueError(f"unknown metric {metric!r}: expected a metric of tcn_ahrs.metrics without its _deg "
                         "(e.g. 'aae', 'aye', 'inclination') or a callable (q_gt, q_est, mask) -> float")
    return lambda seq, quat, axes: metrics.scored_metric(seq, quat, axes, f"{metric}_deg")


def _initial_quats(seqs: Sequence[ImuSequence], init: str) -> List[Optional[np.ndarray]]:
    if init not in ("gt", "sensor"):
        raise ValueError(f"init must be 'gt' or 'sensor', got {init!r}")
    for s in seqs:
        if s.quat is None:
            raise ValueError(f"{s.source}: field 'quat': tuning needs ground truth, the recording has none")
    return [initial_quat(s) if init == "gt" else None for s in seqs]


def score_points(estimator: ClassicalEstimator, seqs: Sequence[ImuSequence], points: Sequence[Mapping[str, float]],
                 metric: Union[str, MetricFn] = "aae", init: str = "gt", max_batch: int = 256) -> np.ndarray:
    """Metric of each parameter point on each recording, (P, R): ALL recordings x a chunk of
    points in ONE batched filter call (:meth:`ClassicalEstimator.quat_batch`; recordings padded
    to the longest, padding never scored), ``max_batch`` runs per call.

    ``init="gt"`` starts the filters at the ground-truth attitude of the first valid sample
    (:func:`tcn_ahrs.estimators.base.initial_quat`); ``"sensor"`` lets them initialise from the
    accelerometer/magnetometer (TRIAD). A recording without scored samples scores NaN.
    """
    fn = _metric_fn(metric)
    q0s = _initial_quats(seqs, init)
    out = np.full((len(points), len(seqs)), np.nan)
    per_call = max(1, int(max_batch) // max(1, len(seqs)))
    for start in range(0, len(points), per_call):
        chunk = points[start:start + per_call]
        params = {k: torch.tensor([[c[k]] for c in chunk], dtype=estimator.dtype) for k in chunk[0]}
        quat, _ = estimator.quat_batch(seqs, q0s, params)
        quat = quat.reshape(-1, len(seqs), quat.shape[-2], 4)
        if quat.shape[0] == 1 and len(chunk) > 1:  # no parameter actually batched
            quat = quat.expand(len(chunk), -1, -1, -1)
        qn = quat.cpu().numpy()
        for j, s in enumerate(seqs):
            if s.scored().any():
                for i in range(len(chunk)):
                    out[start + i, j] = fn(s, qn[i, j, :len(s)], min(estimator.axes, s.num_axes))
    return out


def evaluate_params(estimator: ClassicalEstimator, seq: ImuSequence, combos: Sequence[Mapping[str, float]],
                    metric: Union[str, MetricFn] = "aae", init: str = "gt", max_batch: int = 256) -> np.ndarray:
    """Metric of each parameter combination on one recording, (len(combos),)."""
    return score_points(estimator, [seq], combos, metric, init, max_batch)[:, 0]


def _ranked(points: Sequence[Mapping[str, Any]], scores: np.ndarray,
            seqs: Sequence[ImuSequence]) -> Tuple[Dict[str, Any], List[dict]]:
    """(P, R) scores -> best point and the table sorted best first. Recordings without scored
    samples (NaN for every point) are ignored; a point that diverges (non-finite score) on any
    other recording scores inf and cannot win."""
    keep = ~np.isnan(scores).all(0)
    if not keep.any():
        raise ValueError("tuning: no recording with scored ground truth samples")
    sub = scores[:, keep]
    with np.errstate(invalid="ignore"):
        mean = np.where(np.isfinite(sub).all(1), np.where(np.isfinite(sub), sub, 0.0).mean(1), np.inf)
    order = np.argsort(mean, kind="stable")
    table = [{"params": dict(points[i]), "score": float(mean[i]),
              "per_sequence": {s.name: float(scores[i, j]) for j, s in enumerate(seqs)}} for i in order]
    return dict(points[order[0]]), table


def tune_grid(
    estimator_cls,
    sequences: Sequence[ImuSequence],
    grid: Optional[Union[Mapping[str, Sequence], Sequence[Mapping[str, Any]]]] = None,
    metric: Union[str, MetricFn] = "aae",
    init: str = "gt",
    max_batch: int = 256,
    **fixed,
) -> Tuple[Dict[str, float], List[dict]]:
    """Grid search of a classical estimator's parameters on training recordings (the one tuner).

    Args:
        estimator_cls: a :class:`ClassicalEstimator` subclass (or an instance, whose other
            parameters are kept).
        sequences: training recordings with ground truth.
        grid: parameter name -> candidate values (their product is searched), or a list of
            points (dicts); default the class's ``default_grid``.
        metric: ``"aae"`` (default; :func:`tcn_ahrs.metrics.aae`), another metric name of
            :mod:`tcn_ahrs.metrics`, or a callable ``(q_gt, q_est, mask) -> float`` (lower is better).
        init: ``"gt"`` or ``"sensor"`` initial attitude (see :func:`score_points`).
        max_batch: filter runs (points x recordings) per batched call.
        **fixed: other estimator fields (e.g. ``axes=6``).
    Returns:
        ``(best_params, table)``: the point with the lowest mean metric over the recordings,
        and one row per point sorted best first: ``{"params": {...}, "score": mean,
        "per_sequence": {name: value}}`` (see :func:`_ranked` for NaN/divergence).
    """
    est = estimator_cls.with_params(**fixed) if isinstance(estimator_cls, ClassicalEstimator) else estimator_cls(**fixed)
    grid = grid if grid is not None else type(est).default_grid
    points = grid_combinations(grid) if isinstance(grid, Mapping) else [dict(p) for p in grid]
    if not points:
        raise ValueError(f"{type(est).__name__}: empty grid and no default_grid")
    names = set(est.param_names())
    bad = sorted({k for p in points for k in p if k not in names})
    if bad:
        raise ValueError(f"{type(est).__name__}: cannot tune {bad}; parameters are {sorted(names)}")
    if not sequences:
        raise ValueError("tune_grid needs at least one training recording")
    return _ranked(points, score_points(est, sequences, points, metric, init, max_batch), sequences)


def tune_method(method: str, axes: int, sequences: Sequence[ImuSequence],
                grid: Optional[Sequence[Mapping[str, Any]]] = None, metric: Union[str, MetricFn] = "aae",
                max_batch: int = 128, device: str = "cpu") -> Tuple[Dict[str, Any], List[dict]]:
    """Tune a registered method (:mod:`tcn_ahrs.estimators.registry`) over its grid (or
    ``grid``): classical filters batched (:func:`tune_grid`), other methods (the PyPI peers)
    one run per point and recording. Same return as :func:`tune_grid`."""
    import warnings

    from ..estimators import registry

    m = registry.get(method)
    points = [dict(p) for p in (grid if grid is not None else m.grid)]
    if not points:
        raise ValueError(f"method {method!r} has no tuning grid")
    if m.kind == "classical":
        return tune_grid(registry.build(method, axes, device=device), sequences, points, metric, "gt", max_batch)
    fn = _metric_fn(metric)
    q0s = _initial_quats(sequences, "gt")
    views = [s.without_mag() if (axes == 6 and s.has_mag) else s for s in sequences]
    scores = np.full((len(points), len(sequences)), np.nan)
    for i, p in enumerate(points):
        est = registry.build(method, axes, **p)
        for j, (s, v) in enumerate(zip(sequences, views)):
            if not s.scored().any():
                continue
            try:
                scores[i, j] = fn(s, est.run(v, q0s[j]).quat, v.num_axes)
            except (FloatingPointError, np.linalg.LinAlgError, ValueError) as e:
                scores[i, j] = np.inf
                warnings.warn(f"tuning {method}{axes}d {p} on {s.name}: {type(e).__name__}: {e}")
    return _ranked(points, scores, sequences)


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
    from .. import so3

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


def tuning_clips(seqs: Sequence[ImuSequence], max_seconds: Optional[float] = 60.0, lead_seconds: float = 10.0,
                 max_recordings: Optional[int] = None) -> Tuple[List[ImuSequence], List[dict]]:
    """The clips tuning runs on, and a record of each (name, source, start_s, duration_s).

    Keeps recordings with scored samples; at most ``max_recordings`` of them, evenly spaced
    over the list. Each is cut to ``[k0 - lead, k0 - lead + max_seconds]`` with ``k0`` its first
    scored sample (``max_seconds=None``: the whole recording).
    """
    seqs = [s for s in seqs if s.quat is not None and s.scored().any()]
    if max_recordings is not None and 0 < int(max_recordings) < len(seqs):
        idx = np.unique(np.round(np.linspace(0, len(seqs) - 1, int(max_recordings))).astype(int))
        seqs = [seqs[i] for i in idx]
    clips, record = [], []
    for s in seqs:
        if max_seconds is None or max_seconds <= 0:
            c, start = s, 0
        else:
            k0 = int(np.argmax(s.scored()))
            start = max(0, k0 - int(round(lead_seconds * s.rate)))
            stop = min(len(s), start + int(round(float(max_seconds) * s.rate)) + 1)
            c = s.slice(start, stop)
            if not c.scored().any():
                continue
        clips.append(c)
        record.append({"name": s.name, "source": s.source, "start_s": round(float(s.time[start] - s.time[0]), 3),
                       "time_range": [round(float(c.time[0]), 3), round(float(c.time[-1]), 3)],
                       "duration_s": round(c.duration, 3), "n_samples": len(c),
                       "n_scored": int(c.scored().sum())})
    return clips, record
