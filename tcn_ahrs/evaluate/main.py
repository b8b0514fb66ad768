"""``scripts/evaluate.py``: a checkpoint (+ Raw IMU and ``baselines``) through the runner."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Dict

import torch
from omegaconf import DictConfig, open_dict

from ..checkpoint import check_layout, checkpoint_meta, load_checkpoint
from ..config import EvaluateConfig, check_keys, keys
from ..app import output_dir, refuse_earlier_output, staged_output
from ..validate import set_threads
from .reports import print_table
from .runner import evaluate

EVAL_KEYS = keys(EvaluateConfig)  # conf/evaluate.yaml's top level: tcn_ahrs/config/scripts.py
_D = EvaluateConfig()  # the defaults of keys a hand-built config may lack


def dataset_axes(name: str) -> int | None:
    """The axes a named dataset's config declares (``conf/data/<name>.yaml``: 6 for
    EuRoC and TUM VI, which have no magnetometer); None for a dataset without one."""
    from omegaconf import OmegaConf

    from ..config import conf_path

    p = conf_path("data", f"{name}.yaml")
    if not p.is_file():
        return None
    axes = (OmegaConf.to_container(OmegaConf.load(p), resolve=False) or {}).get("axes")
    return int(axes) if isinstance(axes, int) else None


def evaluate_main(cfg: DictConfig) -> Dict[str, Any]:
    """``scripts/evaluate.py``: the learned estimator + Raw IMU (+ ``baselines``) on
    ``load_split(data, data.split)``; writes results.json/.md, plots, TUM trajectories."""
    from ..estimators.learned import LearnedEstimator

    check_keys({k: v for k, v in cfg.items() if k not in ("data", "hydra")}, EvaluateConfig, "evaluate config")
    set_threads(cfg.get("threads"))
    default_estimator = not cfg.get("ckpt")
    if not default_estimator:
        with open_dict(cfg):
            cfg.ckpt = shipped(str(cfg.ckpt))
    # the general models (any IMU) are given device-checked recordings, as they were chosen on
    general_model = not default_estimator and Path(str(cfg.ckpt)).stem in GENERAL_MODELS
    # run_dir= (a training run): its eval/ subfolder, never the run's own files
    explicit = cfg.get("out") or (str(Path(str(cfg.run_dir)) / "eval") if cfg.get("run_dir") else None)
    out = str(output_dir(explicit, Path("runs") / "evaluate"))
    refuse_earlier_output(out, bool(cfg.get("overwrite", _D.overwrite)), "evaluate")  # before any work
    from ..estimators.families import is_estimator_file, load_estimator

    axes = int(cfg.data.get("axes", 9))
    if default_estimator:
        print("note: no ckpt given: the backbone with VQF's defaults and the causal device check (the gyro bias "
              "of each rest so far, beyond VQF's 2 °/s clip: what the exported runtimes run); every method on the "
              "same raw readings (device_check=offline: the bias read from the whole recording, a device cannot); "
              "the learned models for any IMU are ckpt=general9_residual / ckpt=general6_residual, your "
              "device's own: tcn-ahrs search")
        name = str(cfg.get("name")) if cfg.get("name") not in (None, _D.name) else DEFAULT_NAME
        return _run(cfg, default(axes, name), *_recordings(cfg, False), axes, out)
    if is_estimator_file(cfg.ckpt):  # a classical family chosen by tcn-ahrs search
        from ..device_check import RestBiasCalibration

        learned = load_estimator(str(cfg.ckpt), name=str(cfg.get("name") or _D.name))
        axes = min(axes, int(learned.axes or axes))
        # its calibration the device check: every method gets the checked recordings (side by side
        # means the same input; the release alone got them, the baselines raw), the check run once
        on_check = isinstance(learned.cal, RestBiasCalibration) and str(cfg.get("device_check", _D.device_check)).lower() != "false"
        if on_check:
            learned.cal = None
            print(f"note: {Path(str(cfg.ckpt)).name} runs on the device check: every method gets the checked recordings")
        return _run(cfg, learned, *_recordings(cfg, general_model or on_check), axes, out)
    ck = load_checkpoint(cfg.ckpt)
    layout = checkpoint_meta(ck, cfg.ckpt)["layout"]
    if axes == 9 and int(layout["axes"]) == 6:
        # a 6-axis model needs only the gyro and the accelerometer: score the 6-axis view
        print(f"note: {cfg.ckpt} is a 6-axis model: the magnetometer is not used and every method "
              "is scored as 6-axis (heading relative to the start)")
        axes = 6
    check_layout(ck, axes, cfg.ckpt, data_axes=dataset_axes(str(cfg.data.name)))
    # auto: the general models, and a model that learned on checked recordings (train.device_check)
    checked_input = general_model or bool(layout.get("device_check"))
    seqs, refused = _recordings(cfg, checked_input)
    learned = LearnedEstimator(str(cfg.ckpt), name=str(cfg.get("name") or _D.name),
                               device=str(cfg.get("device", _D.device)), reanchor=cfg.get("reanchor"),
                               other_rate=str(cfg.get("other_rate", _D.other_rate)))
    return _run(cfg, learned, seqs, refused, axes, out)


DEFAULT_NAME = "Backbone (default)"
GENERAL_MODELS = ("general6_residual", "general9_residual")
"""Shipped learned models for any IMU, run by name (``ckpt=general9_residual``): named options, not the
default, while they are worse than VQF on datasets they never saw (docs/results.md, leave one
dataset out)."""


DEFAULT_KNOBS = {"rest_check": 1.0}
"""The default's knobs beyond VQF's defaults: the causal device check in the filter
(:func:`tcn_ahrs.kernels.backbone.rest_check`)."""


def default(axes: int, name: str = DEFAULT_NAME):
    """What ``tcn-ahrs evaluate`` runs without ``ckpt=``: the VQF-grade backbone with VQF's defaults
    and the causal device check (each rest's gyro bias, read from the past only, taken where it lies
    beyond VQF's clip: :data:`DEFAULT_KNOBS`) — the filter every runtime runs (``tcn-ahrs export
    ckpt=default``), on the same raw readings as every other method. No training, no file: the
    estimator with the evidence that it is never worse than VQF on every real recording the project
    has (``tcn-ahrs benchmark devices``), where no general model has earned it yet."""
    from ..estimators.families import FAMILIES, Calibrated

    fam = FAMILIES["backbone"]
    return Calibrated(fam.build(axes, **{**fam.defaults_for(axes), **DEFAULT_KNOBS}), None, name=name)


def shipped(ckpt: str) -> str:
    """``ckpt`` as given, or a shipped model named without folder and suffix (``general9_residual``,
    ``euroc6_closed_loop``, ``tumvi6_ecf``) or ``checkpoints/<file>`` where there is no such file:
    ``<name>.ckpt`` or ``.json`` of the installed package (:data:`tcn_ahrs.checkpoints.SHIPPED_DIR`,
    the checkout's ``checkpoints/``). An old name
    (``general9``, ``checkpoints/broad9.ckpt``: :data:`tcn_ahrs.config.renamed.CHECKPOINTS`) runs the
    renamed file and says so."""
    from ..checkpoints import SHIPPED_DIR
    from ..config.renamed import CHECKPOINTS

    path = Path(ckpt)
    if path.exists():
        return ckpt
    if path.stem in CHECKPOINTS and ("/" not in ckpt or path.parent.name == "checkpoints"):
        new = CHECKPOINTS[path.stem]
        print(f"note: ckpt={ckpt} is now ckpt={new} (README, \"Renamed\")")
        ckpt, path = new, Path(new)
    if path.parent.name == "checkpoints" and (SHIPPED_DIR / path.name).is_file():
        return str(SHIPPED_DIR / path.name)   # checkpoints/<file> outside a checkout: the installed one
    if "/" in ckpt or path.suffix:
        return ckpt
    for suffix in (".ckpt", ".json"):
        if (SHIPPED_DIR / f"{ckpt}{suffix}").is_file():
            print(f"note: ckpt={ckpt}: the shipped {SHIPPED_DIR / (ckpt + suffix)}")
            return str(SHIPPED_DIR / f"{ckpt}{suffix}")
    names = sorted(p.stem for p in SHIPPED_DIR.glob("*.ckpt")) + sorted(p.stem for p in SHIPPED_DIR.glob("*.json"))
    raise FileNotFoundError(f"evaluate: ckpt={ckpt}: no such file, nor a shipped model of that name "
                            f"(shipped: {', '.join(names) or 'none in this install'})")


def _recordings(cfg: DictConfig, general_model: bool = False):
    """(the split's recordings with ground truth, [(recording, reason)] of those its checks
    refused); with the offline device check on (``device_check``: auto = for the general models and
    the models trained on checked recordings; ``offline`` for any) each recording's gyro bias at rest,
    read from the whole recording, is subtracted before every method, and what the check found is
    printed. (The default's own check is causal and in its filter: :func:`default`.)"""
    from ..datasets import load_split

    refused: list = []
    seqs = [s for s in load_split(cfg.data, str(cfg.data.split), refused) if s.has_gt]
    mode = str(cfg.get("device_check", _D.device_check)).lower()
    mode = "offline" if mode == "true" else mode   # the old name
    if mode not in ("auto", "offline", "false"):
        raise ValueError(f"device_check: expected auto, offline or false, got {mode!r}")
    if mode == "offline" or (mode == "auto" and general_model):
        from ..device_check import checked

        seqs = checked(seqs, lambda rec, dc: print(f"device check, {rec}: {dc.summary()}"))
    return seqs, refused


def print_health(res: Dict[str, Any], file=None) -> None:
    """Per recording, what the health checks of the methods that run them found (tcn_ahrs.health):
    one line per distinct finding, naming the methods; "no fault found" when they ran and found none."""
    import sys

    file = file or sys.stdout
    for i, rec in enumerate(res["recordings"]):
        found: Dict[str, list] = {}
        for method, m in res["methods"].items():
            health = m["recordings"][i].get("health") if i < len(m["recordings"]) else None
            if health is not None:
                found.setdefault("; ".join(health) or "no fault found", []).append(method)
        for text, methods in found.items():
            print(f"health, {rec} ({', '.join(methods)}): {text}", file=file)


def _run(cfg: DictConfig, learned, seqs, refused, axes: int, out: str) -> Dict[str, Any]:
    """The chosen estimator + Raw IMU (+ ``baselines``) through the runner, written to ``out``.
    Recordings the loader ``refused`` (name, reason) are listed on screen and in
    ``refused.txt``; the good ones are evaluated; then the command fails (exit status 2), so
    nothing refused is silently dropped."""
    from ..estimators.registry import baseline_estimators, load_plugins

    why = "".join(f"\n  {name}: {reason}" for name, reason in refused)
    if not seqs:
        raise ValueError(f"evaluate: no recordings with ground truth in data '{cfg.data.name}' split "
                         f"'{cfg.data.split}' (root {cfg.data.get('root')})" + (f"; refused:{why}" if refused else ""))
    load_plugins(cfg.get("plugins"))
    estimators = [learned] + baseline_estimators(["raw"] + list(cfg.get("baselines") or []), axes)
    landed: list = []
    with staged_output(out, bool(cfg.get("overwrite", _D.overwrite)), "evaluate", landed) as stage:
        res = evaluate(estimators, seqs, out_dir=stage, axes=axes, dataset=str(cfg.data.name),
                       plots=bool(cfg.get("plots", _D.plots)),
                       trajectories=bool(cfg.get("trajectories", _D.trajectories)),
                       align=cfg.get("align", _D.align))
        if refused:
            (stage / "refused.txt").write_text("".join(f"{name}: {reason}\n" for name, reason in refused))
    out = str(landed[0])  # <out>-2 where a concurrent run filled <out> meanwhile
    print(f"results in {out}")
    print_table(res)
    print_health(res)
    if refused:
        raise ValueError(f"evaluate: {len(refused)} recording(s) refused (the other {len(seqs)} are evaluated in "
                         f"{out}; the reasons also in {Path(out) / 'refused.txt'}):{why}")
    return res
