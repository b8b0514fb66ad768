"""General models (issue 25): several datasets as one, windows resampled to random rates and
another sensor's errors, a checkpoint that runs at any rate it was trained at, self-supervised
labels, fine-tuning, and the leave-one-dataset-out table's bookkeeping."""
import json
import math
import warnings

import numpy as np
import pytest
import torch

from tcn_ahrs import so3
from tcn_ahrs.data import SequenceStore, augment_sensor, balanced_starts
from tcn_ahrs.losses import increment_loss, self_labels, trust_labels
from tcn_ahrs.sequence import DataError, ImuSequence
from tcn_ahrs.conf import CONF_DIR


def _sim(rate=100.0, count=2, duration=20.0, seed_offset=0):
    return {"name": "simulated", "axes": 9, "rate": rate, "device_seed": 7,
            "splits": {s: {"count": count, "duration": duration, "seed_offset": seed_offset + 1000 * i,
                           "profiles": ["walking", "fast_rotation"]} for i, s in enumerate(["train", "val", "test"])}}


def _turning(rate=200.0, seconds=20.0, omega=(0.3, -0.5, 0.8)):
    """Constant body rate about a fixed axis: gyro = omega exactly, ground truth exp(omega t)."""
    n = int(seconds * rate)
    t = np.arange(n) / rate
    w = np.asarray(omega, dtype=np.float64)
    rot = so3.exp(torch.as_tensor(t[:, None] * w, dtype=torch.float64))
    quat = so3.matrix_to_quat(rot).numpy()
    acc = (rot.transpose(-1, -2) @ torch.tensor([0.0, 0.0, 9.81], dtype=torch.float64)).numpy()
    return ImuSequence(name="turn", source="test", time=t, gyro=np.tile(w, (n, 1)), accel=acc,
                       quat=quat, rate=rate)


def test_parts_load_as_one_dataset_named_by_part_and_leave_one_out():
    from tcn_ahrs.datasets import data_parts, load_split

    cfg = {"name": "two", "axes": 6, "parts": {"slow": _sim(100.0), "fast": _sim(250.0, seed_offset=50)}}
    seqs = load_split(cfg, "train")
    assert [s.name.split("/")[0] for s in seqs] == ["slow", "slow", "fast", "fast"]
    assert all(not s.has_mag for s in seqs)  # the top-level axes apply to every part
    assert sorted({round(s.rate) for s in seqs}) == [100, 250]
    # a recording's identity (one device check each) carries its part: parts may share names
    assert [s.meta["recording"] for s in seqs] == [s.name for s in seqs]
    left = load_split({**cfg, "leave_out": "slow"}, "train")
    assert [s.name.split("/")[0] for s in left] == ["fast", "fast"]
    assert list(data_parts({**cfg, "leave_out": ["fast"]})) == ["slow"]
    with pytest.raises(DataError, match="leave_out"):
        load_split({**cfg, "leave_out": "medium"}, "train")


def test_resampled_windows_are_the_same_motion_at_another_rate():
    """A constant rotation rate: at any rate (irregular steps too) the resampled gyro integrates
    to the interpolated ground truth's increments, and the mean step is 1/rate."""
    store = SequenceStore([_turning()], 6)
    starts = torch.tensor([0, 400, 1000])
    gen = torch.Generator().manual_seed(0)
    native = store.gather(starts, 300)
    same = store.gather_resampled(starts, 300, (200.0, 200.0), 0.0, gen)
    for k in ("imu", "rot", "valid"):
        assert torch.allclose(same[k].double(), native[k].double(), atol=1e-6), k
    for rate in (50.0, 1000.0):
        w = store.gather_resampled(starts, 300, (rate, rate), 0.0, gen)
        assert torch.allclose(w["rate"], torch.full((3,), rate, dtype=torch.float64))
        assert abs(float(w["dt"].double().mean()) - 1.0 / rate) < 1e-6
        loss = increment_loss(w["imu"][..., 0:3].double(), w["dt"].double(), w["rot"].double(), w["valid"], [16, 32])
        assert float(loss) < 1e-4, rate
    w = store.gather_resampled(starts, 300, (50.0, 1000.0), 0.3, gen)
    d = w["dt"].double()
    assert bool((d > 0).all()) and float((d.std(1) / d.mean(1)).min()) > 0.05  # irregular
    loss = increment_loss(w["imu"][..., 0:3].double(), d, w["rot"].double(), w["valid"], [16, 32])
    assert float(loss) < 1e-4
    # a window that would run past its recording is sampled as slowly as the recording allows
    late = store.gather_resampled(torch.tensor([3000]), 300, (50.0, 50.0), 0.0, gen)
    assert float(late["rate"][0]) > 50.0 and bool(late["valid"].all())


