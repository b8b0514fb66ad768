"""The tuned ECF of a ``tcn-ahrs search`` file as a *stateless* step graph for ONNX and
``torch.export`` (``format=onnx|export`` on a ``.json`` estimator file): ``quat (4,), omega (3,),
state' (S,) = step(sample (C,), dt (), state (S,))``, float64, the same contract and loaders as the
residual models' step (:mod:`tcn_ahrs.export.stateless`: :class:`OnnxStreaming`, ``ExportedStreaming``).

One sample is Eqs. 4-8 of :func:`tcn_ahrs.filters.ecf.ecf` on the calibrated readings, written
with that filter's own tensor functions (``normalize``, ``field_gates``, ``gain_schedule``,
``so3.exp``): the state carries the attitude matrix as the filter does. The first sample after
``reset(q0)`` only fixes the start (9 axes: the magnetic frame of its field, as
:func:`~tcn_ahrs.filters.common.magnetic_from_nav`); its output is q0. State layout::

    t       (1,)  samples since reset (0: the next one starts the filter)
    q0      (4,)  the attitude given to reset
    m_conj  (4,)  9 axes: the magnetic frame's conjugate (set at the first sample)
    r       (9,)  the attitude nav_from_body (magnetic frame for 9 axes), row by row
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
from ..filters.common import field_gates, gain_schedule, normalize

F64 = torch.float64
LAYOUT = (("t", 1), ("q0", 4), ("m_conj", 4), ("r", 9), ("elapsed", 1))


class ECFStep(nn.Module):
    """The step graph of an ECF estimator file's contents (``doc``: family, axes, knobs,
    calibration; :func:`~tcn_ahrs.estimators.families.read_estimator`). ``onnx``: float64 atan2
    from ops ONNX Runtime runs (:func:`tcn_ahrs.export.stateless.onnx_ops`)."""

    def __init__(self, doc: Dict, onnx: bool = False):
        super().__init__()
        from ..calibration import StaticCalibration
        from ..filters.ecf import ECFParams
        from .stateless import onnx_ops

        self.axes = c = int(doc["axes"])
        knobs = {**ECFParams().__dict__, **dict(doc.get("knobs") or {})}
        self.knobs = {k: float(v) for k, v in knobs.items()}
        cal = StaticCalibration.from_dict(doc["calibration"]) if doc.get("calibration") else StaticCalibration()
        inv = np.zeros((c, c))
        for s, m in enumerate((cal.gyro_matrix, cal.acc_matrix, cal.mag_matrix)[:c // 3]):
            inv[3 * s:3 * s + 3, 3 * s:3 * s + 3] = np.linalg.inv(m)
        bias = np.concatenate([cal.gyro_bias, cal.acc_bias, cal.hard_iron])[:c]
        self.register_buffer("cal_inv", torch.tensor(inv, dtype=F64))
        self.register_buffer("cal_bias", torch.tensor(bias, dtype=F64))
        self.atan2 = onnx_ops().atan2 if onnx else torch.atan2
        self.layout: Dict[str, Tuple[int, Tuple[int, ...]]] = {}
        off = 0
        for name, n in LAYOUT:
            self.layout[name] = (off, (n,))
            off += n
        self.state_size = off

    def _part(self, state: Tensor, name: str) -> Tensor:
        off, (n,) = self.layout[name]
        return state[off:off + n]

    def initial_state(self, q0: Tensor) -> Tensor:
        q = q0.to(F64).reshape(4)
        return torch.cat([torch.zeros(1, dtype=F64), q / torch.sqrt((q * q).sum()),
                          torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=F64), torch.zeros(10, dtype=F64)])

    def forward(self, sample: Tensor, dt: Tensor, state: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
        k = {n: torch.full((1,), v, dtype=F64) for n, v in self.knobs.items()}
        x = self.cal_inv @ (sample.to(F64) - self.cal_bias)
        dt = dt.to(F64).reshape(())
        gyro, acc = x[0:3], x[3:6]
        mag = x[6:9] if self.axes == 9 else None
        first = self._part(state, "t")[0] < 0.5
        q0, m_conj = self._part(state, "q0"), self._part(state, "m_conj")
        r = self._part(state, "r").reshape(3, 3)
        # the start (the first sample): 9 axes in the magnetic frame of its field
        q_start, m_start = q0, m_conj
        if mag is not None:
            v = so3.quat_rotate(q0, mag)
            h = 0.5 * (0.5 * math.pi - self.atan2(v[1], v[0]))
            zero = torch.zeros((), dtype=F64)
            q_start = so3.quat_mul(torch.stack([torch.cos(h), zero, zero, torch.sin(h)]), q0)
            m_start = torch.stack([torch.cos(h), zero, zero, -torch.sin(h)])
        # one step of the filter (Eqs. 4-8)
        t = self._part(state, "elapsed")[0] + dt
        acc_ok, mag_ok = field_gates(acc[None], None if mag is None else mag[None], k["a_min"], k["m_min"],
                                     k["m_max"], GRAVITY)
        gain = gain_schedule(t.reshape(1, 1), k["k_norm"], k["k_init"], k["t_init"])[0, 0]
        e = (gain * acc_ok[0]) * torch.linalg.cross(normalize(acc), r[2])                  # Eq. 5
        if mag is not None:
            e = e + (gain * mag_ok[0]) * torch.linalg.cross(normalize(torch.linalg.cross(mag, acc)), r[0])  # Eq. 6
        r_next = r @ so3.exp((gyro + e) * dt)                                               # Eq. 4
        r_out = torch.where(first, so3.quat_to_matrix(q_start), r_next)
        m_out = torch.where(first, m_start, m_conj)
        quat = so3.quat_mul(m_out, so3.matrix_to_quat(r_out))
        quat = torch.where(quat[0] < 0.0, -quat, quat)  # w >= 0 representative
        new_state = torch.cat([(self._part(state, "t") + 1.0), q0, m_out, r_out.reshape(9),
                               torch.where(first, torch.zeros_like(t), t).reshape(1)])
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
    from ..conventions import INPUT_LIMITS, MAX_DT
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
          "state": ecf_state_spec(step), "max_dt": float(MAX_DT), "input_limits": [float(v) for v in INPUT_LIMITS]}
    return step, md
