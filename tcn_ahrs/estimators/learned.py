"""The learned AHRS as an :class:`~tcn_ahrs.estimators.base.Estimator` (wraps a trained checkpoint)."""
from __future__ import annotations

import warnings
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch

from .. import so3
from ..conventions import NETWORK_DTYPE, STATE_DTYPE
from ..filters.backbone import HEALTH_KEYS
from ..checkpoint import CheckpointError, model_from_checkpoint
from ..filters.common import heading_ref_for
from ..model.ahrs import LearnedAHRS
from ..sequence import ImuSequence
from ..validate import check_number
from .base import EstimatorOutput
from .registry import register


def model_input(model: LearnedAHRS, seq: ImuSequence, device, what: str = "model") -> torch.Tensor:
    """The recording as the model's input (1, N, C) float32: gyro, accelerometer (and, for a
    9-axis model, magnetometer); a 9-axis model on a recording without one is an error."""
    if model.axes == 9 and not seq.has_mag:
        raise CheckpointError(
            f"{seq.source}: field 'mag': the {what} (variant '{model.variant}') expects 9-axis input but "
            f"recording {seq.name!r} has no magnetometer; use a 6-axis checkpoint")
    parts = [seq.gyro, seq.accel] + ([seq.mag] if model.axes == 9 else [])
    # the backbone model filters the raw float64 readings (its networks cast for themselves), so
    # its untrained form equals the backbone estimator to round-off
    dtype = STATE_DTYPE if getattr(model, "backbone", None) is not None else NETWORK_DTYPE
    return torch.as_tensor(np.concatenate(parts, 1), dtype=dtype, device=device)[None]


class LearnedEstimator:
    """A trained :class:`LearnedAHRS` on a whole recording, run as the checkpoint says: the
    learned closed loop (default model; sample by sample, float64) or the paper's open-loop ECF
    (feed-forward).

    The networks see every sample (causally); the filter and the integration start at sample
    ``init_index`` from ``init_quat`` (identity when ``None``); the runner passes the first
    sample with valid ground truth.

    Output signals (N, 3), body frame:
        ``gyro_correction`` ω̂ − y_gyr (rad/s; everything the model adds to the raw gyro),
        ``gyro_bias`` the TCN's gyro error term ω̃ (rad/s, Eq. 12),
        ``acc_error`` ã (m/s^2, Eq. 13), ``mag_error`` m̃ (uT, Eq. 14; 9-axis only);
        closed loop also ``gyro_bias_state`` b (rad/s), ``acc_trust``, ``mag_trust`` (N,) and
        ``rest`` (N,) from the rest detector.
    """

    OTHER_RATE = ("backbone", "model")

    def __init__(self, model: Union[LearnedAHRS, str, Path], name: str = "TCN-ECF",
                 device: Union[str, torch.device] = "cpu", reanchor: Optional[int] = None,
                 other_rate: str = "backbone", heading_ref: str = "auto"):
        if isinstance(model, (str, Path)):
            self.ckpt_path = str(model)
            model = model_from_checkpoint(model)
        else:
            self.ckpt_path = None
        self.model = model.to(device).eval()
        self.device = torch.device(device)
        self.name = name
        # 9 axes: "auto" refers heading to magnetic north on magnetic-north ground truth (the
        # yardstick), else to the field at the start — what the streaming runtimes do ("init")
        heading_ref_for(heading_ref, None)  # a misspelt reference fails here, not at the first run
        self.heading_ref = heading_ref
        # restart the open-loop ECF from the estimate every `reanchor` samples
        # (LearnedAHRS.run_sequence); None = the paper's single pass
        self.reanchor = None if reanchor is None else check_number(reanchor, "reanchor", int, 1)
        if other_rate not in self.OTHER_RATE:
            raise ValueError(f"other_rate: expected one of {self.OTHER_RATE}, got {other_rate!r}")
        # a recording at another rate than training comes from another device: a learned model
        # (residual, closed or open loop) runs there as the backbone with VQF's default
        # parameters (other_rate=backbone), because what it learned (gyro correction, trusts,
        # gains, bias prior) belongs to its device and its networks' receptive field is counted
        # in samples (the closed loop shipped for EuRoC scored 13.96 on BROAD's trials run as
        # itself, against the backbone's 2.56)
        self.other_rate = other_rate
        self._fallback = None
        self.fell_back: list = []  # names of the recordings run as the backbone

    def _device_fallback(self):
        """The classical ``backbone`` estimator with VQF's default parameters (the matrix's
        "backbone" column): nothing learned applied."""
        if self._fallback is None:
            from .registry import build

            self._fallback = build("backbone", axes=int(self.model.axes))
        return self._fallback

    @property
    def axes(self) -> int:
        return self.model.axes

    def trained_rates(self) -> str:
        span = getattr(self.model, "trained_rate_range", None)
        if span:
            return f"{span[0]:.4g}-{span[1]:.4g} Hz"
        return f"{getattr(self.model, 'trained_rate_hz', None) or float('nan'):.4g} Hz"

    def other_device(self, rate_hz: float) -> bool:
        """Whether a recording at ``rate_hz`` lies outside the rates the model was trained at:
        ±5 % of its training rate, or its trained range (rate augmentation) ±5 %."""
        span = getattr(self.model, "trained_rate_range", None)
        if span:
            return not (0.95 * span[0] <= rate_hz <= 1.05 * span[1])
        trained = getattr(self.model, "trained_rate_hz", None)
        return bool(trained) and abs(rate_hz / trained - 1.0) > 0.05

    def run(self, seq: ImuSequence, init_quat: Optional[np.ndarray] = None,
            init_index: int = 0) -> EstimatorOutput:
        if self.other_device(float(seq.rate)):
            if self.other_rate == "backbone":
                if not self.fell_back:  # once per model: the list names every recording
                    warnings.warn(f"{self.name}: recording {seq.name!r} is at {seq.rate:.4g} Hz, the model was "
                                  f"trained at {self.trained_rates()} (another device): such recordings run as the "
                                  "backbone with VQF's default parameters, nothing learned applied "
                                  "(other_rate=model runs the model anyway)", stacklevel=2)
                self.fell_back.append(seq.name)
                out = self._device_fallback().run(seq, init_quat, init_index)
                out.signals = {**(out.signals or {}), "gyro_correction": np.zeros((len(seq), 3))}
                return out
            else:
                warnings.warn(f"{self.name}: recording {seq.name!r} is at {seq.rate:.4g} Hz but the model was "
                              f"trained at {self.trained_rates()}: its networks' time scale and rest window assume "
                              "those rates (resample the recording, or train at its rate)", stacklevel=2)
        imu = model_input(self.model, seq, self.device, f"model {self.ckpt_path or ''}")
        dt = torch.as_tensor(seq.dt, dtype=imu.dtype, device=self.device)[None]
        start = check_number(init_index, "init_index", int, 0, high=len(seq))
        if init_quat is None:
            q0 = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
        else:
            q0 = torch.as_tensor(np.asarray(init_quat, dtype=np.float64).reshape(4))
        r0 = so3.quat_to_matrix(q0).to(self.device)[None]
        with torch.no_grad():
            out = self.model.run_sequence(imu, dt, r0, start, reanchor=self.reanchor,
                                          heading_ref=heading_ref_for(self.heading_ref, seq.meta))
        quat = so3.matrix_to_quat(out["rot"][0]).cpu().numpy()
        sig = {
            "gyro_correction": (out["omega"][0] - imu[0, :, 0:3]).cpu().double().numpy(),
            "gyro_bias": out["gyro_error"][0].cpu().double().numpy(),
            "acc_error": out["acc_error"][0].cpu().double().numpy(),
        }
        if "mag_error" in out:
            sig["mag_error"] = out["mag_error"][0].cpu().double().numpy()
        # the health flags of the filter it runs (the backbone's, or the closed loop's frozen/gap
        # checks): tcn-ahrs evaluate names what they found
        sig.update({k: out[k][0].cpu().numpy() > 0.5 for k in HEALTH_KEYS if k in out})
        if "gyro_bias" in out:  # closed loop: states from `start` on
            n0 = len(seq) - out["gyro_bias"].shape[1]
            b = np.zeros((len(seq), 3))
            b[n0:] = out["gyro_bias"][0].cpu().numpy()
            sig["gyro_bias_state"] = b
            for k in ("acc_trust", "mag_trust", "rest"):
                sig[k] = out[k][0].cpu().double().numpy()
        return EstimatorOutput(quat=quat, signals=sig)


