"""SO(3) math against independent references (scipy.spatial.transform, finite differences)."""
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from tcn_ahrs import so3
from tcn_ahrs.conventions import quat_wxyz_to_xyzw, quat_xyzw_to_wxyz


def random_rotvecs(n, seed=0, max_angle=math.pi):
    g = np.random.default_rng(seed)
    axis = g.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = g.uniform(0, max_angle, size=(n, 1))
    return axis * angle


def t64(a):
    return torch.as_tensor(a, dtype=torch.float64)


def canonical_wxyz(q):
    q = np.asarray(q)
    return q * np.where(q[..., :1] < 0, -1.0, 1.0)


def test_hat_vee_cross():
    a, b = t64(np.random.default_rng(1).normal(size=(2, 50, 3)))
    assert torch.allclose(so3.hat(a) @ b.unsqueeze(-1), torch.cross(a, b, dim=-1).unsqueeze(-1))
    assert torch.allclose(so3.vee(so3.hat(a)), a)


def test_exp_matches_scipy():
    phi = random_rotvecs(500)
    ref = Rotation.from_rotvec(phi).as_matrix()
    np.testing.assert_allclose(so3.exp(t64(phi)).numpy(), ref, atol=1e-12)


def test_log_matches_scipy_and_roundtrip():
    phi = random_rotvecs(500, seed=2, max_angle=math.pi - 1e-6)
    r = Rotation.from_rotvec(phi).as_matrix()
    out = so3.log(t64(r)).numpy()
    np.testing.assert_allclose(out, phi, atol=1e-9)
    # exp(log(R)) = R, including angles within 1e-6 of pi where log is ambiguous in sign
    np.testing.assert_allclose(so3.exp(so3.log(t64(r))).numpy(), r, atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 0.5, math.pi / 2, math.pi - 1e-4, math.pi])
def test_log_exp_roundtrip_special_angles(angle):
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    r = Rotation.from_rotvec(axis * angle).as_matrix()
    back = so3.exp(so3.log(t64(r))).numpy()
    np.testing.assert_allclose(back, r, atol=1e-12)
    assert abs(np.linalg.norm(so3.log(t64(r)).numpy()) - angle) < 1e-9


