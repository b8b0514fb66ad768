"""Strapdown INS/GNSS in the local geographic (ENU) frame and in the polar grid frame, with the
covariance transformation between them: ``../shared/papers/ins-gnss-grid-frame-covariance-transformation.txt``
(its equation numbers). numpy float64, batched over B runs (navigation-grade errors are 1e-8 rad/s:
float32 cannot hold them).

Navigation state per frame (``InsState``): attitude ``C_b^f`` (body to frame f), velocity ``v^f``,
position -- ``(L, lambda, h)`` in the n-frame (``"n"``, ENU), ECEF ``r^e`` in the grid frame
(``"G"``: grid east, grid north, up; no singularity at the pole) -- and the gyro / accelerometer
bias estimates (body). Error state (15, Eqs. 24-25), every error *computed minus true*:
``[phi (3), dv (3), dp (3), eps (3), nabla (3)]`` with ``C~ = (I - [phi x]) C`` (Eq. 10), ``dp`` =
``(dL, dlambda, dh)`` (n) or ``dr^e`` (G); the bias states are the other way round, true minus
estimated (``eps`` is the gyro bias the estimate still lacks: the estimate is subtracted from the
increments, and a correction adds ``eps`` to it).

* Mechanisation (Eqs. 5-7 in G; the same form in n): attitude ``C <- exp(-[w_if dt x]) C exp([dtheta x])``,
  velocity with the rotation correction of the increment and Coriolis/transport terms, position
  with the mid-step velocity (and the mid-step frame / radii). Increments ``dtheta, dv`` come from
  :func:`preintegrate` (a 200 Hz IMU summed to the navigation rate with coning and sculling terms).
* Error dynamics: n-frame the standard phi-angle model (the paper's Eqs. 15 and 18 with n for G;
  its position coupling written out); G-frame Eqs. 15 and 18 with ``omega_eG^G = M v^G`` (Eq. 8),
  the coupling of the position error into the rates and the gravity error neglected (|dr| ~ 10 m:
  ``Omega |dr| / R`` ~ 1e-10 rad/s against a 5e-8 rad/s gyro bias; the paper drops the same
  terms, Eq. 18).
* GNSS: position at 1 Hz, ``z = p~ - p_GNSS`` (n: in rad/rad/m with ``R`` scaled by the radii; G: ECEF m).
* Frame switch (:func:`switch_frame`): the navigation parameters converted exactly; the covariance
  by ``P_G = Phi P_n Phi^T`` (Eqs. 28-34; the paper's Phi_a has the sign of its third row flipped
  against its own Eq. 29 -- fixed here, tested by transforming error samples) or kept as it is (the
  "non-transformation" the paper compares against).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Dict, Optional, Tuple

import numpy as np
from scipy.spatial.transform import Rotation

from . import earth
from .earth import skew


@dataclass(frozen=True)
class InsNoise:
    """Filter noise (defaults: a navigation-grade RLG IMU as the paper's, GNSS < 10 m).

    gyro_arw: angle random walk, rad/sqrt(s) (0.001 deg/sqrt(h)).
    accel_vrw: velocity random walk, m/s/sqrt(s) (10 ug/sqrt(Hz)).
    gyro_bias_walk, accel_bias_walk: bias instability as a slow walk, per sqrt(s).
    gnss_std: GNSS position std per axis, m.
    init_att, init_vel, init_pos, init_gyro_bias, init_accel_bias: P_0 stds (rad, m/s, m, rad/s, m/s^2).
    """

    gyro_arw: float = np.radians(0.001) / 60.0
    accel_vrw: float = 10e-6 * 9.80665
    gyro_bias_walk: float = np.radians(0.001 / 3600.0) / 60.0
    accel_bias_walk: float = 1e-6 * 9.80665 / 60.0
    gnss_std: float = 10.0 / 3.0
    init_att: Tuple[float, float, float] = (np.radians(0.5 / 60), np.radians(0.5 / 60), np.radians(3.0 / 60))
    init_vel: float = 0.1
    init_pos: float = 5.0
    init_gyro_bias: float = np.radians(0.01 / 3600.0)
    init_accel_bias: float = 20e-6 * 9.80665


@dataclass
class InsState:
    """Batched navigation state in one frame (see the module docstring). P (B, 15, 15)."""

    frame: str
    att: np.ndarray
    vel: np.ndarray
    pos: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    P: np.ndarray = field(default=None)

    def geodetic(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self.frame == "n":
            return self.pos[:, 0], self.pos[:, 1], self.pos[:, 2]
        return earth.geodetic(self.pos)

    def ecef(self) -> np.ndarray:
        return earth.ecef(*self.geodetic()) if self.frame == "n" else self.pos

    def copy(self) -> "InsState":
        return replace(self, att=self.att.copy(), vel=self.vel.copy(), pos=self.pos.copy(),
                       gyro_bias=self.gyro_bias.copy(), accel_bias=self.accel_bias.copy(),
                       P=None if self.P is None else self.P.copy())


def exp_so3(rv: np.ndarray) -> np.ndarray:
    """Rotation matrices (B, 3, 3) of rotation vectors (B, 3) (scipy)."""
    return Rotation.from_rotvec(rv).as_matrix()


def preintegrate(gyro: np.ndarray, acc: np.ndarray, dt: float, k: int) -> Tuple[np.ndarray, np.ndarray]:
    """Sum a high-rate IMU (N, 3) rad/s, m/s^2 into increments over k samples (the navigation rate):
    ``dtheta = sum a_i + 1/2 sum_{i<j} a_i x a_j`` (coning) and ``dv = sum u_i + sum_{i<j} a_i x u_j
    + 1/2 sum_i a_i x u_i`` (the body's rotation during the interval: rotation and sculling terms;
    ``1/2 dtheta x dv`` for constant rates), a_i = gyro_i dt, u_i = acc_i dt. Returns (N // k, 3)
    each, expressed in the body frame at the start of each interval."""
    n = (gyro.shape[0] // k) * k
    a = (gyro[:n] * dt).reshape(-1, k, 3)
    u = (acc[:n] * dt).reshape(-1, k, 3)
    a_before = np.cumsum(a, 1) - a                      # sum of the earlier samples in the interval
    dtheta = a.sum(1) + 0.5 * np.cross(a_before, a).sum(1)
    dv = u.sum(1) + (np.cross(a_before, u) + 0.5 * np.cross(a, u)).sum(1)
    return dtheta, dv


def frame_rates(state: InsState, lat: np.ndarray, lon: np.ndarray, h: np.ndarray) -> Dict[str, np.ndarray]:
    """Earth rate, transport-rate matrix M (omega_ef = M v) and gravity in the state's frame."""
    if state.frame == "n":
        w_ie = earth.earth_rate_enu(lat)
        M = earth.transport_matrix_enu(lat, h)
        C_e = None
    else:
        C_e = earth.grid_from_ecef(lat, lon)
        w_ie = C_e[..., :, 2] * earth.OMEGA                # C_e^G [0, 0, Omega] (Eq. 8)
        M = earth.transport_matrix_grid(lat, lon, h)
    g = np.zeros_like(state.vel)
    g[:, 2] = -earth.gravity(lat, h)
    return {"w_ie": w_ie, "M": M, "g": g, "C_e": C_e}


def mechanise(state: InsState, dtheta: np.ndarray, dv: np.ndarray, dt: float) -> Dict[str, np.ndarray]:
    """One navigation step in place (Eqs. 5-7) with bias-corrected increments (B, 3). Returns
    the frame quantities at the start of the step and the specific force in the frame (for F)."""
    lat, lon, h = state.geodetic()
    fr = frame_rates(state, lat, lon, h)
    dtheta = dtheta - state.gyro_bias * dt
    dv = dv - state.accel_bias * dt
    v0 = state.vel
    w_ef = (fr["M"] @ v0[..., None])[..., 0]
    w_if = fr["w_ie"] + w_ef
    # dv is in the body frame at the step's start; the frame turns by w_if dt meanwhile: resolve
    # it in the frame at mid-step (without this, 1/2 w_if x g is a ~1 ug horizontal bias)
    dv_f = (state.att @ dv[..., None])[..., 0]
    dv_f = dv_f - 0.5 * dt * np.cross(w_if, dv_f)
    v1 = v0 + dv_f + (fr["g"] - np.cross(2.0 * fr["w_ie"] + w_ef, v0)) * dt
    # second pass with the mid-step velocity in the Coriolis and transport terms (trapezoidal)
    w_ef_mid = (fr["M"] @ (0.5 * (v0 + v1))[..., None])[..., 0]
    v1 = v0 + dv_f + (fr["g"] - np.cross(2.0 * fr["w_ie"] + w_ef_mid, 0.5 * (v0 + v1))) * dt
    w_if = fr["w_ie"] + w_ef_mid
    state.att = exp_so3(-w_if * dt) @ state.att @ exp_so3(dtheta)
    v_mid = 0.5 * (v0 + v1)
    if state.frame == "n":
        h_mid = h + 0.5 * v_mid[:, 2] * dt
        lat_mid = lat + 0.5 * v_mid[:, 1] * dt / (earth.radii(lat)[0] + h_mid)
        RM, RN = earth.radii(lat_mid)
        state.pos = state.pos + np.stack([v_mid[:, 1] / (RM + h_mid), v_mid[:, 0] / ((RN + h_mid) * np.cos(lat_mid)),
                                          v_mid[:, 2]], -1) * dt
    else:
        # r_e' = C_G^e v^G with the frame at mid-step: C_G^e(t + dt/2) = C_G^e (I + [w_eG dt/2 x])
        C_ge = np.swapaxes(fr["C_e"], -1, -2)
        C_mid = C_ge @ (np.eye(3) + skew(0.5 * dt * (fr["M"] @ v_mid[..., None])[..., 0]))
        state.pos = state.pos + (C_mid @ v_mid[..., None])[..., 0] * dt
    state.vel = v1
    fr.update(f=dv_f / dt, w_ef=w_ef, lat=lat, lon=lon, h=h)
    return fr


def error_dynamics(state: InsState, fr: Dict[str, np.ndarray]) -> np.ndarray:
    """F (B, 15, 15) of the error state at the step's start (module docstring)."""
    B = state.vel.shape[0]
    F = np.zeros((B, 15, 15))
    C, v, f, M = state.att, state.vel, fr["f"], fr["M"]
    w_ie, w_ef = fr["w_ie"], fr["w_ef"]
    F[:, 0:3, 0:3] = -skew(w_ie + w_ef)
    F[:, 0:3, 3:6] = M
    F[:, 0:3, 9:12] = -C
    F[:, 3:6, 0:3] = skew(f)
    F[:, 3:6, 3:6] = skew(v) @ M - skew(2.0 * w_ie + w_ef)
    F[:, 3:6, 12:15] = C
    if state.frame == "n":
        lat, h = fr["lat"], fr["h"]
        RM, RN = earth.radii(lat)
        rm, rn = RM + h, RN + h
        sL, cL, tL = np.sin(lat), np.cos(lat), np.tan(lat)
        vE, vN = v[:, 0], v[:, 1]
        z = np.zeros(B)
        Mie = np.stack([np.stack([z, z, z], -1), np.stack([-earth.OMEGA * sL, z, z], -1),
                        np.stack([earth.OMEGA * cL, z, z], -1)], -2)
        Men = np.stack([np.stack([z, z, vN / rm ** 2], -1), np.stack([z, z, -vE / rn ** 2], -1),
                        np.stack([vE / (cL ** 2 * rn), z, -vE * tL / rn ** 2], -1)], -2)
        F[:, 0:3, 6:9] = Mie + Men
        F[:, 3:6, 6:9] = skew(v) @ (2.0 * Mie + Men)
        F[:, 6:9, 3:6] = np.stack([np.stack([z, 1.0 / rm, z], -1), np.stack([1.0 / (cL * rn), z, z], -1),
                                   np.stack([z, z, np.ones(B)], -1)], -2)
        F[:, 6:9, 6:9] = np.stack([np.stack([z, z, -vN / rm ** 2], -1),
                                   np.stack([vE * tL / (cL * rn), z, -vE / (cL * rn ** 2)], -1),
                                   np.stack([z, z, z], -1)], -2)
    else:
        F[:, 6:9, 3:6] = np.swapaxes(fr["C_e"], -1, -2)   # dr_e' = C_G^e dv^G (Eq. 19, first term)
    return F


def process_noise(noise: InsNoise, dt: float) -> np.ndarray:
    """Q_d (15,) diagonal: white gyro / accelerometer noise on phi / dv (isotropic: the rotation
    into the frame leaves it unchanged) and the bias walks."""
    return np.concatenate([np.full(3, noise.gyro_arw ** 2), np.full(3, noise.accel_vrw ** 2), np.zeros(3),
                           np.full(3, noise.gyro_bias_walk ** 2), np.full(3, noise.accel_bias_walk ** 2)]) * dt


def propagate(P: np.ndarray, F: np.ndarray, dt: float, q: np.ndarray) -> np.ndarray:
    """``P <- Phi P Phi^T + Q``, ``Phi = I + F dt + (F dt)^2 / 2``."""
    Fd = F * dt
    Phi = np.eye(15) + Fd + 0.5 * Fd @ Fd
    P = Phi @ P @ np.swapaxes(Phi, -1, -2) + np.diag(q)
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def initial_cov(state: InsState, noise: InsNoise) -> np.ndarray:
    """P_0 (B, 15, 15) in the state's frame (n: position stds converted to rad)."""
    B = state.vel.shape[0]
    d = np.zeros((B, 15))
    d[:, 0:3] = np.asarray(noise.init_att) ** 2
    d[:, 3:6] = noise.init_vel ** 2
    if state.frame == "n":
        lat, h = state.pos[:, 0], state.pos[:, 2]
        RM, RN = earth.radii(lat)
        d[:, 6] = (noise.init_pos / (RM + h)) ** 2
        d[:, 7] = (noise.init_pos / ((RN + h) * np.cos(lat))) ** 2
        d[:, 8] = noise.init_pos ** 2
    else:
        d[:, 6:9] = noise.init_pos ** 2
    d[:, 9:12] = noise.init_gyro_bias ** 2
    d[:, 12:15] = noise.init_accel_bias ** 2
    return np.eye(15)[None] * d[:, None, :]


def gnss_update(state: InsState, r_gnss: np.ndarray, std: float) -> np.ndarray:
    """Kalman update with GNSS ECEF positions (B, 3) and the closed-loop correction (injection
    and reset). Returns the innovations (B, 3) (n: rad, rad, m)."""
    B = state.vel.shape[0]
    H = np.zeros((B, 3, 15))
    H[:, :, 6:9] = np.eye(3)
    fix = np.isfinite(r_gnss).all(-1)                    # runs without a fix: a zero row adds nothing
    r_gnss = np.where(fix[:, None], r_gnss, state.ecef())
    H[~fix] = 0.0
    if state.frame == "n":
        lat, lon, h = earth.geodetic(r_gnss)
        z = state.pos - np.stack([lat, lon, h], -1)
        z[:, 1] = (z[:, 1] + np.pi) % (2 * np.pi) - np.pi
        RM, RN = earth.radii(state.pos[:, 0])
        scale = np.stack([1.0 / (RM + state.pos[:, 2]), 1.0 / ((RN + state.pos[:, 2]) * np.cos(state.pos[:, 0])),
                          np.ones(B)], -1)
        R = np.eye(3)[None] * (std * scale)[:, None, :] ** 2
    else:
        z = state.pos - r_gnss
        R = np.broadcast_to(np.eye(3) * std ** 2, (B, 3, 3)).copy()
    z[~fix] = 0.0
    update(state, z, H, R)
    return z


def velocity_update(state: InsState, v_meas: np.ndarray, std: float) -> np.ndarray:
    """Kalman update with a velocity (B, 3) in the state's frame (a zero-velocity update at rest)."""
    B = state.vel.shape[0]
    H = np.zeros((B, 3, 15))
    H[:, :, 3:6] = np.eye(3)
    z = state.vel - v_meas
    update(state, z, H, np.broadcast_to(np.eye(3) * std ** 2, (B, 3, 3)).copy())
    return z


def update(state: InsState, z: np.ndarray, H: np.ndarray, R: np.ndarray) -> None:
    """``z = h(x~) - measurement`` (computed minus measured, as the error state): the shared
    Joseph-form update (:func:`tcn_ahrs.filters.kalman.kalman_update`), then the correction."""
    import torch

    from ..filters.kalman import kalman_update

    dx, P = kalman_update(torch.from_numpy(state.P), torch.from_numpy(z), torch.from_numpy(H), torch.from_numpy(R))
    state.P = 0.5 * (P.numpy() + np.swapaxes(P.numpy(), -1, -2))
    correct(state, dx.numpy())


def correct(state: InsState, dx: np.ndarray) -> None:
    """Inject an estimated error and reset it to zero: ``C <- exp([phi x]) C~``, v and p minus their
    (computed minus true) errors, the bias estimates plus theirs (true minus estimated)."""
    state.att = exp_so3(dx[:, 0:3]) @ state.att
    state.vel = state.vel - dx[:, 3:6]
    state.pos = state.pos - dx[:, 6:9]
    state.gyro_bias = state.gyro_bias + dx[:, 9:12]
    state.accel_bias = state.accel_bias + dx[:, 12:15]


def transform_matrix(lat: np.ndarray, lon: np.ndarray, h: np.ndarray, v_grid: np.ndarray) -> np.ndarray:
    """Phi (B, 15, 15) with ``x_G = Phi x_n`` (Eqs. 32-33): ``phi_G = C_n^G phi_n + [0, 0, -dsigma]``
    (Eqs. 28-29), ``dv_G = C_n^G dv_n + v_G x [0, 0, -dsigma]`` (Eq. 30), ``dr_e = Phi_c (dL,
    dlambda, dh)`` (Eq. 31, exact radii) with ``dsigma = (cos L sin lon cos lon dL + sin L dlambda)
    / (1 - cos^2 L sin^2 lon)`` (Eq. 23 in a form without 1 / sin L). Phi_a here is the paper's with
    the sign of its third row corrected (as printed it contradicts Eq. 29)."""
    B = lat.shape[0]
    C = earth.grid_from_enu(earth.grid_angle(lat, lon))
    d2 = 1.0 - (np.cos(lat) * np.sin(lon)) ** 2
    Phi_a = np.zeros((B, 3, 3))
    Phi_a[:, 2, 0] = -np.cos(lat) * np.sin(lon) * np.cos(lon) / d2
    Phi_a[:, 2, 1] = -np.sin(lat) / d2
    Phi = np.zeros((B, 15, 15))
    Phi[:, 0:3, 0:3] = C
    Phi[:, 0:3, 6:9] = Phi_a
    Phi[:, 3:6, 3:6] = C
    Phi[:, 3:6, 6:9] = skew(v_grid) @ Phi_a
    Phi[:, 6:9, 6:9] = earth.ecef_jacobian(lat, h, lon)
    Phi[:, 9:15, 9:15] = np.eye(6)
    return Phi


def switch_frame(state: InsState, to: str, transform: bool = True) -> InsState:
    """The state in the other frame: navigation parameters converted exactly (``C_b^G = C_n^G C_b^n``,
    ``v^G = C_n^G v^n``, ECEF <-> geodetic), the covariance by Eq. 34 (``transform``; Eq. 35 the
    other way) or carried over unchanged (the paper's "non-covariance transformation")."""
    if to == state.frame:
        return state.copy()
    lat, lon, h = state.geodetic()
    C = earth.grid_from_enu(earth.grid_angle(lat, lon))
    if to == "G":
        att, vel, pos = C @ state.att, (C @ state.vel[..., None])[..., 0], earth.ecef(lat, lon, h)
    elif to == "n":
        Ct = np.swapaxes(C, -1, -2)
        att, vel, pos = Ct @ state.att, (Ct @ state.vel[..., None])[..., 0], np.stack([lat, lon, h], -1)
    else:
        raise ValueError(f"frame: expected 'n' or 'G', got {to!r}")
    P = None if state.P is None else state.P.copy()
    if transform and P is not None:
        Phi = transform_matrix(lat, lon, h, vel if to == "G" else state.vel)
        if to == "n":
            Phi = np.linalg.inv(Phi)                      # Eq. 35
        P = Phi @ P @ np.swapaxes(Phi, -1, -2)
        P = 0.5 * (P + np.swapaxes(P, -1, -2))
    return InsState(to, att, vel, pos, state.gyro_bias.copy(), state.accel_bias.copy(), P)


def attitude_error_enu(state: InsState, C_bn_true: np.ndarray) -> np.ndarray:
    """Small-angle attitude error (B, 3) [E, N, U] of the estimate against a true ``C_b^n``, in n
    (grid estimates rotated back by their own sigma), computed minus true."""
    C = state.att
    if state.frame == "G":
        lat, lon, _ = state.geodetic()
        C = np.swapaxes(earth.grid_from_enu(earth.grid_angle(lat, lon)), -1, -2) @ C
    return -Rotation.from_matrix(C @ np.swapaxes(C_bn_true, -1, -2)).as_rotvec()


def navigate(state: InsState, dtheta: np.ndarray, dv: np.ndarray, dt: float, gnss: Optional[np.ndarray],
             gnss_every: int, noise: InsNoise, switch_at: Optional[int] = None, switch_to: str = "G",
             transform: Optional[np.ndarray] = None, record_every: int = 1,
             zupt_std: Optional[float] = None) -> Dict[str, np.ndarray]:
    """Run the INS/GNSS filter over increments (B, K, 3) at period dt; GNSS ECEF positions (B, K // gnss_every, 3)
    (NaN rows: none); ``zupt_std``: a zero-velocity update with this std (m/s) at each GNSS epoch
    (a stationary alignment). ``switch_at``: step index where the filter changes to ``switch_to``;
    ``transform`` (B,) bool: which runs transform the covariance there. The covariance propagates
    over each GNSS interval with F at its start. Returns per recorded step ``ecef`` (B, T, 3),
    ``att_n`` (B, T, 3, 3) (C_b^n), ``gyro_bias``, ``accel_bias`` (B, T, 3), ``step`` (T,), ``frame`` (T,)."""
    B, K = dtheta.shape[:2]
    if switch_at is not None and switch_at % gnss_every:
        # the covariance propagates per GNSS interval with F of the interval's start frame
        raise ValueError(f"switch_at: expected a multiple of gnss_every ({gnss_every}) steps, got {switch_at}")
    q = process_noise(noise, dt * gnss_every)
    rec = {k: [] for k in ("ecef", "att_n", "gyro_bias", "accel_bias", "step", "frame")}
    if state.P is None:
        state.P = initial_cov(state, noise)
    f_sum = np.zeros((B, 3))
    F = None
    for k in range(K):
        if switch_at is not None and k == switch_at:
            flags = np.ones(B, bool) if transform is None else np.asarray(transform, bool)
            a = switch_frame(state, switch_to, True)
            b = switch_frame(state, switch_to, False)
            a.P = np.where(flags[:, None, None], a.P, b.P)
            state = a
        fr = mechanise(state, dtheta[:, k], dv[:, k], dt)
        if k % gnss_every == 0:
            F = error_dynamics(state, fr)
            f_sum[:] = 0.0
        f_sum += fr["f"]
        if (k + 1) % gnss_every == 0:
            # F with the interval's mean specific force (the f x phi coupling that makes heading observable)
            F[:, 3:6, 0:3] = skew(f_sum / gnss_every)
            state.P = propagate(state.P, F, dt * gnss_every, q)
            j = (k + 1) // gnss_every - 1
            if gnss is not None and j < gnss.shape[1] and np.isfinite(gnss[:, j]).any():
                gnss_update(state, gnss[:, j], noise.gnss_std)
            if zupt_std is not None:
                velocity_update(state, np.zeros_like(state.vel), zupt_std)
        if k % record_every == record_every - 1:
            lat, lon, h = state.geodetic()
            rec["ecef"].append(state.ecef())
            C = state.att
            if state.frame == "G":
                C = np.swapaxes(earth.grid_from_enu(earth.grid_angle(lat, lon)), -1, -2) @ C
            rec["att_n"].append(C)
            rec["gyro_bias"].append(state.gyro_bias.copy())
            rec["accel_bias"].append(state.accel_bias.copy())
            rec["step"].append(k + 1)
            rec["frame"].append(state.frame)
    out = {k: np.stack(v, 1) if k not in ("step", "frame") else np.asarray(v) for k, v in rec.items()}
    out["state"] = state
    return out


__all__ = ["InsNoise", "InsState", "preintegrate", "frame_rates", "mechanise", "error_dynamics", "propagate",
           "initial_cov", "gnss_update", "velocity_update", "update", "correct", "transform_matrix", "switch_frame", "attitude_error_enu",
           "navigate"]
