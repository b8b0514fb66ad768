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

The yardstick (``align="protocol"``, the default everywhere; :class:`Yardstick`)
    One protocol for every method, so that no verdict rests on how an estimate starts:

    * every estimator starts at the ground-truth attitude of the first valid sample where its
      API allows it (the runner's ``init_quat``; VQF through its state); the first
      ``settle_s`` seconds after that sample are scored for nobody, so an estimator that
      initialises itself (RIANN) and converges is not charged for its start;
    * heading is aligned ONCE about the navigation vertical — the circular mean of the
      per-sample heading errors over the scored samples (:func:`align_heading`) — and the
      inclination stays absolute: a constant tilt error is always charged;
    * 9-axis estimates on data whose ground-truth north is magnetic north
      (``seq.meta["heading_reference"] == "magnetic_north"``: BROAD, the simulator) are not
      aligned at all: the magnetometer makes heading observable, so it is scored as it is.

Alignments (``align=``, AAE/AYE/AHE): ``"heading"`` (above); ``"first"`` (``True``, before
    2026-12-05): ``R_est'[k] = R_gt[k0] R_est[k0]^T R_est[k]`` at the first scored sample, which
    freezes its error (inclination included) into the recording; ``"none"`` (``False``);
    ``"protocol"``: the yardstick's choice (:func:`sequence_metrics`, :func:`scored_metric`).

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
import warnings
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


ALIGNMENTS = ("heading", "first", "none")
"""The alignments of one estimate (module docstring); ``"protocol"`` resolves to one of them."""


@dataclass(frozen=True)
class Yardstick:
    """The scoring protocol applied identically to every method (module docstring).

    settle_s: seconds after the first valid ground-truth sample that nobody is scored on
              (the slowest default inclination correction here, VQF's ``tau_acc``, is 3 s; 2 s
              lets a self-initialised filter converge without hiding a wrong steady state)."""

    settle_s: float = 2.0

    def settled(self, seq) -> np.ndarray:
        """(N,) bool: ``seq.scored()`` past the first ``settle_s`` s of ground truth (none: too short to score)."""
        m, valid = seq.scored(), seq.quat_valid
        on = valid.any() and self.settle_s > 0
        return m & (seq.time >= seq.time[int(np.argmax(valid))] + self.settle_s) if on else m

    def mask(self, seq) -> np.ndarray:
        """(N,) bool: :meth:`settled`; ``seq.scored()`` itself where that would leave nothing."""
        m, settled = seq.scored(), self.settled(seq)
        if not settled.any() and m.any():  # a short recording: scored whole, and said, not silently
            warnings.warn(f"{seq.name}: its ground truth ends within the yardstick's {self.settle_s:g} s settle: every "
                          "method is scored on all its samples (not comparable with longer recordings)")
        return settled if settled.any() else m

    @staticmethod
    def alignment(seq, axes: int) -> str:
        """``"none"`` for a 9-axis estimate on data whose ground truth north is magnetic, else ``"heading"``."""
        return "none" if axes == 9 and seq.has_mag and seq.meta.get("heading_reference") == "magnetic_north" else "heading"


YARDSTICK = Yardstick()


def alignment_name(align) -> str:
    """``"protocol"`` or the :data:`ALIGNMENTS` name of ``align`` (True/False: "first"/"none"), as results.json records it."""
    return "protocol" if align == "protocol" else _alignment(align)


def _alignment(align) -> str:
    if align is True:
        return "first"
    if align is False or align is None:
        return "none"
    if align not in ALIGNMENTS:
        raise ValueError(f"align: expected one of {ALIGNMENTS} (or True/False), got {align!r}; "
                         "'protocol' needs the recording: sequence_metrics or scored_metric")
    return align


def align_heading(q_gt, q_est, mask=None) -> np.ndarray:
    """The estimate rotated once about the navigation vertical by ``delta``, the circular mean
    of the per-sample heading errors over the scored samples: ``q_est' = q_z(delta) ⊗ q_est``.
    Inclination errors are unchanged (a rotation about the vertical commutes with the
    heading/inclination split of the earth-frame error). Returns (N, 4) numpy float64."""
    qg, qe = _as_quat(q_gt, "quat_gt"), _as_quat(q_est, "quat_est")
    m = _scored_mask(qg, qe, mask)
    if not m.any():
        return qe.numpy().copy()
    return _rotated_about_up(qe, heading_offset(qg[m], qe[m]))


def heading_offset(q_gt, q_est) -> float:
    """Circular mean (rad) of the heading errors of ``q_est`` against ``q_gt`` ((M, 4), scored samples)."""
    h = broad_error_angles(q_gt, q_est)["heading"]
    return math.atan2(float(np.mean(np.sin(h))), float(np.mean(np.cos(h))))


def _rotated_about_up(qe: torch.Tensor, delta: float) -> np.ndarray:
    """``q_z(delta) ⊗ q_est`` (N, 4): ``q_err' = q_err ⊗ q_z(-delta)``, every heading error minus delta."""
    qz = torch.tensor([math.cos(delta / 2), 0.0, 0.0, math.sin(delta / 2)], dtype=torch.float64)
    return so3.quat_normalize(so3.quat_mul(qz.expand_as(qe), qe)).numpy()


def aligned(q_gt, q_est, mask=None, align="heading") -> np.ndarray:
    """The estimate under one of :data:`ALIGNMENTS` (or True = "first", False = "none")."""
    how = _alignment(align)
    if how == "heading":
        return align_heading(q_gt, q_est, mask)
    if how == "first":
        return align_to_first(q_gt, q_est, mask)
    qg, qe = _as_quat(q_gt, "quat_gt"), _as_quat(q_est, "quat_est")
    _scored_mask(qg, qe, mask)
    return qe.numpy().copy()


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


def attitude_errors(q_gt, q_est, mask=None, align="heading") -> Tuple[np.ndarray, np.ndarray]:
    """Per-sample errors in radians: ``angle`` (N,) = ||Log(R_gt^T R_est')|| and ``yaw`` (N,) =
    wrap(yaw(R_est') - yaw(R_gt)) (signed). NaN where ground truth is missing; the alignment
    (:func:`align`) uses the samples of ``mask``."""
    qg, qe = _as_quat(q_gt, "quat_gt"), _as_quat(q_est, "quat_est")
    qe = so3.quat_normalize(torch.as_tensor(aligned(qg, qe, mask, align)))
    d = so3.quat_mul(so3.quat_conj(qg), qe)  # R_gt^T R_est: error in the body frame
    angle = torch.linalg.norm(so3.quat_log(d), dim=-1)
    dyaw = so3.wrap_angle(so3.yaw(so3.quat_to_matrix(qe)) - so3.yaw(so3.quat_to_matrix(qg)))
    return angle.numpy(), dyaw.numpy()


def aae(q_gt, q_est, mask=None, align="heading") -> float:
    """Absolute attitude error (paper Eq. 29), degrees: RMS over scored samples of
    ``||Log(R_gt^T R_est')||``."""
    qg, qe = _as_quat(q_gt, "quat_gt"), _as_quat(q_est, "quat_est")
    m = _scored_mask(qg, qe, mask)
    angle, _ = attitude_errors(qg, qe, m, align)
    return _rms(angle[m]) * RAD2DEG


def ahe(q_gt, q_est, mask=None, align="heading") -> float:
    """Absolute heading error, degrees: RMS over scored samples of the heading part (rotation
    about the navigation vertical) of the earth-frame error of the aligned estimate."""
    qg, qe = _as_quat(q_gt, "quat_gt"), _as_quat(q_est, "quat_est")
    m = _scored_mask(qg, qe, mask)
    if not m.any():
        return float("nan")
    qe = torch.as_tensor(aligned(qg, qe, m, align))
    return _rms(broad_error_angles(qg[m], qe[m])["heading"]) * RAD2DEG


def aye(q_gt, q_est, mask=None, align="heading") -> float:
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
        offset = heading_offset(qg[m], qe[m])
        qe = torch.as_tensor(_rotated_about_up(qe, offset))
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


def sequence_metrics(seq, quat_est, axes: Optional[int] = None, align="protocol",
                     yardstick: Yardstick = YARDSTICK) -> Dict[str, float]:
    """All metrics of one estimate on one :class:`~tcn_ahrs.sequence.ImuSequence`.

    Args:
        seq:      recording with ground truth; scored samples = ``seq.scored()`` (under the
                  protocol without the first ``yardstick.settle_s`` seconds).
        quat_est: (N, 4) estimated ``nav_from_body`` (w,x,y,z).
        axes:     9 if the estimate used the magnetometer, 6 if not; ``None``: ``seq.num_axes``.
        align:    ``"protocol"`` (the yardstick, module docstring) or one of :data:`ALIGNMENTS`
                  (``True``/``False``: ``"first"``/``"none"``) for AAE/AYE/AHE; BROAD's errors
                  are never aligned (6-axis: heading offset removed).
    Returns:
        ``n_scored``, ``aae_deg``, ``aye_deg``, ``ahe_deg``, ``inclination_deg`` (needs no
        heading), every registered extra metric (:func:`register_metric`); plus BROAD's
        ``total_deg``, ``heading_deg`` (and ``broad_mode``) when the recording has a
        magnetometer and the estimate is 9-axis (``"9d"``), or when the recording carries a
        benchmark score mask (BROAD) and the estimate is 6-axis (``"6d"``, heading offset removed).
    """
    if seq.quat is None:
        raise ValueError(f"{seq.source}: field 'quat': metrics need ground truth, recording {seq.name!r} has none")
    axes = seq.num_axes if axes is None else int(axes)
    if axes not in (6, 9):
        raise ValueError(f"axes: expected 6 or 9, got {axes}")
    qe = _as_quat(quat_est, f"quat_est of {seq.name}")
    if qe.shape[0] != len(seq):
        raise ValueError(f"quat_est: expected {len(seq)} samples for recording {seq.name!r}, got {qe.shape[0]}")
    if align == "protocol":
        m, align = yardstick.mask(seq), yardstick.alignment(seq, axes)
    else:
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
    else:
        out["inclination_deg"] = broad_errors(seq.quat, qe, m, "6d")["inclination_deg"]
    if _EXTRA:
        qe_np = qe.numpy()
        for metric in _EXTRA.values():
            out[metric.key] = float(metric.fn(seq.quat, qe_np, m, align))
    return out


def aae_and_inclination(seq, quat_est, axes: Optional[int] = None, yardstick: Yardstick = YARDSTICK) -> Tuple[float, float]:
    """``(aae_deg, inclination_deg)`` of :func:`sequence_metrics` under the yardstick, computed
    alone (what the family search scores thousands of times): the same numbers, a third of the work."""
    axes = seq.num_axes if axes is None else int(axes)
    m = yardstick.mask(seq)
    qg = _as_quat(seq.quat, "quat_gt")
    qe = so3.quat_normalize(torch.as_tensor(aligned(qg, quat_est, m, yardstick.alignment(seq, axes))))[m]
    angle = torch.linalg.norm(so3.quat_log(so3.quat_mul(so3.quat_conj(qg[m]), qe)), dim=-1).numpy()
    incl = broad_error_angles(qg[m], qe)["inclination"]  # a rotation about the vertical leaves it as it is
    return _rms(angle) * RAD2DEG, _rms(incl) * RAD2DEG


def scored_metric(seq, quat_est, axes: Optional[int] = None, key: str = "aae_deg", align="protocol") -> float:
    """One number of :func:`sequence_metrics` (what the tuners minimise), the tables' protocol."""
    return float(sequence_metrics(seq, quat_est, axes, align)[key])


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
