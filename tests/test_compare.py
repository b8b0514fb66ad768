"""tcn_ahrs.experiments.compare: method registry, tuning on training recordings only, batched filters,
heading-free scoring, tables, the Hydra entry points (short simulated recordings)."""
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf
from scipy.spatial.transform import Rotation

from tcn_ahrs.experiments import compare as cmp
from tcn_ahrs.tuning import grid as tuning
from tcn_ahrs.conventions import quat_xyzw_to_wxyz
from tcn_ahrs.datasets.simulate import simulate
from tcn_ahrs.estimators.base import EstimatorOutput, initial_quat
from tcn_ahrs.estimators.classical import ESEKF, Madgwick
from tcn_ahrs.evaluate import evaluate
from tcn_ahrs.sequence import ImuSequence
from tcn_ahrs.tuning.grid import tune_grid
from tcn_ahrs.conf import CONF_DIR

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def sims():
    """3 short simulated 9-axis recordings (20 s at 50 Hz): [train, eval, eval]."""
    return [simulate(p, 20.0, 50.0, seed=s) for p, s in
            (("walking", 1), ("slow_rotation", 20001), ("fast_rotation", 20002))]


def _peers_installed():
    try:
        import ahrs  # noqa: F401
        import vqf  # noqa: F401
        return True
    except ImportError:
        return False


# ----------------------------------------------------------------------------- registry


def test_method_specs_columns_and_errors():
    specs = cmp.method_specs(["raw", "ecf", "vqf", "riann"], data_axes=9, both_axes=True,
                             variants=["default", "tuned"], ckpts={"Proposed": "x.ckpt"})
    assert [s.name for s in specs] == ["Raw IMU", "ecf9d", "ecf9d (tuned)", "ecf6d", "ecf6d (tuned)",
                                       "vqf9d", "vqf9d (tuned)", "vqf6d", "vqf6d (tuned)", "riann6d", "Proposed"]
    assert [s.name for s in cmp.method_specs(["ecf", "riann"], data_axes=9, both_axes=False)] == ["ecf9d"]
    assert [s.name for s in cmp.method_specs(["ecf"], data_axes=6)] == ["ecf6d"]
    with pytest.raises(ValueError, match="unknown method.*'kalman'"):
        cmp.method_specs(["raw", "kalman"])
    with pytest.raises(ValueError, match="variants"):
        cmp.method_specs(["ecf"], variants=["best"])
    with pytest.raises(ValueError, match="duplicate column"):
        cmp.method_specs(["ecf"], data_axes=6, ckpts={"ecf6d": "x.ckpt"})


def test_run_batch_equals_single_runs_with_padding(sims):
    """One padded batched call == per-recording runs (recordings of different lengths)."""
    seqs = [sims[1], sims[2].slice(0, 700)]
    q0s = [initial_quat(s) for s in seqs]
    for axes in (9, 6):
        m = ESEKF(axes=axes)
        batch = m.run_batch(seqs, q0s)
        for s, q0, b in zip(seqs, q0s, batch):
            view = s if axes == 9 else s.without_mag()
            single = ESEKF(axes=axes).run(view, q0)
            assert b.quat.shape == (len(s), 4)
            np.testing.assert_allclose(b.quat, single.quat, atol=1e-12)
            np.testing.assert_allclose(b.signals["gyro_bias"], single.signals["gyro_bias"], atol=1e-12)


def test_batched_tuning_matches_one_recording_at_a_time(sims):
    """The one tuner runs all clips x grid points in one padded call; each score equals the
    filter run on that recording alone with that point (different lengths: padding unscored)."""
    from tcn_ahrs.metrics import scored_metric
    from tcn_ahrs.tuning.grid import tune_method

    clips = [sims[0], sims[1].slice(0, 700)]
    best, table = tune_method("madgwick", 6, clips)
    ref_best, ref_table = tune_grid(Madgwick, clips, axes=6)
    assert best == ref_best and len(table) == len(Madgwick.default_grid["beta"])
    for row in table[:3]:
        for c in clips:
            alone = Madgwick(axes=6, **row["params"]).run(c.without_mag(), initial_quat(c)).quat
            assert row["per_sequence"][c.name] == pytest.approx(scored_metric(c, alone, 6), rel=1e-9)


