"""Which backbone kernels need double in the C runtime's float build: the double build with every
assignment inside one group of kernels rounded to float32 (the storage rounding of float
arithmetic, statement by statement), against BackboneStreaming over whole recordings:

    python examples/c/precision.py [--ckpt broad9]

Measured 2026-12-05 (broad9, simulated walking 60 s): the low-pass filters rounded 5.6e-4 rad,
every other kernel together 8.4e-6 rad — hence runtime.WIDE_KERNELS (the filters, their
coefficients and, for float arithmetic's sake, the heading update) in double in every build."""
import argparse
import re
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from tcn_ahrs.checkpoint import model_from_checkpoint  # noqa: E402
from tcn_ahrs.datasets.simulate import simulate  # noqa: E402
from tcn_ahrs.export.c import CRuntime, compile_c, generate_c  # noqa: E402
from tcn_ahrs.streaming import BackboneStreaming  # noqa: E402
from test_export_c import _angle, _imu  # noqa: E402

LOWPASS = ("butter", "coefficients", "lp_begin", "lp", "lp_end", "lp3")
OTHERS = ("qmul", "qrot", "quat6", "quat9", "gyro_update", "acc_update", "bias_update", "mag_update")
ASSIGN = re.compile(r"^(\s+)(\*?[A-Za-z_]\w*(?:\[[^\]]*\])?) = (.+);$")


def rounded(src: str, prefix: str, kernels) -> str:
    """``src`` with every plain assignment inside the listed kernels rounded to float."""
    out, cur = [], None
    for ln in src.split("\n"):
        m = re.match(rf"^static \w+ {prefix}_bb_(\w+)\(", ln)
        if m and not ln.endswith(";"):
            cur = m.group(1)
        elif ln == "}":
            cur = None
        mm = ASSIGN.match(ln) if cur in kernels and not re.match(r"^\s+(REAL|WREAL|int) ", ln) else None
        out.append(f"{mm.group(1)}{mm.group(2)} = (float)({mm.group(3)});" if mm else ln)
    return "\n".join(out)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--ckpt", default="broad9")
    a = ap.parse_args()
    model = model_from_checkpoint(ROOT / "checkpoints" / f"{a.ckpt}.ckpt")
    axes = int(model.axes)
    gen = generate_c(model, "m")
    out = Path(tempfile.mkdtemp())
    (out / "m.h").write_text(gen["h"])
    seq = simulate("walking", 60.0, 200.0, seed=1, axes=axes)
    imu, dt, q0 = _imu(seq, axes), np.float32(0.005), np.asarray(seq.quat[0], np.float32)
    stream = BackboneStreaming(model)
    stream.chunk_networks = 1 << 30
    ref, _ = stream.run(imu.astype(np.float64), float(dt), q0.astype(np.float64))
    for k, (tag, kernels) in enumerate([("double build", ()), ("low-pass filters rounded", LOWPASS),
                                        ("all other kernels rounded", OTHERS)] + [(f"{f} rounded", (f,)) for f in OTHERS]):
        (out / f"m{k}.c").write_text(rounded(gen["c"], "m", set(kernels)))
        rt = CRuntime(compile_c(out / f"m{k}.c", out / f"lib{k}.so", "double", None, ["-Wno-error"]), "m", axes)
        rt.reset(q0)
        code, o = rt.run(imu, dt)
        print(f"{tag:32s} max {_angle(o[:, :4].astype(np.float64), ref).max():.1e} rad")


if __name__ == "__main__":
    main()
