"""format=onnx and format=export (torch.export) beside TorchScript, for the shipped residual
checkpoints (broad9, and broad6 for 6 axes): each exported file loaded and compared with the
evaluated model (LearnedEstimator, BackboneStreaming) and the TorchScript streaming module on a
simulated recording and on the start of a BROAD recording (skipped without ../shared); the
inputs refused before any state change; the metadata round trip; other kinds refused.

Bounds: the outputs are float64 (the networks float32 inside, as in every runtime): attitude
within 1e-5 rad of the references, omega within 1e-6 rad/s.
"""
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")
pytest.importorskip("onnxscript")

from tcn_ahrs.datasets.simulate import simulate  # noqa: E402
from tcn_ahrs.estimators.learned import LearnedEstimator  # noqa: E402
from tcn_ahrs.export import ExportError, _script, build_metadata, checkpoint_export_meta  # noqa: E402
from tcn_ahrs.export.backbone import ResidualStreaming  # noqa: E402
from tcn_ahrs.export.onnx_step import OnnxBatch, OnnxStreaming, export_onnx, read_onnx_metadata  # noqa: E402
from tcn_ahrs.export.program import ExportedBatch, ExportedStreaming, export_program, read_program_metadata  # noqa: E402

from conftest import built_once  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CKPTS = ROOT / "checkpoints"
ANGLE, OMEGA = 1e-5, 1e-6


def angle(a, b) -> float:
    """Largest angle [rad] between two (N, 4) quaternion series (4 asin(|a ∓ b| / 2): exact near 0,
    where 2 acos|a·b| has a ~3e-8 floor)."""
    a, b = np.atleast_2d(a), np.atleast_2d(b)
    d = np.minimum(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))
    return float((4.0 * np.arcsin(np.clip(d / 2.0, 0.0, 1.0))).max())


def broad_root():
    for base in (ROOT.parent, ROOT.parent.parent):  # ../shared beside the checkout or its worktrees folder
        p = base / "shared" / "datasets" / "broad"
        if p.is_dir():
            return p
    return None


def imu_of(seq, axes):
    return np.concatenate([seq.gyro, seq.accel] + ([seq.mag] if axes == 9 else []), 1)


@pytest.fixture(scope="module", params=["broad9", "broad6"])
def exported(request, tmp_path_factory):
    name = request.param
    ckpt = CKPTS / f"{name}_residual.ckpt"
    # the exports once per session (both workers' tests read them)
    _, files = built_once(tmp_path_factory, f"export_{name}", lambda out: {
        "onnx": export_onnx(ckpt, out / f"{name}.onnx"), "pt2": export_program(ckpt, out / f"{name}.pt2")})
    onnx_files, pt2_files = files["onnx"], files["pt2"]
    from tcn_ahrs.checkpoint import checkpoint_meta, load_checkpoint

    model, meta = checkpoint_export_meta(ckpt, checkpoint_meta(load_checkpoint(ckpt), ckpt))
    md = build_metadata(model, "streaming", meta)
    ts = _script(ResidualStreaming(model, md))
    return dict(name=name, ckpt=ckpt, model=model, onnx=onnx_files, pt2=pt2_files, ts=ts, ts_meta=md,
                axes=int(model.axes), rate=float(meta["rate_hz"]))


def ts_steps(ts, imu, dt, q0):
    ts.reset(torch.as_tensor(q0))
    qs, ws = [], []
    for k in range(len(imu)):
        q, w = ts.step(torch.from_numpy(imu[k]), float(dt[k]))
        qs.append(q.numpy())
        ws.append(w.numpy())
    return np.array(qs), np.array(ws)


def check_all(ex, imu, dt, q0, ref_q, ref_w, n_slow):
    """Every loader against (ref_q, ref_w); the torch.export ones (eager, ~30 ms a sample) on the
    first n_slow samples."""
    onnx_s, onnx_b = OnnxStreaming(ex["onnx"]["streaming"]), OnnxBatch(ex["onnx"]["batch"])
    pt2_s, pt2_b = ExportedStreaming(ex["pt2"]["streaming"]), ExportedBatch(ex["pt2"]["batch"])
    errs = {}
    for label, runner, n in (("onnx streaming", onnx_s.run, len(imu)), ("onnx batch", onnx_b.run, len(imu)),
                             ("export batch", pt2_b.run, n_slow), ("export streaming", pt2_s.run, n_slow // 3)):
        q, w = runner(imu[:n], dt[:n], q0)
        errs[label] = (angle(q, ref_q[:n]), float(np.abs(w - ref_w[:n]).max()))
    # step by step = run (ONNX: the state carried by the loop)
    onnx_s.reset(q0)
    steps = np.array([onnx_s.step(imu[k], dt[k])[0] for k in range(50)])
    errs["onnx step"] = (angle(steps, ref_q[:50]), 0.0)
    for label, (a, w) in errs.items():
        assert a <= ANGLE and w <= OMEGA, (label, a, w)
    return errs


def test_parity_simulated(exported):
    """Simulated walking (irregular dt) at the model's rate: the exported files = LearnedEstimator
    (the evaluated model) = the TorchScript streaming module."""
    ex = exported
    seq = simulate("walking", 2.0, ex["rate"], seed=3, axes=ex["axes"])
    rng = np.random.default_rng(3)
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(0.8, 1.2, len(seq) - 1) / ex["rate"])])
    seq = dataclasses.replace(seq, time=t)
    imu, dt, q0 = imu_of(seq, ex["axes"]), seq.dt, seq.quat[0]
    # the runtimes refer heading to the field at reset: the evaluated model's heading_ref "init"
    ref = LearnedEstimator(ex["model"], other_rate="model", heading_ref="init").run(seq, q0, 0)
    ref_w = imu[:, 0:3] + ref.signals["gyro_correction"] - ref.signals["gyro_bias_state"]
    qt, wt = ts_steps(ex["ts"], imu, dt, q0)
    assert angle(qt, ref.quat) <= ANGLE
    errs = check_all(ex, imu, dt, q0, ref.quat, ref_w, 240)
    print(ex["name"], "simulated", len(imu), errs)


