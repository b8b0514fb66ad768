"""What every command shares (``tcn_ahrs.cli`` dispatches to them): the error contract, output
folders written as a whole, and override checks before Hydra runs.

Error contract: a user error (bad data, config, checkpoint or path: every ``ValueError`` —
:class:`~tcn_ahrs.sequence.DataError`, ``CheckpointError``, ``ExportError`` — and ``OSError``)
prints one line ``error: <message>`` on stderr and exits with status 2; ``HYDRA_FULL_ERROR=1``
shows the traceback instead. Anything else is a bug and keeps its traceback.
"""
from __future__ import annotations

import functools
import os
import shutil
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Dict, Iterator, List, Mapping, Optional

EXIT_USER_ERROR = 2


def user_errors(main):
    """Decorator for a script's Hydra task function (put it below ``@hydra.main``)."""

    @functools.wraps(main)
    def wrapper(*args, **kwargs):
        try:
            return main(*args, **kwargs)
        except (ValueError, OSError) as e:
            if os.environ.get("HYDRA_FULL_ERROR") == "1":
                raise
            print(f"error: {e}\n(HYDRA_FULL_ERROR=1 shows the traceback)", file=sys.stderr)
            raise SystemExit(EXIT_USER_ERROR) from None

    return wrapper


def output_dir(explicit: Optional[str], fallback: Path) -> Path:
    """Where a script writes: ``explicit`` (``out=``/``run_dir=``), else Hydra's run directory
    of this job, else ``fallback/<date_time>`` (called outside Hydra, e.g. from a test)."""
    if explicit:
        return Path(str(explicit))
    try:
        from hydra.core.hydra_config import HydraConfig

        return Path(HydraConfig.get().runtime.output_dir)
    except Exception:  # noqa: BLE001 - no Hydra job
        return Path(fallback) / time.strftime("%Y-%m-%d_%H-%M-%S")


def _earlier_entries(folder: Path) -> List[str]:
    """What a folder holds besides Hydra's own files of this job (``.hydra/``, ``*.log``)."""
    return sorted(p.name for p in folder.iterdir() if p.name != ".hydra" and p.suffix != ".log")


def writable(folder: Path) -> bool:
    """Whether this process can create files in ``folder`` (one place, so a test can say no)."""
    return os.access(folder, os.W_OK | os.X_OK)


def refuse_earlier_output(out, overwrite: bool = False, what: str = "output") -> Path:
    """``out`` as a Path; ValueError if it is a file, a folder this process cannot write (a
    read-only folder of the user's is never swapped for a writable one), or a folder holding an
    earlier run's files and not ``overwrite`` (called before the work starts, and again by
    :func:`staged_output`)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{what}: out={out} exists and is not a folder")
    if out.is_dir() and not writable(out):
        raise ValueError(f"{what}: out={out} is not writable (read-only): choose another out= or make it writable")
    if out.is_dir() and not overwrite:
        earlier = _earlier_entries(out)
        if earlier:
            raise ValueError(f"{what}: out={out} already holds an earlier run's files ({', '.join(earlier[:4])}"
                             f"{', ...' if len(earlier) > 4 else ''}): choose a new out= or pass overwrite=true "
                             "(replaces them when this run completes)")
    return out


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: alive
        return True
    return True


def _remove_dead_stages(out: Path) -> None:
    """Staging folders of ``out`` whose run was killed (its process is gone); live ones are
    another run's, left alone."""
    for stage in out.parent.glob(f".{out.name}.*.partial"):
        pid = stage.name[len(out.name) + 2:].split(".")[0]
        if not pid.isdigit() or not _alive(int(pid)):
            shutil.rmtree(stage, ignore_errors=True)
    legacy = out.parent / f".{out.name}.partial"  # the single staging folder of earlier versions
    if legacy.is_dir():
        shutil.rmtree(legacy, ignore_errors=True)


def _free_sibling(out: Path) -> Path:
    k = 2
    while (out.parent / f"{out.name}-{k}").exists():
        k += 1
    return out.parent / f"{out.name}-{k}"


def staged_files(targets: Mapping[str, Path], write: Callable[[str, Path], None],
                 error: Callable[[str], Exception] = OSError) -> Dict[str, str]:
    """The files of one output, all or none (the one write path of every file output: export
    formats, checkpoints; a whole folder: :func:`staged_output`). ``write(key, tmp)`` writes each
    target to a hidden name beside it, unique per process (``.<stem>.<pid>.partial<suffix>``; the
    suffix kept: torch.export wants ``.pt2``); only when every one is written are they renamed
    into place, so a failed or killed write leaves what was there. An OS error (a read-only folder,
    a full disk) is raised as ``error("cannot write <path>: <why>")``; anything else as it came."""
    paths = {k: Path(p) for k, p in targets.items()}
    staged = {k: p.with_name(f".{p.stem}.{os.getpid()}.partial{p.suffix}") for k, p in paths.items()}
    try:
        for k, tmp in staged.items():
            tmp.parent.mkdir(parents=True, exist_ok=True)
            write(k, tmp)
        for k, tmp in staged.items():
            os.replace(tmp, paths[k])
    except BaseException as e:
        for tmp in staged.values():
            tmp.unlink(missing_ok=True)
        if isinstance(e, OSError):
            raise error(f"cannot write {', '.join(str(p) for p in paths.values())}: {e}") from None
        raise
    return {k: str(p) for k, p in paths.items()}