def test_quaternions_match_scipy():
    phi = random_rotvecs(400, seed=3)
    rot = Rotation.from_rotvec(phi)
    q_ref = canonical_wxyz(quat_xyzw_to_wxyz(rot.as_quat()))
    q = so3.matrix_to_quat(t64(rot.as_matrix())).numpy()
    np.testing.assert_allclose(q, q_ref, atol=1e-12)
    np.testing.assert_allclose(so3.quat_to_matrix(t64(q_ref)).numpy(), rot.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(canonical_wxyz(so3.quat_exp(t64(phi)).numpy()), q_ref, atol=1e-12)
    np.testing.assert_allclose(so3.quat_log(t64(q_ref)).numpy(), rot.as_rotvec(), atol=1e-9)
    # product and rotation of vectors
    rot2 = Rotation.from_rotvec(random_rotvecs(400, seed=4))
    q2 = quat_xyzw_to_wxyz(rot2.as_quat())
    prod = so3.quat_mul(t64(q_ref), t64(q2)).numpy()
    np.testing.assert_allclose(canonical_wxyz(prod), canonical_wxyz(quat_xyzw_to_wxyz((rot * rot2).as_quat())), atol=1e-12)
    v = np.random.default_rng(5).normal(size=(400, 3))
    np.testing.assert_allclose(so3.quat_rotate(t64(q_ref), t64(v)).numpy(), rot.apply(v), atol=1e-12)
    np.testing.assert_allclose(so3.quat_conj(t64(q_ref)).numpy()[:, 1:], -q_ref[:, 1:])


def test_quat_order_conversion_roundtrip():
    q = np.random.default_rng(6).normal(size=(10, 4))
    np.testing.assert_array_equal(quat_wxyz_to_xyzw(quat_xyzw_to_wxyz(q)), q)
    assert quat_xyzw_to_wxyz(np.array([1.0, 2, 3, 4])).tolist() == [4, 1, 2, 3]


def test_slerp_matches_scipy():
    g = np.random.default_rng(7)
    rots = Rotation.from_rotvec(random_rotvecs(2, seed=8, max_angle=2.5))
    t = g.uniform(0, 1, size=20)
    ref = Slerp([0, 1], rots)(t)
    q0 = t64(np.repeat(quat_xyzw_to_wxyz(rots[0].as_quat())[None], 20, 0))
    q1 = t64(np.repeat(quat_xyzw_to_wxyz(rots[1].as_quat())[None], 20, 0))
    out = so3.quat_slerp(q0, q1, t64(t)).numpy()
    np.testing.assert_allclose(canonical_wxyz(out), canonical_wxyz(quat_xyzw_to_wxyz(ref.as_quat())), atol=1e-10)


def test_euler_and_yaw_match_scipy():
    rot = Rotation.from_rotvec(random_rotvecs(300, seed=9))
    ypr = rot.as_euler("ZYX")  # intrinsic yaw, pitch, roll
    rpy = so3.matrix_to_euler(t64(rot.as_matrix())).numpy()
    np.testing.assert_allclose(rpy, ypr[:, ::-1], atol=1e-9)
    np.testing.assert_allclose(so3.yaw(t64(rot.as_matrix())).numpy(), ypr[:, 0], atol=1e-9)
    w = so3.wrap_angle(t64([3 * math.pi / 2, -3 * math.pi / 2, 0.1, 2 * math.pi + 0.2])).numpy()
    np.testing.assert_allclose(w, [-math.pi / 2, math.pi / 2, 0.1, 0.2], atol=1e-12)


@pytest.mark.parametrize("n", [1, 2, 7, 64, 1000])
def test_parallel_cumprod_equals_sequential(n):
    r = so3.exp(t64(random_rotvecs(3 * n, seed=n, max_angle=0.3)).reshape(3, n, 3))
    par = so3.cumprod_matrix(r)
    seq = so3.cumprod_matrix_sequential(r)
    assert par.shape == r.shape
    torch.testing.assert_close(par, seq, atol=1e-12, rtol=0)
    q = so3.matrix_to_quat(r)
    qp = so3.quat_to_matrix(so3.cumprod_quat(q))
    torch.testing.assert_close(qp, seq, atol=1e-11, rtol=0)


def test_integrate_matches_scipy_composition():
    g = np.random.default_rng(10)
    omega = g.normal(size=(200, 3))
    dt = np.full(200, 0.01)
    r0 = Rotation.from_rotvec([0.1, 0.2, -0.3])
    out = so3.integrate(t64(r0.as_matrix()), t64(omega), t64(dt)).numpy()
    ref = r0
    np.testing.assert_allclose(out[0], ref.as_matrix(), atol=1e-12)
    for k in range(1, 200):
        ref = ref * Rotation.from_rotvec(omega[k] * dt[k])
        np.testing.assert_allclose(out[k], ref.as_matrix(), atol=1e-10)


@pytest.mark.parametrize("angle", [1e-7, math.pi / 2, math.pi - 1e-4])
def test_gradcheck_exp_log(angle):
    axis = torch.tensor([0.2, -0.6, 0.77], dtype=torch.float64)
    phi = (axis / axis.norm() * angle).requires_grad_(True)
    assert torch.autograd.gradcheck(so3.exp, (phi,))
    assert torch.autograd.gradcheck(lambda p: so3.log(so3.exp(p)), (phi,))
    assert torch.autograd.gradcheck(so3.quat_exp, (phi,))
    assert torch.autograd.gradcheck(lambda p: so3.quat_log(so3.quat_exp(p)), (phi,))
    r = so3.exp(phi.detach()).requires_grad_(True)
    # log on matrices: perturb along the manifold (R exp(d)) to stay a rotation
    d = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda d_: so3.log(r.detach() @ so3.exp(d_)), (d,))


def test_float32_gradients_finite_everywhere():
    angles = torch.tensor([0.0, 1e-8, 1e-4, 1e-2, 1.0, 3.0, math.pi - 1e-3, math.pi])
    axis = torch.tensor([0.0, 0.6, 0.8])
    phi = (angles[:, None] * axis).float().requires_grad_(True)
    (so3.log(so3.exp(phi)).sum() + so3.quat_log(so3.quat_exp(phi)).sum()).backward()
    assert torch.isfinite(phi.grad).all()
    q = torch.tensor([[1.0, 0, 0, 0], [0.0, 1, 0, 0], [0.0, 0, 0, 1]], requires_grad=True)
    so3.quat_log(q).sum().backward()
    assert torch.isfinite(q.grad).all()
    r = so3.exp(phi.detach()).requires_grad_(True)
    so3.log(r).sum().backward()
    assert torch.isfinite(r.grad).all()


def test_float32_accuracy():
    phi = random_rotvecs(200, seed=11, max_angle=math.pi - 1e-3)
    r = Rotation.from_rotvec(phi).as_matrix()
    out = so3.log(torch.as_tensor(r, dtype=torch.float32)).double().numpy()
    assert np.abs(out - phi).max() < 1e-4


def test_torchscript():
    fns = ["hat", "vee", "exp", "log", "quat_mul", "quat_to_matrix", "matrix_to_quat", "quat_exp",
           "quat_log", "quat_slerp", "matrix_to_euler", "yaw", "cumprod_matrix", "cumprod_quat", "integrate"]
    phi = t64(random_rotvecs(5, seed=12))
    for name in fns:
        torch.jit.script(getattr(so3, name))
    scripted = torch.jit.script(so3.log)
    torch.testing.assert_close(scripted(so3.exp(phi)), so3.log(so3.exp(phi)))
