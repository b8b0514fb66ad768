"""C99's reading of a kernel: the same source as numba and TorchScript compile
(:mod:`tcn_ahrs.kernels.script_ops`), translated from its Python AST into C functions.

The translator knows the kernel subset and nothing else (anything outside it is an error, never
a silent guess):

* parameters typed by their name as in :mod:`~tcn_ahrs.kernels.script_ops` (``s``, ``p``, ``c``:
  flat ``REAL`` arrays; ``f``, ``d``, ``i``, ``at_b``, ``at_a``: ``int``; ``run``, ``start``:
  booleans as ``int``; any other name: a ``REAL`` scalar);
* scalar arithmetic (``+ - * /``, unary ``-``, ``** 2``), comparisons, ``and``/``or``/``not``;
  the ops table's ``where`` (``c ? a : b``), ``both``/``either``/``negate``, ``nograd`` (the
  value itself), ``fmax``/``clip`` (Python's semantics), the math functions (``sqrt``, ``sin``,
  ``cos``, ``tan``, ``exp``, ``atan2``, ``asin``, ``fabs``; ``math.sqrt`` / ``math.pi`` too);
* local variables (typed by their first assignment: ``REAL``, ``int`` for integer index
  arithmetic, booleans as ``int``; declared at the top of the function, zero-initialised);
* tuple assignments (right-hand side evaluated first, as Python), tuple returns (out-pointers
  appended to the parameters), tuple-unpacking calls (``a, b = f(x)`` -> ``f(x, &a, &b)``);
* ``if`` / ``else`` (on parameters: data never branches a kernel), ``for i in range(n)``;
* module constants (upper-case ints and floats) written in as literals;
* the typed scalar kernels the module binds (``qmul = jit(quat.qmul)``) and the ops-table
  kernels it binds from :data:`~tcn_ahrs.kernels.script_ops.KERNEL_MODULES` translated from their
  own source the same way.

The scalar type is the macro ``REAL`` of the generated file (double or float): every float
literal is written ``R_(x)`` and every math function is called through a ``REAL`` wrapper, so the
whole kernel computes in ``REAL`` (float: nothing promotes to double behind one's back).
"""
from __future__ import annotations

import ast
import inspect
import math
import re
from dataclasses import dataclass, field
from types import ModuleType
from typing import Dict, List, Sequence, Tuple

from ...kernels.script_ops import BOOLS, INTS, VECTORS, bound_kernels
from ..inputs import ExportError

REAL, INT, BOOL = "REAL", "int", "bool"

# the ops table's math functions -> the REAL wrappers the generated file defines (see HELPERS)
MATH = {"sqrt": "r_sqrt", "sin": "r_sin", "cos": "r_cos", "tan": "r_tan", "exp": "r_exp", "atan2": "r_atan2",
        "asin": "r_asin", "fabs": "r_fabs", "fmax": "r_fmax", "clip": "r_clip",
        "max": "r_fmax", "abs": "r_fabs"}  # Python's max of two floats and abs, in the typed kernels
# C keywords and <math.h> names a local of that name would shadow
RESERVED = frozenset("""auto break case char const continue default do double else enum extern float for goto if
inline int long register restrict return short signed sizeof static struct switch typedef union unsigned void volatile
while y0 y1 yn j0 j1 jn exp sin cos tan sqrt atan2 asin fabs fmax pow log erf round floor ceil""".split())

def literal(v: float) -> str:
    if math.isinf(v) or math.isnan(v):
        raise ExportError(f"C kernel: constant {v!r} has no C literal")
    return f"R_({float(v)!r})"


@dataclass
class KernelFunction:
    name: str
    node: ast.FunctionDef
    params: List[Tuple[str, str]]          # (name, type: 'vec' | REAL | INT | BOOL)
    returns: List[str] = field(default_factory=list)  # types; [] = void
    locals: Dict[str, str] = field(default_factory=dict)
    written: set = field(default_factory=set)  # vector parameters the function (or a callee) writes


