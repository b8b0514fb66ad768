"""The residual model's streaming step as a *stateless* graph: ``sample, dt, state -> quat, omega,
state'`` (what ONNX and ``torch.export`` can hold: no attributes mutated, no Python state, no
exceptions), and the small Python loop that carries the state between calls.

Built from a :class:`~tcn_ahrs.export.backbone.ResidualStreaming` (its fused float32 weights, its
head rows, its knobs) and the backbone's step on vectors (:class:`~tcn_ahrs.export.backbone_graph.BackboneGraph`:
the kernel :mod:`tcn_ahrs.kernels.backbone` in a few hundred graph nodes instead of ~2,400 scalar
ones, held equal to it by tests/test_backbone_graph.py). What this module writes itself is the
glue of ``ResidualStreaming._filter`` in tensor form (the trusts, the clipped gyro residual, the
skipped zero accelerometer/magnetometer samples, the magnetic frame of the first sample) because
that method branches on Python floats; tests/test_export_formats.py holds the numbers equal.

State: one flat float64 vector (:attr:`ResidualStep.layout`: name -> (offset, shape)), zeros
except what :meth:`ResidualStep.initial_state` writes (``reset(q0)``)::

    t        (1,)              samples since reset (0: the next sample starts the backbone)
    q0       (4,)              the attitude given to reset (w, x, y, z, nav_from_body, ENU)
    m_conj   (4,)              9 axes: the magnetic frame's conjugate (set at the first sample)
    backbone (N_STATE,)        the backbone's state (kernels/backbone_layout.STATE)
    coeff    (22,)             the backbone's coefficients and the dt they are for (0: none yet)
    ring0    (span0, C)        the first layer's ring buffer (raw samples; float32 values)
    ring<i>  (G, span_i, C_i)  hidden layer i's ring buffer (float32 values)

The rings are time-major, shifted one row per sample (oldest first): the newest sample's taps are
rows ``0, d, 2d, ...``, ``ResidualStreaming``'s products without a data-dependent index. The
backbone's coefficients are recomputed when ``dt`` changes (the same numbers as the cached ones).

ONNX Runtime has no float64 Tan, Atan or Asin: :func:`onnx_ops` uses ``tan = sin / cos`` and a
float32 ``atan2`` refined by one float64 step (the backbone's dip is an atan2); float64 outside
the networks.
"""
from __future__ import annotations

import math
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch
from torch import Tensor, nn

from ..kernels import backbone as K
from ..conventions import INPUT_LIMITS, MAX_DT, MIN_DT
from ..kernels.ops import onnx_ops, torch_ops  # noqa: F401 (onnx_ops: read here by the tests)
from .backbone_graph import N_COEFF_GRAPH, BackboneGraph
from .classical_step import magnetic_start
from .fused import gelu_scaled

F64 = torch.float64


