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
* ``axes``: 9 uses the magnetometer when the recording has one, 6 never does; the column name
  is ``<method><axes>d`` (``ecf9d``) unless ``label`` is given;
* heading reference (``heading_ref``): the filters pull heading to magnetic north.
  ``"auto"`` (default): ``"north"`` on recordings whose ground truth is referred to magnetic
  north (:func:`tcn_ahrs.filters.common.heading_ref_for`), else ``"init"``. ``"init"`` takes the horizontal field direction at the initial attitude as the
  reference (:func:`tcn_ahrs.filters.magnetic_from_nav`), so a ground-truth initial attitude in
  a frame whose +y is not magnetic north is kept instead of being rotated away; ``"north"``
  assumes the navigation frame's +y is magnetic north (the paper's ECF, Eq. 6);
* ``quat_batch(seqs, init_quats, params)`` runs R recordings x P parameter sets in one
  batched filter call: the one code path behind ``run``, ``run_batch`` (the evaluation
  runner), ``run_params`` and the tuner (:mod:`tcn_ahrs.tuning.grid`);
* registered under their ``method`` name (:mod:`tcn_ahrs.estimators.registry`);
* float64 on CPU by default (``device`` field to run on a GPU).
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any, ClassVar, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from .. import so3
from ..conventions import STATE_DTYPE
from ..filters import ecf, eskf, madgwick, mahony
from ..filters.common import heading_ref_for, magnetic_from_nav, triad_quat
from ..filters.ecf import ECFParams
from ..filters.eskf import ESEKFParams, RobustESEKFParams
from ..filters.madgwick import MadgwickParams
from ..filters.mahony import MahonyParams
from ..kernels.params import tuning_grid
from ..sequence import ImuSequence
from .base import EstimatorOutput
from .registry import register


def _pad_stack(arrays: Sequence[Tensor], n: int) -> Tensor:
    """(N_i, ...) tensors -> (R, n, ...), each padded by repeating its last sample (the filters
    are causal: padding after the end never changes the samples before it)."""
    out = []
    for a in arrays:
        if a.shape[0] < n:
            a = torch.cat([a, a[-1:].expand((n - a.shape[0],) + tuple(a.shape[1:]))], 0)
        out.append(a)
    return torch.stack(out, 0)


