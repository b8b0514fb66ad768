"""The closed loop compiled by numba: the loop (:func:`scan_numba`, evaluation), the loop with its
reverse pass (:class:`ScanFunction`, CPU training). The per-sample functions are
:mod:`tcn_ahrs.kernels.closed_loop`'s, compiled as they are; ``tests/test_closed_loop_step.py``
holds these equal to the tensor scan and to autograd through it.

numba is optional (the ``[fast]`` extra, in ``[dev]``): without it ``AVAILABLE`` is False and
:meth:`~tcn_ahrs.model.closed_loop.ClosedLoopFilter._scan` runs the tensor scan.
"""
from typing import Tuple

import numpy as np
import torch
from torch import Tensor

from ..kernels import closed_loop as scalar
from ..kernels.quat import matrix_to_quat_nb  # noqa: F401 (re-exported: compiled by the kernel layer)
from .closed_loop_step import OUT

try:
    import numba

    # the per-sample functions, compiled once for every numba kernel of the project
    _jit = numba.njit(cache=True, inline="always")
    update_nb = _jit(scalar.closed_loop_update)
    rest_update_nb = _jit(scalar.rest_update)
    repeat_count_nb = _jit(scalar.repeat_count)
    gap_step_nb = _jit(scalar.gap_step)
    loop_inputs_nb = _jit(scalar.loop_inputs)
    east_reference_nb = _jit(scalar.east_reference_scalar)
    AVAILABLE = True
except ImportError:  # pragma: no cover - the tensor scan is used instead
    numba = None
    AVAILABLE = False


if AVAILABLE:
    @numba.njit(cache=True, parallel=True)
    def _scan_nb(state, rows, east_ref, bias_gain, out):  # pragma: no cover - compiled
        """state (B, 12), rows (B, N, 13), east_ref (B, 3) -> out (B, N, 15) (row 0 = the state)."""
        for b in numba.prange(rows.shape[0]):
            s = state[b]
            r00, r01, r02, r10, r11, r12 = s[0], s[1], s[2], s[3], s[4], s[5]
            r20, r21, r22, b0, b1, b2 = s[6], s[7], s[8], s[9], s[10], s[11]
            c0 = c1 = c2 = 0.0
            e0, e1, e2 = east_ref[b, 0], east_ref[b, 1], east_ref[b, 2]
            for k in range(rows.shape[1]):
                if k > 0:
                    x = rows[b, k]
                    (r00, r01, r02, r10, r11, r12, r20, r21, r22, b0, b1, b2, c0, c1, c2) = update_nb(
                        r00, r01, r02, r10, r11, r12, r20, r21, r22, b0, b1, b2, x[0], x[1], x[2], x[3], x[4],
                        x[5], x[6], x[7], x[8], x[9], x[10], x[11], e0, e1, e2, x[12], bias_gain)
                o = out[b, k]
                o[0], o[1], o[2], o[3], o[4], o[5], o[6], o[7], o[8] = r00, r01, r02, r10, r11, r12, r20, r21, r22
                o[9], o[10], o[11], o[12], o[13], o[14] = b0, b1, b2, c0, c1, c2


