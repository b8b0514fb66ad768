"""Leave-recordings-out cross-validation (``scripts/crossval.py``).

Nested: for each (outer) fold ``i`` of ``data.folds``, train on the other training recordings
with an inner validation set (:func:`inner_split`: the next fold, whole, or the later parts of
the recordings) that chooses the epoch — or, for the residual model, its inference knobs — then
score that checkpoint next to the baselines on fold ``i``'s recordings, which chose nothing, with the one comparison runner
(:func:`tcn_ahrs.experiments.compare.compare`; baselines tuned, if asked, on the fold's training recordings
only). Writes ``crossval.json`` and ``crossval.md`` (per fold and mean ± sample standard
deviation over folds) under the output folder, one sub-folder per fold.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Dict, List, Tuple

import numpy as np
from omegaconf import DictConfig, OmegaConf, open_dict

from ..config import CrossvalSection, check_keys
from ..evaluate.reports import label as metric_label
from ..metrics import metric_keys


def _fold_cfg(cfg: DictConfig, i: int, run_dir: Path) -> DictConfig:
    f = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))
    with open_dict(f):
        f.data.fold = int(i)
        f.run_dir = str(run_dir)
        f.eval.enabled = False
        f.pop("crossval", None)
        f.pop("hydra", None)
    return f


def inner_split(cfg: DictConfig, folds: List[list], i: int, fcfg: DictConfig) -> Tuple[list, list, str]:
    """(train, validation, description) for outer fold ``i``: nothing of fold ``i`` in either.

    ``crossval.inner``: ``fold`` — the next fold's recordings, whole, validate (needs ≥ 3 folds);
    ``split`` — the other recordings' later parts validate (``data.train_part``), their first
    parts train; ``auto`` — ``fold`` with ≥ 3 folds, else ``split`` (too few recordings to
    spare whole ones). Whole recordings where possible: the later parts of a training recording
    share its device state with the first parts (TUM VI, split: the bias prior estimated on a
    room's first 80 s looks right on its last minute and is wrong in another room)."""
    from ..datasets import load_split, split_recording

    mode = str(cfg.crossval.get("inner") or "auto")
    if mode not in ("auto", "fold", "split"):
        raise ValueError(f"crossval.inner: expected auto, fold or split, got {mode!r}")
    if mode == "auto":
        mode = "fold" if len(folds) >= 3 else "split"
    if mode == "fold" and len(folds) < 3:
        raise ValueError(f"crossval.inner=fold needs at least 3 folds; data '{cfg.data.name}' has {len(folds)}")
    others = load_split(fcfg.data, "train")  # the training recordings without fold i, whole
    if mode == "fold":
        j = (int(i) + 1) % len(folds)
        inner = {str(r) for r in folds[j]}
        return ([s for s in others if s.name not in inner], [s for s in others if s.name in inner],
                f"inner validation: fold {j} ({', '.join(sorted(inner))}), whole")
    parts = [split_recording(s, cfg.data.get("train_part") or {}) for s in others]
    return ([a for a, _ in parts if a is not None], [b for _, b in parts if b is not None],
            f"inner validation: the later parts of the {len(others)} other recordings ({dict(cfg.data.get('train_part') or {})} train)")


def release_knobs(fold_knobs: List[List[dict]]) -> Dict[str, Any]:
    """The residual knobs for a released model: each point's criterion (worse ratio to the tuned
    backbone, :func:`tcn_ahrs.tuning.knobs.select_residual_knobs`) averaged over the folds' inner
    validation tables; the lowest wins if it beats the tuned backbone (the tables' reference point,
    criterion 1) by the selection's margin (:data:`tcn_ahrs.tuning.knobs.RESIDUAL_KNOB_MARGIN`)."""
    from ..tuning.knobs import RESIDUAL_KNOB_MARGIN

    scores: Dict[tuple, List[float]] = {}
    reference = None
    for table in fold_knobs:
        for row in table:
            key = tuple(sorted(row["knobs"].items()))
            scores.setdefault(key, []).append(float(row["score"]))
            if row.get("reference"):
                reference = key
    n = max(len(v) for v in scores.values())
    best = min((k for k, v in scores.items() if len(v) == n), key=lambda k: float(np.mean(scores[k])))
    if reference is not None and float(np.mean(scores[best])) >= 1.0 - RESIDUAL_KNOB_MARGIN:
        best = reference
    return {"knobs": dict(best), "score": float(np.mean(scores[best])), "folds": n}


def summarize(folds: List[Dict[str, Any]]) -> Dict[str, Dict[str, Dict[str, float]]]:
    """{method: {metric: {"mean", "std", "n"}}} over the folds' per-fold means."""
    out: Dict[str, Dict[str, Dict[str, float]]] = {}
    for f in folds:
        for method, means in f["means"].items():
            for k, v in means.items():
                if v is None or not math.isfinite(v):
                    continue
                out.setdefault(method, {}).setdefault(k, {"values": []})["values"].append(float(v))
    for method in out.values():
        for k, d in method.items():
            vals = np.asarray(d.pop("values"))
            d.update(mean=float(vals.mean()), std=float(vals.std(ddof=1)) if len(vals) > 1 else 0.0, n=int(len(vals)))
    return out


def markdown(result: Dict[str, Any]) -> str:
    keys = [k for k in metric_keys() if any(k in m for m in result["summary"].values())]
    lines = [f"# Cross-validation: {result['dataset']} ({len(result['folds'])} folds, leave-recordings-out)\n",
             "Nested: each fold's model trained on the other training recordings, its epoch or "
             "inference knobs chosen on an inner validation set (crossval.inner), scored on the "
             "fold's recordings, whole, which chose nothing. Degrees; mean ± sample std over folds.\n",
             "| method | " + " | ".join(metric_label(k, long=True) for k in keys) + " |", "|---" * (len(keys) + 1) + "|"]
    for method, m in result["summary"].items():
        cells = [f"{m[k]['mean']:.2f} ± {m[k]['std']:.2f}" if k in m else "—" for k in keys]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    for f in result["folds"]:
        lines += [f"\n## Fold {f['fold']}: {', '.join(f['recordings'])}\n",
                  "| method | " + " | ".join(metric_label(k, long=True) for k in keys) + " |", "|---" * (len(keys) + 1) + "|"]
        for method, means in f["means"].items():
            cells = ["—" if means.get(k) is None else f"{means[k]:.2f}" for k in keys]
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _folds(cfg: DictConfig) -> Tuple[List[list], List[int]]:
    """``data.folds`` and the indices to run (``crossval.folds``, default all)."""
    folds = list(OmegaConf.to_container(cfg.data.get("folds"), resolve=True) or []) if cfg.data.get("folds") else []
    if not folds:
        raise ValueError(f"crossval: data '{cfg.data.name}' defines no data.folds (lists of training "
                         "recordings to hold out); add them to its conf/data/*.yaml")
    idx = list(cfg.crossval.folds) if cfg.crossval.get("folds") is not None else list(range(len(folds)))
    return folds, idx


def untrained_main(cfg: DictConfig) -> Dict[str, Any]:
    """Score the *untrained* model (networks at zero: the closed loop is a classical filter with
    the model's gains, gates and rest detector) under each ``crossval.untrained`` variant (a
    mapping of ``model.closed_loop`` overrides) on every fold's training and held-out
    recordings. Choose the loop's prior on the training-recording column: those recordings are
    what a fold's training sees. Writes ``untrained.json`` / ``untrained.md``."""
    from ..datasets import load_split
    from ..estimators.learned import LearnedEstimator
    from ..evaluate import evaluate
    from ..model.ahrs import LearnedAHRS

    cv = cfg.crossval
    _, idx = _folds(cfg)
    variants = [dict(v or {}) for v in OmegaConf.to_container(cv.untrained, resolve=True)]
    axes = int(cfg.data.get("axes", 9))
    model_cfg = OmegaConf.to_container(cfg.model, resolve=True)
    rows = []
    for i in idx:
        fcfg = _fold_cfg(cfg, i, Path("."))
        parts = {"training": load_split(fcfg.data, "train"), "held out": load_split(fcfg.data, "val")}
        parts = {k: [s for s in v if s.has_gt] for k, v in parts.items()}
        for v in variants:
            mc = dict(model_cfg)
            mc["closed_loop"] = dict(mc.get("closed_loop") or {}, **v)
            est = LearnedEstimator(LearnedAHRS.from_config(mc, axes=axes), name="untrained")
            row = {"fold": int(i), "variant": v}
            for part, seqs in parts.items():
                res = evaluate([est], seqs, axes=axes, plots=False, trajectories=False)
                row[part] = res["methods"]["untrained"]["mean"]["aae_deg"]
            print(f"fold {i} {v}: AAE training {row['training']:.2f}, held out {row['held out']:.2f}", flush=True)
            rows.append(row)
    # one folder per data x model variant: a finished fold is reused, so broad9 and broad6 (or the
    # closed loop and the residual model) must not share one
    out = Path(str(cv.get("out") or f"runs/crossval/{cfg.data.name}_{cfg.model.variant}"))
    out.mkdir(parents=True, exist_ok=True)
    lines = [f"# Untrained closed loop on {cfg.data.name}: mean AAE (deg) per fold\n",
             "| fold | model.closed_loop overrides | training recordings | held-out recordings |",
             "|---|---|---|---|"]
    lines += [f"| {r['fold']} | `{r['variant'] or 'defaults'}` | {r['training']:.2f} | {r['held out']:.2f} |" for r in rows]
    md = "\n".join(lines) + "\n"
    (out / "untrained.json").write_text(json.dumps(rows, indent=1, default=str))
    (out / "untrained.md").write_text(md)
    print(md)
    return {"rows": rows}


def crossval_main(cfg: DictConfig) -> Dict[str, Any]:
    from .compare import compare
    from ..estimators import registry
    from ..datasets import load_split
    from ..training.run import model_axes, train_main

    cv = cfg.crossval
    check_keys(cv, CrossvalSection, "crossval")  # conf/crossval.yaml's section: tcn_ahrs/config/train.py
    if cv.get("untrained"):
        return untrained_main(cfg)
    folds, idx = _folds(cfg)
    out = Path(str(cv.get("out") or f"runs/crossval/{cfg.data.name}"))
    out.mkdir(parents=True, exist_ok=True)
    methods = list(cv.get("methods") or [])
    if cv.get("peers"):
        methods += [m for m in registry.methods("peer") if m not in methods]
    label = str(cv.get("label") or "Learned")
    fold_results, fold_knobs = [], []
    for i in idx:
        run_dir = out / f"fold{i}"
        fcfg = _fold_cfg(cfg, i, run_dir)
        done = run_dir / "TRAINED"
        best = run_dir / "checkpoints" / "best.ckpt"
        if cv.get("retrain") or not (done.is_file() and best.is_file()):
            with open_dict(fcfg):
                fcfg.resume = (run_dir / "checkpoints" / "last.ckpt").is_file() and not cv.get("retrain")
            train_seqs, val_seqs, inner = inner_split(cfg, folds, i, fcfg)
            print(f"== fold {i}: training on {fcfg.data.name} without {folds[i]}; {inner} (run dir {run_dir})")
            res = train_main(fcfg, train_seqs=train_seqs, val_seqs=val_seqs)
            best = Path(res["best"])
            done.write_text(str(best) + "\n")
        else:
            best = Path(done.read_text().strip())
            print(f"== fold {i}: reusing {best}")
            if cv.get("reselect") and (run_dir / "knobs.json").is_file():
                # the residual model's inference knobs chosen again (e.g. after a change of the
                # grid or criterion) on the same inner validation set, without training again
                from ..training.run import choose_knobs_into_checkpoint

                _, val_seqs, inner = inner_split(cfg, folds, i, fcfg)
                print(f"   re-choosing the inference knobs on the {inner}")
                choose_knobs_into_checkpoint(str(best), val_seqs, run_dir)
        eval_seqs = [s for s in load_split(fcfg.data, "val") if s.has_gt]
        tune_seqs = load_split(fcfg.data, "train") if cv.get("tune") else []
        # nested: the epoch (or the residual model's knobs) was chosen on the inner validation
        # recordings; fold i's recordings choose nothing and only score
        ckpts = {label: str(best)}
        knobs_file = run_dir / "knobs.json"
        if knobs_file.is_file():
            fold_knobs.append(json.loads(knobs_file.read_text())["table"])
        # the baselines read what the learned model reads: a 6-axis model on 9-axis data (broad6)
        # is compared with the 6D filters, not with filters that use the magnetometer
        res = compare(eval_seqs, tune_seqs, methods=methods, data_axes=model_axes(cfg),
                      both_axes=False, tune=bool(cv.get("tune")), ckpts=ckpts,
                      out_dir=run_dir / "eval", dataset=str(cfg.data.name),
                      tune_max_seconds_per_recording=cv.get("tune_max_seconds_per_recording"), progress=True)
        means = {m: {k: v.get("mean", {}).get(k) for k in metric_keys()} for m, v in res["methods"].items()}
        fold_results.append({"fold": int(i), "recordings": [s.name for s in eval_seqs], "checkpoint": str(best),
                             "means": means})
    result = {"dataset": str(cfg.data.name), "folds": fold_results, "summary": summarize(fold_results),
              "config": OmegaConf.to_container(cfg, resolve=True)}
    if fold_knobs:
        result["release_knobs"] = release_knobs(fold_knobs)
        print(f"residual knobs for a released model (mean over the {len(fold_knobs)} folds' inner validation): "
              f"{result['release_knobs']['knobs']}")
    (out / "crossval.json").write_text(json.dumps(result, indent=1, default=str))
    md = markdown(result)
    (out / "crossval.md").write_text(md)
    print(md)
    print(f"results in {out}")
    return result