@contextmanager
def staged_output(out, overwrite: bool = False, what: str = "output", landed: Optional[List[Path]] = None
                  ) -> Iterator[Path]:
    """A run's output folder, written as a whole or not at all: the body writes into a hidden
    sibling ``.<name>.<pid>.<random>.partial`` of its own (concurrent runs with one ``out`` never
    share it; a killed run's is removed by the next run), which replaces ``out`` when the body
    returns. An ``out`` that already holds an earlier run's files is refused unless ``overwrite``
    (then they are replaced, none kept beside the new ones). If another run filled ``out`` while
    this one ran, this run's folder is kept beside it as ``<out>-2`` (a warning names it): nothing
    either produced is lost. Hydra's files of the current job (``.hydra/``, its log) move into the
    new folder. ``landed``: a list the folder the files ended up in is appended to (what the
    command's last line names)."""
    import uuid
    import warnings

    out = refuse_earlier_output(out, overwrite, what)
    out.parent.mkdir(parents=True, exist_ok=True)
    _remove_dead_stages(out)
    stage = out.parent / f".{out.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.partial"
    stage.mkdir()
    try:
        yield stage
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    if out.is_dir() and not overwrite and _earlier_entries(out):
        target = _free_sibling(out)
        stage.rename(target)
        warnings.warn(f"{what}: another run wrote {out} while this one ran; this run's files are in {target}")
        if landed is not None:
            landed.append(target)
        return
    if out.is_dir():
        old = out.parent / f".{out.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.old"
        out.rename(old)
        stage.rename(out)
        for p in old.iterdir():
            if p.name == ".hydra" or p.suffix == ".log":
                p.rename(out / p.name)
        shutil.rmtree(old)
    else:
        stage.rename(out)
    if landed is not None:
        landed.append(out)


NOISY_LOGGERS = ("torch.onnx", "onnxscript", "onnx_ir", "torch.export", "torch._export", "torch._dynamo",
                 "torch._inductor", "torch.fx")
"""Libraries whose own logs fill a command's output: ``tcn-ahrs benchmark speed`` printed 1,780 lines of
the ONNX exporter's INFO around its table, ``tcn-ahrs export`` its "torchvision is not installed"."""


def quiet_third_party(verbose: bool = False) -> None:
    """The libraries of :data:`NOISY_LOGGERS` below ERROR off, and torch's pytree deprecation
    warning, unless ``verbose`` (every command: ``verbose=true`` brings them back)."""
    import logging
    import warnings

    for name in NOISY_LOGGERS:
        logging.getLogger(name).setLevel(logging.NOTSET if verbose else logging.ERROR)
    if not verbose:
        warnings.filterwarnings("ignore", message=r".*isinstance\(treespec, LeafSpec\)", category=FutureWarning)


def leaf_keys(cfg, prefix: str = "") -> List[str]:
    """Every leaf of a config as a dotted key (``train.epochs``)."""
    from omegaconf import DictConfig

    out = []
    for k, v in cfg.items():
        out += leaf_keys(v, f"{prefix}{k}.") if isinstance(v, DictConfig) else [f"{prefix}{k}"]
    return out


def check_overrides(config_name: str, argv: Optional[List[str]] = None, conf_dir=None) -> None:
    """Compose ``config_name`` with the command line's ``key=value`` overrides before Hydra does:
    a misspelt key, a missing group option or a bad value becomes the scripts' one-line error
    (exit 2) with the nearest valid key or option, instead of Hydra's multi-line report (exit 1).
    Arguments Hydra handles itself (``--cfg``, ``-m``, ``hydra.*``) are left to it. ``conf_dir``:
    the config folder (default: the package's, :data:`tcn_ahrs.conf.CONF_DIR`, which the commands'
    ``@hydra.main`` search); without ``<config_name>.yaml`` there, Hydra reports as usual."""
    import difflib
    import re

    args = list(sys.argv[1:] if argv is None else argv)
    if any(a.startswith("-") for a in args):
        return
    overrides = [a for a in args if "=" in a and not a.lstrip("+~").startswith("hydra")]
    if not overrides:
        return
    # config folders of one's own (hydra.searchpath=[file://my_conf]) hold options the overrides name
    overrides += [a for a in args if a.startswith("hydra.searchpath=")]
    from hydra import compose, initialize_config_dir

    from .conf import CONF_DIR

    conf = Path(conf_dir) if conf_dir is not None else CONF_DIR
    if not (conf / f"{config_name}.yaml").is_file():
        return
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        try:
            compose(config_name, overrides=overrides)
            return
        except Exception as e:  # noqa: BLE001 - Hydra and OmegaConf raise many types
            text = str(e)
    if os.environ.get("HYDRA_FULL_ERROR") == "1":
        return  # Hydra reports it with the traceback
    first = text.strip().splitlines()[0] if text.strip() else "invalid override"
    hint = ""
    m = re.search(r"full_key: (\S+)", text) or re.search(r"Could not override '([^']+)'", text)
    group = re.search(r"Could not find '([^/']+)/([^']+)'", text)
    if group:
        options = re.findall(r"^\t(\S+)$", text, flags=re.M)
        near = difflib.get_close_matches(group.group(2), options, n=1)
        hint = f" (did you mean {group.group(1)}={near[0]}?)" if near else f" (options: {', '.join(options)})"
    elif m:
        with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
            keys = leaf_keys(compose(config_name, overrides=[o for o in overrides if not o.startswith(m.group(1) + "=")]))
        near = difflib.get_close_matches(m.group(1), keys, n=1, cutoff=0.6)
        hint = f" (did you mean {near[0]!r}?)" if near else ""
    print(f"error: {config_name} config: {first}{hint}\n(HYDRA_FULL_ERROR=1 shows Hydra's report)", file=sys.stderr)
    raise SystemExit(EXIT_USER_ERROR)
