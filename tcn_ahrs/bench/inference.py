"""Speed of batch inference (eager and TorchScript) and of streaming (per-sample step, RIANN)."""
from __future__ import annotations

import copy
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List

import numpy as np
import torch

from .common import Threads, make_model, summary, synthetic_imu, tcn_flops_per_sample, time_calls


def bench_inference(p: Dict[str, Any], device: str, seed: int = 0) -> Dict[str, Any]:
    from ..export import export_batch

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

    with torch.no_grad(), Threads(p["threads"]):
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
    from ..export import export_streaming

    n, rate = int(p["samples"]), float(p["rate"])
    rows = []
    with torch.no_grad(), Threads(p["threads"]):
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
