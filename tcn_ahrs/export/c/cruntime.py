"""The generated C library through ctypes, for the tests and the benchmarks (not for deployment:
the C files are the runtime). numpy and ctypes only, so the deploy bench times a library in a
process of its own without importing torch (:data:`PATH`, loaded by file)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

PATH = Path(__file__).resolve()


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
