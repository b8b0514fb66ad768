"""A shipped checkpoint's model card, generated from the runs' JSON.

    python scripts/model_card.py NAME CKPT CROSSVAL_JSON TRANSFER_JSON [RELEASE_LOG [SEARCH_JSON]] > checkpoints/NAME.md
    python scripts/model_card.py general6 CKPT LODO_JSON TRANSFER_JSON [RELEASE_LOG] > checkpoints/general6_residual.md
    python scripts/model_card.py NAME MODEL SEARCH_JSON TRANSFER_JSON [RELEASE_LOG] > checkpoints/NAME.md

NAME: the shipped model's name, which is also its recipe's experiment (``broad9_residual``:
``checkpoints/broad9_residual.ckpt``, ``experiment=broad9_residual``); CROSSVAL_JSON: its nested
folds (``scripts/crossval.py``); LODO_JSON: for a general model, its recipe's leave-one-dataset-out
table (``scripts/benchmark.py lodo``); TRANSFER_JSON: the cross-dataset matrix
(``scripts/benchmark.py transfer``); RELEASE_LOG: the release training's output (backbone knobs,
bias prior, wall time). SEARCH_JSON: the ``search.json`` of ``tcn-ahrs search`` whose release MODEL
is (a classical estimator file ``*.json``, or a learned family's checkpoint trained on every
training recording).
"""
import hashlib
import json
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from nested_table import rows  # noqa: E402

from tcn_ahrs.checkpoint import checkpoint_meta, load_checkpoint, model_from_checkpoint  # noqa: E402
from tcn_ahrs.config.renamed import experiment_name  # noqa: E402


def matrix_row(tr_json, name):
    """The transfer matrix's row of the shipped model ``name``."""
    return json.loads(Path(tr_json).read_text())["matrix"].get(name, {})


def cost_lines(model, log=None):
    """Parameters, footprint, FLOPs per sample and the training's wall time."""
    from tcn_ahrs.bench.common import footprint

    f = footprint(model)
    out = [f"- **Cost**: {f['parameters']:,} parameters ({f['weight_bytes'] / 1024:.0f} KiB as float32); streaming state "
           f"{f['state_floats']:,} numbers ({f['state_bytes'] / 1024:.0f} KiB: the networks' ring buffers and the filter); "
           f"{f['flops_per_sample'] / 1e3:.1f} kFLOP per sample (the networks; the filter adds a few hundred)."]
    if log and Path(log).is_file():
        m = re.search(r"training took ([0-9.]+) s", Path(log).read_text(errors="replace"))
        if m:
            out.append(f"- **Training time**: {float(m.group(1)):.0f} s on this 2-core CPU (no GPU).")
    return out


def transfer_rows(row):
    out = []
    for d, c in row.items():
        if not isinstance(c, dict) or "learned" not in c:
            continue
        l, b = c["learned"], c["best_metrics"] or {}
        out.append(f"| {d} ({c.get('split')}, {len(c['recordings'])} rec.) | {l['aae_deg']:.2f} / {l['inclination_deg']:.2f} | "
                   f"{c['best']} {b.get('aae_deg', float('nan')):.2f} | {c['best_inclination_deg']:.2f} | "
                   f"{'yes' if c['never_worse'] else '**no**'} |")
    return out


