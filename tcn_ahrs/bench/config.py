"""Settings of the speed benchmark: defaults, the quick sizes, and their validation."""
from __future__ import annotations

import copy
from typing import Any, Dict, Mapping, Optional

import torch

from ..config import defaults
from ..config.speed import SPEED_QUICK, SpeedConfig

# the defaults and their meaning: tcn_ahrs/config/speed.py (one place)
DEFAULTS: Dict[str, Any] = defaults(SpeedConfig)

QUICK: Dict[str, Any] = SPEED_QUICK

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


SECTIONS = ("train", "inference", "streaming", "filters", "deploy")


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
    bad = set(p["sections"]) - set(SECTIONS)
    if bad:
        raise ValueError(f"benchmark config: speed.sections: unknown {sorted(bad)}; "
                         f"expected a subset of [{', '.join(SECTIONS)}]")
    if p["device"] not in ("cpu", "cuda"):
        raise ValueError(f"benchmark config: device={p['device']!r}; expected 'cpu' or 'cuda'")
    if p["device"] == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"benchmark config: device=cuda but torch.cuda.is_available() is False "
                         f"(torch {torch.__version__}); run with device=cpu")
    return p


# ------------------------------------------------------------------------ environment
