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

import argparse
import dataclasses
import math
import time as _time
from dataclasses import dataclass
from typing import Any, Dict, List, Mapping, Optional, Tuple

import numpy as np

from ..conventions import DEG, GRAVITY
from ..sequence import ImuSequence

PROFILES = ("static", "slow_rotation", "fast_rotation", "walking", "drone")
"""Names of the motion profiles :func:`simulate` accepts."""

EXT_ACC_FLAG_THRESHOLD = 0.5
"""m/s^2: ``meta['acc_disturbed']`` is True where ``|a_nav| >`` this."""

MAG_FLAG_THRESHOLD_UT = 1.0
"""uT: ``meta['mag_disturbed']`` is True where the added external field exceeds this."""

SPLITS = {"train": ("train",), "val": ("val",), "test": ("test",),
          "trainval": ("train", "val"), "all": ("train", "val", "test")}


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


def _split_params(params: Mapping[str, Any]) -> Tuple[SensorErrorModel, Environment]:
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


# =============================================================================
# Quaternion helpers in numpy (float64; the same formulas as tcn_ahrs.so3, which is torch):
# the simulator is I/O-side numpy and must generate > 1 M samples/s.
# =============================================================================


def _qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) quaternions (w,x,y,z); as rotations ``R(p) @ R(q)``."""
    pw, px, py, pz = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([pw * qw - px * qx - py * qy - pz * qz,
                     pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy - px * qz + py * qw + pz * qx,
                     pw * qz + px * qy - py * qx + pz * qw], -1)


def _qconj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _qexp(phi: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) -> unit quaternions (..., 4) (closed form, Taylor near 0)."""
    theta2 = np.sum(phi * phi, -1, keepdims=True)
    theta = np.sqrt(theta2)
    small = theta2 < 1e-6
    with np.errstate(invalid="ignore", divide="ignore"):
        half_sinc = np.where(small, 0.5 - theta2 / 48.0 + theta2 * theta2 / 3840.0,
                             np.sin(0.5 * theta) / np.where(small, 1.0, theta))
    w = np.where(small, 1.0 - theta2 / 8.0 + theta2 * theta2 / 384.0, np.cos(0.5 * theta))
    return np.concatenate([w, half_sinc * phi], -1)


def _qlog(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) -> rotation vectors (..., 3), angle in [0, pi]."""
    q = np.where(q[..., :1] < 0, -q, q)
    w, v = q[..., :1], q[..., 1:]
    n = np.sqrt(np.sum(v * v, -1, keepdims=True))
    small = n < 1e-3
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(small, 2.0 / w * (1.0 - n * n / (3.0 * w * w)),
                         2.0 * np.arctan2(n, w) / np.where(small, 1.0, n))
    return scale * v


def _qz(yaw: np.ndarray) -> np.ndarray:
    """Rotation about the z axis by ``yaw`` (...,) -> (..., 4)."""
    yaw = np.asarray(yaw, dtype=np.float64)
    z = np.zeros_like(yaw)
    return np.stack([np.cos(0.5 * yaw), z, z, np.sin(0.5 * yaw)], -1)


def _qmatrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (N, 4) -> rotation matrices (N, 3, 3)."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r = np.empty((q.shape[0], 3, 3))
    r[:, 0, 0] = 1 - 2 * (y * y + z * z)
    r[:, 0, 1] = 2 * (x * y - w * z)
    r[:, 0, 2] = 2 * (x * z + w * y)
    r[:, 1, 0] = 2 * (x * y + w * z)
    r[:, 1, 1] = 1 - 2 * (x * x + z * z)
    r[:, 1, 2] = 2 * (y * z - w * x)
    r[:, 2, 0] = 2 * (x * z - w * y)
    r[:, 2, 1] = 2 * (y * z + w * x)
    r[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def _to_body(r: np.ndarray, v_nav: np.ndarray) -> np.ndarray:
    """``R^T v`` for (N,3,3) nav_from_body and (N,3) or (3,) navigation vectors -> (N,3)."""
    if v_nav.ndim == 1:
        return v_nav[0] * r[:, 0, :] + v_nav[1] * r[:, 1, :] + v_nav[2] * r[:, 2, :]
    return v_nav[:, 0:1] * r[:, 0, :] + v_nav[:, 1:2] * r[:, 1, :] + v_nav[:, 2:3] * r[:, 2, :]


def cumprod_quat(q: np.ndarray) -> np.ndarray:
    """Inclusive cumulative Hamilton product ``P_k = q_0 q_1 ... q_k`` of (N, 4) quaternions.

    Vectorised chunked scan (numpy): the sequence is cut into C chunks of length L ~ sqrt(N);
    the L in-chunk steps each multiply all C chunks at once, the chunk totals are scanned the
    same way (recursively) and applied to their chunks. O(N) work, O(sqrt N) Python steps;
    round-off grows like O(sqrt N) products (1e-13 for 1e6 samples).
    """
    n = q.shape[0]
    if n <= 64:
        out = q.copy()
        for k in range(1, n):
            out[k] = _qmul(out[k - 1], out[k])
        return out / np.linalg.norm(out, axis=1, keepdims=True)
    chunk = int(math.ceil(math.sqrt(n)))
    count = int(math.ceil(n / chunk))
    pad = count * chunk - n
    qq = np.concatenate([q, np.tile([1.0, 0.0, 0.0, 0.0], (pad, 1))]) if pad else q
    # components as (4, L, C): step l touches the contiguous rows c[:, l, :]
    c = np.ascontiguousarray(qq.reshape(count, chunk, 4).transpose(2, 1, 0))
    w, x, y, z = c[0], c[1], c[2], c[3]
    for l in range(1, chunk):
        pw, px, py, pz = w[l - 1], x[l - 1], y[l - 1], z[l - 1]
        qw, qx, qy, qz = w[l].copy(), x[l].copy(), y[l].copy(), z[l].copy()
        w[l] = pw * qw - px * qx - py * qy - pz * qz
        x[l] = pw * qx + px * qw + py * qz - pz * qy
        y[l] = pw * qy - px * qz + py * qw + pz * qx
        z[l] = pw * qz + px * qy - py * qx + pz * qw
    totals = np.stack([w[-1], x[-1], y[-1], z[-1]], -1)  # (C, 4)
    prefix = cumprod_quat(totals)
    before = np.concatenate([[[1.0, 0.0, 0.0, 0.0]], prefix[:-1]])  # exclusive prefix (C, 4)
    out = _qmul(before[None, :, :], c.transpose(1, 2, 0))  # (L, C, 4)
    out = out.transpose(1, 0, 2).reshape(count * chunk, 4)[:n]
    return out / np.linalg.norm(out, axis=1, keepdims=True)


# =============================================================================
# Smooth building blocks (continuous time, analytic derivatives)
# =============================================================================


def _smoothstep(x: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quintic smoothstep S(x) = 6x^5 - 15x^4 + 10x^3 on [0, 1] (C2) and S', S''."""
    x = np.clip(x, 0.0, 1.0)
    x2 = x * x
    s = x2 * x * (10.0 + x * (-15.0 + 6.0 * x))
    s1 = 30.0 * x2 * (1.0 - x) ** 2
    s2 = 60.0 * x * (1.0 - x) * (1.0 - 2.0 * x)
    return s, s1, s2


