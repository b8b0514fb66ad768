"""Speed of batch inference and of streaming (per-sample step, chunked step, RIANN) for the
shipped model (``checkpoints/closed_loop/broad9.ckpt`` / ``tumvi6.ckpt``; the default architecture with
non-trivial weights where a checkpoint is missing)."""
from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np
import torch

from .common import Threads, gemm_peak_gflops, summary, synthetic_imu, tcn_flops_per_sample, time_calls


def shipped_model(axes: int, ckpt: Optional[str], seed: int = 0) -> Tuple[Any, str, float]:
    """(model, what it is, rate_hz) — the checkpoint when it loads, else the default config."""
    from ..checkpoint import checkpoint_meta, load_checkpoint, model_from_checkpoint
    from .common import make_model

    if ckpt and Path(ckpt).is_file():
        meta = checkpoint_meta(load_checkpoint(ckpt), ckpt)
        rate = meta.get("rate_hz", (meta.get("layout") or {}).get("rate_hz")) or 100.0
        return model_from_checkpoint(ckpt).eval(), f"{ckpt}", float(rate)
    return make_model(axes, seed), f"default config (no {ckpt})", 100.0


def _export(model, rate: float, path: Path, mode: str):
    """The exported module (``mode`` batch | streaming) of ``model``, saved and loaded again."""
    from ..export import export_batch, export_streaming

    (export_batch if mode == "batch" else export_streaming)(model, path, {"rate_hz": rate})
    return torch.jit.load(str(path))


def _compiled(model, rate: float):
    try:
        from ..streaming import CompiledStreaming

        return CompiledStreaming(model, rate), None
    except ImportError as e:
        return None, f"unavailable: {e}"


def bench_inference(p: Dict[str, Any], device: str, seed: int = 0) -> Dict[str, Any]:
    n, rate = int(p["samples"]), float(p["rate"])
    model, what, model_rate = shipped_model(9, p.get("ckpt"), seed)
    data = synthetic_imu(1, n, 9, rate, seed)
    imu, dt = data["imu"], data["dt"]
    r0 = torch.eye(3)[None]
    q0 = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    rows: List[Dict[str, Any]] = []
    tmp = tempfile.TemporaryDirectory()
    batch = _export(model, model_rate, Path(tmp.name) / "batch.pt", "batch")
    stream = _export(model, model_rate, Path(tmp.name) / "stream.pt", "streaming")
    compiled, why = _compiled(model, model_rate)
    w, r, budget = int(p["warmup"]), int(p["repeats"]), float(p["max_seconds"])

    def add(name, fn: Callable, threads, dev="cpu", repeats=r):
        try:
            s = summary(time_calls(fn, w, repeats, dev, max_seconds=budget))
            rows.append({"name": name, "device": dev, "threads": threads, "median_ms": 1e3 * s["median_s"],
                         "p99_ms": 1e3 * s["p99_s"], "samples_per_s": n / s["median_s"]})
        except Exception as e:  # noqa: BLE001
            rows.append({"name": name, "device": dev, "threads": threads,
                         "skipped": f"failed: {type(e).__name__}: {str(e)[:300]}"})

    with torch.no_grad(), Threads(p["threads"]):
        th = torch.get_num_threads()
        add("eager LearnedAHRS.run_sequence (evaluation; loop compiled by numba)", lambda: model.run_sequence(imu, dt, r0, 0), th)
        add("calibration networks only (eager, float32)", lambda: model.calibration(imu), th)
        add("TorchScript batch module (export_batch)", lambda: batch(imu[0], 1.0 / rate, q0), th)
        add("TorchScript streaming module, run() as one chunk", lambda: stream.run(imu[0], 1.0 / rate, q0), th)
        if compiled is not None:
            x = imu[0].double().numpy()
            add("CompiledStreaming.run (numba, networks included)", lambda: compiled.run(x, 1.0 / rate, q0.numpy()), th)
        else:
            rows.append({"name": "CompiledStreaming.run (numba, networks included)", "skipped": why})
        closed = model.closed
        if closed is not None:
            old = closed.backend
            closed.backend = "torch"
            try:  # the loop as tensor ops (what training backpropagates through), for the ratio
                add("eager, loop as tensor ops (backend=torch)", lambda: model.run_sequence(imu, dt, r0, 0), th, repeats=1)
            finally:
                closed.backend = old
        peak = gemm_peak_gflops()
    tmp.cleanup()
    flops = tcn_flops_per_sample(model) * n
    by = {r["name"]: r for r in rows if "median_ms" in r}
    ref = by.get("eager LearnedAHRS.run_sequence (evaluation; loop compiled by numba)")
    for r in rows:
        if "median_ms" in r:
            if ref:
                r["vs_eager"] = r["median_ms"] / ref["median_ms"]
            r["tcn_gflops"] = flops / (r["median_ms"] * 1e-3) / 1e9
    goal = float(p["goal_ms"])
    best = min((r for r in rows if "median_ms" in r and not r["name"].startswith("calibration")),
               key=lambda r: r["median_ms"], default=None)
    return {"samples": n, "rate_hz": rate, "axes": 9, "model": what, "tcn_gflop": flops / 1e9,
            "gemm_peak_gflops": peak, "rows": rows, "goal_ms": goal,
            "best": best["name"] if best else None,
            "goal_met": bool(best and best["median_ms"] <= goal),
            "torchscript_goal_met": bool(by.get("TorchScript batch module (export_batch)", {}).get("median_ms", 1e9) <= goal)}


