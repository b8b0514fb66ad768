"""The learned AHRS model: calibration identity at init, causal TCN, parameter count, ECF signs,
variants from the config files."""

import pytest
import torch

from tcn_ahrs import so3
from tcn_ahrs.config.model import PAPER_MODEL  # the paper's open-loop model
from tcn_ahrs.model.ahrs import LearnedAHRS
from tcn_ahrs.model.open_loop import acc_error, mag_error, previous_attitude
from tcn_ahrs.model.tcn import TCN
from tcn_ahrs.conf import CONF_DIR

CONF = CONF_DIR
G = 9.81
MAG_NAV = torch.tensor([0.0, 20.0, -40.0], dtype=torch.float64)  # north + down (ENU), uT


def _imu(b=2, n=600, axes=9, seed=0):
    g = torch.Generator().manual_seed(seed)
    gyro = 0.5 * torch.randn(b, n, 3, generator=g)
    acc = torch.tensor([0.0, 0.0, G]) + torch.randn(b, n, 3, generator=g)
    parts = [gyro, acc]
    if axes == 9:
        parts.append(torch.tensor([0.0, 20.0, -40.0]) + torch.randn(b, n, 3, generator=g))
    return torch.cat(parts, -1)


def test_untrained_model_outputs_raw_readings():
    model = LearnedAHRS(**PAPER_MODEL, axes=9)
    model.calibration.set_input_stats(torch.randn(9), torch.rand(9) + 0.5)
    imu = _imu()
    for mode in (model.train, model.eval):
        mode()
        out = model(imu, torch.full(imu.shape[:2], 0.01), torch.eye(3).expand(2, 3, 3))
        assert torch.equal(out["gyro"], imu[..., 0:3])  # R̂ = I and TCN output 0: exactly raw
        assert torch.equal(out["acc"], imu[..., 3:6])
        assert torch.equal(out["mag"], imu[..., 6:9])
        assert torch.equal(out["gyro_error"], torch.zeros_like(out["gyro_error"]))


def test_receptive_field_is_asserted():
    assert TCN(9).receptive_field >= 448
    with pytest.raises(AssertionError, match="receptive field"):
        TCN(9, dilations=(1, 2, 4, 8))


def test_tcn_is_causal_and_sees_its_receptive_field():
    torch.manual_seed(0)
    net = TCN(3)
    torch.nn.init.normal_(net.out.weight)  # a non-trivial output layer
    net.eval()
    x = torch.randn(1, 1200, 3)
    y = net(x)
    k = 800
    x2 = x.clone()
    x2[:, k + 1:] = torch.randn(1, 1200 - k - 1, 3)  # change the future only
    y2 = net(x2)
    assert torch.equal(y[:, :k + 1], y2[:, :k + 1])
    assert not torch.allclose(y[:, k + 1:], y2[:, k + 1:])
    rf = net.receptive_field
    x3 = x.clone()
    x3[:, k - rf + 1] += 1.0  # oldest sample inside the receptive field of output k
    assert not torch.allclose(net(x3)[:, k], y[:, k])
    x4 = x.clone()
    x4[:, k - rf] += 1.0  # just outside
    assert torch.equal(net(x4)[:, k], y[:, k])


def test_parameter_count_close_to_paper():
    n9 = LearnedAHRS(**PAPER_MODEL, axes=9).num_parameters()
    n6 = LearnedAHRS(**PAPER_MODEL, axes=6, mag_net="none", use_mag_term=False).num_parameters()
    print(f"\ntrainable parameters: 9-axis {n9:,} (paper: 244,877), 6-axis {n6:,}")
    assert abs(n9 - 244_877) / 244_877 < 0.10


def _ecf_only_model(use_acc, use_mag, gain=1.0, preintegration="raw"):
    # raw pre-integration: with a zero gyro, C̃ stays at the initial attitude, which makes
    # the expected open-loop correction analytic
    m = LearnedAHRS(**PAPER_MODEL, axes=9, gyro_net="none", acc_net="none", mag_net="none", use_acc_term=use_acc,
                    use_mag_term=use_mag, init_gain=gain, preintegration=preintegration).double()
    return m


@pytest.mark.parametrize("axis,use_acc,use_mag", [(0, True, False), (1, True, False), (2, False, True)])
def test_ecf_correction_pulls_toward_measurement(axis, use_acc, use_mag):
    """Body at rest with true attitude I; the initial attitude is off by 0.1 rad about one axis.
    The open-loop correction (positive gains) must rotate the estimate back toward the truth.
    (Open loop: C̃ is not updated by the correction, so over 0.5 s with gain 1/s the error of
    0.1 rad is halved, not driven to zero.)"""
    n, dt = 51, 0.01
    acc = torch.tensor([0.0, 0.0, G], dtype=torch.float64).expand(1, n, 3)
    mag = MAG_NAV.expand(1, n, 3)
    imu = torch.cat([torch.zeros(1, n, 3, dtype=torch.float64), acc, mag], -1)
    phi = torch.zeros(3, dtype=torch.float64)
    phi[axis] = 0.1
    r0 = so3.exp(phi)[None]
    model = _ecf_only_model(use_acc, use_mag)
    d = torch.full((1, n), dt, dtype=torch.float64)
    out = model(imu, d, r0)
    # the correction rate is opposite to the error, on the erroneous axis
    assert out["omega"][0, 0, axis] < -0.05
    rot = model.attitude(out["omega"], d, r0)
    err = so3.log(rot[0]).norm(dim=-1)
    assert torch.all(err[1:] < err[:-1])  # decreases monotonically
    assert abs(float(err[-1]) - 0.05) < 0.005
    # and the untouched attitude would have stayed wrong (no correction without gain)
    assert torch.allclose(model.attitude(torch.zeros_like(out["omega"]), d, r0)[0, -1], r0[0])


