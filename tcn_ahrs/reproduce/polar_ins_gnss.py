"""The polar INS/GNSS paper's experiments (``ins-gnss-grid-frame-covariance-transformation``, its
Tables 1-2 and Figs. 3-4): switching an INS/GNSS filter from the geographic (n) frame to the grid
(G) frame with and without the covariance transformation.

``python scripts/reproduce.py paper=polar_ins_gnss`` (options: ``conf/paper/polar_ins_gnss.yaml``)

Flights (:mod:`tcn_ahrs.nav.polar_sim`, great circles, navigation-grade IMU at 200 Hz, GNSS 1 Hz):

* ``mid_latitude`` (the paper's flight test): reference = the n-frame filter throughout; the
  switched filters change to G at ``switch_h``. At mid latitude the n frame has no singularity, so
  any difference after the switch is the switch's (the paper's "relative error").
* ``polar_80`` (its "virtual polar region" at 80 deg): reference = the G-frame filter throughout.
* ``pole`` (beyond the paper): a route across the pole; the n-frame filter alone against the one
  switched to G before the pole (absolute errors against the truth).

Relative errors per run after the switch, as the paper's tables: maximum attitude error (the
largest of the three small-angle components between the two attitudes, arcmin; yaw separately),
maximum position difference (m), the largest accelerometer (ug) and gyro (deg/h) bias-estimate
difference over the three axes. Every run of a seed shares the IMU and GNSS data and the initial
error; seeds differ in all three.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Mapping

import numpy as np
from scipy.spatial.transform import Rotation

from . import write_report
from ..nav import earth
from ..nav.ins import InsNoise, InsState, initial_cov, navigate
from ..nav.polar_sim import DEG_PER_H, UG, Flight, ImuGrade, simulate_flight

PAPER = {  # Table 1 (with covariance transformation) and Table 2 (without), six flights
    "with": {"attitude": [0.67, 0.64, 0.93, 0.61, 0.66, 0.26], "position": [0.6, 0.58, 0.17, 0.47, 0.44, 0.17],
             "accel_bias": [9.48, 9.24, 1.10, 9.26, 9.36, 1.12], "gyro_bias": [0.002, 0.0023, 0.0022, 0.0003, 0.0003, 0.0003]},
    "without": {"attitude": [3.34, 2.89, 5.56, 4.45, 2.56, 5.56], "position": [2.4, 2.09, 1.26, 2.47, 1.76, 0.89],
                "accel_bias": [59.3, 62.0, 20.0, 62.5, 61.7, 22.8], "gyro_bias": [0.0091, 0.0094, 0.0215, 0.0069, 0.0038, 0.0019]},
}
PAPER_TEXT = {  # the paper's stated maxima (Figs. 3-4), without / with the transformation
    "mid_latitude": {"yaw": (2.2, 0.3), "gyro_bias": (0.01, 0.003), "accel_bias": (50.0, 6.0), "position": ("< 10", "< 10")},
    "polar_80": {"yaw": (5.0, 0.2), "gyro_bias": (0.02, 0.001), "accel_bias": (25.0, 0.1), "position": (12.0, 8.0)},
}
COLUMNS = (("attitude", "attitude [arcmin]"), ("yaw", "yaw [arcmin]"), ("position", "position [m]"),
           ("accel_bias", "accel. bias [ug]"), ("gyro_bias", "gyro bias [deg/h]"))


def start_states(sims: List[dict], noise: InsNoise, reps: int, seed: int) -> InsState:
    """n-frame start of every run: the truth plus an initial error drawn from P_0 (one per seed,
    shared by the seed's ``reps`` variants)."""
    st = InsState("n", np.stack([s["C_bn0"] for s in sims]), np.stack([s["v0_n"] for s in sims]),
                  np.stack([[s["lat0"], s["lon0"], s["h0"]] for s in sims]), np.zeros((len(sims), 3)),
                  np.zeros((len(sims), 3)))
    P0 = initial_cov(st, noise)
    rng = np.random.default_rng(seed)
    e = np.stack([rng.multivariate_normal(np.zeros(15), P0[i]) for i in range(len(sims))])
    att = Rotation.from_rotvec(-e[:, :3]).as_matrix() @ st.att      # C~ = (I - [phi x]) C (Eq. 10)
    tile = lambda x: np.concatenate([x] * reps)  # noqa: E731
    return InsState("n", tile(att), tile(st.vel + e[:, 3:6]), tile(st.pos + e[:, 6:9]), tile(st.gyro_bias),
                    tile(st.accel_bias), tile(P0))


def run(sims: List[dict], noise: InsNoise, reps: int, seed: int, **kw) -> Dict[str, np.ndarray]:
    D = lambda k: np.concatenate([np.stack([s[k] for s in sims])] * reps)  # noqa: E731
    s0 = sims[0]
    return navigate(start_states(sims, noise, reps, seed), D("dtheta"), D("dv"), s0["dt"], D("gnss"),
                    s0["gnss_every"], noise, record_every=s0["gnss_every"], **kw)


def attitude_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Small-angle vector (..., 3) [E, N, U] of ``C_a C_b^T`` (attitudes C_b^n)."""
    d = a @ np.swapaxes(b, -1, -2)
    return Rotation.from_matrix(d.reshape(-1, 3, 3)).as_rotvec().reshape(d.shape[:-2] + (3,))


def relative(sw: Dict[str, np.ndarray], ref: Dict[str, np.ndarray], idx: slice, after: np.ndarray) -> Dict[str, np.ndarray]:
    att = np.degrees(attitude_difference(sw["att_n"][idx], ref["att_n"])) * 60.0
    return {"attitude": np.abs(att[:, after]).max((1, 2)), "yaw": np.abs(att[:, after, 2]).max(1),
            "position": np.linalg.norm(sw["ecef"][idx] - ref["ecef"], axis=-1)[:, after].max(1),
            "accel_bias": np.abs(sw["accel_bias"][idx] - ref["accel_bias"])[:, after].max((1, 2)) / UG,
            "gyro_bias": np.abs(sw["gyro_bias"][idx] - ref["gyro_bias"])[:, after].max((1, 2)) / DEG_PER_H,
            "series": {"attitude": att, "position": np.linalg.norm(sw["ecef"][idx] - ref["ecef"], axis=-1),
                       "gyro_bias": (sw["gyro_bias"][idx] - ref["gyro_bias"]) / DEG_PER_H,
                       "accel_bias": (sw["accel_bias"][idx] - ref["accel_bias"]) / UG}}


def switch_experiment(name: str, fl: Flight, cfg: Mapping[str, Any], noise: InsNoise, imu: ImuGrade) -> Dict[str, Any]:
    seeds = list(range(int(cfg["first_seed"]), int(cfg["first_seed"]) + int(cfg["seeds"])))
    rate = float(cfg["nav_rate"])
    sims = [simulate_flight(fl, s, rate, imu) for s in seeds]
    S = len(seeds)
    ks = int(round(float(cfg["switch_h"]) * 3600.0 * rate))
    t0 = time.perf_counter()
    if name == "mid_latitude":
        ref = run(sims, noise, 1, 1000 + seeds[0])                            # n-frame throughout
    else:
        ref = run(sims, noise, 1, 1000 + seeds[0], switch_at=0, transform=np.ones(S, bool))  # G throughout
    sw = run(sims, noise, 2, 1000 + seeds[0], switch_at=ks, transform=np.array([True] * S + [False] * S))
    t_s = ref["step"] * sims[0]["dt"]
    after = t_s > ks * sims[0]["dt"]
    out = {"seeds": seeds, "switch_s": ks * sims[0]["dt"], "time_s": round(time.perf_counter() - t0, 1),
           "lat_range_deg": [float(np.degrees(sims[0]["lat"].min())), float(np.degrees(sims[0]["lat"].max()))],
           "hours": fl.hours, "t": t_s}
    for label, idx in (("with", slice(0, S)), ("without", slice(S, 2 * S))):
        out[label] = relative(sw, ref, idx, after)
    truth = np.stack([s["r_e"][s["gnss_every"] - 1::s["gnss_every"]] for s in sims])
    out["reference_position_rms_m"] = float(np.sqrt(np.mean(np.linalg.norm(ref["ecef"] - truth, axis=-1) ** 2)))
    return out


def pole_experiment(fl: Flight, cfg: Mapping[str, Any], noise: InsNoise, imu: ImuGrade) -> Dict[str, Any]:
    """Across the pole: the n-frame filter alone (its longitude rate has 1 / cos L) against the one
    switched to G (with the transformation) at ``switch_h``; absolute errors against the truth."""
    seeds = list(range(int(cfg["first_seed"]), int(cfg["first_seed"]) + int(cfg["pole_seeds"])))
    rate = float(cfg["nav_rate"])
    sims = [simulate_flight(fl, s, rate, imu) for s in seeds]
    ks = int(round(float(cfg["switch_h"]) * 3600.0 * rate))
    every = sims[0]["gnss_every"]
    truth = np.stack([s["r_e"][every - 1::every] for s in sims])
    # attitudes compared as C_b^e: near the pole the n frame itself turns with the longitude, so an
    # n-frame difference there measures the position error, not the attitude's
    C_true = np.stack([np.swapaxes(earth.enu_from_ecef(s["lat"][every - 1::every], s["lon"][every - 1::every]), -1, -2)
                       @ s["C_bn"][every - 1::every] for s in sims])
    res = {"seeds": seeds, "lat_max_deg": float(np.degrees(max(s["lat"].max() for s in sims)))}
    for label, kw in (("n frame only", {}), ("switched to G", {"switch_at": ks, "transform": np.ones(len(seeds), bool)})):
        with np.errstate(all="ignore"):
            try:
                out = run(sims, noise, 1, 2000 + seeds[0], **kw)
                pos = np.linalg.norm(out["ecef"] - truth, axis=-1)
                lat, lon, _ = earth.geodetic(out["ecef"])
                C_be = np.swapaxes(earth.enu_from_ecef(lat, lon), -1, -2) @ out["att_n"]
                att = np.degrees(np.abs(attitude_difference(C_be, C_true))).max(-1) * 60.0
                finite = bool(np.isfinite(pos).all() and np.isfinite(att).all())
                res[label] = {"finite": finite, "position_max_m": float(np.nanmax(pos)) if finite else None,
                              "attitude_max_arcmin": float(np.nanmax(att)) if finite else None,
                              "first_nonfinite_s": None if finite else float(out["step"][~np.isfinite(pos).all(0)][0] / rate)}
            except (ValueError, np.linalg.LinAlgError) as e:  # the n frame at the pole
                res[label] = {"finite": False, "error": f"{type(e).__name__}: {str(e)[:120]}"}
    return res


def _table(res: Dict[str, Any], label: str, paper: bool) -> List[str]:
    head = "| run | " + " | ".join((f"{c} ours | paper" if (paper and k != "yaw") else f"{c} ours") for k, c in COLUMNS) + " |"
    lines = [head, "|---" * (head.count("|") - 1) + "|"]
    r = res[label]
    n = len(r["attitude"])
    for i in range(n + 1):
        cells = []
        for k, _ in COLUMNS:
            ours = float(np.mean(r[k])) if i == n else float(r[k][i])
            fmt = "{:.4f}" if k == "gyro_bias" else ("{:.2f}" if k != "accel_bias" else "{:.1f}")
            cell = "{:.2g}".format(ours)  # with the transformation our differences are 1e-3..1e-6
            if paper and k != "yaw":
                vals = PAPER[label][k]
                pv = float(np.mean(vals)) if i == n else (vals[i] if i < len(vals) else None)
                cell += " | " + ("—" if pv is None else fmt.format(pv))
            cells.append(cell)
        lines.append(f"| {'average' if i == n else i + 1} | " + " | ".join(cells) + " |")
    return lines


def markdown(result: Dict[str, Any]) -> str:
    lines = ["# INS/GNSS across the pole: switching to the grid frame with and without the covariance "
             "transformation (paper Tables 1-2)\n",
             "Relative errors after the switch (switched filter minus the reference filter on the same data; "
             "maximum over the time after the switch and over the three axes), one row per seeded flight.\n"]
    for name, title in (("mid_latitude", "Mid latitude (the paper's flight test; reference: n frame throughout)"),
                        ("polar_80", "~80 deg (the paper's virtual polar region; reference: G frame throughout)")):
        if name not in result:
            continue
        r = result[name]
        lines += [f"\n## {title}\n", f"{r['hours']:g} h great-circle flight, latitude "
                  f"{r['lat_range_deg'][0]:.1f}-{r['lat_range_deg'][1]:.1f} deg, switch at {r['switch_s'] / 3600:.2f} h; "
                  f"reference filter's position RMS against the truth {r['reference_position_rms_m']:.2f} m.\n"]
        paper = name == "mid_latitude"
        for label, tname in (("with", "with covariance transformation (Table 1)"),
                             ("without", "without covariance transformation (Table 2)")):
            lines += [f"\n### {tname}\n"] + _table(r, label, paper)
        pt = PAPER_TEXT[name]
        lines += ["\n| stated maximum (paper text) | without: paper | without: ours (max) | with: paper | with: ours (max) |",
                  "|---|---|---|---|---|"]
        for k in ("yaw", "position", "gyro_bias", "accel_bias"):
            lines.append(f"| {k} | {pt[k][0]} | {np.max(r['without'][k]):.4g} | {pt[k][1]} | {np.max(r['with'][k]):.4g} |")
    if "pole" in result:
        p = result["pole"]
        lines += ["\n## Across the pole (beyond the paper; absolute errors against the truth)\n",
                  f"Route up to {p['lat_max_deg']:.3f} deg latitude, {len(p['seeds'])} runs.\n",
                  "| filter | finite | max position error [m] | max attitude error (as C_b^e) [arcmin] | note |",
                  "|---|---|---|---|---|"]
        for label in ("n frame only", "switched to G"):
            q = p[label]
            note = q.get("error") or (f"non-finite from {q['first_nonfinite_s']:.0f} s" if q.get("first_nonfinite_s") else "")
            pm = "—" if q.get("position_max_m") is None else f"{q['position_max_m']:.2f}"
            am = "—" if q.get("attitude_max_arcmin") is None else f"{q['attitude_max_arcmin']:.2f}"
            lines.append(f"| {label} | {q['finite']} | {pm} | {am} | {note} |")
    lines.append(f"\nWall time {result['time_s']} s.")
    return "\n".join(lines) + "\n"


def plots(out: Path, result: Dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    for name, fig_no in (("mid_latitude", 3), ("polar_80", 4)):
        if name not in result:
            continue
        r = result[name]
        t = r["t"] / 3600.0
        fig, axes = plt.subplots(2, 2, figsize=(12, 7), sharex=True)
        for label, style in (("without", "-"), ("with", "--")):
            s = r[label]["series"]
            axes[0, 0].plot(t, s["attitude"][0, :, 2], style, label=f"yaw, {label} transformation")
            axes[0, 1].plot(t, s["position"][0], style, label=label)
            axes[1, 0].plot(t, np.abs(s["gyro_bias"][0]).max(-1), style, label=label)
            axes[1, 1].plot(t, np.abs(s["accel_bias"][0]).max(-1), style, label=label)
        for ax, yl in zip(axes.flat, ("relative yaw error [arcmin]", "relative position error [m]",
                                      "relative gyro bias error [deg/h]", "relative accel. bias error [ug]")):
            ax.axvline(r["switch_s"] / 3600.0, color="k", lw=0.7, ls=":")
            ax.set_ylabel(yl)
            ax.legend(fontsize=8)
        for ax in axes[1]:
            ax.set_xlabel("time [h]")
        fig.suptitle(f"{name}: switched minus reference filter, seed {r['seeds'][0]} (paper Fig. {fig_no})")
        fig.tight_layout()
        fig.savefig(out / f"{name}.png", dpi=110)
        plt.close(fig)


def main(cfg: Mapping[str, Any], out: Path) -> Dict[str, Any]:
    t0 = time.perf_counter()
    noise = InsNoise(**dict(cfg.get("noise") or {}))
    imu = ImuGrade(**{k: float(v) for k, v in dict(cfg.get("imu") or {}).items()})
    result: Dict[str, Any] = {"paper": "polar_ins_gnss"}
    flights = dict(cfg["flights"])
    for name in ("mid_latitude", "polar_80"):
        if name in flights:
            result[name] = switch_experiment(name, Flight(**dict(flights[name]), hours=float(cfg["hours"])), cfg,
                                             noise, imu)
            print(f"{name}: {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    if "pole" in flights:
        result["pole"] = pole_experiment(Flight(**dict(flights["pole"]), hours=float(cfg["pole_hours"])), cfg, noise, imu)
        print(f"pole: {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    if cfg.get("plots", True):
        plots(out / "plots", result)
    result["time_s"] = round(time.perf_counter() - t0, 1)
    return write_report(out, result, markdown(result), drop=("series", "t"))