@register("learned", "learned")
def learned_estimator(ckpt: Union[str, Path], name: str = "Learned", device: Union[str, torch.device] = "cpu",
                      reanchor: Optional[int] = None, other_rate: str = "backbone") -> LearnedEstimator:
    """Registry factory: the checkpoint ``ckpt`` as the column ``name``."""
    return LearnedEstimator(ckpt, name=name, device=device, reanchor=reanchor, other_rate=other_rate)


class OnLearnedCalibration:
    """Any estimator run on the *calibrated* signals of a trained model: gyro ω̂_gyr, accelerometer
    ĝ and magnetometer b̂ (Eqs. 12-14: ``R̂ y − e``, the networks' error terms subtracted; no
    filter state of the model) instead of the raw readings — does the learned calibration help a
    classical filter? Name: ``"<estimator> on <label>"``; axes and heading_free are the wrapped
    estimator's."""

    def __init__(self, estimator, model: Union[LearnedAHRS, str, Path], label: str = "learned calibration",
                 device: Union[str, torch.device] = "cpu"):
        self.inner = estimator
        self.model = (model_from_checkpoint(model) if isinstance(model, (str, Path)) else model).to(device).eval()
        self.device = torch.device(device)
        self.name = f"{estimator.name} on {label}"
        self.axes = getattr(estimator, "axes", None)
        self.heading_free = bool(getattr(estimator, "heading_free", False))

    def calibrated(self, seq: ImuSequence) -> ImuSequence:
        from dataclasses import replace

        axes = self.model.axes
        imu = model_input(self.model, seq, self.device, "calibration model")
        with torch.no_grad():
            cal = self.model.calibration(imu)
        f = lambda k: cal[k][0].cpu().double().numpy()  # noqa: E731
        return replace(seq, gyro=f("gyro"), accel=f("acc"), mag=f("mag") if axes == 9 else seq.mag,
                       check_units=False)

    def run(self, seq: ImuSequence, init_quat: Optional[np.ndarray] = None,
            init_index: int = 0) -> EstimatorOutput:
        return self.inner.run(self.calibrated(seq), init_quat, init_index)