def test_parity_broad(exported):
    """The first 6 s of a BROAD recording: the exported files = BackboneStreaming (numba) = the
    TorchScript streaming module."""
    root = broad_root()
    if root is None:
        pytest.skip("BROAD not found under ../shared/datasets/broad")
    from tcn_ahrs.datasets import broad
    from tcn_ahrs.streaming import BackboneStreaming

    ex = exported
    seq = broad.load_recording(root, "07_undisturbed_fast_rotation_B")
    n = 1700
    imu, dt = imu_of(seq, ex["axes"])[:n], np.where(seq.dt > 0, seq.dt, 1.0 / seq.rate)[:n]
    q0 = seq.quat[int(np.argmax(seq.quat_valid))]
    ref_q, ref_w = BackboneStreaming(ex["model"]).run(imu, dt, q0)
    qt, wt = ts_steps(ex["ts"], imu[:300], dt[:300], q0)
    assert angle(qt, ref_q[:300]) <= ANGLE and np.abs(wt - ref_w[:300]).max() <= OMEGA
    errs = check_all(ex, imu, dt, q0, ref_q, ref_w, 240)
    print(ex["name"], "BROAD", n, errs)


@pytest.mark.parametrize("kind", ["onnx", "export"])
def test_bad_samples_refused_with_the_state_unchanged(exported, kind):
    ex = exported
    cls = OnnxStreaming if kind == "onnx" else ExportedStreaming
    path = ex["onnx" if kind == "onnx" else "pt2"]["streaming"]
    seq = simulate("fast_rotation", 1.0, 100.0, seed=0, axes=ex["axes"])
    imu = imu_of(seq, ex["axes"])
    a, b = cls(path), cls(path)
    for s in (a, b):
        s.reset(seq.quat[0])
        s.step_chunk(imu[:20], 0.01)
    before = np.asarray(a.state).copy()
    nan, spike = imu[20].copy(), imu[20].copy()
    nan[4] = np.nan
    spike[1] = 1e6
    for sample, dt, match in ((nan, 0.01, "non-finite"), (spike, 0.01, "beyond any sensor"), (imu[20], 0.0, "dt"),
                              (imu[20], float("nan"), "dt"), (imu[20], 2.0, "dt"), (imu[20], -0.01, "dt"),
                              # the fault trial's tiny steps: below conventions.MIN_DT, as C refuses them
                              (imu[20], 1e-14, "dt"), (imu[20], 1e-9, "dt"), (imu[20], 5e-6, "dt"),
                              (imu[20, :5], 0.01, "expected")):
        with pytest.raises(ValueError, match=match):
            a.step(sample, dt)
        assert np.array_equal(np.asarray(a.state), before)
    with pytest.raises(ValueError, match="q0"):
        a.reset([0.0, 0.0, 0.0, 0.0])
    assert np.array_equal(np.asarray(a.state), before)
    qa, wa = a.step_chunk(imu[20:30], 0.01)
    qb, wb = b.step_chunk(imu[20:30], 0.01)
    assert np.array_equal(qa, qb) and np.array_equal(wa, wb)
    batch = (OnnxBatch if kind == "onnx" else ExportedBatch)(ex["onnx" if kind == "onnx" else "pt2"]["batch"])
    bad = imu[:10].copy()
    bad[3, 0] = np.inf
    with pytest.raises(ValueError, match="non-finite"):
        batch.run(bad, 0.01, seq.quat[0])
    with pytest.raises(ValueError, match="dt"):
        batch.run(imu[:10], np.r_[0.01, 0.01, 0.0, [0.01] * 7], seq.quat[0])
    with pytest.raises(ValueError, match="dt"):
        batch.run(imu[:10], np.r_[0.01, 0.01, 1e-14, [0.01] * 7], seq.quat[0])


