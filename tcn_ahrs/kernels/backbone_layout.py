"""The backbone's parameters and the layouts of its flat vectors (parameters, state,
coefficients), as named indices: what :mod:`tcn_ahrs.kernels.backbone`'s step reads as constants
(numba and TorchScript take module-level ints as compile-time constants) and what its callers
use to read a state (``S_BIAS``, ``N_STATE``, ...).

Deliberate differences of the step from ``vqf`` (tests/test_backbone.py holds the rest equal to
it): the time step may change from sample to sample (coefficients recomputed, filter states kept);
the inclination correction is written with its angle (atan2), to be scaled (trust 1: ``vqf``'s to
round-off); the start may be a given attitude; the sensors' health is checked (frozen, clipped,
gaps: :class:`BackboneParams`; a frozen magnetometer: :data:`MAG_FROZEN_MIN_T`).
"""
from __future__ import annotations

import math
from dataclasses import astuple, dataclass, fields
from typing import Dict, List, Tuple

from .params import knob


# ------------------------------------------------------------------------------ parameters


@dataclass(frozen=True)
class BackboneParams:
    """The backbone's parameters, VQF's defaults (its ``VQFParams``; names in snake case).

    Units: seconds, degrees and °/s where named so (as VQF's), m/s² for ``rest_th_acc``,
    fractions for ``mag_norm_th``. Flags are 1.0 / 0.0 (kept as floats: one flat vector)."""

    tau_acc: float = knob(3.0, "s", "low-pass of the accelerometer in the inertial frame", (0.5, 30.0),
                           grid=[1.0, 3.0, 10.0])
    tau_mag: float = knob(9.0, "s", "heading correction time constant", (1.0, 60.0), grid=[3.0, 9.0, 20.0])
    motion_bias: float = knob(1.0, "flag", "bias estimation in motion", [1.0, 0.0], grid=[1.0, 0.0])
    rest_bias: float = knob(1.0, "flag", "rest detection and bias estimation at rest")
    mag_rejection: float = knob(1.0, "flag", "magnetic disturbance detection and rejection", [1.0, 0.0])
    bias_sigma_init: float = knob(0.5, "°/s", "initial bias uncertainty", (0.1, 10.0))
    bias_forgetting_time: float = knob(100.0, "s", "time for the bias variance to grow to 0.1 °/s", (10.0, 1000.0))
    bias_clip: float = knob(2.0, "°/s", "largest bias estimate (and disagreement)", (0.5, 15.0), grid=[2.0, 8.0])
    bias_sigma_motion: float = knob(0.1, "°/s", "bias measurement noise in motion", (0.01, 1.0))
    bias_vertical_forgetting: float = knob(1e-4, "", "vertical bias measurement weight factor")
    bias_sigma_rest: float = knob(0.03, "°/s", "bias measurement noise at rest", (0.003, 0.3))
    rest_min_time: float = knob(1.5, "s", "still this long to be at rest", (0.3, 5.0))
    rest_filter_tau: float = knob(0.5, "s", "low-pass of the rest detection")
    rest_th_gyro: float = knob(2.0, "°/s", "rest threshold, gyro", (0.5, 10.0))
    rest_th_acc: float = knob(0.5, "m/s²", "rest threshold, accelerometer", (0.1, 2.0))
    mag_current_tau: float = knob(0.05, "s", "low-pass of the field's norm and dip")
    mag_ref_tau: float = knob(20.0, "s", "time constant of the field's reference")
    mag_norm_th: float = knob(0.1, "", "relative norm deviation counted as disturbed")
    mag_dip_th: float = knob(10.0, "°", "dip deviation counted as disturbed")
    mag_new_time: float = knob(20.0, "s", "a new field accepted after this long steady")
    mag_new_first_time: float = knob(5.0, "s", "the first field accepted after this long")
    mag_new_min_gyro: float = knob(20.0, "°/s", "turning this fast to accept a new field")
    mag_min_undisturbed_time: float = knob(0.5, "s", "undisturbed this long to update the reference")
    mag_max_rejection_time: float = knob(60.0, "s", "longest rejection")
    mag_rejection_factor: float = knob(2.0, "", "gain divisor after the longest rejection")
    # sensor health, no ground truth needed (not in VQF): a sensor whose three readings repeat
    # exactly for this long (and FROZEN_MIN_SAMPLES samples) is frozen — its noise makes that
    # improbable (the longest repeat in BROAD, EuRoC, TUM VI and OxIOD: 5 samples, 17 ms) — and is
    # then neither integrated (gyro) nor trusted (accelerometer); 0 switches the check off
    frozen_time: float = knob(0.1, "s", "a sensor repeating its readings this long is frozen; 0: off")
    # a reading that repeats its axis's largest magnitude so far, above these, while another axis
    # changes, is clipped (a saturated sensor; a clipped accelerometer is not trusted); 0: off
    gyro_clip_floor: float = knob(2.0, "rad/s", "clip check above this (±125 °/s, the smallest range, is 2.18)")
    acc_clip_floor: float = knob(19.0, "m/s²", "clip check above this (±2 g, the smallest range, is 19.6)")
    # a step longer than gap_factor × the typical step (its running mean) is a gap (samples
    # lost): the gyro over it is the mean of the readings either side (not the last reading over
    # the whole gap: a 2 s gap in walking, 52° error 10-20 s after, VQF on the resampled stream
    # 23°) and the low-pass filters hold over it; flagged `gap`; 0 switches the check off
    gap_factor: float = knob(4.0, "", "a step this many typical steps long is a gap; 0: off")
    # the causal device check (not in VQF; 0: off, VQF's filter): the gyro bias read from the past's
    # rests, judged by the signal's character (windows whose spread is within CHECK_NOISE_FACTOR x the
    # quietest window so far, for CHECK_MIN_WINDOWS windows at a steady tilt), not by VQF's 2 °/s clip;
    # VQF's own bias estimate then runs within bias_clip of it (kernels/backbone_check.py: rest_check)
    rest_check: float = knob(0.0, "flag", "the causal device check: the gyro bias at rest from the past, "
                             "beyond bias_clip; 0: off")

    def vector(self) -> Tuple[float, ...]:
        return tuple(float(v) for v in astuple(self))

    @classmethod
    def from_mapping(cls, cfg) -> "BackboneParams":
        known = {f.name for f in fields(cls)}
        bad = set(cfg) - known
        if bad:
            raise ValueError(f"backbone parameters: unknown key(s) {sorted(bad)}; expected a subset of {sorted(known)}")
        return cls(**{k: float(v) for k, v in dict(cfg).items()})


