"""Speed benchmark: GPU/CPU training throughput, batch inference, streaming latency, filters.

``python scripts/benchmark.py speed [device=cpu|cuda] [quick=true] [out=DIR] [speed.KEY=VALUE ...]``
(or, without the dispatcher, ``python -m tcn_ahrs.bench_speed [same arguments]``).

Sections (each one table, with ratios against the thing it should be compared with):

* ``train``     — full training step of the 9-axis model (TCN calibration + open-loop ECF +
  increment loss, forward + backward + AdamW step, as :class:`tcn_ahrs.train.AHRSModule`)
  on the BROAD training shape (batch 16 x 3000 samples, data kept on the device), in IMU
  samples/s; wall time of one epoch and of the paper's 1800 epochs on the BROAD training split
  (exact window count from ``load_split`` when the data are there, else a constant; the
  result says which). Variants: CPU ``eager`` (project default: float32 network, float64
  loss products) / ``loss_fp32`` / ``compile``; CUDA ``fp32`` / ``tf32`` / ``bf16`` /
  ``compile`` / ``cuda_graphs``. ``compile`` runs in a subprocess with a timeout.
* ``inference`` — one minute of 100 Hz 9-axis data (6000 samples) through the eager model
  (``LearnedAHRS.run_sequence``, what :class:`LearnedEstimator` runs) and the exported
  TorchScript batch module (:func:`tcn_ahrs.export.export_batch`), on 1 CPU thread (and the
  GPU for device=cuda); median of repeats after warm-up. Goal <= 15 ms on one CPU thread.
* ``streaming`` — per-sample latency (median, p99) of the exported streaming module's
  ``step`` on 1 CPU thread, its in-TorchScript ``run`` loop, and RIANN's ``predict_step``.
  Goal >= 25 k samples/s and faster than RIANN's step mode.
* ``filters``   — samples/s of the project's batched ECF / Mahony / ES-EKF on one recording
  and on ``batch`` parameter sets at once (aggregate), next to VQF and imufusion on the same
  simulated recording. Goal: batched aggregate >= VQF's single-recording rate.

Timings are wall-clock (``time.perf_counter``; CUDA synchronised), so on a shared machine
they are noisy: the result records the load average before and after.
"""
from __future__ import annotations

import copy
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, Optional

import numpy as np
import torch
from torch import Tensor

from . import so3

# ----------------------------------------------------------------------------- config
DEFAULTS: Dict[str, Any] = {
    "sections": ["train", "inference", "streaming", "filters"],
    "seed": 0,
    "train": {
        "axes": 9,
        "window": 3000,            # BROAD training window (conf/experiment/broad9.yaml)
        "batch_size": 16,
        "stride": 100,             # window-start spacing; epoch = all starts (conf/train.yaml)
        "epochs": 1800,            # the paper's schedule
        "rate": 285.71,            # BROAD sampling rate, Hz (synthetic data)
        "variants_cpu": ["eager", "loss_fp32", "compile"],
        "variants_cuda": ["fp32", "tf32", "bf16", "compile", "cuda_graphs"],
        "warmup": 1,               # untimed steps per variant (compile: + its compile call)
        "steps": 2,                # timed steps per variant (at least 1) ...
        "max_seconds": 25.0,       # ... unless this many seconds of timed steps passed
        "compile_timeout_s": 240,  # hard bound on the compile subprocess
        "threads": None,           # torch threads (None: torch's default = all cores)
        "data_config": "conf/data/broad.yaml",  # for the exact epoch size; None: constant
        "split_samples": 601_181,  # fallback: 16 trials x 70 % x ~190 s x 285.7 Hz
        "split_recordings": 16,
    },
    "inference": {"samples": 6000, "rate": 100.0, "warmup": 5, "repeats": 20, "threads": 1,
                  "goal_ms": 15.0},
    "streaming": {"axes": [9, 6], "samples": 3000, "warmup": 300, "rate": 100.0, "threads": 1,
                  "run_samples": 3000, "riann": True, "goal_samples_per_s": 25_000.0},
    "filters": {"samples": 6000, "rate": 100.0, "batches": [1, 64], "repeats": 1, "threads": 1,
                "filters": ["ecf", "mahony", "eskf"], "peers": ["vqf", "imufusion"]},
}

QUICK: Dict[str, Any] = {
    "train": {"window": 256, "batch_size": 2, "variants_cpu": ["eager", "loss_fp32"],
              "variants_cuda": ["fp32", "bf16"], "warmup": 1, "steps": 1, "data_config": None},
    "inference": {"samples": 600, "warmup": 1, "repeats": 2},
    "streaming": {"axes": [9], "samples": 100, "warmup": 10, "run_samples": 100},
    "filters": {"samples": 200, "batches": [1, 4]},
}

TOP_LEVEL = ("device", "out", "quick")


def _merge(base: Dict[str, Any], over: Mapping[str, Any], where: str = "speed") -> Dict[str, Any]:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if k not in out:
            raise ValueError(f"benchmark config: unknown key '{where}.{k}'; expected one of {sorted(out)}")
        if isinstance(out[k], dict):
            if not isinstance(v, Mapping):
                raise ValueError(f"benchmark config: '{where}.{k}' must be a mapping, got {v!r}")
            out[k] = _merge(out[k], v, f"{where}.{k}")
        else:
            out[k] = copy.deepcopy(v)
    return out


