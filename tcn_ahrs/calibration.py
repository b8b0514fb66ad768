"""Static IMU calibration: constant sensor errors fitted once, used by every estimator family.

The seed paper's calibration model (Sec. 3.1, Eqs. 9-11, without its networks' time-varying
terms): each sensor reads an affine function of the true quantity in the body frame,

    gyro    y_g = A_g ω + b_g           ω   body angular rate (rad/s), body = the ground truth's
    accel   y_a = A_a f + b_a           f   specific force (m/s², up)
    mag     y_m = A_m m + h             m   the field in the body frame (µT)

with ``A`` = scale factor × axis misalignment × the IMU-to-body rotation (a mount error the
ground truth sees) and ``b``/``h`` the static bias / hard iron. The calibration inverts it,
``ω̂ = A_g⁻¹ (y_g − b_g)``, so that any filter run on the calibrated signals estimates the
ground truth's body attitude.

Fits (float64, closed-form least squares; :func:`fit`):

* gyro, against ground truth: over windows of ``gyro_window_s`` the readings integrated,
  ``Log(Π exp(y dt)) / T``, against the ground truth's ``Log(R_k^T R_{k+W}) / T`` (both sides
  integrated alike, so fast rotations do not bias the fit; the window's length averages the
  motion-capture noise down, which would otherwise bias the scale towards zero);
* accelerometer, against ground truth: over quasi-static windows of ``acc_window_s`` (little
  rotation, little vibration) the mean reading against the mean of ``R_k^T [0, 0, g]`` (ground
  truth here is attitude only: in motion the body-frame acceleration does not average out);
* magnetometer, from the recordings alone (no ground truth): an ellipsoid fitted to the readings
  (algebraic least squares on the quadric, then its centre = hard iron and the symmetric square
  root of its shape = soft iron, scaled to the mean field norm); heading still comes from the
  filter, only the field's shape is made a sphere.

``mode`` per sensor: ``"none"`` (identity), ``"bias"`` (offset only, A = I), ``"full"``.
Recordings without ground truth are skipped by the gyro/accel fits; missing ground truth is
never filled in.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch

from . import so3
from .conventions import GRAVITY
from .sequence import ImuSequence

MODES = ("none", "bias", "full")


@dataclass
class StaticCalibration:
    """The fitted constants (float64 numpy). ``gyro_matrix`` etc. are the ``A`` of the module
    docstring (sensor reading per unit of true quantity), ``gyro_bias`` rad/s, ``acc_bias`` m/s²,
    ``hard_iron`` µT. Identity / zero where a sensor was not fitted."""

    gyro_matrix: np.ndarray = field(default_factory=lambda: np.eye(3))
    gyro_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acc_matrix: np.ndarray = field(default_factory=lambda: np.eye(3))
    acc_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    mag_matrix: np.ndarray = field(default_factory=lambda: np.eye(3))
    hard_iron: np.ndarray = field(default_factory=lambda: np.zeros(3))
    modes: Dict[str, str] = field(default_factory=lambda: {"gyro": "none", "acc": "none", "mag": "none"})

    def apply(self, seq: ImuSequence) -> ImuSequence:
        """The recording with calibrated readings (ground truth, time and masks unchanged)."""
        inv = np.linalg.inv
        gyro = (seq.gyro - self.gyro_bias) @ inv(self.gyro_matrix).T
        acc = (seq.accel - self.acc_bias) @ inv(self.acc_matrix).T
        mag = None if seq.mag is None else (seq.mag - self.hard_iron) @ inv(self.mag_matrix).T
        return replace(seq, gyro=gyro, accel=acc, mag=mag, check_units=False)

    def to_dict(self) -> Dict[str, object]:
        """JSON-able: every constant as nested lists, the modes, and the readable summary
        (bias in °/s, scale in %, misalignment/mount angle in degrees)."""
        out = {k: np.asarray(getattr(self, k)).tolist() for k in
               ("gyro_matrix", "gyro_bias", "acc_matrix", "acc_bias", "mag_matrix", "hard_iron")}
        out["modes"] = dict(self.modes)
        out["summary"] = {"gyro_bias_dps": np.degrees(self.gyro_bias).round(4).tolist(),
                          "gyro_rotation_deg": round(_rotation_angle_deg(self.gyro_matrix), 4),
                          "acc_bias_mps2": np.round(self.acc_bias, 4).tolist(),
                          "hard_iron_ut": np.round(self.hard_iron, 3).tolist()}
        return out

    @classmethod
    def from_dict(cls, d: Dict[str, object]) -> "StaticCalibration":
        keys = ("gyro_matrix", "gyro_bias", "acc_matrix", "acc_bias", "mag_matrix", "hard_iron")
        return cls(**{k: np.asarray(d[k], dtype=np.float64) for k in keys}, modes=dict(d.get("modes", {})))


def _rotation_angle_deg(a: np.ndarray) -> float:
    """Angle of the rotation nearest to ``a`` (its polar factor)."""
    u, _, vt = np.linalg.svd(a)
    r = u @ vt
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


def _windows(seq: ImuSequence, seconds: float) -> List[np.ndarray]:
    """Index arrays of consecutive non-overlapping windows of ~``seconds`` in which every sample
    has valid ground truth (a gap ends a window)."""
    n = max(2, int(round(seconds * float(seq.rate))))
    valid = seq.quat_valid
    out, k = [], 0
    while k + n <= len(seq):
        idx = np.arange(k, k + n)
        if valid[idx].all():
            out.append(idx)
            k += n
        else:
            k = int(idx[~valid[idx]][-1]) + 1
    return out


def _affine_fit(x: np.ndarray, y: np.ndarray, mode: str) -> (np.ndarray, np.ndarray):
    """Least squares ``y ≈ A x + b`` over rows; ``mode`` "bias": A = I."""
    if mode == "bias":
        return np.eye(3), (y - x).mean(0)
    design = np.concatenate([x, np.ones((len(x), 1))], 1)
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)  # (4, 3)
    return coef[:3].T.copy(), coef[3].copy()


def gyro_pairs(seqs: Sequence[ImuSequence], window_s: float) -> (np.ndarray, np.ndarray):
    """(true rates (M, 3), mean readings (M, 3)) over ground-truth windows."""
    xs, ys = [], []
    for s in seqs:
        if s.quat is None:
            continue
        q = torch.as_tensor(s.quat, dtype=torch.float64)
        wins = [w for w in _windows(s, window_s) if w[-1] + 1 < len(s) and s.quat_valid[w[-1] + 1]]
        if not wins:
            continue
        i = np.array([w[0] for w in wins])
        j = i + len(wins[0])  # every window has the same length
        span = torch.as_tensor(s.time[j] - s.time[i], dtype=torch.float64)[:, None]
        xs.append((so3.quat_log(so3.quat_mul(so3.quat_conj(q[i]), q[j])) / span).numpy())
        # the readings integrated over the same interval the same way (reading k covers
        # (t_k-1, t_k]): both sides carry the window's non-commutativity (coning), so a fast
        # rotation does not bias the fit; to first order in the errors y = A ω + b holds
        steps = np.stack([s.gyro[i + 1 + k] * s.dt[i + 1 + k, None] for k in range(len(wins[0]))], 1)
        yq = so3.quat_exp(torch.as_tensor(steps, dtype=torch.float64))  # (W, n, 4)
        acc = yq[:, 0]
        for k in range(1, yq.shape[1]):
            acc = so3.quat_mul(acc, yq[:, k])
        ys.append((so3.quat_log(acc) / span).numpy())
    return np.concatenate(xs or [np.zeros((0, 3))]), np.concatenate(ys or [np.zeros((0, 3))])


def acc_pairs(seqs: Sequence[ImuSequence], window_s: float, max_rate: float = 0.2,
              max_std: float = 0.5) -> (np.ndarray, np.ndarray):
    """(mean true specific force of gravity (M, 3), mean readings (M, 3)) over quasi-static
    windows: turned by less than ``max_rate`` rad/s on average, readings' std ≤ ``max_std`` m/s²."""
    up = torch.tensor([0.0, 0.0, GRAVITY], dtype=torch.float64)
    xs, ys = [], []
    for s in seqs:
        if s.quat is None:
            continue
        q = torch.as_tensor(s.quat, dtype=torch.float64)
        for idx in _windows(s, window_s):
            # quasi-static windows only: in motion the body-frame acceleration does not average
            # out (a sensor off the rotation centre reads a centripetal term of fixed sign)
            turned = float(torch.linalg.norm(so3.quat_log(so3.quat_mul(so3.quat_conj(q[idx[0]]), q[idx[-1]]))))
            if turned > max_rate * (s.time[idx[-1]] - s.time[idx[0]]) or s.accel[idx].std(0).max() > max_std:
                continue
            g_body = so3.quat_rotate(so3.quat_conj(q[idx]), up.expand(len(idx), 3))
            xs.append(g_body.mean(0).numpy())
            ys.append(s.accel[idx].mean(0))
    return np.asarray(xs).reshape(-1, 3), np.asarray(ys).reshape(-1, 3)


