"""The search's report: the per-fold summary (``docs/results.md``'s generated tables) and the
full ``search.md`` with every candidate's inner and outer scores."""
from __future__ import annotations

from typing import Any, Dict, List

import numpy as np


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
    lines.append(f"Expected on new recordings of this device: {expected_gain(rows)['sentence']}.")
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
            what = " (networks off: the backbone with its knobs)" if c.get("networks_off") else ""
            lines.append(f"| {name}{what} | {c['inner_val_aae']:.2f} | {c['inner_val_inclination']:.2f} | "
                         f"{t.get('aae_deg', float('nan')):.2f} | {t.get('inclination_deg', float('nan')):.2f} | {knobs} |")
    return "\n".join(lines) + "\n"


def expected_gain(rows: List[Dict[str, Any]]) -> Dict[str, Any]:
    """How much better than the best classical filter (defaults, raw or calibrated) the search's
    choice is expected to be on new recordings of the device: the relative AAE gain of each outer
    fold x seed run, (bar - chosen) / bar, its mean and sample spread (positive: better)."""
    gains = np.array([(r["best_classical_aae_deg"] - r["aae_deg"]) / r["best_classical_aae_deg"] for r in rows
                      if r["best_classical_aae_deg"] > 0], dtype=float)
    if gains.size == 0:
        return {"mean": None, "std": None, "n": 0, "sentence": "no outer fold scored"}
    mean, std = float(gains.mean()), float(gains.std(ddof=1)) if gains.size > 1 else 0.0
    word = "better" if mean >= 0 else "worse"
    return {"mean": mean, "std": std, "n": int(gains.size),
            "sentence": f"{abs(mean):.0%} {word} than the best classical filter with its defaults "
                        f"(± {std:.0%} over {gains.size} outer fold x seed runs; worst {gains.min():+.0%})"}


def final_summary(result: Dict[str, Any], out) -> str:
    """The lines a person reads at the end of ``tcn-ahrs search``: the device, the release and how
    to run it, its expected gain over the best classical filter, and what a lighter search left out."""
    rel = result.get("release") or {}
    gain = result.get("expected_gain") or expected_gain(result["rows"])
    lines = ["", "== search summary",
             f"device: {result['dataset']} ({result['axes']}-axis), {len({n for r in result['folds'] for n in r['recordings']})}"
             f" recordings in {len({r['fold'] for r in result['rows']})} outer folds; {result['seconds'] / 60:.1f} min",
             f"release: {rel.get('chosen')}{' (networks off: the backbone with learned knobs)' if rel.get('networks_off') else ''}"
             f" ({rel.get('times_chosen')} of {rel.get('runs')} runs) -> "
             f"{rel.get('path') or rel.get('how')}",
             f"expected on new recordings of this device: {gain['sentence']}"]
    if rel.get("path"):
        lines.append(f"run it: tcn-ahrs evaluate ckpt={rel['path']} data=... (the model card: "
                     f"{rel.get('card', 'the file holds its provenance')})")
    if result.get("skipped"):
        lines.append(f"a lighter search than the full one: {'; '.join(result['skipped'])}")
    lines.append(f"report: {out}/search.md")
    return "\n".join(lines)