def test_metadata_round_trip(exported):
    """The TorchScript metadata (checkpoint, sha256, axes, units, frames, ...) travels with every
    file (ONNX metadata_props, the .pt2's extra file), plus the state's layout."""
    ex = exported
    ts = ex["ts_meta"]
    for kind, path in list(ex["onnx"].items()) + list(ex["pt2"].items()):
        md = read_onnx_metadata(path) if str(path).endswith(".onnx") else read_program_metadata(path)
        assert md["mode"] == kind
        for key in ts:
            if key not in ("format", "mode", "api"):
                assert md[key] == ts[key], key
        assert md["state"]["size"] == sum(int(np.prod(s)) for _, s in md["state"]["layout"].values())
    loaded = OnnxStreaming(ex["onnx"]["streaming"])
    assert loaded.metadata == read_onnx_metadata(ex["onnx"]["streaming"])
    assert len(loaded.state) == loaded.metadata["state"]["size"]
    assert ExportedStreaming(ex["pt2"]["streaming"]).metadata["checkpoint"] == ex["ckpt"].name
    with pytest.raises(ExportError, match="already exist"):
        export_onnx(ex["ckpt"], ex["onnx"]["batch"])
    with pytest.raises(ExportError, match="step graph"):
        OnnxStreaming(ex["onnx"]["batch"])


@pytest.mark.parametrize("ckpt", ["closed_loop/broad9.ckpt", "paper/" + "ahrs9"])
def test_other_model_kinds_are_refused(tmp_path, ckpt):
    path = CKPTS / ckpt
    if not path.exists():
        found = sorted((CKPTS / Path(ckpt).parent).glob("*.ckpt"))
        if not found:
            pytest.skip(f"no checkpoint under {path.parent}")
        path = found[0]
    for fn in (export_onnx, export_program):
        with pytest.raises(ExportError, match="supports the residual models"):
            fn(path, tmp_path / "x.onnx")


def test_cli_format(tmp_path, capsys):
    """scripts/export.py format=export writes the .pt2 graphs; an unknown format is named."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    script = str(ROOT / "scripts" / "export.py")
    out = tmp_path / "b6.pt2"
    res = subprocess.run([sys.executable, script, f"ckpt={CKPTS / 'broad6_residual.ckpt'}", f"out={out}", "format=export",
                          "mode=streaming"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert out.exists() and "streaming:" in res.stdout and read_program_metadata(out)["mode"] == "streaming"
    from tcn_ahrs.cli import main   # the refusal in this process: no second interpreter to start

    with pytest.raises(SystemExit) as e:
        main(["export", f"ckpt={CKPTS / 'broad6_residual.ckpt'}", f"out={out}", "format=tflite"])
    assert e.value.code == 2 and "format='tflite'" in capsys.readouterr().err


# ------------------------------------------------------------------ a tuned classical filter
@pytest.mark.parametrize("name", ["tumvi6", "oxiod9"])
def test_tuned_ecf_exports_to_onnx_and_torch_export(tmp_path, name):
    """The tuned ECF files tcn-ahrs search shipped (checkpoints/tumvi6_ecf.json, oxiod9.json) export
    as step and batch graphs in both formats (the filter's own tensor functions, its knobs and
    calibration in): equal to the estimator evaluate runs (heading from the first sample's field)
    over a simulated recording, a bad sample refused with the state unchanged."""
    from tcn_ahrs.estimators.families import load_estimator

    axes = 9 if name.endswith("9") else 6
    path = CKPTS / f"{name}_ecf.json"
    seq = simulate("walking", 8.0, 200.0, seed=5, axes=axes)
    imu = imu_of(seq, axes)
    est = load_estimator(path)
    est.inner = est.inner.with_params(heading_ref="init")
    ref = np.asarray(est.run(seq, init_quat=seq.quat[0]).quat)
    onnx_files = export_onnx(path, tmp_path / f"{name}.onnx")
    pt2_files = export_program(path, tmp_path / f"{name}.pt2")
    for loader, f in ((OnnxStreaming, onnx_files["streaming"]), (OnnxBatch, onnx_files["batch"]),
                      (ExportedStreaming, pt2_files["streaming"]), (ExportedBatch, pt2_files["batch"])):
        q, w = loader(f).run(imu, 0.005, seq.quat[0])
        assert angle(q, ref) < ANGLE, (loader.__name__, angle(q, ref))
        assert np.abs(w - imu[:, :3]).max() < OMEGA  # no calibration in these files: omega is the gyro
    s = OnnxStreaming(onnx_files["streaming"])
    s.reset(seq.quat[0])
    s.step(imu[0], 0.005)
    before = s.state.copy()
    bad = imu[1].copy()
    bad[0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        s.step(bad, 0.005)
    assert np.array_equal(s.state, before)
    assert read_onnx_metadata(onnx_files["streaming"])["family"] == "ecf"


def test_classical_families_without_a_step_graph_are_named(tmp_path):
    from tcn_ahrs.estimators.families import save_estimator

    save_estimator(tmp_path / "m.json", "madgwick", 6, {}, None)
    for fn in (export_onnx, export_program):
        with pytest.raises(ExportError, match="classical family 'madgwick'; format=.* holds the residual models and "
                                              "the classical family 'ecf'"):
            fn(tmp_path / "m.json", tmp_path / "x.onnx")
