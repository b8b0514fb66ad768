"""One nested search over estimator families: the best attitude estimator for a device, chosen by
evidence (``tcn-ahrs search``).

For each outer fold ``i`` of ``data.folds`` (the recordings scored, which choose nothing):

1. the other training recordings give the inner splits (``search.inner``: with ≥ 3 folds every
   other fold, whole, validates in turn — one validation fold alone is too few recordings to
   choose on; else the later parts of the recordings, :func:`tcn_ahrs.crossval.inner_split`);
2. every candidate is fitted on each inner training set only: a classical family
   (:data:`FAMILIES`: strapdown integration, ECF, Mahony, Madgwick, the VQF-grade backbone with
   VQF's full parameter set), with its defaults or with its knobs searched by Optuna (TPE, seeded,
   the defaults tried first; the studies in SQLite under the output folder, so a killed search
   resumes), on the raw signals or on a static calibration (:mod:`tcn_ahrs.calibration`: gyro
   bias; gyro matrix + accelerometer offset + magnetometer ellipsoid) fitted on the same set;
3. the inner validation sets choose (:func:`choose`): the lowest mean AAE among the candidates
   whose inclination is within ``incl_margin`` of the best default filter's, a simpler family
   (:data:`SIMPLICITY`) winning within ``tie_margin``; a learned family — a fold checkpoint that
   ``tcn-ahrs crossval`` trained without fold ``i`` and without its inner fold
   (``search.learned``: ``{family: crossval folder}``) — replaces the classical choice if it beats
   it by the margin on that inner fold;
4. the classical candidates are fitted again on all the outer training recordings (nested
   cross-validation's refit) and scored on fold ``i``, beside the bar: every family with its
   defaults, on the raw and on the calibrated signals — all with the one yardstick
   (:mod:`tcn_ahrs.metrics`).

``search.seeds`` repeats steps 2–4 with other sampler seeds; the report gives mean and spread.
Writes ``search.json`` and ``search.md``; the numbers are the runner's (:func:`tcn_ahrs.evaluate.evaluate`).
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from . import calibration as cal_mod
from .estimators.families import CALIBRATIONS, FAMILIES, SIMPLICITY, Calibrated, Family, mean_scores  # noqa: F401
from .sequence import ImuSequence


def tune_family(family: Family, seqs: Sequence[ImuSequence], axes: int, trials: int, seed: int,
                storage: Optional[str] = None, study_name: Optional[str] = None,
                cal: Optional[cal_mod.StaticCalibration] = None) -> Tuple[Dict[str, float], float]:
    """Knobs of ``family`` minimising the mean AAE over ``seqs`` (inner training recordings):
    Optuna TPE with ``seed``, the authors' defaults tried first; a finished study in ``storage``
    (an SQLite URL) is continued, not restarted. Returns (knobs, mean AAE)."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    probe = family.space(optuna.trial.FixedTrial(dict(family.defaults))) if family.defaults else {}
    if not probe:  # nothing to tune (strapdown)
        return {}, mean_scores(Calibrated(family.build(axes), cal), seqs, axes)[0]
    if isinstance(storage, str) and storage.startswith("sqlite:"):
        storage = _sqlite_storage(storage)
    study = optuna.create_study(study_name=study_name, storage=storage, load_if_exists=True,
                                sampler=optuna.samplers.TPESampler(seed=seed), direction="minimize")
    if not study.trials:
        study.enqueue_trial(dict(family.defaults))
    left = trials - len([t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE])
    if left > 0:
        def objective(trial):
            return mean_scores(Calibrated(family.build(axes, **family.space(trial)), cal), seqs, axes)[0]
        study.optimize(objective, n_trials=left)
    best = study.best_trial
    return family.space(optuna.trial.FixedTrial(best.params)), float(best.value)


def simplicity_rank(name: str) -> int:
    """Position of a candidate's family (its name's first word) in :data:`SIMPLICITY`; unknown last."""
    family = name.split(" ")[0]
    return SIMPLICITY.index(family) if family in SIMPLICITY else len(SIMPLICITY)