if AVAILABLE:
    @numba.njit(cache=True)
    def _rows_vjp(r, rbar, rprev, p0, p1, p2, t2, a, c):  # pragma: no cover
        """One step's rows r_i' = r_i + a k_i + c (k_i × p), k_i = r_i × p (so3's series a, c of
        t2 = |p|²) in reverse: rbar (3, 3) their adjoint -> rprev (3, 3) the rows' (written) and
        the adjoint of p (returned)."""
        abar = cbar = 0.0
        pb0 = pb1 = pb2 = 0.0
        for i in range(3):
            k0 = r[i, 1] * p2 - r[i, 2] * p1
            k1 = r[i, 2] * p0 - r[i, 0] * p2
            k2 = r[i, 0] * p1 - r[i, 1] * p0
            q0, q1, q2 = rbar[i, 0], rbar[i, 1], rbar[i, 2]
            abar += q0 * k0 + q1 * k1 + q2 * k2
            cbar += q0 * (k1 * p2 - k2 * p1) + q1 * (k2 * p0 - k0 * p2) + q2 * (k0 * p1 - k1 * p0)
            # adjoint of k_i: a q + c (p × q); of p through (k × p): c (q × k)
            kb0 = a * q0 + c * (p1 * q2 - p2 * q1)
            kb1 = a * q1 + c * (p2 * q0 - p0 * q2)
            kb2 = a * q2 + c * (p0 * q1 - p1 * q0)
            pb0 += c * (q1 * k2 - q2 * k1)
            pb1 += c * (q2 * k0 - q0 * k2)
            pb2 += c * (q0 * k1 - q1 * k0)
            # k = r × p: adjoint of r: p × kb; of p: kb × r
            rprev[i, 0] = q0 + (p1 * kb2 - p2 * kb1)
            rprev[i, 1] = q1 + (p2 * kb0 - p0 * kb2)
            rprev[i, 2] = q2 + (p0 * kb1 - p1 * kb0)
            pb0 += kb1 * r[i, 2] - kb2 * r[i, 1]
            pb1 += kb2 * r[i, 0] - kb0 * r[i, 2]
            pb2 += kb0 * r[i, 1] - kb1 * r[i, 0]
        da = -1.0 / 6.0 + t2 / 60.0 - t2 * t2 / 1680.0
        dc = -1.0 / 24.0 + t2 / 360.0 - t2 * t2 / 13440.0
        tb = abar * da + cbar * dc
        pb0 += 2.0 * tb * p0
        pb1 += 2.0 * tb * p1
        pb2 += 2.0 * tb * p2
        return pb0, pb1, pb2

    @numba.njit(cache=True, parallel=True)
    def _scan_vjp_nb(state, rows, east_ref, bias_gain, out, gout, g_state, g_rows, g_east, g_kb):  # pragma: no cover
        """Reverse mode of :func:`_scan_nb`: out (B, N, 15) its outputs, gout (B, N, 15) the
        gradients of the loss w.r.t. them -> g_state (B, 12), g_rows (B, N, 13), g_east (B, 3),
        g_kb (B,). Runs k = N-1 .. 1, carrying the adjoint of (C, b); each step recomputes its
        forward intermediates from the stored state before it. Derivatives of
        :func:`closed_loop_update`, written out (``tests/test_closed_loop_step.py`` checks them
        against autograd through the tensor scan)."""
        for bi in numba.prange(rows.shape[0]):
            r = np.empty((3, 3))
            rbar = np.empty((3, 3))   # adjoint of C after the step (output grad + carried)
            rprev = np.zeros((3, 3))  # adjoint of C before the step
            lam = np.zeros(12)        # carried adjoint of (C, b)
            e0, e1, e2 = east_ref[bi, 0], east_ref[bi, 1], east_ref[bi, 2]
            ge0 = ge1 = ge2 = gkb = 0.0
            for k in range(rows.shape[1] - 1, 0, -1):
                x = rows[bi, k]
                gx, gy, gz, ax, ay, az = x[0], x[1], x[2], x[3], x[4], x[5]
                mx, my, mz, ka, km, kr, dt = x[6], x[7], x[8], x[9], x[10], x[11], x[12]
                prev = out[bi, k - 1]
                for i in range(3):
                    for j in range(3):
                        r[i, j] = prev[3 * i + j]
                        rbar[i, j] = gout[bi, k, 3 * i + j] + lam[3 * i + j]
                b0, b1, b2 = prev[9], prev[10], prev[11]
                bb0, bb1, bb2 = gout[bi, k, 9] + lam[9], gout[bi, k, 10] + lam[10], gout[bi, k, 11] + lam[11]
                cb0, cb1, cb2 = gout[bi, k, 12], gout[bi, k, 13], gout[bi, k, 14]
                # ---- forward intermediates (as closed_loop_update)
                u0, u1, u2 = r[2, 0], r[2, 1], r[2, 2]
                xa0, xa1, xa2 = ay * u2 - az * u1, az * u0 - ax * u2, ax * u1 - ay * u0   # â × u
                v0 = e0 * r[0, 0] + e1 * r[1, 0] + e2 * r[2, 0]
                v1 = e0 * r[0, 1] + e1 * r[1, 1] + e2 * r[2, 1]
                v2 = e0 * r[0, 2] + e1 * r[1, 2] + e2 * r[2, 2]
                xm0, xm1, xm2 = my * v2 - mz * v1, mz * v0 - mx * v2, mx * v1 - my * v0   # east_b × v
                c0, c1, c2 = ka * xa0 + km * xm0, ka * xa1 + km * xm1, ka * xa2 + km * xm2
                n0 = b0 - bias_gain * c0 * dt + kr * (gx - b0)
                n1 = b1 - bias_gain * c1 * dt + kr * (gy - b1)
                n2 = b2 - bias_gain * c2 * dt + kr * (gz - b2)
                w0, w1, w2 = gx - n0 + c0, gy - n1 + c1, gz - n2 + c2
                p0, p1, p2 = w0 * dt, w1 * dt, w2 * dt
                t2 = p0 * p0 + p1 * p1 + p2 * p2
                a = 1.0 - t2 / 6.0 * (1.0 - t2 / 20.0 * (1.0 - t2 / 42.0))
                c = 0.5 - t2 / 24.0 * (1.0 - t2 / 30.0 * (1.0 - t2 / 56.0))
                pb0, pb1, pb2 = _rows_vjp(r, rbar, rprev, p0, p1, p2, t2, a, c)
                # ---- p = (g − b' + w) dt
                gg0, gg1, gg2 = pb0 * dt, pb1 * dt, pb2 * dt
                bb0 -= pb0 * dt
                bb1 -= pb1 * dt
                bb2 -= pb2 * dt
                cb0 += pb0 * dt
                cb1 += pb1 * dt
                cb2 += pb2 * dt
                gdt = pb0 * w0 + pb1 * w1 + pb2 * w2
                # ---- b' = b (1 − kr) − kb dt w + kr g
                bc = bb0 * c0 + bb1 * c1 + bb2 * c2
                gkb -= dt * bc
                gdt -= bias_gain * bc
                gkr = bb0 * (gx - b0) + bb1 * (gy - b1) + bb2 * (gz - b2)
                gg0 += kr * bb0
                gg1 += kr * bb1
                gg2 += kr * bb2
                cb0 -= bias_gain * dt * bb0
                cb1 -= bias_gain * dt * bb1
                cb2 -= bias_gain * dt * bb2
                lam[9], lam[10], lam[11] = bb0 * (1.0 - kr), bb1 * (1.0 - kr), bb2 * (1.0 - kr)
                # ---- w = ka (â × u) + km (east_b × v)
                gka = cb0 * xa0 + cb1 * xa1 + cb2 * xa2
                gkm = cb0 * xm0 + cb1 * xm1 + cb2 * xm2
                g_rows[bi, k, 3] = ka * (u1 * cb2 - u2 * cb1)
                g_rows[bi, k, 4] = ka * (u2 * cb0 - u0 * cb2)
                g_rows[bi, k, 5] = ka * (u0 * cb1 - u1 * cb0)
                rprev[2, 0] += ka * (cb1 * az - cb2 * ay)
                rprev[2, 1] += ka * (cb2 * ax - cb0 * az)
                rprev[2, 2] += ka * (cb0 * ay - cb1 * ax)
                g_rows[bi, k, 6] = km * (v1 * cb2 - v2 * cb1)
                g_rows[bi, k, 7] = km * (v2 * cb0 - v0 * cb2)
                g_rows[bi, k, 8] = km * (v0 * cb1 - v1 * cb0)
                vb0, vb1, vb2 = km * (cb1 * mz - cb2 * my), km * (cb2 * mx - cb0 * mz), km * (cb0 * my - cb1 * mx)
                for j in range(3):
                    rprev[0, j] += e0 * (vb0 if j == 0 else (vb1 if j == 1 else vb2))
                    rprev[1, j] += e1 * (vb0 if j == 0 else (vb1 if j == 1 else vb2))
                    rprev[2, j] += e2 * (vb0 if j == 0 else (vb1 if j == 1 else vb2))
                ge0 += r[0, 0] * vb0 + r[0, 1] * vb1 + r[0, 2] * vb2
                ge1 += r[1, 0] * vb0 + r[1, 1] * vb1 + r[1, 2] * vb2
                ge2 += r[2, 0] * vb0 + r[2, 1] * vb1 + r[2, 2] * vb2
                g_rows[bi, k, 0], g_rows[bi, k, 1], g_rows[bi, k, 2] = gg0, gg1, gg2
                g_rows[bi, k, 9], g_rows[bi, k, 10], g_rows[bi, k, 11], g_rows[bi, k, 12] = gka, gkm, gkr, gdt
                for i in range(3):
                    for j in range(3):
                        lam[3 * i + j] = rprev[i, j]
            for i in range(12):
                g_state[bi, i] = gout[bi, 0, i] + lam[i]
            g_east[bi, 0], g_east[bi, 1], g_east[bi, 2] = ge0, ge1, ge2
            g_kb[bi] = gkb


