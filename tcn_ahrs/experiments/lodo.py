"""Leave one dataset out (``python scripts/benchmark.py lodo``): for each dataset, a general model
trained on the others (``experiment=general6_residual data.leave_out=<dataset>``) scored on every
recording of the left-out dataset, beside that dataset's own model, the backbone, every classical
filter, VQF and RIANN on the same recordings.

* The general model never saw the left-out dataset: not its recordings, not its device, not its
  rate; its knobs were chosen on the other datasets' validation parts.
* Which recordings: the left-out dataset's training recordings, whole (``trainval``; its held-back
  test recordings stay held back).
* The dataset's own model: its nested cross-validation (``runs/nested/<dataset><axes>/crossval.json``,
  ``scripts/crossval.py experiment=<dataset><axes>_res``), whose outer folds cover the same recordings,
  each scored by a model that never saw it (mean over recordings); absent: left blank.

Output: ``lodo.json`` and ``lodo.md`` in ``out``. Training runs live in ``lodo.runs/<dataset>``; a
finished run (its ``knobs.json`` written) is reused, an interrupted one resumes.
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Sequence

from .. import verdict
from ..conf import CONF_DIR
from .transfer import METRICS, score_cell, write_result

DATASETS = ("broad", "euroc", "tumvi", "oxiod")
BASELINES = ("raw", "backbone", "vqf", "ecf", "mahony", "madgwick", "eskf", "robust_eskf", "riann")
CONF = CONF_DIR


def own_model(nested_json: Path) -> Optional[Dict[str, float]]:
    """The dataset's own model on its training recordings from its nested folds: the mean over
    recordings (fold means weighted by their recording counts) of AAE and inclination."""
    if not nested_json.is_file():
        return None
    res = json.loads(nested_json.read_text())
    out: Dict[str, float] = {}
    for k in METRICS:
        tot, n = 0.0, 0
        for f in res["folds"]:
            v = (f["means"].get("Learned") or {}).get(k)
            if v is None:
                return None
            tot += float(v) * len(f["recordings"])
            n += len(f["recordings"])
        out[k] = tot / n
    return out


def compose_train(args: Sequence[str]):
    """``conf/train.yaml`` with ``args``, inside a running Hydra app (``scripts/benchmark.py``,
    whose search path is the same ``conf/``) or outside one."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        return compose("train", list(args))
    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("train", list(args))


def train_left_out(dataset: str, run_dir: Path, experiment: str, overrides: Sequence[str] = ()) -> Path:
    """Train (or resume, or reuse) the general model without ``dataset``; returns its checkpoint."""
    ckpt = run_dir / "checkpoints" / "last.ckpt"
    if (run_dir / "knobs.json").is_file() and ckpt.is_file():
        return ckpt
    from ..training.run import train_main

    args = [f"experiment={experiment}", f"data.leave_out={dataset}", f"run_dir={run_dir}",
            "eval.enabled=false", *overrides]
    if ckpt.is_file():
        args.append("resume=true")
    cfg = compose_train(args)
    print(f"lodo: training without {dataset}: {' '.join(args)}", flush=True)
    train_main(cfg, overrides=list(args))
    return ckpt


def reselect(dataset: str, run_dir: Path, experiment: str, overrides: Sequence[str] = ()) -> None:
    """Choose a finished run's inference knobs again on its validation parts, with the recipe's
    current ``train.knob_grid`` and ``train.knob_rule`` (the checkpoint is rewritten atomically)."""
    from omegaconf import OmegaConf

    from ..datasets import load_split
    from ..training.run import choose_knobs_into_checkpoint

    cfg = compose_train([f"experiment={experiment}", f"data.leave_out={dataset}", *overrides])
    grid = OmegaConf.to_container(cfg.train.knob_grid, resolve=True) if cfg.train.get("knob_grid") else None
    choose_knobs_into_checkpoint(str(run_dir / "checkpoints" / "last.ckpt"), load_split(cfg.data, "val"), run_dir,
                                 grid, str(cfg.train.get("knob_rule") or "both"))


