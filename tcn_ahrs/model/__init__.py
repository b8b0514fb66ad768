"""The learned AHRS: TCN calibration + differentiable open-loop ECF."""
