"""The one Kalman update (tcn_ahrs.filters.kalman) against filterpy, and the robust gate."""
import numpy as np
import pytest
import torch

from tcn_ahrs.filters.kalman import chi2_threshold, kalman_update, mahalanobis
from tcn_ahrs.filters.robust import robust_inflation, rolling_max
from tolerances import F64, REL_F64, tol


def _spd(rng, n):
    a = rng.normal(size=(n, n))
    return a @ a.T + n * np.eye(n)


@pytest.mark.parametrize("n,m", [(6, 3), (6, 1), (15, 4)])
def test_kalman_update_equals_filterpy_joseph_form(n, m):
    KalmanFilter = pytest.importorskip("filterpy.kalman").KalmanFilter
    rng = np.random.default_rng(n * 10 + m)
    B = 4
    P = np.stack([_spd(rng, n) for _ in range(B)])
    H = rng.normal(size=(B, m, n))
    R = np.stack([_spd(rng, m) for _ in range(B)])
    r = rng.normal(size=(B, m))
    dx, P_new = kalman_update(*(torch.as_tensor(x) for x in (P, r, H, R)))
    for i in range(B):
        kf = KalmanFilter(dim_x=n, dim_z=m)
        kf.x = np.zeros(n)
        kf.P = P[i].copy()
        kf.update(r[i], R=R[i], H=H[i])  # filterpy's update is the Joseph form
        np.testing.assert_allclose(dx[i].numpy(), kf.x.ravel(), **tol(F64, "parity"))
        np.testing.assert_allclose(P_new[i].numpy(), kf.P, **tol(F64, "parity"))
        S = H[i] @ P[i] @ H[i].T + R[i]
        assert float(mahalanobis(torch.as_tensor(r[i:i + 1]), torch.as_tensor(S[None]))[0]) == pytest.approx(
            r[i] @ np.linalg.solve(S, r[i]), rel=REL_F64)


def test_chi2_threshold_is_scipys_quantile():
    assert chi2_threshold(0.001, 1) == pytest.approx(10.828, abs=1e-3)  # scipy's quantile to the paper's printed digits
    assert chi2_threshold(0.001, 3) == pytest.approx(16.266, abs=1e-3)


def test_robust_inflation_blames_the_observation_or_the_state():
    """A large residual of an implausible observation inflates R (outlier), of a plausible one
    P (abnormal state, capped); a small residual inflates nothing; after inflation gamma ~ thr."""
    thr = chi2_threshold(0.001, 1)
    r = torch.tensor([[10.0], [10.0], [0.5]], dtype=torch.float64)
    hph = torch.ones(3, 1, 1, dtype=torch.float64)
    R = torch.ones(3, 1, 1, dtype=torch.float64)
    plausible = torch.tensor([False, True, True])
    gamma, lam_p, lam_r = robust_inflation(r, hph, R, plausible, thr, n_iter=3, max_fading=1e6)
    np.testing.assert_allclose(gamma.numpy(), [50.0, 50.0, 0.125])
    assert lam_r[0] > 1 and lam_p[0] == 1
    assert lam_p[1] > 1 and lam_r[1] == 1
    assert lam_p[2] == 1 and lam_r[2] == 1
    after = (r[:2, 0] ** 2 / (lam_p[:2] * 1.0 + lam_r[:2] * 1.0)).numpy()
    assert np.all(after < thr * 1.01)
    _, capped, _ = robust_inflation(r, hph, R, plausible, thr, n_iter=3, max_fading=2.0)
    assert capped[1] == 2.0


def test_rolling_max_is_causal():
    x = torch.tensor([[0.0, 3.0, 1.0, 0.0, 0.0, 2.0]])
    np.testing.assert_array_equal(rolling_max(x, 2).numpy(), [[0.0, 3.0, 3.0, 1.0, 0.0, 2.0]])
