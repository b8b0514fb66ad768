"""The learned closed loop (tcn_ahrs/model/closed_loop.py): an untrained model is a Mahony
filter; the rest detector is causal; the bias state converges at rest; gradients reach gains
and trust networks; the scripted scan equals the Python one."""
import math

import numpy as np
import pytest
import torch

from tcn_ahrs import so3
from tcn_ahrs.filters.mahony import mahony
from tcn_ahrs.model.ahrs import LearnedAHRS
from tcn_ahrs.model.closed_loop import _scan, closed_loop_scan, rest_detector
from tolerances import EXACT_F32, atol

G = 9.81
NO_REST = {"rest_gyro": 0.0}  # the rest detector never fires


def _imu(n=800, axes=6, seed=0, rate=100.0):
    g = torch.Generator().manual_seed(seed)
    gyro = 0.3 * torch.randn(1, n, 3, generator=g, dtype=torch.float64).cumsum(1) / math.sqrt(n)
    acc = torch.tensor([0.3, -0.2, G], dtype=torch.float64) + 0.5 * torch.randn(1, n, 3, generator=g, dtype=torch.float64)
    parts = [gyro, acc]
    if axes == 9:
        parts.append(torch.tensor([2.0, 20.0, -40.0], dtype=torch.float64) + torch.randn(1, n, 3, generator=g, dtype=torch.float64))
    return torch.cat(parts, -1), torch.full((1, n), 1.0 / rate, dtype=torch.float64)


def test_untrained_six_axis_closed_loop_is_mahony():
    model = LearnedAHRS(axes=6, mag_net="none", use_mag_term=False, loop="closed",
                        closed_loop=dict(acc_gain=0.4, bias_gain=0.01, **NO_REST)).double().eval()
    imu, dt = _imu()
    r0 = so3.exp(torch.tensor([[0.2, -0.1, 0.5]], dtype=torch.float64))
    with torch.no_grad():
        out = model.run_sequence(imu, dt, r0, 0)
    # ours: b -= k_bias (k_acc e) dt  ==  Mahony's b -= k_I e dt with k_I = k_bias k_acc
    ref = mahony(imu[0, :, 0:3], imu[0, :, 3:6], dt[0], so3.matrix_to_quat(r0[0]), k_p=0.4, k_i=0.4 * 0.01)
    err = so3.log(so3.quat_to_matrix(ref["quat"]).transpose(-1, -2) @ out["rot"][0])
    assert err.norm(dim=-1).max() < 1e-7
    torch.testing.assert_close(out["gyro_bias"][0], ref["gyro_bias"], atol=1e-9, rtol=0)


def test_rest_detector_is_causal_and_fires_only_at_rest():
    n, rate = 600, 100.0
    imu, dt = _imu(n=n, rate=rate)
    gyro = torch.full((1, n, 3), 0.01, dtype=torch.float64) + 1e-4 * imu[..., 0:3]
    acc = torch.tensor([0.0, 0.0, G], dtype=torch.float64).expand(1, n, 3).clone()
    gyro[:, 300:] += torch.linspace(0, 3, n - 300, dtype=torch.float64)[None, :, None]  # starts moving at 3 s
    rest = rest_detector(gyro, acc, 100)
    assert rest[0, :99].sum() == 0  # not watched long enough yet
    assert rest[0, 100:300].min() == 1  # a constant bias is rest: deviation from the mean counts
    assert rest[0, 320:].max() == 0
    # causal: changing the future leaves the past alone
    gyro2 = gyro.clone()
    gyro2[:, 200:] += 1.0
    rest2 = rest_detector(gyro2, acc, 100)
    assert torch.equal(rest2[0, :200], rest[0, :200])


def test_bias_state_converges_at_rest_and_keeps_the_attitude():
    n, rate = 3000, 100.0
    bias = torch.tensor([0.01, -0.02, 0.015], dtype=torch.float64)
    g = torch.Generator().manual_seed(1)
    gyro = bias + 0.002 * torch.randn(1, n, 3, generator=g, dtype=torch.float64)
    acc = torch.tensor([0.0, 0.0, G], dtype=torch.float64) + 0.02 * torch.randn(1, n, 3, generator=g, dtype=torch.float64)
    mag = torch.tensor([0.0, 20.0, -40.0], dtype=torch.float64).expand(1, n, 3)
    imu = torch.cat([gyro, acc, mag], -1)
    dt = torch.full((1, n), 1.0 / rate, dtype=torch.float64)
    model = LearnedAHRS(axes=9, loop="closed").double().eval()
    with torch.no_grad():
        out = model.run_sequence(imu, dt, torch.eye(3, dtype=torch.float64)[None], 0)
    torch.testing.assert_close(out["gyro_bias"][0, -1], bias, atol=2e-3, rtol=0)
    angle = so3.log(out["rot"][0, -500:]).norm(dim=-1)
    assert float(angle.max()) < math.radians(1.0) and float(angle[-1]) < float(angle[0])  # still converging
    # the same recording without rest detection keeps a heading error (z bias, 9-axis: only the
    # slow magnetometer loop corrects it) larger than with it
    model_nr = LearnedAHRS(axes=9, loop="closed", closed_loop=NO_REST).double().eval()
    with torch.no_grad():
        out_nr = model_nr.run_sequence(imu, dt, torch.eye(3, dtype=torch.float64)[None], 0)
    assert float(so3.log(out_nr["rot"][0, -500:]).norm(dim=-1).mean()) > float(angle.mean())


