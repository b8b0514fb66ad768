"""Evaluation runner: estimators × recordings -> metrics, JSON/Markdown tables, plots, TUM files.

For every recording and every estimator:

1. the estimator runs on the recording (``est.run(seq, init_quat, init_index)``, or once on all
   recordings with ``est.run_batch(seqs, init_quats, init_indices)`` when it has that method);
   an estimator with ``axes == 6`` gets the recording without magnetometer and is scored as
   6-axis; ``init_index`` is the first sample with valid ground truth and ``init_quat`` its
   ground-truth attitude (:func:`tcn_ahrs.estimators.base.initial_state`; what each estimator
   does with them: :class:`~tcn_ahrs.estimators.base.Estimator`). The difference this leaves at the first
   scored sample is removed for AAE/AYE by their alignment (:mod:`tcn_ahrs.metrics`); BROAD's
   errors are never aligned (BROAD trials start with a rest phase whose ground truth is valid);
2. the metrics of :func:`tcn_ahrs.metrics.sequence_metrics` are computed on ``seq.scored()``;
   ``inclination_deg`` (BROAD's inclination error, needs no heading) for every recording; an
   estimator with ``heading_free = True`` (RIANN) gets ``null`` AAE/AYE/total/heading
   (inclination only);
3. optionally a plot (roll/pitch/yaw vs ground truth, error over time, ``gyro_correction`` if the
   estimator reports it — the paper's Figs. 3-8) and TUM trajectories for ``evo`` are written.

The results are one plain dict, exactly what is written to ``results.json``::

    {"dataset": str, "align": bool, "recordings": [names...],
     "methods": {method: {"recordings": [{"name", "n_samples", "duration_s", "axes",
                                          "n_scored", "aae_deg", "aye_deg",
                                          ["total_deg", "heading_deg", "inclination_deg",
                                           "broad_mode"], "run_time_s"}, ...],
                          "mean": {metric: mean over recordings with scored samples},
                          "groups": {group: {"n_recordings": k, metric: mean}}}}}

NaN (a diverged estimator) is stored as ``null``. Groups come from ``seq.meta["groups"]``
(BROAD: ``undisturbed``, ``disturbed``, ``tapping``, ...).

Output layout under ``out_dir``::

    results.json  results.md
    plots/<method>/<recording>.png
    trajectories/<method>/<recording>.txt       (TUM: t x y z qx qy qz qw, positions 0)
    trajectories/groundtruth/<recording>.txt    (valid ground-truth samples only)
"""
from __future__ import annotations

import json
import math
import re
import sys
import time as _time
import warnings
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Sequence

import numpy as np

from .estimators.base import initial_state
from .metrics import attitude_errors, align_to_first, broad_errors, sequence_metrics
from .sequence import ImuSequence

METRIC_KEYS = ("aae_deg", "aye_deg", "ahe_deg", "total_deg", "heading_deg", "inclination_deg")
"""Numeric per-recording metrics that are averaged (means, groups)."""

LABELS = {
    "aae_deg": "AAE",
    "aye_deg": "AYE",
    "ahe_deg": "AHE",
    "total_deg": "total",
    "heading_deg": "heading",
    "inclination_deg": "incl.",
}

MAX_PLOT_POINTS = 5000


