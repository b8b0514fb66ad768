"""The generic recording format: bring your own IMU data (documented in ``data/README.md``).

CSV: a header row naming the columns (any order, extra columns ignored):

* ``t`` (s, strictly increasing), ``gyr_x, gyr_y, gyr_z`` (rad/s), ``acc_x, acc_y, acc_z``
  (m/s^2, specific force: +9.81 along the up axis at rest);
* optional ``mag_x, mag_y, mag_z`` (uT), ``quat_w, quat_x, quat_y, quat_z`` (ground truth
  ``nav_from_body``, ENU; empty/NaN rows = no ground truth there), ``score`` (0/1: samples to
  score).

HDF5: datasets ``t`` (N,), ``gyr`` (N,3), ``acc`` (N,3), optional ``mag`` (N,3), ``quat`` (N,4),
``score`` (N,).

Other units and frames are declared, not guessed: HDF5 root attributes, or for CSV a YAML
sidecar ``<file stem>.yaml`` next to the file, with any of

====================  =====================================  ==========
key                   values                                 default
====================  =====================================  ==========
``time_unit``         ``s``, ``ms``, ``us``, ``ns``          ``s``
``gyr_unit``          ``rad/s``, ``deg/s``                   ``rad/s``
``acc_unit``          ``m/s^2``, ``g``                       ``m/s^2``
``acc_sign``          ``specific_force``, ``gravity``        ``specific_force``
``mag_unit``          ``uT``, ``G`` (Gauss), ``nT``,         ``uT``
                      ``arbitrary`` (direction only: scaled
                      to a median norm of 50 uT)
``quat_order``        ``wxyz``, ``xyzw``                     ``wxyz``
``nav_frame``         ``ENU``, ``NED``, ``NWU``, or the      ``ENU``
                      3x3 matrix ``C_enu_from_frame`` (rows;
                      e.g. an x-up motion-capture world)
``gt_body_from_imu``  the ground-truth body's attitude       identity
                      relative to the IMU: quaternion
                      (w,x,y,z) or 3x3 matrix ``C_body_from_imu``
``rate``              nominal rate in Hz                     from ``t``
``clock``             ``stamps``, or ``nominal``: a regular  ``stamps``
                      stream whose timestamps jitter runs
                      on its uniform grid (both warn)
``gt_time_offset``    s the ground truth's stamps run late   0
                      against the IMU's (the wiring check
                      fits and prints it)
``mag_hard_iron``     the magnetometer's constant offset     none
                      [x, y, z] µT, subtracted (the check
                      that finds one prints it)
``gyr_bias``          the gyro's constant bias [x, y, z]     none
                      rad/s, subtracted (the ground-truth
                      check that finds one prints it)
``acc_bias``          the accelerometer's constant bias      none
                      [x, y, z] m/s², subtracted (printed
                      where the ground truth shows one)
``mag_soft_iron``     3x3 matrix (rows) applied to the       identity
                      magnetometer after ``mag_hard_iron``
                      (printed where the ground truth
                      shows soft iron)
====================  =====================================  ==========

converted here with :mod:`tcn_ahrs.conventions`. A sidecar key not in this table is an error
(a misspelt declaration must not be ignored). Undeclared deg/s, g, millisecond timestamps, a
flipped accelerometer, x,y,z,w quaternions or a ground truth that is not z-up are rejected by
:class:`~tcn_ahrs.sequence.ImuSequence`'s plausibility checks, with the declaration to add.

``list_recordings(root)`` returns every ``*.csv``/``*.h5``/``*.hdf5`` under ``root``
(recursively) as its path relative to ``root`` without the suffix (e.g. ``walk/run1``).
"""
from __future__ import annotations

import warnings
from dataclasses import fields
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from .. import conventions as conv
from ..config.data import GenericDeclarations
from ..sequence import DataError, ImuSequence, clock_kind
from ._common import (check_finite, check_increasing, interpolate_quat, matrix_to_quat, open_hdf5, quat_to_matrix,
                      read_numeric_csv)

SUFFIXES = (".csv", ".h5", ".hdf5")
AXES = ("x", "y", "z")
# the declarations, their meaning and defaults: tcn_ahrs/config/data.py (GenericDeclarations)
ATTR_KEYS = tuple(f.name for f in fields(GenericDeclarations))
_DECL = GenericDeclarations()


