"""The shipped models, installed inside the package as ``tcn_ahrs.checkpoints`` (setup.py), so
``tcn-ahrs evaluate ckpt=general9_residual`` finds them from a wheel as from a checkout.

Each ``<device>_<family>.ckpt`` (learned) or ``.json`` (a classical filter the search chose) has its
model card beside it (``.md``); ``closed_loop/``, ``residual/`` and ``paper/`` hold the other
families' files, for the tables and the tests (not installed). Code finds them through
:data:`SHIPPED_DIR`.
"""
from pathlib import Path

SHIPPED_DIR = Path(__file__).resolve().parent