def lodo(data_cfgs: Mapping[str, Mapping], runs: Path, experiment: str = "general6_residual",
         overrides: Sequence[str] = (), baselines: Sequence[str] = BASELINES, train: bool = True,
         nested: Path = Path("runs/nested"), out: Optional[Path] = None, reselect_knobs: bool = False,
         device_check: bool = True) -> Dict[str, Any]:
    """The table over ``data_cfgs`` {dataset: its data config}, at the experiment's axes
    (general6_residual: 6, general9_residual: 9, datasets without a magnetometer skipped). ``device_check``:
    every method runs on the recordings with their gyro bias at rest subtracted, as ``tcn-ahrs
    evaluate`` does for the general models (:mod:`tcn_ahrs.device_check`, no ground truth)."""
    from ..datasets import load_split

    axes = int(compose_train([f"experiment={experiment}", *overrides]).data.axes)

    rows: Dict[str, Any] = {}
    for name, cfg in data_cfgs.items():
        if axes == 9 and int(cfg.get("axes", 9)) != 9:
            continue  # no magnetometer there
        run_dir = Path(runs) / name
        ckpt = run_dir / "checkpoints" / "last.ckpt"
        if train:
            ckpt = train_left_out(name, run_dir, experiment, overrides)
        if not ckpt.is_file():
            rows[name] = {"skipped": f"no model trained without {name} at {ckpt} (lodo.train=true trains it)"}
            continue
        if reselect_knobs:
            reselect(name, run_dir, experiment, overrides)
        cfg = {**dict(cfg), "fold": None, "axes": axes}
        seqs = raw = [s for s in load_split(cfg, "trainval") if s.quat is not None and s.scored().any()]
        if device_check:
            from ..device_check import checked

            seqs = checked(seqs)
        cell = score_cell(str(ckpt), "general", seqs, axes, baselines)
        cell["on_raw"] = on_raw(raw, axes)   # what a device runs: the default's causal check beside VQF
        cell["own"] = own_model(Path(nested) / f"{name}{axes}" / "crossval.json")
        cell["riann"] = cell["all"].get("riann6d")
        cell["checkpoint"] = str(ckpt)
        g, own = cell["learned"], cell["own"]
        cell["within_10pct_of_own"] = (None if own is None else
                                       bool(g["aae_deg"] <= 1.1 * own["aae_deg"]
                                            and g["inclination_deg"] <= 1.1 * own["inclination_deg"]))
        r = cell["riann"]
        # RIANN has no heading: judged on the inclination alone (the one rule, inclination in the AAE's place)
        cell["inclination_le_riann"] = None if not r else verdict.never_worse(g["inclination_deg"], None,
                                                                               r["inclination_deg"], None)
        rows[name] = cell
        b = cell["best_metrics"] or {}
        print(f"lodo {name} ({len(seqs)} rec.): general {g['aae_deg']:.2f}/{g['inclination_deg']:.2f}, best classical "
              f"{cell['best']} {b.get('aae_deg', float('nan')):.2f}, own "
              f"{'-' if own is None else format(own['aae_deg'], '.2f')}", flush=True)
    result = {"lodo": rows, "axes": axes, "experiment": experiment, "overrides": list(overrides),
              "baselines": list(baselines), "device_check": bool(device_check)}
    write_result(out, "lodo", result, markdown(result))
    return result


def on_raw(seqs, axes: int) -> Dict[str, Any]:
    """The default (its causal device check in the filter: ``tcn-ahrs evaluate`` without ``ckpt=``) and
    VQF on the raw readings: {"default": metrics, "vqf": metrics} (means over ``seqs``)."""
    from ..estimators import registry
    from ..evaluate.main import default
    from ..evaluate.runner import evaluate

    ests = [default(axes, "default"), registry.build("vqf", axes)]
    res = evaluate(ests, seqs, plots=False, trajectories=False, axes=axes)["methods"]
    return {k: {m: res[e.name]["mean"].get(m) for m in ("aae_deg", "inclination_deg")} for k, e in zip(("default", "vqf"), ests)}


