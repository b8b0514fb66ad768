"""The cross-dataset matrix: every checkpoint on every dataset it can read, on recordings it never
saw, beside the backbone and the classical filters on the same recordings
(``python scripts/benchmark.py transfer``).

Which recordings a cell holds: on another dataset, all of that dataset's training recordings,
whole (``trainval``: none was seen by the checkpoint; its test recordings where it lists no
training ones); on the checkpoint's own dataset, its
visible test recordings (``test``) when ``../shared`` has any, else the cell is left out (the
checkpoint saw those recordings: its own folds are the crossval tables); on the simulator, its
test split. A 6-axis checkpoint reads every dataset (without the magnetometer), a 9-axis one only
those with a magnetometer.

Each cell reports the learned model's mean AAE and inclination, the same for the backbone and the
best classical filter (the lowest mean AAE among ``baselines``), and ``never_worse``: learned ≤
best classical in both. Output: ``transfer.json`` and ``transfer.md`` in ``out``.
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence

from .. import verdict
from ..checkpoint import checkpoint_meta, load_checkpoint
from ..config import conf_path
from ..estimators import registry
from ..estimators.families import is_estimator_file, load_estimator, read_estimator
from ..evaluate.runner import evaluate, jsonable

DATASETS = ("broad", "euroc", "tumvi", "oxiod", "iphone5", "iphone4s", "simulated")
BASELINES = ("raw", "backbone", "vqf", "ecf", "mahony", "madgwick")
METRICS = ("aae_deg", "inclination_deg")


def write_result(out: Optional[Path], stem: str, result: Mapping[str, Any], md: str) -> None:
    """``<stem>.json`` and ``<stem>.md`` in ``out`` (created; nothing written when None)."""
    if out is None:
        return
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps(jsonable(result), indent=1))
    (out / f"{stem}.md").write_text(md)


def cell_recordings(data_cfg: Mapping, own: bool) -> Optional[str]:
    """The split a checkpoint is scored on: ``test`` on its own dataset (None when empty), the
    simulator's ``test``, another dataset's ``trainval``."""
    name = str(data_cfg["name"])
    if name == "simulated":
        return "test"
    if own:
        return "test" if list(data_cfg.get("test") or []) else None
    # a device whose every recording is a test recording (the iPhone 4S: one user) is read there
    return "trainval" if list(data_cfg.get("train") or []) else "test"


def own_datasets(data_name: str) -> List[str]:
    """The datasets a checkpoint trained on: its data's ``parts`` (``conf/data/general6.yaml``)
    or its data alone."""
    from omegaconf import OmegaConf

    p = conf_path("data", f"{data_name}.yaml")
    if p.is_file():
        parts = (OmegaConf.to_container(OmegaConf.load(p), resolve=False) or {}).get("defaults") or []
        names = [str(d).split("@")[0] for d in parts if isinstance(d, str) and "@parts." in d]
        if names:
            return names
    return [data_name]


def shipped_meta(path: str) -> Dict[str, Any]:
    """``axes`` and ``data`` (the dataset it was chosen or trained on) of a shipped model: a learned
    checkpoint or a classical estimator file written by ``tcn-ahrs search``."""
    if is_estimator_file(path):
        doc = read_estimator(path)
        family = f"{doc['family']} ({'tuned' if doc.get('knobs') else 'defaults'}{', calibrated' if doc.get('calibration') else ''})"
        return {"axes": int(doc["axes"]), "data": str((doc.get("provenance") or {}).get("dataset", "")),
                "family": family}
    from ..checkpoint import networks_off

    meta = checkpoint_meta(load_checkpoint(path), path)
    loop = str(meta["model"].get("loop", "open"))
    family = {"backbone": "learned residual", "closed": "learned closed loop"}.get(loop, "learned open loop")
    if networks_off(path):  # called what it runs as: the classical filter its knobs leave
        family = "backbone, tuned knobs (networks off)"
    return {"axes": int(meta["layout"]["axes"]), "data": str(meta.get("data", "")), "family": family}


def shipped_paths(folder: Path = Path("checkpoints")) -> Dict[str, str]:
    """Every shipped model in ``folder``: ``*.ckpt`` (learned) and ``*.json`` (a classical family
    chosen by the search), by name."""
    return {p.stem: str(p) for p in sorted([*folder.glob("*.ckpt"), *folder.glob("*.json")])}


def score_cell(ckpt: str, label: str, seqs, axes: int, baselines: Sequence[str]) -> Dict[str, Any]:
    """One cell: the shipped model and the baselines on ``seqs`` through the evaluation runner."""
    ests = [load_estimator(ckpt, name=label) if is_estimator_file(ckpt)
            else registry.build("learned", ckpt=ckpt, label=label)]
    for b in baselines:
        try:
            m = registry.get(b)
            ests.append(registry.build(b, axes if axes in m.axes else m.axes[0]))
        except Exception as e:  # noqa: BLE001 - a missing peer must not lose the cell
            warnings.warn(f"transfer: baseline {b!r} unavailable, skipped: {e}")
    res = evaluate(ests, seqs, plots=False, trajectories=False, axes=axes)
    means = {e.name: {k: res["methods"][e.name]["mean"].get(k) for k in METRICS} for e in ests}
    learned = means.pop(label)
    classical = {k: v for k, v in means.items() if v["aae_deg"] is not None}
    best = min(classical, key=lambda k: classical[k]["aae_deg"]) if classical else None
    best_incl = min((v["inclination_deg"] for v in classical.values() if v["inclination_deg"] is not None),
                    default=None)
    backbone = next((v for k, v in means.items() if k.startswith("backbone")), None)
    # compared at the tables' 0.01 deg rounding (a fallback equal to a classical filter is not worse)
    never_worse = best is not None and verdict.never_worse(learned["aae_deg"], learned["inclination_deg"],
                                                           classical[best]["aae_deg"], best_incl)
    return {"learned": learned, "backbone": backbone, "best": best, "best_metrics": classical.get(best),
            "best_inclination_deg": best_incl, "never_worse": bool(never_worse), "all": means,
            "recordings": [s.name for s in seqs]}


def transfer(ckpts: Mapping[str, str], data_cfgs: Mapping[str, Mapping], baselines: Sequence[str] = BASELINES,
             out: Optional[Path] = None, verbose: bool = True) -> Dict[str, Any]:
    """The matrix over ``ckpts`` {label: path} x ``data_cfgs`` {name: data config}."""
    from ..datasets import load_split

    table: Dict[str, Dict[str, Any]] = {}
    for label, path in ckpts.items():
        meta = shipped_meta(path)
        axes, own = meta["axes"], meta["data"]
        owns = own_datasets(own)
        row: Dict[str, Any] = {"axes": axes, "trained_on": own, "family": meta["family"]}
        for name, cfg in data_cfgs.items():
            if axes == 9 and int(cfg.get("axes", 9)) != 9:
                continue  # no magnetometer there
            split = cell_recordings(cfg, name in owns)
            if split is None:
                row[name] = {"skipped": "own dataset without a visible test split: see its crossval folds"}
                continue
            cfg = dict(cfg)
            cfg["fold"] = None
            seqs = [s for s in load_split(cfg, split) if s.quat is not None and s.scored().any()]
            if axes == 6:
                seqs = [s.without_mag() if s.has_mag else s for s in seqs]
            if not seqs:
                row[name] = {"skipped": f"no scored recordings in split {split!r}"}
                continue
            cell = score_cell(path, label, seqs, axes, baselines)
            cell["split"] = split
            row[name] = cell
            if verbose:
                l, b = cell["learned"], cell["best_metrics"] or {}
                print(f"{label} on {name} ({split}, {len(seqs)} rec.): learned {l['aae_deg']:.2f}/"
                      f"{l['inclination_deg']:.2f}, best classical {cell['best']} {b.get('aae_deg', float('nan')):.2f}"
                      f" (incl. {cell['best_inclination_deg']:.2f})", flush=True)
        table[label] = row
    result = {"matrix": table, "baselines": list(baselines), "metrics": list(METRICS)}
    write_result(out, "transfer", result, markdown(result))
    return result


def markdown(result: Mapping[str, Any]) -> str:
    """The matrix as a table: each cell ``learned AAE (incl.) | best classical AAE (incl.)``."""
    names = [d for d in DATASETS if any(d in row for row in result["matrix"].values())]
    lines = ["| checkpoint | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for label, row in result["matrix"].items():
        cells = []
        for d in names:
            c = row.get(d)
            if c is None:
                cells.append("–")
            elif "skipped" in c:
                cells.append("(own data)")
            else:
                l, b, bb = c["learned"], c["best_metrics"] or {}, c["backbone"] or {}
                mark = "" if c["never_worse"] else " ✗"
                cells.append(f"{l['aae_deg']:.2f} ({l['inclination_deg']:.2f}) / {c['best']} "
                             f"{b.get('aae_deg', float('nan')):.2f} ({c['best_inclination_deg']:.2f}); "
                             f"backbone {bb.get('aae_deg', float('nan')):.2f}{mark}")
        lines.append(f"| {label} ({row['axes']}-axis, {row['trained_on']}) | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("Cell: learned mean AAE (inclination) / best classical filter by AAE on the same recordings "
                 "(lowest inclination of any classical filter); ✗ = the learned model is worse in either.")
    return "\n".join(lines) + "\n"


def transfer_main(cfg) -> Dict[str, Any]:
    """``scripts/benchmark.py transfer``: ``transfer.ckpts`` {label: path} (default: every
    shipped model, :func:`shipped_paths`), ``transfer.datasets`` (conf/data names), ``transfer.baselines``."""
    from omegaconf import OmegaConf

    conf = conf_path("data")
    t = OmegaConf.to_container(cfg.get("transfer") or {}, resolve=True)
    ckpts = t.get("ckpts") or shipped_paths()
    datasets = list(t.get("datasets") or DATASETS)
    data_cfgs: Dict[str, Mapping] = {}
    for d in datasets:
        c = OmegaConf.to_container(OmegaConf.load(conf / f"{d}.yaml"), resolve=True)
        if d != "simulated" and not Path(c["root"]).is_dir():
            warnings.warn(f"transfer: {d} data not found at {c['root']}, skipped")
            continue
        data_cfgs[d] = c
    out = Path(cfg.get("out") or "runs/benchmark/transfer")
    if t.get("rates"):
        return sweep_main(ckpts, data_cfgs, [float(r) for r in t["rates"]], out)
    res = transfer(ckpts, data_cfgs, list(t.get("baselines") or BASELINES), out)
    print(markdown(res))
    print(f"results in {out}")
    return res


def resampled(seq, rate_hz: float):
    """``seq`` as a device at ``rate_hz`` would have recorded it: readings interpolated linearly
    onto a uniform grid, the ground truth along the geodesic (normalised quaternion interpolation
    between neighbours, a few ms apart), valid where both neighbours are."""
    import numpy as np

    from ..sequence import ImuSequence

    t = seq.time
    grid = t[0] + np.arange(int(np.floor((t[-1] - t[0]) * rate_hz)) + 1) / rate_hz
    j = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, len(t) - 2)
    w = ((grid - t[j]) / (t[j + 1] - t[j])).clip(0.0, 1.0)[:, None]

    def lerp(x):
        return None if x is None else (1 - w) * x[j] + w * x[j + 1]

    quat = valid = None
    if seq.quat is not None:
        qa, qb = seq.quat[j], seq.quat[j + 1]
        qb = np.where((qa * qb).sum(1, keepdims=True) < 0, -qb, qb)
        quat = (1 - w) * qa + w * qb
        quat /= np.linalg.norm(quat, axis=1, keepdims=True)
        valid = seq.quat_valid[j] & seq.quat_valid[j + 1]
        quat[~valid] = np.nan
    return ImuSequence(name=seq.name, source=f"{seq.source} at {rate_hz:g} Hz", time=grid, gyro=lerp(seq.gyro),
                       accel=lerp(seq.accel), mag=lerp(seq.mag), quat=quat, rate=float(rate_hz),
                       check_units=False, meta=dict(seq.meta))


def rate_sweep(ckpt: str, seqs, axes: int, rates, baselines=("backbone", "vqf", "mahony")) -> Dict[str, Any]:
    """One checkpoint and ``baselines`` on ``seqs`` resampled to each of ``rates`` (Hz)."""
    rows = {}
    for r in rates:
        cell = score_cell(ckpt, "learned", [resampled(s, float(r)) for s in seqs], axes, baselines)
        rows[str(r)] = {"learned": cell["learned"], "all": cell["all"]}
    return {"rates": [float(r) for r in rates], "rows": rows, "recordings": [s.name for s in seqs]}


def rates_markdown(res: Mapping[str, Any]) -> str:
    """The rate sweep's table (``rates.json`` of :func:`sweep_main`)."""
    lines = ["| checkpoint on data (split) | rate Hz | learned | backbone | VQF | Mahony |", "|---|---|---|---|---|---|"]
    for key, sw in res.items():
        label, name = key.split("/", 1)
        for r, row in sw["rows"].items():
            a = row["all"]
            cells = [row["learned"]] + [next((v for k, v in a.items() if k.startswith(m)), None)
                                         for m in ("backbone", "vqf", "mahony")]
            lines.append(f"| {label} on {name} ({sw['split']}, {len(sw['recordings'])} rec.) | {float(r):g} | " + " | ".join(
                "–" if c is None else f"{c['aae_deg']:.2f} / {c['inclination_deg']:.2f}" for c in cells) + " |")
    return "\n".join(lines) + ("\n\nMean AAE / inclination, degrees; each recording resampled to the rate (readings "
                               "linear, ground truth along the geodesic).\n")