def choose(candidates: Dict[str, Tuple[float, float]], tie_margin: float, incl_margin: float,
           incl_bar: Optional[float] = None) -> str:
    """The chosen candidate from ``{name: (inner-validation AAE, inclination)}``: among those whose
    inclination is within ``incl_margin`` degrees of ``incl_bar`` (the best classical filter's
    with defaults; default: the best candidate's), the lowest AAE — unless a simpler family
    (:data:`SIMPLICITY`, by the name's first word) is within ``tie_margin`` (relative) of it."""
    finite = {k: v for k, v in candidates.items() if math.isfinite(v[0])}
    if not finite:
        raise ValueError("search: every candidate diverged on the inner validation recordings")
    bar = min(v[1] for v in finite.values()) if incl_bar is None else incl_bar
    ok = {k: v for k, v in finite.items() if v[1] <= bar + incl_margin} or finite
    best = min(ok, key=lambda k: ok[k][0])
    ties = [k for k, v in ok.items() if v[0] <= ok[best][0] * (1.0 + tie_margin)]
    return min(ties, key=lambda k: (simplicity_rank(k), ok[k][0]))


def choose_candidate(cands: Dict[str, Dict[str, Any]], learned_split: int, tie_margin: float,
                     incl_margin: float) -> str:
    """The choice among one fold's candidate records (``inner_val``: a row of (AAE, inclination)
    per inner split; a learned candidate has one row, its ``learned_split``): the classical ones by
    :func:`choose` on their mean over the splits (inclination bar: the best untuned filter's), then
    a learned one replaces that choice if it is better by more than ``tie_margin`` on the split it
    was validated on, at an inclination within ``incl_margin``."""
    classical = {k: v for k, v in cands.items() if v["calibration"] != "learned"}
    mean = {k: np.mean(np.asarray(v["inner_val"], dtype=float), axis=0) for k, v in classical.items()}
    bar_incl = min(float(mean[k][1]) for k, v in classical.items() if not v["tuned"])
    chosen = choose({k: (float(m[0]), float(m[1])) for k, m in mean.items()}, tie_margin, incl_margin, bar_incl)
    for name, v in cands.items():
        if v["calibration"] != "learned":
            continue
        # the current choice on the learned split (a learned one has that split's row only)
        ref = cands[chosen]["inner_val"][0 if cands[chosen]["calibration"] == "learned" else learned_split]
        got = v["inner_val"][0]
        if got[0] < ref[0] * (1.0 - tie_margin) and got[1] <= ref[1] + incl_margin:
            chosen = name
    return chosen


def fold_choice(records: Sequence[Dict[str, Any]], tie_margin: float, incl_margin: float) -> str:
    """One outer fold's choice from all its seeds: every candidate's inner-validation scores
    averaged over the seeds (only the tuned knobs differ by seed), then :func:`choose_candidate`.
    A choice that flipped with the sampler's seed (EuRoC fold 0: closed loop on one seed, the
    calibrated backbone on two) cannot flip: the fold has one choice, scored for every seed."""
    first = records[0]
    pooled = {name: dict(c, inner_val=np.mean([np.asarray(r["candidates"][name]["inner_val"], dtype=float)
                                                for r in records], axis=0).tolist())
              for name, c in first["candidates"].items()}
    return choose_candidate(pooled, int(first.get("learned_split", 0)), tie_margin, incl_margin)


# ------------------------------------------------------------------------------ the nested search

