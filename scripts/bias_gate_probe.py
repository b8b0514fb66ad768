"""The learned accelerometer trust gating the bias update (``model.residual.bias_trust_power``) on the
leave-one-dataset-out models, and a choice of it per recording without ground truth.

    python scripts/bias_gate_probe.py [--runs runs/lodo] [--powers 0 4] [DATASET ...]

For each left-out dataset (default: broad euroc tumvi oxiod), the model trained without it
(``<runs>/<dataset>/checkpoints/last.ckpt``, from ``tcn-ahrs benchmark lodo``) runs on every
training recording of the dataset, device-checked as the LODO table, once per power; the
``pick`` column chooses, per recording, the power with the smallest gravity angle
(:func:`tcn_ahrs.training.adaptation.gravity_deg`: no ground truth read). Prints the mean AAE /
inclination of each. A probe of issue 37's item 1 (docs/results.md), not a shipped recipe.
"""
import argparse

import numpy as np

from tcn_ahrs.datasets import load_split
from tcn_ahrs.device_check import checked
from tcn_ahrs.estimators.base import initial_state
from tcn_ahrs.estimators.learned import LearnedEstimator
from tcn_ahrs.experiments.lodo import DATASETS, compose_train
from tcn_ahrs.metrics import aae_and_inclination
from tcn_ahrs.training.adaptation import gravity_deg
from tcn_ahrs.config import plain


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("datasets", nargs="*", default=list(DATASETS))
    ap.add_argument("--runs", default="runs/lodo")
    ap.add_argument("--powers", nargs="+", type=float, default=[0.0, 4.0])
    args = ap.parse_args(argv)
    for d in args.datasets:
        cfg = {**plain(compose_train([f"data={d}"]).data), "fold": None, "axes": 6}
        seqs = checked([s for s in load_split(cfg, "trainval") if s.has_gt])
        est = LearnedEstimator(f"{args.runs}/{d}/checkpoints/last.ckpt", name="general")
        scores = {p: [] for p in args.powers}
        picked = []
        for s in seqs:
            i0, q0 = initial_state(s)
            runs = {}
            for p in args.powers:
                est.model.backbone.bias_trust_power = p
                q = est.run(s, q0, i0).quat
                runs[p] = (aae_and_inclination(s, q, 6), gravity_deg(s, q))
                scores[p].append(runs[p][0])
            picked.append(runs[min(runs, key=lambda p: np.inf if runs[p][1] is None else runs[p][1])][0])
        cells = [f"power {p:g}: {np.mean(v, 0)[0]:.2f} / {np.mean(v, 0)[1]:.2f}" for p, v in scores.items()]
        print(f"{d} ({len(seqs)} rec.): " + ", ".join(cells) + f", pick: {np.mean(picked, 0)[0]:.2f} / {np.mean(picked, 0)[1]:.2f}",
              flush=True)


if __name__ == "__main__":
    main()
