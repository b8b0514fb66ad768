"""The VQF-grade backbone: one update of the attitude filter of Laidig & Seel, "VQF: Highly
accurate IMU orientation estimation with bias estimation and magnetic disturbance rejection",
Information Fusion 91 (2023), written on scalars once (this file's own code, following the
paper's Sec. 3 and the documented algorithm of the ``vqf`` package) and built for two backends
(:mod:`tcn_ahrs.kernels.ops`): numba floats and torch (B,) tensors.

Per sample, as in the paper (frames: body B, almost-inertial I_i, 6D earth E_i, earth E = ENU)::

    gyro   q_gyr <- q_gyr ⊗ exp((ω − b) dt / 2)                strapdown, Eq. (2)
    acc    a_I   = q_gyr a q_gyr*, low-passed (2nd-order Butterworth, τ_acc) in I_i   Sec. 3.2
           a_E   = q_acc a_I q_acc*,  q_acc <- rot(a_E -> up, τ_acc' angle) ⊗ q_acc   inclination
    bias   Kalman update of b from the inclination disagreement in motion (vertical axis
           barely observable) and from the low-passed gyro at rest                     Sec. 3.4
    mag    δ <- δ + k_mag·wrap(atan2(m_Ex, m_Ey) − δ), heading only; k_mag = 0 while the field's
           norm or dip departs from the recording's own reference (disturbance rejection) Sec. 3.3
    output q_6D = q_acc ⊗ q_gyr,  q_9D = [cos δ/2, 0, 0, sin δ/2] ⊗ q_6D    (nav_from_body, ENU)

The learned residuals enter through four per-sample inputs that equal 1 / 0 in the untrained
model (so the untrained model *is* this backbone): the gyro fed in (already corrected), the
accelerometer trust τ_acc' that scales the inclination correction angle, the magnetometer trust
that scales k_mag, and the bias trust that scales each Kalman bias increment. Trust 0 in all three
is plain strapdown integration with the bias frozen.

Deliberate differences from ``vqf``: :mod:`~tcn_ahrs.kernels.backbone_layout` (with the flat
state and coefficient vectors :data:`STATE`, :data:`COEFF` this step reads).
"""
from __future__ import annotations

import math

from .backbone_layout import (  # noqa: F401 (the layout, read by the step as constants; re-exported)
    BackboneParams, PARAM, STATE, COEFF, N_STATE, N_COEFF, N_PARAM, P_TAU_ACC, P_TAU_MAG, P_MOTION_BIAS, P_REST_BIAS,
    P_MAG_REJ, P_SIGMA_INIT, P_FORGET, P_CLIP, P_SIGMA_MOTION, P_VERT_FORGET, P_SIGMA_REST, P_REST_MIN_T, P_REST_TAU,
    P_REST_TH_G, P_REST_TH_A, P_MAG_CUR_TAU, P_MAG_REF_TAU, P_MAG_NORM_TH, P_MAG_DIP_TH, P_MAG_NEW_T,
    P_MAG_NEW_FIRST_T, P_MAG_NEW_MIN_G, P_MAG_MIN_UND_T, P_MAG_MAX_REJ_T, P_MAG_REJ_FACTOR, S_GQ, S_AQ, S_DELTA,
    S_REST, S_MAGDIST, S_KMINIT, S_BIAS, S_P, S_REST_T, S_REST_G, S_MREF_N, S_MREF_D, S_MUND_T, S_MREJ_T, S_MCAND_N,
    S_MCAND_D, S_MCAND_T, F_ACC, F_ROT, F_BIAS, F_RG, F_RA, F_MAG, C_TS, C_ACC_B, C_ACC_A, C_REST_B, C_REST_A, C_MAG_B,
    C_MAG_A, C_KMAG, C_KMAGREF, C_P0, C_V, C_WM, C_WV, C_WR, DEG, EPS, initial_state, S_GPREV, S_GSAME_T, S_GSAME_N,
    S_GFROZEN, S_APREV, S_ASAME_T, S_ASAME_N, S_AFROZEN, P_FROZEN_T, FROZEN_MIN_SAMPLES, S_GMAX, S_GCLIPPED, S_AMAX,
    S_ACLIPPED, P_GCLIP_FLOOR, P_ACLIP_FLOOR, CLIP_MIN_REPEATS, S_TS_TYP, S_GAP, P_GAP_F, S_HEAD_RESTART, S_ADISTRUST,
    S_MPREV, S_MSAME_T, S_MFROZEN, MAG_FROZEN_MIN_T, TS_TYP_RATE, TILT_MIN, TAU_FLOOR, CLIP_BRIDGE_VAR, P_REST_CHECK, S_CHK,
    # the causal check's (kernels/backbone_check.py: every translation reads the constants from here)
    S_CK_N, S_CK_T, S_CK_DEAD, S_CK_GREF, S_CK_GS, S_CK_GQ, S_CK_AREF, S_CK_AS, S_CK_AQ, S_CK_FLOOR, S_CK_RUN,
    S_CK_RUN_N, S_CK_RUN_G, S_CK_RUN_UP, CHECK_WINDOW, CHECK_NOISE_FACTOR, CHECK_MIN_WINDOWS, CHECK_TILT_DEG,
    CHECK_CLIP)
