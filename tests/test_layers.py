"""The package's floors: every import points down (or along its own floor), never up, and no
module grows past what one reader holds in mind (issue 26).

Read from the source (an AST scan of every module under ``tcn_ahrs/``, function-local imports
included), so nothing is imported to check it. Imports by name at run time (the estimator
registry's plug-ins, Hydra's ``_target_`` strings) are outside what this test sees.
"""
import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "tcn_ahrs"
CONF = PACKAGE.parent / "conf"  # installed as tcn_ahrs.conf (setup.py's package_dir)
# the folders at the top installed as packages of tcn_ahrs (setup.py's package_dir): name -> folder
MAPPED = {"conf": CONF, "checkpoints": PACKAGE.parent / "checkpoints"}

# Ground floor first. A unit is a top-level module or package of tcn_ahrs ("" = the package's
# own __init__: ImuSequence, DataError, __version__). A module may import from its own floor and
# the floors below it.
LAYERS = [
    # scalar kernels written once, compiled by numba and read by torch / TorchScript; where numba
    # caches them
    {"kernels", "numba_cache"},
    # units, frames and SO(3) on tensors; argument checks; the shipped YAML files and their typed
    # schemas (each default once); the commands' error contract and output folders; the TUM writer;
    # where the shipped models lie
    {"conventions", "so3", "validate", "conf", "config", "app", "tum", "checkpoints"},
    # the one recording type, its validation, how an IMU agrees with its ground truth
    {"sequence", "agreement", "calibration_faults", ""},
    {"datasets"},
    # the classical filters (torch reference + numba loops) and the backbone's tensor/numba readings;
    # the static calibration (constant sensor errors fitted once, used by every family) and the
    # device check (the gyro bias at rest, read without ground truth)
    {"filters", "calibration", "device_check"},
    # the learned model, its losses and the scores (AAE, ...); checkpoints (which build models);
    # navigation examples built on the filters' Kalman pieces; the health flags in words; the one
    # "never worse" rule
    {"model", "losses", "metrics", "checkpoint", "nav", "health", "verdict"},
    # one interface over classical, learned and peer estimators; the papers' reproductions
    {"estimators", "reproduce"},
    # evaluation runs, knob selection (tuning/: the classical grids, a learned model's knobs), training data
    {"evaluate", "tuning", "data"},
    # what a user runs: export, streaming runtimes, benchmarks, the experiments (experiments/:
    # compare, crossval, search, transfer, lodo, finetune) and training (training/: the run and its parts)
    {"export", "streaming", "bench", "experiments", "training"},
    # the command line (tcn-ahrs COMMAND): reaches the commands above by name
    {"cli", "__main__"},
]
FLOOR = {unit: i for i, layer in enumerate(LAYERS) for unit in layer}

# the navigation examples and the papers' reproductions stand on the filters alone (no model)
MODEL_FREE = {"nav", "reproduce"}
MODEL_FREE_MAY_USE = MODEL_FREE | {u for u, i in FLOOR.items() if i <= FLOOR["filters"]}

MAX_LINES = 450


