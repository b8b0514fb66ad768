"""The learned closed loop (``model.loop=closed``) one sample or one chunk per call, compiled by
numba (:class:`CompiledStreaming`; see :mod:`tcn_ahrs.streaming` for why beside the export)."""
from __future__ import annotations

import math
from typing import Any, Mapping, Optional, Tuple, Union

import numpy as np
import torch

from .backbone import BackboneStreaming
from ..export.contract import check_samples, checked_chunk, one_sample, check_quat0
from .networks import AVAILABLE, flat_networks, scripted_ring_convolutions

if AVAILABLE:  # the compiled parts (without numba the runtimes raise ImportError when built)
    import numba

    from ..kernels.quat import matrix_to_quat_nb as _to_quat
    from ..model.closed_loop_compiled import east_reference_nb as _east_ref
    from ..model.closed_loop_compiled import loop_inputs_nb as _loop_inputs
    from ..model.closed_loop_compiled import gap_step_nb as _gap_step
    from ..model.closed_loop_compiled import repeat_count_nb as _repeat_count
    from ..model.closed_loop_compiled import rest_update_nb as _rest_update
    from ..model.closed_loop_compiled import update_nb as _update
    from .networks import networks_step, scratch

# state: t, C (9) + b (3), east_ref (3), rest sums (6), last unsteady gyro / acc, last gyro and acc
# reading (6), their repeat counts (2), the typical step, the last calibrated gyro (3), rest ring (6 w)
_STATE_RING = 36


if AVAILABLE:
    @numba.njit(cache=True)
    def _steps(xs, dts, feats, params, wts, cfg, ints, state, rings, out):  # pragma: no cover - compiled
        """Samples xs (k, C) with steps dts (k,) through the networks (:func:`networks_step`) and the
        filter; writes [quat (4), omega (3)] per sample into out (k, 7) and advances state and
        rings. feats (k, H): the networks' last features already computed for these samples
        (then the networks are skipped), or an empty (0, H) array."""
        c, nl, w = ints[0], ints[2], ints[3]
        use_acc, use_mag, n_head = ints[4] != 0, ints[5] != 0, ints[7]
        h_in, h_out, tap, pre, v = scratch(ints)
        no_feats = np.empty(0)
        for k in range(xs.shape[0]):
            t = int(state[0])
            x = xs[k]
            networks_step(x, t, feats[k] if feats.shape[0] > 0 else no_feats, params, wts, ints, rings,
                      h_in, h_out, tap, pre, v)
            # ---- rest detector
            rb = _STATE_RING + 6 * (t % w)
            o0 = o1 = o2 = o3 = o4 = o5 = 0.0
            if t >= w:
                o0, o1, o2, o3, o4, o5 = state[rb], state[rb + 1], state[rb + 2], state[rb + 3], state[rb + 4], state[rb + 5]
            for i in range(6):
                state[rb + i] = x[i]
            (state[16], state[17], state[18], state[19], state[20], state[21], lg, la, rest) = _rest_update(
                state[16], state[17], state[18], state[19], state[20], state[21], x[0], x[1], x[2], x[3], x[4], x[5],
                o0, o1, o2, o3, o4, o5, t, w, int(state[22]), int(state[23]), cfg[4], cfg[5])
            state[22], state[23] = lg, la
            # ---- sensor health: a frozen gyro is not integrated, a frozen accelerometer not trusted
            state[30] = _repeat_count(state[24], state[25], state[26], x[0], x[1], x[2], int(state[30]), t)
            state[31] = _repeat_count(state[27], state[28], state[29], x[3], x[4], x[5], int(state[31]), t)
            for i in range(6):
                state[24 + i] = x[i]
            gyro_ok = 0.0 if state[30] >= cfg[10] - 1.0 else 1.0
            acc_ok = 0.0 if state[31] >= cfg[10] - 1.0 else 1.0
            rest = rest * gyro_ok * acc_ok
            # ---- filter
            bx = by = bz = field = 0.0
            if c == 9:
                bx, by, bz = v[6], v[7], v[8]
                field = math.sqrt(x[6] * x[6] + x[7] * x[7] + x[8] * x[8])
            ux, uy, uz, mx, my, mz, ka, km = _loop_inputs(
                v[3], v[4], v[5], bx, by, bz, x[3], x[4], x[5], field, -v[c], -v[c + 1], use_acc, use_mag,
                cfg[0], cfg[1], cfg[6], cfg[7], cfg[8], cfg[9])
            ka, km = ka * acc_ok, km * acc_ok
            s = state
            c0 = c1 = c2 = 0.0
            if t == 0:
                if use_mag:
                    s[13], s[14], s[15] = _east_ref(s[1], s[2], s[3], s[4], s[5], s[6], mx, my, mz)
            else:
                gx, gy, gz = v[0], v[1], v[2]
                s[32], gap = _gap_step(s[32], dts[k], cfg[11])
                if gap > 0.5:  # samples lost: the rate over the gap is the mean of the readings either side
                    gx, gy, gz = 0.5 * (gx + s[33]), 0.5 * (gy + s[34]), 0.5 * (gz + s[35])
                dt = dts[k] * gyro_ok
                (s[1], s[2], s[3], s[4], s[5], s[6], s[7], s[8], s[9], s[10], s[11], s[12], c0, c1, c2) = _update(
                    s[1], s[2], s[3], s[4], s[5], s[6], s[7], s[8], s[9], s[10], s[11], s[12], gx, gy, gz,
                    ux, uy, uz, mx, my, mz, ka, km, min(1.0, rest * dt / cfg[3]), s[13], s[14], s[15], dt, cfg[2])
            s[33], s[34], s[35] = v[0], v[1], v[2]
            state[0] = t + 1
            out[k, 0], out[k, 1], out[k, 2], out[k, 3] = _to_quat(s[1], s[2], s[3], s[4], s[5], s[6], s[7], s[8], s[9])
            out[k, 4], out[k, 5], out[k, 6] = v[0] - s[10] + c0, v[1] - s[11] + c1, v[2] - s[12] + c2