from . import backbone_check as _check_float
from . import backbone_gains as _gains_float
from . import quat as _quat
from .ops import float_ops, load_kernel

# ------------------------------------------------------------------------------ the step
# The ops table this module is built with: the float table (numba) when imported normally;
# :func:`tcn_ahrs.kernels.ops.load_kernel` executes this same file again with the torch table.
ops = globals().get("__ops__") or float_ops()
jit, where, both, either, negate, nograd = ops.jit, ops.where, ops.both, ops.either, ops.negate, ops.nograd
sqrt, sin, cos, tan, exp, atan2, asin, fabs = (ops.sqrt, ops.sin, ops.cos, ops.tan, ops.exp, ops.atan2,
                                               ops.asin, ops.fabs)
fmax, clip = ops.fmax, ops.clip
PI = math.pi
# the formulas shared with the exported graph (coefficients, gains), in this table's reading
_gains = _gains_float if ops.name == "float" else load_kernel(_gains_float, ops)
butter_terms, first_order_gain, bias_noise = _gains.butter_terms, _gains.first_order_gain, _gains.bias_noise
wrap_pi, rejection_gain, initial_gain = _gains.wrap_pi, _gains.rejection_gain, _gains.initial_gain
# the causal device check (kernels/backbone_check.py), in this table's reading
_check = _check_float if ops.name == "float" else load_kernel(_check_float, ops)
rest_check, check_window = _check.rest_check, _check.check_window
# the quaternion product, rotation and matrix, the 3x3 product A Bᵀ of kernels/quat.py, in this table's reading
qmul, qrot, qmat, mat3_mul_t = jit(_quat.qmul), jit(_quat.qrot), jit(_quat.qmat), jit(_quat.mat3_mul_t)

# ------------------------------------------------------------------ coefficients
@jit
def butter(c, at_b, at_a, tau, ts):
    """:func:`butter_terms` into ``c``; passthrough when τ < ts/2 (cut-off beyond 90 % of Nyquist)."""
    b0, a1, a2 = butter_terms(tau, ts)
    thru = tau < ts / 2.0
    c[at_b] = where(thru, 1.0 + 0.0 * b0, b0)
    c[at_b + 1] = where(thru, 0.0 * b0, 2.0 * b0)
    c[at_b + 2] = where(thru, 0.0 * b0, b0)
    c[at_a] = where(thru, 0.0 * b0, a1)
    c[at_a + 1] = where(thru, 0.0 * b0, a2)

@jit
def coefficients(p, ts, c):
    c[C_TS] = ts
    butter(c, C_ACC_B, C_ACC_A, p[P_TAU_ACC], ts)
    butter(c, C_REST_B, C_REST_A, p[P_REST_TAU], ts)
    butter(c, C_MAG_B, C_MAG_A, fmax(p[P_MAG_CUR_TAU], TAU_FLOOR), ts)
    c[C_KMAG] = first_order_gain(p[P_TAU_MAG], ts)
    c[C_KMAGREF] = first_order_gain(p[P_MAG_REF_TAU], ts)
    p0, v, wm, wv, wr = bias_noise(p[P_SIGMA_INIT], p[P_FORGET], p[P_SIGMA_MOTION], p[P_VERT_FORGET],
                                   p[P_SIGMA_REST], ts)
    c[C_P0], c[C_V], c[C_WM], c[C_WV], c[C_WR] = p0, v, wm, wv, wr

# ------------------------------------------------------------------ low-pass filters
# A group of d components at s[f]: [running, count, x1 (d), x2 (d), y1 (d), y2 (d)]. For the first
# tau seconds the output is the mean so far (x1 holds the sum), then the filter starts from it in
# steady state (VQF's filterVec). Direct form I: its memory (last two inputs and outputs) means the
# same whatever the coefficients, so a step that changes every sample continues the signal (VQF's
# transposed form II jumps: ±30 % stamp jitter flagged 100 % of samples magnetically disturbed, 69 %
# evenly). With a fixed step both are one difference equation.
@jit
def lp_begin(s, f, tau, ts):
    run = s[f] > 0.5
    n = s[f + 1] + 1.0
    s[f + 1] = where(run, s[f + 1], n)
    start = both(negate(run), n * ts >= tau)
    return run, n, start

