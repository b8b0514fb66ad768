"""Scalar kernels written once and run by several backends (the ground floor of the package).

A kernel is plain arithmetic on scalars plus a few named operations taken from an *ops table*
(:mod:`tcn_ahrs.kernels.ops`): ``sqrt``, ``atan2``, ``where``, ... The same source is compiled by
numba with the float ops (evaluation, streaming: ~µs per sample) and run by torch with the tensor
ops on (B,) tensors (training: autograd through the recursion). Branches that depend on data are
written as ``where`` so that both readings of the source compute the same thing.
"""
