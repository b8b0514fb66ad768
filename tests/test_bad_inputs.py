"""Bad input gets a clear error, never a silently wrong result (one test per case)."""
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from tcn_ahrs.export import export_batch, export_streaming
from tcn_ahrs.model.ahrs import LearnedAHRS
from tcn_ahrs.conf import CONF_DIR

N = 120
RATE = 100.0
CKPTS = Path(__file__).resolve().parents[1] / "checkpoints"


def _exported(tmp_path, loop: str):
    torch.manual_seed(0)
    m = LearnedAHRS(axes=6, loop=loop, mag_net="none", use_mag_term=False, tcn={"channels": [4, 4, 4, 4]}).eval()
    if m.closed is not None:
        m.closed.set_rate(RATE)
    export_batch(m, tmp_path / f"{loop}.pt", {"rate_hz": RATE})
    export_streaming(m, tmp_path / f"{loop}_s.pt", {"rate_hz": RATE})
    return torch.jit.load(str(tmp_path / f"{loop}.pt")), torch.jit.load(str(tmp_path / f"{loop}_s.pt"))


def _imu():
    g = torch.Generator().manual_seed(1)
    return torch.cat([0.2 * torch.randn(N, 3, generator=g),
                      torch.tensor([0.0, 0.0, 9.81]) + 0.2 * torch.randn(N, 3, generator=g)], 1)


Q0 = torch.tensor([1.0, 0.0, 0.0, 0.0])


@pytest.mark.parametrize("loop", ["closed", "open"])
def test_exported_modules_refuse_non_finite_readings_and_bad_time_steps(tmp_path, loop):
    batch, stream = _exported(tmp_path, loop)
    imu = _imu()
    imu[50, 4] = math.nan
    for run in (batch, stream.run):
        with pytest.raises(Exception, match=r"imu: non-finite value at index \[50, 4\]"):
            run(imu, 1.0 / RATE, Q0)
    dt = torch.full((N,), 1.0 / RATE)
    dt[0] = 0.0  # dt[0] is not used: accepted
    batch(_imu(), dt, Q0)
    for bad in (0.0, -0.01, math.nan):
        dt2 = dt.clone()
        dt2[30] = bad
        with pytest.raises(Exception, match=r"dt: expected finite time steps in \[1e-05, 1\] s .* at index 30"):
            batch(_imu(), dt2, Q0)
    with pytest.raises(Exception, match=r"dt: expected finite time steps in \[1e-05, 1\] s .* at index 1"):
        batch(_imu(), torch.tensor(-0.01), Q0)  # a scalar tensor is checked like a float


@pytest.mark.parametrize("loop", ["closed", "open"])
def test_streaming_step_error_leaves_the_state_as_if_the_sample_was_not_given(tmp_path, loop):
    _, stream = _exported(tmp_path, loop)
    imu = _imu()
    stream.reset(Q0)
    ref = [stream.step(imu[k], 1.0 / RATE)[0] for k in range(N)]
    stream.reset(Q0)
    out = []
    for k in range(N):
        if k == 40:
            bad = imu[k].clone()
            bad[1] = math.inf
            with pytest.raises(Exception, match=r"sample: non-finite value at index \[1\]"):
                stream.step(bad, 1.0 / RATE)
            with pytest.raises(Exception, match=r"dt: expected a finite time step in \[1e-05, 1\] s"):
                stream.step(imu[k], -1.0)
            # finite but impossible: one 1e30 or a dt of 1e6 s would poison every later output
            bad[1] = 1e30
            with pytest.raises(Exception, match=r"sample: value beyond any sensor's range at index \[1\]"):
                stream.step(bad, 1.0 / RATE)
            with pytest.raises(Exception, match=r"dt: expected a finite time step in \[1e-05, 1\] s"):
                stream.step(imu[k], 1e6)
        out.append(stream.step(imu[k], 1.0 / RATE)[0])
    torch.testing.assert_close(torch.stack(out), torch.stack(ref), atol=0, rtol=0)


@pytest.mark.parametrize("key, value, message", [
    ("lr", "abc", r"train.lr: expected a number > 0, got 'abc'"),
    ("epochs", -1, r"train.epochs: expected an integer >= 1, got -1"),
    ("epochs", 0, r"train.epochs: expected an integer >= 1, got 0"),
    ("ema_decay", 1.0, r"train.ema_decay: expected a number >= 0 and < 1, got 1.0"),
    ("batch_size", 2.5, r"train.batch_size: expected an integer >= 1, got 2.5"),
])
def test_numeric_train_values_are_checked_with_the_key_named(key, value, message):
    from tcn_ahrs.training.run import check_train_values

    check_train_values({"lr": 0.001, "epochs": 3, "noise": {"gyro": 0.0}})  # valid
    with pytest.raises(ValueError, match=message):
        check_train_values({key: value})
    with pytest.raises(ValueError, match=r"train.noise.acc: expected a number >= 0, got -0.1"):
        check_train_values({"noise": {"acc": -0.1}})


def test_reanchor_must_be_a_positive_sample_count():
    from tcn_ahrs.estimators.learned import LearnedEstimator

    model = LearnedAHRS(axes=6, loop="open", mag_net="none", use_mag_term=False, tcn={"channels": [4, 4, 4, 4]})
    with pytest.raises(ValueError, match=r"reanchor: expected an integer >= 1, got -5"):
        LearnedEstimator(model, reanchor=-5)


