"""The ``ahrs`` package's filters (Madgwick, Mahony, EKF) as peers: one ``update`` call per
sample in the library's own frame, converted to ENU ``nav_from_body`` (w,x,y,z).

Their conventions (frames, accelerometer sign, magnetic reference) are tabled, with every other
peer's, in :mod:`tcn_ahrs.estimators.peers`; ``tests/test_peers.py`` checks them.
"""
from __future__ import annotations

from typing import Any, Dict, Optional

import numpy as np

from ..sequence import ImuSequence
from .base import EstimatorOutput
from . import peers
from .peers import dip_deg, from_enu, mag_of, Peer, to_enu
from .registry import register

__all__ = ["AhrsMadgwickEstimator", "AhrsMahonyEstimator", "AhrsEKFEstimator"]


class _AhrsFilter(Peer):
    """Common loop for the ``ahrs`` package filters (one ``update`` call per sample)."""

    frame = "ENU"          # navigation frame the filter estimates in
    accel_sign = 1.0       # -1: the filter expects the gravity vector (down), not specific force

    def __init__(self, axes: int, params: Dict[str, Any]):
        super().__init__(axes, params)
        self._ahrs = peers._import_peer("ahrs.filters", "ahrs", self.name)

    def _make(self, seq: ImuSequence, mag):
        raise NotImplementedError

    def _step(self, f, q, gyr, acc, mag, dt):
        raise NotImplementedError

    def _signals(self, f) -> Dict[str, np.ndarray]:
        return {}

    def run(self, seq: ImuSequence, init_quat: Optional[np.ndarray] = None,
            init_index: int = 0) -> EstimatorOutput:
        mag = mag_of(seq, self.axes, self.name)
        f = self._make(seq, mag)
        n = len(seq)
        q_enu0, m_from_nav = self._initial(seq, init_quat, mag)
        quat = np.empty((n, 4))
        quat[0] = from_enu(q_enu0, self.frame)
        gyr, acc, dt = seq.gyro, self.accel_sign * seq.accel, seq.dt
        sig = [self._signals(f)]
        for k in range(1, n):
            quat[k] = self._step(f, quat[k - 1], gyr[k], acc[k], None if mag is None else mag[k], float(dt[k]))
            sig.append(self._signals(f))
        signals = {key: np.stack([s[key] for s in sig]) for key in sig[0]}
        return EstimatorOutput(self._to_caller_frame(to_enu(quat, self.frame), m_from_nav), signals)


# Madgwick beta, rad/s (authors: 0.033 6D / 0.041 9D), log-spaced.
@register("ahrs_madgwick", "peer", grid=[dict(gain=g) for g in (0.005, 0.01, 0.02, 0.041, 0.1, 0.2)])
class AhrsMadgwickEstimator(_AhrsFilter):
    """Madgwick's gradient-descent filter from ``ahrs`` (``ahrs.filters.Madgwick``).

    ``gain`` (beta): authors' defaults 0.033 (6D, ``gain_imu``) and 0.041 (9D, ``gain_marg``)
    when ``None``. Frame NWU (x magnetic north, z up); specific force input.
    """

    base_name = "ahrs_madgwick"
    frame = "NWU"

    def __init__(self, axes: int = 9, gain: Optional[float] = None):
        if gain is None:
            gain = 0.041 if int(axes) == 9 else 0.033
        super().__init__(axes, dict(gain=gain))

    def _make(self, seq, mag):
        return self._ahrs.Madgwick(frequency=float(seq.rate), gain=self.params["gain"])

    def _step(self, f, q, gyr, acc, mag, dt):
        if mag is None:
            return f.updateIMU(q, gyr, acc, dt=dt)
        return f.updateMARG(q, gyr, acc, mag, dt=dt)


# Mahony proportional / integral gains (authors 1.0 / 0.3).
@register("ahrs_mahony", "peer", grid=[dict(k_P=p, k_I=i) for p in (0.3, 1.0, 3.0) for i in (0.03, 0.3)])
class AhrsMahonyEstimator(_AhrsFilter):
    """Mahony's explicit complementary filter from ``ahrs`` (``ahrs.filters.Mahony``).

    Authors' defaults ``k_P=1.0``, ``k_I=0.3``. Frame ENU (its magnetic reference is
    ``[0, b_h, b_z]``: north = +y); specific force input.

    signals: ``gyro_bias`` (N,3) rad/s (the filter's integral term ``b``).
    """

    base_name = "ahrs_mahony"
    frame = "ENU"

    def __init__(self, axes: int = 9, k_P: float = 1.0, k_I: float = 0.3):
        super().__init__(axes, dict(k_P=k_P, k_I=k_I))

    def _make(self, seq, mag):
        return self._ahrs.Mahony(frequency=float(seq.rate), k_P=self.params["k_P"], k_I=self.params["k_I"])

    def _step(self, f, q, gyr, acc, mag, dt):
        if mag is None:
            return f.updateIMU(q, gyr, acc, dt=dt)
        return f.updateMARG(q, gyr, acc, mag, dt=dt)

    def _signals(self, f):
        return {"gyro_bias": np.array(f.b, dtype=np.float64)}


# EKF spectral variances (var_gyr, var_acc, var_mag), authors (0.09, 0.25, 0.64):
# trust in the gyro vs. the references.
@register("ahrs_ekf", "peer", grid=[dict(noises=(g, a, a * 2.56)) for g in (0.01, 0.09) for a in (0.05, 0.25, 1.0)])
class AhrsEKFEstimator(_AhrsFilter):
    """Quaternion EKF from ``ahrs`` (``ahrs.filters.EKF``), in its default NED frame.

    ``noises`` = (var_gyr, var_acc, var_mag) spectral variances, authors' default
    (0.3^2, 0.5^2, 0.8^2). ``magnetic_ref``: the field direction it expects — a dip
    angle in degrees (float) or a 3-vector in NED; ``None`` (default) measures the dip
    at the first sample (the library's own default is the WMM field of Munich).
    The EKF expects the accelerometer to point DOWN at rest (its ``a_ref`` is the
    down axis in both NED and ENU), so the specific force is negated.
    """

    base_name = "ahrs_ekf"
    frame = "NED"
    accel_sign = -1.0

    def __init__(self, axes: int = 9, noises=(0.3 ** 2, 0.5 ** 2, 0.8 ** 2), magnetic_ref=None):
        super().__init__(axes, dict(noises=tuple(float(x) for x in noises), magnetic_ref=magnetic_ref))

    def _make(self, seq, mag):
        mref = self.params["magnetic_ref"]
        if mref is None:
            mref = dip_deg(seq.accel[0], mag[0]) if mag is not None else 60.0  # unused in 6D
        f = self._ahrs.EKF(frequency=float(seq.rate), frame=self.frame, magnetic_ref=mref,
                           noises=list(self.params["noises"]))
        # The EKF's measurement model h() picks 3 or 6 rows from whether ``self.mag`` is set,
        # which only happens in its batch mode: set it for sample-by-sample 9D updates.
        f.mag = mag
        return f

    def _step(self, f, q, gyr, acc, mag, dt):
        return f.update(q, gyr, acc, mag, dt=dt)