def _learned_candidates(spec: Dict[str, str], fold: int, which: str = "last") -> Dict[str, Any]:
    """``{family: crossval folder}`` -> ``{family: estimator}`` of outer fold ``fold``'s checkpoint
    (trained by ``tcn-ahrs crossval`` without fold ``fold`` and without its inner validation fold).
    ``which`` "last": the end of the recipe's schedule — unbiased on the inner fold, which then
    compares it with the classical candidates; "selected": the checkpoint crossval chose on that
    very inner fold (its epoch or knobs), which makes the comparison there optimistic for it
    (EuRoC closed loop, outer fold 0: inner 1.77 selected vs 3.15 last, outer 1.96 vs 3.34)."""
    from .estimators.learned import LearnedEstimator

    if which not in ("last", "selected"):
        raise ValueError(f"search.learned_checkpoint: expected last or selected, got {which!r}")
    out = {}
    for family, folder in (spec or {}).items():
        done = Path(folder) / f"fold{fold}" / "TRAINED"
        if not done.is_file():
            raise FileNotFoundError(f"search.learned.{family}: {done} missing; run `tcn-ahrs crossval` for that "
                                    f"recipe first (its fold {fold} checkpoint is the candidate)")
        last = Path(folder) / f"fold{fold}" / "checkpoints" / "last.ckpt"
        path = str(last) if (which == "last" and last.is_file()) else done.read_text().strip()
        out[family] = LearnedEstimator(path, name=family)
    return out


def _fit_candidate(family: str, calib: str, tuned: bool, train: Sequence[ImuSequence], axes: int, trials: int,
                   seed: int, storage: Optional[str], study: str,
                   tune_seconds: Optional[float] = None) -> Tuple[Any, Dict[str, float]]:
    """One classical candidate fitted on ``train``: its static calibration (whole recordings) and
    (``tuned``) its knobs, on clips of ``tune_seconds`` (:func:`tcn_ahrs.tuning.tuning_clips`,
    from 10 s before the first scored sample; None: whole recordings). Returns (estimator, knobs)."""
    fam = FAMILIES[family]
    cal = None if CALIBRATIONS[calib] is None else cal_mod.fit_calibration(train, strict=False, **CALIBRATIONS[calib])
    knobs = dict(fam.defaults)
    if tuned and fam.defaults:
        seqs = train
        if tune_seconds:
            from .tuning import tuning_clips
            seqs = tuning_clips(train, float(tune_seconds), 10.0, None)[0]
        knobs, _ = tune_family(fam, seqs, axes, trials, seed, storage, study, cal)
    return Calibrated(fam.build(axes, **knobs), cal), knobs


def candidate_names(families: Sequence[str], calibrations: Sequence[str]) -> List[Tuple[str, str, str, bool]]:
    """(name, family, calibration, tuned) of every classical candidate: each family with its
    defaults (the bar: the classical filters a user has without any search) and tuned, on the
    raw and on each calibration's signals."""
    out = []
    for f in families:
        for tuned in (False, True):
            if tuned and not FAMILIES[f].defaults:
                continue  # nothing to tune (strapdown)
            for c in calibrations:
                out.append((f"{f} ({'tuned' if tuned else 'defaults'})" + ("" if c == "none" else f" +cal:{c}"),
                            f, c, tuned))
    return out


def _sqlite_storage(url: str, tries: int = 10):
    """Optuna's storage on an SQLite file that several jobs of one multirun share: each waits for
    the file's lock instead of failing at once, and a job that lost the race to create the schema
    opens the one the other created."""
    import optuna
    from sqlalchemy.exc import IntegrityError, OperationalError

    for k in range(tries):
        try:
            return optuna.storages.RDBStorage(url, engine_kwargs={"connect_args": {"timeout": 300}})
        except (IntegrityError, OperationalError):
            if k == tries - 1:
                raise
            time.sleep(0.2 * (k + 1))


