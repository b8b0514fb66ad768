"""Trainer assembly: the callbacks and loggers of the config groups ``callbacks`` and ``logger``
(conf/callbacks/*.yaml, conf/logger/*.yaml: ``_target_`` entries instantiated by
:func:`hydra.utils.instantiate`), the resume search and the resumed run's configuration.

The groups' YAML may write ``{run_dir}`` and ``{monitor}`` in string values (not ``${...}``:
they are this run's, known only here): :func:`build_trainer` fills them in before instantiating.
"""
from __future__ import annotations

import csv
import os
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
import pytorch_lightning as pl
import torch
from omegaconf import DictConfig, OmegaConf
from pytorch_lightning.loggers import CSVLogger
from pytorch_lightning.loggers.csv_logs import ExperimentWriter

from ..checkpoint import AtomicCheckpointIO, CheckpointError
from ..app import output_dir
from ..config import conf_path, plain

__all__ = ["build_trainer", "build_callbacks", "build_loggers", "check_groups", "RandomState", "AppendingCSVLogger",
           "find_resume_checkpoint", "resume_config", "trim_metrics", "command_line_overrides", "RESUME_KEYS",
           "run_dir_of"]




class _AppendingWriter(ExperimentWriter):
    def _check_log_dir_exists(self) -> None:
        if self._fs.isfile(self.metrics_file_path):
            with self._fs.open(self.metrics_file_path, "r", newline="") as fh:
                self.metrics_keys = list(next(csv.reader(fh), []))


class AppendingCSVLogger(CSVLogger):
    """Lightning's CSVLogger, except that an existing ``<save_dir>/<name>/metrics.csv`` is
    continued, not deleted: a resumed run keeps the history of the epochs before the kill."""

    @property
    def experiment(self):
        if self._experiment is None:
            self._fs.makedirs(self.root_dir, exist_ok=True)
            self._experiment = _AppendingWriter(log_dir=self.log_dir)
        return self._experiment


def optional_tensorboard(**kwargs):
    """Lightning's TensorBoardLogger when ``tensorboard`` is installed, else None (no logger)."""
    try:
        from pytorch_lightning.loggers import TensorBoardLogger
        import tensorboard  # noqa: F401

        return TensorBoardLogger(**kwargs)
    except Exception:  # noqa: BLE001
        return None


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



def _group(cfg, name: str) -> Dict[str, Any]:
    """The config group ``name`` of a run (plain dict of ``_target_`` entries); a configuration
    saved before the group existed (a resumed older run) gets the group's default option."""
    node = cfg.get(name) if hasattr(cfg, "get") else None
    if node is None:
        node = OmegaConf.load(conf_path(name, "default.yaml"))
    return dict(plain(node) or {})


def _fill(value, runtime: Dict[str, str]):
    """``{run_dir}``/``{monitor}`` in the string values of an entry -> this run's."""
    if isinstance(value, str):
        for k, v in runtime.items():
            value = value.replace("{" + k + "}", v)
        return value
    if isinstance(value, dict):
        return {k: _fill(v, runtime) for k, v in value.items()}
    if isinstance(value, list):
        return [_fill(v, runtime) for v in value]
    return value


def _instantiate_all(entries: Dict[str, Any], runtime: Dict[str, str], what: str) -> list:
    from hydra.utils import instantiate

    out = []
    for key, spec in entries.items():
        if spec is None:  # an entry switched off (callbacks.lr_monitor=null)
            continue
        if not isinstance(spec, dict) or "_target_" not in spec:
            raise ValueError(f"{what}.{key}: expected a mapping with a _target_ (a class to instantiate), got {spec!r}")
        try:
            obj = instantiate(_fill(spec, runtime))
        except Exception as e:  # noqa: BLE001 - Hydra wraps the target's error; a config error here
            raise ValueError(f"{what}.{key}: cannot instantiate {spec['_target_']}: "
                             f"{str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__}") from e
        if obj is not None:
            out.append(obj)
    return out


def check_groups(cfg) -> None:
    """The ``callbacks``/``logger`` entries before any work: each a mapping whose ``_target_``
    imports and takes the entry's arguments (a misspelt one is a ``ValueError`` naming it)."""
    import importlib
    import inspect

    for what in ("callbacks", "logger"):
        for key, spec in _group(cfg, what).items():
            if spec is None:
                continue
            if not isinstance(spec, dict) or "_target_" not in spec:
                raise ValueError(f"{what}.{key}: expected a mapping with a _target_ (a class to instantiate), "
                                 f"got {spec!r}")
            mod, _, name = str(spec["_target_"]).rpartition(".")
            try:
                target = getattr(importlib.import_module(mod), name)
            except (ImportError, AttributeError, ValueError) as e:
                raise ValueError(f"{what}.{key}: _target_ {spec['_target_']!r} does not import ({e})") from None
            params = inspect.signature(target).parameters
            if any(p.kind is p.VAR_KEYWORD for p in params.values()):
                continue
            bad = sorted(k for k in spec if not k.startswith("_") and k not in params)
            if bad:
                raise ValueError(f"{what}.{key}: {spec['_target_']} takes no argument(s) {bad}; expected a subset of "
                                 f"{sorted(k for k in params if k != 'self')}")


def build_callbacks(cfg, run_dir: Path, monitor: str) -> list:
    """The ``callbacks`` group's entries, in their order (the first ModelCheckpoint is the one
    ``trainer.checkpoint_callback`` names: the best-validation checkpoint)."""
    return _instantiate_all(_group(cfg, "callbacks"), {"run_dir": str(run_dir), "monitor": str(monitor)}, "callbacks")


def build_loggers(cfg, run_dir: Path) -> list:
    """The ``logger`` group's entries (an entry instantiating to None is left out)."""
    return _instantiate_all(_group(cfg, "logger"), {"run_dir": str(run_dir)}, "logger")


def build_trainer(cfg, run_dir: Path, monitor: str, callbacks_extra=()) -> pl.Trainer:
    """The Lightning Trainer of a run: ``trainer`` group's arguments, the ``callbacks`` and
    ``logger`` groups, atomic checkpoint writes, the schedule and time cap of ``train``."""
    tr = plain(cfg.trainer)
    return pl.Trainer(max_epochs=int(cfg.train.epochs), max_time=cfg.train.get("max_time"),
                      callbacks=[*build_callbacks(cfg, run_dir, monitor), *callbacks_extra],
                      logger=build_loggers(cfg, run_dir), plugins=[AtomicCheckpointIO()],
                      default_root_dir=str(run_dir),
                      limit_train_batches=cfg.train.get("limit_train_batches") or 1.0,
                      **tr)


def run_dir_of(cfg) -> Path:
    """``run_dir=``, else Hydra's run directory (else runs/<date_time>)."""
    return output_dir(cfg.get("run_dir"), Path("runs"))


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
        from ..app import leaf_keys

        keys = [k for k in leaf_keys(cfg) if k.split(".")[0] not in RESUME_KEYS]
    else:
        keys = [o.split("=", 1)[0].lstrip("+~") for o in overrides if "=" in o]
        keys = [k for k in keys if k.split(".")[0] not in RESUME_KEYS and k.split(".")[0] != "hydra"]
    out = OmegaConf.create(OmegaConf.to_container(saved, resolve=True))
    changed = []
    for k in keys:
        new, old = OmegaConf.select(cfg, k), OmegaConf.select(saved, k)
        if isinstance(new, DictConfig) or isinstance(old, DictConfig):  # a group (data=..., model=...)
            new, old = plain(new), plain(old)
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