@jit
def lp(s, c, f, d, i, x, at_b, at_a, run, n, start, held):
    x1 = f + 2 + i
    x2 = f + 2 + d + i
    y1 = f + 2 + 2 * d + i
    y2 = f + 2 + 3 * d + i
    b0, b1, b2, a1, a2 = c[at_b], c[at_b + 1], c[at_b + 2], c[at_a], c[at_a + 1]
    y = b0 * x + b1 * s[x1] + b2 * s[x2] - a1 * s[y1] - a2 * s[y2]
    total = s[x1] + x
    mean = total / n
    zero = 0.0 * mean
    # a running filter holds over a gap's step (S_GAP): its memory, read with the long step's
    # coefficients, then the short one's, overshoots (2 s gap: 142° for 6 s); and where its input is
    # no reading (``held``: a frozen accelerometer, else kept after the fault: 79-113° inclination)
    hold = both(run, either(s[S_GAP] > 0.5, held))
    y_old = s[y1]
    s[x2] = where(hold, s[x2], where(run, s[x1], where(start, mean, zero)))
    s[x1] = where(hold, s[x1], where(run, x, where(start, mean, total)))
    s[y2] = where(hold, s[y2], where(run, s[y1], where(start, mean, zero)))
    s[y1] = where(hold, s[y1], where(run, y, where(start, mean, zero)))
    return where(hold, y_old, where(run, y, mean))

@jit
def lp_end(s, f, run, start):
    s[f] = where(either(run, start), 1.0, 0.0)

@jit
def lp3(s, c, f, x0, x1, x2, at_b, at_a, tau, ts, held):
    """A three-component group through one step (a vector in one frame); ``held``: keep the memory."""
    run, n, start = lp_begin(s, f, tau, ts)
    y0 = lp(s, c, f, 3, 0, x0, at_b, at_a, run, n, start, held)
    y1 = lp(s, c, f, 3, 1, x1, at_b, at_a, run, n, start, held)
    y2 = lp(s, c, f, 3, 2, x2, at_b, at_a, run, n, start, held)
    lp_end(s, f, run, start)
    return y0, y1, y2

# ------------------------------------------------------------------ quaternion helpers
# (qmul, qrot, mat3_mul_t: kernels/quat.py, bound with the ops above)
@jit
def quat6(s):
    return qmul(s[S_AQ], s[S_AQ + 1], s[S_AQ + 2], s[S_AQ + 3], s[S_GQ], s[S_GQ + 1], s[S_GQ + 2], s[S_GQ + 3])

@jit
def quat9(s):
    w, x, y, z = quat6(s)
    ch = cos(s[S_DELTA] / 2.0)
    sh = sin(s[S_DELTA] / 2.0)
    return ch * w - sh * z, ch * x - sh * y, ch * y + sh * x, ch * z + sh * w

# ------------------------------------------------------------------ gyroscope
@jit
def clip_axis(s, maxabs, prev, floor, v):
    """Whether one axis read its largest magnitude so far (above ``floor``) :data:`CLIP_MIN_REPEATS`
    times in a row: a saturated axis (run length kept at ``maxabs + 3``)."""
    a = fabs(v)
    at_max = both(a >= s[maxabs], both(floor > 0.0, a >= floor))
    s[maxabs] = fmax(s[maxabs], a)
    run = where(both(at_max, v == s[prev]), s[maxabs + 3] + 1.0, 0.0 * a)
    s[maxabs + 3] = run
    return run >= CLIP_MIN_REPEATS

@jit
def frozen_check(s, p, ts, prev, same_t, same_n, flag, maxabs, clipflag, floor, x, y, z):
    """Sensor health without ground truth: whether a sensor's three readings have repeated
    exactly (bit for bit) for ``frozen_time`` and :data:`FROZEN_MIN_SAMPLES` samples — a frozen
    or disconnected sensor; its noise makes a real one change. Kept in the state at ``prev``
    (last reading), ``same_t``/``same_n`` (how long it repeated), ``flag``; returns the flag.
    Also sets ``clipflag`` where an axis repeats its largest magnitude so far (above ``floor``)
    while another axis changes — a saturated axis, not a duplicated sample."""
    x_, y_, z_ = nograd(x), nograd(y), nograd(z)
    same = both(x_ == s[prev], both(y_ == s[prev + 1], z_ == s[prev + 2]))
    c0 = clip_axis(s, maxabs, prev, floor, x_)
    c1 = clip_axis(s, maxabs + 1, prev + 1, floor, y_)
    c2 = clip_axis(s, maxabs + 2, prev + 2, floor, z_)
    clipped = both(negate(same), either(c0, either(c1, c2)))
    s[clipflag] = where(clipped, 1.0 + 0.0 * x_, 0.0 * x_)
    t = where(same, s[same_t] + ts, 0.0 * x_)
    n = where(same, s[same_n] + 1.0, 0.0 * x_)
    frozen = both(p[P_FROZEN_T] > 0.0, both(t >= p[P_FROZEN_T], n >= FROZEN_MIN_SAMPLES))
    s[same_t], s[same_n] = t, n
    s[prev], s[prev + 1], s[prev + 2] = x_, y_, z_
    s[flag] = where(frozen, 1.0 + 0.0 * x_, 0.0 * x_)
    return frozen

