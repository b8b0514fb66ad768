"""SO(3) math against independent references (scipy.spatial.transform, finite differences)."""
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from tcn_ahrs import so3
from tcn_ahrs.conventions import quat_wxyz_to_xyzw, quat_xyzw_to_wxyz
from tolerances import ANGLE_F32, ANGLE_F64, INTEGRATE_F64, ROTATION_F64, SCAN_F64, atol, tol


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
    np.testing.assert_allclose(so3.exp(t64(phi)).numpy(), ref, atol=ROTATION_F64)


def test_log_matches_scipy_and_roundtrip():
    phi = random_rotvecs(500, seed=2, max_angle=math.pi - 1e-6)
    r = Rotation.from_rotvec(phi).as_matrix()
    out = so3.log(t64(r)).numpy()
    np.testing.assert_allclose(out, phi, atol=ANGLE_F64)
    # exp(log(R)) = R, including angles within 1e-6 of pi where log is ambiguous in sign
    np.testing.assert_allclose(so3.exp(so3.log(t64(r))).numpy(), r, atol=ROTATION_F64)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 0.5, math.pi / 2, math.pi - 1e-4, math.pi])
def test_log_exp_roundtrip_special_angles(angle, dtype):
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    r = Rotation.from_rotvec(axis * angle).as_matrix()
    rt = torch.as_tensor(np.broadcast_to(r, (2, 3, 3, 3)).copy(), dtype=dtype)  # a (2, 3) batch
    back = so3.exp(so3.log(rt)).double().numpy()
    np.testing.assert_allclose(back, np.broadcast_to(r, back.shape), **tol(dtype, "rotation"))
    via_quat = so3.quat_to_matrix(so3.quat_exp(so3.quat_log(so3.matrix_to_quat(rt)))).double().numpy()
    np.testing.assert_allclose(via_quat, np.broadcast_to(r, back.shape), **tol(dtype, "rotation"))
    assert np.abs(np.linalg.norm(so3.log(rt).double().numpy(), axis=-1) - angle).max() < atol(dtype, "angle")


def test_quaternions_match_scipy():
    phi = random_rotvecs(400, seed=3)
    rot = Rotation.from_rotvec(phi)
    q_ref = canonical_wxyz(quat_xyzw_to_wxyz(rot.as_quat()))
    q = so3.matrix_to_quat(t64(rot.as_matrix())).numpy()
    np.testing.assert_allclose(q, q_ref, atol=ROTATION_F64)
    np.testing.assert_allclose(so3.quat_to_matrix(t64(q_ref)).numpy(), rot.as_matrix(), atol=ROTATION_F64)
    np.testing.assert_allclose(canonical_wxyz(so3.quat_exp(t64(phi)).numpy()), q_ref, atol=ROTATION_F64)
    np.testing.assert_allclose(so3.quat_log(t64(q_ref)).numpy(), rot.as_rotvec(), atol=ANGLE_F64)
    # product and rotation of vectors
    rot2 = Rotation.from_rotvec(random_rotvecs(400, seed=4))
    q2 = quat_xyzw_to_wxyz(rot2.as_quat())
    prod = so3.quat_mul(t64(q_ref), t64(q2)).numpy()
    np.testing.assert_allclose(canonical_wxyz(prod), canonical_wxyz(quat_xyzw_to_wxyz((rot * rot2).as_quat())), atol=ROTATION_F64)
    v = np.random.default_rng(5).normal(size=(400, 3))
    np.testing.assert_allclose(so3.quat_rotate(t64(q_ref), t64(v)).numpy(), rot.apply(v), atol=ROTATION_F64)
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
    np.testing.assert_allclose(canonical_wxyz(out), canonical_wxyz(quat_xyzw_to_wxyz(ref.as_quat())), atol=INTEGRATE_F64)


def test_euler_and_yaw_match_scipy():
    rot = Rotation.from_rotvec(random_rotvecs(300, seed=9))
    ypr = rot.as_euler("ZYX")  # intrinsic yaw, pitch, roll
    rpy = so3.matrix_to_euler(t64(rot.as_matrix())).numpy()
    np.testing.assert_allclose(rpy, ypr[:, ::-1], atol=ANGLE_F64)
    np.testing.assert_allclose(so3.yaw(t64(rot.as_matrix())).numpy(), ypr[:, 0], atol=ANGLE_F64)
    w = so3.wrap_angle(t64([3 * math.pi / 2, -3 * math.pi / 2, 0.1, 2 * math.pi + 0.2])).numpy()
    np.testing.assert_allclose(w, [-math.pi / 2, math.pi / 2, 0.1, 0.2], atol=ROTATION_F64)