def search_fold(outer: int, splits: Sequence[Tuple[list, list]], others: Sequence[ImuSequence],
                test: Sequence[ImuSequence], axes: int, families: Sequence[str], calibrations: Sequence[str],
                trials: int, seed: int, storage: Optional[str], learned: Dict[str, Any], learned_split: int,
                tie_margin: float, incl_margin: float, log: Callable[[str], None] = print,
                tune_seconds: Optional[float] = None) -> Dict[str, Any]:
    """Steps 2-4 of the module docstring for one outer fold and one seed.

    ``splits``: the inner (training, validation) pairs (every other fold as validation in turn,
    or one pair); each classical candidate is fitted on every inner training set and scored on its
    validation set, the choice reads the mean over the splits. A learned candidate (trained by
    crossval on split ``learned_split``) is compared on that split alone. The chosen classical
    candidate is fitted again on ``others`` (every recording but the outer fold's) and scored on
    ``test`` beside every other candidate fitted the same way (the fold's choice over all seeds,
    :func:`fold_choice`, reads these columns). Returns the fold's record for this seed."""
    from .evaluate import evaluate

    t0 = time.perf_counter()
    cands: Dict[str, Dict[str, Any]] = {}
    for name, fam, c, tuned in candidate_names(families, calibrations):
        per_split = []
        for j, (tr, va) in enumerate(splits):
            est, knobs = _fit_candidate(fam, c, tuned, tr, axes, trials, seed, storage,
                                        f"fold{outer}_split{j}_seed{seed}_{fam}_{c}", tune_seconds)
            per_split.append(mean_scores(est, va, axes))
        a = np.array(per_split)
        cands[name] = {"family": fam, "calibration": c, "tuned": tuned, "inner_val": a.tolist(),
                       "inner_val_aae": float(a[:, 0].mean()), "inner_val_inclination": float(a[:, 1].mean())}
        log(f"   fold {outer} seed {seed}: {name:<32s} inner val {a[:, 0].mean():8.3f} / {a[:, 1].mean():6.3f} "
            f"(per split {np.round(a[:, 0], 2).tolist()})")
    for fam, est in learned.items():  # compared on the one split it was validated on
        v = mean_scores(est, splits[learned_split][1], axes)
        cands[fam] = {"family": fam, "calibration": "learned", "tuned": True, "inner_val": [list(v)],
                      "inner_val_aae": v[0], "inner_val_inclination": v[1], "checkpoint": getattr(est, "ckpt_path", None)}
        log(f"   fold {outer} seed {seed}: {fam:<32s} inner val {v[0]:8.3f} / {v[1]:6.3f} (on inner split {learned_split})")
    chosen = choose_candidate(cands, learned_split, tie_margin, incl_margin)
    log(f"   fold {outer} seed {seed}: chose {chosen}")
    # every classical candidate fitted again on all the outer training recordings, the learned
    # ones as trained; the outer fold only scores (one runner, one yardstick)
    fitted: Dict[str, Any] = {}
    for name, fam, c, tuned in candidate_names(families, calibrations):
        est, knobs = _fit_candidate(fam, c, tuned, others, axes, trials, seed, storage,
                                    f"fold{outer}_all_seed{seed}_{fam}_{c}", tune_seconds)
        cands[name]["knobs"] = knobs
        fitted[name] = Calibrated(est, None, name=name)
    fitted.update({k: Calibrated(v, None, name=k) for k, v in learned.items()})
    res = evaluate(list(fitted.values()), test, axes=axes, plots=False, trajectories=False)
    means = {m: {k: v["mean"].get(k) for k in ("aae_deg", "inclination_deg", "n_recordings")}
             for m, v in res["methods"].items()}
    return {"fold": outer, "seed": seed, "recordings": [s.name for s in test], "candidates": cands,
            "bar": [n for n, v in cands.items() if not v["tuned"]], "chosen": chosen, "learned_split": learned_split, "test": means, "seconds": time.perf_counter() - t0}


def best_classical(record: Dict[str, Any]) -> Tuple[str, float, float]:
    """(name, AAE, best inclination) on one fold's outer recordings of the bar: every family with
    its defaults, on the raw and on the calibrated signals — the lowest mean AAE, and the lowest
    inclination of any of them (what the chosen estimator must not be worse than)."""
    cols = {k: record["test"][k] for k in record["bar"] if record["test"][k].get("aae_deg") is not None}
    name = min(cols, key=lambda k: cols[k]["aae_deg"])
    return name, float(cols[name]["aae_deg"]), float(min(v["inclination_deg"] for v in cols.values()))


