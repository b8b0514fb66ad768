"""The generated tables of README.md and docs/results.md, rendered from the runs' JSON.

    python scripts/results_tables.py            # rewrite every generated block from its JSON
    python scripts/results_tables.py --check    # exit 1 if a block differs from what its JSON gives

A number measured by a run is written once: in that run's JSON summary, committed under
``docs/results/json/`` (``runs/`` itself is not committed). Each table that quotes it is a
*generated block* in a markdown file, between the markers

    <!-- generated:NAME begin -->
    ...
    <!-- generated:NAME end -->

and this script is the only writer of what lies between them. To refresh a table: run the
command that produced the JSON, copy its JSON over the committed one, run this script, commit.

Blocks (:data:`BLOCKS`):

``transfer_matrix`` (docs/results.md)
    The cross-dataset matrix, ``python scripts/benchmark.py transfer`` →
    ``runs/benchmark/transfer/transfer.json``, rendered by the very function that writes the
    run's own ``transfer.md`` (:func:`tcn_ahrs.experiments.transfer.markdown`).
``deploy`` (docs/deployment.md)
    The speed benchmark's ``deploy`` section (``tcn-ahrs benchmark speed '+speed.sections=[deploy]'``
    → ``speed.json``): every runtime side by side and the shipped models' footprint.
``search_<dataset>`` (docs/results.md)
    The nested family search (``tcn-ahrs search data=<dataset> ...`` → ``runs/search/<dataset>/summary.json``,
    copied to ``docs/results/json/search_<dataset>.json``): per outer fold the choice of each seed
    beside the best classical filter with its defaults, raw and calibrated
    (:func:`tcn_ahrs.experiments.search.summary_markdown`, the run's own ``search.md`` summary).
``device_check`` (docs/results.md)
    The device check (no ground truth) on and off: ``tcn-ahrs evaluate data=<d> data.split=trainval
    'baselines=[vqf,backbone,ecf,mahony]' device_check=true|false`` per dataset, the runs' mean AAE
    per method collected by ``python scripts/results_tables.py --collect-device-check DIR`` (DIR
    holding ``<d>_true/`` and ``<d>_false/``) into ``docs/results/json/device_check.json``.
``lodo6`` / ``lodo9`` (docs/results.md)
    Leave one dataset out, ``tcn-ahrs benchmark lodo`` (6 axes) and ``tcn-ahrs benchmark lodo
    lodo.experiment=general9_residual lodo.runs=runs/lodo9`` → ``runs/benchmark/lodo/lodo.json``, copied to
    ``docs/results/json/lodo<axes>.json``, rendered by :func:`tcn_ahrs.experiments.lodo.markdown`.
``finetune`` (docs/results.md)
    Fine-tuning on two recordings of a device the general model never saw, ``tcn-ahrs benchmark
    finetune`` → ``runs/benchmark/finetune/finetune.json``, copied to ``docs/results/json/finetune.json``,
    rendered by :func:`tcn_ahrs.experiments.finetune.markdown`.
``finetune_crossfit`` (docs/results.md)
    The same benchmark with the adoption cross-fitted on the own recordings (``train.adopt_on:
    recordings``, 2026-12-07): ``tcn-ahrs benchmark finetune 'finetune.datasets=[broad,euroc,oxiod]'
    'finetune.modes=[gt]'`` → ``docs/results/json/finetune_crossfit.json``.
``rates`` (docs/results.md)
    The general models on BROAD's test trials resampled to 50-1000 Hz, ``tcn-ahrs benchmark transfer
    'transfer.ckpts={general6: checkpoints/general6_residual.ckpt, general9: checkpoints/general9_residual.ckpt}'
    'transfer.datasets=[broad]' 'transfer.rates=[50,100,200,500,1000]'`` → ``rates.json``, copied to
    ``docs/results/json/rates.json``, rendered by :func:`tcn_ahrs.experiments.transfer.rates_markdown`.
``fault_trial`` (docs/troubleshooting.md)
    Faults in a user's recordings on BROAD clips through ``tcn-ahrs evaluate``, before and now:
    ``python -m tcn_ahrs.bench.fault_trial B --code CHECKOUT_OF_1d5b769``, then ``python -m
    tcn_ahrs.bench.fault_trial N --before B/fault_trial.json`` → ``N/fault_trial.json``, copied to
    ``docs/results/json/fault_trial.json``, rendered by :func:`tcn_ahrs.bench.fault_trial.markdown`.
``devices`` (docs/results.md)
    The gate on every real recording, ``tcn-ahrs benchmark devices`` → ``runs/benchmark/devices/devices.json``,
    copied to ``docs/results/json/devices.json``, rendered by :func:`tcn_ahrs.experiments.devices.markdown`
    (the default's recordings worse than VQF listed).
``causality`` (docs/results.md)
    The cost of the default's offline device check against what a device runs, ``python scripts/causality.py``
    → ``docs/results/json/causality.json``, rendered by :func:`tcn_ahrs.experiments.devices.causality_markdown`.
``transfer_summary`` (README.md)
    The same JSON, compact: per shipped checkpoint, on each dataset, the learned model's mean AAE
    (inclination) beside the best classical filter on the same recordings, and whether it is
    never worse (the ``never_worse`` the run computed).
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, NamedTuple, Tuple

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # this checkout's package, not another installed copy
    sys.path.insert(0, str(REPO))

from tcn_ahrs.experiments import lodo as _lodo  # noqa: E402
from tcn_ahrs.experiments import devices as _devices  # noqa: E402
from tcn_ahrs.experiments import finetune as _finetune  # noqa: E402
from tcn_ahrs.experiments import transfer as _transfer  # noqa: E402
from tcn_ahrs.bench import fault_trial as _fault_trial  # noqa: E402

TRANSFER_JSON = "docs/results/json/transfer.json"
DEPLOY_JSON = "docs/results/json/deploy.json"
DEVICE_CHECK_JSON = "docs/results/json/device_check.json"


# ------------------------------------------------------------------------------- renderings
def _deploy_markdown(result: Mapping[str, Any]) -> str:
    """Every deployment runtime side by side and the shipped models' footprint: the speed
    benchmark's ``deploy`` section (:func:`tcn_ahrs.bench.deploy.markdown`), with its machine."""
    from tcn_ahrs.bench.deploy import markdown

    env = result.get("environment") or {}
    load = ", ".join(f"{x:.2f}" for x in env.get("loadavg_start") or [])
    head = (f"Measured {env.get('date', '?')} on {env.get('cpu', '?')} ({env.get('cpu_count', '?')} logical cores), "
            f"git {env.get('git_commit', '?')}, load average at the start {load or '?'}: "
            "`tcn-ahrs benchmark speed '+speed.sections=[deploy]'`.")
    return head + "\n\n" + markdown(result["deploy"])


