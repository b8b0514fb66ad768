"""Published attitude estimators from PyPI ("peers"), run under the project's Estimator interface.

Each wrapper feeds an :class:`~tcn_ahrs.sequence.ImuSequence` (rad/s, m/s^2 specific force
pointing up at rest, uT, ENU) to one library in that library's own conventions and converts
its output back to ``nav_from_body`` quaternions (w,x,y,z) in ENU, so that one benchmark
command scores every estimator on the same recordings with the same metric code.

The ``ahrs`` package's three filters live in :mod:`tcn_ahrs.estimators.peers_ahrs`, RIANN in
:mod:`tcn_ahrs.estimators.peers_riann` (one module per library).

The peers are an optional extra (``pip install -e .[peers]``): importing this module never
imports them; a wrapper imports its library when it is built and raises
:class:`PeerUnavailable` (an ``ImportError``) naming the install command when it is missing.

Conventions of each library, as found in the installed sources and checked by
``tests/test_peers.py`` on synthetic recordings with known attitude:

============  =========================================================================
vqf 2.1       Causal ``VQF(gyrTs).updateBatch(gyr, acc, mag)`` (``offlineVQF`` is the
              non-causal forward-backward variant, not used by default). Inputs rad/s,
              m/s^2 (specific force, up), any field unit; arrays must be C-contiguous
              float64 (the wrapper makes them so). Output ``quat6D``/``quat9D`` w,x,y,z
              ``nav_from_body``; 9D reference frame is ENU (z up; the magnetometer
              heading update uses ``atan2(m_x, m_y)``, i.e. magnetic north is +y). The 6D
              frame is z up with arbitrary heading. The initial attitude is set through
              ``VQF.state`` (``gyrQuat``; ``accQuat`` identity).
imufusion     x-io Fusion (>= 1.3 API). Inputs deg/s and g (specific force), any field unit.
1.3           ``AhrsSettings(...)`` IGNORES its ``convention`` argument (it stays NWU);
              the wrapper sets ``settings.convention = CONVENTION_ENU`` through the
              property setter. Output ``get_quaternion()`` w,x,y,z ``nav_from_body``
              in the chosen convention. Per-sample period via ``set_sample_period(dt)``.
ahrs 0.4      ``Madgwick``: NWU (x magnetic north, z up), specific force (up).
              ``Mahony``: ENU (its magnetic reference is ``[0, b_h, b_z]``), specific
              force (up). ``EKF``: ``frame='NED'`` by default, and in BOTH its frames the
              accelerometer reference ``a_ref`` is the DOWN direction, i.e. it expects
              the gravity vector (-specific force): the wrapper negates the accelerometer.
              The EKF normalises the magnetometer and compares it with the unit vector
              ``magnetic_ref`` (default: the WMM field of Munich); the wrapper passes the
              local dip angle measured at the first sample instead. All three return
              ``nav_from_body`` w,x,y,z; all skip the whole update when the gyro reads
              exactly zero (never happens on real data).
riann 0.2     ``RIANN(onnx_path)``: 0.2.0 looks its model up with
              ``importlib.resources.path("riann.riann", ...)`` which fails (a module, not
              a package) and falls back to paths relative to the working directory, so the
              wrapper passes ``Path(riann.__file__).parent / "riann.onnx"``. Batch API
              ``predict(acc, gyr, fs)`` (one ONNX call over the whole sequence; the GRU is
              causal), streaming API ``set_sampling_rate(fs)`` + ``predict_step(acc, gyr)``
              (one ONNX call per sample; ``reset_state()`` between recordings) -- use the
              latter for latency/speed benchmarks. Inputs m/s^2 (specific force), rad/s.
              Output w,x,y,z ``nav_from_body`` with z up and arbitrary, drifting heading.
============  =========================================================================

Scoring heading-free estimators: RIANN has no heading reference and does not integrate a
meaningful one, so its wrapper has ``heading_free = True``. The benchmark then scores it
on inclination only: BROAD's ``inclination_deg`` (:func:`tcn_ahrs.metrics.broad_errors`)
and the inclination error of the aligned estimate; AYE and heading are reported as NaN.
6-axis wrappers (``axes == 6``) are not heading-free: they integrate heading from the
initial attitude and are scored with the 6D conventions of :mod:`tcn_ahrs.metrics`.

Initial attitude: the ``ahrs`` filters start from ``init_quat`` (else from the first
accelerometer/magnetometer sample, TRIAD in ENU), imufusion is seeded with it (and skips
its start-up phase, which would overwrite it), VQF starts from it through its state (9D:
its heading then snaps to the magnetometer), RIANN initialises itself and ignores it (the
yardstick's unscored settling time covers its start).
"""
from __future__ import annotations

