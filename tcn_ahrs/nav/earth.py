"""WGS-84 Earth model and the grid frame of polar navigation, numpy float64, batched over leading axes.

Geodetic <-> ECEF conversions are pymap3d's (``geodetic``/``ecef``); what pymap3d does not have is
here: the radii of curvature, normal gravity, the local ENU frame (``C_e^n``), and the grid frame
of ``../shared/papers/ins-gnss-grid-frame-covariance-transformation.txt`` (its equation numbers):
the grid angle sigma (Eq. 1), ``C_n^G`` (Eq. 4), ``C_e^G = C_n^G C_e^n`` (Eq. 2) and the grid
transport-rate coefficients of Eq. 8, which the paper names but does not define (derived here:
``1/R_x``, ``1/R_y``, ``1/tau_f``, ``kappa``; tested against ``-dC_e^G/dt C_G^e`` along a motion).

Frames: e = ECEF; n = local ENU (east, north, up); G = grid east, grid north, up (grid north is
the horizontal direction parallel to the Greenwich meridian plane; sigma, the angle from true
north to grid north, positive clockwise). Angles in rad, lengths in m.
"""
from __future__ import annotations

from typing import Tuple

import numpy as np

A = 6378137.0                      # WGS-84 semi-major axis, m
F = 1.0 / 298.257223563            # flattening
E2 = F * (2.0 - F)                 # first eccentricity squared
OMEGA = 7.292115e-5                # Earth rotation rate, rad/s
GM = 3.986004418e14                # m^3/s^2
B_AXIS = A * (1.0 - F)
G_EQUATOR = 9.7803253359           # normal gravity at the equator, m/s^2 (Somigliana)
K_SOMIGLIANA = 0.00193185265241
M_RATIO = OMEGA ** 2 * A ** 2 * B_AXIS / GM


