"""``format: c``: a dependency-free C99 runtime of a residual checkpoint (``<name>.h`` + ``<name>.c``).

What is generated and from where (nothing of the math restated by hand):

* the backbone's C is translated from :mod:`tcn_ahrs.kernels.backbone`'s own source (and the
  quaternion kernels it binds) by :mod:`tcn_ahrs.export.c_kernel`, as numba and TorchScript
  (:mod:`tcn_ahrs.kernels.script_ops`) compile that same source;
* the networks are the folded float32 weights of :func:`~tcn_ahrs.export.fused.fuse_residual` in
  the flat layout of :func:`tcn_ahrs.streaming.networks._flat_networks` (what
  :class:`~tcn_ahrs.streaming.BackboneStreaming` runs), read by one generic ring-buffer dilated
  causal convolution (:data:`TEMPLATE`); GELU as ``u (1 + erf(u))`` with the rational erf of
  :func:`tcn_ahrs.streaming.networks.erf_rational` (its coefficients written in);
* the per-sample composition (networks -> gyro residual and trusts -> backbone calls -> output)
  is :data:`TEMPLATE`, written once after ``_backbone_steps`` of :mod:`tcn_ahrs.streaming.backbone`
  (and ``ResidualStreaming._filter`` / ``_start``).

The C API (``name`` = the prefix)::

    typedef struct {...} name_state;                      static memory: no malloc
    int  name_init(name_state *st, const float q0[4]);    (= name_reset; 0 or NAME_E_Q0)
    int  name_reset(name_state *st, const float q0[4]);   start a recording at q0 (w,x,y,z) nav_from_body ENU
    int  name_step(name_state *st, const float sample[C], float dt,
                   float quat_out[4], float omega_out[3], float bias_out[3], uint32_t *flags);
    int  name_run(name_state *st, const float *samples, uint32_t n, float dt, float *out);  out (n, 7)

``step`` returns 0 or an error code (``NAME_E_NONFINITE``, ``NAME_E_RANGE``, ``NAME_E_DT``) for
a refused sample *before* any state changes (the contract of the streaming runtimes: the
ranges of :mod:`tcn_ahrs.conventions`). Any output pointer may be NULL. ``flags``:
``NAME_FLAG_REST`` (the backbone detects rest), ``NAME_FLAG_MAG_DISTURBED`` (9 axes: the field
is rejected as disturbed), ``NAME_FLAG_ACC_SKIPPED`` / ``NAME_FLAG_MAG_SKIPPED`` (an all-zero
reading, skipped as VQF does). The backbone's scalar type is ``TCN_AHRS_REAL`` (compile with
``-DTCN_AHRS_REAL=float`` for a float build; default double), the networks run in float32.
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any, Dict, Optional

import numpy as np
import torch
from torch import nn

from ..conventions import INPUT_LIMITS, MAX_DT
from ..kernels import backbone as K
from .c_kernel import HELPERS, kernel_c
from .inputs import ExportError

ROOTS_6 = ("coefficients", "gyro_update", "acc_update", "quat6", "qmul")
ROOTS_9 = ROOTS_6 + ("mag_update", "quat9")


def _f32(a) -> str:
    """float32 values as exact C literals."""
    a = np.asarray(a, dtype=np.float32).reshape(-1)
    return ",\n".join(", ".join(f"{float(v):.9g}f" for v in a[i:i + 8]) for i in range(0, a.size, 8)) or "0.0f"


def _f64(a) -> str:
    a = np.asarray(a, dtype=np.float64).reshape(-1)
    return ",\n".join(", ".join(repr(float(v)) for v in a[i:i + 6]) for i in range(0, a.size, 6)) or "0.0"


def _networks(model: nn.Module):
    """The folded networks in BackboneStreaming's flat layout: (wts float32, head_w, head_b, ints)."""
    from .fused import fuse_residual
    from .open_loop import StreamingAHRS
    from ..streaming.networks import _flat_networks

    fused = fuse_residual(model)
    ts = StreamingAHRS(fused, {})
    n_trust = 2 if int(model.axes) == 9 else 1
    w = torch.cat([ts.out_weight_f64[0:3], fused["trust_weight"][:n_trust] * math.sqrt(0.5)], 0)
    b = torch.cat([fused["out_bias"][0:3], fused["trust_bias"][:n_trust]])
    m = torch.zeros(w.shape[0], int(model.axes), dtype=torch.float64)
    wts, params, ints, rings, _, _ = _flat_networks(ts, w, b, m)
    return wts, w.numpy().copy(), b.numpy().copy(), [int(v) for v in ints], int(rings.size), n_trust


