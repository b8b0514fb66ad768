"""The odometry ES-EKF (tcn_ahrs.nav.odometry) and its simulator (tcn_ahrs.nav.diff_drive)."""
import numpy as np
import pytest
import torch

from tcn_ahrs import so3
from tcn_ahrs.nav.diff_drive import Sensors, simulate_drive
from tcn_ahrs.nav.odometry import OdometryNoise, odometry_eskf, predict, wheel_speeds, wheel_velocity

CLEAN = Sensors(accel_noise=0.0, gyro_noise=0.0, mag_noise=0.0, encoder_tick=0.0)


def _run(sim, **kw):
    T = lambda k: torch.as_tensor(sim[k])[None]  # noqa: E731
    n = len(sim["time"])
    dt = torch.full((1, n), float(sim["time"][1] - sim["time"][0]), dtype=torch.float64)
    out = odometry_eskf(T("acc"), T("gyro"), dt, T("v_left"), T("v_right"), T("mag_quat"),
                        T("pos")[:, 0], T("vel")[:, 0], T("quat")[:, 0], **kw)
    return out, np.linalg.norm(out["pos"][0].numpy() - sim["pos"], axis=1)


def test_wheel_speeds_and_velocity_are_inverse():
    v, w = torch.tensor([0.5, 0.3, 0.0], dtype=torch.float64), torch.tensor([0.0, 0.5, -1.0], dtype=torch.float64)
    vl, vr = wheel_speeds(v, w, 0.262)
    np.testing.assert_allclose(((vr - vl) / 0.262).numpy(), w.numpy(), atol=1e-12)
    heading = torch.tensor([0.0, np.pi / 2, 1.0], dtype=torch.float64)
    vel = wheel_velocity(vl, vr, heading)
    np.testing.assert_allclose(vel.numpy(), (v[:, None] * torch.stack([heading.cos(), heading.sin()], -1)).numpy(),
                               atol=1e-12)


def test_prediction_reproduces_a_noise_free_drive():
    """The simulator integrates in the filter's discretisation (Eq. 6): dead reckoning on the
    noise-free IMU follows the true trajectory to round-off."""
    sim = simulate_drive(3, rate=20.0, length=40.0, sensors=CLEAN)
    p = torch.as_tensor(sim["pos"][:1])
    v = torch.as_tensor(sim["vel"][:1])
    rot = so3.quat_to_matrix(torch.as_tensor(sim["quat"][:1]))
    P = torch.eye(9, dtype=torch.float64)[None] * 0.01
    dt = torch.full((1,), 0.05, dtype=torch.float64)
    worst = 0.0
    for k in range(1, len(sim["time"])):
        p, v, rot, P = predict(p, v, rot, P, torch.as_tensor(sim["acc"][k:k + 1]),
                               torch.as_tensor(sim["gyro"][k:k + 1]), dt, OdometryNoise())
        worst = max(worst, float(np.abs(p[0].numpy() - sim["pos"][k]).max()))
    assert worst < 1e-8
    assert torch.allclose(P, P.transpose(-1, -2)) and bool((torch.linalg.eigvalsh(P) > 0).all())


@pytest.mark.slow
def test_filter_bounds_the_drift_that_dead_reckoning_has():
    """Noisy IMU (the paper's white noise, no bias: its filter has no bias states and no vertical
    measurement), quantised encoders, magnetic anomalies: the ES-EKF stays within metres
    of the truth over 60 m while IMU-only propagation (every correction off) is far off; with the
    encoders dropped out the attitude rows still update and the output stays finite."""
    sim = simulate_drive(5, rate=20.0, length=60.0,
                         sensors=Sensors(anomalies_per_100m=2.0))
    n = len(sim["time"])
    out, err = _run(sim)
    assert np.sqrt(np.mean(err ** 2)) < 2.0
    off = torch.zeros(1, n, dtype=torch.bool)
    _, err_dr = _run(sim, encoders_ok=off, mag_ok=off)
    assert err_dr.max() > 20 * err.max()
    out_att, err_att = _run(sim, encoders_ok=off)
    assert np.isfinite(err_att).all() and torch.isfinite(out_att["pos_std"]).all()
    # without velocity updates the position uncertainty grows, with them it stays small
    assert float(out_att["pos_std"][0, -1].norm()) > float(out["pos_std"][0, -1].norm())


