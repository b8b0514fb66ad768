"""The one evaluation runner: estimators x recordings -> metrics (see the package docstring); the
artefacts (JSON, tables, plots, TUM trajectories) are written afterwards by :func:`write_artefacts`."""
from __future__ import annotations

import json
import math
import sys
import time as _time
import warnings
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np

from ..estimators.base import initial_state
from ..health import health_report
from ..metrics import HEADING_KEYS, alignment_name, extra_metrics, metric_keys, sequence_metrics
from ..sequence import ImuSequence
from .files import plot_recording, safe_name, write_tum
from .reports import results_markdown


def jsonable(v):
    """The one JSON sanitiser of results: NaN/inf -> None, numpy scalars and tensors -> Python,
    through dicts, lists and tuples (so a results dict is valid JSON as it is)."""
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [jsonable(x) for x in v]
    if isinstance(v, (np.floating, float)):
        v = float(v)
        return v if math.isfinite(v) else None
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, np.integer):
        return int(v)
    if hasattr(v, "tolist") and callable(v.tolist):  # tensors and arrays
        return jsonable(v.tolist())
    return v


def _mean_metrics(rows: List[dict]) -> Dict[str, Optional[float]]:
    """Mean of each metric over recordings that have scored samples (None if any is None: a
    diverged estimator must not vanish from the average)."""
    rows = [r for r in rows if r.get("n_scored", 0) > 0]
    out: Dict[str, Optional[float]] = {"n_recordings": len(rows)}
    for k in metric_keys():
        vals = [r.get(k, "absent") for r in rows]
        vals = [v for v in vals if v != "absent"]
        if not vals:
            continue
        out[k] = None if any(v is None for v in vals) else float(np.mean(vals))
    return out


def _long_enough(sequences: List[ImuSequence]) -> List[ImuSequence]:
    """The recordings whose ground truth outlasts the yardstick's settle (the first ``settle_s``
    seconds are scored for nobody): a shorter one (a 2-sample file scored 5.4° for its first
    step) is left out with a warning naming it; ValueError when none is left."""
    from ..metrics import YARDSTICK

    keep = []
    for s in sequences:
        if s.quat is None:  # refused below, named
            keep.append(s)
            continue
        valid = s.scored()
        if valid.any() and not YARDSTICK.settled(s).any():
            span = float(s.time[valid][-1] - s.time[int(np.argmax(s.quat_valid))])
            why = (f"{s.source}: recording {s.name!r} is too short to score: its ground truth spans {span:.3g} s "
                   f"({int(valid.sum())} samples), within the yardstick's first {YARDSTICK.settle_s:g} s that nobody "
                   "is scored on (docs/conventions.md); record longer")
            if len(sequences) == 1:
                raise ValueError(why)
            warnings.warn(why + "; left out", stacklevel=3)
            continue
        keep.append(s)
    if not keep:
        raise ValueError("nothing to score: every recording is shorter than the yardstick's "
                         f"{YARDSTICK.settle_s:g} s settle ({', '.join(s.name for s in sequences)})")
    return keep