def _inner_splits(mode: str, folds: List[list], i: int, fcfg, inner_cfg) -> Tuple[List[Tuple[list, list]], int, str]:
    """The inner (training, validation) pairs of outer fold ``i`` and which of them crossval's
    learned candidates were validated on. ``folds`` (the default with ≥ 3 folds): every other fold,
    whole, validates in turn; ``fold`` / ``split``: crossval's one inner split
    (:func:`tcn_ahrs.crossval.inner_split`)."""
    from .crossval import inner_split
    from .datasets import load_split

    if mode not in ("auto", "folds", "fold", "split"):
        raise ValueError(f"search.inner: expected auto, folds, fold or split, got {mode!r}")
    if mode == "auto":
        mode = "folds" if len(folds) >= 3 else "split"
    if mode == "folds":
        if len(folds) < 3:
            raise ValueError(f"search.inner=folds needs at least 3 folds; this data has {len(folds)}")
        others = [s for s in load_split(fcfg.data, "train") if s.has_gt]
        order = [(i + k) % len(folds) for k in range(1, len(folds))]  # crossval's inner fold first
        splits = []
        for j in order:
            names = {str(r) for r in folds[j]}
            splits.append(([s for s in others if s.name not in names], [s for s in others if s.name in names]))
        return splits, 0, f"inner validation: folds {order} in turn, whole"
    with_mode = inner_cfg.copy()
    with_mode.crossval.inner = mode
    tr, va, desc = inner_split(with_mode, folds, i, fcfg)
    return [([s for s in tr if s.has_gt], [s for s in va if s.has_gt])], 0, desc


def auto_folds(cfg, k: int = 3) -> List[List[str]]:
    """Your own recordings without ``data.folds``: every recording under ``data.root`` (or
    ``data.train``) trains, dealt round-robin into ``k`` folds by sorted name; written into
    ``cfg.data`` (folds, train) and printed. Needs at least ``k`` recordings."""
    from omegaconf import open_dict

    from .datasets import loader, resolve_root

    if cfg.data.name == "simulated":
        raise ValueError("search: the simulator has splits, not folds; use data=generic (your recordings), "
                         "broad, euroc, tumvi or oxiod")
    names = [str(r) for r in (cfg.data.get("train") or [])] or sorted(loader(cfg.data.name).list_recordings(resolve_root(cfg.data)))
    if len(names) < k:
        raise ValueError(f"search: {len(names)} recordings under {cfg.data.get('root')} ({names}); the nested "
                         f"search needs at least {k} (one per fold), or give data.folds")
    folds = [names[j::k] for j in range(k)]
    with open_dict(cfg.data):
        cfg.data.train = names
        cfg.data.folds = folds
    print(f"search: no data.folds given: {len(names)} recordings dealt into {k} folds {folds}", flush=True)
    return folds


