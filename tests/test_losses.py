"""Increment loss (Eqs. 26-28): zero at the truth, masking, float64 products."""
import pytest
import torch

from tcn_ahrs import so3
from tolerances import ANGLE_F64, EXACT_F64, ROTATION_F64, SCAN_F64
from tcn_ahrs.losses import (increment_loss, increment_valid, predicted_increments, true_increments,
                             window_products)


def _trajectory(b=2, n=400, seed=0):
    """Ground truth (B, N, 3, 3) and the exact body rates that generate it (sample k moves k-1 -> k)."""
    g = torch.Generator().manual_seed(seed)
    dt = torch.full((b, n), 0.01, dtype=torch.float64)
    omega = torch.cumsum(0.3 * torch.randn(b, n, 3, generator=g, dtype=torch.float64), 1) * 0.1
    r0 = so3.exp(torch.randn(b, 3, generator=g, dtype=torch.float64))
    return so3.integrate(r0, omega, dt), omega, dt


@pytest.mark.parametrize("j", [1, 2, 5, 16, 32, 33])
def test_window_products_match_sequential_reference(j):
    r = so3.exp(0.2 * torch.randn(2, 70, 3, dtype=torch.float64))
    got = window_products(r, j)
    ref = torch.stack([so3.cumprod_matrix_sequential(r[:, i:i + j])[:, -1] for i in range(70 - j + 1)], 1)
    assert got.shape == ref.shape
    assert torch.allclose(got, ref, atol=EXACT_F64)


def test_predicted_increments_equal_true_increments_of_integration():
    rot, omega, dt = _trajectory()
    for j in (16, 32):
        assert torch.allclose(predicted_increments(omega, dt, j), true_increments(rot, j), atol=ROTATION_F64)


def test_loss_zero_for_perfect_prediction_and_positive_otherwise():
    rot, omega, dt = _trajectory()
    valid = torch.ones(rot.shape[:2], dtype=torch.bool)
    assert float(increment_loss(omega, dt, rot, valid)) < ANGLE_F64
    biased = omega + torch.tensor([0.01, 0.0, 0.0], dtype=torch.float64)
    l1 = float(increment_loss(biased, dt, rot, valid))
    l2 = float(increment_loss(omega + torch.tensor([0.02, 0.0, 0.0], dtype=torch.float64), dt, rot, valid))
    assert 0 < l1 < l2
    # a constant bias b over j samples gives |Log| ~ b j dt per increment; Huber/δ of it ~ that - δ/2
    expected = (0.01 * 16 * 0.01 - 0.0025) + (0.01 * 32 * 0.01 - 0.0025)
    assert abs(l1 - expected) / expected < 0.05


def test_masked_increments_are_ignored():
    rot, omega, dt = _trajectory()
    valid = torch.ones(rot.shape[:2], dtype=torch.bool)
    valid[0, 100:140] = False
    valid[1, :5] = False
    pred = omega + 0.003 * torch.randn_like(omega)
    clean = increment_loss(pred, dt, rot, valid)
    garbage = rot.clone()
    garbage[~valid] = so3.exp(torch.randn(int((~valid).sum()), 3, dtype=torch.float64))
    garbage[0, 120] = float("nan")
    assert torch.isfinite(increment_loss(pred, dt, garbage, valid))
    assert torch.equal(increment_loss(pred, dt, garbage, valid), clean)


def test_increment_valid():
    v = torch.tensor([[True, True, True, False, True, True, True, True]])
    m = increment_valid(v, 2)  # increments (i, i+2) for i = 0..5
    assert m.tolist() == [[True, False, False, False, True, True]]


def test_float64_products_vs_float32():
    """Products of many per-sample exponentials: float32 loses accuracy that matters against
    the Huber threshold δ = 5e-3 rad and a trained model's residuals; float64 does not."""
    g = torch.Generator().manual_seed(1)
    n, j = 4096 + 1, 4096
    omega = 2.0 * torch.randn(1, n, 3, generator=g, dtype=torch.float64)  # fast motion, rad/s
    dt = torch.full((1, n), 0.005, dtype=torch.float64)
    ref = so3.cumprod_matrix_sequential(so3.exp(omega[:, 1:] * dt[:, 1:, None]))[:, -1]
    p64 = predicted_increments(omega, dt, j, torch.float64)[:, 0]
    p32 = predicted_increments(omega.float(), dt.float(), j, torch.float32)[:, 0]
    e64 = float(so3.log(ref.transpose(-1, -2) @ p64).norm())
    e32 = float(so3.log(ref.transpose(-1, -2) @ p32.double()).norm())
    print(f"\nproduct of {j} increments: float32 error {e32:.2e} rad, float64 error {e64:.2e} rad")
    assert e64 < SCAN_F64
    assert e32 > 1e3 * e64 and e32 > 1e-7
    # At the loss's own j = 16/32 the float32 round-off (~1e-8 rad) sits deep in Huber's
    # quadratic zone: both precisions give a ~0 loss at the exact rates (printed for the record).
    rot = so3.integrate(torch.eye(3, dtype=torch.float64)[None], omega, dt)
    valid = torch.ones(1, n, dtype=torch.bool)
    l64 = float(increment_loss(omega, dt, rot, valid, dtype=torch.float64))
    l32 = float(increment_loss(omega.float(), dt.float(), rot.float(), valid, dtype=torch.float32))
    print(f"loss (j=16,32) at the exact rates: float64 {l64:.2e}, float32 {l32:.2e}")
    assert l64 < ROTATION_F64