# ----------------------------------------------------------------------------- analytic cases


def _straight_line(n=400, rate=20.0, speed=0.5, yaw=0.7):
    """Constant speed along a fixed heading, perfect sensors (accelerometer: gravity only)."""
    t = np.arange(n) / rate
    d = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    rot = so3.exp(torch.tensor([0.0, 0.0, yaw], dtype=torch.float64)).numpy()
    quat = so3.matrix_to_quat(torch.as_tensor(rot)).numpy()
    return {"time": t, "pos": speed * t[:, None] * d, "vel": np.tile(speed * d, (n, 1)),
            "quat": np.tile(quat, (n, 1)), "acc": np.tile(rot.T @ np.array([0.0, 0.0, 9.81]), (n, 1)),
            "gyro": np.zeros((n, 3)), "v_left": np.full(n, speed), "v_right": np.full(n, speed),
            "mag_quat": np.tile(quat, (n, 1))}


def _baseline(kind, sim, **kw):
    from tcn_ahrs.nav.odometry_baselines import odometry_filter

    dt = np.diff(sim["time"], prepend=sim["time"][0])
    return odometry_filter(kind, sim["acc"], sim["gyro"], dt, sim["v_left"], sim["v_right"], sim["mag_quat"],
                           sim["pos"][0], sim["vel"][0], sim["quat"][0], **kw)


def test_straight_line_with_perfect_sensors_has_zero_error():
    pytest.importorskip("filterpy")
    sim = _straight_line()
    out, err = _run(sim)
    assert err.max() < 1e-9
    assert np.abs(_baseline("ekf", sim)["pos"] - sim["pos"]).max() < 1e-9
    # the UKF propagates the attitude's uncertainty into the mean: with P_0 = 0.01 rad^2 (the
    # paper's) the mean specific force shortens by g sigma^2 (a 0.1 m/s^2 apparent vertical
    # acceleration); with a certain start and no process noise it, too, is exact
    certain = OdometryNoise(init=1e-14, accel=1e-9, gyro=1e-9)
    assert np.abs(_baseline("ukf", sim, noise=certain)["pos"] - sim["pos"]).max() < 1e-6  # P ~ 0: round-off
    assert np.abs(_baseline("ukf", sim)["pos"][:, 2]).max() > 0.01


def test_known_bias_is_recovered_with_the_bias_states():
    """Beyond the paper: with bias states and the zero-vertical-velocity row, a constant gyro
    bias and the vertical accelerometer bias are estimated (the horizontal accelerometer bias is
    not observable: the magnetometer attitude's tilt comes from the same accelerometer)."""
    sim = simulate_drive(5, rate=20.0, length=60.0, sensors=Sensors(accel_bias=0.02, gyro_bias=0.002))
    noise = OdometryNoise(estimate_biases=True, vel_z=0.01)
    out, err = _run(sim, noise=noise)
    bias = out["bias"][0, -1].numpy()
    np.testing.assert_allclose(bias[3:5], sim["gyro_bias"][:2], atol=2e-4)
    assert abs(bias[2] - sim["accel_bias"][2]) < 0.1 * abs(sim["accel_bias"][2])
    _, err_paper = _run(sim)  # the paper's filter integrates the vertical bias twice
    assert err.max() < 1.0 < err_paper.max()


# ----------------------------------------------------------------------------- EKF / UKF baselines


def test_euler_helpers_match_scipy_and_the_jacobian_matches_finite_differences():
    from scipy.spatial.transform import Rotation

    from tcn_ahrs.nav.odometry_baselines import euler_matrix, from_euler, jacobian, propagate, to_euler

    rng = np.random.default_rng(0)
    e = np.array([0.2, -0.4, 2.5])
    R, dR = euler_matrix(e)
    np.testing.assert_allclose(R, Rotation.from_euler("ZYX", e[::-1]).as_matrix(), atol=1e-12)
    q = from_euler(e[None])
    np.testing.assert_allclose(so3.quat_to_matrix(torch.as_tensor(q)).numpy()[0], R, atol=1e-12)
    np.testing.assert_allclose(to_euler(q)[0], e, atol=1e-12)
    x = np.concatenate([rng.normal(size=6), e])
    acc, gyro, dt = np.array([0.3, -0.2, 9.7]), np.array([0.1, -0.3, 0.5]), 0.05
    F = jacobian(x, acc, gyro, dt)
    h = 1e-6
    num = np.stack([(propagate(x + h * np.eye(9)[j], acc, gyro, dt) - propagate(x - h * np.eye(9)[j], acc, gyro, dt))
                    / (2 * h) for j in range(9)], -1)
    np.testing.assert_allclose(F, num, atol=1e-7)
    for j in range(3):  # dR: the partial derivatives of R
        de = np.eye(3)[j] * h
        np.testing.assert_allclose(dR[..., j], (euler_matrix(e + de)[0] - euler_matrix(e - de)[0]) / (2 * h), atol=1e-8)