def transfer_matrix(result: Mapping[str, Any]) -> str:
    """The full matrix: exactly the run's own ``transfer.md``."""
    return _transfer.markdown(result)


def _own(row: Mapping[str, Any]) -> List[str]:
    return _transfer.own_datasets(str(row["trained_on"]))


def _cell(c: Mapping[str, Any]) -> str:
    """``learned AAE (incl.) vs best classical AAE (lowest classical incl.)`` and ✓/✗."""
    l, b = c["learned"], c["best_metrics"] or {}
    mark = "✓" if c["never_worse"] else "✗"
    return (f"{l['aae_deg']:.2f} ({l['inclination_deg']:.2f}) vs "
            f"{b.get('aae_deg', float('nan')):.2f} ({c['best_inclination_deg']:.2f}) {mark}")


def transfer_summary(result: Mapping[str, Any]) -> str:
    """The README's table: one row per checkpoint, one column per dataset. A cell on the
    checkpoint's own dataset (its visible test split) is in italics; ``trained on it``: its own
    dataset without a visible test split (its nested folds are in docs/results.md); ``–``: a
    9-axis checkpoint on 6-axis data."""
    matrix = result["matrix"]
    names = [d for d in _transfer.DATASETS if any(d in row for row in matrix.values())]
    lines = ["| checkpoint | " + " | ".join(names) + " | never worse |", "|---" * (len(names) + 2) + "|"]
    tally = {"own": [0, 0], "other": [0, 0]}
    for label, row in matrix.items():
        own = _own(row)
        cells, ok, n = [], 0, 0
        for d in names:
            c = row.get(d)
            if c is None:
                cells.append("–")
            elif "skipped" in c:
                cells.append("trained on it")
            else:
                text = _cell(c)
                kind = "own" if d in own else "other"
                cells.append(f"*{text}*" if kind == "own" else text)
                ok += bool(c["never_worse"])
                n += 1
                tally[kind][0] += bool(c["never_worse"])
                tally[kind][1] += 1
        family = f", {row['family']}" if row.get("family") else ""
        lines.append(f"| {label} ({row['axes']}-axis{family}) | " + " | ".join(cells) + f" | {ok} of {n} |")
    baselines = ", ".join(str(b) for b in result.get("baselines", []))
    own_ok, own_n = tally["own"]
    other_ok, other_n = tally["other"]
    lines += ["", f"Mean AAE (inclination) in degrees, the shipped model (its family in the first column: a "
                  f"learned model, or a classical filter the family search chose) vs the best classical filter on the same "
                  f"recordings (lowest mean AAE of {baselines}; in brackets the lowest inclination of any of "
                  f"them); ✓ = never worse in both. *Italics*: the checkpoint's own dataset, its test split "
                  f"(training never saw it); other cells: datasets it never saw, all their training "
                  f"recordings; trained on it: its own dataset has no visible test split (its nested "
                  f"folds are in [docs/results.md](docs/results.md)); –: a 9-axis checkpoint on 6-axis data. "
                  f"Never worse in {own_ok + other_ok} of {own_n + other_n} cells: {own_ok} of {own_n} on "
                  f"its own data, {other_ok} of {other_n} on data it never saw. "
                  f"Source: [{TRANSFER_JSON}]({TRANSFER_JSON}) (`tcn-ahrs benchmark transfer`)."]
    return "\n".join(lines) + "\n"


