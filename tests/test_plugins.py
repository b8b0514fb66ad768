"""A newcomer adds each kind of part with one code file and one config file, editing nothing.

Each test writes a tiny plugin module and its YAML into ``tmp_path`` (the module importable
through ``sys.path``, the YAML in a config folder added to Hydra's search path) and shows that
the project picks it up:

* classical filter: a module registering a ``ClassicalEstimator`` with ``@registry.register``;
  ``conf/plugin/<name>.yaml`` (``+plugin=<name>``) lists it in ``plugins`` and ``baselines``
  -> the registry builds it -> the evaluation runner scores it;
* dataset: a module with ``list_recordings`` / ``load_recording``; ``conf/data/<name>.yaml``
  names it (``name: module``) -> ``datasets.load_split``;
* metric: a module with ``@metrics.register_metric``; ``conf/plugin/<name>.yaml`` lists it in
  ``plugins`` -> every results dict, mean and table;
* model variant: a network class; ``conf/model/<variant>.yaml`` names it (``gyro_net:
  module.Class``) -> ``LearnedAHRS.from_config`` (tcn_ahrs/model/calibration.py imports it);
* paper reproduction: a module with ``main(cfg, out)``; ``conf/paper/<name>.yaml`` names it
  (``module:``) -> ``tcn_ahrs.reproduce.run`` (what scripts/reproduce.py calls).
"""
from __future__ import annotations

import json
import sys
import textwrap
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from tcn_ahrs import metrics
from tcn_ahrs.conf import CONF_DIR
from tcn_ahrs.estimators import registry

from synthetic_filters import simulate, wavy