@pytest.mark.parametrize("content, message", [
    (b"", r"not a checkpoint \(an empty file"),
    (b"hello world\n", r"not a checkpoint \(a 12-byte file starting with b'hell'"),
    (b"PK\x03\x04garbage", r"cannot load this checkpoint safely"),
])
def test_a_file_that_is_no_checkpoint_gets_a_one_line_reason(tmp_path, content, message):
    from tcn_ahrs.checkpoint import CheckpointError, load_checkpoint

    p = tmp_path / "model.ckpt"
    p.write_bytes(content)
    with pytest.raises(CheckpointError, match=message) as e:
        load_checkpoint(p)
    assert "\n" not in str(e.value)


def test_scripts_print_one_line_and_exit_2_on_a_user_error(tmp_path):
    import os
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "scripts" / "train.py"
    env = dict(os.environ)
    env.pop("HYDRA_FULL_ERROR", None)
    r = subprocess.run([sys.executable, str(script), "train.epochs=0", f"run_dir={tmp_path}"],
                       capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
    assert r.returncode == 2
    assert r.stderr.startswith("error: train.epochs: expected an integer >= 1, got 0")
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize("script, args, message", [
    ("train", ["train.epoch=3"], r"error: train config: Could not override 'train.epoch'\. \(did you mean 'train.epochs'\?\)"),
    ("evaluate", ["data.splt=test"], r"error: evaluate config: .*'data.splt'.* \(did you mean 'data.split'\?\)"),
    ("train", ["data=broadd"], r"error: train config: .*Could not find 'data/broadd' \(did you mean data=broad\?\)"),
])
def test_hydra_config_errors_are_one_line_with_the_nearest_key(tmp_path, script, args, message):
    import os
    import re
    import subprocess
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / f"{script}.py"
    env = dict(os.environ)
    env.pop("HYDRA_FULL_ERROR", None)
    r = subprocess.run([sys.executable, str(path)] + args, capture_output=True, text=True, env=env, cwd=tmp_path,
                       timeout=300)
    assert r.returncode == 2 and re.match(message, r.stderr), r.stderr
    assert len(r.stderr.strip().splitlines()) == 2  # the error and how to see Hydra's full report


# ------------------------------------------------------------ recordings (generic format)
HEADER = "t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z,quat_w,quat_x,quat_y,quat_z"


def _recording(tmp_path, edit=None, sidecar=None, seconds=20.0):
    import numpy as np

    from tcn_ahrs.datasets.simulate import simulate

    seq = simulate("slow_rotation", seconds, 100.0, seed=4)
    cols = {"t": seq.time.copy(), "gyr": seq.gyro.copy(), "acc": seq.accel.copy(), "mag": seq.mag.copy(),
            "quat": seq.quat.copy()}
    if edit is not None:
        edit(cols)
    path = tmp_path / "rec.csv"
    np.savetxt(path, np.column_stack([cols["t"], cols["gyr"], cols["acc"], cols["mag"], cols["quat"]]),
               delimiter=",", header=HEADER, comments="", fmt="%.10g")
    if sidecar:
        (tmp_path / "rec.yaml").write_text(sidecar)
    return path


def _load(path):
    from tcn_ahrs.datasets.generic import load_file

    return load_file(path)


def _moving_part_in_degrees(c):
    import numpy as np

    c["gyr"] = np.degrees(c["gyr"])


def _gravity_not_specific_force(c):
    c["acc"] = -c["acc"]


def _xyzw(c):
    c["quat"] = c["quat"][:, [1, 2, 3, 0]]


def _ten_second_gap(c):
    c["t"][1000:] += 10.0


def _milliseconds(c):
    c["t"] = c["t"] * 1000.0


def _x_up_ground_truth(c):
    import numpy as np
    import torch

    from tcn_ahrs import so3

    x_up = so3.matrix_to_quat(torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], dtype=torch.float64))
    c["quat"] = so3.quat_mul(x_up, torch.as_tensor(c["quat"])).numpy()
    assert np.isfinite(c["quat"]).all()


def _rotated_ground_truth_body(c):
    import torch

    from tcn_ahrs import so3

    # the motion-capture body frame is the IMU frame turned 90 deg about x: C_nav_from_body = C R
    r = so3.matrix_to_quat(torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], dtype=torch.float64))
    c["quat"] = so3.quat_mul(torch.as_tensor(c["quat"]), r).numpy()


def _arbitrary_field_units(c):
    c["mag"] = c["mag"] * 0.37  # e.g. raw counts of an uncalibrated magnetometer


@pytest.mark.parametrize("edit, field, message", [
    (_rotated_ground_truth_body, "gyro", r"axes wired differently .* declare gt_body_from_imu: \[\[1, 0, 0\], \[0, 0, 1\], \[0, -1, 0\]\]"),
    (_moving_part_in_degrees, "gyro", r"deg/s"),
    (_gravity_not_specific_force, "accel", r"acc_sign: gravity"),
    (_xyzw, "quat", r"in x,y,z,w order \(HDF5: declare quat_order: xyzw"),
    (_ten_second_gap, "time", r"a gap of 10.01 s between samples 999 and 1000 .* split the recording there"),
    (_milliseconds, "time", r"the timestamps look like milliseconds: declare time_unit: ms"),
    (_x_up_ground_truth, "accel", r"frame is not z-up: declare its nav_frame"),
])
def test_undeclared_units_frames_and_gaps_are_refused_with_the_fix(tmp_path, edit, field, message):
    from tcn_ahrs.sequence import DataError

    path = _recording(tmp_path, edit)
    with pytest.raises(DataError, match=message) as e:
        _load(path)
    assert e.value.field_name == field and str(path) in str(e.value)


