"""Emission: the typed kernel functions (:mod:`tcn_ahrs.export.c.kernel_types`) written out as C99
functions of one compilation unit (see :mod:`tcn_ahrs.export.c.kernel_types` for the subset)."""
from __future__ import annotations

import ast
import math
from types import ModuleType
from typing import Dict, List, Optional, Sequence, Tuple

from ..inputs import ExportError
from .kernel_types import INT, MATH, REAL, RESERVED, KernelFunction, KernelTypes, literal


class KernelToC(KernelTypes):
    """Translate the kernel functions of ``modules`` into C (one compilation unit).

    ``prefix`` names the C functions (``static``; only those reachable from ``roots`` are
    emitted, so that -Wall sees no unused function). Two scalar types: ``REAL`` (the build's
    ``TCN_AHRS_REAL``, double or float) and ``WREAL`` (always double), the type of the functions
    in ``wide`` and of the arrays ``s``, ``p``, ``c`` (the state, parameters, coefficients). A
    REAL function reads an array element as ``(REAL)s[k]`` and stores ``(WREAL)(...)``; a call
    between the two kinds converts its arguments and results explicitly (so ``-Wdouble-promotion``
    stays clean, and with REAL = double every conversion is the identity)."""

    wide: frozenset = frozenset()

    # ------------------------------------------------------------------ emission
    def cname(self, f: str) -> str:
        return f"{self.prefix}{f}"

    @staticmethod
    def _var(n: str) -> str:
        return n + "_" if n in RESERVED else n

    def _real(self, f: str) -> str:
        """The C scalar type of kernel ``f``'s arithmetic."""
        return "WREAL" if f in self.wide else "REAL"

    def _ctype(self, t: str, f: Optional[str] = None) -> str:
        return self._real(self._fn.name if f is None else f) if t == REAL else "int"

    def _lit(self, v: float) -> str:
        return literal(v).replace("R_(", "W_(") if self._fn.name in self.wide else literal(v)

    def signature(self, fn: KernelFunction) -> str:
        args = []
        for n, t in fn.params:
            args.append((f"WREAL *{n}" if n in fn.written else f"const WREAL *{n}") if t == "vec"
                        else f"{self._ctype(t, fn.name)} {self._var(n)}")
        if len(fn.returns) > 1:
            args += [f"{self._ctype(t, fn.name)} *ret{i}" for i, t in enumerate(fn.returns)]
        ret = self._ctype(fn.returns[0], fn.name) if len(fn.returns) == 1 else "void"
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
            self._fn = fn
            self._tmp = 0
            for n, t in fn.locals.items():
                lines.append(f"    {self._ctype(t)} {self._var(n)} = 0;")
            used = {node.id for st in fn.node.body for node in ast.walk(st) if isinstance(node, ast.Name)}
            lines += [f"    (void){self._var(n)};" for n, _ in fn.params if n not in used]  # -Wunused-parameter
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
                out.append(f"{ind}{self._target(st.target)} = {self._stored(st.target, self._expr(ast.BinOp(st.target, st.op, st.value)))};")
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
                    if self._real(st.value.func.id) != self._real(self._fn.name):
                        raise self._err(st, "returning the tuple of a kernel of the other scalar type (unpack it first)")
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
            return self._element(t)
        raise self._err(t, "assignment target")

    def _stored(self, t: ast.expr, value: str) -> str:
        """``value`` as assigned to target ``t``: an array element (WREAL) of a REAL function
        gets an explicit conversion."""
        return f"(WREAL)({value})" if isinstance(t, ast.Subscript) and self._real(self._fn.name) != "WREAL" else value

    def _assign(self, tgt: ast.expr, value: ast.expr) -> List[str]:
        if not isinstance(tgt, ast.Tuple):
            return [f"{self._target(tgt)} = {self._stored(tgt, self._expr(value))};"]
        if isinstance(value, ast.Tuple):  # Python evaluates the whole right-hand side first
            env = self._env()
            tmps, lines = [], []
            for v in value.elts:
                self._tmp += 1
                name = f"t_{self._tmp}"
                tmps.append(name)
                lines.append(f"{self._ctype(self._type(v, env))} {name} = {self._expr(v)};")
            lines += [f"{self._target(t)} = {self._stored(t, n)};" for t, n in zip(tgt.elts, tmps)]
            return ["{ " + " ".join(lines) + " }"]
        call = value
        self._call_returns(call)
        callee = call.func.id
        if self._real(callee) == self._real(self._fn.name) and not any(isinstance(t, ast.Subscript) for t in tgt.elts):
            outs = ", ".join("&" + self._target(t) for t in tgt.elts)
            return [f"{self.cname(callee)}({self._args(call)}, {outs});"]
        # results of the other scalar type (or into array elements): through temporaries
        rets = self.fns[callee].returns
        tmps = []
        decl = []
        for t in rets:
            self._tmp += 1
            tmps.append(f"t_{self._tmp}")
            decl.append(f"{self._ctype(t, callee)} {tmps[-1]};")
        conv = self._real(self._fn.name)
        sets = [f"{self._target(tg)} = {self._stored(tg, f'({conv}){n}' if rt == REAL else n)};"
                for tg, n, rt in zip(tgt.elts, tmps, rets)]
        call_s = f"{self.cname(callee)}({self._args(call)}, {', '.join('&' + n for n in tmps)});"
        return ["{ " + " ".join(decl + [call_s] + sets) + " }"]

    def _args(self, call: ast.Call) -> str:
        """A kernel call's arguments, each REAL one in the callee's scalar type."""
        if call.keywords:
            raise self._err(call, "keyword arguments")
        callee = call.func.id if isinstance(call.func, ast.Name) else None
        fn = self.fns.get(callee)
        env = self._env()
        out = []
        for k, a in enumerate(call.args):
            x = self._expr(a)
            if isinstance(a, ast.Subscript) and fn is not None and self._real(callee) == "WREAL":
                x = self._element(a)  # a stored double passed on as it is, not through REAL
            elif (fn is not None and self._real(callee) != self._real(self._fn.name)
                    and k < len(fn.params) and fn.params[k][1] == REAL and self._type(a, env) == REAL):
                x = f"({self._real(callee)}){x}"
            out.append(x)
        return ", ".join(out)

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

    def _element(self, e: ast.Subscript) -> str:
        """An array element (s, p or c: WREAL) as an lvalue."""
        if not (isinstance(e.value, ast.Name) and dict(self._fn.params).get(e.value.id) == "vec"):
            raise self._err(e, "indexing of something other than s, p or c")
        if self._type(e.slice, self._env()) != INT:
            raise self._err(e, "a non-integer index")
        return f"{e.value.id}[{self._cond(e.slice)}]"

    _BIN = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/"}
    _CMP = {ast.Lt: "<", ast.LtE: "<=", ast.Gt: ">", ast.GtE: ">=", ast.Eq: "==", ast.NotEq: "!="}

    def _expr(self, e: ast.expr) -> str:
        if isinstance(e, ast.Constant):
            if isinstance(e.value, bool):
                return "1" if e.value else "0"
            if isinstance(e.value, int):
                return str(e.value)
            if isinstance(e.value, float):
                return self._lit(e.value)
            raise self._err(e, f"constant {e.value!r}")
        if isinstance(e, ast.Name):
            if e.id in self.consts:
                v = self.consts[e.id]
                return str(v) if isinstance(v, int) else self._lit(v)
            if e.id == "PI":
                return self._lit(math.pi)
            if e.id not in self._env():
                raise self._err(e, f"unknown name {e.id!r}")
            return self._var(e.id)
        if isinstance(e, ast.Attribute):
            if isinstance(e.value, ast.Name) and e.value.id == "math" and e.attr == "pi":
                return self._lit(math.pi)
            raise self._err(e, "attribute")
        if isinstance(e, ast.Subscript):
            x = self._element(e)
            return x if self._real(self._fn.name) == "WREAL" else f"((REAL){x})"
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
                a = f"{'W_' if self._fn.name in self.wide else 'R_'}({a})"  # Python's true division
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
                name = MATH[f].replace("r_", "w_", 1) if self._fn.name in self.wide else MATH[f]
                return f"{name}({', '.join(a)})"
            if f in self.fns:
                if len(self.fns[f].returns) > 1:
                    raise self._err(e, f"{f} returns a tuple: unpack it")
                r = f"{self.cname(f)}({self._args(e)})"
                if self.fns[f].returns and self.fns[f].returns[0] == REAL and self._real(f) != self._real(self._fn.name):
                    r = f"(({self._real(self._fn.name)}){r})"
                return r
            raise self._err(e, f"call of {f!r}")
        raise self._err(e, f"expression {type(e).__name__}")


def kernel_c(module: ModuleType, prefix: str, roots: Sequence[str],
             wide: Sequence[str] = (), plain: bool = False) -> Tuple[str, Dict[str, str]]:
    """The C functions (``static``, names ``prefix + kernel name``) of ``roots`` and what they
    call, translated from ``module``'s source; and the C signatures by kernel name. The kernels
    in ``wide`` compute in double in every build (WREAL), the others in REAL. ``plain``: the
    module's kernels are its undecorated top-level functions (the typed scalar kernels of
    :mod:`tcn_ahrs.kernels.classical`) instead of its ``@jit`` ones."""
    tr = KernelToC(module, prefix, plain)
    tr.wide = frozenset(wide)
    names = tr.reachable(roots)
    return tr.emit(roots), {f: tr.signature(tr.fns[f]) for f in names}
