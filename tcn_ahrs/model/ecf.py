"""Old name of :mod:`tcn_ahrs.model.open_loop` (the learned open-loop ECF of the paper), kept
while code outside it still imports from here (``model/ahrs.py``, ``tests/test_model.py``)."""
from .open_loop import (PREINTEGRATIONS, OpenLoopECF, _unit, acc_error, mag_error,  # noqa: F401
                        previous_attitude)