@pytest.mark.parametrize("edit, sidecar", [
    (_moving_part_in_degrees, "gyr_unit: deg/s\n"),
    (_gravity_not_specific_force, "acc_sign: gravity\n"),
    (_milliseconds, "time_unit: ms\n"),
    (_x_up_ground_truth, "nav_frame: [[0, 0, -1], [0, 1, 0], [1, 0, 0]]\n"),
    (_rotated_ground_truth_body, "gt_body_from_imu: [[1, 0, 0], [0, 0, 1], [0, -1, 0]]\n"),
    (_rotated_ground_truth_body, "gt_body_from_imu: [0.7071067811865476, -0.7071067811865476, 0, 0]\n"),
])
def test_the_declaration_named_in_the_message_loads_the_recording_right(tmp_path, edit, sidecar):
    import numpy as np

    (tmp_path / "ref").mkdir()
    ref = _load(_recording(tmp_path / "ref"))
    seq = _load(_recording(tmp_path, edit, sidecar))
    np.testing.assert_allclose(seq.gyro, ref.gyro, atol=1e-8)
    np.testing.assert_allclose(seq.accel, ref.accel, atol=1e-7)
    np.testing.assert_allclose(seq.time, ref.time, atol=1e-9)
    np.testing.assert_allclose(np.abs((seq.quat * ref.quat).sum(1)), 1.0, atol=1e-8)


def test_a_misspelt_sidecar_key_is_an_error_with_the_near_match(tmp_path):
    from tcn_ahrs.sequence import DataError

    path = _recording(tmp_path, sidecar="gyro_unit: deg/s\n")
    with pytest.raises(DataError, match=r"unknown declaration \(did you mean 'gyr_unit'\?\)"):
        _load(path)


@pytest.mark.parametrize("peer", ["vqf", "riann"])
def test_fixed_period_peers_run_irregular_recordings_on_a_uniform_grid(peer):
    """VQF and RIANN take one fixed period: an irregular recording (10-20 ms steps and repeated
    stamps dropped, as a ~91 Hz device) runs on a uniform grid and comes back on its own
    timestamps, within a fraction of a degree of the same motion sampled regularly."""
    from dataclasses import replace

    import numpy as np

    from tcn_ahrs.datasets.simulate import simulate
    from tcn_ahrs.estimators import registry
    from tcn_ahrs.metrics import sequence_metrics

    pytest.importorskip(peer)
    seq = simulate("slow_rotation", 30.0, 400.0, seed=2).without_mag()
    rng = np.random.default_rng(0)
    keep = np.concatenate([[0], np.cumsum(rng.integers(4, 9, size=len(seq)))])  # 10-20 ms steps
    keep = keep[keep < len(seq)]
    irregular = replace(seq, time=seq.time[keep], gyro=seq.gyro[keep], accel=seq.accel[keep], quat=seq.quat[keep],
                        quat_valid=seq.quat_valid[keep], score_mask=None, rate=0.0, check_units=False)
    regular = replace(seq, time=seq.time[::6], gyro=seq.gyro[::6], accel=seq.accel[::6], quat=seq.quat[::6],
                      quat_valid=seq.quat_valid[::6], score_mask=None, rate=0.0, check_units=False)
    est = registry.build(peer, 6)
    out = est.run(irregular, irregular.quat[0], 0)
    assert out.quat.shape == (len(irregular), 4)
    key = "inclination_deg" if getattr(est, "heading_free", False) else "aae_deg"  # RIANN: no heading
    a = sequence_metrics(irregular, out.quat, axes=6)[key]
    b = sequence_metrics(regular, est.run(regular, regular.quat[0], 0).quat, axes=6)[key]
    assert abs(a - b) < 0.5, (a, b)


def test_a_magnetometer_in_arbitrary_units_keeps_its_direction(tmp_path):
    import numpy as np

    (tmp_path / "ref").mkdir()
    ref = _load(_recording(tmp_path / "ref"))
    seq = _load(_recording(tmp_path, _arbitrary_field_units, "mag_unit: arbitrary\n"))
    unit = lambda m: m / np.linalg.norm(m, axis=1, keepdims=True)  # noqa: E731
    np.testing.assert_allclose(unit(seq.mag), unit(ref.mag), atol=1e-7)
    assert np.median(np.linalg.norm(seq.mag, axis=1)) == pytest.approx(50.0)


def test_motion_capture_flips_are_masked_not_scored():
    """gt_outliers: a sample flipped by 180 deg and a 5-sample jump are found; clean data is not touched."""
    import numpy as np

    from tcn_ahrs.datasets._common import gt_outliers, quat_mul
    from tcn_ahrs.datasets.simulate import simulate

    seq = simulate("fast_rotation", 20.0, 100.0, seed=3)
    valid = np.ones(len(seq), bool)
    assert not gt_outliers(seq.quat, valid, seq.gyro, seq.dt).any()
    q = seq.quat.copy()
    flip = np.array([0.0, 0.0, 0.0, 1.0])  # 180 deg about z
    q[700] = quat_mul(flip, q[700])
    q[1200:1205] = quat_mul(np.array([np.cos(0.1), np.sin(0.1), 0.0, 0.0]), q[1200:1205])  # 11.5 deg jump
    out = gt_outliers(q, valid, seq.gyro, seq.dt)
    assert np.flatnonzero(out).tolist() == [700, 1200, 1201, 1202, 1203, 1204]


