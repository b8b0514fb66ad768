"""Clocks (issue: noisy timestamps on a regular stream went unnoticed, AAE 14.2° against 4.3°
clean): the loader tells a regular stream with jittered stamps from truly irregular sampling,
warns about both, and on ``clock: nominal`` runs the former on its uniform grid."""
from __future__ import annotations

import numpy as np
import pytest

from tcn_ahrs.datasets.simulate import simulate
from tcn_ahrs.sequence import DataError, clock_kind

RATE = 100.0


def _stamps(kind: str, n: int = 3000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    if kind == "regular":
        return 5.0 + k / RATE
    if kind == "jittered":  # every stamp off by up to ±30 % of a step
        return 5.0 + (k + rng.uniform(-0.3, 0.3, n)) / RATE
    return 5.0 + np.cumsum(rng.uniform(0.7, 1.3, n)) / RATE  # irregular steps


@pytest.mark.parametrize("kind", ["regular", "jittered", "irregular"])
def test_clock_kind_tells_noisy_stamps_from_irregular_sampling(kind):
    c = clock_kind(_stamps(kind))
    assert c["kind"] == kind
    assert c["step"] == pytest.approx(1.0 / RATE, rel=0.01)


def _write(path, seq, t, **attrs):
    import h5py

    with h5py.File(path, "w") as f:
        for key, val in (("t", t), ("gyr", seq.gyro), ("acc", seq.accel), ("mag", seq.mag), ("quat", seq.quat)):
            f[key] = val
        f.attrs.update(attrs)


def test_jittered_stamps_warn_and_run_on_the_nominal_grid_when_declared(tmp_path):
    from tcn_ahrs.datasets import generic
    from tcn_ahrs.estimators.base import initial_state
    from tcn_ahrs.estimators.registry import build
    from tcn_ahrs.metrics import aae_and_inclination

    seq = simulate("walking", 30.0, RATE, seed=2, device_seed=1)
    t = _stamps("jittered", len(seq.time), seed=3)
    _write(tmp_path / "noisy.h5", seq, t)
    _write(tmp_path / "nominal.h5", seq, t, clock="nominal")
    with pytest.warns(UserWarning, match=r"jitter by \d+ % of the 100 Hz step.*declare clock: nominal"):
        noisy = generic.load_recording(tmp_path, "noisy")
    with pytest.warns(UserWarning, match="run on the nominal period"):
        nominal = generic.load_recording(tmp_path, "nominal")
    assert noisy.meta["clock"] == "jittered" and nominal.meta["clock"] == "nominal"
    np.testing.assert_allclose(np.diff(nominal.time), 1.0 / RATE, rtol=1e-3)
    err = {}
    for name, s in (("stamps", noisy), ("nominal", nominal)):
        k0, q0 = initial_state(s)
        err[name] = aae_and_inclination(s, build("backbone", 9).run(s, q0, k0).quat, 9)[0]
    _write(tmp_path / "clean.h5", seq, seq.time + 5.0)  # the same samples on their true clock
    clean_seq = generic.load_recording(tmp_path, "clean")
    k0, q0 = initial_state(clean_seq)
    clean = aae_and_inclination(clean_seq, build("backbone", 9).run(clean_seq, q0, k0).quat, 9)[0]
    assert err["nominal"] == pytest.approx(clean, abs=0.05) and err["nominal"] < err["stamps"]


def test_irregular_sampling_warns_and_refuses_a_nominal_clock(tmp_path):
    from tcn_ahrs.datasets import generic

    seq = simulate("walking", 30.0, RATE, seed=2, device_seed=1)
    t = _stamps("irregular", len(seq.time), seed=3)
    _write(tmp_path / "irr.h5", seq, t)
    _write(tmp_path / "irr_nominal.h5", seq, t, clock="nominal")
    with pytest.warns(UserWarning, match="irregular sampling .* the filters run on the actual steps"):
        assert generic.load_recording(tmp_path, "irr").meta["clock"] == "irregular"
    with pytest.raises(DataError, match="field 'clock': declared nominal, but the sampling is irregular") as e:
        generic.load_recording(tmp_path, "irr_nominal")
    assert e.value.field_name == "clock"
