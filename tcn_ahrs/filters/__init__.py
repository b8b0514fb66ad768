"""Classical attitude filters in pure torch (tensors in, tensors out), batched.

Every filter takes ``(..., N, 3)`` sensor tensors, ``(..., N)`` time steps, a ``(..., 4)``
initial attitude and parameters broadcastable to the batch shape, so one call runs many
recordings x many parameter sets; float64 by default. See :mod:`tcn_ahrs.estimators.classical`
for the :class:`~tcn_ahrs.estimators.base.Estimator` wrappers.
"""
from .common import magnetic_from_nav, quat_from_accel, triad_quat
from .ecf import ecf
from .eskf import chi2_threshold, eskf
from .madgwick import madgwick
from .mahony import mahony

__all__ = ["ecf", "mahony", "madgwick", "eskf", "chi2_threshold", "triad_quat", "quat_from_accel",
           "magnetic_from_nav"]
