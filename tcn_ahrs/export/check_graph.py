"""The causal device check (:mod:`tcn_ahrs.kernels.backbone_check`: ``rest_check`` and
``check_window``) on vectors, for the backbone's step graph (:class:`~tcn_ahrs.export.backbone_graph.
BackboneGraph`, ONNX and ``torch.export``): the same windows, floors, run and bias, read on (3,)/(6,)
tensors; tests/test_backbone_graph.py holds the state after every sample equal to the kernel's."""
from __future__ import annotations

import math
from typing import Tuple

import torch
from torch import Tensor

from ..kernels import backbone as K

F64 = torch.float64
# the check's state in the layout's order: window sums (gyro ref, sum, square; acc ref, sum, square)
SUMS = list(range(K.S_CK_GREF, K.S_CK_GREF + 18))
CHECK_PART = [K.S_CHK + i for i in range(3)] + [K.S_CK_N, K.S_CK_T, K.S_CK_DEAD] + SUMS + [
    K.S_CK_FLOOR, K.S_CK_FLOOR + 1, K.S_CK_RUN, K.S_CK_RUN_N] + list(range(K.S_CK_RUN_G, K.S_CK_RUN_G + 6))
"""Every state index the check writes (accelerometer part: put back where its reading is [0 0 0])."""


def check_step(s: Tensor, sums_index: Tensor, gyro: Tensor, acc: Tensor, frozen: Tensor, clipped: Tensor, dt: Tensor,
               vqf_clip: float, bias: Tensor, writes) -> Tuple[Tensor, Tensor]:
    """One sample of the check: ``sums_index`` :data:`SUMS` as a buffer of the calling module (a graph
    inside a scan cannot build tensors); gyro, acc (3,) as read; frozen, clipped (2,) the health flags
    of this sample; ``vqf_clip`` rad/s; ``bias`` (3,) the filter's. The new values of :data:`CHECK_PART`
    go to ``writes`` (:class:`~tcn_ahrs.export.graph_state.Writes`). -> (the bias the filter goes on
    from (3,), the check's bias (3,))."""
    n = s[K.S_CK_N] + 1.0
    fresh = s[K.S_CK_N] < 0.5
    dead = clipped.any() | (frozen[0] ^ frozen[1]) | (~fresh & (s[K.S_CK_DEAD] > 0.5))
    old = s[sums_index].reshape(2, 3, 3)                             # (sensor, ref / sum / square, axis)
    x = torch.stack([gyro, acc])
    ref = torch.where(fresh, x, old[:, 0])
    d = x - ref
    sums = torch.where(fresh, 0.0, old[:, 1]) + d
    squares = torch.where(fresh, 0.0, old[:, 2]) + d * d
    t = torch.where(fresh, 0.0, s[K.S_CK_T]) + dt
    done = t >= K.CHECK_WINDOW - 0.5 * dt
    mean = sums / n
    spread = torch.sqrt(torch.clamp((squares / n - mean * mean).amax(1), min=0.0))   # (2,): gyro, acc
    u = ref[1] + sums[1] / n
    u = u / torch.sqrt((u * u).sum() + 1e-300)
    live = ~dead & done
    floor = s[K.S_CK_FLOOR:K.S_CK_FLOOR + 2]
    floor = torch.where(live & ((floor < 0.0) | (spread < floor)), spread, floor)
    quiet = live & (spread <= K.CHECK_NOISE_FACTOR * floor).all()
    m = s[K.S_CK_RUN_UP:K.S_CK_RUN_UP + 3]
    cos_tilt = (m * u).sum() / torch.sqrt((m * m).sum() + 1e-300)
    run = s[K.S_CK_RUN]
    extend = quiet & ((run < 0.5) | (cos_tilt >= math.cos(K.CHECK_TILT_DEG * K.DEG)))
    keep = torch.where(done, extend.to(F64), 1.0)
    new = (done & quiet).to(F64)          # extended or started again (quiet but tilted)
    run = keep * run + new
    count_run = keep * s[K.S_CK_RUN_N] + new * n
    up = keep * m + new * u
    g = keep * s[K.S_CK_RUN_G:K.S_CK_RUN_G + 3] + new * (n * ref[0] + sums[0])
    b = g / torch.clamp(count_run, min=1.0)
    chk = s[K.S_CHK:K.S_CHK + 3]
    take = (done & (run >= K.CHECK_MIN_WINDOWS) & (torch.abs(b) <= K.CHECK_CLIP * K.DEG).all()
            & ((torch.abs(b - chk) > vqf_clip).any() | (torch.abs(chk).sum() > 0.0)))
    zero = torch.zeros_like(n)
    chk = torch.where(take, b, chk)
    writes.add(CHECK_PART, torch.cat([chk, torch.stack([torch.where(done, zero, n), t, dead.to(F64)]),
                                      torch.stack([ref, sums, squares], 1).reshape(-1), floor,
                                      torch.stack([run, count_run]), g, up]))
    return torch.where(take, b, bias), chk
