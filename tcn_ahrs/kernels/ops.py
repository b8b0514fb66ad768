"""The two ops tables a kernel is built with: floats (numba, or plain Python without it) and
torch tensors of one shape (B,) (autograd).

Each table has the same names. ``where(c, a, b)`` selects without branching on tensors;
``both``/``either``/``negate`` combine conditions (Python's ``and``/``or``/``not`` do not work on
tensors); ``nograd`` marks values that only feed decisions (thresholds, detectors): detached under
torch, so a discrete decision never carries a gradient; ``jit`` compiles a kernel function for the
table's backend (numba's ``njit``, cached on disk, or nothing).

A kernel module reads its table from the global ``ops``; :func:`load_kernel` executes the same
file a second time with the torch table, so the math exists once.
"""
from __future__ import annotations

import importlib.util
import math
import sys
from types import ModuleType, SimpleNamespace

try:  # numba is the optional [fast] extra; without it the float table runs as plain Python
    import numba

    NUMBA = True
except ImportError:  # pragma: no cover - exercised only without numba
    numba = None
    NUMBA = False


def _jit(f):
    return numba.njit(cache=True)(f) if NUMBA else f


# module-level (not nested) so that numba can cache what calls them
@_jit
def _where(c, a, b):
    return a if c else b


@_jit
def _both(a, b):
    return a and b


@_jit
def _either(a, b):
    return a or b


@_jit
def _negate(a):
    return not a


@_jit
def _nograd(x):
    return x


@_jit
def _fmax(a, b):
    return a if a > b else b


@_jit
def _clip(x, lo, hi):
    return lo if x < lo else (hi if x > hi else x)


FLOAT = SimpleNamespace(
    name="float", jit=_jit, where=_where, both=_both, either=_either, negate=_negate, nograd=_nograd,
    fmax=_fmax, clip=_clip, sqrt=math.sqrt, sin=math.sin, cos=math.cos, tan=math.tan, exp=math.exp,
    atan2=math.atan2, asin=math.asin, fabs=abs)


def float_ops() -> SimpleNamespace:
    return FLOAT


def torch_ops() -> SimpleNamespace:
    import torch

    def fmax(a, b):
        if not isinstance(a, torch.Tensor) and not isinstance(b, torch.Tensor):
            return max(a, b)  # two constants (parameters): a float64 float, as the float table
        return torch.maximum(torch.as_tensor(a), torch.as_tensor(b))

    def asin(x):  # only reached under nograd (the dip angle): clamp for round-off past ±1
        return torch.asin(torch.clamp(x, -1.0, 1.0))

    return SimpleNamespace(
        name="torch", jit=lambda f: f, where=torch.where, both=lambda a, b: a & b, either=lambda a, b: a | b,
        negate=lambda a: ~a, nograd=lambda x: x.detach(), fmax=fmax, clip=torch.clamp, sqrt=torch.sqrt,
        sin=torch.sin, cos=torch.cos, tan=torch.tan, exp=torch.exp, atan2=torch.atan2, asin=asin,
        fabs=torch.abs)


def load_kernel(module: ModuleType, table: SimpleNamespace) -> ModuleType:
    """``module``'s source executed again with ``table`` as its ops (e.g. the torch reading of a
    numba kernel); cached per (module, table name)."""
    name = f"{module.__name__}__{table.name}"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, module.__file__)
        mod = importlib.util.module_from_spec(spec)
        mod.__dict__["__ops__"] = table
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
    return sys.modules[name]


def onnx_ops() -> SimpleNamespace:
    """The torch ops table with float64 tan and atan2 built from ops ONNX Runtime runs in float64
    (ONNX Runtime has no float64 Tan, Atan or Asin: tan = sin / cos, atan2 a float32 one refined
    once; the export graphs need no asin)."""
    import torch

    base = vars(torch_ops()).copy()

    def tan(x):
        return torch.sin(x) / torch.cos(x)

    def atan2(y, x):
        y, x = torch.as_tensor(y, dtype=torch.float64), torch.as_tensor(x, dtype=torch.float64)
        a0 = torch.atan2(y.float(), x.float()).double()  # within ~1e-7 rad
        c0, s0 = torch.cos(a0), torch.sin(a0)
        num = y * c0 - x * s0        # r sin(a − a0)
        den = x * c0 + y * s0        # r cos(a − a0) ~ r > 0: a − a0 = atan(num / den) = num / den to
        # (1e-7)³ / 3; x = y = 0 gives 0 / 1e-300 = 0 (atan2(0, 0) = 0)
        return a0 + num / (den + 1e-300)

    base.update(name="torch_onnx", tan=tan, atan2=atan2)
    return SimpleNamespace(**base)
