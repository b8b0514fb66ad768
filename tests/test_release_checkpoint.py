"""Released checkpoints: same model, no optimiser state."""
import torch

from tcn_ahrs.checkpoint import atomic_save, layout_meta, model_from_checkpoint, release_checkpoint
from tcn_ahrs.model.ahrs import LearnedAHRS


def test_release_keeps_weights_and_drops_optimiser(tmp_path):
    cfg = {"variant": "ahrs6", "axes": 6, "preintegration": "denoised"}
    model = LearnedAHRS.from_config(cfg)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.01 * torch.randn_like(p))
    state = {f"model.{k}": v for k, v in model.state_dict().items()}
    full = {"state_dict": state, "tcn_ahrs": layout_meta(cfg, 6, "euroc", 200.0),
            "optimizer_states": [{"state": {i: torch.randn(1000) for i in range(50)}}], "epoch": 3}
    atomic_save(full, tmp_path / "full.ckpt")
    meta = release_checkpoint(tmp_path / "full.ckpt", tmp_path / "slim.ckpt")
    assert meta["layout"] == {"axes": 6, "channels": meta["layout"]["channels"], "rate_hz": 200.0}
    slim = torch.load(tmp_path / "slim.ckpt", weights_only=True)
    assert "optimizer_states" not in slim and slim["epoch"] == 3
    back = model_from_checkpoint(tmp_path / "slim.ckpt", axes=6)
    for (k, a), b in zip(model.state_dict().items(), back.state_dict().values()):
        assert torch.equal(a, b), k
    assert (tmp_path / "slim.ckpt").stat().st_size < (tmp_path / "full.ckpt").stat().st_size