def test_a_text_cell_and_a_semicolon_csv_are_named(tmp_path):
    from tcn_ahrs.datasets.generic import load_file
    from tcn_ahrs.sequence import DataError

    p = tmp_path / "r.csv"
    p.write_text("t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z\n0,0,0,0,0,0,9.81\n0.01,0,abc,0,0,0,9.81\n")
    with pytest.raises(DataError, match=r"field 'row 3, column 3 \('gyr_y'\)': expected a number, found 'abc'"):
        load_file(p)
    p.write_text("t;gyr_x;gyr_y;gyr_z;acc_x;acc_y;acc_z\n0;0;0;0;0;0;9.81\n")
    with pytest.raises(DataError, match=r"header is separated by ';'"):
        load_file(p)


def test_nothing_to_score_is_an_error_not_a_table_of_dashes():
    from dataclasses import replace

    import numpy as np

    from tcn_ahrs.datasets.simulate import simulate
    from tcn_ahrs.estimators.raw import RawIntegration
    from tcn_ahrs.evaluate import evaluate

    seq = simulate("slow_rotation", 5.0, 100.0, seed=1)
    no_gt = replace(seq, name="no_gt", quat=np.full_like(seq.quat, np.nan), quat_valid=None, check_units=False)
    masked = replace(seq, name="masked", score_mask=np.zeros(len(seq), bool), check_units=False)
    for bad, why in ((no_gt, "invalid \\(NaN\\) everywhere"), (masked, "score mask selects no sample")):
        with pytest.raises(ValueError, match=f"nothing to score in any recording .*{why}"):
            evaluate([RawIntegration()], [bad], plots=False, trajectories=False)
    with pytest.warns(UserWarning, match="'masked' is not scored"):
        evaluate([RawIntegration()], [seq, masked], plots=False, trajectories=False)


def test_training_a_folder_without_a_train_list_says_what_to_set(tmp_path):
    from hydra import compose, initialize_config_dir

    from tcn_ahrs.training.run import train_main

    _recording(tmp_path)  # tmp_path/rec.csv
    conf = CONF_DIR
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose("train", overrides=["data=generic", f"data.root={tmp_path}", f"run_dir={tmp_path / 'run'}",
                                          "threads=1"])
    with pytest.raises(ValueError, match=r"no training recordings: data.train lists 0 .*found there: rec.*"
                                         r"set data.train=\[name, ...\]"):
        train_main(cfg)


def test_a_recording_at_another_rate_than_the_model_was_trained_at_warns(tmp_path):
    from tcn_ahrs.datasets.simulate import simulate
    from tcn_ahrs.estimators.learned import LearnedEstimator

    model = LearnedAHRS(axes=9, loop="closed", tcn={"channels": [4, 4, 4, 4]})
    model.trained_rate_hz = 285.7
    seq = simulate("slow_rotation", 4.0, 100.0, seed=1)
    with pytest.warns(UserWarning, match=r"at 100 Hz but the model was trained at 285.7 Hz"):
        LearnedEstimator(model, other_rate="model").run(seq, seq.quat[0])
    # by default a closed loop, like a residual model, runs there as the backbone with VQF's defaults
    from tcn_ahrs.estimators.registry import build

    with pytest.warns(UserWarning, match=r"100 Hz.*another device.*backbone with VQF's default parameters"):
        got = LearnedEstimator(model).run(seq, seq.quat[0]).quat
    np.testing.assert_allclose(got, build("backbone", axes=9).run(seq, seq.quat[0]).quat, atol=1e-12)


def test_a_finite_spike_in_a_recording_is_refused_with_file_field_and_sample(tmp_path):
    from tcn_ahrs.sequence import DataError

    def spike(c):
        c["acc"][50, 1] = 1e30

    path = _recording(tmp_path, spike)
    with pytest.raises(DataError, match=r"sample 50, axis y: 1e\+30 m/s\^2 is beyond any sensor's range .* a spike") as e:
        _load(path)
    assert e.value.field_name == "accel" and str(path) in str(e.value)


def test_compiled_streaming_refuses_spikes_huge_steps_and_a_matrix_sample():
    import numpy as np

    from tcn_ahrs.streaming import CompiledStreaming

    torch.manual_seed(0)
    m = LearnedAHRS(axes=6, loop="closed", mag_net="none", use_mag_term=False, tcn={"channels": [4, 4, 4, 4]}).eval()
    m.closed.set_rate(RATE)
    imu = _imu().numpy()
    a, b = CompiledStreaming(m), CompiledStreaming(m)
    for s in (a, b):
        s.reset(Q0.numpy())
        s.step_chunk(imu[:50], 1.0 / RATE)
    bad = imu[50].copy()
    bad[3] = 1e30
    with pytest.raises(ValueError, match="beyond any sensor's range"):
        a.step(bad, 1.0 / RATE)
    with pytest.raises(ValueError, match=r"dt: expected finite time steps in \[1e-05, 1"):
        a.step(imu[50], 1e6)
    with pytest.raises(ValueError, match=r"sample: expected shape \(6,\)"):
        a.step(np.zeros((2, 3)), 1.0 / RATE)
    np.testing.assert_array_equal(a.step_chunk(imu[50:], 1.0 / RATE)[0], b.step_chunk(imu[50:], 1.0 / RATE)[0])


