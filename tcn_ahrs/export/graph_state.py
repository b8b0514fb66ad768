"""Where a graph's backbone step (:class:`tcn_ahrs.export.backbone_graph.BackboneGraph`) reads and
writes the backbone's flat state (``kernels/backbone_layout.STATE``): the index lists of its
groups, and :class:`Writes`, which collects the step's new values and writes them in one gather
over [old state, new values] (the accelerometer's and magnetometer's parts put back where their
reading is [0 0 0])."""
from __future__ import annotations

from typing import List, Tuple

import torch
from torch import Tensor

from ..kernels import backbone as K

# the health checks' state in the order ``health`` writes it: (2, 13) rows, gyro and accelerometer
HEALTH_INDEX = [[K.S_GPREV + i for i in range(3)] + [K.S_GMAX + i for i in range(6)]
                 + [K.S_GCLIPPED, K.S_GSAME_T, K.S_GSAME_N, K.S_GFROZEN],
                 [K.S_APREV + i for i in range(3)] + [K.S_AMAX + i for i in range(6)]
                 + [K.S_ACLIPPED, K.S_ASAME_T, K.S_ASAME_N, K.S_AFROZEN]]


# the magnetometer's rejection state in the order _mag_update reads and writes it
MAG_SCALARS = [K.S_MREF_N, K.S_MREF_D, K.S_MCAND_N, K.S_MCAND_D, K.S_MUND_T, K.S_MCAND_T, K.S_MAGDIST, K.S_MREJ_T]


def filter_index(f: int, d: int) -> Tuple[List[int], List[int]]:
    """The state indices of a low-pass group at ``f`` with ``d`` components: its (running, count)
    and its memory rows (x1, x2, y1, y2), each (d,)."""
    return [f, f + 1], [f + 2 + r * d + i for r in range(4) for i in range(d)]


def _group(f: int, d: int) -> List[int]:
    return list(range(f, f + 2 + 4 * d))


# what the accelerometer's and the magnetometer's updates write: put back where their reading is [0 0 0]
# (rest, rest time and k_mag_init, which the gyro's update writes too, are chosen where they are computed)
ACC_PART = set(_group(K.F_RA, 3) + _group(K.F_ACC, 3) + _group(K.F_ROT, 9) + _group(K.F_BIAS, 2) + HEALTH_INDEX[1]
                + [K.S_ADISTRUST]
                + list(range(K.S_AQ, K.S_AQ + 4)) + list(range(K.S_BIAS, K.S_BIAS + 3)) + list(range(K.S_P, K.S_P + 9))
                + list(range(K.S_CHK, K.S_CHK + 3)) + list(range(K.S_CK_N, K.S_CK_RUN_UP + 3)))  # the causal check
MAG_PART = set(_group(K.F_MAG, 2) + [K.S_MREF_N, K.S_MREF_D, K.S_MAGDIST, K.S_MUND_T, K.S_MCAND_T, K.S_MCAND_N,
                                      K.S_MCAND_D, K.S_MREJ_T, K.S_DELTA, K.S_MSAME_T, K.S_MFROZEN]
               + [K.S_MPREV + i for i in range(3)])


class Writes:
    """The state's new values as they are computed ((indices, values) pairs), written at the end in
    one gather over [old state, new values]."""

    def __init__(self):
        self.index: List[int] = []
        self.values: List[Tensor] = []

    def add(self, index, values: Tensor) -> None:
        flat = [int(i) for row in index for i in (row if isinstance(row, list) else [row])]
        self.index += flat
        self.values.append(values.reshape(-1))

    def assemble(self, g, s: Tensor, skip_acc: Tensor, skip_mag: Tensor) -> Tensor:
        """The new state (N_STATE,) through ``g``'s plan (``BackboneGraph._set_plan``)."""
        if self.index != g.plan:
            raise AssertionError("backbone graph: a step wrote the state in another order than its plan")
        vals = torch.cat(self.values)
        vals = torch.where((g.write_acc & skip_acc) | (g.write_mag & skip_mag), s[g.write_index], vals)
        return torch.cat([s, vals])[g.write_perm]


def plan_buffers(idx: List[int]) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """(index, accelerometer part, magnetometer part, permutation) tensors of a step that writes
    the state indices ``idx`` in this order: the new state is ``cat([s, values])[permutation]``."""
    n = K.N_STATE
    if len(set(idx)) != len(idx):
        twice = sorted(i for i in set(idx) if idx.count(i) > 1)
        raise AssertionError(f"backbone graph: state indices written twice: {twice}")
    perm = list(range(n))
    for j, i in enumerate(idx):
        perm[i] = n + j
    return (torch.tensor(idx), torch.tensor([i in ACC_PART for i in idx]), torch.tensor([i in MAG_PART for i in idx]),
            torch.tensor(perm))
