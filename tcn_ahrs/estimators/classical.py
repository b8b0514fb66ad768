"""Classical attitude estimators under the :class:`~tcn_ahrs.estimators.base.Estimator` interface.

Each class holds its parameters (dataclass fields, units in the field comments) and wraps
one pure-torch filter of :mod:`tcn_ahrs.filters`:

===================  =============================================  ==========================
class                filter                                          tuned by default
===================  =============================================  ==========================
``ClosedLoopECF``    paper Sec. 2, Eqs. 4-8 (:func:`filters.ecf`)    ``k_norm``, ``a_min``
``Mahony``           Mahony et al. 2008 (:func:`filters.mahony`)     ``k_p``, ``k_i``
``Madgwick``         Madgwick 2010 (:func:`filters.madgwick`)        ``beta``
``ESEKF``            error-state EKF (:func:`filters.eskf`)          ``accel_noise``, ``mag_noise``
``RobustESEKF``      adaptive-robust ES-EKF (``robust=True``)        ``accel_noise``, ``mag_noise``
===================  =============================================  ==========================

Common behaviour:

* initial attitude: ``init_quat`` when given (applied at sample 0), else TRIAD from the first
  accelerometer (and magnetometer) sample (:func:`tcn_ahrs.filters.triad_quat`);
* magnetometer: used when the recording has one and ``use_mag`` is True;
* heading reference (``heading_ref``): the filters pull heading to magnetic north.
  ``"init"`` (default) takes the horizontal field direction at the initial attitude as the
  reference (:func:`tcn_ahrs.filters.magnetic_from_nav`), so a ground-truth initial attitude in
  a frame whose +y is not magnetic north is kept instead of being rotated away; ``"north"``
  assumes the navigation frame's +y is magnetic north (the paper's ECF, Eq. 6);
* ``run_params(seq, params)`` runs P parameter sets in one batched call (used by
  :mod:`tcn_ahrs.tuning`);
* float64 on CPU by default (``device`` field to run on a GPU).
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any, ClassVar, Dict, Mapping, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from .. import so3
from ..filters import ecf, eskf, madgwick, mahony
from ..filters.common import magnetic_from_nav, triad_quat
from ..sequence import ImuSequence
from .base import EstimatorOutput


@dataclass
class ClassicalEstimator:
    """Base of the classical estimators (see the module docstring)."""

    use_mag: bool = True
    heading_ref: str = "init"  # "init" | "north"
    device: str = "cpu"
    dtype: torch.dtype = torch.float64

    name: ClassVar[str] = "classical"
    tunable: ClassVar[Sequence[str]] = ()
    default_grid: ClassVar[Dict[str, list]] = {}

    # ------------------------------------------------------------------ to override
    def _filter(self, gyro: Tensor, accel: Tensor, dt: Tensor, q0: Tensor, mag: Optional[Tensor],
                params: Mapping[str, Tensor]) -> Dict[str, Tensor]:
        raise NotImplementedError

    # ------------------------------------------------------------------ helpers
    def param_names(self) -> list:
        base = {f.name for f in fields(ClassicalEstimator)}
        return [f.name for f in fields(self) if f.name not in base]

    def params(self) -> Dict[str, Any]:
        """This estimator's filter parameters (name -> value)."""
        return {k: getattr(self, k) for k in self.param_names()}

    def with_params(self, **kw) -> "ClassicalEstimator":
        unknown = set(kw) - set(self.param_names()) - {f.name for f in fields(ClassicalEstimator)}
        if unknown:
            raise ValueError(f"{type(self).__name__}: unknown parameters {sorted(unknown)}; "
                             f"expected some of {self.param_names()}")
        return replace(self, **kw)

    def _inputs(self, seq: ImuSequence, init_quat: Optional[np.ndarray]):
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=self.dtype, device=self.device)  # noqa: E731
        gyro, accel, dt = t(seq.gyro), t(seq.accel), t(seq.dt)
        mag = t(seq.mag) if (self.use_mag and seq.mag is not None) else None
        if init_quat is None:
            q0 = triad_quat(accel[0], None if mag is None else mag[0])
        else:
            q0 = so3.quat_normalize(t(init_quat))
            if q0.shape != (4,):
                raise ValueError(f"{self.name}: init_quat must have shape (4,) (w,x,y,z), got {tuple(q0.shape)}")
        if mag is not None and self.heading_ref == "init":
            m_from_n = magnetic_from_nav(q0, mag[0])
        elif self.heading_ref in ("init", "north"):
            m_from_n = None
        else:
            raise ValueError(f"{self.name}: heading_ref must be 'init' or 'north', got {self.heading_ref!r}")
        if m_from_n is not None:
            q0 = so3.quat_mul(m_from_n, q0)
        return gyro, accel, dt, q0, mag, m_from_n

    def run_params(self, seq: ImuSequence, params: Optional[Mapping[str, Any]] = None,
                   init_quat: Optional[np.ndarray] = None) -> Dict[str, Tensor]:
        """Run with parameters overridden by ``params`` (name -> scalar or (P,) values, broadcast
        together); returns the filter's tensors with a leading (P,) dimension when any is batched:
        ``quat`` (P, N, 4) and the signals."""
        p = dict(self.params())
        for k, v in (params or {}).items():
            if k not in p:
                raise ValueError(f"{type(self).__name__}: unknown parameter {k!r}; expected one of {sorted(p)}")
            p[k] = v
        p = {k: (torch.as_tensor(v, dtype=self.dtype, device=self.device)
                 if isinstance(v, (int, float, list, tuple, np.ndarray, Tensor)) and not isinstance(v, bool) else v)
             for k, v in p.items()}
        gyro, accel, dt, q0, mag, m_from_n = self._inputs(seq, init_quat)
        with torch.no_grad():
            out = self._filter(gyro, accel, dt, q0, mag, p)
        if m_from_n is not None:
            out["quat"] = so3.quat_mul(so3.quat_conj(m_from_n), out["quat"])
        out["quat"] = so3.quat_positive(so3.quat_normalize(out["quat"]))
        return out

    def run(self, seq: ImuSequence, init_quat: Optional[np.ndarray] = None) -> EstimatorOutput:
        out = self.run_params(seq, None, init_quat)
        quat = out.pop("quat").cpu().numpy()
        return EstimatorOutput(quat=quat, signals={k: v.cpu().numpy() for k, v in out.items()})