# =========================================================================== streaming
def _latency_row(name: str, ns: List[int], threads) -> Dict[str, Any]:
    s = summary([v * 1e-9 for v in ns])
    # samples/s = 1 / median latency (the code's cost per sample); 1 / mean also counts the
    # calls preempted by other processes (p99 of several ms on a loaded machine).
    return {"name": name, "threads": threads, "median_us": 1e6 * s["median_s"], "p99_us": 1e6 * s["p99_s"],
            "samples_per_s": 1.0 / s["median_s"], "samples_per_s_mean": 1.0 / s["mean_s"], "n": s["n"]}


def _time_steps(name, step: Callable[[int], Any], start: int, stop: int, per: int, threads) -> Dict[str, Any]:
    """Latency of step(k) for k = start, start + per, ... < stop; per sample when per > 1."""
    ts = []
    for k in range(start, stop - per + 1, per):
        t = time.perf_counter_ns()
        step(k)
        ts.append((time.perf_counter_ns() - t) / per)
    row = _latency_row(name, ts, threads)
    row["chunk"] = per
    return row


def bench_streaming(p: Dict[str, Any], seed: int = 0) -> Dict[str, Any]:
    n, rate, warm, chunk = int(p["samples"]), float(p["rate"]), int(p["warmup"]), int(p["chunk"])
    dt = 1.0 / rate
    rows: List[Dict[str, Any]] = []
    models = {}
    with torch.no_grad(), Threads(p["threads"]):
        th = torch.get_num_threads()
        tmp = tempfile.TemporaryDirectory()
        for axes in p["axes"]:
            axes = int(axes)
            model, what, model_rate = shipped_model(axes, (p.get("ckpts") or {}).get(str(axes)), seed)
            models[axes] = what
            m = _export(model, model_rate, Path(tmp.name) / f"stream{axes}.pt", "streaming")
            x = synthetic_imu(1, n + warm, axes, rate, seed)["imu"][0]
            xs = list(x.unbind(0))
            q0 = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
            m.reset(q0)
            for k in range(warm):
                m.step(xs[k], dt)
            rows.append(_time_steps(f"TorchScript step ({axes}-axis)", lambda k: m.step(xs[k], dt), warm, n + warm, 1, th))
            rows.append(_time_steps(f"TorchScript step_chunk, {chunk} per call ({axes}-axis)",
                                    lambda k: m.step_chunk(x[k:k + chunk], dt), warm, n + warm, chunk, th))
            cs, why = _compiled(model, model_rate)
            if cs is None:
                rows.append({"name": f"CompiledStreaming step ({axes}-axis)", "skipped": why})
                continue
            xn = x.double().numpy()
            cs.reset(q0.numpy())
            for k in range(warm):
                cs.step(xn[k], dt)
            rows.append(_time_steps(f"CompiledStreaming step (numba, {axes}-axis)", lambda k: cs.step(xn[k], dt),
                                    warm, n + warm, 1, th))
            rows.append(_time_steps(f"CompiledStreaming step_chunk, {chunk} per call ({axes}-axis)",
                                    lambda k: cs.step_chunk(xn[k:k + chunk], dt), warm, n + warm, chunk, th))
        tmp.cleanup()
        if p.get("riann"):
            rows.extend(_riann_rows(p, n, rate, seed, th))
    riann = next((r for r in rows if r["name"].startswith("RIANN predict_step") and "samples_per_s" in r), None)
    for r in rows:
        if riann and "samples_per_s" in r:
            r["vs_riann_step"] = r["samples_per_s"] / riann["samples_per_s"]
    steps = [r for r in rows if r.get("chunk") == 1 and "samples_per_s" in r and "9-axis" in r["name"]]
    chunks = [r for r in rows if (r.get("chunk") or 0) > 1 and "samples_per_s" in r and "9-axis" in r["name"]]
    best_step = max(steps, key=lambda r: r["samples_per_s"], default=None)
    best_chunk = max(chunks, key=lambda r: r["samples_per_s"], default=None)
    goal, goal_chunk = float(p["goal_samples_per_s"]), float(p["goal_chunk_samples_per_s"])
    return {"rows": rows, "models": models, "chunk": chunk, "goal_samples_per_s": goal,
            "goal_chunk_samples_per_s": goal_chunk,
            "best_step": best_step["name"] if best_step else None,
            "best_chunk": best_chunk["name"] if best_chunk else None,
            "goal_met": bool(best_step and best_step["samples_per_s"] >= goal
                             and (riann is None or best_step["samples_per_s"] > riann["samples_per_s"])),
            "chunk_goal_met": bool(best_chunk and best_chunk["samples_per_s"] >= goal_chunk)}


def _riann_rows(p, n, rate, seed, threads) -> List[Dict[str, Any]]:
    try:
        from ..estimators.peers_riann import RIANNEstimator

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
    row = _time_steps("RIANN predict_step (6-axis, onnxruntime)", lambda k: rm.predict_step(acc[k], gyr[k]),
                      int(p["warmup"]), len(d), 1, "onnxruntime default")
    t = time.perf_counter()
    rm.predict(acc, gyr, rate)
    el = time.perf_counter() - t
    return [row, {"name": "RIANN predict (batch, 6-axis)", "threads": "onnxruntime default",
                  "median_us": 1e6 * el / len(d), "p99_us": None, "samples_per_s": len(d) / el}]


# ============================================================================= filters