def test_tuning_clips_start_before_first_scored_sample(sims):
    s = sims[0]
    mask = np.zeros(len(s), dtype=bool)
    mask[400:] = True  # "movement" starts at 8 s
    from dataclasses import replace
    s2 = replace(s, score_mask=mask, meta=dict(s.meta))
    clips, rec = tuning.tuning_clips([s2, sims[1], sims[2]], max_seconds=5.0, lead_seconds=2.0, max_recordings=2)
    assert [r["name"] for r in rec] == [s2.name, sims[2].name]  # evenly spaced: first and last
    assert rec[0]["start_s"] == pytest.approx(6.0)
    assert clips[0].duration == pytest.approx(5.0)
    assert clips[0].scored().sum() == 151  # 8 s .. 11 s at 50 Hz


# ----------------------------------------------------------------------------- end to end


def test_compare_tunes_on_train_and_writes_tables(sims, tmp_path):
    train, evals = sims[:1], sims[1:]
    res = cmp.compare(evals, train, methods=["raw", "ecf", "madgwick"], tune=True, out_dir=tmp_path,
                      tune_max_seconds_per_recording=10.0, verbose=False, dataset="sim")
    cols = ["Raw IMU", "ecf9d", "ecf9d (tuned)", "ecf6d", "ecf6d (tuned)",
            "madgwick9d", "madgwick9d (tuned)", "madgwick6d", "madgwick6d (tuned)"]
    assert list(res["methods"]) == cols
    on_disk = json.loads((tmp_path / "results.json").read_text())
    assert list(on_disk["methods"]) == cols
    tun = on_disk["tuning"]
    used = [r["name"] for r in tun["recordings"]]
    assert used == [train[0].name]
    assert not set(used) & set(on_disk["recordings"])
    assert tun["recordings"][0]["duration_s"] == pytest.approx(10.0)
    assert set(tun["methods"]) == {"ecf9d (tuned)", "ecf6d (tuned)", "madgwick9d (tuned)", "madgwick6d (tuned)"}
    # tuned parameters come from the grid and are what the tuned column ran with
    assert tun["methods"]["madgwick9d (tuned)"]["params"]["beta"] in Madgwick.default_grid["beta"]
    assert on_disk["columns"]["madgwick9d (tuned)"]["params"] == tun["methods"]["madgwick9d (tuned)"]["params"]
    assert on_disk["columns"]["ecf6d"]["axes"] == 6
    # the 6D columns are scored as 6-axis, the 9D ones as 9-axis
    assert {r["axes"] for r in on_disk["methods"]["ecf6d"]["recordings"]} == {6}
    assert {r["broad_mode"] for r in on_disk["methods"]["ecf9d"]["recordings"]} == {"9d"}
    for m in cols:
        assert on_disk["methods"][m]["mean"]["inclination_deg"] is not None
    md = (tmp_path / "results.md").read_text()
    assert "| AAE (deg) |" in md and "| AYE (deg) |" in md and "| Average |" in md
    assert "\n| ecf6d (tuned) | " in md and "\n| Raw IMU | " in md
    assert "## Tuned parameters" in md and train[0].name in md
    # the tuned ECF is not worse on the recording it was tuned on than the default
    assert tun["methods"]["ecf9d (tuned)"]["score_aae_deg"] <= (
        tun["methods"]["ecf9d (tuned)"]["default_in_grid_score_aae_deg"] or np.inf) + 1e-9


def test_compare_refuses_tuning_on_evaluation_recordings(sims):
    with pytest.raises(ValueError, match="also evaluation recordings"):
        cmp.compare(sims[1:], sims[1:2], methods=["ecf"], tune=True, verbose=False)