def search_main(cfg) -> Dict[str, Any]:
    """``tcn-ahrs search``: the nested family search over ``data.folds`` (module docstring)."""
    from omegaconf import OmegaConf

    from .config import SearchSection, check_keys
    from .crossval import _fold_cfg
    from .datasets import load_split
    from .training.setup import model_axes

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
    lighter = skipped(OmegaConf.to_container(sc, resolve=True), len(folds))
    print("search settings: " + ("; ".join(lighter) if lighter else "the full search (nothing skipped)"), flush=True)
    t_start = time.perf_counter()
    job = multirun_job()
    recipe = {k: OmegaConf.to_container(sc, resolve=True).get(k) for k in RECIPE_KEYS}
    recipe["folds"] = folds
    records: List[Dict[str, Any]] = []
    read_seconds = 0.0  # the compute time of records an earlier run or another job wrote
    for i in idx:
        seeds = [int(seed) for seed in sc.seeds]
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

        read_seconds += sum(float(r["seconds"]) for r in done.values() if r is not None)
        if all(r is not None for r in done.values()):  # every seed of this fold ran (earlier, or another job)
            print(f"== outer fold {i}: seeds {seeds} read from {out / 'records'}", flush=True)
        learned = None
        for seed in seeds:
            if done[seed] is None:
                d = data()
                if learned is None:
                    learned = _learned_candidates(learned_spec, i, str(sc.get("learned_checkpoint") or "last"))
                rec = search_fold(i, d["splits"], d["others"], d["test"], axes, families, calibs, int(sc.trials), seed,
                                  storage, learned, d["learned_split"], float(sc.tie_margin), float(sc.incl_margin),
                                  tune_seconds=sc.get("tune_seconds"))
                rec["recipe"] = recipe
                _write_record(out, rec)
                done[seed] = rec
            records.append(done[seed])
            if job is None:
                partial = _result(cfg, records, read_seconds + time.perf_counter() - t_start)
                (out / "search.json").write_text(json.dumps(partial, indent=1, default=str))
        if job is None:
            _save_fold_choice(out, i, [done[seed] for seed in seeds], data, axes, int(sc.trials), storage,
                              float(sc.tie_margin), float(sc.incl_margin), sc.get("tune_seconds"))
    if job is not None:
        # one job of a multirun (a fold x seed each): the report and the release come from one
        # plain run over every fold and seed afterwards, which reads these records
        print(f"multirun job {job}: records written to {out / 'records'}; combine them with the same command "
              "without -m and without the swept keys (nothing is computed again)")
        return {"records": records}
    result = _result(cfg, records, read_seconds + time.perf_counter() - t_start)
    result["skipped"] = lighter
    result["release"] = release(cfg, result, out, axes, families, int(sc.trials), storage, sc.get("tune_seconds"))
    (out / "search.json").write_text(json.dumps(result, indent=1, default=str))
    # the per-fold rows alone (what docs/results.md's generated tables read; search.json has every candidate)
    (out / "summary.json").write_text(json.dumps({k: result[k] for k in ("dataset", "axes", "seconds", "rows", "release",
                                                                        "config", "skipped")}, indent=1, default=str))
    md = search_markdown(result)
    (out / "search.md").write_text(md)
    print(md)
    print(f"results in {out}")
    return result


def skipped(sc: Dict[str, Any], n_folds: int) -> List[str]:
    """What a lighter search leaves out against the full one (:class:`~tcn_ahrs.config.SearchSection`'s
    defaults), in words: printed at the start and written in the report."""
    from .config import SearchSection

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
    if not sc.get("learned"):
        out.append("no learned family (search.learned: crossval folders of the learned recipes)")
    return out


def _save_fold_choice(out: Path, fold: int, records: Sequence[Dict[str, Any]], data: Callable[[], Dict[str, Any]],
                      axes: int, trials: int, storage: Optional[str], tie_margin: float, incl_margin: float,
                      tune_seconds: Optional[float]) -> None:
    """The fold's choice (:func:`fold_choice`), when classical, as ``fold<i>_seed<s>.json`` per seed
    (what ``tcn-ahrs evaluate ckpt=`` reads): refitted on the outer training recordings from the
    seed's finished study (no trial runs again), so the file is the column the report scored."""
    from .estimators.families import save_estimator

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


def multirun_job() -> Optional[int]:
    """This job's number in a Hydra multirun (``tcn-ahrs search -m ...``), None in a plain run."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        hc = HydraConfig.get()
    except (ImportError, ValueError):  # not started by Hydra (a library call)
        return None
    return int(hc.job.num) if hc.mode == RunMode.MULTIRUN else None


def _record_path(out: Path, fold: int, seed: int) -> Path:
    return Path(out) / "records" / f"fold{fold}_seed{seed}.json"


RECIPE_KEYS = ("inner", "families", "calibrations", "learned_checkpoint", "learned", "tune_seconds", "trials",
               "tie_margin", "incl_margin")
"""The search settings a fold x seed record depends on (with the folds): a record written with
others is not reused."""


def _read_record(out: Path, fold: int, seed: int, recipe: Dict[str, Any]) -> Optional[Dict[str, Any]]:
    """The record of an earlier run or another multirun job of this search, None if there is none;
    ValueError when it was written with other settings (nothing is overwritten)."""
    p = _record_path(out, fold, seed)
    if not p.is_file():
        return None
    rec = json.loads(p.read_text())
    if rec.get("recipe") != json.loads(json.dumps(recipe, default=float)):
        changed = sorted(k for k in recipe if (rec.get("recipe") or {}).get(k) != recipe[k])
        raise ValueError(f"{p}: written by a search with other settings ({', '.join(changed) or 'format'}); "
                         "choose another search.out (nothing is overwritten)")
    return rec


def _write_record(out: Path, rec: Dict[str, Any]) -> None:
    """One outer fold x seed's record, atomically (a killed job leaves none, and is run again)."""
    import os

    p = _record_path(out, rec["fold"], rec["seed"])
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".partial")
    tmp.write_text(json.dumps(rec, indent=1, default=float))
    os.replace(tmp, p)


