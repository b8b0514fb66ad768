"""The VQF-grade backbone over whole recordings: a compiled loop (numpy in, numpy out) and a
tensor scan (autograd), both built from the one step of :mod:`tcn_ahrs.kernels.backbone`.

``run(gyro, acc, mag, dt, params, q0, acc_trust, mag_trust, bias_trust)``: one recording,
numba (float64), ~1 µs per sample. ``scan(...)``: B recordings at once on (B,) tensors under
autograd (what training backpropagates through), with the state carried between calls as a
list of tensors (truncated backpropagation through time).

Inputs (N samples): gyro rad/s, acc m/s² (specific force, up), mag any unit (body frame), dt (N,)
the step before each sample (s; the first one is used for sample 0 too); trusts (N,) ≥ 0, all 1 =
the plain backbone. Outputs: ``quat`` (N, 4) ``nav_from_body`` (w,x,y,z) in ENU (9D: magnetic
north +y; 6D: heading from the start), ``gyro_bias`` (N, 3) rad/s, ``rest``, ``mag_disturbed``
(N,) and ``delta`` (N,) rad.
"""
from __future__ import annotations

from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from ..kernels import backbone as K
from ..kernels.ops import load_kernel, torch_ops

BackboneParams = K.BackboneParams

_TORCH = load_kernel(K, torch_ops())  # the same step read with torch tensors


def _loop(p, s, gyr, acc, mag, dt, ta, tm, tb, use_mag, q_out, bias_out, flags_out):
    """The compiled recording loop: one kernel step per sample (coefficients recomputed when
    the step changes), outputs written into the given arrays."""
    n = gyr.shape[0]
    c = np.zeros(K.N_COEFF)
    last = -1.0
    for i in range(n):
        if dt[i] != last:
            _coefficients(p, dt[i], c)
            last = dt[i]
        _gyro_update(s, p, c, gyr[i, 0], gyr[i, 1], gyr[i, 2])
        if acc[i, 0] != 0.0 or acc[i, 1] != 0.0 or acc[i, 2] != 0.0:  # VQF skips [0 0 0]
            _acc_update(s, p, c, acc[i, 0], acc[i, 1], acc[i, 2], ta[i], tb[i])
        if use_mag and (mag[i, 0] != 0.0 or mag[i, 1] != 0.0 or mag[i, 2] != 0.0):
            _mag_update(s, p, c, mag[i, 0], mag[i, 1], mag[i, 2], tm[i])
        if use_mag:
            w, x, y, z = _quat9(s)
        else:
            w, x, y, z = _quat6(s)
        q_out[i, 0], q_out[i, 1], q_out[i, 2], q_out[i, 3] = w, x, y, z
        bias_out[i, 0], bias_out[i, 1], bias_out[i, 2] = s[_S_BIAS], s[_S_BIAS + 1], s[_S_BIAS + 2]
        flags_out[i, 0], flags_out[i, 1], flags_out[i, 2] = s[_S_REST], s[_S_MAGDIST], s[_S_DELTA]
        flags_out[i, 3], flags_out[i, 4] = s[_S_GFROZEN], s[_S_AFROZEN]
        flags_out[i, 5], flags_out[i, 6], flags_out[i, 7] = s[_S_GCLIPPED], s[_S_ACLIPPED], s[_S_GAP]
        flags_out[i, 8] = s[_S_MFROZEN]


_coefficients, _gyro_update, _acc_update, _mag_update, _quat6, _quat9 = (
    K.coefficients, K.gyro_update, K.acc_update, K.mag_update, K.quat6, K.quat9)
_S_BIAS, _S_REST, _S_MAGDIST, _S_DELTA = K.S_BIAS, K.S_REST, K.S_MAGDIST, K.S_DELTA
_S_GFROZEN, _S_AFROZEN, _S_GCLIPPED, _S_ACLIPPED, _S_GAP = (K.S_GFROZEN, K.S_AFROZEN, K.S_GCLIPPED,
                                                         K.S_ACLIPPED, K.S_GAP)
_S_MFROZEN = K.S_MFROZEN
_loop = K.ops.jit(_loop)


HEALTH_KEYS = ("gyro_frozen", "acc_frozen", "gyro_clipped", "acc_clipped", "gap", "mag_frozen")
"""The sensors' health flags :func:`run` returns (N,) bool (tcn_ahrs.health names them in words)."""


def start_state(params: BackboneParams, q0: Optional[np.ndarray] = None) -> np.ndarray:
    """The initial state (float64 vector of :data:`~tcn_ahrs.kernels.backbone.N_STATE`); ``q0``
    (w,x,y,z) starts the strapdown quaternion there (q_acc = 1, δ = 0) instead of at the identity."""
    s = np.asarray(K.initial_state(params), dtype=np.float64)
    if q0 is not None:
        q = np.asarray(q0, dtype=np.float64).reshape(4)
        s[K.S_GQ:K.S_GQ + 4] = q / np.linalg.norm(q)
    return s


