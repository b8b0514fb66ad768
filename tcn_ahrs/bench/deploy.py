"""The speed benchmark's ``deploy`` section: every runtime of a shipped residual checkpoint side by
side in one run, on the same samples and one thread, beside VQF's C++ and RIANN, and what each
shipped model costs on a device.

Per-sample step rows (``median_us`` of single ``step`` calls from Python): the numba runtime
(``BackboneStreaming``), TorchScript (``ResidualStreaming``), ONNX (``OnnxStreaming``, one
onnxruntime run per sample), torch.export (``ExportedStreaming``, eager: timed on ``slow_steps``),
the C runtime through ctypes, VQF's per-sample ``update`` and RIANN's ``predict_step``. Loop rows
(``per_sample_us`` = the time of one call over the whole recording / its samples, no Python per
sample): the C runtime's ``name_run`` (-O2 and -march=native; float, the default, and double), VQF's C++ ``updateBatch``, numba's ``run``.
The C runtime against VQF's C++ is the like-for-like figure: both loops in compiled code.

Footprint rows, one per ``checkpoints/*.ckpt``: parameters, float32 weight bytes, the C runtime's
weights (float32 convolutions + the head) and ring buffers (float32; the backbone's state
adds a few hundred bytes: ``sizeof(state)`` of the timed model is in its row), the networks' FLOPs
per sample.
"""
from __future__ import annotations

import shutil
import statistics
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Dict, List

import numpy as np
import torch


REPO = Path(__file__).resolve().parents[2]


def _found(path) -> Path:
    """``path`` as given, else inside the checkout (``checkpoints/...`` from any folder); ValueError
    naming both when neither exists."""
    p = Path(str(path))
    if p.is_file() or p.is_absolute():
        if not p.is_file():
            raise ValueError(f"speed.deploy.ckpt: no checkpoint at {p}")
        return p
    if (REPO / p).is_file():
        return REPO / p
    raise ValueError(f"speed.deploy.ckpt: no checkpoint at {p} (nor at {REPO / p})")


def _steps(name: str, step: Callable[[int], Any], n: int, warm: int) -> Dict[str, Any]:
    for k in range(warm):
        step(k)
    ts = []
    for k in range(warm, warm + n):
        t = time.perf_counter_ns()
        step(k)
        ts.append((time.perf_counter_ns() - t) / 1e3)
    return {"name": name, "kind": "step", "median_us": statistics.median(ts), "steps": n}


def _loop(name: str, run: Callable[[], Any], n: int, repeats: int = 3) -> Dict[str, Any]:
    run()  # warm (compilation, caches)
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - t)
    return {"name": name, "kind": "loop", "per_sample_us": 1e6 * best / n, "samples": n}


_ISOLATED = """
import importlib.util, sys, time, numpy as np
so, name, axes, xs, dt = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4], float(sys.argv[5])
spec = importlib.util.spec_from_file_location("cruntime", sys.argv[6])   # the ctypes wrapper alone: no torch
module = importlib.util.module_from_spec(spec)
spec.loader.exec_module(module)
CRuntime = module.CRuntime
x, q0 = np.load(xs), np.load(xs.replace(".npy", "_q0.npy"))
rt = CRuntime(so, name, axes)
best = float("inf")
for _ in range(4):
    t = time.perf_counter(); rt.reset(q0); rt.run(x, dt); best = min(best, time.perf_counter() - t)
print(1e6 * best / x.shape[0], rt.state_size)
"""