def test_another_mount_is_the_same_motion():
    """A random sensor orientation turns readings and ground truth together: the increments and
    the trust labels are unchanged; a gyro offset is seen by the loss."""
    seq = _turning()
    store = SequenceStore([seq], 6)
    w = store.gather(torch.tensor([0, 500]), 400)
    r = augment_sensor(w, rotate=True, generator=torch.Generator().manual_seed(1))
    assert not torch.allclose(r["imu"], w["imu"])
    loss = increment_loss(r["imu"][..., 0:3].double(), r["dt"].double(), r["rot"].double(), r["valid"], [16])
    assert float(loss) < 1e-4
    lab = trust_labels(r["imu"][0].double(), r["rot"][0].double(), r["valid"][0])
    assert torch.equal(lab[:, 0], w["trust_label"][0, :, 0])
    b = augment_sensor(w, gyro_bias=0.05, generator=torch.Generator().manual_seed(1))
    biased = increment_loss(b["imu"][..., 0:3].double(), b["dt"].double(), b["rot"].double(), b["valid"], [16])
    assert float(biased) > 1e-5 and float(biased) > 100 * float(loss)


def test_balanced_windows_give_every_part_the_same_share():
    from tcn_ahrs.data import window_starts
    from tcn_ahrs.datasets import load_split

    cfg = {"name": "two", "axes": 6, "parts": {"big": _sim(100.0, count=4, duration=40.0),
                                              "small": _sim(100.0, count=1, seed_offset=70)}}
    store = SequenceStore(load_split(cfg, "train"), 6)
    starts = window_starts(store, 200, 100)
    bal = balanced_starts(store, starts)
    part = np.array([store.names[i].split("/")[0] for i in
                     np.searchsorted(store.offsets, bal.numpy(), side="right") - 1])
    assert (part == "big").sum() == (part == "small").sum() == len(bal) // 2


def test_self_labels_read_rest_gravity_and_a_disturbance_without_ground_truth():
    rate, n = 100.0, 3000
    rng = np.random.default_rng(0)
    gyro = 0.01 + 0.0005 * rng.standard_normal((n, 3))  # a biased gyro at rest
    acc = np.array([0.0, 0.0, 9.81]) + 0.005 * rng.standard_normal((n, 3))
    acc[1000:1500] += np.array([3.0, 0.0, 0.0]) * np.sin(np.arange(500) / 5.0)[:, None]  # shaken
    mag = np.array([20.0, 0.0, -40.0]) + 0.05 * rng.standard_normal((n, 3))
    mag[2000:2300] += np.array([15.0, 10.0, 0.0])  # a magnet nearby
    imu = torch.as_tensor(np.concatenate([gyro, acc, mag], 1))
    lab = self_labels(imu, torch.full((n,), 1.0 / rate))
    assert float(lab[100:900, 0].mean()) == 1.0 and float(lab[100:900, 2].mean()) == 1.0
    assert float(lab[1050:1450, 0].mean()) < 0.3 and float(lab[1100:1450, 2].mean()) == 0.0
    assert float(lab[2000:2300, 1].mean()) == 0.0 and float(lab[2400:2900, 1].mean()) == 1.0
    assert bool((self_labels(imu[:, :6], torch.full((n,), 0.01))[:, 1] == 1).all())  # no magnetometer


def _general_checkpoint(tmp_path, axes=6):
    """A residual model saved as a rate-augmented training run saves it."""
    from tcn_ahrs.checkpoint import layout_meta
    from tcn_ahrs.model.ahrs import LearnedAHRS

    cfg = {"axes": axes, "variant": f"residual{axes}", "loop": "backbone", "use_mag_term": axes == 9,
           "residual": {"gyro_clip": 0.01, "trust_weight": 1.0},
           "tcn": {"channels": [4, 4, 4, 4], "kernel_size": 7, "dilations": [1, 4, 16, 64], "dropout": 0.0}}
    torch.manual_seed(0)
    model = LearnedAHRS.from_config(cfg)
    with torch.no_grad():
        for net in (model.calibration.gyro_net, model.calibration.trust_net):
            net.out.weight.normal_(0.0, 0.3)
    path = tmp_path / "general.ckpt"
    torch.save({"state_dict": {f"model.{k}": v for k, v in model.state_dict().items()},
                "tcn_ahrs": layout_meta(cfg, axes, "general6", 200.0, (50.0, 1000.0))}, path)
    return path


