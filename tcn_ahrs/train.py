"""Training glue: the LightningModule and the bodies of the Hydra entry points.

* :class:`AHRSModule` — LearnedAHRS + increment loss (Eqs. 26-28) + AdamW/cosine schedule;
  validation = loss and AAE on the full validation recordings (feed-forward, cheap).
* :func:`train_main(cfg)` — ``scripts/train.py``: build data + model, fit (best-validation and
  ``last.ckpt`` written atomically), then evaluate the best checkpoint on held-out recordings
  with the evaluation runner (:func:`tcn_ahrs.evaluate.evaluate`) and print the table.
"""
from __future__ import annotations

import math
import sys
import os
import time
import warnings
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional

import numpy as np
import pytorch_lightning as pl
import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from . import so3
from .checkpoint import (AtomicCheckpointIO, CheckpointError, check_layout, checkpoint_meta, layout_meta,
                         load_checkpoint)
from .data import AHRSDataModule, augment, augment_sensor
from .losses import attitude_loss, increment_loss, rest_rate_loss, trust_loss
from .model.ahrs import LearnedAHRS
from .cli import output_dir
from .validate import check_keys, check_number, set_threads

TRAIN_KEYS = {"window", "stride", "batch_size", "epochs", "lr", "weight_decay", "loss_js",
              "huber_delta", "noise", "monitor", "max_time", "limit_train_batches", "stream_chunks",
              "attitude_delta", "ema_decay", "init_gyro_bias", "tune_backbone", "all_recordings",
              "select_knobs", "augment", "balance", "supervision", "knob_grid",
              "knob_rule", "tune_criterion"}
AUGMENT_KEYS = {"rate_hz", "jitter", "rotate", "gyro_bias", "scale"}