def resolve_config(cfg: Optional[Mapping[str, Any]] = None) -> Dict[str, Any]:
    """Benchmark config (top-level ``device``, ``out``, ``quick`` + a ``speed:`` section) ->
    the full parameter dict (``DEFAULTS``, then ``QUICK`` when quick, then the user's keys)."""
    try:
        from omegaconf import DictConfig, OmegaConf
        if isinstance(cfg, DictConfig):
            cfg = OmegaConf.to_container(cfg, resolve=True)
    except ImportError:  # pragma: no cover
        pass
    cfg = dict(cfg or {})
    speed = dict(cfg.get("speed") or {})
    top = {k: speed.pop(k, None) for k in TOP_LEVEL}
    for k in TOP_LEVEL:  # the top level (the dispatcher's CLI) wins
        if cfg.get(k) is not None:
            top[k] = cfg[k]
    quick = bool(top["quick"]) if top["quick"] is not None else False
    p = _merge(DEFAULTS, QUICK) if quick else copy.deepcopy(DEFAULTS)
    p = _merge(p, speed)
    p["quick"] = quick
    p["device"] = str(top["device"] or "cpu")
    p["out"] = top["out"]
    bad = set(p["sections"]) - {"train", "inference", "streaming", "filters"}
    if bad:
        raise ValueError(f"benchmark config: speed.sections: unknown {sorted(bad)}; "
                         "expected a subset of [train, inference, streaming, filters]")
    if p["device"] not in ("cpu", "cuda"):
        raise ValueError(f"benchmark config: device={p['device']!r}; expected 'cpu' or 'cuda'")
    if p["device"] == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"benchmark config: device=cuda but torch.cuda.is_available() is False "
                         f"(torch {torch.__version__}); run with device=cpu")
    return p


# ------------------------------------------------------------------------ environment
def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(module: str) -> Optional[str]:
    try:
        from importlib.metadata import version
        return version(module)
    except Exception:  # noqa: BLE001
        return None


def environment(device: str) -> Dict[str, Any]:
    """Versions, CPU, threads, GPU, load average."""
    env = {
        "python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__,
        "platform": platform.platform(), "cpu": _cpu_model(), "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(), "device": device,
        "cuda_available": torch.cuda.is_available(),
        "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "peers": {m: _version(m) for m in ("vqf", "imufusion", "riann", "onnxruntime")},
        "loadavg_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }
    try:
        env["git_commit"] = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                                           text=True, timeout=5).stdout.strip() or None
    except Exception:  # noqa: BLE001
        env["git_commit"] = None
    return env


# ----------------------------------------------------------------------------- timing
def _sync(device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def time_calls(fn: Callable[[], Any], warmup: int, repeats: int, device="cpu",
               max_seconds: Optional[float] = None) -> List[float]:
    """Seconds per call of ``fn`` after ``warmup`` untimed calls: ``repeats`` calls, or fewer
    (at least one) once ``max_seconds`` of timed calls passed."""
    for _ in range(warmup):
        fn()
    _sync(device)
    out: List[float] = []
    start = time.perf_counter()
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        fn()
        _sync(device)
        out.append(time.perf_counter() - t)
        if max_seconds is not None and time.perf_counter() - start > max_seconds:
            break
    return out


def summary(seconds: List[float]) -> Dict[str, float]:
    s = sorted(seconds)
    p99 = s[min(len(s) - 1, int(math.ceil(0.99 * len(s))) - 1)]
    return {"median_s": statistics.median(s), "mean_s": statistics.fmean(s), "p99_s": p99,
            "min_s": s[0], "n": len(s)}


class _Threads:
    """``with _Threads(n):`` torch.set_num_threads(n) inside, restored after (None: unchanged)."""

    def __init__(self, n: Optional[int]):
        self.n = n

    def __enter__(self):
        self.old = torch.get_num_threads()
        if self.n:
            torch.set_num_threads(int(self.n))
        return self

    def __exit__(self, *exc):
        torch.set_num_threads(self.old)


# --------------------------------------------------------------------- synthetic data
def synthetic_imu(batch: int, n: int, axes: int, rate: float, seed: int = 0,
                  device="cpu") -> Dict[str, Tensor]:
    """Plausible raw IMU windows with ground truth: smooth random body rates (rad/s),
    specific force ~ gravity (m/s^2), field ~ 50 uT (9-axis), ground-truth ``nav_from_body``
    = the integrated true rate. Returns imu (B, N, C) float32, dt (B, N), rot (B, N, 3, 3),
    valid (B, N) bool, on ``device``."""
    g = torch.Generator().manual_seed(seed)
    dt = 1.0 / rate
    # smooth rates: a random walk, leaky so it stays ~1 rad/s
    steps = torch.randn(batch, n, 3, generator=g, dtype=torch.float64) * 0.05
    rate_true = torch.cumsum(steps, 1)
    rate_true = rate_true - rate_true.mean(1, keepdim=True)
    rot = so3.integrate(torch.eye(3, dtype=torch.float64).expand(batch, 3, 3), rate_true,
                        torch.full((batch, n), dt, dtype=torch.float64))
    up = rot[..., 2, :]  # C^T e_up: nav up seen in the body frame
    acc = 9.81 * up + 0.2 * torch.randn(batch, n, 3, generator=g, dtype=torch.float64)
    parts = [rate_true + 0.01 + 0.005 * torch.randn(batch, n, 3, generator=g, dtype=torch.float64), acc]
    if axes == 9:
        field = torch.tensor([0.0, 20.0, -45.0], dtype=torch.float64)  # ENU, uT
        parts.append(rot.transpose(-1, -2) @ field + 0.5 * torch.randn(batch, n, 3, generator=g,
                                                                        dtype=torch.float64))
    imu = torch.cat(parts, -1).float()
    return {"imu": imu.to(device), "dt": torch.full((batch, n), dt, device=device),
            "rot": rot.float().to(device), "valid": torch.ones(batch, n, dtype=torch.bool, device=device)}


def model_config(axes: int) -> Dict[str, Any]:
    """The paper's model (conf/model/ahrs.yaml defaults) for ``axes`` 9 or 6."""
    cfg = {"variant": f"ahrs{axes}", "axes": axes}
    if axes == 6:
        cfg.update(mag_net="none", use_mag_term=False)
    return cfg


def make_model(axes: int, seed: int = 0):
    """An eval-mode :class:`LearnedAHRS` with non-trivial weights (BN statistics, output layers,
    gains) and input statistics: the same compute as a trained model."""
    from .model.ahrs import LearnedAHRS

    torch.manual_seed(seed)
    model = LearnedAHRS.from_config(model_config(axes))
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for mod in model.modules():
            if isinstance(mod, torch.nn.BatchNorm1d):
                mod.running_mean.normal_(0.0, 0.3, generator=g)
                mod.running_var.uniform_(0.5, 2.0, generator=g)
        for net in (model.calibration.gyro_error_net, model.calibration.acc_error_net,
                    model.calibration.mag_error_net):
            if net is not None and hasattr(net, "out"):
                net.out.weight.normal_(0.0, 0.05, generator=g)
        mean = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 9.81, 0.0, 20.0, -45.0][:axes])
        std = torch.tensor([1.0, 1.0, 1.0, 3.0, 3.0, 3.0, 30.0, 30.0, 30.0][:axes])
        model.calibration.set_input_stats(mean, std)
    return model.eval()