def test_error_terms_vanish_at_true_attitude():
    r = so3.exp(torch.tensor([[0.3, -0.2, 1.0]], dtype=torch.float64))
    acc = r[0].T @ torch.tensor([0.0, 0.0, G], dtype=torch.float64)
    mag = r[0].T @ MAG_NAV
    assert acc_error(acc[None], r).abs().max() < 1e-12
    assert mag_error(mag[None], acc[None], r).abs().max() < 1e-12


def test_previous_attitude_is_shifted_integration():
    omega = torch.randn(2, 50, 3, dtype=torch.float64)
    dt = torch.full((2, 50), 0.01, dtype=torch.float64)
    r0 = so3.exp(torch.randn(2, 3, dtype=torch.float64))
    prev = previous_attitude(r0, omega, dt)
    full = so3.integrate(r0, omega, dt)
    assert torch.allclose(prev[:, 0], r0)
    assert torch.allclose(prev[:, 1:], full[:, :-1])


def test_run_sequence_matches_forward_from_start():
    model = LearnedAHRS(**PAPER_MODEL, axes=9, preintegration="two_pass").eval()
    torch.nn.init.normal_(model.calibration.gyro_error_net.out.weight, std=0.1)
    imu = _imu(1, 700)
    dt = torch.full((1, 700), 0.01)
    r0 = so3.exp(torch.tensor([[0.1, 0.2, 0.3]]))
    full = model.run_sequence(imu, dt, r0, start=0)
    fw = model(imu, dt, r0)
    assert torch.allclose(full["omega"], fw["omega"], atol=1e-6)
    assert torch.allclose(full["rot"][:, 0], r0.double())
    part = model.run_sequence(imu, dt, r0, start=100)
    assert torch.allclose(part["rot"][:, :101], r0.double().expand(100 + 1, 3, 3)[None])
    assert torch.allclose(part["gyro"], full["gyro"])  # the network sees the whole recording


@pytest.mark.parametrize("name", sorted(p.stem for p in (CONF / "model").glob("*.yaml")))
def test_variants_build_from_config(name):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=[f"model={name}", "data=generic"])
    from omegaconf import OmegaConf

    mc = OmegaConf.to_container(cfg.model, resolve=True)
    model = LearnedAHRS.from_config(mc)
    imu = _imu(1, 500, axes=model.axes)
    out = model(imu, torch.full((1, 500), 0.01), torch.eye(3)[None])
    assert out["omega"].shape == (1, 500, 3) and torch.isfinite(out["omega"]).all()
    if name == "calib_imu":  # network input zeroed: the error terms ignore the data
        assert model.receptive_field == 1
    if name == "dig_like":
        assert model.ecf is None
    if name == "gyro_only_input":
        assert model.calibration.gyro_error_net.hidden[0].conv.in_channels == 3


def test_unknown_model_key_raises():
    with pytest.raises(ValueError, match="unknown key"):
        LearnedAHRS.from_config({"axes": 9, "dropuot": 0.1})
    with pytest.raises(ValueError, match="unknown key"):
        LearnedAHRS.from_config({"axes": 9, "tcn": {"kernal_size": 3}})


def test_reanchor_segments_join_and_reset_the_preintegration():
    """reanchor=None is the single open-loop pass; without an ECF re-anchoring changes nothing
    (segments join exactly); with the ECF each segment's pre-integration restarts from the
    estimate, so the output differs but stays continuous at the anchors."""
    torch.manual_seed(0)
    n = 700
    imu = torch.cat([0.3 * torch.randn(1, n, 3), torch.tensor([0.5, 0.0, G]).expand(1, n, 3)
                     + 0.2 * torch.randn(1, n, 3), MAG_NAV.float().expand(1, n, 3)], -1)
    dt = torch.full((1, n), 0.01)
    r0 = so3.exp(torch.tensor([[0.1, -0.2, 0.3]]))
    plain = LearnedAHRS(**PAPER_MODEL, axes=9, ecf=False).eval()
    with torch.no_grad():
        a = plain.run_sequence(imu, dt, r0, 5)["rot"]
        b = plain.run_sequence(imu, dt, r0, 5, reanchor=100)["rot"]
    torch.testing.assert_close(a, b, atol=1e-10, rtol=0)
    model = LearnedAHRS(**PAPER_MODEL, axes=9, init_gain=1.0).eval()
    with torch.no_grad():
        single = model.run_sequence(imu, dt, r0, 5)
        again = model.run_sequence(imu, dt, r0, 5, reanchor=None)
        anchored = model.run_sequence(imu, dt, r0, 5, reanchor=100)
    torch.testing.assert_close(single["rot"], again["rot"])
    assert anchored["rot"].shape == single["rot"].shape == (1, n, 3, 3)
    # identical up to the first anchor, different after it
    torch.testing.assert_close(anchored["rot"][:, :106], single["rot"][:, :106], atol=1e-9, rtol=0)
    assert (anchored["rot"][:, -1] - single["rot"][:, -1]).abs().max() > 1e-4
    # continuity: each step is one small rotation, also across anchors
    step = so3.log(anchored["rot"][0, :-1].transpose(-1, -2) @ anchored["rot"][0, 1:]).norm(dim=-1)
    assert step.max() < 0.05
