#!/usr/bin/env python
"""The cost of causality (docs/results.md, "What the default does on a device"):

    python scripts/causality.py [OUT.json]   (default docs/results/json/causality.json; about 6 min on 2 cores)

`tcn-ahrs evaluate`'s default subtracts each recording's gyro bias at rest read from the *whole*
recording (the offline device check, tcn_ahrs/device_check.py) before the filter runs — until
2026-12-07 the default did; an exported runtime on a device sees only the past. Per real dataset,
every recording whole, mean AAE (the yardstick) and the recordings worse than VQF on the same raw
input, of: VQF and the backbone (VQF's defaults) on the offline-checked recordings and on raw ones;
the default (the backbone with the causal check in its filter, kernels/backbone.py: rest_check, what
`tcn-ahrs evaluate` runs without `ckpt=` and every exported runtime runs); and the two causal
candidates tried before it, the backbone with a wider bias clip (8 °/s) and also a wider gyro rest
threshold (6 °/s); and an oracle no device has: the default on readings whose gyro bias, read from the
ground truth (the median of gyro minus its rate), is subtracted — what any bias estimate could reach at
best, recording by recording. Every method on VQF's clock (:class:`tcn_ahrs.estimators.peers.OnFixedPeriod`).
"""
import copy
import json
import sys
import warnings
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from omegaconf import OmegaConf  # noqa: E402

from tcn_ahrs import verdict  # noqa: E402
from tcn_ahrs.agreement import ground_truth_agreement  # noqa: E402
from tcn_ahrs.config import conf_path  # noqa: E402
from tcn_ahrs.datasets import load_split, resolve_root  # noqa: E402
from tcn_ahrs.device_check import checked  # noqa: E402
from tcn_ahrs.estimators import registry  # noqa: E402
from tcn_ahrs.estimators.families import FAMILIES  # noqa: E402
from tcn_ahrs.estimators.peers import OnFixedPeriod  # noqa: E402
from tcn_ahrs.evaluate.main import default  # noqa: E402
from tcn_ahrs.evaluate.runner import evaluate  # noqa: E402
from tcn_ahrs.experiments.devices import DATASETS  # noqa: E402

VARIANTS = {"bias clip 8 °/s": {"bias_clip": 8.0}, "bias clip 8 °/s, rest 6 °/s": {"bias_clip": 8.0, "rest_th_gyro": 6.0}}
ORACLE = "default, true gyro bias removed (an oracle)"


def without_true_bias(s):
    """``s`` with the gyro bias its ground truth shows subtracted (an oracle: no device has it)."""
    out = copy.copy(s)
    bias = ground_truth_agreement(s).get("gyro_bias")
    out.gyro = s.gyro - (0.0 if bias is None else bias)
    return out


def worse(rows, vqf) -> int:
    """The recordings of ``rows`` worse than VQF's (``vqf``, the same recordings in order)."""
    return sum(not verdict.never_worse(a["aae_deg"], a["inclination_deg"], b["aae_deg"], b["inclination_deg"])
               for a, b in zip(rows, vqf))


def main(out: Path) -> None:
    warnings.simplefilter("ignore")
    fam, result = FAMILIES["backbone"], {"variants": {k: v for k, v in VARIANTS.items()}, "datasets": {}}
    for name in DATASETS:
        c = OmegaConf.to_container(OmegaConf.load(conf_path("data", f"{name}.yaml")), resolve=True)
        c["root"], c["fold"] = str(resolve_root(c)), None
        raw = [s for s in load_split(c, "all", []) if s.has_gt and s.scored().any()]
        axes = int(c.get("axes", 9))

        def backbone(label, **kw):
            return OnFixedPeriod(fam.build(axes, **{**fam.defaults_for(axes), **kw}), label)

        on_raw = ([registry.build("vqf", axes), backbone("backbone raw"), OnFixedPeriod(default(axes), "default")]
                  + [backbone(k, **v) for k, v in VARIANTS.items()])
        r_raw = evaluate(on_raw, raw, plots=False, trajectories=False, dataset=name)["methods"]
        r_chk = evaluate([registry.build("vqf", axes), backbone("backbone")], checked(raw), plots=False,
                         trajectories=False, dataset=name)["methods"]
        r_orc = evaluate([OnFixedPeriod(default(axes), "default")], [without_true_bias(s) for s in raw], plots=False,
                         trajectories=False, dataset=name)["methods"]["default"]
        vqf = r_raw[on_raw[0].name]["recordings"]
        row = {"recordings": len(raw), "vqf offline check": r_chk[on_raw[0].name]["mean"]["aae_deg"],
               "backbone offline check": r_chk["backbone"]["mean"]["aae_deg"]}
        for e in on_raw:
            rows = r_raw[e.name]["recordings"]
            label = "vqf raw" if e is on_raw[0] else e.name
            row[label] = r_raw[e.name]["mean"]["aae_deg"]
            row[label + ": worse than vqf raw"] = worse(rows, vqf)
        row[ORACLE] = r_orc["mean"]["aae_deg"]
        row[ORACLE + ": worse than vqf raw"] = worse(r_orc["recordings"], vqf)
        result["datasets"][name] = row
        print(name, {k: round(v, 2) for k, v in row.items()}, flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else REPO / "docs" / "results" / "json" / "causality.json")
