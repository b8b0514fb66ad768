"""The gate on every real recording (``tcn-ahrs benchmark devices``): the default of ``tcn-ahrs
evaluate`` and every shipped model beside VQF, the classical filters with their defaults, the
best of them and the per-recording best (an oracle no filter has), and — on phones — the phone
OS's own attitude, **recording by recording**, on every real recording the project has (BROAD,
EuRoC, TUM VI, OxIOD, the iPhones: each dataset's recordings under ``../shared``, whole).

* Same input for every method: each recording's raw readings, as a device gives them (the default
  checks the gyro bias causally inside its filter, :func:`tcn_ahrs.kernels.backbone.rest_check`, as
  ``tcn-ahrs evaluate``'s default and every exported runtime do; no method gets the offline check,
  which reads the whole recording).
* The gate: the default is never worse than VQF on any recording (:func:`tcn_ahrs.verdict.never_worse`:
  AAE and inclination, at the tables' 0.01°), both on the same clock: VQF takes one fixed period, so
  it integrates a regular recording at the nominal period and an irregular one (the iPhone 5's
  jittery steps) on a uniform grid (:class:`tcn_ahrs.estimators.peers.OnFixedPeriod`); the gate runs
  the default on that clock too. The default on the recording's own steps (what a device runs) is a
  column of its own, with the recordings where it is worse or better than VQF counted. A recording
  that fails the gate is listed with its margin.
* A shipped model reads only the datasets whose axes it has (a 9-axis model needs a magnetometer);
  a dataset it trained on is marked, since those recordings are not new to it.

Output: ``devices.json`` (every recording, every method) and ``devices.md`` (a summary per dataset
and the recordings where the default is worse than VQF) in ``out``.
"""
from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence

import numpy as np

from .. import verdict
from ..config import conf_path
from .transfer import METRICS, own_datasets, shipped_meta, shipped_paths, write_result

DATASETS = ("broad", "euroc", "tumvi", "oxiod", "iphone5", "iphone4s")
CLASSICAL = ("vqf", "ecf", "mahony", "madgwick")
"""The classical filters with their defaults (the 'best classical' and the per-recording best are among these)."""
DEFAULT = "default"
DEFAULT_VQF_CLOCK = "default on VQF's clock"
OS = "phone_os"


def _recordings(data_cfg: Mapping, names: Optional[Sequence[str]] = None):
    """(recordings with ground truth, [(recording, reason)] refused): every recording under the
    dataset's root (``all``), or only ``names``."""
    from ..datasets import load_split

    cfg = dict(data_cfg)
    cfg["fold"] = None
    refused: List = []
    seqs = [s for s in load_split(cfg, "all", refused) if s.has_gt and s.scored().any()]
    if names:
        seqs = [s for s in seqs if s.name in set(names)]
    return seqs, refused


OS_FIELD = "os_quat"


def _has_os(seqs) -> bool:
    """Whether every recording's HDF5 file carries the phone OS's attitude."""
    import h5py

    def has(s) -> bool:
        if not str(s.source).endswith((".h5", ".hdf5")):
            return False
        with h5py.File(s.source, "r") as f:
            return OS_FIELD in f

    try:
        return bool(seqs) and all(has(s) for s in seqs)
    except OSError:
        return False