def _isolated_loop(so, name: str, axes: int, x, dt: float, q0, tmp: Path) -> Dict[str, Any]:
    """A C library's loop timed in a process of its own. A -march=native build on an AVX-512
    CPU can leave the vector registers' upper halves dirty; every later SSE instruction in the
    process (VQF's C++, libm, the -O2 builds) then runs several times slower (measured here:
    VQF 0.27 -> 0.99 µs/sample in the same process), so no other row may share its process."""
    import subprocess
    import sys

    xs = tmp / f"x_{name}_{axes}.npy"
    np.save(xs, np.ascontiguousarray(x, dtype=np.float32))
    np.save(str(xs).replace(".npy", "_q0.npy"), np.asarray(q0, dtype=np.float32))
    from ..export.c.cruntime import PATH

    r = subprocess.run([sys.executable, "-c", _ISOLATED, str(so), name, str(axes), str(xs), repr(float(dt)), str(PATH)],
                       capture_output=True, text=True, timeout=600)
    if r.returncode != 0:
        raise RuntimeError(f"isolated C loop failed: {r.stderr[-1000:]}")
    us, size = r.stdout.split()[-2:]
    return {"per_sample_us": float(us), "state_bytes": int(size)}


def _skipped(name: str, e: BaseException) -> Dict[str, Any]:
    return {"name": name, "skipped": f"{type(e).__name__}: {e}"}


def bench_deploy(p: Dict[str, Any], seed: int = 0) -> Dict[str, Any]:
    from ..checkpoint import model_from_checkpoint
    from ..datasets.simulate import simulate

    ckpt = str(_found(p["ckpt"]))
    n, warm, slow = int(p["samples"]), int(p["warmup"]), int(p["slow_steps"])
    torch.set_num_threads(1)
    model = model_from_checkpoint(ckpt).eval()
    axes = int(model.axes)
    rate = float(p["rate"])
    seq = simulate("walking", (n + warm) / rate + 1.0, rate, seed=seed, axes=axes)
    imu = np.concatenate([seq.gyro, seq.accel] + ([seq.mag] if axes == 9 else []), 1)[:n + warm]
    imu = np.ascontiguousarray(imu, dtype=np.float64)
    dt = 1.0 / rate
    q0 = np.array([1.0, 0.0, 0.0, 0.0])
    rows: List[Dict[str, Any]] = []
    tmp = Path(tempfile.mkdtemp())
    try:
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")
            rows += _our_runtimes(model, ckpt, imu, dt, q0, n, warm, slow, tmp, p)
            # before the peers: onnxruntime's (RIANN's) idle threads must not share the cores
            models = _c_models(p.get("c_models") or [], imu, dt, q0, n + warm, tmp, p) if p.get("c", True) else []
            rows += _peers(imu, dt, rate, n, warm)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    vqf_loop = next((r for r in rows if r["name"].startswith("VQF updateBatch")), None)
    riann = next((r for r in rows if r["name"].startswith("RIANN predict_step") and "median_us" in r), None)
    c_loop = next((r for r in rows if r["name"].startswith("C runtime run (float backbone, -O2)")), None)
    c_native = next((r for r in rows if r["name"].startswith("C runtime run (float backbone, -O2 -march")), None)
    c_step = next((r for r in rows if r["name"].startswith("C runtime step") and "median_us" in r), None)
    goals = {}
    if c_loop and vqf_loop and "per_sample_us" in vqf_loop:
        goals["c_loop_vs_vqf_cpp"] = c_loop["per_sample_us"] / vqf_loop["per_sample_us"]  # goal <= 5
    if c_loop and riann:
        goals["riann_step_vs_c_loop"] = riann["median_us"] / c_loop["per_sample_us"]  # goal >= 10
    if c_native and vqf_loop and "per_sample_us" in vqf_loop:
        goals["c_native_loop_vs_vqf_cpp"] = c_native["per_sample_us"] / vqf_loop["per_sample_us"]
    if c_native and riann:
        goals["riann_step_vs_c_native_loop"] = riann["median_us"] / c_native["per_sample_us"]
    if c_step and riann:
        goals["riann_step_vs_c_step"] = riann["median_us"] / c_step["median_us"]
    from ..export.c.runtime import live_networks

    return {"ckpt": ckpt, "axes": axes, "rate_hz": rate, "rows": rows, "goals": goals,
            "live_networks": list(live_networks(model)) if getattr(model, "backbone", None) is not None else [],
            "c_models": models, "footprint": footprint_rows(p["footprint_glob"])}


