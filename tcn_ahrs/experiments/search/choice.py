"""The search's choice rules, pure functions of the candidates' inner-validation scores: one
fold and seed (:func:`choose_candidate`), one fold over its seeds (:func:`fold_choice`), the
release over the folds (:func:`release_choice`), and the bar each outer fold is scored against
(:func:`best_classical`)."""
from __future__ import annotations

import math
from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np

from ...estimators.families import SIMPLICITY


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


def classical_choice(cands: Dict[str, Dict[str, Any]], tie_margin: float, incl_margin: float) -> str:
    """The choice among the classical candidates alone: :func:`choose` on their mean over the inner
    splits, the inclination bar the best untuned filter's."""
    classical = {k: v for k, v in cands.items() if v["calibration"] != "learned"}
    mean = {k: np.mean(np.asarray(v["inner_val"], dtype=float), axis=0) for k, v in classical.items()}
    bar_incl = min(float(mean[k][1]) for k, v in classical.items() if not v["tuned"])
    return choose({k: (float(m[0]), float(m[1])) for k, m in mean.items()}, tie_margin, incl_margin, bar_incl)


def choose_candidate(cands: Dict[str, Dict[str, Any]], learned_split: int, tie_margin: float,
                     incl_margin: float) -> str:
    """The choice among one fold's candidate records (``inner_val``: a row of (AAE, inclination)
    per inner split; a learned candidate has one row, its ``learned_split``): the classical ones by
    :func:`choose` on their mean over the splits (inclination bar: the best untuned filter's), then
    a learned one replaces that choice if it is better on the split it was validated on, at an
    inclination within ``incl_margin``, by more than ``tie_margin`` plus the standard error of its
    gain over that split's recordings (:func:`tcn_ahrs.experiments.search.learn.gain_supported`;
    records without per-recording scores: by ``tie_margin``)."""
    chosen = classical_choice(cands, tie_margin, incl_margin)
    for name, v in cands.items():
        if v["calibration"] != "learned":
            continue
        # the current choice on the learned split (a learned one has that split's row only)
        row = 0 if cands[chosen]["calibration"] == "learned" else learned_split
        ref = cands[chosen]["inner_val"][row]
        got = v["inner_val"][0]
        if got[1] > ref[1] + incl_margin:
            continue
        if "inner_val_recordings" in v and "inner_val_recordings" in cands[chosen]:
            # the gain must stand above its spread over the validation recordings (learn.gain_supported)
            from .learn import gain_supported

            if gain_supported(cands[chosen]["inner_val_recordings"][row], v["inner_val_recordings"][0], tie_margin)[0]:
                chosen = name
        elif got[0] < ref[0] * (1.0 - tie_margin):  # a record written before per-recording scores
            chosen = name
    return chosen


def adoption_reasons(cands: Dict[str, Dict[str, Any]], learned_split: int, tie_margin: float,
                     incl_margin: float) -> Dict[str, str]:
    """Per learned candidate, what its paired test said against the classical choice on the
    recordings it was validated on (:func:`tcn_ahrs.experiments.search.learn.gain_supported`): the
    search prints it, so "cannot decide" (fewer than three recordings) is never silent."""
    from .learn import gain_supported

    ref = classical_choice(cands, tie_margin, incl_margin)
    out = {}
    for name, v in cands.items():
        if v["calibration"] == "learned" and "inner_val_recordings" in v and "inner_val_recordings" in cands[ref]:
            out[name] = f"against {ref}: " + gain_supported(cands[ref]["inner_val_recordings"][learned_split],
                                                            v["inner_val_recordings"][0], tie_margin)[1]
    return out


def fold_choice(records: Sequence[Dict[str, Any]], tie_margin: float, incl_margin: float) -> str:
    """One outer fold's choice from all its seeds: every candidate's inner-validation scores
    averaged over the seeds (only the tuned knobs differ by seed), then :func:`choose_candidate`.
    A choice that flipped with the sampler's seed (EuRoC fold 0: closed loop on one seed, the
    calibrated backbone on two) cannot flip: the fold has one choice, scored for every seed."""
    first = records[0]
    def mean_over_seeds(name: str, key: str):  # split by split (splits may hold unequal numbers of recordings)
        rows = [r["candidates"][name][key] for r in records]
        return [np.mean([np.asarray(r[j], dtype=float) for r in rows], axis=0).tolist() for j in range(len(rows[0]))]

    pooled = {name: dict(c, inner_val=mean_over_seeds(name, "inner_val"),
                         **({"inner_val_recordings": mean_over_seeds(name, "inner_val_recordings")}
                            if "inner_val_recordings" in c else {}))
              for name, c in first["candidates"].items()}
    return choose_candidate(pooled, int(first.get("learned_split", 0)), tie_margin, incl_margin)


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
    learned_tied = any(r["candidates"][k]["calibration"] == "learned" for r in recs for k in tied if k in r["candidates"])

    def score(name: str) -> float:
        vals = []
        for r in recs:
            if name not in r["candidates"]:  # a learned recipe that failed to train in that fold
                continue
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


def best_classical(record: Dict[str, Any]) -> Tuple[str, float, float]:
    """(name, AAE, best inclination) on one fold's outer recordings of the bar: every family with
    its defaults, on the raw and on the calibrated signals — the lowest mean AAE, and the lowest
    inclination of any of them (what the chosen estimator must not be worse than)."""
    cols = {k: record["test"][k] for k in record["bar"] if record["test"][k].get("aae_deg") is not None}
    name = min(cols, key=lambda k: cols[k]["aae_deg"])
    return name, float(cols[name]["aae_deg"]), float(min(v["inclination_deg"] for v in cols.values()))
