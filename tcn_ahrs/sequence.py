"""``ImuSequence``: the one recording type, validated when it is built.

Every loader returns ``ImuSequence`` objects in the project's conventions
(:mod:`tcn_ahrs.conventions`): rad/s, m/s^2 (specific force, +g up at rest), uT, seconds,
ground-truth attitude as ``nav_from_body`` quaternions (w,x,y,z) with ENU navigation frame.
Arrays are numpy float64 (I/O side); models and filters convert to tensors themselves.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np

from .agreement import (EXCITED_RATE, MIN_REPORTED_LAG_S, axis_fit, evidence_text,  # noqa: F401
                        ground_truth_agreement, lag_text, mag_wiring_fit, mag_wiring_problem)
from .calibration_faults import accel_bias_fit, calibration_notes, judged_hard_iron, soft_iron_fit
from .conventions import GRAVITY, INPUT_RANGES, MAX_DT, MIN_DT


class DataError(ValueError):
    """Bad input data. The message names the file (source), the field and what was expected."""

    def __init__(self, source: str, field_name: str, problem: str):
        self.source, self.field_name, self.problem = source, field_name, problem
        super().__init__(f"{source}: field '{field_name}': {problem}")


@dataclass
class ImuSequence:
    """One IMU recording.

    Attributes (N samples):
        name:      short identifier of the recording (e.g. ``"05_undisturbed_slow_rotation_with_breaks_B"``).
        source:    where it came from (file or folder path, or ``"simulator(seed=...)"``).
        time:      (N,) seconds, strictly increasing.
        gyro:      (N, 3) angular rate of the body w.r.t. the navigation frame, body frame, rad/s.
        accel:     (N, 3) specific force, body frame, m/s^2 (+9.81 along the up axis at rest).
        mag:       (N, 3) magnetic field, body frame, uT; ``None`` for 6-axis recordings.
        quat:      (N, 4) ground-truth ``nav_from_body`` (w,x,y,z), ENU; ``None`` without ground truth.
                   Rows where ``quat_valid`` is False hold NaN (nothing is invented).
        quat_valid:(N,) bool, True where ``quat`` is a real measurement.
        score_mask:(N,) bool or None: samples a benchmark scores in addition to ``quat_valid``
                   (BROAD's ``movement``). ``None`` means all valid samples are scored.
        rate:      nominal sampling rate in Hz.
        meta:      free-form extras (dataset groups, sensor info, ...).
    """

    name: str
    source: str
    time: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    mag: Optional[np.ndarray] = None
    quat: Optional[np.ndarray] = None
    quat_valid: Optional[np.ndarray] = None
    score_mask: Optional[np.ndarray] = None
    rate: float = 0.0
    meta: dict = field(default_factory=dict)
    check_units: bool = True

    def __post_init__(self) -> None:
        self._validate()

    # ------------------------------------------------------------------ helpers
    def __len__(self) -> int:
        return int(self.time.shape[0])

    @property
    def has_mag(self) -> bool:
        return self.mag is not None

    @property
    def has_gt(self) -> bool:
        return self.quat is not None

    @property
    def num_axes(self) -> int:
        return 9 if self.has_mag else 6

    @property
    def duration(self) -> float:
        return float(self.time[-1] - self.time[0]) if len(self) > 1 else 0.0

    @property
    def dt(self) -> np.ndarray:
        """(N,) time step before each sample; dt[0] is the nominal 1/rate."""
        d = np.diff(self.time, prepend=self.time[0] - 1.0 / self.rate)
        return d

    def scored(self) -> np.ndarray:
        """(N,) bool: samples that metrics score (valid ground truth and the score mask)."""
        if self.quat_valid is None:
            return np.zeros(len(self), dtype=bool)
        m = self.quat_valid.copy()
        if self.score_mask is not None:
            m &= self.score_mask
        return m

    def imu(self) -> np.ndarray:
        """(N, 6) or (N, 9): gyro, accel[, mag] side by side."""
        parts = [self.gyro, self.accel] + ([self.mag] if self.mag is not None else [])
        return np.concatenate(parts, axis=1)

    def slice(self, start: int, stop: int, name: Optional[str] = None) -> "ImuSequence":
        """Samples ``start:stop`` as a new (validated) sequence."""
        def cut(a):
            return None if a is None else a[start:stop]
        return replace(self, name=name or self.name, time=self.time[start:stop], gyro=self.gyro[start:stop],
                       accel=self.accel[start:stop], mag=cut(self.mag), quat=cut(self.quat),
                       quat_valid=cut(self.quat_valid), score_mask=cut(self.score_mask), meta=dict(self.meta))

    def without_mag(self) -> "ImuSequence":
        """The 6-axis view of a 9-axis recording."""
        return replace(self, mag=None, meta=dict(self.meta))

    # --------------------------------------------------------------- validation
    def _fail(self, field_name: str, problem: str):
        raise DataError(self.source, field_name, problem)

    def _validate(self) -> None:
        self.time = self._array("time", self.time, (None,))
        n = self.time.shape[0]
        if n < 2:
            self._fail("time", f"expected at least 2 samples, got {n}")
        self.gyro = self._array("gyro", self.gyro, (n, 3))
        self.accel = self._array("accel", self.accel, (n, 3))
        if self.mag is not None:
            self.mag = self._array("mag", self.mag, (n, 3))
        d = np.diff(self.time)
        if not np.all(d > 0):
            i = int(np.argmax(~(d > 0)))
            self._fail("time", f"expected strictly increasing timestamps; sample {i + 1} "
                               f"({float(self.time[i + 1])!r} s) does not follow sample {i} ({float(self.time[i])!r} s)")
        if not self.rate or self.rate <= 0:
            self.rate = float(1.0 / np.median(d))
        if self.quat is not None:
            q = np.asarray(self.quat, dtype=np.float64)
            if q.ndim != 2 or q.shape != (n, 4):
                self._fail("quat", f"expected shape ({n}, 4) (w,x,y,z), got {q.shape}")
            finite = np.all(np.isfinite(q), axis=1)
            valid = finite if self.quat_valid is None else (np.asarray(self.quat_valid, dtype=bool) & finite)
            if valid.shape != (n,):
                self._fail("quat_valid", f"expected shape ({n},), got {valid.shape}")
            norms = np.linalg.norm(q[valid], axis=1)
            if norms.size and np.max(np.abs(norms - 1.0)) > 1e-2:
                self._fail("quat", f"expected unit quaternions, found norm {norms.min():.4f}..{norms.max():.4f}")
            q = q.copy()
            q[valid] /= norms[:, None]
            q[~valid] = np.nan
            self.quat = q
            self.quat_valid = valid
        elif self.quat_valid is not None:
            self._fail("quat_valid", "given without ground-truth quaternions")
        if self.score_mask is not None:
            self.score_mask = np.asarray(self.score_mask, dtype=bool)
            if self.score_mask.shape != (n,):
                self._fail("score_mask", f"expected shape ({n},), got {self.score_mask.shape}")
        if self.check_units:
            self._check_time()
            self._check_units()
            self._check_ground_truth()

    def _check_time(self) -> None:
        """Timestamps in seconds, no gap the attitude would be integrated across."""
        d = np.diff(self.time)
        step = float(np.median(d))
        if step > 0.5 or step < 1e-5:
            # the unit in which the file's own step is an IMU's (1 Hz - 20 kHz), given what was declared
            factors = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
            declared = str((self.meta.get("declared") or {}).get("time_unit", "s"))
            raw = step / factors.get(declared, 1.0)
            unit = next((u for u, f in factors.items() if 1.0 <= 1.0 / (raw * f) <= 2e4), None)
            names = {"s": "seconds", "ms": "milliseconds", "us": "microseconds", "ns": "nanoseconds"}
            said = f" (declared time_unit: {declared})" if declared != "s" else ""
            self._fail("time", f"expected seconds; the median step is {step:.4g} s{said}, a {1.0 / step:.3g} Hz IMU: "
                               + (f"the timestamps look like {names[unit]}: declare time_unit: {unit}" if unit
                                  else "check the timestamps' unit"))
        if float(d.min()) < MIN_DT:
            i = int(np.argmin(d))
            self._fail("time", f"samples {i} and {i + 1} are {float(d[i]):.3g} s apart (t = {float(self.time[i]):.9g} s; "
                               f"median step {step:.3g} s): below {MIN_DT:g} s, the shortest step any runtime takes "
                               "(a duplicated or garbled timestamp); drop one of the two samples")
        if float(d.max()) > MAX_DT:
            i = int(np.argmax(d))
            self._fail("time", f"a gap of {d[i]:.4g} s between samples {i} and {i + 1} (t = {self.time[i]:.6g} -> "
                               f"{self.time[i + 1]:.6g} s; median step {step:.3g} s): the attitude cannot be "
                               f"integrated across missing data (limit {MAX_DT:g} s, the runtimes' longest step); "
                               "split the recording there")
        gaps = np.flatnonzero(d > max(MAX_GAP_STEPS * step, MAX_GAP_S))
        if gaps.size:
            where_ = ", ".join(f"{d[i]:.3g} s at t = {self.time[i]:.6g} s" for i in gaps[:3])
            warnings.warn(f"{self.source}: {gaps.size} gap(s) in the IMU stream ({where_}{', …' if gaps.size > 3 else ''}): "
                          "the backbone runs across each (flagged `gap`; the gyro over it is the mean of the "
                          "readings either side, the heading taken from the magnetometer again); samples were "
                          "lost there", UserWarning, stacklevel=3)

    def _check_ground_truth(self) -> None:
        """Where ground truth exists, the gyro must agree with the rate differentiated from it and
        the specific force must point up in its frame: catches a wrong quaternion order, a gyro
        in deg/s, a flipped accelerometer and a ground-truth frame that is not z-up."""
        if self.quat is None or int(self.quat_valid.sum()) < 10:
            return
        agree = ground_truth_agreement(self)
        if agree.get("angle_deg") is not None and agree["angle_deg"] > 45.0:
            alt = agree.get("angle_deg_xyzw")
            if alt is not None and alt < 30.0:
                self._fail("quat", f"the gyro disagrees with the rate differentiated from the ground truth "
                                   f"(median angle {agree['angle_deg']:.0f} deg) but agrees when the quaternions "
                                   f"are read as x,y,z,w ({alt:.0f} deg): the values are in x,y,z,w order (HDF5: declare "
                                   "quat_order: xyzw; CSV: name the columns by what they hold)")
        lag = agree.get("time_offset_s") or 0.0
        if abs(lag) >= MIN_REPORTED_LAG_S:
            warnings.warn(f"{self.source}: the ground truth's stamps run {1000 * lag:.0f} ms late against the IMU's "
                          f"(fitted from the rates; the wiring and mount checks judge what remains): declare "
                          f"gt_time_offset: {lag:.4g} to align them", UserWarning, stacklevel=3)
        self._check_gyro_axes(agree)  # the specific per-axis causes before the general disagreement
        mag_fit = None if self.mag is None else mag_wiring_fit(self.mag, self.quat, self.quat_valid)  # read by both below
        problem = None if mag_fit is None else mag_wiring_problem(mag_fit)
        if problem:
            self._fail("mag", problem)
        soft = None if self.mag is None else soft_iron_fit(self.mag, self.quat, self.quat_valid)
        for note in calibration_notes(agree, mag_fit, self.meta.get("declared") or {}, accel_bias_fit(self), soft):
            warnings.warn(f"{self.source}: {note}", UserWarning, stacklevel=3)
        if agree.get("angle_deg") is not None and agree["angle_deg"] > 45.0:
            self._fail("quat", f"the gyro disagrees with the rate differentiated from the ground truth (median "
                               f"angle {agree['angle_deg']:.0f} deg over {agree['moving']} moving samples; "
                               "expected < 45): the ground truth's body frame is rotated against the IMU's, "
                               "or the quaternions are not nav_from_body (w,x,y,z)")
        scale = agree.get("scale")
        if scale is not None and not 0.5 < scale < 2.0:
            hint = (": is the gyro in deg/s? declare gyr_unit: deg/s" if 0.005 < scale < 0.05
                    else ": check the gyro's and the timestamps' units")
            self._fail("gyro", f"expected rad/s; the ground truth turns {scale:.3g} times as fast as the gyro "
                               f"says (median over {agree['moving']} moving samples){hint}")
        fit = agree.get("accel_fit") or {}
        for k in fit.get("dead_axes") or []:
            self._fail("accel", f"axis {'xyz'[k]} reads (almost) a constant while gravity moves along it: a dead "
                                "or disconnected accelerometer axis; this recording cannot be used")
        up = agree["up"]
        if not (up[2] < 0.5 and agree.get("up_concentration", 1.0) >= 0.9):
            self._check_accel_axes(fit)  # (a frame turned as a whole is the up test's, below)
        if up[2] < 0.5 and agree.get("up_concentration", 1.0) < 0.9:
            self._fail("accel", "the specific force does not keep one direction in the ground-truth frame "
                                f"(concentration {agree['up_concentration']:.2f}, expected ~1): the accelerometer's "
                                "axes disagree with the gyro's and the ground truth's; check its columns")
        if up[2] < 0.5:
            if up[2] < -0.5:
                why = ("the accelerometer reads gravity (down) instead of specific force (up)? declare "
                       "acc_sign: gravity; or the ground truth is in a z-down frame: declare nav_frame: NED")
            else:
                why = "the ground truth's frame is not z-up: declare its nav_frame"
            self._fail("accel", "expected specific force pointing up (+z, ENU) in the ground-truth frame; its "
                                f"mean direction there is [{up[0]:.2f}, {up[1]:.2f}, {up[2]:.2f}]: {why}")

    def _check_accel_axes(self, fit: Optional[dict]) -> None:
        """The accelerometer per axis against the gravity the ground truth predicts in the body
        frame (where the recording tilts enough): a dead axis, a left-handed frame, swapped or
        negated axes — causes the up test below would misreport as a ground-truth frame."""
        if fit and fit.get("static_problem"):
            self._fail("accel", fit["static_problem"])
        if not fit or fit.get("gyro_to_gt") is None:
            return
        judged = sorted(fit.get("judged_axes") or [])
        if len(judged) < 2 or fit.get("explained", 0.0) < 0.5:
            return
        a, perm = fit["gyro_to_gt"], fit["wiring"]
        if fit["det"] < 0 and float(np.linalg.det(perm)) < 0 and len(judged) == 3:
            self._fail("accel", "the accelerometer's axes form a left-handed frame against the ground truth's body "
                                f"frame (fitted map {np.round(a, 2).tolist()}; {evidence_text(fit)}): one axis has the "
                                "wrong sign or two are swapped; negate or swap the column")
        wrong = [i for i in judged if perm[i, i] != 1.0]
        if wrong:
            self._fail("accel", f"axes wired differently from the gyro's and the ground truth's body frame (fitted "
                                f"map {np.round(a, 2).tolist()}; {evidence_text(fit)}): fix the accelerometer's columns")

    def _check_gyro_axes(self, agree: dict) -> None:
        """Per-axis wiring against the ground-truth body rate (:func:`axis_fit`): a dead or
        saturated axis, a flipped sign or swapped axes, a left-handed frame, a rotated body frame,
        and a gyro far slower or faster than the ground truth where only the latter turns (a
        rad/s gyro declared deg/s on a slow clip)."""
        xyz = "xyz"
        gs = agree.get("gt_scale")
        if gs is not None and (30.0 < gs < 100.0 or 0.005 < gs < 0.05):  # a deg/s <-> rad/s mix-up first
            hint = ("is the gyro already in rad/s? remove gyr_unit: deg/s" if gs > 1.0
                    else "is it in deg/s? declare gyr_unit: deg/s")
            self._fail("gyro", f"expected rad/s; where the ground truth turns it turns {gs:.3g} times as fast as "
                               f"the gyro says (median over {agree['gt_moving']} samples): {hint}")
        for k in agree.get("dead_axes") or []:
            self._fail("gyro", f"axis {xyz[k]} reads (almost) a constant while the ground truth turns about it: "
                               "a dead or disconnected gyro axis; this recording cannot be used")
        for k, level in (agree.get("saturated") or {}).items():
            self._fail("gyro", f"axis {xyz[k]} sticks at ±{level:.3g} rad/s while the ground truth turns faster: "
                               "the gyro saturates (its range setting is too small); drop those parts or record "
                               "with a larger range")
        if gs is not None and not 0.5 < gs < 2.0 and (agree.get("scale") is None or agree.get("moving", 0) < 30):
            self._fail("gyro", f"expected rad/s; where the ground truth turns it turns {gs:.3g} times as fast as "
                               f"the gyro says (median over {agree['gt_moving']} samples): check the gyro's and "
                               "the timestamps' units")
        a, perm, judged = agree.get("gyro_to_gt"), agree.get("wiring"), sorted(agree.get("judged_axes") or [])
        if a is None or not judged:
            return
        evidence = evidence_text(agree)
        if agree["det"] < 0 and len(judged) == 3:  # handedness needs all three axes judged
            self._fail("gyro", "the gyro's axes form a left-handed frame against the ground truth's body frame "
                               f"(fitted map {np.round(a, 2).tolist()}, determinant < 0; {evidence}): one axis has "
                               "the wrong sign or two axes are swapped; no rotation fixes that: negate or swap the column")
        wrong = [i for i in judged if perm[i, i] != 1.0]
        if wrong:
            reads = "; ".join(f"the body's {xyz[i]} rate is read by gyro {'-' if perm[i].sum() < 0 else '+'}"
                              f"{xyz[int(np.argmax(np.abs(perm[i])))]}" for i in wrong)
            # a mount rotation is a fix only where every axis is judged and the wiring is a rotation
            mount = (f", or, if the IMU is mounted rotated, declare gt_body_from_imu: {perm.astype(int).tolist()}"
                     if len(judged) == 3 and np.linalg.det(perm) > 0 else "")
            self._fail("gyro", f"axes wired differently from the ground truth's body frame: {reads} (fitted map "
                               f"{np.round(a, 2).tolist()}; {evidence}): fix the columns{mount}")
        mis = agree.get("misalignment_deg")
        if mis is not None and len(judged) == 3 and len(agree["excited_axes"]) >= 2 and mis > MAX_MISALIGNMENT_DEG:
            rot = np.round(agree["rotation"], 4).tolist()
            self._fail("quat", f"the ground truth's body frame is rotated {mis:.1f} deg against the IMU's (fitted "
                               f"from the rates about all three axes{lag_text(agree)}; {evidence}; expected < "
                               f"{MAX_MISALIGNMENT_DEG:g}): declare gt_body_from_imu: {rot} (C_body_from_imu, rows)")

    def _array(self, name: str, a, shape) -> np.ndarray:
        try:
            a = np.asarray(a, dtype=np.float64)
        except (TypeError, ValueError) as e:
            self._fail(name, f"expected numbers: {e}")
        if a.ndim != len(shape) or any(s is not None and s != t for s, t in zip(shape, a.shape)):
            want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
            self._fail(name, f"expected shape {want}, got {a.shape}")
        bad = ~np.isfinite(a)
        if bad.any():
            i = int(np.argmax(bad.reshape(a.shape[0], -1).any(axis=1)))
            self._fail(name, f"expected finite values, found NaN/inf (first at sample {i})")
        limit = INPUT_RANGES.get(name)
        if limit is not None and a.size and float(np.max(np.abs(a))) > limit:
            i, k = (int(v) for v in np.argwhere(np.abs(a) > limit)[0])
            unit = {"gyro": "rad/s", "accel": "m/s^2", "mag": "uT"}[name]
            many = float(np.mean(np.abs(a) > limit)) > 0.01 or (np.abs(a[max(0, i - 2):i + 3, k]) > limit / 4).sum() > 1
            why = ({"gyro": "is it in deg/s? declare gyr_unit: deg/s (or convert with conventions.deg_to_rad)",
                    "accel": "check its unit (m/s^2 expected)",
                    "mag": "is it in nT? convert with conventions.nt_to_ut"}[name] if many
                   else "a spike: drop or interpolate that sample")  # its neighbours well within the range
            self._fail(name, f"sample {i}, axis {'xyz'[k]}: {a[i, k]:.4g} {unit} is beyond any sensor's range "
                             f"(|value| <= {limit:g} {unit}, conventions.INPUT_RANGES): {why}")
        return a

    def _check_units(self) -> None:
        """Catch the common unit mistakes: deg/s gyros, accelerometers in g, fields in Gauss."""
        acc_norm = float(np.median(np.linalg.norm(self.accel, axis=1)))
        if acc_norm < 0.02 * GRAVITY:
            self._fail("accel", f"reads (almost) zero (median norm {acc_norm:.3g} m/s^2; gravity alone gives 9.81): a "
                                "dead or disconnected accelerometer; this recording cannot be used")
        if acc_norm < 0.3 * GRAVITY:
            self._fail("accel", f"expected specific force in m/s^2 (median norm ~9.8), got median norm "
                                f"{acc_norm:.3g}: is it in g? convert with conventions.g_to_mps2")
        if acc_norm > 3.0 * GRAVITY:
            self._fail("accel", f"expected specific force in m/s^2 (median norm ~9.8), got median norm {acc_norm:.3g}")
        gyro_abs = np.abs(self.gyro)
        if float(np.max(gyro_abs)) > 50.0:  # 50 rad/s = 2865 deg/s: beyond any MEMS range
            self._fail("gyro", f"expected rad/s, got values up to {np.max(gyro_abs):.3g}: is it in deg/s? "
                               "convert with conventions.deg_to_rad")
        rest = _rest_samples(self.accel, self.rate)
        if rest.sum() >= max(20, int(0.5 * self.rate)):
            # Sample-to-sample noise of a gyro at rest: a few mrad/s in rad/s, ~0.1-1 in deg/s.
            noise = float(np.median(np.abs(np.diff(self.gyro[rest], axis=0))))
            if noise > 0.05:
                self._fail("gyro", f"expected rad/s; at rest the gyro's sample-to-sample noise is {noise:.3g}, "
                                   "typical of deg/s (rad/s gives ~0.001-0.01): convert with conventions.deg_to_rad")
        if self.mag is not None and not np.any(self.mag):
            # no magnetometer behind the columns: a 6-axis recording (a 9-axis model refuses it)
            warnings.warn(f"{self.source}: field 'mag' reads 0 on every sample: no magnetometer; loaded as a "
                          "6-axis recording", UserWarning, stacklevel=3)
            self.mag, self.meta["mag_absent"] = None, "its field 'mag' reads 0 on every sample (a dead magnetometer)"
        if self.mag is not None:
            mag_norm = float(np.median(np.linalg.norm(self.mag, axis=1)))
            if mag_norm < 2.0:
                self._fail("mag", f"expected microtesla (Earth ~25-65 uT), got median norm {mag_norm:.3g}: "
                                  "is it in Gauss? convert with conventions.gauss_to_ut")
            if mag_norm > 5000.0:
                self._fail("mag", f"expected microtesla (Earth ~25-65 uT), got median norm {mag_norm:.3g}: "
                                  "is it in nT? convert with conventions.nt_to_ut")
            found = None if "mag_hard_iron" in (self.meta.get("declared") or {}) else judged_hard_iron(self.mag)
            if found is not None:  # calibrated here, and said: the offset is removed, as a declaration would
                self.mag = self.mag - found[0]
                warnings.warn(f"{self.source}: field 'mag': {found[1]}: subtracted (declare mag_hard_iron: "
                              f"{[round(float(v), 1) for v in found[0]]} to fix it, or [0, 0, 0] to keep the field as "
                              "recorded)", UserWarning, stacklevel=3)


MAX_MISALIGNMENT_DEG = 5.0  # real recordings fit 0.1-1.9 deg where all three axes turn (EuRoC, TUM VI)
MAX_GAP_STEPS = 20.0  # a time step longer than this many median steps ...
MAX_GAP_S = 0.2      # ... and than this many seconds is a gap in the data (warned), not a late sample;
# one longer than conventions.MAX_DT (the runtimes' longest step) is refused


def _rest_samples(accel: np.ndarray, rate: float, window_s: float = 0.5, tol: float = 0.05) -> np.ndarray:
    """(N,) bool: samples inside windows where the accelerometer is almost constant (rest)."""
    n = accel.shape[0]
    w = max(3, int(window_s * rate))
    if n < w:
        return np.zeros(n, dtype=bool)
    c = np.cumsum(np.vstack([np.zeros((1, 3)), accel]), axis=0)
    c2 = np.cumsum(np.vstack([np.zeros((1, 3)), accel**2]), axis=0)
    mean = (c[w:] - c[:-w]) / w
    var = (c2[w:] - c2[:-w]) / w - mean**2
    # a frozen accelerometer (readings repeating exactly) is not rest: a still window must change
    # (else fast motion read as rest had the gyro's noise "typical of deg/s")
    rep = np.concatenate([[0], np.cumsum(np.r_[False, (np.diff(accel, axis=0) == 0).all(1)])])
    frozen = (rep[w:] - rep[:-w]) > w // 2
    still = (np.sqrt(np.maximum(var, 0).sum(axis=1)) < tol * GRAVITY * 0.2) & ~frozen
    # A sample is at rest if any still window covers it: dilate the window starts by w
    # with a cumulative sum (no Python loop).
    starts = np.concatenate([still.astype(np.int64), np.zeros(w, dtype=np.int64)])
    c_start = np.concatenate([[0], np.cumsum(starts)])
    k = np.arange(n)
    covered = c_start[k + 1] - c_start[np.maximum(k - w + 1, 0)]
    return covered > 0


def rest_mask(seq: ImuSequence, window_s: float = 0.5) -> np.ndarray:
    """(N,) bool: samples of ``seq`` at rest (almost constant accelerometer)."""
    return _rest_samples(seq.accel, seq.rate, window_s)


JITTER_TOL = 0.02  # relative spread of the steps below which a clock counts as regular


def clock_kind(time: np.ndarray) -> dict:
    """How a recording was sampled, from its timestamps alone: ``regular`` (steps within
    :data:`JITTER_TOL` of the median), ``jittered`` (a regular stream whose stamps are noisy: every
    stamp within half a step of one uniform grid, the least-squares line through sample index and
    time) or ``irregular`` (the steps themselves vary: the stamps wander off any grid). Returns
    ``kind``, ``step`` (s, the grid's), ``jitter`` (the steps' relative spread, robust: 1.4826 MAD
    / median) and ``off_grid`` (the largest distance of a stamp from the grid, in steps)."""
    t = np.asarray(time, dtype=np.float64)
    d = np.diff(t)
    med = float(np.median(d))
    jitter = float(1.4826 * np.median(np.abs(d - med)) / med)
    k = np.arange(t.shape[0], dtype=np.float64)
    step, t0 = np.polyfit(k, t, 1)
    off = float(np.max(np.abs(t - (t0 + step * k))) / step)
    kind = "regular" if jitter < JITTER_TOL else ("jittered" if off < 0.5 else "irregular")
    return {"kind": kind, "step": float(step), "jitter": jitter, "off_grid": off, "grid_start": float(t0)}
