"""Learned closed-loop complementary filter on SO(3) (the default learned estimator).

Why: the paper's open-loop ECF (Eq. 25) computes its innovations against a *pre-integrated*
attitude, which drifts away from the filter's own estimate within minutes; on recordings the
training never saw this made the shipped models worse than raw integration. Here every
innovation is computed against the filter's *own* estimate, sample by sample, so the
corrections are self-limiting (a Mahony-type explicit complementary filter, Mahony et al. 2008,
Eq. 32, with the paper's innovations Eqs. 23/24), and the network only says how much to trust
each sensor at each sample.

Per sample k (``dt_k`` the step before k; sample 0 is the initial state)::

    e_acc = â_k × (C_{k-1}^T up)                                   (Eq. 23, own estimate)
    e_mag = east_k × (C_{k-1}^T east_ref)                          (Eq. 24, own estimate)
    w     = k_acc τ_acc,k e_acc + k_mag τ_mag,k e_mag              trust-weighted innovation
    b_k   = b_{k-1} − k_bias w dt_k                                integral term (Mahony)
            + ρ_k dt_k / T_rest (ω̂_gyr,k − b_{k-1})                at rest: the gyro reads its bias
    C_k   = C_{k-1} exp((ω̂_gyr,k − b_k + w) dt_k)                  (Eq. 3 / Eq. 4 of the ECF)

* ``τ_acc, τ_mag`` ∈ (0, 2): per-sample trust from the calibration networks (``2σ(z)``; an
  untrained network outputs z = 0, trust 1, i.e. a plain complementary filter);
* ``ρ_k`` ∈ {0, 1}: a causal rest detector on the raw readings (the gyro and the accelerometer
  stay within ``rest_gyro``/``rest_acc`` of their running mean for ``rest_time`` seconds, as in
  VQF): the gyro bias differs between recordings and is only observable at rest or through the
  vector measurements — a running bias *state* transfers to unseen recordings, a window
  regression does not;
* ``east_ref`` is the horizontal direction of ``unit(m × a)`` at the first sample, rotated to
  the navigation frame by the initial attitude: heading is referred to the initial heading
  (the classical filters' ``heading_ref="init"``), so any motion-capture frame works;
* gains ``k_acc, k_mag`` (1/s), ``k_bias`` (1/s²) and ``T_rest`` (s) are trainable, stored as
  logarithms (always positive).

Frames: body vectors, ``nav_from_body`` quaternions (w,x,y,z), ENU, specific force up.
The loop on tensors (:func:`closed_loop_scan`, TorchScript) is the reference and what autograd
runs on CUDA; the same update on scalars (:mod:`tcn_ahrs.kernels.closed_loop`) is what
evaluation (numba), CPU training (numba, with its reverse pass) and the exports (TorchScript)
run, tested equal to 1e-12 (:meth:`ClosedLoopFilter._scan` picks). It keeps the attitude as a
rotation matrix: ``C exp(φ^)`` is ``C + a (C φ^) + b (C φ^)φ^`` whose rows are two cross
products (``(Cφ^)_i = c_i × φ``), ~3x fewer operations per sample than the quaternion product.
"""
from __future__ import annotations

import math
from typing import Dict, List, Optional, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..config.model import ClosedLoopConfig
from ..conventions import GRAVITY
from ..filters.common import field_gates
from ..kernels.backbone_layout import FROZEN_MIN_SAMPLES, BackboneParams
from ..kernels.closed_loop import gap_step
from . import closed_loop_compiled
from .closed_loop_step import scan_scalar
from .open_loop import unit_vector


def window_samples(rest_time: float, rate_hz: float) -> int:
    """The rest detector's window: samples in ``rest_time`` seconds at ``rate_hz`` (at least 2)."""
    return max(2, int(round(rest_time * rate_hz)))


def rest_window(dt: Tensor, rest_time: float) -> int:
    """Samples in ``rest_time`` seconds at the median step of dt (B, N)."""
    step = float(dt[:, 1:].median()) if dt.shape[1] > 1 else 0.01
    return max(2, int(round(rest_time / max(step, 1e-6))))


