"""The fault trial: faults a new user's recordings carry, injected into clips of real BROAD
recordings (training trials) and of a phone (the iPhone 4S held for texting and held up while walking,
../shared/datasets/phones)
and run through ``tcn-ahrs evaluate`` exactly as a user would run it (generic files, the shipped
``broad9`` / ``broad6`` models on BROAD, the default on the phone, VQF and raw integration beside them).

``python -m tcn_ahrs.bench.fault_trial OUT [--code DIR]`` writes ``OUT/fault_trial.json``: per case
what the command did — refused (its message) or ran (AAE per method, the health lines it printed,
a window error where the case names one). ``--code DIR`` runs another checkout's code (its
``tcn_ahrs`` first on ``PYTHONPATH``): the "before" column of docs/troubleshooting.md's fault
table is this file run against the commit before issue 47 (``1d5b769``), "now" against the tree.
``python scripts/results_tables.py`` renders the table from both JSON files.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable, Dict, List, Optional

import numpy as np

SHARED = Path(__file__).resolve().parents[3] / "shared" / "datasets" / "broad"
CLIP_S, LEAD_S, FAULT_AT = 45.0, 5.0, 15.0  # clip length, rest before the motion, fault start (s into the clip)
CLIPS = {"slow": "02_undisturbed_slow_rotation_B", "fast": "08_undisturbed_fast_rotation_with_breaks_A",
         "translation": "18_undisturbed_fast_translation_with_breaks_B", "phone": "Guillaume_iPhone4S_NoDist_Texting",
         "phone held up": "Guillaume_iPhone4S_NoDist_AR"}
PHONE = SHARED.parent / "phones" / "iphone4s"


def _clip(root: Path, name: str) -> Dict[str, np.ndarray]:
    from ..datasets import loader

    if name in (CLIPS["phone"], CLIPS["phone held up"]):  # the phone's first CLIP_S seconds (it never rests)
        import warnings

        from ..datasets.generic import load_file

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            seq = load_file(PHONE / f"{name}.h5")
        k1 = int(np.searchsorted(seq.time, seq.time[0] + CLIP_S))
        return {"t": seq.time[:k1] - seq.time[0], "gyr": seq.gyro[:k1], "acc": seq.accel[:k1], "mag": seq.mag[:k1],
                "quat": seq.quat[:k1]}
    seq = loader("broad").load_recording(root, name)
    k0 = max(0, int(np.argmax(seq.score_mask)) - int(LEAD_S * seq.rate))
    k1 = k0 + int(CLIP_S * seq.rate)
    return {"t": seq.time[k0:k1] - seq.time[k0], "gyr": seq.gyro[k0:k1], "acc": seq.accel[k0:k1],
            "mag": seq.mag[k0:k1], "quat": seq.quat[k0:k1]}


def _window(a: Dict[str, np.ndarray], seconds: float, start: float = FAULT_AT) -> slice:
    t = a["t"]
    return slice(int(np.searchsorted(t, start)), int(np.searchsorted(t, start + seconds)))


def _frozen(key: str, seconds: float = 5.0):
    def f(a):
        w = _window(a, seconds)
        a[key][w] = a[key][w.start]
        return a
    return f


def _mag_swap(a):
    a["mag"] = a["mag"][:, [1, 0, 2]]
    return a


def _hard_iron(a):
    a["mag"] = a["mag"] + np.array([150.0, -80.0, 60.0])
    return a


def _saturate(a):
    a["acc"] = np.clip(a["acc"], -19.6133, 19.6133)  # a ±2 g accelerometer
    return a


def _zero_mag(a):
    a["mag"] = np.zeros_like(a["mag"])
    return a


def _short(a):
    n = int(np.searchsorted(a["t"], 0.5))
    return {k: v[:n] for k, v in a.items()}


def _lag(seconds: float):
    def f(a):
        from ..datasets._common import interpolate_quat

        # the ground truth stamped `seconds` late (a clock offset between the IMU and motion capture)
        q, ok = interpolate_quat(a["t"] + seconds, a["quat"], a["t"], 0.05, 0.1)
        a["quat"] = q  # NaN where the shifted ground truth does not reach: masked, not invented
        return a
    return f


def _add(key: str, offset):
    def f(a):
        a[key] = a[key] + np.asarray(offset)
        return a
    return f


def _columns(key: str, order, signs=(1.0, 1.0, 1.0)):
    def f(a):
        a[key] = a[key][:, list(order)] * np.asarray(signs)
        return a
    return f


def _soft_iron(a):
    a["mag"] = a["mag"] @ np.array([[1.3, 0.2, 0.0], [0.2, 0.8, 0.0], [0.0, 0.0, 1.1]]).T
    return a


def _two_samples(a):
    return {k: v[:2] for k, v in a.items()}


def _gt_rotated(a):
    from scipy.spatial.transform import Rotation

    ok = np.all(np.isfinite(a["quat"]), axis=1)
    r = Rotation.from_quat(a["quat"][ok][:, [1, 2, 3, 0]]) * Rotation.from_rotvec(np.radians([10.0, 0.0, 0.0]))
    a["quat"][ok] = r.as_quat()[:, [3, 0, 1, 2]]
    return a


def _declared(inject, **attrs):
    def f(a):
        a = inject(a)
        a["_attrs"] = attrs  # HDF5 root attributes: the generic format's declarations
        return a
    return f


# case -> (clip, injector, ckpt, extra overrides, window metric: (what, seconds after the fault ends, length))
CASES: Dict[str, tuple] = {
    "clean (fast rotation)": ("fast", None, "broad9_residual", [], ("inclination", 5.0, 1.0)),
    "clean (slow rotation)": ("slow", None, "broad9_residual", [], ("inclination", 5.0, 1.0)),
    "magnetometer x and y swapped": ("slow", _mag_swap, "broad9_residual", [], None),
    "hard iron +150 / −80 / +60 µT": ("slow", _hard_iron, "broad9_residual", [], None),
    "magnetometer frozen 5 s": ("fast", _frozen("mag"), "broad9_residual", [], ("heading", 4.0, 4.0)),
    "accelerometer saturating at ±2 g (fast translation)": ("translation", _saturate, "broad9_residual", [], None),
    "clean (fast translation)": ("translation", None, "broad9_residual", [], None),
    "accelerometer frozen 5 s": ("slow", _frozen("acc"), "broad9_residual", [], ("inclination", 5.0, 1.0)),
    "accelerometer frozen 5 s in fast motion": ("fast", _frozen("acc"), "broad9_residual", [], ("inclination", 5.0, 1.0)),
    "all-zero magnetometer, 6-axis model": ("slow", _zero_mag, "broad6_residual", ["data.axes=6"], None),
    "a 0.5 s recording": ("slow", _short, "broad9_residual", [], None),
    "ground truth 30 ms late": ("fast", _lag(0.03), "broad9_residual", [], None),
    "ground truth 30 ms late, gt_time_offset: 0.03 declared": ("fast", _declared(_lag(0.03), gt_time_offset=0.03),
                                                                 "broad9_residual", [], None),
    "all-zero magnetometer, 9-axis model": ("slow", _zero_mag, "broad9_residual", [], None),
    "gyro frozen 5 s (fast motion)": ("fast", _frozen("gyr"), "broad9_residual", [], ("heading", 4.0, 4.0)),
    # the sixth pass (issue 55): calibration faults, a dead magnetometer and a 2-sample file with the default
    "gyro bias 5 °/s": ("slow", _add("gyr", np.radians([5.0, 5.0, 5.0])), "broad9_residual", [], None),
    "accelerometer bias 0.5 m/s²": ("slow", _add("acc", [0.5, 0.5, 0.5]), "broad9_residual", [], None),
    "soft iron (a 1.3 / 0.8 / 1.1 scale, 0.2 cross-coupling)": ("slow", _soft_iron, "broad9_residual", [], None),
    "gyro bias 5 °/s, the default (no ckpt=)": ("slow", _add("gyr", np.radians([5.0, 5.0, 5.0])), None, [], None),
    "all-zero magnetometer, the default (no ckpt=)": ("slow", _zero_mag, None, [], None),
    "a 2-sample recording, the default": ("slow", _two_samples, None, [], None),
    # the phone (iPhone 4S held for texting, 100 Hz): the default, as a phone user runs it
    "phone: clean": ("phone", None, None, [], None),
    "phone: accelerometer x and y swapped": ("phone", _columns("acc", (1, 0, 2)), None, [], None),
    "phone: accelerometer z negated": ("phone", _columns("acc", (0, 1, 2), (1.0, 1.0, -1.0)), None, [], None),
    "phone: gyro x and y swapped": ("phone", _columns("gyr", (1, 0, 2)), None, [], None),
    "phone: gyro y negated": ("phone", _columns("gyr", (0, 1, 2), (1.0, -1.0, 1.0)), None, [], None),
    "phone: gyro z negated": ("phone", _columns("gyr", (0, 1, 2), (1.0, 1.0, -1.0)), None, [], None),
    "phone: gyro in deg/s, undeclared": ("phone", _columns("gyr", (0, 1, 2), np.degrees([1.0, 1.0, 1.0])), None, [], None),
    "phone: gyro bias 5 °/s": ("phone", _add("gyr", np.radians([5.0, 5.0, 5.0])), None, [], None),
    "phone: hard iron +150 µT": ("phone", _add("mag", [150.0, 0.0, 0.0]), None, [], None),
    "phone: ground truth in a body frame rotated 10°": ("phone", _gt_rotated, None, [], None),
    # the seventh pass: the default after a frozen sensor (BROAD, the phone); calibration faults on the phone,
    # held for texting (it barely tilts: an accelerometer bias cannot be told from a mount there) and held up
    # while walking (augmented reality: it turns)
    "accelerometer frozen 5 s, the default (no ckpt=)": ("slow", _frozen("acc"), None, [], ("inclination", 5.0, 1.0)),
    "phone: accelerometer frozen 5 s": ("phone", _frozen("acc"), None, [], ("inclination", 5.0, 1.0)),
    "phone: gyro frozen 5 s": ("phone", _frozen("gyr"), None, [], ("heading", 4.0, 4.0)),
    "phone: accelerometer bias 0.5 m/s²": ("phone", _add("acc", [0.5, 0.5, 0.5]), None, [], None),
    "phone: soft iron": ("phone", _soft_iron, None, [], None),
    "phone held up: clean": ("phone held up", None, None, [], None),
    "phone held up: accelerometer bias 0.5 m/s²": ("phone held up", _add("acc", [0.5, 0.5, 0.5]), None, [], None),
    "phone held up: soft iron": ("phone held up", _soft_iron, None, [], None),
}


def _write(path: Path, a: Dict[str, np.ndarray]) -> None:
    import h5py

    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        for k, v in a.items():
            if k == "_attrs":
                f.attrs.update(v)
            else:
                f[k] = v


def _errors(traj: Path, a: Dict[str, np.ndarray], what: str, after: float, length: float) -> Optional[float]:
    from ..metrics import broad_error_angles

    if not traj.is_file():
        return None
    d = np.loadtxt(traj, ndmin=2)
    quat = d[:, [7, 4, 5, 6]]  # TUM: t x y z qx qy qz qw
    end = FAULT_AT + 5.0
    w = _window(a, length, end + after)
    angles = broad_error_angles(a["quat"][w], quat[w])
    return float(np.degrees(np.abs(angles[what])).mean())


def run_case(name: str, code: Optional[Path], work: Path, root: Path = SHARED) -> dict:
    clip, inject, ckpt, extra, metric = CASES[name]
    a = _clip(root, CLIPS[clip])
    if inject is not None:
        a = inject({k: v.copy() for k, v in a.items()})
    data = work / "data" / f"case{list(CASES).index(name):02d}"
    _write(data / f"{'phone' if clip.startswith('phone') else CLIPS[clip][:2]}_clip.h5", a)
    out = work / "out" / data.name
    from ..checkpoints import SHIPPED_DIR

    # the shipped model (a --code checkout before runs the same file), or the default (no ckpt=)
    model = [] if ckpt is None else [f"ckpt={SHIPPED_DIR / f'{ckpt}.ckpt'}"]
    cmd = [sys.executable, "-m", "tcn_ahrs", "evaluate", "data=generic", f"data.root={data}", *model,
           "data.split=all", "baselines=[vqf]", f"out={out}", "plots=false", *extra]
    env = dict(os.environ)
    if code is not None:
        env["PYTHONPATH"] = str(code) + os.pathsep + env.get("PYTHONPATH", "")
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=str(code or Path.cwd()))
    said, keep = [], False
    for ln in (p.stdout + p.stderr).splitlines():
        # what the command says (its reasons for a refusal follow the error line, indented)
        keep = ln.startswith(("error", "health", "warning", "note", "device check")) or "Warning:" in ln or (
            keep and ln.startswith("  ") and said[-1].startswith("error"))
        if keep:
            said.append(ln.strip())
    row = {"case": name, "status": p.returncode, "said": said}
    res = out / "results.json"
    if res.is_file():
        r = json.loads(res.read_text())
        row["aae"] = {m: v["recordings"][0].get("aae_deg") for m, v in r["methods"].items()}
        if metric is not None:
            what, after, length = metric
            row["window"] = {"what": what, "after_s": after, "length_s": length}
            for m in r["methods"]:
                from ..evaluate.files import safe_name

                traj = out / "trajectories" / safe_name(m) / f"{safe_name(r['recordings'][0])}.txt"
                row["window"][m] = _errors(traj, a, what, after, length)
    return row


def _cell(row: Optional[dict], method: Optional[str] = None, now: Optional[dict] = None) -> str:
    """What one run did, for the table: refused (its reason, abridged) or the AAE (and the case's
    window error, where ``now``'s row reads one too) with what the command said about the fault."""
    if row is None:
        return "–"
    if row["status"] != 0:
        said = row["said"]
        # the command's own error, or the per-recording reason listed under "no recordings … refused:"
        why = next((s for s in said if s.startswith("error") and "no recordings" not in s), None)
        if why is None:
            at = next((i for i, s in enumerate(said) if s.startswith("error")), len(said))
            why = next((s for s in said[at + 1:] if "Warning" not in s), "")
        why = why[why.find("field '"):] if "field '" in why else why
        why = re.sub(r"/\S*/checkpoints/", "checkpoints/", why)  # no machine's folders in the table
        return "refused: " + (why[:150] + "…" if len(why) > 150 else why).replace("|", "\\|")
    aae = row.get("aae") or {}
    m = method or next(iter(aae))
    text = "diverged" if aae[m] is None else f"{aae[m]:.2f}°"
    win = row.get("window") or {}
    if win.get(m) is not None and (now is None or now.get("window")):
        text += f" ({win['what']} {win['after_s']:g}–{win['after_s'] + win['length_s']:g} s after: {win[m]:.2f}°)"
    if method is None:
        said = [s.split(": ", 1)[1] if s.startswith("health") else s.split("UserWarning: ", 1)[-1]
                for s in row["said"] if s.startswith("health") or "UserWarning" in s]
        said = [s.split(": ", 1)[1] if s.startswith("/") and ": " in s else s for s in said]
        text += "; says: " + ("; ".join(x[:110] for x in said) if said else "nothing")
    return text


def markdown(result: dict) -> str:
    """The fault table of docs/troubleshooting.md: per case the shipped model before (the commit the
    issue was read at) and now, and VQF now (VQF's code did not change), from ``fault_trial.json``."""
    before = {r["case"]: r for r in (result.get("before") or {}).get("cases", [])}
    lines = ["| fault (BROAD clip, `tcn-ahrs evaluate ckpt=broad9_residual` unless it says the default; phone: the "
             "iPhone 4S held for texting, the default; phone held up: the same phone held up while walking) "
             "| before | now | VQF |", "|---|---|---|---|"]
    for row in result["cases"]:
        # VQF on the faulty clip (its code is the same before and now; refused now, it ran before)
        ran = row if row.get("aae") else before.get(row["case"]) or {}
        vqf = next((m for m in (ran.get("aae") or {}) if m.startswith("vqf")), None)
        lines.append(f"| {row['case']} | {_cell(before.get(row['case']), now=row)} | {_cell(row)} | "
                     f"{_cell(ran, vqf) if vqf else '–'} |")
    lines += ["", "AAE over the clip (the yardstick, degrees); in brackets the case's window error (no "
                  "alignment; the fault from 15 s to 20 s of the 45 s clip); \"says\": the warnings and health "
                  "lines the command printed. Commands: " + result.get("command", "")]
    return "\n".join(lines) + "\n"


def main(argv: Optional[List[str]] = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out")
    ap.add_argument("--code", default=None, help="another checkout whose tcn_ahrs runs the commands")
    ap.add_argument("--cases", nargs="*", default=None)
    ap.add_argument("--before", default=None, help="an earlier run's fault_trial.json: kept as its 'before'")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.cases or list(CASES):
            row = run_case(name, Path(args.code).resolve() if args.code else None, Path(tmp))
            print(json.dumps(row), flush=True)
            rows.append(row)
    result = {"code": args.code or "tree", "cases": rows,
              "command": ("`python -m tcn_ahrs.bench.fault_trial DIR` on the tree (now) and with `--code` on a "
                          "checkout of the commit before issue 47 (before, 1d5b769)")}
    if args.before:
        result["before"] = json.loads(Path(args.before).read_text())
    (out / "fault_trial.json").write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
