"""Shared helpers for the classical filters: batching, normalisation, initial attitude.

Conventions (:mod:`tcn_ahrs.conventions`): quaternions ``(w, x, y, z)`` Hamilton,
``nav_from_body``; navigation frame ENU (x east, y north, z up); the accelerometer reads
specific force (+g along body-up at rest); the magnetometer points north (and down on the
northern hemisphere).

Batching: every filter takes inputs with any leading batch shape ``(..., N, 3)`` and
parameters with a batch shape broadcastable against it (scalars, ``(P,)``, ``(B, 1)``, ...).
:func:`flatten_batch` broadcasts everything to one batch shape and flattens it to ``(B,)``;
:func:`unflatten` restores it on the outputs. So ``gyro`` of shape ``(R, 1, N, 3)`` with a
gain of shape ``(P,)`` runs ``R`` recordings x ``P`` parameter sets in one call.
"""
from __future__ import annotations

import math
from typing import List, Optional, Sequence, Tuple, Union

import numpy as np
import torch
from torch import Tensor

from .. import so3
from ..conventions import STATE_DTYPE, enu_from_frame

Number = Union[float, int, Tensor, np.ndarray]

DEFAULT_DTYPE = STATE_DTYPE  # conventions.STATE_DTYPE: the one float policy


def to_tensor(x, dtype: Optional[torch.dtype] = None, device=None) -> Tensor:
    """numpy / float / tensor -> tensor (float64 unless ``dtype`` says otherwise)."""
    if isinstance(x, Tensor):
        return x.to(dtype=dtype or (x.dtype if x.is_floating_point() else DEFAULT_DTYPE), device=device)
    return torch.as_tensor(np.asarray(x), dtype=dtype or DEFAULT_DTYPE, device=device)


def converter_like(gyro):
    """``T(x)``: convert any filter input (or parameter) to a tensor with the gyro's float dtype
    (float64 when the gyro is not a float tensor) and device; ``T(None)`` is ``None``."""
    dtype = gyro.dtype if isinstance(gyro, Tensor) and gyro.is_floating_point() else DEFAULT_DTYPE
    dev = gyro.device if isinstance(gyro, Tensor) else None
    return lambda x: None if x is None else to_tensor(x, dtype, dev)


def flatten_batch(items: Sequence[Tuple[Optional[Tensor], int]]) -> Tuple[torch.Size, List[Optional[Tensor]]]:
    """Broadcast tensors to one batch shape and flatten it.

    Args:
        items: ``(tensor, event_ndim)`` pairs; ``event_ndim`` trailing dimensions belong to one
            batch element (e.g. 2 for ``(..., N, 3)``, 1 for ``(..., N)`` or ``(..., 4)``, 0 for
            a parameter). ``None`` tensors pass through.
    Returns:
        ``(batch_shape, tensors)`` with every tensor of shape ``(B, *event_shape)``,
        ``B = prod(batch_shape)`` (at least 1).
    """
    shapes = [t.shape[: t.dim() - e] for t, e in items if t is not None]
    batch = torch.broadcast_shapes(*shapes) if shapes else torch.Size([])
    out: List[Optional[Tensor]] = []
    for t, e in items:
        if t is None:
            out.append(None)
            continue
        ev = t.shape[t.dim() - e:] if e > 0 else torch.Size([])
        out.append(t.expand(batch + ev).reshape((-1,) + tuple(ev)))
    return batch, out


def unflatten(x: Tensor, batch: torch.Size) -> Tensor:
    """``(B, *event)`` -> ``(*batch, *event)`` (inverse of :func:`flatten_batch`)."""
    return x.reshape(tuple(batch) + tuple(x.shape[1:]))


def normalize(v: Tensor, dim: int = -1) -> Tensor:
    """Unit vectors along ``dim``; zero vectors stay zero (no NaN)."""
    n = torch.linalg.vector_norm(v, dim=dim, keepdim=True)
    return v / n.clamp_min(1e-300 if v.dtype == torch.float64 else 1e-30)


def field_gates(accel: Tensor, mag: Optional[Tensor], a_min: Tensor, m_min: Tensor, m_max: Tensor,
                gravity: float) -> Tuple[Tensor, Tensor]:
    """The ECF's Eq. 7 tests (bool, (..., N)) on raw accel, mag (..., N, 3):
    ``acc_ok = | |a| − g | < a_min`` (no large external acceleration) and
    ``mag_ok = acc_ok & m_min < |m| < m_max`` (a plausible Earth field; the measured east uses a).
    Thresholds broadcast against (..., N) (m/s², µT). Without a magnetometer mag_ok is all False."""
    acc_ok = (torch.linalg.vector_norm(accel, dim=-1) - gravity).abs() < a_min
    if mag is None:
        return acc_ok, torch.zeros_like(acc_ok)
    m = torch.linalg.vector_norm(mag, dim=-1)
    return acc_ok, acc_ok & (m > m_min) & (m < m_max)