@dataclass
class ClosedLoopECF(ClassicalEstimator):
    """Closed-loop Extended Complementary Filter, paper Section 2 (Eqs. 4-8); see
    :func:`tcn_ahrs.filters.ecf`. Tuned on training recordings: ``k_norm`` and ``a_min``
    (``k_init``/``t_init`` only matter during the first seconds; ``m_min``/``m_max`` bracket the
    local field). Signals: ``acc_used``, ``mag_used`` (Eq. 7 decisions), ``gain`` (Eq. 8)."""

    k_norm: float = 0.5  # 1/s
    k_init: float = 10.0  # 1/s
    t_init: float = 3.0  # s
    a_min: float = 1.0  # m/s^2
    m_min: float = 20.0  # uT
    m_max: float = 70.0  # uT

    name: ClassVar[str] = "ecf"
    tunable: ClassVar[Sequence[str]] = ("k_norm", "a_min")
    default_grid: ClassVar[Dict[str, list]] = {"k_norm": [0.05, 0.1, 0.2, 0.5, 1.0, 2.0],
                                               "a_min": [0.3, 1.0, 3.0]}

    def _filter(self, gyro, accel, dt, q0, mag, p):
        return ecf(gyro, accel, dt, q0, mag=mag, **p)


@dataclass
class Mahony(ClassicalEstimator):
    """Mahony explicit complementary filter with integral gyro-bias term; see
    :func:`tcn_ahrs.filters.mahony` (``compat=True`` reproduces ``ahrs.filters.Mahony``).
    Tuned: ``k_p``, ``k_i``. Signals: ``gyro_bias`` (N, 3) rad/s."""

    k_p: float = 1.0  # 1/s
    k_i: float = 0.3  # 1/s^2
    compat: bool = False

    name: ClassVar[str] = "mahony"
    tunable: ClassVar[Sequence[str]] = ("k_p", "k_i")
    default_grid: ClassVar[Dict[str, list]] = {"k_p": [0.1, 0.3, 1.0, 3.0], "k_i": [0.0, 0.01, 0.1, 0.3]}

    def _filter(self, gyro, accel, dt, q0, mag, p):
        return mahony(gyro, accel, dt, q0, mag=mag, k_p=p["k_p"], k_i=p["k_i"], compat=bool(p["compat"]))