@pytest.mark.parametrize("n", [1, 2, 7, 64, 1000])
def test_parallel_cumprod_equals_sequential(n):
    r = so3.exp(t64(random_rotvecs(3 * n, seed=n, max_angle=0.3)).reshape(3, n, 3))
    par = so3.cumprod_matrix(r)
    seq = so3.cumprod_matrix_sequential(r)
    assert par.shape == r.shape
    torch.testing.assert_close(par, seq, atol=ROTATION_F64, rtol=0)
    q = so3.matrix_to_quat(r)
    qp = so3.quat_to_matrix(so3.cumprod_quat(q))
    torch.testing.assert_close(qp, seq, atol=SCAN_F64, rtol=0)


def test_integrate_matches_scipy_composition():
    g = np.random.default_rng(10)
    omega = g.normal(size=(200, 3))
    dt = np.full(200, 0.01)
    r0 = Rotation.from_rotvec([0.1, 0.2, -0.3])
    out = so3.integrate(t64(r0.as_matrix()), t64(omega), t64(dt)).numpy()
    ref = r0
    np.testing.assert_allclose(out[0], ref.as_matrix(), atol=ROTATION_F64)
    for k in range(1, 200):
        ref = ref * Rotation.from_rotvec(omega[k] * dt[k])
        np.testing.assert_allclose(out[k], ref.as_matrix(), atol=INTEGRATE_F64)


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
    assert np.abs(out - phi).max() < ANGLE_F32


def test_torchscript():
    fns = ["hat", "vee", "exp", "log", "quat_mul", "quat_to_matrix", "matrix_to_quat", "quat_exp",
           "quat_log", "quat_slerp", "matrix_to_euler", "yaw", "cumprod_matrix", "cumprod_quat", "integrate"]
    phi = t64(random_rotvecs(5, seed=12))
    for name in fns:
        torch.jit.script(getattr(so3, name))
    scripted = torch.jit.script(so3.log)
    torch.testing.assert_close(scripted(so3.exp(phi)), so3.log(so3.exp(phi)))


# ---------------------------------------------------------------------------------------------
# every function over batch shapes x dtypes ("any number of leading batch dimensions",
# "float32/float64"), against scipy in float64 and analytic identities; tolerances: tolerances.TOL
# ---------------------------------------------------------------------------------------------

DTYPES = [torch.float64, torch.float32]
SHAPES = [(), (5,), (2, 3), (4, 1, 7)]
grid = pytest.mark.parametrize("shape", SHAPES, ids=lambda s: "x".join(map(str, s)) or "scalar")
dtypes = pytest.mark.parametrize("dtype", DTYPES, ids=lambda d: str(d).split(".")[-1])


def _n(shape):
    return int(np.prod(shape)) if shape else 1


def _rotations(shape, seed, max_angle=math.pi - 1e-3) -> Rotation:
    """_n(shape) scipy rotations (float64), angles up to max_angle (float32's log needs pi - 1e-3)."""
    return Rotation.from_rotvec(random_rotvecs(_n(shape), seed=seed, max_angle=max_angle))


def _t(a, shape, dtype, tail):
    """numpy (n, *tail) -> torch (*shape, *tail) of dtype."""
    return torch.as_tensor(np.asarray(a).reshape(tuple(shape) + tuple(tail)), dtype=dtype)


def _np(x, tail):
    """torch (*shape, *tail) -> float64 numpy (n, *tail)."""
    return x.detach().double().numpy().reshape((-1,) + tuple(tail))


def _wxyz(rot: Rotation) -> np.ndarray:
    return canonical_wxyz(quat_xyzw_to_wxyz(rot.as_quat()))


@grid
@dtypes
def test_grid_hat_vee(shape, dtype):
    a, b = np.random.default_rng(20).normal(size=(2, _n(shape), 3))
    ta, tb = _t(a, shape, dtype, (3,)), _t(b, shape, dtype, (3,))
    h = so3.hat(ta)
    assert h.shape == tuple(shape) + (3, 3) and h.dtype == dtype
    np.testing.assert_allclose(_np(h @ tb.unsqueeze(-1), (3,)), np.cross(a, b), **tol(dtype, "exact"))
    np.testing.assert_allclose(_np(h + h.transpose(-1, -2), (3, 3)), 0.0, atol=0)  # skew-symmetric
    v = so3.vee(h)
    assert v.shape == tuple(shape) + (3,) and v.dtype == dtype
    torch.testing.assert_close(v, ta, atol=0, rtol=0)


