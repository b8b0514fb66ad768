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

import math
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


def sequence_tensors(seq: ImuSequence, axes: int, dtype=torch.float32, supervision: str = "gt") -> Dict[str, Tensor]:
    """One recording as tensors: imu (N, C), dt (N,), rot (N, 3, 3) ground truth (identity where
    invalid), valid (N,) bool, trust_label (N, 2) from the ground truth. ``axes`` 6 drops the
    magnetometer; 9 requires one. ``supervision="self"``: no ground truth is read; every sample
    is valid and trust_label (N, 3) holds :func:`~tcn_ahrs.losses.self_labels` (acc, mag, rest)."""
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
    if supervision == "self":
        from .losses import self_labels

        dt_t = torch.as_tensor(seq.dt, dtype=torch.float64)
        return {"imu": imu_t, "dt": dt_t.to(dtype), "rot": torch.eye(3, dtype=dtype).expand(n, 3, 3).contiguous(),
                "valid": torch.ones(n, dtype=torch.bool), "trust_label": self_labels(imu_t, dt_t, rest=rest_mask(seq))}
    valid_t = torch.as_tensor(valid)
    return {
        "imu": imu_t,
        "dt": torch.as_tensor(seq.dt, dtype=dtype),
        "rot": rot.to(dtype).contiguous(),
        "valid": valid_t,
        # targets of the backbone model's trust logits (whole-recording field reference)
        "trust_label": trust_labels(imu_t, rot, valid_t),
    }


def rest_mask(seq: ImuSequence) -> Tensor:
    """(N,) bool: the samples the device check calls rest (:func:`tcn_ahrs.device_check.rest_windows`:
    the recording's own noise floor and a steady tilt, not absolute thresholds)."""
    from .device_check import rest_windows

    rest, n, _, _ = rest_windows(seq.gyro, seq.accel, float(seq.rate))
    out = np.zeros(len(seq), dtype=bool)
    out[:rest.size * n] = np.repeat(rest, n)
    return torch.as_tensor(out)


class SequenceStore:
    """Recordings concatenated into flat tensors; ``gather(starts, length)`` -> batch of windows."""

    def __init__(self, seqs: Sequence[ImuSequence], axes: int, supervision: str = "gt"):
        if not seqs:
            raise ValueError("SequenceStore: no recordings (is the split empty? check data.root and the lists)")
        parts = [sequence_tensors(s, axes, supervision=supervision) for s in seqs]
        self.names = [s.name for s in seqs]
        self.lengths = [int(p["imu"].shape[0]) for p in parts]
        self.offsets = np.concatenate([[0], np.cumsum(self.lengths)[:-1]]).astype(np.int64)
        self.tensors = {k: torch.cat([p[k] for p in parts], 0) for k in parts[0]}
        # time since each recording's start (float64: resampled windows interpolate in it)
        self.time = torch.cat([torch.cumsum(p["dt"].double(), 0) for p in parts], 0)
        self.rates = torch.as_tensor([float(s.rate) for s in seqs], dtype=torch.float64)
        self.axes = axes
        self._device = torch.device("cpu")

    def to(self, device) -> "SequenceStore":
        device = torch.device(device)
        if device != self._device:
            self.tensors = {k: v.to(device) for k, v in self.tensors.items()}
            self.time, self.rates = self.time.to(device), self.rates.to(device)
            self._device = device
        return self

    def gather(self, starts: Tensor, length: int) -> Dict[str, Tensor]:
        """starts (B,) -> dict of (B, length, ...) windows, on the store's device."""
        idx = starts.to(self._device).long()[:, None] + torch.arange(length, device=self._device)
        return {k: v[idx] for k, v in self.tensors.items()}

    def gather_resampled(self, starts: Tensor, length: int, rate_hz: Sequence[float], jitter: float = 0.0,
                         generator: Optional[torch.Generator] = None) -> Dict[str, Tensor]:
        """Windows of ``length`` samples resampled to a random rate each, log-uniform in
        ``rate_hz`` = (low, high) Hz, as if another device had recorded the motion: the readings
        are interpolated linearly, the ground truth along the geodesic (slerp), the trust labels
        taken from the nearest sample, validity from both neighbours; ``dt`` is the step between
        the interpolated times (float64 inside). ``jitter`` (< 0.5) moves every sample after the
        first by up to ±jitter/2 of a step: irregular sampling. A window whose rate would need
        more samples than its recording has left is sampled as slowly as the recording allows.
        Returns what :meth:`gather` returns, plus ``rate`` (B,) Hz."""
        dev = self._device
        starts = starts.to(dev).long()
        b = starts.shape[0]
        rec = torch.searchsorted(torch.as_tensor(self.offsets, device=dev), starts, right=True) - 1
        end = self.recording_end(starts)
        lo, hi = math.log(float(rate_hz[0])), math.log(float(rate_hz[1]))
        u = torch.rand(b, generator=generator, dtype=torch.float64).to(dev)
        rate = torch.exp(lo + (hi - lo) * u)
        rho = self.rates[rec] / rate  # native samples per output sample
        rho = torch.minimum(rho, (end - starts - 2).double() / max(length - 1, 1))
        rate = self.rates[rec] / rho
        k = torch.arange(length, dtype=torch.float64, device=dev).expand(b, length)
        if jitter > 0.0:
            shift = (torch.rand(b, length, generator=generator, dtype=torch.float64).to(dev) - 0.5) * float(jitter)
            shift[:, 0] = 0.0
            k = k + shift
        f = starts[:, None].double() + rho[:, None] * k
        i0 = torch.minimum(f.floor().long(), (end - 2)[:, None])
        a = (f - i0.double()).clamp(0.0, 1.0)
        i1 = i0 + 1
        t = self.tensors
        imu = t["imu"]
        a_imu = a.to(imu.dtype)[..., None]
        out = {"imu": (1.0 - a_imu) * imu[i0] + a_imu * imu[i1]}
        tt = (1.0 - a) * self.time[i0] + a * self.time[i1]
        dt = torch.diff(tt, dim=1)
        out["dt"] = torch.cat([dt[:, :1], dt], 1).to(t["dt"].dtype)
        r0, r1 = t["rot"][i0].double(), t["rot"][i1].double()
        rel = so3.log(r0.transpose(-1, -2) @ r1)
        out["rot"] = (r0 @ so3.exp(rel * a[..., None])).to(t["rot"].dtype)
        out["valid"] = t["valid"][i0] & t["valid"][i1]
        out["trust_label"] = torch.where((a < 0.5)[..., None], t["trust_label"][i0], t["trust_label"][i1])
        out["rate"] = rate
        return out

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


