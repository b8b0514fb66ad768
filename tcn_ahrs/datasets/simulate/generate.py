"""The simulator's recordings (:func:`simulate`): the package docstring (:mod:`tcn_ahrs.datasets.simulate`)
says what they hold."""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Dict

import numpy as np

from ...conventions import DEG, GRAVITY
from ...sequence import ImuSequence
from .motion import PROFILE_FNS
from .params import Environment, SensorErrorModel, split_params
from .quat import qexp, qmatrix, to_body, cumprod_quat
from .sensors import bias_track, draw_device, mag_disturbance

PROFILES = ("static", "slow_rotation", "fast_rotation", "walking", "drone")
"""Names of the motion profiles :func:`simulate` accepts."""

EXT_ACC_FLAG_THRESHOLD = 0.5
"""m/s^2: ``meta['acc_disturbed']`` is True where ``|a_nav| >`` this."""

MAG_FLAG_THRESHOLD_UT = 1.0
"""uT: ``meta['mag_disturbed']`` is True where the added external field exceeds this."""

SPLITS = {"train": ("train",), "val": ("val",), "test": ("test",),
          "trainval": ("train", "val"), "all": ("train", "val", "test")}




def _sensor_errors(noise_free: bool, device_seed: int, sens, envp, rngs, t: np.ndarray, rate: float,
                   moving: np.ndarray, duration: float) -> Dict[str, Any]:
    """The recording's sensor errors (Eqs. 9-11): K matrices, bias tracks, white noise, hard iron
    and the magnetic disturbance in the navigation frame; all zero / identity when ``noise_free``.
    ``rngs``: the sensor, noise and disturbance streams of :func:`simulate`, drawn in this order."""
    n = t.shape[0]
    if noise_free:
        eye, zeros = np.eye(3), np.zeros((n, 3))
        return {"k_gyro": eye, "k_acc": eye, "k_mag": eye, "gyro_bias": zeros, "acc_bias": zeros.copy(),
                "g_sens": np.zeros((3, 3)),
                "hard_iron": np.zeros(3), "d_nav": zeros.copy(), "gyro_noise": 0.0, "acc_noise": 0.0,
                "mag_noise": 0.0, "b_g0": np.zeros(3), "b_a0": np.zeros(3)}
    rng_sensor, rng_noise, rng_dist = rngs
    dt = 1.0 / rate
    dev = draw_device(device_seed, sens)
    rk = sens.recording_k_std
    k_gyro = dev.k_gyro + rng_sensor.normal(0.0, rk, (3, 3))
    k_acc = dev.k_acc + rng_sensor.normal(0.0, rk, (3, 3))
    k_mag = dev.k_mag + rng_sensor.normal(0.0, rk, (3, 3))
    b_g0 = dev.gyro_bias + rng_sensor.normal(0.0, sens.gyro_bias_repeatability_dps * DEG, 3)
    b_a0 = dev.acc_bias + rng_sensor.normal(0.0, sens.acc_bias_repeatability, 3)
    hard_iron = dev.hard_iron + rng_sensor.normal(0.0, sens.hard_iron_repeatability_ut, 3)
    unit = rng_noise.standard_normal((5, n, 3))  # one draw: bias walks, then white noise
    gyro_bias = bias_track(unit[0], dt, b_g0, sens.gyro_bias_rw_dps * DEG)
    acc_bias = bias_track(unit[1], dt, b_a0, sens.acc_bias_rw)
    sq = math.sqrt(rate)
    gyro_noise = unit[2] * (sens.gyro_noise_density_dps * DEG * sq)
    acc_noise = unit[3] * (sens.acc_noise_density * sq)
    mag_noise = unit[4] * (sens.mag_noise_density_ut * sq)
    rest_end = float(t[np.argmax(moving)]) if moving.any() else 0.0
    d_nav = mag_disturbance(rng_dist, t, envp, not_before=max(rest_end, min(10.0, 0.2 * duration)))
    return {"k_gyro": k_gyro, "k_acc": k_acc, "k_mag": k_mag, "gyro_bias": gyro_bias, "acc_bias": acc_bias,
            "g_sens": dev.gyro_g_sens, "hard_iron": hard_iron, "d_nav": d_nav, "gyro_noise": gyro_noise, "acc_noise": acc_noise,
            "mag_noise": mag_noise, "b_g0": b_g0, "b_a0": b_a0}