@grid
@dtypes
def test_grid_exp_log(shape, dtype):
    rot = _rotations(shape, seed=21)
    phi = _t(rot.as_rotvec(), shape, dtype, (3,))
    r = so3.exp(phi)
    assert r.shape == tuple(shape) + (3, 3) and r.dtype == dtype
    np.testing.assert_allclose(_np(r, (3, 3)), rot.as_matrix(), **tol(dtype, "rotation"))
    eye = np.broadcast_to(np.eye(3), (_n(shape), 3, 3))
    np.testing.assert_allclose(_np(r @ r.transpose(-1, -2), (3, 3)), eye, **tol(dtype, "rotation"))  # R R^T = I
    rm = _t(rot.as_matrix(), shape, dtype, (3, 3))
    back = so3.log(rm)
    assert back.shape == tuple(shape) + (3,) and back.dtype == dtype
    np.testing.assert_allclose(_np(back, (3,)), rot.as_rotvec(), **tol(dtype, "angle"))
    np.testing.assert_allclose(_np(so3.exp(back), (3, 3)), rot.as_matrix(), **tol(dtype, "rotation"))  # exp(log R) = R


@grid
@dtypes
def test_grid_quaternion_conversions(shape, dtype):
    rot = _rotations(shape, seed=22)
    q_ref = _wxyz(rot)
    rm = _t(rot.as_matrix(), shape, dtype, (3, 3))
    q = so3.matrix_to_quat(rm)
    assert q.shape == tuple(shape) + (4,) and q.dtype == dtype
    np.testing.assert_allclose(_np(q, (4,)), q_ref, **tol(dtype, "rotation"))
    assert bool((q[..., 0] >= 0).all())
    tq = _t(q_ref, shape, dtype, (4,))
    m = so3.quat_to_matrix(tq)
    assert m.shape == tuple(shape) + (3, 3) and m.dtype == dtype
    np.testing.assert_allclose(_np(m, (3, 3)), rot.as_matrix(), **tol(dtype, "rotation"))
    # quat_to_matrix normalises: a scaled quaternion is the same rotation
    np.testing.assert_allclose(_np(so3.quat_to_matrix(3.0 * tq), (3, 3)), rot.as_matrix(), **tol(dtype, "rotation"))
    phi = _t(rot.as_rotvec(), shape, dtype, (3,))
    qe = so3.quat_exp(phi)
    assert qe.shape == tuple(shape) + (4,) and qe.dtype == dtype
    np.testing.assert_allclose(canonical_wxyz(_np(qe, (4,))), q_ref, **tol(dtype, "rotation"))
    ql = so3.quat_log(tq)
    assert ql.shape == tuple(shape) + (3,) and ql.dtype == dtype
    np.testing.assert_allclose(_np(ql, (3,)), rot.as_rotvec(), **tol(dtype, "angle"))
    # quat_log(-q) = quat_log(q): q and -q are one rotation
    torch.testing.assert_close(so3.quat_log(-tq), ql, atol=0, rtol=0)


@grid
@dtypes
def test_grid_quaternion_algebra(shape, dtype):
    r1, r2 = _rotations(shape, seed=23), _rotations(shape, seed=24)
    q1, q2 = _t(_wxyz(r1), shape, dtype, (4,)), _t(_wxyz(r2), shape, dtype, (4,))
    prod = so3.quat_mul(q1, q2)
    assert prod.shape == tuple(shape) + (4,) and prod.dtype == dtype
    np.testing.assert_allclose(canonical_wxyz(_np(prod, (4,))), _wxyz(r1 * r2), **tol(dtype, "rotation"))
    # q q^-1 = 1, and the conjugate is the inverse rotation
    ident = np.broadcast_to([1.0, 0.0, 0.0, 0.0], (_n(shape), 4))
    np.testing.assert_allclose(_np(so3.quat_mul(q1, so3.quat_conj(q1)), (4,)), ident, **tol(dtype, "exact"))
    np.testing.assert_allclose(canonical_wxyz(_np(so3.quat_conj(q1), (4,))), _wxyz(r1.inv()), atol=0)
    v = np.random.default_rng(25).normal(size=(_n(shape), 3))
    rv = so3.quat_rotate(q1, _t(v, shape, dtype, (3,)))
    assert rv.shape == tuple(shape) + (3,) and rv.dtype == dtype
    np.testing.assert_allclose(_np(rv, (3,)), r1.apply(v), **tol(dtype, "rotation"))
    # normalise / positive representative
    qn = so3.quat_normalize(2.5 * q1)
    np.testing.assert_allclose(_np(qn.norm(dim=-1), ()), 1.0, **tol(dtype, "exact"))
    qp = so3.quat_positive(-q1)
    assert bool((qp[..., 0] >= 0).all())
    torch.testing.assert_close(qp, so3.quat_positive(q1), atol=0, rtol=0)


