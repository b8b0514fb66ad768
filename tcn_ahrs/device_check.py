"""A device check without ground truth: from a recording's own statistics, the gyro bias at rest,
the sensors' noise floors, how much of it rests, and whether its magnetic field is steady enough
for a 9-axis heading — and from them the correction a filter should start from.

Why: VQF (and the backbone with its defaults) declares rest only while the low-passed gyro lies
within its bias clip (2 °/s) and never estimates a bias beyond it. EuRoC's gyro reads about
4.4 °/s about z at rest, so it never rests there and the heading drifts ~100° in two minutes;
any fixed clip is a guess about one device. Here rest is judged by the signal's *character*, not
by absolute thresholds, so a large constant bias still counts as rest and slow motion does not:

* windows of ``window_s``; a window is quiet when its gyro and accelerometer spreads (largest
  per-axis standard deviation) are within ``noise_factor`` × the recording's own noise floors
  (their ``floor_percentile``-th percentile over all windows: the quietest stretch is the sensor's
  noise, whatever its absolute level);
* at least ``min_rest_s`` of consecutive quiet windows whose mean specific-force direction stays
  within ``max_tilt_deg`` is rest (a slow turn tilts it: handheld motion is not rest);
* the gyro bias is the median reading over all rest samples (robust to a stray window).

``check`` returns the statistics, the decision and the reasons in words; ``calibration`` turns it
into a :class:`~tcn_ahrs.calibration.StaticCalibration` (gyro bias only) that every estimator
family reads. Frames and units: the body frame; rad/s, m/s², µT.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from .kernels.backbone_layout import CHECK_NOISE_FACTOR, CHECK_TILT_DEG, CHECK_WINDOW
from .sequence import ImuSequence


@dataclass(frozen=True)
class DeviceCheckConfig:
    """The check's settings (meaning, unit, default)."""

    # the window, the quiet factor and the tilt are the causal check's (kernels/backbone_layout.py:
    # CHECK_*); its rest is 1.5 s, its floor the quietest window so far (this one's a percentile)
    window_s: float = CHECK_WINDOW           # s, one window of the statistics
    floor_percentile: float = 2.0            # %, the quietest windows' spread taken as the noise floor
    noise_factor: float = CHECK_NOISE_FACTOR  # a quiet window's spread is within this × the noise floor
    min_rest_s: float = 2.0                  # s of consecutive quiet windows that make a rest
    max_tilt_deg: float = CHECK_TILT_DEG     # °, how far the specific force may turn within a rest
    field_spread: float = 0.1      # relative spread (robust) of the field norm a 9-axis heading tolerates
    dip_spread_deg: float = 5.0    # °, the same for the field's dip


@dataclass
class DeviceCheck:
    """What the check found (see the module docstring). ``gyro_bias`` (3,) rad/s or None when the
    recording never rests; ``gyro_noise`` / ``acc_noise``: the noise floors (rad/s, m/s², per
    window's standard deviation); ``rest_fraction`` of the recording; ``axes``: 9 where the field is
    steady, else 6 (advice only: every method still gets the magnetometer); ``reasons``: why, in words."""

    gyro_bias: Optional[np.ndarray]
    gyro_noise: float
    acc_noise: float
    rest_fraction: float
    axes: int
    reasons: List[str] = field(default_factory=list)

    def calibration(self):
        """The gyro bias as a :class:`~tcn_ahrs.calibration.StaticCalibration` (identity without rest)."""
        from .calibration import StaticCalibration

        if self.gyro_bias is None:
            return StaticCalibration()
        return StaticCalibration(gyro_bias=np.asarray(self.gyro_bias, dtype=np.float64).copy(),
                                 modes={"gyro": "bias", "acc": "none", "mag": "none"})

    def summary(self) -> str:
        return "; ".join(self.reasons)


def rest_windows(gyro: np.ndarray, acc: np.ndarray, rate: float, cfg: DeviceCheckConfig = DeviceCheckConfig()):
    """(rest (W,) bool per window, window length in samples, gyro floor, acc floor) for gyro, acc
    (N, 3) at ``rate`` Hz (see the module docstring)."""
    n = max(2, int(round(cfg.window_s * rate)))
    m = gyro.shape[0] // n
    if m < 1:
        return np.zeros(0, bool), n, float("nan"), float("nan")
    g = gyro[:m * n].reshape(m, n, 3)
    a = acc[:m * n].reshape(m, n, 3)
    g_spread, a_spread = g.std(1).max(1), a.std(1).max(1)
    # a frozen sensor (most of a window's readings repeating the previous one exactly while the other
    # sensor's readings change) is not rest: its zero spread would set the noise floor and pass for stillness
    # while the other sensor turns (a BROAD clip with the accelerometer frozen 5 s lost its real rest;
    # issue 55's trial read the freeze as rest, a "gyro bias" of -111, -78, +50 °/s); real noise makes
    # exact repeats rare. Both repeating is a noise-free sensor at rest (the simulator's), kept.
    fg, fa = ((np.diff(x, axis=1) == 0).all(2).mean(1) > 0.5 for x in (g, a))
    frozen = fg ^ fa
    live = ~frozen if (~frozen).any() else np.ones(m, bool)
    g_floor = float(np.percentile(g_spread[live], cfg.floor_percentile))
    a_floor = float(np.percentile(a_spread[live], cfg.floor_percentile))
    quiet = (g_spread <= cfg.noise_factor * g_floor) & (a_spread <= cfg.noise_factor * a_floor) & ~frozen
    up = a.mean(1)
    up = up / np.maximum(np.linalg.norm(up, axis=1, keepdims=True), 1e-12)
    rest = np.zeros(m, bool)
    need = max(1, int(np.ceil(cfg.min_rest_s / cfg.window_s)))
    for i, j in stretches(quiet):
        if j - i >= need:
            mean = up[i:j].mean(0)
            mean = mean / np.linalg.norm(mean)
            tilt = np.degrees(np.arccos(np.clip(up[i:j] @ mean, -1.0, 1.0))).max()
            rest[i:j] = tilt <= cfg.max_tilt_deg
    return rest, n, g_floor, a_floor


