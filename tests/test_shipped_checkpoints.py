"""Every checkpoint shipped in checkpoints/ (learned ``*.ckpt``, or a classical family chosen by
``tcn-ahrs search``: ``*.json``) loads, runs on a short recording, is at most 2 MB and has a model
card beside it."""
from pathlib import Path

import pytest
import torch

from tcn_ahrs.checkpoint import model_from_checkpoint

CKPTS = sorted((Path(__file__).resolve().parents[1] / "checkpoints").rglob("*.ckpt"))


@pytest.mark.parametrize("path", CKPTS, ids=[p.name for p in CKPTS])
def test_shipped_checkpoint_loads_runs_and_has_a_card(path):
    assert path.stat().st_size <= 2 * 1024 * 1024
    assert path.with_suffix(".md").is_file(), f"{path.name}: model card {path.with_suffix('.md').name} missing"
    model = model_from_checkpoint(path)
    n = 300
    imu = torch.zeros(1, n, model.axes)
    imu[..., 5] = 9.81
    if model.axes == 9:
        imu[..., 7], imu[..., 8] = 20.0, -40.0
    with torch.no_grad():
        out = model.run_sequence(imu, torch.full((1, n), 0.0035), torch.eye(3)[None], 0)
    assert out["rot"].shape == (1, n, 3, 3) and torch.isfinite(out["rot"]).all()


ESTIMATORS = sorted((Path(__file__).resolve().parents[1] / "checkpoints").glob("*.json"))


@pytest.mark.parametrize("path", ESTIMATORS, ids=[p.name for p in ESTIMATORS])
def test_shipped_estimator_file_loads_runs_and_has_a_card(path):
    """A classical family the search shipped: the card names its family, and it runs at rest."""
    import numpy as np

    from tcn_ahrs.datasets.simulate import simulate
    from tcn_ahrs.estimators.families import load_estimator, read_estimator
    from tcn_ahrs.metrics import aae_and_inclination

    doc = read_estimator(path)
    card = path.with_suffix(".md")
    assert card.is_file(), f"{path.name}: model card {card.name} missing"
    assert doc["family"] in card.read_text()
    seq = simulate("static", 10.0, 100.0, seed=0, axes=doc["axes"], noise_free=True)
    q = load_estimator(path).run(seq, seq.quat[0], 0).quat
    assert q.shape == (len(seq.time), 4) and np.isfinite(q).all()
    # at rest from the truth, every family stays within a degree of it (the one yardstick)
    aae, inclination = aae_and_inclination(seq, q, doc["axes"])
    assert aae < 1.0 and inclination < 1.0