def balanced_starts(store: SequenceStore, starts: Tensor, seed: int = 0) -> Tensor:
    """As many window starts from every dataset part (recordings named ``<part>/<name>``,
    :func:`tcn_ahrs.datasets.data_parts`) as the parts have on average: a part with fewer is
    repeated, one with more is subsampled (fixed seed), so no dataset dominates an epoch."""
    part_of = np.array([n.split("/", 1)[0] if "/" in n else "" for n in store.names])
    rec = np.searchsorted(store.offsets, starts.numpy(), side="right") - 1
    groups = {p: starts.numpy()[part_of[rec] == p] for p in dict.fromkeys(part_of[rec])}
    target = int(round(np.mean([len(g) for g in groups.values()])))
    rng = np.random.default_rng(seed)
    out = [rng.choice(g, target, replace=len(g) < target) for g in groups.values() if len(g)]
    return torch.as_tensor(np.sort(np.concatenate(out)), dtype=torch.long)


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


def augment_sensor(w: Dict[str, Tensor], rotate: bool = False, gyro_bias: float = 0.0, scale: float = 0.0,
                   generator: Optional[torch.Generator] = None) -> Dict[str, Tensor]:
    """Another sensor's errors on a batch of windows (what :meth:`SequenceStore.gather`
    returns): ``rotate`` mounts each window's sensor in a uniformly random orientation (every
    reading turned by R, the ground truth ``nav_from_body`` by R^T, so the motion is the same);
    ``gyro_bias`` (rad/s) adds a constant gyro offset per window (std); ``scale`` a per-axis
    gyro and accelerometer scale error 1 + N(0, scale²). The trust labels stay valid: a rotation
    or a scale does not move the specific force's direction against the true up, and the
    magnetometer is only rotated (no hard or soft iron: that would change its labels)."""
    imu, b = w["imu"], w["imu"].shape[0]
    out = dict(w)
    if rotate:
        q = torch.randn(b, 4, generator=generator, dtype=torch.float64)
        r = so3.quat_to_matrix(q / q.norm(dim=-1, keepdim=True)).to(imu.device)  # sensor_from_body
        parts = [torch.einsum("bij,bnj->bni", r, imu[..., i:i + 3].double()) for i in range(0, imu.shape[-1], 3)]
        imu = torch.cat(parts, -1).to(w["imu"].dtype)
        out["rot"] = (w["rot"].double() @ r.transpose(-1, -2)[:, None]).to(w["rot"].dtype)
    if gyro_bias > 0.0 or scale > 0.0:
        g = imu[..., 0:3]
        if scale > 0.0:
            s = 1.0 + scale * torch.randn(b, 1, 6, generator=generator, dtype=imu.dtype).to(imu.device)
            g = g * s[..., 0:3]
            imu = torch.cat([g, imu[..., 3:6] * s[..., 3:6], imu[..., 6:]], -1)
        if gyro_bias > 0.0:
            off = gyro_bias * torch.randn(b, 1, 3, generator=generator, dtype=imu.dtype).to(imu.device)
            imu = torch.cat([imu[..., 0:3] + off, imu[..., 3:]], -1)
    out["imu"] = imu
    return out


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
                 val_seqs: Optional[List[ImuSequence]] = None, margin: int = 0, balance: bool = False,
                 supervision: str = "gt", device_check: bool = False):
        super().__init__()
        self.device_check = bool(device_check)
        if supervision not in ("gt", "self"):
            raise ValueError(f"train.supervision: expected 'gt' (motion capture) or 'self' (none needed), got {supervision!r}")
        self.supervision = supervision
        self.balance = bool(balance)
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
        if self.device_check:
            # each recording (part) with its own gyro bias at rest subtracted, as evaluate does for
            # the general models: the model learns on what it will be given
            # (one check per recording, read from the part that rests: device_check.checked)
            from .device_check import checked

            found: Dict[str, bool] = {}
            n_train = len(self.train_seqs)
            both = checked(list(self.train_seqs) + list(self.val_seqs),
                           lambda rec, dc: found.__setitem__(rec, dc.gyro_bias is not None))
            self.train_seqs, self.val_seqs = both[:n_train], both[n_train:]
            print(f"device check: the gyro bias at rest subtracted from {sum(found.values())} of {len(found)} "
                  f"recordings ({len(self.train_seqs)} training, {len(self.val_seqs)} validation parts)")
        keep = [s for s in self.train_seqs if s.has_gt and s.quat_valid.any()]
        if self.supervision == "self":
            keep = list(self.train_seqs)  # no ground truth needed
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
        self.train_store = SequenceStore(keep, self.axes, self.supervision)
        self.starts = window_starts(self.train_store, self.window, self.stride, self.margin)
        if self.balance:
            self.starts = balanced_starts(self.train_store, self.starts)
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