def simulate(profile: str, duration: float, rate: float, seed: int, axes: int = 9,
             noise_free: bool = False, device_seed: int = 0, **error_params) -> ImuSequence:
    """Simulate one IMU recording with exact ground truth.

    Args:
        profile:     one of :data:`PROFILES` (``static``, ``slow_rotation``, ``fast_rotation``,
                     ``walking``, ``drone``).
        duration:    seconds (N = round(duration * rate) + 1 samples, t_k = k / rate).
        rate:        sampling rate, Hz (any; the motion is defined in continuous time).
        seed:        recording seed: motion, per-recording errors, noise, disturbances.
        axes:        9 (gyro, accel, mag) or 6 (``mag`` is None).
        noise_free:  identity K, no bias, no noise, no hard iron, no magnetic disturbances
                     (the motion and its external acceleration stay).
        device_seed: the simulated physical sensor: fixes K matrices, static bias means and
                     hard iron (the same in every recording with this device seed).
        **error_params: overrides of :class:`SensorErrorModel` and :class:`Environment`
                     fields (e.g. ``gyro_noise_density_dps=0.0``, ``mag_disturbances_per_minute=2``).

    Returns:
        :class:`ImuSequence` named ``sim_<profile>_s<seed:04d>`` with ground truth ``quat``
        valid everywhere and ``meta``: ``profile, seed, device_seed, noise_free,
        error_model (dict), environment (dict), K_gyro, K_acc, K_mag (3,3),
        gyro_bias_static, acc_bias_static (3,) (this recording's turn-on bias), hard_iron (3,),
        mag_field_nav (3,)``, and per sample ``true_gyro (N,3)`` rad/s, ``true_gyro_bias (N,3)``
        rad/s, ``true_acc_bias (N,3)``, ``true_ext_acc (N,3)`` body-frame kinematic acceleration,
        ``true_acc_nav, true_vel_nav (N,3)`` ENU, ``true_mag_disturbance (N,3)`` uT body frame
        (added external field before K_mag), ``mag_disturbed, acc_disturbed, moving (N,)`` bool.
    """
    if profile not in PROFILE_FNS:
        raise ValueError(f"simulate: unknown profile {profile!r}; expected one of {list(PROFILES)}")
    if axes not in (6, 9):
        raise ValueError(f"simulate: axes must be 6 or 9, got {axes!r}")
    if not rate > 0 or not duration > 0:
        raise ValueError(f"simulate: expected rate > 0 Hz and duration > 0 s, got rate={rate!r}, "
                         f"duration={duration!r}")
    sens, envp = split_params(error_params)
    seed = int(seed)
    rate = float(rate)
    dt = 1.0 / rate
    n = int(round(duration * rate)) + 1
    t = np.arange(n, dtype=np.float64) * dt

    # independent streams: the motion does not change when error parameters change
    ss = np.random.SeedSequence([seed, 0x51A7])
    rng_motion, rng_sensor, rng_noise, rng_dist = (np.random.default_rng(s) for s in ss.spawn(4))

    omega, q0, vel_nav, acc_nav, moving = PROFILE_FNS[profile](rng_motion, t, dt, float(duration))

    # Ground truth: exact product of exponentials of the piecewise-constant true rate (Eq. 3):
    # q_k = q_0 exp(w_1 dt) ... exp(w_k dt); the first rate sample is not applied.
    inc = qexp(omega * dt)
    inc[0] = q0
    quat = cumprod_quat(inc)
    r = qmatrix(quat)

    ext_acc_body = to_body(r, acc_nav)
    spec_force = ext_acc_body + GRAVITY * r[:, 2, :]  # R^T (a + g up): third row of R
    m_nav = envp.field_nav()

    e = _sensor_errors(noise_free, device_seed, sens, envp, (rng_sensor, rng_noise, rng_dist), t, rate, moving,
                       float(duration))
    k_gyro, k_acc, k_mag, hard_iron, d_nav = e["k_gyro"], e["k_acc"], e["k_mag"], e["hard_iron"], e["d_nav"]
    gyro_bias, acc_bias, b_g0, b_a0 = e["gyro_bias"], e["acc_bias"], e["b_g0"], e["b_a0"]
    gyro_noise, acc_noise, mag_noise = e["gyro_noise"], e["acc_noise"], e["mag_noise"]

    gyro = omega @ k_gyro.T + gyro_bias + gyro_noise                            # Eq. 9
    if np.any(e["g_sens"]):  # g-sensitivity: a MEMS gyro's reading moves with the specific force
        gyro = gyro + spec_force @ e["g_sens"].T / GRAVITY
    accel = spec_force @ k_acc.T + acc_bias + acc_noise                         # Eq. 10
    mag_dist_body = np.zeros((n, 3))
    hit = np.any(d_nav != 0.0, axis=1)
    mag_dist_body[hit] = to_body(r[hit], d_nav[hit])
    mag = None
    if axes == 9:
        mag = (to_body(r, m_nav) + mag_dist_body) @ k_mag.T + hard_iron + mag_noise  # Eq. 11

    meta: Dict[str, Any] = {
        "profile": profile, "seed": seed, "device_seed": int(device_seed), "noise_free": bool(noise_free),
        "error_model": dataclasses.asdict(sens), "environment": dataclasses.asdict(envp),
        "K_gyro": k_gyro, "K_acc": k_acc, "K_mag": k_mag, "gyro_g_sensitivity": e["g_sens"],
        "gyro_bias_static": b_g0, "acc_bias_static": b_a0, "hard_iron": hard_iron,
        "mag_field_nav": m_nav,
        # ground truth is ENU with geographic north; it is magnetic north only without declination
        "heading_reference": "magnetic_north" if envp.declination_deg == 0 else "true_north",
        "true_gyro": omega, "true_gyro_bias": gyro_bias, "true_acc_bias": acc_bias,
        "true_ext_acc": ext_acc_body, "true_acc_nav": acc_nav, "true_vel_nav": vel_nav,
        "true_mag_disturbance": mag_dist_body,
        "mag_disturbed": np.linalg.norm(d_nav, axis=1) > MAG_FLAG_THRESHOLD_UT,
        "acc_disturbed": np.linalg.norm(acc_nav, axis=1) > EXT_ACC_FLAG_THRESHOLD,
        "moving": moving,
    }
    return ImuSequence(
        name=f"sim_{profile}_s{seed:04d}",
        source=f"simulator(seed={seed}, profile={profile}, device_seed={int(device_seed)})",
        time=t, gyro=gyro, accel=accel, mag=mag,
        quat=quat, quat_valid=np.ones(n, dtype=bool), score_mask=None,
        rate=rate, meta=meta,
        # units are right by construction (tests re-validate with the unit heuristics on);
        # the heuristics' rest detection would cost more than generating the data
        check_units=False,
    )
