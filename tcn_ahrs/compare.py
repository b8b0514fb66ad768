"""Method comparison: build the estimators, tune them on training recordings, run them through
the evaluation runner (:func:`tcn_ahrs.evaluate.evaluate`) and write the paper-style tables.

Used by ``scripts/compare.py`` (classical methods, optionally peers and checkpoints) and by
``scripts/benchmark.py accuracy`` (the same code path with the PyPI peers on by default).

Methods (:data:`CLASSICAL_METHODS`, :data:`PEER_METHODS`):

=================  ==============================================================================
``raw``            strapdown integration of the raw gyro (:class:`~tcn_ahrs.estimators.raw.RawIntegration`)
``ecf`` ...        the project's batched torch filters (:mod:`tcn_ahrs.estimators.classical`):
                   ``ecf``, ``mahony``, ``madgwick``, ``eskf``, ``robust_eskf``
``vqf`` ...        PyPI peers (:mod:`tcn_ahrs.estimators.peers`): ``vqf``, ``imufusion``,
                   ``ahrs_madgwick``, ``ahrs_mahony``, ``ahrs_ekf``, ``riann`` (6D only,
                   heading-free); skipped with a warning when their library is missing
learned            checkpoints ``{label: path}`` (:class:`~tcn_ahrs.estimators.learned.LearnedEstimator`)
=================  ==============================================================================

Columns: every classical/peer method appears once per axes variant, ``<method>9d`` (uses the
magnetometer) and ``<method>6d`` (does not): on 9-axis data both when ``both_axes`` is true,
else only 9D; on 6-axis data only 6D. Each appears with the authors' / the project's default
parameters (``vqf9d``) and, with ``tune=True``, tuned on training recordings
(``vqf9d (tuned)``); ``variants`` picks which of the two.

Tuning (never on evaluation recordings): the training parts of the training recordings
(``load_split(data, "train")``), each cut to one clip of at most
``max_seconds_per_recording`` seconds starting ``lead_seconds`` before its first scored
sample (BROAD: the rest phase before the movement is mostly not scored; the lead lets the
filters settle), at most ``recordings`` of them (evenly spaced over the sorted list so
each group stays represented). The loss is the mean AAE over the clips
(:func:`tcn_ahrs.metrics.aae`, filters started at ground truth). Project filters search
their class's ``default_grid`` (the grid of :func:`tcn_ahrs.tuning.tune_grid`) with ALL
clips x ALL grid points in one batched filter call per chunk (clips padded to the longest,
padding ignored; identical to ``tune_grid``, which loops over recordings, checked in the
tests); peers loop over :data:`tcn_ahrs.estimators.peers.PEER_GRIDS`. The chosen parameters,
scores and clip list go to ``results["tuning"]``.

Evaluation: the project filters expose ``run_batch(seqs, init_quats)`` (all recordings in one
padded filter call), which :func:`~tcn_ahrs.evaluate.evaluate` prefers over per-recording
``run``; the default and tuned columns of one filter share that call (:class:`SharedBatch`,
(P, R) batch), so their ``run_time_s`` is the group's time split over recordings, all of it
on the first column of the group (``columns[c]["batched_with"]``) - accuracy runs, not timing. Heading-free estimators (RIANN) are scored on inclination only (AAE, AYE, total and
heading are ``null``); ``inclination_deg`` is reported for every method.
"""
from __future__ import annotations

import json
import math
import sys
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np
import torch

from . import so3
from .estimators.base import EstimatorOutput, initial_quat
from .estimators.classical import ClassicalEstimator, ClosedLoopECF, ESEKF, Madgwick, Mahony, RobustESEKF
from .sequence import ImuSequence

CLASSICAL_CLASSES = {"ecf": ClosedLoopECF, "mahony": Mahony, "madgwick": Madgwick, "eskf": ESEKF,
                     "robust_eskf": RobustESEKF}
"""Project filter name -> :class:`ClassicalEstimator` subclass."""

PEER_KEYS = {"vqf": "vqf", "imufusion": "imufusion", "ahrs_madgwick": "madgwick",
             "ahrs_mahony": "mahony", "ahrs_ekf": "ekf", "riann": "riann"}
"""Comparison method name -> key in :data:`tcn_ahrs.estimators.peers.PEER_CLASSES`."""

CLASSICAL_METHODS = ("raw",) + tuple(CLASSICAL_CLASSES)
PEER_METHODS = tuple(PEER_KEYS)
ALL_METHODS = CLASSICAL_METHODS + PEER_METHODS
VARIANTS = ("default", "tuned")
TUNED_SUFFIX = " (tuned)"


# ===========================================================================
# the project filters as batched estimators
# ===========================================================================


def _param_tensors(est: ClassicalEstimator, params: Mapping[str, Any]) -> Dict[str, Any]:
    """Parameters as ClassicalEstimator.run_params converts them (numbers -> tensors, bools and
    None stay)."""
    return {k: (torch.as_tensor(v, dtype=est.dtype, device=est.device)
                if isinstance(v, (int, float, list, tuple, np.ndarray, torch.Tensor)) and not isinstance(v, bool)
                else v)
            for k, v in params.items()}


def _pad_stack(arrays: Sequence[torch.Tensor], n: int) -> torch.Tensor:
    """(N_i, ...) tensors -> (R, n, ...), each padded by repeating its last sample (the filters
    are causal: padding after the end never changes the samples before it)."""
    out = []
    for a in arrays:
        if a.shape[0] < n:
            a = torch.cat([a, a[-1:].expand((n - a.shape[0],) + tuple(a.shape[1:]))], 0)
        out.append(a)
    return torch.stack(out, 0)