def general(name, ckpt, lodo_json, tr_json, log=None):
    """The card of a general model (``experiment=<name>``): no nested folds of one dataset;
    its recipe's leave-one-dataset-out table instead."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from tcn_ahrs.experiments.lodo import markdown as lodo_markdown

    meta = checkpoint_meta(load_checkpoint(ckpt), ckpt)
    model = model_from_checkpoint(ckpt)
    res = meta["model"].get("residual", {})
    knobs = {k: v for k, v in res.items() if k != "backbone"}
    lo, hi = meta["layout"].get("rate_range_hz") or (None, None)
    data = Path(ckpt).read_bytes()
    out = [f"# `{Path(ckpt).name}` — model card\n",
           f"- **Model**: one {meta['layout']['axes']}-axis model for any IMU: learned residuals on the VQF-grade backbone "
           f"(`experiment={name}`), two causal TCNs (receptive field {model.receptive_field} samples).",
           f"- **Rates**: trained on windows resampled to random rates {lo:g}–{hi:g} Hz (irregular steps too), so any "
           "recording in that range runs as the model, without a warning and without resampling; outside it, as the backbone.",
           f"- **Data**: the training parts of `{meta.get('data')}` (every dataset the same number of windows per epoch), "
           "each window in a random mounting orientation with a random gyro offset and scale error; the later parts "
           "(validation) chose the inference knobs; the fixed schedule's last epoch ships.",
           f"- **Backbone knobs** (chosen on the training parts): `{res.get('backbone')}`; the bias state starts at zero "
           "(no one device's bias).",
           f"- **Inference knobs** (chosen on the validation parts): `{knobs}`.",
           f"- **Size / sha256**: {len(data) / 1e6:.2f} MB, `{hashlib.sha256(data).hexdigest()}`"]
    out += cost_lines(model, log)
    out += ["", "```bash", f"python scripts/train.py experiment={name} run_dir=runs/general/{name}",
            f"python scripts/release_checkpoint.py runs/general/{name}/checkpoints/last.ckpt checkpoints/{name}.ckpt", "```", ""]
    if lodo_json and Path(lodo_json).is_file():
        lj = json.loads(Path(lodo_json).read_text())
        out += ["## Datasets it never saw: the same recipe, one dataset left out (`python scripts/benchmark.py lodo`)", "",
                lodo_markdown(lj)]
    else:
        out += ["## Datasets it never saw", "",
                f"Not measured for this recipe: `python scripts/benchmark.py lodo lodo.experiment={name} "
                "'lodo.datasets=[broad,oxiod]'` would leave BROAD or OxIOD out (not run yet: CPU time).", ""]
    out += ["## Held-out test recordings (`python scripts/benchmark.py transfer`)", "",
            "| data (split) | this checkpoint | best classical (AAE) | best inclination | never worse? |",
            "|---|---|---|---|---|"]
    out += transfer_rows(matrix_row(tr_json, name))
    out += ["", "**Limits**: the networks learned their gains at the training datasets' own rates; on BROAD's test trials "
            "resampled to 50-1000 Hz they cost accuracy against the backbone at the same rate (the rate sweep in "
            "`docs/results/general_2026-12-03.md`): the model runs at any rate, its learned part helps at the rates it "
            "saw most. On a dataset it never saw it is not never worse than the best classical filter (leave-one-dataset-out "
            "table): fine-tune on your recordings (`experiment=finetune`)."]
    print("\n".join(out))


FORMATS = {"classical": "`tcn-ahrs evaluate ckpt=FILE` runs it (Python); `tcn-ahrs export` says in one line that a "
                        "classical family is not exported yet (its C kernel is the next step of the deployment issue)",
           "closed_loop": "`tcn-ahrs export` writes TorchScript, ONNX and torch.export streaming steps; the C runtime "
                          "holds the residual models only and says so in one line"}


def search_card(name, model, search_json, tr_json, log=None):
    """The card of a model the family search chose: what was chosen, how often, with which knobs,
    the search's nested table (every outer fold beside the best classical filter), transfer."""
    from results_tables import _search_summary

    from tcn_ahrs.estimators.families import is_estimator_file, read_estimator

    result = json.loads(Path(search_json).read_text())
    rel = result["release"]
    data = Path(model).read_bytes()
    out = [f"# `{Path(model).name}` — model card\n",
           f"- **Chosen by** `tcn-ahrs search` on {result['dataset']} ({result['axes']}-axis): **{rel['chosen']}**, the "
           f"candidate chosen on the most outer folds (each fold chooses once over its seeds; {rel['times_chosen']} of "
           f"{rel['runs']} fold × seed runs; a tie is read on the inner validation, then goes to the simpler family), "
           "refitted on every training recording.",
           f"- **Size / sha256**: {len(data) / 1024:.1f} KiB, `{hashlib.sha256(data).hexdigest()}`"]
    if is_estimator_file(model):
        doc = read_estimator(model)
        cal = doc.get("calibration")
        out += [f"- **Family**: `{doc['family']}` (a classical filter: nothing learned), knobs `{doc['knobs'] or 'defaults'}`; "
                f"static calibration: {'none' if cal is None else cal}.",
                f"- **Fitted on**: {', '.join(doc['provenance'].get('recordings', []))}.",
                f"- **Runs with**: {FORMATS['classical']}."]
    else:
        meta = checkpoint_meta(load_checkpoint(model), model)
        m = model_from_checkpoint(model)
        out += [f"- **Family**: `{rel['family']}` (learned: `tcn_ahrs/model/closed_loop.py`), {meta['layout']['axes']}-axis, "
                f"{m.num_parameters():,} parameters, receptive field {m.receptive_field} samples at "
                f"{meta['layout'].get('rate_hz') or 0:.1f} Hz; trained on every training recording of `{meta.get('data')}`, "
                "whole (`train.all_recordings=true`); the fixed schedule's last epoch ships (nothing selected).",
                f"- **Runs with**: {FORMATS['closed_loop']}."]
        m_ = re.search(r"training took ([0-9.]+) s", Path(log).read_text(errors="replace")) if log and Path(log).is_file() else None
        if m_:
            out.append(f"- **Training time**: {float(m_.group(1)):.0f} s on this 2-core CPU (no GPU).")
        out += ["", "```bash", f"tcn-ahrs train experiment={name} train.all_recordings=true run_dir=runs/release/{name}",
                f"python scripts/release_checkpoint.py runs/release/{name}/checkpoints/last.ckpt checkpoints/{name}.ckpt",
                "```"]
    out += ["", "**Limits**: chosen for this dataset's device. On other devices it is not never worse (the transfer "
            "table below): a tuned filter's knobs and a learned model's bias prior belong to their IMU; a recording at "
            "another rate runs a learned model as the backbone with VQF's defaults, one at the same rate does not.",
            "", "## Nested outer folds over seeds (the search; degrees, the yardstick of docs/conventions.md)", "",
            _search_summary(result),
            "## Recordings it never saw (`python scripts/benchmark.py transfer`)", "",
            "| data (split) | this model | best classical (AAE) | best inclination | never worse? |",
            "|---|---|---|---|---|"]
    out += transfer_rows(matrix_row(tr_json, name))
    print("\n".join(out))


