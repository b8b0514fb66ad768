"""Sensor health without ground truth (issue: a gyro frozen for 5 s in fast motion was accepted
with no flag, 81° error while frozen and 52° after): a sensor whose three readings repeat
exactly is flagged frozen, a frozen gyro is not integrated and a frozen accelerometer not
trusted, and the filter recovers faster than VQF; real recordings raise no flag."""
from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from tcn_ahrs.datasets.simulate import simulate
from tcn_ahrs.filters import backbone as bb

RATE = 100.0
K0, K1 = 2000, 2500  # 20-25 s frozen
# a clean magnetometer, so the heading's recovery is the filters', not the field's acceptance
CLEAN_MAG = dict(hard_iron_std_ut=0.0, hard_iron_repeatability_ut=0.0, mag_disturbances_per_minute=0.0)
# BROAD trials with an undisturbed field (the recovery read is the filters')
REAL_TRIALS = ("01_undisturbed_slow_rotation_A", "04_undisturbed_slow_rotation_with_breaks_A",
               "08_undisturbed_fast_rotation_with_breaks_A")


def _angle(q, r):
    return np.degrees(2 * np.arccos(np.abs(np.sum(q * r, 1)).clip(max=1.0)))


def _inclination(q, r):
    from scipy.spatial.transform import Rotation

    up = lambda x: Rotation.from_quat(x[:, [1, 2, 3, 0]]).inv().apply([0, 0, 1])  # noqa: E731
    return np.degrees(np.arccos(np.clip(np.sum(up(q) * up(r), 1), -1, 1)))


@pytest.fixture(scope="module")
def walk():
    return simulate("walking", 60.0, RATE, seed=5, device_seed=2, **CLEAN_MAG)


def _frozen(seq, sensor):
    f = copy.deepcopy(seq)
    arr = f.gyro if sensor == "gyro" else f.accel
    arr[K0:K1] = arr[K0]
    return f


@pytest.mark.parametrize("sensor", ["gyro", "acc"])
def test_a_frozen_sensor_is_flagged_and_the_filter_recovers_faster_than_vqf(walk, sensor):
    from tcn_ahrs.estimators.registry import build

    f = _frozen(walk, sensor)
    out = bb.run(f.gyro, f.accel, f.mag, f.dt, bb.BackboneParams(), q0=f.quat[0])
    flag = out[f"{sensor}_frozen"]
    onset = int(0.1 * RATE) + 1
    assert flag[K0 + onset:K1].all() and not flag[:K0].any() and not flag[K1 + 1:].any()
    other = out["acc_frozen" if sensor == "gyro" else "gyro_frozen"]
    assert not other.any()
    vqf = build("vqf", 9).run(f, f.quat[0], 0).quat
    after = slice(K1 + int(10 * RATE), K1 + int(20 * RATE))  # 10-20 s after the fault
    ours, theirs = _angle(out["quat"], f.quat)[after].mean(), _angle(vqf, f.quat)[after].mean()
    assert ours <= theirs  # measured: gyro 1.1 vs 40.4 (the heading taken again after), accelerometer 1.7 vs 2.2 deg
    if sensor == "gyro":  # held, not integrated: the inclination stays (2.6 vs 47 deg integrating it)
        unchecked = bb.run(f.gyro, f.accel, f.mag, f.dt, bb.BackboneParams(frozen_time=0.0), q0=f.quat[0])
        during = slice(K0, K1)
        assert _inclination(out["quat"], f.quat)[during].mean() < 0.2 * _inclination(unchecked["quat"],
                                                                                     f.quat)[during].mean()


@pytest.mark.parametrize("profile", ["walking", "fast_rotation"])
@pytest.mark.parametrize("sensor", ["gyro", "acc"])
def test_a_frozen_sensor_with_ground_truth_is_not_refused_as_a_mount_or_a_unit(profile, sensor):
    """Issue: 5 s of a frozen gyro in fast motion was refused as "body frame rotated 10.7 deg", a
    frozen accelerometer as "expected rad/s … deg/s"; the agreement checks (units, wiring, mount)
    judge only what the recording shows with evidence, and the frozen seconds do not make it."""
    seq = simulate(profile, 60.0, RATE, seed=5, device_seed=2)
    f = _frozen(seq, sensor)
    loaded = dataclasses.replace(f, check_units=True)  # every check of a loaded recording runs
    assert len(loaded) == len(seq)


