"""Speed benchmark smoke test: tiny sizes, the expected fields and files; no timing assertions."""
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from tcn_ahrs import bench
from tcn_ahrs.losses import increment_loss

REPO = Path(__file__).resolve().parents[1]


def _finite_pos(x):
    return isinstance(x, float) and math.isfinite(x) and x > 0


def test_quick_run_fields_and_files(tmp_path):
    cfg = {"quick": True, "device": "cpu", "out": str(tmp_path / "bench"),
           "speed": {"train": {"window": 64, "steps": 1, "warmup": 0},
                     "inference": {"samples": 200, "repeats": 1, "warmup": 0},
                     "streaming": {"samples": 20, "warmup": 2, "chunk": 5},
                     "filters": {"samples": 50, "batches": [1, 3], "peers": ["vqf", "imufusion"]},
                     # one more model's C loop (the deploy section's own test runs the others)
                     "deploy": {"c_models": ["checkpoints/tumvi6_ecf.json"]}}}
    res = bench.main(cfg)
    env = res["environment"]
    for k in ("torch", "numpy", "cpu", "cpu_count", "torch_threads", "device", "gpu", "loadavg_start"):
        assert k in env
    assert env["device"] == "cpu"

    tr = res["train"]
    assert tr["baseline"] == "eager"
    assert [r["variant"] for r in tr["rows"]] == ["eager", "bf16"]
    assert tr["model"] == "closed" and set(tr["loss_curves"]) == {"eager", "bf16"}
    for r in tr["rows"]:
        assert _finite_pos(r["samples_per_s"]) and _finite_pos(r["epoch_s"]) and _finite_pos(r["schedule_h"])
        assert r["schedule_h"] == pytest.approx(r["epoch_s"] * tr["epochs"] / 3600)
    assert tr["rows"][0]["vs_baseline"] == pytest.approx(1.0)
    assert tr["epoch"]["source"].startswith("constant")  # quick: no data loading
    assert any("CUDA" in n for n in tr["notes"])

    inf = res["inference"]
    names = [r["name"] for r in inf["rows"]]
    assert any(n.startswith("eager") for n in names) and any(n.startswith("TorchScript batch") for n in names)
    assert any(n.startswith("CompiledStreaming.run") for n in names)
    assert all(_finite_pos(r["median_ms"]) for r in inf["rows"])
    assert isinstance(inf["goal_met"], bool) and _finite_pos(inf["gemm_peak_gflops"])
    assert inf["model"].startswith("checkpoints/closed_loop/broad9.ckpt")  # the shipped model, not a stand-in

    st = res["streaming"]
    for name in ("TorchScript step (9-axis)", "CompiledStreaming step (numba, 9-axis)"):
        step = [r for r in st["rows"] if r["name"] == name]
        assert len(step) == 1 and _finite_pos(step[0]["samples_per_s"]) and step[0]["p99_us"] >= step[0]["median_us"]
    chunk = [r for r in st["rows"] if r.get("chunk") == 5]
    assert len(chunk) == 2 and all(_finite_pos(r["samples_per_s"]) for r in chunk)
    assert isinstance(st["goal_met"], bool) and isinstance(st["chunk_goal_met"], bool)

    fi = res["filters"]
    got = {(r["name"], r.get("batch")) for r in fi["rows"] if "samples_per_s" in r}
    for f in ("ecf", "mahony", "eskf"):
        assert (f"tcn_ahrs.filters.{f}", 1) in got and (f"tcn_ahrs.filters.{f}", 3) in got

    out = tmp_path / "bench"
    data = json.loads((out / "speed.json").read_text())
    assert set(data) >= {"environment", "config", "train", "inference", "streaming", "filters", "total_s"}
    md = (out / "speed.md").read_text()
    for head in ("## Training step", "## Batch inference", "## Streaming", "## Classical filters"):
        assert head in md


def test_config_errors():
    with pytest.raises(ValueError, match="speed.train.batchsize"):
        bench.resolve_config({"speed": {"train": {"batchsize": 4}}})
    with pytest.raises(ValueError, match="sections"):
        bench.resolve_config({"speed": {"sections": ["trian"]}})
    with pytest.raises(ValueError, match="device"):
        bench.resolve_config({"device": "tpu"})
    p = bench.resolve_config({"quick": True, "speed": {"train": {"batch_size": 3}}})
    assert p["train"]["batch_size"] == 3 and p["train"]["window"] == bench.QUICK["train"]["window"]


