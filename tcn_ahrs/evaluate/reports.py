"""Every table of the project from one module, one label set, degrees everywhere: the runner's
results.md and terminal table, and compare's results.md (one table per metric, methods in rows)."""
from __future__ import annotations

import sys
from typing import Iterable, List, Optional, Sequence

from .. import metrics
from ..metrics import extra_metrics

_SHORT = {"aae_deg": "AAE", "aye_deg": "AYE", "ahe_deg": "AHE", "total_deg": "total", "heading_deg": "heading",
          "inclination_deg": "incl."}
_LONG = {"total_deg": "BROAD total", "heading_deg": "BROAD heading", "inclination_deg": "inclination"}


def label(key: str, long: bool = False) -> str:
    """Table heading of a metric key: the built-ins' names, a registered metric's own label."""
    if long and key in _LONG:
        return _LONG[key]
    if key in _SHORT:
        return _SHORT[key]
    return next((m.label for m in extra_metrics() if m.key == key), key)


def _extra_keys(results: dict) -> List[str]:
    """Registered extra metrics present in these results."""
    return [m.key for m in extra_metrics() if _has(results, m.key)]


MAX_PLOT_POINTS = 5000


def _fmt(v) -> str:
    return "—" if v is None else f"{v:.2f}"


def _has(results: dict, key: str) -> bool:
    return any(key in r for m in results["methods"].values() for r in m["recordings"])