def test_compare_main_hydra_config(tmp_path):
    """compare_main: loads data.split for evaluation and the train split for tuning."""
    data = {"name": "simulated", "axes": 9, "rate": 50.0, "device_seed": 0, "split": "test",
            "splits": {"train": {"count": 1, "duration": 15.0, "seed_offset": 0, "profiles": ["walking"]},
                       "test": {"count": 2, "duration": 15.0, "seed_offset": 20000,
                                "profiles": ["slow_rotation", "fast_rotation"]}}}
    cfg = OmegaConf.create({"data": data, "methods": ["raw", "mahony"], "tune": True, "both_axes": False,
                            "variants": ["default", "tuned"], "tune_max_seconds_per_recording": 10,
                            "out": str(tmp_path)})
    res = cmp.compare_main(cfg)
    assert list(res["methods"]) == ["Raw IMU", "mahony9d", "mahony9d (tuned)"]
    assert [r["name"] for r in res["tuning"]["recordings"]] == ["sim_walking_s0000"]
    assert res["split"] == "test" and res["tune_split"] == "train"
    bad = OmegaConf.merge(cfg, {"data": {"split": "train"}})
    with pytest.raises(ValueError, match="would include the tuning recordings"):
        cmp.compare_main(bad)
    with pytest.raises(ValueError, match="unknown key"):
        cmp.compare_main(OmegaConf.merge(cfg, {"methodz": ["ecf"]}))


# ----------------------------------------------------------------------------- heading-free


def _seq_with_tilted_estimate(n=300, mag=False):
    """Ground truth spinning about a tilted axis; the 'estimate' = q_x(2 deg) q_z(30 deg) q_gt:
    heading error 30 deg, inclination error exactly 2 deg."""
    t = np.arange(n) / 100.0
    gt = Rotation.from_rotvec(np.outer(t, [0.3, -0.2, 0.8]))
    q_gt = quat_xyzw_to_wxyz(gt.as_quat())
    est = Rotation.from_euler("x", 2, degrees=True) * Rotation.from_euler("z", 30, degrees=True) * gt
    q_est = quat_xyzw_to_wxyz(est.as_quat())
    seq = ImuSequence(name="tilted", source="synthetic", time=t, gyro=np.tile([0.3, -0.2, 0.8], (n, 1)),
                      accel=gt.inv().apply([0, 0, 9.81]), mag=gt.inv().apply([0, 20, -40]) if mag else None,
                      quat=q_gt, quat_valid=np.ones(n, bool), rate=100.0, check_units=False)
    return seq, q_est


class _Fixed:
    def __init__(self, name, quat, heading_free, axes=None):
        self.name, self.quat, self.heading_free = name, quat, heading_free
        if axes is not None:
            self.axes = axes

    def run(self, seq, init_quat=None, init_index=0):
        return EstimatorOutput(self.quat.copy(), {})


def test_heading_free_scored_on_inclination_only():
    seq, q_est = _seq_with_tilted_estimate()
    res = evaluate([_Fixed("hf", q_est, True), _Fixed("normal", q_est, False)], [seq], align=False)
    hf, normal = res["methods"]["hf"], res["methods"]["normal"]
    for k in ("aae_deg", "aye_deg", "total_deg", "heading_deg"):
        assert hf["recordings"][0].get(k) is None
        assert hf["mean"].get(k) is None
    assert hf["recordings"][0]["inclination_deg"] == pytest.approx(2.0, abs=1e-6)
    assert hf["mean"]["inclination_deg"] == pytest.approx(2.0, abs=1e-6)
    assert hf["recordings"][0]["heading_free"] is True
    # a normal estimator on a 6-axis recording without a score mask still gets inclination
    assert normal["recordings"][0]["inclination_deg"] == pytest.approx(2.0, abs=1e-6)
    assert 25.0 < normal["recordings"][0]["aye_deg"] < 35.0  # Euler yaw of a tilted estimate: ~30