def test_static_loss_equals_increment_loss():
    """The CUDA-graph variant's sync-free loss is the project's loss (with and without gaps)."""
    d = bench.synthetic_imu(2, 120, 9, 100.0, seed=3)
    omega = d["imu"][..., 0:3] + 0.05 * torch.randn(2, 120, 3, generator=torch.Generator().manual_seed(0))
    valid = d["valid"].clone()
    for v in (valid, valid.index_fill(1, torch.arange(40, 50), False)):
        ref = increment_loss(omega, d["dt"], d["rot"], v, (16, 32), 0.005)
        got = bench.static_increment_loss(omega, d["dt"], d["rot"], v, (16, 32), 0.005)
        assert float(ref) > 0
        assert float(got) == pytest.approx(float(ref), rel=1e-6)


def test_broad_epoch_constant_fallback():
    p = dict(bench.DEFAULTS["train"], data_config=None)
    e = bench.broad_epoch(p)
    # 16 recordings of ~37.6 k samples: (37573 - 1000) // 500 + 1 = 74 windows each, 32 per step
    assert e["windows"] == 16 * 74 and e["steps"] == math.ceil(16 * 74 / 32)
    assert "constant" in e["source"]


def test_the_aoti_row_steps_a_compiled_step_program(tmp_path):
    """The deploy section's AOTInductor row on the smallest step graph the exporter writes (a tuned
    ECF file: compiling broad9's backbone graph takes ~60 s; the same code path)."""
    pytest.importorskip("torch._inductor")
    if shutil.which("c++") is None and shutil.which("g++") is None:
        pytest.skip("no C++ compiler")
    from tcn_ahrs.bench.deploy import _aoti_step
    from tcn_ahrs.datasets.simulate import simulate

    seq = simulate("walking", 2.0, 100.0, seed=0, axes=6)
    imu = np.concatenate([seq.gyro, seq.accel], 1)
    row = _aoti_step(REPO / "checkpoints" / "tumvi6_ecf.json", imu, 0.01, np.array([1.0, 0.0, 0.0, 0.0]), 5,
                     tmp_path / "m")
    assert row["steps"] == 5 and _finite_pos(row["median_us"])


def test_deploy_section_rows_goals_and_footprint(tmp_path):
    """The deploy section at tiny sizes (ONNX and torch.export off): the C rows of the default
    checkpoint (broad9: both networks off, the backbone alone), the other checkpoints' C loops
    beside VQF's loop of their axes, the goals and the footprint of every shipped checkpoint."""
    import shutil

    from tcn_ahrs.bench.deploy import bench_deploy, markdown

    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler")
    pytest.importorskip("vqf")
    res = bench_deploy({"ckpt": "checkpoints/broad9_residual.ckpt", "rate": 285.71, "samples": 40, "warmup": 5,
                        "slow_steps": 3, "c": True, "onnx": False, "export": False, "aoti": False,
                        "footprint_glob": "checkpoints/*.ckpt,checkpoints/residual/*.ckpt",
                        "c_models": ["checkpoints/residual/oxiod9.ckpt", "checkpoints/euroc6_residual_small.ckpt", "checkpoints/nope.ckpt"]})
    names = [r["name"] for r in res["rows"]]
    assert "C runtime run (float backbone, -O2)" in names and "VQF updateBatch (C++ loop)" in names
    assert res["live_networks"] == []
    assert _finite_pos(res["goals"]["c_loop_vs_vqf_cpp"])
    ox, small, nope = res["c_models"]
    assert ox["axes"] == 9 and ox["live_networks"] == ["gyro", "trust"] and _finite_pos(ox["c_vs_vqf"])
    assert small["axes"] == 6 and small["state_bytes"] < 64 * 1024 < ox["state_bytes"]  # each model its own library
    assert "no checkpoint" in nope["skipped"]
    foot = {f["checkpoint"]: f for f in res["footprint"]}
    assert foot["broad9_residual"]["c_ring_bytes"] == 0 and foot["euroc6_residual_small"]["c_ring_bytes"] < foot["residual/euroc6"]["c_ring_bytes"]
    md = markdown(res)
    assert "| euroc6_residual_small | 6 | gyro, trust |" in md and "Networks in `broad9_residual.ckpt`'s C runtime: none" in md
