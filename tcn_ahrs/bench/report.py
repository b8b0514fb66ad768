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


def to_markdown(res: Dict[str, Any]) -> str:
    env = res["environment"]
    out = ["# Speed benchmark", "",
           f"device={env['device']}; torch {env['torch']}, numpy {env['numpy']}, Python {env['python']}; "
           f"CPU {env['cpu']} ({env['cpu_count']} logical cores, torch threads {env['torch_threads']}); "
           f"GPU {env['gpu'] or 'none'}; peers {env['peers']}; git {env.get('git_commit')}; "
           f"load average start {env.get('loadavg_start')} end {env.get('loadavg_end')}; "
           f"quick={res['config']['quick']}; total {res['total_s']:.0f} s.", ""]
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
    return "\n".join(out)
