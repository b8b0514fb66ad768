"""The learned closed loop one sample (or one chunk) per call, compiled by numba: the library's
fast streaming runtime, beside the exported TorchScript module.

Why two: the exported streaming module (:class:`tcn_ahrs.export.ClosedLoopStreaming`) needs only
torch, but TorchScript interprets every tensor op (~1 µs each, ~40 per sample for three
four-layer TCNs) and every scalar op (~25 ns) of the filter, which bounds it near 10 k samples/s
(``python scripts/benchmark.py speed``). Here the same per-sample work — the ring buffers and
matrix-vector products of the networks, the head, the rest detector and the filter update —
runs as one compiled function: a few µs per sample, called from Python.

Numbers: the same as the exported module (the weights come from the same folding:
:class:`~tcn_ahrs.export.ClosedLoopStreaming`, BatchNorm folded, input normalisation in the
first layer, GELU as ``u (1 + erf(u))`` on scaled pre-activations; the filter is
:mod:`tcn_ahrs.kernels.closed_loop`'s scalar functions), with the networks in float64 instead
of float32; ``tests/test_streaming.py`` holds it to the evaluation model within the export's
parity bound. Frames and units as everywhere: raw body-frame readings (rad/s, m/s², µT),
``nav_from_body`` quaternions (w, x, y, z), ENU.

    stream = CompiledStreaming(model)            # a LearnedAHRS with the closed loop
    stream.reset(q0)
    quat, omega = stream.step(sample, dt)        # (4,), (3,) float64 numpy
    quats, omegas = stream.step_chunk(samples, dt)

numba is optional (``[fast]``, in ``[dev]``): without it this class raises ImportError.

Modules: :mod:`~tcn_ahrs.streaming.closed_loop` (:class:`CompiledStreaming`),
:mod:`~tcn_ahrs.streaming.backbone` (:class:`BackboneStreaming`, the residual model),
:mod:`~tcn_ahrs.streaming.networks` (the networks on ring buffers, shared by both) and
:mod:`~tcn_ahrs.export.contract` (the input checks every runtime applies).
"""
from .backbone import BackboneStreaming
from .closed_loop import CompiledStreaming
from .networks import AVAILABLE, erf_rational

__all__ = ["CompiledStreaming", "BackboneStreaming", "erf_rational", "AVAILABLE"]