def _module_name(path: Path) -> str:
    for name, folder in MAPPED.items():
        if path.parent == folder:
            return f"tcn_ahrs.{name}" + ("" if path.name == "__init__.py" else "." + path.stem)
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _unit(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _is_module(dotted: str) -> bool:
    rel = Path(*dotted.split(".")[1:]) if "." in dotted else Path()
    if rel.parts[:1] and rel.parts[0] in MAPPED:
        folder, inner = MAPPED[rel.parts[0]], Path(*rel.parts[1:])
        return (folder / inner).with_suffix(".py").is_file() or (folder / inner / "__init__.py").is_file()
    return (PACKAGE / rel).with_suffix(".py").is_file() or (PACKAGE / rel / "__init__.py").is_file()


def _imports(path: Path):
    """(line, imported tcn_ahrs module) for every import statement of the file."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "tcn_ahrs":
                    yield node.lineno, a.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "tcn_ahrs":
                continue
            for a in node.names:  # `from pkg import submodule` imports the submodule
                sub = f"{target}.{a.name}"
                yield node.lineno, sub if _is_module(sub) else target


def _sources():
    return sorted(PACKAGE.rglob("*.py")) + [p for folder in MAPPED.values() for p in sorted(folder.glob("*.py"))]


def test_every_unit_has_a_floor():
    units = {_unit(_module_name(p)) for p in _sources()}
    missing = sorted(units - set(FLOOR))
    assert not missing, f"place these in LAYERS (tests/test_layers.py): {missing}"
    assert not set(FLOOR) - units, f"LAYERS names units that do not exist: {sorted(set(FLOOR) - units)}"


def test_no_import_points_up():
    bad = []
    for path in _sources():
        unit = _unit(_module_name(path))
        for line, target in _imports(path):
            other = _unit(target)
            if FLOOR[other] > FLOOR[unit]:
                bad.append(f"{path.relative_to(PACKAGE.parent)}:{line}: {unit or 'tcn_ahrs'} (floor {FLOOR[unit]}) "
                           f"imports {target} (floor {FLOOR[other]})")
    assert not bad, "imports from a higher floor:\n" + "\n".join(bad)


def test_navigation_and_reproductions_need_no_model():
    bad = []
    for path in _sources():
        if _unit(_module_name(path)) not in MODEL_FREE:
            continue
        for line, target in _imports(path):
            if _unit(target) not in MODEL_FREE_MAY_USE:
                bad.append(f"{path.relative_to(PACKAGE.parent)}:{line}: imports {target}")
    assert not bad, "nav/reproduce import above the filters:\n" + "\n".join(bad)


# rooms allowed to import each other (function-local imports included): none — the streaming
# runtimes build on export's modules; the input contract and the flat network layout live in
# export (export/contract.py, export/flat.py), so export no longer reads streaming
KNOWN_CYCLES: list = []


def _unit_graph():
    edges = {}
    for path in _sources():
        unit = _unit(_module_name(path))
        for _, target in _imports(path):
            other = _unit(target)
            if other != unit:
                edges.setdefault(unit, set()).add(other)
    return edges


def _cycles(edges):
    """The strongly connected components with more than one unit (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(comp)

    for v in list(edges):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycle_between_rooms():
    """Units on one floor may import each other's code, but never in a circle (knobs ⇄ tuning was
    one: tuning re-exported knobs' names, knobs built on tuning)."""
    found = _cycles(_unit_graph())
    new = [sorted(c) for c in found if c not in KNOWN_CYCLES]
    gone = [sorted(c) for c in KNOWN_CYCLES if c not in found]
    assert not new, f"import cycles between rooms: {new}"
    assert not gone, f"cycle(s) {gone} no longer exist: remove them from KNOWN_CYCLES"


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [{"a", "b", "c"}]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_the_scan_sees_function_local_and_relative_imports():
    found = set(_imports(PACKAGE / "experiments" / "compare.py"))
    assert any(t == "tcn_ahrs.tuning.grid" for _, t in found)        # `from ..tuning.grid import ...` inside a function
    assert ("tcn_ahrs.so3" in {t for _, t in _imports(PACKAGE / "filters" / "ecf.py")})  # `from .. import so3`


@pytest.mark.parametrize("path", _sources(), ids=lambda p: str(p.relative_to(PACKAGE.parent)))
def test_no_module_over_the_line_limit(path):
    rel = str(path.relative_to(PACKAGE.parent))
    n = len(path.read_text().splitlines())
    assert n <= MAX_LINES, f"{rel}: {n} lines (limit {MAX_LINES}): split it along a seam"


def test_every_imported_name_exists():
    """Each ``from tcn_ahrs... import name`` of the package, function-local ones included, names
    something its module has (a renamed or moved name cannot hide in a rarely run function)."""
    import importlib

    missing = []
    for path in _sources():
        module = _module_name(path)
        package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.ImportFrom):
                continue
            if node.level:
                base = package.split(".")
                target = ".".join(base[:len(base) - (node.level - 1)] + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "tcn_ahrs":
                continue
            imported = importlib.import_module(target)
            for a in node.names:
                if a.name != "*" and not hasattr(imported, a.name) and not _is_module(f"{target}.{a.name}"):
                    missing.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno}: {target} has no {a.name!r}")
    assert not missing, "\n".join(sorted(missing))


MAX_FUNCTION_LINES = 120


def test_no_function_over_120_lines():
    """A function a newcomer reads in one sitting: none longer than MAX_FUNCTION_LINES (train_main was
    186, eskf 163, the closed loop's reverse pass 124, simulate 121)."""
    import ast

    long = []
    for path in _sources():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, "functions over the limit:\n" + "\n".join(long)


def test_no_import_circle_between_files():
    """No two files of the package import each other, directly or around a circle (function-local
    imports included; a package's ``__init__`` counts as a file): issue 48 found three —
    ``export``'s package ⇄ stateless ⇄ classical_step ⇄ backbone_graph, ``export.c`` classical ⇄
    runtime, ``datasets.simulate`` ⇄ its splits."""
    graph = {}
    for path in _sources():
        module = _module_name(path)
        graph[module] = {t for _, t in _imports(path) if t != module}
    circles = [sorted(c) for c in _cycles({m: {t for t in ts if t in graph} for m, ts in graph.items()})]
    assert not circles, f"files importing each other: {circles}"
