"""The learned accelerometer trust gating the backbone's bias update in motion
(``model.residual.bias_trust_power``, issue 37 item 1): every runtime reads it the same way —
the evaluated model, the numba streaming runtime, TorchScript, ONNX and C — and it acts."""
import shutil

import numpy as np
import pytest
import torch

from tcn_ahrs.checkpoint import load_checkpoint, model_from_checkpoint
from tcn_ahrs.datasets.simulate import simulate
from tcn_ahrs.estimators.learned import LearnedEstimator

CKPT = "checkpoints/residual/oxiod9.ckpt"  # both networks on: the acc trust is learned
ANGLE = 1e-5  # rad, as tests/test_export_formats.py


def _angle(a, b) -> float:
    """The largest rotation angle (rad) between (N, 4) quaternions (atan2: exact near zero)."""
    from test_export_c import _angle as angles

    return float(angles(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)).max())


@pytest.fixture(scope="module")
def gated(tmp_path_factory):
    """(checkpoint with bias_trust_power 2, the same with 0, a simulated 9-axis walk)."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    out = tmp_path_factory.mktemp("gate")
    paths = {}
    for p in (0.0, 2.0):
        ck = load_checkpoint(root / CKPT)
        meta = dict(ck["tcn_ahrs"])
        meta["model"] = {**meta["model"], "residual": {**meta["model"]["residual"], "bias_trust_power": p}}
        ck["tcn_ahrs"] = meta
        paths[p] = out / f"oxiod9_p{p:g}.ckpt"
        torch.save(ck, paths[p])
    seq = simulate("walking", 20.0, 100.0, seed=5, axes=9)
    return paths, seq


def test_every_runtime_reads_the_gate_alike_and_it_acts(gated, tmp_path):
    pytest.importorskip("numba")
    from tcn_ahrs.export.backbone import ResidualStreaming
    from tcn_ahrs.streaming import BackboneStreaming

    paths, seq = gated
    imu = np.concatenate([seq.gyro, seq.accel, seq.mag], 1)
    dt, q0 = seq.dt, seq.quat[0]
    model = model_from_checkpoint(paths[2.0])
    assert model.backbone.bias_trust_power == 2.0
    ref = LearnedEstimator(model, other_rate="model", heading_ref="init").run(seq, q0, 0)
    stream = BackboneStreaming(model)
    q_nb, w_nb = stream.run(imu, dt, q0)
    assert _angle(q_nb, ref.quat) <= ANGLE
    ts = torch.jit.script(ResidualStreaming(model, {}))
    ts.reset(torch.as_tensor(q0))
    q_ts = np.array([ts.step(torch.from_numpy(imu[k]), float(dt[k]))[0].numpy() for k in range(len(imu))])
    assert _angle(q_ts, ref.quat) <= ANGLE
    # the gate acts: without it the same weights give another attitude
    plain = LearnedEstimator(model_from_checkpoint(paths[0.0]), other_rate="model", heading_ref="init").run(seq, q0, 0)
    assert _angle(plain.quat, ref.quat) > 1e-3


def test_onnx_and_c_read_the_gate(gated, tmp_path):
    pytest.importorskip("numba")
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    from tcn_ahrs.export.c import CRuntime, compile_c, export_c
    from tcn_ahrs.export.onnx_step import OnnxStreaming, export_onnx
    from tcn_ahrs.streaming import BackboneStreaming

    paths, seq = gated
    n = 600
    imu = np.concatenate([seq.gyro, seq.accel, seq.mag], 1)[:n]
    dt, q0 = seq.dt[:n], seq.quat[0]
    q_ref, _ = BackboneStreaming(model_from_checkpoint(paths[2.0])).run(imu, dt, q0)
    files = export_onnx(paths[2.0], tmp_path / "gated.onnx", "streaming")   # the step graph is what it checks
    q_onnx, _ = OnnxStreaming(files["streaming"]).run(imu, dt, q0)
    assert _angle(q_onnx, q_ref) <= ANGLE
    cc = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        pytest.skip("no C compiler")
    c = export_c(paths[2.0], tmp_path, "gated")
    rt = CRuntime(compile_c(c["c"], tmp_path / "libgated.so", "double", cc), "gated", 9)
    rt.reset(np.asarray(q0, dtype=np.float32))
    code, out = rt.run(imu.astype(np.float32), float(np.median(dt)))
    stream = BackboneStreaming(model_from_checkpoint(paths[2.0]))
    stream.chunk_networks = 1 << 30  # the networks per sample, as the C runtime (tests/test_export_c.py)
    q_c_ref, _ = stream.run(
        imu.astype(np.float32).astype(np.float64), float(np.median(dt)), np.asarray(q0, dtype=np.float32).astype(np.float64))
    assert code == 0 and _angle(out[:, :4].astype(np.float64), q_c_ref) <= 1e-4  # the C runtime's bound
