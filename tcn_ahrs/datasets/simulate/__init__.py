"""IMU simulator: the embedded default dataset (nothing to download).

Recordings with *exact* ground truth, generated from the sensor error model of the paper
(Eqs. 9-11), in the project's conventions (:mod:`tcn_ahrs.conventions`: ENU, ``nav_from_body``
Hamilton quaternions (w,x,y,z), specific force +9.81 up at rest, rad/s, m/s^2, uT, s)::

    y_gyr,k = K_gyr w_k + b_gyr,k + v_gyr,k                                  (Eq. 9)
    y_acc,k = K_acc R_k^T (a_nav(t_k) + [0, 0, 9.81]) + b_acc,k + v_acc,k    (Eq. 10)
    y_mag,k = K_mag R_k^T (m_nav + d_nav(t_k)) + h_hard + v_mag,k            (Eq. 11)

* ``w_k`` is the true body angular rate, constant over the step ``(t_{k-1}, t_k]``; the ground
  truth is its exact product of exponentials ``R_k = R_0 exp(w_1 dt) ... exp(w_k dt)`` (the
  convention of :func:`tcn_ahrs.so3.integrate`), so integrating the noise-free gyro reproduces
  the ground truth to round-off.
* ``a_nav`` is the kinematic acceleration: the analytic derivative of a smooth velocity
  trajectory (``true_vel_nav`` in ``meta``); the paper's external acceleration ``a_k`` is
  ``R_k^T a_nav`` (``true_ext_acc``).
* The paper's magnetic distortion ``d_k`` is split into the sensor's hard iron ``h_hard``
  (with soft iron inside ``K_mag``) and transient external fields ``d_nav`` near "magnets"
  (``true_mag_disturbance = R_k^T d_nav`` in the body frame, before ``K_mag``).
* Biases: a per-*device* static mean (fixed by ``device_seed``), a per-recording turn-on
  offset, and a random walk. ``K`` matrices: per-device scale factor + misalignment plus a
  small per-recording variation, so a learned calibration transfers to held-out recordings.

Motion profiles (all start with 5-10 s of rest and end with 1-3 s of rest, move in segments of
15-45 s separated by 2-5 s rest breaks, and are defined in continuous time, so the same seed
gives the same motion at any rate, up to the piecewise-constant sampling of the rate):

* ``static``: rest for the whole recording.
* ``slow_rotation`` / ``fast_rotation``: body rate = sums of random sinusoids per axis
  (RMS ~25 deg/s, 0.05-0.5 Hz / ~150 deg/s, 0.2-1.5 Hz) plus small translations.
* ``walking``: hand-held phone while walking (1.0-1.5 m/s, step frequency 1.6-2.0 Hz with
  vertical bounce, surge and lateral sway of a few m/s^2, hand sway of a few degrees) with
  heading turns of 45-180 deg.
* ``drone``: smooth horizontal position trajectory; the attitude tilts so that the body z
  axis follows the thrust ``a_nav + g`` (accelerations of ~2 m/s^2 RMS, tilts ~10-25 deg),
  with slowly varying yaw.

Public API: :func:`simulate`, :class:`SensorErrorModel`, :class:`Environment`,
:func:`load_split`, :func:`split_plan`, :func:`list_recordings`, :data:`PROFILES`;
``python -m tcn_ahrs.datasets.simulate --benchmark`` measures the generation speed.
Sequences are built with ``check_units=False`` (units are right by construction and the tests
re-validate them with the heuristics on; those would cost more than the generation).
"""
from __future__ import annotations

from .generate import (EXT_ACC_FLAG_THRESHOLD, MAG_FLAG_THRESHOLD_UT, PROFILES, SPLITS, Environment,  # noqa: F401
                       SensorErrorModel, cumprod_quat, simulate)
from .splits import list_recordings, load_split, split_plan

__all__ = ["simulate", "SensorErrorModel", "Environment", "load_split", "split_plan", "list_recordings",
           "PROFILES", "EXT_ACC_FLAG_THRESHOLD", "MAG_FLAG_THRESHOLD_UT", "cumprod_quat"]