def list_recordings(root) -> List[str]:
    """Every ``*.csv``/``*.h5``/``*.hdf5`` under ``root``, as relative paths without suffix, sorted."""
    root = Path(root)
    return sorted({p.relative_to(root).with_suffix("").as_posix()
                   for p in root.rglob("*") if p.suffix.lower() in SUFFIXES and p.is_file()})


def load_recording(root, name: str) -> ImuSequence:
    """Load recording ``name`` (relative path, with or without suffix) from ``root``."""
    root = Path(root)
    direct = root / name
    if direct.suffix.lower() in SUFFIXES and direct.is_file():
        return load_file(direct, name=Path(name).with_suffix("").as_posix())
    for suf in SUFFIXES:
        p = root / f"{name}{suf}"
        if p.is_file():
            return load_file(p, name=name)
    raise DataError(str(root), "recording", f"expected a file {name}.csv/.h5/.hdf5 under this folder, found none")


def load_file(path, name: Optional[str] = None) -> ImuSequence:
    """Load one generic CSV or HDF5 file (see the module docstring for the format)."""
    path = Path(path)
    if path.suffix.lower() == ".csv":
        arrays, attrs = _read_csv(path)
    elif path.suffix.lower() in (".h5", ".hdf5"):
        arrays, attrs = _read_hdf5(path)
    else:
        raise DataError(str(path), "file", f"expected a .csv, .h5 or .hdf5 file, got suffix {path.suffix!r}")
    return build(path, name or path.stem, arrays, attrs)


# --------------------------------------------------------------------------------- readers
def _read_sidecar(path: Path) -> Dict:
    side = path.with_suffix(".yaml")
    if not side.is_file():
        return {}
    from omegaconf import OmegaConf

    try:
        cfg = OmegaConf.to_container(OmegaConf.load(side))
    except Exception as e:  # yaml errors come in many types
        raise DataError(str(side), "file", f"expected a YAML mapping of unit/frame declarations: {e}") from None
    if not isinstance(cfg, dict):
        raise DataError(str(side), "file", "expected a YAML mapping of unit/frame declarations")
    check_declarations(str(side), cfg)
    return cfg


def _clock(src: str, t: np.ndarray, declared: str) -> Tuple[np.ndarray, str]:
    """The timestamps the filters run on, and what was found (:func:`~tcn_ahrs.sequence.clock_kind`).
    Jittered stamps on a regular stream make every step wrong by the jitter (measured: ±30 %
    stamp noise took the learned model from 4.3° to 14.2° AAE) and are warned about; declared
    ``clock: nominal``, the stream runs on its uniform grid instead. Truly irregular sampling
    is warned about and runs on its steps (``nominal`` is refused there: there is no grid)."""
    if declared not in ("stamps", "nominal"):
        raise DataError(src, "clock", f"expected 'stamps' or 'nominal', got {declared!r}")
    c = clock_kind(t)
    what = (f"timestamps jitter by {100 * c['jitter']:.0f} % of the {1.0 / c['step']:.4g} Hz step (every stamp "
            f"within {c['off_grid']:.2f} steps of a uniform grid)")
    if c["kind"] == "jittered":
        if declared == "nominal":
            warnings.warn(f"{src}: {what}: run on the nominal period (declared clock: nominal)", stacklevel=3)
            k = np.arange(t.shape[0], dtype=np.float64)
            return c["grid_start"] + c["step"] * k, "nominal"
        warnings.warn(f"{src}: {what}: a regular stream with noisy timestamps? The filters integrate over the "
                      "stamped steps; declare clock: nominal to run on the nominal period", stacklevel=3)
        return t, "jittered"
    if c["kind"] == "irregular":
        if declared == "nominal":
            raise DataError(src, "clock", f"declared nominal, but the sampling is irregular (stamps up to "
                                          f"{c['off_grid']:.1f} steps off any uniform grid): drop the declaration")
        warnings.warn(f"{src}: irregular sampling (steps vary by {100 * c['jitter']:.0f} %, stamps up to "
                      f"{c['off_grid']:.1f} steps off any uniform grid): the filters run on the actual steps",
                      stacklevel=3)
    return t, c["kind"]