def test_estimator_axes_6_gets_6_axis_view():
    seq, q_est = _seq_with_tilted_estimate(mag=True)
    seen = {}

    class Spy(_Fixed):
        def run(self, s, init_quat=None, init_index=0):
            seen[self.name] = s.has_mag
            return super().run(s, init_quat)

    res = evaluate([Spy("six", q_est, False, axes=6), Spy("nine", q_est, False, axes=9)], [seq], align=False)
    assert seen == {"six": False, "nine": True}
    assert res["methods"]["six"]["recordings"][0]["axes"] == 6
    assert res["methods"]["nine"]["recordings"][0]["broad_mode"] == "9d"


@pytest.mark.skipif(not importlib.util.find_spec("riann"), reason="riann not installed (pip install -e .[peers])")
def test_riann_column_is_heading_free(sims):
    res = cmp.compare(sims[1:2], (), methods=["riann"], tune=False, verbose=False)
    row = res["methods"]["riann6d"]["recordings"][0]
    assert row["aae_deg"] is None and row["aye_deg"] is None
    assert row["inclination_deg"] is not None and row["inclination_deg"] < 20.0
    assert res["columns"]["riann6d"]["heading_free"] is True


# ----------------------------------------------------------------------------- peers, ablation


def test_missing_peers_are_skipped_with_warning(sims, monkeypatch):
    from tcn_ahrs.estimators import peers

    def unavailable(module, package, peer):
        raise peers.PeerUnavailable(f"peer estimator '{peer}' needs the package '{package}'")

    monkeypatch.setattr(peers, "_import_peer", unavailable)
    with pytest.warns(UserWarning, match="peer estimators skipped.*vqf9d"):
        res = cmp.compare(sims[1:2], sims[:1], methods=["raw", "vqf", "ahrs_madgwick"], tune=True,
                          tune_max_seconds_per_recording=5.0, verbose=False)
    assert list(res["methods"]) == ["Raw IMU"]


@pytest.mark.skipif(not _peers_installed(), reason="vqf/ahrs not installed (pip install -e .[peers])")
def test_peer_tuning_loops_over_peer_grid(sims):
    from tcn_ahrs.estimators import registry

    res = cmp.compare(sims[1:2], sims[:1], methods=["vqf"], both_axes=False, tune=True,
                      tune_max_seconds_per_recording=8.0, verbose=False)
    t = res["tuning"]["methods"]["vqf9d (tuned)"]
    grid = registry.get("vqf").grid
    assert t["grid_size"] == len(grid)
    assert t["params"] in [dict(p) for p in grid]
    assert res["columns"]["vqf9d (tuned)"]["params"] == t["params"]


def test_ablation_table_layout(sims, tmp_path, monkeypatch):
    """Checkpoints go through LearnedEstimator; faked here (constant-bias raw integrations)."""
    from tcn_ahrs.estimators.raw import RawIntegration

    class Fake(RawIntegration):
        def __init__(self, name):
            self.name = name

    from tcn_ahrs.experiments import columns

    real_build = columns.build_estimator
    monkeypatch.setattr(columns, "build_estimator",
                        lambda spec, device="cpu", reanchor=None: (Fake(spec.name) if spec.kind == "learned"
                                                                   else real_build(spec, device, reanchor)))
    abl = {"full": "a.ckpt", "w/o mag term": "b.ckpt", "w/o acc term": "c.ckpt", "w/o both": "d.ckpt"}
    res = cmp.compare(sims[1:], (), methods=["raw"], tune=False, ckpts={"full": "a.ckpt"},
                      ablation_ckpts=abl, out_dir=tmp_path, verbose=False)
    assert res["ablation"] == list(abl)
    assert list(res["methods"]) == ["Raw IMU"] + list(abl)
    md = (tmp_path / "results.md").read_text()
    section = md.split("## Ablation (paper Table 3): AAE / AYE")[1]
    assert "\n| full | " in section and "\n| w/o mag term | " in section and "| AYE (deg) |" in section
    assert "| Raw IMU |" not in section.split("##")[0]
    with pytest.raises(ValueError, match="one label, one checkpoint"):
        cmp.compare(sims[1:], (), methods=["raw"], tune=False, ckpts={"full": "x.ckpt"}, ablation_ckpts=abl)


