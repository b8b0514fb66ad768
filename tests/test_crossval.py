"""scripts/crossval.py end to end on a tiny generic folder: every fold trains on the other
recordings, is scored on its own next to the baselines, and the summary is mean ± spread."""
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from tcn_ahrs.experiments.crossval import crossval_main, summarize
from tcn_ahrs.datasets.simulate import simulate
from tcn_ahrs.conf import CONF_DIR

CONF = CONF_DIR


def _write(path: Path, seq):
    table = np.column_stack([seq.time, seq.gyro, seq.accel, seq.mag, seq.quat])
    header = "t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z,quat_w,quat_x,quat_y,quat_z"
    np.savetxt(path, table, delimiter=",", header=header, comments="", fmt="%.10g")


def test_summary_mean_and_sample_spread():
    folds = [{"means": {"m": {"aae_deg": 1.0}}}, {"means": {"m": {"aae_deg": 3.0, "ahe_deg": None}}}]
    s = summarize(folds)
    assert s["m"]["aae_deg"] == {"mean": 2.0, "std": pytest.approx(2 ** 0.5), "n": 2}
    assert "ahe_deg" not in s["m"]


def test_crossval_runs_every_fold(tmp_path):
    for i, prof in enumerate(["slow_rotation", "walking", "fast_rotation"]):
        _write(tmp_path / f"r{i}.csv", simulate(prof, 30.0, 50.0, seed=i))
    out = tmp_path / "cv"
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("crossval", overrides=[
            "data=generic", f"data.root={tmp_path}", "data.train=[r0,r1,r2]", "data.folds=[[r0],[r1,r2]]",
            "train.epochs=1", "train.window=200", "train.stride=100", "train.batch_size=4",
            "model.tcn.channels=[4,4,4,4]", "trainer.enable_progress_bar=false", "threads=1",
            "crossval.methods=[raw]", "crossval.peers=false", f"crossval.out={out}"])
    res = crossval_main(cfg)
    assert [f["fold"] for f in res["folds"]] == [0, 1]
    assert res["folds"][1]["recordings"] == ["r1", "r2"]
    assert {"Learned", "Raw IMU"} <= set(res["summary"])
    assert res["summary"]["Raw IMU"]["aae_deg"]["n"] == 2
    assert (out / "crossval.md").is_file() and (out / "fold0" / "TRAINED").is_file()
    # a second call reuses the finished folds instead of training again
    mtime = (out / "fold0" / "checkpoints" / "best.ckpt").stat().st_mtime
    crossval_main(cfg)
    assert (out / "fold0" / "checkpoints" / "best.ckpt").stat().st_mtime == mtime


def test_inner_validation_never_holds_the_outer_fold(tmp_path):
    """Nested folds: with >= 3 folds the next fold validates, whole; with fewer, the later parts of
    the other recordings; the outer fold is in neither."""
    from tcn_ahrs.experiments.crossval import _fold_cfg, inner_split

    names = [f"r{i}" for i in range(4)]
    for i, n in enumerate(names):
        _write(tmp_path / f"{n}.csv", simulate("slow_rotation", 4.0, 50.0, seed=i))
    for folds, mode in (([["r0"], ["r1"], ["r2"], ["r3"]], "fold"), ([["r0", "r1"], ["r2", "r3"]], "split")):
        with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
            cfg = compose("crossval", overrides=["data=generic", f"data.root={tmp_path}", f"data.train={names}",
                                                 f"data.folds={folds}", "data.train_part={fraction: 0.5}"])
        for i, held in enumerate(folds):
            train, val, what = inner_split(cfg, folds, i, _fold_cfg(cfg, i, tmp_path / "cv"))
            assert not {s.name for s in train + val} & set(held)
            if mode == "fold":
                assert [s.name for s in val] == folds[(i + 1) % 4] and len(train) == 2
            else:  # the same recordings, first half trains, second half validates
                assert [s.name for s in train] == [s.name for s in val] and len(val) == 2
                assert all(v.time[0] > t.time[-1] for t, v in zip(train, val))


def test_untrained_mode_scores_each_variant_on_training_and_held_out_recordings(tmp_path):
    for i, prof in enumerate(["slow_rotation", "walking"]):
        _write(tmp_path / f"r{i}.csv", simulate(prof, 8.0, 50.0, seed=i))
    out = tmp_path / "cv"
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("crossval", overrides=[
            "data=generic", f"data.root={tmp_path}", "data.train=[r0,r1]", "data.folds=[[r0],[r1]]",
            "model.tcn.channels=[4,4,4,4]", "threads=1", f"crossval.out={out}",
            "crossval.untrained=[{},{acc_gain:1e-9,mag_gain:1e-9}]"])
    rows = crossval_main(cfg)["rows"]
    assert [(r["fold"], r["variant"]) for r in rows] == [(0, {}), (0, {"acc_gain": 1e-9, "mag_gain": 1e-9}),
                                                          (1, {}), (1, {"acc_gain": 1e-9, "mag_gain": 1e-9})]
    # fold 0 trains on r1 and holds r0 out; fold 1 the reverse: the same loop scores the same
    assert rows[0]["training"] == pytest.approx(rows[2]["held out"])
    assert all(np.isfinite([r["training"], r["held out"]]).all() for r in rows)
    assert (out / "untrained.md").is_file() and not (out / "fold0").exists()


def test_residual_model_chooses_its_knobs_on_the_inner_fold_and_can_choose_again(tmp_path):
    """model=residual: each outer fold's checkpoint carries knobs chosen on the inner fold
    (knobs.json beside it names those recordings, never the outer ones); crossval.reselect
    chooses again without training; release_knobs is one point of the grid."""
    import json

    from tcn_ahrs.checkpoint import checkpoint_meta, load_checkpoint
    from tcn_ahrs.tuning.knobs import residual_knob_points

    for i, prof in enumerate(["slow_rotation", "walking", "fast_rotation"]):
        _write(tmp_path / f"r{i}.csv", simulate(prof, 30.0, 50.0, seed=i))
    out = tmp_path / "cv"
    overrides = ["data=generic", f"data.root={tmp_path}", "data.train=[r0,r1,r2]", "data.folds=[[r0],[r1],[r2]]",
                 "model=residual", "train.epochs=1", "train.window=200", "train.stride=100", "train.batch_size=4",
                 "train.tune_backbone=false", "model.tcn.channels=[4,4,4,4]", "trainer.enable_progress_bar=false",
                 "threads=1", "crossval.methods=[raw]", "crossval.peers=false", f"crossval.out={out}"]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("crossval", overrides=overrides)
    res = crossval_main(cfg)
    points = [tuple(sorted(p.items())) for p in residual_knob_points()]
    assert tuple(sorted(res["release_knobs"]["knobs"].items())) in points
    for i in range(3):
        knobs = json.loads((out / f"fold{i}" / "knobs.json").read_text())
        assert knobs["on"] == [f"r{(i + 1) % 3}"]
        meta = checkpoint_meta(load_checkpoint(out / f"fold{i}" / "checkpoints" / "last.ckpt"))
        assert {k: meta["model"]["residual"][k] for k in knobs["chosen"]} == knobs["chosen"]
    trained = (out / "fold0" / "TRAINED").stat().st_mtime_ns
    chosen = (out / "fold0" / "knobs.json").stat().st_mtime_ns
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("crossval", overrides=overrides + ["crossval.reselect=true"])
    crossval_main(cfg)
    assert (out / "fold0" / "TRAINED").stat().st_mtime_ns == trained  # not trained again
    assert (out / "fold0" / "knobs.json").stat().st_mtime_ns > chosen  # the knobs chosen again
