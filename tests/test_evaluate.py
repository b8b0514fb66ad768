"""The evaluation runner on synthetic recordings with exact ground truth (scipy-built)."""
import io
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tcn_ahrs.conventions import quat_xyzw_to_wxyz
from tcn_ahrs.estimators.base import Estimator, EstimatorOutput
from tcn_ahrs.estimators.raw import RawIntegration
from tcn_ahrs.evaluate import evaluate, load_results, markdown_table, print_table, safe_name
from tcn_ahrs.sequence import ImuSequence

RATE = 100.0


def constant_rate_sequence(name, omega, n=600, q0=None, invalid_first=0, groups=None, mag=False):
    """Body rate ``omega`` (rad/s) held constant; ground truth R_k = R_0 exp(omega t_k) exactly."""
    t = 10.0 + np.arange(n) / RATE
    r0 = Rotation.from_quat(q0) if q0 is not None else Rotation.identity()
    gt = r0 * Rotation.from_rotvec(np.outer(t - t[0], omega))
    quat = quat_xyzw_to_wxyz(gt.as_quat())
    valid = np.ones(n, dtype=bool)
    valid[:invalid_first] = False
    quat[~valid] = np.nan
    acc = gt.inv().apply([0.0, 0.0, 9.81])
    m = gt.inv().apply([0.0, 20.0, -40.0]) if mag else None
    gyro = np.tile(omega, (n, 1))
    return ImuSequence(name=name, source=f"synthetic:{name}", time=t, gyro=gyro, accel=acc, mag=m,
                       quat=quat, quat_valid=valid, rate=RATE, meta={"groups": groups or []},
                       check_units=False)


class BiasedGyro:
    """Raw integration of gyro + a constant bias (a known, growing error)."""

    def __init__(self, bias):
        self.name = "Biased"
        self.bias = np.asarray(bias, dtype=float)
        self._raw = RawIntegration()

    def run(self, seq, init_quat=None, init_index=0):
        from dataclasses import replace
        return self._raw.run(replace(seq, gyro=seq.gyro + self.bias, meta={}), init_quat)


class ConstantBodyOffset:
    """Ground truth times a constant body-frame rotation of ``deg`` about x, plus a signal."""

    name = "Offset 2deg"

    def run(self, seq, init_quat=None, init_index=0):
        gt = np.where(np.isfinite(seq.quat), seq.quat, [1.0, 0, 0, 0])
        r = Rotation.from_quat(np.concatenate([gt[:, 1:], gt[:, :1]], 1)) * Rotation.from_euler("x", 2.0, degrees=True)
        q = quat_xyzw_to_wxyz(r.as_quat())
        return EstimatorOutput(quat=q, signals={"gyro_correction": np.full((len(seq), 3), 0.01)})


@pytest.fixture
def sequences():
    s1 = constant_rate_sequence("spin_z", np.array([0.0, 0.0, 0.8]), groups=["all", "yaw_only"])
    s2 = constant_rate_sequence("tumble", np.array([0.3, -0.5, 0.4]), n=500,
                                q0=Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_quat(),
                                invalid_first=25, groups=["all"])
    return [s1, s2]