@jit
def gyro_update(s, p, c, gx, gy, gz):
    ts = c[C_TS]
    # a gap (a step far longer than the typical one, a running mean: samples lost): the rate over
    # it is the mean of the readings either side (what resampling onto the grid gives), not the
    # last reading over the whole gap; the low-pass filters hold over it (lp)
    gap = both(p[P_GAP_F] > 0.0, both(s[S_TS_TYP] > 0.0, ts > p[P_GAP_F] * s[S_TS_TYP]))
    s[S_TS_TYP] = where(s[S_TS_TYP] > 0.0, s[S_TS_TYP] + TS_TYP_RATE * (ts - s[S_TS_TYP]), ts + 0.0 * gx)
    s[S_GAP] = where(gap, 1.0 + 0.0 * gx, 0.0 * gx)
    p0, p1, p2, was_frozen = s[S_GPREV], s[S_GPREV + 1], s[S_GPREV + 2], s[S_GFROZEN] > 0.5  # before the check
    # a frozen gyro is not integrated (the attitude holds) and is not rest (no bias from it)
    frozen = frozen_check(s, p, ts, S_GPREV, S_GSAME_T, S_GSAME_N, S_GFROZEN, S_GMAX, S_GCLIPPED,
                          p[P_GCLIP_FLOOR], gx, gy, gz)
    # moving again, the held heading is stale: taken from the field again as at the start once the
    # inclination had tau_acc to settle (at once: BROAD 20° 10-20 s after, VQF 10°, settled first 7°)
    wait = s[S_HEAD_RESTART]
    wait = where(both(was_frozen, negate(frozen)), p[P_TAU_ACC] + 0.0 * gx, where(wait > 0.0, wait - ts, wait))
    s[S_KMINIT] = where(both(s[S_HEAD_RESTART] > 0.0, wait <= 0.0), 1.0 + 0.0 * gx, s[S_KMINIT])
    s[S_HEAD_RESTART] = wait
    if p[P_REST_BIAS] > 0.5 or p[P_MAG_REJ] > 0.5:
        # rest detection, gyro part: deviation from the low-passed rate (decisions only)
        l0, l1, l2 = lp3(s, c, F_RG, nograd(gx), nograd(gy), nograd(gz), C_REST_B, C_REST_A, p[P_REST_TAU], ts, False)
        d0, d1, d2 = nograd(gx) - l0, nograd(gy) - l1, nograd(gz) - l2
        clip_ = p[P_CLIP] * DEG
        moving = either(frozen, either(d0 * d0 + d1 * d1 + d2 * d2 >= (p[P_REST_TH_G] * DEG) ** 2,
                                       either(fabs(l0 - s[S_CHK]) > clip_,
                                              either(fabs(l1 - s[S_CHK + 1]) > clip_, fabs(l2 - s[S_CHK + 2]) > clip_))))
        s[S_REST_T] = where(moving, 0.0 * l0, s[S_REST_T])
        s[S_REST] = where(moving, 0.0 * l0, s[S_REST])
        s[S_REST_G], s[S_REST_G + 1], s[S_REST_G + 2] = l0, l1, l2
    wx = where(gap, 0.5 * (gx + p0), gx) - s[S_BIAS]
    wy = where(gap, 0.5 * (gy + p1), gy) - s[S_BIAS + 1]
    wz = where(gap, 0.5 * (gz + p2), gz) - s[S_BIAS + 2]
    n2 = wx * wx + wy * wy + wz * wz
    norm = sqrt(n2 + 1e-300)  # the tiny term keeps the gradient finite at a zero rate
    turn = both(norm > EPS, negate(frozen))
    safe = where(turn, norm, 1.0 + 0.0 * norm)
    half = norm * ts / 2.0
    cw = cos(half)
    k = sin(half) / safe
    q0, q1, q2, q3 = qmul(s[S_GQ], s[S_GQ + 1], s[S_GQ + 2], s[S_GQ + 3], cw, k * wx, k * wy, k * wz)
    inv = 1.0 / sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    s[S_GQ] = where(turn, q0 * inv, s[S_GQ])
    s[S_GQ + 1] = where(turn, q1 * inv, s[S_GQ + 1])
    s[S_GQ + 2] = where(turn, q2 * inv, s[S_GQ + 2])
    s[S_GQ + 3] = where(turn, q3 * inv, s[S_GQ + 3])