@dataclass
class ClassicalEstimator:
    """Base of the classical estimators (see the module docstring).

    ``axes`` 9 uses the magnetometer when the recording has one, 6 never does (the column
    ``<method><axes>d``, e.g. ``ecf9d``); ``label`` overrides that column name.
    """

    axes: int = 9
    label: Optional[str] = None
    heading_ref: str = "auto"  # "auto" | "init" | "north"
    device: str = "cpu"
    dtype: torch.dtype = STATE_DTYPE

    method: ClassVar[str] = "classical"
    heading_free: ClassVar[bool] = False
    tunable: ClassVar[Sequence[str]] = ()
    default_grid: ClassVar[Dict[str, list]] = {}

    def __post_init__(self):
        if isinstance(self.axes, bool) or int(self.axes) not in (6, 9):
            raise ValueError(f"{type(self).__name__}: axes: expected 6 or 9, got {self.axes!r}")
        self.axes = int(self.axes)

    @property
    def name(self) -> str:
        """Column name: ``label`` or ``<method><axes>d``."""
        return self.label or f"{self.method}{self.axes}d"

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
        mag = t(seq.mag) if (self.axes == 9 and seq.mag is not None) else None
        if init_quat is None:
            q0 = triad_quat(accel[0], None if mag is None else mag[0])
        else:
            q0 = so3.quat_normalize(t(init_quat))
            if q0.shape != (4,):
                raise ValueError(f"{self.name}: init_quat must have shape (4,) (w,x,y,z), got {tuple(q0.shape)}")
        ref = heading_ref_for(self.heading_ref, seq.meta)
        m_from_n = magnetic_from_nav(q0, mag[0]) if (mag is not None and ref == "init") else None
        if m_from_n is not None:
            q0 = so3.quat_mul(m_from_n, q0)
        return gyro, accel, dt, q0, mag, m_from_n

    def _param_tensors(self, params: Optional[Mapping[str, Any]]) -> Dict[str, Any]:
        """This estimator's parameters overridden by ``params``; numbers become tensors (bools
        and ``None`` stay)."""
        p = dict(self.params())
        for k, v in (params or {}).items():
            if k not in p:
                raise ValueError(f"{type(self).__name__}: unknown parameter {k!r}; expected one of {sorted(p)}")
            p[k] = v
        return {k: (torch.as_tensor(v, dtype=self.dtype, device=self.device)
                    if isinstance(v, (int, float, list, tuple, np.ndarray, Tensor)) and not isinstance(v, bool) else v)
                for k, v in p.items()}

    def quat_batch(self, seqs: Sequence[ImuSequence], init_quats: Sequence[Optional[np.ndarray]],
                   params: Optional[Mapping[str, Any]] = None) -> Tuple[Tensor, Dict[str, Tensor]]:
        """Run on all recordings in ONE filter call (the one code path of every run).

        Args:
            seqs: R recordings (any lengths; padded to the longest with their last sample).
            init_quats: R initial attitudes (or ``None``: TRIAD), applied at sample 0.
            params: parameter overrides; (P, 1)-shaped tensors batch P parameter sets against
                    the R recordings.
        Returns:
            ``quat`` (R, N_max, 4) or (P, R, N_max, 4) nav_from_body (padding beyond each
            recording's length is meaningless), and the other outputs with the same leading dims.
        """
        if len(seqs) != len(init_quats):
            raise ValueError(f"{self.name}: {len(seqs)} recordings but {len(init_quats)} initial attitudes")
        if not seqs:
            raise ValueError(f"{self.name}: no recordings")
        ins = [self._inputs(s, q) for s, q in zip(seqs, init_quats)]
        has_mag = [x[4] is not None for x in ins]
        if any(has_mag) and not all(has_mag):
            raise ValueError(f"{self.name}: batch mixes recordings with and without magnetometer; "
                             "run them separately")
        n = max(len(s) for s in seqs)
        gyro, accel, dt = (_pad_stack([x[i] for x in ins], n) for i in range(3))
        q0 = torch.stack([x[3] for x in ins], 0)
        mag = _pad_stack([x[4] for x in ins], n) if all(has_mag) else None
        p = self._param_tensors(params)
        with torch.no_grad():
            out = self._filter(gyro, accel, dt, q0, mag, p)
        q = out.pop("quat")
        if all(x[5] is not None for x in ins):
            m = torch.stack([x[5] for x in ins], 0)[:, None, :]  # (R, 1, 4) broadcasts over (..., R, N, 4)
            q = so3.quat_mul(so3.quat_conj(m).expand_as(q), q)
        return so3.quat_positive(so3.quat_normalize(q)), out

    def run_params(self, seq: ImuSequence, params: Optional[Mapping[str, Any]] = None,
                   init_quat: Optional[np.ndarray] = None) -> Dict[str, Tensor]:
        """One recording with parameters overridden by ``params`` (name -> scalar or (P,) values,
        broadcast together); returns the filter's tensors with a leading (P,) dimension when any
        is batched: ``quat`` (P, N, 4) and the signals."""
        if params:
            params = {k: (torch.as_tensor(v, dtype=self.dtype)[..., None]
                          if isinstance(v, (list, tuple, np.ndarray, Tensor)) and np.ndim(v) == 1 else v)
                      for k, v in params.items()}  # (P,) -> (P, 1): P parameter sets x 1 recording
        quat, sig = self.quat_batch([seq], [init_quat], params)
        batched = quat.dim() == 4
        take = (lambda v: v[:, 0]) if batched else (lambda v: v[0])  # noqa: E731
        out = {"quat": take(quat)}
        out.update({k: take(v) for k, v in sig.items() if v.dim() >= (3 if batched else 2)})
        return out

    def run_batch(self, seqs: Sequence[ImuSequence], init_quats: Sequence[Optional[np.ndarray]],
                  init_indices: Optional[Sequence[int]] = None) -> List[EstimatorOutput]:
        """One :class:`EstimatorOutput` per recording, computed in one batched filter call
        (what the evaluation runner uses); ``init_quats`` are applied at sample 0 (see
        :class:`~tcn_ahrs.estimators.base.Estimator` for ``init_indices``)."""
        quat, sig = self.quat_batch(seqs, init_quats)
        res = []
        for i, s in enumerate(seqs):
            n = len(s)
            res.append(EstimatorOutput(quat=quat[i, :n].cpu().numpy(),
                                       signals={k: v[i, :n].cpu().numpy() for k, v in sig.items()
                                                if v.dim() >= 2 and v.shape[0] == len(seqs)}))
        return res

    def run(self, seq: ImuSequence, init_quat: Optional[np.ndarray] = None,
            init_index: int = 0) -> EstimatorOutput:
        return self.run_batch([seq], [init_quat], [init_index])[0]


