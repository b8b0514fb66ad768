"""One entry point for every paper's experiment: ``tcn-ahrs reproduce paper=<name>``.

Each experiment is one module here (or anywhere importable, named by its config's ``module``) with
``main(cfg, out) -> results`` (cfg: its ``conf/paper/<name>.yaml``), printing the paper's table with the paper's numbers beside ours and
writing results.json, results.md, trajectories and plots to ``out``.
"""
from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any, Dict, List, Mapping, Sequence


def write_report(out: Path, result: Dict[str, Any], md: str, drop: Sequence[str] = ()) -> Dict[str, Any]:
    """The one results tail of every experiment: ``results.json`` (``result`` without the keys in
    ``drop`` at any depth, arrays as lists), ``results.md`` (``md``), ``md`` on stdout and where it
    went on stderr. Returns ``result`` unchanged."""
    import json
    import sys

    import numpy as np

    def strip(x):
        if isinstance(x, dict):
            return {k: strip(v) for k, v in x.items() if k not in drop}
        if isinstance(x, (list, tuple)):
            return [strip(v) for v in x]
        return x.tolist() if isinstance(x, (np.ndarray, np.generic)) else x

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(strip(result), indent=1))
    (out / "results.md").write_text(md)
    print(md)
    print(f"written to {out}", file=sys.stderr)
    return result


def papers() -> List[str]:
    """The experiments present (one module each)."""
    import pkgutil

    return sorted(i.name for i in pkgutil.iter_modules(__path__) if not i.name.startswith("_"))


def run(name: str, cfg: Mapping[str, Any], out: Path) -> Dict[str, Any]:
    """Run experiment ``name``: a module of this package, or any importable module with
    ``main(cfg, out)``, named by the config's ``module`` key (else by ``name`` itself): a
    reproduction of one's own is one module + one ``<config folder>/paper/<name>.yaml``, nothing here changes."""
    module = cfg.get("module") if hasattr(cfg, "get") else None
    if module is None and name in papers():
        module = f"{__name__}.{name}"
        from ..config import check_keys
        from ..config.papers import PAPERS

        if name in PAPERS:  # conf/paper/<name>.yaml's keys: tcn_ahrs/config/papers.py
            check_keys(cfg, PAPERS[name], f"paper {name}")
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


def reproduce_main(cfg) -> Dict[str, Any]:
    """``tcn-ahrs reproduce paper=<name>``: the experiment with its config, written to ``out`` (else
    Hydra's run folder, else ``runs/reproduce/<name>/<time>``)."""
    from omegaconf import OmegaConf

    from ..app import output_dir

    paper = OmegaConf.to_container(cfg.paper, resolve=True)
    return run(str(paper["name"]), paper, output_dir(cfg.get("out"), Path("runs/reproduce") / str(paper["name"])))
