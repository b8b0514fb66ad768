"""TorchScript export: eager model == scripted batch == streaming (sample by sample), the saved
files load and run with torch alone, metadata, and clear errors for bad checkpoints/inputs."""
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from tcn_ahrs import __version__, so3
from tcn_ahrs.checkpoint import CheckpointError, atomic_save, layout_meta
from tcn_ahrs.export import (BatchAHRS, ExportError, StreamingAHRS, hamilton_table, _script,
                             build_metadata, export_batch, export_checkpoint, export_streaming,
                             file_sha256, fuse_model, quat_cumprod, quat_integrate, read_metadata,
                             streaming_path)
from tcn_ahrs.config.model import PAPER_MODEL  # the paper's open-loop model
from tcn_ahrs.model.ahrs import LearnedAHRS
from tolerances import INTEGRATE_F64, PARITY_F64, ROTATION_F64, SCAN_F64

REPO = Path(__file__).resolve().parents[1]
TOL_RAD = 1e-5  # the float32 export's parity bound (the issue's), not round-off
N = 2000  # 20 s at 100 Hz

CONFIGS = {
    # the paper's 9-axis model, raw pre-integration (Eq. 25)
    "ahrs9_raw": dict(axes=9, variant="ahrs9", preintegration="raw"),
    # 6-axis with the non-default 'denoised' pre-integration
    "ahrs6_denoised": dict(axes=6, variant="ahrs6", mag_net="none", use_mag_term=False,
                           preintegration="denoised"),
    # 9-axis two-pass ECF, gyro-only gyro-network input, a constant acc error term
    "ahrs9_two_pass": dict(axes=9, variant="two_pass", preintegration="two_pass", gyro_input="gyro",
                           acc_net="constant"),
    # no ECF (DIG-like): plain integration of the calibrated gyro
    "dig_like": dict(axes=9, variant="dig_like", acc_net="none", mag_net="none", ecf=False),
}
CONFIGS = {name: {**PAPER_MODEL, **c} for name, c in CONFIGS.items()}  # the paper's open loop and TCN