def tcn_flops_per_sample(model) -> int:
    """Multiply-adds x 2 of the calibration TCNs per sample (convolutions only)."""
    total = 0
    for mod in model.modules():
        if isinstance(mod, torch.nn.Conv1d):
            total += 2 * mod.in_channels * mod.out_channels * mod.kernel_size[0] // mod.groups
    return total


# ============================================================================ training
def broad_epoch(p: Dict[str, Any]) -> Dict[str, Any]:
    """Size of one epoch on the BROAD training split: samples, windows (every ``stride``, as
    :func:`tcn_ahrs.data.window_starts`) and optimiser steps; exact from the data when
    ``data_config`` loads, else from the constant ``split_samples`` (``source`` says which)."""
    window, stride, batch = int(p["window"]), int(p["stride"]), int(p["batch_size"])
    cfg_path = p.get("data_config")
    if cfg_path:
        try:
            from omegaconf import OmegaConf

            from .data import SequenceStore, window_starts
            from .datasets import load_split

            data_cfg = OmegaConf.load(str(cfg_path))
            seqs = load_split(data_cfg, "train")
            store = SequenceStore(seqs, int(p["axes"]))
            n_win = int(window_starts(store, window, stride).numel())
            return {"source": f"load_split({cfg_path}, 'train') at {data_cfg.get('root')}",
                    "recordings": len(seqs), "samples": int(sum(store.lengths)), "windows": n_win,
                    "steps": math.ceil(n_win / batch)}
        except Exception as e:  # noqa: BLE001  no data here: fall back to the constant
            reason = f"{type(e).__name__}: {e}"
    else:
        reason = "data_config unset"
    samples, recs = int(p["split_samples"]), int(p["split_recordings"])
    per = samples / recs
    n_win = int(recs * (max(0.0, per - window) // stride + 1))
    return {"source": f"constant split_samples={samples} ({recs} recordings; {reason})",
            "recordings": recs, "samples": samples, "windows": n_win, "steps": math.ceil(n_win / batch)}


def static_increment_loss(omega: Tensor, dt: Tensor, rot_gt: Tensor, valid: Tensor, js, delta: float,
                          dtype=torch.float64) -> Tensor:
    """:func:`tcn_ahrs.losses.increment_loss` without host synchronisation or data-dependent
    shapes (masked mean instead of boolean indexing), as CUDA graphs need; equal to it
    whenever at least one increment per j is valid (tested)."""
    import torch.nn.functional as F

    from .losses import increment_valid, predicted_increments, true_increments

    gt = torch.where(valid[..., None, None], rot_gt.to(dtype), torch.eye(3, dtype=dtype, device=omega.device))
    total = omega.new_zeros(())
    for j in js:
        if omega.shape[-2] <= j:
            continue
        err = so3.log(true_increments(gt, j).transpose(-1, -2) @ predicted_increments(omega, dt, j, dtype))
        m = increment_valid(valid, j).to(dtype)[..., None]
        per = F.smooth_l1_loss(err, torch.zeros_like(err), beta=delta, reduction="none")
        total = total + ((per * m).sum() / (3.0 * m.sum()).clamp_min(1.0)).to(omega.dtype)
    return total


def _train_setup(p: Dict[str, Any], device: str, seed: int):
    from .data import augment  # noqa: F401  (imported here so a broken import fails early)
    from .train import AHRSModule

    torch.manual_seed(seed)
    axes = int(p["axes"])
    module = AHRSModule(model_config(axes), axes, window=int(p["window"]))
    model = module.model.to(device).train()
    mean = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 9.81, 0.0, 20.0, -45.0][:axes])
    std = torch.tensor([1.0, 1.0, 1.0, 3.0, 3.0, 3.0, 30.0, 30.0, 30.0][:axes])
    model.calibration.set_input_stats(mean, std)
    # a device-resident "store" holding 2 x batch windows; each step gathers random windows
    n_store = 2 * int(p["batch_size"])
    store = synthetic_imu(1, n_store * int(p["window"]), axes, float(p["rate"]), seed, device)
    store = {k: v[0] for k, v in store.items()}
    return module, model, store