class ClassicalMethod:
    """A project filter (:class:`ClassicalEstimator`) run at a fixed number of axes, with a
    batched multi-recording path.

    ``axes == 6`` never uses the magnetometer (the evaluation runner also hands it the 6-axis
    view of the recording); ``axes == 9`` uses it when the recording has one.
    """

    heading_free = False

    def __init__(self, estimator: ClassicalEstimator, axes: int, name: Optional[str] = None):
        if int(axes) not in (6, 9):
            raise ValueError(f"axes: expected 6 or 9, got {axes!r}")
        self.axes = int(axes)
        self.estimator = estimator.with_params(use_mag=(self.axes == 9))
        self.name = name or f"{type(estimator).name}{self.axes}d"

    def __repr__(self) -> str:
        return f"ClassicalMethod({self.name!r}, {self.estimator!r})"

    def quat_batch(self, seqs: Sequence[ImuSequence], init_quats: Sequence[Optional[np.ndarray]],
                   params: Optional[Mapping[str, Any]] = None) -> Tuple[torch.Tensor, Dict[str, torch.Tensor]]:
        """Run on all recordings in ONE filter call.

        Args:
            seqs: R recordings (any lengths; padded to the longest with their last sample).
            init_quats: R initial attitudes (or ``None``: TRIAD), applied at sample 0.
            params: parameter overrides; (P, 1)-shaped tensors batch P parameter sets against
                    the R recordings.
        Returns:
            ``quat`` (R, N_max, 4) or (P, R, N_max, 4) nav_from_body (padding beyond each
            recording's length is meaningless), and the other outputs with the same leading dims.
        """
        est = self.estimator
        if len(seqs) != len(init_quats):
            raise ValueError(f"{self.name}: {len(seqs)} recordings but {len(init_quats)} initial attitudes")
        if not seqs:
            raise ValueError(f"{self.name}: no recordings")
        ins = [est._inputs(s, q) for s, q in zip(seqs, init_quats)]  # the single-run code path
        has_mag = [x[4] is not None for x in ins]
        if any(has_mag) and not all(has_mag):
            raise ValueError(f"{self.name}: batch mixes recordings with and without magnetometer; "
                             "run them separately")
        n = max(len(s) for s in seqs)
        gyro = _pad_stack([x[0] for x in ins], n)
        accel = _pad_stack([x[1] for x in ins], n)
        dt = _pad_stack([x[2] for x in ins], n)
        q0 = torch.stack([x[3] for x in ins], 0)
        mag = _pad_stack([x[4] for x in ins], n) if all(has_mag) else None
        m_from_n = [x[5] for x in ins]
        p = dict(est.params())
        for k, v in (params or {}).items():
            if k not in p:
                raise ValueError(f"{type(est).__name__}: unknown parameter {k!r}; expected one of {sorted(p)}")
            p[k] = v
        p = _param_tensors(est, p)
        with torch.no_grad():
            out = est._filter(gyro, accel, dt, q0, mag, p)
        q = out["quat"]
        if all(m is not None for m in m_from_n):
            m = torch.stack(m_from_n, 0)[:, None, :]  # (R, 1, 4) broadcasts over (..., R, N, 4)
            q = so3.quat_mul(so3.quat_conj(m).expand_as(q), q)
        out["quat"] = so3.quat_positive(so3.quat_normalize(q))
        return out["quat"], {k: v for k, v in out.items() if k != "quat"}

    _shared: Optional["SharedBatch"] = None

    def run_batch(self, seqs: Sequence[ImuSequence],
                  init_quats: Sequence[Optional[np.ndarray]]) -> List[EstimatorOutput]:
        """One :class:`EstimatorOutput` per recording, computed in one batched filter call
        (shared with the other parameter variants of the same filter when grouped by
        :func:`share_batches`)."""
        if self._shared is not None:
            return self._shared.outputs(self, seqs, init_quats)
        quat, sig = self.quat_batch(seqs, init_quats)
        return _split_outputs(quat, sig, seqs)

    def run(self, seq: ImuSequence, init_quat: Optional[np.ndarray] = None) -> EstimatorOutput:
        """One recording on its own (never through a shared batch)."""
        quat, sig = self.quat_batch([seq], [init_quat])
        return _split_outputs(quat, sig, [seq])[0]


def _split_outputs(quat: torch.Tensor, sig: Dict[str, torch.Tensor], seqs) -> List[EstimatorOutput]:
    """(R, N_max, ...) batch outputs -> one EstimatorOutput per recording, padding removed."""
    res = []
    for i, s in enumerate(seqs):
        n = len(s)
        res.append(EstimatorOutput(quat=quat[i, :n].cpu().numpy(),
                                   signals={k: v[i, :n].cpu().numpy() for k, v in sig.items()
                                            if v.dim() >= 2 and v.shape[0] == len(seqs)}))
    return res