def randomize(model: LearnedAHRS, seed: int = 1) -> LearnedAHRS:
    """Non-trivial weights everywhere: BN running stats/affine, output layers (zero at init),
    calibration matrices, gains, input statistics; eval mode."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for mod in model.modules():
            if isinstance(mod, torch.nn.BatchNorm1d):
                mod.running_mean.normal_(0.0, 0.3, generator=g)
                mod.running_var.uniform_(0.5, 2.0, generator=g)
                mod.weight.uniform_(0.5, 1.5, generator=g)
                mod.bias.normal_(0.0, 0.2, generator=g)
        cal = model.calibration
        for net in (cal.gyro_error_net, cal.acc_error_net, cal.mag_error_net):
            if net is None:
                continue
            if hasattr(net, "out"):
                net.out.weight.normal_(0.0, 0.1, generator=g)
                net.out.bias.normal_(0.0, 0.1, generator=g)
            else:
                net.bias.normal_(0.0, 0.5, generator=g)
        for mat in (cal.gyro_matrix, cal.acc_matrix, cal.mag_matrix):
            if mat is not None:
                mat.delta.normal_(0.0, 0.01, generator=g)
        if model.ecf is not None:
            for p in (model.ecf.acc_gain, model.ecf.mag_gain):
                if p is not None:
                    p.uniform_(0.02, 0.3, generator=g)
        mean = torch.cat([0.1 * torch.randn(3, generator=g), torch.tensor([0.0, 0.0, 9.8]),
                          torch.tensor([0.0, 20.0, -40.0])])[:model.axes]
        cal.set_input_stats(mean, torch.rand(model.axes, generator=g) + 0.5)
    return model.eval()


def make_imu(axes: int, n: int = N, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(n, dtype=torch.float32) * 0.01
    gyro = torch.stack([0.8 * torch.sin(1.3 * t), 0.5 * torch.cos(0.7 * t), 0.6 * torch.sin(0.4 * t + 1)], -1)
    gyro = gyro + 0.01 * torch.randn(n, 3, generator=g)
    acc = torch.tensor([0.0, 0.0, 9.81]) + 0.5 * torch.randn(n, 3, generator=g)
    mag = torch.tensor([0.0, 20.0, -40.0]) + torch.randn(n, 3, generator=g)
    return torch.cat([gyro, acc, mag][: 2 + (axes == 9)], -1)


def q0_for(seed: int) -> torch.Tensor:
    q = torch.tensor([0.9, 0.1 * seed, -0.2, 0.3], dtype=torch.float64)
    return q / q.norm()


def angle(qa: torch.Tensor, qb: torch.Tensor) -> torch.Tensor:
    """Rotation angle (rad) between quaternion sequences (..., 4), sign-invariant."""
    d = so3.quat_mul(so3.quat_conj(qa.double()), qb.double())
    return 2.0 * torch.atan2(d[..., 1:].norm(dim=-1), d[..., 0].abs())


def eager(model: LearnedAHRS, imu, dt, q0):
    with torch.no_grad():
        out = model.run_sequence(imu[None], dt[None].to(imu.dtype), so3.quat_to_matrix(q0)[None])
    return so3.matrix_to_quat(out["rot"][0]), out["omega"][0].double()


@pytest.fixture(scope="module", params=[pytest.param(n, marks=pytest.mark.slow) if n == "dig_like" else n
                                        for n in CONFIGS])
def case(request):
    name = request.param
    model = randomize(LearnedAHRS(**CONFIGS[name]), seed=len(name))
    fused = fuse_model(model)
    md = build_metadata(model, "batch")
    return {"name": name, "model": model, "batch": _script(BatchAHRS(fused, md)),
            "stream": _script(StreamingAHRS(fused, build_metadata(model, "streaming")))}


def test_parity_eager_batch_streaming(case):
    model = case["model"]
    imu = make_imu(model.axes)
    g = torch.Generator().manual_seed(3)
    dt = 0.01 + 0.0005 * torch.rand(N, generator=g, dtype=torch.float64)  # jittered time steps
    q0 = q0_for(2)
    q_e, w_e = eager(model, imu, dt, q0)
    q_b, w_b = case["batch"](imu, dt, q0)
    q_s, w_s = case["stream"].run(imu, dt, q0)
    err_eb, err_es, err_bs = angle(q_e, q_b).max(), angle(q_e, q_s).max(), angle(q_b, q_s).max()
    print(f"\n{case['name']}: max attitude difference over {N} samples: eager-batch {err_eb:.2e} rad, "
          f"eager-streaming {err_es:.2e} rad, batch-streaming {err_bs:.2e} rad; "
          f"omega eager-batch {(w_e - w_b).abs().max():.2e} rad/s")
    assert err_eb < TOL_RAD and err_es < TOL_RAD and err_bs < TOL_RAD
    assert (w_e - w_b).abs().max() < 1e-5 and (w_b - w_s).abs().max() < 1e-6
    # the attitude really moved (a test of parity, not of two identities)
    assert angle(q_e[:1], q_e[-1:]).item() > 0.3
    assert torch.allclose(q_b[0], q0 * torch.sign(q0[0]), atol=ROTATION_F64)
    # the learned terms really act: the output differs from plain integration of the raw gyro
    q_raw = so3.matrix_to_quat(so3.integrate(so3.quat_to_matrix(q0), imu[:, 0:3].double(), dt))
    assert angle(q_raw, q_b).max() > 1e-3


def test_step_matches_run_and_reset(case):
    if case["name"] not in ("ahrs9_raw", "ahrs9_two_pass"):  # these two carry every kind of state
        pytest.skip("covered by ahrs9_raw / ahrs9_two_pass")
    stream = case["stream"]
    imu = make_imu(case["model"].axes, n=200, seed=5)
    q0 = q0_for(1)
    q_run, w_run = stream.run(imu, 0.01, q0)
    for _ in range(2):  # a second reset must restart from a clean state
        stream.reset(q0)
        for k in range(imu.shape[0]):
            # dt as a float or a 0-d tensor; dt of the first step is ignored
            q, w = stream.step(imu[k], 0.01 if k % 2 else torch.tensor(0.01 if k else 123.0, dtype=torch.float64))
            assert q.shape == (4,) and w.shape == (3,)
            assert angle(q, q_run[k]) < ROTATION_F64 and torch.equal(w, w_run[k])
    stream.reset(q0)
    q, w = stream(imu[0], 0.01)  # forward = step
    assert angle(q, q0) < ROTATION_F64 and torch.equal(w, w_run[0])


def test_float64_network_matches_float64_eager_model():
    """With a float64 network the export reproduces the eager model (run in float64) to round-off."""
    model = randomize(LearnedAHRS(**CONFIGS["ahrs9_raw"])).double()
    fused = fuse_model(model)
    batch = _script(BatchAHRS(fused, build_metadata(model, "batch"), torch.float64))
    stream = _script(StreamingAHRS(fused, build_metadata(model, "streaming"), torch.float64))
    imu = make_imu(9, n=1500).double()
    dt = torch.full((1500,), 0.01, dtype=torch.float64)
    q0 = q0_for(3)
    q_e, w_e = eager(model, imu, dt, q0)
    q_b, w_b = batch(imu, 0.01, q0)
    q_s, w_s = stream.run(imu, dt, q0)
    assert angle(q_e, q_b).max() < INTEGRATE_F64 and angle(q_e, q_s).max() < INTEGRATE_F64
    assert (w_e - w_b).abs().max() < SCAN_F64 and (w_e - w_s).abs().max() < SCAN_F64


def test_streaming_history_is_the_receptive_field():
    """A change older than the receptive field does not reach the network output (ring buffers
    hold exactly the needed history); one inside it does."""
    model = randomize(LearnedAHRS(**PAPER_MODEL, axes=9, ecf=False))
    stream = _script(StreamingAHRS(fuse_model(model), build_metadata(model, "streaming")))
    rf = model.receptive_field
    n = rf + 50
    imu = make_imu(9, n=n)
    _, w = stream.run(imu, 0.01, q0_for(0))
    far, near = imu.clone(), imu.clone()
    far[n - 1 - rf, 6] += 5.0   # just outside the receptive field of the last output
    near[n - rf, 6] += 5.0      # the oldest sample inside it
    _, w_far = stream.run(far, 0.01, q0_for(0))
    _, w_near = stream.run(near, 0.01, q0_for(0))
    assert torch.allclose(w_far[-1], w[-1], atol=PARITY_F64[1], rtol=0)
    assert not torch.allclose(w_near[-1], w[-1], atol=1e-9, rtol=0)


def test_bad_inputs_raise_clear_errors():
    model = randomize(LearnedAHRS(**PAPER_MODEL, axes=6, mag_net="none", use_mag_term=False))
    fused = fuse_model(model)
    batch = _script(BatchAHRS(fused, build_metadata(model, "batch")))
    stream = _script(StreamingAHRS(fused, build_metadata(model, "streaming")))
    q0 = q0_for(0)
    with pytest.raises(Exception, match=r"imu: expected shape \(N, 6\)"):
        batch(torch.zeros(10, 9), 0.01, q0)
    with pytest.raises(Exception, match="dt: expected"):
        batch(torch.zeros(10, 6), torch.zeros(7), q0)
    with pytest.raises(Exception, match="q0: expected"):
        batch(torch.zeros(10, 6), 0.01, torch.zeros(4))
    stream.reset(q0)
    with pytest.raises(Exception, match=r"sample: expected shape \(6,\)"):
        stream.step(torch.zeros(9), 0.01)


# ------------------------------------------------------------------- fast-path building blocks
@pytest.mark.parametrize("n", [1, 2, 7, 64, 65, 97, 1000, 1001])
@pytest.mark.parametrize("block", [4, 32])
def test_quat_cumprod_matches_sequential_matrix_products(n, block):
    """The blocked quaternion scan == a plain left-to-right product of rotation matrices (an
    independent reference), for lengths around and between block multiples."""
    g = torch.Generator().manual_seed(n)
    q = so3.quat_normalize(torch.randn(n, 4, dtype=torch.float64, generator=g))
    got = quat_cumprod(q, hamilton_table(), block)
    assert got.shape == (n, 4)
    ref = so3.cumprod_matrix_sequential(so3.quat_to_matrix(q))
    assert torch.allclose(so3.quat_to_matrix(got / got.norm(dim=1, keepdim=True)), ref, atol=PARITY_F64[1], rtol=0)
    # the Hamilton table is the Hamilton product
    assert torch.allclose(hamilton_table().T @ (q[:, :, None] * q.flip(0)[:, None, :]).reshape(n, 16).T,
                          so3.quat_mul(q, q.flip(0)).T, atol=1e-15)


def test_quat_integrate_matches_so3_integrate():
    g = torch.Generator().manual_seed(2)
    n = 3001
    omega = 2.0 * torch.randn(n, 3, dtype=torch.float64, generator=g)
    dt = 0.01 + 0.001 * torch.rand(n, dtype=torch.float64, generator=g)
    q0 = q0_for(1)
    q = quat_integrate(q0, omega, dt, hamilton_table())
    ref = so3.integrate(so3.quat_to_matrix(q0), omega, dt)
    assert torch.allclose(so3.quat_to_matrix(q / q.norm(dim=1, keepdim=True)), ref, atol=PARITY_F64[1], rtol=0)
    assert torch.equal(q[0], q0)


def test_streaming_output_tensor_is_float64_exact():
    """TorchScript's torch.tensor(List[float], dtype=float64) rounds through float32; the
    streaming output goes through a float32-residual correction instead."""
    f = torch.jit.script(StreamingAHRS._f64_tensor)
    vals = [0.1234567891234567, 1.0 / 3.0, -2.0 / 3.0, 1e-9 / 7.0, 12345.678901234, -0.7, 0.9]
    got = f(vals)
    assert got.dtype == torch.float64
    rel = ((got - torch.tensor(vals, dtype=torch.float64)).abs() / torch.tensor(vals, dtype=torch.float64).abs())
    assert rel.max() < 1e-14


def test_bfloat16_network_is_batch_only_and_opt_in(tmp_path):
    """bfloat16 convolutions (opt-in, ~2x faster TCN on AVX512-BF16 CPUs): runs, is close to the
    float32 export but NOT within the 1e-5 rad parity (documented in docs/performance.md)."""
    model = randomize(LearnedAHRS(**CONFIGS["ahrs9_raw"]), seed=9)
    fused = fuse_model(model)
    imu, q0 = make_imu(9, n=1000), q0_for(0)
    q32, w32 = _script(BatchAHRS(fused, build_metadata(model, "batch")))(imu, 0.01, q0)
    md = build_metadata(model, "batch", net_dtype=torch.bfloat16)
    assert md["dtype"]["network"] == "bfloat16"
    q16, w16 = _script(BatchAHRS(fused, md, torch.bfloat16))(imu, 0.01, q0)
    assert q16.dtype == torch.float64 and w16.dtype == torch.float64
    err = angle(q32, q16).max().item()
    assert 0.0 < err < 5e-3, err
    with pytest.raises(ExportError, match="batch module only"):
        StreamingAHRS(fused, build_metadata(model, "streaming"), torch.bfloat16)
    with pytest.raises(ExportError, match="net_dtype"):
        BatchAHRS(fused, md, torch.float16)
    ckpt, _ = _checkpoint(tmp_path, dict(CONFIGS["ahrs6_denoised"]))
    with pytest.raises(ValueError, match="mode=batch only"):
        export_checkpoint(ckpt, tmp_path / "b.pt", "both", rate_hz=100, net_dtype="bfloat16")
    written = export_checkpoint(ckpt, tmp_path / "b.pt", "batch", rate_hz=100, net_dtype="bfloat16")
    assert read_metadata(written["batch"])["dtype"]["network"] == "bfloat16"


# ------------------------------------------------------------------- files and checkpoints
def _checkpoint(tmp_path, cfg, seed=4):
    model = randomize(LearnedAHRS.from_config(cfg), seed=seed)
    ckpt = {"state_dict": {f"model.{k}": v for k, v in model.state_dict().items()},
            "tcn_ahrs": layout_meta(cfg, cfg["axes"], "simulated"), "epoch": 3}
    path = tmp_path / "model.ckpt"
    atomic_save(ckpt, path)
    return path, model


_ISOLATED = textwrap.dedent("""
    import json, sys
    sys.modules["tcn_ahrs"] = None  # any import of the package now fails
    try:
        import tcn_ahrs  # noqa: F401
        raise SystemExit("tcn_ahrs is importable in the isolated process")
    except ImportError:
        pass
    import torch
    batch = torch.jit.load(sys.argv[1])
    stream = torch.jit.load(sys.argv[2])
    imu, q0 = torch.load(sys.argv[3])
    qb, wb = batch(imu, 0.01, q0)
    stream.reset(q0)
    qs = torch.stack([stream.step(imu[k], 0.01)[0] for k in range(imu.shape[0])])
    torch.save({"qb": qb, "wb": wb, "qs": qs, "meta": json.loads(batch.metadata())}, sys.argv[4])
    assert "tcn_ahrs" not in [m.split(".")[0] for m, v in sys.modules.items() if v is not None]
