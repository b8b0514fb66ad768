"""Fine-tuning that never hurts (tcn_ahrs.training.adaptation): the evidence without ground truth
reads what it claims (drift at rest, the gravity angle), the decision keeps the starting model
without evidence, and a fine-tuning run that is not better ships the start."""
import json

import numpy as np
import pytest
import torch

from tcn_ahrs import so3
from tcn_ahrs.datasets.simulate import simulate
from tcn_ahrs.training.adaptation import decide, gravity_deg, rest_drift_dps


def _turned(quat: np.ndarray, t: np.ndarray, rate_dps: float) -> np.ndarray:
    """quat (N, 4) nav_from_body turned about the navigation frame's up at ``rate_dps`` (a heading drift)."""
    ang = np.radians(rate_dps) * t
    yaw = np.stack([np.cos(ang / 2), 0 * ang, 0 * ang, np.sin(ang / 2)], 1)
    return so3.quat_mul(torch.as_tensor(yaw), torch.as_tensor(quat)).numpy()


def test_drift_at_rest_reads_how_fast_an_estimate_turns_while_the_device_rests():
    seq = simulate("static", 30.0, 100.0, seed=1, device_seed=2)
    truth = rest_drift_dps(seq, seq.quat)
    assert truth is not None and truth[1] > 20.0  # rests most of the half minute
    assert truth[0] < 0.01
    drift, _ = rest_drift_dps(seq, _turned(seq.quat, seq.time, 1.0))
    assert drift == pytest.approx(1.0, rel=0.05)


def _never_resting(seconds=25.0, rate=100.0):
    """A slow tumble (0.2 rad/s about a tilted axis) with sensor noise: never at rest."""
    from test_general import _turning

    seq = _turning(rate, seconds, omega=(0.1, -0.15, 0.05))
    rng = np.random.default_rng(0)
    seq.gyro = seq.gyro + 0.002 * rng.standard_normal(seq.gyro.shape)
    seq.accel = seq.accel + 0.02 * rng.standard_normal(seq.accel.shape)
    return seq


def test_drift_at_rest_is_no_evidence_where_the_device_never_rests():
    seq = _never_resting()
    assert rest_drift_dps(seq, seq.quat) is None


def test_the_gravity_angle_reads_a_tilt_of_the_estimate():
    seq = simulate("static", 20.0, 100.0, seed=1, device_seed=2, noise_free=True)
    assert gravity_deg(seq, seq.quat) < 0.05
    tilt = so3.quat_exp(torch.tensor([np.radians(3.0), 0.0, 0.0], dtype=torch.float64))  # 3° about body x
    tilted = so3.quat_mul(torch.as_tensor(seq.quat), tilt.expand(len(seq), 4)).numpy()
    assert gravity_deg(seq, tilted) == pytest.approx(3.0, abs=0.05)


@pytest.mark.parametrize("before, after, supervision, adopt", [
    ({"aae_deg": 3.0, "inclination_deg": 1.0}, {"aae_deg": 2.0, "inclination_deg": 1.0}, "gt", True),
    ({"aae_deg": 3.0, "inclination_deg": 1.0}, {"aae_deg": 2.0, "inclination_deg": 1.2}, "gt", False),
    ({"aae_deg": 3.0, "inclination_deg": 1.0}, {"aae_deg": 3.1, "inclination_deg": 0.5}, "gt", False),
    ({"aae_deg": None, "inclination_deg": None}, {"aae_deg": None, "inclination_deg": None}, "gt", False),
    ({"rest_drift_dps": 0.5, "rest_s": 10, "gravity_deg": 1.0}, {"rest_drift_dps": 0.1, "rest_s": 10, "gravity_deg": 1.0}, "self", True),
    ({"rest_drift_dps": 0.5, "rest_s": 10, "gravity_deg": 1.0}, {"rest_drift_dps": 0.48, "rest_s": 10, "gravity_deg": 1.0}, "self", False),
    ({"rest_drift_dps": 0.5, "rest_s": 10, "gravity_deg": 1.0}, {"rest_drift_dps": 0.1, "rest_s": 10, "gravity_deg": 1.5}, "self", False),
    ({"rest_drift_dps": None, "rest_s": 0, "gravity_deg": 1.0}, {"rest_drift_dps": None, "rest_s": 0, "gravity_deg": 0.5}, "self", False),
])
def test_the_fine_tuned_model_ships_only_on_evidence(before, after, supervision, adopt):
    got, why = decide(before, after, supervision)
    assert got is adopt
    assert ("fine-tuned model ships" in why) is adopt