# ------------------------------------------------------------------ accelerometer
@jit
def acc_update(s, p, c, ax, ay, az, acc_trust, bias_trust):
    ts = c[C_TS]
    frozen = frozen_check(s, p, ts, S_APREV, S_ASAME_T, S_ASAME_N, S_AFROZEN, S_AMAX, S_ACLIPPED,
                          p[P_ACLIP_FLOOR], ax, ay, az)
    # frozen or clipped: not trusted; no bias learnt then, or while either sensor is frozen (a held
    # gyro's drift would be carried past as bias). A clipped sample stays in the low-passed direction:
    # left out, the samples that remain are biased the other way (running phones clipped at ±2 g:
    # 27.2° against VQF's 16.6°, up to 83° worse). After a clipped sample the accelerometer waits
    # tau_acc (the low-passed direction still holds it) only while the gyro bias is known
    # (:data:`CLIP_BRIDGE_VAR`): the gyro alone then bridges the clipping (BROAD's fast translation
    # at ±2 g after rest: 1.8° against VQF's 22.7° and raw integration's 8.4°); with the bias unknown
    # it would drift for the whole run (the running phones: 18.4° against VQF's 16.6°, up to 19.6° worse)
    if p[P_REST_CHECK] > 0.5:
        rest_check(s, p, ts)
    clipped = s[S_ACLIPPED] > 0.5
    known = fmax(s[S_P], fmax(s[S_P + 4], s[S_P + 8])) <= CLIP_BRIDGE_VAR * c[C_P0]
    wait = s[S_ADISTRUST]
    wait = where(both(clipped, known), p[P_TAU_ACC] + 0.0 * ax, where(wait > 0.0, wait - ts, wait))
    s[S_ADISTRUST] = wait
    distrust = either(frozen, either(clipped, wait > 0.0))
    acc_trust = where(distrust, 0.0 * acc_trust, acc_trust)
    bias_trust = where(either(distrust, s[S_GFROZEN] > 0.5), 0.0 * bias_trust, bias_trust)
    if p[P_REST_BIAS] > 0.5:
        l0, l1, l2 = lp3(s, c, F_RA, nograd(ax), nograd(ay), nograd(az), C_REST_B, C_REST_A, p[P_REST_TAU], ts, False)
        d0, d1, d2 = nograd(ax) - l0, nograd(ay) - l1, nograd(az) - l2
        still = both(negate(frozen), d0 * d0 + d1 * d1 + d2 * d2 < p[P_REST_TH_A] ** 2)
        rest_t = where(still, s[S_REST_T] + ts, 0.0 * l0)
        s[S_REST] = where(still, where(rest_t >= p[P_REST_MIN_T], 1.0 + 0.0 * l0, s[S_REST]), 0.0 * l0)
        s[S_REST_T] = rest_t
    # the accelerometer in the almost-inertial frame I_i, low-passed there (Sec. 3.2)
    e0, e1, e2 = qrot(s[S_GQ], s[S_GQ + 1], s[S_GQ + 2], s[S_GQ + 3], ax, ay, az)
    f0, f1, f2 = lp3(s, c, F_ACC, e0, e1, e2, C_ACC_B, C_ACC_A, p[P_TAU_ACC], ts, frozen)
    # ... in the 6D earth frame E_i, normalised
    v0, v1, v2 = qrot(s[S_AQ], s[S_AQ + 1], s[S_AQ + 2], s[S_AQ + 3], f0, f1, f2)
    inv = 1.0 / sqrt(v0 * v0 + v1 * v1 + v2 * v2 + 1e-300)
    v0, v1, v2 = v0 * inv, v1 * inv, v2 * inv
    # inclination correction: the rotation taking v to up, its angle scaled by the trust
    # (trust 1: VQF's full correction of the low-passed direction)
    sh = sqrt(v0 * v0 + v1 * v1 + 1e-300)
    half = acc_trust * atan2(sh, v2) / 2.0
    tilted = sh > TILT_MIN
    k = sin(half) / where(tilted, sh, 1.0 + 0.0 * sh)
    cx = where(tilted, k * v1, where(v2 < 0.0, sin(half), 0.0 * sh))  # upside down: about x
    cy = where(tilted, -k * v0, 0.0 * sh)
    q0, q1, q2, q3 = qmul(cos(half), cx, cy, 0.0 * sh, s[S_AQ], s[S_AQ + 1], s[S_AQ + 2], s[S_AQ + 3])
    inv = 1.0 / sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    s[S_AQ], s[S_AQ + 1], s[S_AQ + 2], s[S_AQ + 3] = q0 * inv, q1 * inv, q2 * inv, q3 * inv
    if p[P_MOTION_BIAS] > 0.5 or p[P_REST_BIAS] > 0.5:
        bias_update(s, p, c, v0, v1, bias_trust)

