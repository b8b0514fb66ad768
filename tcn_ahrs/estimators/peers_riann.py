"""RIANN (Weber, Gühmann & Seel, 2021) as a peer: the published ONNX GRU, 6-axis, heading-free.

Its conventions (model lookup, batch vs streaming API, frames) are tabled, with every other
peer's, in :mod:`tcn_ahrs.estimators.peers`; ``tests/test_peers.py`` checks them.
"""
from __future__ import annotations

import importlib
from pathlib import Path
from typing import Optional

import numpy as np

from ..sequence import ImuSequence
from . import peers
from .base import EstimatorOutput
from .peers import constant_period, Peer, to_enu, is_constant_period, run_resampled
from .registry import register

__all__ = ["RIANNEstimator"]


# RIANN has no tunable parameters.
@register("riann", "peer", axes=(6,))
class RIANNEstimator(Peer):
    """RIANN (Weber, Gühmann & Seel, AI 2021), 6-axis, ``pip install riann``.

    No parameters besides ``onnx_path`` (default: the model shipped inside the installed
    package, passed explicitly because riann 0.2.0 does not find it on its own) and
    ``streaming``: ``False`` (default) runs the batch API ``predict(acc, gyr, fs)``,
    ``True`` calls ``predict_step`` per sample (same result; for speed benchmarks).
    Heading-free: ``heading_free = True`` (score inclination only).
    """

    base_name = "riann"
    heading_free = True

    def __init__(self, axes: int = 6, onnx_path: Optional[str] = None, streaming: bool = False):
        if int(axes) != 6:
            raise ValueError(f"axes: RIANN is a 6-axis estimator (no magnetometer), got axes={axes!r}")
        riann = peers._import_peer("riann", "riann", "riann6d")
        peers._import_peer("riann.riann", "riann", "riann6d")
        if onnx_path is None:
            onnx_path = str(Path(riann.__file__).resolve().parent / "riann.onnx")
        if not Path(onnx_path).is_file():
            raise FileNotFoundError(f"riann: ONNX model not found at {onnx_path}")
        super().__init__(6, dict(onnx_path=str(onnx_path), streaming=bool(streaming)))
        self._model = importlib.import_module("riann.riann").RIANN(str(onnx_path))

    def run(self, seq: ImuSequence, init_quat: Optional[np.ndarray] = None,
            init_index: int = 0) -> EstimatorOutput:
        if not is_constant_period(seq):  # RIANN takes one fixed rate: run it on a uniform grid
            return run_resampled(self, seq, init_quat, init_index)
        acc = np.ascontiguousarray(seq.accel, dtype=np.float64)
        gyr = np.ascontiguousarray(seq.gyro, dtype=np.float64)
        fs = 1.0 / constant_period(seq, self.name)
        if self.params["streaming"]:
            self._model.reset_state()
            self._model.set_sampling_rate(fs)
            quat = np.stack([self._model.predict_step(acc[k], gyr[k]) for k in range(len(seq))])
        else:
            quat = self._model.predict(acc, gyr, fs)
        return EstimatorOutput(to_enu(np.asarray(quat, dtype=np.float64), "ENU"), {})