import importlib
from dataclasses import replace
from typing import Any, Dict, Optional, Tuple

import numpy as np

from ..conventions import GRAVITY, enu_from_frame, rad_to_deg
# quaternions (w,x,y,z, Hamilton) on numpy arrays: the project's so3 through its numpy wrappers
from ..datasets._common import matrix_to_quat as _matrix_to_quat
from ..datasets._common import quat_conj as _quat_conj
from ..datasets._common import quat_mul as _quat_mul
from ..sequence import ImuSequence
from .base import EstimatorOutput
from .registry import register

__all__ = [
    "PeerUnavailable",
    "VQFEstimator",
    "ImufusionEstimator",
]

INSTALL_HINT = "pip install -e .[peers]"


class PeerUnavailable(ImportError):
    """A peer estimator's library is not installed."""


def _import_peer(module: str, package: str, peer: str):
    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise PeerUnavailable(
            f"peer estimator '{peer}' needs the package '{package}' (not importable: {e}); "
            f"install the optional peers with: {INSTALL_HINT}") from e


def _frame_to_enu_quat(frame: str) -> np.ndarray:
    """Quaternion of ``enu_from_frame(frame)``: q_enu_from_body = q ⊗ q_frame_from_body."""
    return _matrix_to_quat(enu_from_frame(frame))


def to_enu(q_frame_from_body: np.ndarray, frame: str) -> np.ndarray:
    """(N,4) ``frame_from_body`` -> (N,4) ``enu_from_body``, normalised, w >= 0."""
    q = _quat_mul(_frame_to_enu_quat(frame), np.asarray(q_frame_from_body, dtype=np.float64))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def from_enu(q_enu_from_body: np.ndarray, frame: str) -> np.ndarray:
    """(...,4) ``enu_from_body`` -> ``frame_from_body``."""
    return _quat_mul(_quat_conj(_frame_to_enu_quat(frame)), q_enu_from_body)


def triad_quat(accel: np.ndarray, mag: Optional[np.ndarray] = None) -> np.ndarray:
    """:func:`tcn_ahrs.filters.common.triad_quat` (the one TRIAD) on numpy samples (3,) -> (4,)."""
    import torch

    from ..filters.common import triad_quat as _triad

    t = lambda x: torch.as_tensor(np.asarray(x, dtype=np.float64))  # noqa: E731
    return _triad(t(accel), None if mag is None else t(mag)).numpy()


def dip_deg(accel: np.ndarray, mag: np.ndarray) -> float:
    """Magnetic dip angle in degrees (positive: field points below the horizon)."""
    a = accel / np.linalg.norm(accel)
    m = mag / np.linalg.norm(mag)
    return float(np.degrees(np.arcsin(np.clip(-a @ m, -1.0, 1.0))))


def _check_axes(axes: int) -> int:
    if int(axes) not in (6, 9):
        raise ValueError(f"axes: expected 6 or 9, got {axes!r}")
    return int(axes)


def mag_of(seq: ImuSequence, axes: int, peer: str) -> Optional[np.ndarray]:
    if axes == 6:
        return None
    if seq.mag is None:
        why = seq.meta.get("mag_absent", "it has none")
        raise ValueError(f"{seq.source}: field 'mag': peer '{peer}' (9-axis) needs a magnetometer and recording "
                         f"{seq.name!r} has none: {why}; run every method 6-axis (data.axes=6)")
    return seq.mag


