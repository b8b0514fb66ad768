"""``scripts/train.py``'s body, :func:`train_main`: build data + model, fit (best-validation and
``last.ckpt`` written atomically), then evaluate the best checkpoint on held-out recordings with
the evaluation runner (:func:`tcn_ahrs.evaluate.evaluate`) and print the table.

The parts live in :mod:`tcn_ahrs.training`: the LightningModule (:mod:`~tcn_ahrs.training.module`),
the trainer with its callbacks, loggers and resume search (:mod:`~tcn_ahrs.training.trainer`), the
checks and starting points (:mod:`~tcn_ahrs.training.setup`); they are re-exported here. The
configuration's schema: :mod:`tcn_ahrs.config` (train.yaml = :class:`~tcn_ahrs.config.TrainScriptConfig`).
"""
from __future__ import annotations

import json
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
import pytorch_lightning as pl
import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from ..checkpoint import check_layout, checkpoint_meta, load_checkpoint
from ..config import EvalSection, TrainConfig, TrainScriptConfig, check_keys, check_types, plain
from ..config.train import TRAIN_GROUPS
from ..data import AHRSDataModule
from ..model.ahrs import LearnedAHRS
from .module import AHRSModule
from .setup import (AUGMENT_KEYS, MONITORS, TRAIN_KEYS, TRAIN_VALUES, check_train_values,  # noqa: F401
                             choose_knobs_into_checkpoint, model_axes, rest_gyro_mean)
from .trainer import (RESUME_KEYS, AppendingCSVLogger, RandomState, build_trainer, check_groups,  # noqa: F401
                               command_line_overrides, find_resume_checkpoint, resume_config, run_dir_of,
                               trim_metrics)
from ..validate import set_threads

__all__ = ["train_main", "check_config", "AHRSModule", "choose_knobs_into_checkpoint", "rest_gyro_mean",
           "check_train_values", "model_axes", "build_trainer", "RandomState", "find_resume_checkpoint",
           "resume_config", "trim_metrics", "command_line_overrides", "TRAIN_KEYS", "AUGMENT_KEYS",
           "TRAIN_VALUES", "MONITORS", "RESUME_KEYS", "AppendingCSVLogger"]


_T, _E = TrainConfig(), EvalSection()  # the defaults of keys a hand-built config may lack


def check_config(cfg) -> None:
    """train.yaml's top level, ``train:`` and ``eval:`` against their schemas (a misspelt key is
    an error naming the expected set; the groups ``data``/``model``/``trainer``/``callbacks``/
    ``logger`` are checked by their own code — the last two here too, before any work —
    ``crossval`` by scripts/crossval.py)."""
    check_keys(cfg, TrainScriptConfig, "train config", extra=TRAIN_GROUPS + ("crossval",))
    check_keys(cfg.train, TrainConfig, "train")
    check_train_values(cfg.train)  # numbers and their ranges first: the established messages
    check_keys(cfg.get("eval") or {}, EvalSection, "eval")
    own = {k: v for k, v in cfg.items() if k not in TRAIN_GROUPS and k != "crossval"}
    check_types(own, TrainScriptConfig, "")  # lists, booleans, strings (train.loss_js=16)
    check_groups(cfg)


def train_main(cfg: DictConfig, train_seqs=None, val_seqs=None, test_seqs=None,
               overrides: Optional[List[str]] = None, callbacks=()) -> Dict[str, Any]:
    """Train, then evaluate on held-out data. Returns {"run_dir", "best", "last", "results"}.

    ``train_seqs``/``val_seqs``/``test_seqs`` replace the data config's splits (tests).
    ``resume=true`` continues the run in ``run_dir`` with its saved configuration
    (:func:`resume_config`; ``overrides``: this command's ``key=value`` settings, by default the
    Hydra job's). ``callbacks``: more Lightning callbacks (tests).

    The steps of a run, as docs/architecture describes it: set up (the checked configuration, the
    model's, the data), tune (the backbone's knobs on the training recordings), build (the module
    and its starting points), fit, select (the checkpoint that ships and its inference knobs),
    evaluate (held-out recordings, beside the baselines)."""
    cfg, run_dir, axes = _set_up(cfg, overrides)
    model_cfg, init_model = _model_config(cfg, axes)
    probe = LearnedAHRS.from_config(model_cfg)  # fail early on a bad model config
    dm, supervision = _data(cfg, axes, probe, init_model, train_seqs, val_seqs)
    model_cfg = _tune(cfg, axes, probe, dm, model_cfg, supervision)
    module = _build_module(cfg, axes, dm, model_cfg, init_model, supervision)
    monitor = str(cfg.train.monitor) if dm.val_store is not None else "train/loss_epoch"
    trainer, fit_s = _fit(cfg, run_dir, axes, dm, module, model_cfg, monitor, callbacks)
    result = _select(cfg, run_dir, dm, module, trainer, fit_s, monitor)
    if init_model is not None and trainer.is_global_zero:
        result["best"] = _keep_if_not_better(cfg, run_dir, axes, dm, result["best"], supervision)
    if trainer.is_global_zero:
        result["results"] = _evaluate(cfg, run_dir, axes, result["best"], test_seqs)
    return result