class AHRSModule(pl.LightningModule):
    """LightningModule around :class:`LearnedAHRS`. All arguments are plain types (they are
    saved in the checkpoint, which is loaded with ``weights_only=True``)."""

    def __init__(self, model_cfg: Dict[str, Any], axes: int, lr: float = 0.01,
                 weight_decay: float = 0.1, epochs: int = 100, window: int = 2000,
                 loss_js: List[int] = (16, 32), huber_delta: float = 0.005,
                 noise: Optional[Dict[str, float]] = None, data_name: str = "",
                 rate_hz: Optional[float] = None, stream_chunks: int = 8, attitude_delta: float = 0.01,
                 ema_decay: float = 0.0, augment: Optional[Dict[str, Any]] = None, supervision: str = "gt"):
        super().__init__()
        self.save_hyperparameters()
        self.model = LearnedAHRS.from_config(model_cfg, axes=axes)
        # Exponential moving average of the weights (Polyak averaging): what validation, the
        # checkpoint selection and the released model use. The closed loop's whole-recording
        # error swings by degrees between neighbouring SGD iterates (a 1e-3 rad/s change of a
        # learned bias is 10 deg of heading over three minutes); the average does not.
        self.ema_model: Optional[LearnedAHRS] = None
        if ema_decay and float(ema_decay) > 0.0:
            self.ema_model = LearnedAHRS.from_config(model_cfg, axes=axes)
            self.ema_model.requires_grad_(False)
            self.reset_ema()
        self.loss_js = [int(j) for j in loss_js]
        self.noise = dict(noise or {})
        self.augment = dict(augment or {})  # train.augment: rate resampling and sensor errors
        self._stream: Optional[Dict[str, torch.Tensor]] = None  # closed-loop TBPTT state

    @torch.no_grad()
    def reset_ema(self) -> None:
        """The average restarts at the current weights (after the data-driven initialisation)."""
        if self.ema_model is not None:
            self.ema_model.load_state_dict(self.model.state_dict())

    @torch.no_grad()
    def on_train_batch_end(self, outputs, batch, batch_idx) -> None:
        if self.ema_model is None:
            return
        w = 1.0 - float(self.hparams.ema_decay)
        for p_avg, p in zip(self.ema_model.parameters(), self.model.parameters()):
            p_avg.lerp_(p.detach(), w)
        for b_avg, b in zip(self.ema_model.buffers(), self.model.buffers()):
            b_avg.copy_(b)

    @property
    def eval_model(self) -> LearnedAHRS:
        return self.model if self.ema_model is None else self.ema_model

    # ------------------------------------------------------------------ steps
    def _store(self, which: str):
        store = getattr(self.trainer.datamodule, which)
        return store.to(self.device)

    def training_step(self, batch, batch_idx):
        (starts,) = batch
        if self.model.closed is not None:
            return self._closed_loop_step(starts)
        w = self._windows(starts)
        imu = augment(w["imu"], self.noise)
        out = self.model(imu, w["dt"], w["rot"][:, 0])
        if self.hparams.get("supervision") == "self":
            return self._self_supervised_loss(out, w, starts.shape[0])
        loss = increment_loss(out["omega"], w["dt"], w["rot"], w["valid"], self.loss_js,
                              self.hparams.huber_delta)
        if self.model.backbone is not None:  # the trust logits: separate network, own loss
            loss = loss + trust_loss(out["acc_trust_logit"], w["trust_label"][..., 0], w["valid"])
            if "mag_trust_logit" in out:
                loss = loss + trust_loss(out["mag_trust_logit"], w["trust_label"][..., 1], w["valid"])
        self.log("train/loss", loss, prog_bar=True, on_step=True, on_epoch=True,
                 batch_size=starts.shape[0], sync_dist=True)
        return loss

    def _self_supervised_loss(self, out: Dict[str, torch.Tensor], w: Dict[str, torch.Tensor], b: int):
        """No motion capture (``train.supervision=self``): the corrected rate is zero at rest
        (:func:`~tcn_ahrs.losses.rest_rate_loss`), the trust logits learn the sensors' own
        consistency (:func:`~tcn_ahrs.losses.self_labels`)."""
        label, valid = w["trust_label"], w["valid"]
        loss = rest_rate_loss(out["omega"], label[..., 2] > 0.5, self.hparams.huber_delta)
        if "acc_trust_logit" in out:
            loss = loss + trust_loss(out["acc_trust_logit"], label[..., 0], valid)
        if "mag_trust_logit" in out:
            loss = loss + trust_loss(out["mag_trust_logit"], label[..., 1], valid)
        self.log("train/loss", loss, prog_bar=True, on_step=True, on_epoch=True, batch_size=b, sync_dist=True)
        return loss

    def _windows(self, starts: torch.Tensor) -> Dict[str, torch.Tensor]:
        """The batch's training windows: at a random rate each when ``augment.rate_hz`` is set
        (:meth:`~tcn_ahrs.data.SequenceStore.gather_resampled`), then another sensor's errors
        (:func:`~tcn_ahrs.data.augment_sensor`)."""
        store, a = self._store("train_store"), self.augment
        window = self.trainer.datamodule.window
        if a.get("rate_hz"):
            w = store.gather_resampled(starts, window, a["rate_hz"], float(a.get("jitter") or 0.0))
        else:
            w = store.gather(starts, window)
        if a.get("rotate") or a.get("gyro_bias") or a.get("scale"):
            w = augment_sensor(w, bool(a.get("rotate")), float(a.get("gyro_bias") or 0.0), float(a.get("scale") or 0.0))
        return w

    def _closed_loop_step(self, starts: torch.Tensor):
        """Truncated backpropagation through the closed loop over chained chunks.

        B streams run through the training recordings; each training step advances every
        stream by one chunk of ``window`` samples from its carried (detached) filter state, so
        the filter is trained in the state it runs in at inference — including a gyro-bias state
        that has converged over earlier chunks — while gradients stay within one chunk. A stream
        restarts (at a new random window start, from ground truth, zero bias, a new random
        constant gyro offset ``noise.gyro_bias``) after ``stream_chunks`` chunks or at the end of
        its recording. The networks see ``receptive_field - 1`` samples of context before each
        chunk (the window starts leave that margin)."""
        store = self._store("train_store")
        L = int(self.trainer.datamodule.window)
        ctx = int(self.model.receptive_field) - 1
        starts = starts.to(self.device)
        b = starts.shape[0]
        st = self._stream
        if st is None or st["pos"].shape[0] != b:
            reset = torch.ones(b, dtype=torch.bool, device=self.device)
            st = {"pos": starts.clone(), "left": torch.zeros(b, dtype=torch.long, device=self.device),
                  "rot": torch.zeros(b, 3, 3, device=self.device), "bias": torch.zeros(b, 3, device=self.device),
                  "offset": torch.zeros(b, 3, device=self.device)}
        else:
            reset = (st["left"] <= 0) | (st["pos"] + L > store.recording_end(st["pos"]))
        if bool(reset.any()):
            st["pos"] = torch.where(reset, starts, st["pos"])
            st["left"] = torch.where(reset, torch.full_like(st["left"], int(self.hparams.stream_chunks)), st["left"])
            st["rot"] = torch.where(reset[:, None, None], store.tensors["rot"][st["pos"]], st["rot"])
            st["bias"] = torch.where(reset[:, None], torch.zeros_like(st["bias"]), st["bias"])
            off = torch.randn_like(st["offset"]) * float(self.noise.get("gyro_bias", 0.0))
            st["offset"] = torch.where(reset[:, None], off, st["offset"])
        w = store.gather(st["pos"] - ctx, L + ctx)
        imu = augment(w["imu"], self.noise)
        imu = torch.cat([imu[..., 0:3] + st["offset"][:, None], imu[..., 3:]], -1)
        out = self.model.filter_closed_loop(imu, w["dt"], st["rot"], st["bias"], context=ctx)
        valid = w["valid"][:, ctx:].clone()
        valid[:, 0] = False  # the initial state is given, not estimated
        loss = attitude_loss(out["rot"], w["rot"][:, ctx:], valid, float(self.hparams.attitude_delta))
        # carried on detached and re-orthonormalised (float32 round-off over many chunks)
        st["rot"] = so3.quat_to_matrix(so3.matrix_to_quat(out["rot"][:, -1].detach()))
        st["bias"] = out["gyro_bias"][:, -1].detach()
        st["pos"] = st["pos"] + (L - 1)
        st["left"] = st["left"] - 1
        self._stream = st
        self.log("train/loss", loss, prog_bar=True, on_step=True, on_epoch=True, batch_size=b, sync_dist=True)
        return loss

    def _closed_loop_validation(self):
        """All validation recordings in one padded closed-loop pass (the loop costs the same for
        B recordings as for one). Each starts at its first valid ground truth; padding has
        dt = 0 and is not scored. Logs the mean over recordings of AAE and of the loss."""
        store = self._store("val_store")
        seqs = []
        for i in range(len(store.lengths)):
            s = store.sequence(i)
            k0 = int(torch.argmax(s["valid"][0].to(torch.int8)))
            seqs.append({k: v[:, k0:] for k, v in s.items()})
        n = max(s["imu"].shape[1] for s in seqs)

        def pad(x, fill_last: bool):
            extra = n - x.shape[1]
            if extra == 0:
                return x
            tail = x[:, -1:].expand(-1, extra, *x.shape[2:]) if fill_last else torch.zeros_like(x[:, :1]).expand(-1, extra, *x.shape[2:])
            return torch.cat([x, tail], 1)

        imu = torch.cat([pad(s["imu"], True) for s in seqs])
        dt = torch.cat([pad(s["dt"], False) for s in seqs])
        rot_gt = torch.cat([pad(s["rot"], True) for s in seqs])
        valid = torch.cat([pad(s["valid"], False) for s in seqs])
        out = self.eval_model.filter_closed_loop(imu, dt, rot_gt[:, 0].double(), dtype=torch.float64)
        aaes, losses = [], []
        for i in range(len(seqs)):
            m = valid[i]
            aaes.append(_aae_deg(rot_gt[i, m], out["rot"][i, m]))
            losses.append(attitude_loss(out["rot"][i:i + 1], rot_gt[i:i + 1], valid[i:i + 1],
                                        float(self.hparams.attitude_delta)))
        self.log("val/loss", torch.stack(losses).mean().float(), prog_bar=True, batch_size=1)
        self.log("val/aae_deg", torch.stack(aaes).mean().float(), prog_bar=True, batch_size=1)

    def validation_step(self, batch, batch_idx):
        if self.model.closed is not None:
            if batch_idx == 0:
                self._closed_loop_validation()
            return
        i = int(batch[0])
        s = self._store("val_store").sequence(i)
        valid = s["valid"]
        k0 = int(torch.argmax(valid[0].to(torch.int8)))
        out = self.eval_model.run_sequence(s["imu"], s["dt"], s["rot"][:, k0], k0)
        loss = increment_loss(out["omega"], s["dt"], s["rot"], valid, self.loss_js, self.hparams.huber_delta)
        aae = _aae_deg(s["rot"][0, valid[0]], out["rot"][0, valid[0]])
        self.log("val/loss", loss, prog_bar=True, batch_size=1, sync_dist=True)
        self.log("val/aae_deg", aae.float(), prog_bar=True, batch_size=1, sync_dist=True)

    # -------------------------------------------------------------- optimiser
    def configure_optimizers(self):
        decay, no_decay = [], []
        for name, p in self.model.named_parameters():
            # Convolution kernels and the calibration matrices' deviation from I decay; biases,
            # BatchNorm and the ECF gains do not.
            (decay if (p.ndim >= 2) else no_decay).append(p)
        opt = torch.optim.AdamW([{"params": decay, "weight_decay": self.hparams.weight_decay},
                                 {"params": no_decay, "weight_decay": 0.0}], lr=self.hparams.lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, int(self.hparams.epochs)))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "epoch"}}

    def on_save_checkpoint(self, checkpoint: Dict[str, Any]) -> None:
        cfg = dict(self.hparams.model_cfg)
        cfg["axes"] = self.model.axes
        checkpoint["tcn_ahrs"] = layout_meta(cfg, self.model.axes, self.hparams.data_name,
                                             self.hparams.get("rate_hz"), self.augment.get("rate_hz"))


