#!/usr/bin/env python
"""Recordings of one simulated device, in the generic format, for ``tcn-ahrs search data=generic``.

    python scripts/simulated_device.py DIR [--n 6] [--seconds 60] [--profile drone] [--rate 100]
        [--gyro-bias-dps 5] [--bias-repeatability-dps 0] [--g-sensitivity-dps 0] [--device-seed 5]

Writes ``DIR/rec<i>.csv`` (t, gyro rad/s, accelerometer m/s², ground-truth quaternion w,x,y,z; 6 axes):
the same device (``device_seed``) in every recording, each with its own motion (seed 10 + i). The
devices of docs/results.md's "Learning inside the search": a 5 °/s gyro bias varying by 3 °/s per
recording (``--bias-repeatability-dps 3``, walking), and a g-sensitive gyro on a drone
(``--g-sensitivity-dps 3``: the reading moves by G f / g with the specific force f,
:class:`tcn_ahrs.datasets.simulate.SensorErrorModel`).
"""
import argparse
from pathlib import Path

import numpy as np

from tcn_ahrs.datasets.simulate import PROFILES, simulate

HEADER = "t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,quat_w,quat_x,quat_y,quat_z"


def write_device(root: Path, n: int = 6, seconds: float = 60.0, profile: str = "drone", rate: float = 100.0,
                 gyro_bias_dps: float = 5.0, bias_repeatability_dps: float = 0.0, g_sensitivity_dps: float = 0.0,
                 device_seed: int = 5) -> list:
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        s = simulate(profile, seconds, rate, seed=10 + i, device_seed=device_seed, axes=6,
                     gyro_bias_range_dps=(gyro_bias_dps, gyro_bias_dps + 0.1),
                     gyro_bias_repeatability_dps=bias_repeatability_dps, gyro_bias_rw_dps=0.0,
                     gyro_g_sensitivity_dps=g_sensitivity_dps)
        path = root / f"rec{i}.csv"
        np.savetxt(path, np.column_stack([s.time, s.gyro, s.accel, s.quat]), delimiter=",", comments="",
                   fmt="%.10g", header=HEADER)
        paths.append(path)
    return paths


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("root")
    ap.add_argument("--n", type=int, default=6)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--profile", choices=PROFILES, default="drone")
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--gyro-bias-dps", type=float, default=5.0)
    ap.add_argument("--bias-repeatability-dps", type=float, default=0.0)
    ap.add_argument("--g-sensitivity-dps", type=float, default=0.0)
    ap.add_argument("--device-seed", type=int, default=5)
    a = ap.parse_args(argv)
    paths = write_device(a.root, a.n, a.seconds, a.profile, a.rate, a.gyro_bias_dps, a.bias_repeatability_dps,
                         a.g_sensitivity_dps, a.device_seed)
    print(f"{len(paths)} recordings of one simulated device in {a.root}")


if __name__ == "__main__":
    main()
