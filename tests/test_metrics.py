"""Analytic checks of tcn_ahrs.metrics (AAE, AYE, alignment, BROAD errors, masks)."""
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tcn_ahrs import metrics
from tcn_ahrs.conventions import quat_xyzw_to_wxyz
from tcn_ahrs.sequence import ImuSequence
from tolerances import DEG_F32, DEG_F64, DEG_SMALL_F64, DEG_ZERO_F64, REL_METRIC_F64


def rot_to_wxyz(r: Rotation) -> np.ndarray:
    return quat_xyzw_to_wxyz(r.as_quat())


def random_gt(n=400, seed=0) -> Rotation:
    """A smooth-ish random attitude trajectory (scipy, independent of so3)."""
    rng = np.random.default_rng(seed)
    rotvec = np.cumsum(rng.normal(scale=0.05, size=(n, 3)), axis=0)
    return Rotation.from_rotvec(rotvec)


def z_rot(deg):
    return Rotation.from_euler("z", deg, degrees=True)


def test_constant_yaw_offset_unaligned_and_aligned():
    gt = random_gt()
    est = z_rot(5.0) * gt  # navigation-frame heading offset of 5 deg
    qg, qe = rot_to_wxyz(gt), rot_to_wxyz(est)
    assert metrics.aye(qg, qe, align=False) == pytest.approx(5.0, abs=DEG_F64)
    assert metrics.aae(qg, qe, align=False) == pytest.approx(5.0, abs=DEG_F64)
    assert metrics.aye(qg, qe, align=True) == pytest.approx(0.0, abs=DEG_F64)
    assert metrics.aae(qg, qe, align=True) == pytest.approx(0.0, abs=DEG_F64)


def test_constant_tilt_offset():
    gt = random_gt(seed=1)
    est = Rotation.from_euler("x", 3.0, degrees=True) * gt  # tilt about the east axis
    b = metrics.broad_errors(rot_to_wxyz(gt), rot_to_wxyz(est), mode="9d")
    assert b["inclination_deg"] == pytest.approx(3.0, abs=DEG_F64)
    assert b["heading_deg"] == pytest.approx(0.0, abs=DEG_F64)
    assert b["total_deg"] == pytest.approx(3.0, abs=DEG_F64)
    assert metrics.aae(rot_to_wxyz(gt), rot_to_wxyz(est), align=False) == pytest.approx(3.0, abs=DEG_F64)


def test_heading_offset_broad_9d_and_6d():
    gt = random_gt(seed=2)
    qg, qe = rot_to_wxyz(gt), rot_to_wxyz(z_rot(4.0) * gt)
    b9 = metrics.broad_errors(qg, qe, mode="9d")
    assert b9["heading_deg"] == pytest.approx(4.0, abs=DEG_F64)
    assert b9["inclination_deg"] == pytest.approx(0.0, abs=DEG_ZERO_F64)
    assert b9["total_deg"] == pytest.approx(4.0, abs=DEG_F64)
    b6 = metrics.broad_errors(qg, qe, mode="6d")
    assert b6["heading_deg"] == pytest.approx(0.0, abs=DEG_SMALL_F64)
    assert b6["total_deg"] == pytest.approx(0.0, abs=DEG_ZERO_F64)
    assert abs(b6["heading_offset_deg"]) == pytest.approx(4.0, abs=DEG_F64)


def test_broad_6d_removes_only_the_constant_heading_part():
    gt = random_gt(seed=3)
    # estimate = heading offset 30 deg AND a 2 deg tilt: 6d keeps the tilt, 9d sees both
    est = z_rot(30.0) * Rotation.from_euler("y", 2.0, degrees=True) * gt
    qg, qe = rot_to_wxyz(gt), rot_to_wxyz(est)
    b6 = metrics.broad_errors(qg, qe, mode="6d")
    b9 = metrics.broad_errors(qg, qe, mode="9d")
    assert b6["inclination_deg"] == pytest.approx(2.0, abs=DEG_F64)
    assert b9["inclination_deg"] == pytest.approx(2.0, abs=DEG_F64)
    assert b6["heading_deg"] == pytest.approx(0.0, abs=DEG_SMALL_F64)
    assert b9["heading_deg"] == pytest.approx(30.0, abs=DEG_F64)
    assert b6["total_deg"] == pytest.approx(2.0, abs=DEG_SMALL_F64)


