"""Datasets: loaders for real recordings, splits as configuration, per-recording summaries.

Each real-data module (``broad``, ``euroc``, ``tumvi``, ``oxiod``, ``generic``) exposes
``list_recordings(root) -> list[str]`` and ``load_recording(root, name) -> ImuSequence``;
``simulate`` (the embedded default) exposes ``load_split(data_cfg, split)``. Adding a dataset =
one module with those two functions (here, or anywhere importable: ``name: my_pkg.my_dataset``)
+ one ``conf/data/<name>.yaml``; nothing here changes.

Data configuration (``conf/data/<name>.yaml``; ``data/README.md`` documents each)::

    name: euroc                       # module name in this package
    root: ../shared/datasets/euroc    # relative to the working directory (falls back to the repo root)
    split: train                      # train | val | trainval | test | all
    train: [MH_01_easy, ...]          # training recordings: first part trains, the rest validates
    test: [MH_02_easy, ...]           # test recordings (absent ones are skipped with a warning)
    train_part: {seconds: 80}         # or {fraction: 0.7}
    axes: 9                           # 6 drops the magnetometer

Several datasets as one (``conf/data/general6.yaml``): ``parts`` {dataset: its data config} and
``leave_out`` (a part's name or a list, for leave-one-dataset-out); every split is the union of
the parts' splits, recordings named ``<part>/<recording>``, each part read with the top-level
``axes``.
"""
from __future__ import annotations

import importlib
import warnings
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Tuple

import numpy as np

from ..config import plain
from ..sequence import DataError, ImuSequence, ground_truth_agreement, rest_mask

SPLITS = ("train", "val", "trainval", "test", "all")
_REPO_ROOT = Path(__file__).resolve().parents[2]

__all__ = ["load_split", "list_recordings", "loader", "resolve_root", "split_recording", "summarize",
           "gt_gaps", "builtin_datasets", "SPLITS"]


def _get(cfg: Mapping, key: str, default: Any = None) -> Any:
    try:
        v = cfg.get(key, default)
    except AttributeError:
        v = getattr(cfg, key, default)
    return default if v is None else v




def check_data_keys(data_cfg: Mapping) -> None:
    """The data config's keys against its kind's schema (:func:`tcn_ahrs.config.data.data_schema`),
    when it is loaded: a misspelt key (``data.tarin``) is an error naming the expected set."""
    from ..config import check_keys
    from ..config.data import GeneralData, data_schema

    # several datasets as one are GeneralData whatever their name; callers clear `fold` generically
    schema = GeneralData if _get(data_cfg, "parts") is not None else data_schema(_get(data_cfg, "name"))
    check_keys(data_cfg, schema, "data", extra=("fold",))


def builtin_datasets() -> List[str]:
    """The dataset modules of this package (every module but the helpers; ``simulated`` is the
    embedded simulator): a new loader dropped in here is found without editing anything."""
    import pkgutil

    found = [i.name for i in pkgutil.iter_modules(__path__) if not i.name.startswith("_") and i.name != "simulate"]
    return sorted(found) + ["simulated"]


def loader(name: str):
    """The module loading dataset ``name``: ``tcn_ahrs.datasets.<name>``, or any importable
    module of that dotted name (a dataset of one's own: ``data.name=my_pkg.my_dataset``) with
    ``list_recordings(root)`` and ``load_recording(root, name)``."""
    candidates = [f"{__name__}.{name}", name] if "." not in name else [name]
    for mod_name in candidates:
        try:
            mod = importlib.import_module(mod_name)
        except ModuleNotFoundError as e:
            if e.name is not None and not mod_name.startswith(e.name):
                raise  # the module exists but one of its own imports is missing
            continue
        missing = [f for f in ("list_recordings", "load_recording") if not callable(getattr(mod, f, None))]
        if missing:
            raise DataError("data config", "name", f"module {mod_name!r} is not a dataset loader: it lacks "
                                                   f"{' and '.join(missing)} (see tcn_ahrs/datasets/__init__.py)")
        return mod
    raise DataError("data config", "name", f"unknown dataset {name!r}; expected one of {builtin_datasets()} "
                                           "or an importable module with list_recordings and load_recording")


