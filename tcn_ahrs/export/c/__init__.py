"""``format: c``: a dependency-free C99 runtime of a residual checkpoint or of a tuned ECF file of
``tcn-ahrs search`` (:mod:`tcn_ahrs.export.c.classical`) (``<name>.h`` + ``<name>.c``).

What is generated and from where (nothing of the math restated by hand):

* the backbone's C is translated from :mod:`tcn_ahrs.kernels.backbone`'s own source (and the
  quaternion kernels it binds) by :mod:`tcn_ahrs.export.c.translate`, as numba and TorchScript
  (:mod:`tcn_ahrs.kernels.script_ops`) compile that same source;
* the networks are the folded float32 weights of :func:`~tcn_ahrs.export.fused.fuse_residual` in
  the flat layout of :func:`tcn_ahrs.export.flat.flat_networks` (what
  :class:`~tcn_ahrs.streaming.BackboneStreaming` runs), read by one generic ring-buffer dilated
  causal convolution (``model.c.in``) over up to ``runtime.BLOCK`` samples per pass (``name_run``;
  ``name_step`` passes one: the same floats), its sums on GNU C vectors with an AVX2 copy chosen at
  run time on x86 (no fused multiply-add: every path the scalar loop's floats); GELU as
  ``u (1 + erf(u))`` with the rational erf of :func:`tcn_ahrs.export.flat.erf_rational` (its
  coefficients written in);
* the per-sample composition (networks -> gyro residual and trusts -> backbone calls -> output)
  is the template ``model.c.in``, written once after ``_backbone_steps`` of :mod:`tcn_ahrs.streaming.backbone`
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
reading, skipped as VQF does), ``NAME_FLAG_GYRO_FROZEN`` / ``NAME_FLAG_ACC_FROZEN`` (the sensor's
three readings repeated exactly for ``frozen_time``: a frozen gyro is not integrated, a frozen
accelerometer not trusted), ``NAME_FLAG_GYRO_CLIPPED`` / ``NAME_FLAG_ACC_CLIPPED`` (an axis repeats
its largest magnitude so far above the clip floor: saturated; a clipped accelerometer is not trusted),
``NAME_FLAG_GAP`` (``dt`` over ``gap_factor`` × the typical step: samples were lost; the gyro is
not integrated over it), ``NAME_FLAG_MAG_FROZEN`` (the magnetometer's readings repeated exactly for
``frozen_time`` and 0.5 s: not trusted). The backbone's scalar type is ``TCN_AHRS_REAL`` (float by default;
``-DTCN_AHRS_REAL=double`` for a double build); its low-pass filters, their coefficients and the
heading update compute in double in both (``runtime.WIDE_KERNELS``), the networks in float32.
"""
from .runtime import CRuntime, compile_c, export_c, generate_c
from .translate import kernel_c

__all__ = ["generate_c", "export_c", "compile_c", "CRuntime", "kernel_c"]
