"""Frame and unit converters against hand-derived cases."""
import numpy as np
import pytest

from tcn_ahrs import conventions as c


def test_frame_converters_map_axes():
    north_ned, east_ned, down_ned = np.eye(3)
    enu = c.nav_vectors_to_enu(np.eye(3), "NED")
    np.testing.assert_allclose(enu, [[0, 1, 0], [1, 0, 0], [0, 0, -1]])  # N, E, D in ENU
    nwu = c.nav_vectors_to_enu(np.eye(3), "NWU")
    np.testing.assert_allclose(nwu, [[0, 1, 0], [-1, 0, 0], [0, 0, 1]])  # N, W, U in ENU
    for f in ("NED", "NWU", "ENU"):
        m = c.enu_from_frame(f)
        np.testing.assert_allclose(m @ m.T, np.eye(3))
        assert np.isclose(np.linalg.det(m), 1.0)  # proper rotations (all right-handed)
    with pytest.raises(ValueError, match="unknown navigation frame"):
        c.enu_from_frame("XYZ")


def test_attitude_conversion_keeps_body_vectors():
    # a body x axis pointing north: in NED attitude = identity, in ENU it must map x_b to north
    r_ned = np.eye(3)
    r_enu = c.nav_matrices_to_enu(r_ned, "NED")
    np.testing.assert_allclose(r_enu @ [1, 0, 0], c.NORTH_NAV)


def test_units():
    assert np.isclose(c.deg_to_rad(180.0), np.pi)
    assert np.isclose(c.rad_to_deg(np.pi), 180.0)
    assert np.isclose(c.g_to_mps2(1.0), c.GRAVITY)
    assert np.isclose(c.mps2_to_g(c.GRAVITY), 1.0)
    assert np.isclose(c.gauss_to_ut(0.5), 50.0)
    assert np.isclose(c.nt_to_ut(48000.0), 48.0)
    np.testing.assert_allclose(c.accel_down_to_up([0, 0, -9.81]), [0, 0, 9.81])


def test_the_float_policy_is_followed():
    """conventions' one float policy: recordings and every filter state in float64, the networks
    in float32, the loss's increments in float64 — checked on what the code produces."""
    import torch

    from tcn_ahrs import conventions as cv
    from tcn_ahrs.datasets.simulate import simulate
    from tcn_ahrs.estimators.classical import Mahony
    from tcn_ahrs.estimators.learned import LearnedEstimator, model_input
    from tcn_ahrs.losses import predicted_increments
    from tcn_ahrs.model.ahrs import LearnedAHRS

    assert (cv.STORAGE_DTYPE, cv.STATE_DTYPE, cv.NETWORK_DTYPE, cv.LOSS_DTYPE) == (
        np.float64, torch.float64, torch.float32, torch.float64)
    seq = simulate("slow_rotation", 3.0, 50.0, seed=1)
    assert seq.gyro.dtype == cv.STORAGE_DTYPE and seq.quat.dtype == cv.STORAGE_DTYPE
    quat, _ = Mahony().quat_batch([seq], [None])
    assert quat.dtype == cv.STATE_DTYPE
    model = LearnedAHRS(axes=9, loop="open", tcn={"channels": [4, 4, 4, 4]}).eval()
    assert model_input(model, seq, "cpu").dtype == cv.NETWORK_DTYPE
    assert next(model.calibration.parameters()).dtype == cv.NETWORK_DTYPE
    imu = model_input(model, seq, "cpu")
    dt = torch.full((1, len(seq)), 0.02)
    out = model.run_sequence(imu, dt, torch.eye(3, dtype=torch.float64)[None])
    assert out["rot"].dtype == cv.STATE_DTYPE
    assert predicted_increments(out["omega"].float(), dt, 4).dtype == cv.LOSS_DTYPE
    assert LearnedEstimator(model).run(seq).quat.dtype == np.float64