@jit
def bias_update(s, p, c, v0, v1, bias_trust):
    """Sec. 3.4: a Kalman filter on the bias b. In motion the measurement is the inclination
    disagreement as a rate, y = [−v_y, v_x, 0]/ts + (low-passed R b)_xy with H = low-passed R
    (the 6D attitude as a matrix); the vertical component is barely observable (large W). At
    rest y is the low-passed gyro with H = I. Covariances in (0.01 °/s)²."""
    ts = c[C_TS]
    b0, b1, b2 = s[S_BIAS], s[S_BIAS + 1], s[S_BIAS + 2]
    w, x, y, z = quat6(s)
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = qmat(w, x, y, z)
    rb0 = r00 * b0 + r01 * b1 + r02 * b2
    rb1 = r10 * b0 + r11 * b1 + r12 * b2
    run, n, start = lp_begin(s, F_ROT, p[P_TAU_ACC], ts)
    h00 = lp(s, c, F_ROT, 9, 0, r00, C_ACC_B, C_ACC_A, run, n, start, False)
    h01 = lp(s, c, F_ROT, 9, 1, r01, C_ACC_B, C_ACC_A, run, n, start, False)
    h02 = lp(s, c, F_ROT, 9, 2, r02, C_ACC_B, C_ACC_A, run, n, start, False)
    h10 = lp(s, c, F_ROT, 9, 3, r10, C_ACC_B, C_ACC_A, run, n, start, False)
    h11 = lp(s, c, F_ROT, 9, 4, r11, C_ACC_B, C_ACC_A, run, n, start, False)
    h12 = lp(s, c, F_ROT, 9, 5, r12, C_ACC_B, C_ACC_A, run, n, start, False)
    h20 = lp(s, c, F_ROT, 9, 6, r20, C_ACC_B, C_ACC_A, run, n, start, False)
    h21 = lp(s, c, F_ROT, 9, 7, r21, C_ACC_B, C_ACC_A, run, n, start, False)
    h22 = lp(s, c, F_ROT, 9, 8, r22, C_ACC_B, C_ACC_A, run, n, start, False)
    lp_end(s, F_ROT, run, start)
    run, n, start = lp_begin(s, F_BIAS, p[P_TAU_ACC], ts)
    bl0 = lp(s, c, F_BIAS, 2, 0, rb0, C_ACC_B, C_ACC_A, run, n, start, False)
    bl1 = lp(s, c, F_BIAS, 2, 1, rb1, C_ACC_B, C_ACC_A, run, n, start, False)
    lp_end(s, F_BIAS, run, start)
    rest = both(s[S_REST] > 0.5, p[P_REST_BIAS] > 0.5)
    motion = p[P_MOTION_BIAS] > 0.5
    one, zero = 1.0 + 0.0 * h00, 0.0 * h00
    # measurement residual e = y − H b and its model (H, W) for the case at hand
    m0 = -v1 / ts + bl0 - (h00 * b0 + h01 * b1 + h02 * b2)
    m1 = v0 / ts + bl1 - (h10 * b0 + h11 * b1 + h12 * b2)
    m2 = -(h20 * b0 + h21 * b1 + h22 * b2)
    e0 = where(rest, s[S_REST_G] - b0, m0)
    e1 = where(rest, s[S_REST_G + 1] - b1, m1)
    e2 = where(rest, s[S_REST_G + 2] - b2, m2)
    H00, H01, H02 = where(rest, one, h00), where(rest, zero, h01), where(rest, zero, h02)
    H10, H11, H12 = where(rest, zero, h10), where(rest, one, h11), where(rest, zero, h12)
    H20, H21, H22 = where(rest, zero, h20), where(rest, zero, h21), where(rest, one, h22)
    W0 = where(rest, c[C_WR] * one, c[C_WM] * one)
    W2 = where(rest, c[C_WR] * one, c[C_WV] * one)
    update = either(rest, motion)
    # P <- P + V (also without a measurement): the bias may drift
    for i in range(3):
        k = S_P + 4 * i
        s[k] = where(s[k] < c[C_P0], s[k] + c[C_V], s[k])
    P00, P01, P02 = s[S_P], s[S_P + 1], s[S_P + 2]
    P10, P11, P12 = s[S_P + 3], s[S_P + 4], s[S_P + 5]
    P20, P21, P22 = s[S_P + 6], s[S_P + 7], s[S_P + 8]
    # disagreement clipped to ±bias_clip (also limits the first inclination step's harm)
    cl = p[P_CLIP] * DEG
    e0, e1, e2 = clip(e0, -cl, cl), clip(e1, -cl, cl), clip(e2, -cl, cl)
    # A = P H^T, S = W + H P H^T, K = A S^-1
    A00, A01, A02, A10, A11, A12, A20, A21, A22 = mat3_mul_t(P00, P01, P02, P10, P11, P12, P20, P21, P22,
                                                             H00, H01, H02, H10, H11, H12, H20, H21, H22)
    S00, S01, S02, S10, S11, S12, S20, S21, S22 = mat3_mul_t(H00, H01, H02, H10, H11, H12, H20, H21, H22,  # H (Aᵀ)ᵀ
                                                             A00, A10, A20, A01, A11, A21, A02, A12, A22)
    S00, S11, S22 = W0 + S00, W0 + S11, W2 + S22
    # S^-1 by cofactors
    c00, c01, c02 = S11 * S22 - S12 * S21, S02 * S21 - S01 * S22, S01 * S12 - S02 * S11
    c10, c11, c12 = S12 * S20 - S10 * S22, S00 * S22 - S02 * S20, S02 * S10 - S00 * S12
    c20, c21, c22 = S10 * S21 - S11 * S20, S01 * S20 - S00 * S21, S00 * S11 - S01 * S10
    det = S00 * c00 + S01 * c10 + S02 * c20
    c00, c01, c02, c10, c11, c12, c20, c21, c22 = (c00 / det, c01 / det, c02 / det, c10 / det, c11 / det,
                                                   c12 / det, c20 / det, c21 / det, c22 / det)
    K00, K01, K02, K10, K11, K12, K20, K21, K22 = mat3_mul_t(A00, A01, A02, A10, A11, A12, A20, A21, A22,  # A (Cᵀ)ᵀ
                                                             c00, c10, c20, c01, c11, c21, c02, c12, c22)
    # b <- clip(b + trust K e); the learned bias trust scales the increment (0: frozen); the clip is
    # about the device check's bias (rest_check; 0 without it: VQF's clip about zero)
    k0, k1, k2 = s[S_CHK], s[S_CHK + 1], s[S_CHK + 2]
    nb0 = clip(b0 + bias_trust * (K00 * e0 + K01 * e1 + K02 * e2), k0 - cl, k0 + cl)
    nb1 = clip(b1 + bias_trust * (K10 * e0 + K11 * e1 + K12 * e2), k1 - cl, k1 + cl)
    nb2 = clip(b2 + bias_trust * (K20 * e0 + K21 * e1 + K22 * e2), k2 - cl, k2 + cl)
    # P <- P − K H P = P − K A^T
    N00, N01, N02, N10, N11, N12, N20, N21, N22 = mat3_mul_t(K00, K01, K02, K10, K11, K12, K20, K21, K22,
                                                             A00, A01, A02, A10, A11, A12, A20, A21, A22)
    N00, N01, N02, N10, N11, N12, N20, N21, N22 = (P00 - N00, P01 - N01, P02 - N02, P10 - N10, P11 - N11,
                                                   P12 - N12, P20 - N20, P21 - N21, P22 - N22)
    s[S_BIAS], s[S_BIAS + 1], s[S_BIAS + 2] = where(update, nb0, b0), where(update, nb1, b1), where(update, nb2, b2)
    s[S_P], s[S_P + 1], s[S_P + 2] = where(update, N00, P00), where(update, N01, P01), where(update, N02, P02)
    s[S_P + 3], s[S_P + 4], s[S_P + 5] = where(update, N10, P10), where(update, N11, P11), where(update, N12, P12)
    s[S_P + 6], s[S_P + 7], s[S_P + 8] = where(update, N20, P20), where(update, N21, P21), where(update, N22, P22)