class SharedBatch:
    """Runs P parameter variants of one filter (same class and axes) in ONE batched call over
    all recordings, (P, R) batch; each member's ``run_batch`` takes its share. Halves the
    evaluation time of default + tuned columns (the time loop is the cost)."""

    def __init__(self, members: Sequence[ClassicalMethod]):
        self.members = list(members)
        first = self.members[0].estimator
        p_all = [m.estimator.params() for m in self.members]
        self.params: Dict[str, Any] = {}
        for k in p_all[0]:
            vals = [p[k] for p in p_all]
            if all(v == vals[0] for v in vals):
                continue
            self.params[k] = torch.tensor([[float(v)] for v in vals], dtype=first.dtype)
        self._key = None
        self._out: Dict[str, List[EstimatorOutput]] = {}

    @staticmethod
    def can_share(members: Sequence[ClassicalMethod]) -> bool:
        """Same class, axes and non-numeric parameters; differing ones all numbers."""
        if len(members) < 2 or len({(type(m.estimator), m.axes) for m in members}) != 1:
            return False
        p_all = [m.estimator.params() for m in members]
        base = {f: getattr(members[0].estimator, f) for f in ("use_mag", "heading_ref", "device", "dtype")}
        if any({f: getattr(m.estimator, f) for f in base} != base for m in members):
            return False
        for k in p_all[0]:
            vals = [p[k] for p in p_all]
            if all(v == vals[0] for v in vals):
                continue
            if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals):
                return False
        return True

    def outputs(self, member: ClassicalMethod, seqs, init_quats) -> List[EstimatorOutput]:
        key = tuple((s.name, len(s), s.has_mag, float(s.gyro[0, 0])) for s in seqs)
        if key != self._key or member.name not in self._out:
            quat, sig = self.members[0].quat_batch(seqs, init_quats, self.params)
            if quat.dim() == 3:  # no parameter differs
                quat, sig = quat[None], {k: v[None] for k, v in sig.items()}
            self._key = key
            self._out = {m.name: _split_outputs(quat[i], {k: v[i] for k, v in sig.items()}, seqs)
                         for i, m in enumerate(self.members)}
        return self._out.pop(member.name)


def share_batches(estimators: Sequence) -> Dict[str, str]:
    """Group the :class:`ClassicalMethod` columns of the same filter and axes (default + tuned)
    into :class:`SharedBatch` runs. Returns column -> first column of its group."""
    groups: Dict[Tuple[type, int], List[ClassicalMethod]] = {}
    for e in estimators:
        if isinstance(e, ClassicalMethod):
            groups.setdefault((type(e.estimator), e.axes), []).append(e)
    shared = {}
    for members in groups.values():
        if SharedBatch.can_share(members):
            sb = SharedBatch(members)
            for m in members:
                m._shared = sb
                shared[m.name] = members[0].name
    return shared

    def run(self, seq: ImuSequence, init_quat: Optional[np.ndarray] = None) -> EstimatorOutput:
        return self.run_batch([seq], [init_quat])[0]


# ===========================================================================
# method specs and the registry
# ===========================================================================


@dataclass
class MethodSpec:
    """One column of the comparison before it is built.

    name: column label (``"vqf9d"``, ``"vqf9d (tuned)"``, a checkpoint label);
    method: registry name (``"vqf"``) or ``"learned"``; axes: 6/9 (None: raw/learned);
    variant: ``"default"`` | ``"tuned"``; params: constructor keyword arguments
    (tuned ones filled in by :func:`tune_methods`); ckpt: checkpoint path for learned ones.
    """

    name: str
    method: str
    axes: Optional[int] = None
    variant: str = "default"
    params: Dict[str, Any] = field(default_factory=dict)
    ckpt: Optional[str] = None

    @property
    def kind(self) -> str:
        if self.method == "learned":
            return "learned"
        if self.method == "raw":
            return "raw"
        return "classical" if self.method in CLASSICAL_CLASSES else "peer"


def _peer_axes(method: str) -> Tuple[int, ...]:
    from .estimators.peers import PEER_AXES

    return PEER_AXES[PEER_KEYS[method]]


def method_specs(methods: Sequence[str], data_axes: int = 9, both_axes: bool = True,
                 variants: Sequence[str] = ("default",), ckpts: Optional[Mapping[str, str]] = None) -> List[MethodSpec]:
    """The columns to compare, in order: for each method, each axes variant (9D first), each
    parameter variant; then the checkpoints.

    Raises ``ValueError`` for an unknown method name or variant.
    """
    data_axes = int(data_axes)
    if data_axes not in (6, 9):
        raise ValueError(f"data.axes: expected 6 or 9, got {data_axes!r}")
    bad = [m for m in methods if m not in ALL_METHODS]
    if bad:
        raise ValueError(f"methods: unknown method(s) {bad}; expected names among {list(ALL_METHODS)} "
                         "(learned models go in ckpts={label: path})")
    badv = [v for v in variants if v not in VARIANTS]
    if badv or not variants:
        raise ValueError(f"variants: expected a non-empty subset of {list(VARIANTS)}, got {list(variants)}")
    axes_list = [9, 6] if (data_axes == 9 and both_axes) else [data_axes]
    specs: List[MethodSpec] = []
    for m in dict.fromkeys(methods):
        if m == "raw":
            specs.append(MethodSpec("Raw IMU", "raw"))
            continue
        allowed = (6, 9) if m in CLASSICAL_CLASSES else _peer_axes(m)
        for ax in axes_list:
            if ax not in allowed:
                continue
            for v in variants:
                if v == "tuned" and m == "riann":
                    continue  # no tunable parameters
                base = f"{m}{ax}d"
                specs.append(MethodSpec(base + (TUNED_SUFFIX if v == "tuned" else ""), m, ax, v))
    for label, path in (ckpts or {}).items():
        specs.append(MethodSpec(str(label), "learned", ckpt=str(path)))
    names = [s.name for s in specs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"duplicate column names {dup}: checkpoint labels must differ from method columns")
    return specs


def build_estimator(spec: MethodSpec, device: str = "cpu", reanchor: Optional[int] = None):
    """The estimator of one spec (raises :class:`~tcn_ahrs.estimators.peers.PeerUnavailable`
    when a peer's library is missing)."""
    if spec.kind == "raw":
        from .estimators.raw import RawIntegration

        return RawIntegration()
    if spec.kind == "learned":
        from .estimators.learned import LearnedEstimator

        return LearnedEstimator(spec.ckpt, name=spec.name, device=device, reanchor=reanchor)
    if spec.kind == "classical":
        cls = CLASSICAL_CLASSES[spec.method]
        return ClassicalMethod(cls(device=device, **spec.params), spec.axes, name=spec.name)
    from .estimators.peers import make_peer

    est = make_peer(PEER_KEYS[spec.method], spec.axes, **spec.params)
    est.name = spec.name
    return est