def make_train_step(variant: str, p: Dict[str, Any], device: str, seed: int = 0):
    """Build one variant's full training step (gather + augment + forward + loss + backward +
    AdamW step, as :meth:`tcn_ahrs.train.AHRSModule.training_step`) -> (step(), info dict).
    Builds (and for ``compile``/``cuda_graphs`` compiles/captures) before returning."""
    from .data import augment
    from .losses import increment_loss

    B, N = int(p["batch_size"]), int(p["window"])
    module, model, store = _train_setup(p, device, seed)
    opt = module.configure_optimizers()["optimizer"]
    js, delta, noise = module.loss_js, float(module.hparams.huber_delta), {"gyro": 0.001, "acc": 0.01, "mag": 0.1}
    n_store = store["imu"].shape[0]
    gen = torch.Generator(device="cpu").manual_seed(seed)
    arange = torch.arange(N, device=device)
    cuda = torch.device(device).type == "cuda"
    loss_dtype = torch.float32 if variant == "loss_fp32" else torch.float64
    known = ("eager", "loss_fp32", "bf16", "compile", "fp32", "tf32", "cuda_graphs")
    if variant not in known:
        raise ValueError(f"training variant {variant!r}: expected one of {known}")
    if variant in ("fp32", "tf32", "cuda_graphs") and not cuda:
        raise RuntimeError(f"variant {variant!r} needs device=cuda")

    def gather() -> Dict[str, Tensor]:  # tcn_ahrs.data.SequenceStore.gather
        starts = torch.randint(0, n_store - N + 1, (B,), generator=gen).to(device)
        idx = starts[:, None] + arange
        return {k: v[idx] for k, v in store.items()}

    def forward_loss(imu, dt, rot, valid):
        if variant == "bf16":
            # The TCNs in bfloat16; ECF (pre-integration over thousands of samples) and loss in
            # float32/float64 — autocast over the ECF would integrate attitudes in bf16.
            with torch.autocast(torch.device(device).type, dtype=torch.bfloat16):
                cal = model.calibration(imu)
            cal = {k: v.float() for k, v in cal.items()}
            omega, _, _ = model.ecf(cal["gyro"], cal["acc"], cal.get("mag"), imu[..., 0:3], imu[..., 3:6],
                                    rot[:, 0], dt)
        else:
            omega = model(imu, dt, rot[:, 0])["omega"]
        return increment_loss(omega, dt, rot, valid, js, delta, dtype=loss_dtype)

    def tf32_mode():
        if cuda:  # fp32 must switch TF32 off explicitly (cuDNN convolutions default to TF32)
            torch.backends.cuda.matmul.allow_tf32 = variant == "tf32"
            torch.backends.cudnn.allow_tf32 = variant == "tf32"

    info: Dict[str, Any] = {"variant": variant, "compile_s": None}
    if variant == "cuda_graphs":
        tf32_mode()
        graph_step, info["compile_s"] = _cuda_graph_step(model, opt, store, B, N, js, delta, noise, gen, device)

        def step():
            tf32_mode()
            graph_step()
        return step, info
    fl = torch.compile(forward_loss) if variant == "compile" else forward_loss

    def step():
        tf32_mode()
        w = gather()
        loss = fl(augment(w["imu"], noise), w["dt"], w["rot"], w["valid"])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return loss

    if variant == "compile":  # the first call compiles; the second may recompile
        t = time.perf_counter()
        step()
        step()
        _sync(device)
        info["compile_s"] = time.perf_counter() - t
    return step, info


def _finish_row(info: Dict[str, Any], ts: List[float], p: Dict[str, Any], device: str) -> Dict[str, Any]:
    st = summary(ts)
    B, N = int(p["batch_size"]), int(p["window"])
    row = dict(info)
    row.update({"step_s": st["median_s"], "steps_timed": st["n"], "samples_per_s": B * N / st["median_s"],
                "threads": torch.get_num_threads()})
    if torch.device(device).type == "cuda":
        row["max_memory_gb"] = torch.cuda.max_memory_allocated() / 1e9
    return row


def train_variant(variant: str, p: Dict[str, Any], device: str, seed: int = 0) -> Dict[str, Any]:
    """Time one variant's training step alone: {step_s (median), samples_per_s, compile_s, ...}."""
    saved = _save_tf32()
    try:
        step, info = make_train_step(variant, p, device, seed)
        ts = time_calls(step, int(p["warmup"]), int(p["steps"]), device, p.get("max_seconds"))
    finally:
        _restore_tf32(saved)
    return _finish_row(info, ts, p, device)


def _save_tf32():
    return (torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32)


def _restore_tf32(saved) -> None:
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = saved


def train_variants_interleaved(variants: List[str], p: Dict[str, Any], device: str, seed: int = 0) -> List[Dict[str, Any]]:
    """Time several in-process variants round-robin (one timed step of each in turn), so that a
    change of machine load affects all of them alike; a variant that fails to build is reported
    as skipped. Stops after ``steps`` rounds or ``max_seconds`` x len(variants) seconds."""
    saved = _save_tf32()
    built, rows = [], {}
    try:
        for v in variants:
            t0 = time.perf_counter()
            try:
                step, info = make_train_step(v, p, device, seed)
                for _ in range(int(p["warmup"])):
                    step()
                _sync(device)
                info["build_s"] = time.perf_counter() - t0
                built.append((v, step, info, []))
            except Exception as e:  # noqa: BLE001  one failing variant must not lose the others
                rows[v] = {"variant": v, "skipped": f"failed: {type(e).__name__}: {str(e)[:300]}"}
        budget = float(p.get("max_seconds") or float("inf")) * max(1, len(built))
        start = time.perf_counter()
        for i in range(max(1, int(p["steps"]))):
            if i > 0 and time.perf_counter() - start > budget:
                break
            for v, step, info, ts in built:
                try:
                    t = time.perf_counter()
                    step()
                    _sync(device)
                    ts.append(time.perf_counter() - t)
                except Exception as e:  # noqa: BLE001
                    info["error"] = f"{type(e).__name__}: {str(e)[:300]}"
        for v, step, info, ts in built:
            rows[v] = _finish_row(info, ts, p, device) if ts else {"variant": v, "skipped": f"failed: {info.get('error')}"}
    finally:
        _restore_tf32(saved)
    return [rows[v] for v in variants]


