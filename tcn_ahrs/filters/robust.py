"""Adaptive-robust gating of a Kalman observation (the ARCKF paper's Eqs. 39-42, Algorithm 1).

Per observation with residual r, ``gamma = r^T S^-1 r`` (Eq. 39) is compared with the
chi-square quantile ``chi2.ppf(1 - alpha, dof)`` (Eq. 40). A state-independent plausibility
test (the paper's robustness factor ``C_u < C_u,max``, Eqs. 35-37) decides who is to blame
when ``gamma`` is too large: a *plausible* observation means the state is abnormal, so the
predicted covariance is inflated, ``P <- (gamma/chi2) P`` (fading factor, Eq. 42); an
*implausible* one is an outlier, ``R <- (gamma/chi2) R`` (Eq. 41). As in Algorithm 1's ``while``
loops the inflation repeats (a fixed ``n_iter`` times, so a batch needs no data-dependent
control flow) until ``gamma < chi2``.
"""
from __future__ import annotations

from typing import Tuple

import torch
from torch import Tensor

from .kalman import mahalanobis


def robust_inflation(r: Tensor, hph: Tensor, R: Tensor, plausible: Tensor, thr: float, n_iter: int,
                     max_fading: float) -> Tuple[Tensor, Tensor, Tensor]:
    """Algorithm 1 lines 3-9 for a batch of observations.

    Args: residual r (B, m), ``H P H^T`` (B, m, m), R (B, m, m), plausible (B,) bool, the
    chi-square threshold, iterations, cap on the fading factor.
    Returns: gamma (B,) before inflation, lam_p (B,) factor on P, lam_r (B,) factor on R.
    """
    lam_p = torch.ones_like(r[:, 0])
    lam_r = torch.ones_like(r[:, 0])
    gamma0 = r[:, 0]
    for it in range(n_iter + 1):
        gamma = mahalanobis(r, lam_p[:, None, None] * hph + lam_r[:, None, None] * R)
        if it == 0:
            gamma0 = gamma
        if it == n_iter:
            break
        f = torch.where(gamma >= thr, gamma / thr, torch.ones_like(gamma))
        lam_p = torch.where(plausible, (lam_p * f).clamp(max=max_fading), lam_p)
        lam_r = torch.where(plausible, lam_r, lam_r * f)
    return gamma0, lam_p, lam_r


def rolling_max(x: Tensor, w: int) -> Tensor:
    """Causal running maximum over the last ``w`` samples of (B, N) (a plausibility test must
    hold over a window, not at one sample)."""
    if w <= 1:
        return x
    xp = torch.nn.functional.pad(x[:, None], (w - 1, 0), value=float("-inf"))
    return torch.nn.functional.max_pool1d(xp, kernel_size=w, stride=1)[:, 0]
