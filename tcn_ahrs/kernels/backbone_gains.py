"""The backbone's coefficients and gains (Laidig & Seel, VQF, Information Fusion 91 (2023), Sec. 3):
the formulas from its parameters and the step ts that every reading of the backbone shares — the
scalar kernel (:mod:`tcn_ahrs.kernels.backbone`, numba floats and torch (B,) tensors) and the
exported vector graph (:mod:`tcn_ahrs.export.backbone_graph`, which calls them on (K,) tensors).

Built like the kernel (:mod:`tcn_ahrs.kernels.ops`): this file's ``ops`` is the float table when
imported, and :func:`~tcn_ahrs.kernels.ops.load_kernel` executes it again with another table.
"""
from __future__ import annotations

import math

from .ops import float_ops

ops = globals().get("__ops__") or float_ops()
jit, where, both, tan, exp, fmax = ops.jit, ops.where, ops.both, ops.tan, ops.exp, ops.fmax
PI = math.pi


@jit
def butter_terms(tau, ts):
    """2nd-order Butterworth low-pass (VQF's filterCoeffs) at step ts, cut-off √2/(2π τ):
    (b0, a1, a2); b1 = 2 b0, b2 = b0."""
    cc = tan(PI * (math.sqrt(2.0) / (2.0 * PI * tau)) * ts)
    d = cc * cc + math.sqrt(2.0) * cc + 1.0
    return cc * cc / d, 2.0 * (cc * cc - 1.0) / d, (1.0 - math.sqrt(2.0) * cc + cc * cc) / d

@jit
def first_order_gain(tau, ts):
    """The gain of a first-order low-pass with 1/e time tau at step ts."""
    return 1.0 - exp(-ts / tau)

@jit
def bias_noise(sigma_init, forget, sigma_motion, vert_forget, sigma_rest, ts):
    """The bias Kalman filter's noise at step ts (Sec. 3.4), covariances in (0.01 °/s)² as VQF:
    (P0, V, W_motion, W_vertical, W_rest). The system noise V grows the variance from 0 to
    (0.1 °/s)² in ``forget`` seconds; W = σ⁴/V + σ² for a measurement of accuracy σ."""
    v = (0.1 * 100.0) ** 2 * ts / forget
    pm = (sigma_motion * 100.0) ** 2
    wm = pm * pm / v + pm
    pr = (sigma_rest * 100.0) ** 2
    return (sigma_init * 100.0) ** 2, v, wm, wm / fmax(vert_forget, 1e-10), pr * pr / v + pr

@jit
def wrap_pi(a):
    """An angle wrapped to [-π, π] (one turn at most, as a step's change is)."""
    return where(a > PI, a - 2.0 * PI, where(a < -PI, a + 2.0 * PI, a))

@jit
def rejection_gain(k, disturbed, rej_t, max_rej_t, factor, ts):
    """The heading gain under magnetic disturbance rejection (Sec. 3.3): no correction while
    disturbed, for at most ``max_rej_t`` seconds, then k / ``factor``; the allowance recovers at
    ``factor`` × real time. -> (gain, rejection time)."""
    within = rej_t <= max_rej_t
    gain = where(disturbed, where(within, 0.0 * k, k / factor), k)
    return gain, where(disturbed, where(within, rej_t + ts, rej_t), fmax(rej_t - factor * ts, 0.0 * k))

@jit
def initial_gain(k, ki, tau_mag, ts):
    """Fast initial convergence (VQF): while ki ≠ 0 the heading gain is at least ki (1/N over the
    first N samples: ki -> ki / (ki + 1)), until ki tau_mag < ts. -> (gain, next ki)."""
    active = ki != 0.0
    gain = where(both(active, k < ki), ki + 0.0 * k, k)
    ki_next = ki / (ki + 1.0)
    return gain, where(active, where(ki_next * tau_mag < ts, 0.0 * ki, ki_next), ki)
