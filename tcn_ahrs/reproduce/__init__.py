"""One entry point for every paper's experiment: ``python scripts/reproduce.py paper=<name>``.

Each experiment is one module here with ``main(cfg, out) -> results`` (cfg: its
``conf/paper/<name>.yaml``), printing the paper's table with the paper's numbers beside ours and
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
    if name not in papers():
        raise ValueError(f"paper: unknown experiment {name!r}; expected one of {papers()}")
    from ..config import check_keys
    from ..config.papers import PAPERS

    if name in PAPERS:  # conf/paper/<name>.yaml's keys: tcn_ahrs/config/papers.py
        check_keys(cfg, PAPERS[name], f"paper {name}")
    return importlib.import_module(f"{__name__}.{name}").main(cfg, Path(out))
