"""ONNX export of the residual models (``format=onnx``): the stateless step graph and the batch
graph of :mod:`tcn_ahrs.export.stateless`, with the metadata as ONNX ``metadata_props``
(``metadata.json``: the JSON TorchScript exports carry, plus the state's layout), and the two
reference loaders on onnxruntime.

Files (``export_onnx(ckpt, "FILE.onnx", mode="both")``):

* ``FILE_streaming.onnx`` (step graph): inputs ``sample`` (C,) float64, ``dt`` () float64 [s],
  ``state`` (S,) float64 -> outputs ``quat`` (4,) (w, x, y, z, nav_from_body, ENU, w >= 0),
  ``omega`` (3,) [rad/s], ``state_out`` (S,). The state after ``reset(q0)``: metadata
  ``state`` (layout and init; :func:`tcn_ahrs.export.stateless.initial_state`).
  :class:`OnnxStreaming` is the reference loop (reset/step/step_chunk/run, the inputs checked
  before the graph runs; ONNX graphs cannot raise).
* ``FILE.onnx`` (batch graph): inputs ``imu`` (N, C) float64, ``dt`` (N,) float64, ``q0`` (4,)
  float64 -> ``quat`` (N, 4), ``omega`` (N, 3): the step graph inside an ONNX ``Scan`` over the
  samples (N dynamic). :class:`OnnxBatch` checks the inputs and runs it.

The networks run in float32 inside (ONNX Runtime's float32 kernels; the backbone, the head and
the outputs are float64; float64 tan/atan2 as in :func:`tcn_ahrs.kernels.ops.onnx_ops`).
Needs ``pip install 'tcn-ahrs[deploy]'`` (onnx, onnxscript, onnxruntime) to export;
onnxruntime (and numpy) to run.
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Dict, Optional

import numpy as np
import torch

from .inputs import ExportError, output_paths
from .stateless import CheckedBatch, ResidualScan, StatefulLoop, example_inputs, prepare, staged_write

STEP_INPUTS, STEP_OUTPUTS = ["sample", "dt", "state"], ["quat", "omega", "state_out"]
BATCH_INPUTS, BATCH_OUTPUTS = ["imu", "dt", "q0"], ["quat", "omega"]


def _require():
    try:
        import onnx  # noqa: F401
        import onnxscript  # noqa: F401
    except ImportError as e:
        raise ExportError(f"format=onnx needs onnx and onnxscript ({e}): pip install 'tcn-ahrs[deploy]'") from None


def _save(program, path: Path, metadata: Dict) -> None:
    import onnx

    model = program.model_proto
    del model.metadata_props[:]
    onnx.helper.set_model_props(model, {"metadata.json": json.dumps(metadata, sort_keys=True)})
    onnx.save(model, str(path))


def export_onnx(ckpt_path, out_path, mode: str = "both", rate_hz: Optional[float] = None,
                overwrite: bool = False) -> Dict[str, str]:
    """Export a residual checkpoint as ONNX (see the module docstring). Returns {"batch": path,
    "streaming": path} (the ones written). Other model kinds: :class:`ExportError`."""
    _require()
    paths = output_paths(out_path, mode, ".onnx")
    step, md = prepare(ckpt_path, list(paths.values()), "onnx", rate_hz, overwrite, onnx=True)
    x, dt, state = example_inputs(step)
    written: Dict[str, str] = {}
    import logging

    quiet = logging.getLogger("torch.export._trace")  # "always_classified is unsupported": harmless here
    level = quiet.level
    quiet.setLevel(logging.CRITICAL)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*axis name.*will not be used")  # the dynamic N keeps its own name
            _export(step, md, paths, x, dt, state, written)
    finally:
        quiet.setLevel(level)
    return written


def _export(step, md, paths, x, dt, state, written) -> None:
    with torch.no_grad():
        if "streaming" in paths:
            prog = torch.onnx.export(step, (x, dt, state), dynamo=True, input_names=STEP_INPUTS,
                                     output_names=STEP_OUTPUTS, verbose=False)
            meta = dict(md, mode="streaming", graph={"inputs": STEP_INPUTS, "outputs": STEP_OUTPUTS})
            written["streaming"] = staged_write(paths["streaming"], lambda t: _save(prog, t, meta))
        if "batch" in paths:
            n = torch.export.Dim("n", min=2)
            imu = x.unsqueeze(0).expand(4, -1).contiguous()
            prog = torch.onnx.export(ResidualScan(step).eval(), (imu, dt.expand(4).contiguous(), torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)),
                                     dynamo=True, input_names=BATCH_INPUTS, output_names=BATCH_OUTPUTS,
                                     dynamic_shapes={"imu": {0: n}, "dt": {0: n}, "q0": None}, verbose=False)
            meta = dict(md, mode="batch", graph={"inputs": BATCH_INPUTS, "outputs": BATCH_OUTPUTS})
            written["batch"] = staged_write(paths["batch"], lambda t: _save(prog, t, meta))


def read_onnx_metadata(path) -> Dict:
    """The ``metadata.json`` entry of an exported ONNX file's metadata_props (needs onnx)."""
    import onnx

    props = {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}
    if "metadata.json" not in props:
        raise ExportError(f"{path}: not a tcn-ahrs ONNX export (no metadata.json in metadata_props)")
    return json.loads(props["metadata.json"])


def _session(path, threads: int):
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads)
    so.inter_op_num_threads = 1
    # the basic rewrites only: on these graphs of small float64 nodes ORT_ENABLE_ALL's layout and
    # fusion passes cost time per run (broad9's step 2.1 -> 1.85 ms, the ECF's 270 -> 175 us; same outputs)
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_BASIC
    sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    props = sess.get_modelmeta().custom_metadata_map
    if "metadata.json" not in props:
        raise ExportError(f"{path}: not a tcn-ahrs ONNX export (no metadata.json in metadata_props)")
    return sess, json.loads(props["metadata.json"])


class OnnxStreaming(StatefulLoop):
    """The exported step graph on onnxruntime, one session run per sample: ``reset(q0)``,
    ``step(sample, dt)`` -> quat (4,), omega (3,) (float64 numpy), ``step_chunk``, ``run``; the
    inputs checked before the graph runs (a refused sample leaves the state unchanged). Needs
    onnxruntime and numpy (the metadata: ``.metadata``)."""

    def __init__(self, path, threads: int = 1):
        self.session, md = _session(path, threads)
        if md.get("mode") != "streaming":
            raise ExportError(f"{path}: a {md.get('mode')} graph; OnnxStreaming runs the step graph (FILE_streaming.onnx)")
        self._setup(md)

    def _run_graph(self, x, dt, state):
        q, w, s = self.session.run(None, {"sample": x, "dt": np.array(dt), "state": state})
        return q, w, s


class OnnxBatch(CheckedBatch):
    """The exported batch graph on onnxruntime: ``run(imu (N, C), dt, q0)`` -> quat (N, 4),
    omega (N, 3), the inputs checked first."""

    def __init__(self, path, threads: int = 1):
        self.session, md = _session(path, threads)
        if md.get("mode") != "batch":
            raise ExportError(f"{path}: a {md.get('mode')} graph; OnnxBatch runs the batch graph")
        self._setup(md)

    def _run_graph(self, imu, dt, q0):
        q, w = self.session.run(None, {"imu": imu, "dt": dt, "q0": q0})
        return q, w
