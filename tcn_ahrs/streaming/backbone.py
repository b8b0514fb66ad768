"""The residual model (``model.loop=backbone``) one sample or one chunk per call, compiled by
numba (:class:`BackboneStreaming`, what ``CompiledStreaming(model)`` returns for it)."""
from __future__ import annotations

import math
from typing import Tuple, Union

import numpy as np
import torch

from ..export.contract import check_samples, checked_chunk, one_sample, check_quat0
from .networks import AVAILABLE, flat_networks, scripted_ring_convolutions

if AVAILABLE:  # the compiled parts (without numba the runtimes raise ImportError when built)
    import numba

    from ..kernels import backbone as _K
    from .networks import networks_step, scratch

    _bb_coefficients, _bb_gyro, _bb_acc, _bb_mag = _K.coefficients, _K.gyro_update, _K.acc_update, _K.mag_update
    _bb_quat6, _bb_quat9, _bb_qmul = _K.quat6, _K.quat9, _K.qmul
    _BB_S_BIAS = _K.S_BIAS

    @numba.njit(cache=True)
    def _backbone_steps(xs, dts, feats, params, wts, ints, rings, p, s, coeff, knobs, m_conj, out):  # pragma: no cover
        """The residual model per sample: networks (:func:`networks_step`, head rows = −[gyro net
        pre-tanh (3), trust logits]) -> gyro residual and trusts (as
        :class:`~tcn_ahrs.model.residual.BackboneLoop`) -> one backbone step (the kernel of
        :mod:`tcn_ahrs.kernels.backbone`). knobs: [gyro_scale, gyro_clip, trust_max, trust_weight,
        acc, mag, bias trust scale, last dt, use_mag, networks' time index, bias trust power]; m_conj (4,): the magnetic frame's
        conjugate (9D; identity for 6D), applied to the output. out (k, 7): quat, omega."""
        h_in, h_out, tap, pre, v = scratch(ints)
        no_feats = np.empty(0)
        g_scale, g_clip, t_max, t_w = knobs[0], knobs[1], knobs[2], knobs[3]
        use_mag = knobs[8] > 0.5
        for k in range(xs.shape[0]):
            x = xs[k]
            t = int(knobs[9])
            networks_step(x, t, feats[k] if feats.shape[0] > 0 else no_feats, params, wts, ints, rings,
                      h_in, h_out, tap, pre, v)
            knobs[9] = t + 1
            trusts = np.ones(3)
            for j in range(2):
                if 3 + j < ints[7]:
                    tr = min(t_max, 2.0 / (1.0 + math.exp(v[3 + j])))  # 2 σ(z) with z = −v
                    trusts[j] = knobs[4 + j] * (1.0 + t_w * (tr - 1.0))
                else:
                    trusts[j] = knobs[4 + j]
            trusts[2] = knobs[6]
            if knobs[10] > 0.0 and ints[7] > 3:  # the acc trust gating the bias update
                tr = min(t_max, 2.0 / (1.0 + math.exp(v[3])))
                trusts[2] = knobs[6] * (tr / t_max) ** knobs[10]
            gx = x[0] - min(g_clip, max(-g_clip, g_scale * math.tanh(-v[0])))
            gy = x[1] - min(g_clip, max(-g_clip, g_scale * math.tanh(-v[1])))
            gz = x[2] - min(g_clip, max(-g_clip, g_scale * math.tanh(-v[2])))
            if dts[k] != knobs[7]:
                _bb_coefficients(p, dts[k], coeff)
                knobs[7] = dts[k]
            _bb_gyro(s, p, coeff, gx, gy, gz)
            if x[3] != 0.0 or x[4] != 0.0 or x[5] != 0.0:  # the batch loop skips [0 0 0], as VQF
                _bb_acc(s, p, coeff, x[3], x[4], x[5], trusts[0], trusts[2])
            if use_mag and (x[6] != 0.0 or x[7] != 0.0 or x[8] != 0.0):
                _bb_mag(s, p, coeff, x[6], x[7], x[8], trusts[1])
            if use_mag:
                w, qx, qy, qz = _bb_quat9(s)
            else:
                w, qx, qy, qz = _bb_quat6(s)
            out[k, 0], out[k, 1], out[k, 2], out[k, 3] = _bb_qmul(m_conj[0], m_conj[1], m_conj[2], m_conj[3],
                                                                  w, qx, qy, qz)
            out[k, 4], out[k, 5], out[k, 6] = gx - s[_BB_S_BIAS], gy - s[_BB_S_BIAS + 1], gz - s[_BB_S_BIAS + 2]