def _cuda_graph_step(model, opt, store, B, N, js, delta, noise, gen, device):
    """Whole-step CUDA graph (forward, backward, AdamW(capturable)) with the static loss."""
    # same groups/hyper-parameters as configure_optimizers, but capturable (state on the GPU)
    groups = [dict({k: v for k, v in g.items() if k != "initial_lr"}, capturable=True) for g in opt.param_groups]
    opt = torch.optim.AdamW(groups)
    axes = store["imu"].shape[-1]
    std = torch.tensor([noise["gyro"]] * 3 + [noise["acc"]] * 3 + [noise["mag"]] * 3, device=device)[:axes]
    n_store = store["imu"].shape[0]
    starts = torch.zeros(B, dtype=torch.long, device=device)
    arange = torch.arange(N, device=device)

    def body():
        idx = starts[:, None] + arange
        w = {k: v[idx] for k, v in store.items()}
        imu = w["imu"] + torch.randn_like(w["imu"]) * std  # tcn_ahrs.data.augment, sync-free
        omega = model(imu, w["dt"], w["rot"][:, 0])["omega"]
        loss = static_increment_loss(omega, w["dt"], w["rot"], w["valid"], js, delta)
        loss.backward()
        opt.step()
        return loss

    t = time.perf_counter()
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(3):
            opt.zero_grad(set_to_none=True)
            body()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    opt.zero_grad(set_to_none=True)
    with torch.cuda.graph(graph):
        body()
    torch.cuda.synchronize()
    capture_s = time.perf_counter() - t

    def step():
        starts.copy_(torch.randint(0, n_store - N + 1, (B,), generator=gen))
        graph.replay()

    return step, capture_s


def _train_variant_subprocess(variant: str, p: Dict[str, Any], device: str, seed: int,
                              threads: Optional[int]) -> Dict[str, Any]:
    """Run :func:`train_variant` in a child process bounded by ``compile_timeout_s``."""
    payload = json.dumps({"variant": variant, "p": p, "device": device, "seed": seed, "threads": threads})
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    try:
        r = subprocess.run([sys.executable, "-m", "tcn_ahrs.bench_speed", "--train-worker", payload],
                           capture_output=True, text=True, timeout=float(p["compile_timeout_s"]), env=env)
    except subprocess.TimeoutExpired:
        return {"variant": variant, "skipped": f"did not finish within compile_timeout_s={p['compile_timeout_s']} s"}
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    if r.returncode != 0 or not lines:
        tail = (r.stderr or r.stdout).strip().splitlines()[-3:]
        return {"variant": variant, "skipped": f"failed (exit {r.returncode}): {' | '.join(tail)[:400]}"}
    return json.loads(lines[-1])


def bench_train(p: Dict[str, Any], device: str, seed: int = 0) -> Dict[str, Any]:
    cuda = device == "cuda"
    variants = list(p["variants_cuda"] if cuda else p["variants_cpu"])
    notes = []
    if not cuda:
        notes.append("CUDA variants (fp32, tf32, bf16, compile, CUDA graphs) skipped: device=cpu")
    epoch = broad_epoch(p)
    with _Threads(p.get("threads")):
        threads = torch.get_num_threads()
        inproc = [v for v in variants if v != "compile"]
        t0 = time.perf_counter()
        by = {r["variant"]: r for r in train_variants_interleaved(inproc, p, device, seed)} if inproc else {}
        for r in by.values():
            r["wall_s"] = time.perf_counter() - t0
        if "compile" in variants:
            t0 = time.perf_counter()
            by["compile"] = _train_variant_subprocess("compile", p, device, seed, threads)
            by["compile"]["wall_s"] = time.perf_counter() - t0
        rows = [by[v] for v in variants]
    base = next((r for r in rows if "samples_per_s" in r), None)
    per_pass = epoch["samples"]
    per_epoch = epoch["windows"] * int(p["window"])  # samples processed per epoch (overlapping windows)
    for r in rows:
        if "samples_per_s" not in r:
            continue
        r["vs_baseline"] = r["samples_per_s"] / base["samples_per_s"]
        r["epoch_s"] = epoch["steps"] * r["step_s"]
        r["schedule_h"] = r["epoch_s"] * int(p["epochs"]) / 3600.0
        r["one_pass_s"] = per_pass / r["samples_per_s"]
    return {"shape": {"batch_size": int(p["batch_size"]), "window": int(p["window"]), "axes": int(p["axes"])},
            "baseline": base["variant"] if base else None, "threads": threads, "epoch": epoch,
            "samples_per_epoch": per_epoch, "epochs": int(p["epochs"]), "rows": rows, "notes": notes}