# ----------------------------------------------------------------------------- scripts


def test_baseline_estimators_registry():
    from tcn_ahrs.estimators.registry import baseline_estimators

    ests = baseline_estimators(["raw", "ecf", "robust_eskf"])
    assert [e.name for e in ests] == ["Raw IMU", "ecf9d", "robust_eskf9d"]
    with pytest.raises(ValueError, match="unknown method 'nonsense'"):  # a typo is an error, not a warning
        baseline_estimators(["raw", "nonsense"])
    assert [e.name for e in baseline_estimators(["raw", "eskf"], axes=6)] == ["Raw IMU", "eskf6d"]
    assert [e.axes for e in baseline_estimators(["mahony6d"])] == [6]


def test_benchmark_dispatcher_mode_argument(capsys):
    from tcn_ahrs.cli import mode_as_override

    assert mode_as_override(["accuracy", "data=broad"]) == ["mode=accuracy", "data=broad"]
    assert mode_as_override(["data=broad"]) == ["data=broad"]
    with pytest.raises(SystemExit) as e:
        mode_as_override(["sped"])
    assert e.value.code == 2 and "unknown mode 'sped'" in capsys.readouterr().err


def test_parameter_sets_batched_equal_separate_runs(sims):
    """P parameter sets x R recordings in one quat_batch call == each set run alone."""
    import torch

    from tcn_ahrs.estimators.classical import Mahony

    seqs = [sims[1], sims[2].slice(0, 600)]
    q0s = [initial_quat(s) for s in seqs]
    est = Mahony()
    quat, _ = est.quat_batch(seqs, q0s, {"k_p": torch.tensor([[1.0], [0.3]]), "k_i": torch.tensor([[0.3], [0.0]])})
    assert quat.shape == (2, 2, len(seqs[0]), 4)
    for i, (kp, ki) in enumerate([(1.0, 0.3), (0.3, 0.0)]):
        for j, r in enumerate(Mahony(k_p=kp, k_i=ki).run_batch(seqs, q0s)):
            # float64; batched reductions are not bit-identical to unbatched ones (~1e-9 after 1000 steps)
            np.testing.assert_allclose(quat[i, j, :len(seqs[j])].numpy(), r.quat, atol=1e-8)


def test_classical_run_equals_its_batched_path(sims):
    m = Madgwick(axes=9)
    q0 = initial_quat(sims[1])
    np.testing.assert_allclose(m.run(sims[1], q0).quat, m.run_batch([sims[1], sims[2]], [q0, None])[0].quat,
                               atol=1e-12)


def test_on_calibrated_columns_use_the_models_calibration(sims, tmp_path):
    """An untrained model's calibration is the identity, so a filter on its calibrated signals
    scores exactly as on the raw ones; a model with a scaled gyro changes the column."""
    import torch

    from tcn_ahrs.estimators.learned import OnLearnedCalibration
    from tcn_ahrs.model.ahrs import LearnedAHRS

    model = LearnedAHRS(axes=9, loop="closed")
    seq = sims[1]
    base = Madgwick(axes=9)
    q0 = initial_quat(seq)
    same = OnLearnedCalibration(base, model, "untrained").run(seq, q0)
    np.testing.assert_allclose(same.quat, base.run(seq, q0).quat, atol=1e-6)
    with torch.no_grad():
        model.calibration.gyro_matrix.delta.fill_diagonal_(0.05)
    wrapped = OnLearnedCalibration(base, model, "scaled")
    assert wrapped.name == "madgwick9d on scaled" and wrapped.axes == 9
    np.testing.assert_allclose(wrapped.calibrated(seq).gyro, 1.05 * seq.gyro, rtol=1e-5, atol=1e-7)


