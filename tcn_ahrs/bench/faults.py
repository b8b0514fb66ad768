"""The fault table: sensor faults a deployed AHRS meets, injected into simulated recordings,
each run through the backbone with its health checks (``now``), the same backbone with them off
(``before``: frozen_time, the clip floors and gap_factor 0), VQF and the default learned model.

``python scripts/benchmark.py faults [faults.seeds=[0,1,2]] [faults.ckpt=checkpoints/general9_residual.ckpt]``
writes ``faults.json`` / ``faults.md`` (out=DIR, default runs/benchmark/faults). Per case: which
flag the filter raised and on what share of the faulty samples, and the total attitude error
(degrees, no alignment: the filters start from the ground truth) during the fault and 10-20 s
after it, and the heading error 10-20 s after (the recovery), each the mean over the seeds.

Recordings: the simulator's walking profile, 60 s at 100 Hz, 9 axes, a clean magnetometer (no
hard iron, no disturbances: the recovery measured is the filters', not the field's acceptance),
the fault at 20 s. (A clipped gyro needs faster motion than walking reaches below the smallest
common range: tests/test_health.py clips the fast-rotation profile.)
"""
from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Any, Callable, Dict, Mapping, Optional, Tuple

import numpy as np

RATE, DURATION, START = 100.0, 60.0, 20.0
CLEAN_MAG = dict(hard_iron_std_ut=0.0, hard_iron_repeatability_ut=0.0, mag_disturbances_per_minute=0.0)
OFF = dict(frozen_time=0.0, gyro_clip_floor=0.0, acc_clip_floor=0.0, gap_factor=0.0)  # "before"


def _frozen(attr: str, seconds: float):
    def inject(seq, k0):
        k1 = k0 + int(seconds * RATE)
        arr = getattr(seq, attr).copy()
        arr[k0:k1] = arr[k0]
        return dataclasses.replace(seq, **{attr: arr}), slice(k0, k1), k1
    return inject


def _zeros(seconds: float):
    def inject(seq, k0):
        k1 = k0 + int(seconds * RATE)
        arrays = {a: getattr(seq, a).copy() for a in ("gyro", "accel", "mag")}
        for arr in arrays.values():
            arr[k0:k1] = 0.0
        return dataclasses.replace(seq, **arrays), slice(k0, k1), k1
    return inject


def _gap(seconds: float):
    def inject(seq, k0):
        n = int(round(seconds * RATE))
        keep = np.r_[0:k0, k0 + n:len(seq)]
        names = ("time", "gyro", "accel", "mag", "quat", "quat_valid", "score_mask")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # the loader's gap warning
            out = dataclasses.replace(seq, **{a: getattr(seq, a)[keep] for a in names if getattr(seq, a) is not None})
        return out, slice(k0, k0 + 1), k0
    return inject


# case -> (injector, the flag that should name it); an injector returns the faulty recording, its
# faulty samples (a slice or a mask) and where the fault ends (the recovery is read after it)
CASES: Dict[str, Tuple[Callable, str]] = {
    "gyro frozen 5 s": (_frozen("gyro", 5.0), "gyro_frozen"),
    "accelerometer frozen 5 s": (_frozen("accel", 5.0), "acc_frozen"),
    "all sensors read zero for 2 s": (_zeros(2.0), "gyro_frozen"),
    "0.5 s of samples lost (gap)": (_gap(0.5), "gap"),
    "0.9 s of samples lost (gap)": (_gap(0.9), "gap"),
}


def _errors(seq, quat, window, end) -> Dict[str, float]:
    from ..metrics import broad_error_angles

    angles = broad_error_angles(seq.quat, np.asarray(quat))
    total, heading = np.degrees(angles["total"]), np.degrees(np.abs(angles["heading"]))
    after = slice(end + int(10 * RATE), min(end + int(20 * RATE), len(seq)))
    nan = float("nan")
    return {"during": float(total[window].mean()),
            "after": float(total[after].mean()) if after.start < len(seq) else nan,
            "heading_after": float(heading[after].mean()) if after.start < len(seq) else nan}


def fault_table(seeds=(0, 1, 2), ckpt: Optional[str] = "checkpoints/general9_residual.ckpt") -> Dict[str, Any]:
    from ..datasets.simulate import simulate
    from ..estimators.registry import build
    from ..filters import backbone as bb

    learned = None
    if ckpt and Path(ckpt).is_file():
        from ..estimators.learned import LearnedEstimator

        learned = LearnedEstimator(ckpt, name=Path(ckpt).stem)
    methods = ["before", "now", "vqf"] + ([learned.name] if learned else [])
    rows: Dict[str, Any] = {}
    for case, (inject, flag) in CASES.items():
        per: Dict[str, list] = {m: [] for m in methods}
        flagged = []
        for seed in seeds:
            clean = simulate("walking", DURATION, RATE, seed=seed, device_seed=seed + 1, **CLEAN_MAG)
            seq, window, end = inject(clean, int(START * RATE))
            q0 = seq.quat[0]
            out = bb.run(seq.gyro, seq.accel, seq.mag, seq.dt, bb.BackboneParams(), q0=q0)
            flagged.append(float(out[flag][window].mean()))
            off = bb.run(seq.gyro, seq.accel, seq.mag, seq.dt, bb.BackboneParams(**OFF), q0=q0)
            quats = {"before": off["quat"], "now": out["quat"], "vqf": build("vqf", 9).run(seq, q0, 0).quat}
            if learned:
                quats[learned.name] = learned.run(seq, q0, 0).quat
            for m in methods:
                per[m].append(_errors(seq, quats[m], window, end))
        rows[case] = {"flag": flag, "flagged_share": float(np.mean(flagged)),
                      "errors": {m: {k: float(np.mean([e[k] for e in v])) for k in v[0]} for m, v in per.items()}}
    return {"rows": rows, "methods": methods, "seeds": list(seeds), "recording": "simulated walking, "
            f"{DURATION:g} s at {RATE:g} Hz, clean magnetometer, fault at {START:g} s"}


def markdown(result: Mapping[str, Any]) -> str:
    methods = result["methods"]
    lines = [f"{result['recording']}; mean over seeds {result['seeds']}; total attitude error during / "
             "10-20 s after the fault (heading error 10-20 s after), degrees.", "",
             "| fault | flag (share of faulty samples) | " + " | ".join(methods) + " |",
             "|---" * (len(methods) + 2) + "|"]
    for case, row in result["rows"].items():
        cells = [f"{e['during']:.1f} / {e['after']:.1f} ({e['heading_after']:.1f})"
                 for e in (row["errors"][m] for m in methods)]
        lines.append(f"| {case} | `{row['flag']}` ({100 * row['flagged_share']:.0f} %) | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def faults_main(cfg) -> Dict[str, Any]:
    """``scripts/benchmark.py faults``: ``faults.seeds``, ``faults.ckpt`` (null: no learned column)."""
    from omegaconf import OmegaConf

    from ..experiments.transfer import write_result

    f = OmegaConf.to_container(cfg.faults, resolve=True)  # defaults: tcn_ahrs/config/scripts.py FaultsSection
    result = fault_table(tuple(f["seeds"]), f["ckpt"])
    md = markdown(result)
    print(md)
    write_result(Path(cfg.get("out") or "runs/benchmark/faults"), "faults", result, md)
    return result