def _with_gap(seq, k0, n):
    """``seq`` with samples k0 .. k0 + n - 1 lost (the stamps jump over them)."""
    keep = np.r_[0:k0, k0 + n:len(seq)]
    names = ("time", "gyro", "accel", "mag", "quat", "quat_valid", "score_mask")
    return dataclasses.replace(seq, **{a: getattr(seq, a)[keep] for a in names if getattr(seq, a) is not None})


def test_a_gap_is_flagged_and_the_attitude_recovers_as_fast_as_vqf(walk):
    """0.5 s of samples lost while walking (the loaders take gaps up to conventions.MAX_DT, with
    a warning): flagged on the one long step; the gyro over it is the mean of the readings either
    side and the low-pass filters hold, so the error 10-20 s after is VQF's on the stream
    resampled onto its grid (3.1°); integrating the last reading over the gap: 23.0°."""
    from tcn_ahrs.estimators.registry import build

    f = _with_gap(walk, K0, 50)
    with pytest.warns(UserWarning, match=r"1 gap\(s\) in the IMU stream \(0.51 s at t = 19.99"):
        dataclasses.replace(f, check_units=True)  # a loaded recording's checks
    out = bb.run(f.gyro, f.accel, f.mag, f.dt, bb.BackboneParams(), q0=f.quat[0])
    assert out["gap"][K0] and out["gap"].sum() == 1
    after = slice(K0 + int(10 * RATE), K0 + int(20 * RATE))
    err = lambda q: _angle(np.asarray(q), f.quat)[after].mean()  # noqa: E731
    ours, vqf = err(out["quat"]), err(build("vqf", 9).run(f, f.quat[0], 0).quat)
    unchecked = err(bb.run(f.gyro, f.accel, f.mag, f.dt, bb.BackboneParams(gap_factor=0.0), q0=f.quat[0])["quat"])
    assert ours <= vqf + 0.05 and unchecked > 5.0 * ours


def test_after_a_gap_in_real_recordings_the_heading_recovers_as_fast_as_vqf():
    """BROAD's undisturbed trials with 0.9 s lost at 30 s: heading error 10-20 s after, mean over
    the trials, no worse than VQF's (measured 6.2 vs 11.4°; with the last reading integrated over
    the gap 29.3°)."""
    from omegaconf import OmegaConf

    from tcn_ahrs.config import conf_path
    from tcn_ahrs.datasets import load_split
    from tcn_ahrs.estimators.registry import build
    from tcn_ahrs.metrics import broad_error_angles

    cfg = OmegaConf.to_container(OmegaConf.load(conf_path("data", "broad.yaml")), resolve=True)
    if not Path(cfg["root"]).is_dir():
        pytest.skip("BROAD not in ../shared")
    cfg["fold"] = None
    trials = REAL_TRIALS
    methods = {"ours": build("backbone", 9), "vqf": build("vqf", 9),
               "unchecked": build("backbone", 9, extra={"gap_factor": 0.0})}
    err = {k: [] for k in methods}
    for seq in load_split(cfg, "trainval"):
        if seq.name not in trials:
            continue
        k0 = int(30 * seq.rate)
        with pytest.warns(UserWarning, match="gap"):
            f = _with_gap(seq, k0, int(0.9 * seq.rate))
        after = slice(k0 + int(10 * f.rate), k0 + int(20 * f.rate))
        ok = np.isfinite(f.quat[after]).all(1)
        for name, est in methods.items():
            q = np.asarray(est.run(f, f.quat[0], 0).quat)[after][ok]
            err[name].append(np.degrees(np.abs(broad_error_angles(f.quat[after][ok], q)["heading"])).mean())
    assert len(err["ours"]) == len(trials)
    mean = {k: float(np.mean(v)) for k, v in err.items()}
    assert mean["ours"] <= mean["vqf"] and mean["unchecked"] > 2.0 * mean["ours"], mean


