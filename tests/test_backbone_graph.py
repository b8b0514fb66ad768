"""The backbone's step on vectors (tcn_ahrs/export/backbone_graph.py, what the ONNX and torch.export
step graphs run) against the kernel it restates (tcn_ahrs/kernels/backbone.py, the float reading):
the whole state after every sample, over a simulated recording with every path the kernel has —
rest, a gap, a frozen gyro and accelerometer, a clipped axis, magnetic disturbances and their
acceptance, skipped [0 0 0] readings, learned trusts in [0, 1.5] — and with each switch off."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from tcn_ahrs.datasets.simulate import simulate
from tcn_ahrs.export.backbone_graph import BackboneGraph
from tcn_ahrs.export.stateless import onnx_ops
from tcn_ahrs.kernels import backbone as K
from tcn_ahrs.kernels.backbone_layout import BackboneParams
from tcn_ahrs.kernels.ops import torch_ops

from tolerances import TOL

# one algorithm written twice (the parity row), worst |graph − kernel| / (1 + |kernel|)
BOUND = TOL[torch.float64]["parity"][0]

N = 1200


def _stream(axes: int, seed: int = 0, n: int = N):
    seq = simulate("drone", n / 100.0, 100.0, seed, axes=axes)
    imu = np.concatenate([seq.gyro, seq.accel] + ([seq.mag] if axes == 9 else []), 1)[:n].copy()
    rng = np.random.default_rng(seed)
    dt = 0.01 * (1.0 + 0.3 * rng.uniform(-1.0, 1.0, n))   # a jittered clock: coefficients change every sample
    dt[n // 2] = 0.5                                    # a gap
    imu[n // 4:n // 4 + 50, 0:3] = imu[n // 4, 0:3]     # a frozen gyro (0.5 s)
    imu[n // 3:n // 3 + 30, 3:6] = imu[n // 3, 3:6]     # a frozen accelerometer
    imu[n // 5:n // 5 + 10, 3] = 25.0                   # one accelerometer axis clipped
    imu[n // 5:n // 5 + 10, 4] += rng.normal(0.0, 0.1, 10)
    imu[n - 60:n - 55, 3:6] = 0.0                       # skipped accelerometer samples
    if axes == 9:
        imu[n - 40:n - 35, 6:9] = 0.0                   # skipped magnetometer samples
    return imu, dt, rng.uniform(0.0, 1.5, (n, 3))


def _compare(params: BackboneParams, axes: int, ops, seed: int = 0, gyro_bias_dps: float = 0.0):
    """-> (the worst |graph − kernel| / (1 + |kernel|) over the state and the samples, the kernel's
    flags seen set / seen clear); ``gyro_bias_dps`` added to the gyro's z axis."""
    imu, dt, trust = _stream(axes, seed)
    imu[:, 2] += np.radians(gyro_bias_dps)
    p = np.array(params.vector())
    s, c = np.array(K.initial_state(params)), np.zeros(K.N_COEFF)
    graph = BackboneGraph(params.vector(), axes == 9, ops)
    st = torch.tensor(s)
    worst, seen = 0.0, {}
    flags = {"rest": K.S_REST, "gap": K.S_GAP, "gyro_frozen": K.S_GFROZEN, "acc_frozen": K.S_AFROZEN,
             "acc_clipped": K.S_ACLIPPED, "mag_disturbed": K.S_MAGDIST}
    with torch.no_grad():
        for k in range(len(dt)):
            x = imu[k]
            K.coefficients(p, dt[k], c)
            K.gyro_update(s, p, c, x[0], x[1], x[2])
            skip_acc = bool((x[3:6] == 0.0).all())
            if not skip_acc:
                K.acc_update(s, p, c, x[3], x[4], x[5], trust[k, 0], trust[k, 2])
            skip_mag = axes == 6 or bool((x[6:9] == 0.0).all())
            if not skip_mag:
                K.mag_update(s, p, c, x[6], x[7], x[8], trust[k, 1])
            xt = torch.tensor(x)
            st = graph(st, xt[0:3], xt[3:6], xt[6:9] if axes == 9 else xt[3:6], torch.tensor(dt[k]),
                       *(torch.tensor(trust[k, j]) for j in range(3)), torch.tensor(skip_acc), torch.tensor(skip_mag))
            worst = max(worst, float((np.abs(st.numpy() - s) / (1.0 + np.abs(s))).max()))
            for name, i in flags.items():
                seen.setdefault(name, set()).add(bool(s[i] > 0.5))
            seen.setdefault("check_took", set()).add(bool(s[K.S_CHK + 2] != 0.0))
    return worst, seen


@pytest.mark.parametrize("axes", [9, 6])
def test_the_vector_step_is_the_kernel_on_every_path(axes):
    # a new field accepted after 1 s turning at 5 °/s (not 5 s at 20 °/s): the rejection's whole
    # cycle (disturbed, accepted, disturbed again) within the 12 s
    params = dataclasses.replace(BackboneParams(), mag_new_first_time=1.0, mag_new_time=2.0, mag_new_min_gyro=5.0)
    worst, seen = _compare(params, axes, torch_ops())
    assert worst <= BOUND, worst
    paths = ["rest", "gap", "gyro_frozen", "acc_frozen", "acc_clipped"] + (["mag_disturbed"] if axes == 9 else [])
    assert all(seen[name] == {True, False} for name in paths), seen   # every path was taken (and left)


@pytest.mark.parametrize("switches", [dict(rest_bias=0.0), dict(mag_rejection=0.0), dict(motion_bias=0.0),
                                      dict(motion_bias=0.0, rest_bias=0.0, mag_rejection=0.0),
                                      dict(gap_factor=0.0, frozen_time=0.0, gyro_clip_floor=0.0, acc_clip_floor=0.0),
                                      dict(mag_current_tau=0.0)], ids=str)
def test_the_vector_step_is_the_kernel_with_switches_off(switches):
    worst, _ = _compare(dataclasses.replace(BackboneParams(), **switches), 9, torch_ops(), seed=1)
    assert worst <= BOUND, worst


def test_the_onnx_reading_keeps_float64():
    """ONNX Runtime's float64 atan2 (a float32 one refined once: stateless.onnx_ops) changes nothing."""
    worst, _ = _compare(BackboneParams(), 9, onnx_ops(), seed=2)
    assert worst <= BOUND, worst


@pytest.mark.parametrize("axes", [9, 6])
def test_the_vector_step_is_the_kernel_with_the_causal_check(axes):
    """The default's causal device check (rest_check; export/check_graph.py) on the same paths, with a
    4 °/s gyro bias about z it takes from the recording's rest (beyond VQF's clip)."""
    worst, seen = _compare(BackboneParams(rest_check=1.0), axes, torch_ops(), seed=3, gyro_bias_dps=4.0)
    assert worst <= BOUND, worst
    assert seen["check_took"] == {True, False}, seen
