"""``ImuSequence``: the one recording type, validated when it is built.

Every loader returns ``ImuSequence`` objects in the project's conventions
(:mod:`tcn_ahrs.conventions`): rad/s, m/s^2 (specific force, +g up at rest), uT, seconds,
ground-truth attitude as ``nav_from_body`` quaternions (w,x,y,z) with ENU navigation frame.
Arrays are numpy float64 (I/O side); models and filters convert to tensors themselves.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np

from .conventions import GRAVITY, INPUT_RANGES


class DataError(ValueError):
    """Bad input data. The message names the file (source), the field and what was expected."""

    def __init__(self, source: str, field_name: str, problem: str):
        self.source = source
        self.field_name = field_name
        self.problem = problem
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
        return replace(
            self,
            name=name or self.name,
            time=self.time[start:stop],
            gyro=self.gyro[start:stop],
            accel=self.accel[start:stop],
            mag=cut(self.mag),
            quat=cut(self.quat),
            quat_valid=cut(self.quat_valid),
            score_mask=cut(self.score_mask),
            meta=dict(self.meta),
        )

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
                               f"({self.time[i + 1]!r}) does not follow sample {i} ({self.time[i]!r})")
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
        if step > 0.5:
            self._fail("time", f"expected seconds; the median step is {step:.4g} (a {1.0 / step:.3g} Hz IMU): "
                               "timestamps in milliseconds? declare time_unit: ms (or convert to s)")
        if step < 1e-5:
            self._fail("time", f"expected seconds; the median step is {step:.3g} (a {1.0 / step:.3g} Hz IMU): "
                               "timestamps in microseconds or nanoseconds? declare time_unit: us / ns")
        limit = max(MAX_GAP_STEPS * step, MAX_GAP_S)
        if float(d.max()) > limit:
            i = int(np.argmax(d))
            self._fail("time", f"a gap of {d[i]:.4g} s between samples {i} and {i + 1} (t = {self.time[i]:.6g} -> "
                               f"{self.time[i + 1]:.6g} s; median step {step:.3g} s): the attitude cannot be "
                               f"integrated across missing data (limit {limit:.3g} s); split the recording there")

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
        up = agree["up"]
        if up[2] < 0.5:
            if up[2] < -0.5:
                why = ("the accelerometer reads gravity (down) instead of specific force (up)? declare "
                       "acc_sign: gravity; or the ground truth is in a z-down frame: declare nav_frame: NED")
            else:
                why = "the ground truth's frame is not z-up: declare its nav_frame"
            self._fail("accel", "expected specific force pointing up (+z, ENU) in the ground-truth frame; its "
                                f"mean direction there is [{up[0]:.2f}, {up[1]:.2f}, {up[2]:.2f}]: {why}")

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
            many = float(np.mean(np.abs(a) > limit)) > 0.01
            why = ({"gyro": "is it in deg/s? declare gyr_unit: deg/s (or convert with conventions.deg_to_rad)",
                    "accel": "check its unit (m/s^2 expected)",
                    "mag": "is it in nT? convert with conventions.nt_to_ut"}[name] if many
                   else "a spike: drop or interpolate that sample")
            self._fail(name, f"sample {i}, axis {'xyz'[k]}: {a[i, k]:.4g} {unit} is beyond any sensor's range "
                             f"(|value| <= {limit:g} {unit}, conventions.INPUT_RANGES): {why}")
        return a

    def _check_units(self) -> None:
        """Catch the common unit mistakes: deg/s gyros, accelerometers in g, fields in Gauss."""
        acc_norm = float(np.median(np.linalg.norm(self.accel, axis=1)))
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
        if self.mag is not None:
            mag_norm = float(np.median(np.linalg.norm(self.mag, axis=1)))
            if mag_norm < 2.0:
                self._fail("mag", f"expected microtesla (Earth ~25-65 uT), got median norm {mag_norm:.3g}: "
                                  "is it in Gauss? convert with conventions.gauss_to_ut")
            if mag_norm > 5000.0:
                self._fail("mag", f"expected microtesla (Earth ~25-65 uT), got median norm {mag_norm:.3g}: "
                                  "is it in nT? convert with conventions.nt_to_ut")


MAX_GAP_STEPS = 20.0  # a time step longer than this many median steps ...
MAX_GAP_S = 0.2      # ... and than this many seconds is a gap in the data, not a late sample


def ground_truth_agreement(seq: "ImuSequence", lag_s: float = 0.05, min_rate: float = 0.2) -> dict:
    """How the IMU agrees with the ground truth of ``seq`` (shown by ``inspect_data``, checked
    when a recording is built):

    * ``angle_deg``: median angle between the mean gyro over ``lag_s`` and the body rate
      differentiated from the ground truth over the same interval, on samples where both turn
      faster than ``min_rate`` rad/s (``moving`` of them); a few degrees when frames agree;
      ``angle_deg_xyzw`` the same with the quaternions read as x,y,z,w;
    * ``scale``: median |ground-truth rate| / |gyro rate| (1 in rad/s; 0.017 for deg/s);
    * ``up``: mean direction (3,) of the specific force in the ground-truth frame (+z, ENU).
    ``angle_deg``/``scale`` are None when fewer than 30 samples move."""
    import torch

    from . import so3

    valid = seq.quat_valid
    t = seq.time
    lag = max(1, int(round(lag_s * seq.rate)))
    ok = valid[lag:] & valid[:-lag]
    q = torch.as_tensor(np.where(valid[:, None], seq.quat, 0.0), dtype=torch.float64)
    a = torch.as_tensor(seq.accel[valid], dtype=torch.float64)
    f = so3.quat_rotate(q[torch.as_tensor(valid)], a / a.norm(dim=1, keepdim=True).clamp_min(1e-9))
    out = {"up": f.mean(0).numpy(), "angle_deg": None, "angle_deg_xyzw": None, "scale": None, "moving": 0}
    if ok.sum() < 30:
        return out
    okt = torch.as_tensor(ok)
    span = torch.as_tensor(t[lag:] - t[:-lag])[okt][:, None]
    # mean gyro over (t_k, t_{k+lag}]: sample k moves the attitude from k-1 to k
    c = np.cumsum(np.vstack([np.zeros((1, 3)), seq.gyro[1:] * np.diff(t)[:, None]]), 0)
    w_gyro = torch.as_tensor((c[lag:] - c[:-lag]))[okt] / span

    def gt_rate(qq):
        return so3.quat_log(so3.quat_mul(so3.quat_conj(qq[:-lag][okt]), qq[lag:][okt])) / span

    w_gt = gt_rate(q)
    moving = (w_gyro.norm(dim=1) > min_rate) & (w_gt.norm(dim=1) > min_rate)
    out["moving"] = int(moving.sum())
    if out["moving"] < 30:
        return out

    def angle(w):
        cos = torch.nn.functional.cosine_similarity(w[moving], w_gyro[moving], dim=1)
        return float(torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0))).median())

    out["angle_deg"] = angle(w_gt)
    out["angle_deg_xyzw"] = angle(gt_rate(q[:, [3, 0, 1, 2]]))
    out["scale"] = float((w_gt[moving].norm(dim=1) / w_gyro[moving].norm(dim=1)).median())
    return out


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
    still = np.sqrt(np.maximum(var, 0).sum(axis=1)) < tol * GRAVITY * 0.2
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