def build_estimators(specs: Sequence[MethodSpec], device: str = "cpu",
                     reanchor: Optional[int] = None) -> Tuple[list, List[MethodSpec]]:
    """Estimators of ``specs``; peers whose library is missing are skipped with ONE warning
    naming them. Returns ``(estimators, specs_kept)``."""
    from .estimators.peers import INSTALL_HINT, PeerUnavailable

    out, kept, missing = [], [], []
    for s in specs:
        try:
            out.append(build_estimator(s, device, reanchor))
            kept.append(s)
        except PeerUnavailable as e:
            missing.append(f"{s.name} ({e})")
    if missing:
        warnings.warn(f"peer estimators skipped (library not installed): {'; '.join(missing)}; "
                      f"install them with: {INSTALL_HINT}", stacklevel=2)
    return out, kept


_TRAIN_ALIASES = {"robust": "robust_eskf", "esekf": "eskf"}


def baseline_estimators(names) -> list:
    """Baselines by short name for the training/evaluation scripts: ``raw`` (Raw IMU), project
    filters (``ecf``, ``mahony``, ``madgwick``, ``eskf``, ``robust_eskf``; named after the
    method, using the magnetometer when the recording has one) and peers (``vqf9d``-style names
    or the method name for 9D). Unavailable or unknown ones are skipped with a warning (a
    missing baseline must not lose a trained model's evaluation)."""
    out = []
    for n in names or []:
        n = _TRAIN_ALIASES.get(str(n), str(n))
        try:
            if n == "raw":
                from .estimators.raw import RawIntegration

                out.append(RawIntegration())
            elif n in CLASSICAL_CLASSES:
                out.append(CLASSICAL_CLASSES[n]())
            else:
                axes = 9
                if n[-2:] in ("6d", "9d") and n[:-2] in PEER_KEYS:
                    n, axes = n[:-2], int(n[-2])
                if n not in PEER_KEYS:
                    raise ValueError(f"unknown baseline; expected one of {list(ALL_METHODS)}")
                if axes not in _peer_axes(n):
                    axes = _peer_axes(n)[0]
                out.append(build_estimator(MethodSpec(f"{n}{axes}d", n, axes)))
        except Exception as e:  # noqa: BLE001
            warnings.warn(f"baseline {n!r} unavailable, skipped: {type(e).__name__}: {e}")
    return out


# ===========================================================================
# tuning
# ===========================================================================


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


def _mean_score(scores: np.ndarray) -> np.ndarray:
    """(P, R) -> (P,) mean over recordings with a finite score; inf if none (diverged)."""
    valid = np.isfinite(scores)
    with np.errstate(invalid="ignore"):
        s = np.where(valid, scores, 0.0).sum(1) / np.maximum(valid.sum(1), 1)
    # a combination that diverges on any clip must not win
    return np.where(valid.all(1), s, np.inf)


def tune_classical(method: str, axes: int, clips: Sequence[ImuSequence], grid: Optional[Mapping[str, list]] = None,
                   max_batch: int = 128, device: str = "cpu") -> Tuple[Dict[str, Any], List[dict]]:
    """Grid search of a project filter on the clips (see module docstring): same result as
    :func:`tcn_ahrs.tuning.tune_grid` (mean AAE over clips, started at ground truth), but all
    clips x grid points run batched. Returns ``(best_params, table)`` (table best first:
    ``{"params", "score", "per_sequence"}``)."""
    from .metrics import aae
    from .tuning import grid_combinations

    cls = CLASSICAL_CLASSES[method]
    grid = dict(grid if grid is not None else cls.default_grid)
    combos = grid_combinations(grid)
    wrapper = ClassicalMethod(cls(device=device), axes)
    views = [c.without_mag() if (axes == 6 and c.has_mag) else c for c in clips]
    q0s = [initial_quat(c) for c in clips]
    scores = np.full((len(combos), len(clips)), np.nan)
    per_call = max(1, int(max_batch) // max(1, len(clips)))
    for start in range(0, len(combos), per_call):
        chunk = combos[start:start + per_call]
        params = {k: torch.tensor([[c[k]] for c in chunk], dtype=wrapper.estimator.dtype) for k in chunk[0]}
        quat, _ = wrapper.quat_batch(views, q0s, params)
        quat = quat.reshape(-1, len(clips), quat.shape[-2], 4)
        if quat.shape[0] == 1 and len(chunk) > 1:
            quat = quat.expand(len(chunk), -1, -1, -1)
        qn = quat.cpu().numpy()
        for i in range(len(chunk)):
            for j, c in enumerate(clips):
                scores[start + i, j] = aae(c.quat, qn[i, j, :len(c)], c.scored())
    mean = _mean_score(scores)
    order = np.argsort(mean, kind="stable")
    table = [{"params": dict(combos[i]), "score": float(mean[i]),
              "per_sequence": {c.name: float(scores[i, j]) for j, c in enumerate(clips)}} for i in order]
    return dict(combos[order[0]]), table


def tune_peer(method: str, axes: int, clips: Sequence[ImuSequence]) -> Tuple[Dict[str, Any], List[dict]]:
    """Loop over :data:`~tcn_ahrs.estimators.peers.PEER_GRIDS` of a peer (each point run on each
    clip, started at ground truth where the library allows). Same return as
    :func:`tune_classical`."""
    from .estimators.peers import PEER_GRIDS, make_peer
    from .metrics import aae

    key = PEER_KEYS[method]
    combos = [dict(p) for p in PEER_GRIDS[key]]
    views = [c.without_mag() if (axes == 6 and c.has_mag) else c for c in clips]
    scores = np.full((len(combos), len(clips)), np.nan)
    for i, p in enumerate(combos):
        est = make_peer(key, axes, **p)
        for j, (c, v) in enumerate(zip(clips, views)):
            try:
                q = est.run(v, initial_quat(c)).quat
                scores[i, j] = aae(c.quat, q, c.scored())
            except (FloatingPointError, np.linalg.LinAlgError, ValueError) as e:
                warnings.warn(f"tuning {method}{axes}d {p} on {c.name}: {type(e).__name__}: {e}")
    mean = _mean_score(scores)
    order = np.argsort(mean, kind="stable")
    table = [{"params": _jsonable(combos[i]), "score": float(mean[i]),
              "per_sequence": {c.name: float(scores[i, j]) for j, c in enumerate(clips)}} for i in order]
    return dict(combos[order[0]]), table


def _jsonable(v):
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (np.floating, float)):
        v = float(v)
        return v if math.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, torch.Tensor):
        return _jsonable(v.tolist())
    return v


