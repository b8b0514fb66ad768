"""Splits as configuration: conf/data/*.yaml, load_split semantics, the summary and the script."""
from __future__ import annotations

import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

import tcn_ahrs.datasets as ds
from tcn_ahrs.conventions import GRAVITY
from tcn_ahrs.datasets import format_summary_table, gt_gaps, load_split, split_recording, summarize
from tcn_ahrs.sequence import DataError, ImuSequence
from tcn_ahrs.conf import CONF_DIR

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "datasets"
CONF = CONF_DIR / "data"

BROAD_TEST = ["05", "09", "15", "26", "30", "35"]
BROAD_TRAIN = ["01", "02", "04", "06", "07", "08", "10", "11", "14", "18", "24", "28", "29", "32", "33", "36"]


def shared(name: str) -> Path:
    p = SHARED / name
    if not p.is_dir():
        pytest.skip(f"real {name} data not found at {p} (needs ../shared/datasets/{name})")
    return p


def _write_csv(path: Path, seconds: float, rate: float = 100.0, seed: int = 0):
    rng = np.random.default_rng(seed)
    n = int(round(seconds * rate))
    t = np.arange(n) / rate
    gyr = 0.002 * rng.standard_normal((n, 3))
    acc = np.tile([0.0, 0.0, GRAVITY], (n, 1)) + 0.01 * rng.standard_normal((n, 3))
    mag = np.tile([0.0, 20.0, -40.0], (n, 1))
    quat = np.tile([1.0, 0, 0, 0], (n, 1))
    quat[int(0.5 * rate):int(0.7 * rate)] = np.nan  # a 0.2 s ground-truth gap
    table = np.column_stack([t, gyr, acc, mag, quat])
    path.parent.mkdir(parents=True, exist_ok=True)
    header = "t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z,quat_w,quat_x,quat_y,quat_z"
    np.savetxt(path, table, delimiter=",", header=header, comments="", fmt="%.10g")


@pytest.fixture()
def generic_root(tmp_path):
    _write_csv(tmp_path / "a.csv", 100.0, seed=1)
    _write_csv(tmp_path / "sub" / "b.csv", 50.0, seed=2)
    _write_csv(tmp_path / "c.csv", 10.0, seed=3)
    return tmp_path


def cfg(root, **kw):
    base = {"name": "generic", "root": str(root), "split": "train", "train": ["a", "sub/b"], "test": ["c"],
            "train_part": {"seconds": 80}, "axes": 9}
    base.update(kw)
    return base


# ------------------------------------------------------------------ semantics on fixtures
def test_train_val_seconds(generic_root):
    c = cfg(generic_root, train=["a"])
    train, val, full = load_split(c, "train"), load_split(c, "val"), load_split(c, "trainval")
    assert [s.name for s in train] == [s.name for s in val] == [s.name for s in full] == ["a"]
    # a: 100 s at 100 Hz -> first 80 s train, last 20 s validate, nothing lost or shared
    assert len(train[0]) == 8000 and len(val[0]) == 2000 and len(full[0]) == 10000
    assert train[0].time[-1] < 80.0 <= val[0].time[0]
    np.testing.assert_array_equal(np.concatenate([train[0].accel, val[0].accel]), full[0].accel)
    assert train[0].meta["part"] == "train" and val[0].meta["part"] == "val"
    # b: 50 s < 80 s -> all of it trains
    assert len(load_split(cfg(generic_root, train=["sub/b"]), "train")[0]) == 5000


def test_val_part_missing_is_skipped_with_warning(generic_root):
    with pytest.warns(UserWarning, match="sub/b has no val part"):
        val = load_split(cfg(generic_root, train=["sub/b"]), "val")
    assert val == []


def test_train_val_fraction(generic_root):
    c = cfg(generic_root, train_part={"fraction": 0.7})
    tr, va = load_split(c, "train")[0], load_split(c, "val")[0]
    assert len(tr) == 7000 and len(va) == 3000
    np.testing.assert_array_equal(np.concatenate([tr.gyro, va.gyro]), load_split(c, "trainval")[0].gyro)


