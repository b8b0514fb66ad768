#!/usr/bin/env python
"""Benchmarks, one dispatcher: ``python scripts/benchmark.py MODE [hydra overrides]``.

    python scripts/benchmark.py accuracy data=broad [data.root=DIR] [ckpt=PATH] [tune=true]
    python scripts/benchmark.py accuracy data=euroc data.split=val
    python scripts/benchmark.py speed ...
    python scripts/benchmark.py transfer [transfer.ckpts={label: path}] [transfer.datasets=[broad,...]]
    python scripts/benchmark.py lodo [lodo.datasets=[broad,...]] [lodo.overrides=[train.epochs=20]]
    python scripts/benchmark.py finetune [finetune.k=2] [finetune.datasets=[tumvi]]
    python scripts/benchmark.py faults [faults.seeds=[0,1,2]] [faults.ckpt=PATH]
    python scripts/benchmark.py devices [devices.models=[]] [devices.quick=true]

accuracy: every method incl. the PyPI peers on one dataset through the evaluation runner
          (tcn_ahrs.experiments.compare.benchmark_accuracy_main; same code as scripts/compare.py).
speed:    tcn_ahrs.bench.main(cfg) (imported only in that mode).
transfer: tcn_ahrs.experiments.transfer.transfer_main(cfg): every checkpoint on every dataset it can read, on
          recordings it never saw, beside the backbone and the classical filters.
lodo:     tcn_ahrs.experiments.lodo.lodo_main(cfg): leave one dataset out: a general model trained on the
          others (trained here unless present), scored on the left-out dataset.
finetune: tcn_ahrs.experiments.finetune.finetune_main(cfg): those models fine-tuned on k recordings of the
          left-out dataset (with and without ground truth), scored on its other recordings.
faults:   tcn_ahrs.bench.faults.faults_main(cfg): sensor faults injected into simulated recordings,
          the backbone with and without its health checks beside VQF and the default model.
devices:  tcn_ahrs.experiments.devices.devices_main(cfg): the default and every shipped model beside VQF and the
          classical filters on every real recording, recording by recording (the gate: never worse than VQF).
Config: conf/benchmark.yaml. Output: runs/benchmark/<mode>/<data>/<time> unless out=DIR.

Same as ``tcn-ahrs benchmark ...`` (tcn_ahrs/cli.py); this file is kept for ``python scripts/benchmark.py``.
"""
import sys

from tcn_ahrs.cli import main

if __name__ == "__main__":
    main(["benchmark", *sys.argv[1:]])
