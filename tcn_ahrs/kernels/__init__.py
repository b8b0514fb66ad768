"""Scalar kernels written once and run by several backends (the ground floor of the package:
kernels import nothing else of it, ``tests/test_layers.py``).

Three kinds, one rule — the per-sample math exists once:

* *ops-table kernels* (:mod:`~tcn_ahrs.kernels.backbone`): plain arithmetic on scalars plus a few
  named operations taken from an *ops table* (:mod:`tcn_ahrs.kernels.ops`): ``sqrt``, ``atan2``,
  ``where``, ... The same source is compiled by numba with the float ops (evaluation, streaming:
  ~µs per sample), run by torch with the tensor ops on (B,) tensors (training: autograd through
  the recursion) and read by TorchScript (:mod:`tcn_ahrs.kernels.script_ops`). Branches that
  depend on data are written as ``where`` so that every reading computes the same thing.
* *typed scalar kernels* (:mod:`~tcn_ahrs.kernels.quat`, :mod:`~tcn_ahrs.kernels.closed_loop`):
  Python on floats with type annotations, compiled by numba and read by TorchScript as they
  are; they never meet a tensor, so they may branch on data. :mod:`~tcn_ahrs.kernels.classical`
  (one sample of ECF, Mahony, Madgwick) is of this kind for numba alone.
* *array kernels for numba* (:mod:`~tcn_ahrs.kernels.eskf`): one ES-EKF sample in place on small
  preallocated buffers.

The compiled loops that drive them (:mod:`tcn_ahrs.filters.compiled`, :mod:`tcn_ahrs.model.closed_loop_compiled`,
:mod:`tcn_ahrs.streaming`) live with their callers;
the torch filters and the tensor scan of the closed loop are the independent references the
kernels are tested against.
"""
