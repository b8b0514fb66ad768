"""``model:`` — :class:`~tcn_ahrs.model.ahrs.LearnedAHRS` (conf/model/*.yaml). Defaults: the
project's default model (conf/model/ahrs.yaml: TCN calibration + learned closed loop)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional


@dataclass
class TCNConfig:
    """``model.tcn``: the calibration networks (:class:`~tcn_ahrs.model.tcn.TCN`)."""
    channels: List[int] = field(default_factory=lambda: [16, 16, 32, 32])  # per dilated layer; 41 k parameters (9-axis)
    kernel_size: int = 7
    dilations: List[int] = field(default_factory=lambda: [1, 4, 16, 64])  # receptive field 1 + 6 * 85 = 511 >= 448
    dropout: float = 0.1


#: The paper's TCN (16-32-64-128 channels; 245 k parameters 9-axis): conf/model/paper.yaml
PAPER_CHANNELS = [16, 32, 64, 128]


@dataclass
class ClosedLoopConfig:
    """``model.closed_loop``: the learned closed loop's initial gains (trainable) and rest detector
    (:class:`~tcn_ahrs.model.closed_loop.ClosedLoopFilter`)."""
    acc_gain: float = 0.3            # 1/s
    mag_gain: float = 0.1            # 1/s
    bias_gain: float = 0.003         # 1/s^2, integral term
    rest_time_constant: float = 2.0  # s, bias update at rest
    rest_time: float = 1.5           # s, rest detector window
    rest_gyro: float = 0.0349        # rad/s (2 deg/s) deviation from the window mean
    rest_acc: float = 0.5            # m/s^2
    acc_reject: float = 0.0          # m/s^2: no correction while | |a| - g | >= this (0: off)
    mag_min: float = 0.0             # uT: no heading correction below (0: off)
    mag_max: float = 0.0             # uT: ... or above (0: off)


@dataclass
class ErrorScaleConfig:
    """``model.error_scale``: network output (O(1)) -> physical error size."""
    gyro: float = 0.02  # rad/s
    acc: float = 1.0    # m/s^2
    mag: float = 1.0    # uT


@dataclass
class ResidualConfig:
    """``model.residual`` (``loop: backbone``): learned residuals on the VQF-grade backbone
    (:mod:`tcn_ahrs.model.residual`)."""
    gyro_scale: float = 0.1        # rad/s, bound of the gyro residual the network learns (tanh)
    gyro_clip: float = 0.0         # rad/s, bound of the part applied to the filter; 0: learned, not applied
    acc_trust_scale: float = 1.0   # multiplies 2 sigma(z_acc): 0 = no inclination correction
    mag_trust_scale: float = 1.0   # multiplies 2 sigma(z_mag): 0 = no heading correction
    bias_trust_scale: float = 1.0  # multiplies the backbone's bias increments: 0 = bias frozen
    trust_max: float = 2.0         # upper clip of 2 sigma(z)
    trust_weight: float = 0.5      # trust = 1 + w (2 sigma(z) - 1)
    bias_prior: float = 1.0        # multiplies the bias state's start: 0 = zero start
    # the learned accelerometer trust gates the bias update in motion: bias trust = bias_trust_scale
    # × (2 σ(z_acc) / trust_max)^p — where the network doubts the specific force is gravity alone,
    # the tilt error is the hand's acceleration, not the gyro's bias; 0: ungated (VQF's)
    bias_trust_power: float = 0.0
    backbone: Dict[str, float] = field(default_factory=dict)  # BackboneParams fields; {}: VQF's defaults


@dataclass
class ModelConfig:
    """``model:``. ``variant`` is a label saved with checkpoints; ``axes`` null: data.axes."""
    variant: str = "ahrs9"
    axes: Optional[int] = None
    gyro_net: str = "tcn"            # tcn | constant | none
    acc_net: str = "tcn"
    mag_net: str = "tcn"
    gyro_input: str = "all"          # all: gyro TCN sees every sensor (Eq. 15); gyro: gyro only (Fig. 10)
    use_acc_term: bool = True        # gamma * e_acc in Eq. 22
    use_mag_term: bool = True        # eta * e_mag in Eq. 22 (9-axis only)
    ecf: bool = True                 # false: plain integration of the calibrated gyro
    loop: str = "closed"             # closed | open (the paper's open-loop ECF) | backbone (residual)
    trust: Optional[bool] = None     # per-sample sensor trust from the networks (null: with the closed loop)
    closed_loop: ClosedLoopConfig = field(default_factory=ClosedLoopConfig)
    preintegration: str = "two_pass"  # open loop only: raw (Eq. 25) | denoised | two_pass
    init_gain: float = 0.05          # open loop only: initial gamma, eta (1/s)
    error_scale: ErrorScaleConfig = field(default_factory=ErrorScaleConfig)
    tcn: TCNConfig = field(default_factory=TCNConfig)
    residual: Optional[ResidualConfig] = None  # loop: backbone only


#: Model keys that are optional in a YAML (present in some variants only).
MODEL_OPTIONAL = frozenset({"residual"})
LOOPS = ("open", "closed", "backbone")

#: The paper's model over the defaults (conf/model/paper.yaml: open-loop ECF, the paper's TCN):
#: ``LearnedAHRS(axes=9, **PAPER_MODEL)``
PAPER_MODEL = {"loop": "open", "tcn": {"channels": list(PAPER_CHANNELS), "kernel_size": 7,
                                       "dilations": [1, 4, 16, 64], "dropout": 0.1}}