def device_table(name: str, data_cfg: Mapping, models: Mapping[str, str], names: Optional[Sequence[str]] = None
                 ) -> Dict[str, Any]:
    """One dataset: every method on every recording (see the module docstring)."""
    from ..estimators import registry
    from ..estimators.families import is_estimator_file, load_estimator
    from ..evaluate.main import default
    from ..evaluate.runner import evaluate

    axes = int(data_cfg.get("axes", 9))
    seqs, refused = _recordings(data_cfg, names)
    if not seqs:
        return {"skipped": f"no recordings with ground truth under {data_cfg.get('root')}", "refused": refused}
    from ..estimators.peers import OnFixedPeriod

    ests: List[Any] = [default(axes, DEFAULT), OnFixedPeriod(default(axes, DEFAULT), DEFAULT_VQF_CLOCK)]
    trained_on: Dict[str, bool] = {}
    model_axes: Dict[str, int] = {DEFAULT: axes}
    for label, path in models.items():
        meta = shipped_meta(path)
        if meta["axes"] > axes:
            continue  # a 9-axis model on a dataset without a magnetometer
        trained_on[label] = name in own_datasets(meta["data"]) or meta["data"] == name
        model_axes[label] = meta["axes"]
        ests.append(load_estimator(path, name=label) if is_estimator_file(path)
                    else registry.build("learned", ckpt=path, label=label))
    classical = [registry.build("raw", axes)] + [registry.build(c, axes) for c in CLASSICAL]
    ests += classical
    # a 6-axis model on 9-axis data is held against VQF without the magnetometer (the same input)
    vqf6 = registry.build("vqf", 6) if axes == 9 and 6 in model_axes.values() else None
    if vqf6 is not None:
        ests.append(vqf6)
    if axes == 9 and _has_os(seqs):
        ests.append(registry.build(OS, 9))
    # the 6-axis view of a dataset read as 6-axis; otherwise every recording with its magnetometer
    # (the device check only advises 6 axes on a disturbed field: every column alike)
    res = evaluate(ests, seqs, plots=False, trajectories=False, axes=axes if axes == 6 else None, dataset=name)
    rows: Dict[str, Dict[str, Dict[str, float]]] = {}
    for e in ests:
        for r in res["methods"][e.name]["recordings"]:
            rows.setdefault(r["name"], {})[e.name] = {k: r.get(k) for k in METRICS}
    cl_names = [c.name for c in classical if c.name != "Raw IMU"]
    vqf = next(c.name for c in classical if c.name.startswith("vqf"))
    means = {e.name: {k: res["methods"][e.name]["mean"].get(k) for k in METRICS} for e in ests}
    best = min(cl_names, key=lambda c: means[c]["aae_deg"])
    oracle = float(np.mean([min(rows[r][c]["aae_deg"] for c in cl_names) for r in rows]))
    def worse(m: str, ref: str, than: bool = True) -> Dict[str, float]:
        # than: recordings where m is worse than ref; else where ref is worse than m (m better)
        a, b = (m, ref) if than else (ref, m)
        return {r: round(v[m]["aae_deg"] - v[ref]["aae_deg"], 3) for r, v in rows.items()
                if not verdict.never_worse(v[a]["aae_deg"], v[a]["inclination_deg"], v[b]["aae_deg"],
                                           v[b]["inclination_deg"])}

    gate = {}
    for m in [DEFAULT, *[k for k in models if k in means]]:
        ref = vqf6.name if (vqf6 is not None and model_axes[m] == 6) else vqf
        w = worse(DEFAULT_VQF_CLOCK if m == DEFAULT else m, ref)
        gate[m] = {"worse_than_vqf": w, "never_worse": not w, "vqf": ref}
    gate[DEFAULT]["input"] = DEFAULT_VQF_CLOCK
    gate[DEFAULT]["own_steps"] = {"worse_than_vqf": worse(DEFAULT, vqf), "better_than_vqf": worse(DEFAULT, vqf, False)}
    return {"axes": axes, "recordings": rows, "means": means, "vqf": vqf, "best_classical": best,
            "per_recording_best_mean": oracle, "gate": gate, "trained_on": trained_on,
            "refused": [list(x) for x in refused]}


