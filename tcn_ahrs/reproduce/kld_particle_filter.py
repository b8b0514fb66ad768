"""The particle-filter report's evaluation (``particle-filter-kld-sampling``): Monte Carlo
localisation with a fixed particle count and with KLD-sampling, on the simulated arena of
:mod:`tcn_ahrs.nav.arena`.

``python scripts/reproduce.py paper=kld_particle_filter`` (options: ``conf/paper/kld_particle_filter.yaml``)

* The report's table: the robot drives a rectangle ``laps`` times steered by the filter; the mean
  deviation of the true end pose from the start pose (m, deg) and the mean update time, for the
  fixed-size filter and the KLD one (with its mean particle count).
* Global localisation (uniform prior) and a kidnapped robot (carried away mid-run) with and
  without random particle injection: steps until the estimate is back within 0.1 m.
* Scaling: one update (motion, likelihood, resampling) vs particle count, torch against the same
  operations in plain numpy in the same run (CPU; CUDA too when present).
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Dict, Mapping

import numpy as np
import torch

from . import write_report
from ..nav.arena import Arena, Robot, Scanner, drive_rectangle
from ..nav.particle import LikelihoodField, Mcl, MclParams, low_variance_resample, sample_motion

PAPER = {"PF": {"position": 0.0324, "angle": 10.2899, "ms": 127.82, "particles": 200},
         "KLD-PF": {"position": 0.0514, "angle": 11.3925, "ms": 42.71, "particles": 48}}


def _estimator(mcl: Mcl, angles: torch.Tensor):
    def est(prev, now, ranges):
        out = mcl.step(torch.as_tensor(prev), torch.as_tensor(now), torch.as_tensor(ranges, dtype=torch.float32), angles)
        return out["pose"].numpy()
    return est


def evaluation(cfg: Mapping[str, Any], arena: Arena, scanner: Scanner, robot: Robot, params: MclParams) -> Dict[str, Any]:
    """The report's table: both filters on the same seeded drive (start known: particles around it)."""
    grid, res, origin = arena.grid()
    field = LikelihoodField(grid, res, origin, params)
    angles = torch.as_tensor(scanner.angles(), dtype=torch.float32)
    start = np.asarray(cfg["start"], float)
    out = {}
    for name, kld in (("PF", False), ("KLD-PF", True)):
        g = torch.Generator().manual_seed(int(cfg["seed"]))
        init = torch.as_tensor(start, dtype=torch.float32)[None] + torch.randn(params.n_particles, 3, generator=g) * \
            torch.tensor([0.02, 0.02, 0.05])
        mcl = Mcl(field, params, kld, seed=int(cfg["seed"]), initial=init)
        t0 = time.perf_counter()
        run = drive_rectangle(_estimator(mcl, angles), start, tuple(cfg["rectangle"]), int(cfg["laps"]), int(cfg["seed"]),
                              arena, scanner, robot)
        d = run["ends"] - start
        ang = np.degrees(np.abs((d[:, 2] + math.pi) % (2 * math.pi) - math.pi))
        out[name] = {"position": float(np.hypot(d[:, 0], d[:, 1]).mean()), "angle": float(ang.mean()),
                     "ms": 1e3 * float(np.mean(run["time"])), "particles": float(np.mean(mcl.counts)),
                     "tracking_m": float(np.hypot(*(run["est"][:, :2] - run["true"][:, :2]).T).mean()),
                     "laps": len(run["ends"]), "steps": len(run["true"]), "wall_s": round(time.perf_counter() - t0, 1),
                     "run": run, "counts": np.asarray(mcl.counts)}
    return out


def recovery_steps(err: np.ndarray, after: int, tol: float = 0.1, hold: int = 50):
    """First step after ``after`` from which the error stays below tol for ``hold`` steps (None: never)."""
    bad = err > tol
    for i in range(after, len(err) - hold):
        if not bad[i:i + hold].any():
            return int(i - after)
    return None