def tune_methods(specs: Sequence[MethodSpec], tune_seqs: Sequence[ImuSequence], max_seconds: Optional[float] = 60.0,
                 lead_seconds: float = 10.0, max_recordings: Optional[int] = None, max_batch: int = 128,
                 device: str = "cpu", verbose: bool = True) -> dict:
    """Fill in ``params`` of every ``variant == "tuned"`` spec (in place) from a grid search on
    clips of ``tune_seqs`` (training recordings only!). One search per (method, axes).

    Returns the tuning record ``{"recordings": [clip records], "max_seconds_per_recording",
    "lead_seconds", "methods": {column: {"params", "score_aae_deg", "default_params",
    "grid_size", "time_s", "top": [best 3 rows]}}}``.
    """
    from .estimators.peers import PeerUnavailable

    todo = [s for s in specs if s.variant == "tuned"]
    clips, rec = tuning_clips(tune_seqs, max_seconds, lead_seconds, max_recordings)
    record = {"recordings": rec, "max_seconds_per_recording": max_seconds, "lead_seconds": lead_seconds,
              "max_recordings": max_recordings, "methods": {}}
    if not todo:
        return record
    if not clips:
        raise ValueError("tuning: no training recording with scored ground truth; tune=false to skip tuning")
    cache: Dict[Tuple[str, int], Tuple[dict, list, float]] = {}
    for s in todo:
        key = (s.method, int(s.axes))
        if key not in cache:
            t0 = time.perf_counter()
            try:
                if s.kind == "classical":
                    best, table = tune_classical(s.method, s.axes, clips, max_batch=max_batch, device=device)
                else:
                    best, table = tune_peer(s.method, s.axes, clips)
            except PeerUnavailable:
                cache[key] = None  # the build step skips it with the warning
                continue
            cache[key] = (best, table, time.perf_counter() - t0)
            if verbose:
                print(f"tuned {s.method}{s.axes}d on {len(clips)} clips in {cache[key][2]:.1f} s: {best} "
                      f"(AAE {table[0]['score']:.2f} deg)", file=sys.stderr)
        if cache[key] is None:
            continue
        best, table, dt = cache[key]
        s.params = dict(best)
        if s.kind == "classical":
            default = {k: getattr(CLASSICAL_CLASSES[s.method](), k) for k in best}
        else:
            default = {}
        d_row = next((r for r in table if all(_jsonable(r["params"].get(k)) == _jsonable(v) for k, v in default.items())
                      and default), None)
        record["methods"][s.name] = {
            "params": _jsonable(best), "score_aae_deg": _jsonable(table[0]["score"]),
            "grid_size": len(table), "time_s": round(dt, 2),
            "default_params": _jsonable(default) if default else "authors' defaults (see estimators/peers.py)",
            "default_in_grid_score_aae_deg": _jsonable(d_row["score"]) if d_row else None,
            "top": _jsonable(table[:3]),
        }
    return record


# ===========================================================================
# the comparison
# ===========================================================================