def sweep_main(ckpts: Mapping[str, str], data_cfgs: Mapping[str, Mapping], rates: Sequence[float], out: Path):
    """``transfer.rates=[...]``: every checkpoint on the recordings of its matrix cells,
    resampled to each rate, beside the backbone, VQF and Mahony at the same rate."""
    from ..datasets import load_split

    out.mkdir(parents=True, exist_ok=True)
    res: Dict[str, Any] = {}
    for label, path in ckpts.items():
        meta = checkpoint_meta(load_checkpoint(path), path)
        axes, owns = int(meta["layout"]["axes"]), own_datasets(str(meta.get("data", "")))
        for name, cfg in data_cfgs.items():
            split = cell_recordings(cfg, name in owns)
            if split is None or (axes == 9 and int(cfg.get("axes", 9)) != 9):
                continue
            seqs = [s for s in load_split({**dict(cfg), "fold": None}, split) if s.quat is not None and s.scored().any()]
            seqs = [s.without_mag() if (axes == 6 and s.has_mag) else s for s in seqs]
            sw = rate_sweep(path, seqs, axes, rates)
            res[f"{label}/{name}"] = {**sw, "split": split}
            print(rates_markdown({f"{label}/{name}": res[f"{label}/{name}"]}), flush=True)
    (out / "rates.json").write_text(json.dumps(jsonable(res), indent=1))
    md = rates_markdown(jsonable(res))
    (out / "rates.md").write_text(md)
    print(md)
    return res
