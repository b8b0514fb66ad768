"""One outer fold and one seed of the search: the candidates fitted on the inner training sets
(Optuna for the knobs), scored on the inner validation sets, the choice, and every candidate
refitted on the outer training recordings and scored on the outer fold."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ... import calibration as cal_mod
from ...estimators.families import FAMILIES, Calibrated, Family, fit_named_calibration, mean_scores, recording_scores
from ...sequence import ImuSequence
from .choice import adoption_reasons, choose_candidate
from ...checkpoint import networks_off
from .records import _sqlite_storage


def tune_family(family: Family, seqs: Sequence[ImuSequence], axes: int, trials: int, seed: int,
                storage: Optional[str] = None, study_name: Optional[str] = None,
                cal: Optional[cal_mod.StaticCalibration] = None) -> Tuple[Dict[str, float], float]:
    """Knobs of ``family`` minimising the mean AAE over ``seqs`` (inner training recordings):
    Optuna TPE with ``seed``, the authors' defaults tried first; a finished study in ``storage``
    (an SQLite URL) is continued, not restarted. Returns (knobs, mean AAE)."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    if not family.knobs:  # nothing to tune (strapdown)
        return {}, mean_scores(Calibrated(family.build(axes), cal), seqs, axes)[0]
    if isinstance(storage, str) and storage.startswith("sqlite:"):
        storage = _sqlite_storage(storage)
    study = optuna.create_study(study_name=study_name, storage=storage, load_if_exists=True,
                                sampler=optuna.samplers.TPESampler(seed=seed), direction="minimize")
    if not study.trials:
        study.enqueue_trial(family.defaults_for(axes))
    left = trials - len([t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE])
    if left > 0:
        def objective(trial):
            return mean_scores(Calibrated(family.build(axes, **family.space(trial)), cal), seqs, axes)[0]
        study.optimize(objective, n_trials=left)
    best = study.best_trial
    return family.space(optuna.trial.FixedTrial(best.params)), float(best.value)