def test_ekf_and_ukf_agree_with_the_eskf_on_the_same_run():
    """Three formulations of one model (filterpy's EKF and UKF over [p, v, Euler angles], the
    error-state filter over [dp, dv, dtheta]): on the same noisy drive their horizontal errors
    agree to a few per cent."""
    pytest.importorskip("filterpy")
    sim = simulate_drive(2, rate=20.0, length=20.0)
    out, _ = _run(sim)
    h = {"eskf": np.sqrt(np.mean(np.sum((out["pos"][0, :, :2].numpy() - sim["pos"][:, :2]) ** 2, 1)))}
    for kind in ("ekf", "ukf"):
        o = _baseline(kind, sim)
        h[kind] = np.sqrt(np.mean(np.sum((o["pos"][:, :2] - sim["pos"][:, :2]) ** 2, 1)))
    assert h["eskf"] < 0.1
    assert abs(h["ekf"] - h["eskf"]) < 0.05 * h["eskf"] and abs(h["ukf"] - h["eskf"]) < 0.05 * h["eskf"], h


def test_dropouts_only_predict_and_the_covariance_grows():
    """Encoders and magnetometer both off for 10 s: the ES-EKF is pure prediction there (equal to
    predict() from the state at the window's start), and every filter's position std grows."""
    pytest.importorskip("filterpy")
    sim = simulate_drive(4, rate=20.0, length=30.0)
    n = len(sim["time"])
    ok = np.ones(n, bool)
    a, b = 400, 600
    ok[a:b] = False
    okt = torch.as_tensor(ok)[None]
    out, _ = _run(sim, encoders_ok=okt, mag_ok=okt)
    std = out["pos_std"][0, a - 1:b, :2].norm(dim=-1).numpy()
    assert np.all(np.diff(std) > 0)
    # the state at the window's start, then prediction only
    p, v = out["pos"][:, a - 1].clone(), out["vel"][:, a - 1].clone()
    rot = so3.quat_to_matrix(out["quat"][:, a - 1])
    P = torch.eye(9, dtype=torch.float64)[None]
    dt = torch.full((1,), 0.05, dtype=torch.float64)
    for k in range(a, b):
        p, v, rot, P = predict(p, v, rot, P, torch.as_tensor(sim["acc"][k:k + 1]), torch.as_tensor(sim["gyro"][k:k + 1]),
                               dt, OdometryNoise())
    np.testing.assert_allclose(out["pos"][0, b - 1].numpy(), p[0].numpy(), atol=1e-9)
    for kind in ("ekf", "ukf"):
        o = _baseline(kind, sim, encoders_ok=ok, mag_ok=ok)
        s = np.linalg.norm(o["pos_std"][a - 1:b, :2], axis=1)
        assert np.all(np.diff(s) > 0), kind


@pytest.mark.slow
def test_magnetometer_gate_rejects_anomalies_and_helps():
    sim = simulate_drive(5, rate=20.0, length=60.0, sensors=Sensors(anomalies_per_100m=4.0, anomaly_ut=20.0))
    out, err = _run(sim, noise=OdometryNoise(mag_gate_alpha=1e-3))
    _, err_plain = _run(sim)
    rej = out["mag_rejected"][0].numpy()
    # the TRIAD attitude's error: large inside anomalies
    q_err = so3.log(so3.quat_to_matrix(torch.as_tensor(sim["quat"])).transpose(-1, -2)
                    @ so3.quat_to_matrix(torch.as_tensor(sim["mag_quat"]))).norm(dim=-1).numpy()
    disturbed = q_err > np.radians(10.0)
    assert disturbed.sum() > 20
    assert rej[disturbed].mean() > 0.9
    assert np.sqrt(np.mean(err ** 2)) < np.sqrt(np.mean(err_plain ** 2))


