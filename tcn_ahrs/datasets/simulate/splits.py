"""Dataset splits of the simulator (``conf/data/simulated.yaml``)."""
from __future__ import annotations

from typing import Any, Dict, List, Optional


from ...sequence import ImuSequence
from .generate import PROFILES, SPLITS, simulate


# =============================================================================
# Dataset splits (conf/data/simulated.yaml)
# =============================================================================


def _plain(cfg) -> dict:
    """Mapping or OmegaConf DictConfig -> plain dict."""
    from ...config import plain

    return dict(plain(cfg))


def split_plan(data_cfg, split: Optional[str] = None) -> List[Dict[str, Any]]:
    """The recordings ``split`` consists of, as keyword dicts for :func:`simulate` (no data made).

    Recording ``i`` of split part ``p`` gets seed ``splits.p.seed_offset + i`` and profile
    ``splits.p.profiles[i % len(profiles)]``; seed ranges of the parts must be disjoint.
    """
    cfg = _plain(data_cfg)
    src = "conf/data/simulated.yaml"
    split = split or cfg.get("split") or "train"
    if split not in SPLITS:
        raise ValueError(f"{src}: field 'split': expected one of {list(SPLITS)}, got {split!r}")
    parts = cfg.get("splits")
    if not isinstance(parts, dict):
        raise ValueError(f"{src}: field 'splits': expected a mapping with keys train, val, test")
    ranges = {}
    for name, spec in parts.items():
        try:
            off, cnt = int(spec.get("seed_offset", 0)), int(spec["count"])
        except (KeyError, AttributeError, TypeError, ValueError):
            raise ValueError(f"{src}: field 'splits.{name}': expected count (int) and seed_offset (int)") from None
        ranges[name] = (off, off + cnt)
    names = sorted(ranges)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            (a0, a1), (b0, b1) = ranges[a], ranges[b]
            if a0 < b1 and b0 < a1 and a1 > a0 and b1 > b0:
                raise ValueError(f"{src}: fields 'splits.{a}.seed_offset' / 'splits.{b}.seed_offset': seed ranges "
                                 f"[{a0}, {a1}) and [{b0}, {b1}) overlap; splits must use disjoint seeds")
    axes = int(cfg.get("axes", 9))
    rate = float(cfg.get("rate", 100.0))
    device_seed = int(cfg.get("device_seed", 0))
    common = dict(cfg.get("error_params") or {})
    plan = []
    for part in SPLITS[split]:
        if part not in parts:
            raise ValueError(f"{src}: field 'splits.{part}': missing (needed for split {split!r})")
        spec = parts[part]
        profiles = list(spec.get("profiles") or ["slow_rotation"])
        bad = [p for p in profiles if p not in PROFILES]
        if bad:
            raise ValueError(f"{src}: field 'splits.{part}.profiles': unknown {bad}; expected any of {list(PROFILES)}")
        extra = dict(common)
        extra.update(spec.get("error_params") or {})
        off, end = ranges[part]
        for i, seed in enumerate(range(off, end)):
            plan.append(dict(profile=profiles[i % len(profiles)], duration=float(spec.get("duration", 60.0)),
                             rate=rate, seed=seed, axes=axes, device_seed=device_seed,
                             noise_free=bool(spec.get("noise_free", cfg.get("noise_free", False))), **extra))
    return plan


def load_split(data_cfg, split: Optional[str] = None) -> List[ImuSequence]:
    """Generate the recordings of ``split`` (train | val | test | trainval | all) from
    ``data_cfg`` (see ``conf/data/simulated.yaml``). ``trainval`` = train + val recordings,
    ``all`` = train + val + test; every split uses the same device (``device_seed``)."""
    return [simulate(**kw) for kw in split_plan(data_cfg, split)]


def list_recordings(data_cfg) -> List[str]:
    """Names of every recording the config generates (all splits)."""
    return [f"sim_{kw['profile']}_s{kw['seed']:04d}" for kw in split_plan(data_cfg, "all")]