def test_after_a_frozen_gyro_in_real_recordings_the_heading_recovers_faster_than_vqf():
    """BROAD's undisturbed trials 01, 04 and 08, the gyro frozen for 5 s at 30 s: heading error
    10-20 s after, mean over the trials, 7.0° against VQF's 10.2° (integrating the frozen reading;
    held without taking the heading again 12.3°, taken again at once 20.1°)."""
    from omegaconf import OmegaConf

    from tcn_ahrs.config import conf_path
    from tcn_ahrs.datasets import load_split
    from tcn_ahrs.estimators.registry import build
    from tcn_ahrs.metrics import broad_error_angles

    cfg = OmegaConf.to_container(OmegaConf.load(conf_path("data", "broad.yaml")), resolve=True)
    if not Path(cfg["root"]).is_dir():
        pytest.skip("BROAD not in ../shared")
    cfg["fold"] = None
    err = {"ours": [], "vqf": []}
    for seq in load_split(cfg, "trainval"):
        if seq.name not in REAL_TRIALS:
            continue
        k0, k1 = int(30 * seq.rate), int(35 * seq.rate)
        gyro = seq.gyro.copy()
        gyro[k0:k1] = gyro[k0]
        f = dataclasses.replace(seq, gyro=gyro)
        after = slice(k1 + int(10 * f.rate), k1 + int(20 * f.rate))
        ok = np.isfinite(f.quat[after]).all(1)
        for name in err:
            q = np.asarray(build("backbone" if name == "ours" else "vqf", 9).run(f, f.quat[0], 0).quat)[after][ok]
            err[name].append(np.degrees(np.abs(broad_error_angles(f.quat[after][ok], q)["heading"])).mean())
    assert len(err["ours"]) == len(REAL_TRIALS)
    assert np.mean(err["ours"]) < np.mean(err["vqf"]), err


def test_the_c_runtime_flags_a_frozen_gyro(tmp_path):
    import shutil

    from tcn_ahrs.export.c import CRuntime, compile_c, export_c

    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler")
    ckpt = Path(__file__).resolve().parents[1] / "checkpoints" / "broad9_residual.ckpt"
    paths = export_c(ckpt, tmp_path, "m")
    rt = CRuntime(compile_c(paths["c"], tmp_path / "libm.so", "double", cc), "m", 9)
    rate = 285.71
    seq = simulate("walking", 20.0, rate, seed=1, device_seed=2, **CLEAN_MAG)
    imu = np.concatenate([seq.gyro, seq.accel, seq.mag], 1).astype(np.float32)
    k0, k1 = int(8 * rate), int(13 * rate)
    imu[k0:k1, :3] = imu[k0, :3]
    rt.reset(seq.quat[0])
    flags = np.array([rt.step(imu[k], 1.0 / rate)[4] for k in range(imu.shape[0])])
    frozen = (flags & 16) > 0
    assert frozen[k0 + int(0.1 * rate) + 1:k1].all() and not frozen[:k0].any() and not frozen[k1 + 1:].any()
    assert not (flags & 32).any() and not (flags & 256).any()
    # a gap (one step of 0.5 s): flagged 256 on that step only
    code, *_, flag = rt.step(imu[-1], 0.5)
    assert code == 0 and flag & 256 and not rt.step(imu[-1], 1.0 / rate)[4] & 256
    # the same runtime on a gyro clipped at ±150 °/s flags it (64)
    lim = np.radians(150.0)
    fast = simulate("fast_rotation", 30.0, rate, seed=1, device_seed=2, **CLEAN_MAG)
    imu = np.concatenate([np.clip(fast.gyro, -lim, lim), fast.accel, fast.mag], 1).astype(np.float32)
    rt.reset(fast.quat[0])
    flags = np.array([rt.step(imu[k], 1.0 / rate)[4] for k in range(imu.shape[0])])
    stuck = (np.abs(imu[:, :3]) >= np.float32(lim)).any(1)
    clipped = (flags & 64) > 0
    assert stuck.sum() > 50 and not (clipped & ~stuck).any() and clipped[stuck].mean() > 0.6