class Peer:
    """Shared bits: name, axes, params, heading_free."""

    base_name = "peer"
    heading_free = False
    heading_ref = "auto"   # as the project filters: "init" (the given start), "north", "auto" (heading_ref_for)

    def __init__(self, axes: int, params: Dict[str, Any]):
        self.axes = _check_axes(axes)
        self.params = dict(params)
        self.name = f"{self.base_name}{self.axes}d"

    def __repr__(self) -> str:
        return f"{type(self).__name__}(axes={self.axes}, {self.params})"

    def _initial(self, seq: ImuSequence, init_quat: Optional[np.ndarray], mag) -> Tuple[np.ndarray, Optional[np.ndarray]]:
        """The start attitude the peer gets (ENU, w,x,y,z) and the rotation ``m`` its estimates
        are mapped back with (:meth:`_to_caller_frame`): ``init_quat`` — for a 9-axis peer rotated
        about up into the *magnetic* frame (:meth:`_magnetic_from_nav`) — else TRIAD (m None)."""
        if init_quat is None:
            return triad_quat(seq.accel[0], None if mag is None else mag[0]), None
        q = np.asarray(init_quat, dtype=np.float64).reshape(4)
        q = q / np.linalg.norm(q)
        m = self._magnetic_from_nav(q, mag, seq.meta)
        return (q, None) if m is None else (_quat_mul(m, q), m)

    def _magnetic_from_nav(self, q0: np.ndarray, mag, meta=None) -> Optional[np.ndarray]:
        """With a magnetometer and a given start attitude, the rotation about up from the caller's
        navigation frame into the magnetic one (``heading_ref="init"`` of the project filters,
        :func:`tcn_ahrs.filters.common.magnetic_from_nav`): a 9-axis peer pulls heading to
        magnetic north, so started from a motion-capture attitude with arbitrary yaw it would
        swing by that yaw; run in the magnetic frame and mapped back, it keeps the start.
        ``heading_ref = "north"``: none (the caller's frame is magnetic ENU)."""
        from ..filters.common import heading_ref_for, magnetic_from_nav

        if mag is None or heading_ref_for(self.heading_ref, meta) == "north":
            return None
        import torch

        m = magnetic_from_nav(torch.as_tensor(q0, dtype=torch.float64), torch.as_tensor(mag[0], dtype=torch.float64))
        return m.numpy()

    @staticmethod
    def _to_caller_frame(quat: np.ndarray, m: Optional[np.ndarray]) -> np.ndarray:
        """(N, 4) ENU estimates in the magnetic frame -> the caller's frame (``m`` from :meth:`_initial`)."""
        return quat if m is None else _quat_mul(_quat_conj(m), quat)


def is_constant_period(seq: ImuSequence, tol: float = 0.1) -> bool:
    """Every step within ``tol`` (relative) of the nominal period 1 / rate."""
    d = seq.dt[1:]
    return not d.size or float((np.abs(d - 1.0 / float(seq.rate)) * float(seq.rate)).max()) <= tol


def run_resampled(est, seq: ImuSequence, init_quat: Optional[np.ndarray], init_index: int) -> EstimatorOutput:
    """``est`` (a peer that takes one fixed period) on an irregular recording: the IMU
    interpolated linearly onto a uniform grid at the recording's median rate, the estimator run
    there from the grid point nearest to ``init_index``'s time, its attitudes mapped back to the
    recording's own timestamps (normalised linear interpolation between the two neighbouring grid
    points: steps of a few ms), numeric signals interpolated, flags taken from the nearest point.
    The ground truth is never interpolated (scores stay on the recording's samples)."""
    t = seq.time
    rate = float(1.0 / np.median(np.diff(t)))
    grid = t[0] + np.arange(int(np.floor((t[-1] - t[0]) * rate)) + 1) / rate

    def lerp(x):
        return np.stack([np.interp(grid, t, x[:, k]) for k in range(x.shape[1])], 1)

    uniform = ImuSequence(name=seq.name, source=seq.source, time=grid, gyro=lerp(seq.gyro), accel=lerp(seq.accel),
                          mag=None if seq.mag is None else lerp(seq.mag), rate=rate, check_units=False,
                          meta=dict(seq.meta))
    k0 = int(np.clip(np.searchsorted(grid, t[init_index]), 0, len(grid) - 1))
    out = est.run(uniform, init_quat, k0)
    j = np.clip(np.searchsorted(grid, t, side="right") - 1, 0, len(grid) - 2)
    w = ((t - grid[j]) * rate).clip(0.0, 1.0)[:, None]
    qa, qb = out.quat[j], out.quat[j + 1]
    qb = np.where((qa * qb).sum(1, keepdims=True) < 0, -qb, qb)  # the shorter way
    quat = (1 - w) * qa + w * qb
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    nearest = np.clip(np.rint((t - grid[0]) * rate).astype(int), 0, len(grid) - 1)
    signals = {}
    for name, v in (out.signals or {}).items():
        v = np.asarray(v)
        if v.dtype.kind == "f" and v.shape[0] == len(grid):
            signals[name] = (1 - w.reshape((-1,) + (1,) * (v.ndim - 1))) * v[j] + w.reshape((-1,) + (1,) * (v.ndim - 1)) * v[j + 1]
        elif v.shape[:1] == (len(grid),):
            signals[name] = v[nearest]
    return EstimatorOutput(quat=quat, signals=signals)