def _set_up(cfg: DictConfig, overrides: Optional[List[str]]):
    """The checked configuration (a resumed run's own), the seeds and threads, the run folder."""
    if cfg.get("resume") and not cfg.get("ckpt_path"):
        cfg = resume_config(cfg, run_dir_of(cfg), overrides if overrides is not None else command_line_overrides())
    check_config(cfg)
    from ..estimators.registry import check_method_names

    check_method_names((cfg.get("eval") or {}).get("baselines"))  # a typo fails now, not after training
    set_threads(cfg.get("threads"))
    pl.seed_everything(int(cfg.seed), workers=True)
    run_dir = run_dir_of(cfg)
    run_dir.mkdir(parents=True, exist_ok=True)
    return cfg, run_dir, model_axes(cfg)


def _model_config(cfg: DictConfig, axes: int):
    """(the model's configuration, the model fine-tuning starts from or None)."""
    model_cfg = plain(cfg.model)
    model_cfg["axes"] = axes
    if not cfg.get("init"):
        return model_cfg, None
    # fine-tuning: the architecture, knobs and weights are the checkpoint's; the model group is not used
    from ..checkpoint import model_from_checkpoint

    from ..evaluate.main import shipped

    with open_dict(cfg):   # checkpoints/<name>.ckpt or <name>: the shipped model, from anywhere (an old name said)
        cfg.init = shipped(str(cfg.init))
    init_model = model_from_checkpoint(str(cfg.init))
    check_layout(load_checkpoint(str(cfg.init)), axes, str(cfg.init))
    model_cfg = dict(checkpoint_meta(load_checkpoint(str(cfg.init)), str(cfg.init))["model"])
    model_cfg["axes"] = axes
    if cfg.train.get("init_gyro_bias", _T.init_gyro_bias) and model_cfg.get("residual") is not None:
        # the bias state starts at this device's estimated bias (general models start at zero)
        model_cfg["residual"] = {**dict(model_cfg["residual"]), "bias_prior": 1.0}
    print(f"fine-tuning from {cfg.init} ({model_cfg.get('variant')}, {init_model.num_parameters():,} parameters)")
    return model_cfg, init_model


def _data(cfg: DictConfig, axes: int, probe: LearnedAHRS, init_model, train_seqs, val_seqs):
    """(the data module, prepared; the supervision: "gt" or "self")."""
    # the closed loop trains on chained chunks whose networks see receptive_field - 1 samples before
    margin = probe.receptive_field - 1 if probe.closed is not None else 0
    if cfg.train.get("all_recordings") and train_seqs is None:
        # the released model: every training recording, whole, with the fixed schedule; nothing
        # held out, so nothing is selected (the last epoch ships)
        from ..datasets import load_split

        train_seqs, val_seqs = load_split(cfg.data, "trainval"), []
    supervision = str(cfg.train.get("supervision") or _T.supervision)
    if supervision == "self" and (probe.backbone is None or init_model is None):
        raise ValueError("train.supervision=self: fine-tunes a residual model without ground truth; set "
                         "init=<checkpoint of a residual model> (e.g. checkpoints/general9_residual.ckpt)")
    dm = AHRSDataModule(cfg.data, axes, cfg.train.window, cfg.train.stride, cfg.train.batch_size,
                        train_seqs, val_seqs, margin=margin, balance=bool(cfg.train.get("balance")),
                        supervision=supervision, device_check=bool(cfg.train.get("device_check", _T.device_check)))
    dm.prepare()
    if supervision == "self":
        # no validation loss without ground truth; the held-out parts stay for the evidence that
        # decides whether the fine-tuned model ships (training.adaptation)
        dm.val_store = None
    return dm, supervision


