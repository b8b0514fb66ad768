#!/usr/bin/env python
"""The saturation rule on the clipped recordings the project has (docs/results.md, "Saturation"):

    python scripts/saturation.py [--shared ../shared/datasets]

The eight running recordings of the iPhones (hand, pocket) with their accelerometer clipped at ±2 g
(±19.55 m/s², as a Nexus 5's), device-checked as ``tcn-ahrs evaluate`` gives them, and BROAD's fast
translation clipped at ±2 g (the fault trial's clip): per recording the mean AAE (the yardstick) of
VQF, the default (the backbone with VQF's defaults and its clip rule), the same backbone with the clip
check off (``acc_clip_floor=0``: VQF's handling, on the recording's own time steps) and raw
integration. Run it at an earlier commit for the rule before.
"""
import argparse
import copy
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from tcn_ahrs.bench import fault_trial as ft  # noqa: E402
from tcn_ahrs.datasets import generic  # noqa: E402
from tcn_ahrs.device_check import checked  # noqa: E402
from tcn_ahrs.estimators.families import FAMILIES, recording_scores  # noqa: E402
from tcn_ahrs.estimators.registry import build  # noqa: E402
from tcn_ahrs.sequence import ImuSequence  # noqa: E402

ACC_RANGE = 19.55  # m/s²: ±2 g


def clipped_recordings(shared: Path):
    phones = []
    for f in sorted((shared / "phones").glob("*/*Running*.h5")):
        s = copy.copy(generic.load_file(f))
        s.accel = np.clip(s.accel, -ACC_RANGE, ACC_RANGE)
        phones.append(s)
    a = ft._saturate(ft._clip(shared / "broad", ft.CLIPS["translation"]))
    broad = ImuSequence("broad_translation_2g", "clip", a["t"], a["gyr"], a["acc"], a["mag"], a["quat"],
                        check_units=False, meta={"heading_reference": "magnetic_north"})
    return checked(phones) + [broad]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shared", default=str(REPO.parent / "shared" / "datasets"))
    args = ap.parse_args(argv)
    seqs = clipped_recordings(Path(args.shared))
    fam = FAMILIES["backbone"]
    methods = {"VQF": build("vqf", 9), "default": fam.build(9, **fam.defaults_for(9)),
               "clip check off": fam.build(9, **{**fam.defaults_for(9), "acc_clip_floor": 0.0}),
               "raw integration": build("raw", 9)}
    scores = {k: recording_scores(e, seqs, 9)[0] for k, e in methods.items()}
    print("| recording | " + " | ".join(methods) + " |")
    print("|---" * (len(methods) + 1) + "|")
    for i, s in enumerate(seqs):
        print(f"| {s.name} | " + " | ".join(f"{scores[k][i]:.2f}" for k in methods) + " |")
    n = len(seqs) - 1
    print(f"| mean of the {n} phones | " + " | ".join(f"{np.mean(scores[k][:n]):.2f}" for k in methods) + " |")
    worst = max(scores["default"][i] - scores["VQF"][i] for i in range(n))
    print(f"\nthe default against VQF on the phones: worst {worst:+.2f}°")
    return 0


if __name__ == "__main__":
    sys.exit(main())
