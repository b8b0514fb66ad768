"""Tests of the IMU simulator (tcn_ahrs.datasets.simulate): exact ground truth, the error
model of Eqs. 9-11, determinism, splits."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tcn_ahrs import so3
from tcn_ahrs.conventions import DEG, GRAVITY
from tcn_ahrs.datasets import simulate as sim
from tcn_ahrs.sequence import ImuSequence
from tcn_ahrs.conf import CONF_DIR

CONF = CONF_DIR / "data" / "simulated.yaml"


def _rot(seq: ImuSequence) -> np.ndarray:
    """(N,3,3) ground-truth nav_from_body, via the independent torch implementation."""
    return so3.quat_to_matrix(torch.from_numpy(seq.quat)).numpy()


def _angle_between(r_a: np.ndarray, r_b: np.ndarray) -> np.ndarray:
    return so3.log(torch.from_numpy(np.swapaxes(r_a, -1, -2) @ r_b)).norm(dim=-1).numpy()


# ----------------------------------------------------------------------------- exact ground truth


@pytest.mark.parametrize("profile", ["fast_rotation", "walking", "drone"])
def test_noise_free_gyro_integrates_to_ground_truth(profile):
    seq = sim.simulate(profile, 60.0, 100.0, seed=11, noise_free=True)
    assert seq.quat.dtype == np.float64 and seq.quat_valid.all()
    if profile == "fast_rotation":  # the profile really is fast
        assert np.abs(seq.gyro).max() > 3.0
    r_gt = _rot(seq)
    dt = torch.full((len(seq),), 1.0 / seq.rate, dtype=torch.float64)
    r_int = so3.integrate(torch.from_numpy(r_gt[0]), torch.from_numpy(seq.gyro), dt).numpy()
    assert _angle_between(r_int, r_gt).max() < 1e-6


def test_cumprod_quat_matches_sequential_product():
    rng = np.random.default_rng(0)
    for n in (1, 7, 65, 1000, 4099):
        q = rng.normal(size=(n, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        ref = [q[0]]
        for k in range(1, n):
            ref.append(so3.quat_mul(torch.from_numpy(ref[-1]), torch.from_numpy(q[k])).numpy())
        ref = np.array(ref)
        got = sim.cumprod_quat(q)
        assert np.abs(np.abs(np.sum(got * ref, axis=1)) - 1.0).max() < 1e-12, n


def test_noise_free_accelerometer_is_specific_force():
    seq = sim.simulate("walking", 40.0, 100.0, seed=3, noise_free=True)
    r = _rot(seq)
    g_body = np.einsum("nji,j->ni", r, [0.0, 0.0, GRAVITY])
    rest = ~seq.meta["moving"]
    assert rest[: int(5 * seq.rate)].all()  # at least 5 s of rest at the start
    assert np.abs(seq.accel[rest] - g_body[rest]).max() < 1e-9
    still = rest & np.concatenate([[True], rest[:-1]])  # gyro k: the rate over (t_{k-1}, t_k]
    assert np.abs(seq.gyro[still]).max() < 1e-12
    # moving: R^T (a_nav + g), and the body-frame external acceleration is R^T a_nav
    a_nav = seq.meta["true_acc_nav"]
    assert np.linalg.norm(a_nav, axis=1).max() > 2.0
    np.testing.assert_allclose(seq.accel, np.einsum("nji,nj->ni", r, a_nav) + g_body, atol=1e-9)
    np.testing.assert_allclose(seq.meta["true_ext_acc"], np.einsum("nji,nj->ni", r, a_nav), atol=1e-9)


@pytest.mark.parametrize("profile", ["walking", "drone", "slow_rotation"])
def test_acceleration_is_derivative_of_velocity(profile):
    seq = sim.simulate(profile, 30.0, 1000.0, seed=5, noise_free=True)
    v, a = seq.meta["true_vel_nav"], seq.meta["true_acc_nav"]
    a_num = (v[2:] - v[:-2]) * (seq.rate / 2.0)
    assert np.abs(a_num - a[1:-1]).max() < 1e-3 * max(1.0, np.abs(a).max())


def test_drone_thrust_along_body_z():
    seq = sim.simulate("drone", 40.0, 100.0, seed=2, noise_free=True)
    f = seq.accel
    assert np.abs(f[:, :2]).max() < 1e-9 * GRAVITY * 10  # specific force only along body z
    tilt = np.arccos(np.clip(_rot(seq)[:, 2, 2], -1, 1))
    assert 5 * DEG < tilt.max() < 45 * DEG


def test_noise_free_magnetometer_is_earth_field_in_body():
    seq = sim.simulate("fast_rotation", 20.0, 100.0, seed=4, noise_free=True)
    m_nav = np.array([0.0, 49.0 * math.cos(65 * DEG), -49.0 * math.sin(65 * DEG)])
    np.testing.assert_allclose(seq.mag, np.einsum("nji,j->ni", _rot(seq), m_nav), atol=1e-9)
    # configurable field: 30 uT, dip -30 deg (southern hemisphere: points up), declination 10 deg
    seq = sim.simulate("slow_rotation", 20.0, 100.0, seed=4, noise_free=True,
                       field_ut=30.0, dip_deg=-30.0, declination_deg=10.0)
    h = 30.0 * math.cos(30 * DEG)
    m_nav = np.array([h * math.sin(10 * DEG), h * math.cos(10 * DEG), 30.0 * math.sin(30 * DEG)])
    np.testing.assert_allclose(seq.mag, np.einsum("nji,j->ni", _rot(seq), m_nav), atol=1e-9)


# ----------------------------------------------------------------------------- error model


def test_error_model_reconstructs_measurements():
    """Eqs. 9-11 from the truths in meta leave only white noise of the configured density."""
    seq = sim.simulate("walking", 60.0, 100.0, seed=8, mag_disturbances_per_minute=3.0)
    m, p = seq.meta, sim.SensorErrorModel()
    r = _rot(seq)
    sq = math.sqrt(seq.rate)
    gyro_res = seq.gyro - (m["true_gyro"] @ m["K_gyro"].T + m["true_gyro_bias"])
    acc_true = m["true_ext_acc"] + np.einsum("nji,j->ni", r, [0, 0, GRAVITY])
    acc_res = seq.accel - (acc_true @ m["K_acc"].T + m["true_acc_bias"])
    mag_true = np.einsum("nji,j->ni", r, m["mag_field_nav"]) + m["true_mag_disturbance"]
    mag_res = seq.mag - (mag_true @ m["K_mag"].T + m["hard_iron"])
    for res, density in ((gyro_res, p.gyro_noise_density_dps * DEG), (acc_res, p.acc_noise_density),
                         (mag_res, p.mag_noise_density_ut)):
        assert np.abs(res.mean(0)).max() < 5 * density * sq / math.sqrt(len(seq))
        np.testing.assert_allclose(res.std(0), density * sq, rtol=0.05)
    # K really is a calibration error (not identity), close to identity
    for k in ("K_gyro", "K_acc", "K_mag"):
        assert 1e-3 < np.abs(m[k] - np.eye(3)).max() < 0.3


def test_bias_statistics():
    p = sim.SensorErrorModel()
    lo, hi = p.gyro_bias_range_dps
    steps, statics = [], []
    for seed in range(4):
        seq = sim.simulate("static", 120.0, 100.0, seed=seed, device_seed=seed)
        b = seq.meta["true_gyro_bias"]
        statics.append(seq.meta["gyro_bias_static"])
        steps.append(np.diff(b, axis=0))
        # at rest the mean gyro reading is the bias (K w = 0)
        np.testing.assert_allclose(seq.gyro.mean(0), b.mean(0), atol=0.01 * DEG)
        # BROAD-like magnitude: 0.1-0.5 deg/s (+- the per-recording repeatability)
        mag_dps = np.abs(seq.meta["gyro_bias_static"]) / DEG
        slack = 4 * p.gyro_bias_repeatability_dps
        assert np.all(mag_dps > lo - slack) and np.all(mag_dps < hi + slack)
        assert np.allclose(b[0], seq.meta["gyro_bias_static"])
    step_std = np.concatenate(steps).std()
    np.testing.assert_allclose(step_std, p.gyro_bias_rw_dps * DEG * math.sqrt(0.01), rtol=0.05)
    # a configured bias range is honoured
    seq = sim.simulate("static", 10.0, 100.0, seed=1, gyro_bias_range_dps=(2.0, 2.0),
                       gyro_bias_repeatability_dps=0.0)
    np.testing.assert_allclose(np.abs(seq.meta["gyro_bias_static"]) / DEG, 2.0, rtol=1e-12)


def test_same_device_across_recordings():
    a = sim.simulate("walking", 20.0, 100.0, seed=1, device_seed=7)
    b = sim.simulate("drone", 20.0, 100.0, seed=2, device_seed=7)
    c = sim.simulate("walking", 20.0, 100.0, seed=1, device_seed=8)
    k_std = sim.SensorErrorModel().recording_k_std
    assert np.abs(a.meta["K_gyro"] - b.meta["K_gyro"]).max() < 8 * k_std
    assert np.abs(a.meta["K_gyro"] - c.meta["K_gyro"]).max() > 8 * k_std
    rep = sim.SensorErrorModel().gyro_bias_repeatability_dps * DEG
    assert np.abs(a.meta["gyro_bias_static"] - b.meta["gyro_bias_static"]).max() < 8 * rep
    assert np.abs(a.meta["hard_iron"] - b.meta["hard_iron"]).max() < 5.0


def test_noise_free_has_no_errors():
    seq = sim.simulate("fast_rotation", 20.0, 100.0, seed=3, noise_free=True)
    m = seq.meta
    for k in ("K_gyro", "K_acc", "K_mag"):
        assert np.array_equal(m[k], np.eye(3))
    assert not m["true_gyro_bias"].any() and not m["true_mag_disturbance"].any()
    assert not m["mag_disturbed"].any()
    assert np.array_equal(seq.gyro, m["true_gyro"])


def test_disturbance_flags_line_up_with_added_field():
    seq = sim.simulate("slow_rotation", 90.0, 100.0, seed=6, mag_disturbances_per_minute=4.0,
                       mag_noise_density_ut=0.0)
    m = seq.meta
    flag = m["mag_disturbed"]
    added = np.linalg.norm(m["true_mag_disturbance"], axis=1)
    assert 0.02 < flag.mean() < 0.6
    np.testing.assert_array_equal(flag, added > sim.MAG_FLAG_THRESHOLD_UT)
    assert added.max() > 10.0
    # the measured field deviates from the undisturbed model exactly there
    clean = (np.einsum("nji,j->ni", _rot(seq), m["mag_field_nav"]) @ m["K_mag"].T + m["hard_iron"])
    dev = np.linalg.norm(seq.mag - clean, axis=1)
    assert dev[~flag].max() < 1.5 * sim.MAG_FLAG_THRESHOLD_UT
    assert np.median(dev[flag]) > 3.0
    # no disturbance during the initial rest (initial alignment stays possible)
    first_move = int(np.argmax(m["moving"]))
    assert not flag[:first_move].any()
    # external-acceleration flag
    np.testing.assert_array_equal(m["acc_disturbed"],
                                  np.linalg.norm(m["true_acc_nav"], axis=1) > sim.EXT_ACC_FLAG_THRESHOLD)
    # disturbances can be switched off
    off = sim.simulate("slow_rotation", 90.0, 100.0, seed=6, mag_disturbances_per_minute=0.0)
    assert not off.meta["mag_disturbed"].any()


# ----------------------------------------------------------------------------- API behaviour


def test_determinism():
    a = sim.simulate("walking", 20.0, 100.0, seed=3)
    b = sim.simulate("walking", 20.0, 100.0, seed=3)
    c = sim.simulate("walking", 20.0, 100.0, seed=4)
    for f in ("gyro", "accel", "mag", "quat"):
        assert np.array_equal(getattr(a, f), getattr(b, f))
        assert not np.allclose(getattr(a, f), getattr(c, f))
    # the noise-free twin has the same motion
    nf = sim.simulate("walking", 20.0, 100.0, seed=3, noise_free=True)
    assert np.array_equal(nf.quat, a.quat)


def test_six_axis_drops_mag_only():
    a9 = sim.simulate("drone", 20.0, 100.0, seed=1, axes=9)
    a6 = sim.simulate("drone", 20.0, 100.0, seed=1, axes=6)
    assert a6.mag is None and a6.num_axes == 6 and a9.num_axes == 9
    assert np.array_equal(a6.gyro, a9.gyro) and np.array_equal(a6.accel, a9.accel)


@pytest.mark.parametrize("rate", [50.0, 200.0, 285.71])
def test_valid_sequence_at_any_rate(rate):
    seq = sim.simulate("fast_rotation", 30.0, rate, seed=2)
    assert isinstance(seq, ImuSequence)
    assert len(seq) == int(round(30.0 * rate)) + 1
    assert seq.rate == rate and seq.score_mask is None and seq.quat_valid.all()
    assert seq.name == "sim_fast_rotation_s0002"
    assert seq.source.startswith("simulator(seed=2, profile=fast_rotation")
    np.testing.assert_allclose(np.diff(seq.time), 1.0 / rate)
    # every profile yields a valid 9-axis sequence whose units pass the ImuSequence heuristics
    # (the simulator skips them for speed: re-validate with check_units on)
    for p in sim.PROFILES:
        s = sim.simulate(p, 15.0, rate, seed=1)
        ImuSequence(s.name, s.source, s.time, s.gyro, s.accel, s.mag, s.quat, rate=rate, check_units=True)
        assert 20.0 < np.median(np.linalg.norm(s.mag, axis=1)) < 120.0
        assert abs(np.median(np.linalg.norm(s.accel, axis=1)) - GRAVITY) < 2.0


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="unknown profile"):
        sim.simulate("flying_carpet", 10.0, 100.0, seed=0)
    with pytest.raises(ValueError, match="axes"):
        sim.simulate("walking", 10.0, 100.0, seed=0, axes=7)
    with pytest.raises(TypeError, match="gyro_noise"):
        sim.simulate("walking", 10.0, 100.0, seed=0, gyro_noise=1.0)


# ----------------------------------------------------------------------------- splits


def _cfg():
    from omegaconf import OmegaConf
    return OmegaConf.load(CONF)


def test_load_split_from_yaml():
    cfg = _cfg()
    assert cfg.name == "simulated" and cfg.axes == 9
    tiny = {**_plain(cfg), "splits": {k: {**v, "duration": 12.0} for k, v in _plain(cfg)["splits"].items()}}
    train = sim.load_split(tiny, "train")
    val = sim.load_split(tiny, "val")
    test = sim.load_split(tiny, "test")
    trainval = sim.load_split(tiny, "trainval")
    every = sim.load_split(tiny, "all")
    assert [len(x) for x in (train, val, test)] == [8, 4, 6]
    names = [s.name for s in train + val + test]
    assert len(set(names)) == len(names)  # disjoint seeds
    assert [s.name for s in trainval] == [s.name for s in train + val]
    assert [s.name for s in every] == names
    assert {s.meta["profile"] for s in train} == {"walking", "slow_rotation", "fast_rotation", "drone"}
    assert {"walking"} <= {s.meta["profile"] for s in test}
    assert all(s.meta["environment"]["mag_disturbances_per_minute"] == 2.0 for s in test)
    # one device everywhere: the calibration a model learns on train transfers to test
    k_std = sim.SensorErrorModel().recording_k_std
    assert np.abs(train[0].meta["K_gyro"] - test[0].meta["K_gyro"]).max() < 8 * k_std
    assert sim.load_split({**tiny, "split": "val"})[0].name == val[0].name  # default from the config
    six = sim.load_split({**tiny, "axes": 6}, "val")
    assert all(s.mag is None for s in six)
    assert sim.list_recordings(tiny) == names


def test_default_split_is_small():
    """Training on the default config must fit in a few CPU minutes."""
    plan = sim.split_plan(_cfg(), "trainval")
    samples = sum(int(kw["duration"] * kw["rate"]) for kw in plan)
    assert samples <= 100_000


def test_split_config_errors():
    base = _plain(_cfg())
    bad = {**base, "splits": {**base["splits"], "val": {**base["splits"]["val"], "seed_offset": 3}}}
    with pytest.raises(ValueError, match="overlap"):
        sim.split_plan(bad, "train")
    bad = {**base, "splits": {**base["splits"], "test": {**base["splits"]["test"], "profiles": ["jogging"]}}}
    with pytest.raises(ValueError, match="jogging"):
        sim.split_plan(bad, "test")
    with pytest.raises(ValueError, match="split"):
        sim.split_plan(base, "validation")


def _plain(cfg):
    from omegaconf import OmegaConf
    return OmegaConf.to_container(cfg, resolve=True)


def test_envelope_clock_is_integral_of_envelope():
    from tcn_ahrs.datasets.simulate.motion import _Envelope

    env = _Envelope(np.array([5.0, 20.0]), np.array([15.0, 30.5]), ramp=2.0)
    t = np.arange(0.0, 40.0, 1e-3)
    e, e1, e2 = env(t)
    tau = env.clock(t)
    np.testing.assert_allclose(np.gradient(tau, t), e, atol=1e-6)
    np.testing.assert_allclose(np.gradient(e, t), e1, atol=1e-4)
    np.testing.assert_allclose(np.gradient(e1, t), e2, atol=1e-2)
    np.testing.assert_allclose(tau[-1], (15.0 - 5.0 - 2.0) + (30.5 - 20.0 - 2.0))
    assert e.min() == 0.0 and e.max() == 1.0
    np.testing.assert_array_equal(env.moving(t), (e > 0) | ((t > 5.0) & (t < 15.0)) | ((t > 20.0) & (t < 30.5)))
