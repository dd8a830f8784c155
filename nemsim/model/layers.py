"""Small 3-D convolutional building blocks shared by the encoder, MRC trunk and decoder.

GroupNorm uses groups of (at most) 6 channels, so widths 12, 18, 24 get 2, 3, 4 groups; the paper names GN
for the MRC trunk ([supp_mrc], eq:supp_mrc_shared_trunk) and is silent elsewhere, we use it throughout.

``Conv3d`` routes float32 CPU convolutions straight to oneDNN (``aten.mkldnn_convolution``, which has its own
autograd formula). PyTorch's dispatcher otherwise sends batch-1 3-D convolutions with few channels to the
much slower im2col ``slow_conv3d`` path. 1x1x1 stride-1 kernels run as one matrix product (faster than
oneDNN at our sizes). Other devices, dtypes, autocast and torch.compile use the standard path.

Line mode (``line = True``, a trench's cross-section, ``NEMSim`` sets it on its 3x3x3 convolutions): the
input is constant along H on a periodic H axis, so every tap of a kernel's H column sees the same row and the
convolution is exactly the kernel summed over H, applied with no H padding (a (k, 1, k) kernel; stride
unchanged, so two rows become one and one row stays one). The parameters and state dict are the 3-D
kernel's: a line-mode model computes what the same 3-D model with periodic H padding computes on a field
constant along H, at a third of the taps and on one row.

Depth window (``nemsim.model.window``): while a ``WindowRun`` is attached (``_window``), 3x3x3 convolutions
and GroupNorm compute on a suffix crop of the depth axis as if on the whole volume (the slice below the crop
and the statistics below it come from the last full call). Unattached, nothing changes.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from nemsim.model.window import window_conv, window_group_norm

_PREPACK = hasattr(torch.ops.mkldnn, "_convolution_pointwise") and hasattr(
    torch.ops.mkldnn, "_reorder_convolution_weight"
)


def _onednn_ok(x: torch.Tensor) -> bool:
    """fp32 on CPU with oneDNN, outside autocast and torch.compile tracing."""
    return (
        not torch.compiler.is_compiling()  # inductor lowers aten.convolution itself
        and x.device.type == "cpu"
        and x.dtype == torch.float32
        and torch.backends.mkldnn.is_available()
        and not torch.is_autocast_enabled("cpu")
    )


def conv3d(
    x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, stride: int | tuple = 1,
    padding: int | tuple = 0,
) -> torch.Tensor:
    """F.conv3d (zero padding, no dilation or groups) with the oneDNN fast path for fp32 on CPU, and
    1x1x1 stride-1 kernels as one matrix product (oneDNN is slower there at these sizes)."""
    if _onednn_ok(x):
        stride = tuple(stride) if isinstance(stride, (tuple, list)) else (stride,) * 3
        padding = tuple(padding) if isinstance(padding, (tuple, list)) else (padding,) * 3
        if weight.shape[2:] == (1, 1, 1) and stride == (1, 1, 1) and padding == (0, 0, 0):
            B, C, D, H, W = x.shape
            w2 = weight.reshape(weight.shape[0], C)  # (C_out, C)
            if x.is_contiguous(memory_format=torch.channels_last_3d) and not x.is_contiguous():
                # channels-last input (oneDNN's output layout): (B, N, C) @ (C, C_out); output channels-last
                y = torch.matmul(x.permute(0, 2, 3, 4, 1).reshape(B, D * H * W, C), w2.t())  # (B, N, C_out)
                if bias is not None:
                    y = y + bias
                return y.view(B, D, H, W, -1).permute(0, 4, 1, 2, 3)
            y = torch.matmul(w2, x.reshape(B, C, D * H * W))  # (B, C_out, N)
            if bias is not None:
                y = y + bias[:, None]
            return y.view(B, -1, D, H, W)
        return torch.ops.aten.mkldnn_convolution(x, weight, bias, list(padding), list(stride), [1, 1, 1], 1)
    return F.conv3d(x, weight, bias, stride, padding)


class Conv3d(nn.Conv3d):
    """nn.Conv3d (same parameters and state dict) with the fp32 CPU fast paths of ``conv3d``."""

    _packed: tuple | None = None  # (key, oneDNN-packed weight) for inference, see _prepacked
    _window = None  # a WindowRun while a depth-windowed call runs (nemsim.model.window)
    line = False  # line mode: a field constant along H (module docstring)

    def __getstate__(self) -> dict:
        """Copies and pickles leave the packed weight behind (an opaque oneDNN tensor: deepcopy of a model
        that has run inference failed with "Cannot access storage of OpaqueTensorImpl")."""
        state = dict(super().__getstate__())
        state.pop("_packed", None)
        return state

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self._window is not None and self.kernel_size == (3, 3, 3):
            assert not self.line, "a depth window runs on full and quarter domains, not on a line"
            return window_conv(self, x, self._window, self._forward)
        return self._forward(x)

    def _weight(self) -> torch.Tensor:
        """The kernel applied: the module's, or in line mode its sum over H (module docstring)."""
        return self.weight.sum(dim=3, keepdim=True) if self.line else self.weight

    def _forward(self, x: torch.Tensor, padding: tuple | None = None) -> torch.Tensor:
        """The convolution, with ``padding`` instead of the module's (the depth window's own padding)."""
        padding = self.padding if padding is None else tuple(padding)  # type: ignore[assignment]
        if self.line:
            padding = (padding[0], 0, padding[2])  # type: ignore[index]
        if self.padding_mode == "zeros" and isinstance(self.padding, tuple) and self.dilation == (1, 1, 1) \
                and self.groups == 1:
            inference = _PREPACK and not torch.is_grad_enabled() and _onednn_ok(x)
            if inference and self.kernel_size != (1, 1, 1) and self.in_channels >= 8:
                return self._prepacked(x, padding)  # type: ignore[arg-type]
            return conv3d(x, self._weight(), self.bias, self.stride, padding)  # type: ignore[arg-type]
        assert padding == self.padding and not self.line, f"padding {padding} on the standard path of {self}"
        return super().forward(x)

    def _prepacked(self, x: torch.Tensor, padding: tuple) -> torch.Tensor:
        """Inference: the weight reordered once into oneDNN's blocked layout for this input shape (a rollout
        calls every convolution with the same shape each step; not for the 2-channel stem, where it does
        not pay). Its output is channels-last. The packed copy
        is keyed by input shape and the weight's storage and version, so training updates or
        ``load_state_dict`` invalidate it."""
        w = self.weight
        key = (tuple(x.shape), padding, w.data_ptr(), w._version, self.line)
        packed = self._packed  # one read: another thread may replace it meanwhile
        if packed is None or packed[0] != key:
            packed = (key, torch.ops.mkldnn._reorder_convolution_weight(
                self._weight().detach(), list(padding), list(self.stride), [1, 1, 1], 1, list(x.shape)
            ))
            self._packed = packed
        return torch.ops.mkldnn._convolution_pointwise(
            x, packed[1], self.bias, list(padding), list(self.stride), [1, 1, 1], 1, "none", [], ""
        )