# ====================================================================== helpers
def _aae_deg(rot_gt: torch.Tensor, rot_est: torch.Tensor) -> torch.Tensor:
    """AAE (Eq. 29) of (M, 3, 3) estimates against ground truth on valid samples, degrees, float64.
    Validation starts the estimate at ground truth, so no alignment is needed (the same
    definition as :func:`tcn_ahrs.metrics.aae`)."""
    err = so3.log(rot_gt.double().transpose(-1, -2) @ rot_est.double())
    return torch.sqrt((err ** 2).sum(-1).mean()) * (180.0 / math.pi)


def choose_knobs_into_checkpoint(ckpt_path: str, val_seqs, run_dir: Path,
                                 grid: Optional[Mapping[str, Any]] = None, rule: str = "both") -> Dict[str, float]:
    """Choose the residual model's inference knobs (:func:`tcn_ahrs.tuning.select_residual_knobs`,
    over ``grid``, default its own) on ``val_seqs`` and write them into the checkpoint's model
    config (atomically; the checkpoint then IS the selected model); the table goes to
    ``run_dir/knobs.json``."""
    import json

    from .checkpoint import atomic_save, model_from_checkpoint
    from .tuning import select_residual_knobs

    model = model_from_checkpoint(ckpt_path)
    chosen, table = select_residual_knobs(model, val_seqs, grid=grid, rule=rule)
    ck = load_checkpoint(ckpt_path)
    for cfg in (ck["tcn_ahrs"]["model"], (ck.get("hyper_parameters") or {}).get("model_cfg")):
        if cfg is not None:
            cfg["residual"] = {**dict(cfg.get("residual") or {}), **chosen}
    atomic_save(ck, ckpt_path)
    (run_dir / "knobs.json").write_text(json.dumps({"chosen": chosen, "on": [s.name for s in val_seqs],
                                                     "table": table}, indent=1))
    ref = next(r for r in table if r["reference"])
    row = next(r for r in table if r["knobs"] == chosen)
    print(f"inference knobs chosen on the {len(val_seqs)} validation recordings: {chosen} (mean AAE "
          f"{row['aae_deg']:.2f} / inclination {row['inclination_deg']:.2f} deg; the tuned backbone "
          f"alone {ref['aae_deg']:.2f} / {ref['inclination_deg']:.2f}); table in {run_dir / 'knobs.json'}")
    return chosen