def global_and_kidnap(cfg: Mapping[str, Any], arena: Arena, scanner: Scanner, robot: Robot, params: MclParams) -> Dict[str, Any]:
    grid, res, origin = arena.grid()
    angles = torch.as_tensor(scanner.angles(), dtype=torch.float32)
    start = np.asarray(cfg["start"], float)
    k_step, k_pose = int(cfg["kidnap_step"]), np.asarray(cfg["kidnap_pose"], float)
    res_out: Dict[str, Any] = {}
    inject = replace(params, alpha_slow=float(cfg["alpha_slow"]), alpha_fast=float(cfg["alpha_fast"]))
    for name, p, kid in (("global", params, None), ("kidnapped, no injection", params, (k_step, k_pose)),
                         ("kidnapped, random injection", inject, (k_step, k_pose))):
        mcl = Mcl(LikelihoodField(grid, res, origin, p), p, kld=True, seed=int(cfg["seed"]) + 1)
        clouds = {"start": mcl.particles.clone()}

        est_fn = _estimator(mcl, angles)
        seen = {"n": 0}

        def est(prev, now, r):
            out = est_fn(prev, now, r)
            seen["n"] += 1
            if seen["n"] == int(cfg["cloud_step"]):
                clouds["converged"] = mcl.particles.clone()
            return out

        run = drive_rectangle(est, start, tuple(cfg["rectangle"]), int(cfg["kidnap_laps"]), int(cfg["seed"]), arena,
                              scanner, robot, kidnap=kid)
        err = np.hypot(*(run["est"][:, :2] - run["true"][:, :2]).T)
        res_out[name] = {"converged_after_steps": recovery_steps(err, 0) if kid is None else None,
                         "recovered_after_steps": recovery_steps(err, k_step + 1) if kid is not None else None,
                         "final_error_m": float(err[-1]), "steps": len(err), "run": run, "err": err,
                         "counts": np.asarray(mcl.counts), "clouds": clouds}
    return res_out


# -- the plain numpy reference of one update, for the scaling benchmark --------------------------------

def numpy_update(particles, weights, prev, now, alphas, log_p, res, origin, ranges, angles, params, rng):
    """The update's operations in plain numpy, for timing only: low-variance resampling, odometry
    motion, the tabulated likelihood field (log_p (H, W)); without the torch path's angle wrap
    and small-turn noise fold (a few element-wise ops on N values, against N x beams look-ups)."""
    c = np.cumsum(weights)
    n = particles.shape[0]
    u = rng.uniform(0, c[-1] / n) + np.arange(n) * (c[-1] / n)
    p = particles[np.minimum(np.searchsorted(c, u, side="right"), n - 1)]
    dx, dy = now[0] - prev[0], now[1] - prev[1]
    trans = math.hypot(dx, dy)
    rot1 = math.atan2(dy, dx) - prev[2] if trans > 1e-6 else 0.0
    rot2 = now[2] - prev[2] - rot1
    a1, a2, a3, a4 = alphas
    e = rng.standard_normal((n, 3))
    h1 = rot1 + math.sqrt(a1 * rot1 ** 2 + a2 * trans ** 2) * e[:, 0]
    ht = trans + math.sqrt(a3 * trans ** 2 + a4 * (rot1 ** 2 + rot2 ** 2)) * e[:, 1]
    h2 = rot2 + math.sqrt(a1 * rot2 ** 2 + a2 * trans ** 2) * e[:, 2]
    th = p[:, 2] + h1
    p = np.stack([p[:, 0] + ht * np.cos(th), p[:, 1] + ht * np.sin(th), th + h2], -1)
    tb = p[:, 2:3] + angles[None]
    ex, ey = p[:, 0:1] + ranges[None] * np.cos(tb), p[:, 1:2] + ranges[None] * np.sin(tb)
    j = np.floor((ex - origin[0]) / res).astype(np.int64)
    i = np.floor((ey - origin[1]) / res).astype(np.int64)
    inside = (i >= 0) & (i < log_p.shape[0]) & (j >= 0) & (j < log_p.shape[1])
    ll = np.where(inside, log_p[np.clip(i, 0, log_p.shape[0] - 1), np.clip(j, 0, log_p.shape[1] - 1)],
                  math.log(params.z_rand / params.z_max)).sum(-1)
    return p, np.exp(ll - ll.max())