class ScanFunction(torch.autograd.Function):
    """:func:`~tcn_ahrs.model.closed_loop.closed_loop_scan` with a compiled forward
    (:func:`_scan_nb`) and a compiled reverse pass (:func:`_scan_vjp_nb`), float64 inside: what
    training runs on the CPU. The tensor scan costs ~25 autograd nodes per sample forward and
    again backward — ~60 % of a training step; this costs ~1 µs per sample both ways."""

    @staticmethod
    def forward(ctx, rot, bias, gyro, acc_unit, east_b, acc_gain, mag_gain, rest_gain, east_ref, dt, bias_gain):
        rows = torch.cat([gyro, acc_unit, east_b, acc_gain, mag_gain, rest_gain, dt], -1).detach().double()
        rows = np.ascontiguousarray(rows.numpy())
        state = np.ascontiguousarray(torch.cat([rot.reshape(-1, 9), bias], -1).detach().double().numpy())
        ref = np.array(east_ref.detach().double().numpy(), copy=True)  # kept for backward: no view
        b, n = rows.shape[0], rows.shape[1]
        out = np.empty((b, n, OUT))
        kb = float(bias_gain)
        _scan_nb(state, rows, ref, kb, out)
        ctx.saved = (state, rows, ref, kb, out)
        ctx.dtypes = (rot.dtype, bias_gain.dtype, bias_gain.shape)
        o = torch.from_numpy(out).to(gyro.dtype)
        return o[..., 0:9].reshape(b, n, 3, 3), o[..., 9:12].contiguous(), o[..., 12:15].contiguous()

    @staticmethod
    def backward(ctx, g_rot, g_bias, g_corr):
        state, rows, ref, kb, out = ctx.saved
        b, n = rows.shape[0], rows.shape[1]
        gout = np.zeros((b, n, OUT))
        if g_rot is not None:
            gout[..., 0:9] = g_rot.detach().double().reshape(b, n, 9).numpy()
        if g_bias is not None:
            gout[..., 9:12] = g_bias.detach().double().numpy()
        if g_corr is not None:
            gout[..., 12:15] = g_corr.detach().double().numpy()
        g_state, g_rows = np.zeros((b, 12)), np.zeros((b, n, 13))
        g_east, g_kb = np.zeros((b, 3)), np.zeros(b)
        _scan_vjp_nb(state, rows, ref, kb, out, gout, g_state, g_rows, g_east, g_kb)
        dt_, kb_dtype, kb_shape = ctx.dtypes
        gs, gr = torch.from_numpy(g_state).to(dt_), torch.from_numpy(g_rows).to(dt_)
        return (gs[:, 0:9].reshape(b, 3, 3), gs[:, 9:12], gr[..., 0:3], gr[..., 3:6], gr[..., 6:9], gr[..., 9:10],
                gr[..., 10:11], gr[..., 11:12], torch.from_numpy(g_east).to(dt_), gr[..., 12:13],
                torch.tensor(float(g_kb.sum()), dtype=kb_dtype).reshape(kb_shape))


