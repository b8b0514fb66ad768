"""What the runner writes besides the tables: TUM trajectories (for ``evo``) and the per-recording
plots (the paper's Figs. 3-8 layout)."""
from __future__ import annotations

import re
from pathlib import Path
from typing import Optional

import numpy as np

from ..metrics import YARDSTICK, aligned, attitude_errors
from ..sequence import ImuSequence
from ..tum import write_tum  # noqa: F401  (the one TUM writer; evaluate's artefacts use it from here)

MAX_PLOT_POINTS = 5000


def safe_name(name: str) -> str:
    """A file-name-safe version of a method or recording name (``"Raw IMU"`` -> ``"Raw_IMU"``)."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", str(name)).strip("_") or "unnamed"


def plot_recording(path, seq: ImuSequence, quat_est: np.ndarray, method: str,
                   signals: Optional[dict] = None, align="protocol",
                   max_points: int = MAX_PLOT_POINTS, axes: Optional[int] = None) -> None:
    """Roll/pitch/yaw of the (aligned) estimate vs ground truth, the attitude and yaw error over
    time, and ``signals["gyro_correction"]`` (N, 3) rad/s if present; Agg backend, at most
    ``max_points`` points per curve."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    import torch

    from .. import so3

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    m = seq.scored()
    if align == "protocol":  # the estimate as the metrics score it (tcn_ahrs.metrics.Yardstick)
        m, align = YARDSTICK.mask(seq), YARDSTICK.alignment(seq, seq.num_axes if axes is None else axes)
    q_est = aligned(seq.quat, quat_est, m, align)
    angle, dyaw = attitude_errors(seq.quat, quat_est, m, align)
    n = len(seq)
    idx = np.unique(np.linspace(0, n - 1, min(n, max_points)).astype(int))
    t = seq.time[idx] - seq.time[0]
    eul_est = np.degrees(so3.quat_to_euler(torch.as_tensor(q_est[idx])).numpy())
    gt = seq.quat[idx]
    gt_ok = np.all(np.isfinite(gt), axis=1)
    eul_gt = np.full_like(eul_est, np.nan)
    if gt_ok.any():
        eul_gt[gt_ok] = np.degrees(so3.quat_to_euler(torch.as_tensor(gt[gt_ok])).numpy())
    corr = None if not signals else signals.get("gyro_correction")
    nrows = 5 if corr is not None else 4
    fig, axs = plt.subplots(nrows, 1, figsize=(10, 2.2 * nrows), sharex=True)
    for i, lab in enumerate(("roll", "pitch", "yaw")):
        axs[i].plot(t, eul_gt[:, i], "k-", lw=1.0, label="ground truth")
        axs[i].plot(t, eul_est[:, i], "C0-", lw=0.8, label=method)
        axs[i].set_ylabel(f"{lab} [°]")
    axs[0].legend(loc="upper right", fontsize=8)
    err_a = np.where(m, np.degrees(angle), np.nan)[idx]
    err_y = np.where(m, np.degrees(dyaw), np.nan)[idx]
    axs[3].plot(t, err_a, "C3-", lw=0.8, label="attitude error ||Log(R_gt^T R_est)||")
    axs[3].plot(t, err_y, "C2-", lw=0.8, label="yaw error")
    axs[3].set_ylabel("error [°]")
    axs[3].legend(loc="upper left", fontsize=8)
    if corr is not None:
        c = np.degrees(np.asarray(corr, dtype=np.float64).reshape(n, -1)[idx])
        for j in range(c.shape[1]):
            axs[4].plot(t, c[:, j], lw=0.8, label="xyz"[j] if j < 3 else str(j))
        axs[4].set_ylabel("gyro corr. [°/s]")
        axs[4].legend(loc="upper right", fontsize=8)
    axs[-1].set_xlabel("time [s]")
    fig.suptitle(f"{method} — {seq.name}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
