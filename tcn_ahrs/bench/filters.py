"""Speed of the classical filters (registry, batched parameter sets) next to VQF and imufusion."""
from __future__ import annotations

from typing import Any, Dict, List

import torch

from ..filters import compiled
from .common import Threads, summary, time_calls

COMPILED = ("ecf", "mahony", "madgwick", "eskf", "robust_eskf")  # registry names with a numba loop


def bench_filters(p: Dict[str, Any], device: str, seed: int = 0) -> Dict[str, Any]:
    """Samples/s of registered classical filters (``p["filters"]``, registry names) on one
    recording: batch b = b parameter sets of the first ``default_grid`` parameter, spread over
    its grid range, in one ``quat_batch`` call (the path of evaluation and tuning; on the CPU in
    float64 the compiled loops of :mod:`tcn_ahrs.filters.compiled` when numba is installed, their
    parameter sets in numba's threads). Each row also gives the torch loop's speed (``torch_*``)
    measured in the same run, so the ratio is on one machine and load."""
    from ..datasets.simulate import simulate
    from ..estimators import registry

    n, rate = int(p["samples"]), float(p["rate"])
    batches = [int(b) for b in p["batches"]]
    seq = simulate("walking", duration=(n - 1) / rate, rate=rate, seed=seed, axes=9)
    rows = []
    devices = ["cpu"] + (["cuda"] if device == "cuda" else [])
    with Threads(p["threads"]):
        th = torch.get_num_threads()
        for dev in devices:
            for name in p["filters"]:
                if name not in registry.methods("classical"):
                    raise ValueError(f"speed.filters.filters: unknown filter {name!r}; expected one of "
                                     f"{list(registry.methods('classical'))}")
                est = registry.build(name, 9, device=dev)
                key, values = next(iter(type(est).default_grid.items()))
                lo, hi = float(min(values)), float(max(values))
                for b in batches:
                    val = (torch.linspace(lo, hi, b, dtype=torch.float64, device=dev)[:, None] if b > 1
                           else (lo + hi) / 2)
                    call = lambda: est.quat_batch([seq], [None], {key: val})  # noqa: E731
                    ts = time_calls(call, 1, int(p["repeats"]), dev)  # warm-up: numba's JIT / cache load
                    s = summary(ts)
                    row = {"name": f"tcn_ahrs.filters.{name}", "device": dev, "batch": b, "threads": th,
                           "seconds": s["median_s"], "samples_per_s": b * n / s["median_s"],
                           "per_recording_samples_per_s": n / s["median_s"],
                           "loop": "numba" if (dev == "cpu" and compiled.available() and name in COMPILED) else "torch"}
                    if row["loop"] == "numba":
                        with compiled.torch_loops():
                            t_torch = summary(time_calls(call, 0, int(p["repeats"]), dev))["median_s"]
                        row["torch_samples_per_s"] = b * n / t_torch
                        row["vs_torch_loop"] = t_torch / s["median_s"]
                    rows.append(row)
        rows.extend(_peer_filter_rows(p, seq))
    vqf = next((r for r in rows if r["name"].startswith("vqf") and "samples_per_s" in r), None)
    for r in rows:
        if vqf and "samples_per_s" in r:
            r["vs_vqf"] = r["samples_per_s"] / vqf["samples_per_s"]
    batched = [r for r in rows if r.get("batch", 1) > 1 and r["device"] == "cpu" and "samples_per_s" in r]
    goal = {r["name"]: bool(vqf and r["samples_per_s"] >= vqf["samples_per_s"]) for r in batched}
    return {"samples": n, "rate_hz": rate, "batches": batches, "recording": seq.name, "rows": rows,
            "goal_met": goal if vqf else None}


def _peer_filter_rows(p, seq) -> List[Dict[str, Any]]:
    from ..estimators import registry

    rows = []
    for key in p["peers"]:
        try:
            est = registry.build(key, 9)
        except Exception as e:  # noqa: BLE001
            rows.append({"name": f"{key} (9D)", "device": "cpu", "batch": 1,
                         "skipped": f"unavailable: {type(e).__name__}: {e}"})
            continue
        est.run(seq)  # warm-up (imports, first-call allocations)
        ts = time_calls(lambda: est.run(seq), 0, int(p["repeats"]))
        s = summary(ts)
        rows.append({"name": f"{key} (9D, {est.name} wrapper)", "device": "cpu", "batch": 1, "threads": 1,
                     "seconds": s["median_s"], "samples_per_s": len(seq) / s["median_s"],
                     "per_recording_samples_per_s": len(seq) / s["median_s"]})
    return rows


# ============================================================================= report
