"""Tests of tcn_ahrs.tuning.grid (batched grid search of classical filter parameters)."""
from __future__ import annotations

import numpy as np
import pytest

from tcn_ahrs.estimators.base import initial_quat
from tcn_ahrs.estimators.classical import ESEKF, ClosedLoopECF, Madgwick, Mahony
from tcn_ahrs.sequence import ImuSequence
from tcn_ahrs.tuning.grid import evaluate_params, grid_combinations, tune_gradient, tune_grid

from synthetic_filters import simulate, wavy


@pytest.fixture(scope="module")
def train():
    return [simulate(duration=10.0, rate=25.0, omega=wavy, bias=(0.02, -0.01, 0.01), seed=s) for s in (11, 12)]


def test_grid_combinations_cartesian_order():
    combos = grid_combinations({"a": [1, 2], "b": [10, 20, 30]})
    assert len(combos) == 6 and combos[0] == {"a": 1, "b": 10} and combos[-1] == {"a": 2, "b": 30}
    with pytest.raises(ValueError, match="empty"):
        grid_combinations({"a": []})


def test_tune_grid_madgwick_picks_a_sensible_gain(train):
    from tcn_ahrs.metrics import scored_metric

    grid = {"beta": [0.0005, 0.03, 3.0]}
    best, table = tune_grid(Madgwick, train, grid)
    assert len(table) == 3
    assert [r["score"] for r in table] == sorted(r["score"] for r in table)
    assert best == table[0]["params"]
    # too small a gain drifts with the gyro bias, too large follows accelerometer noise
    assert best["beta"] == 0.03
    # the batched run gives exactly what one estimator run per value gives
    for row in table:
        one = np.mean([scored_metric(s, Madgwick(beta=row["params"]["beta"]).run(s, initial_quat(s)).quat)
                       for s in train])
        assert abs(one - row["score"]) < 1e-9


def test_tune_grid_two_parameters_with_fixed_fields(train):
    grid = {"k_norm": [0.05, 0.5], "a_min": [0.5, 2.0]}
    best, table = tune_grid(ClosedLoopECF, train, grid, axes=6)
    assert len(table) == 4 and set(best) == {"k_norm", "a_min"}
    assert all(set(r["per_sequence"]) == {s.name for s in train} for r in table)
    assert all(np.isfinite(r["score"]) for r in table)


def test_tune_grid_custom_metric_and_instance(train):
    calls = []

    def worst_error(q_gt, q_est, mask):
        calls.append(1)
        d = np.abs(np.sum(q_gt[mask] * q_est[mask], 1)).clip(max=1.0)
        return float(np.degrees(2 * np.arccos(d)).max())

    best, table = tune_grid(Mahony(axes=6), train[:1], {"k_p": [0.5, 2.0], "k_i": [0.0, 0.2]},
                            metric=worst_error)
    assert len(calls) == 4 and len(table) == 4


def test_tune_grid_rejects_bad_input(train):
    with pytest.raises(ValueError, match="cannot tune"):
        tune_grid(Madgwick, train, {"gain": [0.1]})
    no_gt = ImuSequence(name="x", source="test", time=train[0].time, gyro=train[0].gyro, accel=train[0].accel)
    with pytest.raises(ValueError, match="ground truth"):
        evaluate_params(Madgwick(), no_gt, [{"beta": 0.1}])


def test_default_grids_name_real_parameters():
    for cls in (ClosedLoopECF, Mahony, Madgwick, ESEKF):
        names = set(cls().param_names())
        assert set(cls.default_grid) <= names and set(cls.tunable) <= names


def test_tune_gradient_reduces_the_loss(train):
    params, history = tune_gradient(Mahony, train[:1], ["k_p"], steps=4, lr=0.3, window=100, k_p=0.02, axes=6)
    assert history[-1] < history[0]
    assert params["k_p"] > 0.02