# =========================================================================== inference
def bench_inference(p: Dict[str, Any], device: str, seed: int = 0) -> Dict[str, Any]:
    from .export import export_batch

    n, rate = int(p["samples"]), float(p["rate"])
    model = make_model(9, seed)
    data = synthetic_imu(1, n, 9, rate, seed)
    imu, dt = data["imu"], data["dt"]
    r0 = torch.eye(3)[None]
    q0 = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    rows = []
    tmp = tempfile.TemporaryDirectory()
    path = Path(tmp.name) / "batch.pt"
    export_batch(model, path)
    scripted = torch.jit.load(str(path))
    w, r = int(p["warmup"]), int(p["repeats"])

    def add(name, dev, fn, threads):
        try:
            ts = time_calls(fn, w, r, dev)
            s = summary(ts)
            rows.append({"name": name, "device": dev, "threads": threads, "median_ms": 1e3 * s["median_s"],
                         "p99_ms": 1e3 * s["p99_s"], "samples_per_s": n / s["median_s"]})
        except Exception as e:  # noqa: BLE001
            rows.append({"name": name, "device": dev, "threads": threads,
                         "skipped": f"failed: {type(e).__name__}: {str(e)[:300]}"})

    with torch.no_grad(), _Threads(p["threads"]):
        th = torch.get_num_threads()
        add("eager (LearnedAHRS.run_sequence)", "cpu", lambda: model.run_sequence(imu, dt, r0, 0), th)
        add("TorchScript batch (export_batch)", "cpu", lambda: scripted(imu[0], 1.0 / rate, q0), th)
        add("TorchScript TCN only (errors)", "cpu", lambda: scripted.errors(imu[0]), th)
        if device == "cuda":
            m_gpu = copy.deepcopy(model).to("cuda")
            imu_g, dt_g, r0_g = imu.to("cuda"), dt.to("cuda"), r0.to("cuda")
            add("eager (LearnedAHRS.run_sequence)", "cuda", lambda: m_gpu.run_sequence(imu_g, dt_g, r0_g, 0), th)
            try:
                s_gpu = torch.jit.load(str(path), map_location="cuda")
                add("TorchScript batch (export_batch)", "cuda", lambda: s_gpu(imu_g[0], 1.0 / rate, q0.cuda()), th)
            except Exception as e:  # noqa: BLE001
                rows.append({"name": "TorchScript batch (export_batch)", "device": "cuda",
                             "skipped": f"failed: {type(e).__name__}: {str(e)[:300]}"})
    tmp.cleanup()
    flops = tcn_flops_per_sample(model) * n
    by = {(r["name"], r["device"]): r for r in rows if "median_ms" in r}
    eager = by.get(("eager (LearnedAHRS.run_sequence)", "cpu"))
    for r in rows:
        if "median_ms" in r and eager:
            r["vs_eager_cpu"] = r["median_ms"] / eager["median_ms"]
        if "median_ms" in r:
            r["tcn_gflops"] = flops / (r["median_ms"] * 1e-3) / 1e9
    script = by.get(("TorchScript batch (export_batch)", "cpu"))
    return {"samples": n, "rate_hz": rate, "axes": 9, "tcn_gflop": flops / 1e9, "rows": rows,
            "goal_ms": float(p["goal_ms"]),
            "goal_met": bool(script and script["median_ms"] <= float(p["goal_ms"]))}


# =========================================================================== streaming
def bench_streaming(p: Dict[str, Any], seed: int = 0) -> Dict[str, Any]:
    from .export import export_streaming

    n, rate = int(p["samples"]), float(p["rate"])
    rows = []
    with torch.no_grad(), _Threads(p["threads"]):
        th = torch.get_num_threads()
        tmp = tempfile.TemporaryDirectory()
        for axes in p["axes"]:
            axes = int(axes)
            model = make_model(axes, seed)
            path = Path(tmp.name) / f"stream{axes}.pt"
            export_streaming(model, path)
            m = torch.jit.load(str(path))
            x = synthetic_imu(1, n + int(p["warmup"]), axes, rate, seed)["imu"][0]
            xs = list(x.unbind(0))
            q0 = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
            dt = 1.0 / rate
            m.reset(q0)
            for k in range(int(p["warmup"])):
                m.step(xs[k], dt)
            ts = []
            for k in range(int(p["warmup"]), len(xs)):
                t = time.perf_counter_ns()
                m.step(xs[k], dt)
                ts.append(time.perf_counter_ns() - t)
            rows.append(_latency_row(f"TorchScript streaming step ({axes}-axis)", ts, th))
            nr = int(p["run_samples"])
            xr = x[:nr]
            m.run(xr, dt, q0)  # warm-up (profiling executor)
            t = time.perf_counter()
            m.run(xr, dt, q0)
            el = time.perf_counter() - t
            rows.append({"name": f"TorchScript streaming run() loop ({axes}-axis)", "threads": th,
                         "median_us": 1e6 * el / nr, "p99_us": None, "samples_per_s": nr / el})
        tmp.cleanup()
        if p.get("riann"):
            rows.extend(_riann_rows(p, n, rate, seed, th))
    ours = next((r for r in rows if r["name"].startswith("TorchScript streaming step") and "samples_per_s" in r), None)
    riann = next((r for r in rows if r["name"].startswith("RIANN predict_step") and "samples_per_s" in r), None)
    for r in rows:
        if riann and "samples_per_s" in r:
            r["vs_riann_step"] = r["samples_per_s"] / riann["samples_per_s"]
    goal = float(p["goal_samples_per_s"])
    return {"rows": rows, "goal_samples_per_s": goal,
            "goal_met": bool(ours and ours["samples_per_s"] >= goal and (riann is None or ours["samples_per_s"] > riann["samples_per_s"]))}


def _latency_row(name: str, ns: List[int], threads: int) -> Dict[str, Any]:
    s = summary([v * 1e-9 for v in ns])
    # samples/s = 1 / median latency (the code's cost per sample); 1 / mean also counts the
    # calls preempted by other processes (p99 of several ms on a loaded machine).
    return {"name": name, "threads": threads, "median_us": 1e6 * s["median_s"], "p99_us": 1e6 * s["p99_s"],
            "samples_per_s": 1.0 / s["median_s"], "samples_per_s_mean": 1.0 / s["mean_s"], "n": s["n"]}