def test_raw_integration_is_exact_and_files_are_written(tmp_path, sequences):
    raw = RawIntegration()
    assert isinstance(raw, Estimator)
    res = evaluate([raw, ConstantBodyOffset()], sequences, out_dir=tmp_path, dataset="synthetic")
    rows = res["methods"]["Raw IMU"]["recordings"]
    assert [r["name"] for r in rows] == ["spin_z", "tumble"]
    # spin_z starts with valid ground truth: exact under the yardstick; tumble turns before its
    # ground truth starts (real recordings rest there) — exact once aligned at its first sample
    assert rows[0]["aae_deg"] < 1e-6 and rows[0]["aye_deg"] < 1e-6
    first = evaluate([raw], sequences, align="first")["methods"]["Raw IMU"]["recordings"]
    assert all(r["aae_deg"] < 1e-6 and r["aye_deg"] < 1e-6 for r in first)
    assert rows[1]["n_scored"] == 475 - 2 * RATE  # the yardstick's 2 s of settling are not scored
    assert first[1]["n_scored"] == 475
    assert "total_deg" not in rows[0]  # 6-axis data: no BROAD errors
    # known constant body offset: AAE = 2 deg without alignment; with alignment it stays nonzero
    off = evaluate([ConstantBodyOffset()], sequences, align=False)["methods"]["Offset 2deg"]
    assert off["mean"]["aae_deg"] == pytest.approx(2.0, abs=1e-9)

    # results.json is exactly the returned dict
    loaded = load_results(tmp_path)
    assert loaded == json.loads(json.dumps(res))
    assert loaded["dataset"] == "synthetic"
    assert loaded["methods"]["Raw IMU"]["groups"]["all"]["n_recordings"] == 2
    assert loaded["methods"]["Raw IMU"]["groups"]["yaw_only"]["n_recordings"] == 1

    md = (tmp_path / "results.md").read_text()
    names = " | ".join(s.name for s in sequences)
    for metric in ("AAE", "AYE", "AHE"):  # one table per metric: methods in rows, recordings in columns
        assert f"| {metric} (deg) | {names} | Average |" in md
    rows = [line for line in md.splitlines() if line.startswith("| Raw IMU |") or line.startswith("| Offset 2deg |")]
    assert len(rows) >= 6 and all(line.count("|") == len(sequences) + 3 for line in rows[:6])
    assert "tumble" in md and "## Group averages" in md

    for m in ("Raw IMU", "Offset 2deg"):
        for s in sequences:
            png = tmp_path / "plots" / safe_name(m) / f"{s.name}.png"
            assert png.stat().st_size > 1000 and png.read_bytes()[:4] == b"\x89PNG"

    # TUM: one line per sample (after the '#' header), t x y z qx qy qz qw, positions zero
    s = sequences[1]
    lines = (tmp_path / "trajectories" / "Raw_IMU" / "tumble.txt").read_text().splitlines()
    assert lines[0].startswith("#")
    data = np.loadtxt(lines[1:])
    assert data.shape == (len(s), 8)
    np.testing.assert_allclose(data[:, 0], s.time, atol=1e-9)
    assert np.all(data[:, 1:4] == 0)
    gt_lines = (tmp_path / "trajectories" / "groundtruth" / "tumble.txt").read_text().splitlines()
    gt = np.loadtxt([l for l in gt_lines if not l.startswith("#")])
    assert gt.shape == (475, 8)
    np.testing.assert_allclose(gt[:, 4:], np.concatenate([s.quat[25:, 1:], s.quat[25:, :1]], 1), atol=1e-8)


def test_known_bias_gives_analytic_aae(sequences):
    """Yaw-only motion + z gyro bias b: the heading error is e_k = b (t_k - t_k0) exactly. Aligned
    at k0 it is scored as it is; under the yardstick the first 2 s are not scored and the circular
    mean of e over the rest is removed (heading alignment), which leaves the spread about it."""
    b = np.radians(0.5)
    seq = sequences[0]
    e = b * (seq.time - seq.time[0])
    first = evaluate([BiasedGyro([0.0, 0.0, b])], [seq], align="first")["methods"]["Biased"]["recordings"][0]
    assert first["aae_deg"] == pytest.approx(np.degrees(np.sqrt(np.mean(e ** 2))), rel=1e-6)
    assert first["aye_deg"] == pytest.approx(np.degrees(np.sqrt(np.mean(e ** 2))), rel=1e-6)
    r = evaluate([BiasedGyro([0.0, 0.0, b])], [seq])["methods"]["Biased"]["recordings"][0]
    e = e[seq.time >= seq.time[0] + 2.0]
    delta = np.arctan2(np.mean(np.sin(e)), np.mean(np.cos(e)))
    expected = np.degrees(np.sqrt(np.mean((e - delta) ** 2)))
    assert r["n_scored"] == e.size
    assert r["aae_deg"] == pytest.approx(expected, rel=1e-6)
    assert r["aye_deg"] == pytest.approx(expected, rel=1e-6)


def test_ground_truth_starting_late_is_aligned(sequences):
    """init_quat = ground truth at the first valid sample applied at sample 0; the 25-sample
    rotation between sample 0 and the first valid one is removed by the alignment."""
    res = evaluate([RawIntegration()], [sequences[1]], align=False)
    assert res["methods"]["Raw IMU"]["recordings"][0]["aae_deg"] > 1.0
    res = evaluate([RawIntegration()], [sequences[1]], align=True)
    assert res["methods"]["Raw IMU"]["recordings"][0]["aae_deg"] < 1e-6


def test_axes_and_broad_columns():
    seq = constant_rate_sequence("mag", np.array([0.1, 0.2, 0.3]), n=300, mag=True)  # 3 s: past the 2 s settle
    res9 = evaluate([ConstantBodyOffset()], [seq], align=False)
    r9 = res9["methods"]["Offset 2deg"]["recordings"][0]
    assert r9["axes"] == 9 and r9["broad_mode"] == "9d" and r9["total_deg"] == pytest.approx(2.0, abs=1e-9)
    res6 = evaluate([ConstantBodyOffset()], [seq], axes=6)
    r6 = res6["methods"]["Offset 2deg"]["recordings"][0]
    assert r6["axes"] == 6 and "total_deg" not in r6  # no benchmark score mask: no BROAD 6d errors
    table = markdown_table(res9, ("total_deg", "heading_deg", "inclination_deg"))
    assert "| total (deg) |" in table and "| Offset 2deg | 2.00 | 2.00 |" in table


