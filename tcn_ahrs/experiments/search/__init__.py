"""One nested search over estimator families: the best attitude estimator for a device, chosen by
evidence (``tcn-ahrs search``).

For each outer fold ``i`` of ``data.folds`` (the recordings scored, which choose nothing):

1. the other training recordings give the inner splits (``search.inner``: with ≥ 3 folds every
   other fold, whole, validates in turn — one validation fold alone is too few recordings to
   choose on; else the later parts of the recordings, :func:`tcn_ahrs.experiments.crossval.inner_split`);
2. every candidate is fitted on each inner training set only: a classical family
   (:data:`FAMILIES`: strapdown integration, ECF, Mahony, Madgwick, the VQF-grade backbone with
   VQF's full parameter set), with its defaults or with its knobs searched by Optuna (TPE, seeded,
   the defaults tried first; the studies in SQLite under the output folder, so a killed search
   resumes), on the raw signals or on a static calibration (:mod:`tcn_ahrs.calibration`: gyro
   bias; gyro matrix + accelerometer offset + magnetometer ellipsoid) fitted on the same set;
3. the inner validation sets choose (:func:`choose`): the lowest mean AAE among the candidates
   whose inclination is within ``incl_margin`` of the best default filter's, a simpler family
   (:data:`SIMPLICITY`) winning within ``tie_margin``; a learned candidate — a recipe of
   ``search.learn`` trained here on the first inner training set (:mod:`.learn`, within
   ``search.budget_minutes``), or a fold checkpoint that ``tcn-ahrs crossval`` trained without fold
   ``i`` and its inner fold (``search.learned``: ``{family: crossval folder}``) — replaces the
   classical choice only if its gain over that split's validation recordings stands above the
   margin plus its spread (:func:`.learn.gain_supported`);
4. the classical candidates are fitted again on all the outer training recordings (nested
   cross-validation's refit) and scored on fold ``i``, beside the bar: every family with its
   defaults, on the raw and on the calibrated signals — all with the one yardstick
   (:mod:`tcn_ahrs.metrics`).

``search.seeds`` repeats steps 2–4 with other sampler seeds, and the fold chooses once from the
inner scores averaged over them (:func:`fold_choice`); the report gives mean and spread of the
outer scores. Each fold × seed record is written to ``search.out/records/`` (resume; Hydra
multirun jobs); the release is :func:`release_choice`. Writes ``search.json``, ``summary.json``
and ``search.md``; the numbers are the runner's (:func:`tcn_ahrs.evaluate.evaluate`).
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence

from ... import verdict
from ...estimators.families import CALIBRATIONS, FAMILIES, SIMPLICITY, Calibrated, Family, mean_scores  # noqa: F401
from .choice import best_classical, choose, choose_candidate, fold_choice, release_choice, simplicity_rank  # noqa: F401
from .fold import (_fit_candidate, _inner_splits, _learned_candidates, auto_folds, candidate_names,  # noqa: F401
                   search_fold, tune_family)
from .records import RECIPE_KEYS, _read_record, _write_record, multirun_job  # noqa: F401
from .learn import check_recipes, data_overrides, train_fold_candidates
from .progress import Budget, Progress
from .report import expected_gain, final_summary, search_markdown, summary_markdown  # noqa: F401


def search_main(cfg) -> Dict[str, Any]:
    """``tcn-ahrs search``: the nested family search over ``data.folds`` (module docstring)."""
    from omegaconf import OmegaConf

    from ...config import SearchSection, check_keys
    from ..crossval import _fold_cfg
    from ...datasets import load_split
    from ...training.setup import model_axes

    sc = cfg.search
    check_keys(sc, SearchSection, "search")
    folds = list(OmegaConf.to_container(cfg.data.get("folds"), resolve=True) or []) if cfg.data.get("folds") else []
    if not folds:
        folds = auto_folds(cfg)
    idx = list(sc.folds) if sc.get("folds") is not None else list(range(len(folds)))
    inner_cfg = OmegaConf.create({"crossval": {"inner": str(sc.inner)}, "data": OmegaConf.to_container(cfg.data)})
    out = Path(str(sc.get("out") or f"runs/search/{cfg.data.name}_{model_axes(cfg)}"))
    out.mkdir(parents=True, exist_ok=True)
    storage = f"sqlite:///{(out / 'search.db').resolve()}"
    axes = model_axes(cfg)
    families = list(sc.families)
    unknown = [f for f in families if f not in FAMILIES]
    if unknown:
        raise ValueError(f"search.families: unknown {unknown}; expected some of {list(FAMILIES)}")
    calibs = list(sc.calibrations)
    bad = [c for c in calibs if c not in CALIBRATIONS]
    if bad:
        raise ValueError(f"search.calibrations: unknown {bad}; expected some of {list(CALIBRATIONS)}")
    learned_spec = dict(OmegaConf.to_container(sc.learned, resolve=True) or {}) if sc.get("learned") else {}
    learn = check_recipes(list(sc.get("learn") or []))
    settings = OmegaConf.to_container(sc, resolve=True)
    lighter = skipped(settings, len(folds))
    print("search settings: " + ("; ".join(lighter) if lighter else "the full search (nothing skipped)"), flush=True)
    seeds = [int(seed) for seed in sc.seeds]
    budget = Budget(sc.get("budget_minutes"), 2 * len(learn) * len(idx) + (1 if learn else 0), len(idx))  # cross-fitted: 2 each
    print(budget.describe(len(learn)), flush=True)
    t_start = time.perf_counter()
    job = multirun_job()
    recipe = {k: settings.get(k) for k in RECIPE_KEYS}
    recipe["folds"] = folds
    records: List[Dict[str, Any]] = []
    read_seconds = 0.0  # the compute time of records an earlier run or another job wrote
    bar = Progress(len(idx) * (len(seeds) * 2 * len(candidate_names(families, calibs)) + len(learn)), "search")
    for i in idx:
        done = {seed: _read_record(out, i, seed, recipe) for seed in seeds}
        fold_data: Dict[str, Any] = {}

        def data(i=i, fold_data=fold_data):  # the fold's recordings, loaded once and only if needed
            if not fold_data:
                fcfg = _fold_cfg(cfg, i, out / f"fold{i}")
                splits, learned_split, inner = _inner_splits(str(sc.inner), folds, i, fcfg, inner_cfg)
                fold_data.update(splits=splits, learned_split=learned_split,
                                 others=[s for s in load_split(fcfg.data, "train") if s.has_gt],
                                 test=[s for s in load_split(fcfg.data, "val") if s.has_gt])
                print(f"== outer fold {i}: scored on {[s.name for s in fold_data['test']]}; {inner}", flush=True)
            return fold_data

        read_seconds += sum(float(r["seconds"]) + float(r.get("learn_seconds", 0.0)) for r in done.values() if r is not None)
        if all(r is not None for r in done.values()):  # every seed of this fold ran (earlier, or another job)
            print(f"== outer fold {i}: seeds {seeds} read from {out / 'records'}", flush=True)
        learned, t_learn = None, None
        for seed in seeds:
            if done[seed] is None:
                d = data()
                if learned is None:
                    learned = _learned_candidates(learned_spec, i, str(sc.get("learned_checkpoint") or "last"))
                    # the learned recipes trained on the inner split crossval's candidates are validated on
                    tr, va = d["splits"][d["learned_split"]]
                    t_learn = time.perf_counter()
                    learned.update(train_fold_candidates(learn, out, i, tr, va, data_overrides(cfg.data, axes), axes,
                                                         budget, log=bar.write,
                                                         progress=lambda name: bar.step(f"fold {i}: {name} trained"),
                                                         lodo_runs=_lodo_runs(sc)))
                rec = search_fold(i, d["splits"], d["others"], d["test"], axes, families, calibs, int(sc.trials), seed,
                                  storage, learned, d["learned_split"], float(sc.tie_margin), float(sc.incl_margin),
                                  tune_seconds=sc.get("tune_seconds"), log=bar.write,
                                  progress=lambda name, i=i, seed=seed: bar.step(f"fold {i} seed {seed}: {name}"))
                rec["recipe"] = recipe
                if t_learn is not None:  # the fold's trainings, counted once (in its first record written)
                    rec["learn_seconds"], t_learn = time.perf_counter() - t_learn - rec["seconds"], None
                _write_record(out, rec)
                done[seed] = rec
            else:
                bar.step(f"fold {i} seed {seed}: read", 2 * len(candidate_names(families, calibs)))
            records.append(done[seed])
            if job is None:
                partial = _result(cfg, records, read_seconds + time.perf_counter() - t_start)
                (out / "search.json").write_text(json.dumps(partial, indent=1, default=str))
        if learned is None:  # this fold's trainings were read with its records
            bar.step(f"fold {i}: learned candidates read", len(learn))
        budget.fold_done()
        if job is None:
            _save_fold_choice(out, i, [done[seed] for seed in seeds], data, axes, int(sc.trials), storage,
                              float(sc.tie_margin), float(sc.incl_margin), sc.get("tune_seconds"))
    bar.close()
    if job is not None:
        # one job of a multirun (a fold x seed each): the report and the release come from one
        # plain run over every fold and seed afterwards, which reads these records
        print(f"multirun job {job}: records written to {out / 'records'}; combine them with the same command "
              "without -m and without the swept keys (nothing is computed again)")
        return {"records": records}
    result = _result(cfg, records, read_seconds + time.perf_counter() - t_start)
    result["skipped"] = lighter
    result["release"] = release(cfg, result, out, axes, families, int(sc.trials), storage, sc.get("tune_seconds"),
                                folds, budget)
    result["expected_gain"] = expected_gain(result["rows"])
    result["budget_minutes"] = sc.get("budget_minutes")
    result["seconds"] = read_seconds + time.perf_counter() - t_start
    (out / "search.json").write_text(json.dumps(result, indent=1, default=str))
    # the per-fold rows alone (what docs/results.md's generated tables read; search.json has every candidate)
    (out / "summary.json").write_text(json.dumps({k: result[k] for k in ("dataset", "axes", "seconds", "rows", "release",
                                                                        "config", "skipped", "expected_gain",
                                                                        "budget_minutes")}, indent=1, default=str))
    md = search_markdown(result)
    (out / "search.md").write_text(md)
    print(md)
    if budget.overrun():
        print(f"WARNING: {budget.overrun()}")
    print(final_summary(result, out))
    return result


def _lodo_runs(sc) -> Dict[str, str]:
    """``search.lodo_runs`` as {axes: folder} (where a recipe whose starting model saw the data finds
    the general model trained without it)."""
    return {str(k): str(v) for k, v in dict(sc.get("lodo_runs") or {}).items()}


def skipped(sc: Dict[str, Any], n_folds: int) -> List[str]:
    """What a lighter search leaves out against the full one (:class:`~tcn_ahrs.config.SearchSection`'s
    defaults), in words: printed at the start and written in the report."""
    from ...config import SearchSection

    full = SearchSection()
    out = []
    if int(sc["trials"]) < full.trials:
        out.append(f"{sc['trials']} Optuna trials per candidate (full: {full.trials})")
    if len(sc["seeds"]) < len(full.seeds):
        out.append(f"{len(sc['seeds'])} seed(s) (full: {len(full.seeds)}: no spread over seeds)")
    if sc.get("tune_seconds"):
        out.append(f"knobs tuned on {sc['tune_seconds']:g} s clips of each recording (full: whole recordings)")
    for key in ("families", "calibrations"):
        left = [x for x in getattr(full, key) if x not in sc[key]]
        if left:
            out.append(f"{key} left out: {', '.join(left)}")
    if sc.get("folds") is not None and len(sc["folds"]) < n_folds:
        out.append(f"outer folds {list(sc['folds'])} of {n_folds}")
    left = [r for r in full.learn if r not in (sc.get("learn") or [])]
    if left:
        out.append(f"learned recipes left out: {', '.join(left)}")
    if sc.get("budget_minutes") is not None and full.budget_minutes is not None \
            and float(sc["budget_minutes"]) < full.budget_minutes and sc.get("learn"):
        out.append(f"trainings capped by a {sc['budget_minutes']:g} min budget (full: {full.budget_minutes:g})")
    return out


def _save_fold_choice(out: Path, fold: int, records: Sequence[Dict[str, Any]], data: Callable[[], Dict[str, Any]],
                      axes: int, trials: int, storage: Optional[str], tie_margin: float, incl_margin: float,
                      tune_seconds: Optional[float]) -> None:
    """The fold's choice (:func:`fold_choice`), when classical, as ``fold<i>_seed<s>.json`` per seed
    (what ``tcn-ahrs evaluate ckpt=`` reads): refitted on the outer training recordings from the
    seed's finished study (no trial runs again), so the file is the column the report scored."""
    from ...estimators.families import save_estimator

    name = fold_choice(records, tie_margin, incl_margin)
    c = records[0]["candidates"][name]
    if c["calibration"] == "learned":
        return
    for r in records:
        path = Path(out) / f"fold{fold}_seed{r['seed']}.json"
        if path.is_file() and json.loads(path.read_text()).get("provenance", {}).get("chosen") == name:
            continue
        others = data()["others"]
        est, knobs = _fit_candidate(c["family"], c["calibration"], c["tuned"], others, axes, trials, int(r["seed"]),
                                    storage, f"fold{fold}_all_seed{r['seed']}_{c['family']}_{c['calibration']}",
                                    tune_seconds)
        save_estimator(path, c["family"], axes, knobs, est.cal,
                       {"outer_fold": fold, "seed": r["seed"], "chosen": name, "fitted_on": [s.name for s in others]})


