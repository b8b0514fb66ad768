"""``python -m tcn_ahrs.datasets.simulate [--benchmark]``: generation speed, or one recording's summary."""
from __future__ import annotations

import argparse
import time as _time
from typing import Dict, Tuple

import numpy as np

from ...conventions import DEG
from .generate import PROFILES, simulate


# =============================================================================
# Benchmark / CLI
# =============================================================================


def benchmark(samples: int = 1_000_000, rate: float = 100.0, repeats: int = 3) -> Dict[str, Tuple[float, float]]:
    """Generation speed per profile (9-axis, full error model, including ImuSequence validation):
    ``{profile: (samples/s wall clock, samples/s process CPU time)}``, best of ``repeats``
    (CPU time is the fairer number on a shared, loaded machine)."""
    out = {}
    duration = (samples - 1) / rate
    for profile in PROFILES:
        best_wall = best_cpu = float("inf")
        for r in range(repeats):
            w0, c0 = _time.perf_counter(), _time.process_time()
            simulate(profile, duration, rate, seed=r, axes=9)
            best_wall = min(best_wall, _time.perf_counter() - w0)
            best_cpu = min(best_cpu, _time.process_time() - c0)
        out[profile] = (samples / best_wall, samples / best_cpu)
    return out


def _main(argv=None) -> None:
    ap = argparse.ArgumentParser(description="tcn-ahrs IMU simulator")
    ap.add_argument("--benchmark", action="store_true", help="measure generation speed (samples/s)")
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=3, help="benchmark: best of this many runs")
    ap.add_argument("--profile", default="walking", choices=PROFILES)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.benchmark:
        res = benchmark(args.samples, args.rate, args.repeats)
        print(f"{args.samples} samples per recording at {args.rate:g} Hz, 9-axis, full error model")
        print(f"{'profile':15s} {'wall':>10s} {'cpu':>10s}   (M samples/s)")
        for k, (wall, cpu) in res.items():
            print(f"{k:15s} {wall / 1e6:10.2f} {cpu / 1e6:10.2f}")
        walls, cpus = zip(*res.values())
        print(f"{'mean':15s} {np.mean(walls) / 1e6:10.2f} {np.mean(cpus) / 1e6:10.2f}")
        return
    seq = simulate(args.profile, args.duration, args.rate, args.seed)
    m = seq.meta
    print(f"{seq.name}: {len(seq)} samples, {seq.duration:.1f} s, source {seq.source}")
    print(f"  |gyro| max {np.abs(m['true_gyro']).max() / DEG:.1f} deg/s, "
          f"|ext acc| max {np.linalg.norm(m['true_acc_nav'], axis=1).max():.2f} m/s^2, "
          f"moving {m['moving'].mean():.0%}, acc disturbed {m['acc_disturbed'].mean():.0%}, "
          f"mag disturbed {m['mag_disturbed'].mean():.0%}")


if __name__ == "__main__":
    _main()