class OnFixedPeriod:
    """``est`` on the clock a fixed-period peer (VQF) integrates: an irregular recording on the grid
    of :func:`run_resampled`, a regular one at the nominal period 1 / rate (VQF's ``Ts``), not its
    small jitter: the same input as VQF, what "never worse than VQF" needs (on the iPhone 5's own
    jittery steps the backbone and VQF differ by up to 1.4° either way, on VQF's clock by 0.002°)."""

    def __init__(self, est, name: Optional[str] = None):
        self.est, self.name = est, name or f"{est.name} (VQF's clock)"
        self.axes = getattr(est, "axes", None)

    def run(self, seq: ImuSequence, init_quat: Optional[np.ndarray] = None, init_index: int = 0) -> EstimatorOutput:
        if not is_constant_period(seq):
            return run_resampled(self.est, seq, init_quat, init_index)
        nominal = replace(seq, time=seq.time[0] + np.arange(len(seq)) / float(seq.rate), check_units=False,
                          meta=dict(seq.meta))
        return self.est.run(nominal, init_quat, init_index)


def constant_period(seq: ImuSequence, name: str, tol: float = 0.1) -> float:
    """The sample period (s) of ``seq`` for a peer that takes one fixed period (VQF, RIANN);
    a ``ValueError`` when any step differs from the nominal period by more than ``tol``
    (relative): integrating irregular steps with a fixed period would be silently wrong."""
    ts = 1.0 / float(seq.rate)
    d = seq.dt[1:]
    off = np.abs(d - ts) / ts
    if d.size and float(off.max()) > tol:
        k = int(np.argmax(off)) + 1
        raise ValueError(f"{name}: needs a constant sample period, but recording {seq.name!r} steps "
                         f"{d[k - 1]:.4g} s at sample {k} against its nominal {ts:.4g} s ({seq.rate:.4g} Hz; "
                         f"steps range {d.min():.4g}..{d.max():.4g} s): resample it to a constant rate, "
                         "or use a method that takes per-sample time steps (the project filters, imufusion, ahrs)")
    return ts


# ---------------------------------------------------------------------------
# VQF
# ---------------------------------------------------------------------------


