"""Input checks shared by every exported module, and the export error type."""
# No `from __future__ import annotations`: TorchScript reads the class-level attribute
# annotations (List[Tensor], ...) as real types.
import math
from pathlib import Path
from typing import Dict, List, Union

import torch
from torch import Tensor, nn

from ..conventions import INPUT_LIMITS, MAX_DT, MIN_DT



class ExportError(ValueError):
    """The model cannot be exported (a structure this exporter does not know)."""


class InputChecks(nn.Module):
    """Input checks shared by every exported module (``self.axes`` set by the subclass)."""

    def _check_imu(self, imu: Tensor):
        if imu.dim() != 2 or imu.size(1) != self.axes:
            raise ValueError("imu: expected shape (N, " + str(self.axes) + ") [gyro rad/s, acc m/s^2"
                             + (", mag uT" if self.axes == 9 else "") + "], got " + str(list(imu.shape)))
        if imu.size(0) < 1:
            raise ValueError("imu: expected at least one sample")
        self._check_finite(imu, "imu")

    def __init__(self):
        super().__init__()
        # per channel: gyro x,y,z, acc x,y,z, mag x,y,z (conventions.INPUT_LIMITS)
        self.register_buffer("input_limits", torch.tensor(INPUT_LIMITS, dtype=torch.float64))
        self.max_dt = float(MAX_DT)
        self.min_dt = float(MIN_DT)
        self.max_dt_text = f"{MAX_DT:g}"
        self.min_dt_text = f"{MIN_DT:g}"

    def _check_finite(self, x: Tensor, what: str):
        """Raise on NaN/inf or a value beyond any sensor's range (``input_limits``), naming the
        first bad entry: one NaN or 1e30 would otherwise spread through the networks' receptive
        field and the filter state into every later output. One comparison catches both."""
        bad = torch.logical_not(x.abs() <= self.input_limits[:x.size(-1)])
        if bool(bad.any()):
            where: List[int] = torch.nonzero(bad)[0].tolist()
            if bool(torch.isfinite(x).all()):
                raise ValueError(what + ": value beyond any sensor's range at index " + str(where)
                                 + " (|gyro| <= " + str(self.input_limits[0].item()) + " rad/s, |acc| <= "
                                 + str(self.input_limits[3].item()) + " m/s^2, |mag| <= "
                                 + str(self.input_limits[6].item()) + " uT per axis): a spike; drop or "
                                 "interpolate that sample")
            raise ValueError(what + ": non-finite value at index " + str(where)
                             + " (expected finite readings: drop or interpolate that sample)")

    def _check_step(self, dt: float, first: bool):
        """dt of a step after the first must be finite and in [min_dt, max_dt] s (the first is not used)."""
        if not first and not (dt >= self.min_dt and dt <= self.max_dt):
            raise ValueError("dt: expected a finite time step in [" + self.min_dt_text + ", " + self.max_dt_text
                             + "] s since the previous sample, got " + str(dt))

    def _q0(self, q0: Tensor) -> Tensor:
        if q0.numel() != 4:
            raise ValueError("q0: expected 4 values (w, x, y, z), got shape " + str(list(q0.shape)))
        q = q0.reshape(4).to(torch.float64)
        n = float(torch.linalg.norm(q))
        if not (n > 0.0 and math.isfinite(n)):
            raise ValueError("q0: expected a non-zero finite quaternion (w, x, y, z)")
        return q / n

    def _dt(self, dt: Union[float, Tensor], n: int, dtype: torch.dtype = torch.float64) -> Tensor:
        if isinstance(dt, Tensor):
            d = dt.to(dtype)
            if d.dim() == 0:
                d = d.expand(n)
            elif d.dim() != 1 or d.size(0) != n:
                raise ValueError("dt: expected a float or shape (" + str(n) + ",), got " + str(list(d.shape)))
        else:
            d = torch.full([n], float(dt), dtype=dtype)
        # dt[0] is not used (Eq. 3); every later step must be a finite positive time
        later = d[1:]
        bad = torch.logical_not((later >= self.min_dt) & (later <= self.max_dt))
        if bool(bad.any()):
            k = int(torch.nonzero(bad)[0, 0]) + 1
            raise ValueError("dt: expected finite time steps in [" + self.min_dt_text + ", " + self.max_dt_text
                             + "] s after sample 0, got "
                             + str(float(d[k])) + " at index " + str(k))
        return d


MODES = ("batch", "streaming", "both")


def output_paths(out_path, mode: str, suffix: str) -> Dict[str, Path]:
    """The files an export of ``mode`` writes, every format alike: ``both``: the batch model in
    FILE, the streaming one in FILE_streaming (``suffix`` when FILE has none); ``batch`` /
    ``streaming``: that one in FILE."""
    out = Path(out_path)
    if mode not in MODES:
        raise ValueError(f"export mode {mode!r}: expected one of {MODES}")
    paths: Dict[str, Path] = {}
    if mode in ("batch", "both"):
        paths["batch"] = out
    if mode in ("streaming", "both"):
        paths["streaming"] = out if mode == "streaming" else out.with_name(f"{out.stem}_streaming{out.suffix or suffix}")
    return paths
