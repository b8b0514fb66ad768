"""The speed benchmark's ``speed:`` section (``python scripts/benchmark.py speed``; tcn_ahrs/bench/)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional


@dataclass
class SpeedTrain:
    """closed: the shipped recipe's step (experiment=broad9_closed_loop: 32 streams x 1000-sample chunks,
    truncated backpropagation through the closed loop, 12 epochs); paper: the open-loop model on
    16 x 3000 windows, 1800 epochs (model=paper)."""
    model: str = "closed"
    axes: int = 9
    window: int = 1000
    batch_size: int = 32
    stride: int = 500             # window-start spacing; epoch = all starts (tcn_ahrs.data.window_starts)
    epochs: int = 12              # the shipped CPU schedule (checkpoints/closed_loop/broad9.md)
    rate: float = 285.71          # BROAD sampling rate, Hz (synthetic data)
    variants_cpu: List[str] = field(default_factory=lambda: ["eager", "tensor_scan", "threads1", "bf16", "compile"])
    # model=paper also: loss_fp32 (CPU); fp32, tf32, cuda_graphs (CUDA)
    variants_cuda: List[str] = field(default_factory=lambda: ["eager", "bf16", "compile"])
    warmup: int = 1               # untimed steps per variant (compile: + its compile call)
    steps: int = 3                # timed steps per variant (at least 1) ...
    max_seconds: float = 25.0     # ... unless this many seconds of timed steps passed
    compile_timeout_s: int = 300  # hard bound on the compile subprocess
    # loss curves checked against the first variant's
    curve_variants: List[str] = field(default_factory=lambda: ["bf16"])
    curve_steps: int = 10
    threads: Optional[int] = None  # torch threads (None: torch's default = all cores)
    data_config: Optional[str] = "conf/data/broad.yaml"  # for the exact epoch size; None: constant
    split_samples: int = 601_181   # fallback: 16 trials x 70 % x ~190 s x 285.7 Hz
    split_recordings: int = 16


@dataclass
class SpeedInference:
    """One minute of 100 Hz data through the shipped model."""
    samples: int = 6000
    rate: float = 100.0
    warmup: int = 3
    repeats: int = 20
    max_seconds: float = 10.0
    threads: int = 1
    ckpt: str = "checkpoints/closed_loop/broad9.ckpt"
    goal_ms: float = 15.0


@dataclass
class SpeedStreaming:
    """Per-sample latency of the streaming modules."""
    axes: List[int] = field(default_factory=lambda: [9, 6])
    samples: int = 3000
    warmup: int = 300
    rate: float = 100.0
    threads: int = 1
    chunk: int = 100
    ckpts: Dict[str, str] = field(default_factory=lambda: {"9": "checkpoints/closed_loop/broad9.ckpt",
                                                           "6": "checkpoints/closed_loop/tumvi6.ckpt"})
    riann: bool = True
    goal_samples_per_s: float = 25_000.0
    goal_chunk_samples_per_s: float = 1_000_000.0


@dataclass
class SpeedFilters:
    """The project's batched filters beside VQF and imufusion."""
    samples: int = 6000
    rate: float = 100.0
    batches: List[int] = field(default_factory=lambda: [1, 64])
    repeats: int = 1
    threads: int = 1
    filters: List[str] = field(default_factory=lambda: ["ecf", "mahony", "madgwick", "eskf"])
    peers: List[str] = field(default_factory=lambda: ["vqf", "imufusion"])


@dataclass
class SpeedDeploy:
    """Every runtime of a shipped residual checkpoint side by side (C, ONNX, torch.export,
    TorchScript, numba) beside VQF's C++ and RIANN; the footprint of every shipped checkpoint."""
    ckpt: str = "checkpoints/broad9_residual.ckpt"
    rate: float = 285.71          # Hz of the simulated samples (BROAD's rate: the checkpoint's own)
    samples: int = 3000           # timed steps (single calls) per runtime; loops run the whole recording
    warmup: int = 200
    slow_steps: int = 300         # ONNX steps timed (~1 ms each); torch.export: a tenth of these
    c: bool = True                # the C runtime (needs a C compiler)
    onnx: bool = True             # needs the [deploy] extra
    export: bool = True           # torch.export (slow: ~10 ms a step)
    aoti: bool = True             # the torch.export step compiled by AOTInductor (~40 s; a C++ compiler)
    footprint_glob: str = "checkpoints/*.ckpt,checkpoints/residual/*.ckpt"  # comma-separated globs
    # more checkpoints whose C loop is timed in the same run, beside VQF's C++ loop of the same
    # axes: networks on (residual/oxiod9: ckpt's broad9 runs as the backbone alone, its networks off) and small
    # and the tuned ECF files tcn-ahrs search shipped (C, ONNX and torch.export too)
    c_models: List[str] = field(default_factory=lambda: ["checkpoints/residual/oxiod9.ckpt",
                                                         "checkpoints/euroc6_residual_small.ckpt", "checkpoints/oxiod9_ecf.json",
                                                         "checkpoints/tumvi6_ecf.json"])


@dataclass
class SpeedConfig:
    """``speed:``."""
    sections: List[str] = field(default_factory=lambda: ["train", "inference", "streaming", "filters", "deploy"])
    seed: int = 0
    train: SpeedTrain = field(default_factory=SpeedTrain)
    inference: SpeedInference = field(default_factory=SpeedInference)
    streaming: SpeedStreaming = field(default_factory=SpeedStreaming)
    filters: SpeedFilters = field(default_factory=SpeedFilters)
    deploy: SpeedDeploy = field(default_factory=SpeedDeploy)


#: quick=true: the sizes of a smoke run (over the defaults)
SPEED_QUICK: Dict[str, Any] = {
    "train": {"window": 256, "batch_size": 2, "variants_cpu": ["eager", "bf16"],
              "variants_cuda": ["eager", "bf16"], "warmup": 1, "steps": 1, "curve_steps": 2, "data_config": None},
    "inference": {"samples": 600, "warmup": 1, "repeats": 2},
    "streaming": {"axes": [9], "samples": 100, "warmup": 10, "chunk": 10},
    "filters": {"samples": 200, "batches": [1, 4]},
    "deploy": {"samples": 50, "warmup": 5, "slow_steps": 5, "onnx": False, "export": False, "aoti": False,
               "footprint_glob": "checkpoints/broad9_residual.ckpt"},
}
