"""Test-session setup shared by every test file."""
import os

# `python -m pytest -n 2` (pytest-xdist, the README's test command) runs two worker processes on
# this 2-core machine: each keeps to one torch thread, so the two do not fight over the cores
if os.environ.get("PYTEST_XDIST_WORKER"):
    import torch

    torch.set_num_threads(1)


def built_once(tmp_path_factory, name: str, build):
    """``build(folder) -> JSON-able`` run once per test session even when both xdist workers need
    it (a module fixture is otherwise built by each worker its tests land on: 30-40 s for an
    exported model): the first worker builds under a file lock in the session's shared temp
    folder, the other reads its result. -> (folder, build's result)."""
    import json

    from filelock import FileLock

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the session's folder, above each worker's own
    folder = root / f"once_{name}"
    done = folder / "built.json"
    with FileLock(str(folder) + ".lock"):
        if not done.is_file():
            folder.mkdir(parents=True, exist_ok=True)
            done.write_text(json.dumps(build(folder)))
    return folder, json.loads(done.read_text())