@dtypes
def test_quat_mul_broadcasts(dtype):
    r1, r2 = _rotations((2,), seed=26), _rotations((3,), seed=27)
    p = _t(_wxyz(r1), (2, 1), dtype, (4,))
    q = _t(_wxyz(r2), (3,), dtype, (4,))
    out = so3.quat_mul(p, q)
    assert out.shape == (2, 3, 4)
    ref = np.stack([_wxyz(r1[i] * r2) for i in range(2)])
    np.testing.assert_allclose(canonical_wxyz(out.double().numpy()), ref, **tol(dtype, "rotation"))


@grid
@dtypes
def test_grid_slerp(shape, dtype):
    r0, r1 = _rotations(shape, seed=28), _rotations(shape, seed=29)
    t = np.random.default_rng(30).uniform(0, 1, size=_n(shape))
    # reference (scipy): r0 * exp(t * log(r0^-1 r1)), the shortest path
    ref = r0 * Rotation.from_rotvec(t[:, None] * (r0.inv() * r1).as_rotvec())
    out = so3.quat_slerp(_t(_wxyz(r0), shape, dtype, (4,)), _t(_wxyz(r1), shape, dtype, (4,)),
                         _t(t, shape, dtype, ()))
    assert out.shape == tuple(shape) + (4,) and out.dtype == dtype
    np.testing.assert_allclose(canonical_wxyz(_np(out, (4,))), _wxyz(ref), **tol(dtype, "integrate"))
    # the end points
    q0 = _t(_wxyz(r0), shape, dtype, (4,))
    ends = so3.quat_slerp(q0, _t(_wxyz(r1), shape, dtype, (4,)), torch.zeros(shape, dtype=dtype))
    np.testing.assert_allclose(canonical_wxyz(_np(ends, (4,))), _wxyz(r0), **tol(dtype, "rotation"))


@grid
@dtypes
def test_grid_euler_yaw_wrap(shape, dtype):
    g = np.random.default_rng(31)
    n = _n(shape)
    # pitch away from +-90 deg, where roll and yaw are not defined (gimbal lock)
    ypr = np.stack([g.uniform(-3.1, 3.1, n), g.uniform(-1.3, 1.3, n), g.uniform(-3.1, 3.1, n)], 1)
    rot = Rotation.from_euler("ZYX", ypr)
    rm = _t(rot.as_matrix(), shape, dtype, (3, 3))
    rpy = so3.matrix_to_euler(rm)
    assert rpy.shape == tuple(shape) + (3,) and rpy.dtype == dtype
    np.testing.assert_allclose(_np(rpy, (3,)), ypr[:, ::-1], **tol(dtype, "angle"))
    rpy_q = so3.quat_to_euler(_t(_wxyz(rot), shape, dtype, (4,)))
    np.testing.assert_allclose(_np(rpy_q, (3,)), ypr[:, ::-1], **tol(dtype, "angle"))
    y = so3.yaw(rm)
    assert y.shape == tuple(shape) and y.dtype == dtype
    np.testing.assert_allclose(_np(y, ()), ypr[:, 0], **tol(dtype, "angle"))
    w = so3.wrap_angle(_t(ypr[:, 0] + 2 * math.pi * g.integers(-3, 4, n), shape, dtype, ()))
    assert w.shape == tuple(shape) and w.dtype == dtype
    # the wrapped angle of a multiple of 2 pi plus ypr: float32 loses ~|k| 2 pi eps in the addition
    err = np.angle(np.exp(1j * (_np(w, ()) - ypr[:, 0])))
    assert np.abs(err).max() < atol(dtype, "angle")
    assert bool((w > -math.pi - 1e-6).all() and (w <= math.pi + 1e-6).all())