# ------------------------------------------------------------------ magnetometer
@jit
def mag_update(s, p, c, mx, my, mz, mag_trust):
    ts = c[C_TS]
    # frozen (readings repeating exactly for frozen_time and MAG_FROZEN_MIN_T): not trusted (BROAD,
    # 5 s frozen turning fast: 11° heading error 4-8 s after with broad9's knobs, VQF 3.6°)
    mx_, my_, mz_ = nograd(mx), nograd(my), nograd(mz)
    same = both(mx_ == s[S_MPREV], both(my_ == s[S_MPREV + 1], mz_ == s[S_MPREV + 2]))
    mt = where(same, s[S_MSAME_T] + ts, 0.0 * mx_)
    mfrozen = both(p[P_FROZEN_T] > 0.0, both(mt >= p[P_FROZEN_T], mt >= MAG_FROZEN_MIN_T))
    s[S_MPREV], s[S_MPREV + 1], s[S_MPREV + 2], s[S_MSAME_T] = mx_, my_, mz_, mt
    s[S_MFROZEN] = where(mfrozen, 1.0 + 0.0 * mx_, 0.0 * mx_)
    mag_trust = where(mfrozen, 0.0 * mag_trust, mag_trust)
    w, x, y, z = quat6(s)
    m0, m1, m2 = qrot(w, x, y, z, mx, my, mz)   # the field in the 6D earth frame E_i
    k = c[C_KMAG] + 0.0 * m0
    if p[P_MAG_REJ] > 0.5:
        # the field's norm and dip against the recording's own reference (decisions only)
        g0, g1, g2 = nograd(m0), nograd(m1), nograd(m2)
        norm = sqrt(g0 * g0 + g1 * g1 + g2 * g2 + 1e-300)
        dip = -asin(g2 / norm)
        if p[P_MAG_CUR_TAU] > 0.0:
            run, n, start = lp_begin(s, F_MAG, p[P_MAG_CUR_TAU], ts)
            norm_f = lp(s, c, F_MAG, 2, 0, norm, C_MAG_B, C_MAG_A, run, n, start, False)
            dip_f = lp(s, c, F_MAG, 2, 1, dip, C_MAG_B, C_MAG_A, run, n, start, False)
            lp_end(s, F_MAG, run, start)
            norm, dip = norm_f, dip_f
        kref = c[C_KMAGREF]
        dip_th = p[P_MAG_DIP_TH] * DEG
        ok = both(fabs(norm - s[S_MREF_N]) < p[P_MAG_NORM_TH] * s[S_MREF_N],
                  fabs(dip - s[S_MREF_D]) < dip_th)
        und_t = where(ok, s[S_MUND_T] + ts, 0.0 * norm)
        settled = both(ok, und_t >= p[P_MAG_MIN_UND_T])
        dist = where(ok, where(settled, 0.0 * norm, s[S_MAGDIST]), 1.0 + 0.0 * norm)
        ref_n = where(settled, s[S_MREF_N] + kref * (norm - s[S_MREF_N]), s[S_MREF_N])
        ref_d = where(settled, s[S_MREF_D] + kref * (dip - s[S_MREF_D]), s[S_MREF_D])
        # a new field is accepted after it stayed steady for mag_new_time while turning
        cand = both(fabs(norm - s[S_MCAND_N]) < p[P_MAG_NORM_TH] * s[S_MCAND_N],
                    fabs(dip - s[S_MCAND_D]) < dip_th)
        g = s[S_REST_G] * s[S_REST_G] + s[S_REST_G + 1] * s[S_REST_G + 1] + s[S_REST_G + 2] * s[S_REST_G + 2]
        turning = sqrt(g + 1e-300) >= p[P_MAG_NEW_MIN_G] * DEG
        cand_t = where(cand, where(turning, s[S_MCAND_T] + ts, s[S_MCAND_T]), 0.0 * norm)
        cand_n = where(cand, s[S_MCAND_N] + kref * (norm - s[S_MCAND_N]), norm)
        cand_d = where(cand, s[S_MCAND_D] + kref * (dip - s[S_MCAND_D]), dip)
        accept = both(cand, both(dist > 0.5, either(cand_t >= p[P_MAG_NEW_T],
                                                    both(ref_n == 0.0, cand_t >= p[P_MAG_NEW_FIRST_T]))))
        s[S_MREF_N] = where(accept, cand_n, ref_n)
        s[S_MREF_D] = where(accept, cand_d, ref_d)
        s[S_MAGDIST] = where(accept, 0.0 * norm, dist)
        s[S_MUND_T] = where(accept, p[P_MAG_MIN_UND_T] + 0.0 * norm, und_t)
        s[S_MCAND_T], s[S_MCAND_N], s[S_MCAND_D] = cand_t, cand_n, cand_d
        # rejection: no heading correction while disturbed, for at most mag_max_rejection_time,
        # then a reduced gain; the allowance recovers at mag_rejection_factor × real time
        k, rej_t = rejection_gain(k, s[S_MAGDIST] > 0.5, s[S_MREJ_T], p[P_MAG_MAX_REJ_T], p[P_MAG_REJ_FACTOR], ts)
        s[S_MREJ_T] = rej_t
    k, ki = initial_gain(k, s[S_KMINIT], p[P_TAU_MAG], ts)
    s[S_KMINIT] = ki
    # heading disagreement, wrapped to [-pi, pi]; the learned trust scales the gain
    s[S_DELTA] = wrap_pi(s[S_DELTA] + mag_trust * k * wrap_pi(atan2(m0, m1) - s[S_DELTA]))