def _tune(cfg: DictConfig, axes: int, probe: LearnedAHRS, dm, model_cfg: Dict[str, Any], supervision: str):
    """The backbone's knobs, chosen on the training recordings before any network trains (never
    on the held-out ones), stored in the model config so that the checkpoint keeps them."""
    if probe.backbone is None or not cfg.train.get("tune_backbone", _T.tune_backbone) or supervision != "gt":
        return model_cfg
    from ..kernels.backbone_layout import BackboneParams
    from ..tuning.knobs import tune_backbone

    criterion = str(cfg.train.get("tune_criterion") or _T.tune_criterion)
    chosen, table = tune_backbone(dm.train_seqs, axes,
                                  gyro_bias_std=float((cfg.train.get("augment") or {}).get("gyro_bias") or 0.0),
                                  criterion=criterion)
    res = dict(model_cfg.get("residual") or {})
    res["backbone"] = {**dict(res.get("backbone") or {}), **chosen}
    model_cfg["residual"] = res
    vqf = BackboneParams()  # VQF's defaults, where the grid holds them
    at_defaults = [r["score"] for r in table if all(float(v) == getattr(vqf, k) for k, v in r["params"].items())]
    beside = f"; VQF's defaults {at_defaults[0]:.2f}" if at_defaults else ""
    print(f"backbone parameters chosen on the {len(dm.train_seqs)} training recordings: {chosen} "
          f"(score {table[0]['score']:.2f}, {criterion}{beside})")
    return model_cfg


def _build_module(cfg: DictConfig, axes: int, dm, model_cfg: Dict[str, Any], init_model, supervision: str):
    """The LightningModule with its starting points: the fine-tuned model's weights, or the
    input statistics; the gyro bias measured at rest (closed loop) or the backbone's bias state."""
    ema = cfg.train.get("ema_decay", _T.ema_decay)
    module = AHRSModule(model_cfg, axes, lr=float(cfg.train.lr), weight_decay=float(cfg.train.weight_decay),
                        epochs=int(cfg.train.epochs), window=dm.window, loss_js=list(cfg.train.loss_js),
                        huber_delta=float(cfg.train.huber_delta), noise=plain(cfg.train.noise),
                        stream_chunks=int(cfg.train.get("stream_chunks") or _T.stream_chunks),
                        attitude_delta=float(cfg.train.get("attitude_delta") or _T.attitude_delta),
                        ema_decay=float(ema or 0.0),  # null or 0: off
                        augment=plain(cfg.train.get("augment") or {}), supervision=supervision,
                        data_name=str(cfg.data.name),
                        device_check=bool(cfg.train.get("device_check", _T.device_check)),
                        # the rate the model learned at (its TCN's time scale), for deployment
                        rate_hz=float(np.median([s.rate for s in dm.train_seqs])))
    if init_model is not None:
        state = init_model.state_dict()
        if module.model.backbone is not None:  # the knobs just tuned (if any) stay this run's
            state = {k: v for k, v in state.items() if not k.startswith("backbone.")}
        module.model.load_state_dict(state, strict=False)
    else:
        mean, std = dm.statistics()
        module.model.calibration.set_input_stats(mean, std)
    at_rest = cfg.train.get("init_gyro_bias", _T.init_gyro_bias)
    if module.model.closed is not None:
        module.model.closed.set_rate(module.hparams.rate_hz)
        bias = rest_gyro_mean(module.model, dm.train_store) if at_rest else None
        if bias is not None:
            # the static gyro bias, measured where the training recordings are at rest, as the
            # gyro error term's starting point: a TCN output that must grow from zero to an
            # uncalibrated bias (EuRoC: 0.077 rad/s) at lr 1e-3 takes thousands of steps
            module.model.calibration.set_gyro_bias(bias)
            print(f"gyro error term starts at the training recordings' mean gyro at rest: "
                  f"{[round(float(v), 5) for v in bias]} rad/s")
    if module.model.backbone is not None and at_rest:
        from ..tuning.knobs import backbone_bias

        b0 = backbone_bias(dm.train_seqs, axes, (model_cfg.get("residual") or {}).get("backbone") or {})
        module.model.backbone.bias_init.copy_(torch.as_tensor(b0))
        print(f"backbone bias state starts at the training recordings' estimated bias {np.round(b0, 5).tolist()} rad/s")
    module.reset_ema()
    return module