class BackboneStreaming:
    """The residual model (``model.loop=backbone``, :mod:`tcn_ahrs.model.residual`) one sample or
    one chunk per call, compiled by numba — what ``CompiledStreaming(model)`` returns for it, with
    the same contract: ``reset(q0)``; ``step(sample (C,), dt)`` -> quat (4,), omega (3,);
    ``step_chunk(samples (k, C), dt)``; ``run(imu, dt, q0)``. float64 numpy out; omega = the gyro
    fed to the backbone minus its bias state (the rate it integrates).

    The two networks run on ring buffers (:func:`~tcn_ahrs.export.fused.fuse_residual`: BatchNorm
    folded, float32 as the batch model; a chunk of ≥ ``chunk_networks`` samples as convolutions),
    their outputs become the gyro residual and the trusts exactly as in
    :class:`~tcn_ahrs.model.residual.BackboneLoop`, and the backbone kernel steps on
    (:mod:`tcn_ahrs.kernels.backbone`, the function the batch loop runs). 9 axes: the heading is
    referred to the field of the first sample after ``reset`` (the batch model's ``heading_ref``
    "init"). Unlike the closed loop's, the dt of the first sample after ``reset`` IS used (the
    backbone integrates sample 0, as the batch model does). A non-finite reading or a dt that is
    not finite and > 0 raises ValueError before any state changes."""

    def __init__(self, model: torch.nn.Module):
        if not AVAILABLE:
            raise ImportError("CompiledStreaming needs numba (pip install -e '.[fast]')")
        from ..export.fused import fuse_residual
        from ..export.open_loop import StreamingAHRS
        from ..filters import backbone as bb

        if getattr(model, "backbone", None) is None:
            raise ValueError("BackboneStreaming: the model has no backbone (model.loop must be 'backbone')")
        model = model.eval()
        self._bb = bb
        self.axes = c = int(model.axes)
        fused = fuse_residual(model)
        ts = StreamingAHRS(fused, {})
        n_trust = 2 if c == 9 else 1
        # head rows: −(W h + b) = −[gyro net before tanh (3), trust logits]; the features arrive
        # as sqrt(2) GELU (the sqrt(1/2) folded into W)
        w = torch.cat([ts.out_weight_f64[0:3], fused["trust_weight"][:n_trust] * math.sqrt(0.5)], 0)
        b = torch.cat([fused["out_bias"][0:3], fused["trust_bias"][:n_trust]])
        nets = flat_networks(ts, w, b, torch.zeros(w.shape[0], c, dtype=torch.float64))
        self._wts, self._nparams, self._ints, self._rings, self._views, self._dilations = nets
        self._ts = ts
        self._no_feats = np.zeros((0, int(w.shape[1])))
        self.chunk_networks = 256
        cal, loop = model.calibration, model.backbone
        self._use_mag = bool(loop.use_mag) and c == 9
        self._p = np.asarray(loop.params.vector())
        self._params = loop.params
        self._bias0 = loop.bias_prior * loop.bias_init.detach().double().numpy().copy()
        self._knobs = np.asarray([cal.gyro_scale, cal.gyro_clip, loop.trust_max, loop.trust_weight,
                                  loop.acc_trust_scale, loop.mag_trust_scale, loop.bias_trust_scale,
                                  -1.0, float(self._use_mag), 0.0, loop.bias_trust_power], dtype=np.float64)
        self._coeff = np.zeros(bb.K.N_COEFF)
        self._m_conj = np.array([1.0, 0.0, 0.0, 0.0])
        self._out1 = np.empty((1, 7))
        self._dt1 = np.zeros(1)
        self.reset(np.array([1.0, 0.0, 0.0, 0.0]))

    def reset(self, q0) -> None:
        """Start a new recording at attitude q0 (w, x, y, z), nav_from_body, ENU."""
        self._q0 = check_quat0(q0).numpy()
        self._state = None  # the backbone starts at the first sample (9D: it needs its field)
        self._knobs[7] = -1.0  # coefficients recomputed at the first step
        self._knobs[9] = 0.0   # networks' time index
        self._ts.t = 0
        self._ts._reset_rings()

    def _start(self, x0: np.ndarray) -> None:
        from .. import so3
        from ..filters.common import magnetic_from_nav

        q = self._q0
        self._m_conj = np.array([1.0, 0.0, 0.0, 0.0])
        if self._use_mag:
            m_from_n = magnetic_from_nav(torch.as_tensor(q), torch.as_tensor(x0[6:9]))
            q = so3.quat_mul(m_from_n, torch.as_tensor(q)).numpy()
            self._m_conj = so3.quat_conj(m_from_n).numpy().copy()
        self._state = self._bb.start_state(self._params, q)
        self._state[self._bb.K.S_BIAS:self._bb.K.S_BIAS + 3] = self._bias0

    def _check(self, xs: np.ndarray, dts: np.ndarray) -> None:
        check_samples(xs, dts)  # every dt is used (the backbone integrates sample 0)

    def step(self, sample, dt: float) -> Tuple[np.ndarray, np.ndarray]:
        """One sample (C,) -> (quat (4,), omega (3,))."""
        x = one_sample(self, sample, dt)
        if self._state is None:
            self._start(x[0])
        _backbone_steps(x, self._dt1, self._no_feats, self._nparams, self._wts, self._ints, self._rings, self._p,
                        self._state, self._coeff, self._knobs, self._m_conj, self._out1)
        return self._out1[0, 0:4].copy(), self._out1[0, 4:7].copy()

    def step_chunk(self, samples, dt: Union[float, np.ndarray]) -> Tuple[np.ndarray, np.ndarray]:
        """k samples (k, C) -> (quat (k, 4), omega (k, 3)): what k calls of :meth:`step` return."""
        xs, dts = checked_chunk(self, samples, dt)
        if xs.shape[0] == 0:
            return np.zeros((0, 4)), np.zeros((0, 3))
        if self._state is None:
            self._start(xs[0])
        feats = self._no_feats
        if xs.shape[0] >= self.chunk_networks:
            with torch.no_grad():
                feats = scripted_ring_convolutions()(torch.from_numpy(xs), int(self._knobs[9]), self._views,
                                             self._ts.chunk_weights, self._ts.chunk_biases, self._dilations,
                                             int(self._ts.groups)).numpy()
        out = np.empty((xs.shape[0], 7))
        _backbone_steps(xs, dts, feats, self._nparams, self._wts, self._ints, self._rings, self._p,
                        self._state, self._coeff, self._knobs, self._m_conj, out)
        return out[:, 0:4], out[:, 4:7]

    def run(self, imu, dt, q0) -> Tuple[np.ndarray, np.ndarray]:
        """reset(q0), then imu (N, C) -> quat (N, 4), omega (N, 3). Every input is checked before
        the state is reset."""
        xs = np.ascontiguousarray(np.asarray(imu, dtype=np.float64))
        if xs.ndim != 2 or xs.shape[1] != self.axes:
            raise ValueError(f"imu: expected shape (N, {self.axes}), got {list(xs.shape)}")
        dts = np.ascontiguousarray(np.broadcast_to(np.asarray(dt, dtype=np.float64), (xs.shape[0],)))
        self._check(xs, dts)
        check_quat0(q0)
        self.reset(q0)
        return self.step_chunk(xs, dts)
