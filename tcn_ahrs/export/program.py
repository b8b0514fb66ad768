"""``torch.export`` of the residual models (``format=export``): the stateless step and the batch
graph of :mod:`tcn_ahrs.export.stateless` as ``ExportedProgram`` files (``torch.export.save``,
``.pt2``) with the same ``metadata.json`` as the other formats (an extra file), and the loaders.

Files (``export_program(ckpt, "FILE.pt2", mode="both")``):

* ``FILE_streaming.pt2``: ``quat (4,), omega (3,), state_out (S,) = program(sample (C,),
  dt (), state (S,))``, float64 (the state: metadata ``state``). :class:`ExportedStreaming`
  carries the state with the streaming contract (reset/step/step_chunk/run, inputs checked
  before the program runs, a refused sample leaves the state unchanged).
* ``FILE.pt2``: ``quat (N, 4), omega (N, 3) = program(imu (N, C), dt (N,), q0 (4,))``: the step
  inside a ``scan`` over the samples (N dynamic). :class:`ExportedBatch` checks and runs it.

torch alone loads them (``torch.export.load(path).module()``); the networks run in float32, the
rest in float64, the same ops as the TorchScript modules.
"""
from __future__ import annotations

import json
from typing import Dict, Optional

import numpy as np
import torch

from .inputs import ExportError, output_paths
from .stateless import CheckedBatch, ResidualScan, StatefulLoop, example_inputs, prepare, staged_write



def export_program(ckpt_path, out_path, mode: str = "both", rate_hz: Optional[float] = None,
                   overwrite: bool = False) -> Dict[str, str]:
    """Export a residual checkpoint with ``torch.export`` (see the module docstring). Returns
    {"batch": path, "streaming": path} (the ones written). Other model kinds: ExportError."""
    paths = output_paths(out_path, mode, ".pt2")
    step, md = prepare(ckpt_path, list(paths.values()), "torch.export", rate_hz, overwrite, onnx=False)
    x, dt, state = example_inputs(step)
    written: Dict[str, str] = {}
    with torch.no_grad():
        if "streaming" in paths:
            ep = torch.export.export(step, (x, dt, state))
            meta = json.dumps(dict(md, mode="streaming"), sort_keys=True)
            written["streaming"] = staged_write(
                paths["streaming"], lambda t: torch.export.save(ep, str(t), extra_files={"metadata.json": meta}))
        if "batch" in paths:
            n = torch.export.Dim("n", min=2)
            imu = x.unsqueeze(0).expand(4, -1).contiguous()
            ep = torch.export.export(ResidualScan(step).eval(),
                                     (imu, dt.expand(4).contiguous(), torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)),
                                     dynamic_shapes={"imu": {0: n}, "dt": {0: n}, "q0": None})
            meta = json.dumps(dict(md, mode="batch"), sort_keys=True)
            written["batch"] = staged_write(
                paths["batch"], lambda t: torch.export.save(ep, str(t), extra_files={"metadata.json": meta}))
    return written


def _load(path):
    extra = {"metadata.json": ""}
    ep = torch.export.load(str(path), extra_files=extra)
    if not extra["metadata.json"]:
        raise ExportError(f"{path}: not a tcn-ahrs torch.export file (no metadata.json)")
    return ep, json.loads(extra["metadata.json"])


def read_program_metadata(path) -> Dict:
    """The ``metadata.json`` of an exported ``.pt2`` file."""
    return _load(path)[1]


class ExportedStreaming(StatefulLoop):
    """The exported step program (``FILE_streaming.pt2``) with the streaming contract:
    ``reset(q0)``, ``step(sample, dt)`` -> quat (4,), omega (3,) float64 numpy, ``step_chunk``,
    ``run``; inputs checked before the program runs (state unchanged on a refused sample)."""

    def __init__(self, path):
        ep, md = _load(path)
        if md.get("mode") != "streaming":
            raise ExportError(f"{path}: a {md.get('mode')} program; ExportedStreaming runs the step (FILE_streaming.pt2)")
        self.program = ep.module()
        self._setup(md)

    def reset(self, q0) -> None:
        super().reset(q0)
        self.state = torch.from_numpy(self.state)

    def _run_graph(self, x, dt, state):
        with torch.no_grad():
            q, w, s = self.program(torch.from_numpy(np.ascontiguousarray(x)), torch.tensor(dt, dtype=torch.float64), state)
        return q.numpy(), w.numpy(), s


class ExportedBatch(CheckedBatch):
    """The exported batch program (``FILE.pt2``): ``run(imu (N, C), dt, q0)`` -> quat (N, 4),
    omega (N, 3) float64 numpy, the inputs checked first."""

    def __init__(self, path):
        ep, md = _load(path)
        if md.get("mode") != "batch":
            raise ExportError(f"{path}: a {md.get('mode')} program; ExportedBatch runs the batch program (FILE.pt2)")
        self.program = ep.module()
        self._setup(md)

    def _run_graph(self, imu, dt, q0):
        with torch.no_grad():
            q, w = self.program(torch.from_numpy(np.array(imu)), torch.from_numpy(np.array(dt)),
                                torch.from_numpy(np.array(q0)))
        return q.numpy(), w.numpy()
