"""One entry point for every paper's experiment: ``python scripts/reproduce.py paper=<name>``.

Each experiment is one module here (or anywhere importable, named by its config's ``module``) with
``main(cfg, out) -> results`` (cfg: its ``conf/paper/<name>.yaml``), printing the paper's table with the paper's numbers beside ours and
writing results.json, results.md, trajectories and plots to ``out``.
"""
from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any, Dict, List, Mapping


def papers() -> List[str]:
    """The experiments present (one module each)."""
    import pkgutil

    return sorted(i.name for i in pkgutil.iter_modules(__path__) if not i.name.startswith("_"))


def run(name: str, cfg: Mapping[str, Any], out: Path) -> Dict[str, Any]:
    """Run experiment ``name``: a module of this package, or any importable module with
    ``main(cfg, out)``, named by the config's ``module`` key (else by ``name`` itself): a
    reproduction of one's own is one module + one ``conf/paper/<name>.yaml``, nothing here changes."""
    module = cfg.get("module") if hasattr(cfg, "get") else None
    if module is None and name in papers():
        module = f"{__name__}.{name}"
    try:
        mod = importlib.import_module(str(module or name))
    except ModuleNotFoundError as e:
        if e.name is not None and not str(module or name).startswith(e.name):
            raise  # the module exists but one of its own imports is missing
        mod = None
    if mod is None or not callable(getattr(mod, "main", None)):
        raise ValueError(f"paper: unknown experiment {name!r}; expected one of {papers()} "
                         "or an importable module with main(cfg, out) (the paper config's 'module')")
    return mod.main(cfg, Path(out))
