"""Every checkpoint shipped in checkpoints/ loads, runs on a short recording, is at most 2 MB and
has a model card beside it."""
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
