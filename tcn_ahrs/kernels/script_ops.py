"""TorchScript's reading of a kernel: the same source compiled by ``torch.jit`` on Python floats.

TorchScript needs what numba infers: parameter types and no module-level globals. So
:func:`script_kernel` rewrites a kernel file's functions into one TorchScript compilation unit:
parameters typed by their name (:data:`VECTORS`, :data:`INTS`, :data:`BOOLS`; any other name is a
float), module constants (``S_BIAS``, ``PI``, ...) written in as literals, and the float ops table
below (the same names as :mod:`tcn_ahrs.kernels.ops`) prepended, and the typed scalar kernels the
module binds (e.g. ``qmul = jit(quat.qmul)``: already annotated) included as they are. Nothing of
the math is restated.
"""
from __future__ import annotations

import ast
import inspect
import math  # noqa: F401 - resolved by name from this module when TorchScript compiles OPS_SOURCE
import re
import sys
from types import ModuleType
from typing import Dict

# the parameter names of the kernels by type (a kernel's parameter list is its contract)
VECTORS = frozenset({"s", "p", "c"})          # state, parameters, coefficients: List[float]
# flat indices and counts
INTS = frozenset({"f", "d", "i", "at_b", "at_a", "prev", "same_t", "same_n", "flag", "maxabs", "clipflag"})
BOOLS = frozenset({"run", "start", "use_mag", "held", "disturbed", "done"})
# modules of typed scalar kernels (annotated for TorchScript) an ops-table kernel may bind
TYPED_MODULES = frozenset({"tcn_ahrs.kernels.quat"})
# ops-table kernel modules whose @jit functions a kernel binds (``butter_terms = _gains.butter_terms``):
# read as the binding module's own kernels (the formulas the exported vector graph shares)
KERNEL_MODULES = frozenset({"tcn_ahrs.kernels.backbone_gains", "tcn_ahrs.kernels.backbone_check"})


def bound_kernels(module: ModuleType):
    """(name, function, its module is typed) of every kernel ``module`` binds from
    :data:`TYPED_MODULES` or :data:`KERNEL_MODULES`, under its own name (else ValueError)."""
    for name, obj in vars(module).items():
        fn = getattr(obj, "py_func", obj)  # a numba dispatcher's Python function
        if (inspect.isfunction(fn) and fn.__module__ in TYPED_MODULES | KERNEL_MODULES
                and fn.__module__ != module.__name__):   # a module's own kernels are not bound ones
            if fn.__name__ != name:
                raise ValueError(f"{module.__name__}.{name}: bind kernels under their own name ({fn.__name__})")
            yield name, fn, fn.__module__ in TYPED_MODULES

OPS_SOURCE = '''
def where(c: bool, a: float, b: float) -> float:
    if c:
        return a
    return b

def both(a: bool, b: bool) -> bool:
    return a and b

def either(a: bool, b: bool) -> bool:
    return a or b

def negate(a: bool) -> bool:
    return not a

def nograd(x: float) -> float:
    return x

def fmax(a: float, b: float) -> float:
    if a > b:
        return a
    return b

def clip(x: float, lo: float, hi: float) -> float:
    if x < lo:
        return lo
    if x > hi:
        return hi
    return x

def fabs(x: float) -> float:
    return abs(x)

def sqrt(x: float) -> float:
    return math.sqrt(x)

def sin(x: float) -> float:
    return math.sin(x)

def cos(x: float) -> float:
    return math.cos(x)

def tan(x: float) -> float:
    return math.tan(x)

def exp(x: float) -> float:
    return math.exp(x)

def atan2(y: float, x: float) -> float:
    return math.atan2(y, x)

def asin(x: float) -> float:
    return math.asin(x)
'''


def _typed(arg: str) -> str:
    t = "List[float]" if arg in VECTORS else "int" if arg in INTS else "bool" if arg in BOOLS else "float"
    return f"{arg}: {t}"


def script_source(module: ModuleType) -> str:
    """TorchScript source of every function a kernel module defines (see the module docstring)."""
    text = inspect.getsource(module)
    tree = ast.parse(text)
    consts: Dict[str, str] = {k: repr(v) for k, v in vars(module).items()
                              if re.fullmatch(r"[A-Z][A-Z0-9_]*", k) and isinstance(v, (int, float))
                              and not isinstance(v, bool)}
    pattern = re.compile(r"\b(" + "|".join(sorted(consts, key=len, reverse=True)) + r")\b")
    parts = [OPS_SOURCE]
    nodes = []   # (source, function node) of the kernels read as this module's own
    for _, fn, typed in bound_kernels(module):  # bound kernels first: the module's own call them
        if typed:
            parts.append(inspect.getsource(fn))
        else:
            src = inspect.getsource(fn)
            nodes.append((src, ast.parse(src).body[0]))
    # the kernels are the decorated (@jit) functions
    nodes += [(text, n) for n in tree.body if isinstance(n, ast.FunctionDef) and n.decorator_list]
    for src, node in nodes:
        seg = ast.get_source_segment(src, node)
        args = ", ".join(_typed(a.arg) for a in node.args.args)
        body = seg.split("\n", 1)[1]
        body = pattern.sub(lambda m: consts[m.group(1)], body)
        parts.append(f"def {node.name}({args}):\n{body}\n")
    return "\n".join(parts)


def script_kernel(module: ModuleType):
    """The kernel module's functions compiled by TorchScript (a ``torch.jit.CompilationUnit``:
    attribute access by name, e.g. ``cu.gyro_update``); cached per module."""
    import torch

    cache = sys.modules[__name__].__dict__.setdefault("_CACHE", {})
    if module.__name__ not in cache:
        cache[module.__name__] = torch.jit.CompilationUnit(script_source(module))
    return cache[module.__name__]
