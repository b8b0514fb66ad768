"""Deployment export: self-contained TorchScript modules (batch and streaming) of a trained
:class:`~tcn_ahrs.model.ahrs.LearnedAHRS`. The residual models also export as ONNX
(:func:`tcn_ahrs.export.onnx_step.export_onnx`) and as ``torch.export`` programs
(:func:`tcn_ahrs.export.program.export_program`): a stateless step graph and a batch graph
(:mod:`tcn_ahrs.export.stateless`; ``scripts/export.py format=onnx|export``).

Contract (also in the README and saved inside every exported file as ``metadata.json`` and as
the string returned by the module's ``metadata()`` method):

* ``python scripts/export.py ckpt=PATH out=FILE.pt [mode=batch|streaming|both]`` writes
  TorchScript that needs only ``torch`` to load and run (no ``tcn_ahrs`` import).
  ``mode=both`` (default) writes the batch module to ``FILE.pt`` and the streaming module to
  ``FILE_streaming.pt``.
* Inputs (the checkpoint's units and frames): raw IMU samples with channels
  gyro x,y,z [rad/s], accelerometer x,y,z [m/s^2, specific force: +9.81 along the body axis
  pointing up at rest] and, for 9-axis models, magnetometer x,y,z [uT]; all in the body
  (sensor) frame. Time step ``dt`` [s] = time since the previous sample. Initial attitude
  ``q0`` = Hamilton quaternion (w, x, y, z), ``nav_from_body``, navigation frame ENU.
* Batch module: ``quat, omega = m(imu (N, C), dt (float or (N,)), q0 (4,))`` ->
  attitude quaternions (N, 4) (w, x, y, z; w >= 0; nav_from_body, ENU; ``quat[0] == q0``)
  and corrected angular rate ω̂ (N, 3) [rad/s, body frame] (paper Eq. 22), float64.
  ``dt[0]`` is not used (the first rate sample does not move the attitude, Eq. 3).
* Streaming module: ``m.reset(q0)``; then per sample ``quat, omega = m.step(sample (C,), dt)``
  -> (4,), (3,) float64; the same numbers as the batch module, sample by sample (the
  ``dt`` of the first call after ``reset`` is not used). ``m.run(imu, dt, q0)`` = reset +
  step over a whole sequence in TorchScript. Closed-loop modules also have
  ``m.step_chunk(samples (k, C), dt)`` -> (k, 4), (k, 3): k samples per call on the same state,
  the networks as convolutions over the chunk (equal to k steps to float32 round-off).
  The fastest way to stream from Python is :class:`tcn_ahrs.streaming.CompiledStreaming`
  (numba; same contract, numpy in and out), measured beside this module by
  ``python scripts/benchmark.py speed``. State: one ring buffer per convolution layer
  (``dilation * (kernel - 1)`` past inputs, zeros after ``reset`` = the batch model's causal
  zero padding), the ECF's pre-integrated attitude(s) C̃ (Eq. 25) and the integrated attitude.
* Input checks (every module): wrong shapes, a NaN/inf reading, or a time step after the first
  that is not finite and > 0 raise ``ValueError`` naming the input and the index; a streaming
  step checks before it changes any state, so after the error the module continues as if that
  sample had not been given (``reset(q0)`` also starts afresh).
* ``m.metadata()`` (and the ``metadata.json`` extra file) is JSON with: axes, channel names,
  variant, model config, the rate the model was trained at (``rate_hz``, null when the
  checkpoint does not record it), units, frames, quaternion order, receptive field, the input
  normalisation (included in the module), the tcn_ahrs version, the checkpoint's sha256.

Numerics: the TCN runs in float32 (``net_dtype``; BatchNorm folded into the convolutions,
dropout off), the calibration matrices, the ECF and the attitude integration in float64
(quaternions, blocked prefix-product scan). The parity bounds (batch vs streaming vs the eager
model; float64 networks vs eager float64) are the tolerances asserted in ``tests/test_export.py``
and ``tests/test_export_closed_loop.py``. ``net_dtype=bfloat16`` (batch module only, opt-in:
``export_checkpoint(..., mode="batch", net_dtype="bfloat16")``) runs the convolutions in bfloat16
(faster on AVX512-BF16 CPUs) and is NOT within those bounds (docs/performance.md).

Exported modules are frozen (:func:`torch.jit.freeze`, public methods kept): flags and
weights become constants. The streaming step folds the input normalisation into the first
layer and computes GELU as ``u (1 + erf(u))`` on sqrt(1/2)-scaled pre-activations (see
:func:`~tcn_ahrs.export.fused.gelu_scaled`), identical math with fewer TorchScript ops.
"""
import json
import os
import warnings
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Union

