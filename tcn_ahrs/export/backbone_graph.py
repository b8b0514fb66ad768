"""The backbone's step (:mod:`tcn_ahrs.kernels.backbone`) on vectors, for the exported step graphs
(ONNX, ``torch.export``): the same state, coefficients and decisions, written with as few graph
nodes as the equations allow, because ONNX Runtime pays per node (~1 µs each on small float64
tensors here, whatever the op), not per flop. The kernel read on scalars was ~2,400 ONNX nodes a
sample; this reading is ~570 (broad9's whole step with its networks: 2,672 -> 707 nodes, its
start and its coefficients as branches of their own: :class:`tcn_ahrs.export.stateless.ResidualStep`).

What changes is the reading, not the filter (tests/test_backbone_graph.py holds the state after
every sample equal to the kernel's to 1e-10 relative, 5e-12 measured, with rest, gaps, a frozen
and a clipped sensor, the magnetometer's rejection cycle and skipped samples):

* the attitude quaternions are vectors; the Hamilton product and the rotation matrix are
  contractions with the constant tensors of :mod:`tcn_ahrs.export.classical_step` (read off
  :mod:`tcn_ahrs.so3`);
* every low-pass filter that can run at once runs as one vector (the rest detectors' gyro and
  accelerometer; the accelerometer in I_i; the rotation matrix, the rotated bias and the field's
  norm and dip), each component with its group's coefficients and averaging phase;
* the two sensors' health checks (frozen, clipped) run as one (2, 3) array;
* the bias Kalman filter (Sec. 3.4) is matrix algebra on (3, 3) tensors, S^-1 by cofactors;
* the state is read through a few index gathers and written once (one gather over [state,
  new values]); the accelerometer's and magnetometer's parts are put back where their reading
  is [0 0 0] (the batch loop skips it, as VQF).

Flags and switches that are parameters (``rest_bias``, ``mag_rejection``, ...) decide the graph
when it is built, as the kernel's ``if p[...]`` does.
"""
from __future__ import annotations

import math
from typing import Dict, List, Optional, Sequence, Tuple

import torch
from torch import Tensor, nn

from ..kernels import backbone as K
from ..kernels import backbone_gains
from ..kernels.backbone_layout import BackboneParams
from ..kernels.ops import load_kernel
from .check_graph import SUMS, check_step
from .classical_step import hamilton, quat_product, rotation_matrix, rotation_rows
from .graph_state import HEALTH_INDEX, MAG_SCALARS, Writes, filter_index, plan_buffers

F64 = torch.float64
# the low-pass coefficient rows (b0, b1, b2, -a1, -a2) this graph computes from dt, by filter kind
_ACC, _REST, _MAG = 0, 1, 2
N_LOWPASS, N_GAINS, N_BIAS_NOISE = 3, 2, 4   # those rows; k_mag and k_mag_ref; V, W_motion, W_vertical, W_rest
# BackboneGraph.coefficients: [dt, the low-pass rows, the gains, the bias filter's noise]
_ROWS = slice(1, 1 + 5 * N_LOWPASS)
_GAINS = slice(_ROWS.stop, _ROWS.stop + N_GAINS)
_NOISE = slice(_GAINS.stop, _GAINS.stop + N_BIAS_NOISE)
N_COEFF_GRAPH = _NOISE.stop


