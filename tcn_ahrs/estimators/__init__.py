"""Attitude estimators under one interface (see :mod:`tcn_ahrs.estimators.base`)."""
from .base import Estimator, EstimatorOutput, initial_quat

__all__ = ["Estimator", "EstimatorOutput", "initial_quat"]