def _pair(m: Optional[Mapping[str, Any]]) -> str:
    if not m or m.get("aae_deg") is None:
        return "–" if not m or m.get("inclination_deg") is None else f"– / {m['inclination_deg']:.2f}"
    return f"{m['aae_deg']:.2f} / {m['inclination_deg']:.2f}"


def markdown(result: Mapping[str, Any]) -> str:
    """One row per left-out dataset: mean AAE / inclination (degrees) of each method."""
    axes = int(result.get("axes", 6))
    lines = [f"| left out (recordings) | general{axes} | own model (nested folds) | backbone (VQF defaults) | VQF | best classical "
             "| RIANN (incl.) | never worse? | default, causal (raw) | VQF raw | default ≤ VQF? |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, c in result["lodo"].items():
        if "skipped" in c:
            lines.append(f"| {name} | {c['skipped']} ||||||||||")
            continue
        raw = c.get("on_raw") or {}
        vqf = c["all"].get(f"vqf{axes}d")
        best = f"{c['best']} {_pair(c['best_metrics'])}"
        riann = "–" if not c.get("riann") else f"{c['riann']['inclination_deg']:.2f}"
        lines.append(f"| {name} ({len(c['recordings'])}) | {_pair(c['learned'])} | {_pair(c['own'])} | {_pair(c['backbone'])} "
                     f"| {_pair(vqf)} | {best} | {riann} | {'yes' if c['never_worse'] else '**no**'} "
                     f"| {_pair(raw.get('default'))} | {_pair(raw.get('vqf'))} "
                     f"| {('yes' if verdict.never_worse_means(raw['default'], raw['vqf']) else '**no**') if raw else '–'} |")
    lines.append("")
    lines.append(("Up to 'never worse?' every method on the readings with each recording's gyro bias at rest, read "
                  "from the whole recording, subtracted (the offline device check, as the general models are given "
                  "them). " if result.get("device_check") else "") +
                 "Mean AAE / inclination in degrees over the left-out dataset's training recordings, whole. "
                 "never worse: the general model ≤ the best classical filter (lowest mean AAE) in AAE and ≤ the "
                 "lowest inclination of any classical filter, at the tables' 0.01° rounding. default, causal (raw): "
                 "what `tcn-ahrs evaluate` runs without `ckpt=` and every export runs (the backbone with VQF's "
                 "defaults and its causal device check) on the raw readings, beside VQF on the same; its gap to the "
                 "backbone's column is the cost of causality. default ≤ VQF: the two on raw readings, in AAE and "
                 "inclination, at the same rounding.")
    return "\n".join(lines) + "\n"


def section_and_datasets(cfg, section: str):
    """A benchmark mode's section of ``conf/benchmark.yaml`` as a dict, and {dataset: its data
    config} for its ``datasets`` (default :data:`DATASETS`), those absent under ``../shared``
    skipped with a warning."""
    from omegaconf import OmegaConf

    t = OmegaConf.to_container(cfg.get(section) or {}, resolve=True)
    data_cfgs: Dict[str, Mapping] = {}
    for d in list(t.get("datasets") or DATASETS):
        c = OmegaConf.to_container(OmegaConf.load(CONF / "data" / f"{d}.yaml"), resolve=True)
        if not Path(c["root"]).is_dir():
            warnings.warn(f"{section}: {d} data not found at {c['root']}, skipped")
            continue
        data_cfgs[d] = c
    return t, data_cfgs


def lodo_main(cfg) -> Dict[str, Any]:
    """``scripts/benchmark.py lodo``: the ``lodo`` section of ``conf/benchmark.yaml``."""
    t, data_cfgs = section_and_datasets(cfg, "lodo")
    out = Path(cfg.get("out") or "runs/benchmark/lodo")
    res = lodo(data_cfgs, Path(t.get("runs") or "runs/lodo"), str(t.get("experiment") or "general6_residual"),
               list(t.get("overrides") or []), list(t.get("baselines") or BASELINES), bool(t.get("train", True)),
               Path(t.get("nested") or "runs/nested"), out, bool(t.get("reselect", False)), bool(t["device_check"]))
    print(markdown(res))
    print(f"results in {out}")
    return res