def test_test_all_axes_and_split_default(generic_root):
    assert [s.name for s in load_split(cfg(generic_root), "test")] == ["c"]
    assert [s.name for s in load_split(cfg(generic_root, train=[], test=[]), "all")] == ["a", "c", "sub/b"]
    assert ds.list_recordings(cfg(generic_root)) == ["a", "c", "sub/b"]
    six = load_split(cfg(generic_root, axes=6), "test")
    assert six[0].mag is None and six[0].num_axes == 6
    assert len(load_split(cfg(generic_root, split="test"))) == 1  # split from the config
    omega = OmegaConf.create(cfg(generic_root))                   # DictConfig works as well
    assert [s.name for s in load_split(omega, "train")] == ["a", "sub/b"]


def test_missing_test_recordings_warn(generic_root):
    with pytest.warns(UserWarning, match="zzz_absent"):
        out = load_split(cfg(generic_root, test=["c", "zzz_absent"]), "test")
    assert [s.name for s in out] == ["c"]


def test_bad_config(generic_root, tmp_path):
    with pytest.raises(DataError, match="split"):
        load_split(cfg(generic_root), "everything")
    with pytest.raises(DataError) as e:
        load_split(cfg(tmp_path / "nowhere"), "all")
    assert e.value.field_name == "root" and "nowhere" in str(e.value)
    with pytest.raises(DataError, match="train_part"):
        load_split(cfg(generic_root, train_part={}), "train")


def test_simulated_delegates(monkeypatch):
    calls = []
    fake = types.ModuleType("tcn_ahrs.datasets.simulate")
    fake.load_split = lambda data_cfg, split: calls.append((data_cfg["name"], split)) or ["sentinel"]
    monkeypatch.setitem(sys.modules, "tcn_ahrs.datasets.simulate", fake)
    monkeypatch.setattr(ds, "simulate", fake, raising=False)
    assert load_split({"name": "simulated", "split": "val"}) == ["sentinel"]
    assert calls == [("simulated", "val")]


# ------------------------------------------------------------------------------- summary
def test_summary_and_gaps(generic_root):
    s = load_split(cfg(generic_root), "test")[0]
    g = gt_gaps(s)
    assert len(g) == 1 and g[0][1] == pytest.approx(0.21, abs=0.011)  # from last valid to first valid
    r = summarize(s)
    assert r["gaps"] == 1 and r["axes"] == 9 and r["rate_hz"] == pytest.approx(100.0)
    assert r["gt_valid_pct"] == pytest.approx(98.0) and not r["gt_missing_at_start"]
    assert r["rest_s"] > 5 and np.all(np.abs(r["rest_gyro_mean_dps"]) < 0.05)
    # frames agree: the gyro follows the ground truth's rate and the specific force points up in it
    assert r["gt_up"][2] > 0.95 and (r["gt_gyro_angle_deg"] is None or r["gt_gyro_angle_deg"] < 10)
    assert "c" in format_summary_table([r])
    # ground truth missing at the start
    q = s.quat.copy()
    q[:30] = np.nan
    s2 = ImuSequence(name="x", source="t", time=s.time, gyro=s.gyro, accel=s.accel, quat=q)
    r2 = summarize(s2)
    assert r2["gt_missing_at_start"] and r2["gt_start_s"] == pytest.approx(0.30)


# ------------------------------------------------------------------------ configs (yaml)
@pytest.mark.parametrize("name", ["broad", "euroc", "tumvi", "oxiod", "generic"])
def test_config_contract(name):
    c = OmegaConf.load(CONF / f"{name}.yaml")
    assert c.name == name and c.split in ("train", "val", "trainval", "test", "all") and c.axes in (6, 9)
    assert set(c.train_part) <= {"fraction", "seconds"}
    assert set(c.train).isdisjoint(c.test)


def test_broad_config_split():
    c = OmegaConf.load(CONF / "broad.yaml")
    assert sorted(n[:2] for n in c.test) == BROAD_TEST
    assert sorted(n[:2] for n in c.train) == BROAD_TRAIN
    assert c.train_part.fraction == 0.7


def test_euroc_tumvi_oxiod_config_lists():
    e = OmegaConf.load(CONF / "euroc.yaml")
    assert list(e.train) == ["MH_01_easy", "MH_03_medium", "MH_05_difficult", "V1_02_medium", "V2_01_easy",
                             "V2_03_difficult"]
    assert list(e.test) == ["MH_02_easy", "MH_04_difficult", "V1_01_easy", "V1_03_difficult", "V2_02_medium"]
    assert e.train_part.seconds == 80 and e.axes == 6
    t = OmegaConf.load(CONF / "tumvi.yaml")
    assert [n.split("_")[0] for n in t.train] == ["dataset-room1", "dataset-room3", "dataset-room5"]
    assert [n.split("_")[0] for n in t.test] == ["dataset-room2", "dataset-room4", "dataset-room6"]
    o = OmegaConf.load(CONF / "oxiod.yaml")
    assert len(o.train) == 6 and list(o.test) == []


