"""The closed loop's three implementations agree: the tensor scan (autograd, the reference),
the numba loop with its hand-written reverse pass (evaluation and CPU training) and the
TorchScript scalar loop (the exports)."""

import pytest
import torch

from tcn_ahrs.model import closed_loop_step as step
from tcn_ahrs.model.closed_loop import _scan, closed_loop_scan
from tolerances import PARITY_F64, REL_METRIC_F64

pytest.importorskip("numba")
from tcn_ahrs.model import closed_loop_compiled as compiled  # noqa: E402


def _inputs(b=3, n=200, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)

    def unit(x):
        return x / x.norm(dim=-1, keepdim=True)

    rot0 = torch.linalg.matrix_exp(torch.tensor([[0.0, -0.3, 0.2], [0.3, 0.0, -0.1], [-0.2, 0.1, 0.0]])).expand(b, 3, 3)
    return (rot0.to(dtype).clone(), 0.01 * torch.randn(b, 3, generator=g, dtype=dtype),
            torch.randn(b, n, 3, generator=g, dtype=dtype), unit(torch.randn(b, n, 3, generator=g, dtype=dtype)),
            unit(torch.randn(b, n, 3, generator=g, dtype=dtype)), torch.rand(b, n, 1, generator=g, dtype=dtype),
            0.3 * torch.rand(b, n, 1, generator=g, dtype=dtype),
            0.01 * (torch.rand(b, n, 1, generator=g, dtype=dtype) > 0.7).to(dtype),
            unit(torch.tensor([[1.0, 0.2, 0.0]] * b, dtype=dtype)),
            0.01 + 0.002 * torch.rand(b, n, 1, generator=g, dtype=dtype), torch.tensor(0.003, dtype=dtype))


def test_numba_and_torchscript_loops_equal_the_tensor_scan():
    args = _inputs()
    ref = _scan(*args)
    scalar = torch.jit.script(step.scan_scalar)
    for got in (compiled.scan_numba(*args), scalar(*args), compiled.ScanFunction.apply(*args)):
        for a, b in zip(ref, got):
            assert float((a - b).abs().max()) < PARITY_F64[1]


def test_compiled_reverse_pass_equals_autograd_through_the_tensor_scan():
    args = [a.clone().requires_grad_(True) for a in _inputs(b=2, n=120, seed=1)]
    g = torch.Generator().manual_seed(5)
    weights = [torch.randn(o.shape, generator=g, dtype=torch.float64) for o in closed_loop_scan(*args)]

    def grads(fn):
        outs = fn(*args)
        loss = sum((w * o).sum() for w, o in zip(weights, outs))
        return torch.autograd.grad(loss, args)

    for a, b in zip(grads(closed_loop_scan), grads(compiled.ScanFunction.apply)):
        scale = float(a.abs().max()) + 1e-12
        assert float((a - b).abs().max()) / scale < REL_METRIC_F64  # reverse pass: another summation order


def test_training_takes_the_compiled_path_with_the_same_gradients():
    from tcn_ahrs.model.ahrs import LearnedAHRS

    torch.manual_seed(0)
    model = LearnedAHRS(axes=9, loop="closed", tcn={"channels": [4, 4, 4, 4]}).train()
    model.closed.set_rate(100.0)
    for p in model.parameters():
        torch.nn.init.normal_(p, std=0.05) if p.dim() > 1 else None
    g = torch.Generator().manual_seed(1)
    imu = torch.cat([0.3 * torch.randn(2, 600, 3, generator=g),
                     torch.tensor([0.0, 0.0, 9.81]) + 0.3 * torch.randn(2, 600, 3, generator=g),
                     torch.tensor([0.0, 20.0, -40.0]) + torch.randn(2, 600, 3, generator=g)], -1)
    dt = torch.full((2, 600), 0.01)
    rot0 = torch.eye(3).expand(2, 3, 3).contiguous()
    grads = {}
    for backend in ("torch", "auto"):
        model.closed.backend = backend
        torch.manual_seed(3)  # the same dropout masks
        out = model.filter_closed_loop(imu, dt, rot0, context=511)
        # the path taken: the compiled reverse pass for "auto", autograd nodes for "torch"
        assert (type(out["rot"].grad_fn).__name__ == "ScanFunctionBackward") == (backend == "auto")
        loss = out["rot"].square().sum() + out["gyro_bias"].sum()
        model.zero_grad()
        loss.backward()
        grads[backend] = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
    assert set(grads["torch"]) == set(grads["auto"]) and len(grads["auto"]) > 10
    for n, a in grads["torch"].items():
        b = grads["auto"][n]
        # float32 training: the tensor scan runs in float32, the compiled one in float64
        assert float((a - b).abs().max()) <= 2e-3 * float(a.abs().max()) + 1e-6, n
