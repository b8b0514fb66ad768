"""Training data: recordings -> device-resident tensors -> random windows (+ noise augmentation).

* :class:`SequenceStore` concatenates recordings into flat tensors (IMU, dt, ground-truth
  ``nav_from_body`` matrices, validity) and gathers windows for a batch of start indices
  with one indexing operation (no per-sample Python loop). It moves itself to the model's
  device once, so the whole training set lives there.
* :func:`window_starts` lists the admissible window starts (inside one recording, valid
  ground truth at the first sample, which the model's ECF needs as C_0).
* :func:`input_statistics` gives the per-channel mean/std the model normalises with.
* :func:`augment` adds Gaussian white noise to the raw readings (paper Sec. 4.2).
* :class:`AHRSDataModule` loads the splits (``load_split``) and serves batches of window
  *start indices* (so Lightning's samplers, DDP included, shard them); the LightningModule
  gathers the windows from the store on its device.
"""
from __future__ import annotations

import warnings
from typing import Dict, List, Mapping, Optional, Sequence

import numpy as np
import pytorch_lightning as pl
import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset, TensorDataset

from . import so3
from .losses import trust_labels
from .sequence import ImuSequence


def sequence_tensors(seq: ImuSequence, axes: int, dtype=torch.float32) -> Dict[str, Tensor]:
    """One recording as tensors: imu (N, C), dt (N,), rot (N, 3, 3) ground truth (identity where
    invalid), valid (N,) bool. ``axes`` 6 drops the magnetometer; 9 requires one."""
    if axes == 9 and not seq.has_mag:
        raise ValueError(f"{seq.source}: field 'mag': the 9-axis model needs a magnetometer but "
                         f"recording {seq.name!r} has none (use a 6-axis model: model=ahrs6 / data.axes=6)")
    imu = np.concatenate([seq.gyro, seq.accel] + ([seq.mag] if axes == 9 else []), axis=1)
    n = len(seq)
    if seq.quat is not None:
        valid = np.asarray(seq.quat_valid, dtype=bool)
        q = np.where(valid[:, None], seq.quat, np.array([1.0, 0.0, 0.0, 0.0]))
        rot = so3.quat_to_matrix(torch.as_tensor(q, dtype=torch.float64))
    else:
        valid = np.zeros(n, dtype=bool)
        rot = torch.eye(3, dtype=torch.float64).expand(n, 3, 3)
    imu_t = torch.as_tensor(imu, dtype=dtype)
    valid_t = torch.as_tensor(valid)
    return {
        "imu": imu_t,
        "dt": torch.as_tensor(seq.dt, dtype=dtype),
        "rot": rot.to(dtype).contiguous(),
        "valid": valid_t,
        # targets of the backbone model's trust logits (whole-recording field reference)
        "trust_label": trust_labels(imu_t, rot, valid_t),
    }


class SequenceStore:
    """Recordings concatenated into flat tensors; ``gather(starts, length)`` -> batch of windows."""

    def __init__(self, seqs: Sequence[ImuSequence], axes: int):
        if not seqs:
            raise ValueError("SequenceStore: no recordings (is the split empty? check data.root and the lists)")
        parts = [sequence_tensors(s, axes) for s in seqs]
        self.names = [s.name for s in seqs]
        self.lengths = [int(p["imu"].shape[0]) for p in parts]
        self.offsets = np.concatenate([[0], np.cumsum(self.lengths)[:-1]]).astype(np.int64)
        self.tensors = {k: torch.cat([p[k] for p in parts], 0) for k in parts[0]}
        self.axes = axes
        self._device = torch.device("cpu")

    def to(self, device) -> "SequenceStore":
        device = torch.device(device)
        if device != self._device:
            self.tensors = {k: v.to(device) for k, v in self.tensors.items()}
            self._device = device
        return self

    def gather(self, starts: Tensor, length: int) -> Dict[str, Tensor]:
        """starts (B,) -> dict of (B, length, ...) windows, on the store's device."""
        idx = starts.to(self._device).long()[:, None] + torch.arange(length, device=self._device)
        return {k: v[idx] for k, v in self.tensors.items()}

    def recording_end(self, flat_index: Tensor) -> Tensor:
        """(B,) flat indices -> (B,) one past the last flat index of their recordings."""
        ends = torch.as_tensor(self.offsets + np.asarray(self.lengths), device=flat_index.device)
        starts = torch.as_tensor(self.offsets, device=flat_index.device)
        i = torch.searchsorted(starts, flat_index, right=True) - 1
        return ends[i]

    def sequence(self, i: int) -> Dict[str, Tensor]:
        """Recording i as a batch of one: dict of (1, N_i, ...)."""
        a, n = int(self.offsets[i]), self.lengths[i]
        return {k: v[a:a + n].unsqueeze(0) for k, v in self.tensors.items()}


def window_starts(store: SequenceStore, window: int, stride: int, margin: int = 0) -> Tensor:
    """Start indices (into the flat store) of windows of ``window`` samples lying inside one
    recording with valid ground truth at their first sample, every ``stride`` samples, at least
    ``margin`` samples after the recording's start (the causal networks' warm-up context)."""
    valid = store.tensors["valid"].cpu().numpy()
    out = []
    for off, n in zip(store.offsets, store.lengths):
        if n < window + margin:
            continue
        s = off + np.arange(margin, n - window + 1, stride)
        out.append(s[valid[s]])
    starts = np.concatenate(out) if out else np.zeros(0, dtype=np.int64)
    if starts.size == 0:
        raise ValueError(f"no training window of {window} samples fits the training recordings "
                         f"(lengths {store.lengths}); lower train.window")
    return torch.as_tensor(starts, dtype=torch.long)


