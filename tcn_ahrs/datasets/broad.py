"""BROAD (Laidig et al., Data 2021): HDF5 trials with optical ground truth.

Reads the published ``data_hdf5`` files (float64) and the project's float32 copies alike
(same schema): ``imu_gyr`` (rad/s), ``imu_acc`` (m/s^2, specific force), ``imu_mag`` (uT),
``opt_quat`` (w,x,y,z, sensor -> ENU = ``nav_from_body``, already the project's convention),
``movement`` (bool, the samples BROAD scores -> ``score_mask``), attribute ``sampling_rate``.
Timestamps are ``index / sampling_rate``. NaN rows of ``opt_quat`` (lost optical tracking)
become ``quat_valid == False``; they are never interpolated. ``meta["groups"]`` comes from
``trials.json`` next to the files when present.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from ..sequence import DataError, ImuSequence
from ._common import check_finite, check_shape, open_hdf5

SUFFIXES = (".hdf5", ".h5")
REQUIRED = ("imu_gyr", "imu_acc", "opt_quat")


def list_recordings(root) -> List[str]:
    """Trial names (file stems) of every ``*.hdf5`` / ``*.h5`` directly under ``root``, sorted."""
    root = Path(root)
    return sorted(p.stem for p in root.iterdir() if p.suffix in SUFFIXES and p.is_file())


def _find(root: Path, name: str) -> Path:
    for suf in SUFFIXES:
        p = root / f"{name}{suf}"
        if p.is_file():
            return p
    raise DataError(str(root), "recording", f"expected a file {name}.hdf5 (or .h5) under this folder, found none")


def read_trials(root) -> Dict[str, dict]:
    """``trials.json`` -> {trial name: {"description", "groups"}} ({} when absent).

    Looked up in ``root`` and, for the published layout (``broad/data_hdf5/*.hdf5`` with
    ``broad/trials.json``), in its parent folder."""
    candidates = [Path(root) / "trials.json", Path(root).parent / "trials.json"]
    p = next((c for c in candidates if c.is_file()), None)
    if p is None:
        return {}
    try:
        return dict(json.loads(p.read_text()).get("trials", {}))
    except (ValueError, AttributeError) as e:
        raise DataError(str(p), "trials", f"expected JSON with a 'trials' object: {e}") from None


def load_recording(root, name: str) -> ImuSequence:
    """Load trial ``name`` (file stem) from folder ``root``, with its groups from trials.json."""
    root = Path(root)
    info = read_trials(root).get(name, {})
    return load_file(_find(root, name), name=name, groups=info.get("groups"),
                     description=info.get("description"))


def load_file(path, name: Optional[str] = None, groups: Optional[List[str]] = None,
              description: Optional[str] = None) -> ImuSequence:
    """Load one BROAD HDF5 file (float32 or float64)."""
    path = Path(path)
    src = str(path)
    fh = open_hdf5(path)
    with fh:
        missing = [k for k in REQUIRED if k not in fh]
        if missing:
            raise DataError(src, missing[0], f"expected dataset '{missing[0]}' (BROAD schema: imu_gyr, imu_acc, "
                                             f"imu_mag, opt_quat, movement); file has {sorted(fh.keys())}")
        if "sampling_rate" not in fh.attrs:
            raise DataError(src, "sampling_rate", "expected the file attribute 'sampling_rate' (Hz)")

        def read(key):
            try:
                return np.asarray(fh[key][()], dtype=np.float64)
            except (OSError, KeyError, TypeError) as e:
                raise DataError(src, key, f"could not read dataset (truncated or corrupt file?): {e}") from None

        rate = float(np.asarray(fh.attrs["sampling_rate"]).reshape(-1)[0])
        gyro = read("imu_gyr")
        accel = read("imu_acc")
        mag = read("imu_mag") if "imu_mag" in fh else None
        quat = read("opt_quat")
        movement = None
        if "movement" in fh:
            try:
                movement = np.asarray(fh["movement"][()]).astype(bool).reshape(-1)
            except OSError as e:
                raise DataError(src, "movement", f"could not read dataset (truncated or corrupt file?): {e}") from None
        info = fh.attrs.get("info", "")
        if isinstance(info, bytes):
            info = info.decode("utf-8", "replace")
    if not (np.isfinite(rate) and rate > 0):
        raise DataError(src, "sampling_rate", f"expected a positive rate in Hz, got {rate!r}")
    n = gyro.shape[0] if gyro.ndim == 2 else -1
    check_shape(src, "imu_gyr", gyro, (None, 3))
    check_shape(src, "imu_acc", accel, (n, 3))
    check_shape(src, "opt_quat", quat, (n, 4))
    check_finite(src, "imu_gyr", gyro)
    check_finite(src, "imu_acc", accel)
    if mag is not None:
        check_shape(src, "imu_mag", mag, (n, 3))
        check_finite(src, "imu_mag", mag)
    if movement is not None:
        check_shape(src, "movement", movement, (n,))
    # Lost optical tracking = NaN rows: masked, never interpolated.
    quat_valid = np.all(np.isfinite(quat), axis=1)
    time = np.arange(n, dtype=np.float64) / rate
    meta = {"dataset": "broad", "groups": list(groups or []), "description": description or "",
            "info": str(info), "sampling_rate": rate,
            # BROAD's optical ground truth is referred to the local magnetic field's north (its paper)
            "heading_reference": "magnetic_north"}
    return ImuSequence(name=name or path.stem, source=src, time=time, gyro=gyro, accel=accel, mag=mag,
                       quat=quat, quat_valid=quat_valid, score_mask=movement, rate=rate, meta=meta)