@contextmanager
def compose(config_name: str, plugin_conf: Path, overrides=()):
    """The project's config ``config_name`` composed with ``plugin_conf`` (a newcomer's config
    folder, same layout as conf/) on Hydra's search path."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        yield hydra_compose(config_name, overrides=[f"hydra.searchpath=[file://{plugin_conf}]", *overrides])


@pytest.fixture
def plugin_dirs(tmp_path, monkeypatch):
    """(code folder on sys.path, config folder); registrations and imported plugin modules
    are undone afterwards so no other test sees them."""
    code, conf = tmp_path / "code", tmp_path / "conf"
    code.mkdir()
    conf.mkdir()
    monkeypatch.syspath_prepend(str(code))
    registry.methods()  # the built-in methods registered, then a copy to register into
    monkeypatch.setattr(registry, "_METHODS", dict(registry._METHODS))
    monkeypatch.setattr(metrics, "_EXTRA", dict(metrics._EXTRA))
    before = set(sys.modules)
    yield code, conf
    for name in set(sys.modules) - before:
        if name.startswith("newcomer_"):
            del sys.modules[name]


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text).lstrip())
    return path


def recordings(n=2, duration=4.0):
    return [simulate(duration=duration, rate=50.0, omega=wavy, seed=i) for i in range(n)]


# ----------------------------------------------------------------------------- classical filter


def test_a_classical_filter_is_one_module_and_one_config(plugin_dirs):
    code, conf = plugin_dirs
    write(code / "newcomer_filter.py", '''
        """Gyro integration with a scale factor: the smallest classical filter."""
        from dataclasses import dataclass
        from typing import ClassVar, Dict

        import torch

        from tcn_ahrs import so3
        from tcn_ahrs.estimators.classical import ClassicalEstimator
        from tcn_ahrs.estimators.registry import register


        @register("scaled_gyro", "classical")
        @dataclass
        class ScaledGyro(ClassicalEstimator):
            gyro_scale: float = 1.0  # multiplies the angular rate
            default_grid: ClassVar[Dict[str, list]] = {"gyro_scale": [0.9, 1.0, 1.1]}

            def _filter(self, gyro, accel, dt, q0, mag, p):
                # gyro (R, N, 3), dt (R, N), q0 (R, 4); a parameter is a scalar, or (P, 1) when the
                # tuner batches P values: the outputs then lead with (P, R)
                s = p["gyro_scale"]
                inc = so3.quat_exp(s.reshape(s.shape + (1, 1)) * gyro[..., 1:, :] * dt[..., 1:, None])
                first = q0[..., None, :].expand(inc.shape[:-2] + (1, 4))
                return {"quat": so3.cumprod_quat(torch.cat([first, inc], -2))}
        ''')
    write(conf / "plugin" / "scaled_gyro.yaml", '''
        # @package _global_
        # python scripts/evaluate.py +plugin=scaled_gyro (compare, benchmark: the same)
        plugins: [newcomer_filter]
        baselines: [scaled_gyro, raw]
        ''')
    with compose("evaluate", conf, ["+plugin=scaled_gyro"]) as cfg:
        assert list(cfg.plugins) == ["newcomer_filter"] and cfg.data.name == "simulated"  # the project's defaults kept
        registry.load_plugins(cfg.plugins)
        assert "scaled_gyro" in registry.methods("classical")
        method = registry.get("scaled_gyro")
        assert method.tunable and len(method.grid) == 3
        ests = registry.baseline_estimators(cfg.baselines, axes=9)
    from tcn_ahrs.evaluate.runner import evaluate

    res = evaluate(ests, recordings())
    assert set(res["methods"]) == {"scaled_gyro9d", "Raw IMU"}
    ours, raw = res["methods"]["scaled_gyro9d"], res["methods"]["Raw IMU"]
    assert len(ours["recordings"]) == 2
    # with gyro_scale 1 it IS strapdown integration: the same errors as the Raw IMU column
    for a, b in zip(ours["recordings"], raw["recordings"]):
        assert a["aae_deg"] == pytest.approx(b["aae_deg"], rel=1e-6, abs=1e-9)
    assert 0.0 < ours["mean"]["aae_deg"] < 10.0
    # and the tuner batches its grid like a built-in's: the true scale (1) wins
    from tcn_ahrs.tuning.grid import tune_method

    best, ranked = tune_method("scaled_gyro", 9, recordings())
    assert best == {"gyro_scale": 1.0} and len(ranked) == 3


# ------------------------------------------------------------------------------------- dataset


def test_a_dataset_is_one_module_and_one_data_config(plugin_dirs, tmp_path):
    code, conf = plugin_dirs
    root = tmp_path / "recordings"
    root.mkdir()
    for i, seq in enumerate(recordings(3)):
        np.savez(root / f"walk{i}.npz", time=seq.time, gyro=seq.gyro, accel=seq.accel, mag=seq.mag, quat=seq.quat)
    write(code / "newcomer_dataset.py", '''
        """Recordings as .npz files (time, gyro, accel, mag, quat) under root."""
        from pathlib import Path

        import numpy as np

        from tcn_ahrs.sequence import ImuSequence


        def list_recordings(root):
            return sorted(p.stem for p in Path(root).glob("*.npz"))


        def load_recording(root, name):
            d = np.load(Path(root) / f"{name}.npz")
            return ImuSequence(name=name, source=str(Path(root) / f"{name}.npz"), time=d["time"], gyro=d["gyro"],
                               accel=d["accel"], mag=d["mag"], quat=d["quat"], rate=50.0)
        ''')
    write(conf / "data" / "npz_walks.yaml", f'''
        name: newcomer_dataset
        root: {root}
        split: train
        train: [walk0, walk1]
        test: [walk2]
        train_part: {{fraction: 0.75}}
        axes: 9
        ''')
    from tcn_ahrs import datasets

    with compose("train", conf, ["data=npz_walks"]) as cfg:
        assert cfg.data.name == "newcomer_dataset"
        assert datasets.list_recordings(cfg.data) == ["walk0", "walk1", "walk2"]
        test = datasets.load_split(cfg.data, "test")
        train = datasets.load_split(cfg.data, "train")
        val = datasets.load_split(cfg.data, "val")
        six = datasets.load_split(OmegaConf.merge(cfg.data, {"axes": 6}), "test")
    assert [s.name for s in test] == ["walk2"] and len(test[0]) == 200 and test[0].has_mag
    assert [len(s) for s in train] == [150, 150] and [len(s) for s in val] == [50, 50]
    assert not six[0].has_mag
    # the scripts' early override check (python scripts/train.py hydra.searchpath=[file://...]
    # data=npz_walks) finds it too, and names it for a misspelt option
    from tcn_ahrs.app import check_overrides

    check_overrides("train", [f"hydra.searchpath=[file://{conf}]", "data=npz_walks"], conf_dir=CONF_DIR)
    with pytest.raises(SystemExit):
        check_overrides("train", [f"hydra.searchpath=[file://{conf}]", "data=npz_walk"], conf_dir=CONF_DIR)


# -------------------------------------------------------------------------------------- metric


def test_a_metric_is_one_module_and_one_config(plugin_dirs):
    code, conf = plugin_dirs
    write(code / "newcomer_metric.py", '''
        """95th percentile of the attitude error."""
        import numpy as np

        from tcn_ahrs.metrics import attitude_errors, register_metric


        @register_metric("p95_deg", "P95")
        def p95(q_gt, q_est, mask=None, align=True):
            angle, _ = attitude_errors(q_gt, q_est, mask, align)
            return float(np.degrees(np.percentile(angle if mask is None else angle[mask], 95)))
        ''')
    write(conf / "plugin" / "p95.yaml", '''
        # @package _global_
        plugins: [newcomer_metric]
        baselines: [mahony]
        ''')
    with compose("evaluate", conf, ["+plugin=p95"]) as cfg:
        registry.load_plugins(cfg.plugins)
        ests = registry.baseline_estimators(cfg.baselines, axes=9)
    assert "p95_deg" in metrics.metric_keys()
    from tcn_ahrs.evaluate.runner import evaluate, results_markdown

    res = evaluate(ests, recordings())
    col = res["methods"]["mahony9d"]
    rows = col["recordings"]
    assert len(rows) == 2 and all(np.isfinite(r["p95_deg"]) and r["p95_deg"] > 0 for r in rows)  # per recording
    assert col["mean"]["p95_deg"] == pytest.approx(np.mean([r["p95_deg"] for r in rows]))  # and in the mean
    assert "P95" in results_markdown(res)  # and in the table


# ------------------------------------------------------------------------------- model variant


def test_a_model_variant_is_one_network_module_and_one_model_config(plugin_dirs):
    code, conf = plugin_dirs
    write(code / "newcomer_nets.py", '''
        """A gyro error network of one's own: a causal moving mean of the inputs, then a linear layer."""
        import torch
        from torch import nn


        class MovingMean(nn.Module):
            def __init__(self, in_channels, out_channels, window=16, **tcn_kwargs):  # model.tcn's keys: unused
                super().__init__()
                self.window = int(window)
                self.receptive_field = self.window
                self.out = nn.Linear(in_channels, out_channels)

            def forward(self, x):  # (B, N, C) -> (B, N, out)
                c = torch.cumsum(x, 1)
                before = torch.nn.functional.pad(c, (0, 0, self.window, 0))[:, : c.shape[1]]
                return self.out((c - before) / self.window)
        ''')
    write(conf / "model" / "moving_mean.yaml", '''
        # the default closed loop with a moving-mean gyro network (newcomer_nets.py)
        defaults:
          - ahrs
          - _self_
        variant: moving_mean${data.axes}
        gyro_net: newcomer_nets.MovingMean
        ''')
    from tcn_ahrs.model.ahrs import LearnedAHRS

    with compose("train", conf, ["model=moving_mean"]) as cfg:
        assert cfg.model.variant == "moving_mean9" and cfg.model.loop == "closed"  # ahrs.yaml's keys inherited
        model = LearnedAHRS.from_config(OmegaConf.to_container(cfg.model, resolve=True), axes=int(cfg.data.axes))
    net = model.calibration.gyro_error_net
    assert type(net).__name__ == "MovingMean" and net.window == 16
    model.calibration.set_gyro_bias(torch.tensor([0.01, -0.02, 0.005]))  # the training start works on it
    seq = recordings(1, duration=2.0)[0]
    imu = torch.as_tensor(np.concatenate([seq.gyro, seq.accel, seq.mag], 1), dtype=torch.float32)[None]
    cal = model.calibration(imu)
    assert cal["gyro"].shape == (1, len(seq), 3) and torch.isfinite(cal["gyro"]).all()
    # the error term starts at the bias set above (the network's weights act on a moving mean)
    assert cal["gyro_error"].abs().max() > 0
    # and the variant is an estimator like any checkpoint: the evaluation runner scores it
    from tcn_ahrs.estimators.learned import LearnedEstimator
    from tcn_ahrs.evaluate.runner import evaluate

    res = evaluate([LearnedEstimator(model, name="moving mean")], recordings(1, duration=3.0))
    assert np.isfinite(res["methods"]["moving mean"]["mean"]["aae_deg"])
    with pytest.raises(ValueError, match="cannot import"):
        with compose("train", conf, ["model=moving_mean", "model.gyro_net=newcomer_nets.Missing"]) as cfg:
            LearnedAHRS.from_config(OmegaConf.to_container(cfg.model, resolve=True), axes=9)


# -------------------------------------------------------------------------- paper reproduction


def test_a_paper_reproduction_is_one_module_and_one_paper_config(plugin_dirs, tmp_path):
    code, conf = plugin_dirs
    write(code / "newcomer_paper.py", '''
        """A paper's table: the mean attitude error of Mahony on seeded simulated recordings."""
        import json
        from pathlib import Path


        def main(cfg, out):
            import numpy as np

            from tcn_ahrs.estimators.registry import build
            from tcn_ahrs.evaluate.runner import evaluate
            from synthetic_filters import simulate, wavy

            seqs = [simulate(duration=float(cfg["duration"]), omega=wavy, seed=s) for s in range(int(cfg["seeds"]))]
            res = evaluate([build("mahony", 9)], seqs)
            ours = res["methods"]["mahony9d"]["mean"]["aae_deg"]
            results = {"paper": cfg["paper_aae_deg"], "ours": ours}
            Path(out).mkdir(parents=True, exist_ok=True)
            (Path(out) / "results.json").write_text(json.dumps(results))
            (Path(out) / "results.md").write_text(f"| | paper | ours |\\n|---|---|---|\\n| AAE | {cfg['paper_aae_deg']} | {ours:.2f} |\\n")
            return results
        ''')
    write(conf / "paper" / "newcomer_table.yaml", '''
        # conf/paper/<name>.yaml of a reproduction living outside tcn_ahrs/reproduce/
        name: newcomer_table
        module: newcomer_paper   # the module with main(cfg, out)
        seeds: 2
        duration: 3.0
        paper_aae_deg: 1.5
        ''')
    from tcn_ahrs.reproduce import papers, run

    with compose("reproduce", conf, ["paper=newcomer_table", "paper.seeds=1"]) as cfg:
        paper = OmegaConf.to_container(cfg.paper, resolve=True)  # as scripts/reproduce.py
    out = tmp_path / "out"
    res = run(str(paper["name"]), paper, out)
    assert res["paper"] == 1.5 and np.isfinite(res["ours"])
    assert json.loads((out / "results.json").read_text()) == res
    assert "| AAE | 1.5 |" in (out / "results.md").read_text()
    # the package's own experiments and the unknown-name error are as before
    assert "uwb_arckf" in papers() and "newcomer_table" not in papers()
    with pytest.raises(ValueError, match="unknown experiment"):
        run("no_such_paper", {"name": "no_such_paper"}, out)
