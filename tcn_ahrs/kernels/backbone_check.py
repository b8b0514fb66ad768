"""The causal device check of the backbone (``rest_check`` on; the default of ``tcn-ahrs evaluate``):
the device check of :mod:`tcn_ahrs.device_check` read from the past only, so that every runtime
(numba, torch, TorchScript, C: each reads this file as it reads :mod:`tcn_ahrs.kernels.backbone`)
runs it. Why: VQF rests only while the low-passed gyro lies within its 2 °/s bias clip and never
estimates a bias beyond it; EuRoC's ADIS16448 reads 4.4 °/s about z and its rotors' vibration never
passes VQF's rest thresholds (VQF: ~80° after two minutes). The offline check read the bias from
the whole recording, later rests included: a device cannot, and the future changed the past.

Built like the kernel (:mod:`tcn_ahrs.kernels.ops`): this file's ``ops`` is the float table when
imported, and :func:`~tcn_ahrs.kernels.ops.load_kernel` executes it again with another table.
"""
from __future__ import annotations

from .backbone_layout import (CHECK_CLIP, CHECK_MIN_WINDOWS, CHECK_NOISE_FACTOR, CHECK_TILT_DEG, CHECK_WINDOW, DEG,
                              P_CLIP, S_ACLIPPED, S_AFROZEN, S_APREV, S_BIAS, S_CHK, S_CK_AQ, S_CK_AREF, S_CK_AS,
                              S_CK_DEAD, S_CK_FLOOR, S_CK_GQ, S_CK_GREF, S_CK_GS, S_CK_N, S_CK_RUN, S_CK_RUN_G,
                              S_CK_RUN_N, S_CK_RUN_UP, S_CK_T, S_GCLIPPED, S_GFROZEN, S_GPREV)
from .ops import float_ops

ops = globals().get("__ops__") or float_ops()
jit, where, both, either, negate = ops.jit, ops.where, ops.both, ops.either, ops.negate
sqrt, cos, fabs, fmax = ops.sqrt, ops.cos, ops.fabs, ops.fmax


@jit
def rest_check(s, p, ts):
    """The device check of :mod:`tcn_ahrs.device_check` read from the past only (``rest_check`` on):
    per window of :data:`CHECK_WINDOW` the largest per-axis spread of the gyro and the accelerometer
    (sums of deviations from the window's first sample: no cancellation in float); the noise floors
    are the quietest live window's so far; a window is quiet within :data:`CHECK_NOISE_FACTOR` × both
    floors, live unless a sensor clipped or exactly one froze in it (a frozen or saturated sensor is
    not rest); :data:`CHECK_MIN_WINDOWS` quiet windows in a row whose mean specific force stays within
    :data:`CHECK_TILT_DEG` of the run's are a rest, and the run's mean gyro (within
    :data:`CHECK_CLIP`) becomes the bias: the check's (``S_CHK``, VQF's estimate is clipped about it)
    and the filter's, which goes on from there. VQF's rest needs |low-passed gyro| < 2 °/s: EuRoC's
    4.4 °/s bias never rests there and its rotor vibration never passes VQF's thresholds. Reads this
    sample's raw readings from the health checks' memory (``S_GPREV``, ``S_APREV``)."""
    zero = 0.0 * ts
    one = 1.0 + zero
    fresh = s[S_CK_N] < 0.5
    gf, af = s[S_GFROZEN] > 0.5, s[S_AFROZEN] > 0.5
    dead = either(either(s[S_GCLIPPED] > 0.5, s[S_ACLIPPED] > 0.5), either(both(gf, negate(af)), both(af, negate(gf))))
    s[S_CK_DEAD] = where(dead, one, where(fresh, zero, s[S_CK_DEAD]))
    for i in range(3):
        gr = where(fresh, s[S_GPREV + i], s[S_CK_GREF + i])
        ar = where(fresh, s[S_APREV + i], s[S_CK_AREF + i])
        dg, da = s[S_GPREV + i] - gr, s[S_APREV + i] - ar
        s[S_CK_GREF + i], s[S_CK_AREF + i] = gr, ar
        s[S_CK_GS + i] = where(fresh, zero, s[S_CK_GS + i]) + dg
        s[S_CK_GQ + i] = where(fresh, zero, s[S_CK_GQ + i]) + dg * dg
        s[S_CK_AS + i] = where(fresh, zero, s[S_CK_AS + i]) + da
        s[S_CK_AQ + i] = where(fresh, zero, s[S_CK_AQ + i]) + da * da
    n = s[S_CK_N] + 1.0
    t = where(fresh, zero, s[S_CK_T]) + ts
    done = t >= CHECK_WINDOW - 0.5 * ts
    s[S_CK_N] = where(done, zero, n)
    s[S_CK_T] = t
    check_window(s, p, n, done)