class KernelTypes:
    """The kernel functions of a module parsed and typed (parameters by name, locals by their
    first assignment, returns by their tuples): what :class:`~tcn_ahrs.export.c.translate.KernelToC`
    writes out."""

    def __init__(self, module: ModuleType, prefix: str, plain: bool = False):
        self.prefix = prefix
        self.consts: Dict[str, object] = {k: v for k, v in vars(module).items()
                                          if re.fullmatch(r"[A-Z][A-Z0-9_]*", k) and isinstance(v, (int, float))
                                          and not isinstance(v, bool)}
        self.fns: Dict[str, KernelFunction] = {}
        # the kernels the module binds (qmul = jit(quat.qmul); the shared formulas of another ops-table
        # kernel, butter_terms = _gains.butter_terms), then its own kernels
        try:
            bound = [fn for _, fn, _ in bound_kernels(module)]
        except ValueError as e:
            raise ExportError(str(e)) from None
        for fn in bound:
            self._add(ast.parse(inspect.getsource(fn)).body[0])
        tree = ast.parse(inspect.getsource(module))
        for node in tree.body:
            # the @jit kernels (or, plain: every top-level function, the typed kernels of classical.py)
            if isinstance(node, ast.FunctionDef) and (node.decorator_list or plain):
                self._add(node)
        self._infer()

    # ------------------------------------------------------------------ typing
    def _add(self, node: ast.FunctionDef) -> None:
        params = []
        for a in node.args.args:
            t = "vec" if a.arg in VECTORS else INT if a.arg in INTS else BOOL if a.arg in BOOLS else REAL
            params.append((a.arg, t))
        self.fns[node.name] = KernelFunction(node.name, node, params)

    def _infer(self) -> None:
        # functions in source order: a kernel calls only those defined before it
        for fn in self.fns.values():
            env = {n: t for n, t in fn.params}
            self._scan(fn, fn.node.body, env)
        # vector parameters written (directly or through a callee) are REAL *, the others const
        changed = True
        while changed:
            changed = False
            for fn in self.fns.values():
                vecs = {n for n, t in fn.params if t == "vec"}
                for node in ast.walk(fn.node):
                    hit = set()
                    if isinstance(node, ast.Subscript) and isinstance(node.ctx, ast.Store):
                        hit = {node.value.id} & vecs
                    elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in self.fns:
                        callee = self.fns[node.func.id]
                        for a, (pn, _) in zip(node.args, callee.params):
                            if isinstance(a, ast.Name) and a.id in vecs and pn in callee.written:
                                hit.add(a.id)
                    if hit - fn.written:
                        fn.written |= hit
                        changed = True

    def _scan(self, fn: KernelFunction, body: Sequence[ast.stmt], env: Dict[str, str]) -> None:
        for st in body:
            if isinstance(st, ast.Assign):
                if len(st.targets) != 1:
                    raise self._err(st, "chained assignment")
                tgt = st.targets[0]
                names = tgt.elts if isinstance(tgt, ast.Tuple) else [tgt]
                if isinstance(tgt, ast.Tuple) and isinstance(st.value, ast.Tuple):
                    types = [self._type(v, env) for v in st.value.elts]
                elif isinstance(tgt, ast.Tuple):
                    types = self._call_returns(st.value)
                else:
                    types = [self._type(st.value, env)]
                if len(types) != len(names):
                    raise self._err(st, "unpacking count")
                for n, t in zip(names, types):
                    if isinstance(n, ast.Name):
                        self._declare(fn, env, n.id, t, st)
            elif isinstance(st, ast.If):
                self._scan(fn, st.body, env)
                self._scan(fn, st.orelse, env)
            elif isinstance(st, ast.For):
                if not isinstance(st.target, ast.Name):
                    raise self._err(st, "for target")
                self._declare(fn, env, st.target.id, INT, st)
                self._scan(fn, st.body, env)
            elif isinstance(st, ast.Return):
                if st.value is None:
                    continue
                if self._tuple_call(st.value):  # return f(...): f's values passed through
                    types = self._call_returns(st.value)
                else:
                    vals = st.value.elts if isinstance(st.value, ast.Tuple) else [st.value]
                    types = [self._type(v, env) for v in vals]
                if fn.returns and fn.returns != types:
                    raise self._err(st, "returns of different types")
                fn.returns = types

    def _declare(self, fn: KernelFunction, env: Dict[str, str], name: str, t: str, st: ast.AST) -> None:
        if name in env and env[name] != t:
            raise self._err(st, f"variable {name!r} changes type ({env[name]} -> {t})")
        if name in self.consts:
            raise self._err(st, f"assignment to the module constant {name!r}")
        env[name] = t
        if name not in dict(fn.params):
            fn.locals.setdefault(name, t)

    def _tuple_call(self, node: ast.expr) -> bool:
        return (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in self.fns
                and len(self.fns[node.func.id].returns) > 1)

    def _call_returns(self, node: ast.expr) -> List[str]:
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in self.fns):
            raise self._err(node, "tuple unpacking of something that is not a kernel call")
        return self.fns[node.func.id].returns

    def _type(self, e: ast.expr, env: Dict[str, str]) -> str:
        if isinstance(e, ast.Constant):
            if isinstance(e.value, bool):
                return BOOL
            return INT if isinstance(e.value, int) else REAL
        if isinstance(e, ast.Name):
            if e.id in env:
                return env[e.id]
            if e.id in self.consts:
                return INT if isinstance(self.consts[e.id], int) else REAL
            if e.id == "PI":
                return REAL
            raise self._err(e, f"unknown name {e.id!r}")
        if isinstance(e, ast.Attribute):
            return REAL  # math.pi
        if isinstance(e, ast.Subscript):
            return REAL
        if isinstance(e, ast.Compare) or isinstance(e, ast.BoolOp):
            return BOOL
        if isinstance(e, ast.UnaryOp):
            return BOOL if isinstance(e.op, ast.Not) else self._type(e.operand, env)
        if isinstance(e, ast.BinOp):
            a, b = self._type(e.left, env), self._type(e.right, env)
            if isinstance(e.op, ast.Div):
                return REAL
            return INT if (a == INT and b == INT) else REAL
        if isinstance(e, ast.IfExp):
            return self._type(e.body, env)
        if isinstance(e, ast.Call):
            f = self._fname(e)
            if f in ("both", "either", "negate"):
                return BOOL
            if f == "nograd":
                return self._type(e.args[0], env)
            if f in self.fns:
                r = self.fns[f].returns
                if len(r) != 1:
                    raise self._err(e, f"{f} returns {len(r)} values; unpack them")
                return r[0]
            return REAL
        raise self._err(e, f"expression {type(e).__name__}")

    @staticmethod
    def _fname(e: ast.Call) -> str:
        if isinstance(e.func, ast.Name):
            return e.func.id
        if isinstance(e.func, ast.Attribute) and isinstance(e.func.value, ast.Name) and e.func.value.id == "math":
            return e.func.attr
        raise ExportError(f"C kernel: line {e.lineno}: call of {ast.dump(e.func)}")

    @staticmethod
    def _err(node: ast.AST, what: str) -> ExportError:
        return ExportError(f"C kernel: line {getattr(node, 'lineno', '?')}: {what} is outside the kernel subset")