def release(cfg, result: Dict[str, Any], out: Path, axes: int, families: Sequence[str], trials: int,
            storage: Optional[str], tune_seconds: Optional[float], folds: Sequence[Sequence[str]] = (),
            budget=None) -> Dict[str, Any]:
    """The estimator to ship (:func:`release_choice`), as a file ``tcn-ahrs evaluate ckpt=FILE`` runs:
    a classical one fitted on every training recording, whole, as ``estimator.json``; a learned one
    trained by its recipe in the search's folder (:func:`release_learned`) as ``release.ckpt`` with
    its model card ``release.md``."""
    from ...datasets import load_split
    from ...estimators.families import save_estimator

    name, counts = release_choice(result, float(cfg.search.tie_margin))
    # (a learned recipe that failed to train in one fold is missing from that fold's record)
    rec = next(r["candidates"][name] for r in result["folds"] if name in r["candidates"])
    info = {"chosen": name, "times_chosen": counts[name], "runs": len(result["rows"]), "family": rec["family"]}
    every = [s for s in load_split(cfg.data, "trainval") if s.has_gt]
    if rec["calibration"] == "learned":
        info.update(release_learned(cfg, result, out, name, rec, every, folds, axes, budget))
        print(f"release: {name} ({counts[name]} of {len(result['rows'])} runs): {info.get('path') or info['how']}")
        return info
    est, knobs = _fit_candidate(rec["family"], rec["calibration"], rec["tuned"], every, axes, trials, 0, storage,
                                f"release_{rec['family']}_{rec['calibration']}", tune_seconds)
    path = out / "estimator.json"
    save_estimator(path, rec["family"], axes, knobs, est.cal,
                   {"dataset": str(cfg.data.name), "recordings": [s.name for s in every], "chosen": name,
                    "times_chosen": f"{counts[name]} of {len(result['rows'])}", "command": "tcn-ahrs search",
                    "expected_gain": expected_gain(result["rows"])})
    info.update(path=str(path), knobs=knobs)
    print(f"release: {name} ({counts[name]} of {len(result['rows'])} runs), fitted on {len(every)} recordings: {path}")
    return info


