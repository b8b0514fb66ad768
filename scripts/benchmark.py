#!/usr/bin/env python
"""Benchmarks, one dispatcher: ``python scripts/benchmark.py MODE [hydra overrides]``.

    python scripts/benchmark.py accuracy data=broad [data.root=DIR] [ckpt=PATH] [tune=true]
    python scripts/benchmark.py accuracy data=euroc data.split=val
    python scripts/benchmark.py speed ...
    python scripts/benchmark.py transfer [transfer.ckpts={label: path}] [transfer.datasets=[broad,...]]
    python scripts/benchmark.py lodo [lodo.datasets=[broad,...]] [lodo.overrides=[train.epochs=20]]
    python scripts/benchmark.py finetune [finetune.k=2] [finetune.datasets=[tumvi]]

accuracy: every method incl. the PyPI peers on one dataset through the evaluation runner
          (tcn_ahrs.compare.benchmark_accuracy_main; same code as scripts/compare.py).
speed:    tcn_ahrs.bench.main(cfg) (imported only in that mode).
transfer: tcn_ahrs.transfer.transfer_main(cfg): every checkpoint on every dataset it can read, on
          recordings it never saw, beside the backbone and the classical filters.
lodo:     tcn_ahrs.lodo.lodo_main(cfg): leave one dataset out: a general model trained on the
          others (trained here unless present), scored on the left-out dataset.
finetune: tcn_ahrs.finetune.finetune_main(cfg): those models fine-tuned on k recordings of the
          left-out dataset (with and without ground truth), scored on its other recordings.
Config: conf/benchmark.yaml. Output: runs/benchmark/<mode>/<data>/<time> unless out=DIR.
"""
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tcn_ahrs.cli import check_overrides, user_errors  # noqa: E402

MODES = ("accuracy", "speed", "transfer", "lodo", "finetune")


def _mode_from_argv(argv) -> None:
    """Turn the positional MODE into the Hydra override ``mode=MODE`` (Hydra rejects bare words)."""
    if len(argv) > 1 and not argv[1].startswith("-") and "=" not in argv[1]:
        mode = argv.pop(1)
        if mode not in MODES:
            sys.exit(f"benchmark.py: unknown mode {mode!r}; expected one of {', '.join(MODES)}")
        argv.insert(1, f"mode={mode}")


@hydra.main(version_base="1.3", config_path="../conf", config_name="benchmark")
@user_errors
def main(cfg: DictConfig) -> None:
    mode = str(cfg.mode)
    if mode == "accuracy":
        from tcn_ahrs.compare import benchmark_accuracy_main

        benchmark_accuracy_main(cfg)
    elif mode == "transfer":
        from tcn_ahrs.transfer import transfer_main

        transfer_main(cfg)
    elif mode == "lodo":
        from tcn_ahrs.lodo import lodo_main

        lodo_main(cfg)
    elif mode == "finetune":
        from tcn_ahrs.finetune import finetune_main

        finetune_main(cfg)
    elif mode == "speed":
        from tcn_ahrs.bench import main as speed_main

        speed_main(cfg)
    else:
        raise SystemExit(f"benchmark.py: unknown mode {mode!r}; expected one of {', '.join(MODES)}")


if __name__ == "__main__":
    _mode_from_argv(sys.argv)
    check_overrides("benchmark")  # a config error as one line with the nearest key (exit 2)
    main()