def test_errors_and_print_table(sequences):
    with pytest.raises(ValueError, match="unique"):
        evaluate([RawIntegration(), RawIntegration()], sequences)

    class Broken:
        name = "broken"

        def run(self, seq, init_quat=None, init_index=0):
            return EstimatorOutput(quat=np.zeros((3, 4)))

    with pytest.raises(ValueError, match="broken.*spin_z"):
        evaluate([Broken()], sequences)
    res = evaluate([RawIntegration()], sequences, plots=False, trajectories=False)
    buf = io.StringIO()
    print_table(res, file=buf)
    text = buf.getvalue()
    assert "Raw IMU — attitude errors in degrees" in text and "Average" in text and "tumble" in text
    assert max(len(line) for line in text.splitlines()) < 100


def test_runner_says_where_the_estimate_starts_and_the_learned_model_reads_no_ground_truth():
    """The runner hands every estimator the first valid ground-truth sample and its attitude;
    the learned model starts its filter there from that alone: removing the recording's ground
    truth (after the runner read it) changes nothing."""
    from dataclasses import replace

    from tcn_ahrs.datasets.simulate import simulate
    from tcn_ahrs.estimators.learned import LearnedEstimator
    from tcn_ahrs.model.ahrs import LearnedAHRS

    seq = simulate("slow_rotation", 6.0, 50.0, seed=4)
    valid = seq.quat_valid.copy()
    valid[:40] = False
    seq = replace(seq, quat_valid=valid, meta=dict(seq.meta))
    seen = {}

    class Spy(RawIntegration):
        name = "spy"

        def run(self, s, init_quat=None, init_index=0):
            seen.update(index=init_index, quat=init_quat)
            return super().run(s, init_quat, init_index)

    evaluate([Spy()], [seq], verbose=False)
    assert seen["index"] == 40
    np.testing.assert_allclose(seen["quat"], seq.quat[40])
    est = LearnedEstimator(LearnedAHRS(axes=9, loop="open", tcn={"channels": [4, 4, 4, 4]}))
    with_gt = est.run(seq, seq.quat[40], 40).quat
    blind = replace(seq, quat=None, quat_valid=None, score_mask=None, meta=dict(seq.meta))
    np.testing.assert_array_equal(est.run(blind, seq.quat[40], 40).quat, with_gt)
    assert np.abs(with_gt[40] - seq.quat[40]).max() < 1e-5  # it started there
    with pytest.raises(ValueError, match="init_index"):
        est.run(seq, seq.quat[40], len(seq))


def test_a_release_on_the_device_check_and_its_baselines_get_the_same_input(tmp_path):
    """`tcn-ahrs evaluate ckpt=estimator.json` whose calibration is the device check gave the release
    each recording's gyro bias at rest subtracted and the baselines the raw recording: side by side
    on different input. Now every method reads the checked recordings (the same backbone as the
    release and as a baseline scores the same)."""
    from tcn_ahrs.cli import main
    from tcn_ahrs.datasets.simulate import simulate
    from tcn_ahrs.device_check import RestBiasCalibration
    from tcn_ahrs.estimators.families import FAMILIES, save_estimator

    root = tmp_path / "device"
    root.mkdir()
    for i in range(2):  # a 4 °/s gyro bias, rests now and then: the device check finds it
        s = simulate("walking", 30.0, 100.0, seed=10 + i, device_seed=5, axes=6, gyro_bias_range_dps=(4.0, 4.1),
                     gyro_bias_repeatability_dps=0.0, gyro_bias_rw_dps=0.0)
        np.savetxt(root / f"rec{i}.csv", np.column_stack([s.time, s.gyro, s.accel, s.quat]), delimiter=",",
                   comments="", fmt="%.10g", header="t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,quat_w,quat_x,quat_y,quat_z")
    release = tmp_path / "estimator.json"
    save_estimator(release, "backbone", 6, FAMILIES["backbone"].defaults_for(6), RestBiasCalibration())
    out = tmp_path / "eval"
    main(["evaluate", f"ckpt={release}", "data=generic", f"data.root={root}", "data.split=all", "data.axes=6",
          "baselines=[backbone]", f"out={out}", "plots=false", "trajectories=false", f"hydra.run.dir={tmp_path / 'h'}"])
    res = json.loads((out / "results.json").read_text())["methods"]
    rel, base = [k for k in res if k != "Raw IMU"]  # the release, then the backbone baseline
    for a, b in zip(res[rel]["recordings"], res[base]["recordings"]):
        assert a["aae_deg"] == pytest.approx(b["aae_deg"], abs=1e-9), (rel, base, a, b)
