"""What every section of the speed benchmark shares: timing, environment, threads, the model and
synthetic data."""
from __future__ import annotations

import math
import os
import platform
import statistics
import subprocess
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional

import numpy as np
import torch
from torch import Tensor

from .. import so3


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
        "date": time.strftime("%Y-%m-%d"),
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
def sync(device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def time_calls(fn: Callable[[], Any], warmup: int, repeats: int, device="cpu",
               max_seconds: Optional[float] = None) -> List[float]:
    """Seconds per call of ``fn`` after ``warmup`` untimed calls: ``repeats`` calls, or fewer
    (at least one) once ``max_seconds`` of timed calls passed."""
    for _ in range(warmup):
        fn()
    sync(device)
    out: List[float] = []
    start = time.perf_counter()
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        fn()
        sync(device)
        out.append(time.perf_counter() - t)
        if max_seconds is not None and time.perf_counter() - start > max_seconds:
            break
    return out


def summary(seconds: List[float]) -> Dict[str, float]:
    s = sorted(seconds)
    p99 = s[min(len(s) - 1, int(math.ceil(0.99 * len(s))) - 1)]
    return {"median_s": statistics.median(s), "mean_s": statistics.fmean(s), "p99_s": p99,
            "min_s": s[0], "n": len(s)}


class Threads:
    """``with Threads(n):`` torch.set_num_threads(n) inside, restored after (None: unchanged)."""

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
    """The paper's open-loop model (:data:`tcn_ahrs.config.model.PAPER_MODEL`: 16-32-64-128 TCNs,
    open-loop ECF) for ``axes`` 9 or 6 — the training section's model."""
    from ..config.model import PAPER_MODEL

    cfg = {**PAPER_MODEL, "variant": f"ahrs{axes}", "axes": axes}
    if axes == 6:
        cfg.update(mag_net="none", use_mag_term=False)
    return cfg


def shipped_config(axes: int) -> Dict[str, Any]:
    """The default model of ``conf/model/ahrs.yaml`` (the learned closed loop) for ``axes``."""
    from omegaconf import OmegaConf

    from ..config import conf_path

    cfg = OmegaConf.load(conf_path("model", "ahrs.yaml"))
    cfg = OmegaConf.to_container(OmegaConf.merge(cfg, {"axes": axes, "variant": f"ahrs{axes}"}), resolve=True)
    cfg.pop("defaults", None)
    if axes == 6:
        cfg.update(mag_net="none", use_mag_term=False)
    return cfg


def make_model(axes: int, seed: int = 0, rate: float = 100.0):
    """An eval-mode :class:`LearnedAHRS` of the default architecture (:func:`shipped_config`)
    with non-trivial weights (BN statistics, output layers, gains) and input statistics: the
    same compute as a trained model. The rest window is set for ``rate`` Hz."""
    from ..model.ahrs import LearnedAHRS

    torch.manual_seed(seed)
    model = LearnedAHRS.from_config(shipped_config(axes))
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
    if model.closed is not None:
        model.closed.set_rate(rate)
    return model.eval()


def gemm_peak_gflops(n: int = 1024, repeats: int = 5) -> float:
    """This core's practical float32 peak: GFLOP/s of an n x n x n matrix product (the best of
    ``repeats``), at the caller's torch thread count."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    torch.mm(a, b)
    best = min(time_calls(lambda: torch.mm(a, b), 0, repeats))
    return 2.0 * n ** 3 / best / 1e9


def tcn_flops_per_sample(model) -> int:
    """Multiply-adds x 2 of the calibration TCNs per sample (convolutions only)."""
    total = 0
    for mod in model.modules():
        if isinstance(mod, torch.nn.Conv1d):
            total += 2 * mod.in_channels * mod.out_channels * mod.kernel_size[0] // mod.groups
    return total


def footprint(model) -> Dict[str, int]:
    """What a model costs on a device: trainable ``parameters``, ``weight_bytes`` (float32),
    the streaming runtime's ``state_floats`` (the networks' ring buffers, float32, plus the
    filter's state, float64) and ``state_bytes``, and ``flops_per_sample`` of the networks
    (:func:`tcn_flops_per_sample`; the filter's few hundred operations not counted)."""
    params = int(sum(p.numel() for p in model.parameters()))
    ring = filt = 0
    if getattr(model, "backbone", None) is not None:
        from ..export.backbone import ResidualStreaming
        from ..kernels import backbone as K

        s = ResidualStreaming(model.eval(), {})
        ring, filt = int(sum(b.numel() for b in s.ring_buffers)), int(K.N_STATE)
    return {"parameters": params, "weight_bytes": 4 * params, "state_floats": ring + filt,
            "state_bytes": 4 * ring + 8 * filt, "flops_per_sample": int(tcn_flops_per_sample(model))}


# ============================================================================ training
