"""The learned closed loop's per-sample update on scalars (typed scalar kernels, see
:mod:`tcn_ahrs.kernels`): compiled by numba (:mod:`tcn_ahrs.model.closed_loop_compiled`:
evaluation, CPU training, the streaming runtime) and read by TorchScript
(:func:`tcn_ahrs.model.closed_loop_step.scan_scalar`: the exported batch and streaming modules).

:func:`tcn_ahrs.model.closed_loop.closed_loop_scan` is the same recursion on tensors — the
differentiable path that training backpropagates through; ``tests/test_closed_loop_step.py``
holds the readings equal (1e-12 rad).

Per sample k (see the module docstring of :mod:`tcn_ahrs.model.closed_loop` for the symbols)::

    w   = k_acc τ_acc â × (C^T up) + k_mag τ_mag east_b × (C^T east_ref)   (Eqs. 23/24)
    b  <- b − k_bias w dt + min(1, ρ dt / T_rest) (ω̂_gyr − b)
    C  <- C exp((ω̂_gyr − b + w) dt)        exp by the Taylor series of the tensor scan
"""
# No `from __future__ import annotations`: TorchScript reads the annotations as real types.
import math
from typing import Tuple


def closed_loop_update(r00: float, r01: float, r02: float, r10: float, r11: float, r12: float,
                       r20: float, r21: float, r22: float, b0: float, b1: float, b2: float,
                       gx: float, gy: float, gz: float, ax: float, ay: float, az: float,
                       mx: float, my: float, mz: float, ka: float, km: float, kr: float,
                       e0: float, e1: float, e2: float, dt: float, kb: float
                       ) -> Tuple[float, float, float, float, float, float, float, float, float,
                                  float, float, float, float, float, float]:
    """One sample: state C (r00..r22, ``nav_from_body``), bias b, inputs (see :data:`ROW`),
    east_ref (e0, e1, e2) nav, k_bias kb -> (C', b', w). Same operations, in the same order, as
    :func:`~tcn_ahrs.model.closed_loop.closed_loop_scan`."""
    # Eq. 23: â × (C^T up), C^T up = third row of C
    c0 = ka * (ay * r22 - az * r21)
    c1 = ka * (az * r20 - ax * r22)
    c2 = ka * (ax * r21 - ay * r20)
    # Eq. 24: east_b × (C^T east_ref)
    v0 = e0 * r00 + e1 * r10 + e2 * r20
    v1 = e0 * r01 + e1 * r11 + e2 * r21
    v2 = e0 * r02 + e1 * r12 + e2 * r22
    c0 = c0 + km * (my * v2 - mz * v1)
    c1 = c1 + km * (mz * v0 - mx * v2)
    c2 = c2 + km * (mx * v1 - my * v0)
    # integral term and, at rest, the gyro reading itself
    b0 = b0 - kb * c0 * dt + kr * (gx - b0)
    b1 = b1 - kb * c1 * dt + kr * (gy - b1)
    b2 = b2 - kb * c2 * dt + kr * (gz - b2)
    p0 = (gx - b0 + c0) * dt
    p1 = (gy - b1 + c1) * dt
    p2 = (gz - b2 + c2) * dt
    t2 = p0 * p0 + p1 * p1 + p2 * p2
    a = 1.0 - t2 / 6.0 * (1.0 - t2 / 20.0 * (1.0 - t2 / 42.0))
    c = 0.5 - t2 / 24.0 * (1.0 - t2 / 30.0 * (1.0 - t2 / 56.0))
    # C exp(φ^): each row r_i <- r_i + a (r_i × φ) + c ((r_i × φ) × φ)
    k0, k1, k2 = r01 * p2 - r02 * p1, r02 * p0 - r00 * p2, r00 * p1 - r01 * p0
    n00, n01, n02 = (r00 + a * k0 + c * (k1 * p2 - k2 * p1), r01 + a * k1 + c * (k2 * p0 - k0 * p2),
                     r02 + a * k2 + c * (k0 * p1 - k1 * p0))
    k0, k1, k2 = r11 * p2 - r12 * p1, r12 * p0 - r10 * p2, r10 * p1 - r11 * p0
    n10, n11, n12 = (r10 + a * k0 + c * (k1 * p2 - k2 * p1), r11 + a * k1 + c * (k2 * p0 - k0 * p2),
                     r12 + a * k2 + c * (k0 * p1 - k1 * p0))
    k0, k1, k2 = r21 * p2 - r22 * p1, r22 * p0 - r20 * p2, r20 * p1 - r21 * p0
    n20, n21, n22 = (r20 + a * k0 + c * (k1 * p2 - k2 * p1), r21 + a * k1 + c * (k2 * p0 - k0 * p2),
                     r22 + a * k2 + c * (k0 * p1 - k1 * p0))
    return n00, n01, n02, n10, n11, n12, n20, n21, n22, b0, b1, b2, c0, c1, c2