def safe_name(name: str) -> str:
    """A file-name-safe version of a method or recording name (``"Raw IMU"`` -> ``"Raw_IMU"``)."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", str(name)).strip("_") or "unnamed"


def _clean(v):
    """NaN/inf -> None, numpy scalars -> Python (so the dict is valid JSON as it is)."""
    if isinstance(v, (np.floating, float)):
        v = float(v)
        return v if math.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    return v


def _mean_metrics(rows: List[dict]) -> Dict[str, Optional[float]]:
    """Mean of each metric over recordings that have scored samples (None if any is None: a
    diverged estimator must not vanish from the average)."""
    rows = [r for r in rows if r.get("n_scored", 0) > 0]
    out: Dict[str, Optional[float]] = {"n_recordings": len(rows)}
    for k in METRIC_KEYS:
        vals = [r.get(k, "absent") for r in rows]
        vals = [v for v in vals if v != "absent"]
        if not vals:
            continue
        out[k] = None if any(v is None for v in vals) else float(np.mean(vals))
    return out


def evaluate(
    estimators: Sequence,
    sequences: Sequence[ImuSequence],
    out_dir=None,
    plots: bool = True,
    trajectories: bool = True,
    axes: Optional[int] = None,
    dataset: Optional[str] = None,
    align: bool = True,
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
        align:      AAE/AYE alignment at the first scored sample (see :mod:`tcn_ahrs.metrics`).
    Returns:
        the results dict (see module docstring).
    """
    estimators = list(estimators)
    sequences = list(sequences)
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

    out = Path(out_dir) if out_dir is not None else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)

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
    if out is not None and trajectories:
        for seq in sequences:
            valid = seq.quat_valid
            write_tum(out / "trajectories" / "groundtruth" / f"{safe_name(seq.name)}.txt",
                      seq.time[valid], seq.quat[valid])
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
            if "inclination_deg" not in m:
                # inclination needs no heading: reported for every estimator (6D convention)
                m["inclination_deg"] = broad_errors(seq.quat, quat, seq.scored(), "6d")["inclination_deg"]
            if heading_free:
                # no heading reference (RIANN): only the inclination is meaningful
                for k in ("aae_deg", "aye_deg", "ahe_deg", "total_deg", "heading_deg"):
                    m[k] = float("nan")
            row = {"name": seq.name, "n_samples": len(seq), "duration_s": seq.duration,
                   "axes": seq_in.num_axes, **m, "run_time_s": run_time}
            if heading_free:
                row["heading_free"] = True
            methods[est.name]["recordings"].append({k: _clean(v) for k, v in row.items()})
            if verbose:
                print(f"{est.name:>20s} {seq.name:<45s} AAE {m['aae_deg']:8.3f}  AYE {m['aye_deg']:8.3f}  "
                      f"incl {m['inclination_deg']:8.3f}", file=sys.stderr)
            if out is not None and plots:
                plot_recording(out / "plots" / safe_name(est.name) / f"{safe_name(seq.name)}.png",
                               seq, quat, est.name, res.signals, align=align)
            if out is not None and trajectories:
                write_tum(out / "trajectories" / safe_name(est.name) / f"{safe_name(seq.name)}.txt",
                          seq.time, quat)
        batched = None

    for name, mres in methods.items():
        rows = mres["recordings"]
        mres["mean"] = _mean_metrics(rows)
        groups: Dict[str, List[dict]] = {}
        for seq, row in zip(sequences, rows):
            for g in seq.meta.get("groups", []) or []:
                groups.setdefault(str(g), []).append(row)
        mres["groups"] = {g: _mean_metrics(r) for g, r in groups.items()}

    results = {"dataset": dataset, "align": bool(align), "recordings": rec_names, "methods": methods}
    if out is not None:
        (out / "results.json").write_text(json.dumps(results, indent=2))
        (out / "results.md").write_text(results_markdown(results))
    return results


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


def _fmt(v) -> str:
    return "—" if v is None else f"{v:.2f}"


def _has(results: dict, key: str) -> bool:
    return any(key in r for m in results["methods"].values() for r in m["recordings"])