class BackboneGraph(nn.Module):
    """One backbone step on a flat state (``kernels/backbone_layout.STATE``)::

        s' = step(s (N_STATE,), gyro (3,), acc (3,), mag (3,), dt (), acc_trust (),
                  mag_trust (), bias_trust (), skip_acc (), skip_mag ())

    float64; gyro the rate fed to the filter (rad/s, body), acc the specific force (m/s²), mag
    the field (µT; any (3,) without a magnetometer); ``skip_*``: that reading is [0 0 0] (its
    update is not applied). ``quat(s)``: the output attitude (6D or 9D), nav_from_body. ``ops``:
    the table whose tan and atan2 the graph uses (:func:`tcn_ahrs.kernels.ops.onnx_ops` for
    ONNX Runtime)."""

    def __init__(self, params: Sequence[float], use_mag: bool, ops):
        super().__init__()
        p = [float(v) for v in params]
        self.p, self.use_mag, self.T = p, bool(use_mag), ops
        # the coefficients' and gains' formulas: the kernel's own (kernels/backbone_gains.py), read
        # with this graph's ops table on (K,) tensors
        self.G = load_kernel(backbone_gains, ops)
        self.noise = (p[K.P_SIGMA_INIT], p[K.P_FORGET], p[K.P_SIGMA_MOTION], p[K.P_VERT_FORGET], p[K.P_SIGMA_REST])
        self.p0 = float(backbone_gains.bias_noise(*self.noise, 1.0)[0])   # P0: the same at every step
        self.register_buffer("p_diag", torch.tensor([K.S_P, K.S_P + 4, K.S_P + 8]))   # the bias variances
        self.rest_bias = p[K.P_REST_BIAS] > 0.5
        self.mag_rej = p[K.P_MAG_REJ] > 0.5
        self.motion = p[K.P_MOTION_BIAS] > 0.5
        self.rest_gyro = self.rest_bias or self.mag_rej
        self.check = p[K.P_REST_CHECK] > 0.5   # the causal device check (export/check_graph.py)
        self.register_buffer("check_sums", torch.tensor(SUMS))
        self.bias = self.motion or self.rest_bias
        self.mag_lp = self.use_mag and self.mag_rej and p[K.P_MAG_CUR_TAU] > 0.0
        ham = hamilton().permute(0, 2, 1).reshape(16, 4)   # (ham @ p).reshape(4, 4) @ q = p ⊗ q
        self.register_buffer("ham", ham)
        self.register_buffer("matrix", rotation_rows((0, 1, 2)))
        taus = [p[K.P_TAU_ACC], p[K.P_REST_TAU], max(p[K.P_MAG_CUR_TAU], K.TAU_FLOOR)]
        self.register_buffer("taus", torch.tensor(taus, dtype=F64))
        self.register_buffer("thru_row", torch.tensor([1.0, 0.0, 0.0, 0.0, 0.0], dtype=F64))
        self.register_buffer("gain_taus", torch.tensor([p[K.P_TAU_MAG], p[K.P_MAG_REF_TAU]], dtype=F64))
        floors = [p[K.P_GCLIP_FLOOR], p[K.P_ACLIP_FLOOR]]
        # a floor <= 0 switches the clip check off: no reading reaches +inf
        self.register_buffer("clip_floor", torch.tensor([[f if f > 0.0 else math.inf] for f in floors], dtype=F64))
        self.register_buffer("eye3", torch.eye(3, dtype=F64))
        self.register_buffer("heading_dip", torch.tensor([0, 2]))   # atan2's numerators: m_x, m_z
        self.register_buffer("lp_running", torch.tensor([0, 1, 5, 3]))   # rows of lowpass's pool: x, x1, y, y1
        self.register_buffer("lp_fresh", torch.tensor([6, 7, 7, 7]))     # total, 0, 0, 0
        self.register_buffer("false", torch.zeros((), dtype=torch.bool))
        self.register_buffer("scalars", torch.tensor([K.S_TS_TYP, K.S_GFROZEN, K.S_HEAD_RESTART, K.S_KMINIT, K.S_REST,
                                                      K.S_REST_T]))
        self.register_buffer("mag_scalars", torch.tensor(MAG_SCALARS))
        th_norm, th_dip = p[K.P_MAG_NORM_TH], p[K.P_MAG_DIP_TH] * K.DEG
        self.register_buffer("mag_th_scale", torch.tensor([[th_norm, 0.0], [th_norm, 0.0]], dtype=F64))
        self.register_buffer("mag_th_add", torch.tensor([[0.0, th_dip], [0.0, th_dip]], dtype=F64))
        # the bias filter's constants: y's rows from v and bl, W's entries in bias_c, P's diagonal,
        # the cofactors' entries of S (row i: S_{i+1} x S_{i+2}, indices mod 3) in S.reshape(9)
        self.register_buffer("perp", torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=F64))
        self.register_buffer("pad2", torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]], dtype=F64))
        self.register_buffer("w_motion", torch.tensor([1, 1, 2]))
        self.register_buffer("w_rest", torch.tensor([3, 3, 3]))
        self.register_buffer("diag9", torch.tensor([i in (0, 4, 8) for i in range(9)]))
        nxt = [1, 2, 0]
        cof = [[[(3 * nxt[i] + nxt[j], 3 * nxt[nxt[i]] + nxt[nxt[j]], 3 * nxt[i] + nxt[nxt[j]],
                  3 * nxt[nxt[i]] + nxt[j])[q] for j in range(3)] for i in range(3)] for q in range(4)]
        self.register_buffer("cof", torch.tensor(cof))
        # [c, s] -> [c, 0, 0, s] (a turn about up), [c, x, y] -> [c, x, y, 0] (about a horizontal axis)
        self.register_buffer("mag_axis", torch.tensor([[1.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 1.0]], dtype=F64))
        self.register_buffer("acc_axes", torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0],
                                                       [0.0, 0.0, 1.0, 0.0]], dtype=F64).T.contiguous())
        # the health checks' state, both sensors: (2, 3) and (2,) index arrays
        self.register_buffer("h_prev", torch.tensor([[K.S_GPREV + i for i in range(3)],
                                                     [K.S_APREV + i for i in range(3)]]))
        self.register_buffer("h_max", torch.tensor([[K.S_GMAX + i for i in range(3)],
                                                    [K.S_AMAX + i for i in range(3)]]))
        self.register_buffer("h_run", torch.tensor([[K.S_GMAX + 3 + i for i in range(3)],
                                                    [K.S_AMAX + 3 + i for i in range(3)]]))
        self.register_buffer("h_same", torch.tensor([[K.S_GSAME_T, K.S_ASAME_T], [K.S_GSAME_N, K.S_ASAME_N]]))
        # the low-pass calls: which groups run together, and each component's group and coefficient row
        self._lp: Dict[str, Dict[str, str]] = {}
        self._lp_index: Dict[str, Tuple[List[int], List[int]]] = {}
        calls = {"rest": [(K.F_RG, 3, _REST)] * self.rest_gyro + [(K.F_RA, 3, _REST)] * self.rest_bias,
                 "acc": [(K.F_ACC, 3, _ACC)],
                 "att": [(K.F_ROT, 9, _ACC), (K.F_BIAS, 2, _ACC)] * self.bias + [(K.F_MAG, 2, _MAG)] * self.mag_lp}
        for name, groups in calls.items():
            if groups:
                self._lp_call(name, groups)
        # where the new values go: the order in which a step writes them (the same every step),
        # recorded once on an example, as constant index buffers (a graph inside a scan cannot
        # build tensors)
        self.plan: List[int] = []
        for name, v in (("write_index", [0]), ("write_acc", [False]), ("write_mag", [False]), ("write_perm", [0])):
            self.register_buffer(name, torch.tensor(v))
        z = torch.zeros((), dtype=F64)
        with torch.no_grad():
            self(torch.tensor(K.initial_state(BackboneParams()), dtype=F64), torch.zeros(3, dtype=F64),
                 torch.tensor([0.0, 0.0, 9.81], dtype=F64), torch.tensor([20.0, 0.0, -40.0], dtype=F64),
                 z + 0.01, z + 1.0, z + 1.0, z + 1.0, self.false, self.false, None, True)

    def _lp_call(self, name: str, groups: List[Tuple[int, int, int]]) -> None:
        """Index buffers of one low-pass call: per component its group's (running, count) indices
        (2, D), its memory (4, D), its coefficients' places in the (3, 5) rows (5, D) and its
        group's tau (D,); per group its first component (the group's flags are written from it)."""
        flags, memory, coef, tau, first = [[], []], [[], [], [], []], [[] for _ in range(5)], [], []
        for f, d, row in groups:
            first.append(len(tau))
            fl, mem = filter_index(f, d)
            for r in range(2):
                flags[r] += [fl[r]] * d
            for r in range(4):
                memory[r] += mem[r * d:(r + 1) * d]
            for j in range(5):
                coef[j] += [5 * row + j] * d
            tau += [(self.p[K.P_TAU_ACC], self.p[K.P_REST_TAU], self.p[K.P_MAG_CUR_TAU])[row]] * d
        n = len(tau)
        bufs = {"flags": torch.tensor(flags), "memory": torch.tensor(memory), "coef": torch.tensor(coef),
                "tau": torch.tensor(tau, dtype=F64), "flag_out": torch.tensor(first + [n + i for i in first])}
        for k, v in bufs.items():
            self.register_buffer(f"lp_{name}_{k}", v)
        self._lp[name] = {k: f"lp_{name}_{k}" for k in bufs}
        self._lp_index[name] = ([f for f, _, _ in groups] + [f + 1 for f, _, _ in groups], memory[0] + memory[1]
                                + memory[2] + memory[3])

    # ---------------------------------------------------------------- helpers
    def _buf(self, call: str, key: str) -> Tensor:
        return getattr(self, self._lp[call][key])

    def mul(self, p: Tensor, q: Tensor) -> Tensor:
        """p ⊗ q (4,)."""
        return quat_product(self.ham, p, q)

    def rot(self, q: Tensor) -> Tensor:
        """The rotation matrix (3, 3) of a unit quaternion q (4,) (q v q* = R v)."""
        return rotation_matrix(self.matrix, q)

    def coefficients(self, dt: Tensor) -> Tensor:
        """(N_COEFF_GRAPH,) at step dt, the kernel's ``coefficients`` (VQF's filterCoeffs and
        gains): [dt, the low-pass rows (3, 5) of the acc / rest / mag filters as b0, b1, b2, -a1,
        -a2, k_mag, k_mag_ref, the bias filter's V, W_motion, W_vertical, W_rest]."""
        b0, a1, a2 = self.G.butter_terms(self.taus, dt)
        rows = torch.stack([b0, 2.0 * b0, b0, -a1, -a2], 1)
        rows = torch.where((self.taus < dt / 2.0)[:, None], self.thru_row, rows)   # the kernel's passthrough
        gains = self.G.first_order_gain(self.gain_taus, dt)
        bias_c = torch.stack(self.G.bias_noise(*self.noise, dt)[1:])
        return torch.cat([dt.reshape(1), rows.reshape(5 * N_LOWPASS), gains, bias_c])

    def lowpass(self, call: str, s: Tensor, x: Tensor, rows: Tensor, dt: Tensor, hold_gap: Tensor,
                writes: "Writes") -> Tensor:
        """The kernel's ``lp_begin``/``lp``/``lp_end`` for every component of a call at once: x (D,)
        -> y (D,); the groups' new flags and memory go to ``writes``. ``rows``: (3, 5) coefficient
        rows with the a's negated; ``hold_gap``: this step is a gap (a running filter holds)."""
        fl = s[self._buf(call, "flags")]                         # (2, D): running, count
        run = fl[0] > 0.5
        n = fl[1] + 1.0
        start = ~run & (n * dt >= self._buf(call, "tau"))
        writes.add(self._lp_index[call][0],
                   torch.cat([(run | start).to(F64), torch.where(run, fl[1], n)])[self._buf(call, "flag_out")])
        mem = s[self._buf(call, "memory")]                       # (4, D): x1, x2, y1, y2
        pool = torch.cat([x[None], mem])                         # x, x1, x2, y1, y2
        y = (rows.reshape(-1)[self._buf(call, "coef")] * pool).sum(0)   # b0 x + b1 x1 + b2 x2 - a1 y1 - a2 y2
        total = x + mem[0]
        mean = total / n
        hold = run & hold_gap
        pool = torch.cat([pool, y[None], total[None], torch.zeros_like(pool[0:1])])
        # memory: running [x, x1, y, y1], starting: the mean, averaging: [sum, 0, 0, 0]; output y1'
        new = torch.where(start, mean, pool[self.lp_fresh])
        new = torch.where(hold, mem, torch.where(run, pool[self.lp_running], new))
        writes.add(self._lp_index[call][1], new)
        return torch.where(run | start, new[2], mean)

    def health(self, s: Tensor, x: Tensor, dt: Tensor, writes: "Writes") -> Tuple[Tensor, Tensor]:
        """The kernel's ``frozen_check`` of both sensors: x (2, 3) (gyro, acc) -> (frozen (2,),
        clipped (2,)) bool; the new health state to ``writes``."""
        prev, mx, run = s[self.h_prev], s[self.h_max], s[self.h_run]
        same_t, same_n = s[self.h_same].unbind(0)              # (2,) each: how long each has repeated
        eq = x == prev
        same = eq.all(1)
        a = torch.abs(x)
        at_max = (a >= mx) & (a >= self.clip_floor)
        run = torch.where(at_max & eq, run + 1.0, torch.zeros_like(a))
        clipped = ~same & (run >= K.CLIP_MIN_REPEATS).any(1)
        t = torch.where(same, same_t + dt, 0.0)
        n = torch.where(same, same_n + 1.0, 0.0)
        ft = self.p[K.P_FROZEN_T]
        frozen = (t >= ft) & (n >= K.FROZEN_MIN_SAMPLES) if ft > 0.0 else torch.zeros_like(same)
        rows = torch.cat([x, torch.maximum(mx, a), run, torch.stack([clipped.to(F64), t, n, frozen.to(F64)], 1)], 1)
        writes.add(HEALTH_INDEX, rows)
        return frozen, clipped

    # ---------------------------------------------------------------- the step
    def forward(self, s: Tensor, gyro: Tensor, acc: Tensor, mag: Tensor, dt: Tensor, acc_trust: Tensor,
                mag_trust: Tensor, bias_trust: Tensor, skip_acc: Tensor, skip_mag: Tensor,
                coeff: Optional[Tensor] = None, plan: bool = False) -> Tensor:
        """``coeff``: :meth:`coefficients` of this dt when the caller keeps them (computed here otherwise)."""
        p = self.p
        coeff = self.coefficients(dt) if coeff is None else coeff
        rows, gains, bias_c = coeff[_ROWS].reshape(N_LOWPASS, 5), coeff[_GAINS], coeff[_NOISE]
        w = Writes()
        sc = s[self.scalars]
        ts_typ, was_frozen, wait0, kminit, rest, rest_t = sc.unbind(0)
        # ---- gyroscope (kernel: gyro_update)
        if p[K.P_GAP_F] > 0.0:
            gap = (ts_typ > 0.0) & (dt > p[K.P_GAP_F] * ts_typ)
        else:
            gap = self.false
        gapf = gap.to(F64)
        ts_typ = torch.where(ts_typ > 0.0, ts_typ + K.TS_TYP_RATE * (dt - ts_typ), dt)
        prev_g = s[K.S_GPREV:K.S_GPREV + 3]
        frozen, clipped = self.health(s, torch.stack([gyro, acc]), dt, w)
        frozen_g, frozen_a = frozen[0], frozen[1]
        wait = torch.where((was_frozen > 0.5) & ~frozen_g, p[K.P_TAU_ACC],
                           torch.where(wait0 > 0.0, wait0 - dt, wait0))
        kminit = torch.where((wait0 > 0.0) & (wait <= 0.0), 1.0, kminit)
        w.add([K.S_TS_TYP, K.S_GAP, K.S_HEAD_RESTART], torch.stack([ts_typ, gapf, wait]))
        rest_g, chk = s[K.S_REST_G:K.S_REST_G + 3], s[K.S_CHK:K.S_CHK + 3]  # chk: the check's bias (0 without it)
        if self.rest_gyro:
            lx = torch.cat([gyro, acc]) if self.rest_bias else gyro
            lr = self.lowpass("rest", s, lx, rows, dt, gap, w)
            rest_g = lr[0:3]
            dg = gyro - rest_g
            clip = p[K.P_CLIP] * K.DEG
            moving = frozen_g | ((dg * dg).sum() >= (p[K.P_REST_TH_G] * K.DEG) ** 2) | (torch.abs(rest_g - chk) > clip).any()
            rest_t, rest = torch.where(moving, 0.0, rest_t), torch.where(moving, 0.0, rest)
            w.add([K.S_REST_G + i for i in range(3)], rest_g)
        bias = s[K.S_BIAS:K.S_BIAS + 3]
        om = torch.where(gap, 0.5 * (gyro + prev_g), gyro) - bias
        norm = torch.sqrt((om * om).sum() + 1e-300)
        turn = (norm > K.EPS) & ~frozen_g
        half = norm * dt / 2.0
        k = torch.sin(half) / torch.where(turn, norm, 1.0)
        gq = s[K.S_GQ:K.S_GQ + 4]
        q = self.mul(gq, torch.cat([torch.cos(half).reshape(1), k * om]))
        gq = torch.where(turn, q / torch.sqrt((q * q).sum()), gq)
        w.add(list(range(K.S_GQ, K.S_GQ + 4)), gq)
        # ---- accelerometer (kernel: acc_update)
        # not trusted for tau_acc after a clipped sample while the gyro bias is known (kernel: acc_update)
        known = s[self.p_diag].max() <= K.CLIP_BRIDGE_VAR * self.p0
        wait_a = s[K.S_ADISTRUST]
        wait_a = torch.where(clipped[1] & known, p[K.P_TAU_ACC], torch.where(wait_a > 0.0, wait_a - dt, wait_a))
        w.add([K.S_ADISTRUST], wait_a.reshape(1))
        distrust = frozen_a | clipped[1] | (wait_a > 0.0)
        acc_trust = torch.where(distrust, 0.0, acc_trust)
        bias_trust = torch.where(distrust | frozen_g, 0.0, bias_trust)
        if self.check:   # the bias update goes on from the check's (kernel: check_window)
            bias, chk = check_step(s, self.check_sums, gyro, acc, frozen, clipped, dt, p[K.P_CLIP] * K.DEG, bias, w)
        rest1, rest_t1 = rest, rest_t
        if self.rest_bias:
            da = acc - lr[3:6]
            still = ~frozen_a & ((da * da).sum() < p[K.P_REST_TH_A] ** 2)
            rest_t = torch.where(still, rest_t + dt, 0.0)
            rest = torch.where(still, torch.where(rest_t >= p[K.P_REST_MIN_T], 1.0, rest), 0.0)
        # the accelerometer in I_i, low-passed there, then in E_i, normalised (Sec. 3.2)
        f = self.lowpass("acc", s, self.rot(gq) @ acc, rows, dt, gap | frozen_a, w)  # no frozen reading kept
        aq = s[K.S_AQ:K.S_AQ + 4]
        v = self.rot(aq) @ f
        v = v / torch.sqrt((v * v).sum() + 1e-300)
        v0, v1, v2 = v.unbind(0)
        sh = torch.sqrt(v0 * v0 + v1 * v1 + 1e-300)
        half = acc_trust * self.T.atan2(sh, v2) / 2.0
        sin_h = torch.sin(half)
        tilted = sh > K.TILT_MIN
        kk = sin_h / torch.where(tilted, sh, 1.0)
        upside = torch.where(v2 < 0.0, sin_h, 0.0)
        axis = torch.where(tilted, torch.stack([kk * v1, -kk * v0]), torch.stack([upside, torch.zeros_like(upside)]))
        q = self.mul(self.acc_axes @ torch.cat([torch.cos(half).reshape(1), axis]), aq)
        aq_new = q / torch.sqrt((q * q).sum())
        w.add(list(range(K.S_AQ, K.S_AQ + 4)), aq_new)
        aq_used = torch.where(skip_acc, aq, aq_new)          # what the magnetometer's update reads
        q6 = self.mul(aq_used, gq)
        # ---- the low-pass filters that read the new attitude: bias (Sec. 3.4) and field (Sec. 3.3)
        att_x: List[Tensor] = []
        if self.bias:
            r = self.rot(self.mul(aq_new, gq))
            att_x += [r.reshape(9), r[0:2] @ bias]
        if self.use_mag:
            m = self.rot(q6) @ mag                                # the field in E_i
            if self.mag_rej:
                # the heading and the dip (−asin(m_z / |m|) = −atan2(m_z, |m_xy|)) in one atan2
                mm = m * m
                horizontal = torch.sqrt(mm[0] + mm[1])
                ang = self.T.atan2(m[self.heading_dip], torch.cat([m[1:2], horizontal.reshape(1)]))
                heading = ang[0]
                nd = torch.cat([torch.sqrt(mm.sum() + 1e-300).reshape(1), -ang[1:2]])    # norm, dip
                if self.mag_lp:
                    att_x.append(nd)
            else:
                heading = self.T.atan2(m[0], m[1])
        if att_x:
            ya = self.lowpass("att", s, torch.cat(att_x), rows, dt, gap, w)
        if self.bias:
            self._bias_update(s, ya[0:9].reshape(3, 3), ya[9:11], bias, chk, v, rest, rest_g, bias_trust, bias_c, dt, w)
        w.add([K.S_REST, K.S_REST_T], torch.where(skip_acc, torch.stack([rest1, rest_t1]), torch.stack([rest, rest_t])),
              )
        if self.use_mag:
            # a frozen magnetometer is not trusted (kernel: mag_update)
            same_m = (mag == s[K.S_MPREV:K.S_MPREV + 3]).all()
            mt = torch.where(same_m, s[K.S_MSAME_T] + dt, 0.0)
            ft = p[K.P_FROZEN_T]
            mfrozen = (mt >= max(ft, K.MAG_FROZEN_MIN_T)) if ft > 0.0 else self.false
            w.add([K.S_MPREV + i for i in range(3)] + [K.S_MSAME_T, K.S_MFROZEN],
                  torch.cat([mag, mt.reshape(1), mfrozen.to(F64).reshape(1)]))
            mag_trust = torch.where(mfrozen, 0.0, mag_trust)
            if self.mag_lp:
                nd = ya[-2:]
            kminit = self._mag_update(s, heading, nd if self.mag_rej else None, rest_g, kminit, gains, mag_trust,
                                      skip_mag, dt, w)
        w.add([K.S_KMINIT], kminit.reshape(1))
        if plan:
            self._set_plan(w.index)
        return w.assemble(self, s, skip_acc, skip_mag)

    def _set_plan(self, idx: List[int]) -> None:
        self.plan = list(idx)
        self.write_index, self.write_acc, self.write_mag, self.write_perm = plan_buffers(idx)

    def _bias_update(self, s, h, bl, b, chk, v, rest, rest_g, bias_trust, bias_c, dt, w) -> None:
        """Sec. 3.4 (kernel: bias_update) on (3, 3) tensors: h the low-passed attitude matrix, bl
        the low-passed (R b)_xy, b the bias, chk the check's bias (the clip's centre), v the
        accelerometer's direction in E_i."""
        p = self.p
        at_rest = (rest > 0.5) if self.rest_bias else self.false
        # the residual e = y − H b: in motion y = [−v_y, v_x, 0]/ts + [bl, 0], H = h; at rest y = the
        # low-passed gyro, H = I; W the measurement noise of the case
        m = (self.perp @ v) / dt + self.pad2 @ bl - h @ b
        e = torch.where(at_rest, rest_g - b, m)
        H = torch.where(at_rest, self.eye3, h)
        W = torch.where(at_rest, bias_c[self.w_rest], bias_c[self.w_motion])
        # P <- P + V on the diagonal below P0 (also without a measurement: the bias may drift)
        P = s[K.S_P:K.S_P + 9]
        P = torch.where(self.diag9 & (P < self.p0), P + bias_c[0], P).reshape(3, 3)
        cl = p[K.P_CLIP] * K.DEG
        e = torch.clamp(e, -cl, cl)
        A = P @ H.T
        S = self.eye3 * W + H @ A
        # S^-1 by cofactors: row i of C is S_{i+1} x S_{i+2} (indices mod 3), S^-1 = C^T / det
        S9 = S.reshape(9)
        C = S9[self.cof[0]] * S9[self.cof[1]] - S9[self.cof[2]] * S9[self.cof[3]]
        det = (S[0] * C[0]).sum()
        Kg = A @ (C.T / det)
        nb = torch.minimum(torch.maximum(b + bias_trust * (Kg @ e), chk - cl), chk + cl)
        N = P - Kg @ A.T
        if not self.motion:
            nb, N = torch.where(at_rest, nb, b), torch.where(at_rest, N, P)
        w.add([K.S_BIAS + i for i in range(3)], nb)
        w.add([K.S_P + i for i in range(9)], N.reshape(9))

    def _mag_update(self, s, heading, nd, rest_g, kminit, gains, mag_trust, skip_mag, dt, w) -> Tensor:
        """Sec. 3.3 (kernel: mag_update): the heading δ and the disturbance state; -> k_mag_init."""
        p = self.p
        k = gains[0]
        if self.mag_rej:
            # [ref norm, ref dip, candidate norm, candidate dip, undisturbed time, candidate time,
            # disturbed, rejection time]
            ms = s[self.mag_scalars]
            refs = ms[0:4].reshape(2, 2)                       # the reference and the candidate field
            off = nd - refs
            # the field's norm and dip close to each: |norm − ref| < th ref, |dip − ref| < th_dip
            close = (torch.abs(off) - (refs * self.mag_th_scale + self.mag_th_add)).amax(1) < 0.0
            ok, cand = close[0], close[1]
            und_t = torch.where(ok, ms[4] + dt, 0.0)
            settled = ok & (und_t >= p[K.P_MAG_MIN_UND_T])
            dist = torch.where(ok, torch.where(settled, 0.0, ms[6]), 1.0)
            moved = refs + gains[1] * off                      # both low-passed towards the field (k_mag_ref)
            ref = torch.where(settled, moved[0], refs[0])
            turning = torch.sqrt((rest_g * rest_g).sum() + 1e-300) >= p[K.P_MAG_NEW_MIN_G] * K.DEG
            cand_t = torch.where(cand, torch.where(turning, ms[5] + dt, ms[5]), 0.0)
            cnd = torch.where(cand, moved[1], nd)
            # a new field is accepted after it stayed steady for mag_new_time while turning
            accept = cand & (dist > 0.5) & ((cand_t >= p[K.P_MAG_NEW_T])
                                            | ((ref[0] == 0.0) & (cand_t >= p[K.P_MAG_NEW_FIRST_T])))
            ref = torch.where(accept, cnd, ref)
            dist = torch.where(accept, 0.0, dist)
            und_t = torch.where(accept, p[K.P_MAG_MIN_UND_T], und_t)
            # rejection: no heading correction while disturbed, for at most mag_max_rejection_time,
            # then a reduced gain; the allowance recovers at mag_rejection_factor × real time
            k, rej_t = self.G.rejection_gain(k, dist > 0.5, ms[7], p[K.P_MAG_MAX_REJ_T], p[K.P_MAG_REJ_FACTOR], dt)
            w.add(MAG_SCALARS, torch.cat([ref, cnd, torch.stack([und_t, cand_t, dist, rej_t])]))
        k, ki_mag = self.G.initial_gain(k, kminit, p[K.P_TAU_MAG], dt)
        delta = s[K.S_DELTA]
        w.add([K.S_DELTA], self.G.wrap_pi(delta + mag_trust * k * self.G.wrap_pi(heading - delta)).reshape(1))
        return torch.where(skip_mag, kminit, ki_mag)

    def quat(self, s: Tensor) -> Tensor:
        """The output attitude (4,) of a state: q_acc ⊗ q_gyr, 9 axes turned by δ about up."""
        q = self.mul(s[K.S_AQ:K.S_AQ + 4], s[K.S_GQ:K.S_GQ + 4])
        if self.use_mag:
            half = s[K.S_DELTA:K.S_DELTA + 1] / 2.0
            q = self.mul(self.mag_axis @ torch.cat([torch.cos(half), torch.sin(half)]), q)
        return q
