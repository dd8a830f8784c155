"""Small 3-D convolutional building blocks shared by the encoder, MRC trunk and decoder.

GroupNorm uses groups of (at most) 6 channels, so widths 12, 18, 24 get 2, 3, 4 groups; the paper names GN
for the MRC trunk ([supp_mrc], eq:supp_mrc_shared_trunk) and is silent elsewhere, we use it throughout.

``Conv3d`` routes float32 CPU convolutions straight to oneDNN (``aten.mkldnn_convolution``, which has its own
autograd formula). PyTorch's dispatcher otherwise sends batch-1 3-D convolutions with few channels to the
im2col ``slow_conv3d`` path, measured 5-9x slower on this CPU (a 12->12 3x3x3 convolution on 34x14x14:
12-18 ms vs 2 ms). Other devices, dtypes and autocast use the standard path.
"""

from __future__ import annotations

import torch
from torch import nn


class Conv3d(nn.Conv3d):
    """nn.Conv3d (same parameters and state dict) with a oneDNN fast path for fp32 on CPU."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if (
            x.device.type == "cpu"
            and x.dtype == torch.float32
            and self.padding_mode == "zeros"
            and isinstance(self.padding, tuple)
            and torch.backends.mkldnn.is_available()
            and not torch.is_autocast_enabled("cpu")
        ):
            return torch.ops.aten.mkldnn_convolution(
                x, self.weight, self.bias, list(self.padding), list(self.stride), list(self.dilation),
                self.groups,
            )
        return super().forward(x)


def group_norm(channels: int) -> nn.GroupNorm:
    """GroupNorm with groups of 6 channels where possible (12 -> 2, 18 -> 3, 24 -> 4 groups)."""
    groups = max(1, channels // 6) if channels % 6 == 0 else 1
    return nn.GroupNorm(groups, channels)


class ConvGNAct(nn.Sequential):
    """Conv3d(k, stride) -> GroupNorm -> SiLU. Input (B, C_in, D, H, W) -> (B, C_out, D', H', W')."""

    def __init__(self, c_in: int, c_out: int, kernel: int = 3, stride: int = 1) -> None:
        super().__init__(
            Conv3d(c_in, c_out, kernel, stride=stride, padding=kernel // 2, bias=False),
            group_norm(c_out),
            nn.SiLU(),
        )


class ResBlock3d(nn.Module):
    """Pre-activation-free residual block: x + GN(Conv(SiLU(GN(Conv(x))))), then SiLU. Shape preserved."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            Conv3d(channels, channels, 3, padding=1, bias=False),
            group_norm(channels),
            nn.SiLU(),
            Conv3d(channels, channels, 3, padding=1, bias=False),
            group_norm(channels),
        )
        self.act = nn.SiLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B, C, D, H, W)
        return self.act(x + self.body(x))


def mlp(d_in: int, d_hidden: int, d_out: int, zero_last: bool = False) -> nn.Sequential:
    """Two-layer MLP with SiLU (the paper's h_sig / h_gate form); optionally zero-initialized last layer."""
    net = nn.Sequential(nn.Linear(d_in, d_hidden), nn.SiLU(), nn.Linear(d_hidden, d_out))
    if zero_last:
        nn.init.zeros_(net[-1].weight)
        nn.init.zeros_(net[-1].bias)
    return net