def release_learned(cfg, result: Dict[str, Any], out: Path, name: str, rec: Dict[str, Any], every, folds,
                    axes: int, budget) -> Dict[str, Any]:
    """A learned release: its recipe (``search.learn``) trained on every recording but the last
    fold's, which chooses its epoch / inference knobs as in the folds, copied to ``release.ckpt``
    (atomically) with the card ``release.md``; a ``search.learned`` family (trained by crossval)
    gets the command that trains it on every recording."""
    import os
    import shutil

    from ...checkpoint import networks_off
    from .learn import RECIPES, candidate_name, data_overrides, train_recipe

    recipe = next((r for r in RECIPES if candidate_name(r) == name), None)
    if recipe is None or not folds:
        return {"how": (f"a learned family: train its recipe on every training recording "
                        f"(tcn-ahrs train experiment=<its recipe> train.all_recordings=true); its fold checkpoints: "
                        f"{rec.get('checkpoint')}")}
    last = {str(r) for r in folds[-1]}
    train, val = [s for s in every if s.name not in last], [s for s in every if s.name in last]
    from contextlib import nullcontext

    with (budget.training() if budget is not None else nullcontext(None)) as minutes:
        best = train_recipe(recipe, out / "learn" / "release" / recipe, train, val, data_overrides(cfg.data, axes),
                            axes, minutes, lodo_runs=_lodo_runs(cfg.get("search") or {}))
    path = out / "release.ckpt"
    tmp = path.with_name(path.name + ".partial")
    shutil.copyfile(best, tmp)
    os.replace(tmp, path)
    gain = expected_gain(result["rows"])
    off = networks_off(path)
    what = ("its inference knobs switch both networks off: it runs as the VQF-grade backbone with the knobs and "
            "bias start it learned, a classical filter" if off else "learned")
    card = "\n".join([
        f"# release.ckpt: {name} for {cfg.data.name} ({axes}-axis)", "",
        f"- family: {name}, {what} (recipe `{recipe}`: {' '.join(RECIPES[recipe][1]).format(axes=axes, shipped='checkpoints')})",
        f"- trained on {len(train)} recordings ({', '.join(s.name for s in train)}); epoch / inference knobs chosen on "
        f"{', '.join(s.name for s in val)}",
        f"- chosen by `tcn-ahrs search` on {sum(r['chosen'] == name for r in result['rows'])} of "
        f"{len(result['rows'])} outer fold x seed runs (nested, leave-recordings-out)",
        f"- expected on new recordings of this device: {gain['sentence']}",
        f"- run it: `tcn-ahrs evaluate ckpt={path} data={cfg.data.name}" +
        (f" data.root={cfg.data.root}`" if cfg.data.get("root") else "`"), ""])
    (out / "release.md").write_text(card)
    return {"path": str(path), "card": str(out / "release.md"), "recipe": recipe, "networks_off": off,
            "trained_on": [s.name for s in train], "validated_on": [s.name for s in val]}


