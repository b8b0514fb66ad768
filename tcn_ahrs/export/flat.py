"""The folded networks of an exported streaming module as flat arrays (weights, head rows, an int
layout, ring buffers) and the rational erf they use: what the compiled per-sample runtimes
(:mod:`tcn_ahrs.streaming.networks`, numba) and the C runtime (:mod:`tcn_ahrs.export.c`) read.
"""
from __future__ import annotations

import numpy as np
import torch

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