def rest_gyro_mean(model: LearnedAHRS, store) -> Optional[torch.Tensor]:
    """Mean raw gyro reading (3,) over the samples the model's rest detector flags in the
    training recordings (None when none is at rest)."""
    total, count = torch.zeros(3, dtype=torch.float64), 0
    for i in range(len(store.lengths)):
        s = store.sequence(i)
        rest = model.closed.rest(s["imu"][..., 0:3], s["imu"][..., 3:6], s["dt"])[0] > 0.5
        if bool(rest.any()):
            total += s["imu"][0, rest, 0:3].double().sum(0)
            count += int(rest.sum())
    return None if count == 0 else (total / count).float()


def _plain(cfg) -> Any:
    return OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else cfg


# (type, lower bound, lower bound included, upper bound exclusive) of the numeric train.* keys
TRAIN_VALUES = {"window": (int, 2, True, None), "stride": (int, 1, True, None),
                "batch_size": (int, 1, True, None), "epochs": (int, 1, True, None),
                "lr": (float, 0.0, False, None), "weight_decay": (float, 0.0, True, None),
                "huber_delta": (float, 0.0, False, None), "stream_chunks": (int, 1, True, None),
                "attitude_delta": (float, 0.0, False, None), "ema_decay": (float, 0.0, True, 1.0)}


def check_train_values(train: Mapping) -> None:
    """Every numeric ``train.*`` value in its range, and the noise levels >= 0 (key named)."""
    for k, (kind, low, low_ok, high) in TRAIN_VALUES.items():
        if train.get(k) is not None:
            check_number(train.get(k), f"train.{k}", kind, low, low_ok, high)
    for k, v in (train.get("noise") or {}).items():
        check_number(v, f"train.noise.{k}", float, 0.0)
    aug = train.get("augment") or {}
    check_keys(aug, AUGMENT_KEYS, "train.augment")
    for k in ("jitter", "gyro_bias", "scale"):
        if aug.get(k) is not None:
            check_number(aug.get(k), f"train.augment.{k}", float, 0.0, True, 0.49 if k == "jitter" else None)
    span = aug.get("rate_hz")
    if span is not None:
        span = list(span)
        if len(span) != 2 or not (0.0 < float(span[0]) <= float(span[1])):
            raise ValueError(f"train.augment.rate_hz: expected [low, high] Hz with 0 < low <= high, got {span}")
    if train.get("monitor") is not None and str(train.get("monitor")) not in MONITORS:
        import difflib

        near = difflib.get_close_matches(str(train.get("monitor")), MONITORS, n=1)
        raise ValueError(f"train.monitor: expected one of {list(MONITORS)} (the validation metrics logged), got "
                         f"{train.get('monitor')!r}" + (f" (did you mean {near[0]!r}?)" if near else ""))


MONITORS = ("val/loss", "val/aae_deg")


def model_axes(cfg) -> int:
    """Model input axes: ``model.axes`` (default: ``data.axes``); a 9-axis model on 6-axis data is an error."""
    data_axes = int(cfg.data.get("axes", 9))
    axes = cfg.model.get("axes")
    axes = data_axes if axes is None else int(axes)
    if axes == 9 and data_axes == 6:
        raise ValueError(f"model '{cfg.model.get('variant')}' needs 9 axes but data '{cfg.data.name}' is "
                         "6-axis (data.axes=6): choose a 6-axis model (model=ahrs6) or data.axes=9")
    return axes


