"""Differentiable open-loop Extended Complementary Filter on SO(3) (paper Sec. 3.3, Eqs. 22-25).

``ω̂_k = ω̂_gyr,k + γ ⊙ e_acc,k + η ⊙ e_mag,k``                                   (Eq. 22)

In the project's ENU convention (accelerometer specific force points UP at rest):

* ``e_acc = ĝ/|ĝ| × (C̃_{k-1}^T [0,0,1])``                                        (Eq. 23)
  measured up direction × up direction predicted by the pre-integrated attitude;
* ``e_mag = east_b × (C̃_{k-1}^T [1,0,0])``, ``east_b = (b̂ × g')/|b̂ × g'|``          (Eq. 24)
  (north × up = east), with g' the RAW accelerometer so the magnetometer network is
  decoupled from the accelerometer network (paper Sec. 3.3, last paragraph).

Sign: if the attitude estimate is rotated by +ε about a body axis relative to the truth,
``e`` is ≈ −ε along that axis, so a positive gain rotates the estimate back toward the
measurement (tested in tests/test_model.py).

Open loop: ``C̃`` is not the filter's own output but a pre-integrated attitude computed in
parallel (Eq. 25), so the whole window is processed without a sequential loop:

* ``raw``      C̃ from the raw gyro (the paper's version);
* ``denoised`` C̃ from the calibrated gyro ω̂_gyr;
* ``two_pass`` a second open-loop pass: e_acc/e_mag recomputed against the attitude of a
  first pass (denoised C̃ + corrections), which brings the correction closer to the
  closed-loop ECF.

Frames: vectors (B, N, 3) in the body frame; attitudes ``nav_from_body`` (B, N, 3, 3), ENU.
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor, nn

from .. import so3

PREINTEGRATIONS = ("raw", "denoised", "two_pass")


def unit_vector(v: Tensor) -> Tensor:
    # epsilon written inline: TorchScript (the exported modules reuse these functions) cannot
    # capture module-level floats
    return v / torch.linalg.norm(v, dim=-1, keepdim=True).clamp_min(1e-9)


def acc_error(acc: Tensor, nav_from_body: Tensor) -> Tensor:
    """Eq. 23: ``ĝ/|ĝ| × (C^T e_up)``. acc (..., 3) m/s^2, nav_from_body (..., 3, 3) -> (..., 3)."""
    up_pred = nav_from_body[..., 2, :]  # C^T [0,0,1] = third row of C
    return torch.cross(unit_vector(acc), up_pred, dim=-1)


def mag_error(mag: Tensor, acc_raw: Tensor, nav_from_body: Tensor) -> Tensor:
    """Eq. 24: ``east_b × (C^T e_east)`` with ``east_b = unit(b̂ × g')``.

    mag (..., 3) uT, acc_raw (..., 3) the raw accelerometer, nav_from_body (..., 3, 3)."""
    east_meas = unit_vector(torch.cross(mag, acc_raw, dim=-1))
    east_pred = nav_from_body[..., 0, :]  # C^T [1,0,0] = first row of C
    return torch.cross(east_meas, east_pred, dim=-1)


def previous_attitude(r0: Tensor, omega: Tensor, dt: Tensor) -> Tensor:
    """Pre-integrated attitude ``C̃_{k-1}`` for every sample k (Eq. 25), as a product of
    exponentials by parallel prefix (:func:`so3.integrate` -> :func:`so3.cumprod_matrix`).

    r0 (B, 3, 3), omega (B, N, 3), dt (B, N) -> (B, N, 3, 3) with entry k = attitude at k-1
    (entry 0 = r0)."""
    c = so3.integrate(r0, omega, dt)  # c[k] = attitude at sample k
    return torch.cat([r0.unsqueeze(-3), c[..., :-1, :, :]], -3)


class OpenLoopECF(nn.Module):
    """Eq. 22 with trainable per-axis gains γ (accelerometer) and η (magnetometer), 1/s.

    Gains start at ``init_gain`` (0.05 1/s, a 20 s time constant): small enough that the
    untrained model stays close to gyro integration over a training window (the open-loop
    correction is not self-limiting, so a large initial gain could dominate the first steps),
    large enough for gradients to reach them immediately. They are learned without weight decay.
    """

    def __init__(self, use_acc: bool = True, use_mag: bool = True, init_gain: float = 0.05,
                 preintegration: str = "two_pass"):
        super().__init__()
        if preintegration not in PREINTEGRATIONS:
            raise ValueError(f"preintegration {preintegration!r}: expected one of {PREINTEGRATIONS}")
        self.use_acc = use_acc
        self.use_mag = use_mag
        self.preintegration = preintegration
        self.acc_gain = nn.Parameter(torch.full((3,), float(init_gain))) if use_acc else None
        self.mag_gain = nn.Parameter(torch.full((3,), float(init_gain))) if use_mag else None

    def correction(self, c_prev: Tensor, acc: Tensor, mag: Optional[Tensor], acc_raw: Tensor):
        """(γ e_acc + η e_mag, e_acc, e_mag) against the attitudes c_prev (B, N, 3, 3)."""
        corr = acc.new_zeros(acc.shape)
        e_acc = e_mag = None
        if self.acc_gain is not None:
            e_acc = acc_error(acc, c_prev)
            corr = corr + self.acc_gain * e_acc
        if self.mag_gain is not None and mag is not None:
            e_mag = mag_error(mag, acc_raw, c_prev)
            corr = corr + self.mag_gain * e_mag
        return corr, e_acc, e_mag

    def forward(self, gyro: Tensor, acc: Tensor, mag: Optional[Tensor], gyro_raw: Tensor,
                acc_raw: Tensor, r0: Tensor, dt: Tensor):
        """Corrected rate ω̂ (B, N, 3) and the innovations.

        gyro: ω̂_gyr (B, N, 3); acc: ĝ; mag: b̂ or None; gyro_raw, acc_raw: raw readings;
        r0: (B, 3, 3) attitude at the first sample; dt: (B, N) s.
        Returns (omega, e_acc or None, e_mag or None)."""
        if self.preintegration == "raw":
            base = gyro_raw.detach()
        else:
            base = gyro
        c_prev = previous_attitude(r0, base, dt)
        corr, e_acc, e_mag = self.correction(c_prev, acc, mag, acc_raw)
        omega = gyro + corr
        if self.preintegration == "two_pass":
            c_prev = previous_attitude(r0, omega, dt)
            corr, e_acc, e_mag = self.correction(c_prev, acc, mag, acc_raw)
            omega = gyro + corr
        return omega, e_acc, e_mag