def generate_c(model: nn.Module, name: str) -> Dict[str, Any]:
    """The C runtime of a residual model (a :class:`~tcn_ahrs.model.ahrs.LearnedAHRS` with
    ``loop: backbone``): {"h": header text, "c": source text, "info": sizes}."""
    from ..streaming.networks import _ERF_P, _ERF_Q, _HEADER, _PER_LAYER

    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name or ""):
        raise ExportError(f"C export: name {name!r} is not a C identifier")
    if getattr(model, "backbone", None) is None:
        kind = "closed-loop" if getattr(model, "closed", None) is not None else "open-loop (paper)"
        raise ExportError(f"C export: the model is a {kind} model; the C runtime covers the residual models "
                          "(model.loop: backbone, checkpoints/*.ckpt) only")
    model = model.eval()
    cal, loop = model.calibration, model.backbone
    c = int(model.axes)
    use_mag = bool(loop.use_mag) and c == 9
    wts, head_w, head_b, ints, n_ring, n_trust = _networks(model)
    kk, nl, n_feat, n_head = ints[1], ints[2], ints[6], ints[7]
    layers = [ints[_HEADER + _PER_LAYER * i:_HEADER + _PER_LAYER * (i + 1)] for i in range(nl)]
    width = max([c, n_feat] + [g * cout for g, _, cout, *_ in layers] + [cin * g for g, cin, *_ in layers])
    # weights tap-major per group, (groups, K c_in, c_out): conv_layer's layout
    wt = wts.copy()
    calls = []
    for li, (g, cin, cout, d, span, wo, bo, ro) in enumerate(layers):
        n_tap = kk * cin
        wt[wo:wo + g * cout * n_tap] = wts[wo:wo + g * cout * n_tap].reshape(g, cout, n_tap).transpose(0, 2, 1).reshape(-1)
        calls.append(f"    /* layer {li}: {g} group(s), {cin} -> {cout} channels, dilation {d} */\n"
                     f"    conv_layer(st->ring + {ro}, st->pos[{li}], h, out, {g}, {cin}, {cout}, {d}, {span}, {wo}, {bo});\n"
                     f"    st->pos[{li}] = st->pos[{li}] + 1 == {span} ? 0 : st->pos[{li}] + 1;\n"
                     f"    for (i = 0; i < {g * cout}; i++) h[i] = out[i];")
    wts = wt
    up = name.upper()
    p = list(loop.params.vector())
    s0 = K.initial_state(loop.params)
    bias0 = (loop.bias_prior * loop.bias_init.detach().double()).numpy()
    kernels, _ = kernel_c(K, f"{name}_bb_", ROOTS_9 if use_mag else ROOTS_6)
    subst = {
        "NAME": name, "UP": up, "C": str(c), "N_STATE": str(K.N_STATE), "N_COEFF": str(K.N_COEFF),
        "N_PARAM": str(K.N_PARAM), "N_RING": str(max(n_ring, 1)), "N_LAYERS": str(max(nl, 1)), "K": str(kk),
        "NL": str(nl), "N_FEAT": str(n_feat), "N_HEAD": str(n_head), "N_TRUST": str(n_trust), "WIDTH": str(width),
        "N_WTS": str(wts.size), "USE_MAG": "1" if use_mag else "0",
        "LAYER_CALLS": "\n".join(calls),
        "WTS": _f32(wts), "HEAD_W": _f64(head_w), "HEAD_B": _f64(head_b), "PARAMS": _f64(p), "STATE0": _f64(s0),
        "BIAS0": _f64(bias0), "LIMITS": _f64(INPUT_LIMITS[:c]), "MAX_DT": repr(float(MAX_DT)),
        "ERF_P": _f64(_ERF_P), "ERF_Q": _f64(_ERF_Q), "N_ERF_P": str(len(_ERF_P)), "N_ERF_Q": str(len(_ERF_Q)),
        "GYRO_SCALE": repr(float(cal.gyro_scale)), "GYRO_CLIP": repr(float(cal.gyro_clip)),
        "TRUST_MAX": repr(float(loop.trust_max)), "TRUST_W": repr(float(loop.trust_weight)),
        "ACC_SCALE": repr(float(loop.acc_trust_scale)), "MAG_SCALE": repr(float(loop.mag_trust_scale)),
        "BIAS_SCALE": repr(float(loop.bias_trust_scale)),
        "S_GQ": str(K.S_GQ), "S_BIAS": str(K.S_BIAS), "S_REST": str(K.S_REST), "S_MAGDIST": str(K.S_MAGDIST),
        "KERNELS": kernels,
    }

    def fill(text: str) -> str:
        return re.sub(r"@(\w+)@", lambda mm: subst[mm.group(1)], text)

    info = {"axes": c, "use_mag": use_mag, "weights_float32": int(wts.size), "head_values": int(head_w.size + head_b.size),
            "ring_floats": n_ring, "layers": layers, "weight_bytes": int(wts.size * 4),
            "head_bytes_double": int((head_w.size + head_b.size) * 8)}
    return {"h": fill(HEADER), "c": fill(SOURCE), "info": info}