class ResidualStep(nn.Module):
    """``quat (4,), omega (3,), state' (S,) = forward(sample (C,), dt (), state (S,))``, float64
    in and out (the networks in float32 inside). ``rs``: a :class:`ResidualStreaming` (its
    weights are copied). ``onnx``: build with :func:`onnx_ops` (float64 tan/atan2 for ONNX
    Runtime); else the plain torch table.

    No input checks (a graph cannot raise): :class:`StatefulLoop` checks before it runs it."""

    def __init__(self, rs: nn.Module, onnx: bool = False):
        super().__init__()
        self.ops = onnx_ops() if onnx else torch_ops()
        self.backbone = BackboneGraph(rs.params, bool(rs.use_backbone_mag), self.ops)
        self.axes = c = int(rs.axes)
        self.groups = g = int(rs.groups)
        self.kernel_size = k = int(rs.kernel_size)
        self.first_dilation = int(rs.first_dilation)
        self.dilations = [int(d) for d in rs.hidden_dilations]
        self.register_buffer("first_weight_t", rs.first_weight_t.detach().clone())
        self.register_buffer("first_bias_step", rs.first_bias_step.detach().clone())
        self.step_weights = nn.ParameterList([nn.Parameter(w.detach().clone(), requires_grad=False)
                                              for w in rs.step_weights])
        self.step_biases = nn.ParameterList([nn.Parameter(b.detach().clone(), requires_grad=False)
                                             for b in rs.step_biases])
        for name in ("head_weight", "head_bias", "head_matrix"):
            self.register_buffer(name, getattr(rs, name).detach().clone())
        self.register_buffer("input_mean", rs.input_mean.detach().clone())
        self.net_dtype = rs.first_weight_t.dtype
        self.n_trust = int(rs.n_trust)
        self.use_mag = bool(rs.use_backbone_mag)
        self.gyro_scale, self.gyro_clip = float(rs.gyro_scale), float(rs.gyro_clip)
        self.trust_max, self.trust_weight = float(rs.trust_max), float(rs.trust_weight_knob)
        self.trust_scales = [float(v) for v in rs.trust_scales]
        self.bias_trust_power = float(rs.bias_trust_power)
        # the backbone's state at the start around its attitude: the initial state with the bias prior
        init = torch.tensor(rs.initial_state, dtype=F64)
        init[K.S_BIAS:K.S_BIAS + 3] = torch.tensor(rs.bias0, dtype=F64)
        self.register_buffer("init_head", init[:K.S_GQ].clone())
        self.register_buffer("init_tail", init[K.S_GQ + 4:].clone())
        self.register_buffer("conj", torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=F64))
        # the state layout
        shapes: List[Tuple[str, Tuple[int, ...]]] = [("t", (1,)), ("q0", (4,)), ("m_conj", (4,)),
                                                     ("backbone", (K.N_STATE,)), ("coeff", (N_COEFF_GRAPH,)),
                                                     ("ring0", (int(rs.first_span), c))]
        for i, (span, w) in enumerate(zip(rs.spans, rs.step_weights)):
            shapes.append((f"ring{i + 1}", (g, int(span), int(w.shape[1]) // k)))
        self.layout: Dict[str, Tuple[int, Tuple[int, ...]]] = {}
        off = 0
        for name, shape in shapes:
            self.layout[name] = (off, shape)
            off += int(math.prod(shape))
        self.state_size = off

    # ---------------------------------------------------------------- state
    def _part(self, state: Tensor, name: str) -> Tensor:
        off, shape = self.layout[name]
        return state[off:off + int(math.prod(shape))].reshape(shape)

    def initial_state(self, q0: Tensor) -> Tensor:
        """The state after ``reset(q0)`` (q0 normalised): the rings at the batch model's causal
        zero padding (the first one at the input mean, folded into its weights). Traceable (the
        batch graph builds it from its q0 input)."""
        q = q0.to(F64).reshape(4)
        span, c = self.layout["ring0"][1]
        ring0 = self.input_mean.to(self.net_dtype).to(F64).reshape(1, c).expand(span, c).reshape(-1)
        head = torch.cat([torch.zeros(1, dtype=F64), q / torch.sqrt((q * q).sum()),
                          torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=F64),
                          torch.zeros(K.N_STATE + N_COEFF_GRAPH, dtype=F64), ring0])
        return torch.cat([head, torch.zeros(self.state_size - head.shape[0], dtype=F64)])

    # ---------------------------------------------------------------- networks

    def _networks(self, sample: Tensor, state: Tensor) -> Tuple[Tensor, List[Tensor]]:
        """Head output v = −[gyro net pre-tanh (3), trust logits] (float64) and the new rings."""
        ring = self._part(state, "ring0").to(self.net_dtype)
        ring = torch.cat([ring[1:], sample.to(self.net_dtype).view(1, -1)], 0)
        rings = [ring]
        taps = ring[0::self.first_dilation].reshape(1, -1)
        h = gelu_scaled(torch.addmm(self.first_bias_step, taps, self.first_weight_t)).view(self.groups, 1, -1)
        for i in range(len(self.dilations)):
            ring = self._part(state, f"ring{i + 1}").to(self.net_dtype)
            ring = torch.cat([ring[:, 1:], h], 1)
            rings.append(ring)
            taps = ring[:, 0::self.dilations[i]].reshape(self.groups, 1, -1)
            h = gelu_scaled(torch.baddbmm(self.step_biases[i], taps, self.step_weights[i]))
        x = sample.to(F64)
        feats = h.reshape(-1).to(F64)
        v = torch.addmv(torch.addmv(self.head_bias, self.head_weight, feats), self.head_matrix, x, beta=-1.0)
        return v, rings

    # ---------------------------------------------------------------- step
    def _start(self, state: Tensor, x: Tensor) -> Tuple[Tensor, Tensor]:
        """The backbone's state at the first sample (from q0; 9 axes in the magnetic frame of the
        sample's field, :func:`tcn_ahrs.filters.common.magnetic_from_nav`) and m_conj."""
        bb = self.backbone
        q, m_conj = self._part(state, "q0"), self._part(state, "m_conj")
        if self.use_mag:
            q, mq = magnetic_start(bb.ham, bb.matrix, bb.mag_axis, q, x[6:9], self.ops.atan2)
            m_conj = mq * self.conj
        else:
            m_conj = m_conj.clone()
        parts = [q / torch.sqrt((q * q).sum()), self.init_tail]
        return torch.cat(([self.init_head] if K.S_GQ else []) + parts), m_conj

    def _coeff_kept(self, state: Tensor, dt: Tensor) -> Tensor:
        return self._part(state, "coeff").clone()

    def _coeff_new(self, state: Tensor, dt: Tensor) -> Tensor:
        return self.backbone.coefficients(dt)

    def _carry(self, state: Tensor, x: Tensor) -> Tuple[Tensor, Tensor]:
        """Every other sample: the backbone's state and m_conj as they are."""
        return self._part(state, "backbone").clone(), self._part(state, "m_conj").clone()

    def forward(self, sample: Tensor, dt: Tensor, state: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
        x = sample.to(F64)
        dt = dt.to(F64).reshape(())
        v, rings = self._networks(sample, state)
        # trusts and gyro residual (ResidualStreaming._filter)
        trusts: List[Tensor] = [torch.full((), s, dtype=F64) for s in self.trust_scales]
        for j in range(self.n_trust):
            tr = torch.clamp(2.0 / (1.0 + torch.exp(v[3 + j])), max=self.trust_max)
            trusts[j] = self.trust_scales[j] * (1.0 + self.trust_weight * (tr - 1.0))
            if j == 0 and self.bias_trust_power > 0.0:  # the acc trust gating the bias update
                trusts[2] = self.trust_scales[2] * torch.pow(tr / self.trust_max, self.bias_trust_power)
        lim = self.gyro_clip
        g = x[0:3] - torch.clamp(self.gyro_scale * torch.tanh(-v[0:3]), -lim, lim)
        # the backbone's start at the first sample after reset (ResidualStreaming._start): a branch
        # of its own (ONNX If), so the other samples do not compute it
        bb = self.backbone
        t = self._part(state, "t")[0]
        s, m_conj = torch.cond(t < 0.5, self._start, self._carry, (state, x))   # (operands may not alias)
        # one backbone step (BackboneGraph: the kernel's step on vectors; [0 0 0] readings skipped, as VQF)
        skip_acc = (x[3:6] == 0.0).all()
        mag = x[6:9] if self.use_mag else x[3:6]
        skip_mag = (mag == 0.0).all()
        # the coefficients of dt, kept in the state: recomputed only when dt changes (ONNX If)
        coeff = torch.cond(self._part(state, "coeff")[0] == dt, self._coeff_kept, self._coeff_new, (state, dt))
        s = bb(s, g, x[3:6], mag, dt, trusts[0], trusts[1], trusts[2], skip_acc, skip_mag, coeff)
        out = bb.mul(m_conj, bb.quat(s))
        out = torch.where(out[0] < 0.0, -out, out)  # w >= 0 representative
        omega = g - s[K.S_BIAS:K.S_BIAS + 3]
        new_state = torch.cat([(t + 1.0).reshape(1), self._part(state, "q0"), m_conj, s, coeff]
                              + [r.to(F64).reshape(-1) for r in rings])
        return out, omega, new_state


class ResidualScan(nn.Module):
    """The batch model as one graph: ``quat (N, 4), omega (N, 3) = forward(imu (N, C), dt (N,),
    q0 (4,))``, float64: :class:`ResidualStep` scanned over the samples from the state of
    ``reset(q0)`` (``torch._higher_order_ops.scan``: ONNX ``Scan``, a ``scan`` node in
    torch.export; N is dynamic). No input checks inside (the loader's)."""

    def __init__(self, step: ResidualStep):
        super().__init__()
        self.step = step

    def forward(self, imu: Tensor, dt: Tensor, q0: Tensor) -> Tuple[Tensor, Tensor]:
        from torch._higher_order_ops.scan import scan

        def body(state: Tensor, xs: Tuple[Tensor, Tensor]):
            q, w, state = self.step(xs[0], xs[1], state)
            return state, torch.cat([q, w])

        _, out = scan(body, self.step.initial_state(q0), (imu.to(F64), dt.to(F64)))
        return out[:, 0:4], out[:, 4:7]


# ============================================================== the state between calls
def state_spec(step: ResidualStep) -> Dict[str, object]:
    """The state's description for the metadata (JSON): size, layout (name -> [offset, shape]),
    what ``reset(q0)`` writes besides q0 (``m_conj`` = identity, every ``ring0`` row = the input
    mean), so a loader without torch builds it; ``flags``: the flags' indices in it."""
    row, base = step.input_mean.to(step.net_dtype).to(F64).tolist(), int(step.layout["backbone"][0])
    return {"size": int(step.state_size), "dtype": "float64",
            "layout": {k: [int(o), [int(v) for v in s]] for k, (o, s) in step.layout.items()},
            "init": {"m_conj": [1.0, 0.0, 0.0, 0.0], "ring0_row": [float(v) for v in row]},
            "flags": {name: base + int(idx) for name, idx in STATE_FLAGS.items()}}  # > 0.5: set


# the backbone's flags (sensor health among them) and where its state holds them
STATE_FLAGS = {"rest": K.S_REST, "mag_disturbed": K.S_MAGDIST, "gyro_frozen": K.S_GFROZEN,
               "acc_frozen": K.S_AFROZEN, "gyro_clipped": K.S_GCLIPPED, "acc_clipped": K.S_ACLIPPED,
               "gap": K.S_GAP, "mag_frozen": K.S_MFROZEN}


def initial_state(spec: Dict, q0):
    """The state after ``reset(q0)`` (numpy, float64) from :func:`state_spec`'s description; q0
    (4,) already checked and normalised."""
    s = np.zeros(int(spec["size"]), dtype=np.float64)
    lay = spec["layout"]
    s[lay["q0"][0]:lay["q0"][0] + 4] = np.asarray(q0, dtype=np.float64).reshape(4)
    s[lay["m_conj"][0]:lay["m_conj"][0] + 4] = spec["init"]["m_conj"]
    if "ring0" in lay:  # the residual models' first ring buffer (a classical step has none)
        off, (span, c) = lay["ring0"]
        s[off:off + span * c] = np.tile(np.asarray(spec["init"]["ring0_row"], dtype=np.float64), span)
    return s


class StatefulLoop:
    """The streaming contract around a stateless step graph (ONNX or torch.export): the state
    lives here, in numpy, and the inputs are checked *before* the graph runs (a graph cannot
    raise), so a refused sample leaves the state as it was (:mod:`tcn_ahrs.export.contract`:
    the same checks and messages as :class:`~tcn_ahrs.streaming.BackboneStreaming`).

    ``reset(q0)``; ``step(sample (C,), dt)`` -> quat (4,), omega (3,) float64 numpy (the dt of the
    first sample after reset IS used, as the batch model); ``step_chunk(samples (k, C), dt)`` and
    ``run(imu (N, C), dt, q0)`` (= the batch model: reset + the step graph scanned here) ->
    (k, 4), (k, 3). Subclasses set ``metadata`` (dict) and implement ``_run_graph(x, dt, state)``
    -> (quat, omega, state')."""

    metadata: Dict

    def _setup(self, metadata: Dict) -> None:
        self.metadata = metadata
        self.axes = int(metadata["axes"])
        self.spec = metadata["state"]
        self._dt1 = np.zeros(1)
        self._limit = np.asarray(INPUT_LIMITS[:self.axes], dtype=np.float64)
        self.reset(np.array([1.0, 0.0, 0.0, 0.0]))

    def _check(self, xs, dts) -> None:
        from .contract import check_samples

        check_samples(xs, dts)

    def reset(self, q0) -> None:
        """Start a new recording at attitude q0 (w, x, y, z), nav_from_body, ENU."""
        from .contract import check_quat0

        self.state = initial_state(self.spec, check_quat0(q0).numpy())

    def step(self, sample, dt: float):
        """One sample (C,) -> (quat (4,), omega (3,)); ValueError before any state change (a good
        sample passes the contract's checks in one comparison, NaN fails it; else the full check)."""
        from .contract import one_sample

        x = np.asarray(sample, dtype=np.float64)
        if not (x.shape == (self.axes,) and MIN_DT <= dt <= MAX_DT and bool((np.abs(x) <= self._limit).all())):
            x = one_sample(self, sample, dt)[0]
        q, w, self.state = self._run_graph(x, float(dt), self.state)
        return q, w

    def flags(self) -> Dict[str, bool]:
        """The backbone's flags after the last step, from the returned state (``state.flags``)."""
        return {name: bool(self.state[idx] > 0.5) for name, idx in (self.spec.get("flags") or {}).items()}

    def step_chunk(self, samples, dt):
        """k samples (k, C), dt float or (k,) -> (quat (k, 4), omega (k, 3)): k steps."""
        from .contract import checked_chunk

        xs, dts = checked_chunk(self, samples, dt)
        quat, omega = np.empty((len(xs), 4)), np.empty((len(xs), 3))
        state = self.state
        for k in range(len(xs)):
            quat[k], omega[k], state = self._run_graph(xs[k], float(dts[k]), state)
        self.state = state
        return quat, omega

    def run(self, imu, dt, q0):
        """reset(q0), then imu (N, C) -> quat (N, 4), omega (N, 3): the batch model (every input
        checked before the state is reset)."""
        from .contract import checked_chunk, check_quat0

        xs, dts = checked_chunk(self, imu, dt)
        check_quat0(q0)
        self.reset(q0)
        return self.step_chunk(xs, dts) if len(xs) else (np.zeros((0, 4)), np.zeros((0, 3)))


# ============================================================== export preparation
SUPPORTED = ("the residual models (model.loop: backbone): checkpoints/broad9, broad6, general6, general9, "
             "euroc6_residual_small and checkpoints/residual/*.ckpt; and tuned ECF files (checkpoints/tumvi6_ecf.json, oxiod9_ecf.json)")


def prepare(ckpt_path, targets: List, fmt: str, rate_hz: Optional[float] = None, overwrite: bool = False,
            onnx: bool = False):
    """Load ``ckpt_path`` for a stateless-step export: checks (existing targets, writable folder,
    a residual model) -> (the :class:`ResidualStep`, the metadata dict). ``fmt``: the format's
    name in the metadata and the messages."""
    import os
    from pathlib import Path

    from ..checkpoint import checkpoint_meta, load_checkpoint
    from .metadata import build_metadata, checkpoint_export_meta
    from .backbone import ResidualStreaming
    from .inputs import ExportError

    classical = str(ckpt_path).endswith(".json")  # a classical estimator file: classical_step.py
    ck_meta = None if classical else checkpoint_meta(load_checkpoint(ckpt_path), ckpt_path)  # missing: named first
    existing = [str(t) for t in targets if Path(t).exists()]
    if existing and not overwrite:
        raise ExportError(f"export: {', '.join(existing)} already exist(s): choose another out= or pass overwrite=true")
    for t in targets:
        folder = Path(t).parent
        folder.mkdir(parents=True, exist_ok=True)
        if not os.access(folder, os.W_OK):
            raise ExportError(f"export: cannot write into {folder} (read-only?): choose another out=")
    if classical:
        from .classical_step import prepare_classical
        return prepare_classical(ckpt_path, fmt, onnx)
    model, meta = checkpoint_export_meta(ckpt_path, ck_meta, rate_hz)
    if getattr(model, "backbone", None) is None:
        kind = "closed-loop" if getattr(model, "closed", None) is not None else "open-loop (paper)"
        raise ExportError(f"format={fmt} supports {SUPPORTED}; {ckpt_path} is a {kind} model: "
                          "export it with format=torchscript")
    md = build_metadata(model, "step", meta)
    with torch.no_grad():
        step = ResidualStep(ResidualStreaming(model, md), onnx=onnx).eval()
    md.update({
        "format": f"tcn-ahrs {fmt} export (stateless step)",
        "mode": "step",
        "api": {"step": "quat (4,), omega (3,), state_out (S,) = step(sample (C,) float64, dt () float64 [s], "
                        "state (S,) float64)  (dt used on every call, also the first after reset)",
                "reset": "state = zeros(S); state[q0] = q0 / |q0|; state[m_conj] = state.init.m_conj; every row of "
                         "state[ring0] = state.init.ring0_row  (tcn_ahrs.export.stateless.initial_state)",
                "batch": "quat (N,4), omega (N,3) = reset(q0) + the step over the N samples (the loader's run)",
                "checks": "none inside the graph: the loader refuses a non-finite or out-of-range sample or a dt "
                          "not in [min_dt, max_dt] before running it (state unchanged)"},
        "state": state_spec(step),
        "max_dt": float(MAX_DT),
        "min_dt": float(MIN_DT),
        "input_limits": [float(v) for v in INPUT_LIMITS],
    })
    return step, md


def example_inputs(step: ResidualStep) -> Tuple[Tensor, Tensor, Tensor]:
    """(sample, dt, state) to trace the step with: a level sensor at rest after reset."""
    x = torch.zeros(step.axes, dtype=F64)
    x[5] = 9.81
    if step.axes == 9:
        x[7], x[8] = 20.0, -40.0
    return x, torch.tensor(0.01, dtype=F64), step.initial_state(torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=F64))


def staged_write(path, write) -> str:
    """``write(tmp)`` to a hidden temporary name beside ``path``, then renamed into place (a
    failed export leaves nothing)."""
    from pathlib import Path

    from ..app import staged_files
    from .inputs import ExportError

    return staged_files({"file": Path(path)}, lambda _, tmp: write(tmp), lambda m: ExportError(f"export: {m}"))["file"]


class CheckedBatch:
    """The batch contract around a :class:`ResidualScan` graph: ``run(imu (N, C), dt float | (N,),
    q0 (4,))`` (also ``__call__``) -> quat (N, 4), omega (N, 3) float64 numpy, every input checked
    first (the same checks as the streaming loaders). Subclasses set ``metadata`` and implement
    ``_run_graph(imu, dt, q0)``."""

    metadata: Dict

    def _setup(self, metadata: Dict) -> None:
        self.metadata = metadata
        self.axes = int(metadata["axes"])

    def _check(self, xs, dts) -> None:
        from .contract import check_samples

        check_samples(xs, dts)

    def run(self, imu, dt, q0):
        from .contract import checked_chunk, check_quat0

        xs, dts = checked_chunk(self, imu, dt)
        q = check_quat0(q0).numpy()
        if len(xs) == 0:
            return np.zeros((0, 4)), np.zeros((0, 3))
        return self._run_graph(xs, dts, q)

    __call__ = run