class CompiledStreaming:
    """The learned closed loop of ``model`` (a :class:`~tcn_ahrs.model.ahrs.LearnedAHRS` with
    ``loop=closed``), one sample or one chunk per call, compiled by numba.

    ``rate_hz`` fixes the rest window when the model does not record it (as the export's
    ``rate=``). Methods take numpy arrays or tensors and return float64 numpy arrays:
    ``reset(q0)``; ``step(sample (C,), dt)`` -> quat (4,), omega (3,); ``step_chunk(samples (k, C),
    dt float | (k,))`` -> (k, 4), (k, 3); ``run(imu, dt, q0)`` = reset + one chunk. The dt of the
    first sample after ``reset`` is not used. A sample with a NaN/inf reading or a dt that is not
    finite and > 0 raises ValueError before any state changes."""

    def __new__(cls, model: torch.nn.Module, rate_hz: Optional[float] = None):
        if cls is CompiledStreaming and getattr(model, "backbone", None) is not None:
            return BackboneStreaming(model)  # the residual model: same contract, its own runtime
        return super().__new__(cls)

    def __init__(self, model: torch.nn.Module, rate_hz: Optional[float] = None):
        if not AVAILABLE:
            raise ImportError("CompiledStreaming needs numba (pip install -e '.[fast]')")
        from ..export import ClosedLoopStreaming

        meta: Mapping[str, Any] = {"rate_hz": rate_hz}
        ts = ClosedLoopStreaming(model.eval(), meta)  # the folded weights (not scripted)
        self.axes = int(ts.axes)
        nets = flat_networks(ts, ts.head_weight, ts.head_bias, ts.head_matrix, ts.window, ts.use_acc, ts.use_mag)
        self._wts, self._params, self._ints, self._rings, self._views, self._dilations = nets
        self._ts = ts
        self._n_feat = int(ts.head_weight.shape[1])
        self._no_feats = np.zeros((0, self._n_feat))
        # from this many samples per call the networks run as convolutions over the chunk
        # (measured, broad9, 1 thread, per sample: 11 µs at 100 per call — the per-call overhead
        # of ~40 small ops — 4.1 µs at 256, 2.8 µs at 1024; the compiled loop 4.5 µs at any size)
        self.chunk_networks = 256
        self._cfg = np.asarray([ts.k_acc, ts.k_mag, ts.k_bias, ts.rest_tc, ts.rest_gyro, ts.rest_acc,
                                ts.acc_reject, ts.gravity, ts.mag_min, ts.mag_max, ts.frozen_window, ts.gap_factor], dtype=np.float64)
        self._state = np.zeros(_STATE_RING + 6 * ts.window)
        self._out1 = np.empty((1, 7))
        self._dt1 = np.zeros(1)
        self.reset(np.array([1.0, 0.0, 0.0, 0.0]))

    @staticmethod
    def _quat0(q0) -> torch.Tensor:
        return check_quat0(q0)

    def reset(self, q0) -> None:
        """Start a new recording at attitude q0 (w, x, y, z), nav_from_body, ENU."""
        from .. import so3

        q = self._quat0(q0)
        s = self._state
        s[:] = 0.0
        s[1:10] = so3.quat_to_matrix(q).reshape(9).numpy()
        s[22] = s[23] = -float(self._ints[3]) - 1.0  # no unsteady sample yet
        self._ts.t = 0
        self._ts._reset_rings()  # zeros; the raw-sample ring holds the input mean (= causal zero padding)

    def _check(self, xs: np.ndarray, dts: np.ndarray) -> None:
        # the dt of the first sample after reset is not used by the closed loop
        check_samples(xs, dts[1:] if self._state[0] == 0.0 else dts)

    def step(self, sample, dt: float) -> Tuple[np.ndarray, np.ndarray]:
        """One sample (C,) -> (quat (4,), omega (3,))."""
        x = one_sample(self, sample, dt)
        _steps(x, self._dt1, self._no_feats, self._params, self._wts, self._cfg, self._ints, self._state, self._rings, self._out1)
        return self._out1[0, 0:4].copy(), self._out1[0, 4:7].copy()

    def step_chunk(self, samples, dt: Union[float, np.ndarray]) -> Tuple[np.ndarray, np.ndarray]:
        """k samples (k, C) -> (quat (k, 4), omega (k, 3)): what k calls of :meth:`step` return."""
        xs, dts = checked_chunk(self, samples, dt)
        out = np.empty((xs.shape[0], 7))
        feats = self._no_feats
        if xs.shape[0] >= self.chunk_networks and self._ts.groups > 0:
            with torch.no_grad():
                feats = scripted_ring_convolutions()(torch.from_numpy(xs), int(self._state[0]), self._views,
                                             self._ts.chunk_weights, self._ts.chunk_biases, self._dilations,
                                             int(self._ts.groups)).numpy()
        _steps(xs, dts, feats, self._params, self._wts, self._cfg, self._ints, self._state, self._rings, out)
        return out[:, 0:4], out[:, 4:7]

    def run(self, imu, dt, q0) -> Tuple[np.ndarray, np.ndarray]:
        """reset(q0), then imu (N, C) -> quat (N, 4), omega (N, 3). Every input is checked before
        the state is reset (after an error the stream goes on as before)."""
        xs = np.ascontiguousarray(np.asarray(imu, dtype=np.float64))
        if xs.ndim != 2 or xs.shape[1] != self.axes:
            raise ValueError(f"imu: expected shape (N, {self.axes}), got {list(xs.shape)}")
        dts = np.broadcast_to(np.asarray(dt, dtype=np.float64), (xs.shape[0],))
        if not np.isfinite(xs).all():
            i = [int(v) for v in np.argwhere(~np.isfinite(xs))[0]]
            raise ValueError(f"imu: non-finite value at index {i} (expected finite readings: drop or interpolate that sample)")
        if xs.shape[0] > 1 and not (np.isfinite(dts[1:]).all() and (dts[1:] > 0.0).all()):
            raise ValueError("dt: expected finite time steps > 0 s after sample 0")
        self._quat0(q0)
        self.reset(q0)
        return self.step_chunk(xs, dts)