def _c_models(paths: List[str], imu, dt, q0, total, tmp: Path, p: Dict[str, Any]) -> List[Dict[str, Any]]:
    """Each model's C loop (float build, -O2 and -march=native) on the same samples (its axes'
    columns) beside VQF's C++ updateBatch of the same axes, and its ONNX and torch.export step
    (``p["onnx"]``, ``p["export"]``), in this run. A model: a residual checkpoint or a tuned ECF
    file (``.json``) of tcn-ahrs search."""
    from ..export.c import CRuntime, compile_c, export_c

    out = []
    slow = int(p["slow_steps"])
    for i, path in enumerate(paths):
        row: Dict[str, Any] = {"ckpt": str(path)}
        try:
            f = _found(path)
            axes, live = _axes_and_networks(f)
            x = np.ascontiguousarray(imu[:, :axes], dtype=np.float32)
            name = f"cm{i}"  # one library file per model and build: ctypes reuses a loaded path
            gen = export_c(f, tmp, name, overwrite=True)
            row.update(axes=axes, live_networks=live)
            rt = CRuntime(compile_c(gen["c"], tmp / f"lib{name}_O2.so", "float"), name, axes)
            row["c_O2_us"] = _loop("", lambda: (rt.reset(q0), rt.run(x, dt)), total)["per_sample_us"]
            row["state_bytes"] = rt.state_size
            so = compile_c(gen["c"], tmp / f"lib{name}_native.so", "float", None, ["-march=native"])
            row["c_native_us"] = _isolated_loop(so, name, axes, x, dt, q0, tmp)["per_sample_us"]
            row["vqf_us"] = _vqf_batch_loop(imu[:, :axes], dt)["per_sample_us"]
            row["c_vs_vqf"] = row["c_O2_us"] / row["vqf_us"]
            row["c_native_vs_vqf"] = row["c_native_us"] / row["vqf_us"]
        except Exception as e:  # noqa: BLE001 - a missing compiler, checkpoint or vqf: the row says why
            row["skipped"] = f"{type(e).__name__}: {e}"
            out.append(row)
            continue
        xs = np.ascontiguousarray(imu[:, :axes])
        for key, flag, steps in (("onnx_step_us", "onnx", slow), ("export_step_us", "export", max(5, slow // 10))):
            if p.get(flag, True):
                try:
                    row[key] = _graph_step(f, flag, xs, dt, q0, steps, tmp / f"{name}_{flag}")["median_us"]
                except Exception as e:  # noqa: BLE001 - the [deploy] extra missing: the row says why
                    row[key + "_skipped"] = f"{type(e).__name__}: {e}"
        out.append(row)
    return out


def _axes_and_networks(path: Path):
    """(axes, the networks its C runtime runs) of a residual checkpoint or an estimator file."""
    if str(path).endswith(".json"):
        from ..estimators.families import read_estimator

        return int(read_estimator(path)["axes"]), []
    from ..checkpoint import model_from_checkpoint
    from ..export.c.runtime import live_networks

    model = model_from_checkpoint(path).eval()
    return int(model.axes), list(live_networks(model))


def _graph_step(path, fmt: str, imu, dt, q0, steps: int, out: Path) -> Dict[str, Any]:
    """The median per-sample step of a model's ONNX (``fmt="onnx"``) or torch.export step graph."""
    if fmt == "onnx":
        from ..export.onnx_step import OnnxStreaming as Loader, export_onnx as export
    else:
        from ..export.program import ExportedStreaming as Loader, export_program as export
    written = export(str(path), str(out) + (".onnx" if fmt == "onnx" else ".pt2"), "streaming", overwrite=True)
    s = Loader(written["streaming"])
    s.reset(q0)
    return _steps(fmt, lambda k: s.step(imu[k], dt), steps, 5)


def _our_runtimes(model, ckpt, imu, dt, q0, n, warm, slow, tmp: Path, p) -> List[Dict[str, Any]]:
    from ..export.backbone import ResidualStreaming
    from ..streaming import BackboneStreaming

    rows: List[Dict[str, Any]] = []
    total = n + warm
    bs = BackboneStreaming(model)
    bs.reset(q0)
    rows.append(_steps("numba BackboneStreaming step", lambda k: bs.step(imu[k], dt), n, warm))
    rows.append(_loop("numba BackboneStreaming run (networks as convolutions over the recording)", lambda: bs.run(imu, dt, q0), total))
    ts = ResidualStreaming(model, {})
    ts.reset(torch.as_tensor(q0))
    xt = torch.as_tensor(imu)
    rows.append(_steps("TorchScript ResidualStreaming step (eager module)", lambda k: ts.step(xt[k], dt), n, warm))
    if p.get("c", True):
        try:
            from ..export.c import CRuntime, compile_c, export_c

            cc = shutil.which("cc") or shutil.which("gcc")
            if cc is None:
                raise FileNotFoundError("no C compiler")
            paths = export_c(ckpt, tmp, "m", overwrite=True)
            xf = np.ascontiguousarray(imu, dtype=np.float32)
            for real, flags in (("float", ()), ("double", ()), ("float", ("-march=native",)), ("double", ("-march=native",))):
                tag = " ".join(("-O2",) + flags)
                so = compile_c(paths["c"], tmp / f"libm_{real}_{len(flags)}.so", real, cc, flags)
                if flags:  # its own process: see _isolated_loop
                    rows.append({"name": f"C runtime run ({real} backbone, {tag})", "kind": "loop", "samples": total,
                                 **_isolated_loop(so, "m", int(model.axes), xf, dt, q0, tmp)})
                    continue
                rt = CRuntime(so, "m", int(model.axes))
                rt.reset(q0)
                rows.append(_loop(f"C runtime run ({real} backbone, {tag})", lambda: (rt.reset(q0), rt.run(xf, dt)), total))
                rows[-1]["state_bytes"] = rt.state_size
                if real == "float" and not flags:
                    rt.reset(q0)
                    rows.append(_steps("C runtime step (ctypes call per sample)", lambda k: rt.step(xf[k], dt), n, warm))
        except Exception as e:  # noqa: BLE001 - a missing compiler skips the rows, named
            rows.append(_skipped("C runtime", e))
    for fmt, label, steps in (("onnx", "ONNX OnnxStreaming step (onnxruntime)", slow),
                              ("export", "torch.export ExportedStreaming step", max(5, slow // 10))):
        if p.get(fmt, True):
            try:
                rows.append(dict(_graph_step(ckpt, fmt, imu, dt, q0, steps, tmp / f"m_{fmt}"), name=label))
            except Exception as e:  # noqa: BLE001 - the [deploy] extra missing
                rows.append(_skipped(label, e))
    if p.get("aoti", True):
        label = "torch.export step compiled by AOTInductor (aoti_compile_and_package)"
        try:
            rows.append(dict(_aoti_step(ckpt, imu, dt, q0, slow, tmp / "m_aoti"), name=label))
        except Exception as e:  # noqa: BLE001 - no C++ compiler: the row says why
            rows.append(_skipped(label, e))
    return rows


def _aoti_step(path, imu, dt, q0, steps: int, out: Path) -> Dict[str, Any]:
    """The exported step program compiled ahead of time by AOTInductor (what a PyTorch deployment
    of the ``.pt2`` runs instead of its eager graph), stepped through the same streaming contract
    as the loaders (inputs checked, the state carried)."""
    from ..export.program import ExportedStreaming, export_program

    written = export_program(str(path), str(out) + ".pt2", "streaming", overwrite=True)
    s = ExportedStreaming(written["streaming"])
    ep = torch.export.load(written["streaming"])
    compiled = torch._inductor.aoti_load_package(
        torch._inductor.aoti_compile_and_package(ep, package_path=str(out) + "_aoti.pt2"))
    s.program = compiled
    s.reset(q0)
    return _steps("aoti", lambda k: s.step(imu[k], dt), steps, 5)


def _vqf_batch_loop(imu, dt: float) -> Dict[str, Any]:
    """VQF's C++ ``updateBatch`` over ``imu`` (N, 6 or 9), a fresh filter per run: the loop row."""
    from vqf import VQF

    cols = [np.ascontiguousarray(imu[:, k:k + 3], dtype=np.float64) for k in range(0, imu.shape[1], 3)]
    return _loop("VQF updateBatch (C++ loop)", lambda: VQF(dt).updateBatch(*cols), imu.shape[0])


def _peers(imu, dt, rate, n, warm) -> List[Dict[str, Any]]:
    rows: List[Dict[str, Any]] = []
    gyr = np.ascontiguousarray(imu[:, 0:3])
    acc = np.ascontiguousarray(imu[:, 3:6])
    mag = np.ascontiguousarray(imu[:, 6:9]) if imu.shape[1] == 9 else None
    try:
        from vqf import VQF

        v = VQF(dt)
        if mag is None:
            rows.append(_steps("VQF update (per sample from Python, C++)", lambda k: v.update(gyr[k], acc[k]), n, warm))
        else:
            rows.append(_steps("VQF update (per sample from Python, C++)", lambda k: v.update(gyr[k], acc[k], mag[k]), n, warm))
        rows.append(_vqf_batch_loop(imu, dt))
    except Exception as e:  # noqa: BLE001 - the peers extra missing
        rows.append(_skipped("VQF", e))
    try:
        from ..estimators.peers_riann import RIANNEstimator

        rm = RIANNEstimator(axes=6)._model
        rm.reset_state()
        rm.set_sampling_rate(rate)
        rows.append(_steps("RIANN predict_step (6-axis, onnxruntime)", lambda k: rm.predict_step(acc[k], gyr[k]), n, warm))
    except Exception as e:  # noqa: BLE001
        rows.append(_skipped("RIANN predict_step", e))
    return rows


def footprint_rows(patterns: str) -> List[Dict[str, Any]]:
    """Parameters, weight bytes, the C runtime's state bytes and FLOPs per sample of each checkpoint
    matching ``patterns`` (comma-separated globs); a checkpoint in a subfolder of ``checkpoints/``
    is named ``<folder>/<name>``."""
    from ..checkpoint import model_from_checkpoint
    from .common import footprint

    out = []
    for pattern in str(patterns).split(","):
        paths = sorted(Path().glob(pattern.strip())) or sorted(REPO.glob(pattern.strip()))
        for path in paths:
            model = model_from_checkpoint(path).eval()
            label = path.stem if path.parent.name == "checkpoints" else f"{path.parent.name}/{path.stem}"
            out.append(_footprint_row(model, label, footprint))
    return out


def _footprint_row(model, label: str, footprint) -> Dict[str, Any]:
    row = {"checkpoint": label, "axes": int(model.axes), **footprint(model)}
    if getattr(model, "backbone", None) is not None:  # a residual model: what its C runtime holds
        from ..export.c import generate_c

        info = generate_c(model, "m")["info"]
        row["c_weight_bytes"] = int(info["weight_bytes"] + info["head_bytes_double"])
        row["c_ring_bytes"] = 4 * int(info["ring_floats"])
        row["c_flops_per_sample"] = int(info["flops_per_sample"])
    return row


def markdown(res: Dict[str, Any]) -> str:
    lines = [f"Deployment runtimes of `{res['ckpt']}` ({res['axes']}-axis, {res['rate_hz']:g} Hz samples), 1 thread:", "",
             "| runtime | per-sample step from Python (µs, median) | per sample in a compiled loop (µs) |",
             "|---|---|---|"]
    for r in res["rows"]:
        if "skipped" in r:
            lines.append(f"| {r['name']} | skipped: {r['skipped']} | |")
            continue
        step = f"{r['median_us']:.1f}" if "median_us" in r else ""
        loop = f"{r['per_sample_us']:.2f}" if "per_sample_us" in r else ""
        lines.append(f"| {r['name']} | {step} | {loop} |")
    g = res.get("goals") or {}
    if g:
        nan = float("nan")
        lines += ["", "Goals (issue 27): C loop / VQF C++ loop = "
                  f"{g.get('c_loop_vs_vqf_cpp', nan):.2f} at -O2, {g.get('c_native_loop_vs_vqf_cpp', nan):.2f} with "
                  f"-march=native (goal ≤ 5); RIANN step / C loop = {g.get('riann_step_vs_c_loop', nan):.1f} at -O2, "
                  f"{g.get('riann_step_vs_c_native_loop', nan):.1f} with -march=native (goal ≥ 10); RIANN step / "
                  f"C step through ctypes = {g.get('riann_step_vs_c_step', nan):.1f}."]
    if res.get("live_networks") is not None:
        lines += ["", f"Networks in `{Path(res['ckpt']).name}`'s C runtime: {', '.join(res['live_networks']) or 'none'} "
                  "(a network its inference knobs switch off is not generated: `tcn_ahrs.export.c.runtime.live_networks`)."]
    if res.get("c_models"):
        lines += ["", "Other models, same run, same samples (their axes' columns): the C loop (float build) beside "
                  "VQF's C++ loop of the same axes, and the ONNX / torch.export step from Python beside RIANN's:", "",
                  "| model | axes | networks | C -O2 (µs) | C -march=native (µs) | VQF C++ (µs) | C / VQF (-O2, native) "
                  "| ONNX step (µs) | torch.export step (µs) | RIANN step / ONNX step | sizeof(state) (B) |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        riann = next((r["median_us"] for r in res["rows"] if r["name"].startswith("RIANN") and "median_us" in r), None)
        for r in res["c_models"]:
            label = Path(r["ckpt"]).name if str(r["ckpt"]).endswith(".json") else Path(r["ckpt"]).stem
            if "skipped" in r:
                lines.append(f"| {label} | skipped: {r['skipped']} | | | | | | | | | |")
                continue
            onnx = f"{r['onnx_step_us']:.1f}" if "onnx_step_us" in r else "–"
            pt2 = f"{r['export_step_us']:.1f}" if "export_step_us" in r else "–"
            ratio = f"{riann / r['onnx_step_us']:.2f}" if riann and "onnx_step_us" in r else "–"
            nets = ", ".join(r["live_networks"]) or ("none (ECF)" if label.endswith(".json") else "none")
            lines.append(f"| {label} | {r['axes']} | {nets} | {r['c_O2_us']:.2f} | {r['c_native_us']:.2f} | "
                         f"{r['vqf_us']:.2f} | {r['c_vs_vqf']:.1f}, {r['c_native_vs_vqf']:.1f} | {onnx} | {pt2} | "
                         f"{ratio} | {r['state_bytes']} |")
    c_rows = [r for r in res["rows"] if "state_bytes" in r]
    if c_rows:
        lines += ["", f"sizeof(state) of the C runtime: {c_rows[0]['state_bytes']} B (float backbone, the default), "
                  f"{c_rows[1]['state_bytes'] if len(c_rows) > 1 else '–'} B (double)."]
    lines += ["", "| checkpoint | axes | parameters | FLOPs / sample (networks) | C weights (B) | C ring buffers (B) "
              "| C FLOPs / sample (networks it runs) |", "|---|---|---|---|---|---|---|"]
    for f in res.get("footprint") or []:
        lines.append(f"| {f['checkpoint']} | {f['axes']} | {f['parameters']} | {f['flops_per_sample']} | "
                     f"{f.get('c_weight_bytes', '–')} | {f.get('c_ring_bytes', '–')} | {f.get('c_flops_per_sample', '–')} |")
    return "\n".join(lines)