def resolve_root(data_cfg: Mapping) -> Path:
    """``data_cfg.root`` as a folder: relative paths are taken from the working directory, or,
    when nothing is there, from the repository root (so ``../shared/datasets/x`` works from both)."""
    root = _get(data_cfg, "root")
    name = _get(data_cfg, "name", "?")
    if not root:
        raise DataError("data config", "root", f"expected the folder holding the {name} recordings")
    p = Path(str(root)).expanduser()
    if not p.is_absolute() and not p.exists() and (_REPO_ROOT / p).exists():
        p = _REPO_ROOT / p
    if not p.is_dir():
        raise DataError(str(p), "root", f"expected a folder with the {name} recordings, found nothing there "
                                        "(see data/README.md for where to get them; set data.root=...)")
    return p


def list_recordings(data_cfg: Mapping) -> List[str]:
    """Every recording found under ``data_cfg.root`` (for ``simulated``: its recording names)."""
    name = _get(data_cfg, "name")
    if name == "simulated":
        from . import simulate  # written separately; imported lazily

        if hasattr(simulate, "list_recordings"):
            return list(simulate.list_recordings(data_cfg))
        return [s.name for s in simulate.load_split(data_cfg, "all")]
    return loader(name).list_recordings(resolve_root(data_cfg))


def split_recording(seq: ImuSequence, train_part: Mapping) -> tuple:
    """(train part, validation part) of one training recording.

    ``train_part`` is ``{fraction: f}`` (first ``round(f*N)`` samples train; BROAD: 0.7) or
    ``{seconds: s}`` (samples with ``time - time[0] < s`` train; EuRoC/TUM VI/OxIOD: 80).
    Either part is ``None`` when it would hold fewer than 2 samples.
    """
    tp = plain(train_part) or {}
    n = len(seq)
    if "fraction" in tp and tp["fraction"] is not None:
        cut = int(round(float(tp["fraction"]) * n))
    elif "seconds" in tp and tp["seconds"] is not None:
        cut = int(np.searchsorted(seq.time - seq.time[0], float(tp["seconds"]), side="left"))
    else:
        raise DataError("data config", "train_part", f"expected {{fraction: f}} or {{seconds: s}}, got {tp!r}")
    parts = []
    for lo, hi, part in ((0, cut, "train"), (cut, n, "val")):
        if hi - lo < 2:
            parts.append(None)
            continue
        s = seq.slice(lo, hi)
        s.meta.update(part=part, recording=seq.name, part_start_s=float(seq.time[lo] - seq.time[0]))
        parts.append(s)
    return tuple(parts)


def load_split(data_cfg: Mapping, split: Optional[str] = None,
               refused: Optional[List[Tuple[str, str]]] = None) -> List[ImuSequence]:
    """The recordings of one split, as :class:`ImuSequence` objects (see the module docstring).

    split (default ``data_cfg.split``, else ``train``): ``train`` = the training parts of the
    training recordings, ``val`` = their remaining parts (with ``data.fold=i`` set:
    leave-recordings-out, ``val`` = the whole recordings of ``data.folds[i]``, ``train`` = the
    other training recordings, whole), ``trainval`` = the full training
    recordings, ``test`` = the test recordings present under root (absent ones are skipped with
    a warning naming them), ``all`` = every recording found under root, full length.
    ``axes: 6`` drops the magnetometer.

    ``refused``: a list to collect ``(recording, reason)`` of recordings whose checks refuse them
    (:class:`DataError`) while the others load — what a folder's evaluation wants; without it
    the first refusal raises (training must not silently lose a recording).
    """
    name = _get(data_cfg, "name")
    check_data_keys(data_cfg)
    split = split or _get(data_cfg, "split", "train")
    if split not in SPLITS:
        raise DataError("data config", "split", f"expected one of {list(SPLITS)}, got {split!r}")
    if _get(data_cfg, "parts"):
        return _load_parts(data_cfg, split)
    if name == "simulated":
        from . import simulate  # written separately; imported lazily

        return simulate.load_split(data_cfg, split)
    mod = loader(name)
    root = resolve_root(data_cfg)
    available = mod.list_recordings(root)
    fold = _get(data_cfg, "fold")
    held_out: List[str] = []
    if fold is not None:
        folds = list(plain(_get(data_cfg, "folds", [])) or [])
        if not (0 <= int(fold) < len(folds)):
            raise DataError("data config", "fold", f"expected an index into data.folds (0..{len(folds) - 1}), "
                                                   f"got {fold!r}")
        held_out = [str(r) for r in folds[int(fold)]]
    if split == "all":
        names = available
    elif fold is not None and split in ("train", "val"):
        # leave-recordings-out: the fold's recordings validate, whole; the others train, whole
        train_names = [str(r) for r in (plain(_get(data_cfg, "train", [])) or [])]
        names = held_out if split == "val" else [r for r in train_names if r not in held_out]
        missing = [r for r in names if r not in available]
        if missing:
            warnings.warn(f"{name}: fold {fold} recordings absent under {root}, skipped: {', '.join(missing)}",
                          stacklevel=2)
        names = [r for r in names if r in available]
    else:
        key = "test" if split == "test" else "train"
        names = list(plain(_get(data_cfg, key, [])) or [])
        missing = [r for r in names if r not in available]
        if missing:
            warnings.warn(f"{name}: {key} recordings absent under {root}, skipped: {', '.join(missing)}",
                          stacklevel=2)
        names = [r for r in names if r in available]
    seqs: List[ImuSequence] = []
    for rec in names:
        try:
            if getattr(mod, "WANTS_CONFIG", False):  # e.g. the ROS bag topics
                seq = mod.load_recording(root, rec, cfg=plain(data_cfg))
            else:
                seq = mod.load_recording(root, rec)
        except DataError as e:
            if refused is None:
                raise
            refused.append((rec, str(e)))
            continue
        seq.meta.setdefault("recording", rec)
        if split in ("train", "val") and fold is None:
            train, val = split_recording(seq, _get(data_cfg, "train_part", {}))
            seq = train if split == "train" else val
            if seq is None:
                warnings.warn(f"{name}: recording {rec} has no {split} part (too short)", stacklevel=2)
                continue
        seqs.append(seq)
    if int(_get(data_cfg, "axes", 9)) == 6:
        seqs = [s.without_mag() if s.has_mag else s for s in seqs]
    return seqs