def find_resume_checkpoint(run_dir: Path) -> Path:
    """``run_dir/checkpoints/last.ckpt``, else the newest ``last.ckpt`` among sibling run dirs."""
    own = run_dir / "checkpoints" / "last.ckpt"
    if own.is_file():
        return own
    cands = sorted(run_dir.parent.glob("*/checkpoints/last.ckpt"), key=lambda p: p.stat().st_mtime)
    cands = [c for c in cands if c.parent.parent != run_dir]
    if not cands:
        raise CheckpointError(f"resume=true: no last.ckpt in {run_dir / 'checkpoints'} nor in any run under "
                              f"{run_dir.parent}; pass ckpt_path=PATH")
    return cands[-1]


# keys a resumed run may set without changing the experiment
RESUME_KEYS = ("resume", "ckpt_path", "run_dir", "threads")


def command_line_overrides() -> Optional[List[str]]:
    """The ``key=value`` overrides of the running Hydra job (None outside one)."""
    try:
        from hydra.core.hydra_config import HydraConfig

        return list(HydraConfig.get().overrides.task)
    except Exception:  # noqa: BLE001 - no Hydra job (library call, compose API)
        return None


def resume_config(cfg: DictConfig, run_dir: Path, overrides: Optional[List[str]]) -> DictConfig:
    """The configuration a resumed run continues with: the run's own ``config_resolved.yaml``
    (its overrides, schedule, time cap), with only what this command sets on top — ``overrides``
    (``key=value`` strings; None: every key of ``cfg`` counts as set, as for a library call).
    Each setting that changes the saved run is named; ``resume``/``run_dir``/``ckpt_path``/
    ``threads`` are this command's own."""
    saved_path = run_dir / "config_resolved.yaml"
    if not saved_path.is_file():
        print(f"WARNING: resume: {saved_path} is missing: the run continues with this command's configuration")
        return cfg
    saved = OmegaConf.load(saved_path)
    if overrides is None:
        from .cli import leaf_keys

        keys = [k for k in leaf_keys(cfg) if k.split(".")[0] not in RESUME_KEYS]
    else:
        keys = [o.split("=", 1)[0].lstrip("+~") for o in overrides if "=" in o]
        keys = [k for k in keys if k.split(".")[0] not in RESUME_KEYS and k.split(".")[0] != "hydra"]
    out = OmegaConf.create(OmegaConf.to_container(saved, resolve=True))
    changed = []
    for k in keys:
        new, old = OmegaConf.select(cfg, k), OmegaConf.select(saved, k)
        if isinstance(new, DictConfig) or isinstance(old, DictConfig):  # a group (data=..., model=...)
            new, old = _plain(new), _plain(old)
        if new != old:
            changed.append(f"{k}: {old!r} -> {new!r}")
        OmegaConf.update(out, k, new if not isinstance(new, (dict, list)) else OmegaConf.create(new), merge=False,
                         force_add=True)
    for k in RESUME_KEYS:
        if k in cfg:
            OmegaConf.update(out, k, cfg.get(k), force_add=True)
    if changed:
        print("resume: this command changes the saved run's configuration: " + "; ".join(changed)
              + f" (everything else as saved in {saved_path})")
    return out


def trim_metrics(metrics_csv: Path, last_epoch: int, global_step: int) -> int:
    """Drop the rows of epochs after ``last_epoch`` (the ones a kill interrupted, logged again
    by the resumed run) from a Lightning ``metrics.csv``: rows of a later epoch, and rows without
    an epoch (the learning-rate monitor's) at or after ``global_step``, the checkpoint's step.
    Returns how many went."""
    import csv

    if not metrics_csv.is_file():
        return 0
    with open(metrics_csv, newline="") as fh:
        reader = csv.DictReader(fh)
        fields, rows = reader.fieldnames, list(reader)
    def later(r) -> bool:
        if r.get("epoch") not in (None, ""):
            return int(float(r["epoch"])) > last_epoch
        return r.get("step") not in (None, "") and int(float(r["step"])) >= global_step

    keep = [r for r in rows if not later(r)]
    if len(keep) != len(rows):
        tmp = metrics_csv.with_name(f".{metrics_csv.name}.tmp")
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=fields)
            w.writeheader()
            w.writerows(keep)
        os.replace(tmp, metrics_csv)
    return len(rows) - len(keep)


def _appending_csv_logger(run_dir: Path):
    """Lightning's CSVLogger, except that an existing ``logs/metrics.csv`` is continued, not
    deleted: a resumed run keeps the history of the epochs before the kill."""
    import csv

    from pytorch_lightning.loggers import CSVLogger
    from pytorch_lightning.loggers.csv_logs import ExperimentWriter

    class _Writer(ExperimentWriter):
        def _check_log_dir_exists(self) -> None:
            if self._fs.isfile(self.metrics_file_path):
                with self._fs.open(self.metrics_file_path, "r", newline="") as fh:
                    self.metrics_keys = list(next(csv.reader(fh), []))

    class _Logger(CSVLogger):
        @property
        def experiment(self):
            if self._experiment is None:
                self._fs.makedirs(self.root_dir, exist_ok=True)
                self._experiment = _Writer(log_dir=self.log_dir)
            return self._experiment

    return _Logger(str(run_dir), name="logs", version="")