# VQF: time constants of the accelerometer (inclination) and magnetometer (heading)
# corrections, around the authors' (3 s, 9 s). 6 points; tauMag is ignored by 6D.
@register("vqf", "peer", grid=[dict(tauAcc=a, tauMag=m) for a in (1.0, 3.0, 6.0) for m in (3.0, 9.0)])
class VQFEstimator(Peer):
    """VQF (Laidig & Seel, Information Fusion 2023), ``pip install vqf``.

    Keyword args are VQF's parameters (authors' defaults: ``tauAcc=3.0`` s, ``tauMag=9.0`` s,
    motion/rest bias estimation and magnetic disturbance rejection enabled); any other
    ``VQFParams`` field may be given too. ``offline=True`` uses ``offlineVQF`` (non-causal,
    forward-backward: not comparable with causal filters).

    signals: ``gyro_bias`` (N,3) rad/s, ``rest`` (N,) bool, and for 9D ``mag_disturbed``
    (N,) bool, ``heading_delta`` (N,) rad.
    """

    base_name = "vqf"

    def __init__(self, axes: int = 9, tauAcc: float = 3.0, tauMag: float = 9.0,
                 motionBiasEstEnabled: bool = True, restBiasEstEnabled: bool = True,
                 magDistRejectionEnabled: bool = True, offline: bool = False, **vqf_params):
        params = dict(tauAcc=tauAcc, tauMag=tauMag, motionBiasEstEnabled=motionBiasEstEnabled,
                      restBiasEstEnabled=restBiasEstEnabled,
                      magDistRejectionEnabled=magDistRejectionEnabled, **vqf_params)
        super().__init__(axes, params)
        self.offline = bool(offline)
        if self.offline:
            self.name += "_offline"
        self._vqf = _import_peer("vqf", "vqf", self.name)

    def run(self, seq: ImuSequence, init_quat: Optional[np.ndarray] = None,
            init_index: int = 0) -> EstimatorOutput:
        if not is_constant_period(seq):  # VQF takes one fixed period: run it on a uniform grid
            return run_resampled(self, seq, init_quat, init_index)
        # VQF's C++ binding wants C-contiguous float64 (N,3) buffers: slices/float32 break it.
        gyr = np.ascontiguousarray(seq.gyro, dtype=np.float64)
        acc = np.ascontiguousarray(seq.accel, dtype=np.float64)
        mag = mag_of(seq, self.axes, self.name)
        mag = None if mag is None else np.ascontiguousarray(mag, dtype=np.float64)
        ts = constant_period(seq, self.name)
        if self.offline:
            out = self._vqf.offlineVQF(gyr, acc, mag, ts, dict(self.params))
        else:
            filt = self._vqf.VQF(ts, **self.params)
            if init_quat is not None:
                # started at the given attitude like every other estimator (the yardstick,
                # tcn_ahrs.metrics): VQF's 6D attitude is accQuat ⊗ gyrQuat (its frame: z up,
                # ENU here); 9-axis, in the magnetic frame of the start (:meth:`_initial`, as the
                # project filters and the other peers: the same start for every method; started in
                # the caller's frame instead, its heading snapped to the field and differed from the
                # backbone's by up to 0.9° on the iPhones)
                q_start, m_from_nav = self._initial(seq, init_quat, mag)
                state = filt.state
                state["gyrQuat"] = np.asarray(q_start, dtype=np.float64).reshape(4)
                state["accQuat"] = np.array([1.0, 0.0, 0.0, 0.0])
                filt.state = state
            out = filt.updateBatch(gyr, acc, mag)
        key = "quat9D" if self.axes == 9 else "quat6D"
        # VQF 9D reference frame: z up, magnetic north +y (heading from atan2(m_x, m_y)) = ENU.
        quat = to_enu(out[key], "ENU")
        if init_quat is not None and not self.offline:
            quat = self._to_caller_frame(quat, m_from_nav)
        signals = {"gyro_bias": np.asarray(out["bias"], dtype=np.float64),
                   "rest": np.asarray(out["restDetected"], dtype=bool)}
        if self.axes == 9:
            signals["mag_disturbed"] = np.asarray(out["magDistDetected"], dtype=bool)
            signals["heading_delta"] = np.asarray(out["delta"], dtype=np.float64)
        return EstimatorOutput(quat, signals)


# ---------------------------------------------------------------------------
# x-io Fusion (imufusion)
# ---------------------------------------------------------------------------


# Fusion: complementary gain (README default 0.5) x acceleration rejection angle.
@register("imufusion", "peer",
          grid=[dict(gain=g, acceleration_rejection=r) for g in (0.1, 0.5, 1.0) for r in (10.0, 20.0)])