@dataclass
class _Envelope:
    """Motion envelope e(t) in [0, 1]: 0 at rest, 1 while moving, quintic ramps of ``ramp`` s.

    Segments ``[starts[i], ends[i]]`` (sorted, disjoint, each longer than 2 ramps) are where
    the device moves; ``e, e', e''`` are evaluated per segment on its own index range.
    """

    starts: np.ndarray
    ends: np.ndarray
    ramp: float = 1.0

    def __call__(self, t: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        e, e1, e2 = np.zeros_like(t), np.zeros_like(t), np.zeros_like(t)
        r = self.ramp
        lo = np.searchsorted(t, self.starts, "left")
        hi = np.searchsorted(t, self.ends, "right")
        for s0, s1_, a, b in zip(self.starts, self.ends, lo, hi):
            tt = t[a:b]
            sa, sa1, sa2 = _smoothstep((tt - s0) / r)
            sb, sb1, sb2 = _smoothstep((s1_ - tt) / r)
            sa1, sa2 = sa1 / r, sa2 / r**2
            sb1, sb2 = -sb1 / r, sb2 / r**2
            e[a:b] = sa * sb
            e1[a:b] = sa1 * sb + sa * sb1
            e2[a:b] = sa2 * sb + 2.0 * sa1 * sb1 + sa * sb2
        return e, e1, e2

    def clock(self, t: np.ndarray) -> np.ndarray:
        """Motion clock ``tau(t) = integral_0^t e(u) du`` (stands still during rest), exact:
        the integral of the quintic smoothstep is ``I(x) = x^6 - 3x^5 + 2.5x^4``."""
        r = self.ramp
        lengths = self.ends - self.starts - r  # clock advance over a whole segment
        done = np.concatenate([[0.0], np.cumsum(lengths)])
        tau = done[np.searchsorted(self.ends, t, "right")]
        lo = np.searchsorted(t, self.starts, "left")
        hi = np.searchsorted(t, self.ends, "left")  # t == end: counted in ``done``

        def integral(x):
            x = np.clip(x, 0.0, 1.0)
            return x**4 * (2.5 + x * (-3.0 + x))

        for s0, s1, a, b in zip(self.starts, self.ends, lo, hi):
            tt = t[a:b]
            tau[a:b] += (r * integral((tt - s0) / r) + np.clip(tt - s0 - r, 0.0, s1 - s0 - 2 * r)
                         + r * (0.5 - integral((s1 - tt) / r)))
        return tau

    def moving(self, t: np.ndarray) -> np.ndarray:
        """(N,) bool: inside a motion segment (envelope > 0)."""
        if self.starts.size == 0:
            return np.zeros(t.shape, dtype=bool)
        k = np.searchsorted(self.starts, t, "right") - 1
        return (k >= 0) & (t < self.ends[np.maximum(k, 0)]) & (t > self.starts[np.maximum(k, 0)])


def _make_envelope(rng: np.random.Generator, duration: float, moving: bool,
                   segment_s=(15.0, 30.0), break_s=(2.0, 5.0)) -> _Envelope:
    """Rest 5-10 s at the start and 1-3 s at the end; motion segments separated by rest breaks."""
    rest_start = rng.uniform(5.0, 10.0)
    rest_end = rng.uniform(1.0, 3.0)
    starts, ends = [], []
    t = rest_start
    stop = duration - rest_end
    while moving:
        seg = rng.uniform(*segment_s)
        brk = rng.uniform(*break_s)
        end = min(t + seg, stop)
        if end - t >= 3.0:
            starts.append(t)
            ends.append(end)
        t = end + brk
        if t >= stop - 3.0:
            break
    return _Envelope(np.array(starts, dtype=np.float64), np.array(ends, dtype=np.float64))


def _sinusoids(rng: np.random.Generator, dims: int, comps: int, freq: Tuple[float, float], rms: float,
               order: int = 0):
    """Random sums of ``comps`` sinusoids per dimension (frequencies uniform in ``freq`` Hz),
    scaled so that the ``order``-th time derivative has RMS ``rms`` per dimension.
    Returns (angular frequencies, amplitudes, phases), each (dims, comps)."""
    w = 2.0 * np.pi * rng.uniform(*freq, size=(dims, comps))
    a = rng.uniform(0.3, 1.0, size=(dims, comps))
    a *= rms / np.sqrt(0.5 * np.sum(a * a, axis=1, keepdims=True))
    ph = rng.uniform(0.0, 2.0 * np.pi, size=(dims, comps))
    return w, a / w**order, ph


def _sum_matrix(params, order: int) -> np.ndarray:
    """(dims*comps, dims) matrix summing the components of each dimension with weights
    ``a w^order`` (the ``order``-th derivative up to the sign of sin/cos)."""
    w, a, _ = params
    dims, comps = w.shape
    m = np.zeros((dims * comps, dims))
    m[np.arange(dims * comps), np.repeat(np.arange(dims), comps)] = (a * w**order).ravel()
    return m


def _eval_sinusoids(params, t: np.ndarray, derivs: int = 0) -> List[np.ndarray]:
    """Sum of sinusoids ``s(t) = sum_j a_j sin(w_j t + p_j)`` per dimension and its first
    ``derivs`` (<= 2) derivatives; each (N, dims)."""
    w, _, ph = params
    arg = np.multiply.outer(t, w.ravel())
    arg += ph.ravel()
    sin = np.sin(arg)
    out = [sin @ _sum_matrix(params, 0)]
    if derivs >= 1:
        out.append(np.cos(arg) @ _sum_matrix(params, 1))
    if derivs >= 2:
        out.append(-(sin @ _sum_matrix(params, 2)))
    return out


def _eval_sinusoids_uniform(params, t0: float, dt: float, n: int, derivs: int = 0) -> List[np.ndarray]:
    """:func:`_eval_sinusoids` on the uniform grid ``t_k = t0 + k dt``, fast. With ``k = j L + l``
    (``L ~ sqrt(N)``) the angle is ``A_j + B_l``, ``A_j = w (t0 + j L dt) + p``, ``B_l = w l dt``, and
    ``sum_m a_m sin(A_jm + B_lm) = sum_m a_m sin A_jm cos B_lm + a_m cos A_jm sin B_lm``: a
    (C x 2M) @ (2M x L) matrix product per dimension, no sine per sample (exact to round-off)."""
    w, a, ph = params
    dims, comps = w.shape
    block = int(math.ceil(math.sqrt(n)))
    count = int(math.ceil(n / block))
    big_a = np.multiply.outer(t0 + np.arange(count) * (block * dt), w) + ph    # (C, dims, comps)
    small_b = np.multiply.outer(np.arange(block) * dt, w)                       # (L, dims, comps)
    sa, ca = np.sin(big_a), np.cos(big_a)
    right = np.concatenate([np.cos(small_b), np.sin(small_b)], axis=2)         # (L, dims, 2 comps)
    out = []
    for order in range(derivs + 1):
        amp = a * w**order
        # d^k/dt^k sin = sin, cos, -sin: f(A + B) = f1(A) cos B + f2(A) sin B
        f1, f2 = [(sa, ca), (ca, -sa), (-sa, -ca)][order]
        left = np.concatenate([f1 * amp, f2 * amp], axis=2)                    # (C, dims, 2 comps)
        res = np.empty((n, dims))
        for d in range(dims):
            res[:, d] = (left[:, d, :] @ right[:, d, :].T).ravel()[:n]
        out.append(res)
    return out


def _translation(env_vals, sin_params, t0: float, dt: float, n: int):
    """Velocity ``v = e(t) s'(t)`` (``s`` a sum of sinusoids, ``e`` the motion envelope) and its
    exact derivative ``a = e' s' + e s''`` on the uniform grid ``t0 + k dt``; (N, dims) each.
    The device starts and stops smoothly and is still wherever ``e = 0``."""
    e, e1, _ = env_vals
    _, s1, s2 = _eval_sinusoids_uniform(sin_params, t0, dt, n, derivs=2)
    return e[:, None] * s1, e1[:, None] * s1 + e[:, None] * s2


def _random_tilt_quat(rng: np.random.Generator, max_tilt: float) -> np.ndarray:
    """Random yaw times a tilt of up to ``max_tilt`` rad about a random horizontal axis."""
    yaw = rng.uniform(-np.pi, np.pi)
    ang = rng.uniform(0.0, max_tilt)
    ax = rng.uniform(-np.pi, np.pi)
    tilt = _qexp(ang * np.array([np.cos(ax), np.sin(ax), 0.0]))
    return _qmul(_qz(yaw), tilt)


# =============================================================================
# Motion profiles: each returns (omega (N,3) body rate over (t_{k-1}, t_k], q0 (4,),
# vel_nav (N,3), acc_nav (N,3), moving (N,) bool) for sample times t (N,) and step dt.
# Rate-defined profiles (rotations) sample a continuous body rate at the step midpoints;
# attitude-defined ones (walking, drone) define q*(t) and take the piecewise-constant rate
# w_k = Log(q*(t_{k-1})^-1 q*(t_k)) / dt that reproduces q* at every sample (rates < pi/dt).
# =============================================================================


def _profile_static(rng, t, dt, duration):
    n = t.shape[0]
    env = _make_envelope(rng, duration, moving=False)
    q0 = _random_tilt_quat(rng, 10 * DEG)
    z = np.zeros((n, 3))
    return z, q0, z.copy(), z.copy(), env.moving(t)


def _profile_rotation(rng, t, dt, duration, rate_rms_dps, freq, acc_rms):
    env = _make_envelope(rng, duration, moving=True)
    q0 = _random_tilt_quat(rng, 20 * DEG)
    rot = _sinusoids(rng, 3, 4, freq, rate_rms_dps * DEG)
    trans = _sinusoids(rng, 3, 2, (max(freq[0], 0.1), freq[1]), acc_rms, order=2)
    tm = t - 0.5 * dt  # the rate over (t_{k-1}, t_k] is the continuous rate at the midpoint
    e_mid = env(tm)[0]
    omega = e_mid[:, None] * _eval_sinusoids_uniform(rot, t[0] - 0.5 * dt, dt, t.shape[0])[0]
    vel, acc = _translation(env(t), trans, t[0], dt, t.shape[0])
    return omega, q0, vel, acc, env.moving(t)


def _profile_walking(rng, t, dt, duration):
    env = _make_envelope(rng, duration, moving=True, segment_s=(20.0, 40.0))
    speed = rng.uniform(1.0, 1.5)            # m/s
    f_step = rng.uniform(1.6, 2.0)           # Hz
    ws = 2 * np.pi * f_step
    surge = rng.uniform(0.1, 0.2)            # relative speed oscillation at the step frequency
    bounce = rng.uniform(0.02, 0.04)         # m, vertical oscillation amplitude
    sway = rng.uniform(0.02, 0.05)           # m, lateral sway at half the step frequency
    ph = rng.uniform(0, 2 * np.pi, size=6)
    osc_amp = np.array([3.0, 4.0, 3.0]) * DEG * rng.uniform(0.5, 1.5, size=3)
    yaw0 = rng.uniform(-np.pi, np.pi)
    # phone held in the hand: pitch/roll/yaw offset w.r.t. the walking direction
    hold = _qmul(_qz(rng.uniform(-30, 30) * DEG),
                 _qmul(_qexp(np.array([0.0, rng.uniform(-40, 10) * DEG, 0.0])),
                       _qexp(np.array([rng.uniform(-15, 15) * DEG, 0.0, 0.0]))))
    # heading turns (45-180 deg, 1.5-3 s) inside the motion segments
    t_on, t_len, t_ang = [], [], []
    for s0, s1 in zip(env.starts, env.ends):
        tt = s0 + rng.uniform(2.0, 6.0)
        while True:
            d = rng.uniform(1.5, 3.0)
            ang = rng.choice([-1.0, 1.0]) * rng.uniform(45.0, 180.0) * DEG
            if tt + d > s1 - 1.5:
                break
            t_on.append(tt)
            t_len.append(d)
            t_ang.append(ang)
            tt += d + rng.uniform(4.0, 12.0)
    t_on, t_len, t_ang = np.array(t_on), np.array(t_len), np.array(t_ang)
    t_off = t_on + t_len
    cum = np.concatenate([[0.0], np.cumsum(t_ang)])

    def heading(tq: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Walking direction psi(t) (ENU, from east) and its rate."""
        psi = yaw0 + cum[np.searchsorted(t_off, tq, "right")]
        dpsi = np.zeros_like(tq)
        lo = np.searchsorted(tq, t_on, "right")
        hi = np.searchsorted(tq, t_off, "left")
        for a, b, s0, d, ang in zip(lo, hi, t_on, t_len, t_ang):
            s, s1, _ = _smoothstep((tq[a:b] - s0) / d)
            psi[a:b] += ang * s
            dpsi[a:b] = ang * s1 / d
        return psi, dpsi

    # everything on t_{-1}, t_0, ..., t_{N-1} (the rates need the attitude one step back)
    tt = np.concatenate([[t[0] - dt], t])
    e, e1, _ = env(tt)
    psi, dpsi = heading(tt)
    # the six periodic terms (unit amplitude) on the uniform grid: sin and cos at once
    wv = np.array([0.5, 1.0, 0.5, 1.0, 1.0, 0.5])[:, None] * ws
    per = (wv, np.ones((6, 1)), ph[:, None])
    sin, wcos = _eval_sinusoids_uniform(per, float(tt[0]), dt, tt.shape[0], derivs=1)
    sin, cos = sin, wcos / wv[:, 0]
    # attitude: heading, hand pose, hand sway of a few degrees
    osc = e[:, None] * osc_amp * sin[:, 0:3]
    c, sn = np.cos(0.5 * psi), np.sin(0.5 * psi)  # Rz(psi) hold, written out (hold is constant)
    h0, h1, h2, h3 = hold
    q = _qmul(np.stack([c * h0 - sn * h3, c * h1 - sn * h2, c * h2 + sn * h1, c * h3 + sn * h0], -1),
              _qexp(osc))
    omega = _qlog(_qmul(_qconj(q[:-1]), q[1:])) / dt
    q0 = q[1]
    e, e1, psi, dpsi, sin, cos = e[1:], e1[1:], psi[1:], dpsi[1:], sin[1:], cos[1:]
    cp, sp = np.cos(psi), np.sin(psi)
    # velocity = v_f fwd + v_l left + v_z up: forward speed with surge, lateral sway at half the
    # step frequency, vertical bounce (all scaled by e(t)); fwd = (cos psi, sin psi, 0), left = (-sin psi, cos psi, 0)
    m = speed * (1.0 + surge * sin[:, 3])
    dm = speed * surge * ws * cos[:, 3]
    wl = 0.5 * ws
    vl = sway * wl * cos[:, 5]
    dvl = -sway * wl**2 * sin[:, 5]
    v_f, v_l = e * m, e * vl
    v_z = e * (bounce * ws * cos[:, 4])
    # analytic derivative; d fwd/dt = psi' left, d left/dt = -psi' fwd
    a_f = e1 * m + e * dm - v_l * dpsi
    a_l = v_f * dpsi + e1 * vl + e * dvl
    a_z = e1 * (bounce * ws * cos[:, 4]) - e * (bounce * ws**2 * sin[:, 4])
    vel = np.stack([v_f * cp - v_l * sp, v_f * sp + v_l * cp, v_z], -1)
    acc = np.stack([a_f * cp - a_l * sp, a_f * sp + a_l * cp, a_z], -1)
    return omega, q0, vel, acc, env.moving(t)


def _profile_drone(rng, t, dt, duration):
    env = _make_envelope(rng, duration, moving=True, segment_s=(20.0, 45.0))
    env.ramp = 2.0  # gentle take-off / stop: the tilt rate follows the jerk
    horiz = _sinusoids(rng, 2, 3, (0.08, 0.4), rng.uniform(1.5, 2.5), order=2)
    vert = _sinusoids(rng, 1, 3, (0.05, 0.3), 0.4, order=2)
    trans = tuple(np.concatenate([h, v]) for h, v in zip(horiz, vert))  # (3 dims, 3 comps)
    yaw_p = _sinusoids(rng, 1, 3, (0.02, 0.2), rng.uniform(20, 60) * DEG)
    yaw0 = rng.uniform(-np.pi, np.pi)

    # evaluated once on t_{-1}, t_0, ..., t_{N-1}: the rates need the attitude one step back
    tt = np.concatenate([[t[0] - dt], t])
    vel, acc = _translation(env(tt), trans, tt[0], dt, tt.shape[0])
    tau = env.clock(tt)  # the yaw pattern pauses while the drone rests
    thrust = acc + np.array([0.0, 0.0, GRAVITY])
    zb = thrust / np.linalg.norm(thrust, axis=1, keepdims=True)
    # shortest-arc rotation taking the nav up axis to the body z axis (|a| < g: zb_z > 0)
    tilt = np.stack([1.0 + zb[:, 2], -zb[:, 1], zb[:, 0], np.zeros_like(zb[:, 0])], -1)
    tilt /= np.linalg.norm(tilt, axis=1, keepdims=True)
    yaw = yaw0 + _eval_sinusoids(yaw_p, tau)[0][:, 0]
    q = _qmul(tilt, _qz(yaw))  # R = R_tilt Rz(yaw): body z = zb
    omega = _qlog(_qmul(_qconj(q[:-1]), q[1:])) / dt
    return omega, q[1], vel[1:], acc[1:], env.moving(t)


_PROFILE_FNS = {
    "static": _profile_static,
    "slow_rotation": lambda rng, t, dt, d: _profile_rotation(rng, t, dt, d, 25.0, (0.05, 0.5), 0.3),
    "fast_rotation": lambda rng, t, dt, d: _profile_rotation(rng, t, dt, d, 150.0, (0.2, 1.5), 1.5),
    "walking": _profile_walking,
    "drone": _profile_drone,
}


# =============================================================================
# Sensor errors
# =============================================================================


@dataclass
class _Device:
    """Per-device constants drawn from ``device_seed`` (shared by every recording)."""

    k_gyro: np.ndarray
    k_acc: np.ndarray
    k_mag: np.ndarray
    gyro_bias: np.ndarray   # rad/s
    acc_bias: np.ndarray    # m/s^2
    hard_iron: np.ndarray   # uT


def _k_matrix(rng, scale_std, mis_std) -> np.ndarray:
    k = np.eye(3) + np.diag(rng.normal(0.0, scale_std, 3))
    off = rng.normal(0.0, mis_std, (3, 3))
    np.fill_diagonal(off, 0.0)
    return k + off


def _draw_device(device_seed: int, p: SensorErrorModel) -> _Device:
    rng = np.random.default_rng([int(device_seed), 0xDE71CE])
    k_gyro = _k_matrix(rng, p.gyro_scale_std, p.gyro_misalignment_std)
    k_acc = _k_matrix(rng, p.acc_scale_std, p.acc_misalignment_std)
    k_mag = _k_matrix(rng, p.mag_scale_std, p.mag_misalignment_std)
    lo, hi = p.gyro_bias_range_dps
    gyro_bias = rng.choice([-1.0, 1.0], 3) * rng.uniform(lo, hi, 3) * DEG
    acc_bias = rng.normal(0.0, p.acc_bias_std, 3)
    hard_iron = rng.normal(0.0, p.hard_iron_std_ut, 3)
    return _Device(k_gyro, k_acc, k_mag, gyro_bias, acc_bias, hard_iron)


def _bias_track(unit_normal: np.ndarray, dt: float, static: np.ndarray, rw: float) -> np.ndarray:
    """(N, 3) static bias plus a random walk starting at 0 (increments ``rw sqrt(dt) n_k``,
    from the (N, 3) standard normals ``unit_normal``)."""
    steps = unit_normal * (rw * math.sqrt(dt))
    steps[0] = 0.0
    return static + np.cumsum(steps, axis=0)


def _mag_disturbance(rng, t: np.ndarray, env: Environment, not_before: float) -> np.ndarray:
    """(N, 3) transient external field in ENU (uT): dipole pass-bys
    ``peak * u * ((1 + x^2)^(-3/2) - c) / (1 - c)`` with ``x = (t - t_c)/tau``, cut at
    ``|x| = 3`` (``c = 10^(-3/2)`` keeps the field continuous)."""
    n = t.shape[0]
    d = np.zeros((n, 3))
    duration = float(t[-1] - t[0])
    count = int(round(env.mag_disturbances_per_minute * duration / 60.0))
    if count <= 0:
        return d
    cut = 10.0 ** -1.5
    for _ in range(count):
        tau = rng.uniform(*env.mag_disturbance_tau_s)
        peak = rng.uniform(*env.mag_disturbance_peak_ut)
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        # the whole pulse lies after ``not_before`` (when the recording is long enough)
        tc = rng.uniform(min(not_before + 3 * tau, t[-1]), t[-1])
        a, b = np.searchsorted(t, [tc - 3 * tau, tc + 3 * tau])
        x = (t[a:b] - tc) / tau
        shape = np.clip(((1.0 + x * x) ** -1.5 - cut) / (1.0 - cut), 0.0, None)
        d[a:b] += peak * shape[:, None] * u
    return d


# =============================================================================
# Public API
# =============================================================================


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
    if profile not in _PROFILE_FNS:
        raise ValueError(f"simulate: unknown profile {profile!r}; expected one of {list(PROFILES)}")
    if axes not in (6, 9):
        raise ValueError(f"simulate: axes must be 6 or 9, got {axes!r}")
    if not rate > 0 or not duration > 0:
        raise ValueError(f"simulate: expected rate > 0 Hz and duration > 0 s, got rate={rate!r}, "
                         f"duration={duration!r}")
    sens, envp = _split_params(error_params)
    seed = int(seed)
    rate = float(rate)
    dt = 1.0 / rate
    n = int(round(duration * rate)) + 1
    t = np.arange(n, dtype=np.float64) * dt

    # independent streams: the motion does not change when error parameters change
    ss = np.random.SeedSequence([seed, 0x51A7])
    rng_motion, rng_sensor, rng_noise, rng_dist = (np.random.default_rng(s) for s in ss.spawn(4))

    omega, q0, vel_nav, acc_nav, moving = _PROFILE_FNS[profile](rng_motion, t, dt, float(duration))

    # Ground truth: exact product of exponentials of the piecewise-constant true rate (Eq. 3):
    # q_k = q_0 exp(w_1 dt) ... exp(w_k dt); the first rate sample is not applied.
    inc = _qexp(omega * dt)
    inc[0] = q0
    quat = cumprod_quat(inc)
    r = _qmatrix(quat)

    ext_acc_body = _to_body(r, acc_nav)
    spec_force = ext_acc_body + GRAVITY * r[:, 2, :]  # R^T (a + g up): third row of R
    m_nav = envp.field_nav()

    if noise_free:
        eye = np.eye(3)
        k_gyro = k_acc = k_mag = eye
        gyro_bias = np.zeros((n, 3))
        acc_bias = np.zeros((n, 3))
        hard_iron = np.zeros(3)
        d_nav = np.zeros((n, 3))
        gyro_noise = acc_noise = mag_noise = 0.0
        b_g0 = b_a0 = np.zeros(3)
    else:
        dev = _draw_device(device_seed, sens)
        rk = sens.recording_k_std
        k_gyro = dev.k_gyro + rng_sensor.normal(0.0, rk, (3, 3))
        k_acc = dev.k_acc + rng_sensor.normal(0.0, rk, (3, 3))
        k_mag = dev.k_mag + rng_sensor.normal(0.0, rk, (3, 3))
        b_g0 = dev.gyro_bias + rng_sensor.normal(0.0, sens.gyro_bias_repeatability_dps * DEG, 3)
        b_a0 = dev.acc_bias + rng_sensor.normal(0.0, sens.acc_bias_repeatability, 3)
        hard_iron = dev.hard_iron + rng_sensor.normal(0.0, sens.hard_iron_repeatability_ut, 3)
        unit = rng_noise.standard_normal((5, n, 3))  # one draw: bias walks, then white noise
        gyro_bias = _bias_track(unit[0], dt, b_g0, sens.gyro_bias_rw_dps * DEG)
        acc_bias = _bias_track(unit[1], dt, b_a0, sens.acc_bias_rw)
        sq = math.sqrt(rate)
        gyro_noise = unit[2] * (sens.gyro_noise_density_dps * DEG * sq)
        acc_noise = unit[3] * (sens.acc_noise_density * sq)
        mag_noise = unit[4] * (sens.mag_noise_density_ut * sq)
        rest_end = float(t[np.argmax(moving)]) if moving.any() else 0.0
        d_nav = _mag_disturbance(rng_dist, t, envp, not_before=max(rest_end, min(10.0, 0.2 * duration)))

    gyro = omega @ k_gyro.T + gyro_bias + gyro_noise                            # Eq. 9
    accel = spec_force @ k_acc.T + acc_bias + acc_noise                         # Eq. 10
    mag_dist_body = np.zeros((n, 3))
    hit = np.any(d_nav != 0.0, axis=1)
    mag_dist_body[hit] = _to_body(r[hit], d_nav[hit])
    mag = None
    if axes == 9:
        mag = (_to_body(r, m_nav) + mag_dist_body) @ k_mag.T + hard_iron + mag_noise  # Eq. 11

    meta: Dict[str, Any] = {
        "profile": profile, "seed": seed, "device_seed": int(device_seed), "noise_free": bool(noise_free),
        "error_model": dataclasses.asdict(sens), "environment": dataclasses.asdict(envp),
        "K_gyro": k_gyro, "K_acc": k_acc, "K_mag": k_mag,
        "gyro_bias_static": b_g0, "acc_bias_static": b_a0, "hard_iron": hard_iron,
        "mag_field_nav": m_nav,
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


# =============================================================================
# Dataset splits (conf/data/simulated.yaml)
# =============================================================================


def _plain(cfg) -> dict:
    """Mapping or OmegaConf DictConfig -> plain dict."""
    try:
        from omegaconf import DictConfig, OmegaConf
        if isinstance(cfg, DictConfig):
            return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    except ImportError:  # pragma: no cover
        pass
    return dict(cfg)


def split_plan(data_cfg, split: Optional[str] = None) -> List[Dict[str, Any]]:
    """The recordings ``split`` consists of, as keyword dicts for :func:`simulate` (no data made).

    Recording ``i`` of split part ``p`` gets seed ``splits.p.seed_offset + i`` and profile
    ``splits.p.profiles[i % len(profiles)]``; seed ranges of the parts must be disjoint.
    """
    cfg = _plain(data_cfg)
    src = "conf/data/simulated.yaml"
    split = split or cfg.get("split") or "train"
    if split not in SPLITS:
        raise ValueError(f"{src}: field 'split': expected one of {list(SPLITS)}, got {split!r}")
    parts = cfg.get("splits")
    if not isinstance(parts, dict):
        raise ValueError(f"{src}: field 'splits': expected a mapping with keys train, val, test")
    ranges = {}
    for name, spec in parts.items():
        try:
            off, cnt = int(spec.get("seed_offset", 0)), int(spec["count"])
        except (KeyError, AttributeError, TypeError, ValueError):
            raise ValueError(f"{src}: field 'splits.{name}': expected count (int) and seed_offset (int)") from None
        ranges[name] = (off, off + cnt)
    names = sorted(ranges)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            (a0, a1), (b0, b1) = ranges[a], ranges[b]
            if a0 < b1 and b0 < a1 and a1 > a0 and b1 > b0:
                raise ValueError(f"{src}: fields 'splits.{a}.seed_offset' / 'splits.{b}.seed_offset': seed ranges "
                                 f"[{a0}, {a1}) and [{b0}, {b1}) overlap; splits must use disjoint seeds")
    axes = int(cfg.get("axes", 9))
    rate = float(cfg.get("rate", 100.0))
    device_seed = int(cfg.get("device_seed", 0))
    common = dict(cfg.get("error_params") or {})
    plan = []
    for part in SPLITS[split]:
        if part not in parts:
            raise ValueError(f"{src}: field 'splits.{part}': missing (needed for split {split!r})")
        spec = parts[part]
        profiles = list(spec.get("profiles") or ["slow_rotation"])
        bad = [p for p in profiles if p not in PROFILES]
        if bad:
            raise ValueError(f"{src}: field 'splits.{part}.profiles': unknown {bad}; expected any of {list(PROFILES)}")
        extra = dict(common)
        extra.update(spec.get("error_params") or {})
        off, end = ranges[part]
        for i, seed in enumerate(range(off, end)):
            plan.append(dict(profile=profiles[i % len(profiles)], duration=float(spec.get("duration", 60.0)),
                             rate=rate, seed=seed, axes=axes, device_seed=device_seed,
                             noise_free=bool(spec.get("noise_free", cfg.get("noise_free", False))), **extra))
    return plan


def load_split(data_cfg, split: Optional[str] = None) -> List[ImuSequence]:
    """Generate the recordings of ``split`` (train | val | test | trainval | all) from
    ``data_cfg`` (see ``conf/data/simulated.yaml``). ``trainval`` = train + val recordings,
    ``all`` = train + val + test; every split uses the same device (``device_seed``)."""
    return [simulate(**kw) for kw in split_plan(data_cfg, split)]


def list_recordings(data_cfg) -> List[str]:
    """Names of every recording the config generates (all splits)."""
    return [f"sim_{kw['profile']}_s{kw['seed']:04d}" for kw in split_plan(data_cfg, "all")]


# =============================================================================
# Benchmark / CLI
# =============================================================================


def benchmark(samples: int = 1_000_000, rate: float = 100.0, repeats: int = 3) -> Dict[str, Tuple[float, float]]:
    """Generation speed per profile (9-axis, full error model, including ImuSequence validation):
    ``{profile: (samples/s wall clock, samples/s process CPU time)}``, best of ``repeats``
    (CPU time is the fairer number on a shared, loaded machine)."""
    out = {}
    duration = (samples - 1) / rate
    for profile in PROFILES:
        best_wall = best_cpu = float("inf")
        for r in range(repeats):
            w0, c0 = _time.perf_counter(), _time.process_time()
            simulate(profile, duration, rate, seed=r, axes=9)
            best_wall = min(best_wall, _time.perf_counter() - w0)
            best_cpu = min(best_cpu, _time.process_time() - c0)
        out[profile] = (samples / best_wall, samples / best_cpu)
    return out


def _main(argv=None) -> None:
    ap = argparse.ArgumentParser(description="tcn-ahrs IMU simulator")
    ap.add_argument("--benchmark", action="store_true", help="measure generation speed (samples/s)")
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=3, help="benchmark: best of this many runs")
    ap.add_argument("--profile", default="walking", choices=PROFILES)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.benchmark:
        res = benchmark(args.samples, args.rate, args.repeats)
        print(f"{args.samples} samples per recording at {args.rate:g} Hz, 9-axis, full error model")
        print(f"{'profile':15s} {'wall':>10s} {'cpu':>10s}   (M samples/s)")
        for k, (wall, cpu) in res.items():
            print(f"{k:15s} {wall / 1e6:10.2f} {cpu / 1e6:10.2f}")
        walls, cpus = zip(*res.values())
        print(f"{'mean':15s} {np.mean(walls) / 1e6:10.2f} {np.mean(cpus) / 1e6:10.2f}")
        return
    seq = simulate(args.profile, args.duration, args.rate, args.seed)
    m = seq.meta
    print(f"{seq.name}: {len(seq)} samples, {seq.duration:.1f} s, source {seq.source}")
    print(f"  |gyro| max {np.abs(m['true_gyro']).max() / DEG:.1f} deg/s, "
          f"|ext acc| max {np.linalg.norm(m['true_acc_nav'], axis=1).max():.2f} m/s^2, "
          f"moving {m['moving'].mean():.0%}, acc disturbed {m['acc_disturbed'].mean():.0%}, "
          f"mag disturbed {m['mag_disturbed'].mean():.0%}")


if __name__ == "__main__":
    _main()