def devices(data_cfgs: Mapping[str, Mapping], models: Mapping[str, str], out: Optional[Path] = None,
            names: Optional[Mapping[str, Sequence[str]]] = None, verbose: bool = True) -> Dict[str, Any]:
    """Every dataset in ``data_cfgs`` {name: data config} with ``models`` {label: path}; ``names``
    {dataset: [recording, ...]}: only those (the quick subset)."""
    table: Dict[str, Any] = {}
    for name, cfg in data_cfgs.items():
        table[name] = t = device_table(name, cfg, models, (names or {}).get(name))
        if verbose and "skipped" not in t:
            d, v = t["means"][DEFAULT], t["means"][t["vqf"]]
            g = t["gate"][DEFAULT]
            print(f"{name}: {len(t['recordings'])} recordings, default {d['aae_deg']:.2f} VQF {v['aae_deg']:.2f}, "
                  f"best classical {t['best_classical']} {t['means'][t['best_classical']]['aae_deg']:.2f}, "
                  f"per-recording best {t['per_recording_best_mean']:.2f}; default worse than VQF on "
                  f"{len(g['worse_than_vqf'])}", flush=True)
    result = {"datasets": table, "models": dict(models), "classical": list(CLASSICAL), "metrics": list(METRICS),
              "input": "raw readings, the same for every method (the default checks the gyro bias causally in its filter)"}
    write_result(out, "devices", result, markdown(result))
    return result


def _f(x: Optional[float]) -> str:
    return "–" if x is None else f"{x:.2f}"