def test_a_checkpoint_with_nan_weights_is_refused_at_load(tmp_path):
    from tcn_ahrs.checkpoint import CheckpointError, model_from_checkpoint

    ck = torch.load(CKPTS / "broad6_residual.ckpt", map_location="cpu", weights_only=False)
    key = next(k for k, v in ck["state_dict"].items() if v.is_floating_point() and v.numel() > 1)
    ck["state_dict"][key] = ck["state_dict"][key].clone()
    ck["state_dict"][key].view(-1)[0] = math.nan
    torch.save(ck, tmp_path / "nan.ckpt")
    with pytest.raises(CheckpointError, match=r"nan.ckpt: weight '.*' holds NaN/inf values"):
        model_from_checkpoint(tmp_path / "nan.ckpt")


def test_staged_output_is_all_or_nothing_and_never_mixes_runs(tmp_path):
    from tcn_ahrs.app import staged_output

    out = tmp_path / "eval"
    with staged_output(out) as stage:
        (stage / "results.json").write_text("1")
        (stage / "old_recording.txt").write_text("x")
        assert not out.exists()  # nothing visible until the run completes
    assert (out / "results.json").read_text() == "1"
    with pytest.raises(ValueError, match=r"already holds an earlier run's files .* overwrite=true"):
        with staged_output(out):
            pass
    with pytest.raises(RuntimeError, match="killed"):  # a failing run leaves the earlier one as it was
        with staged_output(out, overwrite=True) as stage:
            (stage / "results.json").write_text("half")
            raise RuntimeError("killed")
    assert (out / "results.json").read_text() == "1" and not list(tmp_path.glob(".eval.*partial"))
    (out / ".hydra").mkdir()
    (tmp_path / ".eval.999999999.dead.partial").mkdir()  # what a SIGKILL leaves: removed by the next run
    with staged_output(out, overwrite=True) as stage:
        (stage / "results.json").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == [".hydra", "results.json"]  # no earlier recording beside it
    assert not list(tmp_path.glob(".eval.*partial"))
    hydra_dir = tmp_path / "hydra_run"
    (hydra_dir / ".hydra").mkdir(parents=True)
    (hydra_dir / "evaluate.log").write_text("log")
    with staged_output(hydra_dir) as stage:  # Hydra's own files of this job are not an earlier run
        (stage / "results.json").write_text("3")
    assert sorted(p.name for p in hydra_dir.iterdir()) == [".hydra", "evaluate.log", "results.json"]


def test_concurrent_runs_with_one_out_never_share_a_staging_folder(tmp_path):
    """Two evaluates with one out= (measured: one died with "[Errno 2] ... .partial/plots/...png"):
    each stages alone; the first to finish fills out, the other is kept beside it with a warning,
    and says where its files are (its last line named the other run's folder before)."""
    from tcn_ahrs.app import staged_output

    out = tmp_path / "eval"
    landed_a, landed_b = [], []
    first, second = staged_output(out, landed=landed_a), staged_output(out, landed=landed_b)
    a, b = first.__enter__(), second.__enter__()
    assert a != b and a.is_dir() and b.is_dir()
    (a / "plots").mkdir()
    (b / "plots").mkdir()
    (a / "plots" / "x.png").write_text("a")
    (b / "plots" / "x.png").write_text("b")
    first.__exit__(None, None, None)
    with pytest.warns(UserWarning, match="eval-2"):
        second.__exit__(None, None, None)
    assert (out / "plots" / "x.png").read_text() == "a"
    assert (tmp_path / "eval-2" / "plots" / "x.png").read_text() == "b"
    assert not list(tmp_path.glob(".eval.*"))
    assert landed_a == [out] and landed_b == [tmp_path / "eval-2"]


def test_export_writes_both_files_or_neither_and_refuses_to_overwrite(tmp_path, monkeypatch):
    import tcn_ahrs.export as ex

    out = tmp_path / "m.pt"
    written = ex.export_checkpoint(CKPTS / "closed_loop" / "broad6.ckpt", out)
    assert set(written) == {"batch", "streaming"} and out.exists() and ex.streaming_path(out).exists()
    with pytest.raises(ex.ExportError, match="already exist.*overwrite=true"):
        ex.export_checkpoint(CKPTS / "closed_loop" / "broad6.ckpt", out)
    before = (out.read_bytes(), ex.streaming_path(out).read_bytes())

    def killed(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(ex, "export_streaming", killed)  # dies after the batch file is written
    with pytest.raises(KeyboardInterrupt):
        ex.export_checkpoint(CKPTS / "broad6_residual.ckpt", out, overwrite=True)
    assert (out.read_bytes(), ex.streaming_path(out).read_bytes()) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.pt", "m_streaming.pt"]


def _turn_ground_truth_body(deg):
    def edit(c):
        import torch

        from tcn_ahrs import so3

        axis = torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64) / 3 ** 0.5
        r = so3.quat_exp(axis * (deg * 3.141592653589793 / 180.0))
        c["quat"] = so3.quat_mul(torch.as_tensor(c["quat"]), r.expand(len(c["quat"]), 4)).numpy()
    return edit


def _gyro_edit(fn):
    def edit(c):
        c["gyr"] = fn(c["gyr"].copy())
    return edit


def _swap_xy(g):
    return g[:, [1, 0, 2]]


def _quarter_turn(g):  # x <- -y, y <- x: a rotation, not a reflection
    return g[:, [1, 0, 2]] * [-1.0, 1.0, 1.0]