def _result(cfg, records: List[Dict[str, Any]], seconds: float) -> Dict[str, Any]:
    from omegaconf import OmegaConf

    sc = cfg.search
    by_fold: Dict[int, List[Dict[str, Any]]] = {}
    for r in records:
        by_fold.setdefault(int(r["fold"]), []).append(r)
    chosen = {f: fold_choice(rs, float(sc.tie_margin), float(sc.incl_margin)) for f, rs in by_fold.items()}
    rows = []
    for r in records:
        name, bar, incl_bar = best_classical(r)
        got = r["test"][chosen[int(r["fold"])]]
        rows.append({"fold": r["fold"], "seed": r["seed"], "chosen": chosen[int(r["fold"])],
                     "chosen_by_seed_alone": r["chosen"], "aae_deg": got["aae_deg"],
                     "inclination_deg": got["inclination_deg"], "best_classical": name, "best_classical_aae_deg": bar,
                     "best_inclination_deg": incl_bar,
                     "never_worse": verdict.never_worse(got["aae_deg"], got["inclination_deg"], bar, incl_bar)})
    return {"dataset": str(cfg.data.name), "axes": int(cfg.data.get("axes", 9)), "seconds": seconds,
            "rows": rows, "folds": records, "config": OmegaConf.to_container(cfg.search, resolve=True)}