@pytest.mark.parametrize("dataset", ["broad", "euroc", "tumvi", "oxiod"])
def test_real_recordings_raise_no_frozen_flag(dataset):
    """The longest exact repeat of all three readings in the four datasets is 5 samples (BROAD);
    the check needs 10 samples and 0.1 s. Nothing there saturates either."""
    from omegaconf import OmegaConf

    from tcn_ahrs.config import conf_path
    from tcn_ahrs.datasets import load_split

    cfg = OmegaConf.to_container(OmegaConf.load(conf_path("data", f"{dataset}.yaml")), resolve=True)
    if not Path(cfg["root"]).is_dir():
        pytest.skip(f"{dataset} not in ../shared")
    cfg["fold"] = None
    for seq in load_split(cfg, "trainval")[:3]:
        out = bb.run(seq.gyro, seq.accel, seq.mag, seq.dt, bb.BackboneParams(), q0=np.array([1.0, 0, 0, 0]))
        assert not out["gyro_frozen"].any() and not out["acc_frozen"].any(), seq.name
        assert not out["gyro_clipped"].any() and not out["acc_clipped"].any(), seq.name


def test_a_clipped_gyro_is_flagged_without_ground_truth():
    """A gyro clipped at ±250 °/s (the loader names it only with ground truth): flagged on the
    samples it sticks at its extreme, nowhere else, in the batch filter and the C runtime."""
    seq = simulate("fast_rotation", 30.0, RATE, seed=1, device_seed=2, **CLEAN_MAG)
    lim = np.radians(250.0)
    f = copy.deepcopy(seq)
    f.gyro = np.clip(f.gyro, -lim, lim)
    stuck = (np.abs(f.gyro) >= lim).any(1)
    out = bb.run(f.gyro, f.accel, f.mag, f.dt, bb.BackboneParams(), q0=f.quat[0])
    flag = out["gyro_clipped"]
    # from the 5th sample of each stuck run on (a quantised smooth peak repeats once or twice)
    assert stuck.sum() > 100 and not (flag & ~stuck).any() and flag[stuck].mean() > 0.6
    assert not bb.run(seq.gyro, seq.accel, seq.mag, seq.dt, bb.BackboneParams(), q0=seq.quat[0])["gyro_clipped"].any()


def test_a_clipped_accelerometer_is_flagged_and_not_trusted():
    seq = simulate("fast_rotation", 30.0, RATE, seed=1, device_seed=2, **CLEAN_MAG)
    lim = 11.0  # m/s^2: a range this motion exceeds (the floor lowered to match)
    f = copy.deepcopy(seq)
    f.accel = np.clip(f.accel, -lim, lim)
    stuck = (np.abs(f.accel) >= lim).any(1)
    params = bb.BackboneParams(acc_clip_floor=10.0)
    out = bb.run(f.gyro, f.accel, f.mag, f.dt, params, q0=f.quat[0])
    flag = out["acc_clipped"]
    assert stuck.sum() > 20 and not (flag & ~stuck).any() and flag[stuck].mean() > 0.3
    # clipped just above gravity, the readings barely err: not trusting them (nor for tau_acc after
    # each, while the low-passed direction still holds them) costs 0.17 deg here (1.46 vs 1.29); on
    # a real ±2 g clip it is the whole difference (test below)
    trusting = bb.run(f.gyro, f.accel, f.mag, f.dt, bb.BackboneParams(acc_clip_floor=0.0), q0=f.quat[0])
    assert _inclination(out["quat"], f.quat).mean() <= _inclination(trusting["quat"], f.quat).mean() + 0.25


def test_the_onnx_streaming_step_reports_the_flags(tmp_path):
    """The exported step graph returns its state; the metadata names where the flags lie in it
    (``state.flags``), and the streaming wrapper reads them: a frozen gyro is flagged."""
    pytest.importorskip("onnxruntime")
    from tcn_ahrs.export.onnx_step import OnnxStreaming, export_onnx

    ckpt = Path(__file__).resolve().parents[1] / "checkpoints" / "broad9_residual.ckpt"
    paths = export_onnx(ckpt, tmp_path / "m.onnx", mode="streaming")
    rt = OnnxStreaming(paths["streaming"])
    assert set(rt.metadata["state"]["flags"]) >= {"gyro_frozen", "acc_frozen", "gyro_clipped", "acc_clipped", "gap"}
    rate = 285.71
    seq = simulate("walking", 8.0, rate, seed=1, device_seed=2, **CLEAN_MAG)
    imu = np.concatenate([seq.gyro, seq.accel, seq.mag], 1)
    k0, k1 = int(3 * rate), int(6 * rate)
    imu[k0:k1, :3] = imu[k0, :3]
    rt.reset(seq.quat[0])
    frozen = []
    for k in range(imu.shape[0]):
        rt.step(imu[k], 1.0 / rate)
        frozen.append(rt.flags()["gyro_frozen"])
    frozen = np.array(frozen)
    assert frozen[k0 + int(0.1 * rate) + 1:k1].all() and not frozen[:k0].any() and not frozen[k1 + 1:].any()