def _vector(src: str, attrs: Dict, key: str, unit: str) -> np.ndarray:
    """A declared constant offset ``key`` ([x, y, z] in ``unit``; zeros when not declared)."""
    value = attrs.get(key, getattr(_DECL, key))
    if value is None:
        return np.zeros(3)
    try:
        return np.asarray(value, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise DataError(src, key, f"expected [x, y, z] in {unit}, got {value!r}") from None


def _matrix(src: str, attrs: Dict, key: str) -> np.ndarray:
    """A declared 3x3 matrix ``key`` (rows; the identity when not declared), invertible."""
    value = attrs.get(key, getattr(_DECL, key))
    if value is None:
        return np.eye(3)
    try:
        m = np.asarray(value, dtype=np.float64).reshape(3, 3)
    except (TypeError, ValueError):
        m = np.zeros((3, 3))
    if not abs(np.linalg.det(m)) > 1e-6:
        raise DataError(src, key, f"expected an invertible 3x3 matrix (rows), got {value!r}")
    return m


def check_declarations(src: str, attrs: Dict) -> None:
    """A declaration key not in ``ATTR_KEYS`` is an error naming the nearest key (a misspelt
    declaration must not be ignored)."""
    import difflib

    for key in attrs:
        if key not in ATTR_KEYS:
            near = difflib.get_close_matches(str(key), ATTR_KEYS, n=1)
            raise DataError(src, str(key), "unknown declaration" + (f" (did you mean {near[0]!r}?)" if near else "")
                            + f"; expected one of {list(ATTR_KEYS)}")


def _read_csv(path: Path):
    names, values, _ = read_numeric_csv(path, header=True)
    col = {n: i for i, n in enumerate(names)}

    def take(fields, required):
        present = [f in col for f in fields]
        if not any(present) and not required:
            return None
        for f, ok in zip(fields, present):
            if not ok:
                raise DataError(str(path), f, f"expected a column named '{f}'; header has {names}")
        return values[:, [col[f] for f in fields]]

    arrays = {
        "t": take(["t"], True)[:, 0],
        "gyr": take([f"gyr_{a}" for a in AXES], True),
        "acc": take([f"acc_{a}" for a in AXES], True),
        "mag": take([f"mag_{a}" for a in AXES], False),
        "quat": None,
        "score": None,
    }
    attrs = _read_sidecar(path)
    order = str(attrs.get("quat_order", _DECL.quat_order)).lower()
    if order not in ("wxyz", "xyzw"):
        raise DataError(str(path), "quat_order", f"expected 'wxyz' or 'xyzw', got {order!r}")
    arrays["quat"] = take([f"quat_{c}" for c in order], False)
    if "score" in col:
        arrays["score"] = values[:, col["score"]]
    return arrays, attrs


def _read_hdf5(path: Path):
    src = str(path)
    fh = open_hdf5(path)
    arrays = {}
    with fh:
        for key in ("t", "gyr", "acc"):
            if key not in fh:
                raise DataError(src, key, f"expected dataset '{key}' (generic HDF5: t, gyr, acc, [mag], [quat], "
                                          f"[score]); file has {sorted(fh.keys())}")
        for key in ("t", "gyr", "acc", "mag", "quat", "score"):
            if key in fh:
                try:
                    arrays[key] = np.asarray(fh[key][()], dtype=np.float64)
                except (OSError, TypeError, ValueError) as e:
                    raise DataError(src, key, f"could not read dataset (truncated or corrupt file?): {e}") from None
            else:
                arrays[key] = None
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in fh.attrs.items()}
        # other attributes (a description, a creator) may stay; one that looks like a misspelt
        # declaration (mag_units, quat_ordr) must not be ignored
        import difflib

        attrs = {k: v for k, v in attrs.items()
                 if k in ATTR_KEYS or difflib.get_close_matches(str(k), ATTR_KEYS, n=1, cutoff=0.75)}
    order = str(attrs.get("quat_order", _DECL.quat_order)).lower()
    if order not in ("wxyz", "xyzw"):
        raise DataError(src, "quat_order", f"expected 'wxyz' or 'xyzw', got {order!r}")
    if arrays["quat"] is not None and order == "xyzw":
        arrays["quat"] = conv.quat_xyzw_to_wxyz(arrays["quat"])
    return arrays, attrs


