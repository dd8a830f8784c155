"""CNO baseline adapted to 3-D ([supp_baselines], tab:supp_baseline_impl; Raonic et al. 2023), and the
CNO+Prior variant ([supp_rulefeat]).

"The Lift-Encoder-ResNet-ED Link-Decoder-Project topology is extended to 3D. The implementation applies
alias-controlled activations only at resolution-changing operations. A projected control field is broadcast
and concatenated with the state and spatial coordinates before the lifting block. Widths (22, 44, 88), two
residual blocks per stage, oversampling factor 1.5." 1.734 M; [supp_rulefeat] gives 1,733,908 exactly.

Written here because the reference CNO is 2-D research code, not a maintained library, and neuraloperator
ships no CNO. Topology (mirrors the reference CNO's U-Net layout in 3-D):
  input  [x (2), control field (8), coords (3)] = 13 channels (+ 8 RuleFeat channels in CNO+Prior = 21)
  lift   Conv3d(13 -> 32, k3) -> LeakyReLU -> Conv3d(32 -> 22, k3)               (latent width 32)
  enc    for each stage i: Conv3d(c_i -> c_{i+1}, k3) -> BN -> alias-controlled LReLU down to size_{i+1}
  res    two residual blocks (Conv-BN-LReLU-Conv-BN + skip) at each of the widths 22, 44 and the 88 neck
  link   Conv3d(c_i -> c_i, k3) -> BN -> LReLU at each level (the ED link to the decoder)
  dec    Conv3d(c_in -> c_out, k3) -> BN -> alias-controlled LReLU up to the skip's size, then concat
  proj   Conv3d(44 -> 32, k3) -> LeakyReLU -> Conv3d(32 -> 2, k3)
  control field: Linear(14 -> 56) -> GELU -> Linear(56 -> 8).
With these the count is 1,733,908 at any scene, equal to the paper's. The +Prior variant adds the RuleFeat
projection 148 -> 64 -> 8 (10,056) and 8 more input channels of the first lift convolution (8*27*32 =
6,912): +16,968, 1,750,876 total, both as in [supp_rulefeat].

Choices where the paper is silent:
  * Alias-controlled activation in 3-D: trilinear upsampling to ceil(1.5 * target size), LeakyReLU(0.01),
    then adaptive average pooling to the target size (a box low-pass; torch has no antialiased trilinear).
    Level sizes are ceil(n / 2) per axis, so every odd scene size works (paper 127x54x54 -> 64x27x27 ->
    32x14x14) and the decoder returns to the exact encoder sizes.
  * BatchNorm in the encoder, residual, link and decoder blocks (as the reference CNO), none in lift/project.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from nemsim.baselines.common import ControlField, check_inputs, coordinate_grid
from nemsim.baselines.rulefeat import RuleFeat, prior_projection

_SLOPE = 0.01  # LeakyReLU negative slope


@dataclass(frozen=True)
class CNOConfig:
    widths: tuple[int, ...] = (22, 44, 88)  # level widths; the last is the bottleneck (neck)
    n_res: int = 2  # residual blocks per stage (also at the neck)
    lift_latent: int = 32  # hidden width of the lift and project blocks
    oversampling: float = 1.5  # alias-controlled activation: upsampling factor before the nonlinearity
    control_channels: int = 8  # broadcast control field width
    control_hidden: int = 56  # hidden width of the control MLP (0 = one Linear layer)
    rulefeat: bool = False  # CNO+Prior: concatenate the projected RuleFeat before lifting
    rulefeat_hidden: int = 64  # RuleFeat projection 148 -> 64 -> rulefeat_channels
    rulefeat_channels: int = 8
    residual: bool = True  # x_next = x + project (see nemsim.baselines.common)


def _level_sizes(size: tuple[int, int, int], n: int) -> list[tuple[int, int, int]]:
    sizes = [size]
    for _ in range(n):
        d, h, w = sizes[-1]
        sizes.append((math.ceil(d / 2), math.ceil(h / 2), math.ceil(w / 2)))
    return sizes


class AliasFreeLReLU(nn.Module):
    """LeakyReLU evaluated on an oversampled grid, then resampled to ``out_size`` (B, C, *out_size)."""

    def __init__(self, oversampling: float) -> None:
        super().__init__()
        self.oversampling = oversampling

    def forward(self, x: torch.Tensor, out_size: tuple[int, int, int]) -> torch.Tensor:
        fine = tuple(math.ceil(self.oversampling * s) for s in out_size)
        x = F.interpolate(x, size=fine, mode="trilinear", align_corners=False)  # (B, C, *fine)
        x = F.leaky_relu(x, _SLOPE)
        return F.adaptive_avg_pool3d(x, out_size)  # (B, C, *out_size)


class CNOBlock(nn.Module):
    """Conv3d(k3) -> [BN] -> activation; the activation resamples to ``out_size`` when it differs."""

    def __init__(self, c_in: int, c_out: int, oversampling: float, batch_norm: bool = True) -> None:
        super().__init__()
        self.conv = nn.Conv3d(c_in, c_out, 3, padding=1)
        self.norm = nn.BatchNorm3d(c_out) if batch_norm else nn.Identity()
        self.act = AliasFreeLReLU(oversampling)

    def forward(self, x: torch.Tensor, out_size: tuple[int, int, int] | None = None) -> torch.Tensor:
        x = self.norm(self.conv(x))
        if out_size is None or tuple(x.shape[-3:]) == tuple(out_size):
            return F.leaky_relu(x, _SLOPE)  # alias control only where the resolution changes
        return self.act(x, out_size)


class ResidualBlock(nn.Module):
    def __init__(self, c: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv3d(c, c, 3, padding=1), nn.BatchNorm3d(c), nn.LeakyReLU(_SLOPE),
            nn.Conv3d(c, c, 3, padding=1), nn.BatchNorm3d(c),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B, C, D, H, W)
        return x + self.body(x)


class LiftProject(nn.Module):
    """Conv3d(c_in -> latent, k3) -> LeakyReLU -> Conv3d(latent -> c_out, k3); resolution unchanged."""

    def __init__(self, c_in: int, c_out: int, latent: int) -> None:
        super().__init__()
        self.inner = nn.Conv3d(c_in, latent, 3, padding=1)
        self.outer = nn.Conv3d(latent, c_out, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.outer(F.leaky_relu(self.inner(x), _SLOPE))


class CNO3d(nn.Module):
    """CNO (and CNO+Prior with ``cfg.rulefeat`` and the compiled ``rules``)."""

    def __init__(self, cfg: CNOConfig = CNOConfig(), rules=None) -> None:
        super().__init__()
        self.cfg = cfg
        w = list(cfg.widths)
        n_levels = len(w) - 1
        if n_levels < 1:
            raise ValueError(f"CNO needs at least two widths, got {cfg.widths}")
        self.control = ControlField(cfg.control_channels, cfg.control_hidden)
        c_in = 2 + cfg.control_channels + 3
        self.rulefeat: RuleFeat | None = None
        if cfg.rulefeat:
            hidden, channels = cfg.rulefeat_hidden, cfg.rulefeat_channels
            self.rulefeat, self.rule_proj = prior_projection(rules, hidden, channels, "CNO")
            c_in += cfg.rulefeat_channels
        self.lift = LiftProject(c_in, w[0], cfg.lift_latent)
        self.encoder = nn.ModuleList(CNOBlock(w[i], w[i + 1], cfg.oversampling) for i in range(n_levels))
        self.res = nn.ModuleList(
            nn.Sequential(*(ResidualBlock(w[i]) for _ in range(cfg.n_res))) for i in range(n_levels + 1)
        )
        self.link = nn.ModuleList(CNOBlock(w[i], w[i], cfg.oversampling) for i in range(n_levels + 1))
        # decoder level j maps level (n_levels - j) to level (n_levels - j - 1); inputs after the first one
        # are [upsampled features, linked skip] concatenated.
        self.decoder = nn.ModuleList(
            CNOBlock(w[n_levels - j] * (1 if j == 0 else 2), w[n_levels - j - 1], cfg.oversampling)
            for j in range(n_levels)
        )
        self.project = LiftProject(2 * w[0], 2, cfg.lift_latent)

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        check_inputs(x, u)
        B, _, D, H, W = x.shape
        u = u.to(x.dtype)
        parts = [x, self.control(u, (D, H, W))]
        if self.rulefeat is not None:
            r = self.rule_proj(self.rulefeat(u).to(x.dtype))  # (B, 8)
            parts.append(r[:, :, None, None, None].expand(B, r.shape[1], D, H, W))
        parts.append(coordinate_grid((D, H, W), x.device, x.dtype).expand(B, 3, D, H, W))
        h = self.lift(torch.cat(parts, dim=1))  # (B, w0, D, H, W)
        n_levels = len(self.encoder)
        sizes = _level_sizes((D, H, W), n_levels)
        skips = []
        for i in range(n_levels):
            h = self.res[i](h)  # (B, w_i, *size_i)
            skips.append(self.link[i](h))
            h = self.encoder[i](h, sizes[i + 1])  # (B, w_{i+1}, *size_{i+1})
        h = self.link[n_levels](self.res[n_levels](h))  # neck (B, w_L, *size_L)
        for j in range(n_levels):
            level = n_levels - j - 1
            if j > 0:
                h = torch.cat([h, skips[level + 1]], dim=1)
            h = self.decoder[j](h, sizes[level])  # (B, w_level, *size_level)
        h = torch.cat([h, skips[0]], dim=1)  # (B, 2 w0, D, H, W)
        out = self.project(h)  # (B, 2, D, H, W)
        return x + out if self.cfg.residual else out
