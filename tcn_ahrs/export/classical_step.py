"""The tuned ECF of a ``tcn-ahrs search`` file as a *stateless* step graph for ONNX and
``torch.export`` (``format=onnx|export`` on a ``.json`` estimator file): ``quat (4,), omega (3,),
state' (S,) = step(sample (C,), dt (), state (S,))``, float64, the same contract and loaders as the
residual models' step (:mod:`tcn_ahrs.export.stateless`: :class:`OnnxStreaming`, ``ExportedStreaming``).

One sample is Eqs. 4-8 of :func:`tcn_ahrs.filters.ecf.ecf` on the calibrated readings, written as
few graph nodes as the equations allow (ONNX Runtime pays per node, not per flop): the attitude
is one unit quaternion (the filter's matrix ``r <- r exp([phi]x)`` is ``q <- q ⊗ exp(phi)``, equal
to round-off), the Hamilton product, the two rows of the attitude matrix the corrections read
and the cross products are contractions with constant tensors read off :mod:`tcn_ahrs.so3` on
the basis vectors (:func:`hamilton`, :func:`rotation_rows`, :func:`levi_civita`; nothing
restated), the two corrections of Eqs. 5-6 one batched cross product. The first sample after
``reset(q0)`` only fixes the start (9 axes: the magnetic frame of its field, as
:func:`~tcn_ahrs.filters.common.magnetic_from_nav`); its output is q0. State layout::

    t       (1,)  samples since reset (0: the next one starts the filter)
    q0      (4,)  the attitude given to reset
    m_conj  (4,)  9 axes: the magnetic frame's conjugate (set at the first sample)
    q       (4,)  the attitude nav_from_body (magnetic frame for 9 axes), unit
    elapsed (1,)  seconds since the first sample (Eq. 8's t)
"""
from __future__ import annotations

import math
from typing import Dict, Tuple

import numpy as np
import torch
from torch import Tensor, nn

from .. import so3
from ..conventions import GRAVITY

F64 = torch.float64
LAYOUT = (("t", 1), ("q0", 4), ("m_conj", 4), ("q", 4), ("elapsed", 1))


def hamilton() -> Tensor:
    """E (4, 4, 4) with ``(p ⊗ q)_i = sum_jk E[i, j, k] p_j q_k``: :func:`so3.quat_mul` on the basis."""
    e, out = torch.eye(4, dtype=F64), torch.zeros(4, 4, 4, dtype=F64)
    for j in range(4):
        for k in range(4):
            out[:, j, k] = so3.quat_mul(e[j], e[k])
    return out


def levi_civita() -> Tensor:
    """(3, 9) with ``u x v = levi_civita() @ (u v^T).flatten()``: the cross product on the basis."""
    e, out = torch.eye(3, dtype=F64), torch.zeros(3, 3, 3, dtype=F64)
    for j in range(3):
        for k in range(3):
            out[:, j, k] = torch.linalg.cross(e[j], e[k])
    return out.reshape(3, 9)


def rotation_rows(rows=(2, 0)) -> Tensor:
    """(3 len(rows), 16): rows ``rows`` of the rotation matrix of a unit q as ``T @ (q q^T).flatten()``
    (``q ⊗ (0, v) ⊗ q*`` through :func:`hamilton`, i.e. :func:`so3.quat_rotate`; rows (0, 1, 2):
    the whole matrix)."""
    h = hamilton()
    conj = torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=F64)
    # (q ⊗ v ⊗ q*)_i = sum E[i, a, d] E[a, b, c] q_b v_c conj_d q_d: T[i, c, b, d]
    t = torch.einsum("iad,abc,d->icbd", h, h, conj)
    return torch.cat([t[r + 1, 1:4].reshape(3, 16) for r in rows], 0)


def quat_product(ham: Tensor, p: Tensor, q: Tensor) -> Tensor:
    """p ⊗ q (4,) as two products with ``ham`` = ``hamilton().permute(0, 2, 1).reshape(16, 4)``."""
    return (ham @ p).reshape(4, 4) @ q


def rotation_matrix(matrix: Tensor, q: Tensor) -> Tensor:
    """R (3, 3) of a unit q (4,) (q v q* = R v) with ``matrix`` = ``rotation_rows((0, 1, 2))``."""
    return (matrix @ (q[:, None] * q[None, :]).reshape(16)).reshape(3, 3)