def test_tune_on_shipped_training_data_and_evaluate_on_an_own_folder(tmp_path, monkeypatch):
    """benchmark/compare: tune_data=<name> takes the tuning recordings from that dataset's
    training split, so data.split=all on the user's own folder is allowed (no overlap)."""
    from hydra import compose, initialize_config_dir

    from tcn_ahrs.experiments import compare as cmp
    from tcn_ahrs.datasets.simulate import simulate

    seq = simulate("slow_rotation", 8.0, 50.0, seed=1)
    np.savetxt(tmp_path / "mine.csv", np.column_stack([seq.time, seq.gyro, seq.accel, seq.mag, seq.quat]),
               delimiter=",", comments="", fmt="%.10g",
               header="t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z,quat_w,quat_x,quat_y,quat_z")
    seen = {}
    monkeypatch.setattr(cmp, "compare", lambda ev, tu, **kw: seen.update(ev=ev, tu=tu) or {"methods": {}})
    conf = CONF_DIR
    base = ["data=generic", f"data.root={tmp_path}", "data.split=all", "tune=true", "methods=[raw]", "peers=false",
            f"out={tmp_path / 'out'}"]
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        with pytest.raises(ValueError, match="tune_data=broad"):
            cmp.compare_main(compose("compare", overrides=base))
        cfg = compose("compare", overrides=base + ["tune_data=simulated"])
    try:
        cmp.compare_main(cfg)
    except Exception:  # noqa: BLE001 - the printing of the stubbed result is not under test
        pass
    assert [s.name for s in seen["ev"]] == ["mine"]
    assert len(seen["tu"]) > 0 and all(s.meta.get("dataset") != "generic" for s in seen["tu"])


PLUGIN = '''"""A trivial classical filter, added the way a user adds one: this file and `plugins=[...]`."""
from dataclasses import dataclass
from typing import ClassVar, Dict

from tcn_ahrs.estimators.classical import ClassicalEstimator
from tcn_ahrs.estimators.registry import register


@register("hold", "classical")
@dataclass
class Hold(ClassicalEstimator):
    """Keeps the initial attitude (ignores every sensor)."""

    unused_gain: float = 1.0  # 1/s
    default_grid: ClassVar[Dict[str, list]] = {"unused_gain": [0.5, 1.0]}

    def _filter(self, gyro, accel, dt, q0, mag, p):
        return {"quat": q0[:, None, :].expand(gyro.shape[0], gyro.shape[1], 4).clone()}
'''


@pytest.mark.parametrize("config", ["compare", "benchmark"])
def test_a_new_filter_is_one_file_and_one_config_entry(config, tmp_path, monkeypatch, capsys):
    """Issue 9's yardstick: a filter module + `plugins=[module]` puts its columns in compare's and
    benchmark's output, with no other file edited (methods default to every registered one)."""
    from hydra import compose, initialize_config_dir

    from tcn_ahrs.estimators import registry

    (tmp_path / "my_hold_filter.py").write_text(PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path))
    registry.methods()  # the built-in modules register first (into the real table)
    monkeypatch.setattr(registry, "_METHODS", dict(registry._METHODS))  # the registration stays in this test
    monkeypatch.delitem(sys.modules, "my_hold_filter", raising=False)
    seq = simulate("fast_rotation", 20.0, 50.0, seed=1)
    np.savetxt(tmp_path / "mine.csv", np.column_stack([seq.time, seq.gyro, seq.accel, seq.mag, seq.quat]),
               delimiter=",", comments="", fmt="%.10g",
               header="t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z,quat_w,quat_x,quat_y,quat_z")
    conf = CONF_DIR
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose(config, overrides=["data=generic", f"data.root={tmp_path}", "data.split=all", "peers=false",
                                         "plugins=[my_hold_filter]", f"out={tmp_path / 'out'}"])
    res = cmp.compare_main(cfg, cmp.BENCHMARK_KEYS if config == "benchmark" else cmp.COMPARE_KEYS, kind=config)
    assert "hold9d" in res["methods"] and "hold6d" in res["methods"]
    assert list(res["methods"])[:2] == ["Raw IMU", "ecf9d"]  # the built-in methods are all still there
    assert "hold9d" in capsys.readouterr().out
    assert "hold6d" in (tmp_path / "out" / "results.md").read_text()
    # it holds its start, so on a rotating recording it is worse than every real filter
    mean = {k: v["mean"]["aae_deg"] for k, v in res["methods"].items()}
    assert mean["hold9d"] > mean["ecf9d"]


