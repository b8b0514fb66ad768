"""Helpers shared by the real-data loaders: checked array reading, CSV with headers,
ground-truth interpolation onto IMU stamps (with gap masking) and small numpy rotation math.

Every check raises :class:`~tcn_ahrs.sequence.DataError` naming the file, the field *as the
file calls it* (``imu_gyr``, ``w_RS_S_x``, ``gyr_x``) and what was expected.
"""
from __future__ import annotations

from pathlib import Path
from typing import List, Sequence, Tuple

import numpy as np
import torch

from .. import so3
from ..sequence import DataError


# ---------------------------------------------------------------------------------- checks
def check_finite(source, field_name: str, a: np.ndarray) -> np.ndarray:
    """Raise if ``a`` (N, ...) holds NaN/inf; names the first bad sample."""
    a = np.asarray(a, dtype=np.float64)
    bad = ~np.isfinite(a)
    if bad.any():
        i = int(np.argmax(bad.reshape(a.shape[0], -1).any(axis=1)))
        raise DataError(str(source), field_name,
                        f"expected finite numbers, found NaN/inf at sample {i} ({int(bad.reshape(a.shape[0], -1).any(axis=1).sum())} samples)")
    return a


def check_increasing(source, field_name: str, t: np.ndarray) -> np.ndarray:
    """Raise unless timestamps ``t`` (N,) are finite and strictly increasing."""
    t = check_finite(source, field_name, t)
    d = np.diff(t)
    if not np.all(d > 0):
        i = int(np.argmax(~(d > 0)))
        raise DataError(str(source), field_name,
                        f"expected strictly increasing timestamps; row {i + 1} ({t[i + 1]!r}) does not "
                        f"follow row {i} ({t[i]!r})")
    return t


