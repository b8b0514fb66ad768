"""The learned closed loop one sample (or one chunk) per call, compiled by numba: the library's
fast streaming runtime, beside the exported TorchScript module.

Why two: the exported streaming module (:class:`tcn_ahrs.export.ClosedLoopStreaming`) needs only
torch, but TorchScript interprets every tensor op (~1 µs each, ~40 per sample for three
four-layer TCNs) and every scalar op (~25 ns) of the filter, which bounds it near 10 k samples/s
(``python scripts/benchmark.py speed``). Here the same per-sample work — the ring buffers and
matrix-vector products of the networks, the head, the rest detector and the filter update —
runs as one compiled function: a few µs per sample, called from Python.

Numbers: the same as the exported module (the weights come from the same folding:
:class:`~tcn_ahrs.export.ClosedLoopStreaming`, BatchNorm folded, input normalisation in the
first layer, GELU as ``u (1 + erf(u))`` on scaled pre-activations; the filter is
:mod:`tcn_ahrs.model.closed_loop_step`'s scalar functions), with the networks in float64 instead
of float32; ``tests/test_streaming.py`` holds it to the evaluation model within the export's
parity bound. Frames and units as everywhere: raw body-frame readings (rad/s, m/s², µT),
``nav_from_body`` quaternions (w, x, y, z), ENU.

    stream = CompiledStreaming(model)            # a LearnedAHRS with the closed loop
    stream.reset(q0)
    quat, omega = stream.step(sample, dt)        # (4,), (3,) float64 numpy
    quats, omegas = stream.step_chunk(samples, dt)

numba is optional (``[fast]``, in ``[dev]``): without it this class raises ImportError.
"""
from __future__ import annotations

import math
from typing import Any, Mapping, Optional, Tuple, Union

import numpy as np
import torch

from .model.closed_loop_compiled import AVAILABLE

if AVAILABLE:
    import numba

    from .model.closed_loop_compiled import east_reference_nb as _east_ref
    from .model.closed_loop_compiled import loop_inputs_nb as _loop_inputs
    from .model.closed_loop_compiled import matrix_to_quat_nb as _to_quat
    from .model.closed_loop_compiled import rest_update_nb as _rest_update
    from .model.closed_loop_compiled import update_nb as _update

# ints: header, then 8 entries per convolution layer (weights (groups, c_out, k c_in), taps oldest first), then the head's 3 offsets
_HEADER = 8          # C, K, layers, window, use_acc, use_mag, H (features), rows of the head (C + 2)
_PER_LAYER = 8       # groups, c_in, c_out (per group), dilation, span, weight offset, bias offset, ring offset
# state: t, C (9) + b (3), east_ref (3), rest sums (6), last unsteady gyro / acc, rest ring (6 w)
_STATE_RING = 24

# erf(x) = x P(x²) / Q(x²) on [-4, 4] (±1 beyond), |error| < 7e-8 against math.erf (tested): the
# rational form of Eigen's float32 erf; a polynomial and a division vectorise, a libm call does not
# (math.erf was half of the networks' time: 288 calls per sample)
_ERF_P = (-2.72614225801306e-10, 2.77068142495902e-08, -2.10102402082508e-06, -5.69250639462346e-05,
          -7.34990630326855e-04, -2.95459980854025e-03, -1.60960333262415e-02)
_ERF_Q = (-1.45660718464996e-05, -2.13374055278905e-04, -1.68282697438203e-03, -7.37332916720468e-03,
          -1.42647390514189e-02)


def erf_rational(x: float) -> float:
    """erf(x) to 7e-8 absolute (see _ERF_P)."""
    x = min(max(x, -4.0), 4.0)
    x2 = x * x
    p = _ERF_P[0]
    for c in _ERF_P[1:]:
        p = p * x2 + c
    q = _ERF_Q[0]
    for c in _ERF_Q[1:]:
        q = q * x2 + c
    return x * p / q