def test_reproduce_prints_table2_with_the_papers_numbers(tmp_path, capsys):
    pytest.importorskip("filterpy")
    pytest.importorskip("evo")
    from tcn_ahrs.reproduce import papers, run

    assert "es_ekf_odometry" in papers()
    cfg = {"name": "es_ekf_odometry", "seeds": 2, "first_seed": 0, "robustness_seeds": 1,
           "scenarios": ["paper", "dropouts"], "rate": 10.0, "length": 15.0, "sensors": {}, "slip": 0.3,
           "slip_fraction": 0.05, "anomalies_per_100m": 3.0, "anomaly_ut": 20.0, "dropout_windows": 1,
           "dropout_min_s": 5.0, "dropout_max_s": 8.0, "workers": 1, "plots": True}
    res = run("es_ekf_odometry", cfg, tmp_path)
    printed = capsys.readouterr().out
    sc = res["scenarios"]["paper"]
    # the table sets each computed statistic beside the paper's (Table 2), not the paper's alone
    from tcn_ahrs.reproduce.es_ekf_odometry import PAPER_TABLE2

    for f, stats in PAPER_TABLE2.items():
        for k, paper in stats.items():
            s = sc["summary"][f][k]
            assert f"{paper:.3f} | {s['mean']:.3f} ± {s['std']:.3f}" in printed, (f, k)
    # the paper's finding: the error-state EKF is at least as good as the UKF on the same runs
    assert sc["summary"]["ES-EKF"]["rmse"]["mean"] <= sc["summary"]["UKF"]["rmse"]["mean"]
    assert sc["seeds"] == [0, 1] and set(sc["summary"]) == {"ES-EKF", "EKF", "UKF", "ES-EKF robust"}
    assert (tmp_path / "trajectories" / "paper" / "seed1" / "UKF.txt").is_file()
    assert (tmp_path / "plots" / "dropouts.png").is_file() and (tmp_path / "results.md").is_file()
    # evo's RMSE equals the RMS of the position errors of the TUM files written
    gt = np.loadtxt(tmp_path / "trajectories" / "paper" / "seed0" / "groundtruth.txt")
    es = np.loadtxt(tmp_path / "trajectories" / "paper" / "seed0" / "ES-EKF.txt")
    rms = np.sqrt(np.mean(np.sum((gt[:, 1:4] - es[:, 1:4]) ** 2, 1)))
    assert abs(res["scenarios"]["paper"]["runs"]["ES-EKF"][0]["rmse"] - rms) < 1e-6


def test_vectorised_unscented_transform_equals_filterpys():
    """The UKF runs filterpy's UnscentedKalmanFilter with its per-sigma-point loops vectorised;
    the transform and the angle-aware residuals give filterpy's own results to 1e-12."""
    fk = pytest.importorskip("filterpy.kalman")
    from tcn_ahrs.nav.odometry_baselines import ANGLES, _mean_angles, _residual_x, unscented_transform

    rng = np.random.default_rng(3)
    pts = fk.MerweScaledSigmaPoints(9, alpha=0.3, beta=2.0, kappa=0.0, subtract=_residual_x)
    x = np.concatenate([rng.normal(size=6), [0.1, -0.2, 3.1]])  # yaw near the +-pi wrap
    A = rng.normal(size=(9, 9)) * 0.1
    sig = pts.sigma_points(x, A @ A.T + 0.01 * np.eye(9))
    sig[:, ANGLES] = (sig[:, ANGLES] + np.pi) % (2 * np.pi) - np.pi
    mean_fn = lambda s, w: _mean_angles(s, w, ANGLES)  # noqa: E731
    Q = np.eye(9) * 1e-3
    ref = fk.unscented_transform(sig, pts.Wm, pts.Wc, Q, mean_fn, _residual_x)
    ours = unscented_transform(sig, pts.Wm, pts.Wc, Q, mean_fn, _residual_x)
    np.testing.assert_allclose(ours[0], ref[0], atol=1e-12)
    np.testing.assert_allclose(ours[1], ref[1], atol=1e-12)