def check_shape(source, field_name: str, a: np.ndarray, shape: Tuple) -> np.ndarray:
    """Raise unless ``a`` has ``shape`` (None = any length)."""
    if a.ndim != len(shape) or any(s is not None and s != t for s, t in zip(shape, a.shape)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise DataError(str(source), field_name, f"expected shape {want}, got {a.shape}")
    return a


# ------------------------------------------------------------------------------------ HDF5
def open_hdf5(path: Path):
    """Open an HDF5 file for reading; a missing, empty or unreadable file raises one
    :class:`DataError` naming it."""
    import h5py

    src = str(path)
    if not path.is_file():
        raise DataError(src, "file", "expected an HDF5 file, found nothing there")
    if path.stat().st_size == 0:
        raise DataError(src, "file", "expected an HDF5 file, the file is empty")
    try:
        return h5py.File(path, "r")
    except OSError as e:
        raise DataError(src, "file", f"expected a readable HDF5 file (truncated or corrupt?): {e}") from None


# ------------------------------------------------------------------------------------- CSV
def read_numeric_csv(path: Path, header: bool, ncols: Sequence[int] | None = None,
                     int_first_column: bool = False) -> Tuple[List[str], np.ndarray, np.ndarray | None]:
    """Read a comma-separated numeric file.

    Returns ``(column_names, values (R, C) float64, first_column_int64 or None)``. Column names
    are the raw header cells (stripped); ``[]`` without a header. ``int_first_column`` also
    parses column 0 as int64 (nanosecond stamps lose precision as float64).
    Raises DataError for a missing/empty file, ragged rows and non-numeric cells.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(str(path), "file", "expected a file, found nothing there")
    try:
        with open(path, "r", encoding="utf-8-sig") as fh:
            lines = [ln.strip() for ln in fh]
    except UnicodeDecodeError as e:
        raise DataError(str(path), "file", f"expected UTF-8 text, byte {e.start} is not ({e.reason}): save the "
                                           "file as UTF-8 (or plain ASCII)") from None
    lines = [ln for ln in lines if ln]
    names: List[str] = []
    if header:
        if not lines:
            raise DataError(str(path), "file", "expected a header row and data rows, the file is empty")
        names = [c.strip() for c in lines[0].split(",")]
        twice = sorted({n for n in names if names.count(n) > 1 and n})
        if twice:
            raise DataError(str(path), "header", f"column name(s) {twice} appear more than once: which column "
                                                 "holds the data is ambiguous; rename or drop the duplicates")
        if len(names) == 1 and any(d in lines[0] for d in (";", "\t")):
            sep = "';'" if ";" in lines[0] else "a tab"
            raise DataError(str(path), "header", f"expected comma-separated columns, the header is separated "
                                                 f"by {sep}: save the file with commas (e.g. pandas to_csv(sep=','))")
        lines = lines[1:]
    if not lines:
        raise DataError(str(path), "file", "expected data rows, found none (empty file)")
    width = len(names) if header else len(lines[0].split(","))
    if ncols is not None and width not in ncols:
        raise DataError(str(path), "columns", f"expected {' or '.join(map(str, ncols))} columns, found {width}")
    rows = []
    for i, ln in enumerate(lines):
        cells = ln.split(",")
        if len(cells) != width:
            raise DataError(str(path), f"row {i + 1 + int(header)}",
                            f"expected {width} comma-separated values, found {len(cells)} (truncated file?)")
        rows.append([c.strip() or "nan" for c in cells])  # empty cell = missing value
    try:
        values = np.array(rows, dtype=np.float64)
    except ValueError:
        for i, cells in enumerate(rows):  # name the first bad cell: row (1-based, as in an editor) and column
            for j, c in enumerate(cells):
                try:
                    float(c)
                except ValueError:
                    col = f"column {j + 1}" + (f" ({names[j]!r})" if j < len(names) else "")
                    raise DataError(str(path), f"row {i + 1 + int(header)}, {col}",
                                    f"expected a number, found {c!r}") from None
        raise
    first = None
    if int_first_column:
        try:
            first = np.array([r[0].strip() for r in rows], dtype=np.int64)
        except ValueError:
            first = np.round(values[:, 0]).astype(np.int64)
    return names, values, first


# ---------------------------------------------------------------------- rotations (numpy)
def _t(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64))


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) w,x,y,z -> (..., 3, 3) (numpy wrapper of :func:`so3.quat_to_matrix`)."""
    return so3.quat_to_matrix(_t(q)).numpy()


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 4) w,x,y,z with w >= 0."""
    return so3.matrix_to_quat(_t(r)).numpy()


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    return so3.quat_mul(_t(p), _t(q)).numpy()


def quat_conj(q: np.ndarray) -> np.ndarray:
    return so3.quat_conj(_t(q)).numpy()


def quat_log(q: np.ndarray) -> np.ndarray:
    return so3.quat_log(_t(q)).numpy()


def body_rate_from_quat(quat: np.ndarray, time: np.ndarray, half_width: int = 1) -> np.ndarray:
    """(N, 3) body-frame angular rate (rad/s) from attitudes ``nav_from_body`` (N, 4) by central
    differences ``Log(q_{k-h}^-1 q_{k+h}) / (t_{k+h} - t_{k-h})``; NaN where undefined."""
    n = quat.shape[0]
    h = half_width
    out = np.full((n, 3), np.nan)
    if n <= 2 * h:
        return out
    d = quat_mul(quat_conj(quat[:-2 * h]), quat[2 * h:])
    dt = time[2 * h:] - time[:-2 * h]
    out[h:n - h] = quat_log(d) / dt[:, None]
    return out


# ------------------------------------------------------- ground truth onto IMU timestamps
def interpolate_quat(t_ref: np.ndarray, q_ref: np.ndarray, t: np.ndarray,
                     max_nearest_s: float, max_bracket_s: float) -> Tuple[np.ndarray, np.ndarray]:
    """Slerp reference attitudes (t_ref (M,), q_ref (M, 4) w,x,y,z) to stamps ``t`` (N,).

    A sample is valid only if it lies inside ``[t_ref[0], t_ref[-1]]``, its nearest reference
    sample is at most ``max_nearest_s`` away, and the two reference samples that bracket it are
    at most ``max_bracket_s`` apart: gaps in the reference (lost tracking) are masked, never
    bridged by long interpolation. Reference rows that are NaN count as absent.

    Returns ``(quat (N, 4) with NaN rows where invalid, valid (N,) bool)``.
    """
    ok = np.all(np.isfinite(q_ref), axis=1)
    t_ref, q_ref = t_ref[ok], q_ref[ok]
    n = t.shape[0]
    out = np.full((n, 4), np.nan)
    valid = np.zeros(n, dtype=bool)
    if t_ref.shape[0] < 2:
        return out, valid
    j = np.clip(np.searchsorted(t_ref, t, side="right") - 1, 0, t_ref.shape[0] - 2)
    t0, t1 = t_ref[j], t_ref[j + 1]
    inside = (t >= t_ref[0]) & (t <= t_ref[-1])
    nearest = np.minimum(np.abs(t - t0), np.abs(t1 - t))
    valid = inside & (nearest <= max_nearest_s) & ((t1 - t0) <= max_bracket_s)
    q0 = q_ref[j[valid]]
    q1 = q_ref[j[valid] + 1].copy()
    q1[np.sum(q0 * q1, axis=1) < 0] *= -1.0  # shortest path
    frac = np.clip((t[valid] - t0[valid]) / (t1[valid] - t0[valid]), 0.0, 1.0)
    q = so3.quat_slerp(_t(q0), _t(q1), _t(frac)).numpy()
    out[valid] = q / np.linalg.norm(q, axis=1, keepdims=True)
    return out, valid


def gt_outliers(quat: np.ndarray, valid: np.ndarray, gyro: np.ndarray, dt: np.ndarray,
                window: int = 10, max_deg: float = 5.0) -> np.ndarray:
    """(N,) bool: ground-truth samples their neighbours contradict (motion-capture flips, jumps).

    Each valid neighbour j within ±``window`` samples predicts attitude k from its own by the
    gyro's rotation from j to k; a sample whose median disagreement exceeds ``max_deg`` is an
    outlier. Written with ``D_k = C_k P_k^T`` (P_k the gyro's prefix product): the disagreement
    of j with k is the angle of ``D_k^T D_j``, so one prefix product serves every pair.
    quat (N, 4) w,x,y,z nav_from_body (NaN where not valid), gyro (N, 3) rad/s in the same
    body frame, dt (N,) s (sample k moves k-1 -> k)."""
    n = quat.shape[0]
    q = _t(np.where(valid[:, None], quat, [1.0, 0.0, 0.0, 0.0]))
    p = so3.integrate(torch.eye(3, dtype=torch.float64), _t(gyro), _t(dt))  # P_0 = I, P_k = P_{k-1} exp(ω_k dt_k)
    d = (so3.quat_to_matrix(q) @ p.transpose(-1, -2)).numpy()
    errs = np.full((n, 2 * window), np.nan)
    col = 0
    for o in range(-window, window + 1):
        if o == 0:
            continue
        lo, hi = max(0, -o), min(n, n - o)
        k = np.arange(lo, hi)
        tr = np.einsum("nij,nij->n", d[k], d[k + o])
        ang = np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))
        ang[~valid[k + o]] = np.nan
        errs[k, col] = ang
        col += 1
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: no valid neighbour
            med = np.nanmedian(errs, axis=1)
    return valid & np.isfinite(med) & (med > max_deg)