class Block(NamedTuple):
    source: str                                 # the JSON, relative to the repository root
    render: Callable[[Mapping[str, Any]], str]  # JSON -> markdown
    files: Tuple[str, ...]                      # where the block stands


def _search_summary(result: Mapping[str, Any]) -> str:
    """The search's command (from its recorded config) and its summary table."""
    from tcn_ahrs.experiments.search import summary_markdown

    cfg = result.get("config") or {}
    hy = lambda v: "[" + ",".join(str(x) for x in v) + "]" if isinstance(v, list) else (  # noqa: E731
        "{" + ", ".join(f"{k}: {x}" for k, x in v.items()) + "}" if isinstance(v, dict) else str(v))
    from tcn_ahrs.evaluate.main import dataset_axes

    parts = [f"data={result['dataset']}"]
    if dataset_axes(str(result["dataset"])) not in (None, int(result["axes"])):
        parts.append(f"data.axes={result['axes']}")
    parts += [f"search.trials={cfg.get('trials')}", f"'search.seeds={hy(cfg.get('seeds'))}'"]
    from tcn_ahrs.config import SearchSection

    default = SearchSection()
    for key in ("families", "calibrations", "learned"):
        if cfg.get(key) and cfg[key] != getattr(default, key):
            parts.append(f"'search.{key}={hy(cfg[key])}'")
    if list(cfg.get("learn") or []) != default.learn:  # a record from before search.learn had none
        parts.append(f"'search.learn={hy(list(cfg.get('learn') or []))}'")
    if cfg.get("learn") and cfg.get("budget_minutes") != default.budget_minutes:
        parts.append(f"search.budget_minutes={cfg.get('budget_minutes')}")
    if cfg.get("tune_seconds"):
        parts.append(f"search.tune_seconds={cfg['tune_seconds']}")
    return f"`tcn-ahrs search {' '.join(parts)}`\n\n" + summary_markdown(result)


