"""Generate, write, compile and load the C runtime of a residual checkpoint (the package
docstring, :mod:`tcn_ahrs.export.c`, has the API)."""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import nn

from ...app import staged_files
from ...conventions import INPUT_LIMITS, MAX_DT, MIN_DT
from ...kernels import backbone as K
from ..inputs import ExportError
from .templates import TEMPLATES, _f32, _f64, template  # noqa: F401 (template: read by the tests)
from .cruntime import CRuntime  # noqa: F401 (re-exported: tcn_ahrs.export.c.CRuntime)
from .translate import kernel_c



ROOTS_6 = ("coefficients", "gyro_update", "acc_update", "quat6", "qmul")
ROOTS_9 = ROOTS_6 + ("mag_update", "quat9")
# samples per pass of the networks in name_run (each weight read once per block, not per sample)
BLOCK = 8
# the kernels computed in double in every build (the low-pass filters and their coefficients;
# helpers.h.in WREAL says why)
WIDE_KERNELS = ("butter_terms", "first_order_gain", "bias_noise", "butter", "coefficients", "lp_begin", "lp", "lp_end",
                "lp3", "wrap_pi", "rejection_gain", "initial_gain", "mag_update", "rest_check", "check_window")


def _network_arrays(model: nn.Module):
    """The folded networks in BackboneStreaming's flat layout: (wts float32, head_w, head_b, ints)."""
    from ..fused import fuse_residual
    from ..open_loop import StreamingAHRS
    from ..flat import flat_networks

    fused = fuse_residual(model)
    ts = StreamingAHRS(fused, {})
    n_trust = 2 if int(model.axes) == 9 else 1
    w = torch.cat([ts.out_weight_f64[0:3], fused["trust_weight"][:n_trust] * math.sqrt(0.5)], 0)
    b = torch.cat([fused["out_bias"][0:3], fused["trust_bias"][:n_trust]])
    m = torch.zeros(w.shape[0], int(model.axes), dtype=torch.float64)
    wts, params, ints, rings, _, _ = flat_networks(ts, w, b, m)
    return wts, w.numpy().copy(), b.numpy().copy(), [int(v) for v in ints], int(rings.size), n_trust


def live_networks(model: nn.Module) -> Tuple[str, ...]:
    """The residual model's networks whose output reaches the attitude under its inference knobs:
    "gyro" unless ``gyro_clip`` is 0 (the residual is learned, not applied), "trust" unless
    ``trust_weight`` is 0 (every trust 1). A network that is off is not in the C runtime: no
    weights, no ring buffers, no arithmetic (the outputs are the same floats)."""
    cal, loop = model.calibration, model.backbone
    out = []
    if float(cal.gyro_clip) != 0.0 and float(cal.gyro_scale) != 0.0:
        out.append("gyro")
    if float(loop.trust_weight) != 0.0:
        out.append("trust")
    return tuple(out)


def _keep_networks(wts: np.ndarray, layers: List[List[int]], head_w: np.ndarray, kk: int, live: Sequence[str]):
    """The tap-major weights, layers (g, c_in, c_out, d, span, w_off, b_off, ring_off) and head of
    the networks in ``live`` only (groups: [gyro, trust]; the first layer one group whose outputs
    are the gyro net's then the trust net's; the head's columns the gyro net's last features then
    the trust net's). Returns (wts, layers, head_w, ring floats)."""
    keep = [i for i, n in enumerate(("gyro", "trust")) if n in live]
    if len(keep) == 2 or not layers:
        return wts, layers, head_w, sum(sp * g * cin for g, cin, _, _, sp, *_ in layers)
    if not keep:
        return np.zeros(1, np.float32), [], np.zeros((head_w.shape[0], 1)), 0
    gi = keep[0]
    parts, out, size, ring = [], [], 0, 0
    for li, (g, cin, cout, d, span, wo, bo, _) in enumerate(layers):
        w = wts[wo:wo + g * kk * cin * cout].reshape(g, kk * cin, cout)
        b = wts[bo:bo + g * cout].reshape(g, cout)
        if li == 0:  # one group: the live net's half of the outputs
            half = cout // 2
            w, b, cout = w[:, :, gi * half:(gi + 1) * half], b[:, gi * half:(gi + 1) * half], half
        else:
            w, b = w[gi:gi + 1], b[gi:gi + 1]
        out.append([1, cin, cout, d, span, size, size + w.size, ring])
        parts += [np.ascontiguousarray(w).reshape(-1), b.reshape(-1)]
        size += w.size + b.size
        ring += span * cin
    n_feat = head_w.shape[1] // 2
    return (np.concatenate(parts).astype(np.float32), out,
            np.ascontiguousarray(head_w[:, gi * n_feat:(gi + 1) * n_feat]), ring)


