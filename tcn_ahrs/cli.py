"""The command line: ``tcn-ahrs COMMAND [key=value ...]`` (also ``python -m tcn_ahrs``, and
``python scripts/COMMAND.py`` in a checkout).

    tcn-ahrs train experiment=broad9_residual data.fold=0
    tcn-ahrs evaluate data=generic data.root=DIR data.split=all
    tcn-ahrs export ckpt=checkpoints/broad9_residual.ckpt out=model.pt
    tcn-ahrs benchmark transfer

Each command is one Hydra app on a main config shipped in the package (``conf/``), so an
installed wheel runs anywhere; overrides are checked first (a misspelt key is one line with the
nearest valid key, exit 2) and user errors follow :mod:`tcn_ahrs.app`'s contract.
"""
from __future__ import annotations

import difflib
import importlib
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Dict, List, NamedTuple, Optional, Tuple

from . import app as _app
from .app import EXIT_USER_ERROR, check_overrides, quiet_third_party, user_errors
from .conf import SEARCH_PATH
from .config.renamed import experiment_overrides


class Command(NamedTuple):
    config: str   # main config in conf/
    target: str   # "module:function" taking the composed config
    summary: str


COMMANDS: Dict[str, Command] = {
    "train": Command("train", "tcn_ahrs.training.run:train_main",
                     "train a model, then evaluate it on held-out recordings"),
    "evaluate": Command("evaluate", "tcn_ahrs.evaluate.main:evaluate_main",
                        "score a checkpoint (default: the general model) beside classical filters"),
    "export": Command("export", "tcn_ahrs.export:export_main",
                      "a checkpoint as a self-contained deployment file"),
    "compare": Command("compare", "tcn_ahrs.experiments.compare:compare_main",
                       "every classical filter (and a checkpoint) on one dataset"),
    "benchmark": Command("benchmark", "tcn_ahrs.cli:benchmark_main",
                         "accuracy | speed | transfer | lodo | finetune | faults | devices"),
    "crossval": Command("crossval", "tcn_ahrs.experiments.crossval:crossval_main",
                        "nested leave-recordings-out folds of a recipe"),
    "search": Command("search", "tcn_ahrs.experiments.search:search_main",
                      "nested search over estimator families (+ static calibration) for a device"),
    "reproduce": Command("reproduce", "tcn_ahrs.reproduce:reproduce_main",
                         "a navigation paper's tables (paper=...)"),
    "inspect": Command("inspect_data", "tcn_ahrs.evaluate.inspect:inspect_main",
                       "per-recording summary of a data split"),
}

COMMAND_ENV = "TCN_AHRS_COMMAND"

BENCHMARK_MODES = {
    "accuracy": "tcn_ahrs.experiments.compare:benchmark_accuracy_main",
    "transfer": "tcn_ahrs.experiments.transfer:transfer_main",
    "lodo": "tcn_ahrs.experiments.lodo:lodo_main",
    "finetune": "tcn_ahrs.experiments.finetune:finetune_main",
    "speed": "tcn_ahrs.bench:main",
    "faults": "tcn_ahrs.bench.faults:faults_main",
    "devices": "tcn_ahrs.experiments.devices:devices_main",
}


def _resolve(target: str) -> Callable:
    module, name = target.split(":")
    return getattr(importlib.import_module(module), name)


def benchmark_main(cfg) -> None:
    """``tcn-ahrs benchmark MODE``: the mode's function (imported only for that mode)."""
    mode = str(cfg.mode)
    if mode not in BENCHMARK_MODES:
        raise ValueError(f"benchmark: unknown mode {mode!r}; expected one of {', '.join(BENCHMARK_MODES)}")
    _resolve(BENCHMARK_MODES[mode])(cfg)


def mode_as_override(args: List[str]) -> List[str]:
    """``benchmark MODE ...`` -> ``benchmark mode=MODE ...`` (Hydra rejects bare words)."""
    if args and not args[0].startswith("-") and "=" not in args[0]:
        mode = args[0]
        if mode not in BENCHMARK_MODES:
            _usage_error(f"benchmark: unknown mode {mode!r}; expected one of {', '.join(BENCHMARK_MODES)}")
        return [f"mode={mode}", *args[1:]]
    return args


VERBOSE_ENV = "TCN_AHRS_VERBOSE"


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = ["usage: tcn-ahrs COMMAND [key=value ...]   (tcn-ahrs COMMAND --help: its config)", "", "commands:"]
    lines += [f"  {name:<{width}}  {c.summary}" for name, c in COMMANDS.items()]
    return "\n".join(lines)


