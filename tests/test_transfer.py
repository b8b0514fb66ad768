"""The cross-dataset matrix (tcn_ahrs.experiments.transfer): which recordings a cell holds, and one real
cell end to end on the simulator with an untrained residual checkpoint (= the backbone)."""
from __future__ import annotations


import numpy as np
from omegaconf import OmegaConf

from tcn_ahrs.checkpoint import atomic_save, layout_meta
from tcn_ahrs.experiments.transfer import cell_recordings, markdown, transfer

from test_residual import residual_model
from tcn_ahrs.conf import CONF_DIR

CONF = CONF_DIR


def test_cell_recordings():
    assert cell_recordings({"name": "broad", "test": ["05"]}, own=True) == "test"
    assert cell_recordings({"name": "euroc", "test": []}, own=True) is None
    assert cell_recordings({"name": "euroc", "train": ["MH_01"], "test": ["MH_02"]}, own=False) == "trainval"
    assert cell_recordings({"name": "iphone4s", "train": [], "test": ["a"]}, own=False) == "test"  # all test
    assert cell_recordings({"name": "simulated"}, own=True) == "test"


def test_transfer_cell_on_the_simulator(tmp_path):
    model = residual_model(9)
    cfg = OmegaConf.to_container(OmegaConf.load(CONF / "model" / "residual.yaml"), resolve=False)
    path = tmp_path / "untrained.ckpt"
    state = {f"model.{k}": v for k, v in model.state_dict().items()}
    model_cfg = {k: v for k, v in cfg.items() if k != "defaults"}
    model_cfg.update(axes=9, variant="residual9")
    atomic_save({"state_dict": state, "tcn_ahrs": layout_meta(model_cfg, 9, "broad", 100.0)}, path)
    sim = OmegaConf.to_container(OmegaConf.load(CONF / "data" / "simulated.yaml"), resolve=True)
    sim["splits"]["test"].update(count=1, duration=20.0)
    res = transfer({"untrained": str(path)}, {"simulated": sim}, ["raw", "backbone"], tmp_path / "out", verbose=False)
    cell = res["matrix"]["untrained"]["simulated"]
    assert cell["split"] == "test" and cell["recordings"]
    # the untrained model is the backbone: equal scores, so never worse than it
    assert np.isclose(cell["learned"]["aae_deg"], cell["backbone"]["aae_deg"], atol=1e-6)
    assert cell["never_worse"] == (cell["learned"]["aae_deg"] <= cell["best_metrics"]["aae_deg"]
                                   and cell["learned"]["inclination_deg"] <= cell["best_inclination_deg"])
    md = (tmp_path / "out" / "transfer.md").read_text()
    assert "untrained (9-axis, broad)" in md and md == markdown(res)


def test_the_matrix_names_each_shipped_models_family(tmp_path):
    """A classical estimator file the search shipped and a learned checkpoint are both rows of the
    matrix, each named by its family (what the README's summary prints)."""
    from pathlib import Path

    from tcn_ahrs.estimators.families import save_estimator
    from tcn_ahrs.experiments.transfer import shipped_meta, shipped_paths

    root = Path(__file__).resolve().parents[1] / "checkpoints"
    save_estimator(tmp_path / "mine6.json", "ecf", 6, {"k_norm": 0.1, "a_min": 1.0}, None, {"dataset": "simulated"})
    assert shipped_meta(str(tmp_path / "mine6.json")) == {"axes": 6, "data": "simulated", "family": "ecf (tuned)"}
    # a residual whose knobs switch both networks off is called the classical filter it runs as
    assert shipped_meta(str(root / "broad9_residual.ckpt"))["family"] == "backbone, tuned knobs (networks off)"
    assert shipped_meta(str(root / "general9_residual.ckpt"))["family"] == "learned residual"
    assert set(shipped_paths(tmp_path)) == {"mine6"}