def _riann_rows(p, n, rate, seed, threads) -> List[Dict[str, Any]]:
    try:
        from .estimators.peers import RIANNEstimator

        est = RIANNEstimator(axes=6)
    except Exception as e:  # noqa: BLE001
        return [{"name": "RIANN predict_step (6-axis)", "skipped": f"unavailable: {type(e).__name__}: {e}"}]
    rm = est._model
    d = synthetic_imu(1, n + int(p["warmup"]), 6, rate, seed)["imu"][0].double().numpy()
    gyr, acc = np.ascontiguousarray(d[:, 0:3]), np.ascontiguousarray(d[:, 3:6])
    rm.reset_state()
    rm.set_sampling_rate(rate)
    for k in range(int(p["warmup"])):
        rm.predict_step(acc[k], gyr[k])
    ts = []
    for k in range(int(p["warmup"]), len(d)):
        t = time.perf_counter_ns()
        rm.predict_step(acc[k], gyr[k])
        ts.append(time.perf_counter_ns() - t)
    rows = [_latency_row("RIANN predict_step (6-axis, onnxruntime)", ts, threads)]
    rows[0]["threads"] = "onnxruntime default"
    t = time.perf_counter()
    rm.predict(acc, gyr, rate)
    el = time.perf_counter() - t
    rows.append({"name": "RIANN predict (batch, 6-axis)", "threads": "onnxruntime default",
                 "median_us": 1e6 * el / len(d), "p99_us": None, "samples_per_s": len(d) / el})
    return rows


# ============================================================================= filters
def bench_filters(p: Dict[str, Any], device: str, seed: int = 0) -> Dict[str, Any]:
    """Samples/s of registered classical filters (``p["filters"]``, registry names) on one
    recording: batch b = b parameter sets of the first ``default_grid`` parameter, spread over
    its grid range, in one ``quat_batch`` call (the path of evaluation and tuning)."""
    from .datasets.simulate import simulate
    from .estimators import registry

    n, rate = int(p["samples"]), float(p["rate"])
    batches = [int(b) for b in p["batches"]]
    seq = simulate("walking", duration=(n - 1) / rate, rate=rate, seed=seed, axes=9)
    rows = []
    devices = ["cpu"] + (["cuda"] if device == "cuda" else [])
    with _Threads(p["threads"]):
        th = torch.get_num_threads()
        for dev in devices:
            for name in p["filters"]:
                if name not in registry.methods("classical"):
                    raise ValueError(f"speed.filters.filters: unknown filter {name!r}; expected one of "
                                     f"{list(registry.methods('classical'))}")
                est = registry.build(name, 9, device=dev)
                key, values = next(iter(type(est).default_grid.items()))
                lo, hi = float(min(values)), float(max(values))
                for b in batches:
                    val = (torch.linspace(lo, hi, b, dtype=torch.float64, device=dev)[:, None] if b > 1
                           else (lo + hi) / 2)
                    call = lambda: est.quat_batch([seq], [None], {key: val})  # noqa: E731
                    ts = time_calls(call, 0, int(p["repeats"]), dev)
                    s = summary(ts)
                    rows.append({"name": f"tcn_ahrs.filters.{name}", "device": dev, "batch": b, "threads": th,
                                 "seconds": s["median_s"], "samples_per_s": b * n / s["median_s"],
                                 "per_recording_samples_per_s": n / s["median_s"]})
        rows.extend(_peer_filter_rows(p, seq))
    vqf = next((r for r in rows if r["name"].startswith("vqf") and "samples_per_s" in r), None)
    for r in rows:
        if vqf and "samples_per_s" in r:
            r["vs_vqf"] = r["samples_per_s"] / vqf["samples_per_s"]
    batched = [r for r in rows if r.get("batch", 1) > 1 and r["device"] == "cpu" and "samples_per_s" in r]
    goal = {r["name"]: bool(vqf and r["samples_per_s"] >= vqf["samples_per_s"]) for r in batched}
    return {"samples": n, "rate_hz": rate, "batches": batches, "recording": seq.name, "rows": rows,
            "goal_met": goal if vqf else None}


def _peer_filter_rows(p, seq) -> List[Dict[str, Any]]:
    from .estimators import registry

    rows = []
    for key in p["peers"]:
        try:
            est = registry.build(key, 9)
        except Exception as e:  # noqa: BLE001
            rows.append({"name": f"{key} (9D)", "device": "cpu", "batch": 1,
                         "skipped": f"unavailable: {type(e).__name__}: {e}"})
            continue
        est.run(seq)  # warm-up (imports, first-call allocations)
        ts = time_calls(lambda: est.run(seq), 0, int(p["repeats"]))
        s = summary(ts)
        rows.append({"name": f"{key} (9D, {est.name} wrapper)", "device": "cpu", "batch": 1, "threads": 1,
                     "seconds": s["median_s"], "samples_per_s": len(seq) / s["median_s"],
                     "per_recording_samples_per_s": len(seq) / s["median_s"]})
    return rows


# ============================================================================= report
def _f(v, fmt="{:.3g}") -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return fmt.format(v)
    return str(v)