def gain_schedule(t: Tensor, k_norm: Tensor, k_init: Tensor, t_init: Tensor) -> Tensor:
    """Paper Eq. 8: ``K = K_norm + (t_init - t)/t_init (K_init - K_norm)`` for ``t <= t_init``,
    else ``K_norm``. Shapes: ``t`` (B, N) seconds since the first sample, gains (B,) 1/s."""
    t_init_ = t_init.clamp_min(1e-12)[:, None]
    ramp = k_norm[:, None] + (t_init_ - t) / t_init_ * (k_init - k_norm)[:, None]
    return torch.where(t < t_init[:, None], ramp, k_norm[:, None].expand_as(t))


def elapsed(dt: Tensor) -> Tensor:
    """Time since sample 0, (B, N), from per-sample steps ``dt`` (B, N) (``dt[:, 0]`` unused)."""
    d = torch.cat([torch.zeros_like(dt[:, :1]), dt[:, 1:]], 1)
    return torch.cumsum(d, 1)


# ---------------------------------------------------------------------------------------
# Initial attitude and magnetic reference frame
# ---------------------------------------------------------------------------------------


def quat_from_accel(accel: Tensor) -> Tensor:
    """Attitude (..., 4) that maps the measured up direction onto nav up (shortest arc).

    With only an accelerometer the heading is unobservable; this picks the rotation of
    smallest angle, so a level sensor gets yaw 0. ``accel`` (..., 3) specific force, body.
    """
    a = normalize(accel)
    up = torch.zeros_like(a)
    up[..., 2] = 1.0
    # q = [1 + a.up, a x up] normalised rotates a onto up (body -> nav); degenerate when a = -up.
    w = 1.0 + (a * up).sum(-1, keepdim=True)
    v = torch.cross(a, up, dim=-1)
    q = torch.cat([w, v], -1)
    flipped = (w < 1e-9).expand_as(q)
    q = torch.where(flipped, torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=a.dtype, device=a.device).expand_as(q), q)
    return so3.quat_normalize(q)


def triad_quat(accel: Tensor, mag: Optional[Tensor] = None) -> Tensor:
    """TRIAD initial attitude in ENU from one accelerometer (and magnetometer) sample.

    The rows of ``R = nav_from_body`` are the nav axes seen in the body frame:
    up ``u = a/|a|``, east ``e = (m x a)/|m x a|`` (north x up = east), north ``n = u x e``.
    Without a magnetometer falls back to :func:`quat_from_accel`. Shapes (..., 3) -> (..., 4).
    """
    if mag is None:
        return quat_from_accel(accel)
    u = normalize(accel)
    e = normalize(torch.cross(mag, accel, dim=-1))
    n = torch.cross(u, e, dim=-1)
    r = torch.stack([e, n, u], -2)
    return so3.matrix_to_quat(r)


def heading_of(v_nav: Tensor) -> Tensor:
    """Angle (...) of the horizontal part of nav vectors (..., 3), counter-clockwise from east."""
    return torch.atan2(v_nav[..., 1], v_nav[..., 0])


def quat_about_up(angle: Tensor) -> Tensor:
    """Rotation about nav up (z) by ``angle`` (...) radians, counter-clockwise: (..., 4)."""
    h = 0.5 * angle
    z = torch.zeros_like(h)
    return torch.stack([torch.cos(h), z, z, torch.sin(h)], -1)


HEADING_REFS = ("auto", "init", "north")


def heading_ref_for(heading_ref: str, meta) -> str:
    """``"north"`` or ``"init"``: ``"auto"`` (the default of every 9-axis estimator) refers heading
    to magnetic north where the recording's ground truth is referred to it
    (``meta["heading_reference"] == "magnetic_north"``: BROAD, the simulator without declination;
    the yardstick scores those unaligned), else to the field at the initial attitude."""
    if heading_ref not in HEADING_REFS:
        raise ValueError(f"heading_ref: expected one of {HEADING_REFS}, got {heading_ref!r}")
    if heading_ref == "auto":
        return "north" if (meta or {}).get("heading_reference") == "magnetic_north" else "init"
    return heading_ref


def magnetic_from_nav(q0: Tensor, mag0: Tensor) -> Tensor:
    """Rotation ``q_M_from_nav`` (..., 4) about up into the *magnetic* ENU frame ``M``, in which
    the horizontal field at the initial attitude points to +y (north).

    Classical AHRS (ECF, Mahony, Madgwick, the ES-EKF's heading update) pull the heading to
    magnetic north. When the caller's initial attitude ``q0`` is in another frame (e.g. a
    motion-capture frame), run the filter on ``q_M_from_nav * q`` and map the result back
    with the inverse: the filters are equivariant under a constant rotation about up (the
    gravity reference does not change), so this only fixes the heading reference.
    With a TRIAD initial attitude the rotation is the identity (up to round-off).
    """
    v = so3.quat_rotate(q0, mag0)
    # heading_of(v) is CCW from east; north is at +pi/2: rotate by (pi/2 - heading).
    return quat_about_up(math.pi / 2 - heading_of(v))


def nwu_from_enu_quat(dtype=DEFAULT_DTYPE, device=None) -> Tensor:
    """Constant quaternion (4,) of the rotation ENU -> NWU (for ahrs' Madgwick frame)."""
    m = torch.as_tensor(enu_from_frame("NWU").T, dtype=dtype, device=device)
    return so3.matrix_to_quat(m)