@register("ecf", "classical")
@dataclass
class ClosedLoopECF(ECFParams, ClassicalEstimator):
    """Closed-loop Extended Complementary Filter, paper Section 2 (Eqs. 4-8); see
    :func:`tcn_ahrs.filters.ecf`. Tuned on training recordings: ``k_norm`` and ``a_min``
    (``k_init``/``t_init`` only matter during the first seconds; ``m_min``/``m_max`` bracket the
    local field). Signals: ``acc_used``, ``mag_used`` (Eq. 7 decisions), ``gain`` (Eq. 8)."""

    method: ClassVar[str] = "ecf"
    default_grid: ClassVar[Dict[str, list]] = tuning_grid(ECFParams)
    tunable: ClassVar[Sequence[str]] = tuple(default_grid)

    def _filter(self, gyro, accel, dt, q0, mag, p):
        return ecf(gyro, accel, dt, q0, mag=mag, **p)


@register("mahony", "classical")
@dataclass
class Mahony(MahonyParams, ClassicalEstimator):
    """Mahony explicit complementary filter with integral gyro-bias term; see
    :func:`tcn_ahrs.filters.mahony` (``compat=True`` reproduces ``ahrs.filters.Mahony``).
    Tuned: ``k_p``, ``k_i``. Signals: ``gyro_bias`` (N, 3) rad/s."""

    method: ClassVar[str] = "mahony"
    default_grid: ClassVar[Dict[str, list]] = tuning_grid(MahonyParams)
    tunable: ClassVar[Sequence[str]] = tuple(default_grid)

    def _filter(self, gyro, accel, dt, q0, mag, p):
        return mahony(gyro, accel, dt, q0, mag=mag, k_p=p["k_p"], k_i=p["k_i"], compat=bool(p["compat"]))


@register("madgwick", "classical")
@dataclass
class Madgwick(MadgwickParams, ClassicalEstimator):
    """Madgwick gradient-descent filter; see :func:`tcn_ahrs.filters.madgwick` (equal to
    ``ahrs.filters.Madgwick`` after the NWU->ENU conversion). ``beta`` rad/s; ``None`` = ahrs
    default (0.033 6-axis, 0.041 9-axis). Tuned: ``beta``."""

    method: ClassVar[str] = "madgwick"
    default_grid: ClassVar[Dict[str, list]] = tuning_grid(MadgwickParams)
    tunable: ClassVar[Sequence[str]] = tuple(default_grid)

    def _filter(self, gyro, accel, dt, q0, mag, p):
        return madgwick(gyro, accel, dt, q0, mag=mag, beta=p["beta"])


@register("eskf", "classical")
@dataclass
class ESEKF(ESEKFParams, ClassicalEstimator):
    """Error-state EKF (attitude + gyro bias); see :func:`tcn_ahrs.filters.eskf`.
    Tuned: ``accel_noise``, ``mag_noise`` (gyro noise and bias walk come from the sensor's
    datasheet / Allan variance). Signals: ``gyro_bias`` (N, 3) rad/s, ``att_std`` (N, 3) rad."""

    method: ClassVar[str] = "eskf"
    default_grid: ClassVar[Dict[str, list]] = tuning_grid(ESEKFParams)
    tunable: ClassVar[Sequence[str]] = tuple(default_grid)

    def _filter(self, gyro, accel, dt, q0, mag, p):
        return eskf(gyro, accel, dt, q0, mag=mag, robust=False, **p)


@register("robust_eskf", "classical")
@dataclass
class RobustESEKF(RobustESEKFParams, ESEKF):
    """Adaptive-robust ES-EKF: Mahalanobis-gated observations (R inflation) and fading factor
    (P inflation), after the ARCKF paper's Eqs. 39-42 / Algorithm 1; see
    :func:`tcn_ahrs.filters.eskf`. Tuned: ``accel_noise``, ``mag_noise`` (``alpha`` and the
    plausibility tolerances have physical defaults). Signals: ``gyro_bias``, ``att_std``,
    ``acc_gated``, ``mag_gated`` (N,) bool, ``mahalanobis_acc``, ``mahalanobis_mag``, ``fading`` (N,)."""

    method: ClassVar[str] = "robust_eskf"

    def _filter(self, gyro, accel, dt, q0, mag, p):
        p = dict(p)
        scalars = {k: float(p.pop(k)) for k in ("alpha", "max_fading", "plausible_window")}
        n_iter = int(p.pop("n_iter"))
        return eskf(gyro, accel, dt, q0, mag=mag, robust=True, n_iter=n_iter, **scalars, **p)