def _metric_rows(results: dict, key: str, columns: List[str], values, bold_best: bool) -> List[str]:
    """One Markdown table: a row per method, a column per entry of ``columns`` (values(method,
    column) -> number or None); the lowest value of each column in bold."""
    methods = list(results["methods"])
    table = {m: [values(m, c) for c in columns] for m in methods}
    best = [min((table[m][j] for m in methods if table[m][j] is not None), default=None)
            for j in range(len(columns))]
    lines = [f"| {LABELS.get(key, key)} (deg) | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for m in methods:
        cells = []
        for j, v in enumerate(table[m]):
            s = _fmt(v)
            if bold_best and len(methods) > 1 and v is not None and v == best[j]:
                s = f"**{s}**"
            cells.append(s)
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return lines


def markdown_table(results: dict, metric_keys: Iterable[str] = ("aae_deg", "aye_deg"),
                   bold_best: bool = True) -> str:
    """One Markdown table per metric: a row per method, a column per recording and the
    Average (the mean over recordings); the best (lowest) of each column in bold. Readable with
    dozens of methods (the full method x metric matrix is in ``results.json``)."""
    recs = list(results["recordings"])
    out = []
    for key in metric_keys:
        def val(m, c, key=key):
            r = results["methods"][m]
            return (r["mean"] if c == "Average" else r["recordings"][recs.index(c)]).get(key)
        out.append("\n".join(_metric_rows(results, key, recs + ["Average"], val, bold_best)))
    return "\n\n".join(out) + "\n"


def group_table(results: dict, metric_keys: Iterable[str] = ("aae_deg", "aye_deg"), bold_best: bool = True) -> str:
    """Per-group averages, one Markdown table per metric: a row per method, a column per group
    (``group (n)``, n recordings)."""
    methods = list(results["methods"])
    groups: List[str] = []
    for m in methods:
        for g in results["methods"][m].get("groups", {}):
            if g not in groups:
                groups.append(g)
    first = results["methods"][methods[0]].get("groups", {})
    cols = [f"{g} ({first.get(g, {}).get('n_recordings', '?')})" for g in groups]
    out = []
    for key in metric_keys:
        def val(m, c, key=key):
            return results["methods"][m].get("groups", {}).get(groups[cols.index(c)], {}).get(key)
        out.append("\n".join(_metric_rows(results, key, cols, val, bold_best)))
    return "\n\n".join(out) + "\n"


def results_markdown(results: dict) -> str:
    """The whole ``results.md``: AAE/AYE table, BROAD errors (if any), group averages (if any)."""
    title = results.get("dataset") or "evaluation"
    parts = [f"# Results: {title}\n",
             f"AAE / AYE in degrees (RMS over scored samples; alignment at the first scored sample: "
             f"{'yes' if results.get('align', True) else 'no'}); AHE: heading error about the "
             f"navigation vertical, aligned the same way.\n",
             markdown_table(results, ("aae_deg", "aye_deg", "ahe_deg"))]
    broad_keys = ("total_deg", "heading_deg", "inclination_deg")
    if _has(results, "total_deg"):
        parts += ["\n## BROAD errors\n",
                  "Total / heading / inclination RMSE in degrees, earth-frame error, no alignment "
                  "(6-axis estimates: constant heading offset removed).\n",
                  markdown_table(results, broad_keys)]
    if any(m.get("groups") for m in results["methods"].values()):
        keys = broad_keys if _has(results, "total_deg") else ("aae_deg", "aye_deg")
        parts += ["\n## Group averages\n", group_table(results, ("aae_deg", "aye_deg") + tuple(
            k for k in keys if k not in ("aae_deg", "aye_deg")))]
    return "\n".join(parts)


def print_table(results: dict, metric_keys: Optional[Iterable[str]] = None, file=None) -> None:
    """Plain-text tables for terminals (< 100 columns): one block per method, rows recordings
    (+ Average), columns the metrics, all in degrees."""
    file = file or sys.stdout
    if metric_keys is None:
        metric_keys = ["aae_deg", "aye_deg", "ahe_deg"] + [k for k in ("total_deg", "heading_deg", "inclination_deg")
                                                if _has(results, k)]
    metric_keys = list(metric_keys)
    names = [r if len(r) <= 40 else r[:19] + "~" + r[-20:] for r in results["recordings"]]
    w0 = max([len("recording"), len("Average")] + [len(r) for r in names])
    widths = [max(7, len(LABELS.get(k, k))) for k in metric_keys]
    for method, mres in results["methods"].items():
        print(f"\n{method} — attitude errors in degrees", file=file)
        print(f"{'recording':<{w0}}  " + "  ".join(f"{LABELS.get(k, k):>{w}}" for k, w in zip(metric_keys, widths)),
              file=file)
        rows = list(zip(names, mres["recordings"])) + [("Average", mres["mean"])]
        for label, vals in rows:
            print(f"{label:<{w0}}  " + "  ".join(f"{_fmt(vals.get(k)):>{w}}" for k, w in zip(metric_keys, widths)),
                  file=file)


# ---------------------------------------------------------------------------
# files: TUM trajectories, plots
# ---------------------------------------------------------------------------


def write_tum(path, time: np.ndarray, quat: np.ndarray) -> None:
    """TUM trajectory file for ``evo``: one line ``t x y z qx qy qz qw`` per sample, positions 0,
    attitude ``nav_from_body`` (w,x,y,z) reordered to scalar-last; a ``#`` header line."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    q = np.asarray(quat, dtype=np.float64)
    t = np.asarray(time, dtype=np.float64)
    data = np.column_stack([t, np.zeros((len(t), 3)), q[:, 1], q[:, 2], q[:, 3], q[:, 0]])
    np.savetxt(path, data, fmt=["%.9f", "%d", "%d", "%d", "%.9f", "%.9f", "%.9f", "%.9f"],
               header="t x y z qx qy qz qw", comments="# ")


def plot_recording(path, seq: ImuSequence, quat_est: np.ndarray, method: str,
                   signals: Optional[dict] = None, align: bool = True,
                   max_points: int = MAX_PLOT_POINTS) -> None:
    """Roll/pitch/yaw of the (aligned) estimate vs ground truth, the attitude and yaw error over
    time, and ``signals["gyro_correction"]`` (N, 3) rad/s if present; Agg backend, at most
    ``max_points`` points per curve."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    import torch

    from . import so3

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    m = seq.scored()
    q_est = align_to_first(seq.quat, quat_est, m) if align else np.asarray(quat_est, dtype=np.float64)
    angle, dyaw = attitude_errors(seq.quat, quat_est, m, align)
    n = len(seq)
    idx = np.unique(np.linspace(0, n - 1, min(n, max_points)).astype(int))
    t = seq.time[idx] - seq.time[0]
    eul_est = np.degrees(so3.quat_to_euler(torch.as_tensor(q_est[idx])).numpy())
    gt = seq.quat[idx]
    gt_ok = np.all(np.isfinite(gt), axis=1)
    eul_gt = np.full_like(eul_est, np.nan)
    if gt_ok.any():
        eul_gt[gt_ok] = np.degrees(so3.quat_to_euler(torch.as_tensor(gt[gt_ok])).numpy())
    corr = None if not signals else signals.get("gyro_correction")
    nrows = 5 if corr is not None else 4
    fig, axs = plt.subplots(nrows, 1, figsize=(10, 2.2 * nrows), sharex=True)
    for i, lab in enumerate(("roll", "pitch", "yaw")):
        axs[i].plot(t, eul_gt[:, i], "k-", lw=1.0, label="ground truth")
        axs[i].plot(t, eul_est[:, i], "C0-", lw=0.8, label=method)
        axs[i].set_ylabel(f"{lab} [°]")
    axs[0].legend(loc="upper right", fontsize=8)
    err_a = np.where(m, np.degrees(angle), np.nan)[idx]
    err_y = np.where(m, np.degrees(dyaw), np.nan)[idx]
    axs[3].plot(t, err_a, "C3-", lw=0.8, label="attitude error ||Log(R_gt^T R_est)||")
    axs[3].plot(t, err_y, "C2-", lw=0.8, label="yaw error")
    axs[3].set_ylabel("error [°]")
    axs[3].legend(loc="upper left", fontsize=8)
    if corr is not None:
        c = np.degrees(np.asarray(corr, dtype=np.float64).reshape(n, -1)[idx])
        for j in range(c.shape[1]):
            axs[4].plot(t, c[:, j], lw=0.8, label="xyz"[j] if j < 3 else str(j))
        axs[4].set_ylabel("gyro corr. [°/s]")
        axs[4].legend(loc="upper right", fontsize=8)
    axs[-1].set_xlabel("time [s]")
    fig.suptitle(f"{method} — {seq.name}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