def test_a_general_checkpoint_runs_any_rate_in_its_range_without_a_warning(tmp_path):
    """50 Hz, 1000 Hz and irregular steps: the model itself runs (no fallback, no warning);
    outside its range it falls back to the backbone and says so."""
    from tcn_ahrs.datasets.simulate import simulate
    from tcn_ahrs.estimators.learned import LearnedEstimator

    est = LearnedEstimator(str(_general_checkpoint(tmp_path)))
    base = simulate("walking", 10.0, 200.0, 3, axes=6)
    for rate in (50.0, 1000.0):
        seq = simulate("walking", 5.0, rate, 3, axes=6)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            est.run(seq, seq.quat[0], 0)
    t = np.cumsum(np.r_[0.0, np.random.default_rng(0).uniform(0.002, 0.02, len(base) - 1)])
    irregular = ImuSequence(name="irregular", source="test", time=t, gyro=base.gyro, accel=base.accel,
                            quat=base.quat)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        est.run(irregular, irregular.quat[0], 0)
    assert est.fell_back == []
    slow = simulate("walking", 20.0, 20.0, 3, axes=6)
    with pytest.warns(UserWarning, match="50-1000 Hz"):
        est.run(slow, slow.quat[0], 0)
    assert est.fell_back == [slow.name]


def test_own_model_is_the_mean_over_recordings_of_its_nested_folds(tmp_path):
    from tcn_ahrs.experiments.lodo import markdown, own_model

    p = tmp_path / "crossval.json"
    p.write_text(json.dumps({"folds": [
        {"recordings": ["a", "b", "c"], "means": {"Learned": {"aae_deg": 1.0, "inclination_deg": 0.5}}},
        {"recordings": ["d"], "means": {"Learned": {"aae_deg": 5.0, "inclination_deg": 0.9}}}]}))
    got = own_model(p)
    assert math.isclose(got["aae_deg"], 2.0) and math.isclose(got["inclination_deg"], 0.6)
    assert own_model(tmp_path / "absent.json") is None
    cell = {"learned": {"aae_deg": 2.1, "inclination_deg": 0.6}, "own": got, "backbone": None,
            "all": {}, "best": "vqf6d", "best_metrics": {"aae_deg": 2.0, "inclination_deg": 0.6},
            "never_worse": False, "recordings": ["a", "b"], "riann": None}
    md = markdown({"lodo": {"x": cell}})
    assert "| x (2) | 2.10 / 0.60 | 2.00 / 0.60 |" in md and "**no**" in md


def _compose(overrides):
    from hydra import compose, initialize_config_dir

    conf = CONF_DIR
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        return compose("train", overrides=overrides)


@pytest.mark.parametrize("supervision", ["gt", "self"])
def test_fine_tuning_starts_from_the_checkpoint_with_or_without_ground_truth(tmp_path, supervision):
    """init=CKPT: the checkpoint's architecture and weights are the start (one small step away
    after training); supervision=self trains on recordings that have no ground truth at all."""
    from tcn_ahrs.checkpoint import model_from_checkpoint
    from tcn_ahrs.datasets.simulate import simulate
    from tcn_ahrs.training.run import train_main

    init = _general_checkpoint(tmp_path, axes=9)
    tr = [simulate(p, 20.0, 100.0, s) for s, p in enumerate(["static", "walking"])]
    va = [simulate("slow_rotation", 12.0, 100.0, 50)]
    if supervision == "self":
        for s in tr:
            s.quat, s.quat_valid = None, None  # as a loader gives a recording without ground truth
    cfg = _compose(["experiment=finetune", "data=generic", f"init={init}", f"train.supervision={supervision}",
                    "train.epochs=1", "train.window=400", "train.stride=200", "train.batch_size=4",
                    "trainer.enable_progress_bar=false", "eval.enabled=false", "threads=1",
                    f"run_dir={tmp_path / 'run'}"])
    res = train_main(cfg, tr, va, [])
    start, tuned = model_from_checkpoint(str(init)), model_from_checkpoint(res["last"])
    w0, w1 = start.calibration.gyro_net.out.weight, tuned.calibration.gyro_net.out.weight
    assert w1.shape == w0.shape and not torch.equal(w0, w1)
    assert float((w1 - w0).abs().max()) < 0.05 * float(w0.abs().max())  # fine-tuned, not re-initialised
    assert float(tuned.backbone.bias_prior) == 1.0  # this device's bias is the start
    if supervision == "gt":
        assert "knobs" in res  # chosen again on the validation recordings


