"""Motion: rest/move envelopes, sums of sinusoids, and the motion profiles."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Tuple

import numpy as np

from ...conventions import DEG, GRAVITY
from .quat import qconj, qexp, qlog, qmul, quat_about_z


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
    tilt = qexp(ang * np.array([np.cos(ax), np.sin(ax), 0.0]))
    return qmul(quat_about_z(yaw), tilt)


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
    hold = qmul(quat_about_z(rng.uniform(-30, 30) * DEG),
                 qmul(qexp(np.array([0.0, rng.uniform(-40, 10) * DEG, 0.0])),
                       qexp(np.array([rng.uniform(-15, 15) * DEG, 0.0, 0.0]))))
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
    q = qmul(np.stack([c * h0 - sn * h3, c * h1 - sn * h2, c * h2 + sn * h1, c * h3 + sn * h0], -1),
              qexp(osc))
    omega = qlog(qmul(qconj(q[:-1]), q[1:])) / dt
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
    q = qmul(tilt, quat_about_z(yaw))  # R = R_tilt Rz(yaw): body z = zb
    omega = qlog(qmul(qconj(q[:-1]), q[1:])) / dt
    return omega, q[1], vel[1:], acc[1:], env.moving(t)


PROFILE_FNS = {
    "static": _profile_static,
    "slow_rotation": lambda rng, t, dt, d: _profile_rotation(rng, t, dt, d, 25.0, (0.05, 0.5), 0.3),
    "fast_rotation": lambda rng, t, dt, d: _profile_rotation(rng, t, dt, d, 150.0, (0.2, 1.5), 1.5),
    "walking": _profile_walking,
    "drone": _profile_drone,
}


# =============================================================================
# Sensor errors