def export_c(ckpt_path, out_dir, prefix: Optional[str] = None, overwrite: bool = True) -> Dict[str, str]:
    """Generate ``<prefix>.h`` and ``<prefix>.c`` (prefix: the checkpoint's stem) in ``out_dir``
    from a residual checkpoint; closed-loop and open-loop (paper) checkpoints raise ExportError."""
    from ..checkpoint import model_from_checkpoint

    name = prefix or re.sub(r"\W", "_", Path(ckpt_path).stem)
    model = model_from_checkpoint(ckpt_path)
    gen = generate_c(model, name)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"h": out / f"{name}.h", "c": out / f"{name}.c"}
    if not overwrite and any(p_.exists() for p_ in paths.values()):
        raise ExportError(f"C export: {paths['h']} or {paths['c']} exists: pass overwrite")
    for k, p_ in paths.items():
        p_.write_text(gen[k])
    return {k: str(v) for k, v in paths.items()}


def compile_c(c_path, out_so, real: str = "double", cc: Optional[str] = None) -> str:
    """Build the generated source as a shared library with the system compiler (the strict
    flags the tests use); ``real``: the backbone's scalar type. Returns the library's path."""
    import shutil
    import subprocess

    cc = cc or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        raise ExportError("C export: no C compiler (cc) found")
    cmd = [cc, "-std=c99", "-pedantic", "-O2", "-Wall", "-Wextra", "-Wshadow", "-Wdouble-promotion", "-Werror",
           "-shared", "-fPIC", f"-DTCN_AHRS_REAL={real}",
           str(c_path), "-o", str(out_so), "-lm"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise ExportError(f"C export: {' '.join(cmd)} failed:\n{r.stderr[-4000:]}")
    return str(out_so)


class CRuntime:
    """The generated library through ctypes (tests, timing): ``reset(q0)``, ``step(sample, dt)``
    -> (code, quat, omega, bias, flags), ``run(samples (n, C), dt)`` -> (code, out (n, 7))."""

    def __init__(self, so_path, name: str, axes: int):
        import ctypes as ct

        self.ct, self.axes, self.name = ct, axes, name
        lib = ct.CDLL(str(so_path))
        self.lib = lib
        f = ct.POINTER(ct.c_float)
        lib[f"{name}_state_size"].restype = ct.c_uint32
        self.state_size = int(lib[f"{name}_state_size"]())
        self.state = ct.create_string_buffer(self.state_size)
        self._reset = lib[f"{name}_reset"]
        self._reset.argtypes = [ct.c_void_p, f]
        self._step = lib[f"{name}_step"]
        self._step.argtypes = [ct.c_void_p, f, ct.c_float, f, f, f, ct.POINTER(ct.c_uint32)]
        self._run = lib[f"{name}_run"]
        self._run.argtypes = [ct.c_void_p, f, ct.c_uint32, ct.c_float, f]
        self._q, self._w, self._b = (np.zeros(4, np.float32), np.zeros(3, np.float32), np.zeros(3, np.float32))
        self._flags = ct.c_uint32(0)

    def _ptr(self, a):
        return a.ctypes.data_as(self.ct.POINTER(self.ct.c_float))

    def reset(self, q0) -> int:
        q = np.ascontiguousarray(q0, dtype=np.float32)
        return int(self._reset(self.state, self._ptr(q)))

    def step(self, sample, dt: float):
        x = np.ascontiguousarray(sample, dtype=np.float32)
        code = int(self._step(self.state, self._ptr(x), float(dt), self._ptr(self._q), self._ptr(self._w),
                              self._ptr(self._b), self.ct.byref(self._flags)))
        return code, self._q.copy(), self._w.copy(), self._b.copy(), int(self._flags.value)

    def run(self, samples, dt: float):
        x = np.ascontiguousarray(samples, dtype=np.float32)
        out = np.zeros((x.shape[0], 7), dtype=np.float32)
        code = int(self._run(self.state, self._ptr(x), x.shape[0], float(dt), self._ptr(out)))
        return code, out

    def snapshot(self) -> bytes:
        return self.state.raw


HEADER = r"""/* @NAME@.h: a tcn-ahrs residual model (learned residuals on the VQF-grade backbone) as
 * dependency-free C99, generated by tcn_ahrs.export.c_runtime (do not edit: regenerate).
 *
 * Inputs: sample[@C@] = gyro x,y,z [rad/s], acc x,y,z [m/s^2, specific force, +9.81 up at rest]
 * (, mag x,y,z [uT]) in the body frame; dt [s] since the previous sample (used from the first).
 * Output: quat (w,x,y,z, w >= 0) nav_from_body, ENU (9 axes: heading referred to the field of
 * the first sample after reset); omega = the gyro fed to the backbone minus its bias [rad/s];
 * bias = the backbone's gyro bias estimate [rad/s].
 * A refused sample (non-finite, beyond the physical ranges, dt not in (0, @MAX_DT@] s) returns its
 * error code and changes no state. Compile with -DTCN_AHRS_REAL=float for a float backbone. */
#ifndef @UP@_H
#define @UP@_H
#include <stdint.h>

#ifndef TCN_AHRS_REAL
#define TCN_AHRS_REAL double
#endif

#define @UP@_AXES @C@
#define @NAME@_AXES @C@   /* the same, under the lower-case prefix (for token pasting) */
#define @UP@_N_STATE @N_STATE@
#define @UP@_N_COEFF @N_COEFF@
#define @UP@_N_RING @N_RING@
#define @UP@_N_LAYERS @N_LAYERS@

#define @UP@_OK 0
#define @UP@_E_NONFINITE 1   /* a NaN or inf reading */
#define @UP@_E_RANGE 2       /* a reading beyond any sensor's range (a spike) */
#define @UP@_E_DT 3          /* dt not finite, <= 0 or > max */
#define @UP@_E_Q0 4          /* q0 not a finite non-zero quaternion */
#define @UP@_E_NULL 5        /* a NULL state or input */

#define @UP@_FLAG_REST 1u            /* rest detected by the backbone */
#define @UP@_FLAG_MAG_DISTURBED 2u   /* magnetic disturbance: heading correction rejected */
#define @UP@_FLAG_ACC_SKIPPED 4u     /* an all-zero accelerometer reading was skipped */
#define @UP@_FLAG_MAG_SKIPPED 8u     /* an all-zero magnetometer reading was skipped */

typedef struct {
    TCN_AHRS_REAL s[@UP@_N_STATE];      /* the backbone's state (kernels/backbone_layout.py STATE) */
    TCN_AHRS_REAL coeff[@UP@_N_COEFF];  /* its coefficients for last_dt */
    TCN_AHRS_REAL q0[4], m_conj[4], last_dt;
    int32_t pos[@UP@_N_LAYERS];         /* ring-buffer rows of the newest input, per layer */
    int32_t started;
    float ring[@UP@_N_RING];            /* the networks' ring buffers (float32) */
} @NAME@_state;

#ifdef __cplusplus
extern "C" {
#endif
int @NAME@_init(@NAME@_state *st, const float q0[4]);
int @NAME@_reset(@NAME@_state *st, const float q0[4]);
int @NAME@_step(@NAME@_state *st, const float sample[@C@], float dt, float quat_out[4], float omega_out[3],
                float bias_out[3], uint32_t *flags);
/* n samples (n, @C@) row-major at a constant dt -> out (n, 7): quat (4), omega (3). Stops at the
 * first refused sample and returns its error code (the state is as after the sample before). */
int @NAME@_run(@NAME@_state *st, const float *samples, uint32_t n, float dt, float *out);
/* sizeof(@NAME@_state), for callers through an FFI */
uint32_t @NAME@_state_size(void);
#ifdef __cplusplus
}
#endif

#endif
"""

SOURCE = r"""/* @NAME@.c: generated by tcn_ahrs.export.c_runtime from a residual checkpoint (do not edit).
 * The backbone's functions below are translated from tcn_ahrs/kernels/backbone.py's source
 * (tcn_ahrs.export.c_kernel); the networks' weights are the folded float32 weights. */
#include <math.h>
#include <string.h>
#include <stdint.h>
#include "@NAME@.h"
@HELPERS@
static inline REAL r_tanh(REAL x) { return TCN_AHRS_REAL_IS_FLOAT ? (REAL)tanhf((float)x) : (REAL)tanh((double)x); }

/* ------------------------------------------------------------------ the backbone (generated) */
@KERNELS@
/* ------------------------------------------------------------------ the model's constants */
static const float WTS[@N_WTS@] = {
@WTS@
};
static const REAL HEAD_W[@N_HEAD@ * @N_FEAT@] = {
@HEAD_W@
};
static const REAL HEAD_B[@N_HEAD@] = {
@HEAD_B@
};
static const REAL PARAMS[@N_PARAM@] = {
@PARAMS@
};
static const REAL STATE0[@N_STATE@] = {
@STATE0@
};
static const REAL BIAS0[3] = {@BIAS0@};
static const float LIMITS[@C@] = {@LIMITS@};
static const REAL ERF_P[@N_ERF_P@] = {@ERF_P@};
static const REAL ERF_Q[@N_ERF_Q@] = {@ERF_Q@};
#define MAX_DT_ @MAX_DT@f
#define WIDTH @WIDTH@

/* ------------------------------------------------------------------ the networks */
static inline REAL erf_rational(REAL x)   /* streaming/networks.py erf_rational */
{
    REAL x2, p, q;
    int i;
    x = x < R_(-4.0) ? R_(-4.0) : (x > R_(4.0) ? R_(4.0) : x);
    x2 = x * x;
    p = ERF_P[0];
    for (i = 1; i < @N_ERF_P@; i++) p = p * x2 + ERF_P[i];
    q = ERF_Q[0];
    for (i = 1; i < @N_ERF_Q@; i++) q = q * x2 + ERF_Q[i];
    return x * p / q;
}

/* One dilated causal convolution layer on its ring buffer (written once; called with constant
 * sizes per layer so that the compiler unrolls and vectorises it): the newest input h (G*CIN)
 * written at row p, the K taps t - (K - 1 - j) D read oldest first, per group the float32 sums
 * u_o = b_o + sum_i W[i][o] tap_i (weights tap-major: each output one sequential sum, every
 * output of a tap at once), then the sqrt(2)-scaled GELU u (1 + erf(u)) into out (G*COUT). */
static inline void conv_layer(float *ring, int p, const REAL *h, REAL *out, const int G, const int CIN,
                              const int COUT, const int D, const int SPAN, const int WO, const int BO)
{
    float tap[@K@ * WIDTH], u[WIDTH];
    int gr, j, i, o;
    for (gr = 0; gr < G; gr++)
        for (i = 0; i < CIN; i++) ring[(gr * SPAN + p) * CIN + i] = (float)h[gr * CIN + i];
    for (gr = 0; gr < G; gr++) {
        const float *w = WTS + WO + gr * @K@ * CIN * COUT;
        for (j = 0; j < @K@; j++) {
            int row = p - (@K@ - 1 - j) * D;
            const float *rb;
            if (row < 0) row += SPAN;
            rb = ring + (gr * SPAN + row) * CIN;
            for (i = 0; i < CIN; i++) tap[j * CIN + i] = rb[i];
        }
        for (o = 0; o < COUT; o++) u[o] = WTS[BO + gr * COUT + o];
        for (i = 0; i < @K@ * CIN; i++) {
            const float t = tap[i];
            const float *wi = w + i * COUT;
            for (o = 0; o < COUT; o++) u[o] += wi[o] * t;
        }
        for (o = 0; o < COUT; o++) {
            const REAL uu = (REAL)u[o];
            out[gr * COUT + o] = uu * (R_(1.0) + erf_rational(uu));
        }
    }
}

/* One sample x through the stacked networks (float32), then the head:
 * v = -(W h + b) = -[gyro net before tanh (3), trust logits]. */
static void networks(@NAME@_state *st, const REAL *x, REAL *v)
{
    REAL h[WIDTH], out[WIDTH];
    int i, r;
    for (i = 0; i < @C@; i++) h[i] = x[i];
@LAYER_CALLS@
    for (r = 0; r < @N_HEAD@; r++) {
        REAL e = HEAD_B[r];
        for (i = 0; i < @N_FEAT@; i++) e += HEAD_W[r * @N_FEAT@ + i] * h[i];
        v[r] = -e;
    }
}

/* ------------------------------------------------------------------ the API */
static int check(const float *x, float dt)
{
    int i;
    for (i = 0; i < @C@; i++)
        if (!isfinite(x[i])) return @UP@_E_NONFINITE;
    for (i = 0; i < @C@; i++)
        if (fabsf(x[i]) > LIMITS[i]) return @UP@_E_RANGE;
    if (!(isfinite(dt) && dt > 0.0f && dt <= MAX_DT_)) return @UP@_E_DT;
    return @UP@_OK;
}

int @NAME@_reset(@NAME@_state *st, const float q0[4])
{
    REAL q[4], n;
    int i;
    if (st == 0 || q0 == 0) return @UP@_E_NULL;
    for (i = 0; i < 4; i++) {
        if (!isfinite(q0[i])) return @UP@_E_Q0;
        q[i] = (REAL)q0[i];
    }
    n = r_sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    if (!(n > R_(0.0)) || !isfinite(n)) return @UP@_E_Q0;
    memset(st, 0, sizeof(*st));   /* rings: the batch model's causal zero padding */
    for (i = 0; i < 4; i++) st->q0[i] = q[i] / n;
    st->m_conj[0] = R_(1.0);
    st->last_dt = R_(-1.0);
    return @UP@_OK;
}

int @NAME@_init(@NAME@_state *st, const float q0[4]) { return @NAME@_reset(st, q0); }

/* the backbone's state at the first sample (9D: in the magnetic frame of its field, as
 * filters.common.magnetic_from_nav) */
static void start(@NAME@_state *st, const REAL *x)
{
    REAL q[4], n;
    int i;
    (void)x;
    for (i = 0; i < 4; i++) q[i] = st->q0[i];
    st->m_conj[0] = R_(1.0); st->m_conj[1] = st->m_conj[2] = st->m_conj[3] = R_(0.0);
#if @USE_MAG@
    {
        REAL v0, v1, v2, h, ch, sh;
        @NAME@_bb_qrot(q[0], q[1], q[2], q[3], x[6], x[7], x[8], &v0, &v1, &v2);
        h = R_(0.5) * (R_(0.5) * R_(3.141592653589793) - r_atan2(v1, v0));
        ch = r_cos(h); sh = r_sin(h);
        @NAME@_bb_qmul(ch, R_(0.0), R_(0.0), sh, st->q0[0], st->q0[1], st->q0[2], st->q0[3], &q[0], &q[1], &q[2], &q[3]);
        st->m_conj[0] = ch; st->m_conj[3] = -sh;
    }
#endif
    for (i = 0; i < @N_STATE@; i++) st->s[i] = STATE0[i];
    n = r_sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    for (i = 0; i < 4; i++) st->s[@S_GQ@ + i] = q[i] / n;
    for (i = 0; i < 3; i++) st->s[@S_BIAS@ + i] = BIAS0[i];
    st->started = 1;
}

int @NAME@_step(@NAME@_state *st, const float sample[@C@], float dt, float quat_out[4], float omega_out[3],
                float bias_out[3], uint32_t *flags)
{
    REAL x[@C@], v[@N_HEAD@], tr[3], g[3], q[4], w, qx, qy, qz, dtr = (REAL)dt;
    uint32_t fl = 0;
    int i, err;
    if (st == 0 || sample == 0) return @UP@_E_NULL;
    err = check(sample, dt);
    if (err) return err;   /* refused before any state changes */
    for (i = 0; i < @C@; i++) x[i] = (REAL)sample[i];
    if (!st->started) start(st, x);
    networks(st, x, v);
    /* the gyro residual and the trusts, as model/residual.py BackboneLoop */
    tr[0] = R_(@ACC_SCALE@); tr[1] = R_(@MAG_SCALE@); tr[2] = R_(@BIAS_SCALE@);
    for (i = 0; i < @N_TRUST@; i++) {
        REAL t = R_(2.0) / (R_(1.0) + r_exp(v[3 + i]));   /* 2 sigma(z) with z = -v */
        t = t < R_(@TRUST_MAX@) ? t : R_(@TRUST_MAX@);
        tr[i] = tr[i] * (R_(1.0) + R_(@TRUST_W@) * (t - R_(1.0)));
    }
    for (i = 0; i < 3; i++) {
        REAL e = R_(@GYRO_SCALE@) * r_tanh(-v[i]);
        e = e > R_(@GYRO_CLIP@) ? R_(@GYRO_CLIP@) : (e < -R_(@GYRO_CLIP@) ? -R_(@GYRO_CLIP@) : e);
        g[i] = x[i] - e;
    }
    if (dtr != st->last_dt) {
        @NAME@_bb_coefficients(PARAMS, dtr, st->coeff);
        st->last_dt = dtr;
    }
    @NAME@_bb_gyro_update(st->s, PARAMS, st->coeff, g[0], g[1], g[2]);
    if (x[3] != R_(0.0) || x[4] != R_(0.0) || x[5] != R_(0.0))   /* all-zero readings skipped, as VQF */
        @NAME@_bb_acc_update(st->s, PARAMS, st->coeff, x[3], x[4], x[5], tr[0], tr[2]);
    else
        fl |= @UP@_FLAG_ACC_SKIPPED;
#if @USE_MAG@
    if (x[6] != R_(0.0) || x[7] != R_(0.0) || x[8] != R_(0.0))
        @NAME@_bb_mag_update(st->s, PARAMS, st->coeff, x[6], x[7], x[8], tr[1]);
    else
        fl |= @UP@_FLAG_MAG_SKIPPED;
    @NAME@_bb_quat9(st->s, &w, &qx, &qy, &qz);
    if (st->s[@S_MAGDIST@] > R_(0.5)) fl |= @UP@_FLAG_MAG_DISTURBED;
#else
    @NAME@_bb_quat6(st->s, &w, &qx, &qy, &qz);
#endif
    @NAME@_bb_qmul(st->m_conj[0], st->m_conj[1], st->m_conj[2], st->m_conj[3], w, qx, qy, qz,
                   &q[0], &q[1], &q[2], &q[3]);
    if (q[0] < R_(0.0))   /* the w >= 0 representative */
        for (i = 0; i < 4; i++) q[i] = -q[i];
    if (st->s[@S_REST@] > R_(0.5)) fl |= @UP@_FLAG_REST;
    if (quat_out)
        for (i = 0; i < 4; i++) quat_out[i] = (float)q[i];
    if (omega_out)
        for (i = 0; i < 3; i++) omega_out[i] = (float)(g[i] - st->s[@S_BIAS@ + i]);
    if (bias_out)
        for (i = 0; i < 3; i++) bias_out[i] = (float)st->s[@S_BIAS@ + i];
    if (flags) *flags = fl;
    return @UP@_OK;
}

uint32_t @NAME@_state_size(void) { return (uint32_t)sizeof(@NAME@_state); }

int @NAME@_run(@NAME@_state *st, const float *samples, uint32_t n, float dt, float *out)
{
    uint32_t k;
    int err;
    if (st == 0 || samples == 0 || out == 0) return @UP@_E_NULL;
    for (k = 0; k < n; k++) {
        err = @NAME@_step(st, samples + (size_t)k * @C@, dt, out + (size_t)k * 7, out + (size_t)k * 7 + 4, 0, 0);
        if (err) return err;
    }
    return @UP@_OK;
}
""".replace("@HELPERS@", HELPERS)


def main(argv=None) -> int:
    """``python -m tcn_ahrs.export.c_runtime CKPT OUT_DIR [NAME]``: write NAME.h and NAME.c."""
    import sys

    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) not in (2, 3):
        print("usage: python -m tcn_ahrs.export.c_runtime CKPT OUT_DIR [NAME]", file=sys.stderr)
        return 2
    paths = export_c(args[0], args[1], args[2] if len(args) == 3 else None)
    print(paths["h"])
    print(paths["c"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
