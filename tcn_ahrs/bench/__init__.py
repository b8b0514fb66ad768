"""Speed benchmark: GPU/CPU training throughput, batch inference, streaming latency, filters.

``python scripts/benchmark.py speed [device=cpu|cuda] [quick=true] [out=DIR] [speed.KEY=VALUE ...]``
(or, without the dispatcher, ``python -m tcn_ahrs.bench [same arguments]``).

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