if AVAILABLE:
    _erf = numba.njit(cache=True, inline="always")(erf_rational)

    @numba.njit(cache=True, fastmath=True, error_model="numpy")
    def _networks(x, t, feats_k, params, wts, ints, rings, h_in, h_out, tap, pre, v):  # pragma: no cover
        """One sample x (C,) at time t through the networks (ring buffers (groups, span, c_in),
        float32 as the exported module's; the newest input written at row t mod span) — or its
        features feats_k (H,) when given (non-empty) — and the head into v: [M y − (W h + b) ;
        −trust logits]. fastmath (reassociation, so the dot products vectorise) is confined to
        this function; the filter code stays exact."""
        c, kk, nl, n_feat, n_head = ints[0], ints[1], ints[2], ints[6], ints[7]
        hw, hb, hm = ints[_HEADER + _PER_LAYER * nl], ints[_HEADER + _PER_LAYER * nl + 1], ints[_HEADER + _PER_LAYER * nl + 2]
        n_in = c
        for i in range(c):
            h_in[i] = x[i]
        nl_run = nl
        if feats_k.shape[0] > 0:
            for i in range(n_feat):
                h_in[i] = feats_k[i]
            nl_run = 0
        for li in range(nl_run):
            base = _HEADER + _PER_LAYER * li
            g, cin, cout, d, span = ints[base], ints[base + 1], ints[base + 2], ints[base + 3], ints[base + 4]
            wo, bo, ro = ints[base + 5], ints[base + 6], ints[base + 7]
            p = t % span
            for gr in range(g):
                for i in range(cin):
                    rings[ro + (gr * span + p) * cin + i] = h_in[gr * cin + i]
            n_tap = kk * cin
            for gr in range(g):
                for j in range(kk):  # taps oldest first: t - (K - 1 - j) d
                    rb = ro + (gr * span + (t - (kk - 1 - j) * d) % span) * cin
                    for i in range(cin):
                        tap[j * cin + i] = rings[rb + i]
                for o in range(cout):  # one float32 dot product over the K c_in taps per output
                    # (a slice: indices from 0 need no negative-index wrap-around, so the
                    # loop vectorises; wts[offset + i] runs ~5x slower)
                    wv = wts[wo + (gr * cout + o) * n_tap:wo + (gr * cout + o + 1) * n_tap]
                    u = wts[bo + gr * cout + o]
                    for i in range(n_tap):
                        u += wv[i] * tap[i]
                    pre[o] = u
                for o in range(cout):  # GELU, sqrt(2)-scaled: u (1 + erf(u)), vectorised
                    u = float(pre[o])
                    h_out[gr * cout + o] = u * (1.0 + _erf(u))
            n_in = g * cout
            for i in range(n_in):
                h_in[i] = h_out[i]
        for r in range(n_head):
            wv = params[hw + r * n_feat:hw + (r + 1) * n_feat]
            e = params[hb + r]
            for i in range(n_feat):
                e += wv[i] * h_in[i]
            mv = params[hm + r * c:hm + (r + 1) * c]
            m = 0.0
            for i in range(c):
                m += mv[i] * x[i]
            v[r] = m - e

    @numba.njit(cache=True)
    def _scratch(ints):  # pragma: no cover - compiled
        """The per-call work arrays of :func:`_networks` for the layout ``ints``: layer inputs and
        outputs (float64), taps and pre-activations (float32), the head's rows."""
        width = ints[0]
        for li in range(ints[2]):
            width = max(width, ints[_HEADER + _PER_LAYER * li] * ints[_HEADER + _PER_LAYER * li + 2])
        return (np.empty(max(width, ints[6])), np.empty(max(width, ints[6])),
                np.empty(ints[1] * width, dtype=np.float32), np.empty(width, dtype=np.float32), np.empty(ints[7]))

    @numba.njit(cache=True)
    def _steps(xs, dts, feats, params, wts, cfg, ints, state, rings, out):  # pragma: no cover - compiled
        """Samples xs (k, C) with steps dts (k,) through the networks (:func:`_networks`) and the
        filter; writes [quat (4), omega (3)] per sample into out (k, 7) and advances state and
        rings. feats (k, H): the networks' last features already computed for these samples
        (then the networks are skipped), or an empty (0, H) array."""
        c, nl, w = ints[0], ints[2], ints[3]
        use_acc, use_mag, n_head = ints[4] != 0, ints[5] != 0, ints[7]
        h_in, h_out, tap, pre, v = _scratch(ints)
        no_feats = np.empty(0)
        for k in range(xs.shape[0]):
            t = int(state[0])
            x = xs[k]
            _networks(x, t, feats[k] if feats.shape[0] > 0 else no_feats, params, wts, ints, rings,
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
            # ---- filter
            bx = by = bz = field = 0.0
            if c == 9:
                bx, by, bz = v[6], v[7], v[8]
                field = math.sqrt(x[6] * x[6] + x[7] * x[7] + x[8] * x[8])
            ux, uy, uz, mx, my, mz, ka, km = _loop_inputs(
                v[3], v[4], v[5], bx, by, bz, x[3], x[4], x[5], field, -v[c], -v[c + 1], use_acc, use_mag,
                cfg[0], cfg[1], cfg[6], cfg[7], cfg[8], cfg[9])
            s = state
            c0 = c1 = c2 = 0.0
            if t == 0:
                if use_mag:
                    s[13], s[14], s[15] = _east_ref(s[1], s[2], s[3], s[4], s[5], s[6], mx, my, mz)
            else:
                dt = dts[k]
                (s[1], s[2], s[3], s[4], s[5], s[6], s[7], s[8], s[9], s[10], s[11], s[12], c0, c1, c2) = _update(
                    s[1], s[2], s[3], s[4], s[5], s[6], s[7], s[8], s[9], s[10], s[11], s[12], v[0], v[1], v[2],
                    ux, uy, uz, mx, my, mz, ka, km, min(1.0, rest * dt / cfg[3]), s[13], s[14], s[15], dt, cfg[2])
            state[0] = t + 1
            out[k, 0], out[k, 1], out[k, 2], out[k, 3] = _to_quat(s[1], s[2], s[3], s[4], s[5], s[6], s[7], s[8], s[9])
            out[k, 4], out[k, 5], out[k, 6] = v[0] - s[10] + c0, v[1] - s[11] + c1, v[2] - s[12] + c2


if AVAILABLE:
    from .kernels import backbone as _K

    _bb_coefficients, _bb_gyro, _bb_acc, _bb_mag = _K.coefficients, _K.gyro_update, _K.acc_update, _K.mag_update
    _bb_quat6, _bb_quat9, _bb_qmul = _K.quat6, _K.quat9, _K.qmul
    _BB_S_BIAS = _K.S_BIAS

    @numba.njit(cache=True)
    def _backbone_steps(xs, dts, feats, params, wts, ints, rings, p, s, coeff, knobs, m_conj, out):  # pragma: no cover
        """The residual model per sample: networks (:func:`_networks`, head rows = −[gyro net
        pre-tanh (3), trust logits]) -> gyro residual and trusts (as
        :class:`~tcn_ahrs.model.residual.BackboneLoop`) -> one backbone step (the kernel of
        :mod:`tcn_ahrs.kernels.backbone`). knobs: [gyro_scale, gyro_clip, trust_max, trust_weight,
        acc, mag, bias trust scale, last dt, use_mag]; m_conj (4,): the magnetic frame's
        conjugate (9D; identity for 6D), applied to the output. out (k, 7): quat, omega."""
        h_in, h_out, tap, pre, v = _scratch(ints)
        no_feats = np.empty(0)
        g_scale, g_clip, t_max, t_w = knobs[0], knobs[1], knobs[2], knobs[3]
        use_mag = knobs[8] > 0.5
        for k in range(xs.shape[0]):
            x = xs[k]
            t = int(knobs[9])
            _networks(x, t, feats[k] if feats.shape[0] > 0 else no_feats, params, wts, ints, rings,
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


def _one_sample(stream, sample, dt) -> np.ndarray:
    """One sample as a checked (1, C) array; its dt stored in ``stream._dt1``."""
    x = np.asarray(sample, dtype=np.float64)
    if x.ndim != 1:
        raise ValueError(f"sample: expected shape ({stream.axes},), got {list(x.shape)}")
    x = x.reshape(1, -1)
    if x.shape[1] != stream.axes:
        raise ValueError(f"sample: expected {stream.axes} values, got {x.shape[1]}")
    stream._dt1[0] = dt
    stream._check(x, stream._dt1)
    return x


def _chunk(stream, samples, dt) -> Tuple[np.ndarray, np.ndarray]:
    """k samples as a checked (k, C) array and their (k,) steps."""
    xs = np.ascontiguousarray(np.asarray(samples, dtype=np.float64))
    if xs.ndim != 2 or xs.shape[1] != stream.axes:
        raise ValueError(f"samples: expected shape (k, {stream.axes}), got {list(xs.shape)}")
    dts = np.ascontiguousarray(np.broadcast_to(np.asarray(dt, dtype=np.float64), (xs.shape[0],)))
    stream._check(xs, dts)
    return xs, dts


def _check_samples(xs: np.ndarray, dts: np.ndarray) -> None:
    """ValueError unless every reading is finite and within the physical ranges
    (:data:`tcn_ahrs.conventions.INPUT_RANGES`) and every (used) step is finite, > 0 and
    <= :data:`~tcn_ahrs.conventions.MAX_DT` s."""
    from .conventions import INPUT_LIMITS, INPUT_RANGES, MAX_DT

    if not np.isfinite(xs).all():
        i = [int(v) for v in np.argwhere(~np.isfinite(xs))[0]]
        raise ValueError(f"sample: non-finite value at index {i} (expected finite readings: drop or "
                         "interpolate that sample)")
    limit = np.asarray(INPUT_LIMITS[:xs.shape[1]])
    if (np.abs(xs) > limit).any():
        i = [int(v) for v in np.argwhere(np.abs(xs) > limit)[0]]
        raise ValueError(f"sample: value {xs[i[0], i[1]]:.4g} at index {i} is beyond any sensor's range (|gyro| <= "
                         f"{INPUT_RANGES['gyro']:g} rad/s, |acc| <= {INPUT_RANGES['accel']:g} m/s^2, |mag| <= "
                         f"{INPUT_RANGES['mag']:g} uT per axis): a spike; drop or interpolate that sample")
    if dts.size and not (np.isfinite(dts).all() and (dts > 0.0).all() and (dts <= MAX_DT).all()):
        raise ValueError(f"dt: expected finite time steps in (0, {MAX_DT:g}] s since the previous sample, got "
                         f"{dts.tolist()}")


def _flat_networks(ts, head_weight, head_bias, head_matrix, window: int = 1, use_acc: bool = False,
                   use_mag: bool = False):
    """The folded networks of an exported streaming module ``ts`` (:class:`StreamingAHRS`) as the
    flat arrays :func:`_networks` reads: float32 weights, float64 head ``[M y − (W h + b)]`` rows,
    the int layout, and one float32 ring-buffer array that ``ts``'s (unscripted) buffers are made
    to view, so that its chunk convolutions (:func:`ring_convolutions`) and the compiled
    per-sample step advance the same state. Returns (wts, params, ints, rings, views, dilations)."""
    c, k = int(ts.axes), int(ts.kernel_size)
    layers = []  # (groups, c_in, c_out, dilation, span, weight (groups, k*c_in, c_out), bias)
    if ts.groups > 0:
        w0 = ts.first_weight_t.double()
        layers.append((1, c, w0.shape[1], ts.first_dilation, ts.first_span, w0.unsqueeze(0),
                       ts.first_bias_step.double().reshape(-1)))
        for w, b, d, span in zip(ts.step_weights, ts.step_biases, ts.hidden_dilations, ts.spans):
            g, _, c_out = w.shape
            layers.append((g, w.shape[1] // k, c_out, d, span, w.double(), b.double().reshape(-1)))
    # weights as (groups, c_out, k c_in): each output one contiguous dot product over its taps
    layers = [(g, c_in, c_out, d, span, w.transpose(1, 2).contiguous(), b)
              for g, c_in, c_out, d, span, w, b in layers]
    wts, params, ints = [], [], [c, k, len(layers), int(window), int(use_acc), int(use_mag),
                                 head_weight.shape[1], head_weight.shape[0]]
    size = 0
    ring = 0
    for g, c_in, c_out, d, span, w, b in layers:  # the networks' weights in float32, as exported
        ints += [g, c_in, c_out, d, span, size, size + w.numel(), ring]
        wts += [w.reshape(-1), b]
        size += w.numel() + b.numel()
        ring += span * g * c_in
    wts = (torch.cat(wts) if wts else torch.zeros(1)).float().numpy().copy()
    rings = np.zeros(max(ring, 1), dtype=np.float32)
    views = []
    if ts.groups > 0:
        flat = torch.from_numpy(rings)
        off = 0
        for g, c_in, _, _, span, _, _ in layers:
            views.append(flat[off:off + g * span * c_in].view(g, span, c_in))
            off += g * span * c_in
        ts.first_buffer = views[0][0]
        ts.ring_buffers = views[1:]
    dilations = [int(d) for _, _, _, d, _, _, _ in layers]
    size = 0
    for t_ in (head_weight, head_bias, head_matrix):
        ints.append(size)
        params.append(t_.double().reshape(-1))
        size += t_.numel()
    return wts, torch.cat(params).numpy().copy(), np.asarray(ints, dtype=np.int64), rings, views, dilations


_SCRIPTED = {}


def _ring_convolutions():
    """:func:`tcn_ahrs.export.fused.ring_convolutions`, scripted once (TorchScript runs its
    ~40 small tensor ops ~5x faster than eager dispatch)."""
    if "ring" not in _SCRIPTED:
        from .export.fused import ring_convolutions

        _SCRIPTED["ring"] = torch.jit.script(ring_convolutions)
    return _SCRIPTED["ring"]


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
        from .export import ClosedLoopStreaming

        meta: Mapping[str, Any] = {"rate_hz": rate_hz}
        ts = ClosedLoopStreaming(model.eval(), meta)  # the folded weights (not scripted)
        self.axes = int(ts.axes)
        nets = _flat_networks(ts, ts.head_weight, ts.head_bias, ts.head_matrix, ts.window, ts.use_acc, ts.use_mag)
        self._wts, self._params, self._ints, self._rings, self._views, self._dilations = nets
        self._ts = ts
        self._n_feat = int(ts.head_weight.shape[1])
        self._no_feats = np.zeros((0, self._n_feat))
        # from this many samples per call the networks run as convolutions over the chunk
        # (measured, broad9, 1 thread, per sample: 11 µs at 100 per call — the per-call overhead
        # of ~40 small ops — 4.1 µs at 256, 2.8 µs at 1024; the compiled loop 4.5 µs at any size)
        self.chunk_networks = 256
        self._cfg = np.asarray([ts.k_acc, ts.k_mag, ts.k_bias, ts.rest_tc, ts.rest_gyro, ts.rest_acc,
                                ts.acc_reject, ts.gravity, ts.mag_min, ts.mag_max], dtype=np.float64)
        self._state = np.zeros(_STATE_RING + 6 * ts.window)
        self._out1 = np.empty((1, 7))
        self._dt1 = np.zeros(1)
        self.reset(np.array([1.0, 0.0, 0.0, 0.0]))

    @staticmethod
    def _quat0(q0) -> torch.Tensor:
        q = torch.as_tensor(np.asarray(q0, dtype=np.float64)).reshape(-1)
        if q.numel() != 4 or not bool(torch.isfinite(q).all()) or float(q.norm()) == 0.0:
            raise ValueError(f"q0: expected a non-zero finite quaternion (w, x, y, z), got {q.tolist()}")
        return q / q.norm()

    def reset(self, q0) -> None:
        """Start a new recording at attitude q0 (w, x, y, z), nav_from_body, ENU."""
        from . import so3

        q = self._quat0(q0)
        s = self._state
        s[:] = 0.0
        s[1:10] = so3.quat_to_matrix(q).reshape(9).numpy()
        s[22] = s[23] = -float(self._ints[3]) - 1.0  # no unsteady sample yet
        self._ts.t = 0
        self._ts._reset_rings()  # zeros; the raw-sample ring holds the input mean (= causal zero padding)

    def _check(self, xs: np.ndarray, dts: np.ndarray) -> None:
        # the dt of the first sample after reset is not used by the closed loop
        _check_samples(xs, dts[1:] if self._state[0] == 0.0 else dts)

    def step(self, sample, dt: float) -> Tuple[np.ndarray, np.ndarray]:
        """One sample (C,) -> (quat (4,), omega (3,))."""
        x = _one_sample(self, sample, dt)
        _steps(x, self._dt1, self._no_feats, self._params, self._wts, self._cfg, self._ints, self._state, self._rings, self._out1)
        return self._out1[0, 0:4].copy(), self._out1[0, 4:7].copy()

    def step_chunk(self, samples, dt: Union[float, np.ndarray]) -> Tuple[np.ndarray, np.ndarray]:
        """k samples (k, C) -> (quat (k, 4), omega (k, 3)): what k calls of :meth:`step` return."""
        xs, dts = _chunk(self, samples, dt)
        out = np.empty((xs.shape[0], 7))
        feats = self._no_feats
        if xs.shape[0] >= self.chunk_networks and self._ts.groups > 0:
            with torch.no_grad():
                feats = _ring_convolutions()(torch.from_numpy(xs), int(self._state[0]), self._views,
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
        from .export.fused import fuse_residual
        from .export.open_loop import StreamingAHRS
        from .filters import backbone as bb

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
        nets = _flat_networks(ts, w, b, torch.zeros(w.shape[0], c, dtype=torch.float64))
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
                                  -1.0, float(self._use_mag), 0.0], dtype=np.float64)
        self._coeff = np.zeros(bb.K.N_COEFF)
        self._m_conj = np.array([1.0, 0.0, 0.0, 0.0])
        self._out1 = np.empty((1, 7))
        self._dt1 = np.zeros(1)
        self.reset(np.array([1.0, 0.0, 0.0, 0.0]))

    def reset(self, q0) -> None:
        """Start a new recording at attitude q0 (w, x, y, z), nav_from_body, ENU."""
        self._q0 = CompiledStreaming._quat0(q0).numpy()
        self._state = None  # the backbone starts at the first sample (9D: it needs its field)
        self._knobs[7] = -1.0  # coefficients recomputed at the first step
        self._knobs[9] = 0.0   # networks' time index
        self._ts.t = 0
        self._ts._reset_rings()

    def _start(self, x0: np.ndarray) -> None:
        from . import so3
        from .filters.common import magnetic_from_nav

        q = self._q0
        self._m_conj = np.array([1.0, 0.0, 0.0, 0.0])
        if self._use_mag:
            m_from_n = magnetic_from_nav(torch.as_tensor(q), torch.as_tensor(x0[6:9]))
            q = so3.quat_mul(m_from_n, torch.as_tensor(q)).numpy()
            self._m_conj = so3.quat_conj(m_from_n).numpy().copy()
        self._state = self._bb.start_state(self._params, q)
        self._state[self._bb.K.S_BIAS:self._bb.K.S_BIAS + 3] = self._bias0

    def _check(self, xs: np.ndarray, dts: np.ndarray) -> None:
        _check_samples(xs, dts)  # every dt is used (the backbone integrates sample 0)

    def step(self, sample, dt: float) -> Tuple[np.ndarray, np.ndarray]:
        """One sample (C,) -> (quat (4,), omega (3,))."""
        x = _one_sample(self, sample, dt)
        if self._state is None:
            self._start(x[0])
        _backbone_steps(x, self._dt1, self._no_feats, self._nparams, self._wts, self._ints, self._rings, self._p,
                        self._state, self._coeff, self._knobs, self._m_conj, self._out1)
        return self._out1[0, 0:4].copy(), self._out1[0, 4:7].copy()

    def step_chunk(self, samples, dt: Union[float, np.ndarray]) -> Tuple[np.ndarray, np.ndarray]:
        """k samples (k, C) -> (quat (k, 4), omega (k, 3)): what k calls of :meth:`step` return."""
        xs, dts = _chunk(self, samples, dt)
        if xs.shape[0] == 0:
            return np.zeros((0, 4)), np.zeros((0, 3))
        if self._state is None:
            self._start(xs[0])
        feats = self._no_feats
        if xs.shape[0] >= self.chunk_networks:
            with torch.no_grad():
                feats = _ring_convolutions()(torch.from_numpy(xs), int(self._knobs[9]), self._views,
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
        CompiledStreaming._quat0(q0)
        self.reset(q0)
        return self.step_chunk(xs, dts)
