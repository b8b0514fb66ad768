"""The never-worse table of docs/results.md (nested folds) from nested cross-validation results.

    python scripts/nested_table.py runs/nested/broad9/crossval.json runs/nested/euroc6/crossval.json ...

Per outer fold: the learned model's mean AAE / inclination beside VQF and the best classical
filter on the same recordings (lowest AAE of raw integration, the backbone, VQF, imufusion, ECF,
Mahony, Madgwick; lowest inclination of those and RIANN), and whether the learned model is
never worse in both (to the table's 0.01 deg rounding).
"""
import json
import math
import sys
from pathlib import Path

from tcn_ahrs.verdict import never_worse

LEARNED = "Learned"


def rows(result: dict):
    for f in result["folds"]:
        means = f["means"]
        learned = means[LEARNED]
        classical = {m: v for m, v in means.items() if m != LEARNED}
        with_aae = {m: v["aae_deg"] for m, v in classical.items() if v.get("aae_deg") is not None
                    and math.isfinite(v["aae_deg"])}
        best = min(with_aae, key=with_aae.get)
        incl = {m: v["inclination_deg"] for m, v in classical.items() if v.get("inclination_deg") is not None}
        best_incl = min(incl, key=incl.get)
        vqf = next((v for m, v in classical.items() if m.startswith("vqf")), None)
        ok = never_worse(learned["aae_deg"], learned["inclination_deg"], with_aae[best], incl[best_incl])
        yield (f"{result['dataset']} fold {f['fold']}", learned, vqf, best, with_aae[best], best_incl, incl[best_incl], ok)


def main(paths):
    print("| data, outer fold | learned | VQF | best classical (AAE) | best inclination | never worse? |")
    print("|---|---|---|---|---|---|")
    for p in paths:
        for name, l, v, best, b, bi, i, ok in rows(json.loads(Path(p).read_text())):
            vq = f"{v['aae_deg']:.2f} / {v['inclination_deg']:.2f}" if v else "–"
            print(f"| {name} | {l['aae_deg']:.2f} / {l['inclination_deg']:.2f} | {vq} | {best} {b:.2f} | "
                  f"{bi} {i:.2f} | {'yes' if ok else '**no**'} |")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(sys.argv[1:])