def rest_detector(gyro: Tensor, acc: Tensor, window: int, rest_gyro: float = math.radians(2.0),
                  rest_acc: float = 0.5) -> Tensor:
    """Causal rest flag (B, N) in {0., 1.}: over the last ``window`` samples every gyro sample
    stayed within ``rest_gyro`` rad/s and every accelerometer sample within ``rest_acc`` m/s² of
    the running mean (over ``window`` samples, fewer at the start) — VQF's test of steadiness,
    so a constant gyro bias still counts as rest. gyro, acc (B, N, 3). The first ``window - 1``
    samples are never rest (not watched long enough). The flag at sample k depends on samples
    k - 2 window + 2 .. k only. The running means are taken in float64 (a float32 cumulative sum
    over a long recording loses the digits the thresholds compare), so the streaming export's
    running sums give the same flags."""
    out_dtype = gyro.dtype
    gyro = gyro.to(torch.float64)
    acc = acc.to(torch.float64)
    n = gyro.shape[1]
    w = int(window)
    idx = torch.arange(1, n + 1, device=gyro.device)
    lo = (idx - w).clamp_min(0)
    cnt = (idx - lo).to(gyro.dtype)[None, :, None]

    c_g = torch.cumsum(F.pad(gyro, [0, 0, 1, 0]), 1)
    c_a = torch.cumsum(F.pad(acc, [0, 0, 1, 0]), 1)
    dev_g = torch.linalg.vector_norm(gyro - (c_g[:, idx] - c_g[:, lo]) / cnt, dim=-1)
    dev_a = torch.linalg.vector_norm(acc - (c_a[:, idx] - c_a[:, lo]) / cnt, dim=-1)
    max_g = F.max_pool1d(F.pad(dev_g.unsqueeze(1), [w - 1, 0], value=0.0), w, 1).squeeze(1)
    max_a = F.max_pool1d(F.pad(dev_a.unsqueeze(1), [w - 1, 0], value=0.0), w, 1).squeeze(1)
    rest = (max_g < rest_gyro) & (max_a < rest_acc) & (idx >= w).unsqueeze(0)
    return rest.to(out_dtype)


FROZEN_TIME = BackboneParams.frozen_time  # s: one default, the backbone's
GAP_FACTOR = BackboneParams.gap_factor


def frozen_window(rest_window: int, rest_time: float, frozen_time: float = FROZEN_TIME,
                  min_samples: int = int(FROZEN_MIN_SAMPLES)) -> int:
    """Samples a reading must repeat exactly for to count as frozen: the backbone's rule
    (``frozen_time`` and :data:`FROZEN_MIN_SAMPLES`) at the rate the rest window implies."""
    return max(min_samples, int(round(rest_window * frozen_time / rest_time)))


def frozen_detector(x: Tensor, window: int) -> Tensor:
    """Sensor health (B, N) in {0., 1.}: the three readings of x (B, N, 3) have repeated exactly
    (bit for bit) over the last ``window`` samples — a frozen or disconnected sensor (its noise
    makes a real one change); the backbone's check (kernels/backbone.py ``frozen_check``) on a
    regular stream, as tensor ops; one sample at a time: :func:`~tcn_ahrs.kernels.closed_loop.repeat_count`."""
    same = (x[:, 1:] == x[:, :-1]).all(-1).to(torch.float64)
    c = torch.cumsum(F.pad(same, [1, 0]), 1)  # c[k]: repeats up to sample k
    m = int(window) - 1
    before = F.pad(c, [m, 0])[:, :c.shape[1]]  # c[k - m] (0 before the start)
    return ((c - before) >= m).to(x.dtype)


def gap_detector(dt: Tensor, factor: float) -> Tensor:
    """Sensor health (B, N) in {0., 1.}: the steps dt (B, N) longer than ``factor`` × the typical
    step before them (samples lost; :func:`~tcn_ahrs.kernels.closed_loop.gap_step`, the backbone's
    rule); the first step (not used by the loop) is not judged. A stream of one step: no loop."""
    out = torch.zeros_like(dt)
    if dt.shape[1] < 3 or bool((dt[:, 1:] == dt[:, 1:2]).all()):
        return out
    for b in range(dt.shape[0]):
        typical = 0.0
        flags: List[float] = [0.0]
        steps: List[float] = dt[b, 1:].tolist()
        for step in steps:
            typical, gap = gap_step(typical, step, factor)
            flags.append(gap)
        out[b] = torch.tensor(flags, dtype=dt.dtype, device=dt.device)
    return out


