"""Native 3-D Fourier-operator layers: the fallback for FNO and U-NO when the optional ``neuralop`` extra
(neuraloperator) is not installed.

These mirror the parameter layout of neuraloperator's dense ``SpectralConv``/``FNOBlocks``/``ChannelMLP``
(so a configuration has the same trainable-parameter count under either backend, complex weights counted as
two reals), but they are our own code and their state dicts are NOT interchangeable with neuralop's: a
checkpoint must be loaded with the backend it was trained with. Differences in numerics, all documented:
  * Skip paths that change resolution (U-NO) are resampled trilinearly (neuralop: FFT interpolation).
  * A resolution-changing spectral convolution writes its kept modes straight into the spectrum of the
    output grid, keeping negative frequencies along the first two axes.

Mode convention (as neuralop): ``n_modes = (m_d, m_h, m_w)`` keeps m_d and m_h frequencies centred on zero
along D and H, and m_w // 2 + 1 non-negative frequencies along W (the rfft axis). Li et al.'s FNO3d with
"6 x 6 x 6 modes" (four corner blocks) is n_modes = (12, 12, 11): 12 * 12 * 6 complex weights per channel
pair.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from nemsim.baselines.common import coordinate_grid


def _centre(n_fft: int, kept: int) -> slice:
    """Indices of ``kept`` frequencies centred on zero in an fftshifted axis of length n_fft."""
    c = n_fft // 2
    return slice(c - kept // 2, c + kept // 2 + kept % 2)


class SpectralConv3d(nn.Module):
    """Dense spectral convolution. x (B, C_in, D, H, W) -> (B, C_out, *output_shape or (D, H, W))."""

    def __init__(self, c_in: int, c_out: int, n_modes: tuple[int, int, int]) -> None:
        super().__init__()
        self.c_out = c_out
        self.modes = (n_modes[0], n_modes[1], n_modes[2] // 2 + 1)
        std = (2.0 / (c_in + c_out)) ** 0.5
        self.weight = nn.Parameter(std * torch.randn(c_in, c_out, *self.modes, dtype=torch.cfloat))
        self.bias = nn.Parameter(std * torch.randn(c_out, 1, 1, 1))

    def forward(self, x: torch.Tensor, output_shape: tuple[int, int, int] | None = None) -> torch.Tensor:
        B, _, D, H, W = x.shape
        out_shape = tuple(output_shape) if output_shape is not None else (D, H, W)
        xf = torch.fft.fftshift(torch.fft.rfftn(x.float(), dim=(-3, -2, -1), norm="forward"), dim=(-3, -2))
        out_f = torch.zeros(B, self.c_out, out_shape[0], out_shape[1], out_shape[2] // 2 + 1,
                            dtype=torch.cfloat, device=x.device)
        # kept modes per axis, limited by both grids
        kd = min(self.modes[0], D, out_shape[0])
        kh = min(self.modes[1], H, out_shape[1])
        kw = min(self.modes[2], W // 2 + 1, out_shape[2] // 2 + 1)
        wd, wh = _centre(self.modes[0], kd), _centre(self.modes[1], kh)
        w = self.weight[:, :, wd, wh, :kw]  # (C_in, C_out, kd, kh, kw)
        xs = xf[:, :, _centre(D, kd), _centre(H, kh), :kw]  # (B, C_in, kd, kh, kw)
        out_f[:, :, _centre(out_shape[0], kd), _centre(out_shape[1], kh), :kw] = torch.einsum(
            "bixyz,ioxyz->boxyz", xs, w
        )
        out_f = torch.fft.ifftshift(out_f, dim=(-3, -2))
        y = torch.fft.irfftn(out_f, s=out_shape, dim=(-3, -2, -1), norm="forward")
        return y.to(x.dtype) + self.bias


class ChannelMLP(nn.Module):
    """Pointwise two-layer MLP: 1x1x1 conv c_in -> hidden -> GELU -> c_out."""

    def __init__(self, c_in: int, c_out: int, hidden: int) -> None:
        super().__init__()
        self.fc0 = nn.Conv3d(c_in, hidden, 1)
        self.fc1 = nn.Conv3d(hidden, c_out, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc1(F.gelu(self.fc0(x)))


class SoftGating(nn.Module):
    """Per-channel scale, no bias: x * w (w of shape (1, C, 1, 1, 1))."""

    def __init__(self, c: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(1, c, 1, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.weight


def _resample(x: torch.Tensor, shape: tuple[int, int, int]) -> torch.Tensor:
    if tuple(x.shape[-3:]) == tuple(shape):
        return x
    return F.interpolate(x, size=tuple(shape), mode="trilinear", align_corners=False)


class FourierBlock(nn.Module):
    """One Fourier layer: GELU?(spectral(x) + W x) -> ChannelMLP + skip -> GELU?  (neuralop's post-activation
    FNO block with a linear operator skip and a soft-gating or linear channel-MLP skip)."""

    def __init__(self, c_in: int, c_out: int, n_modes: tuple[int, int, int], mlp_expansion: float = 0.5,
                 mlp_skip: str = "soft-gating") -> None:
        super().__init__()
        self.spectral = SpectralConv3d(c_in, c_out, n_modes)
        self.skip = nn.Conv3d(c_in, c_out, 1, bias=False)
        self.mlp = ChannelMLP(c_out, c_out, round(c_out * mlp_expansion))
        if mlp_skip == "soft-gating":
            if c_in != c_out:
                raise ValueError(
                    f"soft-gating skip needs c_in == c_out, got {c_in} and {c_out}; use 'linear'"
                )
            self.mlp_skip: nn.Module = SoftGating(c_out)
        elif mlp_skip == "linear":
            self.mlp_skip = nn.Conv3d(c_in, c_out, 1, bias=False)
        else:
            raise ValueError(f"mlp_skip must be one of ['soft-gating', 'linear'], got {mlp_skip!r}")

    def forward(self, x: torch.Tensor, output_shape: tuple[int, int, int], activate: bool) -> torch.Tensor:
        skip_op = _resample(self.skip(x), output_shape)
        skip_mlp = _resample(self.mlp_skip(x), output_shape)
        h = self.spectral(x, output_shape) + skip_op
        if activate:
            h = F.gelu(h)
        h = self.mlp(h) + skip_mlp
        return F.gelu(h) if activate else h


class NativeFNO(nn.Module):
    """neuralop-style FNO on (B, C_in, D, H, W) with grid embedding, lifting, ``n_layers`` Fourier blocks
    (activation after all but the last) and projection."""

    def __init__(self, c_in: int, c_out: int, width: int, n_modes: tuple[int, int, int], n_layers: int,
                 lifting_ratio: float = 2.0, projection_ratio: float = 2.0) -> None:
        super().__init__()
        self.lifting = ChannelMLP(c_in + 3, width, round(lifting_ratio * width))
        self.blocks = nn.ModuleList(FourierBlock(width, width, n_modes) for _ in range(n_layers))
        self.projection = ChannelMLP(width, c_out, round(projection_ratio * width))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, _, D, H, W = x.shape
        grid = coordinate_grid((D, H, W), x.device, x.dtype).expand(B, 3, D, H, W)
        h = self.lifting(torch.cat([x, grid], dim=1))  # (B, width, D, H, W)
        for k, block in enumerate(self.blocks):
            h = block(h, (D, H, W), activate=k < len(self.blocks) - 1)
        return self.projection(h)


class NativeUNO(nn.Module):
    """neuralop-style U-NO: lifting, one Fourier block per layer with its own width, modes and resolution
    scaling, linear horizontal skips (concatenated at the receiving layer), projection. As in neuralop's
    UNO, each single-layer block applies no outer activation (nonlinearity comes from the channel MLPs)."""

    def __init__(self, c_in: int, c_out: int, hidden: int, out_channels: tuple[int, ...],
                 n_modes: tuple[int, int, int], scalings: tuple[float, ...], skips: dict[int, int],
                 lifting_channels: int, projection_channels: int) -> None:
        super().__init__()
        self.scalings = scalings
        self.skips = dict(skips)
        self.lifting = ChannelMLP(c_in + 3, hidden, lifting_channels)
        blocks, hskips = [], {}
        prev = hidden
        for i, c in enumerate(out_channels):
            if i in self.skips:
                prev += out_channels[self.skips[i]]
            blocks.append(FourierBlock(prev, c, n_modes, mlp_skip="linear"))
            if i in self.skips.values():
                hskips[str(i)] = nn.Conv3d(c, c, 1, bias=False)
            prev = c
        self.blocks = nn.ModuleList(blocks)
        self.hskips = nn.ModuleDict(hskips)
        self.projection = ChannelMLP(prev, c_out, projection_channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, _, D, H, W = x.shape
        grid = coordinate_grid((D, H, W), x.device, x.dtype).expand(B, 3, D, H, W)
        h = self.lifting(torch.cat([x, grid], dim=1))  # (B, hidden, D, H, W)
        saved: dict[int, torch.Tensor] = {}
        for i, block in enumerate(self.blocks):
            if i in self.skips:
                h = torch.cat([h, _resample(saved[self.skips[i]], tuple(h.shape[-3:]))], dim=1)
            if i == len(self.blocks) - 1:
                shape = (D, H, W)
            else:
                d, hh, w = (int(round(s * self.scalings[i])) for s in h.shape[-3:])
                shape = (d, hh, w)
            h = block(h, shape, activate=False)
            if str(i) in self.hskips:
                saved[i] = self.hskips[str(i)](h)
        return self.projection(h)
