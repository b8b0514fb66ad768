"""Training glue: Hydra entry (compose API) -> checkpoints, resume, determinism, config errors,
checkpoint layout checks, atomic saves; DDP with 2 CPU processes (slow)."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf.errors import ConfigAttributeError

from tcn_ahrs.checkpoint import CheckpointError, atomic_save, check_layout, load_checkpoint, model_from_checkpoint
from tcn_ahrs.datasets.simulate import simulate
from tcn_ahrs.estimators.learned import LearnedEstimator
from tcn_ahrs.training.run import train_main
from tcn_ahrs.conf import CONF_DIR

REPO = Path(__file__).resolve().parents[1]
CONF = CONF_DIR
# the learned closed loop (model=ahrs): what these pipeline tests were written against (start at the
# given attitude, best.ckpt by validation); the default (model=residual) is tested in test_residual.py
TINY = ["data=generic", "model=ahrs", "train.epochs=2", "train.window=400", "train.stride=200", "train.batch_size=4",
        "model.tcn.channels=[4,4,4,8]", "trainer.enable_progress_bar=false", "eval.plots=false",
        "eval.trajectories=false", "eval.baselines=[]", "threads=1"]


@pytest.fixture(scope="module")
def seqs():
    tr = [simulate(p, 20.0, 50.0, s) for s, p in enumerate(["slow_rotation", "walking"])]
    va = [simulate("slow_rotation", 12.0, 50.0, 50)]
    te = [simulate("walking", 12.0, 50.0, 60)]
    return tr, va, te


def _cfg(overrides):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("train", overrides=overrides)


def _train(tmp, seqs, extra=()):
    cfg = _cfg(TINY + [f"run_dir={tmp}"] + list(extra))
    return train_main(cfg, *seqs)


def test_tiny_run_writes_checkpoints_config_and_resumes(tmp_path, seqs):
    run = tmp_path / "run"
    res = _train(run, seqs)
    ck = run / "checkpoints"
    assert (ck / "last.ckpt").is_file() and (ck / "best.ckpt").is_file()
    assert (run / "config_resolved.yaml").is_file()
    assert "window: 400" in (run / "config_resolved.yaml").read_text()
    assert res["results"] is not None and "Learned AHRS" in res["results"]["methods"]
    last = load_checkpoint(ck / "last.ckpt")
    assert last["epoch"] == 1 and last["tcn_ahrs"]["layout"]["axes"] == 9
    assert not list(ck.glob("*.tmp"))  # no leftovers of the atomic writes
    # resume with one override: continues from last.ckpt to epoch 3, and keeps the log history
    import csv

    def rows():
        with open(run / "logs" / "metrics.csv", newline="") as fh:
            return list(csv.DictReader(fh))

    before = rows()
    _train(run, seqs, ["resume=true", "train.epochs=3"])
    assert load_checkpoint(ck / "last.ckpt")["epoch"] == 2
    after = rows()
    assert sorted({int(r["epoch"]) for r in after if r.get("epoch")}) == [0, 1, 2]
    assert len(after) > len(before)
    # explicit ckpt_path into a fresh run dir
    _train(tmp_path / "run2", seqs, [f"ckpt_path={ck / 'last.ckpt'}", "train.epochs=4"])
    assert load_checkpoint(tmp_path / "run2" / "checkpoints" / "last.ckpt")["epoch"] == 3
    # the learned estimator runs the checkpoint; signals are there
    est = LearnedEstimator(ck / "best.ckpt")
    out = est.run(seqs[2][0], seqs[2][0].quat[0])
    n = len(seqs[2][0])
    assert out.quat.shape == (n, 4) and np.allclose(out.quat[0], seqs[2][0].quat[0], atol=1e-6)
    for k in ("gyro_correction", "gyro_bias", "acc_error", "mag_error"):
        assert out.signals[k].shape == (n, 3)


def test_resume_after_a_kill_is_the_uninterrupted_run(tmp_path, seqs):
    """A run killed in its second epoch and resumed with only resume=true run_dir=... (the
    README's command) restores its own overrides (train.epochs=3, not the default), continues the
    same schedule and ends with the uninterrupted run's weights and final metrics; the killed
    epoch's rows are not in metrics.csv twice; config_resolved.yaml stays the run's own."""
    import csv

    import pytorch_lightning as pl

    class Kill(pl.Callback):
        def on_train_batch_end(self, trainer, *args):
            if trainer.current_epoch == 1:  # in the middle of the second epoch
                raise RuntimeError("killed")

    def rows(run):
        with open(run / "logs" / "metrics.csv", newline="") as fh:
            return [r for r in csv.DictReader(fh)]

    own = ["train.epochs=3", "train.lr=0.002", "trainer.log_every_n_steps=1"]
    _train(tmp_path / "whole", seqs, own)
    run = tmp_path / "killed"
    with pytest.raises(RuntimeError, match="killed"):
        train_main(_cfg(TINY + [f"run_dir={run}"] + own), *seqs, callbacks=[Kill()])
    saved = (run / "config_resolved.yaml").read_text()
    train_main(_cfg(TINY + [f"run_dir={run}", "resume=true"]), *seqs, overrides=["resume=true", f"run_dir={run}"])
    assert (run / "config_resolved.yaml").read_text() == saved and "epochs: 3" in saved
    a = load_checkpoint(tmp_path / "whole" / "checkpoints" / "last.ckpt")
    b = load_checkpoint(run / "checkpoints" / "last.ckpt")
    assert a["epoch"] == b["epoch"] == 2
    for k in a["state_dict"]:  # (conv biases before BatchNorm get ~0 gradients: float noise, Adam-scaled)
        torch.testing.assert_close(b["state_dict"][k], a["state_dict"][k], rtol=1e-3, atol=1e-4)
    ra, rb = rows(tmp_path / "whole"), rows(run)
    key = lambda r: (r.get("epoch"), r.get("step"), tuple(sorted(k for k, v in r.items() if v)))  # noqa: E731
    assert sorted(map(key, rb)) == sorted(map(key, ra))  # no row twice, none missing
    final = [{k: float(v) for k, v in r.items() if v and k.startswith("val/")} for r in (ra, rb)
             for r in [[x for x in r if x.get("val/loss")][-1]]]
    assert final[0].keys() == final[1].keys() and final[0]
    for k in final[0]:
        assert final[1][k] == pytest.approx(final[0][k], rel=1e-4), k


def test_resume_names_a_changed_setting(tmp_path, seqs, capsys):
    run = tmp_path / "run"
    _train(run, seqs, ["train.epochs=1"])
    train_main(_cfg(TINY + [f"run_dir={run}", "resume=true", "train.epochs=2"]), *seqs,
               overrides=["resume=true", "train.epochs=2"])
    assert "resume: this command changes the saved run's configuration: train.epochs: 1 -> 2" in capsys.readouterr().out
    assert load_checkpoint(run / "checkpoints" / "last.ckpt")["epoch"] == 1


def test_training_is_deterministic(tmp_path, seqs):
    _train(tmp_path / "a", seqs, ["train.epochs=1"])
    _train(tmp_path / "b", seqs, ["train.epochs=1"])
    a = load_checkpoint(tmp_path / "a" / "checkpoints" / "last.ckpt")["state_dict"]
    b = load_checkpoint(tmp_path / "b" / "checkpoints" / "last.ckpt")["state_dict"]
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert a["model.calibration.gyro_error_net.out.weight"].abs().sum() > 0  # it did train


def test_misspelt_config_keys_raise():
    with pytest.raises(ConfigCompositionException):
        _cfg(["train.lr2=0.1"])
    with pytest.raises(ConfigCompositionException):
        _cfg(["model.tcn.kernal_size=3"])
    with pytest.raises(ConfigCompositionException):
        _cfg(["trainr=gpu"])
    cfg = _cfg(["data=generic"])
    with pytest.raises(ConfigAttributeError):
        cfg.train.learning_rate  # struct mode: reading a missing key is an error too


def test_six_axis_checkpoint_on_nine_axis_data(tmp_path, seqs):
    """Loading for 9-axis input is refused (the layout differs), but evaluating a 6-axis
    checkpoint on 9-axis recordings simply scores the 6-axis view."""
    _train(tmp_path / "r6", seqs, ["model=ahrs6", "train.epochs=1"])
    path = tmp_path / "r6" / "checkpoints" / "last.ckpt"
    ck = load_checkpoint(path)
    assert ck["tcn_ahrs"]["layout"]["axes"] == 6
    check_layout(ck, 6, path)
    with pytest.raises(CheckpointError, match=r"ahrs6.*6-axis.*data provides 9 axes.*data.axes=6"):
        check_layout(ck, 9, path)
    with pytest.raises(CheckpointError, match="9 axes"):
        model_from_checkpoint(path, axes=9)
    # the evaluation CLI runs it on 9-axis recordings as 6-axis
    rec = seqs[2][0]
    (tmp_path / "data").mkdir()
    np.savetxt(tmp_path / "data" / "w.csv", np.column_stack([rec.time, rec.gyro, rec.accel, rec.mag, rec.quat]),
               delimiter=",", comments="", fmt="%.10g",
               header="t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z,quat_w,quat_x,quat_y,quat_z")
    r = subprocess.run([sys.executable, "scripts/evaluate.py", f"ckpt={path}", "data=generic",
                        f"data.root={tmp_path / 'data'}", "data.split=all", f"out={tmp_path / 'ev'}",
                        f"hydra.run.dir={tmp_path / 'ev'}", "plots=false", "trajectories=false"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "6-axis model: the magnetometer is not used" in r.stdout
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert res["methods"]["Learned AHRS"]["recordings"][0]["axes"] == 6


def test_atomic_save_keeps_old_file_on_failure(tmp_path, monkeypatch):
    p = tmp_path / "last.ckpt"
    atomic_save({"a": torch.ones(2)}, p)

    def broken(obj, fh, *a, **k):
        fh.write(b"partial")
        raise RuntimeError("disk full")

    monkeypatch.setattr(torch, "save", broken)
    with pytest.raises(RuntimeError, match="disk full"):
        atomic_save({"a": torch.zeros(2)}, p)
    monkeypatch.undo()
    assert torch.equal(load_checkpoint(p)["a"], torch.ones(2))
    assert [f.name for f in tmp_path.iterdir()] == ["last.ckpt"]


def test_staged_files_write_all_or_none(tmp_path):
    """The one write path of every file output (export formats, checkpoints): a failure in any
    file leaves every target as it was and no temporary behind; an OS error is named."""
    from tcn_ahrs.app import staged_files

    a, b = tmp_path / "m.pt", tmp_path / "m_streaming.pt"
    a.write_text("old a")

    def failing(key, tmp):
        tmp.write_text("new " + key)
        if key == "b":
            raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        staged_files({"a": a, "b": b}, failing)
    assert a.read_text() == "old a" and not b.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["m.pt"]
    assert staged_files({"a": a, "b": b}, lambda k, tmp: tmp.write_text("new " + k)) == {"a": str(a), "b": str(b)}
    assert (a.read_text(), b.read_text()) == ("new a", "new b") and len(list(tmp_path.iterdir())) == 2

    def denied(key, tmp):
        raise PermissionError("read-only")

    with pytest.raises(ValueError, match=r"cannot write .*m.pt.*read-only"):
        staged_files({"a": a}, denied, ValueError)
    assert a.read_text() == "new a"


class _Arbitrary:
    pass


def test_unsafe_checkpoint_is_refused(tmp_path):
    p = tmp_path / "evil.ckpt"
    torch.save({"x": _Arbitrary()}, p)  # loading it would run pickle's class lookup
    with pytest.raises(CheckpointError, match="weights_only"):
        load_checkpoint(p)


@pytest.mark.slow
def test_ddp_two_cpu_processes(tmp_path):
    """trainer=ddp with 2 CPU processes (gloo), through the real script."""
    if sys.platform == "win32":
        pytest.skip("gloo DDP test runs on Linux/macOS")
    env = dict(os.environ, PYTHONPATH=str(REPO))
    cmd = [sys.executable, "scripts/train.py", "trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2",
           "data=simulated", "data.rate=50", "data.splits.train.duration=20", "data.splits.val.duration=10",
           "data.splits.train.count=2", "data.splits.val.count=1", "data.splits.test.count=1",
           "data.splits.test.duration=10", f"run_dir={tmp_path}", f"hydra.run.dir={tmp_path}"] + [
        o for o in TINY if not o.startswith("data=")] + ["train.epochs=1"]
    r = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=85, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    assert (tmp_path / "checkpoints" / "last.ckpt").is_file()
    assert "Average" in r.stdout
    # the recipe that trained it is recorded in the file (its model card reads it, never a name)
    from tcn_ahrs.checkpoint import checkpoint_meta, load_checkpoint

    recipe = checkpoint_meta(load_checkpoint(tmp_path / "checkpoints" / "last.ckpt"))["recipe"]
    assert recipe["command"] == "tcn-ahrs train" and {"trainer=ddp", "train.epochs=1"} <= set(recipe["overrides"])


def test_weight_average_is_what_validation_and_release_use(tmp_path, seqs):
    """train.ema_decay: the checkpoint keeps the raw weights (resume) and their average; the
    average is the model that model_from_checkpoint (evaluation, export, release) builds."""
    run = tmp_path / "ema"
    _train(run, seqs, ["train.ema_decay=0.5"])
    ck = load_checkpoint(run / "checkpoints" / "last.ckpt")
    raw = {k[len("model."):]: v for k, v in ck["state_dict"].items() if k.startswith("model.")}
    avg = {k[len("ema_model."):]: v for k, v in ck["state_dict"].items() if k.startswith("ema_model.")}
    assert set(raw) == set(avg)
    assert any(not torch.equal(raw[k], avg[k]) for k in raw if raw[k].is_floating_point())
    model = model_from_checkpoint(run / "checkpoints" / "last.ckpt")
    for k, v in model.state_dict().items():
        assert torch.equal(v, avg[k])


def test_a_time_cap_that_stops_training_says_so(tmp_path, seqs, capsys):
    res = _train(tmp_path / "cap", seqs, ["train.epochs=50", "train.max_time=00:00:00:01"])
    assert res.get("stopped_by_time_cap")
    assert "time cap train.max_time=00:00:00:01 stopped training after" in capsys.readouterr().err