def _resume_point(cfg: DictConfig, run_dir: Path, axes: int) -> Optional[str]:
    """The checkpoint a resumed (or ``ckpt_path=``) run continues from; the interrupted epoch's
    metrics rows dropped (the resumed run logs them again)."""
    ckpt_path = cfg.get("ckpt_path")
    if cfg.get("resume") and not ckpt_path:
        ckpt_path = str(find_resume_checkpoint(run_dir))
    if ckpt_path:
        ck = load_checkpoint(ckpt_path)
        check_layout(ck, axes, ckpt_path)
        print(f"resuming from {ckpt_path} (epoch {ck.get('epoch')})")
        if cfg.get("resume") and ck.get("epoch") is not None:
            dropped = trim_metrics(run_dir / "logs" / "metrics.csv", int(ck["epoch"]), int(ck.get("global_step") or 0))
            if dropped:
                print(f"resume: dropped {dropped} metrics rows of the interrupted epoch {int(ck['epoch']) + 1}")
    return ckpt_path


def _fit(cfg: DictConfig, run_dir: Path, axes: int, dm, module, model_cfg: Dict[str, Any], monitor: str, callbacks):
    """(the trainer after fitting, the fit's wall time in s); the configuration as started written
    to the run folder (a resumed run keeps it and notes its own)."""
    ckpt_path = _resume_point(cfg, run_dir, axes)
    trainer = build_trainer(cfg, run_dir, monitor, callbacks)
    if trainer.is_global_zero:
        name = "config_resumed.yaml" if (cfg.get("resume") and (run_dir / "config_resolved.yaml").is_file()) \
            else "config_resolved.yaml"
        (run_dir / name).write_text(OmegaConf.to_yaml(cfg, resolve=True))
        n = module.model.num_parameters()
        print(f"model {model_cfg.get('variant')} ({axes}-axis): {n:,} trainable parameters, "
              f"receptive field {module.model.receptive_field} samples; "
              f"{len(dm.starts)} training windows of {dm.window} samples; run dir {run_dir}")
    t0 = time.perf_counter()
    trainer.fit(module, datamodule=dm, ckpt_path=ckpt_path)
    return trainer, time.perf_counter() - t0


def _select(cfg: DictConfig, run_dir: Path, dm, module, trainer, fit_s: float, monitor: str) -> Dict[str, Any]:
    """The checkpoint that ships: the best validation epoch, or the fixed schedule's last (every
    recording trained on; a residual model, with its inference knobs chosen on the validation
    recordings, never on the reported ones). A time cap that cut the schedule is warned about."""
    ckpt_cb = trainer.checkpoint_callback
    best = ckpt_cb.best_model_path or str(run_dir / "checkpoints" / "last.ckpt")
    last = str(run_dir / "checkpoints" / "last.ckpt")
    if cfg.train.get("all_recordings"):
        best = last  # nothing was held out: nothing to select on, the fixed schedule's end ships
    result = {"run_dir": str(run_dir), "best": best, "last": last, "fit_s": fit_s, "results": None}
    if not trainer.is_global_zero:
        return result
    if module.model.backbone is not None:
        best = last
        result["best"] = last
        if cfg.train.get("select_knobs", _T.select_knobs) and dm.val_seqs and dm.supervision == "gt":
            result["knobs"] = choose_knobs_into_checkpoint(last, _knob_parts(cfg, dm), run_dir,
                                                           plain(cfg.train.get("knob_grid")) or None,
                                                           str(cfg.train.get("knob_rule") or _T.knob_rule))
    print(f"training took {fit_s:.1f} s; best checkpoint {best} ({monitor} = {ckpt_cb.best_model_score})")
    done_epochs = int(trainer.current_epoch)
    if cfg.train.get("max_time") and done_epochs < int(cfg.train.epochs):
        result["stopped_by_time_cap"] = True
        print(f"WARNING: the time cap train.max_time={cfg.train.max_time} stopped training after "
              f"{done_epochs} of {int(cfg.train.epochs)} epochs: the model is under-trained. Real data: "
              "use its schedule (experiment=<name>_cl, no cap) or set train.max_time=null", file=sys.stderr)
    return result


