"""The Kalman measurement update, written once (batched torch), and the Mahalanobis gate.

Used by the attitude ES-EKF (:mod:`tcn_ahrs.filters.eskf`) and its adaptive-robust variant
(:mod:`tcn_ahrs.filters.robust`); tested against filterpy's ``KalmanFilter.update``.

Shapes: a batch of B filters with n error states and m observations each: ``P`` (B, n, n),
residual ``r = z - h(x)`` (B, m), ``H`` (B, m, n), ``R`` (B, m, m).
"""
from __future__ import annotations

import functools
from typing import Tuple

import torch
from torch import Tensor


@functools.lru_cache(maxsize=64)
def chi2_threshold(alpha: float, dof: int) -> float:
    """Upper ``alpha`` quantile of the chi-square distribution (``Pr(gamma < thr) = 1 - alpha``)."""
    from scipy.stats import chi2

    return float(chi2.ppf(1.0 - alpha, dof))


def symmetrize(p: Tensor) -> Tensor:
    """``(P + P^T) / 2``: removes the asymmetry rounding leaves in a covariance."""
    return 0.5 * (p + p.transpose(-1, -2))


def innovation_cov(P: Tensor, H: Tensor, R: Tensor) -> Tensor:
    """``S = H P H^T + R`` (B, m, m)."""
    return H @ P @ H.transpose(-1, -2) + R


def mahalanobis(r: Tensor, S: Tensor) -> Tensor:
    """``gamma = r^T S^-1 r`` (B,) — chi-square distributed with m degrees of freedom for a
    consistent filter (the ARCKF paper's Eq. 39)."""
    return (r * torch.linalg.solve(S, r[..., None])[..., 0]).sum(-1)


def kalman_update(P: Tensor, r: Tensor, H: Tensor, R: Tensor, S: Tensor = None) -> Tuple[Tensor, Tensor]:
    """Error-state estimate and covariance after one observation.

    ``K = P H^T S^-1`` (gain, the ES-EKF paper's Eq. 12), ``dx = K r`` (Eq. 15) and the Joseph
    form ``P+ = (I - K H) P (I - K H)^T + K R K^T`` (Eq. 17): equal to ``(I - K H) P`` for the
    optimal gain but symmetric and positive semi-definite for *any* gain, so rounding (and the
    robust variant's inflated R) cannot make P indefinite. ``S`` may be passed when already
    computed (the robust gate does). Returns ``(dx (B, n), P+ (B, n, n))``.
    """
    if S is None:
        S = innovation_cov(P, H, R)
    if S.shape[-1] == 1:
        K = (P @ H.transpose(-1, -2)) / S  # scalar observation: no solve
    else:
        K = torch.linalg.solve(S, H @ P).transpose(-1, -2)  # S and P symmetric
    dx = (K @ r[..., None])[..., 0]
    IKH = torch.eye(P.shape[-1], dtype=P.dtype, device=P.device) - K @ H
    return dx, IKH @ P @ IKH.transpose(-1, -2) + K @ R @ K.transpose(-1, -2)