def run(gyro: np.ndarray, acc: np.ndarray, mag: Optional[np.ndarray], dt: np.ndarray,
        params: BackboneParams = BackboneParams(), q0: Optional[np.ndarray] = None,
        acc_trust: Optional[np.ndarray] = None, mag_trust: Optional[np.ndarray] = None,
        bias_trust: Optional[np.ndarray] = None, state: Optional[np.ndarray] = None,
        bias0: Optional[np.ndarray] = None) -> Dict[str, np.ndarray]:
    """The backbone over one recording (compiled; see the module docstring). ``state`` (optional)
    continues from a state vector, which is updated in place; ``bias0`` (3,) rad/s starts the bias
    estimate there instead of at zero (its covariance stays the initial one: a prior, not a fix)."""
    f = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    gyro, acc = f(gyro), f(acc)
    n = gyro.shape[0]
    if acc.shape != (n, 3) or gyro.shape != (n, 3):
        raise ValueError(f"backbone: gyro and acc must be (N, 3), got {gyro.shape} and {acc.shape}")
    use_mag = mag is not None
    mag = f(mag) if use_mag else np.zeros((n, 3))
    dt = f(np.broadcast_to(np.asarray(dt, dtype=np.float64), (n,)))
    if not np.all(np.isfinite(dt)) or np.any(dt <= 0):
        raise ValueError("backbone: dt must be finite and positive")
    one = np.ones(n)
    ta, tm, tb = (one if t is None else f(np.broadcast_to(t, (n,))) for t in (acc_trust, mag_trust, bias_trust))
    s = start_state(params, q0) if state is None else state
    if bias0 is not None:
        s[K.S_BIAS:K.S_BIAS + 3] = np.asarray(bias0, dtype=np.float64).reshape(3)
    q, b, flags = np.empty((n, 4)), np.empty((n, 3)), np.empty((n, 9))
    _loop(np.asarray(params.vector()), s, gyro, acc, mag, dt, ta, tm, tb, use_mag, q, b, flags)
    return {"quat": q, "gyro_bias": b, "rest": flags[:, 0] > 0.5, "mag_disturbed": flags[:, 1] > 0.5,
            "delta": flags[:, 2], "gyro_frozen": flags[:, 3] > 0.5, "acc_frozen": flags[:, 4] > 0.5,
            "gyro_clipped": flags[:, 5] > 0.5, "acc_clipped": flags[:, 6] > 0.5, "gap": flags[:, 7] > 0.5,
            "mag_frozen": flags[:, 8] > 0.5}


# ----------------------------------------------------------------------------- tensor scan


def start_state_tensor(params: BackboneParams, q0: Tensor) -> List[Tensor]:
    """The initial state as a list of (B,) tensors (q0 (B, 4) w,x,y,z; its dtype and device)."""
    base = torch.as_tensor(K.initial_state(params), dtype=q0.dtype, device=q0.device)
    s = [base[i].expand(q0.shape[0]).clone() for i in range(K.N_STATE)]
    q = q0 / q0.norm(dim=-1, keepdim=True)
    for i in range(4):
        s[K.S_GQ + i] = q[:, i]
    return s


def scan(state: List[Tensor], params: BackboneParams, gyro: Tensor, acc: Tensor, mag: Optional[Tensor],
         dt: Tensor, acc_trust: Optional[Tensor] = None, mag_trust: Optional[Tensor] = None,
         bias_trust: Optional[Tensor] = None) -> Tuple[Tensor, Tensor, List[Tensor]]:
    """The backbone on tensors, under autograd: gyro, acc, mag (B, N, 3), dt (B, N), trusts (B, N)
    from ``state`` (list of (B,) tensors, :func:`start_state_tensor`; not modified).

    Returns ``quat`` (B, N, 4) (9D with mag, else 6D), ``gyro_bias`` (B, N, 3) and the state after
    the last sample. Same step as :func:`run` (tested equal); zero acc/mag samples are skipped
    as there (a per-sample Python check, so recordings without them pay nothing)."""
    s = list(state)
    p = params.vector()
    n = gyro.shape[1]
    one = torch.ones_like(dt)
    ta = one if acc_trust is None else acc_trust
    tm = one if mag_trust is None else mag_trust
    tb = one if bias_trust is None else bias_trust
    use_mag = mag is not None
    acc_zero = (acc == 0).all(-1).any(0).tolist()
    mag_zero = (mag == 0).all(-1).any(0).tolist() if use_mag else [False] * n
    constant_dt = bool((dt == dt[:, :1]).all())
    c: List = [None] * K.N_COEFF
    if constant_dt:
        _TORCH.coefficients(p, dt[:, 0], c)
    quats, biases = [], []
    T = _TORCH
    for i in range(n):
        if not constant_dt:
            T.coefficients(p, dt[:, i], c)
        g, a = gyro[:, i], acc[:, i]
        T.gyro_update(s, p, c, g[:, 0], g[:, 1], g[:, 2])
        if acc_zero[i]:
            keep = (a == 0).all(-1)
            old = list(s)
            T.acc_update(s, p, c, a[:, 0], a[:, 1], a[:, 2], ta[:, i], tb[:, i])
            s = [torch.where(keep, o, x) for o, x in zip(old, s)]
        else:
            T.acc_update(s, p, c, a[:, 0], a[:, 1], a[:, 2], ta[:, i], tb[:, i])
        if use_mag:
            m = mag[:, i]
            old = list(s) if mag_zero[i] else None
            T.mag_update(s, p, c, m[:, 0], m[:, 1], m[:, 2], tm[:, i])
            if old is not None:
                keep = (m == 0).all(-1)
                s = [torch.where(keep, o, x) for o, x in zip(old, s)]
            q = T.quat9(s)
        else:
            q = T.quat6(s)
        quats.append(torch.stack(q, -1))
        biases.append(torch.stack([s[K.S_BIAS], s[K.S_BIAS + 1], s[K.S_BIAS + 2]], -1))
    return torch.stack(quats, 1), torch.stack(biases, 1), s


def state_to_tensor(state: Sequence[Tensor]) -> Tensor:
    """(B, N_STATE) from the list form (to carry between chunks, detached by the caller)."""
    return torch.stack([torch.as_tensor(x) for x in state], -1)


def state_from_tensor(t: Tensor) -> List[Tensor]:
    return [t[:, i] for i in range(t.shape[-1])]
