"""An attitude the device itself recorded beside the IMU: a phone OS's own estimate (iOS's
CMDeviceMotion attitude, the ``os_quat`` field of the phone recordings in ``../shared/datasets/phones``)
as a baseline row — what the phone already gives its user. Nothing is estimated here: the field is
read from the recording's own HDF5 file and put in the project's frame.
"""
from __future__ import annotations

from typing import Optional

import h5py
import numpy as np
import torch

from .. import so3
from ..sequence import ImuSequence
from .base import EstimatorOutput
from .registry import register

# iOS's reference frame xMagneticNorthZVertical (x magnetic north, y west, z up) -> ENU: a +90°
# turn about up (the phones' README; loadiOSDataset.m)
ENU_FROM_IOS = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])


@register("phone_os", "recorded", axes=(9,))
class PhoneOSAttitude:
    """The phone OS's own attitude (``field``, (N, 4) w,x,y,z ``nav_from_body`` in iOS's
    ``xMagneticNorthZVertical``) from the recording's HDF5 file, as magnetic ENU. It uses the
    magnetometer (scored as 9-axis); ``init_quat`` is not used (the OS starts on its own)."""

    name = "phone OS"

    def __init__(self, axes: int = 9, field: str = "os_quat"):
        self.axes, self.field = 9, str(field)

    def run(self, seq: ImuSequence, init_quat: Optional[np.ndarray] = None, init_index: int = 0) -> EstimatorOutput:
        src = str(seq.source)
        try:
            with h5py.File(src, "r") as f:
                if self.field not in f:
                    raise ValueError(f"{src}: field '{self.field}': the phone OS's attitude is not in this "
                                     f"recording (expected (N, 4) w,x,y,z); fields: {sorted(f.keys())}")
                q = np.asarray(f[self.field][...], dtype=np.float64)
        except OSError as e:
            raise ValueError(f"{src}: the phone OS's attitude is read from the recording's HDF5 file, "
                             f"which could not be opened ({e})") from None
        if q.shape != (len(seq), 4):
            raise ValueError(f"{src}: field '{self.field}': expected ({len(seq)}, 4) (one per IMU sample), "
                             f"got {q.shape}")
        q = so3.quat_mul(torch.as_tensor(ENU_FROM_IOS).expand(len(q), 4), torch.as_tensor(q))
        return EstimatorOutput(quat=so3.quat_normalize(q).numpy())