def generate_c(model: nn.Module, name: str) -> Dict[str, Any]:
    """The C runtime of a residual model (a :class:`~tcn_ahrs.model.ahrs.LearnedAHRS` with
    ``loop: backbone``): {"h": header text, "c": source text, "info": sizes}."""
    from ..flat import ERF_P, ERF_Q, LAYOUT_HEADER, LAYOUT_PER_LAYER

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
    wts, head_w, head_b, ints, n_ring, n_trust = _network_arrays(model)
    kk, nl = ints[1], ints[2]
    layers = [ints[LAYOUT_HEADER + LAYOUT_PER_LAYER * i:LAYOUT_HEADER + LAYOUT_PER_LAYER * (i + 1)] for i in range(nl)]
    # weights tap-major per group, (groups, K c_in, c_out): conv's layout
    wt = wts.copy()
    for g, cin, cout, d, span, wo, bo, ro in layers:
        n_tap = kk * cin
        wt[wo:wo + g * cout * n_tap] = wts[wo:wo + g * cout * n_tap].reshape(g, cout, n_tap).transpose(0, 2, 1).reshape(-1)
    live = live_networks(model)
    wts, layers, head_w, n_ring = _keep_networks(wt, layers, head_w, kk, live)
    nl, n_head = len(layers), head_w.shape[0]
    n_feat = head_w.shape[1]
    width = max([c, n_feat] + [g * cout for g, _, cout, *_ in layers] + [cin * g for g, cin, *_ in layers])
    calls = [] if layers else ["    (void)st; (void)out;  /* both networks are off (live_networks): the backbone alone */"]
    for li, (g, cin, cout, d, span, wo, bo, ro) in enumerate(layers):
        calls.append(f"    /* layer {li}: {g} group(s), {cin} -> {cout} channels, dilation {d} */\n"
                     f"    conv(st->ring + {ro}, &st->pos[{li}], h, out, ns, {g}, {cin}, {cout}, {d}, {span}, {wo}, {bo});\n"
                     f"    for (n = 0; n < ns; n++) for (i = 0; i < {g * cout}; i++) h[n][i] = out[n][i];")
    up = name.upper()
    p = list(loop.params.vector())
    s0 = K.initial_state(loop.params)
    bias0 = (loop.bias_prior * loop.bias_init.detach().double()).numpy()
    kernels, _ = kernel_c(K, f"{name}_bb_", ROOTS_9 if use_mag else ROOTS_6, WIDE_KERNELS)
    subst = {
        "NAME": name, "UP": up, "C": str(c), "N_STATE": str(K.N_STATE), "N_COEFF": str(K.N_COEFF),
        "N_PARAM": str(K.N_PARAM), "N_RING": str(max(n_ring, 1)), "N_LAYERS": str(max(nl, 1)), "K": str(kk),
        "NL": str(nl), "N_FEAT": str(n_feat), "N_HEAD": str(n_head), "N_TRUST": str(n_trust), "WIDTH": str(width),
        "N_WTS": str(wts.size), "USE_MAG": "1" if use_mag else "0",
        "LAYER_CALLS": "\n".join(calls), "BLOCK": str(BLOCK),
        "WTS": _f32(wts), "HEAD_W": _f64(head_w), "HEAD_B": _f64(head_b), "PARAMS": _f64(p), "STATE0": _f64(s0),
        "BIAS0": _f64(bias0), "LIMITS": _f64(INPUT_LIMITS[:c]), "MAX_DT": repr(float(MAX_DT)), "MIN_DT": repr(float(MIN_DT)),
        "ERF_P": _f32(ERF_P), "ERF_Q": _f32(ERF_Q), "N_ERF_P": str(len(ERF_P)), "N_ERF_Q": str(len(ERF_Q)),
        "GYRO_SCALE": repr(float(cal.gyro_scale)), "GYRO_CLIP": repr(float(cal.gyro_clip)),
        "TRUST_MAX": repr(float(loop.trust_max)), "TRUST_W": repr(float(loop.trust_weight)),
        "ACC_SCALE": repr(float(loop.acc_trust_scale)), "MAG_SCALE": repr(float(loop.mag_trust_scale)),
        "BIAS_SCALE": repr(float(loop.bias_trust_scale)), "BIAS_POWER": repr(float(loop.bias_trust_power)),
        "S_GQ": str(K.S_GQ), "S_BIAS": str(K.S_BIAS), "S_REST": str(K.S_REST), "S_MAGDIST": str(K.S_MAGDIST),
        "S_GFROZEN": str(K.S_GFROZEN), "S_AFROZEN": str(K.S_AFROZEN), "S_GCLIPPED": str(K.S_GCLIPPED),
        "S_ACLIPPED": str(K.S_ACLIPPED), "S_GAP": str(K.S_GAP), "S_MFROZEN": str(K.S_MFROZEN),
        "KERNELS": kernels,
    }

    def fill(text: str) -> str:
        return re.sub(r"@(\w+)@", lambda mm: subst[mm.group(1)], text)

    info = {"axes": c, "use_mag": use_mag, "weights_float32": int(wts.size), "head_values": int(head_w.size + head_b.size),
            "ring_floats": n_ring, "layers": layers, "weight_bytes": int(wts.size * 4) if layers else 0,
            "live_networks": list(live),
            # multiply-adds of the generated networks x 2 (the GELUs and the filter not counted)
            "flops_per_sample": int(sum(2 * g * kk * cin * cout for g, cin, cout, *_ in layers)
                                    + (2 * head_w.size if layers else 0)),
            "head_bytes_double": int((head_w.size + head_b.size) * 8)}
    return {"h": fill(template("model.h.in")), "c": fill(template("model.c.in")), "info": info}


