"""The speed benchmark's Markdown report."""
from __future__ import annotations

from typing import Any, Dict, List




def _f(v, fmt="{:.3g}") -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return fmt.format(v)
    return str(v)


def _table(head: List[str], rows: List[List[Any]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    lines += ["| " + " | ".join(_f(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def _row(rows: List[Dict[str, Any]], name: str) -> Dict[str, Any]:
    return next((r for r in rows if r.get("name") == name or r.get("variant") == name), {})


def summary_table(res: Dict[str, Any]) -> str:
    """The README's speed table: one row per goal, each figure beside its peer from this run."""
    lines = ["| what | measured (this run) | goal | |", "|---|---|---|---|"]
    tr = res.get("train")
    if tr:
        rows = tr["rows"]
        e = _row(rows, tr["baseline"]) if tr.get("baseline") else {}
        cells = [f"{r['variant']} {r['samples_per_s'] / 1e3:.0f} k samples/s ({r['vs_baseline']:.2f}x)"
                 for r in rows if "samples_per_s" in r]
        lines.append(f"| training step, shipped recipe (32 x 1000 samples, closed loop), {tr['threads']} threads | "
                     f"{'; '.join(cells)}; epoch {e.get('epoch_s', float('nan')):.0f} s, {tr['epochs']} epochs "
                     f"{e.get('schedule_h', float('nan')) * 60:.0f} min | fastest correct step | "
                     + " ".join(f"_{n}_" for n in tr["notes"] if "loss curve" in n and "eager deviates" not in n) + " |")
    inf = res.get("inference")
    if inf:
        rows = inf["rows"]
        ev = _row(rows, "eager LearnedAHRS.run_sequence (evaluation; loop compiled by numba)")
        tsb = _row(rows, "TorchScript batch module (export_batch)")
        net = _row(rows, "calibration networks only (eager, float32)")
        lines.append(f"| batch inference, 60 s at 100 Hz, 9-axis, 1 thread | evaluation path {ev.get('median_ms', float('nan')):.1f} ms "
                     f"(networks {net.get('median_ms', float('nan')):.1f} ms at {net.get('tcn_gflops', float('nan')):.0f} GFLOP/s, "
                     f"GEMM peak {inf['gemm_peak_gflops']:.0f}); TorchScript batch {tsb.get('median_ms', float('nan')):.1f} ms | "
                     f"<= {inf['goal_ms']:.0f} ms | {'met' if inf['goal_met'] else 'not met'} (TorchScript: "
                     f"{'met' if inf['torchscript_goal_met'] else 'not met'}) |")
    st = res.get("streaming")
    if st:
        rows = st["rows"]
        ri = next((r for r in rows if r["name"].startswith("RIANN predict_step") and "samples_per_s" in r), {})

        def fig(name):
            r = _row(rows, name)
            if "samples_per_s" not in r:
                return f"{name}: -"
            vs = f", {r['vs_riann_step']:.2f}x RIANN" if "vs_riann_step" in r else ""
            return f"{name} {r['median_us']:.1f} us ({r['samples_per_s'] / 1e3:.0f} k/s{vs})"
        k = st["chunk"]
        lines.append(f"| streaming step, 9-axis, 1 thread | {fig('CompiledStreaming step (numba, 9-axis)')}; "
                     f"{fig('TorchScript step (9-axis)')}; RIANN predict_step {ri.get('median_us', float('nan')):.1f} us | "
                     f">= {st['goal_samples_per_s'] / 1e3:.0f} k/s and > RIANN | {'met' if st['goal_met'] else 'not met'} |")
        lines.append(f"| chunked step, {k} per call, 9-axis | {fig(f'CompiledStreaming step_chunk, {k} per call (9-axis)')}; "
                     f"{fig(f'TorchScript step_chunk, {k} per call (9-axis)')} | >= {st['goal_chunk_samples_per_s'] / 1e6:.0f} M/s | "
                     f"{'met' if st['chunk_goal_met'] else 'not met'} |")
    fi = res.get("filters")
    if fi:
        def rate(name, batch):
            r = next((r for r in fi["rows"] if r["name"] == name and r.get("batch") == batch and "samples_per_s" in r), {})
            return r.get("samples_per_s", float("nan")) / 1e6
        names = [("ECF", "tcn_ahrs.filters.ecf"), ("Mahony", "tcn_ahrs.filters.mahony"),
                 ("Madgwick", "tcn_ahrs.filters.madgwick"), ("ES-EKF", "tcn_ahrs.filters.eskf")]
        batches = [b for b in (1, 64) if any(r.get("batch") == b for r in fi["rows"])]
        cells = "; ".join(f"{lab} " + " / ".join(f"{rate(n, b):.2f}" for b in batches) for lab, n in names)
        vqf = next((r for r in fi["rows"] if r["name"].startswith("vqf") and "samples_per_s" in r), {})
        imf = next((r for r in fi["rows"] if r["name"].startswith("imufusion") and "samples_per_s" in r), {})
        lines.append(f"| classical filters, {fi['samples']} samples, 1 thread (M samples/s, one recording / "
                     f"{batches[-1]} parameter sets) | {cells}; VQF {vqf.get('samples_per_s', float('nan')) / 1e6:.2f}, "
                     f"imufusion {imf.get('samples_per_s', float('nan')) / 1e6:.2f} | >= 0.5 M single, >= 3 M aggregate | "
                     f"{', '.join(lab for lab, n in names if rate(n, 1) >= 0.5 and rate(n, batches[-1]) >= 3.0) or 'none'} met |")
    return "\n".join(lines)


def to_markdown(res: Dict[str, Any]) -> str:
    env = res["environment"]
    out = ["# Speed benchmark", "",
           f"device={env['device']}; torch {env['torch']}, numpy {env['numpy']}, Python {env['python']}; "
           f"CPU {env['cpu']} ({env['cpu_count']} logical cores, torch threads {env['torch_threads']}); "
           f"GPU {env['gpu'] or 'none'}; peers {env['peers']}; git {env.get('git_commit')}; "
           f"load average start {env.get('loadavg_start')} end {env.get('loadavg_end')}; "
           f"quick={res['config']['quick']}; total {res['total_s']:.0f} s.", "",
           "## Summary (the README's speed table)", "", summary_table(res), ""]
    tr = res.get("train")
    if tr:
        e = tr["epoch"]
        what = ("the shipped recipe (closed loop, truncated backpropagation through one chunk after the networks' "
                "context, attitude loss)" if tr.get("model", "closed") == "closed"
                else "the paper's open-loop model (TCN + ECF + increment loss)")
        out += ["## Training step (forward + backward + AdamW)", "", f"Model: {what}.",
                f"Shape batch {tr['shape']['batch_size']} x window {tr['shape']['window']} x {tr['shape']['axes']} axes, "
                f"{tr['threads']} torch threads. Epoch = {e['windows']} windows (stride) = {e['steps']} steps; "
                f"BROAD training split {e['samples']} samples ({e['source']}). Schedule = {tr['epochs']} epochs "
                "(training steps only, no validation).", ""]
        rows = []
        for r in tr["rows"]:
            if "samples_per_s" in r:
                rows.append([r["variant"], r["step_s"], r["steps_timed"], r["samples_per_s"],
                             f"{r['vs_baseline']:.2f}x", r["compile_s"], r["one_pass_s"], r["epoch_s"], r["schedule_h"]])
            else:
                rows.append([r["variant"], "-", "-", "-", "-", "-", "-", "-", r.get("skipped")])
        out += [_table(["variant", "step s", "steps", "samples/s", f"vs {tr['baseline']}", "compile s",
                        "one pass over split s", "epoch s", "schedule h / note"], rows)]
        out += [f"\n_{n}_" for n in tr["notes"]] + [""]
    inf = res.get("inference")
    if inf:
        out += ["## Batch inference (one sequence)", "",
                f"Model: {inf['model']}. {inf['samples']} samples at {inf['rate_hz']:.0f} Hz, 9-axis; the calibration "
                f"networks take {inf['tcn_gflop']:.2f} GFLOP; this core's float32 matrix-product peak, measured in "
                f"this run: {inf['gemm_peak_gflops']:.0f} GFLOP/s. Goal <= {inf['goal_ms']:.0f} ms on 1 CPU thread: "
                f"{'met' if inf['goal_met'] else 'NOT met'} (fastest: {inf['best']}); by the TorchScript batch "
                f"module: {'met' if inf['torchscript_goal_met'] else 'NOT met'}.", ""]
        rows = [[r["name"], r.get("threads"), r.get("median_ms"), r.get("p99_ms"),
                 f"{r['vs_eager']:.2f}x" if "vs_eager" in r else r.get("skipped"), r.get("tcn_gflops")]
                for r in inf["rows"]]
        out += [_table(["path", "threads", "median ms", "p99 ms", "/ evaluation path", "networks' GFLOP/s"], rows), ""]
    st = res.get("streaming")
    if st:
        out += ["## Streaming (one sample, or one chunk, per call)", "",
                f"Models: {st['models']}. samples/s = 1 / median latency per sample (1 / mean in brackets, "
                f"includes preemption by other processes). Goals on 1 CPU thread: a per-sample step >= "
                f"{st['goal_samples_per_s']:.0f} samples/s and faster than RIANN's step: "
                f"{'met' if st['goal_met'] else 'NOT met'} (fastest: {st['best_step']}); a chunked step >= "
                f"{st['goal_chunk_samples_per_s']:.0f} samples/s at {st['chunk']} samples per call: "
                f"{'met' if st['chunk_goal_met'] else 'NOT met'} (fastest: {st['best_chunk']}).", ""]
        rows = [[r["name"], r.get("threads"), r.get("median_us"), r.get("p99_us"),
                 f"{r['samples_per_s']:.3g}" + (f" ({r['samples_per_s_mean']:.3g})" if "samples_per_s_mean" in r else "")
                 if "samples_per_s" in r else "-",
                 f"{r['vs_riann_step']:.2f}x" if "vs_riann_step" in r else r.get("skipped", "-")] for r in st["rows"]]
        out += [_table(["path", "threads", "median us per sample", "p99 us", "samples/s", "/ RIANN step"], rows), ""]
    fi = res.get("filters")
    if fi:
        out += ["## Classical filters", "",
                f"Recording {fi['recording']} ({fi['samples']} samples at {fi['rate_hz']:.0f} Hz, 9-axis); "
                f"batch = number of parameter sets run in one call (samples/s is the aggregate). "
                f"Goal (batched aggregate >= VQF single): {fi['goal_met']}.", ""]
        rows = [[r["name"], r.get("device"), r.get("loop", "-"), r.get("batch"), r.get("seconds"), r.get("samples_per_s"),
                 f"{r['vs_vqf']:.2f}x" if "vs_vqf" in r else r.get("skipped", "-"),
                 f"{r['vs_torch_loop']:.0f}x" if "vs_torch_loop" in r else "-"] for r in fi["rows"]]
        out += [_table(["filter", "device", "loop", "batch", "s per call", "samples/s", "/ VQF", "/ torch loop"], rows), ""]
    if res.get("deploy"):
        from .deploy import markdown as deploy_markdown

        out += ["## Deployment runtimes and footprint", "", deploy_markdown(res["deploy"]), ""]
    return "\n".join(out)
