"""ImuSequence validation: every bad input raises one DataError naming source and field."""
import numpy as np
import pytest

from tcn_ahrs.conventions import GRAVITY, rad_to_deg
from tcn_ahrs.sequence import DataError, ImuSequence, rest_mask


def make(n=2000, rate=100.0, **over):
    g = np.random.default_rng(0)
    t = np.arange(n) / rate
    fields = dict(
        name="x", source="/data/x.csv", time=t,
        gyro=0.003 * g.normal(size=(n, 3)) + [0.002, -0.001, 0.004],
        accel=np.tile([0.0, 0.0, GRAVITY], (n, 1)) + 0.02 * g.normal(size=(n, 3)),
        mag=np.tile([0.0, 20.0, -44.0], (n, 1)) + 0.3 * g.normal(size=(n, 3)),
        quat=np.tile([1.0, 0, 0, 0], (n, 1)), rate=rate,
    )
    fields.update(over)
    return ImuSequence(**fields)


def test_valid_sequence_and_helpers():
    s = make()
    assert len(s) == 2000 and s.num_axes == 9 and s.has_gt
    assert s.quat_valid.all() and s.scored().all()
    assert s.imu().shape == (2000, 9)
    assert s.without_mag().num_axes == 6
    part = s.slice(100, 300)
    assert len(part) == 200 and part.time[0] == s.time[100]
    assert rest_mask(s).mean() > 0.9


def test_missing_ground_truth_stays_masked():
    q = np.tile([1.0, 0, 0, 0], (2000, 1))
    q[10:20] = np.nan
    s = make(quat=q)
    assert not s.quat_valid[10:20].any() and s.quat_valid[:10].all()
    assert np.isnan(s.quat[15]).all()  # nothing invented
    mask = np.ones(2000, bool)
    mask[:5] = False
    s = make(quat=q, score_mask=mask)
    assert s.scored().sum() == 2000 - 15


@pytest.mark.parametrize(
    "override, field, words",
    [
        (lambda s: {"gyro": np.where(np.arange(2000)[:, None] == 7, np.nan, s.gyro)}, "gyro", "finite"),
        (lambda s: {"accel": s.accel[:, :2]}, "accel", "shape"),
        (lambda s: {"time": s.time[::-1].copy()}, "time", "increasing"),
        (lambda s: {"time": np.r_[s.time[:50], s.time[49:1999]]}, "time", "increasing"),
        (lambda s: {"gyro": rad_to_deg(s.gyro)}, "gyro", "deg/s"),
        (lambda s: {"accel": s.accel / GRAVITY}, "accel", "in g"),
        (lambda s: {"mag": s.mag / 100.0}, "mag", "Gauss"),
        (lambda s: {"quat": 2.0 * s.quat}, "quat", "unit"),
        (lambda s: {"quat": s.quat[:, :3]}, "quat", "shape"),
        (lambda s: {"score_mask": np.ones(5, bool)}, "score_mask", "shape"),
    ],
)
def test_bad_inputs_name_source_and_field(override, field, words):
    good = make()
    with pytest.raises(DataError) as e:
        make(**override(good))
    msg = str(e.value)
    assert e.value.field_name == field
    assert "/data/x.csv" in msg and f"'{field}'" in msg and words in msg


def test_deg_per_s_detected_during_motion_by_range():
    n = 1000
    t = np.arange(n) / 100.0
    gyro_deg = np.c_[np.zeros(n), np.zeros(n), 200.0 * np.sin(t)]  # 200 deg/s peaks: fine in deg, too much in rad
    with pytest.raises(DataError, match="deg/s"):
        make(n=n, gyro=gyro_deg)


def test_a_refusal_shows_plain_numbers():
    from tcn_ahrs.datasets.simulate import simulate

    """Messages name values as a person writes them: 3.5, not np.float64(3.5)."""
    from tcn_ahrs.sequence import DataError
    from tcn_ahrs.validate import check_number

    s = simulate("static", 1.0, 100.0, seed=0, axes=6)
    t = s.time.copy()
    t[10] = t[9]
    with pytest.raises(DataError) as e:
        ImuSequence(name="x", source="x.csv", time=t, gyro=s.gyro, accel=s.accel)
    assert "np.float64" not in str(e.value) and "(0.09 s) does not follow" in str(e.value)
    with pytest.raises(ValueError) as e:
        check_number(np.float64(3.5), "rate", float, 0.0, True, 2.0)
    assert str(e.value).endswith("got 3.5")


def test_a_step_below_the_runtimes_floor_is_refused_at_the_loader():
    """Two samples 1e-14 s apart (the fault trial's clock): refused naming both samples and the floor
    every runtime shares (conventions.MIN_DT), not passed on to a filter."""
    from tcn_ahrs.conventions import MIN_DT
    from tcn_ahrs.datasets.simulate import simulate

    s = simulate("static", 1.0, 100.0, seed=0, axes=6)
    for step in (1e-14, 0.5 * MIN_DT):
        t = s.time.copy()
        t[10] = t[9] + step
        with pytest.raises(DataError, match=r"samples 9 and 10 are .* apart .* below 1e-05 s") as e:
            ImuSequence(name="x", source="x.csv", time=t, gyro=s.gyro, accel=s.accel)
        assert e.value.field_name == "time"