def scan_numba(rot: Tensor, bias: Tensor, gyro: Tensor, acc_unit: Tensor, east_b: Tensor, acc_gain: Tensor,
               mag_gain: Tensor, rest_gain: Tensor, east_ref: Tensor, dt: Tensor, bias_gain: Tensor
               ) -> Tuple[Tensor, Tensor, Tensor]:
    """:func:`~tcn_ahrs.model.closed_loop.closed_loop_scan` (same arguments and returns, CPU, no
    gradient) compiled by numba, float64 inside, returned in gyro's dtype; batch entries run in
    parallel threads."""
    rows = torch.cat([gyro, acc_unit, east_b, acc_gain, mag_gain, rest_gain, dt], -1).detach()
    state = torch.cat([rot.reshape(-1, 9), bias], -1).detach()
    b, n = gyro.shape[0], gyro.shape[1]
    out = np.empty((b, n, OUT))
    _scan_nb(np.ascontiguousarray(state.double().numpy()), np.ascontiguousarray(rows.double().numpy()),
             np.ascontiguousarray(east_ref.detach().double().numpy()), float(bias_gain), out)
    o = torch.from_numpy(out).to(gyro.dtype)
    return o[..., 0:9].reshape(b, n, 3, 3), o[..., 9:12], o[..., 12:15]


