"""Learned residuals on the backbone (model.loop=backbone): the untrained model is the backbone,
the residuals stay within their bounds, and the trust labels read the ground truth correctly."""
from __future__ import annotations

import dataclasses

import numpy as np
import torch
from omegaconf import OmegaConf

from tcn_ahrs import so3
from tcn_ahrs.estimators.learned import LearnedEstimator
from tcn_ahrs.filters import backbone as bb
from tcn_ahrs.filters.common import magnetic_from_nav
from tcn_ahrs.losses import trust_labels
from tcn_ahrs.model.ahrs import LearnedAHRS
from tcn_ahrs.sequence import ImuSequence
from tcn_ahrs.conf import CONF_DIR

CONF = CONF_DIR / "model"


def residual_model(axes: int, **residual) -> LearnedAHRS:
    cfg = OmegaConf.merge(OmegaConf.load(CONF / "ahrs.yaml"), OmegaConf.load(CONF / "residual.yaml"))
    cfg = OmegaConf.to_container(cfg, resolve=False)
    cfg.pop("defaults")
    cfg.update(axes=axes, variant=f"residual{axes}")
    cfg["residual"].update(residual)
    return LearnedAHRS.from_config(cfg)


def _seq(n=600, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.01
    gyr = np.stack([0.3 * np.sin(0.7 * t), 0.2 * np.cos(1.3 * t), 0.5 * np.sin(0.4 * t + 1)], -1)
    gyr += 0.01 + 0.002 * rng.standard_normal((n, 3))
    acc = np.array([0.3, -0.2, 9.7]) + 0.3 * rng.standard_normal((n, 3))
    mag = np.array([5.0, 20.0, -40.0]) + 0.5 * rng.standard_normal((n, 3))
    return ImuSequence(name="s", source="test", time=t, gyro=gyr, accel=acc, mag=mag, rate=100.0)


def test_untrained_model_is_the_backbone():
    """Zero-initialised output layers: gyro residual 0, trust 1 -> exactly the backbone run from
    the same start (9D in the magnetic frame of the start, mapped back; and 6D)."""
    seq = _seq()
    q0 = np.array([0.9, 0.1, -0.2, 0.3]) / np.linalg.norm([0.9, 0.1, -0.2, 0.3])
    k = 50
    for axes in (9, 6):
        model = residual_model(axes).eval()
        got = LearnedEstimator(model=model, name="untrained").run(seq if axes == 9 else seq.without_mag(), q0, k).quat
        mag = seq.mag[k:] if axes == 9 else None
        q = q0
        m = None
        if axes == 9:
            m = magnetic_from_nav(torch.as_tensor(q0), torch.as_tensor(seq.mag[k]))
            q = so3.quat_mul(m, torch.as_tensor(q0)).numpy()
        ref = torch.as_tensor(bb.run(seq.gyro[k:], seq.accel[k:], mag, seq.dt[k:], q0=q)["quat"])
        if m is not None:
            ref = so3.quat_mul(so3.quat_conj(m).expand_as(ref), ref)
        assert np.abs(np.abs((got[k:] * ref.numpy()).sum(-1)) - 1.0).max() < 1e-12
        assert np.allclose(got[:k], q0)


def test_residuals_are_bounded():
    model = residual_model(9, gyro_scale=0.05)
    with torch.no_grad():
        for p in model.calibration.parameters():
            p.normal_(0.0, 10.0)  # any weights
    imu = torch.randn(2, 300, 9) * 10
    out = model.calibration(imu)
    assert out["gyro_error"].abs().max() <= 0.05
    tr = model.backbone.trusts(out)
    for k in ("acc_trust", "mag_trust"):
        assert tr[k].min() >= 0.0 and tr[k].max() <= 2.0
    assert model.num_parameters() > 0


def test_trust_scales_zero_is_integration_of_the_corrected_gyro():
    seq = _seq()
    model = residual_model(9, acc_trust_scale=0.0, mag_trust_scale=0.0, bias_trust_scale=0.0).eval()
    q0 = np.array([1.0, 0.0, 0.0, 0.0])
    got = LearnedEstimator(model=model, name="m").run(seq, q0, 0).quat
    pad = lambda a: torch.as_tensor(np.concatenate([np.zeros_like(a[:1]), a]))[None]  # noqa: E731
    rot = so3.integrate(torch.eye(3, dtype=torch.float64)[None], pad(seq.gyro), pad(seq.dt))[0, 1:]
    ref = so3.matrix_to_quat(rot).numpy()
    assert np.abs(np.abs((got * ref).sum(-1)) - 1.0).max() < 1e-9


def test_trust_labels_from_ground_truth():
    n = 200
    rot = so3.quat_to_matrix(so3.quat_normalize(torch.randn(n, 4, dtype=torch.float64)))
    up_b = rot[:, 2, :]
    field_nav = torch.tensor([0.0, 20.0, -40.0], dtype=torch.float64)
    mag = (rot.transpose(-1, -2) @ field_nav).clone()
    acc = 9.81 * up_b.clone()
    acc[:20] += torch.tensor([3.0, 0.0, 0.0], dtype=torch.float64)  # external acceleration
    mag[150:170] = (rot[150:170].transpose(-1, -2) @ torch.tensor([15.0, 15.0, -40.0], dtype=torch.float64))
    valid = torch.ones(n, dtype=torch.bool)
    valid[-5:] = False
    lab = trust_labels(torch.cat([torch.zeros(n, 3, dtype=torch.float64), acc, mag], -1), rot, valid)
    tilt = torch.rad2deg(torch.acos(((acc / acc.norm(dim=-1, keepdim=True)) * up_b).sum(-1).clamp(-1, 1)))
    assert torch.equal(lab[:-5, 0].bool(), (tilt < 2.0)[:-5])
    assert lab[:20, 0].sum() < 20 and lab[20:150, 0].all()
    assert not lab[150:170, 1].any() and lab[:150, 1].all() and lab[170:-5, 1].all()
    assert not lab[-5:].any()


def test_torchscript_exports_equal_the_evaluated_model(tmp_path):
    """The TorchScript batch and streaming modules of a residual model (the kernel compiled by
    TorchScript, tcn_ahrs.kernels.script_ops) after save/load: the whole recording, one sample
    per call, and a second recording after reset() equal LearnedEstimator's run (<= 1e-5 rad),
    6 and 9 axes, irregular dt; a bad sample is refused before any state changes."""
    import pytest

    from tcn_ahrs.datasets.simulate import simulate
    from tcn_ahrs.export import export_batch, export_streaming, read_metadata

    def angle(a, b):
        return 2.0 * np.arccos(np.clip(np.abs((a * b).sum(-1)), 0.0, 1.0)).max()

    for axes in (9, 6):
        model = _trained_like(axes)
        export_batch(model, tmp_path / f"b{axes}.pt")
        export_streaming(model, tmp_path / f"s{axes}.pt")
        assert read_metadata(tmp_path / f"s{axes}.pt")["loop"] == "backbone"
        batch, stream = torch.jit.load(str(tmp_path / f"b{axes}.pt")), torch.jit.load(str(tmp_path / f"s{axes}.pt"))
        for i, prof in enumerate(["walking", "fast_rotation"]):
            seq = simulate(prof, 3.0, 200.0, seed=i, axes=axes)
            rng = np.random.default_rng(i)
            seq = dataclasses.replace(seq, time=np.concatenate([[0.0], np.cumsum(rng.uniform(0.004, 0.006, len(seq) - 1))]))
            # the runtimes refer heading to the field at reset: the evaluated model's "init"
            ref = LearnedEstimator(model, heading_ref="init").run(seq, seq.quat[0], 0)
            imu = torch.from_numpy(np.concatenate([seq.gyro, seq.accel] + ([seq.mag] if axes == 9 else []), 1))
            dt, q0 = torch.from_numpy(seq.dt), torch.from_numpy(seq.quat[0])
            q, omega = batch(imu, dt, q0)
            assert angle(q.numpy(), ref.quat) < 1e-5
            assert np.abs(omega.numpy() - (seq.gyro + ref.signals["gyro_correction"]
                                           - ref.signals["gyro_bias_state"])).max() < 1e-6
            stream.reset(q0)  # the second profile: after reset of the first
            steps = np.array([stream.step(imu[k], float(dt[k]))[0].numpy() for k in range(100)])
            q_rest, _ = stream.step_chunk(imu[100:], dt[100:])
            assert angle(np.concatenate([steps, q_rest.numpy()]), ref.quat) < 1e-5
        # a refused sample leaves no trace: the stream goes on as one that never saw it
        bad = imu[0].clone()
        bad[4] = float("nan")
        stream.reset(q0)
        stream.step_chunk(imu[:50], dt[:50])
        with pytest.raises(Exception, match="non-finite"):
            stream.step(bad, 0.005)
        with pytest.raises(Exception, match="dt"):
            stream.step(imu[50], 0.0)
        after = stream.step_chunk(imu[50:60], dt[50:60])[0]
        stream.reset(q0)
        clean = stream.step_chunk(imu[:60], dt[:60])[0][50:]
        assert angle(after.numpy(), clean.numpy()) < 1e-6  # float32 networks, chunked differently


def test_knob_selection_falls_back_to_integration_only_where_correction_hurts():
    """Inner-fold knob selection (knobs.select_residual_knobs): an exact gyro with walking
    accelerations -> strapdown (every correction hurts); a 1.5-2 deg/s gyro bias -> the backbone.
    The reference point (tuned backbone alone) is always in the table."""
    from tcn_ahrs.datasets.simulate import simulate
    from tcn_ahrs.tuning.knobs import select_residual_knobs

    exact = simulate("walking", 30.0, 100.0, seed=1, axes=6, noise_free=True)
    biased = simulate("slow_rotation", 60.0, 100.0, seed=2, axes=6, gyro_bias_range_dps=(1.5, 2.0))
    for seq, scale in ((exact, 0.0), (biased, 1.0)):
        model = residual_model(6)
        chosen, table = select_residual_knobs(model, [seq])
        assert chosen["acc_trust_scale"] == chosen["bias_trust_scale"] == scale
        assert model.backbone.acc_trust_scale == scale  # applied to the model
        ref = [r for r in table if r["reference"]]
        assert ref[0]["knobs"] == {"gyro_clip": 0.0, "trust_weight": 0.0, "acc_trust_scale": 1.0,
                                   "mag_trust_scale": 1.0, "bias_trust_scale": 1.0, "bias_prior": 1.0}
        assert len(ref) == 1 and table[0]["aae_deg"] <= ref[0]["aae_deg"]
        assert table[0]["inclination_deg"] <= ref[0]["inclination_deg"]


def _trained_like(axes: int, seed: int = 0) -> LearnedAHRS:
    """A residual model with random (non-zero) output layers and BatchNorm statistics, so that the
    gyro residual and both trusts move (the untrained model's zero outputs would prove nothing)."""
    torch.manual_seed(seed)
    model = residual_model(axes, gyro_clip=0.01, trust_weight=1.0)
    with torch.no_grad():
        for net in (model.calibration.gyro_net, model.calibration.trust_net):
            net.out.weight.normal_(0.0, 0.3)
            net.out.bias.normal_(0.0, 0.3)
            for m in net.modules():
                if isinstance(m, torch.nn.BatchNorm1d):
                    m.running_mean.normal_(0.0, 0.1)
                    m.running_var.uniform_(0.5, 2.0)
        model.backbone.bias_init.copy_(torch.tensor([0.002, -0.001, 0.003], dtype=torch.float64))
    return model.eval()


def test_compiled_streaming_equals_the_evaluated_model():
    """CompiledStreaming(model) of a residual model: whole-recording chunks, one sample per call,
    and a second recording after reset() all equal LearnedEstimator's batch run (<= 1e-5 rad),
    6 and 9 axes; irregular dt."""
    from tcn_ahrs.datasets.simulate import simulate
    from tcn_ahrs.streaming import BackboneStreaming, CompiledStreaming

    def angle(a, b):
        return 2.0 * np.arccos(np.clip(np.abs((a * b).sum(-1)), 0.0, 1.0)).max()

    for axes in (9, 6):
        model = _trained_like(axes)
        stream = CompiledStreaming(model)
        assert isinstance(stream, BackboneStreaming)
        for i, prof in enumerate(["walking", "fast_rotation"]):
            seq = simulate(prof, 8.0, 200.0, seed=i, axes=axes)
            rng = np.random.default_rng(i)
            seq = dataclasses.replace(seq, time=np.concatenate([[0.0], np.cumsum(rng.uniform(0.004, 0.006, len(seq) - 1))]))
            # the runtimes refer heading to the field at reset: the evaluated model's "init"
            ref = LearnedEstimator(model, heading_ref="init").run(seq, seq.quat[0], 0)
            imu = np.concatenate([seq.gyro, seq.accel] + ([seq.mag] if axes == 9 else []), 1)
            q, omega = stream.run(imu, seq.dt, seq.quat[0])  # second pass: after reset of the first
            assert angle(q, ref.quat) < 1e-5
            assert np.abs(omega - (imu[:, 0:3] + ref.signals["gyro_correction"]
                                   - ref.signals["gyro_bias_state"])).max() < 1e-6
            stream.reset(seq.quat[0])
            steps = np.array([stream.step(imu[k], seq.dt[k])[0] for k in range(300)])
            assert angle(steps, ref.quat[:300]) < 1e-5


def test_compiled_streaming_refuses_bad_samples_before_any_state_change():
    import pytest

    from tcn_ahrs.streaming import CompiledStreaming

    model = _trained_like(9)
    seq = _seq()
    imu = np.concatenate([seq.gyro, seq.accel, seq.mag], 1)
    a, b = CompiledStreaming(model), CompiledStreaming(model)
    for s in (a, b):
        s.reset([1.0, 0.0, 0.0, 0.0])
        s.step_chunk(imu[:100], 0.01)
    bad = imu[100].copy()
    bad[4] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        a.step(bad, 0.01)
    with pytest.raises(ValueError, match="dt"):
        a.step(imu[100], 0.0)
    with pytest.raises(ValueError, match="expected 9 values"):
        a.step(imu[100, :6], 0.01)
    qa, _ = a.step_chunk(imu[100:200], 0.01)
    qb, _ = b.step_chunk(imu[100:200], 0.01)
    assert np.array_equal(qa, qb)


def test_a_recording_at_another_rate_runs_the_default_backbone():
    """A residual model on a recording at another rate than it was trained at (another device)
    runs as the backbone with VQF's default parameters and nothing learned (a warning says so);
    other_rate=model runs the model as trained. Same rate: the model."""
    import pytest

    seq = _seq()  # 100 Hz
    model = _trained_like(6)
    model.backbone.params = bb.BackboneParams(tau_acc=1.0)  # a tuned backbone that must not carry over
    q0 = np.array([1.0, 0.0, 0.0, 0.0])
    from tcn_ahrs.estimators.registry import build

    plain = build("backbone", axes=6).run(seq, q0, 0).quat  # the matrix's "backbone" column

    def angle(a, b):
        return 2.0 * np.arccos(np.clip(np.abs((a * b).sum(-1)), 0.0, 1.0)).max()

    model.trained_rate_hz = 200.0
    est = LearnedEstimator(model)
    with pytest.warns(UserWarning, match="another device"):
        out = est.run(seq, q0, 0)
    assert np.abs(out.quat - plain).max() < 1e-12 and est.fell_back == ["s"]
    with pytest.warns(UserWarning, match="trained at 200"):
        own = LearnedEstimator(model, other_rate="model").run(seq, q0, 0)
    assert angle(own.quat, plain) > 1e-3
    model.trained_rate_hz = 100.0
    same = LearnedEstimator(model).run(seq, q0, 0)
    assert np.abs(same.quat - own.quat).max() < 1e-12
    with pytest.raises(ValueError, match="other_rate"):
        LearnedEstimator(model, other_rate="vqf")