@dataclass
class Madgwick(ClassicalEstimator):
    """Madgwick gradient-descent filter; see :func:`tcn_ahrs.filters.madgwick` (equal to
    ``ahrs.filters.Madgwick`` after the NWU->ENU conversion). ``beta`` rad/s; ``None`` = ahrs
    default (0.033 6-axis, 0.041 9-axis). Tuned: ``beta``."""

    beta: Optional[float] = None  # rad/s

    name: ClassVar[str] = "madgwick"
    tunable: ClassVar[Sequence[str]] = ("beta",)
    default_grid: ClassVar[Dict[str, list]] = {"beta": [0.005, 0.01, 0.02, 0.033, 0.05, 0.1, 0.2]}

    def _filter(self, gyro, accel, dt, q0, mag, p):
        return madgwick(gyro, accel, dt, q0, mag=mag, beta=p["beta"])


@dataclass
class ESEKF(ClassicalEstimator):
    """Error-state EKF (attitude + gyro bias); see :func:`tcn_ahrs.filters.eskf`.
    Tuned: ``accel_noise``, ``mag_noise`` (gyro noise and bias walk come from the sensor's
    datasheet / Allan variance). Signals: ``gyro_bias`` (N, 3) rad/s, ``att_std`` (N, 3) rad."""

    gyro_noise: float = 1e-3  # rad/s/sqrt(Hz)
    bias_walk: float = 1e-5  # rad/s^2/sqrt(Hz)
    accel_noise: float = 0.05  # m/s^2/sqrt(Hz)
    mag_noise: float = 0.05  # rad/sqrt(Hz)
    init_att_std: float = 0.1  # rad
    init_bias_std: float = 0.01  # rad/s

    name: ClassVar[str] = "eskf"
    tunable: ClassVar[Sequence[str]] = ("accel_noise", "mag_noise")
    default_grid: ClassVar[Dict[str, list]] = {"accel_noise": [0.01, 0.03, 0.1, 0.3],
                                               "mag_noise": [0.01, 0.03, 0.1, 0.3]}

    def _filter(self, gyro, accel, dt, q0, mag, p):
        return eskf(gyro, accel, dt, q0, mag=mag, robust=False, **p)


@dataclass
class RobustESEKF(ESEKF):
    """Adaptive-robust ES-EKF: Mahalanobis-gated observations (R inflation) and fading factor
    (P inflation), after the ARCKF paper's Eqs. 39-42 / Algorithm 1; see
    :func:`tcn_ahrs.filters.eskf`. Tuned: ``accel_noise``, ``mag_noise`` (``alpha`` and the
    plausibility tolerances have physical defaults). Signals: ``gyro_bias``, ``att_std``,
    ``acc_gated``, ``mag_gated`` (N,) bool, ``mahalanobis_acc``, ``mahalanobis_mag``, ``fading`` (N,)."""

    alpha: float = 0.001  # significance level of the chi-square tests
    acc_norm_tol: float = 0.25  # m/s^2
    mag_norm_tol: float = 3.0  # uT
    dip_tol: float = 0.05  # rad
    max_fading: float = 10.0
    n_iter: int = 3
    plausible_window: float = 0.2  # s

    name: ClassVar[str] = "robust_eskf"

    def _filter(self, gyro, accel, dt, q0, mag, p):
        p = dict(p)
        scalars = {k: float(p.pop(k)) for k in ("alpha", "max_fading", "plausible_window")}
        n_iter = int(p.pop("n_iter"))
        return eskf(gyro, accel, dt, q0, mag=mag, robust=True, n_iter=n_iter, **scalars, **p)

