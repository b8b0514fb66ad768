#!/usr/bin/env python
"""How often the calibration-fault checks fire, clean and with the fault (tcn_ahrs/calibration_faults.py):

    python scripts/calibration_faults.py   (about 1 min on 2 cores)

Every real recording of the project (BROAD, EuRoC, TUM VI, OxIOD, iPhone 5, iPhone 4S), whole and as two
45 s clips (0-45 s, 15-60 s): how many the accelerometer-bias note names clean and with 0.5 m/s² added to
every axis; the soft-iron note clean and with the fault trial's soft iron; the hard iron removed at load
(sphere or plane, no ground truth) clean, with 150 µT on x and with (60, -40, 30) µT. A clean recording
named is a false warning: the thresholds in tcn_ahrs/calibration_faults.py are set so that none is.
"""
import copy
import sys
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from omegaconf import OmegaConf  # noqa: E402

from tcn_ahrs.bench.fault_trial import _soft_iron  # noqa: E402
from tcn_ahrs.calibration_faults import (accel_bias_fit, accel_bias_note, judged_hard_iron, soft_iron_fit,  # noqa: E402
                                         soft_iron_note)
from tcn_ahrs.config import conf_path  # noqa: E402
from tcn_ahrs.datasets import load_split, resolve_root  # noqa: E402
from tcn_ahrs.experiments.devices import DATASETS  # noqa: E402

WINDOWS = ((0.0, None), (0.0, 45.0), (15.0, 60.0))


def main() -> None:
    warnings.simplefilter("ignore")
    fired, seen, named = Counter(), Counter(), {}
    for name in DATASETS:
        c = OmegaConf.to_container(OmegaConf.load(conf_path("data", f"{name}.yaml")), resolve=True)
        c["root"], c["fold"] = str(resolve_root(c)), None
        for s in load_split(c, "all", []):
            if not s.has_gt:
                continue
            for a, b in WINDOWS:
                i0 = int(np.searchsorted(s.time, s.time[0] + a))
                x = s if b is None else s.slice(i0, int(np.searchsorted(s.time, s.time[0] + b)))
                label = f"{name}/{s.name}" + ("" if b is None else f"[{a:g}-{b:g} s]")
                seen["accelerometer"] += 1
                for case, acc in (("accelerometer bias: clean", x.accel), ("accelerometer bias: +0.5 m/s²", x.accel + 0.5)):
                    y = copy.copy(x)
                    y.accel = acc
                    if accel_bias_note(accel_bias_fit(y)):
                        fired[case] += 1
                        named.setdefault(case, []).append(label)
                if x.mag is None:
                    continue
                seen["magnetometer"] += 1
                soft = _soft_iron({"mag": x.mag})["mag"]
                for case, mag in (("soft iron: clean", x.mag), ("soft iron: the trial's", soft)):
                    if soft_iron_note(soft_iron_fit(mag, x.quat, x.quat_valid)):
                        fired[case] += 1
                        named.setdefault(case, []).append(label)
                for case, off in (("hard iron: clean", (0.0, 0.0, 0.0)), ("hard iron: +150 µT on x", (150.0, 0.0, 0.0)),
                                  ("hard iron: (60, -40, 30) µT", (60.0, -40.0, 30.0))):
                    if judged_hard_iron(x.mag + np.asarray(off)) is not None:
                        fired[case] += 1
                        named.setdefault(case, []).append(label)
    for case in ("accelerometer bias: clean", "accelerometer bias: +0.5 m/s²", "soft iron: clean", "soft iron: the trial's",
                 "hard iron: clean", "hard iron: +150 µT on x", "hard iron: (60, -40, 30) µT"):
        n = seen["accelerometer" if case.startswith("accelerometer") else "magnetometer"]
        print(f"{case}: named on {fired[case]} of {n}")
        if case.endswith("clean") and named.get(case):
            print("   ", ", ".join(named[case]))


if __name__ == "__main__":
    main()