def _usage_error(message: str) -> None:
    print(f"error: {message}\n{usage()}", file=sys.stderr)
    raise SystemExit(EXIT_USER_ERROR)


OUT_ALIASES = {"train": "run_dir"}
"""Commands whose output folder has another name: ``out=`` (as ``evaluate``, ``search``, ``export``
take it) is accepted for it and said."""


def _quoted(arg: str) -> Optional[str]:
    """``key=value`` with the value quoted for Hydra's grammar when it does not parse as it is
    (a path with non-ASCII letters or an apostrophe) and quoted does; else None."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    try:
        parser.parse_override(arg)
        return None
    except Exception:  # noqa: BLE001 - Hydra's grammar errors
        pass
    key, value = arg.split("=", 1)
    if not value or value[0] in "'\"[{":
        return None
    quoted = f"{key}='" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"
    try:
        parser.parse_override(quoted)
        return quoted
    except Exception:  # noqa: BLE001
        return None


def hydra_arguments(name: str, args: List[str]) -> Tuple[List[str], List[str]]:
    """(``args`` as Hydra takes them, notes to print): ``out=`` as the command's own name for its
    output folder; a value Hydra's grammar refuses unquoted (non-ASCII letters, an apostrophe)
    quoted; and, in a working folder this process cannot write, Hydra's run folder (its log and
    config, and the output of a command given no ``out=``) in the system's temporary folder instead
    of ``./runs`` (Hydra would stop with a PermissionError before the command starts)."""
    out, notes = [], []
    for a in args:
        key = a.split("=", 1)[0] if "=" in a and not a.startswith("-") else None
        if key == "out" and name in OUT_ALIASES:
            key = OUT_ALIASES[name]
            a = f"{key}={a.split('=', 1)[1]}"
            notes.append(f"{name}: out= is {OUT_ALIASES[name]}= (the {name} command's output folder)")
        if key is not None:
            q = _quoted(a)
            if q is not None:
                notes.append(f"{key}: the value quoted for Hydra ({q}); write it so to skip this note")
                a = q
        out.append(a)
    if not any(a.startswith("hydra.run.dir=") for a in out) and not _app.writable(Path.cwd()):
        run_dir = Path(tempfile.gettempdir()) / "tcn-ahrs" / name / time.strftime("%Y-%m-%d_%H-%M-%S")
        out.append(f"hydra.run.dir='{run_dir}'")
        notes.append(f"the working folder {Path.cwd()} is not writable: Hydra's run folder (log, config, and the "
                     f"output where no out= is given) is {run_dir}")
    return out, notes


def main(argv: Optional[List[str]] = None) -> None:
    """Run ``argv`` (default: the process's arguments) = ``[COMMAND, overrides...]``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and "=" in argv[0] and os.environ.get(COMMAND_ENV) in COMMANDS:
        argv = [os.environ[COMMAND_ENV], *argv]  # a re-run child (below)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(usage())
        return
    name, args = argv[0], argv[1:]
    if name not in COMMANDS:
        near = difflib.get_close_matches(name, COMMANDS, n=1)
        _usage_error(f"unknown command {name!r}" + (f" (did you mean {near[0]!r}?)" if near else ""))
    command = COMMANDS[name]
    if name == "benchmark":
        args = mode_as_override(args)
    args, notes = experiment_overrides(args)   # an old experiment name runs its new one, said
    args, more = hydra_arguments(name, args)
    for note in notes + more:
        print(note)
    check_overrides(command.config, args)
    target = command.target

    def task(cfg) -> None:
        # after Hydra set up logging: third-party logs off unless asked for (a command's verbose=true,
        # or TCN_AHRS_VERBOSE=1 for every command)
        quiet_third_party(str(cfg.get("verbose", False)).lower() in ("true", "1")
                          or os.environ.get(VERBOSE_ENV, "") not in ("", "0"))
        _resolve(target)(cfg)

    import hydra

    app = hydra.main(version_base="1.3", config_path=SEARCH_PATH, config_name=command.config)(user_errors(task))
    # Hydra reads its overrides from sys.argv[1:]. Lightning's DDP launcher starts each worker by
    # running sys.argv again (plus its own overrides): the program stays argv[0] and the command
    # word travels in the environment, so `tcn-ahrs train trainer=ddp` and `python -m tcn_ahrs
    # train ...` re-run as themselves. (The job's name, e.g. its log file, is set in each main config.)
    os.environ[COMMAND_ENV] = name
    sys.argv = [sys.argv[0], *args]
    app()


if __name__ == "__main__":
    main()
