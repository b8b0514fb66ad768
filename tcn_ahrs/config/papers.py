"""``paper:`` — each navigation paper's experiment options (conf/paper/<name>.yaml,
tcn_ahrs/reproduce/<name>.py). ``{}`` sections are overrides of the named simulator/filter
parameter structs (checked there)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List


@dataclass
class EsEkfOdometry:
    """ES-EKF vs EKF vs UKF (Table 2), APE by evo."""
    name: str = "es_ekf_odometry"
    seeds: int = 10                   # seeded runs of the paper scenario
    first_seed: int = 0
    robustness_seeds: int = 5         # runs of each robustness scenario
    scenarios: List[str] = field(default_factory=lambda: ["paper", "slip", "mag_disturbance", "dropouts"])
    rate: float = 20.0                # Hz, IMU / encoders / magnetometer
    length: float = 150.0             # m of corridor per run
    sensors: Dict[str, Any] = field(default_factory=dict)  # Sensors overrides (tcn_ahrs/nav/diff_drive.py)
    slip: float = 0.3                 # wheel speed over-read by 30 % ...
    slip_fraction: float = 0.05       # ... in 1 s bursts covering 5 % of the run
    anomalies_per_100m: float = 3.0   # local magnetic anomalies per 100 m ...
    anomaly_ut: float = 20.0          # ... of this peak field, uT
    dropout_windows: int = 2          # outages of the encoders and of the magnetometer ...
    dropout_min_s: float = 5.0        # ... each 5-30 s long
    dropout_max_s: float = 30.0
    workers: int = 2                  # processes for the filterpy EKF/UKF runs
    plots: bool = True


@dataclass
class KldParticleFilter:
    """KLD-sampling MCL in a simulated arena."""
    name: str = "kld_particle_filter"
    seed: int = 0
    laps: int = 20
    start: List[float] = field(default_factory=lambda: [0.4, 0.3, 0.0])  # x, y (m), heading (rad)
    rectangle: List[float] = field(default_factory=lambda: [1.2, 0.6])   # m
    kidnap_laps: int = 2
    kidnap_step: int = 300
    kidnap_pose: List[float] = field(default_factory=lambda: [2.5, 1.5, 2.0])
    cloud_step: int = 20
    alpha_slow: float = 0.001
    alpha_fast: float = 0.1
    scaling: List[int] = field(default_factory=lambda: [100, 1000, 10000, 100000, 1000000])
    threads: int = 1
    arena: Dict[str, Any] = field(default_factory=dict)    # Arena overrides (tcn_ahrs/nav/arena.py)
    scanner: Dict[str, Any] = field(default_factory=dict)  # Scanner overrides
    robot: Dict[str, Any] = field(default_factory=dict)    # Robot overrides
    filter: Dict[str, Any] = field(default_factory=dict)   # MclParams overrides (tcn_ahrs/nav/particle.py)
    plots: bool = True


@dataclass
class Flight:
    lat: float = 0.0      # deg
    lon: float = 0.0      # deg
    heading: float = 0.0  # deg clockwise from north


@dataclass
class PolarInsGnss:
    """Polar INS/GNSS: n -> G frame switch."""
    name: str = "polar_ins_gnss"
    seeds: int = 6
    first_seed: int = 0
    hours: float = 2.0          # flight length
    switch_h: float = 0.5       # n -> G switch
    nav_rate: float = 20.0      # Hz
    flights: Dict[str, Flight] = field(default_factory=lambda: {
        "mid_latitude": Flight(45.0, 110.0, 30.0), "polar_80": Flight(79.0, -30.0, 80.0),
        "pole": Flight(85.0, 20.0, 0.0)})
    pole_hours: float = 1.5
    pole_seeds: int = 2
    imu: Dict[str, Any] = field(default_factory=dict)    # ImuGrade overrides (tcn_ahrs/nav/polar_sim.py)
    noise: Dict[str, Any] = field(default_factory=dict)  # InsNoise overrides (tcn_ahrs/nav/ins.py)
    plots: bool = True


@dataclass
class UwbArckf:
    """UWB/IMU adaptive robust CKF (Tables 4, 6) and the scenarios beyond the paper."""
    name: str = "uwb_arckf"
    seeds: int = 10
    first_seed: int = 0
    outliers: List[int] = field(default_factory=lambda: [1, 2, 3, 4])
    contaminated: List[float] = field(default_factory=lambda: [0.03, 0.05, 0.07, 0.10])
    paper_threshold: float = 6.2     # the chi-square threshold the paper prints ...
    gate_alpha: float = 0.001        # ... and the alpha it says it is
    noise: Dict[str, Dict[str, Any]] = field(default_factory=lambda: {
        "paper": {}, "datasheet": {"from_setup": True, "accel_bias_walk": 0.001, "gyro_bias_walk": 0.0001}})
    laps: int = 2
    setup: Dict[str, Any] = field(default_factory=dict)  # UwbSetup overrides (tcn_ahrs/nav/uwb_sim.py)
    beyond: bool = True
    nlos_bias: List[float] = field(default_factory=lambda: [0.5, 3.0])  # m
    beacon_heights: List[float] = field(default_factory=lambda: [0.5, 2.5, 1.2, 3.0])  # m
    # (beacon index, start s, length s)
    dropouts: List[List[Any]] = field(default_factory=lambda: [[0, 20.0, 15.0], [1, 60.0, 10.0], [2, 60.0, 10.0]])
    burst_len: int = 10
    plots: bool = True


#: conf/paper/<name>.yaml -> its schema
PAPERS = {c().name: c for c in (EsEkfOdometry, KldParticleFilter, PolarInsGnss, UwbArckf)}