# ---------------------------------------------------------------------------- conversions
def _convert(src: str, key: str, value, table: Dict[str, callable]):
    unit = str(value)
    if unit not in table:
        raise DataError(src, key, f"expected one of {sorted(table)}, got {unit!r}")
    return table[unit]


def _rotation(src: str, key: str, value, quaternion: bool) -> Optional[np.ndarray]:
    """A declared rotation as a 3x3 matrix (None: identity/ENU): a frame name (nav_frame), a
    3x3 matrix (rows), or — where ``quaternion`` — a (w,x,y,z) quaternion."""
    if value is None:
        return None
    if isinstance(value, str):
        if quaternion:
            raise DataError(src, key, f"expected a quaternion [w, x, y, z] or a 3x3 matrix, got {value!r}")
        try:
            c = conv.enu_from_frame(value)
        except ValueError as e:
            raise DataError(src, key, str(e)) from None
        return None if value.upper() == "ENU" else c
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = np.zeros(0)
    if quaternion and m.shape == (4,):
        n = np.linalg.norm(m)
        if not abs(n - 1.0) < 1e-3:
            raise DataError(src, key, f"expected a unit quaternion [w, x, y, z], got norm {n:.4g}")
        return quat_to_matrix(m[None] / n)[0]
    if m.shape != (3, 3) or not np.allclose(m @ m.T, np.eye(3), atol=1e-4) or np.linalg.det(m) < 0:
        what = "a frame name (ENU, NED, NWU) or " if not quaternion else "a quaternion [w, x, y, z] or "
        raise DataError(src, key, f"expected {what}a 3x3 rotation matrix (orthonormal rows, det +1), got {value!r}")
    return m


_TIME = {"s": lambda x: x, "ms": lambda x: x * 1e-3, "us": lambda x: x * 1e-6, "ns": lambda x: x * 1e-9}
_GYR = {"rad/s": lambda x: x, "deg/s": conv.deg_to_rad}
_ACC = {"m/s^2": lambda x: x, "m/s2": lambda x: x, "g": conv.g_to_mps2}
_ACC_SIGN = {"specific_force": lambda x: x, "gravity": conv.accel_down_to_up}
def _direction_only(m: np.ndarray) -> np.ndarray:
    """``mag_unit: arbitrary``: an AHRS uses the field's direction (its norm only to flag
    disturbances), so scale to a median norm of 50 uT."""
    return m * (50.0 / max(float(np.median(np.linalg.norm(m, axis=1))), 1e-12))


_MAG = {"uT": lambda x: x, "G": conv.gauss_to_ut, "Gauss": conv.gauss_to_ut, "nT": conv.nt_to_ut,
        "arbitrary": _direction_only}


