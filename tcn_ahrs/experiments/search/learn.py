"""The learned candidates the search trains inside its own folds (``search.learn``).

Each recipe is a YAML file of ``conf/train.yaml`` overrides (``conf/search/learn/``, :data:`RECIPES`); for outer fold ``i`` it
is trained on the fold's first inner training set — never on fold ``i``'s recordings — its epoch or
inference knobs chosen on that split's validation recordings, whole (early stopping on the inner
validation), and it is then compared with the classical candidates on those validation recordings
(:func:`tcn_ahrs.experiments.search.choice.choose_candidate`) and scored, as trained, on fold ``i``.

Compute: every training gets an equal share of what is left of ``search.budget_minutes`` as
Lightning's ``max_time`` (:func:`share_minutes`), so the search keeps the budget it states. A
killed search resumes: a finished training leaves ``TRAINED`` (the checkpoint that ships) in its
run folder, an unfinished one continues from its ``last.ckpt``.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

from ...checkpoints import SHIPPED_DIR
from ...sequence import ImuSequence

LEARN_DIR = "search/learn"
"""The learned recipes: one YAML file each under ``conf/search/learn/`` (its candidate name and its
``conf/train.yaml`` overrides), so a user adds or edits a recipe without touching the code."""


def load_recipes() -> Dict[str, Tuple[str, Tuple[str, ...]]]:
    """Recipe name -> (candidate name, ``conf/train.yaml`` overrides; ``{axes}`` is the data's,
    ``{shipped}`` the installed models' folder, :data:`tcn_ahrs.checkpoints.SHIPPED_DIR`), from
    ``conf/search/learn/*.yaml``."""
    import yaml

    from ...conf import CONF_DIR
    from ...config import check_section
    from ...config.train import LearnRecipe

    recipes = {}
    for path in sorted((CONF_DIR / LEARN_DIR).glob("*.yaml")):
        doc = yaml.safe_load(path.read_text()) or {}
        check_section(doc, LearnRecipe, str(path))
        if not doc.get("name") or not doc.get("overrides"):
            raise ValueError(f"{path}: expected a recipe: name (the candidate's) and overrides (a list)")
        recipes[path.stem] = (str(doc["name"]), tuple(str(o) for o in doc["overrides"]))
    return recipes


RECIPES = load_recipes()


def check_recipes(names: Sequence[str]) -> List[str]:
    bad = [n for n in names if n not in RECIPES]
    if bad:
        raise ValueError(f"search.learn: unknown {bad}; expected some of {list(RECIPES)}")
    return list(names)


def candidate_name(recipe: str) -> str:
    return RECIPES[recipe][0]


def share_minutes(budget_minutes: Optional[float], spent_minutes: float, trainings_left: int,
                  classical_minutes_left: float = 0.0, floor: float = 0.5) -> Optional[float]:
    """Minutes the next training may take: an equal share of what the budget has left once the
    classical work still to do is set aside; None without a budget; at least ``floor`` (a
    training shorter than that learns nothing: the budget is then overrun, and said)."""
    if budget_minutes is None or trainings_left <= 0:
        return None
    left = float(budget_minutes) - spent_minutes - classical_minutes_left
    return max(floor, left / trainings_left)


def _max_time(minutes: Optional[float]) -> str:
    if minutes is None:
        return "null"
    s = max(1, int(round(minutes * 60)))
    return f"{s // 86400:02d}:{s // 3600 % 24:02d}:{s // 60 % 60:02d}:{s % 60:02d}"


def data_overrides(data_cfg, axes: int) -> List[str]:
    """The search's data config as overrides of ``conf/train.yaml`` (the recordings themselves are
    handed to the training, not read through its splits)."""
    args = [f"data={data_cfg.name}", f"data.axes={axes}", "data.fold=null"]
    if data_cfg.get("root"):
        args.append(f"data.root={data_cfg.root}")
    return args


def starting_leak(recipe: str, axes: int, dataset: str) -> Optional[str]:
    """Why ``recipe``'s starting weights would leak ``dataset``'s outer folds into the search, or None:
    the general models trained on the training recordings of every dataset in their mix
    (``conf/data/general{axes}.yaml``'s parts) and chose their knobs on them, so for a dataset in
    the mix "never on fold i's recordings" does not hold for a candidate started from them. Your
    own recordings (``data=generic``) are clean."""
    from ..transfer import own_datasets
    from ...checkpoint import checkpoint_meta, load_checkpoint

    init = next((a.split("=", 1)[1] for a in RECIPES[recipe][1] if a.startswith("init=")), None)
    if init is None:
        return None
    path = Path(init.format(axes=axes, shipped=SHIPPED_DIR))
    trained_on = own_datasets(str(checkpoint_meta(load_checkpoint(str(path)), str(path)).get("data") or ""))
    if dataset not in trained_on:
        return None
    return (f"its starting model {path.name} trained on {dataset}'s training recordings (its mix: {', '.join(trained_on)}) "
            "and chose its knobs on them, this outer fold's among them: left out (a general model trained without "
            f"{dataset}, `tcn-ahrs benchmark lodo`, would start it leak-free)")


def start_without(dataset: str, axes: int, lodo_runs: Optional[Dict[str, str]]) -> Optional[Path]:
    """The general model for ``axes`` trained without ``dataset`` (``tcn-ahrs benchmark lodo``'s run in
    ``lodo_runs[str(axes)]/<dataset>``: finished, its knobs chosen, its resolved config leaving
    ``dataset`` out), or None."""
    from omegaconf import OmegaConf

    folder = Path(str((lodo_runs or {}).get(str(axes), ""))) / dataset
    ckpt, cfg = folder / "checkpoints" / "last.ckpt", folder / "config_resolved.yaml"
    if not (lodo_runs and ckpt.is_file() and cfg.is_file() and (folder / "knobs.json").is_file()):
        return None
    left = OmegaConf.to_container(OmegaConf.load(cfg), resolve=False).get("data", {}).get("leave_out")
    return ckpt if dataset in ([left] if isinstance(left, str) else list(left or [])) else None


def train_recipe(recipe: str, run_dir: Path, train: Sequence[ImuSequence], val: Sequence[ImuSequence],
                 data_args: Sequence[str], axes: int, minutes: Optional[float], seed: int = 0,
                 lodo_runs: Optional[Dict[str, str]] = None) -> Path:
    """Train ``recipe`` on ``train`` (its epoch / inference knobs chosen on ``val``) in ``run_dir``,
    or reuse the finished run there; returns the checkpoint that ships. ``minutes``: its time cap
    (an unfinished run there continues from its ``last.ckpt``). Where its starting weights saw the
    search's dataset (:func:`starting_leak`) it starts from the general model trained without it
    (:func:`start_without`, ``search.lodo_runs``), else ValueError."""
    from ..lodo import compose_train
    from ...training.run import train_main

    dataset = next((a.split("=", 1)[1] for a in data_args if a.startswith("data=")), "")
    args = [a.format(axes=axes, shipped=SHIPPED_DIR) for a in RECIPES[recipe][1]] + list(data_args)
    leak = starting_leak(recipe, axes, dataset)
    if leak:
        clean = start_without(dataset, axes, lodo_runs)
        if clean is None:
            where = (lodo_runs or {}).get(str(axes))
            raise ValueError(leak + (f"; none found in {where}/{dataset}" if where else ""))
        args = [f"init={clean}" if a.startswith("init=") else a for a in args]
    run_dir = Path(run_dir)
    done = run_dir / "TRAINED"
    if done.is_file():
        return Path(done.read_text().strip())
    # Lightning's accelerator is "auto": a GPU trains when there is one; its bar would break the search's
    args += [f"run_dir={run_dir}", "eval.enabled=false", f"seed={seed}", f"train.max_time={_max_time(minutes)}",
             "trainer.enable_progress_bar=false"]
    if (run_dir / "checkpoints" / "last.ckpt").is_file():
        args.append("resume=true")
    cfg = compose_train(args)
    res = train_main(cfg, train_seqs=list(train), val_seqs=list(val), overrides=args)
    best = Path(res["best"])
    done.write_text(str(best) + "\n")
    return best


def learned_estimator(path, name: str):
    """The checkpoint as the search scores it: on device-checked input where it was trained on it
    (as ``tcn-ahrs evaluate`` runs it), through the same calibration the classical candidates use."""
    from ...checkpoint import checkpoint_meta, load_checkpoint
    from ...device_check import RestBiasCalibration
    from ...estimators.families import Calibrated
    from ...estimators.learned import LearnedEstimator

    est = LearnedEstimator(str(path), name=name)
    layout = checkpoint_meta(load_checkpoint(str(path)), str(path))["layout"]
    return Calibrated(est, RestBiasCalibration(), name=name) if layout.get("device_check") else est


class CrossFitted:
    """A learned candidate scored on recordings that chose nothing: trained twice on the same inner
    training recordings, its epoch and inference knobs chosen once on each half of the validation
    recordings (:func:`halves`); each validation recording is run by the model the *other* half chose
    (so the adoption test, :func:`gain_supported`, reads no recording that tuned what it tests), any
    other recording (the outer fold's) by the first. With one validation recording there is one model
    (and nothing to adopt: :data:`MIN_ADOPTION_RECORDINGS`). Otherwise the estimator it wraps."""

    def __init__(self, by_recording: Dict[str, Any], outer, name: str):
        self.by_recording, self.outer, self.name = dict(by_recording), outer, name

    def run(self, seq: ImuSequence, init_quat=None, init_index: int = 0):
        return self.by_recording.get(seq.name, self.outer).run(seq, init_quat, init_index)

    def __getattr__(self, key):   # axes, ckpt_path, heading_free, ...: the outer model's
        if key in ("by_recording", "outer", "name"):
            raise AttributeError(key)
        return getattr(self.outer, key)


def halves(val: Sequence[ImuSequence]) -> List[List[ImuSequence]]:
    """The validation recordings in two halves (alternating; one half where there is one recording)."""
    return [list(val[0::2]), list(val[1::2])] if len(val) >= 2 else [list(val)]


def train_fold_candidates(recipes: Sequence[str], out: Path, fold: int, train: Sequence[ImuSequence],
                          val: Sequence[ImuSequence], data_args: Sequence[str], axes: int, budget,
                          log=print, progress=lambda name: None,
                          lodo_runs: Optional[Dict[str, str]] = None) -> Dict[str, Any]:
    """Every recipe of ``recipes`` trained (or reused) for outer fold ``fold`` on one inner split,
    cross-fitted (:class:`CrossFitted`: two trainings, each choosing its epoch / knobs on one half of
    ``val``), each training capped by ``budget.training()``
    (:class:`~tcn_ahrs.experiments.search.progress.Budget`). Returns ``{candidate name: estimator}``;
    a recipe that fails to train is left out, and said."""
    out_est: Dict[str, Any] = {}
    parts = halves(val)
    for recipe in recipes:
        name = candidate_name(recipe)
        models = []
        for h, chooses in enumerate(parts):
            run_dir = Path(out) / "learn" / f"fold{fold}" / recipe / f"chosen_on_half{h}"
            with budget.training() as minutes:
                cap = "" if minutes is None else f" (at most {minutes:.1f} min)"
                log(f"   fold {fold}: training {name} on {[s.name for s in train]}, epoch and knobs chosen on "
                    f"{[s.name for s in chooses]}{cap}: {run_dir}")
                try:
                    models.append(train_recipe(recipe, run_dir, train, chooses, data_args, axes, minutes,
                                               lodo_runs=lodo_runs))
                except (ValueError, RuntimeError, FileNotFoundError) as e:  # e.g. no general model for these axes
                    log(f"   fold {fold}: {name} left out: {e}")
                    progress(f"{name} failed")
                    break
        if len(models) < len(parts):
            continue
        ests = [learned_estimator(m, name) for m in models]
        by_rec = {s.name: ests[len(parts) - 1 - h] for h, part in enumerate(parts) for s in part}
        out_est[name] = CrossFitted(by_rec, ests[0], name)
        progress(name)
    return out_est


ADOPTION_LEVEL = 0.05
"""One-sided level of the paired test a learned candidate's gain must pass (:func:`gain_supported`):
a candidate no better than the classical choice is adopted in at most 5 % of draws."""
MIN_ADOPTION_RECORDINGS = 3
"""Fewer validation recordings than this: the search cannot decide and keeps the classical choice."""


def gain_supported(ref: Sequence[float], got: Sequence[float], tie_margin: float,
                   level: float = ADOPTION_LEVEL) -> Tuple[bool, str]:
    """Whether a learned candidate's per-recording AAE ``got`` beats the classical choice's ``ref``
    (same recordings) by a margin its spread supports: the mean paired gain above ``tie_margin`` of
    the reference's mean *plus* the one-sided Student-t quantile at ``level`` with n − 1 degrees of
    freedom times the standard error of the gains (n = recordings: with 2 recordings one standard
    error let noise through about a quarter of the time; the t quantile holds the stated level).
    Fewer than :data:`MIN_ADOPTION_RECORDINGS`: no adoption, said. Returns (adopt, why)."""
    import numpy as np
    from scipy.stats import t as student_t

    ref_a, got_a = np.asarray(ref, dtype=float), np.asarray(got, dtype=float)
    if ref_a.shape != got_a.shape or ref_a.size == 0:
        raise ValueError(f"gain_supported: {ref_a.size} reference scores vs {got_a.size} learned ones")
    if not np.all(np.isfinite(got_a)):
        return False, "diverged on a validation recording"
    d = ref_a - got_a
    if d.size < MIN_ADOPTION_RECORDINGS:
        return False, (f"{d.size} validation recording(s), fewer than {MIN_ADOPTION_RECORDINGS}: the search cannot "
                       "decide and keeps the classical choice")
    mean, se = float(d.mean()), float(d.std(ddof=1) / math.sqrt(d.size))
    q = float(student_t.ppf(1.0 - level, d.size - 1))
    need = tie_margin * float(ref_a.mean()) + q * se
    return mean > need, (f"gain {mean:.3f} deg vs needed {need:.3f} ({tie_margin:.0%} + {q:.2f} x standard error "
                         f"{se:.3f}: one-sided {level:.0%} over {d.size} recordings)")