def _layout(spec: List[Tuple[str, int]]) -> Dict[str, int]:
    out, k = {}, 0
    for name, n in spec:
        out[name] = k
        k += n
    out["_size"] = k
    return out


PARAM = _layout([(f.name, 1) for f in fields(BackboneParams)])

# low-pass filter groups: (name, components); each holds [running, count, x1, x2, y1, y2 (d each)]
# (direct form I: kernels/backbone.py explains why)
_FILTERS = [("acc_lp", 3), ("rot_lp", 9), ("bias_lp", 2), ("rest_gyro_lp", 3), ("rest_acc_lp", 3),
            ("mag_lp", 2)]
STATE = _layout([("gyr_quat", 4), ("acc_quat", 4), ("delta", 1), ("rest", 1), ("mag_disturbed", 1),
                 ("k_mag_init", 1), ("bias", 3), ("bias_p", 9), ("rest_time", 1), ("rest_gyro", 3),
                 ("mag_ref_norm", 1), ("mag_ref_dip", 1), ("mag_undisturbed_time", 1),
                 ("mag_reject_time", 1), ("mag_cand_norm", 1), ("mag_cand_dip", 1), ("mag_cand_time", 1),
                 ("gyr_prev", 3), ("gyr_same_time", 1), ("gyr_same_count", 1), ("gyr_frozen", 1),
                 ("acc_prev", 3), ("acc_same_time", 1), ("acc_same_count", 1), ("acc_frozen", 1),
                 ("gyr_max_abs", 3), ("gyr_clip_run", 3), ("gyr_clipped", 1), ("acc_max_abs", 3), ("acc_clip_run", 3),
                 ("acc_clipped", 1), ("ts_typical", 1), ("gap", 1), ("heading_restart_in", 1),
                 ("acc_distrust_in", 1), ("mag_prev", 3), ("mag_same_time", 1), ("mag_frozen", 1),
                 ("check_bias", 3), ("check_count", 1), ("check_time", 1), ("check_dead", 1), ("check_gyr_ref", 3),
                 ("check_gyr_sum", 3), ("check_gyr_sq", 3), ("check_acc_ref", 3), ("check_acc_sum", 3),
                 ("check_acc_sq", 3), ("check_floor", 2), ("check_run", 1), ("check_run_count", 1),
                 ("check_run_gyr", 3), ("check_run_up", 3)]
                + [(n, 2 + 4 * d) for n, d in _FILTERS])
