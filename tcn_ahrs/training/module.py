"""The LightningModule: :class:`LearnedAHRS` + increment loss (Eqs. 26-28) or the closed loop's
attitude loss (truncated backpropagation over chained chunks) + AdamW/cosine schedule; validation
= loss and AAE on the full validation recordings."""
from __future__ import annotations

import math
from typing import Any, Dict, List, Optional

import pytorch_lightning as pl
import torch

from .. import so3
from ..checkpoint import layout_meta
from ..config import TrainConfig
from ..data import augment, augment_sensor
from ..losses import attitude_loss, increment_loss, rest_rate_loss, trust_loss
from ..model.ahrs import LearnedAHRS

_T = TrainConfig()  # the defaults (meaning, units): tcn_ahrs/config/train.py

__all__ = ["AHRSModule"]


class AHRSModule(pl.LightningModule):
    """LightningModule around :class:`LearnedAHRS`. All arguments are plain types (they are
    saved in the checkpoint, which is loaded with ``weights_only=True``); their defaults are
    ``train:``'s (:class:`tcn_ahrs.config.TrainConfig`). ``noise``/``augment``: ``train.noise`` /
    ``train.augment`` (None: no noise, no augmentation)."""

    def __init__(self, model_cfg: Dict[str, Any], axes: int, lr: float = _T.lr,
                 weight_decay: float = _T.weight_decay, epochs: int = _T.epochs, window: int = _T.window,
                 loss_js: List[int] = tuple(_T.loss_js), huber_delta: float = _T.huber_delta,
                 noise: Optional[Dict[str, float]] = None, data_name: str = "",
                 rate_hz: Optional[float] = None, stream_chunks: int = _T.stream_chunks,
                 attitude_delta: float = _T.attitude_delta, ema_decay: float = _T.ema_decay,
                 augment: Optional[Dict[str, Any]] = None, supervision: str = _T.supervision,
                 device_check: bool = _T.device_check):
        super().__init__()
        self.save_hyperparameters()
        self.model = LearnedAHRS.from_config(model_cfg, axes=axes)
        # Exponential moving average of the weights (Polyak averaging): what validation, the
        # checkpoint selection and the released model use. The closed loop's whole-recording
        # error swings by degrees between neighbouring SGD iterates (a 1e-3 rad/s change of a
        # learned bias is 10 deg of heading over three minutes); the average does not.
        self.ema_model: Optional[LearnedAHRS] = None
        if ema_decay and float(ema_decay) > 0.0:
            self.ema_model = LearnedAHRS.from_config(model_cfg, axes=axes)
            self.ema_model.requires_grad_(False)
            self.reset_ema()
        self.loss_js = [int(j) for j in loss_js]
        self.noise = dict(noise or {})
        self.augment = dict(augment or {})  # train.augment: rate resampling and sensor errors
        self._stream: Optional[Dict[str, torch.Tensor]] = None  # closed-loop TBPTT state

    @torch.no_grad()
    def reset_ema(self) -> None:
        """The average restarts at the current weights (after the data-driven initialisation)."""
        if self.ema_model is not None:
            self.ema_model.load_state_dict(self.model.state_dict())

    @torch.no_grad()
    def on_train_batch_end(self, outputs, batch, batch_idx) -> None:
        if self.ema_model is None:
            return
        w = 1.0 - float(self.hparams.ema_decay)
        for p_avg, p in zip(self.ema_model.parameters(), self.model.parameters()):
            p_avg.lerp_(p.detach(), w)
        for b_avg, b in zip(self.ema_model.buffers(), self.model.buffers()):
            b_avg.copy_(b)

    @property
    def eval_model(self) -> LearnedAHRS:
        return self.model if self.ema_model is None else self.ema_model

    # ------------------------------------------------------------------ steps
    def _store(self, which: str):
        store = getattr(self.trainer.datamodule, which)
        return store.to(self.device)

    def training_step(self, batch, batch_idx):
        (starts,) = batch
        if self.model.closed is not None:
            return self._closed_loop_step(starts)
        w = self._windows(starts)
        imu = augment(w["imu"], self.noise)
        out = self.model(imu, w["dt"], w["rot"][:, 0])
        if self.hparams.get("supervision") == "self":
            return self._self_supervised_loss(out, w, starts.shape[0])
        loss = increment_loss(out["omega"], w["dt"], w["rot"], w["valid"], self.loss_js,
                              self.hparams.huber_delta)
        if self.model.backbone is not None:  # the trust logits: separate network, own loss
            loss = loss + trust_loss(out["acc_trust_logit"], w["trust_label"][..., 0], w["valid"])
            if "mag_trust_logit" in out:
                loss = loss + trust_loss(out["mag_trust_logit"], w["trust_label"][..., 1], w["valid"])
        self.log("train/loss", loss, prog_bar=True, on_step=True, on_epoch=True,
                 batch_size=starts.shape[0], sync_dist=True)
        return loss

    def _self_supervised_loss(self, out: Dict[str, torch.Tensor], w: Dict[str, torch.Tensor], b: int):
        """No motion capture (``train.supervision=self``): the corrected rate is zero at rest
        (:func:`~tcn_ahrs.losses.rest_rate_loss`), the trust logits learn the sensors' own
        consistency (:func:`~tcn_ahrs.losses.self_labels`)."""
        label, valid = w["trust_label"], w["valid"]
        loss = rest_rate_loss(out["omega"], label[..., 2] > 0.5, self.hparams.huber_delta)
        if "acc_trust_logit" in out:
            loss = loss + trust_loss(out["acc_trust_logit"], label[..., 0], valid)
        if "mag_trust_logit" in out:
            loss = loss + trust_loss(out["mag_trust_logit"], label[..., 1], valid)
        self.log("train/loss", loss, prog_bar=True, on_step=True, on_epoch=True, batch_size=b, sync_dist=True)
        return loss

    def _windows(self, starts: torch.Tensor) -> Dict[str, torch.Tensor]:
        """The batch's training windows: at a random rate each when ``augment.rate_hz`` is set
        (:meth:`~tcn_ahrs.data.SequenceStore.gather_resampled`), then another sensor's errors
        (:func:`~tcn_ahrs.data.augment_sensor`)."""
        store, a = self._store("train_store"), self.augment
        window = self.trainer.datamodule.window
        if a.get("rate_hz"):
            w = store.gather_resampled(starts, window, a["rate_hz"], float(a.get("jitter") or 0.0))
        else:
            w = store.gather(starts, window)
        if a.get("rotate") or a.get("gyro_bias") or a.get("scale"):
            w = augment_sensor(w, bool(a.get("rotate")), float(a.get("gyro_bias") or 0.0), float(a.get("scale") or 0.0))
        return w

    def _closed_loop_step(self, starts: torch.Tensor):
        """Truncated backpropagation through the closed loop over chained chunks.

        B streams run through the training recordings; each training step advances every
        stream by one chunk of ``window`` samples from its carried (detached) filter state, so
        the filter is trained in the state it runs in at inference — including a gyro-bias state
        that has converged over earlier chunks — while gradients stay within one chunk. A stream
        restarts (at a new random window start, from ground truth, zero bias, a new random
        constant gyro offset ``noise.gyro_bias``) after ``stream_chunks`` chunks or at the end of
        its recording. The networks see ``receptive_field - 1`` samples of context before each
        chunk (the window starts leave that margin)."""
        store = self._store("train_store")
        L = int(self.trainer.datamodule.window)
        ctx = int(self.model.receptive_field) - 1
        starts = starts.to(self.device)
        b = starts.shape[0]
        st = self._stream
        if st is None or st["pos"].shape[0] != b:
            reset = torch.ones(b, dtype=torch.bool, device=self.device)
            st = {"pos": starts.clone(), "left": torch.zeros(b, dtype=torch.long, device=self.device),
                  "rot": torch.zeros(b, 3, 3, device=self.device), "bias": torch.zeros(b, 3, device=self.device),
                  "offset": torch.zeros(b, 3, device=self.device)}
        else:
            reset = (st["left"] <= 0) | (st["pos"] + L > store.recording_end(st["pos"]))
        if bool(reset.any()):
            st["pos"] = torch.where(reset, starts, st["pos"])
            st["left"] = torch.where(reset, torch.full_like(st["left"], int(self.hparams.stream_chunks)), st["left"])
            st["rot"] = torch.where(reset[:, None, None], store.tensors["rot"][st["pos"]], st["rot"])
            st["bias"] = torch.where(reset[:, None], torch.zeros_like(st["bias"]), st["bias"])
            off = torch.randn_like(st["offset"]) * float(self.noise.get("gyro_bias", 0.0))
            st["offset"] = torch.where(reset[:, None], off, st["offset"])
        w = store.gather(st["pos"] - ctx, L + ctx)
        imu = augment(w["imu"], self.noise)
        imu = torch.cat([imu[..., 0:3] + st["offset"][:, None], imu[..., 3:]], -1)
        out = self.model.filter_closed_loop(imu, w["dt"], st["rot"], st["bias"], context=ctx)
        valid = w["valid"][:, ctx:].clone()
        valid[:, 0] = False  # the initial state is given, not estimated
        loss = attitude_loss(out["rot"], w["rot"][:, ctx:], valid, float(self.hparams.attitude_delta))
        # carried on detached and re-orthonormalised (float32 round-off over many chunks)
        st["rot"] = so3.quat_to_matrix(so3.matrix_to_quat(out["rot"][:, -1].detach()))
        st["bias"] = out["gyro_bias"][:, -1].detach()
        st["pos"] = st["pos"] + (L - 1)
        st["left"] = st["left"] - 1
        self._stream = st
        self.log("train/loss", loss, prog_bar=True, on_step=True, on_epoch=True, batch_size=b, sync_dist=True)
        return loss

    def _closed_loop_validation(self):
        """All validation recordings in one padded closed-loop pass (the loop costs the same for
        B recordings as for one). Each starts at its first valid ground truth; padding has
        dt = 0 and is not scored. Logs the mean over recordings of AAE and of the loss."""
        store = self._store("val_store")
        seqs = []
        for i in range(len(store.lengths)):
            s = store.sequence(i)
            k0 = int(torch.argmax(s["valid"][0].to(torch.int8)))
            seqs.append({k: v[:, k0:] for k, v in s.items()})
        n = max(s["imu"].shape[1] for s in seqs)

        def pad(x, fill_last: bool):
            extra = n - x.shape[1]
            if extra == 0:
                return x
            tail = x[:, -1:].expand(-1, extra, *x.shape[2:]) if fill_last else torch.zeros_like(x[:, :1]).expand(-1, extra, *x.shape[2:])
            return torch.cat([x, tail], 1)

        imu = torch.cat([pad(s["imu"], True) for s in seqs])
        dt = torch.cat([pad(s["dt"], False) for s in seqs])
        rot_gt = torch.cat([pad(s["rot"], True) for s in seqs])
        valid = torch.cat([pad(s["valid"], False) for s in seqs])
        out = self.eval_model.filter_closed_loop(imu, dt, rot_gt[:, 0].double(), dtype=torch.float64)
        aaes, losses = [], []
        for i in range(len(seqs)):
            m = valid[i]
            aaes.append(_aae_deg(rot_gt[i, m], out["rot"][i, m]))
            losses.append(attitude_loss(out["rot"][i:i + 1], rot_gt[i:i + 1], valid[i:i + 1],
                                        float(self.hparams.attitude_delta)))
        self.log("val/loss", torch.stack(losses).mean().float(), prog_bar=True, batch_size=1)
        self.log("val/aae_deg", torch.stack(aaes).mean().float(), prog_bar=True, batch_size=1)

    def validation_step(self, batch, batch_idx):
        if self.model.closed is not None:
            if batch_idx == 0:
                self._closed_loop_validation()
            return
        i = int(batch[0])
        s = self._store("val_store").sequence(i)
        valid = s["valid"]
        k0 = int(torch.argmax(valid[0].to(torch.int8)))
        out = self.eval_model.run_sequence(s["imu"], s["dt"], s["rot"][:, k0], k0)
        loss = increment_loss(out["omega"], s["dt"], s["rot"], valid, self.loss_js, self.hparams.huber_delta)
        aae = _aae_deg(s["rot"][0, valid[0]], out["rot"][0, valid[0]])
        self.log("val/loss", loss, prog_bar=True, batch_size=1, sync_dist=True)
        self.log("val/aae_deg", aae.float(), prog_bar=True, batch_size=1, sync_dist=True)

    # -------------------------------------------------------------- optimiser
    def configure_optimizers(self):
        decay, no_decay = [], []
        for name, p in self.model.named_parameters():
            # Convolution kernels and the calibration matrices' deviation from I decay; biases,
            # BatchNorm and the ECF gains do not.
            (decay if (p.ndim >= 2) else no_decay).append(p)
        opt = torch.optim.AdamW([{"params": decay, "weight_decay": self.hparams.weight_decay},
                                 {"params": no_decay, "weight_decay": 0.0}], lr=self.hparams.lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, int(self.hparams.epochs)))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "epoch"}}

    def on_save_checkpoint(self, checkpoint: Dict[str, Any]) -> None:
        cfg = dict(self.hparams.model_cfg)
        cfg["axes"] = self.model.axes
        checkpoint["tcn_ahrs"] = layout_meta(cfg, self.model.axes, self.hparams.data_name,
                                             self.hparams.get("rate_hz"), self.augment.get("rate_hz"),
                                             bool(self.hparams.get("device_check")))
        # the recipe that trained it, recorded in the file (its model card reads it, never a name)
        from .trainer import command_line_overrides

        overrides = command_line_overrides()
        if overrides is not None:
            checkpoint["tcn_ahrs"]["recipe"] = {"command": "tcn-ahrs train", "overrides": overrides}


# ====================================================================== helpers
def _aae_deg(rot_gt: torch.Tensor, rot_est: torch.Tensor) -> torch.Tensor:
    """AAE (Eq. 29) of (M, 3, 3) estimates against ground truth on valid samples, degrees, float64.
    Validation starts the estimate at ground truth, so no alignment is needed (the same
    definition as :func:`tcn_ahrs.metrics.aae`)."""
    err = so3.log(rot_gt.double().transpose(-1, -2) @ rot_est.double())
    return torch.sqrt((err ** 2).sum(-1).mean()) * (180.0 / math.pi)
