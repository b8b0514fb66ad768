#!/usr/bin/env python
"""Export a trained checkpoint as self-contained TorchScript (batch and/or streaming).

    python scripts/export.py ckpt=runs/simulated/<run>/checkpoints/best.ckpt out=exports/ahrs9.pt
    python scripts/export.py ckpt=PATH out=FILE.pt mode=streaming rate=200

Loading the result needs only torch:
    m = torch.jit.load("FILE.pt");  quat, omega = m(imu, dt, q0);  print(m.metadata())
    s = torch.jit.load("FILE_streaming.pt");  s.reset(q0);  quat, omega = s.step(sample, dt)

Configuration: conf/export.yaml; the contract is in tcn_ahrs/export.py's docstring.

Same as ``tcn-ahrs export ...`` (tcn_ahrs/cli.py); this file is kept for ``python scripts/export.py``.
"""
import sys

from tcn_ahrs.cli import main

if __name__ == "__main__":
    main(["export", *sys.argv[1:]])
