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
* the typed scalar kernels the module binds (``qmul = jit(quat.qmul)``) translated from their
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
from typing import Dict, List, Optional, Sequence, Tuple

from .inputs import ExportError
from ..kernels.script_ops import BOOLS, INTS, TYPED_MODULES, VECTORS

REAL, INT, BOOL = "REAL", "int", "bool"

# the ops table's math functions -> the REAL wrappers the generated file defines (see HELPERS)
MATH = {"sqrt": "r_sqrt", "sin": "r_sin", "cos": "r_cos", "tan": "r_tan", "exp": "r_exp", "atan2": "r_atan2",
        "asin": "r_asin", "fabs": "r_fabs", "fmax": "r_fmax", "clip": "r_clip"}
# C keywords and <math.h> names a local of that name would shadow
RESERVED = frozenset("""auto break case char const continue default do double else enum extern float for goto if
inline int long register restrict return short signed sizeof static struct switch typedef union unsigned void volatile
while y0 y1 yn j0 j1 jn exp sin cos tan sqrt atan2 asin fabs fmax pow log erf round floor ceil""".split())

HELPERS = r"""
#ifndef TCN_AHRS_REAL
#define TCN_AHRS_REAL double
#endif
typedef TCN_AHRS_REAL REAL;
#define R_(x) ((REAL)(x))
#define TCN_AHRS_REAL_IS_FLOAT (sizeof(REAL) == sizeof(float))
static inline REAL r_sqrt(REAL x) { return TCN_AHRS_REAL_IS_FLOAT ? (REAL)sqrtf((float)x) : (REAL)sqrt((double)x); }
static inline REAL r_sin(REAL x) { return TCN_AHRS_REAL_IS_FLOAT ? (REAL)sinf((float)x) : (REAL)sin((double)x); }
static inline REAL r_cos(REAL x) { return TCN_AHRS_REAL_IS_FLOAT ? (REAL)cosf((float)x) : (REAL)cos((double)x); }
static inline REAL r_tan(REAL x) { return TCN_AHRS_REAL_IS_FLOAT ? (REAL)tanf((float)x) : (REAL)tan((double)x); }
static inline REAL r_exp(REAL x) { return TCN_AHRS_REAL_IS_FLOAT ? (REAL)expf((float)x) : (REAL)exp((double)x); }
static inline REAL r_asin(REAL x) { return TCN_AHRS_REAL_IS_FLOAT ? (REAL)asinf((float)x) : (REAL)asin((double)x); }
static inline REAL r_fabs(REAL x) { return TCN_AHRS_REAL_IS_FLOAT ? (REAL)fabsf((float)x) : (REAL)fabs((double)x); }
static inline REAL r_atan2(REAL y, REAL x)
{ return TCN_AHRS_REAL_IS_FLOAT ? (REAL)atan2f((float)y, (float)x) : (REAL)atan2((double)y, (double)x); }
static inline REAL r_fmax(REAL a, REAL b) { return a > b ? a : b; }               /* ops.fmax: a if a > b else b */
static inline REAL r_clip(REAL x, REAL lo, REAL hi) { return x < lo ? lo : (x > hi ? hi : x); }
"""


def _literal(v: float) -> str:
    if math.isinf(v) or math.isnan(v):
        raise ExportError(f"C kernel: constant {v!r} has no C literal")
    return f"R_({float(v)!r})"


@dataclass
class _Fn:
    name: str
    node: ast.FunctionDef
    params: List[Tuple[str, str]]          # (name, type: 'vec' | REAL | INT | BOOL)
    returns: List[str] = field(default_factory=list)  # types; [] = void
    locals: Dict[str, str] = field(default_factory=dict)
    written: set = field(default_factory=set)  # vector parameters the function (or a callee) writes