def _metric_rows(results: dict, key: str, columns: List[str], values, bold_best: bool) -> List[str]:
    """One Markdown table: a row per method, a column per entry of ``columns`` (values(method,
    column) -> number or None); the lowest value of each column in bold."""
    methods = list(results["methods"])
    table = {m: [values(m, c) for c in columns] for m in methods}
    best = [min((table[m][j] for m in methods if table[m][j] is not None), default=None)
            for j in range(len(columns))]
    lines = [f"| {label(key)} (deg) | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for m in methods:
        cells = []
        for j, v in enumerate(table[m]):
            s = _fmt(v)
            if bold_best and len(methods) > 1 and v is not None and v == best[j]:
                s = f"**{s}**"
            cells.append(s)
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return lines


def markdown_table(results: dict, metric_keys: Iterable[str] = ("aae_deg", "aye_deg"),
                   bold_best: bool = True) -> str:
    """One Markdown table per metric: a row per method, a column per recording and the
    Average (the mean over recordings); the best (lowest) of each column in bold. Readable with
    dozens of methods (the full method x metric matrix is in ``results.json``)."""
    recs = list(results["recordings"])
    out = []
    for key in metric_keys:
        def val(m, c, key=key):
            r = results["methods"][m]
            return (r["mean"] if c == "Average" else r["recordings"][recs.index(c)]).get(key)
        out.append("\n".join(_metric_rows(results, key, recs + ["Average"], val, bold_best)))
    return "\n\n".join(out) + "\n"


def group_table(results: dict, metric_keys: Iterable[str] = ("aae_deg", "aye_deg"), bold_best: bool = True) -> str:
    """Per-group averages, one Markdown table per metric: a row per method, a column per group
    (``group (n)``, n recordings)."""
    methods = list(results["methods"])
    groups: List[str] = []
    for m in methods:
        for g in results["methods"][m].get("groups", {}):
            if g not in groups:
                groups.append(g)
    first = results["methods"][methods[0]].get("groups", {})
    cols = [f"{g} ({first.get(g, {}).get('n_recordings', '?')})" for g in groups]
    out = []
    for key in metric_keys:
        def val(m, c, key=key):
            return results["methods"][m].get("groups", {}).get(groups[cols.index(c)], {}).get(key)
        out.append("\n".join(_metric_rows(results, key, cols, val, bold_best)))
    return "\n\n".join(out) + "\n"


def alignment_text(results: dict) -> str:
    """How the table's estimates were aligned, in words (results.json's ``align``; older files
    hold a bool: True = at the first scored sample)."""
    from ..metrics import alignment_name

    a = alignment_name(results.get("align", "first"))
    return {"protocol": "the yardstick of docs/conventions.md: the first 2 s unscored, heading aligned once "
                        "about the vertical (9-axis on magnetic-north ground truth: none), inclination absolute",
            "heading": "heading aligned once about the vertical, inclination absolute",
            "first": "one rotation aligning the estimate at the first scored sample",
            "none": "no alignment"}.get(a, str(a))


def results_markdown(results: dict) -> str:
    """The whole ``results.md``: AAE/AYE table, BROAD errors (if any), group averages (if any)."""
    title = results.get("dataset") or "evaluation"
    parts = [f"# Results: {title}\n",
             f"AAE / AYE in degrees (RMS over scored samples; {alignment_text(results)}); AHE: heading "
             f"error about the navigation vertical, aligned the same way.\n",
             markdown_table(results, ("aae_deg", "aye_deg", "ahe_deg"))]
    broad_keys = ("total_deg", "heading_deg", "inclination_deg")
    if _has(results, "total_deg"):
        parts += ["\n## BROAD errors\n",
                  "Total / heading / inclination RMSE in degrees, earth-frame error, no alignment "
                  "(6-axis estimates: constant heading offset removed).\n",
                  markdown_table(results, broad_keys)]
    extra = _extra_keys(results)
    if extra:
        parts += ["\n## Further metrics\n", markdown_table(results, extra)]
    if any(m.get("groups") for m in results["methods"].values()):
        keys = broad_keys if _has(results, "total_deg") else ("aae_deg", "aye_deg")
        parts += ["\n## Group averages\n", group_table(results, ("aae_deg", "aye_deg") + tuple(
            k for k in keys if k not in ("aae_deg", "aye_deg")))]
    return "\n".join(parts)


def print_table(results: dict, metric_keys: Optional[Iterable[str]] = None, file=None) -> None:
    """Plain-text tables for terminals (< 100 columns): one block per method, rows recordings
    (+ Average), columns the metrics, all in degrees."""
    file = file or sys.stdout
    if metric_keys is None:
        metric_keys = ["aae_deg", "aye_deg", "ahe_deg"] + [k for k in metrics.metric_keys()[3:] if _has(results, k)]
    metric_keys = list(metric_keys)
    names = [r if len(r) <= 40 else r[:19] + "~" + r[-20:] for r in results["recordings"]]
    w0 = max([len("recording"), len("Average")] + [len(r) for r in names])
    widths = [max(7, len(label(k))) for k in metric_keys]
    for method, mres in results["methods"].items():
        print(f"\n{method} — attitude errors in degrees", file=file)
        print(f"{'recording':<{w0}}  " + "  ".join(f"{label(k):>{w}}" for k, w in zip(metric_keys, widths)),
              file=file)
        rows = list(zip(names, mres["recordings"])) + [("Average", mres["mean"])]
        for row_name, vals in rows:
            print(f"{row_name:<{w0}}  " + "  ".join(f"{_fmt(vals.get(k)):>{w}}" for k, w in zip(metric_keys, widths)),
                  file=file)


def print_summary(results: dict, learned: str, file=None) -> None:
    """One line per method, its mean AAE and inclination (degrees), the best classical filter
    (the lowest mean AAE among the methods other than ``learned`` and Raw IMU) marked."""
    file = file or sys.stdout
    means = {m: r["mean"] for m, r in results["methods"].items()}
    classical = [m for m in means if m != learned and not m.startswith("Raw") and means[m].get("aae_deg") is not None]
    best = min(classical, key=lambda m: means[m]["aae_deg"]) if classical else None
    w = max(len(m) for m in means)
    print(f"\n{'method':<{w}}  {'AAE':>7}  {'incl.':>7}", file=file)
    for m, v in means.items():
        mark = "  <- best classical" if m == best else ("  <- learned" if m == learned else "")
        print(f"{m:<{w}}  {_fmt(v.get('aae_deg')):>7}  {_fmt(v.get('inclination_deg')):>7}{mark}", file=file)


# ---------------------------------------------------------------------------
# files: TUM trajectories, plots
# ---------------------------------------------------------------------------


def _subset(results: dict, names: Sequence[str]) -> dict:
    r = dict(results)
    r["methods"] = {n: results["methods"][n] for n in names if n in results["methods"]}
    return r


def compare_markdown(results: dict) -> str:
    """results.md of a comparison: averages, one table per metric (AAE, AYE; inclination or
    BROAD total/heading/inclination; methods in rows), group averages, ablation (the paper's
    Table 3 columns), tuned parameters."""
    title = results.get("dataset") or "comparison"
    hf = [n for n, c in results.get("columns", {}).items() if c.get("heading_free")]
    parts = [f"# Comparison: {title}\n",
             f"Recordings: {len(results['recordings'])}. AAE / AYE in degrees (RMS over scored samples; "
             f"{alignment_text(results)}). "
             "Bold: best in the column. `—`: not defined"
             + (f" (heading-free estimators {', '.join(hf)} are scored on inclination only)" if hf else "")
             + ".\n",
             "## Averages over recordings (deg)\n", averages_markdown(results),
             "\n## AAE / AYE (methods in rows, recordings in columns)\n",
             markdown_table(results, ("aae_deg", "aye_deg"))]
    broad = _has(results, "total_deg")
    if broad:
        parts += ["\n## BROAD errors: total / heading / inclination (deg, no alignment; 6D: heading offset removed)\n",
                  markdown_table(results, ("total_deg", "heading_deg", "inclination_deg"))]
    elif _has(results, "inclination_deg"):
        parts += ["\n## Inclination error (deg, BROAD definition, no alignment; needs no heading)\n",
                  markdown_table(results, ("inclination_deg",))]
    extra = _extra_keys(results)
    if extra:
        parts += ["\n## Further metrics (registered; deg)\n", markdown_table(results, extra)]
    if any(m.get("groups") for m in results["methods"].values()):
        keys = ("total_deg", "heading_deg", "inclination_deg") if broad else ("aae_deg", "aye_deg", "inclination_deg")
        key = "total_deg" if broad else "aae_deg"
        parts += [f"\n## Group averages: {label(key)} (rows methods, columns groups)\n",
                  group_table(results, (key,)),
                  "\n## Group averages: all metrics\n", group_table(results, keys)]
    abl = results.get("ablation") or []
    if abl:
        parts += ["\n## Ablation (paper Table 3): AAE / AYE\n",
                  markdown_table(_subset(results, abl), ("aae_deg", "aye_deg"))]
    tun = results.get("tuning") or {}
    if tun.get("enabled"):
        recs = ", ".join(f"{r['name']} [{r['start_s']:.0f}+{r['duration_s']:.0f} s]" for r in tun.get("recordings", []))
        parts += ["\n## Tuned parameters\n",
                  f"Grid search, mean AAE over {len(tun.get('recordings', []))} training clips: {recs}.\n",
                  "| column | parameters | tuning AAE | grid | time [s] |", "|---|---|---|---|---|"]
        for name, t in tun.get("methods", {}).items():
            parts.append(f"| {name} | {t['params']} | {t['score_aae_deg'] if t['score_aae_deg'] is None else round(t['score_aae_deg'], 2)} "
                         f"| {t['grid_size']} | {t['time_s']} |")
        parts.append("")
    tm = results.get("timing")
    if tm:
        parts.append(f"\nWall time: tuning {tm['tune_s']} s, evaluation {tm['evaluate_s']} s, total {tm['total_s']} s.\n")
    return "\n".join(parts)


def averages_markdown(results: dict) -> str:
    """Markdown: one row per method (column of the big tables) with its mean over recordings of
    every metric present — the compact summary a README quotes."""
    keys = [k for k in metrics.metric_keys() if any((m.get("mean") or {}).get(k) is not None for m in results["methods"].values())]
    lines = ["| method | " + " | ".join(label(k, long=True) for k in keys) + " |", "|---" * (len(keys) + 1) + "|"]
    for name, m in results["methods"].items():
        mean = m.get("mean") or {}
        lines.append(f"| {name} | " + " | ".join("—" if mean.get(k) is None else f"{mean[k]:.2f}" for k in keys) + " |")
    return "\n".join(lines)


def average_rows(results: dict, keys: Optional[Sequence[str]] = None) -> str:
    """Compact text: one line per column with its averages (for logs and reports); ``keys``
    default: every metric of :func:`tcn_ahrs.metrics.metric_keys`."""
    keys = metrics.metric_keys() if keys is None else keys
    lines = [f"{'column':<28s} " + " ".join(f"{k:>16s}" for k in keys)]
    for name, m in results["methods"].items():
        mean = m.get("mean", {})
        lines.append(f"{name:<28s} " + " ".join(
            f"{'—' if mean.get(k) is None else format(mean[k], '.2f'):>16s}" for k in keys))
    return "\n".join(lines)
