"""The yardstick (tcn_ahrs.metrics.Yardstick): one scoring protocol for every method.

On simulated recordings with exact ground truth: a filter that converges within a second from a
wrong start is not charged for its start; a constant inclination offset is always charged; a
constant heading offset is charged only where the magnetometer makes heading observable against
a magnetic-north ground truth; and VQF started at the ground truth is the backbone (the same
filter), so the two columns of a table no longer differ by their start.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tcn_ahrs import metrics
from tcn_ahrs.conventions import quat_wxyz_to_xyzw, quat_xyzw_to_wxyz
from tcn_ahrs.datasets.simulate import simulate
from tcn_ahrs.estimators.base import initial_state
from tcn_ahrs.evaluate import evaluate
from tolerances import DEG_F64


def _rot(q):
    return Rotation.from_quat(quat_wxyz_to_xyzw(np.asarray(q)))


def _wxyz(r):
    return quat_xyzw_to_wxyz(r.as_quat())


@pytest.fixture(scope="module")
def walk():
    return simulate("walking", 30.0, 100.0, seed=3, axes=9)


def _tilted(seq, deg_of_t):
    """Ground truth with a tilt error about the east axis of ``deg_of_t(t)`` degrees."""
    t = seq.time - seq.time[0]
    tilt = Rotation.from_rotvec(np.outer(np.radians(deg_of_t(t)), [1.0, 0.0, 0.0]))
    return _wxyz(tilt * _rot(seq.quat))


def test_converging_start_is_not_charged_constant_tilt_is(walk):
    # 8 deg wrong at the start, gone after 1 s (a filter initialised from one accelerometer sample)
    converging = _tilted(walk, lambda t: 8.0 * np.clip(1.0 - t, 0.0, None))
    m = metrics.sequence_metrics(walk, converging, axes=6)
    assert m["aae_deg"] == pytest.approx(0.0, abs=DEG_F64)
    assert m["inclination_deg"] == pytest.approx(0.0, abs=DEG_F64)
    # the old metric froze the start's error into the whole recording
    assert metrics.sequence_metrics(walk, converging, axes=6, align="first")["aae_deg"] > 7.0
    # a constant tilt is charged in full, in AAE and inclination, with or without magnetometer
    for axes in (6, 9):
        m = metrics.sequence_metrics(walk, _tilted(walk, lambda t: 3.0 + 0 * t), axes=axes)
        assert m["aae_deg"] == pytest.approx(3.0, abs=1e-6)
        assert m["inclination_deg"] == pytest.approx(3.0, abs=1e-6)


def test_heading_offset_charged_only_against_magnetic_north(walk):
    est = _wxyz(Rotation.from_euler("z", 5.0, degrees=True) * _rot(walk.quat))
    assert walk.meta["heading_reference"] == "magnetic_north"  # no declination in the simulator
    assert metrics.sequence_metrics(walk, est, axes=6)["aae_deg"] == pytest.approx(0.0, abs=DEG_F64)
    assert metrics.sequence_metrics(walk, est, axes=9)["aae_deg"] == pytest.approx(5.0, abs=1e-6)
    declined = simulate("walking", 30.0, 100.0, seed=3, axes=9, declination_deg=10.0)
    assert declined.meta["heading_reference"] == "true_north"
    est = _wxyz(Rotation.from_euler("z", 5.0, degrees=True) * _rot(declined.quat))
    assert metrics.sequence_metrics(declined, est, axes=9)["aae_deg"] == pytest.approx(0.0, abs=DEG_F64)


def test_settling_time_and_heading_alignment_are_the_tables(walk):
    """The runner's tables and the tuners' loss are the same protocol."""
    est = _tilted(walk, lambda t: 8.0 * np.clip(1.0 - t, 0.0, None) + 0.05 * t)

    class Fixed:
        name, axes = "fixed", 6

        def run(self, seq, init_quat=None, init_index=0):
            from tcn_ahrs.estimators.base import EstimatorOutput
            return EstimatorOutput(est)

    row = evaluate([Fixed()], [walk])["methods"]["fixed"]["recordings"][0]
    assert row["aae_deg"] == pytest.approx(metrics.scored_metric(walk, est, 6), rel=1e-12)
    assert row["n_scored"] == int(np.sum(walk.time >= walk.time[0] + metrics.YARDSTICK.settle_s))


def test_a_recording_shorter_than_the_settle_is_scored_whole_and_said():
    """A 1.5 s recording: every sample is scored (nothing else is left), and a warning names the
    recording and the settle (it was silent)."""
    short = simulate("walking", 1.5, 100.0, seed=3, axes=6)
    with pytest.warns(UserWarning, match=r"sim_walking.*within the yardstick's 2 s settle.*scored on all its samples"):
        m = metrics.YARDSTICK.mask(short)
    assert m.sum() == short.scored().sum()


def test_evaluate_refuses_a_recording_too_short_to_score():
    """A 2-sample recording was scored (AAE 5.4° for its first step) beside the others: evaluate
    refuses it alone, and leaves it out of many with a warning naming it."""
    from tcn_ahrs.estimators import registry

    long = simulate("walking", 5.0, 100.0, seed=3, axes=6)
    two = long.slice(0, 2, name="two_samples")
    raw = registry.build("raw", 6)
    with pytest.raises(ValueError, match=r"'two_samples' is too short to score: .*2 samples.*2 s"):
        evaluate([raw], [two])
    with pytest.warns(UserWarning, match=r"'two_samples' is too short to score.*left out"):
        res = evaluate([raw], [long, two])
    assert res["recordings"] == [long.name] and len(res["methods"]["Raw IMU"]["recordings"]) == 1


def test_vqf_started_at_ground_truth_is_the_backbone(walk):
    pytest.importorskip("vqf")
    from tcn_ahrs.estimators.backbone import Backbone
    from tcn_ahrs.estimators.peers import VQFEstimator

    k0, q0 = initial_state(walk)
    for axes in (6, 9):
        view = walk if axes == 9 else walk.without_mag()
        q_vqf = VQFEstimator(axes=axes).run(view, q0, k0).quat
        q_bb = Backbone(axes=axes).run(view, q0, k0).quat
        d = (_rot(q_vqf).inv() * _rot(q_bb)).magnitude()
        assert np.degrees(d).max() < 1e-2, axes  # round-off of two float64 implementations over 3000 steps
        # it starts where it was told to: the heading of the ground truth at k0 (its first
        # accelerometer sample then sets the inclination, in VQF and in the backbone alike)
        if axes == 6:
            h = metrics.broad_error_angles(q0[None], q_vqf[:1])["heading"]
            assert abs(np.degrees(h[0])) < 0.5


def test_aae_and_inclination_alone_equal_the_tables(walk):
    est = _tilted(walk, lambda t: 8.0 * np.clip(1.0 - t, 0.0, None) + 0.05 * t + 1.0)
    for axes in (6, 9):
        m = metrics.sequence_metrics(walk, est, axes)
        a, i = metrics.aae_and_inclination(walk, est, axes)
        assert a == pytest.approx(m["aae_deg"], rel=1e-12) and i == pytest.approx(m["inclination_deg"], rel=1e-12)
