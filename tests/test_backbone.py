"""The VQF-grade backbone (tcn_ahrs.kernels.backbone): equal to the ``vqf`` package on real
recordings, its compiled loop equal to its tensor scan, and the learned inputs' neutral and
extreme settings (trust 1 = the backbone, trust 0 = strapdown integration).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from tcn_ahrs import so3
from tcn_ahrs.filters import backbone as bb
from tcn_ahrs.conf import CONF_DIR
from tolerances import ANGLE_F64, DEG_F64, DEG_ZERO_F64, PARITY_F64

SHARED = Path(__file__).resolve().parents[2] / "shared" / "datasets"


def angle_deg(q1, q2):
    """Rotation angle between unit quaternions (atan2 form: exact near zero, unlike arccos)."""
    d = so3.quat_mul(so3.quat_conj(torch.as_tensor(np.asarray(q1))), torch.as_tensor(np.asarray(q2)))
    return np.degrees(2.0 * np.arctan2(d[..., 1:].norm(dim=-1).numpy(), np.abs(d[..., 0].numpy())))


def _real(name):
    """(gyro, acc, mag, rate) of one real recording through the project's loader."""
    from omegaconf import OmegaConf

    from tcn_ahrs.datasets import load_split

    data, rec = name.split(":")
    if not (SHARED / data).is_dir():
        pytest.skip(f"needs ../shared/datasets/{data}")
    cfg = OmegaConf.load(CONF_DIR / "data" / f"{data}.yaml")
    cfg.root = str(SHARED / data)
    cfg.train = [rec]
    cfg.fold = None
    seq = load_split(cfg, "trainval")[0]
    return seq.gyro, seq.accel, seq.mag, float(seq.rate)


@pytest.mark.shared
@pytest.mark.parametrize("name", ["broad:28_disturbed_stationary_magnet_A", "broad:24_disturbed_tapping_A",
                                  "oxiod:trolley/data2/imu1", "oxiod:handheld/data1/imu2"])
def test_backbone_equals_vqf_package(name):
    """Cross-implementation test: VQF's defaults, VQF's start (identity), the recording's nominal
    period -> the vqf package's 6D and 9D attitude to <= 0.1 deg RMS (in fact to round-off), and its
    bias estimate, rest and disturbance flags."""
    _assert_equals_vqf(*_real(name), name)


@pytest.mark.parametrize("profile", ["walking", "fast_rotation", "static", "drone"])
def test_backbone_equals_vqf_package_on_the_simulator(profile):
    """The same cross-implementation test without ../shared: simulated recordings with a device's
    noise, biases, hard iron and magnetic disturbances (rest, motion bias and rejection all run)."""
    from tcn_ahrs.datasets.simulate import simulate

    seq = simulate(profile, 60.0, 100.0, seed=3, device_seed=1)
    _assert_equals_vqf(seq.gyro, seq.accel, seq.mag, 100.0, profile)


def _assert_equals_vqf(gyr, acc, mag, rate, name):
    vqf = pytest.importorskip("vqf")
    gyr, acc, mag = (np.ascontiguousarray(x, dtype=np.float64) for x in (gyr, acc, mag))
    ts = 1.0 / rate
    dt = np.full(len(gyr), ts)
    for use_mag in (True, False):
        ref = vqf.VQF(ts).updateBatch(gyr, acc, mag if use_mag else None)
        out = bb.run(gyr, acc, mag if use_mag else None, dt)
        err = angle_deg(out["quat"], ref["quat9D" if use_mag else "quat6D"])
        assert np.sqrt(np.mean(err ** 2)) <= 0.1, (name, use_mag)
        assert err.max() < 1e-4, (name, use_mag)  # deg: the docstring's cross-implementation bound
        assert np.abs(out["gyro_bias"] - ref["bias"]).max() < ANGLE_F64
        assert (out["rest"] == ref["restDetected"]).all()
        if use_mag:
            assert (out["mag_disturbed"] == ref["magDistDetected"]).all()


