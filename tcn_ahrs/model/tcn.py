"""f_TCN: a causal temporal convolutional network (paper Sec. 3.2, Eq. 15, Fig. 1).

Five 1-D convolution layers: four dilated causal convolutions whose channel count grows with
depth, each followed by BatchNorm, Dropout and GELU, then a 1x1 output convolution. The
sequence is padded with zeros at its *start only* (causal: the output at sample k depends on
samples <= k). The output layer starts at zero, so an untrained network regresses a zero error
term and the calibrated readings equal the raw ones (paper Sec. 3.2, last paragraph).

Shapes: input (B, N, C_in) -> output (B, N, C_out) (time-major like the rest of the package;
the transposes to PyTorch's (B, C, N) convolution layout happen inside).
"""
from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..config.model import TCNConfig

# The paper's receptive field: N = 448 samples (Sec. 3.2).
MIN_RECEPTIVE_FIELD = 448


def receptive_field(kernel_size: int, dilations: Sequence[int]) -> int:
    """Samples of history (including the current one) one output of the stack sees."""
    return 1 + (kernel_size - 1) * int(sum(dilations))


class CausalConv1d(nn.Module):
    """Conv1d with ``(kernel_size - 1) * dilation`` zeros padded on the left only."""

    def __init__(self, c_in: int, c_out: int, kernel_size: int, dilation: int = 1):
        super().__init__()
        self.left_pad = (kernel_size - 1) * dilation
        self.conv = nn.Conv1d(c_in, c_out, kernel_size, dilation=dilation)

    def forward(self, x: Tensor) -> Tensor:  # (B, C, N) -> (B, C', N)
        return self.conv(F.pad(x, (self.left_pad, 0)))


_T = TCNConfig()  # the defaults: tcn_ahrs/config/model.py


class TCN(nn.Module):
    """Causal dilated TCN regressing a per-sample error term.

    Args:
        in_channels:  C_in (e.g. 9 for gyro+acc+mag, 3 for one sensor).
        out_channels: C_out (3: one error vector per sample).
        channels:     widths of the dilated layers (growing with depth), default 16-16-32-32 (the paper: 16-32-64-128).
        kernel_size:  of the dilated layers.
        dilations:    one per dilated layer; ``1 + (k-1) * sum(d) >= 448`` is asserted.
        dropout:      after each hidden layer (paper: 0.1).
    """

    def __init__(self, in_channels: int, out_channels: int = 3,
                 channels: Sequence[int] = tuple(_T.channels), kernel_size: int = _T.kernel_size,
                 dilations: Sequence[int] = tuple(_T.dilations), dropout: float = _T.dropout,
                 min_receptive_field: int = MIN_RECEPTIVE_FIELD):
        super().__init__()
        if len(channels) != len(dilations):
            raise ValueError(f"TCN: channels {list(channels)} and dilations {list(dilations)} "
                             "must have the same length (one per dilated layer)")
        self.receptive_field = receptive_field(kernel_size, dilations)
        assert self.receptive_field >= min_receptive_field, (
            f"TCN receptive field {self.receptive_field} < {min_receptive_field} samples "
            f"(kernel {kernel_size}, dilations {list(dilations)})")
        layers = []
        c_prev = in_channels
        for c, d in zip(channels, dilations):
            layers += [CausalConv1d(c_prev, c, kernel_size, d), nn.BatchNorm1d(c),
                       nn.Dropout(dropout), nn.GELU()]
            c_prev = c
        self.hidden = nn.Sequential(*layers)
        self.out = nn.Conv1d(c_prev, out_channels, 1)
        # Zero output layer: the untrained error term is exactly 0 (paper Sec. 3.2).
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, x: Tensor) -> Tensor:
        """(B, N, C_in) -> (B, N, C_out)."""
        h = self.hidden(x.transpose(1, 2))
        return self.out(h).transpose(1, 2)


class ConstantError(nn.Module):
    """Error term that ignores its input: a learned constant vector (the 'Calibrated IMU'
    baseline of the paper, Sec. 4.4: network input set to zero, only constants learned)."""

    receptive_field = 1

    def __init__(self, out_channels: int = 3):
        super().__init__()
        self.bias = nn.Parameter(torch.zeros(out_channels))

    def forward(self, x: Tensor) -> Tensor:
        return self.bias.expand(x.shape[0], x.shape[1], -1)
