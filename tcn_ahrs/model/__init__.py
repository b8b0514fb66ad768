"""The learned AHRS: TCN calibration + differentiable open-loop ECF."""
from .ahrs import LearnedAHRS
from .calibration import Calibration
from .open_loop import OpenLoopECF
from .tcn import TCN

__all__ = ["LearnedAHRS", "Calibration", "OpenLoopECF", "TCN"]
