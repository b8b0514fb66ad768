"""Does fine-tuning on a few of one's own recordings help? (``python scripts/benchmark.py finetune``)

For each dataset, the general model that never saw it (the leave-one-dataset-out run,
``runs/lodo/<dataset>``) plays the user's starting point; the dataset plays the user's device:

* ``k`` of its recordings (the first ``k`` of its first cross-validation fold) are the user's own;
* fine-tuned twice from the general model (``experiment=finetune``, device-checked recordings):
  with their ground truth (``train.supervision=gt``: backbone knobs, bias, networks on the earlier
  parts, inference knobs on the later parts) and without (``train.supervision=self``: bias and
  networks from the sensors' own consistency on the earlier parts); each run ships the fine-tuned
  model only when the later parts say it is better than the general model
  (:mod:`tcn_ahrs.training.adaptation`), else the general model;
* scored on the dataset's other training recordings, whole (which chose nothing), beside the
  general model, the backbone and the classical filters.

Output: ``finetune.json`` and ``finetune.md`` in ``out``; runs in ``finetune.runs/<dataset>_<mode>``
(reused when finished).
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence

from ..evaluate.runner import evaluate
from .transfer import METRICS, write_result

BASELINES = ("raw", "backbone", "vqf", "ecf", "mahony", "madgwick")
MODES = ("gt", "self")


def own_recordings(data_cfg: Mapping, k: int) -> List[str]:
    """The user's k recordings: the first k of the dataset's first fold (else of its train list)."""
    folds = list(data_cfg.get("folds") or [])
    names = [str(r) for r in (folds[0] if folds else data_cfg.get("train") or [])]
    return names[:k]


def finetune_run(dataset: str, mode: str, init: Path, recordings: Sequence[str], run_dir: Path,
                 overrides: Sequence[str] = ()) -> Dict[str, Any]:
    """Fine-tune ``init`` on ``recordings`` of ``dataset`` (6 axes, device-checked, their later parts
    held out); returns the run's ``adaptation.json``: ``shipped`` (the fine-tuned checkpoint, or the
    starting model when the held-out parts did not say it is better), ``adopted``, the evidence."""
    record = run_dir / "adaptation.json"
    if record.is_file():
        return json.loads(record.read_text())
    from .lodo import compose_train
    from ..training.run import train_main

    recs = "[" + ",".join(f"'{r}'" for r in recordings) + "]"
    args = ["experiment=finetune", f"init={init}", f"data={dataset}", "data.axes=6", f"data.train={recs}",
            "data.fold=null", f"train.supervision={mode}", f"run_dir={run_dir}", "eval.enabled=false"]
    args += list(overrides)
    if (run_dir / "checkpoints" / "last.ckpt").is_file():
        args.append("resume=true")
    cfg = compose_train(args)
    print(f"finetune: {' '.join(args)}", flush=True)
    train_main(cfg, overrides=list(args))
    return json.loads(record.read_text())


def finetune(data_cfgs: Mapping[str, Mapping], lodo_runs: Path, runs: Path, k: int = 2,
             modes: Sequence[str] = MODES, overrides: Sequence[str] = (),
             baselines: Sequence[str] = BASELINES, out: Optional[Path] = None,
             device_check: bool = True) -> Dict[str, Any]:
    from ..datasets import load_split
    from ..estimators import registry
    from ..estimators.learned import LearnedEstimator

    rows: Dict[str, Any] = {}
    for name, cfg in data_cfgs.items():
        init = Path(lodo_runs) / name / "checkpoints" / "last.ckpt"
        if not init.is_file():
            rows[name] = {"skipped": f"no general model trained without {name} at {init} (scripts/benchmark.py lodo)"}
            continue
        mine = own_recordings(cfg, k)
        cfg = {**dict(cfg), "fold": None, "axes": 6}
        seqs = [s for s in load_split(cfg, "trainval") if s.name not in mine and s.quat is not None and s.scored().any()]
        if device_check:  # as evaluate gives the general model and the fine-tuned ones (train.device_check)
            from ..device_check import checked

            seqs = checked(seqs)
        ests = [LearnedEstimator(str(init), name="general")]
        ckpts = {"general": str(init)}
        adopted: Dict[str, bool] = {}
        for mode in modes:
            run = finetune_run(name, mode, init, mine, Path(runs) / f"{name}_{mode}", overrides)
            ests.append(LearnedEstimator(run["shipped"], name=f"finetuned_{mode}"))
            ckpts[f"finetuned_{mode}"] = run["shipped"]
            adopted[mode] = bool(run["adopted"])
        for b in baselines:
            try:
                ests.append(registry.build(b, 6))
            except Exception as e:  # noqa: BLE001 - a missing peer must not lose the row
                warnings.warn(f"finetune: baseline {b!r} unavailable, skipped: {e}")
        res = evaluate(ests, seqs, plots=False, trajectories=False, axes=6)
        means = {e.name: {m: res["methods"][e.name]["mean"].get(m) for m in METRICS} for e in ests}
        classical = {n: v for n, v in means.items() if n not in ckpts and v["aae_deg"] is not None}
        best = min(classical, key=lambda n: classical[n]["aae_deg"])
        rows[name] = {"own_recordings": mine, "scored": [s.name for s in seqs], "means": means, "best": best,
                      "checkpoints": ckpts, "adopted": adopted}
        print(f"finetune {name}: " + ", ".join(f"{n} {means[n]['aae_deg']:.2f}/{means[n]['inclination_deg']:.2f}"
                                               for n in list(ckpts) + [best]), flush=True)
    adopt_on = next((o.split("=", 1)[1] for o in overrides if o.startswith("train.adopt_on=")), "recordings")
    result = {"finetune": rows, "k": int(k), "modes": list(modes), "overrides": list(overrides), "adopt_on": adopt_on,
              "device_check": bool(device_check)}
    write_result(out, "finetune", result, markdown(result))
    return result


def markdown(result: Mapping[str, Any]) -> str:
    modes = list(result["modes"])
    head = ["general (never saw it)"] + [f"fine-tuned ({'with ground truth' if m == 'gt' else 'self-supervised'})"
                                         for m in modes] + ["backbone", "best classical"]
    lines = ["| dataset (own / scored recordings) | " + " | ".join(head) + " |", "|---" * (len(head) + 1) + "|"]

    def pair(v):
        return "–" if not v or v.get("aae_deg") is None else f"{v['aae_deg']:.2f} / {v['inclination_deg']:.2f}"

    for name, r in result["finetune"].items():
        if "skipped" in r:
            lines.append(f"| {name} | {r['skipped']} |" + " |" * (len(head) - 1))
            continue
        m = r["means"]
        kept = {x: (r.get("adopted") or {}).get(x) is False for x in modes}
        cells = [pair(m["general"])] + [pair(m.get(f"finetuned_{x}")) + (" (kept the start)" if kept[x] else "")
                                        for x in modes]
        cells += [pair(next((v for n, v in m.items() if n.startswith("backbone")), None)),
                  f"{r['best']} {pair(m[r['best']])}"]
        lines.append(f"| {name} ({len(r['own_recordings'])} / {len(r['scored'])}) | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append(f"Mean AAE / inclination in degrees (6 axes) over the dataset's other training recordings, whole; "
                 f"the {result['k']} own recordings are the first of its first fold"
                 + ("; every method on device-checked recordings" if result.get("device_check") else "")
                 + ". (kept the start): " + ("each own recording, left out of a fine-tuning of its own and scored whole,"
                                            if result.get("adopt_on") == "recordings" else
                                            "the later parts of the own recordings")
                 + " did not say the fine-tuned model is better, so the run shipped the general model "
                 "(tcn_ahrs/training/adaptation.py).")
    return "\n".join(lines) + "\n"


def finetune_main(cfg) -> Dict[str, Any]:
    """``scripts/benchmark.py finetune``: the ``finetune`` section of ``conf/benchmark.yaml``."""
    from .lodo import section_and_datasets

    t, data_cfgs = section_and_datasets(cfg, "finetune")
    out = Path(cfg.get("out") or "runs/benchmark/finetune")
    res = finetune(data_cfgs, Path(t.get("lodo_runs") or "runs/lodo"), Path(t.get("runs") or "runs/finetune"),
                   int(t.get("k") or 2), list(t.get("modes") or MODES), list(t.get("overrides") or []),
                   list(t.get("baselines") or BASELINES), out, bool(t.get("device_check", True)))
    print(markdown(res))
    print(f"results in {out}")
    return res