def test_broad_heading_time_varying_matches_scipy_decomposition():
    """Heading error = rotation about z of the earth-frame error, checked with scipy's
    extrinsic z-decomposition on a pure (time-varying) heading error."""
    gt = random_gt(seed=4)
    ang = np.linspace(-170, 170, len(gt))
    est = Rotation.from_euler("z", ang[:, None], degrees=True) * gt
    e = metrics.broad_error_angles(rot_to_wxyz(gt), rot_to_wxyz(est))
    # q_err = q_gt q_est^-1 = Rz(-ang)
    np.testing.assert_allclose(np.degrees(e["heading"]), -ang, atol=DEG_F64)
    np.testing.assert_allclose(e["inclination"], 0.0, atol=DEG_ZERO_F64)


def test_masked_samples_are_ignored():
    gt = random_gt(seed=5)
    qg = rot_to_wxyz(gt)
    qe = rot_to_wxyz(z_rot(5.0) * gt)
    mask = np.ones(len(gt), dtype=bool)
    bad = np.arange(len(gt)) % 3 == 0
    mask[bad] = False
    mask[0] = False  # alignment must use the first *scored* sample
    qe_bad = qe.copy()
    qe_bad[bad] = rot_to_wxyz(Rotation.from_euler("x", 170, degrees=True) * gt[np.nonzero(bad)[0]])
    qg_bad = qg.copy()
    qg_bad[np.nonzero(bad)[0][1::2]] = np.nan  # missing ground truth on some masked samples
    assert metrics.aye(qg_bad, qe_bad, mask, align=False) == pytest.approx(5.0, abs=DEG_F64)
    assert metrics.aae(qg_bad, qe_bad, mask, align=False) == pytest.approx(5.0, abs=DEG_F64)
    assert metrics.aae(qg_bad, qe_bad, mask, align=True) == pytest.approx(0.0, abs=DEG_F64)
    assert metrics.broad_errors(qg_bad, qe_bad, mask)["heading_deg"] == pytest.approx(5.0, abs=DEG_F64)
    # the huge errors are there: scoring them changes the result
    assert metrics.aae(qg, qe_bad, None, align=False) > 50.0


def test_mask_selecting_missing_ground_truth_raises():
    gt = random_gt(n=10)
    qg = rot_to_wxyz(gt)
    qg[3] = np.nan
    with pytest.raises(ValueError, match="sample 3"):
        metrics.aae(qg, rot_to_wxyz(gt), np.ones(10, dtype=bool))


def test_yaw_wrapping():
    qg = rot_to_wxyz(Rotation.from_euler("z", [[359.0], [1.0], [-179.0]], degrees=True))
    qe = rot_to_wxyz(Rotation.from_euler("z", [[1.0], [359.0], [179.0]], degrees=True))
    assert metrics.aye(qg, qe, align=False) == pytest.approx(2.0, abs=DEG_F64)
    assert metrics.broad_errors(qg, qe)["heading_deg"] == pytest.approx(2.0, abs=DEG_F64)


def test_aae_matches_scipy_and_yaw_matches_scipy_euler():
    rng = np.random.default_rng(7)
    gt = Rotation.random(300, random_state=1)
    est = gt * Rotation.from_rotvec(rng.normal(scale=0.8, size=(300, 3)))
    ref = np.sqrt(np.mean((gt.inv() * est).magnitude() ** 2)) * 180 / np.pi
    qg, qe = rot_to_wxyz(gt), rot_to_wxyz(est)
    assert metrics.aae(qg, qe, align=False) == pytest.approx(ref, rel=REL_METRIC_F64)
    # the quaternion sign must not matter
    assert metrics.aae(qg, -qe, align=False) == pytest.approx(ref, rel=REL_METRIC_F64)
    # aligned: scipy reference with R_est' = R_gt[0] R_est[0]^T R_est
    est_al = gt[0] * est[0].inv() * est
    ref_al = np.sqrt(np.mean((gt.inv() * est_al).magnitude() ** 2)) * 180 / np.pi
    assert metrics.aae(qg, qe, align=True) == pytest.approx(ref_al, rel=REL_METRIC_F64)
    # AYE against scipy's intrinsic ZYX yaw
    yg = gt.as_euler("ZYX")[:, 0]
    ye = est.as_euler("ZYX")[:, 0]
    d = (ye - yg + np.pi) % (2 * np.pi) - np.pi
    assert metrics.aye(qg, qe, align=False) == pytest.approx(np.degrees(np.sqrt(np.mean(d**2))), rel=REL_METRIC_F64)
    # broad total angle = same per-sample rotation angle, earth frame
    tot = np.sqrt(np.mean((gt * est.inv()).magnitude() ** 2)) * 180 / np.pi
    assert metrics.broad_errors(qg, qe)["total_deg"] == pytest.approx(tot, rel=REL_METRIC_F64)


