"""Simulator of the particle-filter report's evaluation: a small differential-drive robot (AMiRo-
like) with a laser scanner in an arena mapped as an occupancy grid (5 cm cells), driving a
rectangle repeatedly by its own localisation, seeded. Ray casting lives here only (the filter
uses the likelihood field).

Arena (default): 3 m x 2 m inside walls, three box obstacles placed without symmetry (a bare
rectangle looks the same rotated by 180 deg: global localisation would have two answers).
Scanner: 240 deg field of view, ``n_beams`` beams, 4 m range, Gaussian range noise (a URG-04LX-
like sensor). Odometry: wheel slip as a per-step scale error on the true increments plus white
noise, so the odometry pose drifts from the truth.

The drive (:func:`drive_rectangle`): waypoints at the rectangle's corners and back to the start,
steered by the *estimated* pose (turn in place until within ``yaw_tol`` of the bearing, then
forward), a waypoint reached when the estimate is within ``pos_tol`` (the report: 0.03 m and 0.1
rad); at the start pose the robot turns to the start heading. The end-pose deviation of each lap
is the true pose's difference to the true start (the report's measure).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np


@dataclass(frozen=True)
class Arena:
    width: float = 3.0
    height: float = 2.0
    resolution: float = 0.05
    wall: float = 0.05
    boxes: Tuple[Tuple[float, float, float, float], ...] = ((0.5, 1.2, 0.9, 1.5), (2.0, 0.3, 2.3, 0.8),
                                                           (1.4, 1.6, 1.6, 2.0))  # (x0, y0, x1, y1) m

    def grid(self) -> Tuple[np.ndarray, float, Tuple[float, float]]:
        """(occupancy (H, W) bool, resolution, origin): walls around [0, width] x [0, height]."""
        r = self.resolution
        ox, oy = -self.wall, -self.wall
        W = int(round((self.width + 2 * self.wall) / r))
        H = int(round((self.height + 2 * self.wall) / r))
        xs = ox + (np.arange(W) + 0.5) * r
        ys = oy + (np.arange(H) + 0.5) * r
        X, Y = np.meshgrid(xs, ys)
        occ = (X < 0) | (X > self.width) | (Y < 0) | (Y > self.height)
        for x0, y0, x1, y1 in self.boxes:
            occ |= (X >= x0) & (X <= x1) & (Y >= y0) & (Y <= y1)
        return occ, r, (ox, oy)


@dataclass(frozen=True)
class Scanner:
    fov: float = math.radians(240.0)
    n_beams: int = 61
    max_range: float = 4.0
    noise: float = 0.01

    def angles(self) -> np.ndarray:
        return np.linspace(-self.fov / 2, self.fov / 2, self.n_beams)


def ray_cast(grid: np.ndarray, res: float, origin: Tuple[float, float], pose: np.ndarray, angles: np.ndarray,
             max_range: float, step: Optional[float] = None) -> np.ndarray:
    """True ranges (M,) from pose (3,) along angles (M,): march each ray in steps of res/4 to the
    first occupied cell (NaN: nothing within max_range)."""
    step = step or res / 4.0
    s = np.arange(step, max_range + step, step)
    th = pose[2] + angles
    x = pose[0] + s[None] * np.cos(th)[:, None]
    y = pose[1] + s[None] * np.sin(th)[:, None]
    j = np.floor((x - origin[0]) / res).astype(int)
    i = np.floor((y - origin[1]) / res).astype(int)
    inside = (i >= 0) & (i < grid.shape[0]) & (j >= 0) & (j < grid.shape[1])
    hit = np.zeros_like(inside)
    hit[inside] = grid[i[inside], j[inside]]
    hit |= ~inside
    first = np.argmax(hit, 1)
    r = s[first]
    r[~hit.any(1)] = np.nan
    return r


@dataclass(frozen=True)
class Robot:
    speed: float = 0.1                 # m/s
    turn_rate: float = 0.6             # rad/s
    dt: float = 0.1                    # s per control / scan step
    slip: float = 0.02                 # odometry scale error std per step (translation and rotation)
    odom_noise: Tuple[float, float] = (0.002, 0.004)  # white odometry noise per step: m, rad
    radius: float = 0.05               # m, for the bumper check
    pos_tol: float = 0.03              # the report's tolerances
    yaw_tol: float = 0.1


def _move(pose: np.ndarray, trans: float, rot: float) -> np.ndarray:
    th = pose[2] + 0.5 * rot
    out = np.array([pose[0] + trans * math.cos(th), pose[1] + trans * math.sin(th), pose[2] + rot])
    out[2] = (out[2] + math.pi) % (2 * math.pi) - math.pi
    return out


def drive_rectangle(estimator: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray], start: np.ndarray,
                    size: Tuple[float, float], laps: int, seed: int, arena: Arena = Arena(), scanner: Scanner = Scanner(),
                    robot: Robot = Robot(), max_steps_per_leg: int = 2000,
                    kidnap: Optional[Tuple[int, np.ndarray]] = None) -> Dict[str, np.ndarray]:
    """Drive ``laps`` rectangles (``size`` m, counter-clockwise from ``start``) steered by
    ``estimator(odom_prev, odom_now, ranges) -> pose estimate``. ``kidnap``: (step, pose) -- the
    robot is carried to pose at that step (odometry unaware). Returns the true / odometry /
    estimated poses per step, the true end pose of each lap, the per-step filter time."""
    rng = np.random.default_rng(seed)
    grid, res, origin = arena.grid()
    angles = scanner.angles()
    true = np.asarray(start, float).copy()
    odom = true.copy()
    est = true.copy()
    c, s = math.cos(start[2]), math.sin(start[2])
    corners = [np.array([start[0] + dx * c - dy * s, start[1] + dx * s + dy * c])
               for dx, dy in ((size[0], 0.0), (size[0], size[1]), (0.0, size[1]), (0.0, 0.0))]
    log: Dict[str, List] = {"true": [], "odom": [], "est": [], "time": []}
    ends = []
    step = 0

    def advance(trans: float, rot: float):
        nonlocal true, odom, est, step
        true_t = trans * (1.0 + robot.slip * rng.standard_normal())
        true_r = rot * (1.0 + robot.slip * rng.standard_normal())
        if true_t > 0 and np.isfinite(ray_cast(grid, res, origin, true, np.zeros(1), true_t + robot.radius)[0]):
            true_t = 0.0                       # an obstacle within reach: the wheels slip in place
        true = _move(true, true_t, true_r)
        if kidnap is not None and step == kidnap[0]:
            true = np.asarray(kidnap[1], float).copy()
        prev = odom.copy()
        odom = _move(odom, trans + robot.odom_noise[0] * rng.standard_normal(),
                     rot + robot.odom_noise[1] * rng.standard_normal())
        r = ray_cast(grid, res, origin, true, angles, scanner.max_range)
        r = r + scanner.noise * rng.standard_normal(r.shape)
        t0 = time.perf_counter()
        est = np.asarray(estimator(prev, odom, r), float)
        log["time"].append(time.perf_counter() - t0)
        log["true"].append(true.copy())
        log["odom"].append(odom.copy())
        log["est"].append(est.copy())
        step += 1

    def turn_to(heading: float):
        for _ in range(max_steps_per_leg):
            err = (heading - est[2] + math.pi) % (2 * math.pi) - math.pi
            if abs(err) < robot.yaw_tol:
                return
            advance(0.0, float(np.clip(err, -robot.turn_rate * robot.dt, robot.turn_rate * robot.dt)))

    def go_to(p: np.ndarray):
        for _ in range(max_steps_per_leg):
            d = p - est[:2]
            dist = float(np.hypot(*d))
            if dist < robot.pos_tol:
                return
            bearing = math.atan2(d[1], d[0])
            err = (bearing - est[2] + math.pi) % (2 * math.pi) - math.pi
            if abs(err) > robot.yaw_tol:
                turn_to(bearing)
            else:
                advance(min(robot.speed * robot.dt, dist), 0.5 * err)

    for _ in range(laps):
        for p in corners:
            go_to(p)
        turn_to(float(start[2]))
        ends.append(true.copy())
    out = {k: np.asarray(v) for k, v in log.items()}
    out["ends"] = np.asarray(ends)
    out["start"] = np.asarray(start, float)
    return out


__all__ = ["Arena", "Scanner", "Robot", "ray_cast", "drive_rectangle"]