def _learned_candidates(spec: Dict[str, str], fold: int, which: str = "last") -> Dict[str, Any]:
    """``{family: crossval folder}`` -> ``{family: estimator}`` of outer fold ``fold``'s checkpoint
    (trained by ``tcn-ahrs crossval`` without fold ``fold`` and without its inner validation fold).
    ``which`` "last": the end of the recipe's schedule — unbiased on the inner fold, which then
    compares it with the classical candidates; "selected": the checkpoint crossval chose on that
    very inner fold (its epoch or knobs), which makes the comparison there optimistic for it
    (EuRoC closed loop, outer fold 0: inner 1.77 selected vs 3.15 last, outer 1.96 vs 3.34)."""
    from ...estimators.learned import LearnedEstimator

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
    (``tuned``) its knobs, on clips of ``tune_seconds`` (:func:`tcn_ahrs.tuning.grid.tuning_clips`,
    from 10 s before the first scored sample; None: whole recordings). Returns (estimator, knobs)."""
    fam = FAMILIES[family]
    cal = fit_named_calibration(calib, train)
    knobs = fam.defaults_for(axes)
    if tuned and fam.knobs:
        seqs = train
        if tune_seconds:
            from ...tuning.grid import tuning_clips
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
            if tuned and not FAMILIES[f].knobs:
                continue  # nothing to tune (strapdown)
            for c in calibrations:
                out.append((f"{f} ({'tuned' if tuned else 'defaults'})" + ("" if c == "none" else f" +cal:{c}"),
                            f, c, tuned))
    return out


def search_fold(outer: int, splits: Sequence[Tuple[list, list]], others: Sequence[ImuSequence],
                test: Sequence[ImuSequence], axes: int, families: Sequence[str], calibrations: Sequence[str],
                trials: int, seed: int, storage: Optional[str], learned: Dict[str, Any], learned_split: int,
                tie_margin: float, incl_margin: float, log: Callable[[str], None] = print,
                tune_seconds: Optional[float] = None,
                progress: Callable[[str], None] = lambda step: None) -> Dict[str, Any]:
    """Steps 2-4 of the module docstring for one outer fold and one seed.

    ``splits``: the inner (training, validation) pairs (every other fold as validation in turn,
    or one pair); each classical candidate is fitted on every inner training set and scored on its
    validation set, the choice reads the mean over the splits. A learned candidate (trained by
    crossval on split ``learned_split``) is compared on that split alone. The chosen classical
    candidate is fitted again on ``others`` (every recording but the outer fold's) and scored on
    ``test`` beside every other candidate fitted the same way (the fold's choice over all seeds,
    :func:`fold_choice`, reads these columns). Returns the fold's record for this seed."""
    from ...evaluate import evaluate

    t0 = time.perf_counter()
    cands: Dict[str, Dict[str, Any]] = {}
    for name, fam, c, tuned in candidate_names(families, calibrations):
        per_split, per_rec = [], []
        for j, (tr, va) in enumerate(splits):
            est, knobs = _fit_candidate(fam, c, tuned, tr, axes, trials, seed, storage,
                                        f"fold{outer}_split{j}_seed{seed}_{fam}_{c}", tune_seconds)
            aae, incl = recording_scores(est, va, axes)
            per_split.append((float(np.mean(aae)), float(np.mean(incl))))
            per_rec.append(aae)
        a = np.array(per_split)
        cands[name] = {"family": fam, "calibration": c, "tuned": tuned, "inner_val": a.tolist(),
                       "inner_val_recordings": per_rec,
                       "inner_val_aae": float(a[:, 0].mean()), "inner_val_inclination": float(a[:, 1].mean())}
        progress(name)
        log(f"   fold {outer} seed {seed}: {name:<32s} inner val {a[:, 0].mean():8.3f} / {a[:, 1].mean():6.3f} "
            f"(per split {np.round(a[:, 0], 2).tolist()})")
    for fam, est in learned.items():  # compared on the one split it was validated on
        aae, incl = recording_scores(est, splits[learned_split][1], axes)
        v = (float(np.mean(aae)), float(np.mean(incl)))
        cands[fam] = {"family": fam.split(" ")[0], "calibration": "learned", "tuned": True, "inner_val": [list(v)],
                      "inner_val_recordings": [aae], "inner_val_aae": v[0], "inner_val_inclination": v[1],
                      "checkpoint": getattr(est, "ckpt_path", None),
                      "networks_off": networks_off(getattr(est, "ckpt_path", None))}
        log(f"   fold {outer} seed {seed}: {fam:<32s} inner val {v[0]:8.3f} / {v[1]:6.3f} (on inner split {learned_split})")
    chosen = choose_candidate(cands, learned_split, tie_margin, incl_margin)
    for name, why in adoption_reasons(cands, learned_split, tie_margin, incl_margin).items():
        log(f"   fold {outer} seed {seed}: {name}: {why}")
    log(f"   fold {outer} seed {seed}: chose {chosen}")
    # every classical candidate fitted again on all the outer training recordings, the learned
    # ones as trained; the outer fold only scores (one runner, one yardstick)
    fitted: Dict[str, Any] = {}
    for name, fam, c, tuned in candidate_names(families, calibrations):
        est, knobs = _fit_candidate(fam, c, tuned, others, axes, trials, seed, storage,
                                    f"fold{outer}_all_seed{seed}_{fam}_{c}", tune_seconds)
        cands[name]["knobs"] = knobs
        fitted[name] = Calibrated(est, None, name=name)
        progress(f"{name} refitted")
    fitted.update({k: Calibrated(v, None, name=k) for k, v in learned.items()})
    res = evaluate(list(fitted.values()), test, axes=axes, plots=False, trajectories=False)
    means = {m: {k: v["mean"].get(k) for k in ("aae_deg", "inclination_deg", "n_recordings")}
             for m, v in res["methods"].items()}
    return {"fold": outer, "seed": seed, "recordings": [s.name for s in test], "candidates": cands,
            "bar": [n for n, v in cands.items() if not v["tuned"]], "chosen": chosen, "learned_split": learned_split, "test": means, "seconds": time.perf_counter() - t0}


def _inner_splits(mode: str, folds: List[list], i: int, fcfg, inner_cfg) -> Tuple[List[Tuple[list, list]], int, str]:
    """The inner (training, validation) pairs of outer fold ``i`` and which of them crossval's
    learned candidates were validated on. ``folds`` (the default with ≥ 3 folds): every other fold,
    whole, validates in turn; ``fold`` / ``split``: crossval's one inner split
    (:func:`tcn_ahrs.experiments.crossval.inner_split`)."""
    from ..crossval import inner_split
    from ...datasets import load_split

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

    from ...datasets import loader, resolve_root

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