def compare(eval_seqs: Sequence[ImuSequence], tune_seqs: Sequence[ImuSequence] = (),
            methods: Sequence[str] = CLASSICAL_METHODS, data_axes: Optional[int] = None, both_axes: bool = True,
            variants: Sequence[str] = VARIANTS, tune: bool = True, ckpts: Optional[Mapping[str, str]] = None,
            ablation_ckpts: Optional[Mapping[str, str]] = None, out_dir=None,
            tune_max_seconds_per_recording: Optional[float] = 60.0, tune_lead_seconds: float = 10.0,
            tune_recordings: Optional[int] = None, tune_max_batch: int = 128, dataset: Optional[str] = None,
            plots: bool = False, trajectories: bool = False, align: bool = True, device: str = "cpu",
            reanchor: Optional[int] = None, on_calibrated: Optional[Mapping[str, str]] = None,
            verbose: bool = False, progress: bool = True, extra: Optional[dict] = None) -> dict:
    """Build, tune, evaluate, write tables.

    Args:
        eval_seqs: recordings to score (with ground truth).
        tune_seqs: TRAINING recordings for tuning (must not share samples with ``eval_seqs``:
            same name and overlapping time span is an error).
        methods: names among :data:`ALL_METHODS`.
        data_axes: 9 or 6 (default: 9 if every evaluation recording has a magnetometer).
        both_axes: on 9-axis data also the 6D variant of each method.
        variants: ``"default"`` and/or ``"tuned"``; ``tune=False`` drops ``"tuned"``.
        ckpts: learned checkpoints ``{label: path}`` (columns after the methods).
        on_calibrated: ``{label: checkpoint}``: every classical/peer column once more, run on
            that model's calibrated signals (``"<column> on <label>"``).
        ablation_ckpts: ``{label: path}`` for the Table 3 ablation layout (also scored in the
            main tables); a label equal to one of ``ckpts`` with the same path is reused.
        out_dir: folder for results.json / results.md (None: write nothing).
        tune_*: see :func:`tune_methods`.
        verbose: one line per recording and column (evaluation); progress: one line per tuned
            method and per evaluated column, on stderr.
    Returns:
        the results dict of :func:`tcn_ahrs.evaluate.evaluate` plus ``tuning``, ``columns``
        (column -> {method, axes, variant, params, ckpt}), ``ablation`` (labels), ``timing``.
    """
    from .evaluate import evaluate

    t_start = time.perf_counter()
    eval_seqs = [s for s in eval_seqs]
    if not eval_seqs:
        raise ValueError("compare: no evaluation recordings")
    if data_axes is None:
        data_axes = 9 if all(s.has_mag for s in eval_seqs) else 6
    variants = [v for v in variants if tune or v != "tuned"] or ["default"]
    ckpts = dict(ckpts or {})
    ablation = dict(ablation_ckpts or {})
    for label, path in ablation.items():
        if label in ckpts and str(ckpts[label]) != str(path):
            raise ValueError(f"ablation_ckpts[{label!r}] = {path} but ckpts[{label!r}] = {ckpts[label]}: "
                             "one label, one checkpoint")
    all_ckpts = dict(ckpts)
    all_ckpts.update({k: v for k, v in ablation.items() if k not in ckpts})
    specs = method_specs(methods, data_axes, both_axes, variants, all_ckpts)

    tuning: dict = {"enabled": bool(tune and "tuned" in variants)}
    t0 = time.perf_counter()
    if tuning["enabled"]:
        tune_seqs = list(tune_seqs)
        # same recording AND overlapping time span (EuRoC/TUM VI: the train part of a recording
        # tunes, its later val part is evaluated - allowed; the same samples never)
        spans = {}
        for s in eval_seqs:
            spans.setdefault(s.name, []).append((s.time[0], s.time[-1]))
        overlap = sorted({s.name for s in tune_seqs for (a, b) in spans.get(s.name, [])
                          if s.time[0] <= b and a <= s.time[-1]})
        if overlap:
            raise ValueError(f"tuning recordings {overlap} are also evaluation recordings: tune only on "
                             "training recordings (data.split=train parts) and evaluate on others")
        tuning.update(tune_methods(specs, tune_seqs, tune_max_seconds_per_recording, tune_lead_seconds,
                                   tune_recordings, tune_max_batch, device, progress))
    tune_s = time.perf_counter() - t0

    estimators, specs = build_estimators(specs, device, reanchor)
    for label, path in dict(on_calibrated or {}).items():
        from .estimators.learned import OnLearnedCalibration

        for s_, e in list(zip(specs, estimators)):
            if s_.kind in ("classical", "peer"):
                w = OnLearnedCalibration(e, path, label, device)
                estimators.append(w)
                specs.append(replace(s_, name=w.name))
    shared = share_batches(estimators)
    if progress:
        estimators = [_timed(e) for e in estimators]
    t0 = time.perf_counter()
    res = evaluate(estimators, eval_seqs, out_dir=out_dir, plots=plots, trajectories=trajectories,
                   axes=data_axes, dataset=dataset, align=align, verbose=verbose)
    eval_s = time.perf_counter() - t0
    estimators = [getattr(e, "inner", e) for e in estimators]
    res["tuning"] = tuning
    res["columns"] = {s.name: {"method": s.method, "axes": s.axes, "variant": s.variant,
                               "params": _jsonable(s.params), "ckpt": s.ckpt,
                               "heading_free": bool(getattr(e, "heading_free", False)),
                               "batched_with": shared.get(s.name)}
                      for s, e in zip(specs, estimators)}
    res["ablation"] = [k for k in ablation if k in res["methods"]]
    res["timing"] = {"tune_s": round(tune_s, 2), "evaluate_s": round(eval_s, 2),
                     "total_s": round(time.perf_counter() - t_start, 2)}
    if extra:
        res.update(extra)
    if out_dir is not None:
        out = Path(out_dir)
        (out / "results.json").write_text(json.dumps(res, indent=2))
        (out / "results.md").write_text(compare_markdown(res))
    return res