def release_choice(result: Dict[str, Any], tie_margin: float) -> Tuple[str, Dict[str, int]]:
    """The candidate chosen on the most outer folds; a tie is broken on the inner validation — the
    tied candidates' scores averaged over the folds and seeds (on the learned candidates' inner
    split when one of them is learned, so all are read on the same recordings) — and within
    ``tie_margin`` of the best of those, the simpler family. Returns (name, times chosen by name,
    counted over fold x seed runs)."""
    from collections import Counter

    counts = Counter(r["chosen"] for r in result["rows"])
    top = max(counts.values())
    tied = sorted(k for k, v in counts.items() if v == top)
    if len(tied) == 1:
        return tied[0], dict(counts)
    recs = result["folds"]
    learned_tied = any(recs[0]["candidates"][k]["calibration"] == "learned" for k in tied)

    def score(name: str) -> float:
        vals = []
        for r in recs:
            c = r["candidates"][name]
            rows = np.asarray(c["inner_val"], dtype=float)
            if learned_tied and c["calibration"] != "learned":
                rows = rows[int(r.get("learned_split", 0))][None]
            vals.append(float(rows[:, 0].mean()))
        return float(np.mean(vals))

    scores = {k: score(k) for k in tied}
    best = min(scores.values())
    near = [k for k in tied if scores[k] <= best * (1.0 + tie_margin)]
    return min(near, key=lambda k: (simplicity_rank(k), scores[k])), dict(counts)


def release(cfg, result: Dict[str, Any], out: Path, axes: int, families: Sequence[str], trials: int,
            storage: Optional[str], tune_seconds: Optional[float]) -> Dict[str, Any]:
    """The estimator to ship (:func:`release_choice`); a classical one is fitted on every training
    recording, whole, and written as ``estimator.json`` (``tcn-ahrs evaluate ckpt=.../estimator.json``);
    a learned one is its recipe trained on every recording (the command is printed)."""
    from .datasets import load_split
    from .estimators.families import save_estimator

    name, counts = release_choice(result, float(cfg.search.tie_margin))
    rec = result["folds"][0]["candidates"][name]
    info = {"chosen": name, "times_chosen": counts[name], "runs": len(result["rows"]), "family": rec["family"]}
    if rec["calibration"] == "learned":
        info["how"] = (f"a learned family: train its recipe on every training recording "
                       f"(tcn-ahrs train experiment=<its recipe> train.all_recordings=true); its fold checkpoints: "
                       f"{rec.get('checkpoint')}")
        print(f"release: {name} ({counts[name]} of {len(result['rows'])} runs): {info['how']}")
        return info
    every = [s for s in load_split(cfg.data, "trainval") if s.has_gt]
    est, knobs = _fit_candidate(rec["family"], rec["calibration"], rec["tuned"], every, axes, trials, 0, storage,
                                f"release_{rec['family']}_{rec['calibration']}", tune_seconds)
    path = out / "estimator.json"
    save_estimator(path, rec["family"], axes, knobs, est.cal,
                   {"dataset": str(cfg.data.name), "recordings": [s.name for s in every], "chosen": name,
                    "times_chosen": f"{counts[name]} of {len(result['rows'])}", "command": "tcn-ahrs search"})
    info.update(path=str(path), knobs=knobs)
    print(f"release: {name} ({counts[name]} of {len(result['rows'])} runs), fitted on {len(every)} recordings: {path}")
    return info


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
                     "never_worse": bool(got["aae_deg"] <= bar + 1e-9 and got["inclination_deg"] <= incl_bar + 0.05)})
    return {"dataset": str(cfg.data.name), "axes": int(cfg.data.get("axes", 9)), "seconds": seconds,
            "rows": rows, "folds": records, "config": OmegaConf.to_container(cfg.search, resolve=True)}