def _gated(cfg: DictConfig) -> bool:
    """Fine-tuning whose result ships only on held-out evidence (:func:`_keep_if_not_better`)."""
    return bool(cfg.get("init")) and bool(cfg.train.get("keep_if_not_better", _T.keep_if_not_better))


def _knob_parts(cfg: DictConfig, dm) -> List:
    """The validation recordings the inference knobs are chosen on: all of them, or, when a
    fine-tuning's result must prove itself on held-out evidence, the first half of each (the
    second half is the evidence: knobs chosen on it would make it say "better" for the fit to
    them — BROAD, two recordings: 1.60 → 0.62° on the parts that chose the knobs, 2.58 → 3.20°
    on the other 14)."""
    if not _gated(cfg):
        return list(dm.val_seqs)
    return [s.slice(0, _half(s)) for s in dm.val_seqs if len(s) >= 4]


def _evidence_parts(cfg: DictConfig, dm) -> List:
    """The held-out parts a fine-tuning is judged on: the halves :func:`_knob_parts` left out
    (all of each part without ground truth, where no knob was chosen)."""
    if dm.supervision != "gt":
        return list(dm.val_seqs)
    return [s.slice(_half(s), len(s)) for s in dm.val_seqs if len(s) >= 4]


def _half(seq) -> int:
    """Where a part splits into halves of equal scored ground truth (BROAD scores no final rest:
    halves by samples left the second without any)."""
    scored = np.nonzero(seq.scored())[0] if seq.has_gt else np.zeros(0, int)
    cut = int(scored[scored.size // 2]) if scored.size >= 2 else len(seq) // 2
    return min(max(cut, 2), len(seq) - 2)


def _crossfit(cfg: DictConfig, run_dir: Path, dm, supervision: str, axes: int):
    """Evidence about the user's *other* recordings (``train.adopt_on: recordings``, with ≥ 2 of them):
    for each recording, the same fine-tuning run without it (its parts left out of training and of
    the knob choice) and both models scored on it, whole. Halves of the recordings that trained say
    little about the device's next recording (OxIOD, another user: adopted on the held-out halves
    3.34 → 2.85, then 8.64 against 8.46 before it on the user's two other recordings). Returns
    (before, after, the recordings) pooled over the recordings, or None where it does not apply."""
    if str(cfg.train.get("adopt_on", _T.adopt_on)) != "recordings":
        return None
    from ..estimators.learned import LearnedEstimator
    from ..evaluate.files import safe_name
    from .adaptation import evidence

    key = lambda s: s.meta.get("recording", s.name)  # noqa: E731
    names = sorted({key(s) for s in list(dm.train_seqs) + list(dm.val_seqs or [])})
    if len(names) < 2:
        return None
    whole = {key(s): s for s in _whole_recordings(cfg, names)}
    held, before_est = [], LearnedEstimator(str(cfg.init), name="before")
    rows = {"before": [], "after": []}
    for name in names:
        sub = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
        with open_dict(sub):
            sub.run_dir = str(run_dir / "crossfit" / safe_name(name))
            sub.train.keep_if_not_better = False
            sub.eval.enabled = False
            sub.resume = (Path(sub.run_dir) / "checkpoints" / "last.ckpt").is_file()
        print(f"fine-tuning without {name} (cross-fitted evidence, {names.index(name) + 1} of {len(names)})")
        res = train_main(sub, [s for s in dm.train_seqs if key(s) != name],
                         [s for s in (dm.val_seqs or []) if key(s) != name], [], overrides=[])
        rec = [whole[name]] if name in whole else [s for s in list(dm.train_seqs) + list(dm.val_seqs or []) if key(s) == name]
        held += rec
        rows["before"].append(evidence(before_est, rec, supervision, axes))
        rows["after"].append(evidence(LearnedEstimator(res["best"], name="after"), rec, supervision, axes))
    pooled = {k: _pool(v) for k, v in rows.items()}
    return pooled["before"], pooled["after"], held


def _pool(records: List[Dict[str, Any]]) -> Dict[str, Any]:
    """The mean of each number over the per-recording evidence records (None where any is None)."""
    out: Dict[str, Any] = {}
    for k in records[0]:
        vals = [r.get(k) for r in records]
        ok = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals)
        out[k] = float(np.mean(vals)) if ok else (None if any(v is None for v in vals) else vals[0])
    return out


def _whole_recordings(cfg: DictConfig, names: List[str]) -> List:
    """The user's recordings, whole (device-checked as training read them), where the data config lists them."""
    from ..datasets import load_split

    try:
        seqs = [s for s in load_split(cfg.data, "trainval") if s.name in names and s.has_gt]
    except (ValueError, FileNotFoundError, KeyError):
        return []
    if cfg.train.get("device_check", _T.device_check):
        from ..device_check import checked
        seqs = checked(seqs)
    return seqs


def _keep_if_not_better(cfg: DictConfig, run_dir: Path, axes: int, dm, tuned: str, supervision: str) -> str:
    """Fine-tuning: the checkpoint that ships — the fine-tuned one when the held-out parts of the
    user's recordings (the halves that chose no knob) say it is better than the starting model (with ground truth: AAE and
    inclination; without: drift at rest and the gravity angle, :mod:`tcn_ahrs.training.adaptation`),
    else the starting model (``checkpoints/kept.ckpt``). The evidence goes to ``adaptation.json``."""
    if not _gated(cfg):
        return tuned
    from ..checkpoint import atomic_save
    from ..estimators.learned import LearnedEstimator
    from .adaptation import decide, evidence

    crossfit = _crossfit(cfg, run_dir, dm, supervision, axes)
    if crossfit is not None:  # whole recordings each fine-tuning never saw
        before, after, seqs = crossfit
    else:
        seqs = _evidence_parts(cfg, dm)
        before = evidence(LearnedEstimator(str(cfg.init), name="before"), seqs, supervision, axes)
        after = evidence(LearnedEstimator(tuned, name="after"), seqs, supervision, axes)
    adopt, why = decide(before, after, supervision)
    if crossfit is not None:
        why = why.replace("held-out parts", "each recording left out of its own fine-tuning, whole")
    shipped = tuned
    if not adopt:
        ck = load_checkpoint(str(cfg.init))
        if cfg.train.get("device_check", _T.device_check):  # compared on checked input: it is given that
            ck["tcn_ahrs"] = {**ck["tcn_ahrs"], "layout": {**ck["tcn_ahrs"]["layout"], "device_check": True}}
        shipped = str(run_dir / "checkpoints" / "kept.ckpt")
        atomic_save(ck, shipped)
    record = {"supervision": supervision, "evidence": "recordings left out (cross-fitted)" if crossfit else "held-out parts",
              "held_out_parts": [s.name for s in seqs], "before": before,
              "after": after, "adopted": bool(adopt), "why": why, "shipped": shipped, "fine_tuned": tuned}
    (run_dir / "adaptation.json").write_text(json.dumps(record, indent=2) + "\n")
    print(f"fine-tuning: {why} ({shipped})")
    return shipped


def _evaluate(cfg: DictConfig, run_dir: Path, axes: int, best: str, test_seqs) -> Optional[Dict[str, Any]]:
    """The shipped checkpoint on the held-out recordings beside Raw IMU and ``eval.baselines``,
    through the evaluation runner; the table printed."""
    ev = cfg.get("eval") or {}
    if not ev.get("enabled", _E.enabled):
        return None
    from ..evaluate import evaluate, print_table
    from ..evaluate.reports import print_summary
    from ..estimators.learned import LearnedEstimator
    from ..estimators.registry import baseline_estimators

    if test_seqs is None:
        from ..datasets import load_split
        test_seqs = load_split(cfg.data, str(ev.get("split", _E.split)))
    test_seqs = [s for s in test_seqs if s.has_gt]
    if not test_seqs:
        warnings.warn(f"no held-out recordings with ground truth in split {ev.get('split', 'test')!r}; "
                      "skipping the evaluation")
        return None
    learned = LearnedEstimator(best, name=str(ev.get("name", _E.name)))
    estimators = [learned] + baseline_estimators(["raw"] + list(ev.get("baselines", _E.baselines)), axes)
    res = evaluate(estimators, test_seqs, out_dir=run_dir / "eval", axes=axes,
                   dataset=str(cfg.data.name), plots=bool(ev.get("plots", _E.plots)),
                   trajectories=bool(ev.get("trajectories", _E.trajectories)))
    print(f"\nHeld-out evaluation ({cfg.data.name}, split {ev.get('split', 'test')}, "
          f"{len(test_seqs)} recordings; results in {run_dir / 'eval'}):")
    print_table(res)
    print_summary(res, learned.name)
    return res
