"""tcn-ahrs: learned IMU calibration (TCN) + differentiable open-loop ECF on SO(3)."""
from . import numba_cache
from .sequence import DataError, ImuSequence

numba_cache.configure()  # before any kernel is compiled: a changed source never runs stale code

__all__ = ["ImuSequence", "DataError"]
__version__ = "0.1.0"
