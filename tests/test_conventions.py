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