# --------------------------------------------------------------------------- real roots
def test_real_roots_match_configs():
    """Every configured training recording is present in ../shared; the lists cover the folders."""
    for name in ["broad", "euroc", "tumvi", "oxiod"]:
        root = shared(name)
        c = OmegaConf.load(CONF / f"{name}.yaml")
        found = ds.loader(name).list_recordings(root)
        assert set(c.train) <= set(found), (name, set(c.train) - set(found))
        assert set(found) <= set(c.train) | set(c.test), (name, set(found) - set(c.train) - set(c.test))


def test_real_euroc_train_is_first_80s():
    shared("euroc")
    c = OmegaConf.load(CONF / "euroc.yaml")
    c.train = ["V1_02_medium"]
    c.root = str(SHARED / "euroc")
    tr, va = load_split(c, "train")[0], load_split(c, "val")[0]
    assert tr.duration == pytest.approx(80.0, abs=0.01) and va.time[0] >= 80.0
    with pytest.warns(UserWarning, match="MH_02_easy"):
        assert load_split(c, "test") == []


def test_real_broad_test_split_and_6_axes():
    shared("broad")
    c = OmegaConf.load(CONF / "broad.yaml")
    c.root = str(SHARED / "broad")
    c.test = ["30_disturbed_stationary_magnet_C"]
    c.axes = 6
    (s,) = load_split(c, "test")
    assert s.mag is None and s.meta["groups"][:2] == ["all_trials", "disturbed"] and s.score_mask is not None


def test_inspect_data_script():
    shared("tumvi")
    out = subprocess.run([sys.executable, "scripts/inspect_data.py", "data=tumvi"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert "recordings=3" in lines[0]
    row = [ln for ln in lines if ln.startswith("dataset-room3_512_16")][0]
    assert float(row.split()[1]) == pytest.approx(141.0, abs=0.5)   # duration
    assert 28 <= int(row.split()[5]) <= 36                           # README: 31 gaps > 50 ms
    # and what the sensors' health checks find in each recording (TUM VI: clean)
    assert "health, dataset-room3_512_16: no fault found" in lines


def test_split_recording_edges(generic_root):
    (s,) = load_split(cfg(generic_root), "test")       # 10 s at 100 Hz
    tr, va = split_recording(s, {"seconds": 80})
    assert len(tr) == 1000 and va is None               # nothing left to validate on
    tr, va = split_recording(s, {"fraction": 0.25})
    assert len(tr) == 250 and len(va) == 750 and va.meta["part_start_s"] == pytest.approx(2.5)


# ------------------------------------------------------------------ leave-recordings-out folds
def test_fold_holds_out_whole_recordings(generic_root):
    c = cfg(generic_root, folds=[["a"], ["sub/b"]], fold=0)
    train, val = load_split(c, "train"), load_split(c, "val")
    assert [s.name for s in val] == ["a"] and [s.name for s in train] == ["sub/b"]
    assert len(val[0]) == 10000 and len(train[0]) == 5000  # whole recordings, not parts
    c1 = cfg(generic_root, folds=[["a"], ["sub/b"]], fold=1)
    assert [s.name for s in load_split(c1, "val")] == ["sub/b"]
    assert [s.name for s in load_split(c1, "train")] == ["a"]
    # test and trainval do not depend on the fold
    assert [s.name for s in load_split(c1, "test")] == ["c"]
    assert sorted(s.name for s in load_split(c1, "trainval")) == ["a", "sub/b"]


def test_bad_fold_index_is_a_clear_error(generic_root):
    with pytest.raises(DataError, match="fold"):
        load_split(cfg(generic_root, folds=[["a"]], fold=3), "train")


@pytest.mark.parametrize("name", ["broad", "euroc", "tumvi", "oxiod"])
def test_shipped_folds_cover_training_recordings_once(name):
    c = OmegaConf.load(CONF_DIR / "data" / f"{name}.yaml")
    held = [r for f in c.folds for r in f]
    assert sorted(held) == sorted(c.train), f"{name}: every training recording in exactly one fold"
    assert not set(held) & set(c.test or [])