@grid
@dtypes
@pytest.mark.parametrize("n", [1, 2, 7, 50])
def test_grid_cumulative_products(shape, dtype, n):
    rot = _rotations(tuple(shape) + (n,), seed=32 + n, max_angle=0.3)
    mats = rot.as_matrix().reshape((-1, n, 3, 3))
    ref = np.empty_like(mats)  # the sequential product with scipy, per batch element
    for b in range(mats.shape[0]):
        acc = Rotation.identity()
        for k in range(n):
            acc = acc * Rotation.from_matrix(mats[b, k])
            ref[b, k] = acc.as_matrix()
    r = _t(mats, shape, dtype, (n, 3, 3))
    par = so3.cumprod_matrix(r)
    assert par.shape == r.shape and par.dtype == dtype
    np.testing.assert_allclose(_np(par, (n, 3, 3)), ref, **tol(dtype, "scan"))
    torch.testing.assert_close(par, so3.cumprod_matrix_sequential(r), **tol(dtype, "scan"))
    cq = so3.cumprod_quat(so3.matrix_to_quat(r))
    assert cq.shape == tuple(shape) + (n, 4) and cq.dtype == dtype
    np.testing.assert_allclose(_np(so3.quat_to_matrix(cq), (n, 3, 3)), ref, **tol(dtype, "scan"))


@grid
@dtypes
def test_grid_integrate(shape, dtype):
    n = 50
    g = np.random.default_rng(33)
    omega = g.normal(size=(_n(shape), n, 3))
    dt = g.uniform(0.005, 0.02, size=(_n(shape), n))
    r0 = _rotations(shape, seed=34)
    out = so3.integrate(_t(r0.as_matrix(), shape, dtype, (3, 3)), _t(omega, shape, dtype, (n, 3)),
                        _t(dt, shape, dtype, (n,)))
    assert out.shape == tuple(shape) + (n, 3, 3) and out.dtype == dtype
    out = _np(out, (n, 3, 3))
    for b in range(_n(shape)):
        ref = r0[b]
        np.testing.assert_allclose(out[b, 0], ref.as_matrix(), **tol(dtype, "rotation"))
        for k in range(1, n):
            ref = ref * Rotation.from_rotvec(omega[b, k] * dt[b, k])
            np.testing.assert_allclose(out[b, k], ref.as_matrix(), **tol(dtype, "integrate"))


def test_the_tensor_and_the_scalar_hamilton_product_are_one_expression():
    """so3.quat_mul (tensors: batched, autograd) and kernels.quat.qmul (scalars: numba, TorchScript)
    are two readings of one product: equal bit for bit, so neither can drift from the other."""
    from tcn_ahrs.kernels.quat import qmul, quat_step

    g = torch.Generator().manual_seed(3)
    p, q = torch.randn(64, 4, dtype=torch.float64, generator=g), torch.randn(64, 4, dtype=torch.float64, generator=g)
    scalar = torch.tensor([qmul(*a.tolist(), *b.tolist()) for a, b in zip(p, q)], dtype=torch.float64)
    assert torch.equal(so3.quat_mul(p, q), scalar)
    # the scalar step q ⊗ exp(φ) agrees with the tensor exp (the same series below 1e-6 rad²)
    qn = so3.quat_normalize(p)
    phi = 0.3 * torch.randn(64, 3, dtype=torch.float64, generator=g)
    step = torch.tensor([quat_step(*a.tolist(), *f.tolist()) for a, f in zip(qn, phi)], dtype=torch.float64)
    assert torch.allclose(step, so3.quat_normalize(so3.quat_mul(qn, so3.quat_exp(phi))), atol=1e-14)


def test_constant_tensor_forms_equal_so3():
    """The ECF step graph's contractions (tcn_ahrs/export/classical_step.py) are so3's products
    read off on the basis vectors: the Hamilton product, the rotation matrix of a unit quaternion
    and the cross product, on random inputs (float64, 1e-15)."""
    from tcn_ahrs.export.classical_step import hamilton, levi_civita, rotation_rows

    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        p, q = torch.randn(4, generator=g, dtype=torch.float64), torch.randn(4, generator=g, dtype=torch.float64)
        h = hamilton().permute(0, 2, 1).reshape(16, 4)
        assert torch.allclose((h @ p).reshape(4, 4) @ q, so3.quat_mul(p, q), atol=1e-14)
        u = so3.quat_normalize(q)
        r = (rotation_rows((0, 1, 2)) @ (u[:, None] * u[None, :]).reshape(16)).reshape(3, 3)
        assert torch.allclose(r, so3.quat_to_matrix(u), atol=1e-15)
        a, b = p[:3], q[:3]
        assert torch.allclose(levi_civita() @ (a[:, None] * b[None, :]).reshape(9), torch.linalg.cross(a, b), atol=1e-15)