class _Timed:
    """Progress wrapper: prints the wall time per estimator column (forwards everything)."""

    def __init__(self, inner):
        self.inner = inner

    def __getattr__(self, k):  # name, axes, heading_free, ... of the wrapped estimator
        if k == "inner":
            raise AttributeError(k)
        return getattr(self.inner, k)

    def run(self, seq, init_quat=None):
        t0 = time.perf_counter()
        r = self.inner.run(seq, init_quat)
        print(f"  {self.inner.name} on {seq.name}: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        return r


def _add_run_batch():
    def run_batch(self, seqs, init_quats):
        t0 = time.perf_counter()
        r = self.inner.run_batch(seqs, init_quats)
        print(f"  {self.inner.name} on {len(seqs)} recordings (batched): {time.perf_counter() - t0:.1f} s",
              file=sys.stderr)
        return r
    return run_batch


def _timed(e):
    """``_Timed(e)``, with ``run_batch`` only when ``e`` has one (the runner checks hasattr)."""
    w = _Timed(e)
    if hasattr(e, "run_batch"):
        w = type("_TimedBatch", (_Timed,), {"run_batch": _add_run_batch()})(e)
    return w


def _subset(results: dict, names: Sequence[str]) -> dict:
    r = dict(results)
    r["methods"] = {n: results["methods"][n] for n in names if n in results["methods"]}
    return r


def compare_markdown(results: dict) -> str:
    """results.md of a comparison: Table 1/2 layout (AAE, AYE), inclination, BROAD total/heading/
    inclination, group averages, ablation (Table 3 layout), tuned parameters."""
    from .evaluate import LABELS, _has, group_table, markdown_table

    title = results.get("dataset") or "comparison"
    hf = [n for n, c in results.get("columns", {}).items() if c.get("heading_free")]
    parts = [f"# Comparison: {title}\n",
             f"Recordings: {len(results['recordings'])}. AAE / AYE in degrees (RMS over scored samples, "
             f"aligned at the first scored sample: {'yes' if results.get('align', True) else 'no'}). "
             "Bold: best in the row. `—`: not defined"
             + (f" (heading-free estimators {', '.join(hf)} are scored on inclination only)" if hf else "")
             + ".\n",
             "## Averages over recordings (deg)\n", averages_markdown(results),
             "\n## AAE / AYE (paper Tables 1/2 layout)\n",
             markdown_table(results, ("aae_deg", "aye_deg"))]
    broad = _has(results, "total_deg")
    if broad:
        parts += ["\n## BROAD errors: total / heading / inclination (deg, no alignment; 6D: heading offset removed)\n",
                  markdown_table(results, ("total_deg", "heading_deg", "inclination_deg"))]
    elif _has(results, "inclination_deg"):
        parts += ["\n## Inclination error (deg, BROAD definition, no alignment; needs no heading)\n",
                  markdown_table(results, ("inclination_deg",))]
    if any(m.get("groups") for m in results["methods"].values()):
        keys = ("total_deg", "heading_deg", "inclination_deg") if broad else ("aae_deg", "aye_deg", "inclination_deg")
        key = "total_deg" if broad else "aae_deg"
        parts += [f"\n## Group averages: {LABELS.get(key, key)} (rows groups, columns methods)\n",
                  group_table(results, (key,)).replace(f" {LABELS.get(key, key)} |", " |"),
                  "\n## Group averages: all metrics\n", group_table(results, keys)]
    abl = results.get("ablation") or []
    if abl:
        parts += ["\n## Ablation (paper Table 3 layout): AAE / AYE\n",
                  markdown_table(_subset(results, abl), ("aae_deg", "aye_deg"))]
    tun = results.get("tuning") or {}
    if tun.get("enabled"):
        recs = ", ".join(f"{r['name']} [{r['start_s']:.0f}+{r['duration_s']:.0f} s]" for r in tun.get("recordings", []))
        parts += ["\n## Tuned parameters\n",
                  f"Grid search, mean AAE over {len(tun.get('recordings', []))} training clips: {recs}.\n",
                  "| column | parameters | tuning AAE | grid | time [s] |", "|---|---|---|---|---|"]
        for name, t in tun.get("methods", {}).items():
            parts.append(f"| {name} | {t['params']} | {t['score_aae_deg'] if t['score_aae_deg'] is None else round(t['score_aae_deg'], 2)} "
                         f"| {t['grid_size']} | {t['time_s']} |")
        parts.append("")
    tm = results.get("timing")
    if tm:
        parts.append(f"\nWall time: tuning {tm['tune_s']} s, evaluation {tm['evaluate_s']} s, total {tm['total_s']} s.\n")
    return "\n".join(parts)


def averages_markdown(results: dict) -> str:
    """Markdown: one row per method (column of the big tables) with its mean over recordings of
    every metric present — the compact summary a README quotes."""
    keys = [k for k in ("aae_deg", "aye_deg", "ahe_deg", "total_deg", "heading_deg", "inclination_deg")
            if any((m.get("mean") or {}).get(k) is not None for m in results["methods"].values())]
    names = {"aae_deg": "AAE", "aye_deg": "AYE", "ahe_deg": "AHE", "total_deg": "BROAD total", "heading_deg": "BROAD heading",
             "inclination_deg": "inclination"}
    lines = ["| method | " + " | ".join(names[k] for k in keys) + " |", "|---" * (len(keys) + 1) + "|"]
    for name, m in results["methods"].items():
        mean = m.get("mean") or {}
        lines.append(f"| {name} | " + " | ".join("—" if mean.get(k) is None else f"{mean[k]:.2f}" for k in keys) + " |")
    return "\n".join(lines)


def average_rows(results: dict, keys: Sequence[str] = ("aae_deg", "aye_deg", "inclination_deg")) -> str:
    """Compact text: one line per column with its averages (for logs and reports)."""
    lines = [f"{'column':<28s} " + " ".join(f"{k:>16s}" for k in keys)]
    for name, m in results["methods"].items():
        mean = m.get("mean", {})
        lines.append(f"{name:<28s} " + " ".join(
            f"{'—' if mean.get(k) is None else format(mean[k], '.2f'):>16s}" for k in keys))
    return "\n".join(lines)


# ===========================================================================
# Hydra entry points
# ===========================================================================

COMPARE_KEYS = {"on_calibrated", "methods", "peers", "both_axes", "variants", "tune", "tune_split", "tune_data", "tune_root", "tune_max_seconds_per_recording",
                "tune_lead_seconds", "tune_recordings", "tune_max_batch", "ckpts", "ablation_ckpts", "out", "plots",
                "trajectories", "align", "device", "threads", "verbose", "reanchor"}
BENCHMARK_KEYS = COMPARE_KEYS | {"mode", "ckpt", "ckpt_label", "speed", "quick"}  # speed/quick: speed mode


def _plain(v):
    from omegaconf import OmegaConf

    return OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v


def _default_out(cfg, kind: str) -> Path:
    if cfg.get("out"):
        return Path(str(cfg.out))
    try:
        from hydra.core.hydra_config import HydraConfig

        return Path(HydraConfig.get().runtime.output_dir)
    except Exception:  # noqa: BLE001
        return Path("runs") / kind / str(cfg.data.name) / time.strftime("%Y-%m-%d_%H-%M-%S")


def _tune_data_cfg(cfg):
    """The data config the tuning recordings come from: ``tune_data`` (a name in conf/data/, e.g.
    ``broad``: its shipped training recordings, ``tune_root`` to move its root), else ``cfg.data``."""
    name = cfg.get("tune_data")
    if not name:
        if cfg.get("tune_root"):
            raise ValueError("tune_root: give tune_data=<name> too (the dataset whose training recordings tune)")
        return cfg.data
    from omegaconf import OmegaConf

    path = Path(__file__).resolve().parents[1] / "conf" / "data" / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(f"tune_data: no data config {name!r} (expected conf/data/{name}.yaml)")
    dc = OmegaConf.load(path)
    dc.pop("defaults", None)
    if cfg.get("tune_root"):
        dc.root = str(cfg.tune_root)
    dc.axes = cfg.data.get("axes", dc.get("axes", 9))
    return dc


def compare_main(cfg, allowed_keys=COMPARE_KEYS, kind: str = "compare") -> dict:
    """``scripts/compare.py`` (and ``scripts/benchmark.py accuracy``): load ``data.split`` for
    evaluation and ``tune_split`` (train) for tuning, run :func:`compare`, print the averages."""
    from .datasets import load_split

    unknown = set(k for k in cfg.keys() if k not in ("data", "hydra")) - set(allowed_keys)
    if unknown:
        raise ValueError(f"{kind} config: unknown key(s) {sorted(unknown)}; expected a subset of {sorted(allowed_keys)}")
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    split = str(cfg.data.get("split", "test"))
    tune_split = str(cfg.get("tune_split") or "train")
    if tune_split not in ("train", "trainval"):
        raise ValueError(f"tune_split: expected 'train' (the training parts of the training recordings) or "
                         f"'trainval', got {tune_split!r}: tuning never uses test/validation recordings")
    tune_data = _tune_data_cfg(cfg)
    if (cfg.get("tune") and tune_data is cfg.data
            and (split in ("train", "trainval", "all") or (tune_split == "trainval" and split == "val"))):
        raise ValueError(f"tune=true with data.split={split}: the evaluation would include the tuning recordings "
                         f"(tune_split={tune_split}); evaluate on test (or val with tune_split=train), or tune on "
                         "another dataset's training recordings (tune_data=broad)")
    methods = list(_plain(cfg.get("methods")) or CLASSICAL_METHODS)
    if cfg.get("peers"):
        methods += [m for m in PEER_METHODS if m not in methods]
    ckpts = dict(_plain(cfg.get("ckpts")) or {})
    if cfg.get("ckpt"):
        ckpts.setdefault(str(cfg.get("ckpt_label") or "Proposed"), str(cfg.ckpt))
    t0 = time.perf_counter()
    eval_seqs = [s for s in load_split(cfg.data, split) if s.has_gt]
    if not eval_seqs:
        raise ValueError(f"{kind}: no recordings with ground truth in data '{cfg.data.name}' split '{split}' "
                         f"(root {cfg.data.get('root')})")
    tune_seqs = load_split(tune_data, tune_split) if cfg.get("tune") else []
    load_s = time.perf_counter() - t0
    out = _default_out(cfg, kind)
    res = compare(eval_seqs, tune_seqs, methods=methods, data_axes=int(cfg.data.get("axes", 9)),
                  both_axes=bool(cfg.get("both_axes", True)), variants=list(_plain(cfg.get("variants")) or VARIANTS),
                  tune=bool(cfg.get("tune")), ckpts=ckpts, ablation_ckpts=_plain(cfg.get("ablation_ckpts")) or {},
                  out_dir=out, tune_max_seconds_per_recording=cfg.get("tune_max_seconds_per_recording"),
                  tune_lead_seconds=float(cfg.get("tune_lead_seconds", 10.0)),
                  tune_recordings=cfg.get("tune_recordings"), tune_max_batch=int(cfg.get("tune_max_batch", 128)),
                  dataset=str(cfg.data.name), plots=bool(cfg.get("plots", False)),
                  trajectories=bool(cfg.get("trajectories", False)), align=bool(cfg.get("align", True)),
                  device=str(cfg.get("device", "cpu")), verbose=bool(cfg.get("verbose", False)),
                  reanchor=cfg.get("reanchor"), on_calibrated=_plain(cfg.get("on_calibrated")) or None,
                  extra={"split": split, "tune_split": tune_split if cfg.get("tune") else None,
                         "config": _plain(cfg), "load_s": round(load_s, 2)})
    print(f"results in {out}")
    print(average_rows(res, ("aae_deg", "aye_deg", "ahe_deg", "total_deg", "heading_deg", "inclination_deg")))
    return res


def benchmark_accuracy_main(cfg) -> dict:
    """``scripts/benchmark.py accuracy``: :func:`compare_main` with the peers (``peers: true`` in
    conf/benchmark.yaml) and an optional learned checkpoint ``ckpt``."""
    return compare_main(cfg, BENCHMARK_KEYS, kind="benchmark")