COEFF = _layout([("ts", 1), ("acc_b", 3), ("acc_a", 2), ("rest_b", 3), ("rest_a", 2), ("mag_b", 3), ("mag_a", 2),
                 ("k_mag", 1), ("k_mag_ref", 1), ("bias_p0", 1), ("bias_v", 1), ("bias_motion_w", 1),
                 ("bias_vertical_w", 1), ("bias_rest_w", 1)])
N_STATE = STATE["_size"]
N_COEFF = COEFF["_size"]
N_PARAM = PARAM["_size"]

# flat indices as module constants (numba reads globals as compile-time constants)
_P = {k: v for k, v in PARAM.items()}
_S = {k: v for k, v in STATE.items()}
_C = {k: v for k, v in COEFF.items()}
P_TAU_ACC, P_TAU_MAG = _P["tau_acc"], _P["tau_mag"]
P_MOTION_BIAS, P_REST_BIAS, P_MAG_REJ = _P["motion_bias"], _P["rest_bias"], _P["mag_rejection"]
P_SIGMA_INIT, P_FORGET, P_CLIP = _P["bias_sigma_init"], _P["bias_forgetting_time"], _P["bias_clip"]
P_SIGMA_MOTION, P_VERT_FORGET, P_SIGMA_REST = (_P["bias_sigma_motion"], _P["bias_vertical_forgetting"],
                                               _P["bias_sigma_rest"])
P_REST_MIN_T, P_REST_TAU, P_REST_TH_G, P_REST_TH_A = (_P["rest_min_time"], _P["rest_filter_tau"],
                                                      _P["rest_th_gyro"], _P["rest_th_acc"])
P_MAG_CUR_TAU, P_MAG_REF_TAU, P_MAG_NORM_TH, P_MAG_DIP_TH = (_P["mag_current_tau"], _P["mag_ref_tau"],
                                                              _P["mag_norm_th"], _P["mag_dip_th"])
P_MAG_NEW_T, P_MAG_NEW_FIRST_T, P_MAG_NEW_MIN_G = (_P["mag_new_time"], _P["mag_new_first_time"],
                                                   _P["mag_new_min_gyro"])
P_MAG_MIN_UND_T, P_MAG_MAX_REJ_T, P_MAG_REJ_FACTOR = (_P["mag_min_undisturbed_time"],
                                                      _P["mag_max_rejection_time"], _P["mag_rejection_factor"])
S_GQ, S_AQ, S_DELTA, S_REST, S_MAGDIST, S_KMINIT = (_S["gyr_quat"], _S["acc_quat"], _S["delta"], _S["rest"],
                                                    _S["mag_disturbed"], _S["k_mag_init"])
S_BIAS, S_P, S_REST_T, S_REST_G = _S["bias"], _S["bias_p"], _S["rest_time"], _S["rest_gyro"]
S_MREF_N, S_MREF_D, S_MUND_T, S_MREJ_T = (_S["mag_ref_norm"], _S["mag_ref_dip"], _S["mag_undisturbed_time"],
                                          _S["mag_reject_time"])
