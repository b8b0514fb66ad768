"""Method comparison: build the estimators, tune them on training recordings, run them through
the evaluation runner (:func:`tcn_ahrs.evaluate.evaluate`) and write the paper-style tables.

Used by ``scripts/compare.py`` (classical methods, optionally peers and checkpoints) and by
``scripts/benchmark.py accuracy`` (the same code path with the PyPI peers on by default).

Methods: every name of the one registry (:mod:`tcn_ahrs.estimators.registry`; default: every
raw and classical method, ``peers=true`` adds the PyPI peers, ``plugins=[module]`` imports
modules registering more):

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
(:func:`tcn_ahrs.metrics.aae`, filters started at ground truth); the search is the one tuner,
:func:`tcn_ahrs.tuning.grid.tune_method`, over the method's registered grid (project filters: ALL
clips x ALL grid points in one batched filter call per chunk; peers: one run per point and
clip). The chosen parameters, scores and clip list go to ``results["tuning"]``.

Evaluation: the project filters expose ``run_batch(seqs, init_quats)`` (all recordings in one
padded filter call), which :func:`~tcn_ahrs.evaluate.evaluate` prefers over per-recording
``run``. Heading-free estimators (RIANN) are scored on inclination only (AAE, AYE, total and
heading are ``null``); ``inclination_deg`` is reported for every method.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Dict, Mapping, Optional, Sequence, Tuple

import torch

from ..config import BenchmarkConfig, CompareConfig, conf_path, keys, plain
from .columns import VARIANTS, MethodSpec, build_estimators, default_methods, method_specs  # noqa: F401  (re-exported)
from ..estimators import registry
from ..evaluate.reports import average_rows, compare_markdown
from ..evaluate.runner import jsonable
from ..sequence import ImuSequence
from ..validate import set_threads

# ===========================================================================
# tuning
# ===========================================================================


def tune_methods(specs: Sequence[MethodSpec], tune_seqs: Sequence[ImuSequence], max_seconds: Optional[float] = 60.0,
                 lead_seconds: float = 10.0, max_recordings: Optional[int] = None, max_batch: int = 128,
                 device: str = "cpu", verbose: bool = True) -> dict:
    """Fill in ``params`` of every ``variant == "tuned"`` spec (in place) from a grid search
    (:func:`tcn_ahrs.tuning.grid.tune_method`, the registry's grid) on clips of ``tune_seqs``
    (training recordings only!). One search per (method, axes).

    Returns the tuning record ``{"recordings": [clip records], "max_seconds_per_recording",
    "lead_seconds", "methods": {column: {"params", "score_aae_deg", "default_params",
    "grid_size", "time_s", "top": [best 3 rows]}}}``.
    """
    from ..estimators.peers import PeerUnavailable
    from ..tuning.grid import tune_method, tuning_clips

    todo = [s for s in specs if s.variant == "tuned"]
    clips, rec = tuning_clips(tune_seqs, max_seconds, lead_seconds, max_recordings)
    record = {"recordings": rec, "max_seconds_per_recording": max_seconds, "lead_seconds": lead_seconds,
              "max_recordings": max_recordings, "methods": {}}
    if not todo:
        return record
    if not clips:
        raise ValueError("tuning: no training recording with scored ground truth; tune=false to skip tuning")
    cache: Dict[Tuple[str, int], Optional[Tuple[dict, list, float]]] = {}
    for s in todo:
        key = (s.method, int(s.axes))
        if key not in cache:
            t0 = time.perf_counter()
            try:
                best, table = tune_method(s.method, s.axes, clips, max_batch=max_batch, device=device)
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
            est = registry.build(s.method, s.axes)
            default = {k: getattr(est, k) for k in best}
        else:
            default = {}
        d_row = next((r for r in table if all(jsonable(r["params"].get(k)) == jsonable(v) for k, v in default.items())
                      and default), None)
        record["methods"][s.name] = {
            "params": jsonable(best), "score_aae_deg": jsonable(table[0]["score"]),
            "grid_size": len(table), "time_s": round(dt, 2),
            "default_params": jsonable(default) if default else "authors' defaults (see estimators/peers.py)",
            "default_in_grid_score_aae_deg": jsonable(d_row["score"]) if d_row else None,
            "top": jsonable(table[:3]),
        }
    return record


# ===========================================================================
# the comparison
# ===========================================================================


def compare(eval_seqs: Sequence[ImuSequence], tune_seqs: Sequence[ImuSequence] = (),
            methods: Optional[Sequence[str]] = None, data_axes: Optional[int] = None, both_axes: bool = True,
            variants: Sequence[str] = VARIANTS, tune: bool = True, ckpts: Optional[Mapping[str, str]] = None,
            ablation_ckpts: Optional[Mapping[str, str]] = None, out_dir=None,
            tune_max_seconds_per_recording: Optional[float] = 60.0, tune_lead_seconds: float = 10.0,
            tune_recordings: Optional[int] = None, tune_max_batch: int = 128, dataset: Optional[str] = None,
            plots: bool = False, trajectories: bool = False, align="protocol", device: str = "cpu",
            reanchor: Optional[int] = None, on_calibrated: Optional[Mapping[str, str]] = None,
            verbose: bool = False, progress: bool = True, extra: Optional[dict] = None) -> dict:
    """Build, tune, evaluate, write tables.

    Args:
        eval_seqs: recordings to score (with ground truth).
        tune_seqs: TRAINING recordings for tuning (must not share samples with ``eval_seqs``:
            same name and overlapping time span is an error).
        methods: registered method names (:mod:`tcn_ahrs.estimators.registry`; None:
            :func:`default_methods`).
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
    from ..evaluate.runner import evaluate

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
    specs = method_specs(default_methods() if methods is None else methods, data_axes, both_axes, variants, all_ckpts)

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
        from ..estimators.learned import OnLearnedCalibration

        for s_, e in list(zip(specs, estimators)):
            if s_.kind in ("classical", "peer"):
                w = OnLearnedCalibration(e, path, label, device)
                estimators.append(w)
                specs.append(replace(s_, name=w.name))
    if progress:
        estimators = [_timed(e) for e in estimators]
    t0 = time.perf_counter()
    res = evaluate(estimators, eval_seqs, out_dir=out_dir, plots=plots, trajectories=trajectories,
                   axes=data_axes, dataset=dataset, align=align, verbose=verbose)
    eval_s = time.perf_counter() - t0
    estimators = [getattr(e, "inner", e) for e in estimators]
    res["tuning"] = tuning
    res["columns"] = {s.name: {"method": s.method, "axes": s.axes, "variant": s.variant,
                               "params": jsonable(s.params), "ckpt": s.ckpt,
                               "heading_free": bool(getattr(e, "heading_free", False))}
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

    def run(self, seq, init_quat=None, init_index=0):
        t0 = time.perf_counter()
        r = self.inner.run(seq, init_quat, init_index)
        print(f"  {self.inner.name} on {seq.name}: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        return r


def _add_run_batch():
    def run_batch(self, seqs, init_quats, init_indices=None):
        t0 = time.perf_counter()
        r = self.inner.run_batch(seqs, init_quats, init_indices)
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


# ===========================================================================
# Hydra entry points
# ===========================================================================

# conf/compare.yaml's and conf/benchmark.yaml's top-level keys: tcn_ahrs/config/scripts.py
COMPARE_KEYS = keys(CompareConfig)
BENCHMARK_KEYS = keys(BenchmarkConfig)  # speed/quick: speed mode; transfer, lodo, finetune: theirs
_C = CompareConfig()  # the defaults of keys a hand-built config may lack


def _default_out(cfg, kind: str) -> Path:
    from ..app import output_dir

    return output_dir(cfg.get("out"), Path("runs") / kind / str(cfg.data.name))


def _tune_data_cfg(cfg):
    """The data config the tuning recordings come from: ``tune_data`` (a name in conf/data/, e.g.
    ``broad``: its shipped training recordings, ``tune_root`` to move its root), else ``cfg.data``."""
    name = cfg.get("tune_data")
    if not name:
        if cfg.get("tune_root"):
            raise ValueError("tune_root: give tune_data=<name> too (the dataset whose training recordings tune)")
        return cfg.data
    from omegaconf import OmegaConf

    path = conf_path("data", f"{name}.yaml")
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
    from ..datasets import load_split

    unknown = set(k for k in cfg.keys() if k not in ("data", "hydra")) - set(allowed_keys)
    if unknown:
        raise ValueError(f"{kind} config: unknown key(s) {sorted(unknown)}; expected a subset of {sorted(allowed_keys)}")
    set_threads(cfg.get("threads"))
    split = str(cfg.data.get("split", "test"))
    tune_split = str(cfg.get("tune_split") or _C.tune_split)
    if tune_split not in ("train", "trainval"):
        raise ValueError(f"tune_split: expected 'train' (the training parts of the training recordings) or "
                         f"'trainval', got {tune_split!r}: tuning never uses test/validation recordings")
    tune_data = _tune_data_cfg(cfg)
    if (cfg.get("tune") and tune_data is cfg.data
            and (split in ("train", "trainval", "all") or (tune_split == "trainval" and split == "val"))):
        raise ValueError(f"tune=true with data.split={split}: the evaluation would include the tuning recordings "
                         f"(tune_split={tune_split}); evaluate on test (or val with tune_split=train), or tune on "
                         "another dataset's training recordings (tune_data=broad)")
    registry.load_plugins(plain(cfg.get("plugins")))
    methods = list(plain(cfg.get("methods")) or default_methods())
    if cfg.get("peers"):
        methods += [m for m in registry.methods("peer") if m not in methods]
    ckpts = dict(plain(cfg.get("ckpts")) or {})
    if cfg.get("ckpt"):
        ckpts.setdefault(str(cfg.get("ckpt_label") or BenchmarkConfig.ckpt_label), str(cfg.ckpt))
    t0 = time.perf_counter()
    eval_seqs = [s for s in load_split(cfg.data, split) if s.has_gt]
    if not eval_seqs:
        raise ValueError(f"{kind}: no recordings with ground truth in data '{cfg.data.name}' split '{split}' "
                         f"(root {cfg.data.get('root')})")
    tune_seqs = load_split(tune_data, tune_split) if cfg.get("tune") else []
    load_s = time.perf_counter() - t0
    out = _default_out(cfg, kind)
    res = compare(eval_seqs, tune_seqs, methods=methods, data_axes=int(cfg.data.get("axes", 9)),
                  both_axes=bool(cfg.get("both_axes", _C.both_axes)),
                  variants=list(plain(cfg.get("variants")) or VARIANTS),
                  tune=bool(cfg.get("tune")), ckpts=ckpts, ablation_ckpts=plain(cfg.get("ablation_ckpts")) or {},
                  out_dir=out, tune_max_seconds_per_recording=cfg.get("tune_max_seconds_per_recording"),
                  tune_lead_seconds=float(cfg.get("tune_lead_seconds", _C.tune_lead_seconds)),
                  tune_recordings=cfg.get("tune_recordings"),
                  tune_max_batch=int(cfg.get("tune_max_batch", _C.tune_max_batch)),
                  dataset=str(cfg.data.name), plots=bool(cfg.get("plots", _C.plots)),
                  trajectories=bool(cfg.get("trajectories", _C.trajectories)),
                  align=cfg.get("align", _C.align),
                  device=str(cfg.get("device", _C.device)), verbose=bool(cfg.get("verbose", _C.verbose)),
                  reanchor=cfg.get("reanchor"), on_calibrated=plain(cfg.get("on_calibrated")) or None,
                  extra={"split": split, "tune_split": tune_split if cfg.get("tune") else None,
                         "config": plain(cfg), "load_s": round(load_s, 2)})
    print(f"results in {out}")
    print(average_rows(res))
    from ..evaluate.main import print_health

    print_health(res)
    return res


def benchmark_accuracy_main(cfg) -> dict:
    """``scripts/benchmark.py accuracy``: :func:`compare_main` with the peers (``peers: true`` in
    conf/benchmark.yaml) and an optional learned checkpoint ``ckpt``."""
    return compare_main(cfg, BENCHMARK_KEYS, kind="benchmark")
