"""Per-sample step time of the residual model's streaming runtimes in one run, on the same data
and one thread: OnnxStreaming (one onnxruntime session run per sample), ExportedStreaming (the
torch.export program, eager), the TorchScript ResidualStreaming and BackboneStreaming (numba).

    python -m tcn_ahrs.bench.formats [--ckpt checkpoints/broad9_residual.ckpt] [--steps 3000] [--slow-steps 300]

ExportedStreaming runs ~2300 tensor ops eagerly per sample (tens of ms): it is timed on
``--slow-steps`` samples. Exports go to a temporary folder. Prints one row per runtime (median and
mean microseconds per step after a warm-up of 50 steps) and the largest attitude difference of
each to BackboneStreaming on the steps it ran.
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
import warnings
from pathlib import Path
from typing import Callable, Dict, List

import numpy as np
import torch


def _time(step: Callable[[int], np.ndarray], n: int, warm: int = 50):
    for k in range(warm):
        step(k)
    ts, qs = [], []
    for k in range(warm, warm + n):
        t0 = time.perf_counter()
        q = step(k)
        ts.append(time.perf_counter() - t0)
        qs.append(np.asarray(q))
    return ts, np.array(qs)


def step_formats(ckpt: str = "checkpoints/broad9_residual.ckpt", steps: int = 3000, slow_steps: int = 300,
                 seed: int = 0) -> List[Dict]:
    """The rows (see the module docstring)."""
    import logging

    from ..checkpoint import model_from_checkpoint
    from ..datasets.simulate import simulate
    from ..export import _script, build_metadata
    from ..export.backbone import ResidualStreaming
    from ..export.onnx_step import OnnxStreaming, export_onnx
    from ..export.program import ExportedStreaming, export_program
    from ..streaming import BackboneStreaming

    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    logging.disable(logging.WARNING)
    model = model_from_checkpoint(ckpt).eval()
    axes = int(model.axes)
    rate = float(getattr(model, "trained_rate_hz", None) or 100.0)
    n = steps + 50
    seq = simulate("walking", n / rate + 1.0, rate, seed=seed, axes=axes)
    imu = np.concatenate([seq.gyro, seq.accel] + ([seq.mag] if axes == 9 else []), 1)[:n]
    dt = np.full(n, 1.0 / rate)
    q0 = seq.quat[0]
    with tempfile.TemporaryDirectory() as tmp:
        onnx_path = export_onnx(ckpt, Path(tmp) / "m.onnx", mode="streaming")["streaming"]
        pt2_path = export_program(ckpt, Path(tmp) / "m.pt2", mode="streaming")["streaming"]
        runtimes = {"OnnxStreaming (onnxruntime, 1 thread)": (OnnxStreaming(onnx_path, threads=1), steps),
                    "ExportedStreaming (torch.export, eager)": (ExportedStreaming(pt2_path), slow_steps)}
        ts = _script(ResidualStreaming(model, build_metadata(model, "streaming", {})))
        ref = BackboneStreaming(model)
        rows, ref_q = [], None
        xt = [torch.from_numpy(imu[k]) for k in range(n)]

        def ts_step(k):
            return ts.step(xt[k], float(dt[k]))[0]

        order = [("BackboneStreaming (numba)", ref, steps), ("ResidualStreaming (TorchScript)", ts, steps)]
        order += [(name, rt, m) for name, (rt, m) in runtimes.items()]
        for name, rt, m in order:
            rt.reset(q0) if not isinstance(rt, torch.jit.ScriptModule) else rt.reset(torch.from_numpy(q0))
            fn = ts_step if rt is ts else (lambda k, rt=rt: rt.step(imu[k], dt[k])[0])
            times, qs = _time(fn, m)
            if ref_q is None:
                ref_q = qs
            d = np.minimum(np.linalg.norm(qs - ref_q[:m], axis=-1), np.linalg.norm(qs + ref_q[:m], axis=-1))
            rows.append({"runtime": name, "steps": m, "median_us": 1e6 * statistics.median(times),
                         "mean_us": 1e6 * statistics.fmean(times),
                         "max_angle_to_numba_rad": float((4 * np.arcsin(np.clip(d / 2, 0, 1))).max())})
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ckpt", default="checkpoints/broad9_residual.ckpt")
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--slow-steps", type=int, default=300)
    a = ap.parse_args(argv)
    import platform

    import onnxruntime

    print(f"{a.ckpt}: torch {torch.__version__}, onnxruntime {onnxruntime.__version__}, {platform.processor() or platform.machine()}, 1 thread")
    for r in step_formats(a.ckpt, a.steps, a.slow_steps):
        print(f"{r['runtime']:42s} {r['steps']:6d} steps  median {r['median_us']:10.1f} us  mean {r['mean_us']:10.1f} us"
              f"  max angle to numba {r['max_angle_to_numba_rad']:.1e} rad")


if __name__ == "__main__":
    main()