class RandomState(pl.Callback):
    """Keeps the random generators' states (torch, numpy, Python) in every checkpoint and
    restores them on resume, so that a resumed run draws the same shuffles, noise and dropout
    as the run that was not interrupted (Lightning restores weights, optimiser and loops only)."""

    def on_save_checkpoint(self, trainer, pl_module, checkpoint) -> None:
        import random

        name, keys, pos, has_gauss, cached = np.random.get_state()
        # plain types and tensors only: checkpoints are read with torch.load(weights_only=True)
        checkpoint["rng_states"] = {"torch": torch.get_rng_state(), "python": random.getstate(),
                                    "numpy": [name, torch.from_numpy(keys.astype(np.int64)), int(pos), int(has_gauss),
                                              float(cached)]}

    def on_load_checkpoint(self, trainer, pl_module, checkpoint) -> None:
        import random

        st = checkpoint.get("rng_states")
        if st is None:
            return
        torch.set_rng_state(st["torch"])
        random.setstate(st["python"])
        name, keys, pos, has_gauss, cached = st["numpy"]
        np.random.set_state((name, keys.numpy().astype(np.uint32), pos, has_gauss, cached))


def build_trainer(cfg, run_dir: Path, monitor: str, callbacks_extra=()) -> pl.Trainer:
    from pytorch_lightning.callbacks import LearningRateMonitor, ModelCheckpoint

    ckpt_cb = ModelCheckpoint(dirpath=str(run_dir / "checkpoints"), filename="best", monitor=monitor,
                              mode="min", save_top_k=1, save_last=False, auto_insert_metric_name=False,
                              enable_version_counter=False)
    # last.ckpt every epoch. (Lightning 2.6's save_last=True only refreshes last.ckpt when the
    # top-k checkpoint was saved in the same step, which leaves it stale after a non-improving
    # epoch; a monitor-less top-1 checkpoint named "last" is rewritten every epoch.)
    last_cb = ModelCheckpoint(dirpath=str(run_dir / "checkpoints"), filename="last", monitor=None,
                              save_top_k=1, every_n_epochs=1, enable_version_counter=False)
    loggers = [_appending_csv_logger(run_dir)]
    try:
        from pytorch_lightning.loggers import TensorBoardLogger
        import tensorboard  # noqa: F401
        loggers.append(TensorBoardLogger(str(run_dir), name="tb", version="", default_hp_metric=False))
    except Exception:  # noqa: BLE001
        pass
    tr = _plain(cfg.trainer)
    return pl.Trainer(max_epochs=int(cfg.train.epochs), max_time=cfg.train.get("max_time"),
                      callbacks=[ckpt_cb, last_cb, LearningRateMonitor("epoch"), RandomState(), *callbacks_extra],
                      logger=loggers, plugins=[AtomicCheckpointIO()],
                      default_root_dir=str(run_dir),
                      limit_train_batches=cfg.train.get("limit_train_batches") or 1.0,
                      **tr)


def _run_dir(cfg) -> Path:
    return output_dir(cfg.get("run_dir"), Path("runs"))


