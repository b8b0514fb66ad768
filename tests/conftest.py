"""Test-session setup shared by every test file."""
import os

# `python -m pytest -n 2` (pytest-xdist, the README's test command) runs two worker processes on
# this 2-core machine: each keeps to one torch thread, so the two do not fight over the cores
if os.environ.get("PYTEST_XDIST_WORKER"):
    import torch

    torch.set_num_threads(1)
