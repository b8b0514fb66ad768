"""Speed of the training step (CPU and CUDA variants) and of one BROAD epoch."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional

import torch
from torch import Tensor

from .. import so3
from .common import Threads, model_config, shipped_config, summary, sync, synthetic_imu, time_calls


def broad_epoch(p: Dict[str, Any]) -> Dict[str, Any]:
    """Size of one epoch on the BROAD training split: samples, windows (every ``stride``, as
    :func:`tcn_ahrs.data.window_starts`) and optimiser steps; exact from the data when
    ``data_config`` loads, else from the constant ``split_samples`` (``source`` says which)."""
    window, stride, batch = int(p["window"]), int(p["stride"]), int(p["batch_size"])
    cfg_path = p.get("data_config")
    if cfg_path:
        try:
            from omegaconf import OmegaConf

            from ..data import SequenceStore, window_starts
            from ..datasets import load_split

            from pathlib import Path

            from ..config import conf_path

            path = Path(str(cfg_path))
            if not path.is_file() and path.parts and path.parts[0] == "conf":  # conf/...: the config folder's
                path = conf_path(*path.parts[1:])
            data_cfg = OmegaConf.load(str(path))
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

    from ..losses import increment_valid, predicted_increments, true_increments

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
    from ..data import augment  # noqa: F401  (imported here so a broken import fails early)
    from ..training.module import AHRSModule

    torch.manual_seed(seed)
    axes = int(p["axes"])
    closed = p.get("model", "closed") == "closed"
    cfg = shipped_config(axes) if closed else model_config(axes)
    module = AHRSModule(cfg, axes, window=int(p["window"]), lr=1e-3 if closed else 0.01, ema_decay=0.0)
    model = module.model.to(device).train()
    if model.closed is not None:
        model.closed.set_rate(float(p["rate"]))
    mean = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 9.81, 0.0, 20.0, -45.0][:axes])
    std = torch.tensor([1.0, 1.0, 1.0, 3.0, 3.0, 3.0, 30.0, 30.0, 30.0][:axes])
    model.calibration.set_input_stats(mean, std)
    # a device-resident "store" holding 2 x batch windows; each step gathers random windows
    n_store = 2 * int(p["batch_size"])
    span = int(p["window"]) + (model.receptive_field - 1 if model.closed is not None else 0)
    store = synthetic_imu(1, n_store * span, axes, float(p["rate"]), seed, device)
    store = {k: v[0] for k, v in store.items()}
    return module, model, store


def make_train_step(variant: str, p: Dict[str, Any], device: str, seed: int = 0):
    """Build one variant's full training step (gather + augment + forward + loss + backward +
    AdamW step, as :meth:`tcn_ahrs.training.run.AHRSModule.training_step`) -> (step(), info dict).
    Builds (and for ``compile``/``cuda_graphs`` compiles/captures) before returning."""
    from ..data import augment
    from ..losses import increment_loss

    B, N = int(p["batch_size"]), int(p["window"])
    module, model, store = _train_setup(p, device, seed)
    opt = module.configure_optimizers()["optimizer"]
    if model.closed is not None:
        from .training_closed import closed_loop_step

        return closed_loop_step(variant, p, device, seed, module, model, store, opt)
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
        sync(device)
        info["compile_s"] = time.perf_counter() - t
    return step, info


def loss_curves(variants: List[str], p: Dict[str, Any], device: str, seed: int = 0) -> Dict[str, List[float]]:
    """``curve_steps`` training steps of each variant from the same initial weights on the same
    batches (same seed): does a faster variant train like the reference?"""
    curves = {}
    for v in variants:
        step, _ = make_train_step(v, p, device, seed)
        curves[v] = [float(step()) for _ in range(int(p["curve_steps"]))]
    return curves


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
                sync(device)
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
                    sync(device)
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
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    try:
        r = subprocess.run([sys.executable, "-m", "tcn_ahrs.bench", "--train-worker", payload],
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
        notes.append(f"CUDA variants {list(p['variants_cuda'])} skipped: device=cpu (no GPU)")
    epoch = broad_epoch(p)
    with Threads(p.get("threads")):
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
    curves = {}
    check = [v for v in p.get("curve_variants") or [] if v in variants and v != "compile"]
    if check and int(p.get("curve_steps") or 0) > 0:
        ref = variants[0]
        with Threads(p.get("threads")):
            curves = loss_curves([ref] + [v for v in check if v != ref], p, device, seed)
        for v, c in curves.items():
            r0 = curves[ref]
            dev = max(abs(a - b) / max(abs(b), 1e-12) for a, b in zip(c, r0))
            notes.append(f"loss curve, {len(c)} steps from the same weights and batches: {v} deviates from "
                         f"{ref} by at most {100 * dev:.2f} % (first {c[0]:.4g} -> last {c[-1]:.4g}; "
                         f"{ref}: {r0[0]:.4g} -> {r0[-1]:.4g})")
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
            "samples_per_epoch": per_epoch, "epochs": int(p["epochs"]), "rows": rows, "notes": notes,
            "model": p.get("model", "closed"), "loss_curves": curves}


# =========================================================================== inference


def speed_worker(payload: str) -> None:
    a = json.loads(payload)
    if a.get("threads"):
        torch.set_num_threads(int(a["threads"]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = train_variant(a["variant"], a["p"], a["device"], int(a["seed"]))
    print(json.dumps(r))
