"""The configuration files, shipped inside the package (Hydra's search path ``pkg://tcn_ahrs.conf``).

``train.yaml evaluate.yaml export.yaml compare.yaml benchmark.yaml crossval.yaml reproduce.yaml
inspect_data.yaml`` are the commands' main configs; the folders are config groups (``data/``,
``model/``, ``trainer/``, ``experiment/``, ``paper/``). Code that reads a config file by path
goes through :data:`CONF_DIR`, so an installed wheel and a checkout read the same files.
"""
from pathlib import Path

CONF_DIR = Path(__file__).resolve().parent
SEARCH_PATH = "pkg://tcn_ahrs.conf"


def group_file(group: str, name: str) -> Path:
    """``<CONF_DIR>/<group>/<name>.yaml`` (e.g. ``group_file("data", "broad")``); ValueError naming
    the options when there is no such file."""
    path = CONF_DIR / group / f"{name}.yaml"
    if not path.is_file():
        options = sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))
        raise ValueError(f"no {group} config {name!r} (options: {', '.join(options)})")
    return path
