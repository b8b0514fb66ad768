"""Parity and speed of the generated C runtime beside BackboneStreaming (numba), same data:

    python examples/c/bench.py [--ckpts broad9 broad6 ...] [--cflags "-O2"] [--seconds 60]

For each residual checkpoint: generate, compile (double and float backbone), run a simulated
recording (and BROAD trials when ../shared has them) through ``<name>_run`` (the loop in C, one
ctypes call) and through ``BackboneStreaming.run`` (networks per sample, and its default chunked
networks); print the max attitude difference (rad), the per-sample times (median of 3) and the
sizes (state, weights)."""
import argparse
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from tcn_ahrs.checkpoint import model_from_checkpoint  # noqa: E402
from tcn_ahrs.datasets.simulate import simulate  # noqa: E402
from tcn_ahrs.export.c import CRuntime, compile_c, generate_c  # noqa: E402
from tcn_ahrs.streaming import BackboneStreaming  # noqa: E402
from test_export_c import BROAD, _angle, _imu  # noqa: E402


def best(f, reps=3):
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        r = f()
        ts.append(time.perf_counter() - t)
    return r, float(np.median(ts))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--ckpts", nargs="*", default=["broad9_residual", "residual/oxiod9", "general9_residual", "euroc6_residual_small"])
    ap.add_argument("--cflags", default="")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--broad", nargs="*", default=["05_undisturbed_slow_rotation_with_breaks_B",
                                                   "29_disturbed_stationary_magnet_B"])
    a = ap.parse_args()
    out = Path(tempfile.mkdtemp())
    import subprocess
    import tcn_ahrs.export.c.runtime as cr

    for name in a.ckpts:
        model = model_from_checkpoint(ROOT / "checkpoints" / f"{name}.ckpt")
        axes = int(model.axes)
        gen = generate_c(model, name)
        (out / f"{name}.h").write_text(gen["h"])
        (out / f"{name}.c").write_text(gen["c"])
        info = gen["info"]
        libs = {}
        for real in ("double", "float"):
            so = out / f"lib{name}_{real}.so"
            if a.cflags:
                cmd = (["cc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-shared", "-fPIC"] + shlex.split(a.cflags)
                       + [f"-DTCN_AHRS_REAL={real}", str(out / f"{name}.c"), "-o", str(so), "-lm"])
                subprocess.run(cmd, check=True)
            else:
                compile_c(out / f"{name}.c", so, real)
            libs[real] = CRuntime(so, name, axes)
        stream = BackboneStreaming(model)
        recs = [("sim_walking", simulate("walking", a.seconds, 200.0, seed=1, axes=axes))]
        for r in a.broad:
            if (BROAD / f"{r}.hdf5").is_file():
                from tcn_ahrs.datasets import broad
                recs.append((r[:2] + "_broad", broad.load_recording(BROAD, r)))
        print(f"{name}: axes {axes}, state {libs['double'].state_size} B (double) / {libs['float'].state_size} B "
              f"(float), weights {info['weight_bytes']} B float32 + head {info['head_bytes_double']} B, "
              f"ring {info['ring_floats'] * 4} B")
        for tag, seq in recs:
            imu = _imu(seq, axes)
            dt = np.float32(1.0 / seq.rate)
            k0 = int(np.argmax(np.isfinite(seq.quat).all(1)))
            q0 = np.asarray(seq.quat[k0], np.float32)
            x64, q64 = imu.astype(np.float64), q0.astype(np.float64)
            stream.chunk_networks = 1 << 30
            (q_ref, _), t_ps = best(lambda: stream.run(x64, float(dt), q64))
            stream.chunk_networks = 256
            _, t_ch = best(lambda: stream.run(x64, float(dt), q64))
            row = [f"  {tag:>12} n={imu.shape[0]:6d}"]
            for real, lib in libs.items():
                (code, o), t_c = best(lambda: (lib.reset(q0), lib.run(imu, dt))[1])
                assert code == 0
                ang = float(_angle(o[:, :4].astype(np.float64), q_ref).max())
                row.append(f"C {real}: max {ang:.2e} rad, {t_c / imu.shape[0] * 1e6:.2f} us")
            row.append(f"numba per-sample nets {t_ps / imu.shape[0] * 1e6:.2f} us, chunked {t_ch / imu.shape[0] * 1e6:.2f} us")
            print(" | ".join(row))


if __name__ == "__main__":
    main()
