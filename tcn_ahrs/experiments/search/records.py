"""Each outer fold x seed's record on disk (``search.out/records/``): what a killed search resumes
from and what the jobs of a Hydra multirun hand to the run that combines them; and Optuna's
SQLite storage that those jobs share."""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Dict, Optional


def _sqlite_storage(url: str, tries: int = 10):
    """Optuna's storage on an SQLite file that several jobs of one multirun share: each waits for
    the file's lock instead of failing at once, and a job that lost the race to create the schema
    opens the one the other created."""
    import optuna
    from sqlalchemy.exc import IntegrityError, OperationalError

    for k in range(tries):
        try:
            return optuna.storages.RDBStorage(url, engine_kwargs={"connect_args": {"timeout": 300}})
        except (IntegrityError, OperationalError):
            if k == tries - 1:
                raise
            time.sleep(0.2 * (k + 1))


def multirun_job() -> Optional[int]:
    """This job's number in a Hydra multirun (``tcn-ahrs search -m ...``), None in a plain run."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        hc = HydraConfig.get()
    except (ImportError, ValueError):  # not started by Hydra (a library call)
        return None
    return int(hc.job.num) if hc.mode == RunMode.MULTIRUN else None


def _record_path(out: Path, fold: int, seed: int) -> Path:
    return Path(out) / "records" / f"fold{fold}_seed{seed}.json"


RECIPE_KEYS = ("inner", "families", "calibrations", "learned_checkpoint", "learned", "learn", "tune_seconds", "trials",
               "tie_margin", "incl_margin")
"""The search settings a fold x seed record depends on (with the folds): a record written with
others is not reused."""


def _read_record(out: Path, fold: int, seed: int, recipe: Dict[str, Any]) -> Optional[Dict[str, Any]]:
    """The record of an earlier run or another multirun job of this search, None if there is none;
    ValueError when it was written with other settings (nothing is overwritten)."""
    p = _record_path(out, fold, seed)
    if not p.is_file():
        return None
    rec = json.loads(p.read_text())
    if rec.get("recipe") != json.loads(json.dumps(recipe, default=float)):
        changed = sorted(k for k in recipe if (rec.get("recipe") or {}).get(k) != recipe[k])
        raise ValueError(f"{p}: written by a search with other settings ({', '.join(changed) or 'format'}); "
                         "choose another search.out (nothing is overwritten)")
    return rec


def _write_record(out: Path, rec: Dict[str, Any]) -> None:
    """One outer fold x seed's record, atomically (a killed job leaves none, and is run again)."""
    import os

    p = _record_path(out, rec["fold"], rec["seed"])
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".partial")
    tmp.write_text(json.dumps(rec, indent=1, default=float))
    os.replace(tmp, p)
