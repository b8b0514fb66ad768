"""The compiled (numba) loops of the classical filters equal the torch reference to 1e-12
(tcn_ahrs.filters.compiled; issue 15)."""
import pytest
import torch

from tcn_ahrs.datasets.simulate import simulate
from tcn_ahrs.filters import ecf, eskf, madgwick, mahony
from tcn_ahrs.filters.common import triad_quat
from tolerances import PARITY_F64, REL_F64

pytest.importorskip("numba")


def _inputs(axes=9, n=1500):
    seq = simulate("walking", duration=(n - 1) / 100.0, rate=100.0, seed=4, axes=axes)
    T = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    gyro, acc = T(seq.gyro), T(seq.accel)
    mag = T(seq.mag) if axes == 9 else None
    dt = torch.diff(T(seq.time), prepend=T(seq.time[:1]))
    q0 = triad_quat(acc[0], mag[0] if mag is not None else None)
    return gyro, acc, mag, dt, q0


CASES = {
    "ecf": (ecf, {"k_norm": torch.tensor([0.1, 0.5, 2.0], dtype=torch.float64)}),
    "mahony": (mahony, {"k_p": torch.tensor([0.3, 1.0, 3.0], dtype=torch.float64), "k_i": 0.1}),
    "mahony_compat": (mahony, {"k_p": 1.0, "k_i": 0.3, "compat": True}),
    "madgwick": (madgwick, {"beta": torch.tensor([0.01, 0.041, 0.2], dtype=torch.float64)}),
    "eskf": (eskf, {"accel_noise": torch.tensor([0.03, 0.05, 0.3], dtype=torch.float64)}),
    "robust_eskf": (eskf, {"robust": True, "mag_noise": torch.tensor([0.01, 0.1], dtype=torch.float64)}),
}


@pytest.mark.parametrize("axes", [6, 9])
@pytest.mark.parametrize("name", sorted(CASES))
def test_compiled_loop_equals_the_torch_filter(name, axes):
    fn, params = CASES[name]
    gyro, acc, mag, dt, q0 = _inputs(axes)
    ref = fn(gyro, acc, dt, q0, mag=mag, backend="torch", **params)
    fast = fn(gyro, acc, dt, q0, mag=mag, backend="numba", **params)
    for key in ref:
        if ref[key].dtype == torch.bool:
            assert torch.equal(ref[key], fast[key]), key
        else:
            # parity's 1e-12 absolute; the Mahalanobis statistic (values up to ~100) also 1e-12 relative
            rtol = REL_F64 if key.startswith("mahalanobis") else 0.0
            torch.testing.assert_close(fast[key], ref[key], atol=PARITY_F64[1], rtol=rtol, msg=key)


def test_a_stiff_eskf_differs_only_at_its_round_off_floor():
    """accel_noise = 0.01 (large gains): over 1500 samples the two loops part by ~1e-12, as much as
    the torch loop itself moves when the gyro input changes by one ulp -- the summation order of
    the 6x6 products, amplified by the filter's conditioning, not a different recursion."""
    gyro, acc, mag, dt, q0 = _inputs(6)
    ref = eskf(gyro, acc, dt, q0, accel_noise=0.01, backend="torch")["quat"]
    fast = eskf(gyro, acc, dt, q0, accel_noise=0.01, backend="numba")["quat"]
    ulp = eskf(gyro * (1 + 2.0 ** -52), acc, dt, q0, accel_noise=0.01, backend="torch")["quat"]
    floor = (ulp - ref).abs().max().item()
    assert (fast - ref).abs().max().item() <= max(1e-12, 10 * floor)


def test_auto_backend_keeps_torch_where_gradients_flow():
    gyro, acc, mag, dt, q0 = _inputs(6, 200)
    k = torch.tensor(0.5, dtype=torch.float64, requires_grad=True)
    out = ecf(gyro, acc, dt, q0, k_norm=k)          # auto: a parameter needs a gradient -> torch loop
    out["quat"].sum().backward()
    assert k.grad is not None and torch.isfinite(k.grad)