def test_self_supervised_fine_tuning_without_rest_to_judge_by_ships_the_start(tmp_path):
    """Held-out parts that never rest: no evidence without ground truth, so the run ships the
    starting model (its weights, marked as taking device-checked input) and says why."""
    from tcn_ahrs.checkpoint import checkpoint_meta, load_checkpoint, model_from_checkpoint
    from tcn_ahrs.training.run import train_main
    from test_general import _compose, _general_checkpoint

    init = _general_checkpoint(tmp_path, axes=6)
    tr = [simulate(p, 20.0, 100.0, s, axes=6) for s, p in enumerate(["static", "walking"])]
    va = [_never_resting()]
    for s in tr + va:
        s.quat, s.quat_valid = None, None
    cfg = _compose(["experiment=finetune", "data=generic", "data.axes=6", f"init={init}", "train.supervision=self",
                    "train.epochs=1", "train.window=400", "train.stride=200", "train.batch_size=4",
                    "trainer.enable_progress_bar=false", "eval.enabled=false", "threads=1",
                    f"run_dir={tmp_path / 'run'}"])
    res = train_main(cfg, tr, va, [])
    record = json.loads((tmp_path / "run" / "adaptation.json").read_text())
    assert record["adopted"] is False and "never rest" in record["why"]
    assert res["best"] == record["shipped"] and res["best"].endswith("kept.ckpt")
    start, shipped = model_from_checkpoint(str(init)), model_from_checkpoint(res["best"])
    for (k, a), b in zip(start.state_dict().items(), shipped.state_dict().values()):
        assert torch.equal(a, b), k
    assert checkpoint_meta(load_checkpoint(res["best"]))["layout"].get("device_check") is True
    assert not torch.equal(start.calibration.gyro_net.out.weight,
                           model_from_checkpoint(res["last"]).calibration.gyro_net.out.weight)  # it did train


def test_a_part_that_never_rests_is_corrected_by_its_recordings_rest():
    """train.device_check: one check per recording, read from the part that rests (a later part in
    flight never rests: EuRoC's 4.4 °/s bias would otherwise stay in it)."""
    from tcn_ahrs.data import AHRSDataModule

    bias = np.radians([1.0, -2.0, 5.0])
    still = simulate("static", 20.0, 100.0, seed=1, device_seed=2, axes=6, noise_free=True)
    still.gyro = still.gyro + bias
    moving = _never_resting()
    moving.gyro = moving.gyro + bias
    for s in (still, moving):
        s.meta["recording"] = "device"
    dm = AHRSDataModule(None, 6, 200, 100, 4, [still], [moving], device_check=True)
    dm.prepare()
    assert np.allclose(dm.val_seqs[0].gyro, moving.gyro - bias, atol=np.radians(0.02))
    assert np.allclose(dm.train_seqs[0].gyro.mean(0), still.gyro.mean(0) - bias, atol=np.radians(0.02))


def test_the_evidence_half_holds_half_of_the_scored_ground_truth():
    """Knobs on one half of each later part, evidence on the other, split by scored samples (BROAD
    scores no final rest: a split by samples left the evidence half with nothing to score)."""
    from tcn_ahrs.training.run import _half

    seq = simulate("walking", 20.0, 100.0, seed=1)
    seq.score_mask = np.arange(len(seq)) < 0.6 * len(seq)
    cut = _half(seq)
    assert abs(cut - 0.3 * len(seq)) <= 2
    assert seq.slice(cut, len(seq)).scored().sum() >= 0.49 * seq.scored().sum()


def test_fine_tuning_on_several_recordings_is_judged_on_recordings_it_never_saw(tmp_path):
    """train.adopt_on=recordings (the default): each of the user's recordings is left out of a
    fine-tuning of its own and scored whole; the pooled evidence decides (adaptation.json says so),
    and the fine-tuning runs without it are in crossfit/."""
    from tcn_ahrs.training.run import train_main
    from test_general import _compose, _general_checkpoint

    init = _general_checkpoint(tmp_path, axes=6)
    recs = [simulate("walking", 20.0, 100.0, s, axes=6) for s in range(2)]
    tr = [r.slice(0, 1400) for r in recs]
    va = [r.slice(1400, len(r)) for r in recs]
    for whole, parts in zip(recs, zip(tr, va)):
        for p in parts:
            p.meta["recording"] = whole.name
    cfg = _compose(["experiment=finetune", "data=generic", "data.axes=6", f"init={init}", "train.epochs=1",
                    "train.window=400", "train.stride=200", "train.batch_size=4", "trainer.enable_progress_bar=false",
                    "eval.enabled=false", "threads=1", f"run_dir={tmp_path / 'run'}"])
    train_main(cfg, tr, va, [])
    record = json.loads((tmp_path / "run" / "adaptation.json").read_text())
    assert record["evidence"] == "recordings left out (cross-fitted)"
    assert "each recording left out of its own fine-tuning" in record["why"]
    assert sorted(p.name for p in (tmp_path / "run" / "crossfit").iterdir()) == sorted(r.name for r in recs)
    assert record["before"]["aae_deg"] is not None and record["after"]["aae_deg"] is not None