def apply_group_norm(gn: nn.GroupNorm, x: torch.Tensor) -> torch.Tensor:
    """``gn`` applied to x (B, C, ...): ``F.group_norm``. A module global so that an exporter can swap in
    an equal form that its runtime runs faster (``nemsim.inference.runtime``)."""
    return F.group_norm(x, gn.num_groups, gn.weight, gn.bias, gn.eps)


class GroupNorm(nn.GroupNorm):
    """nn.GroupNorm (same parameters and state dict) that follows an attached depth window."""

    _window = None  # a WindowRun while a depth-windowed call runs (nemsim.model.window)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self._window is not None:
            return window_group_norm(self, x, self._window)
        return apply_group_norm(self, x)


def group_norm(channels: int) -> nn.GroupNorm:
    """GroupNorm with groups of 6 channels where possible (12 -> 2, 18 -> 3, 24 -> 4 groups)."""
    groups = max(1, channels // 6) if channels % 6 == 0 else 1
    return GroupNorm(groups, channels)


class ConvGNAct(nn.Sequential):
    """Conv3d(k, stride) -> GroupNorm -> SiLU. Input (B, C_in, D, H, W) -> (B, C_out, D', H', W')."""

    def __init__(self, c_in: int, c_out: int, kernel: int = 3, stride: int = 1) -> None:
        super().__init__(
            Conv3d(c_in, c_out, kernel, stride=stride, padding=kernel // 2, bias=False),
            group_norm(c_out),
            nn.SiLU(),
        )


class ResBlock3d(nn.Module):
    """Pre-activation-free residual block: x + GN(Conv(SiLU(GN(Conv(x))))), then SiLU. Shape preserved.

    ``identity_init``: no SiLU after the sum and the last GroupNorm's scale starts at zero, so the block is
    the identity until trained: inserted into a trained network it leaves its outputs unchanged (growing a
    model without losing what it learned; the scale still receives gradients, so the block trains)."""

    def __init__(self, channels: int, identity_init: bool = False) -> None:
        super().__init__()
        self.body = nn.Sequential(
            Conv3d(channels, channels, 3, padding=1, bias=False),
            group_norm(channels),
            nn.SiLU(),
            Conv3d(channels, channels, 3, padding=1, bias=False),
            group_norm(channels),
        )
        if identity_init:
            nn.init.zeros_(self.body[-1].weight)  # type: ignore[arg-type]
        self.act: nn.Module = nn.Identity() if identity_init else nn.SiLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B, C, D, H, W)
        return self.act(x + self.body(x))


def mlp(d_in: int, d_hidden: int, d_out: int, zero_last: bool = False) -> nn.Sequential:
    """Two-layer MLP with SiLU (the paper's h_sig / h_gate form); optionally zero-initialized last layer."""
    net = nn.Sequential(nn.Linear(d_in, d_hidden), nn.SiLU(), nn.Linear(d_hidden, d_out))
    if zero_last:
        nn.init.zeros_(net[-1].weight)  # type: ignore[arg-type]
        nn.init.zeros_(net[-1].bias)  # type: ignore[arg-type]
    return net
