"""The numba streaming runtime (tcn_ahrs.streaming.CompiledStreaming) computes what evaluation
(LearnedAHRS.run_sequence) and the exported streaming module compute, one sample or one chunk
at a time, and refuses bad samples before its state changes."""

import numpy as np
import pytest
import torch

from tcn_ahrs import so3
from tcn_ahrs.export import export_streaming

pytest.importorskip("numba")
from tcn_ahrs.streaming import CompiledStreaming  # noqa: E402

from test_export_closed_loop import N, RATE, STEP_CHUNK_TOL, TOL, _angle, _eager, _imu, _model  # noqa: E402


@pytest.mark.parametrize("axes", [9, 6])
def test_matches_evaluation_and_the_exported_module(tmp_path, axes):
    model = _model(axes)
    stream = CompiledStreaming(model)
    export_streaming(model, tmp_path / "s.pt", {"rate_hz": RATE})
    exported = torch.jit.load(str(tmp_path / "s.pt"))
    dt = torch.full((N,), 1.0 / RATE)
    for seed in (1, 2):  # the second recording after reset()
        imu = _imu(axes, seed)
        q0 = so3.quat_normalize(torch.tensor([0.9, 0.1, -0.2, 0.3 * seed]))
        q_ref, w_ref = _eager(model, imu, dt, q0)
        q, w = stream.run(imu.numpy(), 1.0 / RATE, q0.numpy())
        assert float(_angle(q_ref, torch.from_numpy(q)).max()) < TOL
        assert float((torch.from_numpy(w) - w_ref).abs().max()) < TOL
        q_ts, _ = exported.run(imu, dt, q0)
        assert float(_angle(q_ts, torch.from_numpy(q)).max()) < TOL


def test_steps_and_chunks_of_any_size_are_one_run():
    model = _model(9)
    stream = CompiledStreaming(model)
    imu = _imu(9, 3).numpy()
    q0 = np.array([0.9, 0.1, -0.2, 0.3])
    q_run, w_run = stream.run(imu, 1.0 / RATE, q0)
    stream.reset(q0)
    q_step = np.stack([stream.step(imu[k], 1.0 / RATE)[0] for k in range(N)])
    # short chunks run the networks sample by sample too: the same compiled code to the last bit
    stream.reset(q0)
    cuts = list(range(0, N, 7)) + [N]
    q_short = np.concatenate([stream.step_chunk(imu[a:b], 1.0 / RATE)[0] for a, b in zip(cuts[:-1], cuts[1:])])
    assert np.array_equal(q_short, q_step)
    # long chunks run them as convolutions (other float32 summation order), on the same state
    stream.chunk_networks = 16
    stream.reset(q0)
    q_chunk = np.concatenate([stream.step_chunk(imu[a:b], 1.0 / RATE)[0]
                              for a, b in ((0, 1), (1, 8), (8, 150), (150, 151), (151, N))])
    for q in (q_step, q_chunk):
        assert float(_angle(torch.from_numpy(q), torch.from_numpy(q_run)).max()) < STEP_CHUNK_TOL


def test_bad_samples_raise_before_the_state_changes():
    stream = CompiledStreaming(_model(9))
    imu = _imu(9, 1).numpy()
    q0 = np.array([1.0, 0.0, 0.0, 0.0])
    q_ref, _ = stream.run(imu[:20], 1.0 / RATE, q0)
    stream.reset(q0)
    stream.step_chunk(imu[:10], 1.0 / RATE)
    bad = imu[10].copy()
    bad[4] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        stream.step(bad, 1.0 / RATE)
    with pytest.raises(ValueError, match="dt"):
        stream.step(imu[10], 0.0)
    with pytest.raises(ValueError, match="expected 9 values"):
        stream.step(imu[10, :6], 1.0 / RATE)
    with pytest.raises(ValueError, match="q0"):
        stream.reset([0.0, 0.0, 0.0, 0.0])
    # run() checks everything before it resets: a refused run leaves the stream where it was
    with pytest.raises(ValueError, match="non-finite"):
        stream.run(np.where(np.arange(20)[:, None] == 5, np.nan, imu[:20]), 1.0 / RATE, q0)
    with pytest.raises(ValueError, match="q0"):
        stream.run(imu[:20], 1.0 / RATE, [0.0, 0.0, 0.0, 0.0])
    q, _ = stream.step_chunk(imu[10:20], 1.0 / RATE)
    assert float(_angle(torch.from_numpy(q), torch.from_numpy(q_ref[10:20])).max()) < STEP_CHUNK_TOL


def test_rational_erf_is_erf_to_float32_precision():
    import math

    from tcn_ahrs.streaming import erf_rational

    xs = np.linspace(-6.0, 6.0, 24001)
    assert max(abs(erf_rational(float(x)) - math.erf(float(x))) for x in xs) < 1e-7


def test_a_gap_is_read_alike_in_every_runtime(tmp_path):
    """0.4 s lost at sample 30 (a step of 40 periods): the batch model flags it and integrates the
    mean of the calibrated readings either side; the numba and TorchScript runtimes do the same."""
    model = _model(9)
    imu = _imu(9, 4)
    dt = torch.full((N,), 1.0 / RATE)
    dt[30] = 0.4
    q0 = so3.quat_normalize(torch.tensor([0.9, 0.1, -0.2, 0.3]))
    q_ref, w_ref = _eager(model, imu, dt, q0)
    with torch.no_grad():
        out = model.run_sequence(imu[None], dt[None], so3.quat_to_matrix(q0.double())[None], 0)
    assert out["gap"][0].nonzero().flatten().tolist() == [30]
    q, w = CompiledStreaming(model).run(imu.numpy(), dt.numpy(), q0.numpy())
    export_streaming(model, tmp_path / "s.pt", {"rate_hz": RATE})
    q_ts, w_ts = torch.jit.load(str(tmp_path / "s.pt")).run(imu, dt, q0)
    for qq, ww in ((torch.from_numpy(q), torch.from_numpy(w)), (q_ts, w_ts)):
        assert float(_angle(q_ref, qq).max()) < TOL and float((ww.double() - w_ref).abs().max()) < TOL
    model.closed.gap_factor = 0.0  # the last reading integrated over the gap instead: another attitude
    assert float(_angle(q_ref, _eager(model, imu, dt, q0)[0]).max()) > 1e-3