def stretches(mask: np.ndarray) -> List[Tuple[int, int]]:
    """[(start, stop)) of each run of consecutive True in the (W,) bool ``mask``."""
    edges = np.diff(np.concatenate([[0], np.asarray(mask, dtype=np.int8), [0]]))
    return list(zip(np.nonzero(edges == 1)[0].tolist(), np.nonzero(edges == -1)[0].tolist()))


def check(seq: ImuSequence, cfg: DeviceCheckConfig = DeviceCheckConfig()) -> DeviceCheck:
    """The device check of one recording (no ground truth read)."""
    rest, n, g_floor, a_floor = rest_windows(seq.gyro, seq.accel, float(seq.rate), cfg)
    reasons: List[str] = []
    bias = None
    frac = float(rest.mean()) if rest.size else 0.0
    if rest.any():
        samples = seq.gyro[:rest.size * n].reshape(rest.size, n, 3)[rest].reshape(-1, 3)
        bias = np.median(samples, 0)
        reasons.append(f"rests {100 * frac:.0f} % of the time (gyro noise {np.degrees(g_floor):.3f} °/s, "
                       f"accelerometer {a_floor:.3f} m/s²): gyro bias [{', '.join(f'{v:+.2f}' for v in np.degrees(bias))}] "
                       "°/s, subtracted before the filter")
    else:
        reasons.append("never rests (no stretch of the noise floor with a steady tilt): no gyro bias subtracted, "
                       "the filter estimates it")
    axes = 6
    if seq.mag is not None:
        norm = np.linalg.norm(seq.mag, axis=1)
        spread = float(1.4826 * np.median(np.abs(norm - np.median(norm))) / max(np.median(norm), 1e-9))
        up = seq.accel / np.maximum(np.linalg.norm(seq.accel, axis=1, keepdims=True), 1e-12)
        dip = np.degrees(np.arcsin(np.clip(np.sum(seq.mag * up, 1) / np.maximum(norm, 1e-9), -1.0, 1.0)))
        dip_spread = float(1.4826 * np.median(np.abs(dip - np.median(dip))))
        if spread <= cfg.field_spread and dip_spread <= cfg.dip_spread_deg:
            axes = 9
            reasons.append(f"the field is steady (norm spread {100 * spread:.1f} %, dip spread {dip_spread:.1f}°): 9 axes")
        else:
            # said, not applied: the filters' own disturbance rejection handles it per sample; dropping the
            # magnetometer instead (heading from the gyro) measured 47.5° against 18.4° on the 45 iPhone
            # recordings this flags
            reasons.append(f"the field is not steady (norm spread {100 * spread:.1f} %, dip spread {dip_spread:.1f}°; "
                           f"limits {100 * cfg.field_spread:.0f} %, {cfg.dip_spread_deg:g}°): magnetic disturbance, "
                           "the magnetometer is kept and the filter's disturbance rejection decides when to trust it")
    else:
        reasons.append("no magnetometer: 6 axes")
    return DeviceCheck(gyro_bias=bias, gyro_noise=g_floor, acc_noise=a_floor, rest_fraction=frac, axes=axes,
                       reasons=reasons)


def checked(seqs: Sequence[ImuSequence], report: Optional[Callable[[str, DeviceCheck], None]] = None,
            cfg: DeviceCheckConfig = DeviceCheckConfig()) -> List[ImuSequence]:
    """``seqs`` with their gyro bias at rest subtracted, one check per recording (``meta["recording"]``,
    else the name): read from whichever of its parts rests longest and applied to all of them (a
    later part in flight never rests: EuRoC's 4.4 °/s bias would stay in it). ``report(recording,
    check)``: called once per recording (``evaluate`` prints it)."""
    best: Dict[str, Tuple[float, DeviceCheck]] = {}
    for s in seqs:
        dc, rec = check(s, cfg), s.meta.get("recording", s.name)
        rest_s = dc.rest_fraction * s.duration
        if rec not in best or rest_s > best[rec][0]:
            best[rec] = (rest_s, dc)
    if report is not None:
        for rec, (_, dc) in best.items():
            report(rec, dc)
    return [best[s.meta.get("recording", s.name)][1].calibration().apply(s) for s in seqs]


class RestBiasCalibration:
    """The device check as a calibration a classical filter runs on: each recording's own gyro bias
    at rest subtracted when it is run (:func:`checked`; nothing fitted, no ground truth read) —
    what ``tcn-ahrs evaluate`` gives every method by default. Written to an estimator file as
    ``{"kind": "device_check"}``."""

    KIND = "device_check"

    def apply(self, seq: ImuSequence) -> ImuSequence:
        return checked([seq])[0]

    def to_dict(self) -> Dict[str, object]:
        return {"kind": self.KIND, "summary": "each recording's gyro bias at rest subtracted (tcn_ahrs.device_check)"}

