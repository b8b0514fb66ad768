"""Tests of the classical filters (tcn_ahrs.filters) and their Estimator wrappers.

Synthetic recordings are built here from a known attitude trajectory (ENU, specific force,
field pointing north and down), so every test has an exact reference.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tcn_ahrs import so3
from tcn_ahrs.conventions import GRAVITY
from tcn_ahrs.estimators.base import Estimator
from tcn_ahrs.estimators.classical import ESEKF, ClosedLoopECF, Madgwick, Mahony, RobustESEKF
from tcn_ahrs.filters import chi2_threshold, ecf, eskf, madgwick, mahony, triad_quat
from tcn_ahrs.filters.common import magnetic_from_nav, nwu_from_enu_quat
from tcn_ahrs.sequence import ImuSequence

from synthetic_filters import MAG_NAV, simulate, wavy  # noqa: E402  (shared with test_tuning)
from tolerances import ANGLE_F64, DEG_F64, LIB_PARITY_F64, PARITY_F64, ROTATION_F64  # noqa: E402


def angle_err_deg(q_gt, q_est):
    d = so3.quat_mul(so3.quat_conj(torch.as_tensor(q_gt)), torch.as_tensor(q_est))
    return np.degrees(so3.quat_log(d).norm(dim=-1).numpy())


def heading_err_deg(q_gt, q_est):
    y = lambda q: so3.yaw(so3.quat_to_matrix(torch.as_tensor(q))).numpy()  # noqa: E731
    return np.degrees(np.abs(np.angle(np.exp(1j * (y(q_est) - y(q_gt))))))


def rotz(q, angle):
    """Rotate nav_from_body quaternions by ``angle`` about nav up (left multiplication)."""
    c = torch.tensor([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)], dtype=torch.float64)
    return so3.quat_mul(c, torch.as_tensor(q)).numpy()


# ----------------------------------------------------------------------------- ahrs parity


def _pos(q):
    return q * np.sign(q[:, :1])


@pytest.fixture(scope="module")
def parity_data():
    seq = simulate(duration=16.0, rate=100.0, omega=wavy, bias=(0.02, -0.01, 0.015), seed=3)
    q0 = np.array([0.9, 0.1, -0.2, 0.3])
    return seq, q0 / np.linalg.norm(q0)


@pytest.mark.parametrize("axes", [6, 9])
def test_madgwick_matches_ahrs(parity_data, axes):
    ahrs = pytest.importorskip("ahrs")
    seq, q0 = parity_data
    mag = seq.mag if axes == 9 else None
    c = nwu_from_enu_quat()
    q0_nwu = so3.quat_mul(c, torch.as_tensor(q0)).numpy()
    ref = ahrs.filters.Madgwick(gyr=seq.gyro, acc=seq.accel, mag=mag, frequency=seq.rate, q0=q0_nwu, gain=0.1).Q
    # ahrs' 9-axis Madgwick ignores q0 and starts from ecompass(); start ours from its Q[0].
    ref_enu = so3.quat_mul(so3.quat_conj(c), torch.as_tensor(ref)).numpy()
    ours = madgwick(seq.gyro, seq.accel, np.full(len(seq), 1.0 / seq.rate), ref_enu[0], mag=mag, beta=0.1)["quat"]
    assert np.abs(_pos(ours.numpy()) - _pos(ref_enu)).max() < LIB_PARITY_F64


@pytest.mark.parametrize("axes", [6, 9])
def test_mahony_matches_ahrs(parity_data, axes):
    ahrs = pytest.importorskip("ahrs")
    seq, q0 = parity_data
    mag = seq.mag if axes == 9 else None
    ref = ahrs.filters.Mahony(gyr=seq.gyro, acc=seq.accel, mag=mag, frequency=seq.rate, q0=q0, k_P=1.3, k_I=0.4)
    ours = mahony(seq.gyro, seq.accel, np.full(len(seq), 1.0 / seq.rate), q0, mag=mag, k_p=1.3, k_i=0.4, compat=True)
    assert np.abs(_pos(ours["quat"].numpy()) - _pos(ref.Q)).max() < LIB_PARITY_F64
    assert np.abs(ours["gyro_bias"][-1].numpy() - ref.b).max() < ANGLE_F64
    # the exponential-map integration differs from ahrs' first-order step only at O(dt^2)
    exact = mahony(seq.gyro, seq.accel, np.full(len(seq), 1.0 / seq.rate), q0, mag=mag, k_p=1.3, k_i=0.4)
    assert angle_err_deg(ref.Q, exact["quat"].numpy()).max() < 0.01


# ----------------------------------------------------------------------- conventions / signs


def test_triad_recovers_static_attitude():
    q_true = so3.quat_exp(torch.tensor([0.3, -0.5, 2.0], dtype=torch.float64))
    r = so3.quat_to_matrix(q_true)
    a = r.T @ torch.tensor([0.0, 0.0, GRAVITY], dtype=torch.float64)
    m = r.T @ torch.as_tensor(MAG_NAV)
    assert angle_err_deg(q_true[None], triad_quat(a, m)[None]).max() < DEG_F64
    # accelerometer only: tilt right, heading arbitrary
    q_a = triad_quat(a)
    assert torch.allclose(so3.quat_rotate(q_a, a / a.norm()), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


def test_magnetic_from_nav_aligns_field_north():
    q0 = so3.quat_exp(torch.tensor([0.2, 0.1, 0.9], dtype=torch.float64))
    field_nav = torch.tensor([12.0, 15.0, -40.0], dtype=torch.float64)  # declination ~39 deg
    m0 = so3.quat_rotate(so3.quat_conj(q0), field_nav)
    c = magnetic_from_nav(q0, m0)
    v = so3.quat_rotate(c, field_nav)
    assert abs(float(v[0])) < ROTATION_F64 and float(v[1]) > 0 and abs(float(v[2]) + 40.0) < ROTATION_F64


def test_chi2_threshold_from_alpha():
    # the ARCKF paper quotes 6.2 for dof 1 at alpha = 0.001; the 0.999 quantile is 10.83
    assert abs(chi2_threshold(0.001, 1) - 10.828) < 1e-3
    assert abs(chi2_threshold(0.001, 3) - 16.266) < 1e-3


def test_ecf_rejection_rules_eq7():
    seq = simulate(duration=2.0, rate=50.0, seed=1)
    accel = seq.accel.copy()
    accel[20:30] *= 1.3  # | |a| - g | ~ 2.9 m/s^2 > a_min
    mag = seq.mag.copy()
    mag[40:50] *= 2.0  # |m| ~ 90 uT > m_max
    out = ecf(seq.gyro, accel, seq.dt, seq.quat[0], mag=mag, a_min=1.0, m_min=20.0, m_max=70.0, t_init=1.0)
    acc_used, mag_used = out["acc_used"].numpy(), out["mag_used"].numpy()
    assert not acc_used[20:30].any() and acc_used[:20].all() and acc_used[30:].all()
    assert not mag_used[20:30].any() and not mag_used[40:50].any() and mag_used[50:].all()
    g = out["gain"].numpy()  # Eq. 8: K_init at t=0, K_norm after t_init
    assert abs(g[0] - 10.0) < 1e-12 and abs(g[-1] - 0.5) < 1e-12


@pytest.mark.parametrize("use_mag", [True, False])
def test_ecf_converges_from_wrong_initial_attitude(use_mag):
    q_start = so3.quat_exp(torch.tensor([0.4, -0.2, 0.7], dtype=torch.float64)).numpy()
    seq = simulate(duration=10.0, rate=50.0, seed=2, q_start=q_start)
    wrong = so3.quat_mul(torch.as_tensor(q_start), so3.quat_exp(torch.tensor([1.0, 0.6, -1.2], dtype=torch.float64)))
    est = ClosedLoopECF(axes=9 if use_mag else 6, heading_ref="north")
    out = est.run(seq, wrong.numpy())
    assert angle_err_deg(seq.quat[:1], out.quat[:1]).max() > 60
    if use_mag:
        assert angle_err_deg(seq.quat[-100:], out.quat[-100:]).max() < 1.0
    else:  # heading is unobservable: check the tilt (gravity direction in body)
        up_est = so3.quat_to_matrix(torch.as_tensor(out.quat[-100:]))[:, 2, :]
        up_true = so3.quat_to_matrix(torch.as_tensor(seq.quat[-100:]))[:, 2, :]
        assert np.degrees(float(torch.acos((up_est * up_true).sum(-1).clamp(max=1.0)).max())) < 1.0


@pytest.mark.parametrize("cls", [ClosedLoopECF, Mahony, Madgwick, ESEKF, RobustESEKF])
def test_heading_converges_to_magnetic_north(cls):
    """Sign check of every magnetometer correction: 40 deg heading error must shrink."""
    seq = simulate(duration=40.0, rate=25.0, omega=lambda t: 0.3 * wavy(t), seed=4)
    wrong = rotz(seq.quat[0], math.radians(40.0))
    kw = {"k_p": 2.0} if cls is Mahony else {"beta": 0.1} if cls is Madgwick else {}
    out = cls(heading_ref="north", **kw).run(seq, wrong)
    e = heading_err_deg(seq.quat, out.quat)
    assert e[0] > 39 and e[-25:].max() < 3.0, (e[0], e[-25:].max())


# ------------------------------------------------------------------------------ gyro bias


@pytest.mark.parametrize("cls", [Mahony, ESEKF])
def test_static_gyro_bias_is_estimated(cls):
    bias = np.array([0.02, -0.01, 0.015])
    q_start = so3.quat_exp(torch.tensor([0.3, 0.2, -1.0], dtype=torch.float64)).numpy()
    seq = simulate(duration=50.0, rate=25.0, bias=bias, seed=5, q_start=q_start)
    out = cls().run(seq, seq.quat[0])
    b = out.signals["gyro_bias"]
    assert b.shape == (len(seq), 3)
    assert np.abs(b[-125:].mean(0) - bias).max() < 1.5e-3, b[-1]
    assert angle_err_deg(seq.quat[-25:], out.quat[-25:]).max() < 1.0


# ------------------------------------------------------------------- robust gating vs plain


@pytest.fixture(scope="module")
def disturbed():
    acc_win, mag_win = (10.0, 12.0), (20.0, 23.0)
    ext = lambda t: np.where(((t >= acc_win[0]) & (t < acc_win[1]))[:, None], [3.0, 0.0, 0.0], 0.0)  # noqa: E731
    dist = lambda t: np.where(((t >= mag_win[0]) & (t < mag_win[1]))[:, None], [30.0, 0.0, 0.0], 0.0)  # noqa: E731
    seq = simulate(duration=30.0, rate=50.0, omega=lambda t: 0.2 * wavy(t), acc_ext_nav=ext, mag_dist_nav=dist,
                   bias=(0.003, -0.002, 0.002), seed=6)
    # noise densities matched to the simulated sensor (accel 0.05 m/s^2 and ~0.8 deg heading per sample at 50 Hz)
    kw = dict(accel_noise=0.05, mag_noise=0.01)
    plain = ESEKF(**kw).run(seq, seq.quat[0])
    robust = RobustESEKF(**kw).run(seq, seq.quat[0])
    return seq, acc_win, mag_win, plain, robust


def test_robust_gating_fires_in_disturbance_windows(disturbed):
    seq, acc_win, mag_win, _, robust = disturbed
    t = seq.time
    in_acc = (t >= acc_win[0]) & (t < acc_win[1])
    in_mag = (t >= mag_win[0]) & (t < mag_win[1])
    s = robust.signals
    assert s["acc_gated"].shape == (len(seq),) and s["acc_gated"].dtype == bool
    assert s["acc_gated"][in_acc].mean() > 0.9
    assert s["acc_gated"][~in_acc].mean() < 0.01
    assert s["mag_gated"][in_mag].mean() > 0.9
    assert s["mag_gated"][~in_mag].mean() < 0.01
    assert s["mahalanobis_acc"][in_acc].min() > chi2_threshold(0.001, 3)
    assert np.all(s["fading"] >= 1.0)


def test_robust_beats_plain_under_disturbance(disturbed):
    seq, acc_win, mag_win, plain, robust = disturbed
    e_plain = angle_err_deg(seq.quat, plain.quat)
    e_robust = angle_err_deg(seq.quat, robust.quat)
    t = seq.time
    for (a, b) in (acc_win, mag_win):
        w = (t >= a) & (t < b + 2.0)
        # Eq. 41 down-weights (R * gamma/chi2) rather than discards, and a disturbance below the
        # gate still pulls: the robust error is smaller, not zero.
        assert e_robust[w].max() < 0.6 * e_plain[w].max(), (a, e_robust[w].max(), e_plain[w].max())
    assert np.sqrt(np.mean(e_robust ** 2)) < 0.6 * np.sqrt(np.mean(e_plain ** 2))


# -------------------------------------------------------------------------------- batching


def _batch_inputs():
    seqs = [simulate(duration=2.0, rate=50.0, omega=wavy, bias=(0.01, 0.0, -0.01), seed=s) for s in (7, 8)]
    g = torch.as_tensor(np.stack([s.gyro for s in seqs]))[:, None]  # (R=2, 1, N, 3)
    a = torch.as_tensor(np.stack([s.accel for s in seqs]))[:, None]
    m = torch.as_tensor(np.stack([s.mag for s in seqs]))[:, None]
    dt = torch.as_tensor(np.stack([s.dt for s in seqs]))[:, None]
    q0 = torch.as_tensor(np.stack([s.quat[0] for s in seqs]))[:, None]
    return g, a, m, dt, q0


@pytest.mark.parametrize("name", ["ecf", "mahony", "madgwick", "eskf", "robust_eskf"])
def test_batched_equals_one_by_one(name):
    g, a, m, dt, q0 = _batch_inputs()
    fn, pname, values, kw = {
        "ecf": (ecf, "k_norm", [0.1, 0.5, 2.0], {}),
        "mahony": (mahony, "k_i", [0.0, 0.1, 0.5], {}),
        "madgwick": (madgwick, "beta", [0.01, 0.05, 0.2], {}),
        "eskf": (eskf, "accel_noise", [0.01, 0.05, 0.2], {}),
        "robust_eskf": (eskf, "mag_noise", [0.005, 0.05, 0.2], {"robust": True}),
    }[name]
    p = torch.tensor(values, dtype=torch.float64)  # (P,) -> batch (2, 3)
    batched = fn(g, a, dt, q0, mag=m, **{pname: p}, **kw)
    assert batched["quat"].shape == (2, 3, g.shape[2], 4)
    for i in range(2):
        for j in range(3):
            single = fn(g[i, 0], a[i, 0], dt[i, 0], q0[i, 0], mag=m[i, 0], **{pname: values[j]}, **kw)
            for k, v in single.items():
                assert torch.allclose(batched[k][i, j].to(v.dtype), v, atol=PARITY_F64[1]), (k, i, j)


# ----------------------------------------------------------------------- Estimator interface


@pytest.mark.parametrize("cls", [ClosedLoopECF, Mahony, Madgwick, ESEKF, RobustESEKF])
def test_estimator_interface_and_heading_reference(cls):
    seq = simulate(duration=8.0, rate=50.0, omega=lambda t: 0.5 * wavy(t), seed=9)
    # ground truth in a frame whose +y is 50 deg away from magnetic north (e.g. motion capture)
    q_gt = rotz(seq.quat, math.radians(50.0))
    seq_gt = ImuSequence(name=seq.name, source=seq.source, time=seq.time, gyro=seq.gyro, accel=seq.accel,
                         mag=seq.mag, quat=q_gt, rate=seq.rate)
    est = cls()
    assert isinstance(est, Estimator) and isinstance(est.name, str)
    out = est.run(seq_gt, q_gt[0])
    assert out.quat.shape == (len(seq), 4)
    assert np.allclose(np.linalg.norm(out.quat, axis=1), 1.0)
    assert all(v.shape[0] == len(seq) for v in out.signals.values())
    assert angle_err_deg(q_gt, out.quat).max() < 3.0  # heading_ref="init" keeps the GT frame
    north = cls(heading_ref="north").run(seq_gt, q_gt[0])
    assert heading_err_deg(q_gt, north.quat)[-1] > 5.0  # ... while "north" pulls toward magnetic north
    six = cls(axes=6).run(seq_gt, None)  # TRIAD init from the accelerometer only
    assert six.quat.shape == (len(seq), 4) and np.isfinite(six.quat).all()


def test_run_params_rejects_unknown_parameter():
    seq = simulate(duration=1.0, rate=50.0)
    with pytest.raises(ValueError, match="unknown parameter"):
        Madgwick().run_params(seq, {"gain": 0.1})