def fit_ellipsoid(mag: np.ndarray, mode: str = "full") -> (np.ndarray, np.ndarray):
    """``(A, h)`` with ``y = A m + h`` and ``|m|`` constant (the mean field norm): hard iron
    ``h`` and soft iron ``A`` (symmetric) from readings ``mag`` (M, 3) alone. ``mode`` "bias":
    a sphere (A = I), its centre by linear least squares on ``|y|² = 2 h·y + c``."""
    y = np.asarray(mag, dtype=np.float64)
    if mode == "bias":
        design = np.concatenate([2.0 * y, np.ones((len(y), 1))], 1)
        coef, *_ = np.linalg.lstsq(design, (y ** 2).sum(1), rcond=None)
        return np.eye(3), coef[:3]
    # quadric y^T M y + 2 v^T y = 1 (M symmetric): 9 unknowns
    x, yy, z = y.T
    design = np.stack([x * x, yy * yy, z * z, 2 * x * yy, 2 * x * z, 2 * yy * z, 2 * x, 2 * yy, 2 * z], 1)
    coef, *_ = np.linalg.lstsq(design, np.ones(len(y)), rcond=None)
    m = np.array([[coef[0], coef[3], coef[4]], [coef[3], coef[1], coef[5]], [coef[4], coef[5], coef[2]]])
    v = coef[6:9]
    h = -np.linalg.solve(m, v)
    # (y-h)^T M (y-h) = 1 + h^T M h: the unit sphere of u = W (y-h), W = sqrtm(M / (1 + h^T M h))
    w_eig, vec = np.linalg.eigh(m / (1.0 + h @ m @ h))
    if np.any(w_eig <= 0):
        raise ValueError("fit_ellipsoid: the readings do not span an ellipsoid (too little rotation "
                         "of the magnetometer); use mode 'bias' or 'none'")
    w = vec @ np.diag(np.sqrt(w_eig)) @ vec.T
    # y - h = W^-1 u with |u| = 1; the field's norm and the soft iron's overall scale are not
    # separable: A = W^-1 scaled to det(A) = 1 (a soft iron that preserves volume)
    a = np.linalg.inv(w)
    return a / np.cbrt(np.linalg.det(a)), h


