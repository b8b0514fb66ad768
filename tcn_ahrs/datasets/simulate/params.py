"""The simulator's parameters: the sensor error model (paper Eqs. 9-11) and the environment."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Mapping, Tuple

import numpy as np

from ...conventions import DEG


# =============================================================================
# Parameters
# =============================================================================


@dataclass
class SensorErrorModel:
    """Error parameters of the simulated MEMS IMU (paper Eqs. 9-11). Magnitudes are typical of
    consumer MEMS IMUs (e.g. BMI160 / MPU-9250 / myon aktos-t of BROAD).

    "device" parameters are drawn once from ``device_seed`` (the same physical sensor in every
    recording); "repeatability"/"recording" parameters are drawn per recording from its seed.
    White-noise densities convert to a per-sample standard deviation ``density * sqrt(rate)``;
    random-walk densities give a per-step increment ``rw * sqrt(dt)``.

    Gyroscope:
        gyro_scale_std:             std of the diagonal of K_gyr - I (scale-factor error), device. [-]
        gyro_misalignment_std:      std of the off-diagonal entries of K_gyr (axis misalignment), device. [rad]
        gyro_bias_range_dps:        per-axis static bias magnitude of the device, uniform in
                                    (lo, hi) with random sign (BROAD-like 0.1-0.5 deg/s). [deg/s]
        gyro_bias_repeatability_dps: per-recording (turn-on) bias offset std. [deg/s]
        gyro_bias_rw_dps:           bias random walk. [deg/s/sqrt(s)]
        gyro_noise_density_dps:     white noise density. [deg/s/sqrt(Hz)]
        gyro_g_sensitivity_dps:     std of the entries of G, the gyro's g-sensitivity (its reading moves
                                    by G f / g with the specific force f), device; 0: none. [deg/s per g]
    Accelerometer:
        acc_scale_std, acc_misalignment_std: as for the gyro, K_acc. [-], [rad]
        acc_bias_std:               per-axis static bias of the device (std). [m/s^2]
        acc_bias_repeatability:     per-recording bias offset std. [m/s^2]
        acc_bias_rw:                bias random walk. [m/s^2/sqrt(s)]
        acc_noise_density:          white noise density (0.002 = ~200 ug/sqrt(Hz)). [m/s^2/sqrt(Hz)]
    Magnetometer:
        mag_scale_std, mag_misalignment_std: soft iron (diagonal / off-diagonal of K_mag). [-]
        hard_iron_std_ut:           per-axis hard-iron offset of the device (std). [uT]
        hard_iron_repeatability_ut: per-recording hard-iron variation std. [uT]
        mag_noise_density_ut:       white noise density. [uT/sqrt(Hz)]
    All sensors:
        recording_k_std:            per-recording std added to every entry of each K. [-]
    """

    gyro_scale_std: float = 0.01
    gyro_misalignment_std: float = 0.005
    gyro_bias_range_dps: Tuple[float, float] = (0.1, 0.5)
    gyro_bias_repeatability_dps: float = 0.03
    gyro_bias_rw_dps: float = 0.002
    gyro_noise_density_dps: float = 0.01
    gyro_g_sensitivity_dps: float = 0.0

    acc_scale_std: float = 0.01
    acc_misalignment_std: float = 0.005
    acc_bias_std: float = 0.05
    acc_bias_repeatability: float = 0.01
    acc_bias_rw: float = 0.0005
    acc_noise_density: float = 0.002

    mag_scale_std: float = 0.05
    mag_misalignment_std: float = 0.03
    hard_iron_std_ut: float = 10.0
    hard_iron_repeatability_ut: float = 0.5
    mag_noise_density_ut: float = 0.03

    recording_k_std: float = 0.001


@dataclass
class Environment:
    """Where the simulated IMU lives.

    field_ut:        Earth magnetic field strength. [uT]
    dip_deg:         inclination (positive: field points down, northern hemisphere). [deg]
    declination_deg: magnetic north east of true (ENU) north. [deg]
    mag_disturbances_per_minute: number of transient magnetic disturbances per minute of
                     recording (rounded; placed after the initial rest). 0 disables them.
    mag_disturbance_peak_ut: peak added field, uniform in (lo, hi). [uT]
    mag_disturbance_tau_s: time constant of a dipole pass-by, uniform in (lo, hi): the added field
                     is ~ (1 + ((t - t_c)/tau)^2)^(-3/2) (a magnet at closest distance d passed at
                     speed v = d/tau), cut at |t - t_c| = 3 tau. [s]
    """

    field_ut: float = 49.0
    dip_deg: float = 65.0
    declination_deg: float = 0.0
    mag_disturbances_per_minute: float = 1.0
    mag_disturbance_peak_ut: Tuple[float, float] = (10.0, 50.0)
    mag_disturbance_tau_s: Tuple[float, float] = (0.5, 2.0)

    def field_nav(self) -> np.ndarray:
        """(3,) Earth field in ENU, uT: north and (for positive dip) down."""
        inc, dec = self.dip_deg * DEG, self.declination_deg * DEG
        h = self.field_ut * math.cos(inc)
        return np.array([h * math.sin(dec), h * math.cos(dec), -self.field_ut * math.sin(inc)])


def split_params(params: Mapping[str, Any]) -> Tuple[SensorErrorModel, Environment]:
    """Route keyword overrides to :class:`SensorErrorModel` / :class:`Environment` fields."""
    sens_keys = {f.name for f in dataclasses.fields(SensorErrorModel)}
    env_keys = {f.name for f in dataclasses.fields(Environment)}
    unknown = sorted(set(params) - sens_keys - env_keys)
    if unknown:
        raise TypeError(f"simulate: unknown error/environment parameter(s) {unknown}; expected fields of "
                        f"SensorErrorModel {sorted(sens_keys)} or Environment {sorted(env_keys)}")
    def conv(v):
        return tuple(v) if isinstance(v, (list, tuple)) else v
    sens = SensorErrorModel(**{k: conv(v) for k, v in params.items() if k in sens_keys})
    env = Environment(**{k: conv(v) for k, v in params.items() if k in env_keys})
    return sens, env
