"""Navigation systems from the papers in ``../shared/papers`` (position, velocity and attitude),
built on the same pieces as the attitude filters: :mod:`tcn_ahrs.so3` for rotations and
:mod:`tcn_ahrs.filters.kalman` for the one Kalman update (Joseph form).

* :mod:`tcn_ahrs.nav.odometry` — IMU + wheel-encoder + magnetometer error-state EKF for a
  differential-drive robot without GNSS (paper ``es-ekf-imu-encoder-magnetometer``).
* :mod:`tcn_ahrs.nav.odometry_baselines` — that paper's EKF and UKF baselines over the same state
  and sensors (filterpy).
* :mod:`tcn_ahrs.nav.diff_drive` — the simulator of that paper's experiment (a Jackal-like robot
  in a mine-corridor route).

Each paper's experiment is :mod:`tcn_ahrs.reproduce` (``python scripts/reproduce.py paper=...``).

Frames and units as everywhere (:mod:`tcn_ahrs.conventions`): ENU navigation frame, body frame
x forward / z up, specific force +9.81 m/s² along up at rest, rad/s, m/s², µT, s.
"""