def east_reference(rot0: Tensor, acc0: Tensor, mag0: Tensor) -> Tensor:
    """Horizontal unit vector (B, 3), navigation frame: the measured magnetic east
    ``unit(m × a)`` at the initial attitude ``rot0`` (B, 3, 3) ``nav_from_body``."""
    east_b = unit_vector(torch.cross(mag0, acc0, dim=-1))
    e = (rot0 @ east_b.unsqueeze(-1)).squeeze(-1)
    e = torch.stack([e[:, 0], e[:, 1], torch.zeros_like(e[:, 2])], -1)
    return unit_vector(e)


def closed_loop_scan(rot: Tensor, bias: Tensor, gyro: Tensor, acc_unit: Tensor, east_b: Tensor,
                     acc_gain: Tensor, mag_gain: Tensor, rest_gain: Tensor, east_ref: Tensor,
                     dt: Tensor, bias_gain: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
    """The closed loop over samples 1..N-1 from the state (rot (B, 3, 3) ``nav_from_body``,
    bias (B, 3)) at sample 0.

    gyro ω̂_gyr, acc_unit â, east_b unit(m × a) (B, N, 3) body; acc_gain k_acc τ_acc,
    mag_gain k_mag τ_mag (1/s), rest_gain min(1, ρ dt / T_rest) (B, N, 1); east_ref (B, 3) nav;
    dt (B, N, 1) s; bias_gain k_bias (0-dim), 1/s².
    Returns (rot (B, N, 3, 3), bias (B, N, 3), correction w (B, N, 3)); entry 0 = the initial state.
    exp(φ^) uses the Taylor series of sin(t)/t and (1 - cos t)/t² to t⁶ (error < 1e-7 for
    |φ| < 0.5 rad per sample), smooth at 0 for the gradient."""
    n = gyro.shape[1]
    rs: List[Tensor] = [rot]
    bs: List[Tensor] = [bias]
    cs: List[Tensor] = [torch.zeros_like(bias)]
    er = east_ref.unsqueeze(1)
    r = rot
    b = bias
    for k in range(1, n):
        corr = acc_gain[:, k] * torch.cross(acc_unit[:, k], r[:, 2, :], dim=-1)  # Eq. 23: C^T up = row 2
        corr = corr + mag_gain[:, k] * torch.cross(east_b[:, k], (er @ r).squeeze(1), dim=-1)  # Eq. 24
        d = dt[:, k]
        b = b - bias_gain * corr * d + rest_gain[:, k] * (gyro[:, k] - b)
        phi = ((gyro[:, k] - b + corr) * d).unsqueeze(1).expand(-1, 3, 3)
        t2 = (phi[:, 0] * phi[:, 0]).sum(-1, keepdim=True).unsqueeze(-1)
        a = 1.0 - t2 / 6.0 * (1.0 - t2 / 20.0 * (1.0 - t2 / 42.0))
        c = 0.5 - t2 / 24.0 * (1.0 - t2 / 30.0 * (1.0 - t2 / 56.0))
        rk = torch.cross(r, phi, dim=-1)
        r = r + a * rk + c * torch.cross(rk, phi, dim=-1)
        rs.append(r)
        bs.append(b)
        cs.append(corr)
    return torch.stack(rs, 1), torch.stack(bs, 1), torch.stack(cs, 1)


_scan = torch.jit.script(closed_loop_scan)


_CL = ClosedLoopConfig()  # the defaults (meaning, units): tcn_ahrs/config/model.py


class ClosedLoopFilter(nn.Module):
    """Trainable gains of the closed loop (see the module docstring).

    Args:
        use_acc, use_mag: which innovations feed back (``use_mag`` needs 9-axis input).
        acc_gain:  k_acc, 1/s (default 0.3: a ≈ 3 s time constant, VQF's τ_acc).
        mag_gain:  k_mag, 1/s (default 0.1: ≈ 10 s, VQF's τ_mag ≈ 9 s).
        bias_gain: k_bias, 1/s² (default 0.003).
        rest_time_constant: T_rest, s, of the bias update at rest (default 2).
        rest_time, rest_gyro, rest_acc: the rest detector (s, rad/s, m/s²; :func:`rest_detector`).
        acc_reject: m/s²; samples with ``| |a| − g | ≥ acc_reject`` (raw) neither correct the
            attitude nor, through the measured east, the heading (the ECF's Eq. 7 test); 0: off.
        mag_min, mag_max: µT; the magnetometer corrects heading only while the raw field norm lies
            in this range (Eq. 7; the Earth's field is 22–67 µT, a norm outside it is a local
            disturbance — a steel trolley reads 15 µT); 0, 0: off.
        backend: the loop's implementation in eager mode (see :meth:`_scan`); TorchScript (the
            exports) runs :func:`~tcn_ahrs.model.closed_loop_step.scan_scalar`.
    The gates multiply the networks' trust: they are the classical prior, the trust learns the rest.
    The rest window in samples is fixed at training time from the training rate
    (:meth:`set_rate`, saved as the buffer ``rest_window``; 0: from the data's median step),
    like the networks' time scale, so evaluation and the exports use the same window.
    """

    def __init__(self, use_acc: bool = True, use_mag: bool = True, acc_gain: float = _CL.acc_gain,
                 mag_gain: float = _CL.mag_gain, bias_gain: float = _CL.bias_gain,
                 rest_time_constant: float = _CL.rest_time_constant, rest_time: float = _CL.rest_time,
                 rest_gyro: float = _CL.rest_gyro, rest_acc: float = _CL.rest_acc, acc_reject: float = _CL.acc_reject,
                 mag_min: float = _CL.mag_min, mag_max: float = _CL.mag_max, backend: str = "auto"):
        super().__init__()
        self.acc_reject = float(acc_reject)
        self.gravity = float(GRAVITY)
        self.mag_min = float(mag_min)
        self.mag_max = float(mag_max)
        self.rest_time = float(rest_time)
        self.rest_gyro = float(rest_gyro)
        self.rest_acc = float(rest_acc)
        self.register_buffer("rest_window", torch.zeros((), dtype=torch.long))
        self.frozen_time, self.frozen_min_samples = float(FROZEN_TIME), int(FROZEN_MIN_SAMPLES)
        self.gap_factor = float(GAP_FACTOR)
        if backend not in ("auto", "torch", "numba"):
            raise ValueError(f"ClosedLoopFilter: backend {backend!r}: expected 'auto', 'torch' or 'numba'")
        self.backend = str(backend)
        self.use_acc = bool(use_acc)
        self.use_mag = bool(use_mag)
        self.log_acc_gain = nn.Parameter(torch.tensor(math.log(acc_gain)))
        self.log_mag_gain = nn.Parameter(torch.tensor(math.log(mag_gain)))
        self.log_bias_gain = nn.Parameter(torch.tensor(math.log(bias_gain)))
        self.log_rest_tc = nn.Parameter(torch.tensor(math.log(rest_time_constant)))

    @torch.jit.unused
    def set_rate(self, rate_hz: float) -> None:
        """Fix the rest window (samples) for data at ``rate_hz``."""
        self.rest_window.fill_(window_samples(self.rest_time, float(rate_hz)))

    def window(self, dt: Tensor) -> int:
        w = int(self.rest_window)
        if w > 0:
            return w
        return rest_window(dt, self.rest_time)

    def rest(self, gyro: Tensor, acc: Tensor, dt: Tensor) -> Tensor:
        """:func:`rest_detector` on raw readings (B, N, 3) with this filter's settings."""
        return rest_detector(gyro, acc, self.window(dt), self.rest_gyro, self.rest_acc)

    def gates(self, acc: Tensor, mag: Optional[Tensor]) -> Tuple[Tensor, Tensor]:
        """Eq. 7 gates (B, N) in {0., 1.} from raw acc, mag (B, N, 3): accelerometer near 1 g,
        field norm in [mag_min, mag_max] (and the accelerometer gate: the measured east uses a)."""
        one = torch.ones_like(acc[..., 0])
        if self.acc_reject <= 0.0 and self.mag_max <= 0.0:
            return one, one
        a_min = math.inf if self.acc_reject <= 0.0 else self.acc_reject
        m_max = math.inf if self.mag_max <= 0.0 else self.mag_max
        m_min = self.mag_min if self.mag_max > 0.0 else -1.0
        acc_ok, mag_ok = field_gates(acc, mag, one * a_min, one * m_min, one * m_max, self.gravity)
        acc_ok = acc_ok.to(acc.dtype)
        mag_ok = mag_ok.to(acc.dtype)
        return acc_ok, mag_ok

    @torch.jit.unused
    def _scan(self, *args: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
        """The loop (arguments of :func:`closed_loop_scan`). ``backend="auto"`` on the CPU with
        numba: evaluation (no gradient) runs the compiled loop
        (:mod:`~tcn_ahrs.model.closed_loop_step`, ~1000x faster than the tensor scan); training
        (a gradient needed) runs :class:`~tcn_ahrs.model.closed_loop_compiled.ScanFunction`, the
        compiled loop with its compiled reverse pass. Otherwise (CUDA, no numba, or
        ``backend="torch"``) the tensor scan :func:`closed_loop_scan` under autograd.
        ``backend``: "auto" | "torch" | "numba"."""
        cpu = closed_loop_compiled.AVAILABLE and all(a.device.type == "cpu" for a in args)
        grad = torch.is_grad_enabled() and any(a.requires_grad for a in args)
        if self.backend == "numba" and not cpu:
            raise ValueError("ClosedLoopFilter(backend='numba'): needs numba and CPU tensors "
                             "(use backend='auto' or 'torch')")
        if self.backend == "torch" or not cpu:
            return _scan(*args)
        if grad:  # training: compiled forward and reverse pass (float64 inside)
            return closed_loop_compiled.ScanFunction.apply(*args)
        return closed_loop_compiled.scan_numba(*args)

    @torch.jit.unused
    def gains(self) -> Dict[str, float]:
        return {"acc_gain": float(self.log_acc_gain.exp()), "mag_gain": float(self.log_mag_gain.exp()),
                "bias_gain": float(self.log_bias_gain.exp()), "rest_time_constant": float(self.log_rest_tc.exp())}

    def run(self, cal: Dict[str, Tensor], imu: Tensor, dt: Tensor, rot0: Tensor, bias0: Tensor,
            east_ref: Optional[Tensor], context: int, dtype: torch.dtype) -> Dict[str, Tensor]:
        """The closed loop behind a :class:`~tcn_ahrs.model.calibration.Calibration` output
        ``cal`` (dict of (B, N, 3) / (B, N)) for raw imu (B, N, C), dt (B, N): rest detection on
        the raw readings, trust ``2σ(logit)``, then :meth:`forward` in ``dtype`` from sample
        ``context`` on (the samples before only warm the causal networks up). Returns ``cal``
        plus ``rot``, ``gyro_bias``, ``correction`` (B, N - context, ...), ``east_ref``,
        ``rest``, ``gyro_frozen``, ``acc_frozen``, ``gap``, ``acc_trust``, ``mag_trust`` (B, N)."""
        rest = self.rest(imu[..., 0:3], imu[..., 3:6], dt)
        # sensor health: a frozen gyro is not integrated (the step is held: no turn, no bias
        # change), a frozen accelerometer not trusted (nor the measured east built from it)
        fw = frozen_window(self.window(dt), self.rest_time, self.frozen_time, self.frozen_min_samples)
        gyro_frozen = frozen_detector(imu[..., 0:3], fw)
        acc_frozen = frozen_detector(imu[..., 3:6], fw)
        rest = rest * (1.0 - gyro_frozen) * (1.0 - acc_frozen)
        dt_run = dt * (1.0 - gyro_frozen)
        # a gap (samples lost): the rate over it is the mean of the readings either side
        gap = gap_detector(dt, self.gap_factor)
        gyro = cal["gyro"]
        before = torch.cat([gyro[:, :1], gyro[:, :-1]], 1)
        gyro = torch.where(gap.unsqueeze(-1) > 0.5, 0.5 * (gyro + before), gyro)
        raw_mag: Optional[Tensor] = None
        if imu.shape[-1] >= 9:
            raw_mag = imu[..., 6:9]
        acc_ok, mag_ok = self.gates(imu[..., 3:6], raw_mag)
        acc_ok, mag_ok = acc_ok * (1.0 - acc_frozen), mag_ok * (1.0 - acc_frozen)
        acc_trust = 2.0 * torch.sigmoid(cal["acc_trust_logit"]) * acc_ok
        mag_trust = torch.ones_like(acc_trust)
        mag: Optional[Tensor] = None
        if "mag" in cal:
            mag_trust = 2.0 * torch.sigmoid(cal["mag_trust_logit"]) * mag_ok
            mag = cal["mag"][:, context:].to(dtype)
        ref: Optional[Tensor] = None
        if east_ref is not None:
            ref = east_ref.to(dtype)
        out = self.forward(gyro[:, context:].to(dtype), cal["acc"][:, context:].to(dtype), mag,
                           imu[:, context:, 3:6].to(dtype), acc_trust[:, context:].to(dtype),
                           mag_trust[:, context:].to(dtype), rest[:, context:].to(dtype),
                           dt_run[:, context:].to(dtype), rot0.to(dtype), bias0.to(dtype), ref)
        res = dict(cal)
        for k, v in out.items():
            res[k] = v
        res["rest"] = rest
        res["gyro_frozen"] = gyro_frozen
        res["acc_frozen"] = acc_frozen
        res["gap"] = gap
        res["acc_trust"] = acc_trust
        res["mag_trust"] = mag_trust
        return res

    def forward(self, gyro: Tensor, acc: Tensor, mag: Optional[Tensor], acc_raw: Tensor,
                acc_trust: Tensor, mag_trust: Tensor, rest: Tensor, dt: Tensor, rot0: Tensor,
                bias0: Tensor, east_ref: Optional[Tensor] = None) -> Dict[str, Tensor]:
        """Run over a window from the state (rot0 (B, 3, 3) ``nav_from_body``, bias0 (B, 3))
        *at sample 0*.

        gyro ω̂_gyr, acc ĝ, mag b̂ (B, N, 3) calibrated; acc_raw the raw accelerometer (for the
        measured east, Eq. 24); acc_trust, mag_trust (B, N) ∈ (0, 2); rest (B, N) ∈ [0, 1];
        dt (B, N) s; east_ref (B, 3) (default: from rot0 and sample 0).
        Returns ``rot`` (B, N, 3, 3) (entry 0 = rot0), ``gyro_bias`` (B, N, 3), ``correction``
        (B, N, 3) rad/s, ``east_ref`` (B, 3)."""
        acc_unit = unit_vector(acc)
        dt_ = dt.unsqueeze(-1)
        zero = torch.zeros_like(dt_)
        east_b = torch.zeros_like(gyro)
        mag_gain = zero
        ref = torch.zeros_like(gyro[:, 0])
        if self.use_mag and mag is not None:
            east_b = unit_vector(torch.cross(mag, acc_raw, dim=-1))
            if east_ref is None:
                ref = east_reference(rot0, acc_raw[:, 0], mag[:, 0])
            else:
                ref = east_ref
            mag_gain = self.log_mag_gain.exp().to(gyro.dtype) * mag_trust.unsqueeze(-1)
        acc_gain = zero
        if self.use_acc:
            acc_gain = self.log_acc_gain.exp().to(gyro.dtype) * acc_trust.unsqueeze(-1)
        rest_gain = (rest.unsqueeze(-1) * dt_ / self.log_rest_tc.exp().to(gyro.dtype)).clamp_max(1.0)
        bias_gain = self.log_bias_gain.exp().to(gyro.dtype)
        if torch.jit.is_scripting():  # the exported modules: the scalar loop (closed_loop_step)
            rot, bias, corr = scan_scalar(rot0, bias0, gyro, acc_unit, east_b, acc_gain, mag_gain, rest_gain,
                                          ref, dt_, bias_gain)
        else:
            rot, bias, corr = self._scan(rot0, bias0, gyro, acc_unit, east_b, acc_gain, mag_gain, rest_gain,
                                         ref, dt_, bias_gain)
        return {"rot": rot, "gyro_bias": bias, "correction": corr, "east_ref": ref}