def skew(v: np.ndarray) -> np.ndarray:
    """``[v x]`` (..., 3, 3) of v (..., 3). (The numpy twin of :func:`tcn_ahrs.so3.hat`, for the
    INS's numpy loops.)"""
    z = np.zeros_like(v[..., 0])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def geodetic(r_e: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lat, lon, h) of ECEF positions (..., 3) (pymap3d, WGS-84)."""
    import pymap3d

    lat, lon, h = pymap3d.ecef2geodetic(r_e[..., 0], r_e[..., 1], r_e[..., 2], deg=False)
    shape = r_e.shape[:-1]  # pymap3d may hand back 0-d values for one point
    return tuple(np.broadcast_to(np.asarray(x, float), shape).copy() for x in (lat, lon, h))


def ecef(lat: np.ndarray, lon: np.ndarray, h: np.ndarray) -> np.ndarray:
    """ECEF positions (..., 3) of geodetic (lat, lon, h) (pymap3d, WGS-84; the paper's Eq. 9)."""
    import pymap3d

    return np.stack([np.asarray(c, float) for c in pymap3d.geodetic2ecef(lat, lon, h, deg=False)], -1)


def radii(lat: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(R_M meridian, R_N prime vertical) radii of curvature, m. (The paper's R_N is the prime
    vertical one, its Eq. 9.)"""
    s2 = np.sin(lat) ** 2
    w = np.sqrt(1.0 - E2 * s2)
    return A * (1.0 - E2) / w ** 3, A / w


def gravity(lat: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Normal gravity magnitude (Somigliana, with the second-order free-air height correction), m/s^2;
    along -up in n and G (their up axes are the same)."""
    s2 = np.sin(lat) ** 2
    g0 = G_EQUATOR * (1.0 + K_SOMIGLIANA * s2) / np.sqrt(1.0 - E2 * s2)
    return g0 * (1.0 - 2.0 / A * (1.0 + F + M_RATIO - 2.0 * F * s2) * h + 3.0 / A ** 2 * h ** 2)


def enu_from_ecef(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """``C_e^n`` (..., 3, 3), the paper's Eq. 3 (rows: east, north, up in ECEF)."""
    sL, cL, sl, cl = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    z = np.zeros_like(sL)
    return np.stack([np.stack([-sl, cl, z], -1),
                     np.stack([-sL * cl, -sL * sl, cL], -1),
                     np.stack([cL * cl, cL * sl, sL], -1)], -2)


def grid_angle(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """sigma of Eq. 1: ``atan2(sin L sin lambda, cos lambda)`` (defined up to the pole, where it is
    lambda; singular only on the equator at lambda = +-90 deg, far from where the grid is used)."""
    return np.arctan2(np.sin(lat) * np.sin(lon), np.cos(lon))


def grid_from_enu(sigma: np.ndarray) -> np.ndarray:
    """``C_n^G`` (..., 3, 3), Eq. 4."""
    s, c = np.sin(sigma), np.cos(sigma)
    z, o = np.zeros_like(s), np.ones_like(s)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def grid_from_ecef(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """``C_e^G = C_n^G C_e^n`` (Eq. 2)."""
    return grid_from_enu(grid_angle(lat, lon)) @ enu_from_ecef(lat, lon)


def transport_matrix_grid(lat: np.ndarray, lon: np.ndarray, h: np.ndarray) -> np.ndarray:
    """M (..., 3, 3) with ``omega_eG^G = M v^G`` (Eq. 8; zero third column: the vertical velocity
    does not turn the frame). The paper's undefined coefficients, derived from the ENU transport
    rate rotated by sigma plus the grid's own turn ``-sigma_dot`` about up::

        1/R_x = sin^2 s/(R_M+h) + cos^2 s/(R_N+h),   1/R_y = cos^2 s/(R_M+h) + sin^2 s/(R_N+h)
        1/tau_f = (1/(R_M+h) - 1/(R_N+h)) sin s cos s,   kappa = cos L sin lon / sqrt(1 - cos^2 L sin^2 lon)

    (kappa: grid north stays orthogonal to the ECEF y axis, which ties the vertical rate to the
    horizontal ones; finite at the pole, unlike the ENU ``v_E tan L / (R_N+h)``.)"""
    RM, RN = radii(lat)
    a, b = 1.0 / (RM + h), 1.0 / (RN + h)
    s = grid_angle(lat, lon)
    ss, cc, sc = np.sin(s) ** 2, np.cos(s) ** 2, np.sin(s) * np.cos(s)
    inv_rx, inv_ry, inv_tau = ss * a + cc * b, cc * a + ss * b, (a - b) * sc
    kappa = np.cos(lat) * np.sin(lon) / np.sqrt(1.0 - (np.cos(lat) * np.sin(lon)) ** 2)
    z = np.zeros_like(a)
    return np.stack([np.stack([inv_tau, -inv_ry, z], -1),
                     np.stack([inv_rx, -inv_tau, z], -1),
                     np.stack([kappa * inv_tau, -kappa * inv_ry, z], -1)], -2)


def transport_matrix_enu(lat: np.ndarray, h: np.ndarray) -> np.ndarray:
    """M (..., 3, 3) with ``omega_en^n = M v^n``: ``[-v_N/(R_M+h), v_E/(R_N+h), v_E tan L/(R_N+h)]``."""
    RM, RN = radii(lat)
    z = np.zeros_like(RM)
    return np.stack([np.stack([z, -1.0 / (RM + h), z], -1),
                     np.stack([1.0 / (RN + h), z, z], -1),
                     np.stack([np.tan(lat) / (RN + h), z, z], -1)], -2)


def earth_rate_enu(lat: np.ndarray) -> np.ndarray:
    """``omega_ie^n`` (..., 3) = ``[0, Omega cos L, Omega sin L]``."""
    return np.stack([np.zeros_like(lat), OMEGA * np.cos(lat), OMEGA * np.sin(lat)], -1)


def ecef_jacobian(lat: np.ndarray, h: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """``d r_e / d(L, lambda, h)`` (..., 3, 3), the paper's Eq. 31 / Phi_c with the exact
    meridian radius (R_M + h) in the latitude column (the paper writes (R_N + h) and
    [R_N (1-f)^2 + h], which neglects dR_N/dL: centimetres for 10 m errors)."""
    RM, RN = radii(lat)
    sL, cL, sl, cl = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    col_L = (RM + h)[..., None] * np.stack([-sL * cl, -sL * sl, cL], -1)
    col_l = ((RN + h) * cL)[..., None] * np.stack([-sl, cl, np.zeros_like(sl)], -1)
    col_h = np.stack([cL * cl, cL * sl, sL], -1)
    return np.stack([col_L, col_l, col_h], -1)


__all__ = ["A", "F", "E2", "OMEGA", "skew", "geodetic", "ecef", "radii", "gravity", "enu_from_ecef", "grid_angle",
           "grid_from_enu", "grid_from_ecef", "transport_matrix_grid", "transport_matrix_enu", "earth_rate_enu",
           "ecef_jacobian"]