def evaluate(
    estimators: Sequence,
    sequences: Sequence[ImuSequence],
    out_dir=None,
    plots: bool = True,
    trajectories: bool = True,
    axes: Optional[int] = None,
    dataset: Optional[str] = None,
    align="protocol",
    verbose: bool = False,
) -> dict:
    """Run every estimator on every recording and score it.

    Args:
        estimators: objects with ``name`` and ``run(seq, init_quat) -> EstimatorOutput``
                    (:class:`tcn_ahrs.estimators.base.Estimator`); names must be unique.
        sequences:  recordings with ground truth (names must be unique).
        out_dir:    folder for results.json / results.md / plots / trajectories; ``None``: write nothing.
        plots, trajectories: write those too (only with ``out_dir``).
        axes:       6 drops the magnetometer before running (the 6-axis view of 9-axis data);
                    9 or ``None`` uses whatever each recording has.
        dataset:    name stored in the results (default: ``seq.meta["dataset"]`` of the first
                    recording, else ``""``).
        align:      ``"protocol"`` (the yardstick of :mod:`tcn_ahrs.metrics`, the default) or an
                    alignment of :data:`tcn_ahrs.metrics.ALIGNMENTS` for AAE/AYE/AHE.
    Returns:
        the results dict (see module docstring).
    """
    estimators = list(estimators)
    sequences = _long_enough(list(sequences)) if align == "protocol" else list(sequences)
    if axes not in (None, 6, 9):
        raise ValueError(f"axes: expected 6, 9 or None, got {axes!r}")
    names = [e.name for e in estimators]
    if len(set(names)) != len(names):
        raise ValueError(f"estimators: names must be unique (they label the results), got {names}")
    rec_names = [s.name for s in sequences]
    if len(set(rec_names)) != len(rec_names):
        raise ValueError(f"sequences: recording names must be unique, got duplicates in {rec_names}")
    for s in sequences:
        if s.quat is None:
            raise ValueError(f"{s.source}: field 'quat': recording {s.name!r} has no ground truth to evaluate against")
    unscored = [s for s in sequences if not s.scored().any()]
    for s in unscored:
        why = ("its ground truth is invalid (NaN) everywhere" if not s.quat_valid.any()
               else "its score mask selects no sample with valid ground truth")
        if len(unscored) == len(sequences):
            raise ValueError(f"{s.source}: field 'quat': nothing to score in any recording ({s.name!r}: {why})")
        warnings.warn(f"{s.source}: recording {s.name!r} is not scored: {why}", stacklevel=2)
    if dataset is None:
        dataset = str(sequences[0].meta.get("dataset", "")) if sequences else ""

    methods: Dict[str, dict] = {n: {"recordings": []} for n in names}
    # The view of each recording the estimators get (axes=6: no magnetometer) and the initial
    # attitudes; an estimator with ``axes == 6`` (e.g. a 6D peer/filter column on 9-axis data)
    # gets the 6-axis view and is scored as 6-axis.
    views: List[ImuSequence] = []
    for seq in sequences:
        if axes == 6 and seq.has_mag:
            views.append(seq.without_mag())
        else:
            if axes == 9 and not seq.has_mag:
                warnings.warn(f"axes=9 requested but recording {seq.name!r} has no magnetometer; "
                              "evaluating it as 6-axis")
            views.append(seq)
    inits = [initial_state(seq) for seq in sequences]
    k0s, q0s = [k for k, _ in inits], [q for _, q in inits]
    estimates: Dict[str, List[tuple]] = {n: [] for n in names}  # (quat, signals) per recording
    for est in estimators:
        est_views = [v.without_mag() if (getattr(est, "axes", None) == 6 and v.has_mag) else v for v in views]
        heading_free = bool(getattr(est, "heading_free", False))
        batched = None
        if hasattr(est, "run_batch") and len({v.has_mag for v in est_views}) == 1:
            # all recordings in one (padded) filter call; run time split evenly over them
            t0 = _time.perf_counter()
            batched = est.run_batch(est_views, q0s, k0s)
            batch_time = (_time.perf_counter() - t0) / max(1, len(sequences))
        for i, (seq, seq_in) in enumerate(zip(sequences, est_views)):
            if batched is not None:
                res, run_time = batched[i], batch_time
            else:
                t0 = _time.perf_counter()
                res = est.run(seq_in, q0s[i], k0s[i])
                run_time = _time.perf_counter() - t0
            quat = np.asarray(res.quat, dtype=np.float64)
            if quat.shape != (len(seq), 4):
                raise ValueError(f"estimator {est.name!r} on {seq.name!r}: expected quat of shape "
                                 f"({len(seq)}, 4), got {quat.shape}")
            m = sequence_metrics(seq, quat, axes=seq_in.num_axes, align=align)
            if heading_free:
                # no heading reference (RIANN): only the inclination is meaningful
                for k in HEADING_KEYS + tuple(x.key for x in extra_metrics() if x.needs_heading):
                    m[k] = float("nan")
            row = {"name": seq.name, "n_samples": len(seq), "duration_s": seq.duration,
                   "axes": seq_in.num_axes, **m, "run_time_s": run_time}
            if heading_free:
                row["heading_free"] = True
            health = health_report(seq_in.time, res.signals)
            if health is not None:  # the estimator runs the health checks: what they found (or [])
                row["health"] = health
            methods[est.name]["recordings"].append({k: jsonable(v) for k, v in row.items()})
            if verbose:
                print(f"{est.name:>20s} {seq.name:<45s} AAE {m['aae_deg']:8.3f}  AYE {m['aye_deg']:8.3f}  "
                      f"incl {m['inclination_deg']:8.3f}", file=sys.stderr)
            estimates[est.name].append((quat, res.signals))
        batched = None

    for name, mres in methods.items():
        rows = mres["recordings"]
        mres["mean"] = _mean_metrics(rows)
        groups: Dict[str, List[dict]] = {}
        for seq, row in zip(sequences, rows):
            for g in seq.meta.get("groups", []) or []:
                groups.setdefault(str(g), []).append(row)
        mres["groups"] = {g: _mean_metrics(r) for g, r in groups.items()}

    results = {"dataset": dataset, "align": alignment_name(align), "recordings": rec_names, "methods": methods}
    if out_dir is not None:
        write_artefacts(out_dir, results, sequences, estimates, plots=plots, trajectories=trajectories, align=align)
    return results


def write_artefacts(out_dir, results: dict, sequences: Sequence[ImuSequence], estimates: Dict[str, List[tuple]],
                    plots: bool = True, trajectories: bool = True, align="protocol") -> None:
    """What :func:`evaluate` computed, written afterwards: results.json / results.md, and per
    method and recording a plot (``plots/<method>/<recording>.png``) and a TUM trajectory
    (``trajectories/<method>/<recording>.txt``, ground truth under ``groundtruth/``).
    ``estimates``: {method: [(quat (N, 4), signals dict or None) per recording]}."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if trajectories:
        for seq in sequences:
            valid = seq.quat_valid
            write_tum(out / "trajectories" / "groundtruth" / f"{safe_name(seq.name)}.txt",
                      seq.time[valid], seq.quat[valid])
    axes_of = {(m, r["name"]): r.get("axes") for m, res in results["methods"].items() for r in res["recordings"]}
    for method, runs in estimates.items():
        for seq, (quat, signals) in zip(sequences, runs):
            if plots:
                plot_recording(out / "plots" / safe_name(method) / f"{safe_name(seq.name)}.png",
                               seq, quat, method, signals, align=align, axes=axes_of.get((method, seq.name)))
            if trajectories:
                write_tum(out / "trajectories" / safe_name(method) / f"{safe_name(seq.name)}.txt", seq.time, quat)
    (out / "results.json").write_text(json.dumps(results, indent=2))
    (out / "results.md").write_text(results_markdown(results))


def load_results(path) -> dict:
    """Read a ``results.json`` (a file or the ``out_dir`` holding it) back into the results dict."""
    p = Path(path)
    if p.is_dir():
        p = p / "results.json"
    try:
        return json.loads(p.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"{p}: no results.json (expected the output of tcn_ahrs.evaluate.evaluate)") from None


# ---------------------------------------------------------------------------
# tables
# ---------------------------------------------------------------------------