SEARCHES = tuple(p.stem[len("search_"):] for p in sorted((REPO / "docs/results/json").glob("search_*.json")))


def shipped_summary(result: Mapping[str, Any]) -> str:
    """The README's table of what ships per dataset: each shipped model of the transfer matrix
    that belongs to one dataset, its family, and that dataset's family search (its release, the
    mean over outer folds and seeds beside the best classical filter with its defaults, never
    worse over fold × seed runs) from ``docs/results/json/search_<dataset>[6].json``."""
    import numpy as np

    lines = ["| file | family | the search's release | search, mean AAE over folds × seeds (best classical, "
             "defaults) | never worse |", "|---|---|---|---|---|"]
    for label, row in result["matrix"].items():
        data, axes = str(row.get("trained_on", "")), int(row["axes"])
        found = [REPO / "docs/results/json" / f"search_{data}{suffix}.json" for suffix in ("", str(axes))]
        found = [f for f in found if f.is_file() and int(json.loads(f.read_text())["axes"]) == axes]
        if not found or label.endswith("_small"):
            continue
        srch = json.loads(found[0].read_text())
        rows = srch["rows"]
        ext = ".ckpt" if (REPO / "checkpoints" / f"{label}.ckpt").is_file() else ".json"
        lines.append(f"| `checkpoints/{label}{ext}` | {row.get('family', '?')} | {srch['release']['chosen']} | "
                     f"{np.mean([r['aae_deg'] for r in rows]):.2f} ({np.mean([r['best_classical_aae_deg'] for r in rows]):.2f}) | "
                     f"{sum(r['never_worse'] for r in rows)} of {len(rows)} |")
    lines += ["", "Degrees, the yardstick ([docs/conventions.md](docs/conventions.md)); every fold's table with its "
                  "command: [docs/results.md](docs/results.md#the-yardstick-and-the-family-search-2026-12-05). Where "
                  "the file's family is not the release, the project kept an earlier model that is at or below the "
                  "release on the same folds."]
    return "\n".join(lines) + "\n"

def collect_device_check(runs: Path) -> Dict[str, Any]:
    """{dataset: {"true"|"false": {method: mean AAE}, "recordings": n}} from the evaluate runs in
    ``runs`` (``<dataset>_true/results.json``, ``<dataset>_false/results.json``)."""
    out: Dict[str, Any] = {}
    for f in sorted(Path(runs).glob("*_true/results.json")):
        d = f.parent.name[:-len("_true")]
        row: Dict[str, Any] = {}
        for mode in ("true", "false"):
            res = json.loads((Path(runs) / f"{d}_{mode}" / "results.json").read_text())["methods"]
            # one column per method whatever the data's axes (vqf6d / vqf9d -> vqf)
            row[mode] = {re.sub(r"[69]d$", "", m): sum(r["aae_deg"] for r in v["recordings"]) / len(v["recordings"])
                         for m, v in res.items()}
            row["recordings"] = len(next(iter(res.values()))["recordings"])
        out[d] = row
    return out