def _dead_y(g):
    g[:, 1] = 0.0
    return g


def _saturated(g):
    import numpy as np

    top = 0.4 * np.abs(g).max()
    return np.clip(g, -top, top)


@pytest.mark.parametrize("edit, sidecar, field, message", [
    (_gyro_edit(lambda g: g * [1.0, 1.0, -1.0]), None, "gyro", r"left-handed frame .* one axis has the wrong sign"),
    (_gyro_edit(_swap_xy), None, "gyro", r"left-handed frame .* two axes are swapped"),
    (_gyro_edit(_quarter_turn), None, "gyro", r"axes wired differently .* declare gt_body_from_imu"),
    (_gyro_edit(_dead_y), None, "gyro", r"axis y reads \(almost\) a constant"),
    (_gyro_edit(lambda g: g * 0.0), None, "gyro", r"axis x reads \(almost\) a constant"),
    (_gyro_edit(_saturated), None, "gyro", r"sticks at ±.* the gyro saturates"),
    (None, "gyr_unit: deg/s\n", "gyro", r"already in rad/s\? remove gyr_unit: deg/s"),
    (_turn_ground_truth_body(10.0), None, "quat", r"rotated 10.\d deg against the IMU's .* gt_body_from_imu"),
])
def test_wiring_faults_are_caught_per_axis(tmp_path, edit, sidecar, field, message):
    from tcn_ahrs.sequence import DataError

    path = _recording(tmp_path, edit, sidecar)
    with pytest.raises(DataError, match=message) as e:
        _load(path)
    assert e.value.field_name == field and str(path) in str(e.value)


def test_a_constant_gyro_bias_is_not_taken_for_a_rotated_mount(tmp_path):
    """Simulated walks with a 5 deg/s gyro bias (3 deg/s more or less per recording): the wiring fit
    takes up the bias as an offset; through the origin it read 16 deg of mount rotation and refused
    2 of 6 recordings."""
    import numpy as np

    from tcn_ahrs.datasets import load_split
    from tcn_ahrs.datasets.simulate import simulate

    for i in range(6):
        s = simulate("walking", 30.0, 100.0, seed=10 + i, device_seed=5, axes=6, gyro_bias_range_dps=(5.0, 5.1),
                     gyro_bias_repeatability_dps=3.0, gyro_bias_rw_dps=0.0)
        np.savetxt(tmp_path / f"rec{i}.csv", np.column_stack([s.time, s.gyro, s.accel, s.quat]), delimiter=",",
                   comments="", fmt="%.10g", header="t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,quat_w,quat_x,quat_y,quat_z")
    refused = []
    assert len(load_split({"name": "generic", "root": str(tmp_path), "split": "all", "axes": 6}, "all", refused)) == 6
    assert refused == []


def _acc_edit(fn):
    def edit(c):
        c["acc"] = fn(c["acc"].copy())
    return edit


def _acc_dead_x(a):
    a[:, 0] = 0.3
    return a


def _left_handed(c):  # y negated in every sensor (and the ground truth stays right-handed)
    for k in ("gyr", "acc", "mag"):
        c[k][:, 1] *= -1.0


@pytest.mark.parametrize("edit, field, message", [
    (_acc_edit(lambda a: a[:, [1, 0, 2]]), "accel", r"accelerometer's axes form a left-handed frame|axes wired differently|does not keep one direction"),
    (_acc_edit(_acc_dead_x), "accel", r"axis x reads \(almost\) a constant while gravity moves along it"),
    (_left_handed, "gyro", r"left-handed frame"),
])
def test_accelerometer_wiring_is_told_apart_from_a_ground_truth_frame(tmp_path, edit, field, message):
    from tcn_ahrs.sequence import DataError

    path = _recording(tmp_path, edit)
    with pytest.raises(DataError, match=message) as e:
        _load(path)
    assert e.value.field_name == field


def test_fast_translation_keeps_the_up_test(tmp_path):
    """Fast back-and-forth translation (±2 g along x, as BROAD's fast-translation trials): the
    mean of unit specific-force directions drops below 0.5, their vector mean stays up."""
    import numpy as np

    def shake(c):
        t = c["t"]
        c["acc"] = c["acc"] + np.stack([20.0 * np.sign(np.sin(2 * np.pi * 2.0 * t)), 0 * t, 0 * t], 1)

    seq = _load(_recording(tmp_path, shake))
    # loaded whole, the shaking kept (not refused, not filtered away)
    assert seq.has_gt and seq.quat_valid.all() and float(np.abs(seq.accel[:, 0]).max()) > 15.0