def build(path: Path, name: str, a: Dict, attrs: Dict, dataset: str = "generic") -> ImuSequence:
    """Arrays in the generic layout (``t``, ``gyr``, ``acc``, ``mag``, ``quat``, ``score``; absent:
    None) plus the declarations ``attrs`` -> a validated :class:`ImuSequence` (also used by the
    ROS bag loader, so every format gets the same conversions and checks)."""
    src = str(path)
    check_declarations(src, attrs)
    t = np.asarray(a["t"], dtype=np.float64).reshape(-1)
    t = _convert(src, "time_unit", attrs.get("time_unit", _DECL.time_unit), _TIME)(t)
    n = t.shape[0]
    if n < 2:
        raise DataError(src, "t", f"expected at least 2 samples, got {n}")
    check_increasing(src, "t", t)
    t, clock_note = _clock(src, t, attrs.get("clock", _DECL.clock))
    for key, width in (("gyr", 3), ("acc", 3), ("mag", 3), ("quat", 4)):
        if a[key] is not None and (a[key].ndim != 2 or a[key].shape != (n, width)):
            raise DataError(src, key, f"expected shape ({n}, {width}), got {a[key].shape}")
    gyro = _convert(src, "gyr_unit", attrs.get("gyr_unit", _DECL.gyr_unit), _GYR)(check_finite(src, "gyr", a["gyr"]))
    acc = check_finite(src, "acc", a["acc"])
    acc = _convert(src, "acc_unit", attrs.get("acc_unit", _DECL.acc_unit), _ACC)(acc)
    acc = _convert(src, "acc_sign", attrs.get("acc_sign", _DECL.acc_sign), _ACC_SIGN)(acc)
    mag = None
    if a["mag"] is not None:
        mag = _convert(src, "mag_unit", attrs.get("mag_unit", _DECL.mag_unit), _MAG)(check_finite(src, "mag", a["mag"]))
        mag = mag - _vector(src, attrs, "mag_hard_iron", "uT")
        mag = mag @ _matrix(src, attrs, "mag_soft_iron").T
    gyro = gyro - _vector(src, attrs, "gyr_bias", "rad/s")
    acc = acc - _vector(src, attrs, "acc_bias", "m/s^2")
    quat = valid = None
    if a["quat"] is not None:
        quat = np.asarray(a["quat"], dtype=np.float64)
        valid = np.all(np.isfinite(quat), axis=1)
        norms = np.linalg.norm(quat[valid], axis=1)
        if norms.size and np.max(np.abs(norms - 1.0)) > 1e-2:  # before any declared frame renormalises them
            raise DataError(src, "quat", f"expected unit quaternions, found norm {norms.min():.4f}..{norms.max():.4f}")
        c_nav = _rotation(src, "nav_frame", attrs.get("nav_frame", _DECL.nav_frame), quaternion=False)
        c_body = _rotation(src, "gt_body_from_imu", attrs.get("gt_body_from_imu"), quaternion=True)
        if (c_nav is not None or c_body is not None) and valid.any():
            # ground truth nav'_from_body' -> ENU nav_from_imu: C = C_enu_from_nav' C_gt C_body'_from_imu
            r = quat_to_matrix(quat[valid] / np.linalg.norm(quat[valid], axis=1, keepdims=True))
            if c_nav is not None:
                r = c_nav @ r
            if c_body is not None:
                r = r @ c_body
            q = quat.copy()
            q[valid] = matrix_to_quat(r)
            quat = q
    offset = attrs.get("gt_time_offset", _DECL.gt_time_offset)
    if quat is not None and offset:
        try:
            offset = float(offset)
        except (TypeError, ValueError):
            raise DataError(src, "gt_time_offset", f"expected seconds, got {offset!r}") from None
        # stamp t holds the attitude at IMU time t - offset: resampled onto the IMU's stamps
        step = float(np.median(np.diff(t)))
        quat, valid = interpolate_quat(t - offset, quat, t, 2.0 * step, 4.0 * step)
    score = None
    if a["score"] is not None:
        s = np.asarray(a["score"]).reshape(-1)
        if s.shape != (n,):
            raise DataError(src, "score", f"expected shape ({n},), got {s.shape}")
        score = np.nan_to_num(s, nan=0.0) > 0.5
    try:
        rate = float(attrs.get("rate", _DECL.rate) or 0.0)
    except (TypeError, ValueError):
        raise DataError(src, "rate", f"expected the nominal rate as a number in Hz, got {attrs.get('rate')!r}") from None
    if rate:
        measured = 1.0 / float(np.median(np.diff(t)))
        if not (rate > 0 and abs(rate / measured - 1.0) <= 0.05):
            raise DataError(src, "rate", f"declared {rate:g} Hz, but the timestamps step at {measured:.4g} Hz "
                                         "(median): correct the declaration or drop it (the rate is read from t)")
    meta = {"dataset": dataset, "declared": {k: attrs[k] for k in ATTR_KEYS if k in attrs}, "clock": clock_note}
    return ImuSequence(name=name, source=src, time=t, gyro=gyro, accel=acc, mag=mag, quat=quat,
                       quat_valid=valid, score_mask=score, rate=rate, meta=meta)


def device_loader(dataset: str):
    """``load_recording`` for a device whose recordings are in the generic format under a name of
    its own (``data=iphone5``): the generic loader, the recordings named as that dataset."""
    def load(root, name: str) -> ImuSequence:
        seq = load_recording(root, name)
        seq.meta["dataset"] = dataset
        return seq
    return load