# ================================================================== entry points
def train_main(cfg: DictConfig, train_seqs=None, val_seqs=None, test_seqs=None,
               overrides: Optional[List[str]] = None, callbacks=()) -> Dict[str, Any]:
    """Train, then evaluate on held-out data. Returns {"run_dir", "best", "last", "results"}.

    ``train_seqs``/``val_seqs``/``test_seqs`` replace the data config's splits (tests).
    ``resume=true`` continues the run in ``run_dir`` with its saved configuration
    (:func:`resume_config`; ``overrides``: this command's ``key=value`` settings, by default the
    Hydra job's). ``callbacks``: more Lightning callbacks (tests)."""
    if cfg.get("resume") and not cfg.get("ckpt_path"):
        cfg = resume_config(cfg, _run_dir(cfg), overrides if overrides is not None else command_line_overrides())
    check_keys(cfg.train, TRAIN_KEYS, "train")
    check_train_values(cfg.train)
    from .estimators.registry import check_method_names

    check_method_names((cfg.get("eval") or {}).get("baselines"))  # a typo fails now, not after training
    set_threads(cfg.get("threads"))
    pl.seed_everything(int(cfg.seed), workers=True)
    run_dir = _run_dir(cfg)
    run_dir.mkdir(parents=True, exist_ok=True)
    axes = model_axes(cfg)
    model_cfg = _plain(cfg.model)
    model_cfg["axes"] = axes
    init_model = None
    if cfg.get("init"):
        # fine-tuning: the architecture, knobs and weights are the checkpoint's; the model group is not used
        from .checkpoint import model_from_checkpoint

        shipped = Path(__file__).resolve().parents[1] / str(cfg.init)
        if not Path(str(cfg.init)).is_file() and shipped.is_file():  # checkpoints/... from anywhere
            with open_dict(cfg):
                cfg.init = str(shipped)
        init_model = model_from_checkpoint(str(cfg.init))
        check_layout(load_checkpoint(str(cfg.init)), axes, str(cfg.init))
        model_cfg = dict(checkpoint_meta(load_checkpoint(str(cfg.init)), str(cfg.init))["model"])
        model_cfg["axes"] = axes
        if cfg.train.get("init_gyro_bias", True) and model_cfg.get("residual") is not None:
            # the bias state starts at this device's estimated bias (general models start at zero)
            model_cfg["residual"] = {**dict(model_cfg["residual"]), "bias_prior": 1.0}
        print(f"fine-tuning from {cfg.init} ({model_cfg.get('variant')}, {init_model.num_parameters():,} parameters)")
    probe = LearnedAHRS.from_config(model_cfg)  # fail early on a bad model config
    # the closed loop trains on chained chunks whose networks see receptive_field - 1 samples before
    margin = probe.receptive_field - 1 if probe.closed is not None else 0

    if cfg.train.get("all_recordings") and train_seqs is None:
        # the released model: every training recording, whole, with the fixed schedule; nothing
        # held out, so nothing is selected (the last epoch ships)
        from .datasets import load_split

        train_seqs, val_seqs = load_split(cfg.data, "trainval"), []
    supervision = str(cfg.train.get("supervision") or "gt")
    if supervision == "self" and (probe.backbone is None or init_model is None):
        raise ValueError("train.supervision=self: fine-tunes a residual model without ground truth; set "
                         "init=<checkpoint of a residual model> (e.g. checkpoints/general9.ckpt)")
    dm = AHRSDataModule(cfg.data, axes, cfg.train.window, cfg.train.stride, cfg.train.batch_size,
                        train_seqs, val_seqs, margin=margin, balance=bool(cfg.train.get("balance")),
                        supervision=supervision)
    dm.prepare()
    if supervision == "self":
        dm.val_seqs, dm.val_store = [], None  # nothing to validate against without ground truth
    if probe.backbone is not None and cfg.train.get("tune_backbone", True) and supervision == "gt":
        from .tuning import tune_backbone

        # the backbone's knobs, chosen on the training recordings before any network trains
        # (never on the held-out ones); stored in the model config, so the checkpoint keeps them
        chosen, table = tune_backbone(dm.train_seqs, axes,
                                      gyro_bias_std=float((cfg.train.get("augment") or {}).get("gyro_bias") or 0.0),
                                      criterion=str(cfg.train.get("tune_criterion") or "aae"))
        res = dict(model_cfg.get("residual") or {})
        res["backbone"] = {**dict(res.get("backbone") or {}), **chosen}
        model_cfg["residual"] = res
        print(f"backbone parameters chosen on the {len(dm.train_seqs)} training recordings: {chosen} "
              f"(score {table[0]['score']:.2f}, {cfg.train.get('tune_criterion') or 'aae'}; VQF's defaults "
              f"{next(r['score'] for r in table if r['params'].get('tau_acc') == 3.0 and r['params'].get('motion_bias') == 1.0 and r['params'].get('bias_clip') == 2.0 and r['params'].get('tau_mag', 9.0) == 9.0):.2f})")
    module = AHRSModule(model_cfg, axes, lr=float(cfg.train.lr), weight_decay=float(cfg.train.weight_decay),
                        epochs=int(cfg.train.epochs), window=dm.window, loss_js=list(cfg.train.loss_js),
                        huber_delta=float(cfg.train.huber_delta), noise=_plain(cfg.train.noise),
                        stream_chunks=int(cfg.train.get("stream_chunks") or 8),
                        attitude_delta=float(cfg.train.get("attitude_delta") or 0.01),
                        ema_decay=float(cfg.train.get("ema_decay") or 0.0),
                        augment=_plain(cfg.train.get("augment") or {}), supervision=supervision,
                        data_name=str(cfg.data.name),
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
    if module.model.closed is not None:
        module.model.closed.set_rate(module.hparams.rate_hz)
        bias = rest_gyro_mean(module.model, dm.train_store) if cfg.train.get("init_gyro_bias", True) else None
        if bias is not None:
            # the static gyro bias, measured where the training recordings are at rest, as the
            # gyro error term's starting point: a TCN output that must grow from zero to an
            # uncalibrated bias (EuRoC: 0.077 rad/s) at lr 1e-3 takes thousands of steps
            module.model.calibration.set_gyro_bias(bias)
            print(f"gyro error term starts at the training recordings' mean gyro at rest: "
                  f"{[round(float(v), 5) for v in bias]} rad/s")
    if module.model.backbone is not None and cfg.train.get("init_gyro_bias", True):
        from .tuning import backbone_bias

        b0 = backbone_bias(dm.train_seqs, axes, (model_cfg.get("residual") or {}).get("backbone") or {})
        module.model.backbone.bias_init.copy_(torch.as_tensor(b0))
        print(f"backbone bias state starts at the training recordings' estimated bias {np.round(b0, 5).tolist()} rad/s")
    module.reset_ema()
    monitor = str(cfg.train.monitor) if dm.val_store is not None else "train/loss_epoch"

    ckpt_path = cfg.get("ckpt_path")
    if cfg.get("resume") and not ckpt_path:
        ckpt_path = str(find_resume_checkpoint(run_dir))
    if ckpt_path:
        ck = load_checkpoint(ckpt_path)
        check_layout(ck, axes, ckpt_path)
        print(f"resuming from {ckpt_path} (epoch {ck.get('epoch')})")
        if cfg.get("resume") and ck.get("epoch") is not None:
            # the interrupted epoch's rows are logged again by the resumed run: drop them
            dropped = trim_metrics(run_dir / "logs" / "metrics.csv", int(ck["epoch"]), int(ck.get("global_step") or 0))
            if dropped:
                print(f"resume: dropped {dropped} metrics rows of the interrupted epoch {int(ck['epoch']) + 1}")

    trainer = build_trainer(cfg, run_dir, monitor, callbacks)
    if trainer.is_global_zero:
        # the run's configuration as started; a resumed run keeps it (and notes its own)
        name = "config_resumed.yaml" if (cfg.get("resume") and (run_dir / "config_resolved.yaml").is_file()) \
            else "config_resolved.yaml"
        (run_dir / name).write_text(OmegaConf.to_yaml(cfg, resolve=True))
        n = module.model.num_parameters()
        print(f"model {model_cfg.get('variant')} ({axes}-axis): {n:,} trainable parameters, "
              f"receptive field {module.model.receptive_field} samples; "
              f"{len(dm.starts)} training windows of {dm.window} samples; run dir {run_dir}")
    t0 = time.perf_counter()
    trainer.fit(module, datamodule=dm, ckpt_path=ckpt_path)
    fit_s = time.perf_counter() - t0
    ckpt_cb = trainer.checkpoint_callback
    best = ckpt_cb.best_model_path or str(run_dir / "checkpoints" / "last.ckpt")
    last = str(run_dir / "checkpoints" / "last.ckpt")
    if cfg.train.get("all_recordings"):
        best = last  # nothing was held out: nothing to select on, the fixed schedule's end ships
    result = {"run_dir": str(run_dir), "best": best, "last": last, "fit_s": fit_s, "results": None}
    if not trainer.is_global_zero:
        return result
    if module.model.backbone is not None:
        # the residual model: the fixed schedule's last epoch ships, with its inference knobs
        # chosen on the held-out (validation) recordings, never on the reported ones
        best = last
        result["best"] = last
        if cfg.train.get("select_knobs", True) and dm.val_seqs:
            result["knobs"] = choose_knobs_into_checkpoint(last, dm.val_seqs, run_dir,
                                                           _plain(cfg.train.get("knob_grid")) or None,
                                                           str(cfg.train.get("knob_rule") or "both"))
    print(f"training took {fit_s:.1f} s; best checkpoint {best} ({monitor} = {ckpt_cb.best_model_score})")
    done_epochs = int(trainer.current_epoch)
    if cfg.train.get("max_time") and done_epochs < int(cfg.train.epochs):
        result["stopped_by_time_cap"] = True
        print(f"WARNING: the time cap train.max_time={cfg.train.max_time} stopped training after "
              f"{done_epochs} of {int(cfg.train.epochs)} epochs: the model is under-trained. Real data: "
              "use its schedule (experiment=<name>_cl, no cap) or set train.max_time=null", file=sys.stderr)

    ev = cfg.get("eval") or {}
    if ev.get("enabled", True):
        from .evaluate import evaluate, print_table
        from .estimators.learned import LearnedEstimator

        if test_seqs is None:
            from .datasets import load_split
            test_seqs = load_split(cfg.data, str(ev.get("split", "test")))
        test_seqs = [s for s in test_seqs if s.has_gt]
        if not test_seqs:
            warnings.warn(f"no held-out recordings with ground truth in split {ev.get('split', 'test')!r}; "
                          "skipping the evaluation")
            return result
        from .estimators.registry import baseline_estimators

        learned = LearnedEstimator(best, name=str(ev.get("name", "Learned AHRS")))
        estimators = [learned] + baseline_estimators(["raw"] + list(ev.get("baselines", [])), axes)
        res = evaluate(estimators, test_seqs, out_dir=run_dir / "eval", axes=axes,
                       dataset=str(cfg.data.name), plots=bool(ev.get("plots", True)),
                       trajectories=bool(ev.get("trajectories", True)))
        print(f"\nHeld-out evaluation ({cfg.data.name}, split {ev.get('split', 'test')}, "
              f"{len(test_seqs)} recordings; results in {run_dir / 'eval'}):")
        print_table(res)
        result["results"] = res
    return result
