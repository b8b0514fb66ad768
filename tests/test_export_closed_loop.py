"""Export of the learned closed loop (the default model): the scripted batch and streaming
modules compute what evaluation computes (LearnedAHRS.run_sequence), after torch.jit.save /
torch.jit.load, and a streaming module's reset() starts a second recording exactly as fresh."""

import pytest
import torch

from tcn_ahrs import so3
from tcn_ahrs.export import ExportError, export_batch, export_streaming, read_metadata
from tcn_ahrs.model.ahrs import LearnedAHRS

TOL = 1e-5  # rad, the parity bound
# step vs chunk: the same float32 network as matrix products per sample or as convolutions over a
# chunk (other summation orders: ~1e-8 relative in the error terms); the filter is the same float64 code
STEP_CHUNK_TOL = 1e-7
N = 300
RATE = 100.0


def _model(axes: int) -> LearnedAHRS:
    torch.manual_seed(3)
    kw = {} if axes == 9 else dict(mag_net="none", use_mag_term=False)
    # a 0.5 s rest window: the rest phase below sets the bias state (rest gain > 0)
    m = LearnedAHRS(axes=axes, loop="closed", tcn={"channels": [4, 4, 4, 4]}, closed_loop={"rest_time": 0.5}, **kw)
    nets = [m.calibration.gyro_error_net, m.calibration.acc_error_net, m.calibration.mag_error_net]
    for net in nets:
        if net is not None:  # zero-initialised output layers: give the error and trust terms a slope
            torch.nn.init.normal_(net.out.weight, std=0.05)
            torch.nn.init.normal_(net.out.bias, std=0.05)
    m.calibration.set_input_stats(torch.randn(axes) * 0.1, torch.rand(axes) + 0.5)
    m.closed.set_rate(RATE)
    return m.eval()


def _imu(axes: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    parts = [0.3 * torch.randn(N, 3, generator=g),
             torch.tensor([0.0, 0.0, 9.81]) + 0.3 * torch.randn(N, 3, generator=g)]
    if axes == 9:
        parts.append(torch.tensor([0.0, 20.0, -40.0]) + torch.randn(N, 3, generator=g))
    imu = torch.cat(parts, 1)
    # a rest phase (bias update), with a sensor's noise: exactly repeated readings are a frozen sensor
    imu[60:230, 0:6] = torch.tensor([0.01, -0.005, 0.0, 0.0, 0.0, 9.81]) + 1e-4 * torch.randn(170, 6, generator=g)
    # sensor faults, so that every runtime's health check is compared too: a frozen gyro, then a
    # frozen accelerometer (frozen after 10 samples here)
    imu[235:260, 0:3] = imu[235, 0:3].clone()
    imu[265:290, 3:6] = imu[265, 3:6].clone()
    return imu


def _eager(model, imu, dt, q0):
    with torch.no_grad():
        out = model.run_sequence(imu[None], dt[None], so3.quat_to_matrix(q0.double())[None], 0)
    return so3.matrix_to_quat(out["rot"][0]), out["omega"][0].double()


def _angle(a, b):
    return so3.quat_log(so3.quat_mul(so3.quat_conj(a), b)).norm(dim=-1)


@pytest.mark.parametrize("axes", [9, 6])
def test_loaded_batch_and_streaming_match_evaluation(tmp_path, axes):
    model = _model(axes)
    export_batch(model, tmp_path / "b.pt", {"rate_hz": RATE})
    export_streaming(model, tmp_path / "s.pt", {"rate_hz": RATE})
    batch, stream = torch.jit.load(str(tmp_path / "b.pt")), torch.jit.load(str(tmp_path / "s.pt"))
    assert read_metadata(tmp_path / "b.pt")["loop"] == "closed"
    dt = torch.full((N,), 1.0 / RATE)
    for seed in (1, 2):  # the second recording runs after reset() on the same streaming module
        imu = _imu(axes, seed)
        q0 = so3.quat_normalize(torch.tensor([0.9, 0.1, -0.2, 0.3 * seed]))
        q_ref, w_ref = _eager(model, imu, dt, q0)
        q_b, w_b = batch(imu, dt, q0)
        q_s, w_s = stream.run(imu, dt, q0)
        assert float(_angle(q_ref, q_b).max()) < TOL
        assert float(_angle(q_ref, q_s).max()) < TOL
        assert float((w_b - w_ref).abs().max()) < TOL and float((w_s - w_b).abs().max()) < TOL
    with torch.no_grad():
        out = model.run_sequence(imu[None], dt[None], so3.quat_to_matrix(q0.double())[None], 0)
    assert 50 < float(out["rest"].sum()) < 200  # the comparison covers the bias update at rest
    # ... and both sensors frozen, from the 10th repeated sample on (the attitude held, then the
    # accelerometer not trusted)
    assert out["gyro_frozen"][0].nonzero().flatten().tolist() == list(range(244, 260))
    assert out["acc_frozen"][0].nonzero().flatten().tolist() == list(range(274, 290))
    # step by step after reset = run, and chunks of any size = steps
    stream.reset(q0)
    q_k = [stream.step(imu[k], 1.0 / RATE)[0] for k in range(N)]
    assert float(_angle(torch.stack(q_k), q_s).max()) < STEP_CHUNK_TOL
    stream.reset(q0)
    q_c = [stream.step_chunk(imu[a:b], dt[a:b])[0] for a, b in ((0, 1), (1, 8), (8, 150), (150, 151), (151, N))]
    assert float(_angle(torch.cat(q_c), q_s).max()) < STEP_CHUNK_TOL


def test_streaming_chunk_refuses_bad_time_steps_before_changing_state(tmp_path):
    model = _model(9)
    export_streaming(model, tmp_path / "s.pt", {"rate_hz": RATE})
    stream = torch.jit.load(str(tmp_path / "s.pt"))
    imu, q0 = _imu(9, 1), torch.tensor([1.0, 0.0, 0.0, 0.0])
    q_ref, _ = stream.run(imu[:20], 1.0 / RATE, q0)
    stream.reset(q0)
    stream.step_chunk(imu[:10], 1.0 / RATE)
    with pytest.raises((ValueError, torch.jit.Error), match="dt"):
        stream.step_chunk(imu[10:20], torch.zeros(10))
    bad = imu[10:20].clone()
    bad[3, 2] = float("nan")
    with pytest.raises((ValueError, torch.jit.Error), match="non-finite"):
        stream.step_chunk(bad, 1.0 / RATE)
    # run() checks everything before it resets: a refused run leaves the stream where it was
    with pytest.raises((ValueError, torch.jit.Error), match="dt"):
        stream.run(imu[:20], torch.zeros(20), q0)
    with pytest.raises((ValueError, torch.jit.Error), match="q0"):
        stream.run(imu[:20], 1.0 / RATE, torch.zeros(4))
    q, _ = stream.step_chunk(imu[10:20], 1.0 / RATE)
    assert float(_angle(q, q_ref[10:20]).max()) < STEP_CHUNK_TOL


def test_closed_loop_export_refuses_other_network_precisions(tmp_path):
    with pytest.raises(ExportError, match="float32"):
        export_batch(_model(9), tmp_path / "b.pt", {"rate_hz": RATE}, net_dtype=torch.float64)
