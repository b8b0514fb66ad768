"""The GPU path: the same code on CUDA gives the CPU's numbers. Runs where a GPU is present
(e.g. the lent device machine); skipped elsewhere. Nothing in the package calls .cuda():
devices come from the inputs or from Lightning."""
import pytest
import torch

from tcn_ahrs import so3
from tcn_ahrs.datasets.simulate import simulate
from tcn_ahrs.filters.ecf import ecf
from tcn_ahrs.losses import increment_loss
from tcn_ahrs.config.model import PAPER_MODEL  # the paper's open-loop model
from tcn_ahrs.model.ahrs import LearnedAHRS

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")


def _batch(device, n=600):
    seq = simulate("walking", duration=n / 100.0, rate=100.0, seed=3)
    imu = torch.tensor(seq.imu(), dtype=torch.float32, device=device)[None]
    dt = torch.tensor(seq.dt, dtype=torch.float32, device=device)[None]
    rot = so3.quat_to_matrix(torch.tensor(seq.quat, device=device))[None]
    return seq, imu, dt, rot


@cuda
def test_model_loss_and_gradients_match_cpu():
    torch.manual_seed(0)
    model = LearnedAHRS(axes=9, **PAPER_MODEL).eval()
    outs = {}
    for dev in ("cpu", "cuda"):
        m = model.to(dev)
        m.zero_grad()
        _, imu, dt, rot = _batch(dev)
        out = m(imu, dt, rot[:, 0].float())
        loss = increment_loss(out["omega"], dt, rot, torch.ones_like(dt, dtype=torch.bool))
        loss.backward()
        outs[dev] = (out["omega"].detach().cpu(), loss.item(),
                     m.ecf.acc_gain.grad.detach().cpu().clone())
    assert torch.allclose(outs["cpu"][0], outs["cuda"][0], atol=1e-4)
    assert outs["cpu"][1] == pytest.approx(outs["cuda"][1], rel=1e-3)
    assert torch.allclose(outs["cpu"][2], outs["cuda"][2], rtol=1e-2, atol=1e-6)


@cuda
def test_classical_filter_matches_cpu():
    seq = simulate("slow_rotation", duration=10.0, rate=100.0, seed=4)
    res = {}
    for dev in ("cpu", "cuda"):
        t = lambda a: torch.tensor(a, dtype=torch.float64, device=dev)  # noqa: E731
        res[dev] = ecf(t(seq.gyro), t(seq.accel), t(seq.dt), t(seq.quat[0]), mag=t(seq.mag))["quat"].cpu()
    assert torch.allclose(res["cpu"], res["cuda"], atol=1e-9)
