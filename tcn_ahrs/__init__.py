"""tcn-ahrs: learned IMU calibration (TCN) + differentiable open-loop ECF on SO(3)."""
from .sequence import DataError, ImuSequence

__all__ = ["ImuSequence", "DataError"]
__version__ = "0.1.0"