class KernelToC:
    """Translate the kernel functions of ``modules`` into C (one compilation unit).

    ``prefix`` names the C functions (``static``; only those reachable from ``roots`` are
    emitted, so that -Wall sees no unused function)."""

    def __init__(self, module: ModuleType, prefix: str):
        self.prefix = prefix
        self.consts: Dict[str, object] = {k: v for k, v in vars(module).items()
                                          if re.fullmatch(r"[A-Z][A-Z0-9_]*", k) and isinstance(v, (int, float))
                                          and not isinstance(v, bool)}
        self.fns: Dict[str, _Fn] = {}
        # the typed scalar kernels the module binds (qmul = jit(quat.qmul)), then its own kernels
        for name, obj in vars(module).items():
            fn = getattr(obj, "py_func", obj)
            if inspect.isfunction(fn) and fn.__module__ in TYPED_MODULES:
                if fn.__name__ != name:
                    raise ExportError(f"{module.__name__}.{name}: bind typed kernels under their own name")
                self._add(ast.parse(inspect.getsource(fn)).body[0])
        tree = ast.parse(inspect.getsource(module))
        for node in tree.body:
            if isinstance(node, ast.FunctionDef) and node.decorator_list:  # the @jit kernels
                self._add(node)
        self._infer()

    # ------------------------------------------------------------------ typing
    def _add(self, node: ast.FunctionDef) -> None:
        params = []
        for a in node.args.args:
            t = "vec" if a.arg in VECTORS else INT if a.arg in INTS else BOOL if a.arg in BOOLS else REAL
            params.append((a.arg, t))
        self.fns[node.name] = _Fn(node.name, node, params)

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

    def _scan(self, fn: _Fn, body: Sequence[ast.stmt], env: Dict[str, str]) -> None:
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

    def _declare(self, fn: _Fn, env: Dict[str, str], name: str, t: str, st: ast.AST) -> None:
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

    # ------------------------------------------------------------------ emission
    def cname(self, f: str) -> str:
        return f"{self.prefix}{f}"

    @staticmethod
    def _var(n: str) -> str:
        return n + "_" if n in RESERVED else n

    def _ctype(self, t: str) -> str:
        return "REAL" if t == REAL else "int"

    def signature(self, fn: _Fn) -> str:
        args = []
        for n, t in fn.params:
            args.append((f"REAL *{n}" if n in fn.written else f"const REAL *{n}") if t == "vec" else f"{self._ctype(t)} {self._var(n)}")
        if len(fn.returns) > 1:
            args += [f"{self._ctype(t)} *ret{i}" for i, t in enumerate(fn.returns)]
        ret = self._ctype(fn.returns[0]) if len(fn.returns) == 1 else "void"
        return f"static {ret} {self.cname(fn.name)}({', '.join(args)})"

    def reachable(self, roots: Sequence[str]) -> List[str]:
        seen, todo = set(), list(roots)
        while todo:
            f = todo.pop()
            if f in seen:
                continue
            if f not in self.fns:
                raise ExportError(f"C kernel: no kernel named {f!r}")
            seen.add(f)
            for node in ast.walk(self.fns[f].node):
                if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in self.fns:
                    todo.append(node.func.id)
        return [f for f in self.fns if f in seen]  # definition order: callees first

    def emit(self, roots: Sequence[str]) -> str:
        names = self.reachable(roots)
        out = ["/* prototypes (a kernel may call one defined after it) */"]
        out += [self.signature(self.fns[f]) + ";" for f in names] + [""]
        for f in names:
            fn = self.fns[f]
            doc = ast.get_docstring(fn.node)
            lines = [f"/* {fn.name} (kernel source line {fn.node.lineno})"
                     + (": " + doc.split(chr(10))[0].replace("*/", "* /") if doc else "") + " */",
                     self.signature(fn) + "\n{"]
            for n, t in fn.locals.items():
                lines.append(f"    {self._ctype(t)} {self._var(n)} = 0;")
            used = {node.id for st in fn.node.body for node in ast.walk(st) if isinstance(node, ast.Name)}
            lines += [f"    (void){self._var(n)};" for n, _ in fn.params if n not in used]  # -Wunused-parameter
            self._fn = fn
            self._tmp = 0
            lines += self._block(fn.node.body, 1)
            lines.append("}\n")
            out.append("\n".join(lines))
        return "\n".join(out)

    def _env(self) -> Dict[str, str]:
        env = dict(self._fn.params)
        env.update(self._fn.locals)
        return env

    def _block(self, body: Sequence[ast.stmt], depth: int) -> List[str]:
        ind = "    " * depth
        out: List[str] = []
        for st in body:
            if isinstance(st, ast.Expr) and isinstance(st.value, ast.Constant) and isinstance(st.value.value, str):
                continue  # docstring
            if isinstance(st, ast.Expr):
                if not isinstance(st.value, ast.Call):
                    raise self._err(st, "expression statement")
                out.append(ind + self._expr(st.value) + ";")
            elif isinstance(st, ast.Assign):
                out += [ind + s for s in self._assign(st.targets[0], st.value)]
            elif isinstance(st, ast.AugAssign):
                out.append(f"{ind}{self._target(st.target)} = {self._expr(ast.BinOp(st.target, st.op, st.value))};")
            elif isinstance(st, ast.If):
                out.append(f"{ind}if ({self._cond(st.test)}) {{")
                out += self._block(st.body, depth + 1)
                if st.orelse:
                    out.append(f"{ind}}} else {{")
                    out += self._block(st.orelse, depth + 1)
                out.append(ind + "}")
            elif isinstance(st, ast.For):
                it = st.iter
                if not (isinstance(it, ast.Call) and isinstance(it.func, ast.Name) and it.func.id == "range"
                        and len(it.args) == 1) or st.orelse:
                    raise self._err(st, "a loop other than for i in range(n)")
                v = self._var(st.target.id)
                out.append(f"{ind}for ({v} = 0; {v} < {self._expr(it.args[0])}; {v}++) {{")
                out += self._block(st.body, depth + 1)
                out.append(ind + "}")
            elif isinstance(st, ast.Return):
                if st.value is None:
                    out.append(ind + "return;")
                elif self._tuple_call(st.value):
                    outs = ", ".join(f"ret{i}" for i in range(len(self._fn.returns)))
                    out.append(f"{ind}{self.cname(st.value.func.id)}({self._args(st.value)}, {outs});")
                    out.append(ind + "return;")
                elif len(self._fn.returns) == 1:
                    out.append(f"{ind}return {self._expr(st.value)};")
                else:
                    vals = st.value.elts
                    for i, v in enumerate(vals):
                        out.append(f"{ind}*ret{i} = {self._expr(v)};")
                    out.append(ind + "return;")
            elif isinstance(st, ast.Pass):
                continue
            else:
                raise self._err(st, f"statement {type(st).__name__}")
        return out

    def _target(self, t: ast.expr) -> str:
        if isinstance(t, ast.Name):
            return self._var(t.id)
        if isinstance(t, ast.Subscript):
            return self._expr(t)
        raise self._err(t, "assignment target")

    def _assign(self, tgt: ast.expr, value: ast.expr) -> List[str]:
        if not isinstance(tgt, ast.Tuple):
            return [f"{self._target(tgt)} = {self._expr(value)};"]
        if isinstance(value, ast.Tuple):  # Python evaluates the whole right-hand side first
            env = self._env()
            tmps, lines = [], []
            for v in value.elts:
                self._tmp += 1
                name = f"t_{self._tmp}"
                tmps.append(name)
                lines.append(f"{self._ctype(self._type(v, env))} {name} = {self._expr(v)};")
            lines += [f"{self._target(t)} = {n};" for t, n in zip(tgt.elts, tmps)]
            return ["{ " + " ".join(lines) + " }"]
        call = value
        self._call_returns(call)
        outs = ", ".join("&" + self._target(t) for t in tgt.elts)
        return [f"{self.cname(call.func.id)}({self._args(call)}, {outs});"]

    def _args(self, call: ast.Call) -> str:
        if call.keywords:
            raise self._err(call, "keyword arguments")
        return ", ".join(self._expr(a) for a in call.args)

    def _cond(self, e: ast.expr) -> str:
        s = self._expr(e)
        return s[1:-1] if s.startswith("(") and s.endswith(")") and self._balanced(s[1:-1]) else s

    @staticmethod
    def _balanced(s: str) -> bool:
        d = 0
        for ch in s:
            d += ch == "("
            d -= ch == ")"
            if d < 0:
                return False
        return d == 0

    _BIN = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/"}
    _CMP = {ast.Lt: "<", ast.LtE: "<=", ast.Gt: ">", ast.GtE: ">=", ast.Eq: "==", ast.NotEq: "!="}

    def _expr(self, e: ast.expr) -> str:
        if isinstance(e, ast.Constant):
            if isinstance(e.value, bool):
                return "1" if e.value else "0"
            if isinstance(e.value, int):
                return str(e.value)
            if isinstance(e.value, float):
                return _literal(e.value)
            raise self._err(e, f"constant {e.value!r}")
        if isinstance(e, ast.Name):
            if e.id in self.consts:
                v = self.consts[e.id]
                return str(v) if isinstance(v, int) else _literal(v)
            if e.id == "PI":
                return _literal(math.pi)
            if e.id not in self._env():
                raise self._err(e, f"unknown name {e.id!r}")
            return self._var(e.id)
        if isinstance(e, ast.Attribute):
            if isinstance(e.value, ast.Name) and e.value.id == "math" and e.attr == "pi":
                return _literal(math.pi)
            raise self._err(e, "attribute")
        if isinstance(e, ast.Subscript):
            if not (isinstance(e.value, ast.Name) and dict(self._fn.params).get(e.value.id) == "vec"):
                raise self._err(e, "indexing of something other than s, p or c")
            if self._type(e.slice, self._env()) != INT:
                raise self._err(e, "a non-integer index")
            return f"{e.value.id}[{self._cond(e.slice)}]"
        if isinstance(e, ast.UnaryOp):
            if isinstance(e.op, ast.USub):
                return f"(-{self._expr(e.operand)})"
            if isinstance(e.op, ast.Not):
                return f"(!{self._expr(e.operand)})"
            if isinstance(e.op, ast.UAdd):
                return self._expr(e.operand)
            raise self._err(e, "unary operator")
        if isinstance(e, ast.BinOp):
            if isinstance(e.op, ast.Pow):
                if isinstance(e.right, ast.Constant) and e.right.value == 2:
                    x = self._expr(e.left)
                    return f"({x} * {x})"
                raise self._err(e, "a power other than ** 2")
            op = self._BIN.get(type(e.op))
            if op is None:
                raise self._err(e, f"operator {type(e.op).__name__}")
            a, b = self._expr(e.left), self._expr(e.right)
            env = self._env()
            if op == "/" and self._type(e.left, env) == INT and self._type(e.right, env) == INT:
                a = f"R_({a})"  # Python's true division
            return f"({a} {op} {b})"
        if isinstance(e, ast.Compare):
            if len(e.ops) != 1:
                raise self._err(e, "a chained comparison")
            op = self._CMP.get(type(e.ops[0]))
            if op is None:
                raise self._err(e, "comparison operator")
            return f"({self._expr(e.left)} {op} {self._expr(e.comparators[0])})"
        if isinstance(e, ast.BoolOp):
            op = " && " if isinstance(e.op, ast.And) else " || "
            return "(" + op.join(self._expr(v) for v in e.values) + ")"
        if isinstance(e, ast.IfExp):
            return f"({self._expr(e.test)} ? {self._expr(e.body)} : {self._expr(e.orelse)})"
        if isinstance(e, ast.Call):
            f = self._fname(e)
            a = [self._expr(x) for x in e.args]
            if f == "where":
                return f"({a[0]} ? {a[1]} : {a[2]})"
            if f == "both":
                return f"({a[0]} && {a[1]})"
            if f == "either":
                return f"({a[0]} || {a[1]})"
            if f == "negate":
                return f"(!{a[0]})"
            if f == "nograd":
                return a[0]
            if f in MATH:
                return f"{MATH[f]}({', '.join(a)})"
            if f in self.fns:
                if len(self.fns[f].returns) > 1:
                    raise self._err(e, f"{f} returns a tuple: unpack it")
                return f"{self.cname(f)}({', '.join(a)})"
            raise self._err(e, f"call of {f!r}")
        raise self._err(e, f"expression {type(e).__name__}")


def kernel_c(module: ModuleType, prefix: str, roots: Sequence[str]) -> Tuple[str, Dict[str, str]]:
    """The C functions (``static``, names ``prefix + kernel name``) of ``roots`` and what they
    call, translated from ``module``'s source; and the C signatures by kernel name."""
    tr = KernelToC(module, prefix)
    names = tr.reachable(roots)
    return tr.emit(roots), {f: tr.signature(tr.fns[f]) for f in names}