def data_parts(data_cfg: Mapping) -> Dict[str, Dict[str, Any]]:
    """{part: its data config} of a multi-dataset config (``parts`` minus ``leave_out``), each
    with the top-level ``axes``; a single dataset: {its name: its config}."""
    parts = plain(_get(data_cfg, "parts")) or {}
    if not parts:
        return {str(_get(data_cfg, "name")): dict(plain(data_cfg))}
    if not isinstance(parts, Mapping):
        raise DataError("data config", "parts", f"expected a mapping {{dataset: data config}}, got {type(parts).__name__}")
    leave = plain(_get(data_cfg, "leave_out")) or []
    leave = [leave] if isinstance(leave, str) else [str(x) for x in leave]
    unknown = [x for x in leave if x not in parts]
    if unknown:
        raise DataError("data config", "leave_out", f"expected part names among {sorted(parts)}, got {unknown}")
    axes = int(_get(data_cfg, "axes", 9))
    return {str(k): {**dict(v), "axes": axes} for k, v in parts.items() if k not in leave}


def _load_parts(data_cfg: Mapping, split: str) -> List[ImuSequence]:
    """The union of the parts' ``split`` (:func:`data_parts`), recordings named ``<part>/<name>``.
    A part whose data is absent is skipped with a warning (its folder missing)."""
    import copy

    seqs: List[ImuSequence] = []
    for part, cfg in data_parts(data_cfg).items():
        if part != "simulated" and cfg.get("name") != "simulated":
            try:
                resolve_root(cfg)
            except DataError as e:
                warnings.warn(f"{_get(data_cfg, 'name', 'data')}: part {part!r} skipped: {e}", stacklevel=2)
                continue
        for s in load_split(cfg, split):
            s = copy.copy(s)  # checked once, at its loader
            # its own meta: the recording (one device check per recording) named with its part too
            s.meta = {**s.meta, "recording": f"{part}/{s.meta.get('recording', s.name)}"}
            s.name = f"{part}/{s.name}"
            seqs.append(s)
    return seqs


# --------------------------------------------------------------------------------- summary
def gt_gaps(seq: ImuSequence, min_gap_s: float = 0.05) -> List[tuple]:
    """Ground-truth gaps longer than ``min_gap_s``: list of ``(start_time, length_s)``.

    A gap is a run of samples without valid ground truth; its length is the time from the last
    valid sample before it to the first valid one after it (or the recording's edge).
    """
    if seq.quat_valid is None:
        return [(float(seq.time[0]), seq.duration)] if seq.duration > min_gap_s else []
    invalid = ~seq.quat_valid
    n = len(seq)
    edges = np.diff(np.concatenate([[0], invalid.astype(np.int8), [0]]))
    starts, stops = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    out = []
    for a, b in zip(starts, stops):
        t_before = seq.time[a - 1] if a > 0 else seq.time[0]
        t_after = seq.time[b] if b < n else seq.time[-1]
        length = float(t_after - t_before)
        if length > min_gap_s:
            out.append((float(seq.time[a]), length))
    return out


