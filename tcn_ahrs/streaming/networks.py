"""The networks of the streaming runtimes, per sample on ring buffers, compiled by numba: the
folded TCNs (laid out as flat arrays by :func:`tcn_ahrs.export.flat.flat_networks`) and the
head, shared by the closed loop (:mod:`tcn_ahrs.streaming.closed_loop`) and the residual model
(:mod:`tcn_ahrs.streaming.backbone`); a chunk of samples runs as convolutions instead
(:func:`scripted_ring_convolutions`), advancing the same ring buffers.
"""
from __future__ import annotations

import numpy as np
import torch

from ..export.flat import ERF_P, ERF_Q, LAYOUT_HEADER, LAYOUT_PER_LAYER, erf_rational, flat_networks  # noqa: F401
from ..model.closed_loop_compiled import AVAILABLE

if AVAILABLE:
    import numba

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


_SCRIPTED = {}


def scripted_ring_convolutions():
    """:func:`tcn_ahrs.export.fused.ring_convolutions`, scripted once (TorchScript runs its
    ~40 small tensor ops ~5x faster than eager dispatch)."""
    if "ring" not in _SCRIPTED:
        from ..export.fused import ring_convolutions

        _SCRIPTED["ring"] = torch.jit.script(ring_convolutions)
    return _SCRIPTED["ring"]
