"""The ES-EKF robust variants measured on the reproduce command's five mag_disturbance runs
(seeds 0-4, 150 m, 3 anomalies per 100 m of 20 uT): horizontal APE RMSE per run, metres.

    python docs/results/es_ekf_odometry_variants.py     # ~2 min on 2 CPU cores

Output on 2026-12-02 (2-core CPU):

    paper                                mean  3.039  per run [7.318 1.483 0.991 2.582 2.819]
    gate (hard rejection)                mean  0.402  per run [0.825 0.287 0.193 0.273 0.431]
    gate + Algorithm 1 (plausibility)    mean  0.777  per run [1.254 1.395 0.196 0.288 0.751]
    gate + v_z row (shipped robust)      mean  0.402  per run [0.825 0.287 0.193 0.273 0.431]
    gate + v_z row + bias states         mean  4.656  per run [21.949  0.319  0.225  0.324  0.464]
"""
import numpy as np
import torch

from tcn_ahrs.nav.diff_drive import Sensors, simulate_drive
from tcn_ahrs.nav.odometry import OdometryNoise, mag_plausible, odometry_eskf
from tcn_ahrs.reproduce.es_ekf_odometry import _pad

sims = [simulate_drive(s, rate=20.0, length=150.0, sensors=Sensors(anomalies_per_100m=3.0, anomaly_ut=20.0))
        for s in range(5)]
n = max(len(s["time"]) for s in sims)
T = lambda k: torch.as_tensor(np.stack([_pad(s[k], n) for s in sims]))  # noqa: E731
dt = torch.full((len(sims), n), 0.05, dtype=torch.float64)
field_ok = mag_plausible(T("acc"), T("mag"), 20.0)
variants = [
    ("paper", OdometryNoise(), None),
    ("gate (hard rejection)", OdometryNoise(mag_gate_alpha=1e-3), None),
    ("gate + Algorithm 1 (plausibility)", OdometryNoise(mag_gate_alpha=1e-3), field_ok),
    ("gate + v_z row (shipped robust)", OdometryNoise(mag_gate_alpha=1e-3, vel_z=0.01), None),
    ("gate + v_z row + bias states", OdometryNoise(mag_gate_alpha=1e-3, vel_z=0.01, estimate_biases=True), None),
]
for name, noise, ok in variants:
    out = odometry_eskf(T("acc"), T("gyro"), dt, T("v_left"), T("v_right"), T("mag_quat"), T("pos")[:, 0],
                        T("vel")[:, 0], T("quat")[:, 0], noise=noise, mag_field_ok=ok)
    h = [np.sqrt(np.mean(np.sum((out["pos"][i, :len(s["time"]), :2].numpy() - s["pos"][:, :2]) ** 2, 1)))
         for i, s in enumerate(sims)]
    print(f"{name:<36s} mean {np.mean(h):6.3f}  per run {np.round(h, 3)}")
