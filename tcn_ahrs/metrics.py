"""Attitude error metrics — the one definition of each.

All inputs are ``nav_from_body`` quaternions ``(w, x, y, z)`` in the ENU navigation frame
(:mod:`tcn_ahrs.conventions`), given as numpy arrays or torch tensors of shape (N, 4), and
boolean masks (N,). All results are floats in degrees. The SO(3) math is
:mod:`tcn_ahrs.so3` in float64.

Scored samples
    ``mask`` selects the samples that count; for a recording it is ``seq.scored()`` = valid
    ground truth AND the benchmark's score mask (BROAD: the ``movement`` phase). Samples
    outside the mask never influence a number (ground truth there may be NaN). ``mask=None``
    means every sample with finite ground truth. With no scored sample the metrics are NaN.

Alignment (``align=True``, used by AAE and AYE)
    The estimate is rotated by ONE constant navigation-frame rotation (left multiplication)
    so that it equals ground truth at the first scored sample ``k0``:
    ``R_est'[k] = R_gt[k0] R_est[k0]^T R_est[k]``. This removes the initial-attitude
    difference (e.g. when ground truth starts later than the IMU), nothing else.
    ``align=False`` scores the estimate as it is.

AAE — absolute attitude error (paper Eq. 29)
    ``AAE = sqrt( mean_k || Log(R_gt[k]^T R_est'[k]) ||^2 )`` over scored samples, in degrees:
    the RMS of the total rotation angle between estimate and ground truth.

AYE — absolute yaw error (paper Eq. 30)
    ``AYE = sqrt( mean_k wrap(yaw(R_est'[k]) - yaw(R_gt[k]))^2 )`` in degrees, with
    ``yaw`` the z-y'-x'' heading in ENU (:func:`tcn_ahrs.so3.yaw`) and ``wrap`` to (-180, 180].

AHE — absolute heading error (about the navigation vertical)
    ``AHE = sqrt( mean_k wrap(heading(q_gt[k] ⊗ q_est'[k]^-1))^2 )`` in degrees, aligned like
    AAE: the heading part of the earth-frame error, as in BROAD's decomposition below. Unlike
    AYE (an Euler angle) it stays defined when the body x axis is near vertical (EuRoC's IMU),
    where the z-y'-x'' yaw difference jumps although the attitude error is small.

BROAD errors (Laidig et al., "BROAD — A Benchmark for Robust Inertial Orientation
Estimation", Data 6(7), 2021) — no alignment
    The error quaternion is expressed in the earth (navigation) frame,
    ``q_err = q_gt ⊗ q_est^-1`` (BROAD's reference code computes ``q_est ⊗ q_gt^-1``, its
    inverse: the same angles). It is split as ``q_err = q_heading ⊗ q_incl`` with
    ``q_heading`` a rotation about the vertical z axis and ``q_incl`` a rotation about a
    horizontal axis (zero z component). Then per sample

    * total error       ``= 2 acos(|q_w|)``                        (the full rotation angle),
    * heading error     ``= wrap(2 atan2(q_z, q_w))``              (angle of ``q_heading``),
    * inclination error ``= 2 acos(clip(sqrt(q_w^2 + q_z^2), 0, 1))`` (angle of ``q_incl``),

    and each reported number is the RMSE over the scored samples in degrees
    (``total_deg``, ``heading_deg``, ``inclination_deg``).

    ``mode="9d"`` (magnetometer used): exactly the above. ``mode="6d"`` (no magnetometer,
    heading unobservable): first the constant heading offset ``delta`` = circular mean of
    the per-sample heading errors over the scored samples is removed from the estimate,
    ``q_est' = q_z(delta) ⊗ q_est``; this subtracts ``delta`` from every heading error and
    leaves every inclination error unchanged. ``delta`` is reported as
    ``heading_offset_deg``. (BROAD's reference code computes the 9D numbers; this 6D
    variant is our documented convention for 6-axis estimates.)
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Dict, Optional, Tuple

import numpy as np
import torch

from . import so3

RAD2DEG = 180.0 / math.pi


# ---------------------------------------------------------------------------
# input handling
# ---------------------------------------------------------------------------


def _as_quat(q, what: str) -> torch.Tensor:
    """(N, 4) numpy/tensor -> float64 CPU tensor, shape checked."""
    if isinstance(q, torch.Tensor):
        t = q.detach().to(device="cpu", dtype=torch.float64)
    else:
        t = torch.as_tensor(np.asarray(q, dtype=np.float64))
    if t.ndim != 2 or t.shape[1] != 4:
        raise ValueError(f"{what}: expected quaternions of shape (N, 4) (w,x,y,z), got {tuple(t.shape)}")
    return t


def _scored_mask(q_gt: torch.Tensor, q_est: torch.Tensor, mask) -> np.ndarray:
    """(N,) bool of scored samples; checks shapes and that scored ground truth is finite."""
    n = q_gt.shape[0]
    if q_est.shape[0] != n:
        raise ValueError(f"quat_est: expected {n} samples like the ground truth, got {q_est.shape[0]}")
    gt_finite = torch.isfinite(q_gt).all(-1).numpy()
    if mask is None:
        return gt_finite
    if isinstance(mask, torch.Tensor):
        mask = mask.detach().cpu().numpy()
    m = np.asarray(mask, dtype=bool)
    if m.shape != (n,):
        raise ValueError(f"mask: expected shape ({n},), got {m.shape}")
    if np.any(m & ~gt_finite):
        k = int(np.argmax(m & ~gt_finite))
        raise ValueError(f"mask: selects sample {k} whose ground truth is not finite; "
                         "score only samples with valid ground truth (seq.scored())")
    return m


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if x.size else float("nan")


# ---------------------------------------------------------------------------
# alignment, AAE, AYE
# ---------------------------------------------------------------------------


def align_to_first(q_gt, q_est, mask=None) -> np.ndarray:
    """The estimate rotated by one constant navigation-frame rotation so that it equals
    ground truth at the first scored sample ``k0``: ``q_est' = q_gt[k0] ⊗ q_est[k0]^-1 ⊗ q_est``.

    Returns (N, 4) numpy float64; the estimate unchanged when no sample is scored.
    """
    qg, qe = _as_quat(q_gt, "quat_gt"), _as_quat(q_est, "quat_est")
    m = _scored_mask(qg, qe, mask)
    if not m.any():
        return qe.numpy().copy()
    k0 = int(np.argmax(m))
    corr = so3.quat_mul(qg[k0], so3.quat_conj(so3.quat_normalize(qe[k0])))
    return so3.quat_normalize(so3.quat_mul(corr.expand_as(qe), qe)).numpy()


def attitude_errors(q_gt, q_est, mask=None, align: bool = True) -> Tuple[np.ndarray, np.ndarray]:
    """Per-sample errors in radians: ``angle`` (N,) = ||Log(R_gt^T R_est')|| and ``yaw`` (N,) =
    wrap(yaw(R_est') - yaw(R_gt)) (signed). NaN where ground truth is missing; the alignment
    (if ``align``) uses the first sample of ``mask``."""
    qg, qe = _as_quat(q_gt, "quat_gt"), _as_quat(q_est, "quat_est")
    if align:
        qe = torch.as_tensor(align_to_first(qg, qe, mask))
    else:
        _scored_mask(qg, qe, mask)
    qe = so3.quat_normalize(qe)
    d = so3.quat_mul(so3.quat_conj(qg), qe)  # R_gt^T R_est: error in the body frame
    angle = torch.linalg.norm(so3.quat_log(d), dim=-1)
    dyaw = so3.wrap_angle(so3.yaw(so3.quat_to_matrix(qe)) - so3.yaw(so3.quat_to_matrix(qg)))
    return angle.numpy(), dyaw.numpy()


def aae(q_gt, q_est, mask=None, align: bool = True) -> float:
    """Absolute attitude error (paper Eq. 29), degrees: RMS over scored samples of
    ``||Log(R_gt^T R_est')||``."""
    qg, qe = _as_quat(q_gt, "quat_gt"), _as_quat(q_est, "quat_est")
    m = _scored_mask(qg, qe, mask)
    angle, _ = attitude_errors(qg, qe, m, align)
    return _rms(angle[m]) * RAD2DEG


def ahe(q_gt, q_est, mask=None, align: bool = True) -> float:
    """Absolute heading error, degrees: RMS over scored samples of the heading part (rotation
    about the navigation vertical) of the earth-frame error of the aligned estimate."""
    qg, qe = _as_quat(q_gt, "quat_gt"), _as_quat(q_est, "quat_est")
    m = _scored_mask(qg, qe, mask)
    if not m.any():
        return float("nan")
    if align:
        qe = torch.as_tensor(align_to_first(qg, qe, m))
    return _rms(broad_error_angles(qg[m], qe[m])["heading"]) * RAD2DEG


def aye(q_gt, q_est, mask=None, align: bool = True) -> float:
    """Absolute yaw error (paper Eq. 30), degrees: RMS over scored samples of the wrapped
    z-y'-x'' yaw difference."""
    qg, qe = _as_quat(q_gt, "quat_gt"), _as_quat(q_est, "quat_est")
    m = _scored_mask(qg, qe, mask)
    _, dyaw = attitude_errors(qg, qe, m, align)
    return _rms(dyaw[m]) * RAD2DEG


# ---------------------------------------------------------------------------
# BROAD total / heading / inclination
# ---------------------------------------------------------------------------


def broad_error_angles(q_gt, q_est) -> Dict[str, np.ndarray]:
    """Per-sample BROAD error angles in radians: ``total`` (N,) >= 0, ``heading`` (N,) signed in
    (-pi, pi], ``inclination`` (N,) >= 0, from ``q_err = q_gt ⊗ q_est^-1`` (earth frame)."""
    qg, qe = _as_quat(q_gt, "quat_gt"), _as_quat(q_est, "quat_est")
    q = so3.quat_mul(qg, so3.quat_conj(so3.quat_normalize(qe)))
    q = q / torch.linalg.norm(q, dim=-1, keepdim=True)
    w, z = q[:, 0], q[:, 3]
    total = 2.0 * torch.acos(w.abs().clamp(0.0, 1.0))
    heading = so3.wrap_angle(2.0 * torch.atan2(z, w))
    incl = 2.0 * torch.acos(torch.sqrt(w * w + z * z).clamp(0.0, 1.0))
    return {"total": total.numpy(), "heading": heading.numpy(), "inclination": incl.numpy()}


def broad_errors(q_gt, q_est, mask=None, mode: str = "9d") -> Dict[str, float]:
    """BROAD RMSEs in degrees over scored samples, no alignment (see module docstring).

    Returns ``{"total_deg", "heading_deg", "inclination_deg", "heading_offset_deg"}``;
    ``heading_offset_deg`` is the removed constant heading offset (0 for ``mode="9d"``).
    """
    if mode not in ("9d", "6d"):
        raise ValueError(f"mode: expected '9d' or '6d', got {mode!r}")
    qg, qe = _as_quat(q_gt, "quat_gt"), _as_quat(q_est, "quat_est")
    m = _scored_mask(qg, qe, mask)
    nan = float("nan")
    if not m.any():
        return {"total_deg": nan, "heading_deg": nan, "inclination_deg": nan, "heading_offset_deg": nan}
    offset = 0.0
    if mode == "6d":
        h = broad_error_angles(qg[m], qe[m])["heading"]
        offset = math.atan2(float(np.mean(np.sin(h))), float(np.mean(np.cos(h))))
        # q_est' = q_z(offset) ⊗ q_est  =>  q_err' = q_err ⊗ q_z(-offset): heading - offset
        qz = torch.tensor([math.cos(offset / 2), 0.0, 0.0, math.sin(offset / 2)], dtype=torch.float64)
        qe = so3.quat_mul(qz.expand_as(qe), qe)
    e = broad_error_angles(qg[m], qe[m])
    return {
        "total_deg": _rms(e["total"]) * RAD2DEG,
        "heading_deg": _rms(e["heading"]) * RAD2DEG,
        "inclination_deg": _rms(e["inclination"]) * RAD2DEG,
        "heading_offset_deg": offset * RAD2DEG,
    }


# ---------------------------------------------------------------------------
# one recording
# ---------------------------------------------------------------------------


def sequence_metrics(seq, quat_est, axes: Optional[int] = None, align: bool = True) -> Dict[str, float]:
    """All metrics of one estimate on one :class:`~tcn_ahrs.sequence.ImuSequence`.

    Args:
        seq:      recording with ground truth; scored samples = ``seq.scored()``.
        quat_est: (N, 4) estimated ``nav_from_body`` (w,x,y,z).
        axes:     9 if the estimate used the magnetometer, 6 if not; ``None``: ``seq.num_axes``.
        align:    alignment at the first scored sample for AAE/AYE (BROAD errors never align).
    Returns:
        ``n_scored``, ``aae_deg``, ``aye_deg``, ``ahe_deg``, every registered extra metric
        (:func:`register_metric`); plus BROAD's ``total_deg``, ``heading_deg``,
        ``inclination_deg`` (and ``broad_mode``) when the recording has a magnetometer and
        the estimate is 9-axis (``"9d"``), or when the recording carries a benchmark score mask
        (BROAD) and the estimate is 6-axis (``"6d"``, heading offset removed).
    """
    if seq.quat is None:
        raise ValueError(f"{seq.source}: field 'quat': metrics need ground truth, recording {seq.name!r} has none")
    axes = seq.num_axes if axes is None else int(axes)
    if axes not in (6, 9):
        raise ValueError(f"axes: expected 6 or 9, got {axes}")
    qe = _as_quat(quat_est, f"quat_est of {seq.name}")
    if qe.shape[0] != len(seq):
        raise ValueError(f"quat_est: expected {len(seq)} samples for recording {seq.name!r}, got {qe.shape[0]}")
    m = seq.scored()
    out: Dict[str, float] = {"n_scored": int(m.sum())}
    angle, dyaw = attitude_errors(seq.quat, qe, m, align)
    out["aae_deg"] = _rms(angle[m]) * RAD2DEG
    out["aye_deg"] = _rms(dyaw[m]) * RAD2DEG
    out["ahe_deg"] = ahe(seq.quat, qe, m, align)
    mode = None
    if axes == 9 and seq.has_mag:
        mode = "9d"
    elif axes == 6 and seq.score_mask is not None:
        mode = "6d"
    if mode is not None:
        b = broad_errors(seq.quat, qe, m, mode)
        out.update(total_deg=b["total_deg"], heading_deg=b["heading_deg"], inclination_deg=b["inclination_deg"])
        out["broad_mode"] = mode
    if _EXTRA:
        qe_np = qe.numpy()
        for metric in _EXTRA.values():
            out[metric.key] = float(metric.fn(seq.quat, qe_np, m, align))
    return out


# ---------------------------------------------------------------------------
# the metric table: built-in keys and registered extras
# ---------------------------------------------------------------------------

BUILTIN_KEYS = ("aae_deg", "aye_deg", "ahe_deg", "total_deg", "heading_deg", "inclination_deg")
"""The per-recording numbers :func:`sequence_metrics` always computes (the runner adds the
inclination for every estimate)."""

HEADING_KEYS = ("aae_deg", "aye_deg", "ahe_deg", "total_deg", "heading_deg")
"""Numbers that need a heading reference (undefined for heading-free estimators such as RIANN)."""


@dataclass(frozen=True)
class Metric:
    """A registered extra metric: ``fn(q_gt, q_est, mask, align) -> float`` in degrees (the
    signature of :func:`aae`), ``label`` its table heading; ``needs_heading``: NaN for
    heading-free estimators."""

    key: str
    label: str
    fn: Callable
    needs_heading: bool = True


_EXTRA: Dict[str, Metric] = {}


def register_metric(key: str, label: Optional[str] = None, needs_heading: bool = True):
    """Decorator: a new metric in one file. ``key`` ends in ``_deg`` (every table is in degrees);
    the module is imported through the configs' ``plugins`` list, and the metric then appears in
    every results.json, table and mean of ``evaluate``, ``compare`` and ``benchmark``::

        @register_metric("p95_deg", "P95")
        def p95(q_gt, q_est, mask=None, align=True):
            angle, _ = attitude_errors(q_gt, q_est, mask, align)
            return float(np.degrees(np.percentile(angle[mask], 95)))
    """
    if not key.endswith("_deg"):
        raise ValueError(f"register_metric: key {key!r} must end in '_deg' (every table is in degrees)")

    def deco(fn):
        if key in BUILTIN_KEYS:
            raise ValueError(f"register_metric: {key!r} is a built-in metric")
        _EXTRA[key] = Metric(key, label or key[:-4], fn, needs_heading)
        return fn

    return deco


def metric_keys() -> Tuple[str, ...]:
    """Every averaged per-recording metric: the built-ins, then the registered extras."""
    return BUILTIN_KEYS + tuple(_EXTRA)


def extra_metrics() -> Tuple[Metric, ...]:
    return tuple(_EXTRA.values())