def input_statistics(seqs: Sequence[ImuSequence], axes: int) -> tuple:
    """Per-channel (mean, std) (C,) float32 over all samples of the training recordings."""
    x = np.concatenate([np.concatenate([s.gyro, s.accel] + ([s.mag] if axes == 9 else []), 1) for s in seqs], 0)
    return torch.as_tensor(x.mean(0), dtype=torch.float32), torch.as_tensor(x.std(0), dtype=torch.float32)


def augment(imu: Tensor, noise_std: Mapping[str, float], generator: Optional[torch.Generator] = None) -> Tensor:
    """Add white Gaussian noise to raw readings (B, N, C): std per sensor
    ``{"gyro": rad/s, "acc": m/s^2, "mag": uT}`` (paper Sec. 4.2)."""
    std = [float(noise_std.get("gyro", 0.0))] * 3 + [float(noise_std.get("acc", 0.0))] * 3
    if imu.shape[-1] == 9:
        std += [float(noise_std.get("mag", 0.0))] * 3
    std_t = torch.tensor(std, dtype=imu.dtype, device=imu.device)
    if not bool((std_t > 0).any()):
        return imu
    noise = torch.randn(imu.shape, generator=generator, dtype=imu.dtype, device=imu.device)
    return imu + noise * std_t


class _Indices(Dataset):
    def __init__(self, n: int):
        self.n = n

    def __len__(self):
        return self.n

    def __getitem__(self, i):
        return i


class AHRSDataModule(pl.LightningDataModule):
    """Splits from ``data_cfg`` (via :func:`tcn_ahrs.datasets.load_split`) as device-resident stores.

    Args:
        data_cfg:   the ``data`` config group (``conf/data/*.yaml``, ``data/README.md``).
        axes:       model axes (6/9).
        window:     training window length, samples.
        stride:     spacing of admissible window starts, samples.
        batch_size: windows per batch.
        train_seqs/val_seqs: recordings to use instead of loading them (tests).
    """

    def __init__(self, data_cfg: Optional[Mapping], axes: int, window: int, stride: int,
                 batch_size: int, train_seqs: Optional[List[ImuSequence]] = None,
                 val_seqs: Optional[List[ImuSequence]] = None, margin: int = 0):
        super().__init__()
        self.margin = int(margin)
        self.data_cfg = data_cfg
        self.axes = int(axes)
        self.window = int(window)
        self.stride = int(stride)
        self.batch_size = int(batch_size)
        self.train_seqs = train_seqs
        self.val_seqs = val_seqs
        self.train_store: Optional[SequenceStore] = None
        self.val_store: Optional[SequenceStore] = None
        self.starts: Optional[Tensor] = None

    def prepare(self) -> None:
        """Load the splits and build the stores (idempotent; called before the model is built
        so that the input statistics can be set)."""
        if self.train_store is not None:
            return
        if self.train_seqs is None or self.val_seqs is None:
            from .datasets import load_split

            if self.train_seqs is None:
                self.train_seqs = load_split(self.data_cfg, "train")
            if self.val_seqs is None:
                self.val_seqs = load_split(self.data_cfg, "val")
        keep = [s for s in self.train_seqs if s.has_gt and s.quat_valid.any()]
        if not keep:
            dc = self.data_cfg or {}
            name, root = dc.get("name", "?"), dc.get("root", "?")
            if not self.train_seqs:
                listed = list(dc.get("train") or []) if hasattr(dc, "get") else []
                found = ""
                try:
                    from .datasets import list_recordings

                    found = ", ".join(list_recordings(dc)[:8]) or "none"
                except Exception:  # noqa: BLE001 - only for the hint
                    pass
                raise ValueError(f"data '{name}': no training recordings: data.train lists "
                                 f"{len(listed)} under root {root} (found there: {found}); set "
                                 "data.train=[name, ...] (and data.test) or use a data config that lists them")
            raise ValueError(f"data '{name}': none of the {len(self.train_seqs)} training recordings has valid "
                             "ground truth (quat) to train on")
        longest = max((len(s) for s in keep), default=0) - self.margin
        if longest < 2:
            raise ValueError(f"data '{(self.data_cfg or {}).get('name', '?')}': every training recording is shorter than "
                             f"the model's warm-up context ({self.margin} samples before a window) plus 2 samples; "
                             "use longer recordings or a smaller model.tcn (fewer dilations)")
        if longest < self.window:
            warnings.warn(f"training window {self.window} is longer than every training recording "
                          f"(longest {longest}); using {longest}")
            self.window = longest
        self.train_store = SequenceStore(keep, self.axes)
        self.starts = window_starts(self.train_store, self.window, self.stride, self.margin)
        vals = [s for s in self.val_seqs if s.has_gt and s.quat_valid.sum() > 1]
        self.val_store = SequenceStore(vals, self.axes) if vals else None

    def setup(self, stage: Optional[str] = None) -> None:
        self.prepare()

    def statistics(self) -> tuple:
        self.prepare()
        return input_statistics(self.train_seqs, self.axes)

    def train_dataloader(self):
        return DataLoader(TensorDataset(self.starts), batch_size=self.batch_size, shuffle=True,
                          drop_last=len(self.starts) > self.batch_size)

    def val_dataloader(self):
        n = 0 if self.val_store is None else len(self.val_store.lengths)
        return DataLoader(_Indices(n), batch_size=1, shuffle=False)