def markdown(result: Mapping[str, Any], listed: Optional[Sequence[str]] = None) -> str:
    """Per dataset: recordings, mean AAE (inclination) of the default, VQF, the best classical filter,
    the per-recording best, the phone OS and each shipped model, and the gate; then the recordings
    where a gated method (those in ``listed``; None: every one) is worse than VQF."""
    models = list(result["models"])
    head = ["dataset", "recordings", "default", "VQF", "best classical", "per-recording best", "phone OS",
            *models, "default never worse than VQF (its clock)", "default on its own steps against VQF"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    worse_rows: List[str] = []
    for name, t in result["datasets"].items():
        if "skipped" in t:
            lines.append(f"| {name} | {t['skipped']} |" + " |" * (len(head) - 2))
            continue
        m = t["means"]
        cell = lambda k: f"{_f(m[k]['aae_deg'])} ({_f(m[k]['inclination_deg'])})" if k in m else "–"  # noqa: E731
        gate = t["gate"][DEFAULT]
        n = len(t["recordings"])
        verdict_cell = "yes" if gate["never_worse"] else f"no: {len(gate['worse_than_vqf'])} of {n}"
        own = gate.get("own_steps")
        own_cell = (f"worse on {len(own['worse_than_vqf'])}, better on {len(own['better_than_vqf'])}" if own else "–")
        model_cells = [cell(k) + (" (own data)" if t["trained_on"].get(k) else "") for k in models]
        os_name = next((k for k in m if k == "phone OS"), None)
        lines.append(f"| {name} ({t['axes']}-axis) | {n} | {cell(DEFAULT)} | {cell(t['vqf'])} | "
                     f"{t['best_classical']} {cell(t['best_classical'])} | {t['per_recording_best_mean']:.2f} | "
                     f"{cell(os_name) if os_name else '–'} | " + " | ".join(model_cells)
                     + (" | " if model_cells else "") + f"{verdict_cell} | {own_cell} |")
        for meth, g in t["gate"].items():
            if listed is not None and meth not in listed:
                continue
            ref = g.get("vqf", t["vqf"])
            col = g.get("input", meth)
            for rec, d in sorted(g["worse_than_vqf"].items(), key=lambda x: -x[1]):
                r = t["recordings"][rec]
                worse_rows.append(f"| {name} | {rec} | {col} | {_f(r[col]['aae_deg'])} ({_f(r[col]['inclination_deg'])}) | "
                                  f"{ref} {_f(r[ref]['aae_deg'])} ({_f(r[ref]['inclination_deg'])}) | {d:+.2f} |")
    lines += ["", "Mean AAE (inclination) in degrees over every recording, the yardstick (docs/conventions.md); "
              f"input: {result['input']}. Best classical: the lowest mean AAE among {', '.join(result['classical'])} "
              "with their defaults; per-recording best: the lowest of them on each recording (an oracle). "
              "Never worse: AAE and inclination ≤ VQF's at 0.01° on every recording (a 6-axis model against VQF "
              "without the magnetometer); the default on VQF's clock (VQF takes one fixed period: the nominal one, "
              "or a uniform grid on an irregular clock), its column on the recording's own steps (what a device runs). "
              "A shipped model at another rate than it was trained at runs as the "
              "backbone with VQF's defaults (`other_rate: backbone`); \"own data\": recordings it trained on."]
    if worse_rows:
        lines += ["", "Recordings where " + ("a method" if listed is None else " or ".join(listed)) + " is worse than VQF:", "",
                  "| dataset | recording | method | AAE (incl.) | VQF (same axes) | AAE − VQF |", "|---|---|---|---|---|---|",
                  *worse_rows]
    return "\n".join(lines) + "\n"


QUICK = {"iphone4s": ["Guillaume_iPhone4S_NoDist_RunningHand", "Guillaume_iPhone4S_Dist_Phoning"],
         "broad": ["18_undisturbed_fast_translation_with_breaks_B"]}
"""The quick subset (the README's test command): a running phone, a disturbed one, a BROAD trial."""


def devices_main(cfg) -> Dict[str, Any]:
    """``tcn-ahrs benchmark devices``: ``devices.datasets`` (conf/data names; default every real
    dataset), ``devices.models`` (shipped model names; default every shipped model, [] for none),
    ``devices.quick`` (the quick subset), ``out``."""
    from omegaconf import OmegaConf

    d = OmegaConf.to_container(cfg.get("devices") or {}, resolve=True)
    quick = bool(d.get("quick", False))
    datasets = list(d.get("datasets") or (QUICK if quick else DATASETS))
    shipped = shipped_paths(_shipped_dir())
    wanted = d.get("models")
    models = shipped if wanted is None else {k: shipped[k] for k in wanted}
    from ..datasets import resolve_root

    data_cfgs: Dict[str, Mapping] = {}
    for name in datasets:
        c = OmegaConf.to_container(OmegaConf.load(conf_path("data", f"{name}.yaml")), resolve=True)
        try:
            c["root"] = str(resolve_root(c))
        except Exception as e:  # noqa: BLE001 - an absent dataset is said, the others run
            warnings.warn(f"devices: {name} not found ({e}), skipped")
            continue
        data_cfgs[name] = c
    out = Path(cfg.get("out") or "runs/benchmark/devices")
    res = devices(data_cfgs, models, out, QUICK if quick else None)
    print(markdown(res))
    print(f"results in {out}")
    return res


def _shipped_dir() -> Path:
    from ..checkpoints import SHIPPED_DIR

    return Path(SHIPPED_DIR)


def causality_markdown(result: Mapping[str, Any]) -> str:
    """``scripts/causality.py``'s table: per dataset VQF's filter on the offline device check (the bias
    read from the whole recording: no device can) and on raw input, the default (the causal check in
    the filter: what a device runs) and the earlier causal candidates, mean AAE, with the recordings
    worse than VQF on the same raw input."""
    oracle = "default, true gyro bias removed (an oracle)"
    variants = list(result["variants"]) + ([oracle] if oracle in next(iter(result["datasets"].values()), {}) else [])
    head = ["dataset", "recordings", "VQF, offline check", "backbone, offline check", "VQF raw", "backbone raw",
            "default: causal check (a device)", *variants]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for name, r in result["datasets"].items():
        cells = [f"{r['vqf offline check']:.2f}", f"{r['backbone offline check']:.2f}", f"{r['vqf raw']:.2f}",
                 f"{r['backbone raw']:.2f}"]
        cells += [f"{r[v]:.2f} (worse on {r[v + ': worse than vqf raw']})" for v in ["default", *variants]]
        lines.append(f"| {name} | {r['recordings']} | " + " | ".join(cells) + " |")
    lines += ["", "Mean AAE in degrees over every recording (the yardstick); in brackets the recordings where the "
              "method is worse than VQF on the same raw input (AAE or inclination, at 0.01°). The backbone: VQF's "
              "defaults; the default: the backbone with the causal check (`tcn-ahrs evaluate` without `ckpt=`). "
              "Every method on VQF's clock. The oracle: the gyro bias the ground truth shows (the median of gyro "
              "minus its rate) subtracted before the default runs — no device has it; it bounds what any bias "
              "estimate could reach. Command: `python scripts/causality.py`."]
    return "\n".join(lines) + "\n"