def summarize(seq: ImuSequence, min_gap_s: float = 0.05) -> Dict[str, Any]:
    """Per-recording facts worth checking before training or evaluating on it.

    Keys: name, samples, duration_s, rate_hz, axes, gt_valid_pct, gaps (number of ground-truth
    gaps > ``min_gap_s``), gaps_total_s, gt_missing_at_start (bool), gt_start_s (time of the first
    valid ground truth after the start), scored_pct (valid and in score_mask), rest_s (time at
    rest per :func:`~tcn_ahrs.sequence.rest_mask`), rest_gyro_mean_dps (3 floats, mean gyro at
    rest in deg/s, i.e. the uncalibrated bias; NaN without rest); with ground truth (else None)
    gt_gyro_angle_deg (median angle between the gyro and the rate differentiated from the
    ground truth: a few degrees when frames agree) and gt_up (3 floats: the specific force's
    mean direction in the ground-truth frame, [0, 0, 1] in ENU) — a wrong frame shows at a
    glance (:func:`~tcn_ahrs.sequence.ground_truth_agreement`).
    """
    valid = seq.quat_valid if seq.quat_valid is not None else np.zeros(len(seq), dtype=bool)
    gaps = gt_gaps(seq, min_gap_s)
    rest = rest_mask(seq)
    rest_mean = np.degrees(seq.gyro[rest].mean(axis=0)) if rest.any() else np.full(3, np.nan)
    first = int(np.argmax(valid)) if valid.any() else len(seq) - 1
    agree = ground_truth_agreement(seq) if valid.sum() >= 10 else {"angle_deg": None, "up": None}
    return {
        "name": seq.name,
        "samples": len(seq),
        "duration_s": seq.duration,
        "rate_hz": float(seq.rate),
        "axes": seq.num_axes,
        "gt_valid_pct": 100.0 * float(valid.mean()),
        "gaps": len(gaps),
        "gaps_total_s": float(sum(g[1] for g in gaps)),
        "gt_missing_at_start": bool(not valid[0]),
        "gt_start_s": float(seq.time[first] - seq.time[0]),
        "scored_pct": 100.0 * float(seq.scored().mean()),
        "rest_s": float(rest.sum() / seq.rate),
        "rest_gyro_mean_dps": [float(x) for x in rest_mean],
        "gt_gyro_angle_deg": agree["angle_deg"],
        "gt_up": None if agree["up"] is None else [float(x) for x in agree["up"]],
    }


def format_summary_table(rows: List[Dict[str, Any]]) -> str:
    """Fixed-width text table of :func:`summarize` rows."""
    head = (f"{'recording':<46} {'dur[s]':>7} {'rate[Hz]':>8} {'ax':>2} {'GT%':>6} {'gaps>50ms':>9} "
            f"{'gap[s]':>6} {'GT@start':>9} {'rest[s]':>7} {'gyro~GT[deg]':>12} {'up in GT frame':>18}"
            "  rest gyro mean [deg/s]")
    lines = [head, "-" * len(head)]
    for r in rows:
        start = "missing" if r["gt_missing_at_start"] else "ok"
        if r["gt_missing_at_start"]:
            start += f" {r['gt_start_s']:.1f}s"
        g = r["rest_gyro_mean_dps"]
        gs = "n/a" if not np.all(np.isfinite(g)) else "(" + ", ".join(f"{x:+.3f}" for x in g) + ")"
        ang = "n/a" if r.get("gt_gyro_angle_deg") is None else f"{r['gt_gyro_angle_deg']:.1f}"
        up = "n/a" if r.get("gt_up") is None else "(" + ", ".join(f"{x:+.2f}" for x in r["gt_up"]) + ")"
        lines.append(f"{r['name'][:46]:<46} {r['duration_s']:7.1f} {r['rate_hz']:8.2f} {r['axes']:>2} "
                     f"{r['gt_valid_pct']:6.2f} {r['gaps']:9d} {r['gaps_total_s']:6.2f} {start:>9} "
                     f"{r['rest_s']:7.1f} {ang:>12} {up:>18}  {gs}")
    return "\n".join(lines)