import torch
from torch import nn

from ..app import staged_files
from ..conventions import NETWORK_DTYPE
from .closed_loop import ClosedLoopBatch, ClosedLoopStreaming
from .fused import hamilton_table, fuse_model, quat_cumprod, quat_integrate
from .inputs import MODES, ExportError
from .metadata import CHANNELS, build_metadata, checkpoint_export_meta, file_sha256  # noqa: F401 (re-exported)
from .open_loop import NET_DTYPES, BatchAHRS, StreamingAHRS

__all__ = ["export_main", "export_batch", "export_streaming", "export_checkpoint", "read_metadata", "build_metadata",
           "file_sha256", "streaming_path", "ExportError", "BatchAHRS", "StreamingAHRS", "ClosedLoopBatch",
           "ClosedLoopStreaming", "fuse_model", "quat_cumprod", "quat_integrate", "MODES", "NET_DTYPES",
           "CHANNELS", "hamilton_table"]

def _script(module: nn.Module, freeze: bool = True):
    """TorchScript ``module`` (eval mode). ``freeze``: :func:`torch.jit.freeze` it, keeping the
    public methods: attributes that are never mutated (flags, weights, layer lists) become
    constants, dead branches go, and the per-sample ``step`` runs ~8% faster."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # torch.jit.script is deprecated in 2.13
        scripted = torch.jit.script(module.eval())
        if not freeze:
            return scripted
        keep = [n for n in ("metadata", "errors", "corrected_rate", "reset", "step", "step_chunk", "run") if scripted._c._has_method(n)]
        # state written in place by several methods stays one attribute: frozen, each method would
        # get its own constant copy once saved and loaded (reset would not clear what step_chunk reads)
        keep += [n for n in ("first_buffer", "ring_buffers", "rest_ring", "backbone_state", "coeff")
                 if scripted._c.hasattr(n)]
        return torch.jit.freeze(scripted, preserved_attrs=keep)


def _export(cls, model: nn.Module, path, meta, net_dtype: torch.dtype, mode: str):
    model = model.eval()
    md = build_metadata(model, mode, meta, net_dtype)
    if getattr(model, "backbone", None) is not None:
        if net_dtype != torch.float32:
            raise ExportError("the residual model's export runs its networks in float32 (net_dtype=float32)")
        from .backbone import ResidualBatch, ResidualStreaming

        module = (ResidualStreaming if mode == "streaming" else ResidualBatch)(model, md).eval()
    elif getattr(model, "closed", None) is not None:
        if net_dtype != torch.float32:
            raise ExportError("the closed-loop export runs its networks in float32 (net_dtype=float32)")
        cls = ClosedLoopStreaming if mode == "streaming" else ClosedLoopBatch
        module = cls(model, md).eval()
    else:
        module = cls(fuse_model(model), md, net_dtype).eval()
    scripted = _script(module)
    try:
        staged_files({"module": Path(path)}, lambda _, tmp: torch.jit.save(
            scripted, str(tmp), _extra_files={"metadata.json": scripted.metadata()}), _export_error)
    except RuntimeError as e:  # torch's writer reports a read-only folder or a full disk this way
        raise ExportError(f"export: cannot write {path}: {e}") from None
    return scripted


def export_batch(model: nn.Module, path, meta: Optional[Mapping[str, Any]] = None,
                 net_dtype: torch.dtype = NETWORK_DTYPE):
    """Script ``model`` (a :class:`LearnedAHRS`, eval mode) as a :class:`BatchAHRS` and save it
    to ``path`` (with ``metadata.json``). Returns the scripted module."""
    return _export(BatchAHRS, model, path, meta, net_dtype, "batch")


def export_streaming(model: nn.Module, path, meta: Optional[Mapping[str, Any]] = None,
                     net_dtype: torch.dtype = NETWORK_DTYPE):
    """Script ``model`` as a :class:`StreamingAHRS` and save it to ``path``. Returns the module."""
    return _export(StreamingAHRS, model, path, meta, net_dtype, "streaming")


def streaming_path(out) -> Path:
    """Where ``mode=both`` writes the streaming module: ``FILE.pt`` -> ``FILE_streaming.pt``."""
    out = Path(out)
    return out.with_name(f"{out.stem}_streaming{out.suffix or '.pt'}")


def export_checkpoint(ckpt_path, out_path, mode: str = "both", rate_hz: Optional[float] = None,
                      net_dtype: Union[str, torch.dtype] = "float32", overwrite: bool = False) -> Dict[str, str]:
    """Load a checkpoint (``weights_only=True``, :func:`tcn_ahrs.checkpoint.model_from_checkpoint`)
    and export it. Returns {"batch": path, "streaming": path} (the ones written).

    The files are written as a set: each to a hidden temporary name first, all renamed into place
    at the end (a killed export leaves none of them; never a batch file of one checkpoint beside a
    streaming file of another). Existing files are refused unless ``overwrite``.

    Raises :class:`tcn_ahrs.checkpoint.CheckpointError` for a missing, corrupt or foreign file."""
    from ..checkpoint import checkpoint_meta, load_checkpoint

    if mode not in MODES:
        raise ValueError(f"export mode {mode!r}: expected one of {MODES}")
    if isinstance(net_dtype, str):
        if net_dtype not in ("float32", "float64", "bfloat16"):
            raise ValueError(f"net_dtype {net_dtype!r}: expected 'float32', 'float64' or 'bfloat16'")
        net_dtype = getattr(torch, net_dtype)
    if net_dtype == torch.bfloat16 and mode != "batch":
        raise ValueError(f"net_dtype bfloat16 is for mode=batch only (got mode={mode})")
    ck_meta = checkpoint_meta(load_checkpoint(ckpt_path), ckpt_path)  # a missing checkpoint is named first
    targets: Dict[str, Path] = {}
    if mode in ("batch", "both"):
        targets["batch"] = Path(out_path)
    if mode in ("streaming", "both"):
        targets["streaming"] = Path(out_path) if mode == "streaming" else streaming_path(out_path)
    existing = [str(t) for t in targets.values() if t.exists()]
    if existing and not overwrite:
        raise ExportError(f"export: {', '.join(existing)} already exist(s): choose another out= or pass overwrite=true")
    folder = Path(out_path).parent
    folder.mkdir(parents=True, exist_ok=True)
    if not os.access(folder, os.W_OK):
        raise ExportError(f"export: cannot write into {folder} (read-only?): choose another out=")
    model, meta = checkpoint_export_meta(ckpt_path, ck_meta, rate_hz)
    return staged_files(targets, lambda kind, tmp: (export_batch if kind == "batch" else export_streaming)(
        model, tmp, meta, net_dtype), _export_error)


def _export_error(message: str) -> ExportError:
    return ExportError(f"export: {message}")


def read_metadata(path) -> Dict[str, Any]:
    """The ``metadata.json`` of an exported TorchScript file, read from its archive (where
    ``torch.jit.save`` puts ``_extra_files``: ``<archive>/extra/``) without loading the module:
    loading compiles its TorchScript, ~7 s for a residual model's kernel."""
    import zipfile

    try:
        with zipfile.ZipFile(str(path)) as z:
            name = next((n for n in z.namelist() if n.endswith("/extra/metadata.json")), None)
            if name is not None:
                return json.loads(z.read(name))
    except zipfile.BadZipFile:
        pass
    raise _export_error(f"{path}: not a file tcn-ahrs export wrote (no metadata.json in a TorchScript archive)")