@jit
def check_window(s, p, n, done):
    """Where ``done`` (a full window of :func:`rest_check`, ``n`` samples): the floors, the run, the
    bias (computed every sample, written only then: one reading for scalars and batches)."""
    zero = 0.0 * n
    gsp, asp = zero, zero
    for i in range(3):
        mg, ma = s[S_CK_GS + i] / n, s[S_CK_AS + i] / n
        gsp = fmax(gsp, s[S_CK_GQ + i] / n - mg * mg)
        asp = fmax(asp, s[S_CK_AQ + i] / n - ma * ma)
    gsp, asp = sqrt(gsp), sqrt(asp)
    u0 = s[S_CK_AREF] + s[S_CK_AS] / n
    u1 = s[S_CK_AREF + 1] + s[S_CK_AS + 1] / n
    u2 = s[S_CK_AREF + 2] + s[S_CK_AS + 2] / n
    inv = 1.0 / sqrt(u0 * u0 + u1 * u1 + u2 * u2 + 1e-300)
    u0, u1, u2 = u0 * inv, u1 * inv, u2 * inv
    live = both(s[S_CK_DEAD] < 0.5, done)
    gfl, afl = s[S_CK_FLOOR], s[S_CK_FLOOR + 1]
    first = gfl < 0.0
    gfl = where(live, where(either(first, gsp < gfl), gsp, gfl), gfl)
    afl = where(live, where(either(first, asp < afl), asp, afl), afl)
    s[S_CK_FLOOR], s[S_CK_FLOOR + 1] = gfl, afl
    quiet = both(live, both(gsp <= CHECK_NOISE_FACTOR * gfl, asp <= CHECK_NOISE_FACTOR * afl))
    # the run's mean direction so far against this window's
    m0, m1, m2 = s[S_CK_RUN_UP], s[S_CK_RUN_UP + 1], s[S_CK_RUN_UP + 2]
    cos_tilt = (m0 * u0 + m1 * u1 + m2 * u2) / sqrt(m0 * m0 + m1 * m1 + m2 * m2 + 1e-300)
    run = s[S_CK_RUN]
    extend = both(quiet, either(run < 0.5, cos_tilt >= cos(CHECK_TILT_DEG * DEG)))
    again = both(quiet, negate(extend))   # quiet, but tilted: a new run from this window
    keep = where(done, where(extend, 1.0 + zero, zero), 1.0 + zero)   # between windows the run is kept
    new = where(both(done, either(extend, again)), 1.0 + zero, zero)
    run = keep * run + new
    s[S_CK_RUN] = run
    s[S_CK_RUN_N] = keep * s[S_CK_RUN_N] + new * n
    s[S_CK_RUN_UP], s[S_CK_RUN_UP + 1], s[S_CK_RUN_UP + 2] = (keep * m0 + new * u0, keep * m1 + new * u1,
                                                             keep * m2 + new * u2)
    take = both(done, run >= CHECK_MIN_WINDOWS)
    count = fmax(s[S_CK_RUN_N], 1.0)
    cl, vqf_cl = CHECK_CLIP * DEG, p[P_CLIP] * DEG
    beyond = fabs(zero) > 1.0   # False
    for i in range(3):
        g = keep * s[S_CK_RUN_G + i] + new * (n * s[S_CK_GREF + i] + s[S_CK_GS + i])
        s[S_CK_RUN_G + i] = g
        take = both(take, fabs(g / count) <= cl)
        beyond = either(beyond, fabs(g / count - s[S_CHK + i]) > vqf_cl)
    # taken where VQF cannot reach it (beyond its clip about the check's last bias); within it, VQF's
    # own rest and motion updates are left alone (taken there too: 0.002-0.03° worse than VQF on one
    # BROAD and three OxIOD recordings, whose biases VQF already reads)
    take = both(take, either(beyond, fabs(s[S_CHK]) + fabs(s[S_CHK + 1]) + fabs(s[S_CHK + 2]) > 0.0))
    for i in range(3):
        b = s[S_CK_RUN_G + i] / count
        s[S_CHK + i] = where(take, b, s[S_CHK + i])
        s[S_BIAS + i] = where(take, b, s[S_BIAS + i])