def rest_update(s0: float, s1: float, s2: float, s3: float, s4: float, s5: float,
                g0: float, g1: float, g2: float, a0: float, a1: float, a2: float,
                o0: float, o1: float, o2: float, o3: float, o4: float, o5: float, t: int, window: int,
                last_gyro: int, last_acc: int, rest_gyro: float, rest_acc: float
                ) -> Tuple[float, float, float, float, float, float, int, int, float]:
    """:func:`~tcn_ahrs.model.closed_loop.rest_detector` one sample at a time (the streaming
    exports): running sums s of the raw gyro, acc over the window, plus the newest reading
    (g, a), minus the one leaving it (o; zeros while t < window), the index of the last sample
    that deviated from the window mean by ``rest_gyro`` / ``rest_acc`` or more. Returns the new
    sums and indices and the flag at sample t (1.0: every sample of the last ``window`` stayed
    within the thresholds, and the detector has watched ``window`` samples)."""
    s0, s1, s2 = s0 + g0 - o0, s1 + g1 - o1, s2 + g2 - o2
    s3, s4, s5 = s3 + a0 - o3, s4 + a1 - o4, s5 + a2 - o5
    inv = 1.0 / float(min(t + 1, window))
    d0, d1, d2 = g0 - s0 * inv, g1 - s1 * inv, g2 - s2 * inv
    if not d0 * d0 + d1 * d1 + d2 * d2 < rest_gyro * rest_gyro:
        last_gyro = t
    d0, d1, d2 = a0 - s3 * inv, a1 - s4 * inv, a2 - s5 * inv
    if not d0 * d0 + d1 * d1 + d2 * d2 < rest_acc * rest_acc:
        last_acc = t
    rest = 0.0
    if t + 1 >= window and t - last_gyro >= window and t - last_acc >= window:
        rest = 1.0
    return s0, s1, s2, s3, s4, s5, last_gyro, last_acc, rest


def repeat_count(p0: float, p1: float, p2: float, x: float, y: float, z: float, count: int, t: int) -> int:
    """Sensor health: how many samples in a row a reading (x, y, z) has repeated the one before
    (p0, p1, p2) exactly; frozen from ``count >= window - 1`` (:func:`~tcn_ahrs.model.closed_loop.frozen_detector`
    on tensors). ``t``: the sample's index (the first has nothing before it)."""
    if t > 0 and x == p0 and y == p1 and z == p2:
        return count + 1
    return 0


def gap_step(typical: float, dt: float, factor: float) -> Tuple[float, float]:
    """Sensor health: the backbone's gap rule (kernels/backbone.py ``gyro_update``) one step at a
    time -> (the typical step after dt, 1.0 where dt is longer than ``factor`` × the typical step
    before it: samples were lost). ``typical`` 0: no step seen yet; ``factor`` 0: no check."""
    gap = 0.0
    if factor > 0.0 and typical > 0.0 and dt > factor * typical:
        gap = 1.0
    if typical > 0.0:
        typical = typical + 0.1 * (dt - typical)
    else:
        typical = dt
    return typical, gap


def loop_inputs(ax: float, ay: float, az: float, bx: float, by: float, bz: float,
                rx: float, ry: float, rz: float, field_norm: float, acc_logit: float, mag_logit: float,
                use_acc: bool, use_mag: bool, acc_gain: float, mag_gain: float, acc_reject: float,
                gravity: float, mag_min: float, mag_max: float
                ) -> Tuple[float, float, float, float, float, float, float, float]:
    """What :meth:`ClosedLoopFilter.run` / ``forward`` compute from one sample before the loop:
    calibrated acc (a), calibrated field (b), raw acc (r), the raw field's norm (µT) and the trust
    logits -> unit(â) (3), east_b = unit(b̂ × a_raw) (3; zeros without the magnetometer),
    k_acc τ_acc, k_mag τ_mag (the Eq. 7 gates applied)."""
    mx, my, mz = 0.0, 0.0, 0.0
    if use_mag:
        mx, my, mz = by * rz - bz * ry, bz * rx - bx * rz, bx * ry - by * rx
        n = max(math.sqrt(mx * mx + my * my + mz * mz), 1e-9)
        mx, my, mz = mx / n, my / n, mz / n
    acc_ok = True
    if acc_reject > 0.0:
        acc_ok = abs(math.sqrt(rx * rx + ry * ry + rz * rz) - gravity) < acc_reject
    mag_ok = acc_ok
    if mag_max > 0.0:
        mag_ok = acc_ok and field_norm > mag_min and field_norm < mag_max
    ka, km = 0.0, 0.0
    if use_acc and acc_ok:
        ka = acc_gain * 2.0 / (1.0 + math.exp(-acc_logit))
    if use_mag and mag_ok:
        km = mag_gain * 2.0 / (1.0 + math.exp(-mag_logit))
    n = max(math.sqrt(ax * ax + ay * ay + az * az), 1e-9)
    return ax / n, ay / n, az / n, mx, my, mz, ka, km


def east_reference_scalar(r00: float, r01: float, r02: float, r10: float, r11: float, r12: float,
                          mx: float, my: float, mz: float) -> Tuple[float, float, float]:
    """:func:`~tcn_ahrs.model.closed_loop.east_reference` from the first two rows of the initial
    ``nav_from_body`` and east_b = unit(b̂ × a_raw) of sample 0: the measured east, horizontal."""
    e0 = r00 * mx + r01 * my + r02 * mz
    e1 = r10 * mx + r11 * my + r12 * mz
    n = max(math.sqrt(e0 * e0 + e1 * e1), 1e-9)
    return e0 / n, e1 / n, 0.0