def magnetic_start(ham: Tensor, matrix: Tensor, about_up: Tensor, q0: Tensor, mag: Tensor, atan2
                   ) -> Tuple[Tensor, Tensor]:
    """9 axes, the first sample: the start in the magnetic frame of its field, as
    :func:`~tcn_ahrs.filters.common.magnetic_from_nav` -> (mq ⊗ q0, mq = [cos h, 0, 0, sin h]) with
    h = (π/2 − the heading of R(q0) m) / 2; ``about_up`` (4, 2) maps [c, s] to [c, 0, 0, s]."""
    v = rotation_matrix(matrix, q0) @ mag
    h = 0.5 * (0.5 * math.pi - atan2(v[1], v[0]))
    mq = about_up @ torch.stack([torch.cos(h), torch.sin(h)])
    return quat_product(ham, mq, q0), mq


class ECFStep(nn.Module):
    """The step graph of an ECF estimator file's contents (``doc``: family, axes, knobs,
    calibration; :func:`~tcn_ahrs.estimators.families.read_estimator`). ``onnx``: float64 atan2
    from ops ONNX Runtime runs (:func:`tcn_ahrs.kernels.ops.onnx_ops`)."""

    def __init__(self, doc: Dict, onnx: bool = False):
        super().__init__()
        from ..calibration import StaticCalibration
        from ..filters.ecf import ECFParams
        from ..kernels.ops import onnx_ops

        self.axes = c = int(doc["axes"])
        knobs = {**ECFParams().__dict__, **dict(doc.get("knobs") or {})}
        self.knobs = {k: float(v) for k, v in knobs.items()}
        cal = StaticCalibration.from_dict(doc["calibration"]) if doc.get("calibration") else StaticCalibration()
        inv = np.zeros((c, c))
        for s, m in enumerate((cal.gyro_matrix, cal.acc_matrix, cal.mag_matrix)[:c // 3]):
            inv[3 * s:3 * s + 3, 3 * s:3 * s + 3] = np.linalg.inv(m)
        bias = np.concatenate([cal.gyro_bias, cal.acc_bias, cal.hard_iron])[:c]
        self.register_buffer("cal_inv", torch.tensor(inv, dtype=F64))
        self.register_buffer("cal_offset", torch.tensor(inv @ bias, dtype=F64))   # inv(A) (x - b) = inv(A) x - this
        self.register_buffer("ham", hamilton().permute(0, 2, 1).reshape(16, 4))  # (ham @ p).reshape(4, 4) @ q = p ⊗ q
        self.register_buffer("rows", rotation_rows((2, 0)))
        self.register_buffer("matrix", rotation_rows((0, 1, 2)))
        self.register_buffer("eps", levi_civita())
        self.register_buffer("eps_t", levi_civita().T.contiguous())  # its own buffer: a view would alias in scan
        self.register_buffer("conj", torch.tensor([1.0, 0.0, 0.0, -1.0], dtype=F64))
        self.register_buffer("about_up", torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]], dtype=F64).T)
        tt = max(self.knobs["t_init"], 1e-12)
        self.ramp = (self.knobs["k_init"] - self.knobs["k_norm"]) / tt     # Eq. 8's slope, 1/s²
        self.atan2 = onnx_ops().atan2 if onnx else torch.atan2
        self.layout: Dict[str, Tuple[int, Tuple[int, ...]]] = {}
        off = 0
        for name, n in LAYOUT:
            self.layout[name] = (off, (n,))
            off += n
        self.state_size = off

    def initial_state(self, q0: Tensor) -> Tensor:
        q = q0.to(F64).reshape(4)
        return torch.cat([torch.zeros(1, dtype=F64), q / torch.sqrt((q * q).sum()),
                          torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=F64), torch.zeros(5, dtype=F64)])

    def _mul(self, p: Tensor, q: Tensor) -> Tensor:
        return quat_product(self.ham, p, q)

    def forward(self, sample: Tensor, dt: Tensor, state: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
        k = self.knobs
        x = self.cal_inv @ sample.to(F64) - self.cal_offset          # calibrated readings
        dt = dt.to(F64).reshape(())
        gyro, acc = x[0:3], x[3:6]
        first = state[0:1].reshape(()) < 0.5
        # (static shapes: inside the batch graph's scan the state's length is a symbol)
        q0, m_conj, q = state[1:5].reshape(4), state[5:9].reshape(4), state[9:13].reshape(4)
        # the start (the first sample): 9 axes in the magnetic frame of its field
        q_start = q0
        if self.axes == 9:
            mag = x[6:9]
            q_start, mq = magnetic_start(self.ham, self.matrix, self.about_up, q0, mag, self.atan2)
            m_conj = torch.where(first, mq * self.conj, m_conj)
        # Eqs. 5-8: the unit specific force, the gates, the scheduled gain
        t = state[13:14].reshape(()) + dt
        an = torch.linalg.vector_norm(acc)
        acc_ok = torch.abs(an - GRAVITY) < k["a_min"]                     # Eq. 7
        gain = k["k_norm"] + torch.relu(k["t_init"] - t) * self.ramp      # Eq. 8
        measured = acc / torch.clamp(an, min=1e-30)                      # a^
        weights = torch.where(acc_ok, gain, 0.0).reshape(1)
        if self.axes == 9:
            mn = torch.linalg.vector_norm(mag)
            east = self.eps @ (mag[:, None] * acc[None, :]).reshape(9)     # m x a
            east = east / torch.clamp(torch.linalg.vector_norm(east), min=1e-30)
            mag_ok = acc_ok & (mn > k["m_min"]) & (mn < k["m_max"])
            measured = torch.stack([measured, east])
            weights = torch.cat([weights, torch.where(mag_ok, gain, 0.0).reshape(1)])
        measured = measured.reshape(-1, 3)
        # C^T up and C^T east: the attitude matrix's third and first rows
        rows = (self.rows @ (q[:, None] * q[None, :]).reshape(16)).reshape(2, 3)[:measured.shape[0]]
        crosses = (measured[:, :, None] * rows[:, None, :]).reshape(-1, 9) @ self.eps_t   # Eqs. 5-6
        e = weights @ crosses
        phi = (gyro + e) * dt                                             # Eq. 4: q <- q ⊗ exp(phi)
        # exp(phi) without so3.quat_exp's small-angle branches (half the nodes): sin(t/2)/t at
        # t >= 1e-150 is exact to round-off in float64 (0.5 at the floor)
        theta = torch.sqrt(torch.clamp((phi * phi).sum(), min=1e-300))
        dq = torch.cat([torch.cos(0.5 * theta).reshape(1), torch.sin(0.5 * theta) / theta * phi])
        q_next = self._mul(q, dq)
        q_next = q_next / torch.linalg.vector_norm(q_next)
        q_out = torch.where(first, q_start, q_next)
        quat = self._mul(m_conj, q_out)
        quat = torch.where(quat[0] < 0.0, -quat, quat)  # w >= 0 representative
        new_state = torch.cat([state[0:1] + 1.0, q0, m_conj, q_out, torch.where(first, 0.0, t).reshape(1)])
        return quat, gyro, new_state


def ecf_state_spec(step: ECFStep) -> Dict[str, object]:
    """The state's description for the metadata (what :func:`tcn_ahrs.export.stateless.initial_state` reads)."""
    return {"size": int(step.state_size), "dtype": "float64",
            "layout": {k: [int(o), [int(v) for v in s]] for k, (o, s) in step.layout.items()},
            "init": {"m_conj": [1.0, 0.0, 0.0, 0.0]}, "flags": {}}


def prepare_classical(path, fmt: str, onnx: bool = False):
    """(the :class:`ECFStep`, the metadata dict) of an estimator file; a family without a step
    graph is an ExportError naming the ones with one."""
    import hashlib
    from pathlib import Path

    from .. import __version__
    from ..conventions import INPUT_LIMITS, MAX_DT, MIN_DT
    from ..estimators.families import read_estimator
    from .inputs import ExportError

    doc = read_estimator(path)
    if doc["family"] != "ecf":
        raise ExportError(f"format={fmt}: {path} holds the classical family {doc['family']!r}; format={fmt} holds the "
                          "residual models and the classical family 'ecf'")
    step = ECFStep(doc, onnx=onnx).eval()
    axes = step.axes
    md = {"format": f"tcn-ahrs {fmt} export (stateless step)", "mode": "step", "tcn_ahrs_version": __version__,
          "torch_version": torch.__version__, "variant": "ecf (classical, tuned)", "family": "ecf", "axes": axes,
          "channels": ["gyro_x", "gyro_y", "gyro_z", "acc_x", "acc_y", "acc_z", "mag_x", "mag_y", "mag_z"][:axes],
          "rate_hz": None, "receptive_field": 1, "preintegration": "none", "knobs": step.knobs,
          "calibration": doc.get("calibration"), "checkpoint": str(path),
          "checkpoint_sha256": hashlib.sha256(Path(path).read_bytes()).hexdigest(),
          "units": {"gyro": "rad/s", "acc": "m/s^2 (specific force, +9.81 along the up axis at rest)",
                    "mag": "uT", "dt": "s", "omega": "rad/s (the calibrated gyro)"},
          "frames": {"imu": "body (sensor) frame", "attitude": "nav_from_body", "navigation": "ENU"},
          "quaternion_order": "wxyz", "quaternion_convention": "Hamilton, scalar first, w >= 0",
          "api": {"step": "quat (4,), omega (3,), state_out (S,) = step(sample (C,) float64 raw readings, dt () "
                          "float64 [s], state (S,) float64); the first sample after reset fixes the start and "
                          "returns q0"},
          "state": ecf_state_spec(step), "max_dt": float(MAX_DT), "min_dt": float(MIN_DT), "input_limits": [float(v) for v in INPUT_LIMITS]}
    return step, md