def summary_markdown(result: Dict[str, Any]) -> str:
    """Per outer fold: its one choice over the seeds (:func:`fold_choice`; what each seed alone would
    have chosen where that differs), its outer AAE / inclination beside the bar (every
    family with its defaults, raw and calibrated) — mean ± std over seeds — and never worse."""
    lines = ["| outer fold | chosen (over the seeds) | AAE | inclination | best classical, defaults (AAE) | best inclination | never worse |",
             "|---|---|---|---|---|---|---|"]
    by_fold: Dict[int, List[dict]] = {}
    for r in result["rows"]:
        by_fold.setdefault(r["fold"], []).append(r)
    fmt = lambda xs: f"{np.mean(xs):.2f} ± {np.std(xs):.2f}" if len(xs) > 1 else f"{xs[0]:.2f}"  # noqa: E731
    for f, rows in sorted(by_fold.items()):
        alone = [r.get("chosen_by_seed_alone", r["chosen"]) for r in rows]
        flips = f" (seeds alone: {', '.join(alone)})" if any(a != rows[0]["chosen"] for a in alone) else ""
        lines.append(f"| {f} | {rows[0]['chosen']}{flips} | {fmt([r['aae_deg'] for r in rows])} | "
                     f"{fmt([r['inclination_deg'] for r in rows])} | {rows[0]['best_classical']} "
                     f"{fmt([r['best_classical_aae_deg'] for r in rows])} | {fmt([r['best_inclination_deg'] for r in rows])} | "
                     f"{sum(r['never_worse'] for r in rows)} of {len(rows)} |")
    rows = result["rows"]
    lines += ["", f"{result['dataset']} ({result['axes']}-axis): mean over folds and seeds {np.mean([r['aae_deg'] for r in rows]):.2f} "
                  f"(best classical with defaults {np.mean([r['best_classical_aae_deg'] for r in rows]):.2f}); never worse in "
                  f"{sum(r['never_worse'] for r in rows)} of {len(rows)} fold × seed runs; search time "
                  f"{result['seconds'] / 60:.1f} min on this machine."]
    if result.get("skipped"):
        lines.append(f"Lighter than the full search: {'; '.join(result['skipped'])}.")
    return "\n".join(lines) + "\n"


def search_markdown(result: Dict[str, Any]) -> str:
    """The report: :func:`summary_markdown`, then per fold and seed every candidate's inner
    validation and outer scores with its knobs."""
    lines = [f"# Family search: {result['dataset']} ({result['seconds'] / 60:.1f} min)\n",
             "Nested: knobs tuned on the inner training recordings, the family chosen on the inner "
             "validation recordings, scored on the outer fold (which chose nothing). Degrees, the "
             "yardstick of docs/conventions.md; mean ± std over seeds.\n", summary_markdown(result)]
    for rec in result["folds"]:
        lines += [f"\n## Outer fold {rec['fold']}, seed {rec['seed']} (this seed alone would choose {rec['chosen']})\n",
                  "| candidate | inner val AAE | inner val incl. | outer AAE | outer incl. | knobs |", "|---|---|---|---|---|---|"]
        for name, c in rec["candidates"].items():
            t = rec["test"].get(name, {})
            knobs = ", ".join(f"{k}={v:.3g}" for k, v in (c.get("knobs") or {}).items()) if c.get("tuned") else "defaults"
            lines.append(f"| {name} | {c['inner_val_aae']:.2f} | {c['inner_val_inclination']:.2f} | "
                         f"{t.get('aae_deg', float('nan')):.2f} | {t.get('inclination_deg', float('nan')):.2f} | {knobs} |")
    return "\n".join(lines) + "\n"