def device_check_table(result: Mapping[str, Any]) -> str:
    methods = list(next(iter(result.values()))["true"])
    lines = ["| data (training recordings) | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
    for d, row in result.items():
        cells = [f"{row['false'][m]:.2f} → **{row['true'][m]:.2f}**" for m in methods]
        lines.append(f"| {d} ({row['recordings']}) | " + " | ".join(cells) + " |")
    lines += ["", "Mean AAE in degrees (the yardstick), without → with the device check; `Learned AHRS` is the "
                  "general model for the data's axes (general6 / general9)."]
    return "\n".join(lines) + "\n"


BLOCKS: Dict[str, Block] = {
    **{f"search_{d}": Block(f"docs/results/json/search_{d}.json", _search_summary, ("docs/results.md",))
       for d in SEARCHES},
    "transfer_summary": Block(TRANSFER_JSON, transfer_summary, ("README.md",)),
    "shipped": Block(TRANSFER_JSON, shipped_summary, ("README.md",)),
    "transfer_matrix": Block(TRANSFER_JSON, transfer_matrix, ("docs/results.md",)),
    "deploy": Block(DEPLOY_JSON, lambda result: _deploy_markdown(result), ("docs/deployment.md",)),
    "device_check": Block(DEVICE_CHECK_JSON, device_check_table, ("docs/results.md",)),
    **{f"lodo{a}": Block(f"docs/results/json/lodo{a}.json", lambda result: _lodo.markdown(result), ("docs/results.md",))
       for a in (6, 9)},
    "finetune": Block("docs/results/json/finetune.json", lambda result: _finetune.markdown(result), ("docs/results.md",)),
    "finetune_crossfit": Block("docs/results/json/finetune_crossfit.json", lambda result: _finetune.markdown(result),
                               ("docs/results.md",)),
    "rates": Block("docs/results/json/rates.json", lambda result: _transfer.rates_markdown(result), ("docs/results.md",)),
    "devices": Block("docs/results/json/devices.json", lambda result: _devices.markdown(result, listed=("default",)),
                     ("docs/results.md",)),
    "causality": Block("docs/results/json/causality.json", lambda result: _devices.causality_markdown(result),
                       ("docs/results.md",)),
    "fault_trial": Block("docs/results/json/fault_trial.json", lambda result: _fault_trial.markdown(result),
                         ("docs/troubleshooting.md",)),
}


# ------------------------------------------------------------------------------- the blocks
def _markers(name: str) -> Tuple[str, str]:
    return f"<!-- generated:{name} begin -->", f"<!-- generated:{name} end -->"


def render(name: str, repo: Path = REPO) -> str:
    """Block ``name`` as its JSON gives it (the text between the markers, newline-framed)."""
    b = BLOCKS[name]
    result = json.loads((Path(repo) / b.source).read_text())
    return "\n" + b.render(result).strip("\n") + "\n"


def read_block(text: str, name: str) -> str:
    """The text between ``name``'s markers in ``text`` (ValueError when they are missing or
    not exactly once each)."""
    begin, end = _markers(name)
    if text.count(begin) != 1 or text.count(end) != 1 or text.index(begin) > text.index(end):
        raise ValueError(f"expected the markers {begin!r} ... {end!r} exactly once, in that order")
    return text[text.index(begin) + len(begin):text.index(end)]


def write_block(text: str, name: str, content: str) -> str:
    begin, end = _markers(name)
    read_block(text, name)
    return text[:text.index(begin) + len(begin)] + content + text[text.index(end):]


def generated_blocks(text: str) -> List[str]:
    """Names of every generated block in ``text``."""
    return re.findall(r"<!-- generated:(\S+) begin -->", text)


def update(repo: Path = REPO, check: bool = False) -> List[str]:
    """Rewrite (or with ``check`` only compare) every block; returns ``file: block`` for each one
    that differed (or whose markers are missing)."""
    stale: List[str] = []
    for name, b in BLOCKS.items():
        want = render(name, repo)
        for f in b.files:
            p = Path(repo) / f
            text = p.read_text()
            try:
                have = read_block(text, name)
            except ValueError as e:
                stale.append(f"{f}: {name}: {e}")
                continue
            if have != want:
                stale.append(f"{f}: {name}")
                if not check:
                    p.write_text(write_block(text, name, want))
    return stale


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if a block differs from its JSON; write nothing")
    ap.add_argument("--collect-device-check", metavar="DIR", help=f"write {DEVICE_CHECK_JSON} from the evaluate runs in DIR")
    args = ap.parse_args(argv)
    if args.collect_device_check:
        (REPO / DEVICE_CHECK_JSON).write_text(json.dumps(collect_device_check(Path(args.collect_device_check)), indent=1))
    stale = update(REPO, check=args.check)
    for s in stale:
        print(("differs from its JSON: " if args.check else "rewritten: ") + s)
    missing = [s for s in stale if ": expected the markers" in s]
    if args.check and stale or missing:
        return 1
    if not stale:
        print("every generated block equals its JSON")
    return 0


if __name__ == "__main__":
    sys.exit(main())