def _synthetic(n=400, seed=0, irregular=False):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.01
    gyr = np.stack([0.3 * np.sin(0.7 * t), 0.2 * np.cos(1.3 * t), 0.5 * np.sin(0.4 * t + 1)], -1)
    gyr[: n // 4] = 0.01  # a resting start (rest detection and the rest bias update run)
    gyr += 0.002 * rng.standard_normal((n, 3))
    acc = np.array([0.3, -0.2, 9.7]) + 0.3 * rng.standard_normal((n, 3))
    mag = np.array([5.0, 20.0, -40.0]) + 0.5 * rng.standard_normal((n, 3))
    dt = np.full(n, 0.01)
    if irregular:
        dt = dt * rng.uniform(0.7, 1.3, n)
    return gyr, acc, mag, dt


@pytest.mark.parametrize("irregular", [False, True])
def test_tensor_scan_equals_compiled_loop(irregular):
    """One step, two readings: the torch scan (autograd) equals the numba loop with arbitrary
    per-sample trusts and time steps, for the 9D and 6D filters."""
    params = bb.BackboneParams(tau_acc=0.5, rest_min_time=0.5, mag_new_first_time=0.5, tau_mag=2.0)
    gyr, acc, mag, dt = _synthetic(irregular=irregular)
    n = len(gyr)
    rng = np.random.default_rng(1)
    trusts = rng.uniform(0.0, 2.0, (3, 2, n))
    q0 = np.array([[0.9, 0.1, -0.2, 0.3], [1.0, 0.0, 0.0, 0.0]])
    q0 /= np.linalg.norm(q0, axis=1, keepdims=True)
    T = lambda a: torch.as_tensor(np.stack([a, a]), dtype=torch.float64)  # noqa: E731
    for use_mag in (True, False):
        s0 = bb.start_state_tensor(params, torch.as_tensor(q0))
        q, b, _ = bb.scan(s0, params, T(gyr), T(acc), T(mag) if use_mag else None, T(dt),
                          *(torch.as_tensor(t) for t in trusts))
        for i in range(2):
            ref = bb.run(gyr, acc, mag if use_mag else None, dt, params, q0=q0[i], acc_trust=trusts[0, i],
                         mag_trust=trusts[1, i], bias_trust=trusts[2, i])
            assert angle_deg(q[i].numpy(), ref["quat"]).max() < DEG_F64
            assert np.abs(b[i].numpy() - ref["gyro_bias"]).max() < PARITY_F64[1]
            assert np.abs(ref["gyro_bias"]).max() > 0  # the bias filter ran


def test_scan_gradient_is_finite_and_reaches_every_input():
    params = bb.BackboneParams(tau_acc=0.5, rest_min_time=0.5, mag_new_first_time=0.5)
    gyr, acc, mag, dt = (torch.as_tensor(a)[None] for a in _synthetic(n=300))
    inputs = [gyr.clone().requires_grad_(True)] + [torch.ones(1, 300, dtype=torch.float64, requires_grad=True)
                                                   for _ in range(3)]
    s0 = bb.start_state_tensor(params, torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64))
    q, b, _ = bb.scan(s0, params, inputs[0], acc, mag, dt, *inputs[1:])
    (q[:, -50:, 1:].pow(2).sum() + b.pow(2).sum()).backward()
    for x in inputs:
        assert torch.isfinite(x.grad).all()
        assert x.grad.abs().sum() > 0


def test_zero_trust_is_strapdown_integration():
    """acc, mag and bias trust 0: the backbone integrates the gyro from q0 and nothing else."""
    gyr, acc, mag, dt = _synthetic(n=500)
    q0 = np.array([0.9, 0.1, -0.2, 0.3]) / np.linalg.norm([0.9, 0.1, -0.2, 0.3])
    zero = np.zeros(len(gyr))
    out = bb.run(gyr, acc, mag, dt, q0=q0, acc_trust=zero, mag_trust=zero, bias_trust=zero)
    # the backbone's sample k has applied gyro[0..k]: integrate with one leading dummy sample
    pad = lambda a: torch.as_tensor(np.concatenate([np.zeros_like(a[:1]), a]))[None]  # noqa: E731
    rot = so3.integrate(so3.quat_to_matrix(torch.as_tensor(q0))[None], pad(gyr), pad(dt))[0, 1:]
    expect = so3.matrix_to_quat(rot).numpy()
    assert angle_deg(out["quat"], expect).max() < DEG_ZERO_F64
    assert np.abs(out["gyro_bias"]).max() == 0.0