def search_section(name, search_json):
    """For a learned model the family search did not release but the project keeps: the search's
    table and why it stays (compared on the same folds)."""
    from results_tables import _search_summary

    result = json.loads(Path(search_json).read_text())
    rel = result["release"]
    return ["", f"## The family search on {result['dataset']} ({result['axes']}-axis)", "",
            f"The search's release is **{rel['chosen']}** ({rel['times_chosen']} of {rel['runs']} fold × seed runs). "
            "This model is kept because on the same nested folds it is at or below that release (the project "
            "never ships a result worse than one it already has; docs/results.md, \"What ships\").", "",
            _search_summary(result)]


def main(name, ckpt, cv_json, tr_json, log=None, search_json=None):
    if name.startswith("general"):
        return general(name, ckpt, cv_json, tr_json, log)
    if "release" in json.loads(Path(cv_json).read_text()):
        return search_card(name, ckpt, cv_json, tr_json, log)
    from tcn_ahrs.checkpoint import networks_off

    meta = checkpoint_meta(load_checkpoint(ckpt), ckpt)
    model = model_from_checkpoint(ckpt)
    res = meta["model"].get("residual", {})
    knobs = {k: v for k, v in res.items() if k != "backbone"}
    data = Path(ckpt).read_bytes()
    # the recipe: what the file records (tcn-ahrs train stores its overrides); files trained before
    # that record say so — the card does not guess it from the file's name
    recipe = meta.get("recipe")
    exp = next((experiment_name(o.split("=", 1)[1]) for o in (recipe or {}).get("overrides", [])
                if o.startswith("experiment=")), None)   # a recipe recorded under an old name: its new one
    said = (f"`{recipe['command']} {' '.join(recipe['overrides'])}`" if recipe
            else "recipe not recorded in the file (trained before checkpoints kept it)")
    channels = (meta["model"].get("tcn") or {}).get("channels")
    off = networks_off(ckpt)
    what = ("**the VQF-grade backbone with tuned knobs**: its inference knobs switch both residual networks off "
            "(`gyro_clip` 0, `trust_weight` 0), so it runs as that classical filter; the file carries "
            f"{model.num_parameters():,} unused network parameters" if off else
            "learned residuals on the VQF-grade backbone")
    out = [f"# `{Path(ckpt).name}` — model card\n",
           f"- **Model**: {what} ({said}, channels {channels}), "
           f"{meta['layout']['axes']}-axis, {model.num_parameters():,} parameters (two causal TCNs, receptive field "
           f"{model.receptive_field} samples at {meta['layout'].get('rate_hz') or 0:.1f} Hz).",
           f"- **Backbone knobs** (chosen on the training recordings): `{res.get('backbone')}`; bias state starts at "
           f"{[round(float(v), 5) for v in model.backbone.bias_init]} rad/s.",
           f"- **Inference knobs** (chosen on the nested folds' inner validation sets, averaged over folds): `{knobs}`.",
           f"- **Data**: every training recording of `{meta.get('data')}`, whole (`train.all_recordings=true`); the "
           "fixed schedule's last epoch ships; nothing held out, nothing selected.",
           f"- **Size / sha256**: {len(data) / 1e6:.2f} MB, `{hashlib.sha256(data).hexdigest()}`"]
    out += cost_lines(model, log)
    if recipe:
        out += ["", "```bash", f"{recipe['command']} {' '.join(recipe['overrides'])}",
                f"python scripts/release_checkpoint.py runs/release/{name}/checkpoints/last.ckpt checkpoints/{name}.ckpt",
                "```"]
    out += ["", f"## Nested folds ({f'`python scripts/crossval.py experiment={exp}`' if exp else 'its recipe'}), "
            "mean AAE / inclination, degrees", "",
            "| outer fold | learned | VQF | best classical (AAE) | best inclination | never worse? |", "|---|---|---|---|---|---|"]
    for fold, l, v, best, b, bi, i, ok in rows(json.loads(Path(cv_json).read_text())):
        vq = f"{v['aae_deg']:.2f} / {v['inclination_deg']:.2f}" if v else "–"
        out.append(f"| {fold} | {l['aae_deg']:.2f} / {l['inclination_deg']:.2f} | {vq} | {best} {b:.2f} | {bi} {i:.2f} | "
                   f"{'yes' if ok else '**no**'} |")
    out += ["", "## Recordings it never saw (`python scripts/benchmark.py transfer`)", "",
            "| data (split) | this checkpoint | best classical (AAE) | best inclination | never worse? |",
            "|---|---|---|---|---|"]
    out += transfer_rows(matrix_row(tr_json, name))
    if search_json:
        out += search_section(name, search_json)
    print("\n".join(out))


if __name__ == "__main__":
    if len(sys.argv) not in (5, 6, 7):
        sys.exit(__doc__)
    main(*sys.argv[1:])