class ImufusionEstimator(Peer):
    """x-io Technologies Fusion AHRS, ``pip install imufusion``.

    Defaults are the settings the Fusion README recommends (the library's own defaults
    disable both rejections): ``gain=0.5``, ``gyroscope_range=2000`` deg/s,
    ``acceleration_rejection=10`` deg, ``magnetic_rejection=10`` deg,
    ``rejection_timeout=5`` s (seconds in imufusion >= 1.3, the API wrapped here; 1.2 had a
    different API: ``Settings(...)``, ``recovery_trigger_period`` in samples).
    Without ``init_quat`` Fusion's start-up phase (high gain, first 3 s) initialises the
    attitude; with it, the attitude is seeded and the start-up phase skipped.

    Inputs are converted to deg/s and g; the convention is set to ENU via the property
    setter because the ``AhrsSettings`` constructor ignores its ``convention`` argument.

    signals: ``acc_rejected`` (N,) bool, ``mag_rejected`` (N,) bool (9D).
    """

    base_name = "imufusion"

    def __init__(self, axes: int = 9, gain: float = 0.5, gyroscope_range: float = 2000.0,
                 acceleration_rejection: float = 10.0, magnetic_rejection: float = 10.0,
                 rejection_timeout: float = 5.0):
        super().__init__(axes, dict(gain=gain, gyroscope_range=gyroscope_range,
                                    acceleration_rejection=acceleration_rejection,
                                    magnetic_rejection=magnetic_rejection,
                                    rejection_timeout=rejection_timeout))
        self._fusion = _import_peer("imufusion", "imufusion", self.name)
        if not hasattr(self._fusion, "AhrsSettings"):
            raise PeerUnavailable(f"peer estimator '{self.name}' needs imufusion >= 1.3 (found "
                                  f"{getattr(self._fusion, '__version__', 'an older version')}); "
                                  f"upgrade with: pip install -U imufusion")

    def make_ahrs(self, rate: float):
        """A configured ``imufusion.Ahrs`` in the ENU convention."""
        f, p = self._fusion, self.params
        ahrs = f.Ahrs()
        s = f.AhrsSettings()
        s.sample_rate = float(rate)
        s.gain = p["gain"]
        s.gyroscope_range = p["gyroscope_range"]
        s.acceleration_rejection = p["acceleration_rejection"]
        s.magnetic_rejection = p["magnetic_rejection"]
        s.rejection_timeout = p["rejection_timeout"]
        s.convention = f.CONVENTION_ENU  # AhrsSettings(convention=...) would silently keep NWU
        if s.convention != f.CONVENTION_ENU:
            raise RuntimeError("imufusion: could not set the ENU convention")
        ahrs.set_settings(s)
        return ahrs

    def fusion_inputs(self, seq: ImuSequence):
        """(gyro deg/s (N,3), accel g (N,3), mag uT (N,3) or None) as Fusion takes them.

        (imufusion 1.3 normalises the accelerometer for the attitude update, so the g scale
        only matters for its gravity/linear-acceleration outputs; deg/s matters fully.)"""
        mag = mag_of(seq, self.axes, self.name)
        gyr = np.ascontiguousarray(rad_to_deg(seq.gyro), dtype=np.float64)
        acc = np.ascontiguousarray(seq.accel / GRAVITY, dtype=np.float64)
        mag = None if mag is None else np.ascontiguousarray(mag, dtype=np.float64)
        return gyr, acc, mag

    def run(self, seq: ImuSequence, init_quat: Optional[np.ndarray] = None,
            init_index: int = 0) -> EstimatorOutput:
        gyr, acc, mag = self.fusion_inputs(seq)
        ahrs = self.make_ahrs(seq.rate)
        dt = seq.dt
        n = len(seq)
        quat = np.empty((n, 4))
        acc_rej = np.zeros(n, dtype=bool)
        mag_rej = np.zeros(n, dtype=bool)
        m_from_nav = None
        if init_quat is not None:
            # The start-up phase re-initialises the attitude from the accelerometer (heading 0)
            # at the first update, overwriting set_quaternion: a known start skips it.
            q_start, m_from_nav = self._initial(seq, init_quat, mag)
            ahrs.skip_startup()
            ahrs.set_quaternion(q_start)
        for k in range(n):
            ahrs.set_sample_period(float(dt[k]))
            if mag is None:
                ahrs.update_no_magnetometer(gyr[k], acc[k])
            else:
                ahrs.update(gyr[k], acc[k], mag[k])
            quat[k] = ahrs.get_quaternion()
            st = ahrs.get_internal_states()
            acc_rej[k] = st.accelerometer_ignored
            mag_rej[k] = st.magnetometer_ignored
        signals = {"acc_rejected": acc_rej}
        if self.axes == 9:
            signals["mag_rejected"] = mag_rej
        return EstimatorOutput(self._to_caller_frame(to_enu(quat, "ENU"), m_from_nav), signals)
