"""Speed benchmark: GPU/CPU training throughput, batch inference, streaming latency, filters.

``python scripts/benchmark.py speed [device=cpu|cuda] [quick=true] [out=DIR] [speed.KEY=VALUE ...]``
(or, without the dispatcher, ``python -m tcn_ahrs.bench [same arguments]``).

Sections (each one table, with ratios against the thing it should be compared with):

* ``train``     — the shipped recipe's training step (``model: closed``, experiment=broad9_closed_loop:
  32 streams x 1000-sample chunks after the networks' context, the closed loop as tensor ops,
  attitude loss, backward, AdamW) in IMU samples/s, with the wall time of one epoch and of the
  12-epoch schedule on the BROAD training split (exact window count from ``load_split`` when the
  data are there, else a constant; the result says which). CPU variants ``eager`` (the recipe,
  all cores) / ``threads1`` / ``bf16`` (networks under bfloat16 autocast) / ``compile`` (the
  networks through torch.compile, in a subprocess with a timeout), and the loss curves of
  ``curve_variants`` against ``eager`` from the same weights and batches. ``model: paper``
  times the paper's open-loop model (16 x 3000 windows, increment loss; CUDA fp32 / tf32 /
  cuda_graphs).
* ``inference`` — one minute of 100 Hz 9-axis data (6000 samples) through the shipped model
  (``checkpoints/closed_loop/broad9.ckpt``): evaluation's path (``LearnedAHRS.run_sequence``, the loop
  compiled by numba), the exported TorchScript batch and streaming modules, the numba
  :class:`~tcn_ahrs.streaming.CompiledStreaming`, the networks alone with their GFLOP/s next to
  this core's measured matrix-product peak, and the loop as tensor ops for the ratio; 1 CPU
  thread. Goal <= 15 ms.
* ``streaming`` — per-sample latency (median, p99) of ``step`` and per-sample cost of
  ``step_chunk`` (``chunk`` samples per call) of the exported module and of
  ``CompiledStreaming``, 9- and 6-axis shipped models, beside RIANN's ``predict_step``.
  Goals >= 25 k samples/s and faster than RIANN per sample, >= 1 M samples/s chunked.
* ``filters``   — samples/s of the project's batched ECF / Mahony / ES-EKF on one recording
  and on ``batch`` parameter sets at once (aggregate), next to VQF and imufusion on the same
  simulated recording. Goal: batched aggregate >= VQF's single-recording rate.

Timings are wall-clock (``time.perf_counter``; CUDA synchronised), so on a shared machine
they are noisy: the result records the load average before and after.
"""
from __future__ import annotations

import json
import os
import time
import warnings
from pathlib import Path
from typing import Any, Dict, Mapping, Optional


from .common import environment, synthetic_imu
from .config import DEFAULTS, QUICK, resolve_config
from .filters import bench_filters
from .inference import bench_inference, bench_streaming
from .report import to_markdown
from .training import bench_train, broad_epoch, static_increment_loss, train_variant

__all__ = ["main", "resolve_config", "DEFAULTS", "QUICK", "broad_epoch", "static_increment_loss",
           "synthetic_imu", "train_variant"]


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
            elif section == "deploy":
                from .deploy import bench_deploy

                res["deploy"] = bench_deploy(p["deploy"], seed)
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