def test_accepts_tensors_and_rejects_bad_shapes():
    gt = random_gt(n=50)
    qg = torch.as_tensor(rot_to_wxyz(gt), dtype=torch.float32)
    qe = torch.as_tensor(rot_to_wxyz(z_rot(5.0) * gt), dtype=torch.float32)
    assert metrics.aye(qg, qe, align=False) == pytest.approx(5.0, abs=DEG_F32)
    with pytest.raises(ValueError, match=r"shape \(N, 4\)"):
        metrics.aae(np.zeros((5, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="expected 50 samples"):
        metrics.aae(qg, qe[:10])
    with pytest.raises(ValueError, match="mode"):
        metrics.broad_errors(qg, qe, mode="7d")


def test_no_scored_samples_gives_nan():
    gt = random_gt(n=20)
    q = rot_to_wxyz(gt)
    assert math.isnan(metrics.aae(q, q, np.zeros(20, dtype=bool)))
    assert math.isnan(metrics.broad_errors(q, q, np.zeros(20, dtype=bool))["total_deg"])


def _seq(gt: Rotation, mag=True, score_mask=None):
    n = len(gt)
    t = np.arange(n) / 100.0
    acc = gt.inv().apply(np.array([0, 0, 9.81]))
    m = gt.inv().apply(np.array([0, 20.0, -40.0])) if mag else None
    return ImuSequence(name="s", source="test", time=t, gyro=np.zeros((n, 3)), accel=acc, mag=m,
                       quat=rot_to_wxyz(gt), score_mask=score_mask, rate=100.0, check_units=False)


def test_sequence_metrics_keys_and_values():
    gt = random_gt(n=200, seed=9)
    est = rot_to_wxyz(z_rot(5.0) * gt)
    score = np.ones(200, dtype=bool)
    score[:50] = False
    seq9 = _seq(gt, mag=True, score_mask=score)
    r9 = metrics.sequence_metrics(seq9, est, axes=9)
    assert r9["n_scored"] == 150
    assert r9["aae_deg"] == pytest.approx(0.0, abs=DEG_F64)  # aligned
    assert r9["heading_deg"] == pytest.approx(5.0, abs=DEG_F64)  # BROAD: never aligned
    assert r9["broad_mode"] == "9d"
    r6 = metrics.sequence_metrics(seq9, est, axes=6)
    assert r6["broad_mode"] == "6d" and r6["heading_deg"] == pytest.approx(0.0, abs=DEG_SMALL_F64)
    r_na = metrics.sequence_metrics(seq9, est, axes=6, align=False)
    assert r_na["aye_deg"] == pytest.approx(5.0, abs=DEG_F64)
    seq6 = _seq(gt, mag=False)
    r = metrics.sequence_metrics(seq6, est)
    assert set(r) == {"n_scored", "aae_deg", "aye_deg", "ahe_deg", "inclination_deg"}


def test_heading_error_stays_defined_with_vertical_body_x_axis():
    """EuRoC-like mounting: the body x axis points (nearly) up. A 3 deg error about the
    navigation vertical gives AHE = 3 deg; a 2 deg *tilt* error gives AHE = 0 while the Euler-yaw
    difference (AYE) is degenerate there and reports far more than the whole 2 deg error."""
    n = 400
    rng = np.random.default_rng(3)
    # body x up (pitch -90 deg) with small wobble of the tilt and a slowly turning heading
    heading = np.linspace(0.0, 120.0, n)
    wobble = rng.normal(0.0, 1.0, (n, 2)).cumsum(0) * 0.05
    gt = Rotation.from_euler("ZYX", np.stack([heading, -90.0 + wobble[:, 0], wobble[:, 1]], 1), degrees=True)
    est = z_rot(3.0) * gt  # 3 deg about the navigation vertical
    q_gt, q_est = rot_to_wxyz(gt), rot_to_wxyz(est)
    # the heading of a near-vertical body axis is conditioned like a near-zero angle: DEG_ZERO
    assert metrics.ahe(q_gt, q_est, align=False) == pytest.approx(3.0, abs=DEG_ZERO_F64)
    assert metrics.aae(q_gt, q_est, align=False) == pytest.approx(3.0, abs=DEG_ZERO_F64)
    # aligned at the first sample, a constant offset is removed entirely
    assert metrics.ahe(q_gt, q_est) == pytest.approx(0.0, abs=DEG_ZERO_F64)
    q_tilt = rot_to_wxyz(Rotation.from_euler("x", 2.0, degrees=True) * gt)  # tilt error, nav frame
    assert metrics.ahe(q_gt, q_tilt, align=False) == pytest.approx(0.0, abs=DEG_ZERO_F64)
    assert metrics.aae(q_gt, q_tilt, align=False) == pytest.approx(2.0, abs=DEG_ZERO_F64)
    assert metrics.aye(q_gt, q_tilt, align=False) > 10.0