def _table(head: List[str], rows: List[List[Any]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    lines += ["| " + " | ".join(_f(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def to_markdown(res: Dict[str, Any]) -> str:
    env = res["environment"]
    out = ["# Speed benchmark", "",
           f"device={env['device']}; torch {env['torch']}, numpy {env['numpy']}, Python {env['python']}; "
           f"CPU {env['cpu']} ({env['cpu_count']} logical cores, torch threads {env['torch_threads']}); "
           f"GPU {env['gpu'] or 'none'}; peers {env['peers']}; git {env.get('git_commit')}; "
           f"load average start {env.get('loadavg_start')} end {env.get('loadavg_end')}; "
           f"quick={res['config']['quick']}; total {res['total_s']:.0f} s.", ""]
    tr = res.get("train")
    if tr:
        e = tr["epoch"]
        out += ["## Training step (TCN + ECF + loss, forward + backward + AdamW)", "",
                f"Shape batch {tr['shape']['batch_size']} x window {tr['shape']['window']} x {tr['shape']['axes']} axes, "
                f"{tr['threads']} torch threads. Epoch = {e['windows']} windows (stride) = {e['steps']} steps; "
                f"BROAD training split {e['samples']} samples ({e['source']}). Schedule = {tr['epochs']} epochs "
                "(training steps only, no validation).", ""]
        rows = []
        for r in tr["rows"]:
            if "samples_per_s" in r:
                rows.append([r["variant"], r["step_s"], r["steps_timed"], r["samples_per_s"],
                             f"{r['vs_baseline']:.2f}x", r["compile_s"], r["one_pass_s"], r["epoch_s"], r["schedule_h"]])
            else:
                rows.append([r["variant"], "-", "-", "-", "-", "-", "-", "-", r.get("skipped")])
        out += [_table(["variant", "step s", "steps", "samples/s", f"vs {tr['baseline']}", "compile s",
                        "one pass over split s", "epoch s", "schedule h / note"], rows)]
        out += [f"\n_{n}_" for n in tr["notes"]] + [""]
    inf = res.get("inference")
    if inf:
        out += ["## Batch inference (one sequence)", "",
                f"{inf['samples']} samples at {inf['rate_hz']:.0f} Hz, 9-axis; TCN {inf['tcn_gflop']:.2f} GFLOP. "
                f"Goal <= {inf['goal_ms']:.0f} ms (TorchScript, 1 CPU thread): "
                f"{'met' if inf['goal_met'] else 'NOT met'}.", ""]
        rows = [[r["name"], r["device"], r.get("threads"), r.get("median_ms"), r.get("p99_ms"),
                 f"{r['vs_eager_cpu']:.2f}x" if "vs_eager_cpu" in r else r.get("skipped"), r.get("tcn_gflops")]
                for r in inf["rows"]]
        out += [_table(["path", "device", "threads", "median ms", "p99 ms", "/ eager CPU", "TCN GFLOP/s"], rows), ""]
    st = res.get("streaming")
    if st:
        out += ["## Streaming (one sample per call)", "",
                f"samples/s = 1 / median latency (1 / mean in brackets, includes preemption by other processes). "
                f"Goal >= {st['goal_samples_per_s']:.0f} samples/s on 1 CPU thread and faster than RIANN's step "
                f"mode: {'met' if st['goal_met'] else 'NOT met'}.", ""]
        rows = [[r["name"], r.get("threads"), r.get("median_us"), r.get("p99_us"),
                 f"{r['samples_per_s']:.3g}" + (f" ({r['samples_per_s_mean']:.3g})" if "samples_per_s_mean" in r else "")
                 if "samples_per_s" in r else "-",
                 f"{r['vs_riann_step']:.2f}x" if "vs_riann_step" in r else r.get("skipped", "-")] for r in st["rows"]]
        out += [_table(["path", "threads", "median us", "p99 us", "samples/s", "/ RIANN step"], rows), ""]
    fi = res.get("filters")
    if fi:
        out += ["## Classical filters", "",
                f"Recording {fi['recording']} ({fi['samples']} samples at {fi['rate_hz']:.0f} Hz, 9-axis); "
                f"batch = number of parameter sets run in one call (samples/s is the aggregate). "
                f"Goal (batched aggregate >= VQF single): {fi['goal_met']}.", ""]
        rows = [[r["name"], r.get("device"), r.get("batch"), r.get("seconds"), r.get("samples_per_s"),
                 f"{r['vs_vqf']:.2f}x" if "vs_vqf" in r else r.get("skipped", "-")] for r in fi["rows"]]
        out += [_table(["filter", "device", "batch", "s per call", "samples/s", "/ VQF"], rows), ""]
    return "\n".join(out)


def default_out_dir() -> Path:
    return Path("runs") / "benchmark" / "speed" / time.strftime("%Y-%m-%d_%H-%M-%S")


def main(cfg: Optional[Mapping[str, Any]] = None) -> Dict[str, Any]:
    """Run the speed benchmark; print the tables; write ``speed.json`` and ``speed.md`` to
    ``out`` (default ``runs/benchmark/speed/<time>/``). Returns the result dict."""
    p = resolve_config(cfg)
    device, seed = p["device"], int(p["seed"])
    t0 = time.perf_counter()
    res: Dict[str, Any] = {"environment": environment(device), "config": p}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # torch.jit.script is deprecated in 2.13
        for section in p["sections"]:
            ts = time.perf_counter()
            print(f"[speed] {section} ...", flush=True)
            if section == "train":
                res["train"] = bench_train(p["train"], device, seed)
            elif section == "inference":
                res["inference"] = bench_inference(p["inference"], device, seed)
            elif section == "streaming":
                res["streaming"] = bench_streaming(p["streaming"], seed)
            elif section == "filters":
                res["filters"] = bench_filters(p["filters"], device, seed)
            res.setdefault("section_s", {})[section] = time.perf_counter() - ts
    res["environment"]["loadavg_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    res["total_s"] = time.perf_counter() - t0
    md = to_markdown(res)
    print(md)
    out = Path(p["out"]) if p["out"] else default_out_dir()
    out.mkdir(parents=True, exist_ok=True)
    (out / "speed.json").write_text(json.dumps(res, indent=2, default=str))
    (out / "speed.md").write_text(md + "\n")
    res["out_dir"] = str(out)
    print(f"[speed] wrote {out / 'speed.json'} and {out / 'speed.md'}")
    return res


def _worker(payload: str) -> None:
    a = json.loads(payload)
    if a.get("threads"):
        torch.set_num_threads(int(a["threads"]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = train_variant(a["variant"], a["p"], a["device"], int(a["seed"]))
    print(json.dumps(r))


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--train-worker":
        _worker(sys.argv[2])
    else:
        from omegaconf import OmegaConf

        main(OmegaConf.to_container(OmegaConf.from_dotlist(sys.argv[1:]), resolve=True))
