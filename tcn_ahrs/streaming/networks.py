"""The networks of the streaming runtimes, per sample on ring buffers, compiled by numba: the
folded TCNs (:func:`flat_networks` lays out an exported streaming module's weights as flat
arrays) and the head, shared by the closed loop (:mod:`tcn_ahrs.streaming.closed_loop`) and the
residual model (:mod:`tcn_ahrs.streaming.backbone`); a chunk of samples runs as convolutions
instead (:func:`scripted_ring_convolutions`), advancing the same ring buffers.
"""
from __future__ import annotations

import numpy as np
import torch

from ..model.closed_loop_compiled import AVAILABLE

if AVAILABLE:
    import numba

# ints: header, then 8 entries per convolution layer (weights (groups, c_out, k c_in), taps oldest first), then the head's 3 offsets
LAYOUT_HEADER = 8          # C, K, layers, window, use_acc, use_mag, H (features), rows of the head (C + 2)
LAYOUT_PER_LAYER = 8       # groups, c_in, c_out (per group), dilation, span, weight offset, bias offset, ring offset

# erf(x) = x P(x²) / Q(x²) on [-4, 4] (±1 beyond), |error| < 7e-8 against math.erf (tested): the
# rational form of Eigen's float32 erf; a polynomial and a division vectorise, a libm call does not
# (math.erf was half of the networks' time: 288 calls per sample)
ERF_P = (-2.72614225801306e-10, 2.77068142495902e-08, -2.10102402082508e-06, -5.69250639462346e-05,
          -7.34990630326855e-04, -2.95459980854025e-03, -1.60960333262415e-02)
ERF_Q = (-1.45660718464996e-05, -2.13374055278905e-04, -1.68282697438203e-03, -7.37332916720468e-03,
          -1.42647390514189e-02)


def erf_rational(x: float) -> float:
    """erf(x) to 7e-8 absolute (see ERF_P)."""
    x = min(max(x, -4.0), 4.0)
    x2 = x * x
    p = ERF_P[0]
    for c in ERF_P[1:]:
        p = p * x2 + c
    q = ERF_Q[0]
    for c in ERF_Q[1:]:
        q = q * x2 + c
    return x * p / q


if AVAILABLE:
    _erf = numba.njit(cache=True, inline="always")(erf_rational)

    @numba.njit(cache=True, fastmath=True, error_model="numpy")
    def networks_step(x, t, feats_k, params, wts, ints, rings, h_in, h_out, tap, pre, v):  # pragma: no cover
        """One sample x (C,) at time t through the networks (ring buffers (groups, span, c_in),
        float32 as the exported module's; the newest input written at row t mod span) — or its
        features feats_k (H,) when given (non-empty) — and the head into v: [M y − (W h + b) ;
        −trust logits]. fastmath (reassociation, so the dot products vectorise) is confined to
        this function; the filter code stays exact."""
        c, kk, nl, n_feat, n_head = ints[0], ints[1], ints[2], ints[6], ints[7]
        hw, hb, hm = ints[LAYOUT_HEADER + LAYOUT_PER_LAYER * nl], ints[LAYOUT_HEADER + LAYOUT_PER_LAYER * nl + 1], ints[LAYOUT_HEADER + LAYOUT_PER_LAYER * nl + 2]
        n_in = c
        for i in range(c):
            h_in[i] = x[i]
        nl_run = nl
        if feats_k.shape[0] > 0:
            for i in range(n_feat):
                h_in[i] = feats_k[i]
            nl_run = 0
        for li in range(nl_run):
            base = LAYOUT_HEADER + LAYOUT_PER_LAYER * li
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
    def scratch(ints):  # pragma: no cover - compiled
        """The per-call work arrays of :func:`networks_step` for the layout ``ints``: layer inputs and
        outputs (float64), taps and pre-activations (float32), the head's rows."""
        width = ints[0]
        for li in range(ints[2]):
            width = max(width, ints[LAYOUT_HEADER + LAYOUT_PER_LAYER * li] * ints[LAYOUT_HEADER + LAYOUT_PER_LAYER * li + 2])
        return (np.empty(max(width, ints[6])), np.empty(max(width, ints[6])),
                np.empty(ints[1] * width, dtype=np.float32), np.empty(width, dtype=np.float32), np.empty(ints[7]))


def flat_networks(ts, head_weight, head_bias, head_matrix, window: int = 1, use_acc: bool = False,
                   use_mag: bool = False):
    """The folded networks of an exported streaming module ``ts`` (:class:`StreamingAHRS`) as the
    flat arrays :func:`networks_step` reads: float32 weights, float64 head ``[M y − (W h + b)]`` rows,
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


def scripted_ring_convolutions():
    """:func:`tcn_ahrs.export.fused.ring_convolutions`, scripted once (TorchScript runs its
    ~40 small tensor ops ~5x faster than eager dispatch)."""
    if "ring" not in _SCRIPTED:
        from ..export.fused import ring_convolutions

        _SCRIPTED["ring"] = torch.jit.script(ring_convolutions)
    return _SCRIPTED["ring"]