def test_backbone_estimator_registered_and_runs():
    from tcn_ahrs.estimators import registry
    from tcn_ahrs.sequence import ImuSequence

    gyr, acc, mag, dt = _synthetic(n=300)
    seq = ImuSequence(name="synthetic", source="test", time=np.cumsum(dt), gyro=gyr, accel=acc, mag=mag, rate=100.0)
    for axes in (6, 9):
        est = registry.build("backbone", axes)
        out = est.run(seq, np.array([1.0, 0.0, 0.0, 0.0]))
        assert out.quat.shape == (300, 4) and np.isfinite(out.quat).all()
        assert est.name == f"backbone{axes}d"
    assert registry.get("backbone").tunable


def test_bias0_is_a_prior_the_backbone_keeps_estimating_from():
    gyr, acc, mag, dt = _synthetic(n=400)
    b0 = np.array([0.01, -0.02, 0.005])
    out = bb.run(gyr, acc, mag, dt, bias0=b0, acc_trust=np.ones(400), bias_trust=np.zeros(400))
    assert np.allclose(out["gyro_bias"], b0)  # frozen (bias trust 0): stays at the prior
    free = bb.run(gyr, acc, mag, dt, bias0=b0)
    assert np.allclose(free["gyro_bias"][0], b0, atol=1e-3)  # one update from the prior
    assert not np.allclose(free["gyro_bias"][-1], b0)


def test_an_irregular_clock_does_not_switch_the_magnetometer_off():
    """The same motion sampled evenly and with ±30 % timestamp jitter: the field is accepted at
    the same time and flagged disturbed on the same share of samples (with the transposed direct
    form II low-passes, whose states jump when the step's coefficients change, jitter flagged
    100 % of samples against 69 % evenly)."""
    from tcn_ahrs.datasets.simulate import simulate

    s = simulate("walking", 60.0, 1000.0, seed=3, noise_free=True)
    rng = np.random.default_rng(0)
    even = np.arange(0, len(s.time), 10)
    jittered = np.unique(np.clip(even + rng.integers(-3, 4, len(even)), 0, len(s.time) - 1))
    share = {}
    for name, idx in (("even", even), ("jittered", jittered)):
        t = s.time[idx]
        out = bb.run(s.gyro[idx], s.accel[idx], s.mag[idx], np.diff(t, prepend=t[0] - 0.01), bb.BackboneParams(),
                     q0=s.quat[idx[0]])
        share[name] = out["mag_disturbed"].mean()
    assert share["even"] < 0.8 and abs(share["jittered"] - share["even"]) < 0.02


def test_the_low_pass_continues_a_constant_signal_when_the_step_changes():
    """A constant input stays constant through a 2nd-order low-pass whose step (hence
    coefficients) changes every sample: direct form I keeps inputs and outputs, not states."""
    from dataclasses import asdict

    from tcn_ahrs.kernels import backbone as K

    params = np.zeros(K.N_PARAM)
    for k, v in asdict(K.BackboneParams()).items():
        params[K.PARAM[k]] = v
    s, c = np.zeros(K.N_STATE), np.zeros(K.N_COEFF)
    rng = np.random.default_rng(1)
    ys = []
    for _ in range(300):
        ts = 0.01 * (1.0 + rng.uniform(-0.3, 0.3))
        K.coefficients(params, ts, c)
        run, n, start = K.lp_begin(s, K.F_MAG, 0.05, ts)
        ys.append(K.lp(s, c, K.F_MAG, 2, 0, 50.0, K.C_MAG_B, K.C_MAG_A, run, n, start, False))
        K.lp_end(s, K.F_MAG, run, start)
    np.testing.assert_allclose(ys, 50.0, rtol=1e-12)