def test_gradients_reach_gains_and_trust_networks():
    torch.manual_seed(0)
    model = LearnedAHRS(axes=9, loop="closed", tcn={"channels": [4, 4, 4, 4]})
    for net in (model.calibration.acc_error_net, model.calibration.mag_error_net):
        torch.nn.init.normal_(net.out.weight, std=0.1)  # zero-initialised: give it a slope
    imu, dt = _imu(n=600, axes=9)
    out = model.filter_closed_loop(imu.float(), dt.float(), torch.eye(3)[None], context=100)
    target = so3.exp(torch.tensor([0.0, 0.0, 0.1])).expand(out["rot"].shape)
    loss = (out["rot"] - target).pow(2).sum()
    loss.backward()
    for name in ("log_acc_gain", "log_mag_gain", "log_bias_gain", "log_rest_tc"):
        grad = getattr(model.closed, name).grad
        assert grad is not None and torch.isfinite(grad)
    for net in (model.calibration.acc_error_net, model.calibration.mag_error_net):
        w = net.out.weight.grad
        assert w is not None and torch.isfinite(w).all() and w[3].abs().sum() > 0  # trust channel


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_scripted_scan_equals_python_scan(dtype):
    b, n = 3, 200
    g = torch.Generator().manual_seed(4)
    r = lambda *s: torch.randn(*s, generator=g, dtype=dtype)  # noqa: E731
    unit = lambda x: x / x.norm(dim=-1, keepdim=True)  # noqa: E731
    args = (so3.exp(0.5 * r(b, 3)), 0.01 * r(b, 3), r(b, n, 3), unit(r(b, n, 3)), unit(r(b, n, 3)),
            r(b, n, 1).abs(), r(b, n, 1).abs(), 0.01 * r(b, n, 1).abs(), unit(r(b, 3)),
            torch.full((b, n, 1), 0.01, dtype=dtype), torch.tensor(0.003, dtype=dtype))
    for a, c in zip(closed_loop_scan(*args), _scan(*args)):
        torch.testing.assert_close(a, c, atol=0, rtol=0)
    # the rotation state stays a rotation
    rot = _scan(*args)[0]
    eye = torch.eye(3, dtype=dtype).expand(rot.shape)
    assert (rot.transpose(-1, -2) @ rot - eye).abs().max() < atol(dtype, "rotation")


def test_gyro_error_term_starts_at_the_bias_seen_at_rest():
    from tcn_ahrs.data import SequenceStore
    from tcn_ahrs.datasets.simulate import simulate
    from tcn_ahrs.training.run import rest_gyro_mean

    seq = simulate("static", 30.0, 100.0, seed=3)
    model = LearnedAHRS(axes=9, loop="closed")
    model.closed.set_rate(100.0)
    bias = rest_gyro_mean(model, SequenceStore([seq], 9))
    np.testing.assert_allclose(bias.numpy(), seq.gyro.mean(0), atol=2e-3)
    model.calibration.set_gyro_bias(bias)
    imu = torch.as_tensor(np.concatenate([seq.gyro, seq.accel, seq.mag], 1), dtype=torch.float32)[None]
    with torch.no_grad():
        cal = model.calibration(imu)
    torch.testing.assert_close(cal["gyro"][0], imu[0, :, 0:3] - bias, atol=EXACT_F32, rtol=0)


def test_field_gates_drop_the_corrections_of_implausible_samples():
    """acc_reject / mag_min..mag_max (the ECF's Eq. 7) zero the trust where the raw readings are
    implausible, keep it elsewhere, and are off by default."""
    imu, dt = _imu(n=400, axes=9)
    imu[:, 100:150, 3:6] *= 2.0        # 2 g: a large external acceleration
    imu[:, 250:300, 6:9] *= 0.3        # field norm ≈ 13 µT: a local disturbance
    rot0 = torch.eye(3, dtype=torch.float64)[None]
    bias0 = torch.zeros(1, 3, dtype=torch.float64)
    trusts = {}
    for name, gates in (("off", {}), ("on", dict(acc_reject=1.0, mag_min=20.0, mag_max=70.0))):
        model = LearnedAHRS(axes=9, loop="closed", closed_loop=dict(NO_REST, **gates)).double().eval()
        with torch.no_grad():
            cal = model.calibration(imu)
            out = model.closed.run(cal, imu, dt, rot0, bias0, None, 0, torch.float64)
        trusts[name] = (out["acc_trust"][0], out["mag_trust"][0])
    acc_off, mag_off = trusts["off"]
    acc_on, mag_on = trusts["on"]
    assert torch.all(acc_off > 0) and torch.all(mag_off > 0)
    a_norm = imu[0, :, 3:6].norm(dim=-1)
    m_norm = imu[0, :, 6:9].norm(dim=-1)
    acc_ok = (a_norm - G).abs() < 1.0
    mag_ok = acc_ok & (m_norm > 20.0) & (m_norm < 70.0)
    assert acc_ok[100:150].sum() == 0 and mag_ok[250:300].sum() == 0  # the disturbances are caught
    torch.testing.assert_close(acc_on, acc_off * acc_ok)
    torch.testing.assert_close(mag_on, mag_off * mag_ok)