def export_c(ckpt_path, out_dir, prefix: Optional[str] = None, overwrite: bool = False) -> Dict[str, str]:
    """Generate ``<prefix>.h`` and ``<prefix>.c`` (prefix: the checkpoint's stem) in ``out_dir``
    from a residual checkpoint or a classical estimator file of a family with a C runtime (the
    ECF: :mod:`tcn_ahrs.export.c.classical`); closed-loop and open-loop (paper) checkpoints and
    the other classical families raise ExportError.
    Existing files are refused unless ``overwrite``; the two are written as a set (hidden
    temporary names, renamed together at the end: never a header of one checkpoint beside the
    source of another)."""
    from ...checkpoint import model_from_checkpoint

    name = prefix or re.sub(r"\W", "_", Path(ckpt_path).stem)
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
        raise ExportError(f"C export: name {name!r} is not a C identifier (letters, digits, _)")
    out = Path(out_dir)
    paths = {"h": out / f"{name}.h", "c": out / f"{name}.c"}
    existing = [str(p_) for p_ in paths.values() if p_.exists()]
    if existing and not overwrite:
        raise ExportError(f"export: {', '.join(existing)} already exist(s): choose another out= or pass overwrite=true")
    if str(ckpt_path).endswith(".json"):  # a classical estimator chosen by tcn-ahrs search
        from ...estimators.families import read_estimator
        from .classical import generate_classical_c

        gen = generate_classical_c(read_estimator(ckpt_path), name, source=Path(ckpt_path).name)
    else:
        gen = generate_c(model_from_checkpoint(ckpt_path), name)
    return staged_files(paths, lambda k, tmp: tmp.write_text(gen[k]), lambda m: ExportError(f"export: {m}"))


def compile_c(c_path, out_so, real: str = "float", cc: Optional[str] = None, flags: Sequence[str] = ()) -> str:
    """Build the generated source as a shared library with the system compiler (the strict
    flags the tests use, then ``flags``, e.g. ``["-march=native"]``); ``real``: the backbone's
    scalar type. Returns the library's path."""
    import shutil
    import subprocess

    cc = cc or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        raise ExportError("C export: no C compiler (cc) found")
    cmd = [cc, "-std=c99", "-pedantic", "-O2", "-Wall", "-Wextra", "-Wshadow", "-Wdouble-promotion", "-Werror",
           "-shared", "-fPIC", f"-DTCN_AHRS_REAL={real}", *flags,
           str(c_path), "-o", str(out_so), "-lm"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise ExportError(f"C export: {' '.join(cmd)} failed:\n{r.stderr[-4000:]}")
    return str(out_so)