def scaling(cfg: Mapping[str, Any], arena: Arena, scanner: Scanner, params: MclParams) -> Dict[str, Any]:
    grid, res, origin = arena.grid()
    angles_np = scanner.angles().astype(np.float32)
    ranges_np = np.full(len(angles_np), 1.0, np.float32)
    prev, now = np.array([0.5, 0.5, 0.0]), np.array([0.51, 0.5, 0.01])
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    rows = []
    for n in [int(x) for x in cfg["scaling"]]:
        reps = max(1, min(20, int(2e5 // n)))
        row: Dict[str, Any] = {"particles": n}
        field_np = LikelihoodField(grid, res, origin, params)
        log_p = field_np.log_p.numpy()[:-1].reshape(field_np.H, field_np.W)
        rng = np.random.default_rng(0)
        P = np.column_stack([rng.uniform(0, 3, n), rng.uniform(0, 2, n), rng.uniform(-3, 3, n)]).astype(np.float32)
        W = np.ones(n, np.float32)
        t0 = time.perf_counter()
        for _ in range(reps):
            numpy_update(P, W, prev, now, params.alphas, log_p, res, origin, ranges_np, angles_np, params, rng)
        row["numpy_ms"] = 1e3 * (time.perf_counter() - t0) / reps
        for dev in devices:
            field = LikelihoodField(grid, res, origin, params, device=dev)
            Pt, Wt = torch.as_tensor(P, device=dev), torch.as_tensor(W, device=dev)
            pt, nt = torch.as_tensor(prev, dtype=torch.float32, device=dev), torch.as_tensor(now, dtype=torch.float32, device=dev)
            rt, at = torch.as_tensor(ranges_np, device=dev), torch.as_tensor(angles_np, device=dev)
            g = torch.Generator(device=dev).manual_seed(0)

            def upd():
                idx = low_variance_resample(Wt, n, g)
                q = sample_motion(Pt[idx], pt, nt, params.alphas, g)
                ll = field.log_likelihood(q, rt, at)
                return torch.exp(ll - ll.max())

            upd()
            if dev == "cuda":
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            for _ in range(reps):
                upd()
            if dev == "cuda":
                torch.cuda.synchronize()
            row[f"torch_{dev}_ms"] = 1e3 * (time.perf_counter() - t0) / reps
            row[f"speedup_{dev}"] = row["numpy_ms"] / row[f"torch_{dev}_ms"]
        rows.append(row)
    return {"rows": rows, "devices": devices, "torch_threads": torch.get_num_threads(), "beams": len(angles_np)}


def plots(out: Path, ev: Dict[str, Any], gk: Dict[str, Any], arena: Arena, cfg: Mapping[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    grid, res, origin = arena.grid()
    extent = (origin[0], origin[0] + grid.shape[1] * res, origin[1], origin[1] + grid.shape[0] * res)

    def base(ax):
        ax.imshow(grid, origin="lower", extent=extent, cmap="Greys", alpha=0.8)
        ax.set_aspect("equal")

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    g = gk["global"]
    for ax, key, title in ((axes[0], "start", "uniform prior (KLD: n_max)"),
                           (axes[1], "converged", f"after {cfg['cloud_step']} updates")):
        base(ax)
        cl = g["clouds"].get(key)
        if cl is not None:
            c = cl.numpy()
            ax.quiver(c[:, 0], c[:, 1], np.cos(c[:, 2]), np.sin(c[:, 2]), color="tab:blue", scale=40, width=0.002)
        t = g["run"]["true"][0 if key == "start" else int(cfg["cloud_step"]) - 1]
        ax.plot(t[0], t[1], "r*", ms=12)
        ax.set_title(f"global localisation: {title} ({len(cl) if cl is not None else 0} particles)")
    ax = axes[2]
    base(ax)
    start = np.asarray(cfg["start"], float)
    for name, c in (("PF", "tab:blue"), ("KLD-PF", "tab:orange")):
        e = ev[name]["run"]["ends"]
        ax.quiver(e[:, 0], e[:, 1], np.cos(e[:, 2]), np.sin(e[:, 2]), color=c, scale=25, width=0.004, label=name)
    ax.add_patch(plt.Circle(start[:2], 0.03, color="r", fill=False))
    ax.set_xlim(start[0] - 0.2, start[0] + 0.2)
    ax.set_ylim(start[1] - 0.2, start[1] + 0.2)
    ax.set_title(f"true end poses of {cfg['laps']} laps (red: 3 cm tolerance)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "clouds.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(13, 3.8))
    axes[0].plot(ev["KLD-PF"]["counts"], lw=0.8, label="KLD-PF (drive)")
    axes[0].plot(g["counts"], lw=0.8, label="KLD-PF (global localisation)")
    axes[0].set_yscale("log")
    axes[0].set_xlabel("update")
    axes[0].set_ylabel("particles")
    axes[0].legend()
    for name, r in gk.items():
        if name.startswith("kidnapped"):
            axes[1].semilogy(r["err"], lw=0.8, label=name)
    axes[1].axvline(int(cfg["kidnap_step"]), color="k", ls=":", lw=0.8)
    axes[1].set_xlabel("update")
    axes[1].set_ylabel("position error [m]")
    axes[1].legend()
    fig.tight_layout()
    fig.savefig(out / "particles_and_kidnap.png", dpi=110)
    plt.close(fig)


def markdown(res: Dict[str, Any]) -> str:
    ev = res["evaluation"]
    lines = ["# Monte Carlo localisation with KLD-sampling (the AMiRo report's evaluation)\n",
             f"{ev['PF']['laps']} rectangles driven by the filter's own estimate (simulated arena, seeded); deviation of "
             "the true end pose from the start pose, mean over laps; update time on this CPU (the report: the AMiRo's "
             "ARM board, so only the ratio between the two filters compares).\n",
             "| filter | position dev. [m] ours | report | angle dev. [deg] ours | report | update [ms] ours | report "
             "| particles ours | report | tracking error [m] ours |", "|---" * 10 + "|"]
    for name in ("PF", "KLD-PF"):
        o, p = ev[name], PAPER[name]
        lines.append(f"| {name} | {o['position']:.4f} | {p['position']:.4f} | {o['angle']:.2f} | {p['angle']:.2f} | "
                     f"{o['ms']:.2f} | {p['ms']:.2f} | {o['particles']:.0f} | {p['particles']} | {o['tracking_m']:.4f} |")
    lines.append(f"\nUpdate-time ratio PF / KLD-PF: ours {ev['PF']['ms'] / ev['KLD-PF']['ms']:.2f}, report "
                 f"{PAPER['PF']['ms'] / PAPER['KLD-PF']['ms']:.2f}.\n")
    gk = res["global_kidnap"]
    lines += ["\n## Global localisation and the kidnapped robot (KLD-PF)\n",
              "| run | converged / recovered after [updates] | final error [m] |", "|---|---|---|"]
    for name, r in gk.items():
        n = r["converged_after_steps"] if name == "global" else r["recovered_after_steps"]
        lines.append(f"| {name} | {'never' if n is None else n} | {r['final_error_m']:.3f} |")
    sc = res["scaling"]
    cols = ["numpy_ms"] + [f"torch_{d}_ms" for d in sc["devices"]] + [f"speedup_{d}" for d in sc["devices"]]
    lines += [f"\n## Scaling: one update (resampling, motion, {sc['beams']}-beam likelihood) vs particle count\n",
              f"torch threads: {sc['torch_threads']}; numpy: the same algorithm, vectorised, in the same run.\n",
              "| particles | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for row in sc["rows"]:
        lines.append(f"| {row['particles']:,} | " + " | ".join(f"{row[c]:.3g}" for c in cols) + " |")
    lines.append(f"\nWall time {res['time_s']} s.")
    return "\n".join(lines) + "\n"


def main(cfg: Mapping[str, Any], out: Path) -> Dict[str, Any]:
    t0 = time.perf_counter()
    torch.set_num_threads(int(cfg.get("threads", 1)))
    arena = Arena(**{k: (tuple(map(tuple, v)) if k == "boxes" else v) for k, v in dict(cfg.get("arena") or {}).items()})
    scanner = Scanner(**dict(cfg.get("scanner") or {}))
    robot = Robot(**dict(cfg.get("robot") or {}))
    params = MclParams(**{k: (tuple(v) if isinstance(v, (list, tuple)) else v) for k, v in dict(cfg.get("filter") or {}).items()})
    res: Dict[str, Any] = {"paper": "kld_particle_filter"}
    res["evaluation"] = evaluation(cfg, arena, scanner, robot, params)
    print(f"evaluation: {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    res["global_kidnap"] = global_and_kidnap(cfg, arena, scanner, robot, params)
    print(f"global/kidnap: {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    res["scaling"] = scaling(cfg, arena, scanner, params)
    print(f"scaling: {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    if cfg.get("plots", True):
        plots(out / "plots", res["evaluation"], res["global_kidnap"], arena, cfg)
    res["time_s"] = round(time.perf_counter() - t0, 1)
    return write_report(out, res, markdown(res), drop=("run", "err", "counts", "clouds"))