DATASET_PLUGIN = '''"""A dataset of one's own, added the way a user adds one: this file and `data.name=...`."""
from pathlib import Path

import numpy as np

from tcn_ahrs.sequence import ImuSequence


def list_recordings(root):
    return sorted(p.stem for p in Path(root).glob("*.npz"))


def load_recording(root, name):
    f = np.load(Path(root) / f"{name}.npz")
    return ImuSequence(name=name, source=str(Path(root) / f"{name}.npz"), time=f["t"], gyro=f["gyro"],
                       accel=f["accel"], mag=f["mag"], quat=f["quat"], rate=float(f["rate"]),
                       meta={"dataset": "npz_folder"})
'''

METRIC_PLUGIN = '''"""A metric of one's own: this file and `plugins=[...]`."""
import numpy as np

from tcn_ahrs.metrics import attitude_errors, register_metric


@register_metric("p95_deg", "P95")
def p95(q_gt, q_est, mask=None, align=True):
    angle, _ = attitude_errors(q_gt, q_est, mask, align)
    return float(np.degrees(np.percentile(angle[mask], 95)))
'''


@pytest.mark.parametrize("config", ["compare", "benchmark"])
def test_a_new_dataset_and_a_new_metric_are_one_file_and_one_config_entry(config, tmp_path, monkeypatch, capsys):
    """Issue 9's yardstick for datasets and metrics: a loader module named by `data.name` and a
    metric module named in `plugins` reach compare's and benchmark's output, nothing else edited."""
    from hydra import compose, initialize_config_dir

    from tcn_ahrs import metrics

    (tmp_path / "npz_folder.py").write_text(DATASET_PLUGIN)
    (tmp_path / "my_p95.py").write_text(METRIC_PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(metrics, "_EXTRA", {})  # the registration stays in this test
    for mod in ("npz_folder", "my_p95"):
        monkeypatch.delitem(sys.modules, mod, raising=False)
    rec = tmp_path / "recs"
    rec.mkdir()
    for seed in (1, 2):
        seq = simulate("fast_rotation", 20.0, 50.0, seed=seed)
        np.savez(rec / f"run{seed}.npz", t=seq.time, gyro=seq.gyro, accel=seq.accel, mag=seq.mag, quat=seq.quat,
                 rate=seq.rate)
    conf = CONF_DIR
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose(config, overrides=["data=generic", "data.name=npz_folder", f"data.root={rec}", "data.split=all",
                                         "peers=false", "methods=[raw,ecf]", "plugins=[my_p95]",
                                         f"out={tmp_path / 'out'}"])
    res = cmp.compare_main(cfg, cmp.BENCHMARK_KEYS if config == "benchmark" else cmp.COMPARE_KEYS, kind=config)
    assert res["recordings"] == ["run1", "run2"]
    p95 = {k: v["mean"].get("p95_deg") for k, v in res["methods"].items()}
    assert set(p95) >= {"Raw IMU", "ecf9d"} and all(v is not None for v in p95.values())
    # the 95th percentile of the error angle lies above its RMS for a drifting integration
    assert p95["Raw IMU"] > res["methods"]["Raw IMU"]["mean"]["aae_deg"] * 0.9
    assert "p95_deg" in capsys.readouterr().out  # the terminal summary of averages
    md = (tmp_path / "out" / "results.md").read_text()
    assert "P95" in md and "Further metrics" in md
    with pytest.raises(Exception, match="unknown dataset 'no_such_module'"):
        from tcn_ahrs.datasets import loader

        loader("no_such_module")