def test_knobs_for_another_device_are_chosen_on_offset_copies_and_leave_the_recordings_alone():
    from tcn_ahrs.tuning.knobs import with_gyro_offsets

    seqs = [_turning(), _turning(omega=(0.0, 0.2, 0.0))]
    before = [s.gyro.copy() for s in seqs]
    copies = with_gyro_offsets(seqs, 0.03, seed=1)
    for s, c, g in zip(seqs, copies, before):
        off = c.gyro - s.gyro
        assert np.array_equal(s.gyro, g)  # untouched
        assert np.allclose(off, off[0]) and 0.0 < np.abs(off[0]).max() < 0.2  # one constant offset
        assert c.quat is s.quat
    assert not np.allclose(copies[0].gyro - seqs[0].gyro, copies[1].gyro - seqs[1].gyro)


def test_a_recording_resampled_for_the_rate_sweep_is_the_same_motion():
    from tcn_ahrs.data import sequence_tensors
    from tcn_ahrs.datasets.simulate import simulate
    from tcn_ahrs.experiments.transfer import resampled

    seq = simulate("slow_rotation", 20.0, 200.0, 4, axes=6, noise_free=True)
    same = resampled(seq, 200.0)
    assert len(same) == len(seq) and np.allclose(same.gyro, seq.gyro) and np.allclose(np.abs((same.quat * seq.quat).sum(1)), 1.0)
    for rate in (50.0, 1000.0):
        r = resampled(seq, rate)
        assert abs(r.rate - rate) < 1e-9 and abs(len(r) / len(seq) - rate / 200.0) < 0.01
        t = sequence_tensors(r, 6, torch.float64)
        loss = increment_loss(t["imu"][None, :, 0:3], t["dt"][None], t["rot"][None], t["valid"][None], [16])
        # point samples integrated over 20 ms steps (50 Hz) err by 2e-4; a gyro two samples late: 2.4e-3
        assert float(loss) < (5e-4 if rate == 50.0 else 1e-6), rate


def test_a_knob_point_may_win_on_one_number_only_under_the_either_rule():
    from tcn_ahrs.tuning.knobs import knob_points_eligible

    mean = np.array([[10.0, 1.0],    # the tuned backbone
                     [5.0, 1.0],     # AAE halved, inclination tied
                     [9.0, 0.9],     # both 10 % better
                     [5.0, 1.05],    # AAE halved, inclination 5 % worse
                     [9.95, 0.995]])  # both better, by less than the margin
    finite = np.array([True, True, True, True, True])
    assert knob_points_eligible(mean, finite, 0.02, "both").tolist() == [False, False, True, False, False]
    assert knob_points_eligible(mean, finite, 0.02, "either").tolist() == [False, True, True, False, False]
    finite[2] = False  # diverged on some recording
    assert not knob_points_eligible(mean, finite, 0.02, "either")[2]
    with pytest.raises(ValueError, match="knob rule"):
        knob_points_eligible(mean, finite, 0.02, "any")


def test_never_worse_knob_choice_is_scored_per_dataset_against_vqf_defaults():
    import copy

    from tcn_ahrs.datasets.simulate import simulate
    from tcn_ahrs.tuning.knobs import tune_backbone

    seqs = []
    for part, (profile, seed) in {"a": ("walking", 1), "b": ("slow_rotation", 2)}.items():
        s = copy.copy(simulate(profile, 20.0, 100.0, seed, axes=6))
        s.name = f"{part}/{s.name}"
        seqs.append(s)
    grid = {"tau_acc": [3.0, 10.0], "bias_clip": [2.0, 8.0]}
    chosen, table = tune_backbone(seqs, 6, grid, criterion="never_worse")
    ref = next(r for r in table if r["params"] == {"tau_acc": 3.0, "bias_clip": 2.0})
    assert ref["score"] == pytest.approx(1.0) and table[0]["score"] <= 1.0 and chosen == table[0]["params"]
    with pytest.raises(ValueError, match="tune_criterion"):
        tune_backbone(seqs, 6, grid, criterion="best")
