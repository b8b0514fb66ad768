"""Settings of the speed benchmark: defaults, the quick sizes, and their validation."""
from __future__ import annotations

import copy
from typing import Any, Dict, Mapping, Optional

import torch



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
                "filters": ["ecf", "mahony", "madgwick", "eskf"], "peers": ["vqf", "imufusion"]},
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
