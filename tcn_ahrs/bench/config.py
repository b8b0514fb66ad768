"""Settings of the speed benchmark: defaults, the quick sizes, and their validation."""
from __future__ import annotations

import copy
from typing import Any, Dict, Mapping, Optional

import torch



DEFAULTS: Dict[str, Any] = {
    "sections": ["train", "inference", "streaming", "filters"],
    "seed": 0,
    "train": {
        # closed: the shipped recipe's step (experiment=broad9_cl: 32 streams x 1000-sample chunks
        # after the networks' context, truncated backpropagation through the closed loop, 12
        # epochs); paper: the open-loop model on 16 x 3000 windows, 1800 epochs (model=paper)
        "model": "closed",
        "axes": 9,
        "window": 1000,
        "batch_size": 32,
        "stride": 500,             # window-start spacing; epoch = all starts (tcn_ahrs.data.window_starts)
        "epochs": 12,              # the shipped CPU schedule (checkpoints/closed_loop/broad9.md)
        "rate": 285.71,            # BROAD sampling rate, Hz (synthetic data)
        "variants_cpu": ["eager", "tensor_scan", "threads1", "bf16", "compile"],
        # model=paper also: loss_fp32 (CPU); fp32, tf32, cuda_graphs (CUDA)
        "variants_cuda": ["eager", "bf16", "compile"],
        "warmup": 1,               # untimed steps per variant (compile: + its compile call)
        "steps": 3,                # timed steps per variant (at least 1) ...
        "max_seconds": 25.0,       # ... unless this many seconds of timed steps passed
        "compile_timeout_s": 300,  # hard bound on the compile subprocess
        "curve_variants": ["bf16"],  # loss curves checked against the first variant's
        "curve_steps": 10,
        "threads": None,           # torch threads (None: torch's default = all cores)
        "data_config": "conf/data/broad.yaml",  # for the exact epoch size; None: constant
        "split_samples": 601_181,  # fallback: 16 trials x 70 % x ~190 s x 285.7 Hz
        "split_recordings": 16,
    },
    # the shipped checkpoints (default architecture with synthetic weights where one is missing)
    "inference": {"samples": 6000, "rate": 100.0, "warmup": 3, "repeats": 20, "max_seconds": 10.0, "threads": 1,
                  "ckpt": "checkpoints/closed_loop/broad9.ckpt", "goal_ms": 15.0},
    "streaming": {"axes": [9, 6], "samples": 3000, "warmup": 300, "rate": 100.0, "threads": 1, "chunk": 100,
                  "ckpts": {"9": "checkpoints/closed_loop/broad9.ckpt", "6": "checkpoints/closed_loop/tumvi6.ckpt"}, "riann": True,
                  "goal_samples_per_s": 25_000.0, "goal_chunk_samples_per_s": 1_000_000.0},
    "filters": {"samples": 6000, "rate": 100.0, "batches": [1, 64], "repeats": 1, "threads": 1,
                "filters": ["ecf", "mahony", "madgwick", "eskf"], "peers": ["vqf", "imufusion"]},
}

QUICK: Dict[str, Any] = {
    "train": {"window": 256, "batch_size": 2, "variants_cpu": ["eager", "bf16"],
              "variants_cuda": ["eager", "bf16"], "warmup": 1, "steps": 1, "curve_steps": 2, "data_config": None},
    "inference": {"samples": 600, "warmup": 1, "repeats": 2},
    "streaming": {"axes": [9], "samples": 100, "warmup": 10, "chunk": 10},
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