def test_the_fault_table_names_every_fault_and_the_checks_help():
    """``python scripts/benchmark.py faults`` (one seed here): every injected fault is flagged on
    most of its samples, and the checks never leave the filter worse 10-20 s after it."""
    from tcn_ahrs.bench.faults import fault_table, markdown

    result = fault_table(seeds=(0,), ckpt=None)
    for case, row in result["rows"].items():
        assert row["flagged_share"] > 0.9, case
        e = row["errors"]
        assert e["now"]["after"] <= e["before"]["after"] + 0.2, case
    assert "| gyro frozen 5 s | `gyro_frozen`" in markdown(result)


def test_the_learned_closed_loop_holds_through_a_frozen_gyro(monkeypatch):
    """The shipped closed loop (checkpoints/euroc6_closed_loop.ckpt, its own filter, not the backbone's kernel):
    a gyro frozen for 5 s while walking is held, not integrated (inclination during the fault,
    three walks: 6.8° against 20.2° unchecked, VQF 40.0°; its clean error on this simulated device
    6.3°). Every runtime's check is compared in tests/test_export_closed_loop.py."""
    import tcn_ahrs.model.closed_loop as cl
    from tcn_ahrs.estimators.learned import LearnedEstimator
    from tcn_ahrs.metrics import broad_error_angles

    rate = 200.0
    seq = dataclasses.replace(simulate("walking", 30.0, rate, seed=0, device_seed=1), mag=None)
    k0, k1 = int(10 * rate), int(15 * rate)
    gyro = seq.gyro.copy()
    gyro[k0:k1] = gyro[k0]
    f = dataclasses.replace(seq, gyro=gyro)
    est = LearnedEstimator(Path(__file__).resolve().parents[1] / "checkpoints" / "euroc6_closed_loop.ckpt")

    def inclination_during():
        q = np.asarray(est.run(f, f.quat[0], 0).quat)
        return np.degrees(broad_error_angles(f.quat, q)["inclination"])[k0:k1].mean()

    ours = inclination_during()
    monkeypatch.setattr(cl, "frozen_detector", lambda x, window: torch.zeros_like(x[..., 0]))
    assert ours < 0.5 * inclination_during()


def test_evaluate_names_what_the_health_checks_found_per_recording(tmp_path, capsys):
    """`tcn-ahrs evaluate` (the default backbone here) prints per recording what its health checks
    found — "gyro frozen 4.9 s from 5.1 s" — and writes it to results.json; a clean recording reads
    "no fault found" (the flags were computed and never shown)."""
    import json

    from tcn_ahrs.cli import main

    root = tmp_path / "data"
    root.mkdir()
    header = "t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,quat_w,quat_x,quat_y,quat_z"
    for name, frozen in (("clean", False), ("frozen", True)):
        s = simulate("walking", 20.0, RATE, seed=1, axes=6)
        g = s.gyro.copy()
        if frozen:
            g[500:1000] = g[500]  # 5 s from 5 s
        np.savetxt(root / f"{name}.csv", np.column_stack([s.time, g, s.accel, s.quat]), delimiter=",", comments="",
                   fmt="%.10g", header=header)
    out = tmp_path / "ev"
    main(["evaluate", "data=generic", f"data.root={root}", "data.axes=6", "data.split=all", f"out={out}",
          "plots=false", "trajectories=false", f"hydra.run.dir={tmp_path / 'h'}"])
    printed = capsys.readouterr().out
    assert "health, clean (Backbone (default)): no fault found" in printed
    line = next(x for x in printed.splitlines() if x.startswith("health, frozen"))
    assert "gyro frozen" in line and "from 5." in line, line
    rows = {r["name"]: r for r in json.loads((out / "results.json").read_text())["methods"]["Backbone (default)"]["recordings"]}
    assert rows["clean"]["health"] == [] and rows["frozen"]["health"][0].startswith("gyro frozen 4.9 s")