S_MCAND_N, S_MCAND_D, S_MCAND_T = _S["mag_cand_norm"], _S["mag_cand_dip"], _S["mag_cand_time"]
S_GPREV, S_GSAME_T, S_GSAME_N, S_GFROZEN = _S["gyr_prev"], _S["gyr_same_time"], _S["gyr_same_count"], _S["gyr_frozen"]
S_APREV, S_ASAME_T, S_ASAME_N, S_AFROZEN = _S["acc_prev"], _S["acc_same_time"], _S["acc_same_count"], _S["acc_frozen"]
P_FROZEN_T = _P["frozen_time"]
S_GMAX, S_GCLIPPED, S_AMAX, S_ACLIPPED = _S["gyr_max_abs"], _S["gyr_clipped"], _S["acc_max_abs"], _S["acc_clipped"]
P_GCLIP_FLOOR, P_ACLIP_FLOOR = _P["gyro_clip_floor"], _P["acc_clip_floor"]
S_TS_TYP, S_GAP, P_GAP_F, S_HEAD_RESTART = _S["ts_typical"], _S["gap"], _P["gap_factor"], _S["heading_restart_in"]
S_ADISTRUST = _S["acc_distrust_in"]
S_MPREV, S_MSAME_T, S_MFROZEN = _S["mag_prev"], _S["mag_same_time"], _S["mag_frozen"]
P_REST_CHECK = _P["rest_check"]
S_CHK, S_CK_N, S_CK_T, S_CK_DEAD = _S["check_bias"], _S["check_count"], _S["check_time"], _S["check_dead"]
S_CK_GREF, S_CK_GS, S_CK_GQ = _S["check_gyr_ref"], _S["check_gyr_sum"], _S["check_gyr_sq"]
S_CK_AREF, S_CK_AS, S_CK_AQ = _S["check_acc_ref"], _S["check_acc_sum"], _S["check_acc_sq"]
S_CK_FLOOR, S_CK_RUN, S_CK_RUN_N = _S["check_floor"], _S["check_run"], _S["check_run_count"]
S_CK_RUN_G, S_CK_RUN_UP = _S["check_run_gyr"], _S["check_run_up"]
# the causal device check's settings (tcn_ahrs.device_check.DeviceCheckConfig, the offline check, reads
# its window, quiet factor and tilt from here): one window, the quiet window's spread against the noise floor (the
# quietest window so far), the windows in a row that make a rest, how far the specific force may turn
# within it, and the largest bias it takes (a rest reading more is a steady turn, not a bias: consumer
# MEMS gyros are specified to a few °/s; EuRoC's ADIS16448 reads 4.7 °/s, the iPhone 5 5.5 °/s)
CHECK_WINDOW = 0.5         # s
CHECK_NOISE_FACTOR = 2.5
CHECK_MIN_WINDOWS = 3.0    # 1.5 s
CHECK_TILT_DEG = 0.3       # °
CHECK_CLIP = 10.0          # °/s
MAG_FROZEN_MIN_T = 0.5  # s: a magnetometer repeats its readings exactly this long, at least, to be frozen
# (slower than the IMU, a magnetometer's readings are held: a 10 Hz one in a 100 Hz stream repeats for 0.1 s;
# the longest exact repeat in BROAD and OxIOD is 8 samples, 28 ms)
CLIP_BRIDGE_VAR = 0.25  # a clipped accelerometer is bridged by the gyro alone (tau_acc after each clipped
# sample) only while every axis's bias variance is below this fraction of its initial one (σ below half
# of bias_sigma_init: after rest, or motion updates); 0.05-0.25 give the same on every clipped recording
# the project has (kernels/backbone.py: acc_update)
CLIP_MIN_REPEATS = 4.0  # an axis at its extreme this many times in a row (a smooth, quantised peak
# repeats its value once or twice: BROAD's gyro did at 2.9 rad/s)
FROZEN_MIN_SAMPLES = 10.0  # and at least this many repeated samples (a slow IMU's 0.1 s is few)
F_ACC, F_ROT, F_BIAS, F_RG, F_RA, F_MAG = (_S["acc_lp"], _S["rot_lp"], _S["bias_lp"], _S["rest_gyro_lp"],
                                           _S["rest_acc_lp"], _S["mag_lp"])
C_TS, C_ACC_B, C_ACC_A, C_REST_B, C_REST_A, C_MAG_B, C_MAG_A = (_C["ts"], _C["acc_b"], _C["acc_a"], _C["rest_b"],
                                                               _C["rest_a"], _C["mag_b"], _C["mag_a"])
C_KMAG, C_KMAGREF, C_P0, C_V, C_WM, C_WV, C_WR = (_C["k_mag"], _C["k_mag_ref"], _C["bias_p0"], _C["bias_v"],
                                                  _C["bias_motion_w"], _C["bias_vertical_w"], _C["bias_rest_w"])
DEG = math.pi / 180.0
EPS = 2.220446049250313e-16  # float64 machine epsilon: VQF's threshold for a zero rotation rate
TS_TYP_RATE = 0.1   # the typical step's running mean: its weight per step (a gap is a step far beyond it)
TILT_MIN = 1e-12    # |v_xy| below this: the accelerometer's direction is (anti)parallel to up, no axis to turn about
TAU_FLOOR = 1e-9    # s: a low-pass time constant of 0 (switched off) still gives finite coefficients


def initial_state(params: BackboneParams) -> List[float]:
    """The state at the start (VQF's ``resetState``): identity quaternions, δ = 0, the bias
    covariance at its initial value, the field reference unknown (disturbed until accepted),
    every low-pass filter in its averaging phase."""
    s = [0.0] * N_STATE
    s[S_GQ] = 1.0
    s[S_AQ] = 1.0
    s[S_MAGDIST] = 1.0
    s[S_KMINIT] = 1.0
    p0 = (params.bias_sigma_init * 100.0) ** 2
    for i in range(3):
        s[S_P + 4 * i] = p0
    s[S_MREJ_T] = params.mag_max_rejection_time
    s[S_MCAND_N] = -1.0
    s[S_CK_FLOOR] = s[S_CK_FLOOR + 1] = -1.0  # no window seen yet
    return s