FORMATS = ("torchscript", "onnx", "export", "c")


def export_main(cfg) -> Dict[str, Path]:
    """``tcn-ahrs export ckpt=PATH out=FILE [format=torchscript|onnx|export|c] [mode=batch|streaming|both]
    [rate=HZ]`` (``conf/export.yaml``): writes the files and prints one line per file."""
    from ..config import ExportConfig, keys

    KEYS = keys(ExportConfig)  # conf/export.yaml's keys: tcn_ahrs/config/scripts.py
    unknown = set(cfg) - KEYS
    if unknown:
        raise ValueError(f"export: unknown key(s) {sorted(unknown)}; expected a subset of {sorted(KEYS)}")
    if not cfg.ckpt or not cfg.out:
        raise ValueError("export: pass ckpt=PATH (a checkpoint written by tcn-ahrs train, or default6 / default9: "
                         "what tcn-ahrs evaluate runs without ckpt=) and out=FILE.pt")
    if str(cfg.ckpt) == "default":
        raise ValueError("export: ckpt=default: name the axes, ckpt=default6 or ckpt=default9")
    from .default import DEFAULTS, write_default_checkpoint

    if str(cfg.ckpt) in DEFAULTS and not Path(str(cfg.ckpt)).exists():
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            cfg = dict(cfg)
            cfg["ckpt"] = str(write_default_checkpoint(str(cfg["ckpt"]), tmp))
            from omegaconf import OmegaConf

            return export_main(OmegaConf.create(cfg))
    fmt = str(cfg.get("format", "torchscript"))
    if fmt not in FORMATS:
        raise ValueError(f"export: format={fmt!r}: expected one of {FORMATS}")
    if str(cfg.ckpt).endswith(".json") and fmt == "torchscript":
        raise ValueError(f"export: {cfg.ckpt} is a classical estimator chosen by tcn-ahrs search; format={fmt} holds "
                         "learned checkpoints only; format=c, onnx and export hold the tuned ECF (run the others "
                         "with tcn_ahrs.estimators.families.load_estimator)")
    if fmt == "c":
        from .c import export_c

        out = Path(str(cfg.out))
        if out.suffix != ".c":
            raise ValueError(f"export format=c: out={out} must name the C file, e.g. out=exports/{Path(str(cfg.ckpt)).stem}.c")
        written = export_c(str(cfg.ckpt), out.parent, out.stem, overwrite=bool(cfg.get("overwrite", False)))
        print(f"c: {written['c']} + {written['h']}  (C99, no dependencies; tcn_ahrs/export/c/, examples/c/)")
        return {k: Path(v) for k, v in written.items()}
    rate = None if cfg.rate is None else float(cfg.rate)
    overwrite = bool(cfg.get("overwrite", False))
    if fmt != "torchscript":
        if str(cfg.net_dtype) != "float32":
            raise ValueError(f"export: format={fmt} runs the networks in float32 (net_dtype=float32)")
        if fmt == "onnx":
            from .onnx_step import export_onnx as export_fn, read_onnx_metadata as read_format_metadata
        else:
            from .program import export_program as export_fn, read_program_metadata as read_format_metadata
        written = export_fn(str(cfg.ckpt), str(cfg.out), str(cfg.mode), rate_hz=rate, overwrite=overwrite)
        _print_written(written, read_format_metadata)
        return {k: Path(v) for k, v in written.items()}
    written = export_checkpoint(str(cfg.ckpt), str(cfg.out), str(cfg.mode), rate_hz=rate,
                                net_dtype=str(cfg.net_dtype), overwrite=overwrite)
    _print_written(written, read_metadata)
    return written


def _print_written(written: Mapping[str, Any], read) -> None:
    """One line per written file from its own metadata."""
    for mode, path in written.items():
        md = read(path)
        rate = "{:g}-{:g}".format(*md["rate_range_hz"]) if md.get("rate_range_hz") else md["rate_hz"]
        print(f"{mode}: {path}  ({md['variant']}, {md['axes']}-axis, preintegration {md['preintegration']}, "
              f"receptive field {md['receptive_field']}, rate {rate} Hz, "
              f"checkpoint sha256 {md['checkpoint_sha256'][:12]}...)")