@dataclass(frozen=True)
class CalibrationConfig:
    """What :func:`fit` fits. gyro / acc / mag: one of :data:`MODES`; windows in seconds."""

    gyro: str = "full"
    acc: str = "bias"
    mag: str = "full"
    gyro_window_s: float = 0.1
    acc_window_s: float = 1.0


def fit(seqs: Sequence[ImuSequence], cfg: CalibrationConfig = CalibrationConfig(),
        strict: bool = True) -> StaticCalibration:
    """Fit the static calibration on training recordings (gyro and accelerometer against their
    ground truth, magnetometer from its readings). A sensor the recordings cannot calibrate
    (too few windows: 3 for an offset, 12 for a full matrix) raises ValueError naming what is
    missing; with ``strict=False`` it stays uncalibrated and ``modes`` says why."""
    for name in ("gyro", "acc", "mag"):
        if getattr(cfg, name) not in MODES:
            raise ValueError(f"calibration.{name}: expected one of {MODES}, got {getattr(cfg, name)!r}")
    cal = StaticCalibration(modes={"gyro": cfg.gyro, "acc": cfg.acc, "mag": cfg.mag})
    def enough(sensor: str, n: int, what: str) -> bool:
        need = 3 if getattr(cfg, sensor) == "bias" else 12
        if n >= need:
            return True
        msg = f"calibration.{sensor}: {n} {what}; need at least {need}"
        if strict:
            raise ValueError(msg)
        cal.modes[sensor] = f"none ({msg})"
        return False

    if cfg.gyro != "none":
        x, y = gyro_pairs(seqs, cfg.gyro_window_s)
        if enough("gyro", len(x), f"ground-truth windows of {cfg.gyro_window_s} s in {[s.name for s in seqs]} "
                                  "(recordings with ground truth)"):
            cal.gyro_matrix, cal.gyro_bias = _affine_fit(x, y, cfg.gyro)
    if cfg.acc != "none":
        x, y = acc_pairs(seqs, cfg.acc_window_s)
        if enough("acc", len(x), f"quasi-static ground-truth windows of {cfg.acc_window_s} s (rotating < 0.2 "
                                 "rad/s, readings' std < 0.5 m/s²): record some rests in several orientations, "
                                 "or use calibration.acc=none"):
            cal.acc_matrix, cal.acc_bias = _affine_fit(x, y, cfg.acc)
    if cfg.mag != "none":
        mags = [s.mag for s in seqs if s.mag is not None]
        if mags:
            try:
                cal.mag_matrix, cal.hard_iron = fit_ellipsoid(np.concatenate(mags, 0), cfg.mag)
            except ValueError as e:  # too little rotation in these recordings to see the ellipsoid
                msg = f"calibration.mag: {e} (recordings {[s.name for s in seqs]})"
                if strict:
                    raise ValueError(msg) from None
                cal.modes["mag"] = f"none ({msg})"
        else:
            cal.modes["mag"] = "none"  # 6-axis data: nothing to fit
    return cal


def fit_calibration(seqs: Sequence[ImuSequence], gyro: str = "full", acc: str = "bias", mag: str = "full",
                    strict: bool = True, **windows) -> StaticCalibration:
    """:func:`fit` with the modes as keywords."""
    return fit(seqs, CalibrationConfig(gyro=gyro, acc=acc, mag=mag, **windows), strict)


def as_dict(cal: Optional[StaticCalibration]) -> Optional[Dict[str, object]]:
    return None if cal is None else cal.to_dict()