def test_twenty_second_clips_of_real_fast_translation_are_accepted(tmp_path):
    """BROAD's fast-translation trials cut into 20 s clips through the generic CSV format: the up
    test (the vector mean of the specific force in the ground-truth frame) and the per-axis
    checks accept every clip with continuous ground truth."""
    from pathlib import Path

    import numpy as np

    from tcn_ahrs.datasets import broad

    root = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "broad"
    names = [n for n in ("18_undisturbed_fast_translation_with_breaks_B", "15_undisturbed_fast_translation_with_breaks_A")
             if (root / f"{n}.hdf5").is_file()]
    if not names:
        pytest.skip("BROAD's fast-translation trials not found under ../shared/datasets/broad")
    loaded = 0
    for name in names:
        s = broad.load_recording(root, name)
        k = int(20 * s.rate)
        for start in range(0, len(s.time) - k, len(s.time) // 4):
            sl = slice(start, start + k)
            if not s.quat_valid[sl].all():
                continue
            p = tmp_path / f"{name}_{start}.csv"
            np.savetxt(p, np.column_stack([s.time[sl] - s.time[start], s.gyro[sl], s.accel[sl], s.mag[sl], s.quat[sl]]),
                       delimiter=",", header=HEADER, comments="", fmt="%.10g")
            clip = _load(p)
            assert clip.quat_valid.all() and np.allclose(np.abs(np.sum(clip.quat * s.quat[sl], 1)), 1.0, atol=1e-6)
            loaded += 1
    assert loaded >= 3


def _time_scaled(f):
    def edit(c):
        c["t"] = c["t"] * f
    return edit


def _scaled_quaternions(c):
    c["quat"] = c["quat"] * 1.5


@pytest.mark.parametrize("edit, sidecar, field, message", [
    (_time_scaled(1e6), None, "time", r"look like microseconds: declare time_unit: us"),
    (_time_scaled(1e9), None, "time", r"look like nanoseconds: declare time_unit: ns"),
    (_time_scaled(1e6), "time_unit: ms\n", "time", r"\(declared time_unit: ms\).* look like microseconds"),
    (None, "rate: 200\n", "rate", r"declared 200 Hz, but the timestamps step at 100 Hz"),
    (None, "rate: fast\n", "rate", r"expected the nominal rate as a number in Hz, got 'fast'"),
    (_scaled_quaternions, "nav_frame: NED\n", "quat", r"expected unit quaternions, found norm 1.5"),
])
def test_declarations_and_timestamps_are_checked_against_the_data(tmp_path, edit, sidecar, field, message):
    from tcn_ahrs.sequence import DataError

    path = _recording(tmp_path, edit, sidecar)
    with pytest.raises(DataError, match=message) as e:
        _load(path)
    assert e.value.field_name == field and str(path).replace(".csv", "") in str(e.value)


def test_duplicate_columns_misspelt_hdf5_attributes_and_non_utf8_files_are_named(tmp_path):
    import h5py
    import numpy as np

    from tcn_ahrs.sequence import DataError

    path = _recording(tmp_path)
    lines = path.read_text().splitlines()
    path.write_text("\n".join([lines[0].replace("mag_x", "gyr_x")] + lines[1:]) + "\n")
    with pytest.raises(DataError, match=r"column name\(s\) \['gyr_x'\] appear more than once") as e:
        _load(path)
    assert e.value.field_name == "header"
    path.write_bytes(b"t,gyr_x\n0.0,\xff\xfe\n")
    with pytest.raises(DataError, match=r"expected UTF-8 text") as e:
        _load(path)
    assert str(path) in str(e.value)
    h5 = tmp_path / "r.h5"
    with h5py.File(h5, "w") as f:
        f["t"], f["gyr"], f["acc"] = np.arange(300) * 0.01, np.zeros((300, 3)), np.tile([0.0, 0.0, 9.81], (300, 1))
        f.attrs["mag_units"] = "G"
        f.attrs["description"] = "a bench test"  # other attributes may stay
    with pytest.raises(DataError, match=r"unknown declaration \(did you mean 'mag_unit'\?\)") as e:
        _load(h5)
    assert e.value.field_name == "mag_units"


def test_config_values_fail_early_with_the_key_and_the_nearest_valid_value():
    from tcn_ahrs.estimators.registry import baseline_estimators
    from tcn_ahrs.training.run import check_train_values
    from tcn_ahrs.validate import set_threads

    with pytest.raises(ValueError, match=r"threads: expected an integer >= 1, got -3"):
        set_threads(-3)
    with pytest.raises(ValueError, match=r"train.monitor: expected one of \['val/loss', 'val/aae_deg'\].*'val/foo'"):
        check_train_values({"monitor": "val/foo"})
    with pytest.raises(ValueError, match=r"baselines: unknown method 'vqff' \(did you mean 'vqf'\?\)"):
        baseline_estimators(["raw", "vqff"], 9)
    assert len(baseline_estimators(["raw", "ecf6d"], 9)) == 2


def test_a_dead_accelerometer_is_named_as_such(tmp_path):
    from tcn_ahrs.sequence import DataError

    def dead(c):
        c["acc"] = c["acc"] * 0.0

    with pytest.raises(DataError, match=r"reads \(almost\) zero .* a dead or disconnected accelerometer") as e:
        _load(_recording(tmp_path, dead))
    assert e.value.field_name == "accel"


def test_an_export_that_cannot_be_written_is_a_clean_error(tmp_path, monkeypatch):
    import tcn_ahrs.export as ex

    def read_only(*a, **k):
        raise RuntimeError("File m.pt cannot be opened: Permission denied")

    monkeypatch.setattr(ex.torch.jit, "save", read_only)
    with pytest.raises(ex.ExportError, match=r"export: cannot write .* Permission denied"):
        ex.export_checkpoint(CKPTS / "closed_loop" / "broad6.ckpt", tmp_path / "m.pt")
    assert not list(tmp_path.iterdir())  # nothing half-written left behind


def test_a_9_axis_checkpoint_on_data_without_magnetometer_gets_advice_that_can_work():
    """broad9 on EuRoC advised `data.axes=9`, which cannot load (EuRoC has no magnetometer)."""
    from tcn_ahrs.checkpoint import CheckpointError, check_layout, load_checkpoint
    from tcn_ahrs.evaluate.main import dataset_axes

    ck = load_checkpoint(CKPTS / "broad9_residual.ckpt")
    assert dataset_axes("euroc") == 6 and dataset_axes("tumvi") == 6 and dataset_axes("broad") == 9
    with pytest.raises(CheckpointError, match="no magnetometer: use a 6-axis checkpoint") as e:
        check_layout(ck, 6, "broad9_residual.ckpt", data_axes=dataset_axes("euroc"))
    assert "data.axes=9" not in str(e.value)
    # a 9-axis dataset read as 6 axes: data.axes=9 does work there, and is what it says
    with pytest.raises(CheckpointError, match="data.axes=9"):
        check_layout(ck, 6, "broad9_residual.ckpt", data_axes=dataset_axes("broad"))


_PHONES = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "phones"


@pytest.mark.skipif(not (_PHONES / "iphone4s").is_dir(), reason="phones not in ../shared")
def test_a_phone_gyro_in_deg_per_s_in_motion_is_named_a_unit_not_a_spike():
    """Issue 55: a phone's gyro in deg/s while it moves exceeds the range on under 1 % of its samples and
    was called "a spike: drop or interpolate that sample"; the fix is the unit."""
    from tcn_ahrs.datasets import generic
    from tcn_ahrs.sequence import DataError, ImuSequence

    s = generic.load_file(_PHONES / "iphone4s" / "Guillaume_iPhone4S_Dist_Phoning.h5")
    with pytest.raises(DataError, match=r"field 'gyro'.*is it in deg/s\? declare gyr_unit: deg/s"):
        ImuSequence(s.name, s.source, s.time, np.degrees(s.gyro), s.accel, s.mag, s.quat)


def test_an_all_zero_magnetometer_is_named_dead_when_a_9_axis_peer_refuses_it(tmp_path):
    """The default's run with baselines=[vqf] on a recording whose magnetometer reads 0 everywhere
    said only "needs a magnetometer; use the 6-axis variant": it now says the field read 0 (a dead
    magnetometer) and which setting runs every method 6-axis."""
    pytest.importorskip("vqf")
    import warnings

    import numpy as np

    from tcn_ahrs.estimators import registry

    def dead(c):
        c["mag"][:] = 0.0

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        seq = _load(_recording(tmp_path, dead))
    assert seq.mag is None
    with pytest.raises(ValueError, match=r"field 'mag'.*reads 0 on every sample \(a dead magnetometer\).*data\.axes=6"):
        registry.build("vqf", 9).run(seq, np.array([1.0, 0, 0, 0]), 0)


PHONE = (Path(__file__).resolve().parents[2] / "shared" / "datasets" / "phones" / "iphone4s"
         / "Guillaume_iPhone4S_NoDist_Texting.h5")


def _phone_with(tmp_path, edit):
    """The iPhone 4S texting recording (../shared/datasets/phones) with ``edit(fields)`` applied."""
    import shutil

    import h5py

    if not PHONE.is_file():
        pytest.skip("the phones are not in ../shared")
    path = tmp_path / "phone.h5"
    shutil.copy(PHONE, path)
    with h5py.File(path, "r+") as f:
        fields = {k: f[k][...] for k in ("gyr", "acc", "mag")}
        edit(fields)
        for k, v in fields.items():
            f[k][...] = v
    return path


def test_a_phones_negated_gyro_axis_it_barely_turns_about_is_refused(tmp_path):
    """A phone held for texting turns little about its y axis (under 10 °/s of spread), so that axis
    was never judged: its gyro y negated loaded silently (inclination 4.75° against 0.96°). An axis
    the fitted map explains well (R² ≥ 0.85) is judged however little it turns; the clean one loads."""
    def negate_y(f):
        f["gyr"][:, 1] *= -1.0

    from tcn_ahrs.sequence import DataError

    _load(_phone_with(tmp_path, lambda f: None))
    with pytest.raises(DataError, match=r"field 'gyro'.*(left-handed|wired differently)"):
        _load(_phone_with(tmp_path, negate_y))


def test_a_phones_swapped_accelerometer_and_rotated_ground_truth_are_refused(tmp_path):
    """A phone held for texting barely tilts and barely turns about y: its accelerometer x/y swapped
    (inclination 8.1° against 1.0°) and its ground truth in a body frame rotated 10° loaded silently;
    the swap is read on the still samples against the gravity the ground truth predicts, the rotation
    from the rates about all three axes (y judged by its R²)."""
    from scipy.spatial.transform import Rotation

    from tcn_ahrs.sequence import DataError

    def swap_acc(f):
        f["acc"] = f["acc"][:, [1, 0, 2]]

    with pytest.raises(DataError, match=r"field 'accel': axes wired differently.*still samples.*\[\[0, 1, 0\], \[1, 0, 0\]"):
        _load(_phone_with(tmp_path, swap_acc))

    path = _phone_with(tmp_path, lambda f: None)
    import h5py

    with h5py.File(path, "r+") as f:
        q = f["quat"][...]
        ok = np.all(np.isfinite(q), axis=1)
        r = Rotation.from_quat(q[ok][:, [1, 2, 3, 0]]) * Rotation.from_rotvec(np.radians([10.0, 0.0, 0.0]))
        q[ok] = r.as_quat()[:, [3, 0, 1, 2]]
        f["quat"][...] = q
    with pytest.raises(DataError, match=r"field 'quat': the ground truth's body frame is rotated 10\.\d deg.*gt_body_from_imu"):
        _load(path)