""")


def test_exported_files_run_without_tcn_ahrs(tmp_path):
    cfg = dict(CONFIGS["ahrs9_raw"])
    ckpt, model = _checkpoint(tmp_path, cfg)
    out = tmp_path / "exports" / "ahrs9.pt"
    with pytest.warns(UserWarning, match="rate"):
        written = export_checkpoint(ckpt, out, "both")
    assert written == {"batch": str(out), "streaming": str(streaming_path(out))}
    imu, q0 = make_imu(9, n=600), q0_for(1)
    torch.save((imu, q0), tmp_path / "in.pt")
    script = tmp_path / "isolated.py"
    script.write_text(_ISOLATED)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    workdir = tmp_path / "elsewhere"
    workdir.mkdir()
    res = subprocess.run([sys.executable, "-I", str(script), str(out), str(streaming_path(out)),
                          str(tmp_path / "in.pt"), str(tmp_path / "res.pt")],
                         cwd=workdir, env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-3000:]
    got = torch.load(tmp_path / "res.pt")
    q_e, w_e = eager(model, imu, torch.full((600,), 0.01, dtype=torch.float64), q0)
    assert angle(q_e, got["qb"]).max() < TOL_RAD and angle(q_e, got["qs"]).max() < TOL_RAD
    assert (w_e - got["wb"]).abs().max() < 1e-5
    md = got["meta"]
    assert md == read_metadata(out)  # method and extra file agree
    assert md["axes"] == 9 and md["channels"][-1] == "mag_z" and md["variant"] == "ahrs9"
    assert md["quaternion_order"] == "wxyz" and md["frames"]["navigation"] == "ENU"
    assert md["frames"]["attitude"] == "nav_from_body" and md["units"]["gyro"] == "rad/s"
    assert md["receptive_field"] == model.receptive_field == 511
    assert md["input_normalisation"]["included"] is True
    assert md["input_normalisation"]["std"] == pytest.approx(model.calibration.input_std.tolist())
    assert md["tcn_ahrs_version"] == __version__ and md["rate_hz"] is None
    assert md["checkpoint_sha256"] == file_sha256(ckpt) and len(md["checkpoint_sha256"]) == 64
    assert md["preintegration"] == "raw" and md["model_config"]["variant"] == "ahrs9"
    assert read_metadata(streaming_path(out))["mode"] == "streaming"


def test_export_modes_and_rate(tmp_path):
    cfg = dict(CONFIGS["ahrs6_denoised"])
    ckpt, _ = _checkpoint(tmp_path, cfg)
    out = tmp_path / "s.pt"
    written = export_checkpoint(ckpt, out, "streaming", rate_hz=200)
    assert written == {"streaming": str(out)} and not streaming_path(out).exists()
    md = read_metadata(out)
    assert md["rate_hz"] == 200.0 and md["axes"] == 6 and md["preintegration"] == "denoised"
    m = torch.jit.load(str(out))
    m.reset(q0_for(0))
    assert m.step(torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 9.81]), 0.005)[0].shape == (4,)
    with pytest.raises(ValueError, match="export mode"):
        export_checkpoint(ckpt, out, "onnx")


def test_module_level_api_saves_loadable_files(tmp_path):
    model = randomize(LearnedAHRS(**CONFIGS["ahrs9_two_pass"]))
    pb, ps = tmp_path / "b.pt", tmp_path / "s.pt"
    sb = export_batch(model, pb, {"rate_hz": 100.0})
    ss = export_streaming(model, ps, {"rate_hz": 100.0})
    imu, q0 = make_imu(9, n=300), q0_for(0)
    lb, ls = torch.jit.load(str(pb)), torch.jit.load(str(ps))
    assert torch.equal(lb(imu, 0.01, q0)[0], sb(imu, 0.01, q0)[0])
    assert torch.equal(ls.run(imu, 0.01, q0)[0], ss.run(imu, 0.01, q0)[0])
    assert json.loads(lb.metadata())["rate_hz"] == 100.0


def test_bad_checkpoints_give_clear_errors(tmp_path):
    with pytest.raises(CheckpointError, match="not found"):
        export_checkpoint(tmp_path / "missing.ckpt", tmp_path / "x.pt")
    bad = tmp_path / "corrupt.ckpt"
    bad.write_bytes(b"\x80\x04 this is not a checkpoint" * 10)
    with pytest.raises(CheckpointError, match="corrupt.ckpt: cannot load"):
        export_checkpoint(bad, tmp_path / "x.pt")
    foreign = tmp_path / "foreign.ckpt"
    torch.save({"state_dict": {}}, foreign)
    with pytest.raises(CheckpointError, match="not a tcn-ahrs checkpoint"):
        export_checkpoint(foreign, tmp_path / "x.pt")
    assert not (tmp_path / "x.pt").exists()


@pytest.mark.slow
def test_cli(tmp_path, capsys):
    ckpt, _ = _checkpoint(tmp_path, dict(CONFIGS["ahrs6_denoised"]))
    out = tmp_path / "cli.pt"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    res = subprocess.run([sys.executable, str(REPO / "scripts" / "export.py"), f"ckpt={ckpt}", f"out={out}",
                          "rate=100"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-3000:]
    assert out.exists() and streaming_path(out).exists() and "streaming:" in res.stdout
    assert read_metadata(out)["rate_hz"] == 100.0
    from tcn_ahrs.cli import main   # the refusal in this process: no second interpreter to start

    with pytest.raises(SystemExit) as e:
        main(["export", f"ckpt={tmp_path / 'nope.ckpt'}", f"out={out}"])
    assert e.value.code == 2 and "nope.ckpt: checkpoint file not found" in capsys.readouterr().err
